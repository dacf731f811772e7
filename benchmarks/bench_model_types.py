"""Throughput of every model type's runtime predictor (frames/s, 5 sensors, batches of 5000).

Target (runtime contract): >= 50 000 frames/s per model type. Prints one line per type.
Usage: .venv/bin/python benchmarks/bench_model_types.py
"""

import time

import numpy as np

from fbgcomp.bench import load_scenario, simulate
from fbgcomp.model_types import CalibratedModel, DynamicModel, HybridModel, KinematicModel
from fbgcomp.models import MRAModel
from fbgcomp.structure import Twin, load_machine


def main(n_frames=200_000, batch=5000):
    machine = load_machine()
    twin = Twin(machine, resolution=0.3)
    sc = load_scenario("combined")
    train, _ = simulate(machine, sc, seed=1, twin=twin)
    models = {"mra eq13": MRAModel(features="eq13").fit([train]),
              "kinematic": KinematicModel(machine).fit(),
              "hybrid eq13": HybridModel(machine, features="eq13").fit([train]),
              "calibrated": CalibratedModel(machine, features="eq13").fit([train]),
              "dynamic": DynamicModel().fit([train])}
    rng = np.random.default_rng(0)
    for name, model in models.items():
        w0 = np.array([s.lambda0_nm for s in model.sensors])
        t0 = np.full(len(model.probe_names), 30.0)
        w = w0 + 1e-3 * rng.standard_normal((n_frames, len(w0)))
        t = t0 + rng.standard_normal((n_frames, len(t0)))
        p = model.predictor()
        if hasattr(p, "reset"):
            p.reset()
        start = time.perf_counter()
        for i in range(0, n_frames, batch):
            p.predict(w[i:i + batch], t[i:i + batch], w0, t0)
        rate = n_frames / (time.perf_counter() - start)
        print(f"{name:<12} {rate:>12,.0f} frames/s  (batches of {batch})")


if __name__ == "__main__":
    main()
