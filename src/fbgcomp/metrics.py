"""How well a model predicts the TTP deviation of a campaign it was (or was not) fitted on.

Per axis: peak |reference| (µm), max |error| (µm), RMS error (µm), max error as % of the peak,
and the compensation ratio ``1 - RMS(residual) / RMS(reference)`` (1 = perfect compensation,
0 = no better than not compensating). With prediction-interval half-widths, also the coverage
of the 95 % interval (the fraction of reference samples inside it, ~0.95 when honest).
"""

from __future__ import annotations

import numpy as np

AXES = ("dx", "dy", "dz")


def axis_metrics(reference_um, predicted_um, halfwidth_um=None) -> dict:
    """Metrics of one axis from reference and predicted deviations (1-D arrays, µm)."""
    reference_um = np.asarray(reference_um, dtype=float)
    error = np.asarray(predicted_um, dtype=float) - reference_um
    peak = float(np.max(np.abs(reference_um))) if reference_um.size else float("nan")
    rms_ref = float(np.sqrt(np.mean(reference_um ** 2))) if reference_um.size else float("nan")
    rms_err = float(np.sqrt(np.mean(error ** 2))) if error.size else float("nan")
    max_err = float(np.max(np.abs(error))) if error.size else float("nan")
    out = {
        "peak_um": peak,
        "max_abs_error_um": max_err,
        "rms_error_um": rms_err,
        "error_pct_of_peak": 100.0 * max_err / peak if peak > 0 else float("nan"),
        "compensation_ratio": 1.0 - rms_err / rms_ref if rms_ref > 0 else float("nan"),
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
    axes = {a: axis_metrics(reference_um[:, j], predicted_um[:, j], None if hw is None else hw[:, j])
            for j, a in enumerate(AXES)}
    return {"n_samples": int(reference_um.shape[0]), "axes": axes}


def dominant_axis(metrics: dict) -> str:
    """The axis with the largest peak reference deviation."""
    return max(metrics["axes"], key=lambda a: metrics["axes"][a]["peak_um"])


def format_metrics(metrics: dict, title: str = "") -> str:
    """A readable table of :func:`validation_metrics` output."""
    has_cov = any("pi95_coverage" in m for m in metrics["axes"].values())
    head = f"{'axis':<5}{'peak µm':>10}{'max|err| µm':>13}{'RMS err µm':>12}{'% of peak':>11}{'comp. ratio':>12}"
    if has_cov:
        head += f"{'PI95 cover':>11}"
    lines = ([title] if title else []) + [f"n = {metrics['n_samples']}", head]
    for a, m in metrics["axes"].items():
        line = (f"{a:<5}{m['peak_um']:>10.3f}{m['max_abs_error_um']:>13.3f}{m['rms_error_um']:>12.3f}"
                f"{m['error_pct_of_peak']:>11.2f}{m['compensation_ratio']:>12.4f}")
        if has_cov:
            line += f"{m.get('pi95_coverage', float('nan')):>11.3f}"
        lines.append(line)
    return "\n".join(lines)
