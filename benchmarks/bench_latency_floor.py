"""The error no causal correction can avoid on a load ramp: the reference clock runs ahead of the
last interrogator frame.

The runtime publishes the correction of the last frame it has read; validation judges it at the
interferometer's samples, which sit between frames (ram2, ram3, ram4, ram5: +0.3 s or +0.5 s after
a 1 s frame). While a force ramps, the TTP moves on after that frame, and a tracker that knew the
force at every frame exactly would still be that far behind. This script measures that floor with
no model at all:

* the compliance C (3 x 3, µm/N) by least squares of the interferometer on the load cell over the
  ram's static training campaign (static_xyz: uniform temperature, so the reference is C F plus
  the interferometer's noise);
* per judged campaign with loads, at each reference time t_r: C (F(t_r) - F(t_f)), F(t_r) the
  load cell interpolated to t_r (the ramps are linear) and t_f the last frame at or before t_r;
* printed per axis: that floor's max |.| (µm) and as % of the axis's uncompensated peak (the
  target's measure: thermal_c's loaded lateral axis <= 3 % of its peak), and the time it falls.

A target below the floor cannot be met by any causal correction at the campaign's frame rate: the
gratings at the last frame do not yet carry what the TTP does at t_r. Compare with the default
model's figures in bench_accuracy.py.

    nice -n 10 .venv/bin/python benchmarks/bench_latency_floor.py [--ram2 PATH] [--rams ram2,...,ram6] [--twin]

``--twin`` (TWIN-ONLY): also the built-in machine's ``combined`` campaign (thermal_c's role in
bench_accuracy.py, seed 0 as ``fbgcomp demo`` makes it), its compliance from ``static-xyz``.

Last line: one JSON object.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

import numpy as np
import pandas as pd

from _ram3 import HELD_OUT, add_ram_arguments, ram_folder
from bench_accuracy import TWIN_ROLES, twin_campaigns

AXES = ("dx", "dy", "dz")
FORCES = ("fx_N", "fy_N", "fz_N")
#: ram -> (static training campaign, judged campaigns with loads: thermal_c and the static one)
JUDGED = {ram: ("static_xyz", held[1:]) for ram, held in HELD_OUT.items()}


def read(folder: Path):
    """Frame times (s), load cell (times, (n, 3) N) and reference (times, (n, 3) µm) of a campaign."""
    fbg_t = pd.read_csv(folder / "fbg.csv", usecols=["time_s"])["time_s"].to_numpy(float)
    loads = pd.read_csv(folder / "loads.csv")
    ref = pd.read_csv(folder / "reference.csv")
    return (
        fbg_t,
        loads["time_s"].to_numpy(float),
        loads[list(FORCES)].to_numpy(float),
        ref["time_s"].to_numpy(float),
        ref[[f"{a}_um" for a in AXES]].to_numpy(float),
    )


def at(t_src, values, t):
    """``values`` (n, 3) interpolated linearly to times ``t``."""
    return np.column_stack([np.interp(t, t_src, values[:, j]) for j in range(values.shape[1])])


def compliance(folder: Path):
    """C (3 x 3) µm/N: the reference on the load cell, least squares with a constant."""
    _, lt, f, rt, r = read(folder)
    A = np.column_stack([at(lt, f, rt), np.ones(rt.size)])
    coef = np.linalg.lstsq(A, r, rcond=None)[0]
    return coef[:3].T  # (axes, forces)


def floor(folder: Path, C):
    """Per axis: max |C (F(t_r) - F(t_f))| µm, the reference time it falls at, and the peak."""
    fbg_t, lt, f, rt, r = read(folder)
    inside = rt >= fbg_t[0]
    rt, r = rt[inside], r[inside]
    tf = fbg_t[np.clip(np.searchsorted(fbg_t, rt, side="right") - 1, 0, fbg_t.size - 1)]
    ahead = (at(lt, f, rt) - at(lt, f, tf)) @ C.T  # (n, 3) µm the TTP moves after the frame
    peak = np.abs(r - r[0]).max(axis=0)
    worst = np.abs(ahead).argmax(axis=0)
    return {
        a: {
            "floor_um": round(float(abs(ahead[worst[j], j])), 3),
            "at_s": float(rt[worst[j]]),
            "peak_um": round(float(peak[j]), 2),
            "floor_pct": round(100.0 * float(abs(ahead[worst[j], j])) / max(float(peak[j]), 1e-9), 2),
            "lead_s": round(float(np.median(rt - tf)), 2),
        }
        for j, a in enumerate(AXES)
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_ram_arguments(ap, "ram2,ram3,ram4,ram5,ram6")
    ap.add_argument(
        "--twin", action="store_true", help="also the built-in machine's combined campaign (TWIN-ONLY)"
    )
    args = ap.parse_args(argv)
    out = {}
    with tempfile.TemporaryDirectory() as tmp:
        cases = []
        for ram in [r.strip() for r in args.rams.split(",") if r.strip()]:
            try:
                data, _ = ram_folder(ram, tmp, args.ram2)
            except ValueError as e:
                print(e, file=sys.stderr)
                return 2
            static, judged = JUDGED[ram]
            cases.append((ram, data, static, judged))
        if args.twin:
            static, judged = TWIN_ROLES["static_x"], (TWIN_ROLES["thermal_c"],)
            twin = twin_campaigns(Path(tmp), 0, (static, *judged))[static].parent
            cases.append(("twin", twin, static, judged))
        for ram, data, static, judged in cases:
            C = compliance(data / static)
            for name in judged:
                res = floor(data / name, C)
                out[f"{ram}/{name}"] = res
                lead = res["dx"]["lead_s"]
                label = " TWIN-ONLY" if ram == "twin" else ""
                print(f"{ram}/{name}{label} (reference {lead:+.1f} s after the last frame)")
                for a in AXES:
                    f = res[a]
                    print(
                        f"  {a}: floor {f['floor_um']:7.3f} µm = {f['floor_pct']:5.2f} % of peak "
                        f"{f['peak_um']:7.2f} µm (t = {f['at_s']:.1f} s)"
                    )
    print(json.dumps({"latency_floor": out}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
