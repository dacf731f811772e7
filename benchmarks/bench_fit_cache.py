"""What the on-disk cache saves a default fit: ``fbgcomp fit`` on ram2 with no cache, cold and warm.

``fbgcomp fit thermal_a static_xyz --machine examples/machines/ram2.yaml`` (the default physical
model, ../shared/reference/ram2 or ``--ram2``) run as a command three ways, interleaved, median
of ``--reps``:

* **no cache** (the baseline): ``FBGCOMP_CACHE_DIR=off``, the twin built, its thermal-map
  population and the heat prior's observer run computed, nothing stored;
* **cold**: an empty cache folder (a new one each repetition): the same work, plus writing the
  twin's entry and the derived results (``fbgcomp.structure.cache``);
* **warm**: the folder the cold run filled: the twin loaded, the population and the observer
  run read back.

The three model files must be the same but for their creation time (the cache gives the same
numbers: exit 1 otherwise). Last line: one JSON object.

    .venv/bin/python benchmarks/bench_fit_cache.py [--ram2 PATH] [--reps 3]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from datetime import UTC, datetime
from pathlib import Path

from _loopback import git_commit

REPO = Path(__file__).resolve().parents[1]
MACHINE = REPO / "examples" / "machines" / "ram2.yaml"


def fit(data: Path, out: Path, cache: str) -> float:
    """Seconds of one ``fbgcomp fit`` command with ``FBGCOMP_CACHE_DIR=cache``."""
    env = {**os.environ, "FBGCOMP_CACHE_DIR": cache}
    cmd = [sys.executable, "-m", "fbgcomp", "-q", "fit", data / "thermal_a", data / "static_xyz"]
    t0 = time.perf_counter()
    r = subprocess.run(
        [*map(str, cmd), "--machine", str(MACHINE), "-o", str(out)], env=env, capture_output=True, text=True
    )
    seconds = time.perf_counter() - t0
    if r.returncode != 0:
        raise SystemExit(f"fbgcomp fit failed ({cache}):\n{r.stderr[-3000:]}")
    return seconds


def content(path: Path) -> dict:
    """The model file without the fields that name the run (creation time, the id derived from it)."""
    d = json.loads(path.read_text())
    for k in ("created_utc", "model_id"):
        d.pop(k, None)
    return d


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--ram2", type=Path, default=REPO.parent / "shared" / "reference" / "ram2")
    ap.add_argument("--reps", type=int, default=3)
    args = ap.parse_args(argv)
    data = args.ram2 / "data"
    if not data.is_dir():
        raise SystemExit(f"ram2 not found at {args.ram2} (give --ram2)")
    started = datetime.now(UTC)
    print(f"{started:%Y-%m-%d %H:%M} UTC, code of {git_commit()}, load average {os.getloadavg()[0]:.1f}")
    times: dict[str, list[float]] = {"no cache": [], "cold": [], "warm": []}
    with tempfile.TemporaryDirectory(prefix="bench-fit-cache-") as tmp:
        work = Path(tmp)
        files = {}
        for rep in range(args.reps):
            folder = work / f"cache{rep}"
            for name, cache in (("no cache", "off"), ("cold", str(folder)), ("warm", str(folder))):
                files[name] = work / f"{name.replace(' ', '-')}.json"
                s = fit(data, files[name], cache)
                times[name].append(s)
                print(f"  rep {rep + 1} {name:8s} {s:6.1f} s", flush=True)
        same = content(files["no cache"]) == content(files["cold"]) == content(files["warm"])
    med = {k: statistics.median(v) for k, v in times.items()}
    print(
        f"median of {args.reps}: no cache {med['no cache']:.1f} s, cold {med['cold']:.1f} s, "
        f"warm {med['warm']:.1f} s; no cache / warm {med['no cache'] / med['warm']:.2f}x, "
        f"cold / no cache {med['cold'] / med['no cache']:.2f}"
    )
    print(f"model files the same but for their creation: {same}")
    print(f"load average after: {os.getloadavg()[0]:.1f}")
    print(
        json.dumps(
            {
                "benchmark": "bench_fit_cache",
                "started": f"{started:%Y-%m-%dT%H:%M}Z",
                "baseline": "no cache",
                "seconds": times,
                "median_s": med,
                "speedup_warm": med["no cache"] / med["warm"],
                "cold_over_no_cache": med["cold"] / med["no cache"],
                "same_model": same,
            }
        )
    )
    return 0 if same else 1


if __name__ == "__main__":
    sys.exit(main())
