"""What the default fit costs on ram2, and what the training's heat prior and the expansion test add.

``PhysicalModel`` fitted on ram2's thermal_a + static_xyz (../shared/reference/ram2 or
``--ram2``) with examples/machines/ram2.yaml, as ``fbgcomp fit`` does, with the bearing power
prior from the training campaign (``heat_prior="training"``, the default: the thermal observer
runs over thermal_a's 12,960 steps of 10 s) against the description's nominal
(``heat_prior="declared"``, the baseline), and the default without the test of the
description's expansion coefficients (``calibrate_cte=False``: the twin population without its
moments per material), in turn in one process, best of ``--repeat``. A first untimed fit warms
the twin cache, so the figures are the fit's own work, not a twin build.

    .venv/bin/python benchmarks/bench_physical_fit.py [--ram2 PATH] [--repeat 3]

Prints seconds per fit of each, the default's ratios to the baseline and to the fit without the
expansion test and, last, one JSON line.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from datetime import UTC, datetime
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--ram2", type=Path, default=REPO.parent / "shared" / "reference" / "ram2")
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args(argv)
    from fbgcomp.io.campaign import read_campaign
    from fbgcomp.models.physical import PhysicalModel

    machine = REPO / "examples" / "machines" / "ram2.yaml"
    campaigns = [read_campaign(args.ram2 / "data" / name) for name in ("thermal_a", "static_xyz")]
    PhysicalModel(machine=machine).fit(campaigns)  # warms the twin cache
    seconds = {}
    settings = {
        "declared": {"heat_prior": "declared"},
        "training": {},  # the default
        "no expansion test": {"calibrate_cte": False},
    }
    for name, kw in settings.items():
        best = float("inf")
        for _ in range(args.repeat):
            start = time.perf_counter()
            PhysicalModel(machine=machine, **kw).fit(campaigns)
            best = min(best, time.perf_counter() - start)
        seconds[name] = best
        print(f"{name:<18} {best:6.2f} s per fit (best of {args.repeat})", flush=True)
    ratio = seconds["training"] / seconds["declared"]
    ratio_cte = seconds["training"] / seconds["no expansion test"]
    print(f"default (training) / declared: {ratio:.2f}")
    print(f"default / without the expansion test: {ratio_cte:.2f}")
    print(
        json.dumps(
            {
                "benchmark": "bench_physical_fit",
                "date_utc": datetime.now(UTC).isoformat(timespec="seconds"),
                "baseline": "declared",
                "seconds": seconds,
                "ratio": ratio,
                "ratio_to_no_expansion_test": ratio_cte,
            }
        )
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
