"""How hard the bearings ran in the training campaign, read from the campaign itself: the thermal
observer's inferred bearing heat on thermal_a against the truth, whatever nominal is declared.

The twin map's scenarios run each volume source at duty levels of 0-1.25 × its declared
``nominal_W`` (mean 0.64 ×), and that nominal is the map's prior (docs/accuracy.md: declared at
half, ram2's thermal_b dz goes from 4.62 to 12.51 µm). A prior set by the training data instead
of the data sheet's guess needs the campaign's own heat; this measures how well the observer
(``ThermalObserver``, heat inferred from probes and gratings, nothing known) recovers it on ram2
(../shared/reference/ram2 or ``--ram2``) and ram3 (tests/data/ram3.tar.xz), with each ram's
description and its bearing heat declared at 60, 120 and 200 W, and the nominal a mean-matched
prior would give (estimated mean / 0.64).

    nice -n 10 .venv/bin/python benchmarks/bench_heat_prior.py [--ram2 PATH]

Prints the estimated and true mean and 90th percentile per ram and declaration and, last, one
JSON line.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from datetime import UTC, datetime
from pathlib import Path

import numpy as np
import pandas as pd
import yaml

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _ram3 import RAM3_MACHINE, unpack_ram3

REPO = Path(__file__).resolve().parents[1]
DECLARED_W = (60.0, 120.0, 200.0)
SOURCE = "spindle_heat_W"


def estimate(root: Path, desc: dict) -> dict:
    from fbgcomp.io.campaign import read_campaign
    from fbgcomp.models.physical.observer import ThermalObserver, campaign_inputs
    from fbgcomp.structure.machine import parse_machine
    from fbgcomp.structure.scenarios import ScenarioDesign, generic_heat_machine
    from fbgcomp.structure.twin import Twin

    machine = parse_machine(desc)
    twin = Twin(generic_heat_machine(machine))
    c = read_campaign(root / "data" / "thermal_a")
    truth = pd.read_csv(root / "truth" / "thermal_a.csv")
    point = {q.name for q in machine.probes if q.kind == "point"}
    air = {q.name for q in machine.probes if q.kind == "ambient"}
    probes = [q for q in c.probe_names if q in point]
    ambient = [q for q in c.probe_names if q in air]
    obs = ThermalObserver(twin, c.meta.sensors, probes, probe_bias_K=0.1)
    ends, amb, pr, gr = campaign_inputs(c, c.meta.sensors, probes, ambient, obs.step_s, zero_s=60.0)
    r = obs.run(amb, pr, gr)
    heat = r.heat[:, list(r.input_names).index(SOURCE)]
    true = np.interp(ends - float(c.fbg["time_s"].iloc[0]), truth["time_s"], truth["spindle_W"])
    mean_level = ScenarioDesign().mean_duty_fraction
    return {
        "estimated_mean_W": float(heat.mean()),
        "estimated_p90_W": float(np.percentile(heat, 90)),
        "true_mean_W": float(true.mean()),
        "true_p90_W": float(np.percentile(true, 90)),
        "mean_matched_nominal_W": float(heat.mean() / mean_level),
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--ram2", type=Path, default=REPO.parent / "shared" / "reference" / "ram2")
    args = ap.parse_args(argv)
    start = time.perf_counter()
    results: dict = {}
    print("bearing heat on thermal_a, inferred by the observer / truth (W)")
    with tempfile.TemporaryDirectory(prefix="bench-heat-prior-") as tmp:
        rams = {"ram3": (unpack_ram3(Path(tmp)), RAM3_MACHINE)}
        if (args.ram2 / "truth").is_dir():
            rams = {"ram2": (args.ram2, REPO / "examples" / "machines" / "ram2.yaml"), **rams}
        else:
            print(f"ram2 not found at {args.ram2}: ram3 only", file=sys.stderr)
        for ram, (root, machine_yaml) in rams.items():
            for declared in DECLARED_W:
                desc = yaml.safe_load(Path(machine_yaml).read_text())
                volume = [h for h in desc["thermal"]["heat_sources"] if h["kind"] == "volume"]
                volume[0]["nominal_W"] = declared
                res = estimate(root, desc)
                results[f"{ram}/{declared:g}W"] = res
                print(
                    f"{ram} declared {declared:5.0f} W: mean {res['estimated_mean_W']:6.1f} / "
                    f"{res['true_mean_W']:6.1f}, p90 {res['estimated_p90_W']:6.1f} / {res['true_p90_W']:6.1f}, "
                    f"mean-matched nominal {res['mean_matched_nominal_W']:6.1f} W",
                    flush=True,
                )
    print(
        json.dumps(
            {
                "benchmark": "bench_heat_prior",
                "date_utc": datetime.now(UTC).isoformat(timespec="seconds"),
                "baseline": "truth",
                "seconds": round(time.perf_counter() - start, 1),
                "results": results,
            }
        )
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
