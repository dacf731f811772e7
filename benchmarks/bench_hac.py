"""Autocorrelation-robust (HAC) statistics: what the Bartlett sums cost, in a fit and in compare.

Every MRA fit with Newey-West inference (the default ``cov_type="HAC"``) keeps, per bandwidth of
its grid (1, 2, 4, ..., 4096 lags), the Bartlett-weighted past of every row's score products
(:func:`fbgcomp.models.regression.hac._bartlett_sums`). Up to 32 lags they are shifted
additions, 63 passes over each 8192-row block; beyond, two cumulative sums.

**Baseline**: the same sums formed over the whole block at once (fbgcomp up to 3d7d9bc, kept
below as ``whole_block_sums``). The library's form walks the block a few hundred rows at a time,
in cache, adding in the same order: the same bits.

Two data sets (``--data``): the README tour's, simulated on the built-in twin (twin-only: thermal-36h
seed 1 and static-y seed 2 to train, thermal-36h-b seed 3 to judge; 1 sample/s, so 10^5 rows) and
ram2's (independent: thermal_a + static_xyz, thermal_b; a sample every 10 s).

1. The paper's recipe, ``MRAModel(features="eq13", stepwise=True)`` (HAC), fitted on the training
   campaigns, library and baseline interleaved, median of ``--runs``; their coefficient tables
   must be equal to the bit.
2. ``compare`` (every model type) on the same training, judged on the held-out campaign, once
   each: seconds and ratio; the comparison tables must be identical.

Last line: one JSON object.

    .venv/bin/python benchmarks/bench_hac.py [--data twin|ram2] [--ram2 PATH] [--runs 3] [--no-compare]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import time
from contextlib import contextmanager
from datetime import UTC, datetime

import numpy as np

from _loopback import git_commit
from fbgcomp.bench.virtual import load_scenario, simulate
from fbgcomp.cli.demo import find_ram2
from fbgcomp.io.campaign import read_campaign
from fbgcomp.models import compare as compare_mod
from fbgcomp.models.mra import MRAModel
from fbgcomp.models.regression import hac
from fbgcomp.structure import load_machine


def whole_block_sums(w, first, lags):
    """The baseline: fbgcomp's Bartlett sums up to 3d7d9bc, each shifted addition over the block."""
    n = w.shape[0]
    out = []
    p_sum = q_sum = None
    for lag in lags:
        if lag <= hac._HAC_DIRECT_MAX_LAG:
            acc = np.zeros((n - first, w.shape[1]))
            for j in range(1, lag + 1):
                lo = first - j
                if lo >= 0:
                    acc += (lag + 1 - j) * w[lo : n - j]
                elif n - j > 0:
                    acc[-lo:] += (lag + 1 - j) * w[: n - j]
        else:
            if p_sum is None or q_sum is None:
                p_sum = np.zeros((n + 1, w.shape[1]))
                np.cumsum(w, axis=0, out=p_sum[1:])
                q_sum = np.zeros((n + 2, w.shape[1]))
                np.cumsum(p_sum, axis=0, out=q_sum[1:])
            rows = np.arange(first, n)
            acc = lag * p_sum[rows] - q_sum[rows] + q_sum[np.maximum(rows - lag, 0)]
        out.append(acc / (lag + 1))
    return out


@contextmanager
def baseline():
    library = hac._bartlett_sums
    hac._bartlett_sums = whole_block_sums
    try:
        yield
    finally:
        hac._bartlett_sums = library


def _fit(train):
    t0 = time.perf_counter()
    m = MRAModel(features="eq13", stepwise=True).fit(train)
    return time.perf_counter() - t0, json.dumps(m.to_dict(), sort_keys=True)


def _compare(train, test):
    t0 = time.perf_counter()
    out = compare_mod.compare(train, test)
    return time.perf_counter() - t0, json.dumps(out, sort_keys=True, default=str)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", choices=("twin", "ram2"), default="twin", help="the campaigns (default: twin)")
    ap.add_argument("--ram2", help="the ram2 data set (default: as fbgcomp demo finds it)")
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--no-compare", action="store_true", help="time the MRA fit only")
    args = ap.parse_args(argv)
    if args.data == "ram2":
        data, looked = find_ram2(args.ram2)
        if data is None:
            raise SystemExit(f"ram2 not found at {looked} (give --ram2)")
        train = [read_campaign(data / "thermal_a"), read_campaign(data / "static_xyz")]
        held = [read_campaign(data / "thermal_b")]
    else:
        machine = load_machine()
        train = [
            simulate(machine, load_scenario(n), seed=s)[0] for n, s in (("thermal-36h", 1), ("static-y", 2))
        ]
        held = [simulate(machine, load_scenario("thermal-36h-b"), seed=3)[0]]
    label = "ram2 (independent)" if args.data == "ram2" else "the built-in twin (twin-only)"
    load = [os.getloadavg()[0]]
    fits: dict[str, list[float]] = {"library": [], "whole block (baseline)": []}
    tables = set()
    for i in range(args.runs):
        for name in fits if i % 2 == 0 else list(fits)[::-1]:  # alternate the order
            if name == "library":
                s, table = _fit(train)
            else:
                with baseline():
                    s, table = _fit(train)
            fits[name].append(s)
            tables.add(table)
    med = {k: statistics.median(v) for k, v in fits.items()}
    fit_ratio = med["whole block (baseline)"] / med["library"]
    print(f"{label}: eq13 stepwise (HAC) fitted on {', '.join(c.meta.name for c in train)}")
    for k, v in fits.items():
        print(f"  {k:24} median {med[k]:6.2f} s  ({', '.join(f'{x:.2f}' for x in v)})")
    print(
        f"  baseline / library {fit_ratio:.2f}x; coefficient tables {'identical' if len(tables) == 1 else 'DIFFER'}"
    )
    result = {
        "benchmark": "bench_hac",
        "date_utc": datetime.now(UTC).isoformat(timespec="seconds"),
        "commit": git_commit(),
        "data": args.data,
        "rows": {c.meta.name: len(c.aligned().time_s) for c in train},
        "fit_s": fits,
        "fit_median_s": med,
        "fit_ratio": fit_ratio,
        "fit_identical": len(tables) == 1,
    }
    if not args.no_compare:
        lib_s, lib_table = _compare(train, held)
        with baseline():
            base_s, base_table = _compare(train, held)
        ratio = base_s / lib_s
        same = lib_table == base_table
        print(f"compare, every model type, the same training, judged on {held[0].meta.name}")
        print(
            f"  library {lib_s:6.2f} s, whole block (baseline) {base_s:6.2f} s: {ratio:.2f}x; "
            f"tables {'identical' if same else 'DIFFER'}"
        )
        result.update(compare_s={"library": lib_s, "whole block (baseline)": base_s}, compare_ratio=ratio)
        result["compare_identical"] = same
    load.append(os.getloadavg()[0])
    print(f"load average (1 min) {load[0]:.1f} at the start, {load[1]:.1f} at the end")
    result["load_average_1min"] = load
    print(json.dumps(result))
    return 0 if result["fit_identical"] and result.get("compare_identical", True) else 1


if __name__ == "__main__":
    raise SystemExit(main())
