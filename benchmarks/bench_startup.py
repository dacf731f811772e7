"""Start-up of the commands that load a model: this checkout against a baseline commit.

Every ``fbgcomp`` command is a new process, and a test suite, a CNC integrator's script or a
dashboard's reload pays its imports each time. Measured, interleaved, median of ``--reps``, each
in a fresh process:

* **imports**: ``python -c "import <the modules fit, validate, compare and serve load>"``;
* **validate**: ``fbgcomp validate mra.json ram2/static_x`` end to end (the paper's eq. 13 model,
  fitted once by this checkout on ram2's thermal_a; the file reads the same in both);

for this checkout and for ``--baseline`` (default b94d669, the last commit whose models imported
scipy.stats and scipy.signal at start-up), checked out in a temporary git worktree and run with
its ``src`` first on ``PYTHONPATH``. Both validate runs must print the same table (exit 1
otherwise). Last line: one JSON object.

    .venv/bin/python benchmarks/bench_startup.py [--ram2 PATH] [--reps 7] [--baseline REV]
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

from _loopback import baseline_worktree, git_commit

REPO = Path(__file__).resolve().parents[1]
MODULES = (
    "fbgcomp.cli.offline",
    "fbgcomp.models.registry",
    "fbgcomp.models.physical",
    "fbgcomp.models.mra",
    "fbgcomp.models.compare",
    "fbgcomp.runtime.pipeline",
    "fbgcomp.runtime.service",
)


def timed(cmd, src: Path) -> tuple[float, str]:
    """Seconds and stdout of one command with ``src`` first on PYTHONPATH."""
    env = {**os.environ, "PYTHONPATH": str(src)}
    t0 = time.perf_counter()
    r = subprocess.run([*map(str, cmd)], env=env, capture_output=True, text=True, cwd=src.parent)
    seconds = time.perf_counter() - t0
    if r.returncode != 0:
        raise SystemExit(f"{' '.join(map(str, cmd))} failed ({src}):\n{r.stderr[-3000:]}")
    return seconds, r.stdout


def main(argv=None) -> int:
    from fbgcomp.cli.demo import find_ram2

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--ram2", type=Path, help="the ram2 data set (default: as fbgcomp demo finds it)")
    ap.add_argument("--reps", type=int, default=7)
    ap.add_argument("--baseline", default="b94d669", help="the commit to compare with (default b94d669)")
    args = ap.parse_args(argv)
    data, looked = find_ram2(args.ram2)
    if data is None:
        raise SystemExit(f"ram2 not found at {looked} (give --ram2)")
    with (
        tempfile.TemporaryDirectory(prefix="bench-startup-") as tmp,
        baseline_worktree(args.baseline, Path(tmp) / "baseline") as base,
    ):
        model = Path(tmp) / "mra.json"
        fbgcomp = [sys.executable, "-m", "fbgcomp", "-q"]
        timed([*fbgcomp, "fit", data / "thermal_a", "--features", "eq13", "-o", model], REPO / "src")
        imports = [sys.executable, "-c", "import " + ", ".join(MODULES)]
        validate = [*fbgcomp, "validate", model, data / "static_x"]
        runs = {("now", k): [] for k in ("imports", "validate")}
        runs |= {("baseline", k): [] for k in ("imports", "validate")}
        tables = {}
        for _ in range(args.reps):
            for who, src in (("baseline", base / "src"), ("now", REPO / "src")):
                runs[who, "imports"].append(timed(imports, src)[0])
                s, out = timed(validate, src)
                runs[who, "validate"].append(s)
                tables.setdefault(who, out)
    med = {f"{who}_{k}_s": round(statistics.median(v), 3) for (who, k), v in runs.items()}
    load = os.getloadavg()[0]
    print(f"start-up, median of {args.reps} (load average {load:.1f}); baseline {args.baseline}")
    print(f"{'':10} {'baseline':>10} {'now':>10} {'saved':>8} {'ratio':>7}")
    for k in ("imports", "validate"):
        b, n = med[f"baseline_{k}_s"], med[f"now_{k}_s"]
        print(f"{k:10} {b:>9.3f}s {n:>9.3f}s {b - n:>7.3f}s {b / n:>6.2f}x")
    same = tables["now"] == tables["baseline"]
    print("validate tables identical" if same else "validate tables DIFFER")
    print(
        json.dumps(
            {
                "benchmark": "bench_startup",
                "date_utc": datetime.now(UTC).isoformat(timespec="seconds"),
                "commit": git_commit(),
                "baseline": args.baseline,
                "reps": args.reps,
                "load_average": round(load, 2),
                **med,
                "tables_identical": same,
            }
        )
    )
    return 0 if same else 1


if __name__ == "__main__":
    raise SystemExit(main())
