"""BLAS threads and the default fit: its offline prediction, and two fits side by side.

1. **The default fit in this process**, whose offline prediction (``PhysicalModel._served``: the
   runtime's predictor over every frame of a campaign, 22 times on ram2; ``validate`` runs it
   once per campaign) has BLAS on as many threads as cores (the baseline: the model's
   ``one_blas_thread`` switched off) or as the model runs it (one thread); median of ``--reps``,
   wall and CPU seconds. The twin cache is warm (below).
2. ``fbgcomp fit thermal_a static_xyz --machine examples/machines/ram2.yaml`` (the default physical
   model on ../shared/reference/ram2, or ``--ram2``), two commands started together on a warm
   twin cache (one cold fit fills it first), as the test suite's two workers run them, two ways,
   interleaved, median of ``--reps``:

   * **library threads** (the baseline): the environment without ``OPENBLAS_NUM_THREADS``,
     ``OMP_NUM_THREADS`` or ``MKL_NUM_THREADS``, so BLAS starts a thread per core in each process;
   * **one thread**: each process with ``OPENBLAS_NUM_THREADS=1`` (what ``scripts/test`` sets
     for its pytest-xdist workers). The offline prediction is on one thread in both (1.); what
     the environment still decides is the rest of the fit.

   Printed: wall seconds of the pair, CPU seconds of both processes, and the ratios; the model
   files must be the same but for their creation time, and the models of 1. the same to the
   bit (exit 1 otherwise). Last line: one JSON object.

    .venv/bin/python benchmarks/bench_fit_threads.py [--ram2 PATH] [--reps 3]
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from datetime import UTC, datetime
from pathlib import Path

from _loopback import git_commit
from bench_fit_cache import content

REPO = Path(__file__).resolve().parents[1]
MACHINE = REPO / "examples" / "machines" / "ram2.yaml"
THREAD_VARS = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")


def _children_cpu_s() -> float:
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def pair(data: Path, outs: list[Path], cache: Path, one_thread: bool) -> tuple[float, float]:
    """Wall and CPU seconds of two ``fbgcomp fit`` commands started together."""
    env = {k: v for k, v in os.environ.items() if k not in THREAD_VARS}
    env["FBGCOMP_CACHE_DIR"] = str(cache)
    if one_thread:
        env.update(dict.fromkeys(THREAD_VARS, "1"))
    cmd = [sys.executable, "-m", "fbgcomp", "-q", "fit", data / "thermal_a", data / "static_xyz"]
    cpu0, t0 = _children_cpu_s(), time.perf_counter()
    procs = [
        subprocess.Popen(
            [*map(str, cmd), "--machine", str(MACHINE), "-o", str(out)],
            env=env,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
            text=True,
        )
        for out in outs
    ]
    errs = [p.communicate()[1] for p in procs]
    wall, cpu = time.perf_counter() - t0, _children_cpu_s() - cpu0
    for p, err in zip(procs, errs):
        if p.returncode != 0:
            raise SystemExit(f"fbgcomp fit failed:\n{err[-3000:]}")
    return wall, cpu


def in_process(data: Path, reps: int) -> dict:
    """Wall and CPU seconds of the default fit in this process, its offline prediction threaded
    (the baseline) and on one thread (as the model runs it), and whether the models agree."""
    import contextlib

    from threadpoolctl import threadpool_limits

    import fbgcomp.models.physical.model as pm
    from fbgcomp.io.campaign import read_campaign
    from fbgcomp.models.physical import PhysicalModel

    campaigns = [read_campaign(data / "thermal_a"), read_campaign(data / "static_xyz")]
    own = pm.one_blas_thread
    out: dict = {"wall_s": {}, "cpu_s": {}}
    models = {}
    for rep in range(reps):
        for name, threaded in (("threaded", True), ("one thread", False)):
            with threadpool_limits(os.cpu_count() or 1, user_api="blas"):
                pm.one_blas_thread = contextlib.nullcontext if threaded else own
                try:
                    c0, t0 = time.process_time(), time.perf_counter()
                    m = PhysicalModel(machine=MACHINE).fit(campaigns)
                    w, c = time.perf_counter() - t0, time.process_time() - c0
                finally:
                    pm.one_blas_thread = own
            models[name] = {k: v for k, v in m.to_dict().items() if k not in ("created_utc", "model_id")}
            out["wall_s"].setdefault(name, []).append(w)
            out["cpu_s"].setdefault(name, []).append(c)
            print(f"  rep {rep + 1} fit in process, {name:10s} wall {w:6.2f} s, CPU {c:6.2f} s", flush=True)
    out["same"] = json.dumps(models["threaded"], default=str) == json.dumps(models["one thread"], default=str)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--ram2", type=Path, help="the ram2 data set (default: as fbgcomp demo finds it)")
    ap.add_argument("--reps", type=int, default=3)
    args = ap.parse_args(argv)
    from fbgcomp.cli.demo import find_ram2

    data, looked = find_ram2(args.ram2)
    if data is None:
        raise SystemExit(f"ram2 not found at {looked} (give --ram2)")
    started = datetime.now(UTC)
    print(
        f"{started:%Y-%m-%d %H:%M} UTC, code of {git_commit()}, {os.cpu_count()} cores, "
        f"load average {os.getloadavg()[0]:.1f}"
    )
    ways = {"library threads": False, "one thread": True}
    wall: dict[str, list[float]] = {k: [] for k in ways}
    cpu: dict[str, list[float]] = {k: [] for k in ways}
    with tempfile.TemporaryDirectory(prefix="bench-fit-threads-") as tmp:
        work = Path(tmp)
        pair(data, [work / "warm-up.json"], work / "cache", one_thread=True)  # fills the cache
        pred = in_process(data, args.reps)
        files = []
        for rep in range(args.reps):
            for name, one in ways.items():
                outs = [work / f"{name.replace(' ', '-')}-{i}.json" for i in (0, 1)]
                w, c = pair(data, outs, work / "cache", one)
                wall[name].append(w)
                cpu[name].append(c)
                files += outs
                print(f"  rep {rep + 1} {name:16s} wall {w:6.1f} s, CPU {c:6.1f} s", flush=True)
        first = content(files[0])
        same = all(content(f) == first for f in files[1:])
    med_w = {k: statistics.median(v) for k, v in wall.items()}
    med_c = {k: statistics.median(v) for k, v in cpu.items()}
    base, one = "library threads", "one thread"
    pw = {k: statistics.median(v) for k, v in pred["wall_s"].items()}
    pc = {k: statistics.median(v) for k, v in pred["cpu_s"].items()}
    print(
        f"median of {args.reps}, the fit in process: prediction threaded wall {pw['threaded']:.2f} s, "
        f"CPU {pc['threaded']:.2f} s; one thread wall {pw[one]:.2f} s, CPU {pc[one]:.2f} s; "
        f"wall {pw['threaded'] / pw[one]:.2f}x, CPU {pc['threaded'] / pc[one]:.2f}x; "
        f"the same to the bit: {pred['same']}"
    )
    print(
        f"median of {args.reps}, two fits side by side: library threads wall {med_w[base]:.1f} s, "
        f"CPU {med_c[base]:.1f} s; one thread wall {med_w[one]:.1f} s, CPU {med_c[one]:.1f} s; "
        f"wall {med_w[base] / med_w[one]:.2f}x, CPU {med_c[base] / med_c[one]:.2f}x"
    )
    print(f"model files the same but for their creation: {same}")
    print(
        json.dumps(
            {
                "benchmark": "bench_fit_threads",
                "started": f"{started:%Y-%m-%dT%H:%M}Z",
                "code": git_commit(),
                "in_process_fit": {
                    "baseline": "threaded",
                    **pred,
                    "wall_ratio": pw["threaded"] / pw[one],
                    "cpu_ratio": pc["threaded"] / pc[one],
                },
                "baseline": base,
                "wall_s": wall,
                "cpu_s": cpu,
                "median_wall_s": med_w,
                "median_cpu_s": med_c,
                "wall_ratio": med_w[base] / med_w[one],
                "cpu_ratio": med_c[base] / med_c[one],
                "same_model": same,
            }
        )
    )
    return 0 if same and pred["same"] else 1


if __name__ == "__main__":
    sys.exit(main())
