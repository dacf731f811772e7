"""What the thermal observer (``fbgcomp fit --observer``) costs per served frame, against the
default model (baseline) in the same run.

ram2's thermal_b (../shared/reference/ram2 or ``--ram2``) replayed one frame per call, as the
runtime serves a live feed, through the predictor of the default model fitted on thermal_a +
static_xyz with examples/machines/ram2.yaml, and of the same model file with its observer
(``fit --observer``); the first ``--frames`` frames, each model in turn, best of ``--repeat``.

    nice -n 10 .venv/bin/python benchmarks/bench_observer_speed.py [--ram2 PATH] [--frames N]

Prints µs per frame of each and their ratio and, last, one JSON line.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from datetime import UTC, datetime
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
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
    us = {"default": [], "observer": []}
    for _ in range(args.repeat):
        for name, m in (("default", default), ("observer", with_obs)):
            us[name].append(per_frame_us(m, campaign, args.frames))
    best = {k: min(v) for k, v in us.items()}
    ratio = best["observer"] / best["default"]
    print(
        f"one frame per call, {args.frames} frames of ram2 thermal_b, best of {args.repeat}: "
        f"default {best['default']:.0f} µs, --observer {best['observer']:.0f} µs, ratio {ratio:.2f}"
    )
    print(
        json.dumps(
            {
                "benchmark": "bench_observer_speed",
                "date_utc": datetime.now(UTC).isoformat(timespec="seconds"),
                "baseline": "default",
                "us_per_frame": best,
                "ratio": ratio,
            }
        )
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
