"""The on-disk twin cache (fbgcomp.structure.cache), with real files in a temporary cache folder:
keyed by the machine's content and the code, atomic, a bad entry rebuilt, off means off."""

from __future__ import annotations

import os
import threading
from pathlib import Path

import numpy as np
import pytest
import yaml

import fbgcomp_testing
from fbgcomp.structure import cache as twin_cache
from fbgcomp.structure import load_machine

RES = 0.3
DEFAULT_YAML = Path(__file__).resolve().parents[1] / "src" / "fbgcomp" / "data" / "ram.yaml"


@pytest.fixture()
def Twin():
    fbgcomp_testing.require("skfem")
    from fbgcomp.structure import Twin

    return Twin


@pytest.fixture()
def cache_dir(tmp_path, monkeypatch):
    monkeypatch.setenv("FBGCOMP_CACHE_DIR", str(tmp_path / "cache"))
    return tmp_path / "cache" / "twin"


@pytest.fixture(scope="session")
def machine():
    return load_machine()


def _entries(folder: Path):
    return sorted(folder.glob("*.twin")) if folder.exists() else []


def _responses(twin):
    """Every kind of output a twin gives, as arrays."""
    t = np.arange(0.0, 4 * 3600.0, 60.0)
    ambient = 20.0 + 2.0 * np.sin(t / 5000.0)
    spindle = 300.0 * (t > 3600.0)
    th = twin.thermal(t, ambient, spindle, initial_C=20.0)
    paths = twin.path_influence(twin.machine.sensors[:2])
    elong, temp = twin.thermal_paths(paths, t, ambient, spindle)
    inf = twin.influence
    return [
        twin.static([[100.0, -50.0, 20.0], [0.0, 1.0, 0.0]]).ttp_um,
        twin.static(np.eye(3)).sensor_elongation_um,
        th.sensor_elongation_um,
        th.ttp_um,
        th.probe_C,
        th.sensor_temperature_C,
        *twin.static_temperature_response("gradient_x", 2.0),
        paths.per_force_um_per_N,
        paths.per_temperature_um_per_K,
        elong,
        temp,
        inf.elastic_per_temperature,
        inf.steady_per_input,
        inf.sensor_per_force_um_per_N,
        twin._elastic.solve(twin._R[-1]),
    ]


def _assert_identical(a, b):
    assert len(a) == len(b)
    for x, y in zip(a, b):
        assert np.asarray(x).shape == np.asarray(y).shape
        assert np.array_equal(x, y)  # bit for bit, not approximately


@pytest.mark.slow
def test_cold_build_writes_one_entry_and_the_warm_load_is_bit_identical(Twin, machine, cache_dir):
    cold = Twin(machine, resolution=RES)
    assert not cold.times.from_cache
    entries = _entries(cache_dir)
    assert len(entries) == 1 and entries[0].name.endswith(".twin")
    assert cold.times.cache_path == str(entries[0])
    assert not list(cache_dir.glob(".*"))  # no temporary file left over
    warm = Twin(machine, resolution=RES)
    assert warm.times.from_cache and warm.times.assemble_s == 0.0
    assert set(warm.times.extra["cold_build_s"]) >= {"assemble_s", "elastic_factor_s"}
    _assert_identical(_responses(cold), _responses(warm))
    # ... and both equal a twin built without any cache.
    _assert_identical(_responses(Twin(machine, resolution=RES, cache=False)), _responses(warm))
    assert len(_entries(cache_dir)) == 1


def test_a_twin_without_its_thermal_reduction_gives_the_same_bits_and_its_entry_is_completed(
    Twin, machine, cache_dir
):
    """``reduce_thermal=False`` (twin-check) leaves the reduced thermal model until something
    needs it; the static operators and the steady gain are those of a full twin to the bit, and
    so is the reduction made on first use. Its entry, stored without the reduction, is read by a
    twin that needs it, which reduces and completes it."""
    from fbgcomp.structure import thermal

    full = Twin(machine, resolution=RES, cache=False)
    static = Twin(machine, resolution=RES, reduce_thermal=False)
    assert static._reduced is None and not static.times.from_cache
    (entry,) = _entries(cache_dir)
    key = entry.name[: -len(".twin")]
    assert twin_cache.load(key, Twin._UNREDUCED_ARRAYS) is not None
    assert twin_cache.load(key, Twin._ARRAYS) is None  # no reduction stored
    inf, ref = static.influence, full.influence
    for a in (
        "sensor_per_force_um_per_N",
        "ttp_per_force_um_per_N",
        "elastic_per_temperature",
        "steady_per_input",
    ):
        assert np.array_equal(getattr(inf, a), getattr(ref, a)), a
    _assert_identical(
        list(static.static_temperature_response("uniform", 10.0)),
        list(full.static_temperature_response("uniform", 10.0)),
    )
    assert static._reduced is None  # none of that needed it
    # a twin that needs the reduction completes the entry, and a later one loads it whole
    completed = Twin(machine, resolution=RES)
    assert completed.times.from_cache and completed._reduced is not None
    assert twin_cache.load(key, Twin._ARRAYS) is not None
    whole = Twin(machine, resolution=RES)
    assert whole.times.from_cache and whole.times.cache_store_s == 0.0
    for twin in (static, completed, whole):  # the first reduces on first use
        for name in thermal.ReducedThermal.ARRAYS:
            assert np.array_equal(getattr(twin.reduced, name), getattr(full.reduced, name)), name
    _assert_identical(_responses(static), _responses(full))


def test_a_twin_that_differs_in_its_thermal_description_only_shares_the_static_half(Twin, machine):
    """The physical model's generic-heat twin (the machine's, with a radiant source on every
    face) has the machine twin's mesh, elasticity and instruments: built after it in the same
    process it takes that half as it is, and answers to the bit as when built alone. Another
    grating or a heat zone that refines the mesh is another static half."""
    from fbgcomp.structure import twin as twin_module
    from fbgcomp.structure.scenarios import generic_heat_machine

    heat_machine = generic_heat_machine(machine)
    twin_module._last_static.clear()
    alone = Twin(heat_machine, resolution=RES, cache=False)
    assert "static_half_shared" not in alone.times.extra
    Twin(machine, resolution=RES, cache=False)
    shared = Twin(heat_machine, resolution=RES, cache=False)
    assert shared.times.extra["static_half_shared"] and shared.times.elastic_factor_s == 0.0
    _assert_identical(_responses(shared), _responses(alone))
    assert np.array_equal(shared.influence.steady_per_input, alone.influence.steady_per_input)
    # a grating moved: its own static half
    d = machine.model_dump()
    d["sensors"][0]["offset_mm"] = d["sensors"][0]["offset_mm"] + 10.0
    from fbgcomp.structure.machine import parse_machine

    assert "static_half_shared" not in Twin(parse_machine(d), resolution=RES, cache=False).times.extra
    # a lamp on part of a face: its zone's ends are grid lines, another mesh, its own half too
    d = heat_machine.model_dump()
    lamp = {"name": "lamp", "kind": "radiant", "face": "+Y", "z_mm": [300.0, 777.0], "nominal_W_per_m2": 50.0}
    d["thermal"]["heat_sources"] = [*d["thermal"]["heat_sources"], lamp]
    assert "static_half_shared" not in Twin(parse_machine(d), resolution=RES, cache=False).times.extra


def test_another_process_takes_the_static_half_from_the_cached_entry_of_a_twin_that_has_it(
    Twin, machine, cache_dir
):
    """A process that builds a twin whose description differs from a cached one's in its thermal
    section only (an edited film, the physical model's generic-heat twin after a simulate) finds
    the static half in that entry: it assembles and factorises no elasticity, and answers to the
    bit as when built alone. A pruned entry takes its record with it, and the next such twin
    builds its own half."""
    from fbgcomp.structure import twin as twin_module
    from fbgcomp.structure.scenarios import generic_heat_machine

    heat_machine = generic_heat_machine(machine)
    alone = Twin(heat_machine, resolution=RES, cache=False)
    twin_module._last_static.clear()
    first = Twin(machine, resolution=RES)
    assert "static_half_from_cache" not in first.times.extra
    (record,) = (cache_dir / twin_cache.STATIC).iterdir()
    assert record.name == first._static_key and record.read_text() == first.cache_key
    twin_module._last_static.clear()  # as in another process
    taken = Twin(heat_machine, resolution=RES)
    assert not taken.times.from_cache and taken.times.extra["static_half_from_cache"]
    assert taken.times.elastic_factor_s == 0.0
    assert len(_entries(cache_dir)) == 2  # its own entry, stored whole
    _assert_identical(_responses(taken), _responses(alone))
    # the record now names the newer entry; with the older pruned away it still holds
    (cache_dir / f"{first.cache_key}.twin").unlink()
    twin_cache.prune(cache_dir)
    assert twin_cache.static_entry(first._static_key, cache_dir) == taken.cache_key
    # with no entry left that holds it, the record is gone and the half is built again
    (cache_dir / f"{taken.cache_key}.twin").unlink()
    assert twin_cache.static_entry(first._static_key, cache_dir) is None
    twin_cache.prune(cache_dir)
    assert not list((cache_dir / twin_cache.STATIC).iterdir())
    twin_module._last_static.clear()
    again = Twin(heat_machine, resolution=RES)
    assert "static_half_from_cache" not in again.times.extra and again.times.elastic_factor_s > 0.0


def test_key_follows_the_machine_content_not_its_file(tmp_path, machine):
    data = yaml.safe_load(DEFAULT_YAML.read_text())
    same = tmp_path / "elsewhere" / "same.yaml"
    same.parent.mkdir()
    same.write_text(yaml.safe_dump(data, sort_keys=True, indent=4))  # other path and layout
    key = twin_cache.twin_key(machine, RES, 12)
    assert twin_cache.twin_key(load_machine(same), RES, 12) == key
    data["materials"]["cfrp"]["E_L_GPa"] = 121.0
    changed = tmp_path / "changed.yaml"
    changed.write_text(yaml.safe_dump(data))
    assert twin_cache.twin_key(load_machine(changed), RES, 12) != key
    assert twin_cache.twin_key(machine, 0.31, 12) != key
    assert twin_cache.twin_key(machine, RES, 11) != key
    assert twin_cache.twin_key(machine.with_z_axis(100.0), RES, 12) != key


def test_code_version_covers_the_structure_sources_and_invalidates_the_key(machine, monkeypatch):
    version = twin_cache.code_version()
    assert version.startswith("fbgcomp=") and "structure=" in version and "scikit-fem=" in version
    key = twin_cache.twin_key(machine, RES, 12)
    monkeypatch.setattr(twin_cache, "code_version", lambda: version + "-edited")
    assert twin_cache.twin_key(machine, RES, 12) != key


@pytest.fixture(scope="session")
def good_entry(machine, tmp_path_factory):
    """(file name, bytes) of a complete entry of the RES twin, and that twin's responses."""
    fbgcomp_testing.require("skfem")
    from fbgcomp.structure import Twin

    folder = tmp_path_factory.mktemp("good-entry")
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("FBGCOMP_CACHE_DIR", str(folder))
        twin = Twin(machine, resolution=RES)
    (entry,) = _entries(folder / "twin")
    return entry.name, entry.read_bytes(), _responses(twin)


@pytest.mark.parametrize("damage", ["truncate", "flip", "garbage", "empty", "other_key"])
def test_a_bad_entry_is_rebuilt_never_used(Twin, machine, cache_dir, good_entry, damage):
    name, data, reference = good_entry
    cache_dir.mkdir(parents=True)
    entry = cache_dir / name
    if damage == "truncate":
        entry.write_bytes(data[: len(data) // 2])
    elif damage == "flip":
        i = len(data) * 2 // 3
        entry.write_bytes(data[:i] + bytes([data[i] ^ 0x01]) + data[i + 1 :])
    elif damage == "garbage":
        entry.write_bytes(b"PK\x03\x04" + bytes(1000))
    elif damage == "empty":
        entry.write_bytes(b"")
    else:  # a complete, valid entry of another twin under this twin's name
        entry.write_bytes(twin_cache.dumps("0" * 64, {"K": np.eye(2)}))
    again = Twin(machine, resolution=RES)
    assert not again.times.from_cache
    _assert_identical(reference, _responses(again))
    assert len(entry.read_bytes()) == len(data)  # rewritten, complete (times differ)
    assert twin_cache.load(name[: -len(".twin")], Twin._ARRAYS) is not None


def test_the_good_entry_itself_loads(Twin, machine, cache_dir, good_entry):
    name, data, reference = good_entry
    cache_dir.mkdir(parents=True)
    (cache_dir / name).write_bytes(data)
    warm = Twin(machine, resolution=RES)
    assert warm.times.from_cache
    _assert_identical(reference, _responses(warm))


def test_an_entry_lacking_an_array_is_rebuilt(machine, cache_dir):
    key = twin_cache.twin_key(machine, RES, 12)
    twin_cache.store(key, {"K": np.eye(3)})
    assert twin_cache.load(key, required=("K",)) is not None
    assert twin_cache.load(key, required=("K", "Th")) is None


def test_disabled_cache_reads_and_writes_nothing(Twin, machine, tmp_path, monkeypatch):
    user = tmp_path / "user-cache"
    monkeypatch.setattr("platformdirs.user_cache_dir", lambda *a, **k: str(user))
    for off in ("OFF", "0", "disabled", " off "):
        monkeypatch.setenv("FBGCOMP_CACHE_DIR", off)
        assert twin_cache.cache_dir() is None
    monkeypatch.setenv("FBGCOMP_CACHE_DIR", "off")
    twin = Twin(machine, resolution=RES)
    assert not twin.times.from_cache and twin.times.cache_path is None
    assert not user.exists() and not (Path.cwd() / "off").exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == []


def test_cache_false_reads_and_writes_nothing(Twin, machine, cache_dir):
    Twin(machine, resolution=RES, cache=False)
    assert not cache_dir.exists()


def test_default_folder_is_the_users_cache_dir(tmp_path, monkeypatch):
    monkeypatch.delenv("FBGCOMP_CACHE_DIR", raising=False)
    monkeypatch.setattr("platformdirs.user_cache_dir", lambda name, *a, **k: str(tmp_path / "user" / name))
    assert twin_cache.cache_dir() == tmp_path / "user" / "fbgcomp" / "twin"


def test_unwritable_cache_folder_still_builds(Twin, machine, tmp_path, monkeypatch):
    blocker = tmp_path / "a-file"
    blocker.write_text("not a folder")
    monkeypatch.setenv("FBGCOMP_CACHE_DIR", str(blocker))
    twin = Twin(machine, resolution=RES)
    assert not twin.times.from_cache and twin.times.cache_path is None
    assert twin.static(np.eye(3)).ttp_um.shape == (3, 3)


def test_concurrent_writers_and_readers_see_whole_entries_only(cache_dir):
    rng = np.random.default_rng(0)
    arrays = {"a": rng.standard_normal((400, 1000)), "b": np.arange(10)}
    key = "f" * 64
    errors, seen = [], []

    def write():
        try:
            for _ in range(5):
                twin_cache.store(key, arrays)
        except Exception as err:  # pragma: no cover - the assertion below reports it
            errors.append(err)

    def read():
        for _ in range(40):
            got = twin_cache.load(key, required=("a", "b"))
            if got is not None:
                seen.append(np.array_equal(got["a"], arrays["a"]) and np.array_equal(got["b"], arrays["b"]))

    threads = [threading.Thread(target=write) for _ in range(3)] + [threading.Thread(target=read)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not errors and all(seen)
    assert [p.name for p in cache_dir.iterdir()] == [f"{key}.twin"]  # no temporary file left
    assert twin_cache.load(key, required=("a",)) is not None


def test_old_entries_are_pruned_to_the_most_recently_used(cache_dir):
    import os

    keys = [f"{i:064x}" for i in range(5)]
    for i, k in enumerate(keys):
        path = twin_cache.store(k, {"x": np.zeros(3)}, folder=cache_dir)
        os.utime(path, (1e9 + i, 1e9 + i))  # distinct use times, oldest first
    stale = cache_dir / ".dead-writer.twin.abc.tmp"
    stale.write_bytes(b"half")
    os.utime(stale, (1e9, 1e9))
    twin_cache.prune(cache_dir, keep=3)
    assert [p.name[:-5] for p in _entries(cache_dir)] == sorted(keys[2:])
    assert not stale.exists()
    # the size cap: only the newest entry fits in 1 byte, and it always stays
    twin_cache.prune(cache_dir, max_bytes=1)
    assert [p.name[:-5] for p in _entries(cache_dir)] == [keys[-1]]


def test_the_limits_come_from_the_environment_and_a_bad_value_keeps_the_default(
    cache_dir, monkeypatch, caplog
):
    keys = [f"{i:064x}" for i in range(4)]
    for i, k in enumerate(keys):
        path = twin_cache.store(k, {"x": np.zeros(3)}, folder=cache_dir)
        os.utime(path, (1e9 + i, 1e9 + i))
    monkeypatch.setenv(twin_cache.ENV_MAX_ENTRIES, "two")
    twin_cache.prune(cache_dir)
    assert len(_entries(cache_dir)) == 4  # the default (8) kept them all
    assert "FBGCOMP_CACHE_MAX_ENTRIES='two' is not a positive integer; using 8" in caplog.text
    monkeypatch.setenv(twin_cache.ENV_MAX_ENTRIES, "2")
    twin_cache.prune(cache_dir)
    assert [p.name[:-5] for p in _entries(cache_dir)] == sorted(keys[2:])
    monkeypatch.setenv(twin_cache.ENV_MAX_ENTRIES, "64")
    monkeypatch.setenv(twin_cache.ENV_MAX_BYTES, "1")
    twin_cache.prune(cache_dir)
    assert [p.name[:-5] for p in _entries(cache_dir)] == [keys[-1]]


def test_a_stale_lock_of_a_gone_entry_is_pruned_and_a_live_ones_lock_kept(cache_dir):
    kept, gone = "a" * 64, "b" * 64
    twin_cache.store(kept, {"x": np.zeros(3)}, folder=cache_dir)
    for key in (kept, gone):
        with twin_cache.build_lock(key, cache_dir):
            pass
        os.utime(cache_dir / twin_cache.LOCKS / f"{key}.lock", (1e9, 1e9))
    fresh = "c" * 64
    with twin_cache.build_lock(fresh, cache_dir):
        pass
    twin_cache.prune(cache_dir)
    left = sorted(p.name for p in (cache_dir / twin_cache.LOCKS).iterdir())
    assert left == [f"{kept}.lock", f"{fresh}.lock"]


def test_the_build_lock_excludes_a_second_holder(cache_dir):
    """A second process asking for the lock of a key another holds waits until it is released."""
    import subprocess
    import sys
    import time

    key = "d" * 64
    code = (
        "import sys, time; from pathlib import Path; from fbgcomp.structure import cache; "
        "print('asking', flush=True); t = time.time(); "
        f"ctx = cache.build_lock({key!r}, Path(sys.argv[1])); ctx.__enter__(); print(time.time() - t)"
    )
    with twin_cache.build_lock(key, cache_dir):
        proc = subprocess.Popen(
            [sys.executable, "-c", code, str(cache_dir)], stdout=subprocess.PIPE, text=True
        )
        assert proc.stdout.readline().strip() == "asking"
        time.sleep(1.0)
        assert proc.poll() is None  # still waiting for the lock
    out, _ = proc.communicate(timeout=60)
    assert proc.returncode == 0 and float(out) >= 1.0


def test_entries_hold_no_pickle(cache_dir):
    with pytest.raises(TypeError):
        twin_cache.dumps("0" * 64, {"x": np.array([object()], dtype=object)})


@pytest.mark.slow
def test_concurrent_builder_processes_leave_one_whole_entry(Twin, machine, cache_dir, good_entry):
    """Two processes build the same twin at once into one cache folder: both finish, one complete
    entry remains, and it loads into the twin the reference build gives. The build lock makes
    one of them build it and the other load that build."""
    import os
    import subprocess
    import sys

    code = (
        "from fbgcomp.structure import Twin, load_machine; "
        f"t = Twin(load_machine(), resolution={RES}); print(t.times.from_cache)"
    )
    env = dict(os.environ)  # FBGCOMP_CACHE_DIR: this test's folder (monkeypatched)
    procs = [
        subprocess.Popen(
            [sys.executable, "-c", code], env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
        )
        for _ in range(2)
    ]
    outs = [p.communicate(timeout=300) for p in procs]
    assert [p.returncode for p in procs] == [0, 0], [o[1][-2000:] for o in outs]
    assert sorted(o[0].split()[-1] for o in outs) == ["False", "True"]  # built once, loaded once
    # the entry, the lock folder and its static half's record: no temporary file
    assert sorted(p.name for p in cache_dir.iterdir()) == sorted(
        [good_entry[0], twin_cache.LOCKS, twin_cache.STATIC]
    )
    assert not [p for p in (cache_dir / twin_cache.STATIC).iterdir() if p.name.startswith(".")]
    warm = Twin(machine, resolution=RES)
    assert warm.times.from_cache
    # the entry is another process's build: a threaded BLAS may round its sums differently
    # there (it did, in the last bits, on a loaded machine), so equal to round-off, not bit for bit
    got = _responses(warm)
    assert len(got) == len(good_entry[2])
    for x, y in zip(good_entry[2], got):
        np.testing.assert_allclose(y, x, rtol=1e-9, atol=1e-12 * max(1.0, float(np.abs(x).max())))


def test_the_test_session_never_uses_the_users_cache():
    """tests/conftest.py points FBGCOMP_CACHE_DIR at a temporary folder of the run, the same for
    every xdist worker."""
    import os
    import tempfile

    import platformdirs

    folder = os.environ.get("FBGCOMP_CACHE_DIR", "")
    assert folder and Path(folder).resolve().is_relative_to(Path(tempfile.gettempdir()).resolve())
    assert not Path(folder).resolve().is_relative_to(Path(platformdirs.user_cache_dir("fbgcomp")).resolve())
    assert os.environ.get(twin_cache.ENV_MAX_ENTRIES) == "64"  # room for the suite's twins


def test_a_machine_with_an_infinite_value_has_a_key_of_its_own(machine):
    """The schema accepts carriage_stiffness_N_per_um: .inf; its key must neither crash (JSON
    has no Infinity by default) nor collide with another machine's."""
    from fbgcomp.structure import parse_machine

    data = machine.model_dump(mode="json")
    data["supports"]["carriage_stiffness_N_per_um"] = float("inf")
    inf_key = twin_cache.twin_key(parse_machine(data), RES, 12)
    data["supports"]["carriage_stiffness_N_per_um"] = 1e300
    assert inf_key != twin_cache.twin_key(parse_machine(data), RES, 12)
    assert inf_key != twin_cache.twin_key(machine, RES, 12)


def test_a_derived_result_is_computed_once_and_read_back_exactly(cache_dir):
    calls = []
    value = {
        "f64": np.array([[0.1, np.nan], [np.inf, -1e-300]]),
        "i32": np.arange(3, dtype=np.int32),
        "list": [0.1 + 0.2, float("nan"), 3, "S1", None, True],
        "nested": [{"a": np.ones((0, 2))}],
    }

    def compute():
        calls.append(1)
        return value

    first = twin_cache.cached_json("test", {"machine": "m", "seed": 0}, compute)
    again = twin_cache.cached_json("test", {"seed": 0, "machine": "m"}, compute)  # same ident
    assert first is value and len(calls) == 1
    assert again["f64"].dtype == np.float64 and np.array_equal(again["f64"], value["f64"], equal_nan=True)
    assert again["i32"].dtype == np.int32 and again["i32"].tolist() == [0, 1, 2]
    assert again["list"][0] == 0.1 + 0.2 and again["list"][1] != again["list"][1]
    assert again["list"][2:] == [3, "S1", None, True]
    assert again["nested"][0]["a"].shape == (0, 2)
    (entry,) = _entries(cache_dir.parent / twin_cache.DERIVED)
    assert b"pickle" not in entry.read_bytes()
    twin_cache.cached_json("test", {"machine": "m", "seed": 1}, compute)  # another ident
    twin_cache.cached_json("other", {"machine": "m", "seed": 0}, compute)  # another kind
    assert len(calls) == 3


def test_a_damaged_derived_entry_is_computed_again(cache_dir):
    calls = []

    def compute():
        calls.append(1)
        return {"x": np.arange(4.0)}

    twin_cache.cached_json("test", {"k": 1}, compute)
    (entry,) = _entries(cache_dir.parent / twin_cache.DERIVED)
    data = entry.read_bytes()
    entry.write_bytes(data[: len(data) // 2])
    again = twin_cache.cached_json("test", {"k": 1}, compute)
    assert len(calls) == 2 and again["x"].tolist() == [0.0, 1.0, 2.0, 3.0]
    assert entry.read_bytes() == data  # rewritten whole
    assert twin_cache.cached_json("test", {"k": 1}, compute)["x"].tolist() == [0.0, 1.0, 2.0, 3.0]
    assert len(calls) == 2


def test_numpy_scalars_are_kept_and_a_result_json_cannot_hold_is_computed_each_time(cache_dir):
    calls = []

    def scalars():
        calls.append(1)
        return {"n": np.int64(7), "x": np.float64(0.1), "ok": np.bool_(True)}

    twin_cache.cached_json("test", {"k": 2}, scalars)
    back = twin_cache.cached_json("test", {"k": 2}, scalars)
    assert len(calls) == 1 and back == {"n": 7, "x": 0.1, "ok": True} and type(back["n"]) is int

    def opaque():
        calls.append(1)
        return {"f": object()}

    for _ in range(2):
        assert set(twin_cache.cached_json("test", {"k": 3}, opaque)) == {"f"}
    assert len(calls) == 3


def test_with_the_cache_off_a_derived_result_is_always_computed(tmp_path, monkeypatch):
    monkeypatch.setenv("FBGCOMP_CACHE_DIR", "off")
    monkeypatch.chdir(tmp_path)
    calls = []
    for _ in range(2):
        twin_cache.cached_json("test", {"k": 1}, lambda: calls.append(1) or [1.0])
    assert len(calls) == 2 and list(tmp_path.iterdir()) == []
