"""Stream-fit a long synthetic campaign: throughput and peak memory of the regression engine.

A 36 h campaign (default 10^7 samples) of 5 FBG elongations (µm) and 3 temperature changes (°C)
is generated chunk by chunk, expanded into the paper's eq. 12 quadratic design (intercept, 5
elongations, 3 temperatures, 3 squares, 3 pairwise products: 15 columns) and accumulated with
the TTP deviations dx, dy, dz (µm) in one :class:`fbgcomp.models.regression.QRAccumulator`; then all
three axes are fitted from the factor. The whole campaign is never in memory, so peak RSS must
not grow with ``--rows``.

Prints rows/s (accumulation alone and end to end), peak RSS and the recovery of the known
coefficients (largest |estimate - truth| / standard error), then the same figures as one JSON
line.

    python benchmarks/bench_fit.py [--rows 10000000] [--chunk-rows 200000] [--seed 0]
"""

from __future__ import annotations

import os

# Small dense kernels on a shared machine: BLAS threads only add synchronisation cost.
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import json  # noqa: E402
import resource  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402

from fbgcomp.models.regression import QRAccumulator, ols_from_factor  # noqa: E402

SENSORS = ["S1", "S2", "S3", "S4", "S5"]
PROBES = ["T_bulk", "T_surf", "T_flange"]
AXES = ["dx", "dy", "dz"]
CAMPAIGN_S = 36 * 3600.0
NOISE_UM = 0.5


def term_names() -> list[str]:
    t = PROBES
    return (
        ["const"]
        + [f"dL_{s}" for s in SENSORS]
        + [f"dT_{p}" for p in t]
        + [f"dT_{p}^2" for p in t]
        + [f"dT_{t[i]}*dT_{t[j]}" for i in range(3) for j in range(i + 1, 3)]
    )


def eq12_design(elongation_um: np.ndarray, temperature_C: np.ndarray) -> np.ndarray:
    """Eq. 12 quadratic design (n, 15) from elongations (n, 5) µm and temperature changes (n, 3) °C."""
    t = temperature_C
    return np.column_stack(
        [np.ones(len(t)), elongation_um, t, t * t, t[:, 0] * t[:, 1], t[:, 0] * t[:, 2], t[:, 1] * t[:, 2]]
    )


def true_coefficients(seed: int) -> np.ndarray:
    """(15, 3) coefficients: µm per µm of elongation, µm per °C, µm per °C^2."""
    rng = np.random.default_rng([seed, 999])
    scale = np.array([1.0] + [0.5] * 5 + [2.0] * 3 + [0.1] * 3 + [0.05] * 3)
    return rng.normal(size=(15, 3)) * scale[:, None]


def campaign_chunk(seed: int, index: int, start: int, rows: int, total: int):
    """Rows [start, start + rows) of the campaign: design (rows, 15) and TTP deviation (rows, 3) µm."""
    rng = np.random.default_rng([seed, index])
    time_s = (start + np.arange(rows)) * (CAMPAIGN_S / total)
    phase = 2.0 * np.pi * time_s / CAMPAIGN_S
    # Thermal drift of the ram over the campaign: slow cycles plus probe noise (°C).
    temperature_C = np.column_stack(
        [4.0 * (1 - np.cos(phase)), 1.5 * np.sin(3 * phase + 0.4), 2.5 * (1 - np.cos(2 * phase + 1.1))]
    ) + rng.normal(scale=0.05, size=(rows, 3))
    # Elongations: thermal expansion seen by each grating plus load-induced strain (µm).
    thermal = temperature_C @ np.array(
        [[1.2, 0.8, 1.0, 0.6, 1.1], [0.3, -0.5, 0.2, 0.9, -0.4], [0.5, 0.4, -0.7, 0.2, 0.6]]
    )
    elongation_um = thermal + rng.normal(scale=2.0, size=(rows, 5))
    design = eq12_design(elongation_um, temperature_C)
    deviation_um = design @ true_coefficients(seed) + rng.normal(scale=NOISE_UM, size=(rows, 3))
    return design, deviation_um


def peak_rss_mb() -> float:
    # ru_maxrss is in KiB on Linux, bytes on macOS.
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return peak / 1024.0 ** (2 if sys.platform == "darwin" else 1)


def current_rss_mb() -> float | None:
    try:
        import psutil
    except ImportError:
        return None
    return psutil.Process().memory_info().rss / 2**20


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rows", type=int, default=10_000_000)
    parser.add_argument("--chunk-rows", type=int, default=200_000)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)

    names = term_names()
    rss_start = peak_rss_mb()
    acc = QRAccumulator(len(names), len(AXES), feature_names=names, target_names=AXES)
    t_generate = t_update = 0.0
    wall0 = time.perf_counter()
    for index, start in enumerate(range(0, args.rows, args.chunk_rows)):
        rows = min(args.chunk_rows, args.rows - start)
        t0 = time.perf_counter()
        design, deviation_um = campaign_chunk(args.seed, index, start, rows, args.rows)
        t1 = time.perf_counter()
        acc.update(design, deviation_um)
        t_update += time.perf_counter() - t1
        t_generate += t1 - t0
        del design, deviation_um
    t0 = time.perf_counter()
    fits = [ols_from_factor(acc, None, axis) for axis in AXES]
    t_fit = time.perf_counter() - t0
    wall = time.perf_counter() - wall0

    truth = true_coefficients(args.seed)
    worst_z = max(float(np.max(np.abs((f.params - truth[:, j]) / f.bse))) for j, f in enumerate(fits))
    figures = {
        "rows": acc.n_obs,
        "columns": len(names),
        "targets": len(AXES),
        "chunk_rows": args.chunk_rows,
        "double_double_data_pass": bool(acc.extended_),
        "accumulate_rows_per_s": acc.n_obs / t_update,
        "end_to_end_rows_per_s": acc.n_obs / wall,
        "generate_s": t_generate,
        "accumulate_s": t_update,
        "fit_3_axes_s": t_fit,
        "wall_s": wall,
        "peak_rss_mb": peak_rss_mb(),
        "rss_before_mb": rss_start,
        "rss_now_mb_psutil": current_rss_mb(),
        "max_abs_z_vs_truth": worst_z,
        "resid_sd_um": [f.resid_sd for f in fits],
        "rsquared": [f.rsquared for f in fits],
    }
    print(
        f"rows                {acc.n_obs:,} x {len(names)} columns x {len(AXES)} targets "
        f"(chunks of {args.chunk_rows:,})"
    )
    print(
        f"accumulate          {figures['accumulate_rows_per_s']:,.0f} rows/s "
        f"({t_update:.2f} s; data pass in "
        f"{'double-double' if acc.extended_ else 'LAPACK double'})"
    )
    print(
        f"end to end          {figures['end_to_end_rows_per_s']:,.0f} rows/s "
        f"({wall:.2f} s, of which generating the data {t_generate:.2f} s)"
    )
    print(f"fit dx, dy, dz      {t_fit * 1e3:.1f} ms from the factor")
    print(f"peak RSS            {figures['peak_rss_mb']:.1f} MB (before accumulating: {rss_start:.1f} MB)")
    print(
        f"truth recovery      max |estimate - truth| / SE = {worst_z:.2f} over 45 coefficients; "
        f"residual SD {', '.join(f'{s:.4f}' for s in figures['resid_sd_um'])} µm "
        f"(simulated {NOISE_UM})"
    )
    print(json.dumps(figures))
    return figures


if __name__ == "__main__":
    main()
