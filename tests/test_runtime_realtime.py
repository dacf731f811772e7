"""What ``fbgcomp serve`` sets for its own process (fbgcomp.runtime.realtime), in a fresh process."""

import json
import os
import subprocess
import sys

import pytest

import fbgcomp_testing

SCRIPT = """
import json, sys
import numpy  # loads BLAS with the environment's thread count
from threadpoolctl import threadpool_info
from fbgcomp.runtime import realtime
blas = lambda: sorted({p["num_threads"] for p in threadpool_info() if p["user_api"] == "blas"})
before = blas()
lines = realtime.apply(realtime.RealtimeConfig(gc_threshold=0, blas_threads=int(sys.argv[1])))
print(json.dumps({"before": before, "after": blas(), "lines": lines}))
"""


def _apply(blas_threads: int) -> dict:
    env = {k: v for k, v in os.environ.items() if not k.endswith("_NUM_THREADS")}
    env["OPENBLAS_NUM_THREADS"] = "2"  # a threaded BLAS, as a machine with cores would load it
    out = subprocess.run(
        [sys.executable, "-c", SCRIPT, str(blas_threads)], env=env, capture_output=True, text=True, timeout=60
    )
    assert out.returncode == 0, out.stderr
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_serve_runs_blas_on_one_thread_and_says_so():
    fbgcomp_testing.require("threadpoolctl")
    got = _apply(1)
    if got["before"] != [2]:
        pytest.fail(f"the test's threaded BLAS did not load: {got}")
    assert got["after"] == [1]
    assert "BLAS on 1 thread (was 2)" in got["lines"]


def test_blas_threads_zero_keeps_the_library_setting():
    fbgcomp_testing.require("threadpoolctl")
    got = _apply(0)
    assert got["after"] == got["before"] == [2]
    assert not any("BLAS" in line for line in got["lines"])


def test_blas_threads_is_a_realtime_key_of_serves_configuration(tmp_path):
    from fbgcomp.errors import InputError
    from fbgcomp.runtime.service import RuntimeConfig

    assert RuntimeConfig().realtime.blas_threads == 1
    (tmp_path / "serve.toml").write_text("[realtime]\nblas_threads = 0\n")
    assert RuntimeConfig.from_toml(tmp_path / "serve.toml").realtime.blas_threads == 0
    (tmp_path / "bad.toml").write_text('[realtime]\nblas_threads = "one"\n')
    with pytest.raises(InputError, match=r"realtime\.blas_threads"):
        RuntimeConfig.from_toml(tmp_path / "bad.toml")
