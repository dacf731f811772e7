"""Shared test helpers (imported by the tests; pytest puts this folder on sys.path)."""

from __future__ import annotations

import contextlib
import importlib
import io
import os
import shutil
import subprocess
from pathlib import Path

import pytest


def require_all() -> bool:
    """True in CI: every optional component must be present, no silent skips."""
    return os.environ.get("FBGCOMP_REQUIRE_ALL", "") not in ("", "0")


def require(module: str):
    """Import an optional module, skipping the test locally when it is missing (failing in CI)."""
    try:
        return importlib.import_module(module)
    except ImportError as exc:
        if require_all():
            pytest.fail(f"optional component {module!r} is required in CI: {exc}")
        pytest.skip(f"{module} not installed")


def require_program(name: str) -> str:
    """Path of an external program, skipping locally when missing (failing in CI)."""
    path = shutil.which(name)
    if path is None:
        if require_all():
            pytest.fail(f"program {name!r} is required in CI but not on PATH")
        pytest.skip(f"{name} not on PATH")
    return path


def cli(*args, cwd=None, env=None) -> subprocess.CompletedProcess:
    """``fbgcomp ARGS`` run in this process by the console script's own function
    (:func:`fbgcomp.cli.app.main`): its exit code, stdout and stderr, as ``subprocess.run`` gives
    them. What a command does, prints and writes is the same as in a process of its own, without
    that process's ~1.5 s of imports (the suite's short commands: ~85 processes). What only a
    process shows (the console script itself, signals, a kill, a server's lifetime) is tested in
    one. A traceback fails the test here, where a process would print it. ``cwd``: the working
    folder of the call; ``env``: variables set for the call (``None`` removes one)."""
    from fbgcomp.cli.app import main

    argv = [str(a) for a in args]
    out, err = io.StringIO(), io.StringIO()
    saved = {k: os.environ.get(k) for k in env or {}}
    try:
        for k, v in (env or {}).items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = str(v)
        with contextlib.ExitStack() as stack:
            if cwd is not None:
                stack.enter_context(contextlib.chdir(cwd))
            stack.enter_context(contextlib.redirect_stdout(out))
            stack.enter_context(contextlib.redirect_stderr(err))
            code = main(argv)
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v
    return subprocess.CompletedProcess(["fbgcomp", *argv], code, out.getvalue(), err.getvalue())


#: The independent reference ram: ``$FBGCOMP_RAM2`` (the data set's root, as ``fbgcomp demo`` and
#: the benchmarks read it), else ../shared/reference/ram2 beside the repository (CI has it).
RAM2_DIR = Path(
    os.environ.get("FBGCOMP_RAM2") or Path(__file__).resolve().parents[2] / "shared" / "reference" / "ram2"
)


def read_ram2(*names: str) -> dict:
    """ram2's campaigns by name, read from ``RAM2_DIR/data``; fails (never skips) when the data
    set is missing, because the project's accuracy is judged on it."""
    from fbgcomp.io.campaign import read_campaign

    data = RAM2_DIR / "data"
    if not data.is_dir():
        pytest.fail(f"the independent reference data set is missing: {data}")
    return {n: read_campaign(data / n) for n in names}


#: A second independent ram (CalculiX, five gratings, three probes, both rails on -X), held in the
#: repository as a compressed archive (tests/data/README.md); its description from its data sheet.
RAM3_ARCHIVE = Path(__file__).resolve().parent / "data" / "ram3.tar.xz"
RAM3_MACHINE = Path(__file__).resolve().parents[1] / "examples" / "machines" / "ram3.yaml"
#: A third (CalculiX, rails on two adjacent faces, seven gratings and two strain-free reference
#: gratings, a cast-iron housing with two heat sources), held the same way.
RAM4_ARCHIVE = Path(__file__).resolve().parent / "data" / "ram4.tar.xz"
RAM4_MACHINE = Path(__file__).resolve().parents[1] / "examples" / "machines" / "ram4.yaml"
#: A fourth (CalculiX, rails on two opposite faces, the -Y one floating along its normal, five
#: gratings, five probes), held the same way.
RAM5_ARCHIVE = Path(__file__).resolve().parent / "data" / "ram5.tar.xz"
RAM5_MACHINE = Path(__file__).resolve().parents[1] / "examples" / "machines" / "ram5.yaml"
#: A fifth (CalculiX, rails on two adjacent faces, the +Y one floating along its normal, a CFRP
#: that shortens when warmed, six gratings, a heat source at the top), held the same way.
RAM6_ARCHIVE = Path(__file__).resolve().parent / "data" / "ram6.tar.xz"
RAM6_MACHINE = Path(__file__).resolve().parents[1] / "examples" / "machines" / "ram6.yaml"
#: A sixth (CalculiX, a long box on two opposite faces, both rails locating at three carriage
#: stations, five gratings, an aluminium housing), held the same way.
RAM7_ARCHIVE = Path(__file__).resolve().parent / "data" / "ram7.tar.xz"
RAM7_MACHINE = Path(__file__).resolve().parents[1] / "examples" / "machines" / "ram7.yaml"
#: A seventh (CalculiX, a box whose +X wall, carrying both rails, is thicker than the -X wall:
#: a wall per face in its description; six gratings), held the same way.
RAM8_ARCHIVE = Path(__file__).resolve().parent / "data" / "ram8.tar.xz"
RAM8_MACHINE = Path(__file__).resolve().parents[1] / "examples" / "machines" / "ram8.yaml"


def unpacked(archive: Path) -> Path:
    """An independent ram's folder (README.md, data/<campaign>/), unpacked once per archive into
    the temporary directory (under a name of the archive's size and time, renamed into place when
    complete)."""
    import tarfile
    import tempfile

    st = archive.stat()
    stem = archive.name.split(".")[0]
    dest = Path(tempfile.gettempdir()) / f"fbgcomp-{stem}-{st.st_size}-{int(st.st_mtime)}"
    if not (dest / "data").is_dir():
        part = Path(tempfile.mkdtemp(prefix=f"fbgcomp-{stem}-part-"))
        with tarfile.open(archive) as tar:
            tar.extractall(part, filter="data")
        try:
            part.rename(dest)
        except OSError:  # another process finished first
            shutil.rmtree(part, ignore_errors=True)
    return dest


def ram3_dir() -> Path:
    """ram3's folder, unpacked once (:func:`unpacked`)."""
    return unpacked(RAM3_ARCHIVE)


def read_unpacked(archive: Path, *names: str) -> dict:
    """An archived ram's campaigns by name (:func:`unpacked`)."""
    from fbgcomp.io.campaign import read_campaign

    data = unpacked(archive) / "data"
    return {n: read_campaign(data / n) for n in names}


def read_ram3(*names: str) -> dict:
    """ram3's campaigns by name."""
    return read_unpacked(RAM3_ARCHIVE, *names)


def read_ram4(*names: str) -> dict:
    """ram4's campaigns by name."""
    return read_unpacked(RAM4_ARCHIVE, *names)


def read_ram5(*names: str) -> dict:
    """ram5's campaigns by name."""
    return read_unpacked(RAM5_ARCHIVE, *names)


def read_ram6(*names: str) -> dict:
    """ram6's campaigns by name."""
    return read_unpacked(RAM6_ARCHIVE, *names)


def read_ram7(*names: str) -> dict:
    """ram7's campaigns by name."""
    return read_unpacked(RAM7_ARCHIVE, *names)


def read_ram8(*names: str) -> dict:
    """ram8's campaigns by name."""
    return read_unpacked(RAM8_ARCHIVE, *names)


def assert_data_sheet_describes(archive: Path, machine: Path, campaigns, phrase: str) -> None:
    """An archived ram holds its data sheet (README.md, which says ``phrase``) and every campaign
    in ``campaigns``, each naming the description's gratings and probes in its order."""
    import yaml

    folder = unpacked(archive)
    assert phrase in (folder / "README.md").read_text()
    desc = yaml.safe_load(Path(machine).read_text())
    for name in campaigns:
        meta = yaml.safe_load((folder / "data" / name / "campaign.yaml").read_text())
        assert [s["name"] for s in meta["sensors"]] == [s["name"] for s in desc["sensors"]]
        header = (folder / "data" / name / "temperatures.csv").read_text().splitlines()[0]
        assert header.split(",")[1:] == [f"{p['name']}_C" for p in desc["probes"]]


def held_out_figures(model, campaign):
    """A model judged on a campaign it never saw, as ``fbgcomp validate`` judges it: per axis
    (3,) the max |error| µm, the uncompensated peak µm and the 95 % interval's coverage."""
    import numpy as np

    ref = campaign.aligned(zero_window_s=model.zero_window_s).reference_um
    pred, half = model.predict_interval(campaign)
    err = np.abs(pred - ref)
    return err.max(axis=0), np.abs(ref).max(axis=0), (err <= half).mean(axis=0)


def assert_twin_check(machine, results_json, sensor_names, n_judged, resolution=0.5):
    """``fbgcomp twin-check MACHINE --against RESULTS``, asserted: the independent model names
    ``sensor_names``, and every one of its ``n_judged`` judged quantities is within target (unit
    loads 3 %, uniform +10 K dz 2 %), and the TTP 36 h after each unit thermal step the results
    carry within 5 % (reported by the command without a target). The twin is built coarser than
    the description's own mesh by default (hex8i converges fast): one FE build of seconds."""
    from fbgcomp.structure import Twin, load_machine, twin_check

    reference = twin_check.load_reference(results_json)
    assert reference.sensor_names == tuple(sensor_names)
    rows = twin_check.compare(
        Twin(load_machine(machine), resolution=resolution, reduce_thermal=False), reference
    )
    judged = [r for r in rows if r.passed is not None]
    assert len(judged) == n_judged
    assert all(r.passed for r in judged), [r for r in judged if not r.passed]
    dz = next(r for r in rows if r.quantity == "+10 K dz (um)")
    assert abs(dz.twin / dz.independent - 1) <= 0.02
    # the unit thermal steps (reported, no target): each input the results carry has its rows,
    # and each TTP component of at least a tenth of its step's largest is within 5 %. The
    # ambient step's lateral figures are left out, as the uniform case's are: they rest on the
    # held strips' restraint, the least converged figure of an independent model (ram5's
    # uniform dy moves 5.2 % on halving its mesh; its ambient step's dy is 5.7 % off the twin's)
    by_name = {r.quantity: r for r in rows}
    for case, figures in reference.thermal_steps_um.items():
        largest = max(abs(figures[a]) for a in ("dx", "dy", "dz"))
        for a in ("dx", "dy", "dz"):
            r = by_name[f"36 h {case} step {a} (um)"]
            if abs(r.independent) >= 0.1 * largest and (case != "ambient" or a == "dz"):
                assert abs(r.twin / r.independent - 1) <= 0.05, r
