"""What the thermal observer (``fbgcomp fit --observer``) costs per served frame, against the
default model (baseline) in the same run; and what BLAS threads cost both, as ``serve`` limits
them (fbgcomp.runtime.realtime: one thread) against the library's own threading.

ram2's thermal_b (../shared/reference/ram2 or ``--ram2``) replayed one frame per call, as the
runtime serves a live feed, through the predictor of the default model fitted on thermal_a +
static_xyz with examples/machines/ram2.yaml, and of the same model file with its observer
(``fit --observer``); the first ``--frames`` frames, each model in turn, best of ``--repeat``,
beside ``--load`` busy processes the benchmark starts itself (default 2: a loaded 2-core machine,
as on a CNC's PC), once with BLAS as the library loads it (a thread per core) and once on one
thread, as ``serve`` runs.

    .venv/bin/python benchmarks/bench_observer_speed.py [--ram2 PATH] [--frames N] [--load N]

Prints µs per frame of each, the observer's ratio to the default on one thread, the threaded
against one-thread ratio of each and, last, one JSON line.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import sys
import time
from datetime import UTC, datetime
from pathlib import Path

from _loopback import busy_processes

REPO = Path(__file__).resolve().parents[1]


def per_frame_us(model, campaign, frames: int) -> float:
    aligned = campaign.aligned(zero_window_s=model.zero_window_s)
    _, _, w0, t0 = model.instrument_arrays(aligned)
    ft, w, t = model.frame_arrays(campaign, aligned)
    p = model.predictor()
    p.reset()
    start = time.perf_counter()
    for i in range(frames):
        p.predict(w[i : i + 1], t[i : i + 1], w0, t0, time_s=ft[i : i + 1])
    return (time.perf_counter() - start) / frames * 1e6


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--ram2", type=Path, default=REPO.parent / "shared" / "reference" / "ram2")
    ap.add_argument("--frames", type=int, default=5000)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--load", type=int, default=2, help="busy background processes (default 2)")
    args = ap.parse_args(argv)
    from fbgcomp.io.campaign import read_campaign
    from fbgcomp.models.physical import PhysicalModel

    data = args.ram2 / "data"
    if not data.is_dir():
        print(f"ram2 not found at {args.ram2}", file=sys.stderr)
        return 2
    train = [read_campaign(data / n) for n in ("thermal_a", "static_xyz")]
    machine = REPO / "examples" / "machines" / "ram2.yaml"
    with_obs = PhysicalModel(machine=machine, observer=True).fit(train)
    default = PhysicalModel.from_dict({**with_obs.to_dict(), "observer": None})  # the plain fit's file
    campaign = read_campaign(data / "thermal_b")
    from threadpoolctl import threadpool_info

    from fbgcomp.threads import one_blas_thread

    cores = sorted({p["num_threads"] for p in threadpool_info() if p["user_api"] == "blas"})
    us: dict[str, list[float]] = {}
    with busy_processes(args.load):
        for _ in range(args.repeat):
            for blas, context in (("threaded", contextlib.nullcontext), ("one_thread", one_blas_thread)):
                with context():
                    for name, m in (("default", default), ("observer", with_obs)):
                        us.setdefault(f"{name}_{blas}", []).append(per_frame_us(m, campaign, args.frames))
    best = {k: min(v) for k, v in us.items()}
    ratio = best["observer_one_thread"] / best["default_one_thread"]
    threaded = {n: best[f"{n}_threaded"] / best[f"{n}_one_thread"] for n in ("default", "observer")}
    print(
        f"one frame per call, {args.frames} frames of ram2 thermal_b, best of {args.repeat}, "
        f"{args.load} busy processes, BLAS threads as loaded {cores}:"
    )
    for n in ("default", "observer"):
        print(
            f"  {n:8s}  one BLAS thread (serve) {best[f'{n}_one_thread']:6.0f} µs   "
            f"threaded {best[f'{n}_threaded']:6.0f} µs   threaded / one {threaded[n]:.2f}"
        )
    print(f"  --observer / default on one BLAS thread: {ratio:.2f}")
    print(
        json.dumps(
            {
                "benchmark": "bench_observer_speed",
                "date_utc": datetime.now(UTC).isoformat(timespec="seconds"),
                "baseline": "default",
                "load": args.load,
                "blas_threads_loaded": cores,
                "us_per_frame": best,
                "ratio": ratio,
                "threaded_over_one_thread": threaded,
            }
        )
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
