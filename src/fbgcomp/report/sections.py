"""What the report shows about one campaign: sensor and probe health on the raw records, the
validation metrics and the paper's figures 6-9 that apply to it (:func:`analyse_campaign`).

Nothing here writes a file; :mod:`fbgcomp.report.html` renders the sections and writes the report.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from fbgcomp.io.campaign import WAVELENGTH_BAND_NM
from fbgcomp.io.campaign.align import diff_noise_sd
from fbgcomp.models.base import check_compatible
from fbgcomp.models.features import FeatureMap
from fbgcomp.models.metrics import validation_metrics
from fbgcomp.report import figures
from fbgcomp.units import AXES

__all__ = [
    "LOAD_LABELS",
    "MAX_JUMP_NM",
    "MAX_TEMPERATURE_JUMP_C",
    "NOISE_WARN_PM",
    "STUCK_S",
    "TEMPERATURE_NOISE_WARN_C",
    "TEMPERATURE_STUCK_S",
    "CampaignSection",
    "analyse_campaign",
    "probe_health",
    "sensor_health",
    "slugify",
]

LOAD_LABELS = ("F_x", "F_y", "F_z")

# Offline sensor-health thresholds: the runtime's own (fbgcomp.runtime.health.HealthConfig
# defaults, repeated so the offline report does not import the runtime) plus a noise bound.
MAX_JUMP_NM = 0.1  # ~80 µε or ~10 K between two samples: not physical for the ram
STUCK_S = 2.0  # exactly the same wavelength this long = stuck interrogator channel
STUCK_REPEATS = 5  # ... repeated at least this many times in a row (1 frame/s: chance repeats)
NOISE_WARN_PM = 5.0  # sample-to-sample noise above this swamps sub-µm elongations
MAX_TEMPERATURE_JUMP_C = 2.0  # a probe jumping 2 K between samples is a contact/wiring fault
TEMPERATURE_STUCK_S = 600.0  # a probe logging the very same value for 10 min is suspicious
TEMPERATURE_NOISE_WARN_C = 0.2


def _robust_noise(values: np.ndarray) -> float:
    """Sample-to-sample noise SD from the median absolute first difference (robust to steps
    and slow drift: a smooth signal has tiny differences, white noise sigma gives
    MAD(diff) * 1.4826 / sqrt 2 = sigma)."""
    if np.size(values) < 2:
        return float("nan")
    return float(diff_noise_sd(values))


def _longest_constant_run_s(time_s: np.ndarray, values: np.ndarray, min_repeats: int = 0) -> float:
    """Longest time span over which the value stays exactly the same, s, among the runs that
    repeat it at least ``min_repeats`` times (0 when none does)."""
    if values.size < 2:
        return 0.0
    change = np.flatnonzero(np.diff(values) != 0)
    # run boundaries: sample indices where a new value starts
    starts = np.concatenate([[0], change + 1])
    ends = np.concatenate([change, [values.size - 1]])
    long = (ends - starts) >= min_repeats
    return float(np.max(time_s[ends[long]] - time_s[starts[long]])) if long.any() else 0.0


def _channel_health(time_s, values, *, noise_unit_scale, noise_warn, jump, stuck_s, stuck_repeats=0):
    noise = _robust_noise(values) * noise_unit_scale
    d = np.abs(np.diff(values))
    jumps = int(np.sum(d > jump))
    stuck = _longest_constant_run_s(time_s, values, stuck_repeats)
    problems = []
    if np.isfinite(noise) and noise > noise_warn:
        problems.append(f"noisy ({noise:.3g} > {noise_warn:g})")
    if jumps:
        problems.append(f"{jumps} jump(s) > {jump:g}")
    if stuck >= stuck_s:
        problems.append(f"constant for {stuck:.3g} s (stuck?)")
    return noise, jumps, stuck, problems


def sensor_health(time_s, wavelength_nm, lambda0_nm, sensor_names, *, band_nm=5.0) -> list[dict]:
    """Per-sensor checks on an interrogator record (fbg.csv on its own clock).

    Parameters
    ----------
    time_s : (n,) s.
    wavelength_nm : (n, S) Bragg peak wavelengths, nm.
    lambda0_nm : (S,) nominal wavelengths of the gratings, nm.

    Returns one dict per sensor: ``noise_pm`` (robust sample-to-sample SD, pm), ``jumps``
    (steps > 0.1 nm between consecutive samples, the runtime's jump bound), ``longest_constant_s``
    (stuck channel when >= 2 s, the runtime's bound), ``out_of_band_fraction`` (samples further
    than ``band_nm`` from lambda0), ``band_margin_nm`` (how far the worst sample stays from the
    band edge), ``status`` ("OK" or "CHECK") and ``problems`` (text).
    """
    t = np.asarray(time_s, dtype=float)
    wl = np.asarray(wavelength_nm, dtype=float).reshape(t.size, -1)
    lam0 = np.asarray(lambda0_nm, dtype=float)
    out = []
    for j, name in enumerate(sensor_names):
        v = wl[:, j]
        noise, jumps, stuck, problems = _channel_health(
            t,
            v,
            noise_unit_scale=1000.0,
            noise_warn=NOISE_WARN_PM,
            jump=MAX_JUMP_NM,
            stuck_s=STUCK_S,
            stuck_repeats=STUCK_REPEATS,
        )
        excursion = np.abs(v - lam0[j])
        outside = float(np.mean(excursion > band_nm)) if v.size else float("nan")
        if outside > 0:
            problems.append(f"{100 * outside:.3g} % of samples outside ±{band_nm:g} nm")
        out.append(
            {
                "sensor": name,
                "samples": int(v.size),
                "noise_pm": noise,
                "jumps": jumps,
                "longest_constant_s": stuck,
                "out_of_band_fraction": outside,
                "band_margin_nm": float(band_nm - np.max(excursion)) if v.size else float("nan"),
                "status": "CHECK" if problems else "OK",
                "problems": problems,
            }
        )
    return out


def probe_health(time_s, temperature_C, probe_names) -> list[dict]:
    """The same checks for temperature probes (temperatures.csv): noise (K), jumps > 2 K,
    constant for >= 10 min."""
    t = np.asarray(time_s, dtype=float)
    temp = np.asarray(temperature_C, dtype=float).reshape(t.size, -1)
    out = []
    for j, name in enumerate(probe_names):
        noise, jumps, stuck, problems = _channel_health(
            t,
            temp[:, j],
            noise_unit_scale=1.0,
            noise_warn=TEMPERATURE_NOISE_WARN_C,
            jump=MAX_TEMPERATURE_JUMP_C,
            stuck_s=TEMPERATURE_STUCK_S,
        )
        out.append(
            {
                "probe": name,
                "samples": int(t.size),
                "noise_C": noise,
                "jumps": jumps,
                "longest_constant_s": stuck,
                "status": "CHECK" if problems else "OK",
                "problems": problems,
            }
        )
    return out


@dataclass
class CampaignSection:
    """Everything the report shows about one campaign (figures as PNG bytes)."""

    name: str
    kind: str
    summary: dict
    metrics: dict
    sensor_health: list
    probe_health: list
    figures: dict = field(default_factory=dict)  # key -> (title, png bytes, file name)
    not_applicable: dict = field(default_factory=dict)  # key -> reason
    notes: list = field(default_factory=list)


def slugify(text: str) -> str:
    """``text`` with every character but letters, digits, - and _ replaced by _ (for file names
    and HTML ids)."""
    keep = "".join(ch if ch.isalnum() or ch in "-_" else "_" for ch in text)
    return keep.strip("_") or "campaign"


def analyse_campaign(campaign, model, *, slug: str | None = None) -> CampaignSection:
    """Predict, measure and draw one campaign with one model (no file is written)."""
    check_compatible(model, campaign)
    aligned = campaign.aligned(zero_window_s=model.zero_window_s)
    pred, half = model.predict_interval(campaign)
    # ΔS from the campaign's own sensor metadata and the model's zero window: the same
    # elongations a regression model uses, and defined for every model type
    sensors = list(aligned.sensor_names)
    elongation = FeatureMap(list(campaign.meta.sensors), list(aligned.probe_names), False).base(
        aligned.wavelength_nm, aligned.temperature_C, aligned.wavelength_zero_nm, aligned.temperature_zero_C
    )
    ref = aligned.reference_um
    slug = slug or slugify(campaign.name)

    fbg_t = campaign.fbg["time_s"].to_numpy()
    fbg_v = campaign.fbg[[s.column for s in campaign.meta.sensors]].to_numpy(dtype=float)
    lam0 = [s.lambda0_nm for s in campaign.meta.sensors]
    temp_cols = [f"{p}_C" for p in campaign.probe_names]
    section = CampaignSection(
        name=campaign.name,
        kind=campaign.meta.kind,
        summary=campaign.summary(),
        metrics=validation_metrics(ref, pred, half),
        sensor_health=sensor_health(fbg_t, fbg_v, lam0, campaign.sensor_names, band_nm=WAVELENGTH_BAND_NM),
        probe_health=probe_health(
            campaign.temperatures["time_s"].to_numpy(),
            campaign.temperatures[temp_cols].to_numpy(dtype=float),
            campaign.probe_names,
        ),
    )

    def add(key, title, fig):
        section.figures[key] = (title, figures.png_bytes(fig), f"{slug}_{key}.png")

    loads = aligned.loads_N
    has_loads = loads is not None and np.isfinite(loads).any(axis=1).sum() >= 2
    if has_loads:
        ranges = np.nanmax(loads, axis=0) - np.nanmin(loads, axis=0)
        has_loads = bool(np.nanmax(ranges) > 0)
    if has_loads:
        k = int(np.nanargmax(ranges))
        load = loads[:, k]
        axis = max(range(3), key=lambda j: np.nanmax(np.abs(ref[:, j])))
        add(
            "fig6",
            f"Fig. 6 - sensor elongations vs. applied force {LOAD_LABELS[k]}",
            figures.elongation_vs_load(
                load,
                elongation,
                sensors,
                load_label=LOAD_LABELS[k],
                title=f"{campaign.name}: sensor elongations vs. applied "
                f"force {LOAD_LABELS[k]} (paper fig. 6)",
            ),
        )
        add(
            "fig7",
            f"Fig. 7 - real vs. predicted TTP deviation {AXES[axis]} under static load",
            figures.static_validation(
                load,
                ref[:, axis],
                pred[:, axis],
                half[:, axis],
                axis_name=AXES[axis],
                load_label=LOAD_LABELS[k],
                title=f"{campaign.name}: real vs. predicted TTP deviation "
                f"{AXES[axis]} under static load (paper fig. 7)",
            ),
        )
        section.notes.append(
            f"Load component varied: {LOAD_LABELS[k]} "
            f"({np.nanmin(load):.4g} to {np.nanmax(load):.4g} N); figure 7 "
            f"shows axis {AXES[axis]}, the largest measured deviation."
        )
    else:
        why = (
            "no loads.csv in this campaign"
            if loads is None
            else "loads.csv does not vary inside the aligned time range"
        )
        section.not_applicable["fig6"] = f"Fig. 6 not applicable: {why}."
        section.not_applicable["fig7"] = f"Fig. 7 not applicable: {why}."

    if campaign.meta.kind in ("thermal", "combined") or not has_loads:
        add(
            "fig8",
            "Fig. 8 - sensor elongations and temperatures over time",
            figures.time_history(
                aligned.time_s,
                elongation,
                sensors,
                aligned.temperature_C,
                aligned.probe_names,
                title=f"{campaign.name}: sensor elongations and temperatures over time (paper fig. 8)",
            ),
        )
        add(
            "fig9",
            "Fig. 9 - real vs. predicted TTP drift, residual and uncompensated error",
            figures.drift_validation(
                aligned.time_s,
                ref,
                pred,
                half,
                title=f"{campaign.name}: real vs. predicted TTP drift (paper fig. 9)",
            ),
        )
    else:
        why = (
            f"a {campaign.meta.kind} campaign is judged against the applied load "
            "(figs. 6 and 7), not as a time history"
        )
        section.not_applicable["fig8"] = f"Fig. 8 not applicable: {why}."
        section.not_applicable["fig9"] = f"Fig. 9 not applicable: {why}."
    return section
