"""The runtime's adaptive output filter: what it costs beside the rest of the core.

The filter (``fbgcomp.runtime.output_filter``) decides once per block of frames (20 Hz at the
defaults); at 1 frame/s every frame is a block, so a campaign recorded at 1 Hz (ram2's 36 h
thermal_b: 129 600 frames) runs its per-block Python 129 600 times.

1. ram2's default fit (``fbgcomp fit thermal_a static_xyz --machine examples/machines/ram2.yaml``)
   serves thermal_b through ``Pipeline`` in batches of 100 frames on the interrogator's clock,
   with the default output policy and with the output filter switched off (the **baseline**: the
   rest of the core, same frames, same run), interleaved, median of ``--runs``; printed: seconds
   of each, their ratio and the filter's cost per block.
2. The filter alone on 3-axis noise, at a 1 s and a 1 ms frame interval (blocks of 1 and of 50
   frames), batches of 100: µs per block and per frame.

Last line: one JSON object.

    .venv/bin/python benchmarks/bench_output_filter.py [--ram2 PATH] [--runs 3]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import statistics
import time
from datetime import UTC, datetime

import numpy as np

from _loopback import git_commit
from fbgcomp.bench.served import served
from fbgcomp.cli.demo import RAM2_MACHINE, find_ram2
from fbgcomp.io.campaign import read_campaign
from fbgcomp.models.physical import PhysicalModel
from fbgcomp.runtime.output_filter import AdaptiveLevelFilter, OutputFilterConfig
from fbgcomp.runtime.pipeline import Pipeline, PipelineConfig


def _served_s(model, campaign, config) -> float:
    t0 = time.perf_counter()
    served(model, campaign, pipe=Pipeline(model, config))
    return time.perf_counter() - t0


def _filter_alone(frame_interval_s: float, n_frames: int) -> dict:
    x = np.random.default_rng(1).normal(0.0, 0.1, (n_frames, 3))
    f = AdaptiveLevelFilter(OutputFilterConfig(), frame_interval_s, [0.1, 0.1, 0.1])
    t0 = time.perf_counter()
    for i in range(0, n_frames, 100):
        f.process(x[i : i + 100])
    s = time.perf_counter() - t0
    return {
        "frame_interval_s": frame_interval_s,
        "frames": n_frames,
        "block_frames": f.block_n,
        "us_per_block": 1e6 * s / max(f.k, 1),
        "us_per_frame": 1e6 * s / n_frames,
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--ram2", help="the ram2 data set (default: as fbgcomp demo finds it)")
    ap.add_argument("--runs", type=int, default=3)
    args = ap.parse_args(argv)
    data, looked = find_ram2(args.ram2)
    if data is None:
        raise SystemExit(f"ram2 not found at {looked} (give --ram2)")
    model = PhysicalModel(machine=RAM2_MACHINE).fit(
        [read_campaign(data / "thermal_a"), read_campaign(data / "static_xyz")]
    )
    held = read_campaign(data / "thermal_b")
    on = PipelineConfig()
    off = dataclasses.replace(on, output_filter=OutputFilterConfig(enabled=False))
    times: dict[str, list[float]] = {"filter on": [], "filter off (baseline)": []}
    for _ in range(args.runs):
        times["filter on"].append(_served_s(model, held, on))
        times["filter off (baseline)"].append(_served_s(model, held, off))
    med = {k: statistics.median(v) for k, v in times.items()}
    n_frames = len(model.frame_arrays(held, held.aligned(zero_window_s=model.zero_window_s))[0])
    extra_us = 1e6 * (med["filter on"] - med["filter off (baseline)"]) / n_frames
    print(f"ram2 thermal_b served through Pipeline, {n_frames} frames at 1 frame/s, batches of 100")
    for k, v in times.items():
        print(f"  {k:22} median {med[k]:6.2f} s  ({', '.join(f'{x:.2f}' for x in v)})")
    ratio = med["filter on"] / med["filter off (baseline)"]
    print(f"  ratio on / off {ratio:.2f}; the filter's cost {extra_us:.1f} µs per frame (= per block)")
    alone = [_filter_alone(1.0, 129_600), _filter_alone(0.001, 600_000)]
    print("the filter alone, 3-axis noise, batches of 100")
    for a in alone:
        print(
            f"  frame interval {a['frame_interval_s']:g} s, blocks of {a['block_frames']}: "
            f"{a['us_per_block']:.1f} µs per block, {a['us_per_frame']:.2f} µs per frame"
        )
    print(
        json.dumps(
            {
                "benchmark": "bench_output_filter",
                "date_utc": datetime.now(UTC).isoformat(timespec="seconds"),
                "commit": git_commit(),
                "served_s": times,
                "served_median_s": med,
                "ratio_on_off": ratio,
                "filter_us_per_frame_served": extra_us,
                "alone": alone,
            }
        )
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
