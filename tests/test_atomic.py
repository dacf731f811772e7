"""fbgcomp.atomic: a target is either its old content or the complete new one, never a half,
and no temporary file is left behind, whatever happens in between."""

import os
import stat

import numpy as np
import pytest

from fbgcomp.atomic import atomic_path, staged_dir, write_bytes, write_json


def test_atomic_path_replaces_the_target_only_on_success(tmp_path):
    target = tmp_path / "data.bin"
    target.write_bytes(b"old")
    with atomic_path(target) as tmp:
        assert tmp.parent == tmp_path and tmp.name.startswith(".data.bin.")
        assert tmp.name.endswith(".tmp") and tmp.is_file() and tmp.stat().st_size == 0
        tmp.write_bytes(b"new")
        assert target.read_bytes() == b"old"  # not yet: the block has not ended
    assert target.read_bytes() == b"new"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["data.bin"]


def test_atomic_path_keeps_the_old_target_and_removes_the_temporary_file_on_failure(tmp_path):
    target = tmp_path / "data.bin"
    target.write_bytes(b"old")
    with pytest.raises(RuntimeError, match="disk full"), atomic_path(target) as tmp:
        tmp.write_bytes(b"half")
        raise RuntimeError("disk full")
    assert target.read_bytes() == b"old"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["data.bin"]


def test_atomic_path_names_and_modes(tmp_path):
    """A library that insists on a suffix (np.save appends .npy) gets it; a trust-list folder's
    temporary file (prefix .incoming-) never spells der or pem; modes are as asked."""
    with atomic_path(tmp_path / "log.npy", suffix=".npy") as tmp:
        np.save(tmp, np.arange(3.0))
    assert np.array_equal(np.load(tmp_path / "log.npy"), [0.0, 1.0, 2.0])
    assert sorted(p.name for p in tmp_path.iterdir()) == ["log.npy"]
    for _ in range(50):
        with atomic_path(tmp_path / "plc-0123.der", prefix=".incoming-") as tmp:
            stem = tmp.name.removeprefix(".incoming-")
            assert "der" not in stem and "pem" not in stem
    old = os.umask(0o022)
    try:
        write_bytes(tmp_path / "public.der", b"c", mode=0o644)
        write_bytes(tmp_path / "key.pem", b"k")
    finally:
        os.umask(old)
    assert stat.S_IMODE((tmp_path / "public.der").stat().st_mode) == 0o644
    assert stat.S_IMODE((tmp_path / "key.pem").stat().st_mode) == 0o600


def test_write_json_check_refuses_without_touching_the_target(tmp_path):
    target = tmp_path / "sub" / "model.json"
    write_json(target, {"a": float("nan"), "b": np.float64(2.0)})
    assert target.read_text() == '{\n "a": null,\n "b": 2.0\n}\n'

    def refuse(written):
        assert written.read_text().startswith("{")  # complete before it is checked
        raise ValueError("not a model")

    with pytest.raises(ValueError, match="not a model"):
        write_json(target, {"a": 1}, check=refuse)
    assert '"b": 2.0' in target.read_text()
    assert sorted(p.name for p in target.parent.iterdir()) == ["model.json"]


def test_staged_dir_swaps_the_whole_folder_in_or_leaves_the_old_one(tmp_path):
    target = tmp_path / "out"
    target.mkdir()
    (target / "old.txt").write_text("old")
    with staged_dir(target) as staging:
        assert staging.parent == tmp_path and staging.name.startswith(".out.tmp-")
        assert not list(staging.iterdir())
        (staging / "new.txt").write_text("new")
        assert (target / "old.txt").is_file()  # nothing of the new folder is visible yet
    assert sorted(p.name for p in target.iterdir()) == ["new.txt"]
    with pytest.raises(RuntimeError, match="half way"), staged_dir(target) as staging:
        (staging / "half.txt").write_text("half")
        raise RuntimeError("half way")
    assert sorted(p.name for p in target.iterdir()) == ["new.txt"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]  # no staging or retired folder left
