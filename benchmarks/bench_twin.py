"""Speed of the FE twin: a full 36 h thermal campaign at 1 s output steps on the default mesh
(target: < 60 s on 2 cores with >= 50,000 thermo-elastic DOF), beside the naive approach (one
thermal implicit-Euler step + one elastic solve + outputs per time step) timed on a 1 h window
and extrapolated. Prints times, the ratio and the peak RSS.

    .venv/bin/python benchmarks/bench_twin.py [--resolution R] [--naive-window-s 3600]
"""

from __future__ import annotations

import argparse
import resource
import time

import numpy as np

from fbgcomp.structure import Twin, load_machine
from fbgcomp.structure.fe import Factorised


def campaign_inputs(time_s: np.ndarray, machine):
    """Paper section 3.2-like test: start at 30 °C, a few-K day/night swing, spindle cycles,
    a radiant load on one face in the afternoon."""
    hours = time_s / 3600.0
    ambient_C = 30.0 - 3.0 * np.sin(2 * np.pi * hours / 24.0)
    # Spindle on for 2 h, off for 2 h, first switched on after a quarter of an hour (so the naive
    # window below sees a heat step).
    spindle_W = machine.thermal.nominal_spindle_heat_W * ((hours >= 0.25)
                                                          & (((hours - 0.25) // 2) % 2 == 0))
    radiant = machine.thermal.nominal_radiant_W_per_m2 * ((hours % 24 > 12) & (hours % 24 < 16))
    return ambient_C, spindle_W.astype(float), radiant.astype(float)


def naive(twin: Twin, time_s, ambient_C, spindle_W, radiant):
    """Full thermo-elastic solve per step: thermal implicit Euler, elastic solve, outputs."""
    t, u = twin._inputs(time_s, ambient_C, spindle_W, radiant)
    h = t[1] - t[0]
    K, C, B = twin._thermal_K, twin._thermal_C, twin._thermal_B
    step = Factorised((C / h + K).tocsr())
    theta = np.full(twin.n_nodes, 30.0 - twin.machine.reference_temperature_C)
    R = twin._R
    S = len(twin.sensor_names)
    Tsens = twin.influence.sensor_temperature_rows
    Tprobe = twin.influence.probe_temperature_rows
    out = np.empty((len(t), R.shape[0] + Tsens.shape[0] + Tprobe.shape[0]))
    for k in range(len(t)):
        if k:
            theta = step.solve(C @ theta / h + B @ u[k])
        disp = twin._elastic.solve(twin._Th @ theta)
        out[k] = np.concatenate([R @ disp, Tsens @ theta, Tprobe @ theta])
    return out[:, :S], out[:, S:S + 3]


def main():
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--resolution", type=float, default=None)
    ap.add_argument("--naive-window-s", type=float, default=3600.0)
    args = ap.parse_args()

    machine = load_machine()
    t0 = time.perf_counter()
    twin = Twin(machine, resolution=args.resolution)
    build_s = time.perf_counter() - t0
    b = twin.times
    print(f"mesh: {twin.n_nodes} nodes, {twin.n_dof} thermo-elastic DOF "
          f"({3 * twin.n_nodes} displacement + {twin.n_nodes} temperature)")
    print(f"build: {build_s:.1f} s (assemble {b.assemble_s:.1f} s, elastic factor + "
          f"{twin._R.shape[0]} adjoint solves {b.elastic_factor_s:.1f} s [{twin._elastic.backend}], "
          f"thermal reduction {b.thermal_reduction_s:.1f} s, {twin.reduced.n_modes} reduced modes)")

    time_s = np.arange(0.0, 36 * 3600.0 + 1.0, 1.0)
    ambient, spindle, radiant = campaign_inputs(time_s, machine)
    t0 = time.perf_counter()
    h = twin.thermal(time_s, ambient, spindle, radiant, initial_C=30.0)
    reduced_s = time.perf_counter() - t0
    drift = h.change_from_start()
    print(f"reduced twin, 36 h at 1 s ({len(time_s)} samples): {reduced_s:.2f} s "
          f"(target < 60 s: {'met' if reduced_s < 60 else 'MISSED'})")
    print("  TTP drift range dx, dy, dz [um]: "
          + ", ".join(f"{v:.1f}" for v in np.ptp(drift.ttp_um, axis=0))
          + f"; max |TTP drift| {np.abs(drift.ttp_um).max():.1f} um")
    print("  sensor elongation range [um]: "
          + ", ".join(f"{n} {v:.2f}" for n, v in zip(h.sensor_names, np.ptp(h.sensor_elongation_um, 0))))
    print("  probe range [K]: "
          + ", ".join(f"{n} {v:.2f}" for n, v in zip(h.probe_names, np.ptp(h.probe_C, 0))))

    n_win = int(args.naive_window_s) + 1
    t0 = time.perf_counter()
    elong, ttp = naive(twin, time_s[:n_win], ambient[:n_win], spindle[:n_win], radiant[:n_win])
    naive_s = time.perf_counter() - t0
    per_step = naive_s / n_win
    extrapolated = per_step * len(time_s)
    # Same window from the reduced model (both start at a uniform 30 °C).
    ref = h.ttp_um[:n_win]
    print(f"naive per-step solve, {args.naive_window_s / 3600:.2f} h window ({n_win} steps): "
          f"{naive_s:.1f} s = {1e3 * per_step:.1f} ms/step -> 36 h extrapolated "
          f"{extrapolated:.0f} s ({extrapolated / 3600:.2f} h)")
    print(f"speed-up reduced vs naive (36 h): {extrapolated / reduced_s:.0f}x")
    print(f"  reduced vs naive (implicit Euler) on the window, max |TTP diff| "
          f"{np.abs(ref - ttp).max():.3f} um of range {np.ptp(ttp, axis=0).max():.3f} um")
    print(f"peak RSS: {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MiB")


if __name__ == "__main__":
    main()
