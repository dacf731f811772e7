"""The default model served through a lost interrogator link: the probes alone, or carried over.

When every grating is lost and the probes arrive live, the runtime runs the physical model's set
without gratings (docs/runtime.md). The probes see no gradient between the faces; that set goes on
from the gratings' last thermal correction, the difference fading with ``link_loss_tau_s``
(default 3600 s). This benchmark judges that choice on independent data: the default fit
(``fbgcomp fit thermal_a static_xyz --machine examples/machines/<ram>.yaml``) served through
``Pipeline`` (default output policy, batches of 100 frames on the interrogator's clock) with every
grating lost for 1 h, 3 h and 8 h from 1 h, 5 h, 9 h ... of each held-out thermal campaign.
Per window: max |interferometer + published correction| per axis inside the window with the
probes alone (``link_loss_tau_s=0``), carried over (the default) and carried without fading
(``link_loss_tau_s=1e12``), against the uncompensated peak inside it. Counted: windows where the
carried correction is worse than the probes alone (by more than 0.1 µm) and worse than
uncompensated (+0.5 µm, the interferometer's noise on an axis that hardly moves), apart where a
force was applied or released while the link was down (over 200 N on a component, from the
campaign's loads.csv): no sensor left reads it, and where the heat moves an axis against the load
the thermal correction then leaves more of the load than uncompensated (docs/runtime.md).

    nice -n 10 .venv/bin/python benchmarks/bench_link_loss.py [--ram2 PATH] [--rams ram2,ram5]

Prints one line per window and, last, one JSON line with every figure.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from _ram3 import add_ram_arguments, default_fit, ram_folder
from fbgcomp.bench.served import served
from fbgcomp.io.campaign import read_campaign
from fbgcomp.models.registry import load_model

ALLOWANCE_UM = 0.5
WORSE_UM = 0.1
FORCE_CHANGE_N = 200.0
LENGTHS_H = (1.0, 3.0, 8.0)
SETTINGS = {"probes alone": 0.0, "carried": None, "never fading": 1e12}  # None: the default


def windows(duration_s: float):
    """(start, end) s of every window: each length from 1 h, 5 h, 9 h ... that ends in the run."""
    out = []
    for length in LENGTHS_H:
        h0 = 1.0
        while (h0 + length) * 3600.0 < duration_s:
            out.append((h0 * 3600.0, (h0 + length) * 3600.0))
            h0 += 4.0
    return out


def force_changed(campaign, t0: float, a: float, b: float) -> bool:
    """Whether a force component of ``campaign`` (loads.csv) moved over ``FORCE_CHANGE_N`` from
    its value at ``a`` inside the window [a, b) s after ``t0`` s."""
    loads = campaign.loads
    if loads is None:
        return False
    t = loads["time_s"].to_numpy() - t0
    f = loads[[c for c in loads.columns if c.endswith("_N")]].to_numpy()
    inside = (t >= a) & (t < b)
    at = f[min(int(np.searchsorted(t, a)), len(t) - 1)]
    return bool(inside.any() and (np.abs(f[inside] - at).max() > FORCE_CHANGE_N))


def judge(models: dict, campaign) -> list:
    """Every window of ``campaign`` served by each model of ``models`` {setting: model}."""
    m0 = next(iter(models.values()))
    t = campaign.aligned(zero_window_s=m0.zero_window_s).time_s
    t0 = float(t[0])
    t = t - t0
    span = float(t[-1])
    rows = []
    for a, b in windows(span):
        inside = (t >= a) & (t < b)
        row = {
            "from_h": a / 3600.0,
            "hours": (b - a) / 3600.0,
            "force_changed": force_changed(campaign, t0, a, b),
        }
        for setting, model in models.items():
            corr, ref, _ = served(
                model, campaign, lost=list(model.sensor_names), lost_from=a / span, lost_until=b / span
            )
            row[setting] = np.abs(ref + corr)[inside].max(axis=0).tolist()
        row["uncompensated"] = np.abs(ref[inside]).max(axis=0).tolist()  # the same for every setting
        carried, alone = np.array(row["carried"]), np.array(row["probes alone"])
        row["worse_than_alone"] = bool((carried > alone + WORSE_UM).any())
        row["harm"] = bool((carried > np.array(row["uncompensated"]) + ALLOWANCE_UM).any())
        row["harm_never_fading"] = bool(
            (np.array(row["never fading"]) > np.array(row["uncompensated"]) + ALLOWANCE_UM).any()
        )
        rows.append(row)
        fig = "  ".join(f"{s} " + "/".join(f"{v:.2f}" for v in row[s]) for s in (*SETTINGS, "uncompensated"))
        flags = ("  WORSE" if row["worse_than_alone"] else "") + ("  HARM" if row["harm"] else "")
        flags += "  (force changed while down)" if row["force_changed"] else ""
        print(f"  {row['from_h']:4.0f} h +{row['hours']:.0f} h  {fig}{flags}", flush=True)
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_ram_arguments(ap, "ram2")
    args = ap.parse_args(argv)
    rams = [r.strip() for r in args.rams.split(",") if r.strip()]
    t0 = time.perf_counter()
    result: dict = {}
    with tempfile.TemporaryDirectory() as tmp:
        try:
            folders = [(ram, *ram_folder(ram, tmp, args.ram2)) for ram in rams]
        except ValueError as e:
            print(e, file=sys.stderr)
            return 2
        for ram, data, machine in folders:
            fitted = default_fit(data, machine)
            path = fitted.save(Path(tmp) / f"{ram}.json")
            models = {
                s: load_model(path) if tau is None else load_model(path).set_params(link_loss_tau_s=tau)
                for s, tau in SETTINGS.items()
            }
            print(f"\n{ram} ({data}): every grating lost, max |error| dx/dy/dz µm inside each window")
            result[ram] = {}
            for name in ("thermal_b", "thermal_c"):
                print(name)
                result[ram][name] = judge(models, read_campaign(data / name))
    rows = [r for per in result.values() for runs in per.values() for r in runs]
    counts = {
        "windows": len(rows),
        "carried_worse_than_alone": sum(r["worse_than_alone"] for r in rows),
        "carried_harm": sum(r["harm"] for r in rows),
        "carried_harm_force_changed": sum(r["harm"] and r["force_changed"] for r in rows),
        "never_fading_harm": sum(r["harm_never_fading"] for r in rows),
    }
    seconds = round(time.perf_counter() - t0, 1)
    print(
        f"\n{counts['windows']} windows: carried worse than the probes alone (+{WORSE_UM} µm) in "
        f"{counts['carried_worse_than_alone']}, worse than uncompensated (+{ALLOWANCE_UM} µm) in "
        f"{counts['carried_harm']} ({counts['carried_harm_force_changed']} with a force changed while the "
        f"link was down); never fading: worse than uncompensated in {counts['never_fading_harm']} "
        f"({seconds:.0f} s)"
    )
    print(json.dumps({**result, **counts, "seconds": seconds}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
