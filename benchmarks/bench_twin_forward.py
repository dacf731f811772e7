"""The twin driven by an independent ram's own inputs: how far its TTP, elongations and probe
temperatures are from what the independent FE model reports, nothing fitted.

On ram2 (../shared/reference/ram2, ``--ram2`` or $FBGCOMP_RAM2) and the project's own rams
(tests/data/ram3..ram7.tar.xz), each described from its data sheet (examples/machines/ramN.yaml):
the thermal campaigns' truth files (``truth/<campaign>.csv``) hold the inputs the FE model was
given (ambient, each heat source's power or flux, thermal_c's force at the TTP; ram2's radiant
load of thermal_b is not in its truth file and is rebuilt from its README: a 90 W/m² half-sine
from 8 to 14 h). The twin (``Twin.thermal``, each declared source driven by name) runs them and
its changes from the first sample are compared with the truth's. ram3's bearings are off-centre
(towards -Y); the same heat declared centred and mirrored shows how much a source's position
matters against how well the twin follows it.

This separates the twin's physics from the models built on it: a model's error on these
campaigns that the forward twin does not have comes from what the model has to infer (the heat
inputs it does not read), not from the twin's response.

    nice -n 10 .venv/bin/python benchmarks/bench_twin_forward.py [--rams ram2,ram3] [--no-variants]

Prints per ram, campaign and declaration the max |error| per axis against the uncompensated
peak, the worst elongation and housing-probe errors, and, last, one JSON line.
"""

from __future__ import annotations

import argparse
import copy
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

from _ram3 import add_ram_arguments, ram_folder

AXES = ("dx", "dy", "dz")
H = 3600.0


def ram2_radiant_W_per_m2(campaign: str, time_s: np.ndarray) -> np.ndarray:
    """ram2's README: thermal_b has a 90 W/m² half-sine on +X from 8 to 14 h; no other campaign."""
    if campaign != "thermal_b":
        return np.zeros_like(time_s)
    phase = (time_s - 8 * H) / (6 * H)
    return np.where((phase > 0) & (phase < 1), 90.0 * np.sin(np.pi * np.clip(phase, 0, 1)), 0.0)


#: per ram: the description's heat source driven by each truth column, and the housing probe
SOURCES = {
    "ram2": ({"spindle_heat": "spindle_W"}, "T_flange"),
    "ram3": ({"spindle_heat": "spindle_W", "radiant": "radiant_W_per_m2"}, "T_housing"),
    "ram4": ({"bearings": "spindle_W", "motor": "motor_W", "radiant": "radiant_W_per_m2"}, "T_head"),
    "ram5": ({"bearings": "spindle_W", "radiant": "radiant_W_per_m2"}, "T_spindle"),
    "ram6": ({"bearings": "spindle_W", "nut": "nut_W", "radiant": "radiant_W_per_m2"}, "T_housing"),
    "ram7": ({"bearings": "spindle_W", "radiant": "radiant_W_per_m2"}, "T_spindle"),
}


def forward(desc: dict, truth: pd.DataFrame, heat: dict, housing_probe: str) -> dict:
    from fbgcomp.structure.machine import parse_machine
    from fbgcomp.structure.twin import Twin

    twin = Twin(parse_machine(desc))
    t = truth["time_s"].to_numpy(float)
    r = twin.thermal(t, truth["T_amb_C"].to_numpy(float), heat=heat)
    loaded = twin.static(truth[["fx_N", "fy_N", "fz_N"]].to_numpy(float))  # thermal_c's force
    ttp = r.ttp_um + loaded.ttp_um
    ttp = ttp - ttp[0]
    ref = truth[[f"{a}_um" for a in AXES]].to_numpy(float)
    ref = ref - ref[0]
    names = list(r.sensor_names)
    el = r.sensor_elongation_um + loaded.sensor_elongation_um
    el = el - el[0]
    el_ref = truth[[f"{n}_um" for n in names]].to_numpy(float)
    el_ref = el_ref - el_ref[0]
    probe = r.probe(housing_probe)
    return {
        "max_error_um": dict(zip(AXES, np.abs(ttp - ref).max(axis=0).tolist(), strict=True)),
        "rms_error_um": dict(zip(AXES, np.sqrt(((ttp - ref) ** 2).mean(axis=0)).tolist(), strict=True)),
        "uncompensated_um": dict(zip(AXES, np.abs(ref).max(axis=0).tolist(), strict=True)),
        "elongation_max_error_um": float(np.abs(el - el_ref).max()),
        "elongation_peak_um": float(np.abs(el_ref).max()),
        "housing_probe_max_error_K": float(np.abs(probe - truth[f"{housing_probe}_C"].to_numpy(float)).max()),
    }


def _moved(desc: dict, y_mm) -> dict:
    out = copy.deepcopy(desc)
    out["thermal"]["heat_sources"][0]["y_mm"] = list(y_mm)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_ram_arguments(ap, "ram2,ram3,ram4,ram5,ram6,ram7")
    ap.add_argument("--no-variants", action="store_true", help="ram3's declared bearings only")
    args = ap.parse_args(argv)
    start = time.perf_counter()
    results: dict = {}
    print(
        "twin driven by the ram's own inputs, against its truth: max |error| µm dx / dy / dz (uncompensated)"
    )
    with tempfile.TemporaryDirectory(prefix="bench-twin-forward-") as tmp:
        rams = []
        for ram in [r for r in args.rams.split(",") if r]:
            try:
                data, machine = ram_folder(ram, Path(tmp), args.ram2)
            except ValueError as exc:
                if ram != "ram2":
                    ap.error(str(exc))
                print(f"{exc}: skipped", file=sys.stderr)
                continue
            root = data.parent
            desc = yaml.safe_load(machine.read_text())
            variants = {"declared": desc}
            if ram == "ram3" and not args.no_variants:
                variants["centred"] = _moved(desc, (-45.0, 45.0))
                variants["mirrored"] = _moved(desc, (-10.0, 80.0))
            rams.append((ram, root, variants))
        for ram, root, variants in rams:
            columns, probe = SOURCES[ram]
            for campaign in ("thermal_a", "thermal_b", "thermal_c"):
                truth = pd.read_csv(root / "truth" / f"{campaign}.csv")
                t = truth["time_s"].to_numpy(float)
                heat = {src: truth[col].to_numpy(float) for src, col in columns.items() if col in truth}
                if ram == "ram2":
                    heat["radiant"] = ram2_radiant_W_per_m2(campaign, t)
                for name, desc in variants.items():
                    res = forward(desc, truth, heat, probe)
                    results[f"{ram}/{campaign}/{name}"] = res
                    cells = " / ".join(
                        f"{res['max_error_um'][a]:5.2f} ({res['uncompensated_um'][a]:5.1f})" for a in AXES
                    )
                    print(
                        f"{ram} {campaign:<10}{name:<9} {cells}   elongations {res['elongation_max_error_um']:.2f} "
                        f"of {res['elongation_peak_um']:.1f} µm   {probe} {res['housing_probe_max_error_K']:.2f} K",
                        flush=True,
                    )
    print(
        json.dumps(
            {
                "benchmark": "bench_twin_forward",
                "date_utc": datetime.now(UTC).isoformat(timespec="seconds"),
                "baseline": "uncompensated",
                "seconds": round(time.perf_counter() - start, 1),
                "results": results,
            }
        )
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
