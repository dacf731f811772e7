"""How well a model predicts the TTP deviation of a campaign it was (or was not) fitted on.

Per axis: peak |reference| (µm), max |error| (µm), RMS error (µm), max error as % of the peak,
and the compensation ratio ``1 - RMS(residual) / RMS(reference)`` (1 = perfect compensation,
0 = no better than not compensating). With prediction-interval half-widths, also the coverage
of the 95 % interval (the fraction of reference samples inside it, ~0.95 when honest).
"""

from __future__ import annotations

import numpy as np

from fbgcomp.tables import Column, format_table, text
from fbgcomp.units import AXES

#: The do-no-harm rule: a compensated axis may not end with a larger max |error| than without
#: compensation; 0.5 µm is allowed for the interferometer's own noise on an axis that hardly moves.
HARM_TOLERANCE_UM = 0.5


def axis_metrics(reference_um, predicted_um, halfwidth_um=None) -> dict:
    """Metrics of one axis from reference and predicted deviations (1-D arrays, µm)."""
    reference_um = np.asarray(reference_um, dtype=float)
    error = np.asarray(predicted_um, dtype=float) - reference_um
    peak = float(np.max(np.abs(reference_um))) if reference_um.size else float("nan")
    rms_ref = float(np.sqrt(np.mean(reference_um**2))) if reference_um.size else float("nan")
    rms_err = float(np.sqrt(np.mean(error**2))) if error.size else float("nan")
    max_err = float(np.max(np.abs(error))) if error.size else float("nan")
    out = {
        "peak_um": peak,
        "max_abs_error_um": max_err,
        "rms_error_um": rms_err,
        "error_pct_of_peak": 100.0 * max_err / peak if peak > 0 else float("nan"),
        "compensation_ratio": 1.0 - rms_err / rms_ref if rms_ref > 0 else float("nan"),
        # uncompensated, the error is the deviation itself: max |ref| and RMS(ref)
        "uncompensated_max_um": peak,
        "uncompensated_rms_um": rms_ref,
        "harm": bool(max_err > peak + HARM_TOLERANCE_UM),
    }
    if halfwidth_um is not None:
        inside = np.abs(error) <= np.asarray(halfwidth_um, dtype=float)
        out["pi95_coverage"] = float(np.mean(inside)) if inside.size else float("nan")
        out["pi95_mean_halfwidth_um"] = float(np.mean(halfwidth_um)) if inside.size else float("nan")
    return out


def validation_metrics(reference_um, predicted_um, halfwidth_um=None) -> dict:
    """Metrics for all three axes: ``{"n_samples": N, "axes": {"dx": {...}, ...}}``.

    Parameters
    ----------
    reference_um, predicted_um : array_like, shape (n, 3)
        Reference (interferometer) and predicted TTP deviations dx, dy, dz, µm.
    halfwidth_um : array_like, shape (n, 3), optional
        Half-widths of the 95 % prediction intervals, µm.
    """
    reference_um = np.asarray(reference_um, dtype=float).reshape(-1, 3)
    predicted_um = np.asarray(predicted_um, dtype=float).reshape(-1, 3)
    hw = None if halfwidth_um is None else np.asarray(halfwidth_um, dtype=float).reshape(-1, 3)
    axes = {
        a: axis_metrics(reference_um[:, j], predicted_um[:, j], None if hw is None else hw[:, j])
        for j, a in enumerate(AXES)
    }
    return {"n_samples": int(reference_um.shape[0]), "axes": axes}


def format_metrics(metrics: dict, title: str = "") -> str:
    """A readable table of :func:`validation_metrics` output (:mod:`fbgcomp.tables`)."""
    has_cov = any("pi95_coverage" in m for m in metrics["axes"].values())
    cols = [
        text("axis"),
        Column("uncomp. max", "µm"),
        Column("max|err|", "µm"),
        Column("uncomp. RMS", "µm"),
        Column("RMS err", "µm"),
        Column("max err", "% of peak", 2),
        Column("comp. ratio", "", 4),
    ]
    if has_cov:
        cols.append(Column("PI95 cover", "", 3))
    rows = []
    for a, m in metrics["axes"].items():
        row = [
            a,
            m["peak_um"],
            m["max_abs_error_um"],
            m.get("uncompensated_rms_um", float("nan")),
            m["rms_error_um"],
            m["error_pct_of_peak"],
            m["compensation_ratio"],
        ]
        if has_cov:
            row.append(m.get("pi95_coverage", float("nan")))
        if m.get("harm"):
            row.append("WORSE than uncompensated")
        rows.append(row)
    lines = ([title] if title else []) + [f"n = {metrics['n_samples']}", format_table(cols, rows)]
    return "\n".join(lines)


def load_plateaus(loads_N, *, tolerance_N=None, min_samples=5):
    """Index arrays of the samples on each held load level (ramps between levels excluded).

    A plateau is a run of consecutive samples whose applied force vector stays within
    ``tolerance_N`` (default: 2 % of the largest force, at least 5 N) of the run's median; the
    first and last sample of each run are dropped as transitions.
    """
    loads_N = np.asarray(loads_N, dtype=float).reshape(-1, 3)
    finite = np.all(np.isfinite(loads_N), axis=1)
    scale = float(np.max(np.linalg.norm(loads_N[finite], axis=1))) if finite.any() else 0.0
    tol = max(0.02 * scale, 5.0) if tolerance_N is None else tolerance_N
    runs, start = [], 0
    for i in range(1, len(loads_N) + 1):
        if i == len(loads_N) or not finite[i] or np.linalg.norm(loads_N[i] - loads_N[i - 1]) > tol / 2:
            if i - start - 2 >= min_samples and finite[start:i].all():
                runs.append(np.arange(start + 1, i - 1))
            start = i
    return runs


def static_level_metrics(loads_N, reference_um, predicted_um, **plateau_options) -> dict:
    """Errors of the plateau means under held static loads (paper fig. 7: one point per load).

    Per axis: the largest |mean prediction - mean reference| over the loaded plateaus (µm) and
    that error as a percentage of the largest plateau deflection on the axis. Averaging over a
    hold is what a static calibration measures; per-sample errors add the sensors' white noise.
    """
    reference_um = np.asarray(reference_um, dtype=float).reshape(-1, 3)
    predicted_um = np.asarray(predicted_um, dtype=float).reshape(-1, 3)
    levels = []
    for idx in load_plateaus(loads_N, **plateau_options):
        force = np.nanmean(np.asarray(loads_N, dtype=float)[idx], axis=0)
        levels.append(
            {
                "force_N": force.tolist(),
                "n_samples": int(idx.size),
                "reference_um": reference_um[idx].mean(axis=0).tolist(),
                "predicted_um": predicted_um[idx].mean(axis=0).tolist(),
            }
        )
    axes = {}
    for j, a in enumerate(AXES):
        ref = np.array([lv["reference_um"][j] for lv in levels]) if levels else np.zeros(0)
        err = (
            np.array([lv["predicted_um"][j] - lv["reference_um"][j] for lv in levels])
            if levels
            else np.zeros(0)
        )
        peak = float(np.max(np.abs(ref))) if ref.size else float("nan")
        worst = float(np.max(np.abs(err))) if err.size else float("nan")
        axes[a] = {
            "max_plateau_deflection_um": peak,
            "max_plateau_error_um": worst,
            "error_pct_of_deflection": 100.0 * worst / peak if peak > 0 else float("nan"),
        }
    return {"n_levels": len(levels), "levels": levels, "axes": axes}


def format_static_metrics(m: dict) -> str:
    """A readable table of :func:`static_level_metrics` output (:mod:`fbgcomp.tables`)."""
    cols = [
        text("axis"),
        Column("max deflection", "µm"),
        Column("max error", "µm"),
        Column("max error", "% of deflection", 2),
    ]
    rows = [
        [a, v["max_plateau_deflection_um"], v["max_plateau_error_um"], v["error_pct_of_deflection"]]
        for a, v in m["axes"].items()
    ]
    return "\n".join(
        [f"static load plateaus: {m['n_levels']} (means over each hold)", format_table(cols, rows)]
    )
