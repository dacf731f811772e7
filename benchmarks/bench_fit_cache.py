"""What the on-disk cache saves a default fit: ``fbgcomp fit`` on ram2 with no cache, cold and warm.

``fbgcomp fit thermal_a static_xyz --machine examples/machines/ram2.yaml`` (the default physical
model, ../shared/reference/ram2 or ``--ram2``) run as a command three ways, interleaved, median
of ``--reps``:

* **no cache** (the baseline): ``FBGCOMP_CACHE_DIR=off``, the twin built, its thermal-map
  population and the heat prior's observer run computed, nothing stored;
* **cold**: an empty cache folder (a new one each repetition): the same work, plus writing the
  twin's entry and the derived results (``fbgcomp.structure.cache``);
* **warm**: the folder the cold run filled: the twin loaded, the population and the observer
  run read back;
* **edited, cold** and **edited**: the description with one film edited (+X, 7 -> 8 W/m2K, as
  when calibrating the films), fitted in an empty folder and in the folder the cold run filled:
  a twin that differs in its thermal section only takes the static half (elasticity, factor,
  adjoint responses) from the entry that holds it; the rest is built.

The first three model files must be the same but for their creation time, and so must the two
edited ones (the cache gives the same numbers: exit 1 otherwise). Last line: one JSON object.

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


def fit(data: Path, out: Path, cache: str, machine: Path = MACHINE) -> float:
    """Seconds of one ``fbgcomp fit`` command with ``FBGCOMP_CACHE_DIR=cache``."""
    env = {**os.environ, "FBGCOMP_CACHE_DIR": cache}
    cmd = [sys.executable, "-m", "fbgcomp", "-q", "fit", data / "thermal_a", data / "static_xyz"]
    t0 = time.perf_counter()
    r = subprocess.run(
        [*map(str, cmd), "--machine", str(machine), "-o", str(out)], env=env, capture_output=True, text=True
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
    times: dict[str, list[float]] = {"no cache": [], "cold": [], "warm": [], "edited, cold": [], "edited": []}
    with tempfile.TemporaryDirectory(prefix="bench-fit-cache-") as tmp:
        work = Path(tmp)
        edited = work / "ram2-film-edited.yaml"
        text = MACHINE.read_text()
        if '"+X": 7.0' not in text:
            raise SystemExit(f"{MACHINE}: no '\"+X\": 7.0' film to edit")
        edited.write_text(text.replace('"+X": 7.0', '"+X": 8.0', 1))
        files = {}
        for rep in range(args.reps):
            folder = work / f"cache{rep}"
            for name, cache, machine in (
                ("no cache", "off", MACHINE),
                ("cold", str(folder), MACHINE),
                ("warm", str(folder), MACHINE),
                ("edited, cold", str(work / f"edited{rep}"), edited),
                ("edited", str(folder), edited),
            ):
                files[name] = work / f"{name.replace(' ', '-').replace(',', '')}.json"
                s = fit(data, files[name], cache, machine)
                times[name].append(s)
                print(f"  rep {rep + 1} {name:12s} {s:6.1f} s", flush=True)
        same = content(files["no cache"]) == content(files["cold"]) == content(files["warm"])
        same = same and content(files["edited, cold"]) == content(files["edited"])
    med = {k: statistics.median(v) for k, v in times.items()}
    print(
        f"median of {args.reps}: no cache {med['no cache']:.1f} s, cold {med['cold']:.1f} s, "
        f"warm {med['warm']:.1f} s; no cache / warm {med['no cache'] / med['warm']:.2f}x, "
        f"cold / no cache {med['cold'] / med['no cache']:.2f}; one film edited: cold "
        f"{med['edited, cold']:.1f} s, beside the unedited entry {med['edited']:.1f} s "
        f"({med['edited, cold'] / med['edited']:.2f}x)"
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
                "speedup_edited": med["edited, cold"] / med["edited"],
                "same_model": same,
            }
        )
    )
    return 0 if same else 1


if __name__ == "__main__":
    sys.exit(main())
