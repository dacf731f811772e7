"""How well can dz be known from ram2's instruments at all? (issue 12's dz <= 2 um target)

ram2's only housing probe (T_flange) sits on the far face of the steel spindle housing from the
bearings; a spindle power step moves dz by micrometres before the probe sees it. This script
bounds what *any* linear model of the housing's transient can do, so a missed target can be
told from a weak model:

* ``measured``: the campaign's probes (quantised 0.1 K, 10 s), low-passed over 60 s, with the
  flange's leads ``T - lowpass(T, tau)`` for tau in 300..2400 s, at the reference times;
* ``truth``: the same features from ram2's noise-free FE probe temperatures (``truth/``, 300 s);
* ``measured, every instr.``: every probe and every grating (a grating on CFRP is a thermometer
  of its gauge), low-passed over 60 s, with the flange's and each grating's leads;
* ``truth + spindle power``: adding the bearings' power (low-passed at 300..3600 s), which a
  CNC knows and the campaigns do not carry.

Each is fitted by least squares on thermal_a (as the default model is) and, as an oracle, on
the judged campaign itself (in-sample: no held-out model can beat it with these inputs). dz of
thermal_c is taken net of its applied force through the compliance (0.826 um/kN on Fz; Fz = 0
there). Figures are max |error| / RMS in um.

    .venv/bin/python benchmarks/bench_dz_observability.py [--ram2 PATH]

Prints the table and, last, one JSON line.
"""

from __future__ import annotations

import argparse
import json
import sys
from datetime import UTC, datetime
from pathlib import Path

import numpy as np
import pandas as pd
from scipy import signal

ROOT = Path(__file__).resolve().parents[1]
LEADS_S = (300.0, 600.0, 1200.0, 2400.0)
CAMPAIGNS = ("thermal_a", "thermal_b", "thermal_c")


def lowpass(x, t, tau_s):
    """First-order low-pass of x sampled at (near-)uniform times t, started at x[0]."""
    dt = float(np.median(np.diff(t)))
    a = np.exp(-dt / tau_s)
    y, _ = signal.lfilter([1 - a], [1, -a], x, zi=[a * x[0]])
    return y


def housing_features(t, flange_K, amb_K, power_W=None):
    cols = {"1": np.ones_like(t), "flange": flange_K, "amb": amb_K}
    for tau in LEADS_S:
        cols[f"lead{tau:g}"] = flange_K - lowpass(flange_K, t, tau)
    if power_W is not None:
        for tau in (300.0, 900.0, 1800.0, 3600.0):
            cols[f"P{tau:g}"] = lowpass(power_W, t, tau)
    return np.column_stack(list(cols.values()))


def measured(ram2, name):
    base = ram2 / "data" / name
    temps = pd.read_csv(base / "temperatures.csv")
    ref = pd.read_csv(base / "reference.csv")
    t = temps["time_s"].to_numpy(float)
    f = temps["T_flange_C"].to_numpy(float)
    a = temps["T_amb_C"].to_numpy(float)
    f, a = lowpass(f - f[0], t, 60.0), lowpass(a - a[0], t, 60.0)
    X = housing_features(t, f, a)
    rt = ref["time_s"].to_numpy(float)
    at = np.clip(np.searchsorted(t, rt, side="right") - 1, 0, t.size - 1)
    dz = ref["dz_um"].to_numpy(float)
    return X[at], dz - dz[0]


def measured_all(ram2, name):
    """Every instrument the campaign carries: the four probes and the six gratings (wavelength
    shifts in pm, each low-passed over 60 s), with the flange's and every grating's leads. A
    grating on CFRP is a good thermometer of its gauge (~10.5 pm/K), so this asks whether the
    box's own temperatures tell the housing's transient that the flange probe shows late."""
    base = ram2 / "data" / name
    temps = pd.read_csv(base / "temperatures.csv")
    fbg = pd.read_csv(base / "fbg.csv")
    ref = pd.read_csv(base / "reference.csv")
    rt = ref["time_s"].to_numpy(float)
    cols = [np.ones_like(rt)]
    for frame, scale, leads_of in ((temps, 1.0, ("T_flange_C",)), (fbg, 1e3, None)):
        t = frame["time_s"].to_numpy(float)
        for c in frame.columns.drop("time_s"):
            x = frame[c].to_numpy(float) * scale
            x = lowpass(x - x[0], t, 60.0)
            cols.append(np.interp(rt, t, x))
            if leads_of is None or c in leads_of:
                cols += [np.interp(rt, t, x - lowpass(x, t, tau)) for tau in LEADS_S]
    dz = ref["dz_um"].to_numpy(float)
    if (base / "loads.csv").exists():  # thermal_c: net of the applied force (Fz = 0 there)
        loads = pd.read_csv(base / "loads.csv")
        dz = dz - 0.826e-3 * np.interp(rt, loads["time_s"], loads["fz_N"])
    return np.column_stack(cols), dz - dz[0]


def truth(ram2, name, power):
    d = pd.read_csv(ram2 / "truth" / f"{name}.csv")
    t = d["time_s"].to_numpy(float)
    X = housing_features(
        t,
        d["T_flange_C"].to_numpy(float) - 22.0,
        d["T_amb_C"].to_numpy(float) - 22.0,
        d["spindle_W"].to_numpy(float) if power else None,
    )
    return X, d["dz_um"].to_numpy(float) - 0.826e-3 * d["fz_N"].to_numpy(float)


def errors(data, train):
    X, y = data[train]
    coef = np.linalg.lstsq(X, y, rcond=None)[0]
    out = {}
    for name, (Xc, yc) in data.items():
        e = Xc @ coef - yc
        out[name] = {
            "max_abs_error_um": float(np.abs(e).max()),
            "rms_error_um": float(np.sqrt(np.mean(e**2))),
        }
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--ram2", type=Path, default=ROOT.parent / "shared" / "reference" / "ram2")
    args = ap.parse_args(argv)
    sources = {
        "measured": lambda n: measured(args.ram2, n),
        "measured, every instr.": lambda n: measured_all(args.ram2, n),
        "truth": lambda n: truth(args.ram2, n, False),
        "truth + spindle power": lambda n: truth(args.ram2, n, True),
    }
    result = {
        "benchmark": "bench_dz_observability",
        "date_utc": datetime.now(UTC).isoformat(timespec="seconds"),
        "features": ["1", "flange", "amb"] + [f"lead{t:g}" for t in LEADS_S],
        "rows": [],
    }
    print("dz max |error| / RMS (um): linear housing models, fitted on thermal_a or in-sample (oracle)")
    print(f"{'inputs':<24}{'fitted on':<12}" + "".join(f"{n:>16}" for n in CAMPAIGNS))
    for label, load in sources.items():
        data = {n: load(n) for n in CAMPAIGNS}
        for train in ("thermal_a", "in-sample"):
            figs = {n: errors(data, n)[n] for n in CAMPAIGNS} if train == "in-sample" else errors(data, train)
            print(
                f"{label:<24}{train:<12}"
                + "".join(
                    f"{figs[n]['max_abs_error_um']:>9.2f} /{figs[n]['rms_error_um']:>5.2f}" for n in CAMPAIGNS
                )
            )
            result["rows"].append({"inputs": label, "fitted_on": train, "campaigns": figs})
    print(json.dumps(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
