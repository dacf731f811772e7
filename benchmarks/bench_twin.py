"""Speed of the FE twin on the default mesh (>= 50,000 thermo-elastic DOF), against fair baselines.

1. Build: a cold build (mesh, assembly, elastic factor + adjoint solves, thermal reduction; no
   cache) against a warm load of the same twin from the on-disk twin cache
   (fbgcomp.structure.cache), interleaved cold / warm, medians; the ratio is cold / warm.
2. A 36 h thermal campaign at 1 s output steps (129 601 samples): the reduced twin
   (``Twin.thermal``) against the library's own full-order stepper (``Twin.thermal_direct``:
   implicit Euler on the full thermal model, one banded solve per step, the elastic outputs read
   through the adjoint influence rows, never an elastic solve per step). The full-order stepper
   is timed on a window and extrapolated to 36 h as setup + per-step cost x steps; the two are
   interleaved, medians. Target: the reduced 36 h campaign < 60 s on 2 cores.

The 1-minute load average is printed before and after each measurement (the machine is shared).
BLAS is single-threaded for both contenders. The twin cache used is a temporary folder (the
user's cache is neither read nor written). Last line: one JSON object with the figures.

    .venv/bin/python benchmarks/bench_twin.py [--resolution R] [--reps 3] [--window-s 900]
"""

from __future__ import annotations

import os

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import json  # noqa: E402
import resource  # noqa: E402
import statistics  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402

from fbgcomp.structure import Twin, load_machine  # noqa: E402


def campaign_inputs(time_s: np.ndarray, machine):
    """Paper section 3.2-like test: start at 30 °C, a few-K day/night swing, spindle cycles,
    a radiant load on one face in the afternoon."""
    hours = time_s / 3600.0
    ambient_C = 30.0 - 3.0 * np.sin(2 * np.pi * hours / 24.0)
    # Spindle on for 2 h, off for 2 h, first switched on after 5 min (so a short full-order
    # window sees a heat step).
    spindle_W = machine.thermal.nominal_spindle_heat_W * (
        (hours >= 1 / 12) & (((hours - 1 / 12) // 2) % 2 == 0)
    )
    radiant = machine.thermal.nominal_radiant_W_per_m2 * ((hours % 24 > 12) & (hours % 24 < 16))
    return ambient_C, spindle_W.astype(float), radiant.astype(float)


def load1() -> float:
    return os.getloadavg()[0]


def timed(fn):
    t0 = time.perf_counter()
    out = fn()
    return time.perf_counter() - t0, out


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--resolution", type=float, default=None)
    ap.add_argument("--reps", type=int, default=3, help="interleaved repetitions (medians)")
    ap.add_argument(
        "--window-s",
        type=float,
        default=900.0,
        help="campaign window the full-order stepper is timed on (s at 1 s steps)",
    )
    args = ap.parse_args()
    machine = load_machine()
    loads = [load1()]
    print(
        f"load average (1 min) at start: {' '.join(f'{v:.2f}' for v in os.getloadavg())}; "
        f"OPENBLAS_NUM_THREADS={os.environ.get('OPENBLAS_NUM_THREADS')}"
    )

    with tempfile.TemporaryDirectory(prefix="bench-twin-cache-") as cache_root:
        os.environ["FBGCOMP_CACHE_DIR"] = cache_root
        # ---------------------------------------------------------------- build vs cache
        miss_s, twin = timed(lambda: Twin(machine, resolution=args.resolution))
        b = twin.times
        print(
            f"mesh: {twin.n_nodes} nodes, {twin.n_dof} thermo-elastic DOF "
            f"({3 * twin.n_nodes} displacement + {twin.n_nodes} temperature)"
        )
        print(
            f"first build (cache miss): {miss_s:.2f} s = mesh {b.mesh_s:.2f} + assemble "
            f"{b.assemble_s:.2f} + elastic factor and {twin._R.shape[0]} adjoint solves "
            f"{b.elastic_factor_s:.2f} [{twin._elastic.backend}] + thermal reduction "
            f"{b.thermal_reduction_s:.2f} ({twin.reduced.n_modes} modes) + cache write "
            f"{b.cache_store_s:.2f} s"
        )
        entry_mib = os.path.getsize(b.cache_path) / 2**20
        n_dof = twin.n_dof
        del twin  # one twin in memory at a time (peak RSS of one build)
        cold, warm, cold_parts = [], [], []
        for _ in range(args.reps):
            loads.append(load1())
            s, tw = timed(lambda: Twin(machine, resolution=args.resolution, cache=False))
            cold.append(s)
            cold_parts.append((tw.times.assemble_s, tw.times.elastic_factor_s, tw.times.thermal_reduction_s))
            del tw
            loads.append(load1())
            s, tw = timed(lambda: Twin(machine, resolution=args.resolution))
            assert tw.times.from_cache
            warm.append(s)
            del tw
        loads.append(load1())
        cold_med, warm_med = statistics.median(cold), statistics.median(warm)
        parts = np.median(np.array(cold_parts), axis=0)
        print(
            f"cold build (no cache), median of {args.reps}: {cold_med:.2f} s "
            f"[{', '.join(f'{v:.2f}' for v in cold)}] (assemble {parts[0]:.2f}, elastic factor "
            f"{parts[1]:.2f}, thermal reduction {parts[2]:.2f}; target <= 8 s: "
            f"{'met' if cold_med <= 8 else 'MISSED'})"
        )
        print(
            f"warm load (twin cache, {entry_mib:.0f} MiB entry), median of {args.reps}: "
            f"{warm_med:.3f} s [{', '.join(f'{v:.3f}' for v in warm)}]"
        )
        print(f"cold / warm: {cold_med / warm_med:.0f}x")
        twin = Twin(machine, resolution=args.resolution)  # from the cache: same numbers
        os.environ.pop("FBGCOMP_CACHE_DIR")

    # -------------------------------------------------------- reduced vs full-order stepper
    time_s = np.arange(0.0, 36 * 3600.0 + 1.0, 1.0)
    ambient, spindle, radiant = campaign_inputs(time_s, machine)
    n, n_win = len(time_s), int(args.window_s) + 1
    reduced, full_win, full_setup = [], [], []
    for _ in range(args.reps):
        loads.append(load1())
        s, h = timed(lambda: twin.thermal(time_s, ambient, spindle, radiant, initial_C=30.0))
        reduced.append(s)
        loads.append(load1())
        # setup: the one factorisation of C/h + K and the first output (a 2-sample campaign)
        s, _ = timed(
            lambda: twin.thermal_direct(time_s[:2], ambient[:2], spindle[:2], radiant[:2], initial_C=30.0)
        )
        full_setup.append(s)
        s, d = timed(
            lambda: twin.thermal_direct(
                time_s[:n_win], ambient[:n_win], spindle[:n_win], radiant[:n_win], initial_C=30.0
            )
        )
        full_win.append(s)
    loads.append(load1())
    red_med = statistics.median(reduced)
    setup_med, win_med = statistics.median(full_setup), statistics.median(full_win)
    per_step = max(win_med - setup_med, 0.0) / (n_win - 2)
    full_36h = setup_med + per_step * (n - 2)
    drift = h.change_from_start()
    print(
        f"reduced twin, 36 h at 1 s ({n} samples), median of {args.reps}: {red_med:.3f} s "
        f"[{', '.join(f'{v:.3f}' for v in reduced)}] (target < 60 s: "
        f"{'met' if red_med < 60 else 'MISSED'}) = {1e6 * red_med / n:.2f} us/step"
    )
    print(
        f"full-order implicit Euler with adjoint outputs (Twin.thermal_direct), "
        f"{n_win}-step window, median of {args.reps}: {win_med:.2f} s "
        f"[{', '.join(f'{v:.2f}' for v in full_win)}] = setup {setup_med:.3f} s + "
        f"{1e3 * per_step:.2f} ms/step -> 36 h extrapolated {full_36h:.0f} s"
    )
    print(f"speed-up reduced vs full-order stepper (36 h): {full_36h / red_med:.0f}x")
    err = np.abs(h.ttp_um[:n_win] - d.ttp_um).max()
    print(
        f"  reduced vs full-order on the window: max |TTP diff| {err:.4f} um of range "
        f"{np.ptp(d.ttp_um, axis=0).max():.3f} um"
    )
    print(
        "  36 h TTP drift range dx, dy, dz [um]: "
        + ", ".join(f"{v:.1f}" for v in np.ptp(drift.ttp_um, axis=0))
    )
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(f"peak RSS: {rss:.0f} MiB; load average (1 min) during the runs {min(loads):.2f}-{max(loads):.2f}")
    print(
        json.dumps(
            {
                "bench": "twin",
                "dof": n_dof,
                "reps": args.reps,
                "first_build_miss_s": round(miss_s, 3),
                "cache_store_s": round(b.cache_store_s, 3),
                "cache_entry_mib": round(entry_mib),
                "cold_build_s": round(cold_med, 3),
                "warm_load_s": round(warm_med, 4),
                "cold_over_warm": round(cold_med / warm_med, 1),
                "reduced_36h_s": round(red_med, 4),
                "full_order_ms_per_step": round(1e3 * per_step, 3),
                "full_order_36h_s": round(full_36h, 1),
                "reduced_speedup": round(full_36h / red_med, 0),
                "window_max_ttp_diff_um": float(err),
                "peak_rss_mib": round(rss),
                "load1_min": min(loads),
                "load1_max": max(loads),
            }
        )
    )


if __name__ == "__main__":
    main()
