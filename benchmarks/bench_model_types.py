"""Throughput of every model type at run time (frames/s, the built-in machine's 5 sensors).

For each type - mra (eq13), dynamic, kinematic, hybrid, calibrated and the default ``physical``
model - two figures, at batches of 1, 100 and 5000 frames:

* ``predictor``: the model's own ``predict`` alone;
* ``core``: the runtime core around it (:class:`fbgcomp.runtime.pipeline.Pipeline`: sensor
  checks, fallback choice, model, envelope, output filter, rate limit), timed after the zero
  state is set, so every timed frame reaches the model.

Runs are interleaved (type by type, round after round) and the median of ``--runs`` is printed,
with the load average. ``--load 2`` starts two busy background processes for the whole run (the
machine of a busy shop floor PC); the runtime's own settings (``--pin CPU``: a pinned core,
``--fifo``: SCHED_FIFO where permitted) may be applied to the measuring process.

Targets (issue 16): core at batch 100 >= 100 000 frames/s for every type; batch 1 (a fixed cost
per batch <= 100 us, bench_runtime.py) >= 5 000 frames/s, printed per type.
Usage: .venv/bin/python benchmarks/bench_model_types.py [--load 2] [--runs 5] [--quick]
The last line printed is the JSON summary.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from datetime import UTC, datetime

import numpy as np

from _loopback import busy_processes, git_commit, realtime_settings


def _models():
    from fbgcomp.bench.virtual import load_scenario, simulate
    from fbgcomp.models import CalibratedModel, DynamicModel, HybridModel, KinematicModel
    from fbgcomp.models.mra import MRAModel
    from fbgcomp.models.physical import PhysicalModel
    from fbgcomp.structure import Twin, load_machine

    machine = load_machine()
    twin = Twin(machine, resolution=0.3)
    # loads along X and Y in training: every type's correction envelope spans the benchmark's
    # inputs, so the core runs its usual path (trained on "combined" alone, whose dx hardly
    # moves, the chain models' dx left a 0.34 µm envelope and every frame took the hold path)
    train = [
        simulate(machine, load_scenario(name), seed=seed, twin=twin)[0]
        for name, seed in (("combined", 1), ("static-xyz", 2))
    ]
    return {
        "mra eq13": MRAModel(features="eq13").fit(train),
        "dynamic": DynamicModel().fit(train),
        "kinematic": KinematicModel(machine).fit(),
        "hybrid eq13": HybridModel(machine, features="eq13").fit(train),
        "calibrated": CalibratedModel(machine, features="eq13").fit(train),
        "physical": PhysicalModel(machine=machine).fit(train),
    }


def _inputs(model, n_frames, rng):
    w0 = np.array([s.lambda0_nm for s in model.sensors])
    t0 = np.full(len(model.probe_names), 30.0)
    # a slow drift plus noise: every frame differs from the one before (no stuck channel)
    w = w0 + 1e-4 * np.linspace(0, 1, n_frames)[:, None] + 1e-5 * rng.standard_normal((n_frames, w0.size))
    t = t0 + 0.01 * rng.standard_normal((n_frames, t0.size))
    return w, t, w0, t0


def predictor_rate(model, w, t, w0, t0, batch) -> float:
    p = model.predictor()
    if hasattr(p, "reset"):
        p.reset()
    time_s = 1.7e9 + np.arange(w.shape[0]) * 1e-3
    start = time.perf_counter()
    for i in range(0, w.shape[0], batch):
        p.predict(w[i : i + batch], t[i : i + batch], w0, t0, time_s=time_s[i : i + batch])
    return w.shape[0] / (time.perf_counter() - start)


def core_rate(model, w, t, batch) -> float:
    """Frames/s through Pipeline.process after the zero window (1 kHz frame clock)."""
    from fbgcomp.runtime.pipeline import Pipeline

    pipe = Pipeline(model)
    n = w.shape[0]
    time_s = 1.7e9 + np.arange(n) * 1e-3
    counts = np.ones(w.shape, np.int8)
    near = np.zeros(w.shape, np.int8)
    # the zero window (model.zero_window_s) and one block more, untimed
    warm = int(np.searchsorted(time_s, time_s[0] + model.zero_window_s, "right")) + batch
    for i in range(0, warm, batch):
        pipe.process(
            time_s[i : i + batch],
            w[i : i + batch],
            counts[i : i + batch],
            near[i : i + batch],
            t[i : i + batch],
        )
    assert pipe.zeroed
    start = time.perf_counter()
    for i in range(warm, n, batch):
        pipe.process(
            time_s[i : i + batch],
            w[i : i + batch],
            counts[i : i + batch],
            near[i : i + batch],
            t[i : i + batch],
        )
    return (n - warm) / (time.perf_counter() - start)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--load", type=int, default=0, help="busy background processes to start")
    ap.add_argument("--runs", type=int, default=5, help="interleaved rounds (median printed)")
    ap.add_argument("--quick", action="store_true", help="fewer frames")
    ap.add_argument("--pin", type=int, default=None, help="pin this process to one CPU")
    ap.add_argument("--fifo", action="store_true", help="SCHED_FIFO where permitted")
    args = ap.parse_args(argv)
    started = datetime.now(UTC)
    print(f"{started:%Y-%m-%d %H:%M} UTC, code of {git_commit()}")
    models = _models()
    rng = np.random.default_rng(0)
    frames = {
        1: 2_000 if args.quick else 5_000,
        100: 20_000 if args.quick else 50_000,
        5000: 50_000 if args.quick else 200_000,
    }
    inputs = {name: _inputs(m, max(frames.values()) + 20_000, rng) for name, m in models.items()}
    rates: dict = {}
    loads = []
    with busy_processes(args.load):
        settings = realtime_settings(args.pin, args.fifo)
        print(f"background load: {args.load} busy processes; measuring process: {settings}")
        for _ in range(args.runs):
            for name, model in models.items():
                w, t, w0, t0 = inputs[name]
                for batch, n in frames.items():
                    r = rates.setdefault(name, {})
                    r.setdefault(f"predictor_batch_{batch}", []).append(
                        predictor_rate(model, w[:n], t[:n], w0, t0, batch)
                    )
                    r.setdefault(f"core_batch_{batch}", []).append(
                        core_rate(model, w[: n + 20_000], t[: n + 20_000], batch)
                    )
            loads.append(os.getloadavg()[0])
    summary = {
        "utc": f"{started:%Y-%m-%dT%H:%MZ}",
        "commit": git_commit(),
        "background_processes": args.load,
        "measuring_process": settings,
        "load_average_1min": [round(x, 2) for x in loads],
        "frames_per_s": {},
    }
    print(
        f"median of {args.runs} interleaved runs, frames/s; 1-min load average "
        f"{min(loads):.2f}-{max(loads):.2f}"
    )
    print(
        f"{'type':<12} {'pred. b1':>10} {'core b1':>10} {'pred. b100':>12} {'core b100':>12} "
        f"{'pred. b5000':>12} {'core b5000':>12}"
    )
    ok = ok1 = True
    for name, r in rates.items():
        med = {k: float(np.median(v)) for k, v in r.items()}
        summary["frames_per_s"][name] = {k: round(v) for k, v in med.items()}
        ok &= med["core_batch_100"] >= 100_000
        ok1 &= med["core_batch_1"] >= 5_000
        print(
            f"{name:<12} {med['predictor_batch_1']:>10,.0f} {med['core_batch_1']:>10,.0f} "
            f"{med['predictor_batch_100']:>12,.0f} {med['core_batch_100']:>12,.0f} "
            f"{med['predictor_batch_5000']:>12,.0f} {med['core_batch_5000']:>12,.0f}"
        )
    summary["targets_met"] = {
        "core_batch_100_ge_100k_every_type": bool(ok),
        "core_batch_1_ge_5k_every_type": bool(ok1),
    }
    print(json.dumps(summary))


if __name__ == "__main__":
    main()
