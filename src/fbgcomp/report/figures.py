"""The paper's figures 6-9 as matplotlib figures built from plain arrays.

Every function takes numpy arrays with units in their names and returns a
:class:`matplotlib.figure.Figure` (saved as PNG when ``path`` is given), so the HTML report, the
demo and a notebook draw the same pictures. Figures are sized for an A4 page at 150 dpi: axis
labels carry units, every curve is in a legend, displacements are in µm as in the paper.

* :func:`elongation_vs_load` - sensor elongations vs. applied static force (paper fig. 6 a, b);
* :func:`static_validation` - real vs. predicted TTP deviation vs. force with 95 % prediction
  interval error bars (paper fig. 7);
* :func:`time_history` - sensor elongations and temperatures over time (paper fig. 8);
* :func:`drift_validation` - real vs. predicted TTP drift, the residual after compensation and
  the uncompensated error (paper fig. 9).

Matplotlib is imported with the non-interactive Agg backend: nothing here opens a window.
"""

from __future__ import annotations

import io
from pathlib import Path

import matplotlib
import numpy as np
from matplotlib.figure import Figure

from fbgcomp.atomic import write_bytes

matplotlib.use("Agg", force=False)

__all__ = [
    "MAX_PLOT_POINTS",
    "drift_validation",
    "elongation_vs_load",
    "load_levels",
    "png_bytes",
    "save_figure",
    "static_validation",
    "time_axis",
    "time_history",
]

#: Time histories are thinned to at most this many points per curve: a 36 h campaign at 10 Hz
#: would otherwise make multi-megabyte PNGs without showing anything more at print resolution.
MAX_PLOT_POINTS = 4000
DPI = 150
_AXIS_NAMES = ("dx", "dy", "dz")
# Colour-blind-safe (Okabe-Ito) colours, distinguishable in greyscale print by line style too.
_COLOURS = ("#0072B2", "#D55E00", "#009E73", "#CC79A7", "#E69F00", "#56B4E9", "#000000", "#F0E442")
_STYLES = ("-", "--", "-.", ":", (0, (5, 1, 1, 1)), (0, (3, 1)))
_MARKERS = ("o", "s", "^", "D", "v", "P", "X", "*")


def _new_figure(width_in: float, height_in: float, nrows=1, ncols=1, **kw):
    fig = Figure(figsize=(width_in, height_in), dpi=DPI, layout="constrained")
    axes = fig.subplots(nrows, ncols, squeeze=False, **kw)
    for ax in axes.flat:
        ax.grid(True, color="0.85", linewidth=0.6)
        ax.tick_params(labelsize=9)
    return fig, axes


def png_bytes(fig) -> bytes:
    """A figure as PNG at :data:`DPI`, in memory."""
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=DPI)
    return buf.getvalue()


def save_figure(fig, path: str | Path) -> Path:
    """Write a figure as PNG atomically (:func:`fbgcomp.atomic.write_bytes`)."""
    return write_bytes(path, png_bytes(fig))


def _finish(fig, path):
    if path is not None:
        save_figure(fig, path)
    return fig


def time_axis(time_s) -> tuple[np.ndarray, str]:
    """Time relative to the first sample in a readable unit: (values, axis label)."""
    t = np.asarray(time_s, dtype=float)
    rel = t - t[0] if t.size else t
    span = float(rel[-1]) if rel.size else 0.0
    if span >= 2 * 3600:
        return rel / 3600.0, "time since start (h)"
    if span >= 2 * 60:
        return rel / 60.0, "time since start (min)"
    return rel, "time since start (s)"


def _thin(n: int, max_points: int = MAX_PLOT_POINTS) -> np.ndarray:
    """Row indices keeping at most ``max_points`` evenly spaced samples (first and last kept)."""
    if n <= max_points:
        return np.arange(n)
    return np.unique(np.linspace(0, n - 1, max_points).round().astype(int))


def load_levels(load_N, resolution_N: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Group samples of a stepped static load into levels.

    Returns ``(levels_N, index)``: the distinct load levels (sorted) and, per sample, the index
    of its level (-1 for NaN loads). Loads closer than ``resolution_N`` (default 2 % of the
    largest |load|, at least 1 N) are one level; a ramp therefore falls into at most ~50 bins.
    """
    load = np.asarray(load_N, dtype=float)
    finite = np.isfinite(load)
    index = np.full(load.shape, -1, dtype=int)
    if not finite.any():
        return np.empty(0), index
    if resolution_N is None:
        resolution_N = max(1.0, 0.02 * float(np.max(np.abs(load[finite]))))
    keys = np.round(load[finite] / resolution_N).astype(np.int64)
    uniq, inverse = np.unique(keys, return_inverse=True)
    levels = np.array([load[finite][inverse == k].mean() for k in range(uniq.size)])
    index[finite] = inverse
    return levels, index


def _level_means(values, index, n_levels):
    """Mean of ``values`` (n,) or (n, k) per level; NaN for empty levels."""
    values = np.asarray(values, dtype=float)
    flat = values.reshape(values.shape[0], -1)
    out = np.full((n_levels, flat.shape[1]), np.nan)
    for k in range(n_levels):
        sel = index == k
        if sel.any():
            out[k] = np.nanmean(flat[sel], axis=0)
    return out.reshape((n_levels, *values.shape[1:]))


def elongation_vs_load(load_N, elongation_um, sensor_names, *, load_label="F", title=None, path=None):
    """Paper fig. 6: (a) each sensor's elongation against the applied force; (b) sensitivity.

    Parameters
    ----------
    load_N : (n,) applied force at the TTP, N (the component that varies in the campaign).
    elongation_um : (n, S) sensor path elongations relative to the zero state, µm.
    sensor_names : S names (S1...).
    load_label : name of the force component for the axis label, e.g. ``"F_y"``.

    Panel (a) shows the mean elongation at each load level with the sample spread (±1 SD) as
    error bars, and a least-squares line per sensor; panel (b) the slope of that line in µm per
    kN, the paper's "variability of the displacements detected by the sensors" (fig. 6 b).
    """
    load = np.asarray(load_N, dtype=float)
    dl = np.asarray(elongation_um, dtype=float).reshape(load.size, -1)
    levels, index = load_levels(load)
    fig, axes = _new_figure(10.0, 4.2, 1, 2, width_ratios=[1.7, 1])
    ax, bx = axes[0]
    finite = np.isfinite(load)
    slopes = np.full(dl.shape[1], np.nan)
    for j, name in enumerate(sensor_names):
        c = _COLOURS[j % len(_COLOURS)]
        means = _level_means(dl[:, j], index, levels.size)
        spread = np.array(
            [np.nanstd(dl[index == k, j]) if (index == k).any() else np.nan for k in range(levels.size)]
        )
        ax.errorbar(
            levels, means, yerr=spread, fmt=_MARKERS[j % len(_MARKERS)], color=c, ms=5, capsize=3, label=name
        )
        ok = finite & np.isfinite(dl[:, j])
        if ok.sum() >= 2 and np.ptp(load[ok]) > 0:
            slope, icpt = np.polyfit(load[ok], dl[ok, j], 1)
            slopes[j] = slope * 1000.0
            xs = np.array([load[ok].min(), load[ok].max()])
            ax.plot(xs, icpt + slope * xs, color=c, linestyle=_STYLES[j % len(_STYLES)], linewidth=1.2)
    ax.axhline(0.0, color="0.4", linewidth=0.8)
    ax.set_xlabel(f"applied force {load_label} (N)")
    ax.set_ylabel("sensor elongation ΔS (µm)")
    ax.set_title("(a) elongation vs. applied force (mean ± 1 SD per load level)", fontsize=10)
    ax.legend(title="sensor", fontsize=8, title_fontsize=8, ncols=2 if dl.shape[1] > 4 else 1)
    positions = np.arange(dl.shape[1])
    bars = bx.bar(positions, np.nan_to_num(slopes), color=[_COLOURS[j % len(_COLOURS)] for j in positions])
    for rect, s in zip(bars, slopes):
        if np.isfinite(s):
            bx.annotate(
                f"{s:.3g}",
                (rect.get_x() + rect.get_width() / 2, rect.get_height()),
                ha="center",
                va="bottom" if s >= 0 else "top",
                fontsize=8,
            )
    bx.axhline(0.0, color="0.4", linewidth=0.8)
    bx.set_xticks(positions, list(sensor_names))
    bx.set_xlabel("sensor")
    bx.set_ylabel(f"sensitivity dΔS/d{load_label} (µm/kN)")
    bx.set_title("(b) sensitivity per sensor", fontsize=10)
    fig.suptitle(title or "Sensor elongations under static load (paper fig. 6)", fontsize=11)
    return _finish(fig, path)


def static_validation(
    load_N, reference_um, predicted_um, halfwidth_um, *, axis_name="dy", load_label="F", title=None, path=None
):
    """Paper fig. 7: real vs. predicted TTP deviation against the applied force.

    Parameters
    ----------
    load_N : (n,) applied force, N.
    reference_um : (n,) measured TTP deviation on one axis (interferometer), µm.
    predicted_um : (n,) model prediction on the same axis, µm.
    halfwidth_um : (n,) half-width of the 95 % prediction interval, µm (the error bars).

    Points are the mean per load level; the error bars are the mean 95 % prediction-interval
    half-width at that level. The lower panel is the prediction error in % of the largest
    |real| deviation (the paper quotes ~5 %).
    """
    load = np.asarray(load_N, dtype=float)
    ref = np.asarray(reference_um, dtype=float)
    pred = np.asarray(predicted_um, dtype=float)
    half = np.asarray(halfwidth_um, dtype=float)
    levels, index = load_levels(load)
    m_ref = _level_means(ref, index, levels.size)
    m_pred = _level_means(pred, index, levels.size)
    m_half = _level_means(half, index, levels.size)
    fig, axes = _new_figure(8.0, 5.6, 2, 1, sharex=True, height_ratios=[2.2, 1])
    ax, ex = axes[:, 0]
    ax.plot(levels, m_ref, "o-", color=_COLOURS[0], ms=6, label="real (interferometer)")
    ax.errorbar(
        levels,
        m_pred,
        yerr=m_half,
        fmt="s--",
        color=_COLOURS[1],
        ms=5,
        capsize=4,
        label="predicted ± 95 % prediction interval",
    )
    ax.set_ylabel(f"TTP deviation {axis_name} (µm)")
    ax.legend(fontsize=8)
    ax.set_title(f"(a) real vs. predicted TTP deviation, axis {axis_name}", fontsize=10)
    peak = float(np.nanmax(np.abs(ref))) if np.isfinite(ref).any() else float("nan")
    err_pct = 100.0 * (m_pred - m_ref) / peak if peak > 0 else np.full(levels.size, np.nan)
    ex.bar(
        levels,
        err_pct,
        width=0.6 * (np.min(np.diff(levels)) if levels.size > 1 else 1.0),
        color=_COLOURS[2],
        label="predicted − real",
    )
    ex.axhline(0.0, color="0.4", linewidth=0.8)
    ex.set_xlabel(f"applied force {load_label} (N)")
    ex.set_ylabel("error (% of peak)")
    ex.legend(fontsize=8)
    ex.set_title(f"(b) prediction error, % of the peak real deviation ({peak:.3g} µm)", fontsize=10)
    fig.suptitle(title or "Static loads: real vs. predicted TTP deviation (paper fig. 7)", fontsize=11)
    return _finish(fig, path)


def time_history(time_s, elongation_um, sensor_names, temperature_C, probe_names, *, title=None, path=None):
    """Paper fig. 8: sensor elongations (top) and probe temperatures (bottom) over time.

    Parameters
    ----------
    time_s : (n,) s; plotted relative to the first sample in s, min or h.
    elongation_um : (n, S) sensor path elongations relative to the zero state, µm.
    temperature_C : (n, P) probe temperatures, °C (absolute, as logged).
    """
    t, t_label = time_axis(time_s)
    rows = _thin(t.size)
    dl = np.asarray(elongation_um, dtype=float).reshape(t.size, -1)
    temp = np.asarray(temperature_C, dtype=float).reshape(t.size, -1)
    fig, axes = _new_figure(10.0, 6.4, 2, 1, sharex=True)
    ax, tx = axes[:, 0]
    for j, name in enumerate(sensor_names):
        ax.plot(
            t[rows],
            dl[rows, j],
            color=_COLOURS[j % len(_COLOURS)],
            linestyle=_STYLES[j % len(_STYLES)],
            linewidth=1.2,
            label=name,
        )
    ax.axhline(0.0, color="0.4", linewidth=0.8)
    ax.set_ylabel("sensor elongation ΔS (µm)")
    ax.set_title("(a) elongations measured by the FBG sensors", fontsize=10)
    # legends outside the plot: 36 h of data leaves no empty corner to put them in
    ax.legend(title="sensor", fontsize=8, title_fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    for j, name in enumerate(probe_names):
        tx.plot(
            t[rows],
            temp[rows, j],
            color=_COLOURS[(j + 4) % len(_COLOURS)],
            linestyle=_STYLES[j % len(_STYLES)],
            linewidth=1.2,
            label=name,
        )
    tx.set_ylabel("temperature (°C)")
    tx.set_xlabel(t_label)
    tx.set_title("(b) probe temperatures", fontsize=10)
    if len(probe_names):
        tx.legend(title="probe", fontsize=8, title_fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    fig.suptitle(title or "Sensor elongations and temperatures over time (paper fig. 8)", fontsize=11)
    return _finish(fig, path)


def drift_validation(
    time_s, reference_um, predicted_um, halfwidth_um=None, *, axis_names=_AXIS_NAMES, title=None, path=None
):
    """Paper fig. 9: real vs. predicted TTP drift per axis, residual and uncompensated error.

    Parameters
    ----------
    time_s : (n,) s.
    reference_um : (n, A) measured TTP deviation (interferometer), µm, one column per axis.
    predicted_um : (n, A) model prediction, µm.
    halfwidth_um : (n, A) optional 95 % prediction-interval half-width, µm (shaded band).

    Without compensation the machining error is the real deviation itself (the paper's dotted
    curve); with it, the residual ``real - predicted`` (solid). The gap between the two is the
    compensation obtained.
    """
    t, t_label = time_axis(time_s)
    rows = _thin(t.size)
    ref = np.asarray(reference_um, dtype=float).reshape(t.size, -1)
    pred = np.asarray(predicted_um, dtype=float).reshape(t.size, -1)
    half = None if halfwidth_um is None else np.asarray(halfwidth_um, dtype=float).reshape(t.size, -1)
    n_axes = ref.shape[1]
    fig, axes = _new_figure(10.0, 2.6 * n_axes + 0.8, n_axes, 2, sharex=True, width_ratios=[1.25, 1])
    for j in range(n_axes):
        name = axis_names[j]
        ax, rx = axes[j]
        if half is not None:
            ax.fill_between(
                t[rows],
                pred[rows, j] - half[rows, j],
                pred[rows, j] + half[rows, j],
                color=_COLOURS[1],
                alpha=0.18,
                linewidth=0,
                label="95 % prediction interval",
            )
        ax.plot(t[rows], ref[rows, j], color=_COLOURS[0], linewidth=1.4, label="real")
        ax.plot(t[rows], pred[rows, j], color=_COLOURS[1], linestyle="--", linewidth=1.4, label="predicted")
        ax.set_ylabel(f"{name} (µm)")
        ax.set_title(f"axis {name}: real vs. predicted TTP deviation", fontsize=10)
        ax.legend(fontsize=8, loc="best")
        resid = ref[:, j] - pred[:, j]
        rx.plot(
            t[rows],
            ref[rows, j],
            color="0.25",
            linestyle=":",
            linewidth=1.6,
            label=f"uncompensated error (max |·| {np.nanmax(np.abs(ref[:, j])):.3g} µm)",
        )
        rx.plot(
            t[rows],
            resid[rows],
            color=_COLOURS[2],
            linewidth=1.4,
            label=f"residual after compensation (max |·| {np.nanmax(np.abs(resid)):.3g} µm)",
        )
        rx.axhline(0.0, color="0.4", linewidth=0.8)
        rx.set_ylabel(f"{name} error (µm)")
        rx.set_title(f"axis {name}: error without and with compensation", fontsize=10)
        rx.legend(fontsize=8, loc="best")
    for ax in axes[-1]:
        ax.set_xlabel(t_label)
    fig.suptitle(title or "Thermal drift: real vs. predicted TTP deviation (paper fig. 9)", fontsize=11)
    return _finish(fig, path)
