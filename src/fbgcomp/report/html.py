"""``fbgcomp report``: one self-contained HTML file that shows how good a calibration is.

The report is how a calibration is judged and shown to a customer, so it follows the paper's
own evidence (sec. 3): per campaign a summary, the figures that apply to it - sensor elongations
vs. applied load (fig. 6) and real vs. predicted TTP deviation with 95 % prediction-interval
error bars (fig. 7) for campaigns with ``loads.csv``; elongations and temperatures over time
(fig. 8) and real vs. predicted drift with the residual and the uncompensated error (fig. 9) for
time histories - the validation metrics and the sensor health of the campaign data; and for the
model the coefficient table per axis with standard errors, t and p (Table 1) and the stepwise
history.

Output: ``DIR/report.html`` with every figure embedded (data: URIs, no external file, script or
font, so it can be mailed or archived as one file) and the same figures as PNGs in ``DIR``.
The folder is written into a temporary sibling and renamed into place, so a reader never sees
a half-written report; an existing report folder is replaced, any other non-empty folder is
refused.
"""

from __future__ import annotations

import base64
import html
import math
import os
import shutil
import uuid
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import List

import numpy as np
import typer

from fbgcomp.atomic import replace_dir
from fbgcomp.errors import InputError
from fbgcomp.units import AXES

__all__ = ["CampaignSection", "analyse_campaign", "sensor_health", "probe_health",
           "write_report", "render_html", "register", "REPORT_FILE"]

REPORT_FILE = "report.html"
LOAD_COLUMNS = ("fx_N", "fy_N", "fz_N")
LOAD_LABELS = ("F_x", "F_y", "F_z")

# Offline sensor-health thresholds: the runtime's own (fbgcomp.runtime.health.HealthConfig
# defaults, repeated so the offline report does not import the runtime) plus a noise bound.
MAX_JUMP_NM = 0.1            # ~80 µε or ~10 K between two samples: not physical for the ram
STUCK_S = 2.0                # exactly the same wavelength this long = stuck interrogator channel
NOISE_WARN_PM = 5.0          # sample-to-sample noise above this swamps sub-µm elongations
MAX_TEMPERATURE_JUMP_C = 2.0  # a probe jumping 2 K between samples is a contact/wiring fault
TEMPERATURE_STUCK_S = 600.0  # a probe logging the very same value for 10 min is suspicious
TEMPERATURE_NOISE_WARN_C = 0.2


# --------------------------------------------------------------------------------------------
# Sensor health on campaign data
# --------------------------------------------------------------------------------------------

def _robust_noise(values: np.ndarray) -> float:
    """Sample-to-sample noise SD from the median absolute first difference (robust to steps
    and slow drift: a smooth signal has tiny differences, white noise sigma gives
    MAD(diff) * 1.4826 / sqrt 2 = sigma)."""
    d = np.diff(values)
    if d.size == 0:
        return float("nan")
    mad = np.median(np.abs(d - np.median(d)))
    return float(1.4826 * mad / math.sqrt(2.0))


def _longest_constant_run_s(time_s: np.ndarray, values: np.ndarray) -> float:
    """Longest time span over which the value stays exactly the same, s."""
    if values.size < 2:
        return 0.0
    change = np.flatnonzero(np.diff(values) != 0)
    # run boundaries: sample indices where a new value starts
    starts = np.concatenate([[0], change + 1])
    ends = np.concatenate([change, [values.size - 1]])
    return float(np.max(time_s[ends] - time_s[starts]))


def _channel_health(time_s, values, *, noise_unit_scale, noise_warn, jump, stuck_s):
    noise = _robust_noise(values) * noise_unit_scale
    d = np.abs(np.diff(values))
    jumps = int(np.sum(d > jump))
    stuck = _longest_constant_run_s(time_s, values)
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
            t, v, noise_unit_scale=1000.0, noise_warn=NOISE_WARN_PM, jump=MAX_JUMP_NM,
            stuck_s=STUCK_S)
        excursion = np.abs(v - lam0[j])
        outside = float(np.mean(excursion > band_nm)) if v.size else float("nan")
        if outside > 0:
            problems.append(f"{100 * outside:.3g} % of samples outside ±{band_nm:g} nm")
        out.append({"sensor": name, "samples": int(v.size), "noise_pm": noise, "jumps": jumps,
                    "longest_constant_s": stuck, "out_of_band_fraction": outside,
                    "band_margin_nm": float(band_nm - np.max(excursion)) if v.size else float("nan"),
                    "status": "CHECK" if problems else "OK", "problems": problems})
    return out


def probe_health(time_s, temperature_C, probe_names) -> list[dict]:
    """The same checks for temperature probes (temperatures.csv): noise (K), jumps > 2 K,
    constant for >= 10 min."""
    t = np.asarray(time_s, dtype=float)
    temp = np.asarray(temperature_C, dtype=float).reshape(t.size, -1)
    out = []
    for j, name in enumerate(probe_names):
        noise, jumps, stuck, problems = _channel_health(
            t, temp[:, j], noise_unit_scale=1.0, noise_warn=TEMPERATURE_NOISE_WARN_C,
            jump=MAX_TEMPERATURE_JUMP_C, stuck_s=TEMPERATURE_STUCK_S)
        out.append({"probe": name, "samples": int(t.size), "noise_C": noise, "jumps": jumps,
                    "longest_constant_s": stuck, "status": "CHECK" if problems else "OK",
                    "problems": problems})
    return out


# --------------------------------------------------------------------------------------------
# Per-campaign analysis
# --------------------------------------------------------------------------------------------

@dataclass
class CampaignSection:
    """Everything the report shows about one campaign (figures as PNG bytes)."""

    name: str
    kind: str
    summary: dict
    metrics: dict
    sensor_health: list
    probe_health: list
    figures: dict = field(default_factory=dict)      # key -> (title, png bytes, file name)
    not_applicable: dict = field(default_factory=dict)  # key -> reason
    notes: list = field(default_factory=list)


def _png(fig) -> bytes:
    import io

    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    return buf.getvalue()


def _slug(text: str) -> str:
    keep = "".join(ch if ch.isalnum() or ch in "-_" else "_" for ch in text)
    return keep.strip("_") or "campaign"


def analyse_campaign(campaign, model, *, slug: str | None = None) -> CampaignSection:
    """Predict, measure and draw one campaign with one model (no file is written)."""
    from fbgcomp.report import figures
    from fbgcomp.models.metrics import validation_metrics
    from fbgcomp.models.base import check_compatible

    check_compatible(model, campaign)
    aligned = campaign.aligned(zero_window_s=model.zero_window_s)
    pred, half = model.predict_interval(campaign)
    # ΔS from the campaign's own sensor metadata and the model's zero window: the same
    # elongations a regression model uses, and defined for every model type
    from fbgcomp.models.features import FeatureMap

    sensors = list(aligned.sensor_names)
    elongation = FeatureMap(list(campaign.meta.sensors), list(aligned.probe_names), False).base(
        aligned.wavelength_nm, aligned.temperature_C, aligned.wavelength_zero_nm,
        aligned.temperature_zero_C)
    ref = aligned.reference_um
    slug = slug or _slug(campaign.name)

    fbg_t = campaign.fbg["time_s"].to_numpy()
    fbg_v = campaign.fbg[[s.column for s in campaign.meta.sensors]].to_numpy(dtype=float)
    lam0 = [s.lambda0_nm for s in campaign.meta.sensors]
    from fbgcomp.io.campaign import WAVELENGTH_BAND_NM

    temp_cols = [f"{p}_C" for p in campaign.probe_names]
    section = CampaignSection(
        name=campaign.name, kind=campaign.meta.kind, summary=campaign.summary(),
        metrics=validation_metrics(ref, pred, half),
        sensor_health=sensor_health(fbg_t, fbg_v, lam0, campaign.sensor_names,
                                    band_nm=WAVELENGTH_BAND_NM),
        probe_health=probe_health(campaign.temperatures["time_s"].to_numpy(),
                                  campaign.temperatures[temp_cols].to_numpy(dtype=float),
                                  campaign.probe_names))

    def add(key, title, fig):
        section.figures[key] = (title, _png(fig), f"{slug}_{key}.png")

    loads = aligned.loads_N
    has_loads = loads is not None and np.isfinite(loads).any(axis=1).sum() >= 2
    if has_loads:
        ranges = np.nanmax(loads, axis=0) - np.nanmin(loads, axis=0)
        has_loads = bool(np.nanmax(ranges) > 0)
    if has_loads:
        k = int(np.nanargmax(ranges))
        load = loads[:, k]
        axis = max(range(3), key=lambda j: np.nanmax(np.abs(ref[:, j])))
        add("fig6", f"Fig. 6 - sensor elongations vs. applied force {LOAD_LABELS[k]}",
            figures.elongation_vs_load(load, elongation, sensors, load_label=LOAD_LABELS[k],
                                       title=f"{campaign.name}: sensor elongations vs. applied "
                                             f"force {LOAD_LABELS[k]} (paper fig. 6)"))
        add("fig7", f"Fig. 7 - real vs. predicted TTP deviation {AXES[axis]} under static load",
            figures.static_validation(load, ref[:, axis], pred[:, axis], half[:, axis],
                                      axis_name=AXES[axis], load_label=LOAD_LABELS[k],
                                      title=f"{campaign.name}: real vs. predicted TTP deviation "
                                            f"{AXES[axis]} under static load (paper fig. 7)"))
        section.notes.append(f"Load component varied: {LOAD_LABELS[k]} "
                             f"({np.nanmin(load):.4g} to {np.nanmax(load):.4g} N); figure 7 "
                             f"shows axis {AXES[axis]}, the largest measured deviation.")
    else:
        why = ("no loads.csv in this campaign" if loads is None
               else "loads.csv does not vary inside the aligned time range")
        section.not_applicable["fig6"] = f"Fig. 6 not applicable: {why}."
        section.not_applicable["fig7"] = f"Fig. 7 not applicable: {why}."

    if campaign.meta.kind in ("thermal", "combined") or not has_loads:
        add("fig8", "Fig. 8 - sensor elongations and temperatures over time",
            figures.time_history(aligned.time_s, elongation, sensors, aligned.temperature_C,
                                 aligned.probe_names,
                                 title=f"{campaign.name}: sensor elongations and temperatures "
                                       "over time (paper fig. 8)"))
        add("fig9", "Fig. 9 - real vs. predicted TTP drift, residual and uncompensated error",
            figures.drift_validation(aligned.time_s, ref, pred, half,
                                     title=f"{campaign.name}: real vs. predicted TTP drift "
                                           "(paper fig. 9)"))
    else:
        why = (f"a {campaign.meta.kind} campaign is judged against the applied load "
               "(figs. 6 and 7), not as a time history")
        section.not_applicable["fig8"] = f"Fig. 8 not applicable: {why}."
        section.not_applicable["fig9"] = f"Fig. 9 not applicable: {why}."
    return section


# --------------------------------------------------------------------------------------------
# HTML
# --------------------------------------------------------------------------------------------

_CSS = """
body{font-family:"DejaVu Sans",Helvetica,Arial,sans-serif;font-size:11pt;color:#111;
 max-width:1100px;margin:1.5em auto;padding:0 1em;line-height:1.35}
h1{font-size:18pt;margin-bottom:.2em}h2{font-size:14pt;border-bottom:2px solid #0072B2;
 padding-bottom:.15em;margin-top:1.6em}h3{font-size:12pt;margin-top:1.2em}
table{border-collapse:collapse;margin:.5em 0 1em;font-size:10pt}
th,td{border:1px solid #bbb;padding:.2em .5em;text-align:right}
th{background:#eef3f8}td.l,th.l{text-align:left}
.ok{color:#006d2c;font-weight:bold}.check{color:#b30000;font-weight:bold}
.na{color:#555;font-style:italic;border-left:3px solid #bbb;padding-left:.6em}
figure{margin:1em 0;page-break-inside:avoid}figure img{max-width:100%;height:auto;
 border:1px solid #ddd}figcaption{font-size:10pt;color:#333}
.meta{color:#444;font-size:10pt}section.campaign{page-break-before:always}
@media print{body{max-width:none;margin:0}h2{page-break-after:avoid}}
"""


def _e(value) -> str:
    return html.escape(str(value), quote=True)


def _num(value, fmt=".4g") -> str:
    try:
        v = float(value)
    except (TypeError, ValueError):
        return _e(value)
    if math.isnan(v):
        return "–"
    return format(v, fmt)


def _p(value) -> str:
    v = float(value)
    if math.isnan(v):
        return "–"
    return "&lt; 1e-300" if v < 1e-300 else format(v, ".3g")


def _p_relation(value) -> str:
    """``= 0.012`` or ``&lt; 1e-300`` for running text."""
    text = _p(value)
    return text if text.startswith("&lt;") else f"= {text}"


def term_description(term: str) -> tuple[str, str]:
    """(description, coefficient unit) of a model term, in the words of paper Table 1."""
    from fbgcomp.models.features import parse_term

    if term == "const":
        return "intercept", "µm"
    factors = parse_term(term)
    words, units = [], []
    for f in factors:
        if f.startswith("dL_"):
            words.append(f"FBG sensor {f[3:]} elongation ΔS")
            units.append("µm")
        elif f.startswith("dT_"):
            role = {"bulk": "bulk", "surf": "surface", "flange": "flange"}.get(f[3:], f[3:])
            words.append(f"ΔT {role}")
            units.append("K")
        else:
            words.append(f)
            units.append("?")
    if len(factors) == 2 and factors[0] == factors[1]:
        return f"({words[0]})²", f"µm/{units[0]}²"
    denominator = "·".join(units)
    return " × ".join(words), ("µm/µm" if denominator == "µm" else f"µm/{denominator}")


def _table(headers, rows, left=()) -> str:
    head = "".join(f'<th class="l">{_e(h)}</th>' if i in left else f"<th>{_e(h)}</th>"
                   for i, h in enumerate(headers))
    body = []
    for row in rows:
        cells = "".join(f'<td class="l">{c}</td>' if i in left else f"<td>{c}</td>"
                        for i, c in enumerate(row))
        body.append(f"<tr>{cells}</tr>")
    return f"<table><thead><tr>{head}</tr></thead><tbody>{''.join(body)}</tbody></table>"


def _model_html(model, model_path) -> str:
    out = ["<h2 id=\"model\">Model: coefficients per axis (paper Table 1)</h2>"]
    info = getattr(model, "training_", None) or {}
    training = info.get("campaigns", [])
    features = getattr(model, "features", None)
    out.append(f"<p class=\"meta\">Model file <code>{_e(model_path)}</code>, id "
               f"<code>{_e(model.model_id)}</code>, type {_e(getattr(model, 'model_type', '?'))}"
               + (f"; feature set <b>{_e(features)}</b>" if isinstance(features, str) else "")
               + (", stepwise selection" if getattr(model, "stepwise", False) else "")
               + f"; fitted on {info.get('n_samples', 0)} samples from "
               f"{_e(', '.join(c['name'] for c in training) or 'no campaign')}; zero state = mean "
               f"of the first {model.zero_window_s:g} s; fallback models stored: "
               f"{len(getattr(model, 'fallback_sets', []) or [])}.</p>")
    axes = getattr(model, "axes_", None)
    if not axes:
        out.append(f"<p class=\"na\">Table 1 not applicable: a {_e(getattr(model, 'model_type', '?'))} "
                   "model has no fitted regression coefficients.</p>")
        return "\n".join(out)
    for axis in AXES:
        fit = axes[axis]
        rows = []
        for i, (term, p, se, t, pv) in enumerate(zip(fit.terms, fit.params, fit.bse,
                                                     fit.tvalues, fit.pvalues)):
            desc, unit = term_description(term)
            rows.append([f"α<sub>{i}</sub>", _e(desc), f"<code>{_e(term)}</code>", _num(p, ".5g"),
                         _num(se, ".4g"), _e(unit), _num(t, ".2f"), _p(pv)])
        out.append(f"<h3 id=\"table1-{axis}\">Axis {axis} (TTP deviation, µm)</h3>")
        out.append(_table(["coefficient", "description", "term", "value", "standard error",
                           "unit", "t", "P>|t|"], rows, left={0, 1, 2, 5}))
        out.append(f"<p class=\"meta\">n = {fit.nobs}, R² = {fit.rsquared:.5f}, adjusted R² = "
                   f"{fit.rsquared_adj:.5f}, residual SD = {fit.resid_sd:.4g} µm, "
                   f"F = {fit.fvalue:.4g} (p {_p_relation(fit.f_pvalue)}), "
                   f"residual degrees of freedom {fit.df_resid:g}.</p>")
        if fit.history:
            hist = [[_e(h.get("step", "")), _e(h.get("action", "")),
                     f"<code>{_e(h.get('term', ''))}</code>", _num(h.get("F", float("nan"))),
                     _p(h.get("p", float("nan"))), _e(h.get("n_terms", "")),
                     _num(h.get("rsquared_adj", float("nan")), ".5f")] for h in fit.history]
            out.append(f"<h4>Stepwise history, axis {axis}</h4>")
            out.append(_table(["step", "action", "term", "partial F", "p", "terms",
                               "adjusted R²"], hist, left={1, 2}))
        elif model.stepwise:
            out.append(f"<p class=\"na\">Stepwise selection made no change on axis {axis}.</p>")
        else:
            out.append("<p class=\"na\">Stepwise history not applicable: the model was fitted "
                       "with every candidate term (no --stepwise).</p>")
    return "\n".join(out)


def _metrics_html(metrics) -> str:
    rows = []
    for axis, m in metrics["axes"].items():
        rows.append([axis, _num(m["peak_um"], ".4g"), _num(m["max_abs_error_um"], ".4g"),
                     _num(m["rms_error_um"], ".4g"), _num(m["error_pct_of_peak"], ".3g"),
                     _num(m["compensation_ratio"], ".4f"),
                     _num(m.get("pi95_coverage", float("nan")), ".3f"),
                     _num(m.get("pi95_mean_halfwidth_um", float("nan")), ".3g")])
    return _table(["axis", "peak |real| (µm)", "max |error| (µm)", "RMS error (µm)",
                   "max error (% of peak)", "compensation ratio", "95 % PI coverage",
                   "mean PI half-width (µm)"], rows, left={0})


def _status(text) -> str:
    return f'<span class="{"ok" if text == "OK" else "check"}">{_e(text)}</span>'


def _health_html(section: CampaignSection) -> str:
    rows = [[_e(h["sensor"]), _status(h["status"]), _num(h["noise_pm"], ".3g"), h["jumps"],
             _num(h["longest_constant_s"], ".3g"), _num(100 * h["out_of_band_fraction"], ".3g"),
             _num(h["band_margin_nm"], ".3g"), _e("; ".join(h["problems"]) or "none")]
            for h in section.sensor_health]
    out = [_table(["sensor", "status", "noise (pm)", f"jumps > {MAX_JUMP_NM:g} nm",
                   "longest constant (s)", "outside ±5 nm (%)", "band margin (nm)", "problems"],
                  rows, left={0, 7})]
    if section.probe_health:
        rows = [[_e(h["probe"]), _status(h["status"]), _num(h["noise_C"], ".3g"), h["jumps"],
                 _num(h["longest_constant_s"], ".3g"), _e("; ".join(h["problems"]) or "none")]
                for h in section.probe_health]
        out.append(_table(["probe", "status", "noise (K)", f"jumps > {MAX_TEMPERATURE_JUMP_C:g} K",
                           "longest constant (s)", "problems"], rows, left={0, 5}))
    out.append(f"<p class=\"meta\">Checks on the raw records, each on its own clock: noise = "
               f"robust sample-to-sample standard deviation (median absolute first difference); "
               f"a jump is a step larger than {MAX_JUMP_NM:g} nm (the runtime's bound, ~80 µε); "
               f"stuck = the very same value for ≥ {STUCK_S:g} s (probes: "
               f"{TEMPERATURE_STUCK_S:g} s); CHECK also when the noise exceeds "
               f"{NOISE_WARN_PM:g} pm ({TEMPERATURE_NOISE_WARN_C:g} K for probes). Samples "
               f"outside the ±5 nm band are refused when a campaign is read, so that column is "
               f"0 for any campaign that loads; the band margin shows how close the worst sample "
               f"came to the edge.</p>")
    return "\n".join(out)


def _summary_html(s: dict) -> str:
    rows = []
    for role, info in s["files"].items():
        rate = f"{info['rate_hz']:.4g}" if info.get("rate_hz") else "–"
        rows.append([_e(role), info["rows"], _num(info["start_s"], ".6g"),
                     _num(info["duration_s"], ".6g"), rate, info.get("gaps", 0)])
    out = [_table(["file", "rows", "start (s)", "duration (s)", "rate (Hz)", "gaps"], rows,
                  left={0})]
    overlap = s["overlap_s"]
    out.append(f"<p class=\"meta\">Start {_e(s['start'])}; folder <code>{_e(s['path'])}</code>; "
               f"aligned overlap {('%g to %g s' % tuple(overlap)) if overlap else 'none'}; "
               f"sensors {_e(', '.join(x['name'] for x in s['sensors']))}; probes "
               f"{_e(', '.join(s['probes']) or 'none')}.</p>")
    if s["description"]:
        out.append(f"<p>{_e(s['description'])}</p>")
    if s["problems"]:
        out.append("<p><b>Problems found:</b></p><ul>" +
                   "".join(f"<li>{_e(p)}</li>" for p in s["problems"]) + "</ul>")
    else:
        out.append("<p>Problems found: none.</p>")
    return "\n".join(out)


_FIGURE_ORDER = ("fig6", "fig7", "fig8", "fig9")
_FIGURE_ALT = {
    "fig6": "Sensor elongations in micrometres plotted against the applied force in newtons",
    "fig7": "Real and predicted tool-tip deviation in micrometres against the applied force, "
            "with 95 % prediction-interval error bars",
    "fig8": "Sensor elongations in micrometres and probe temperatures in degrees Celsius over time",
    "fig9": "Real and predicted tool-tip deviation over time per axis, with the residual and the "
            "uncompensated error in micrometres",
}


def render_html(sections, model, model_path, *, generated_utc=None) -> str:
    """The report as one HTML document with every figure embedded as a data: URI."""
    from fbgcomp import __version__

    generated_utc = generated_utc or datetime.now(timezone.utc).isoformat(timespec="seconds")
    toc = "".join(f'<li><a href="#c-{_e(_slug(s.name))}">{_e(s.name)}</a> ({_e(s.kind)})</li>'
                  for s in sections)
    parts = [
        "<!DOCTYPE html>",
        '<html lang="en"><head><meta charset="utf-8">',
        '<meta name="viewport" content="width=device-width, initial-scale=1">',
        f"<title>fbgcomp calibration report - model {_e(model.model_id)}</title>",
        f"<style>{_CSS}</style></head><body>",
        "<h1>FBG compensation: calibration report</h1>",
        f"<p class=\"meta\">Generated {_e(generated_utc)} by fbgcomp {_e(__version__)}. Units: "
        "wavelengths nm, elongations and TTP deviations µm, temperatures °C, forces N. "
        "Figures and Table 1 follow <i>A Kinematic Model to Compensate the Structural "
        "Deformations in Machine Tools Using FBG Sensors</i> (sec. 3).</p>",
        f"<h2>Contents</h2><ul><li><a href=\"#summary\">Validation summary</a></li>"
        f"{toc}<li><a href=\"#model\">Model coefficients (Table 1)</a></li></ul>",
        '<h2 id="summary">Validation summary</h2>',
    ]
    rows = []
    for s in sections:
        for axis, m in s.metrics["axes"].items():
            rows.append([_e(s.name), _e(s.kind), axis, _num(m["peak_um"]),
                         _num(m["max_abs_error_um"]), _num(m["rms_error_um"]),
                         _num(m["error_pct_of_peak"], ".3g"),
                         _num(m["compensation_ratio"], ".4f"),
                         _num(m.get("pi95_coverage", float("nan")), ".3f")])
    parts.append(_table(["campaign", "kind", "axis", "peak |real| (µm)", "max |error| (µm)",
                         "RMS error (µm)", "% of peak", "compensation ratio",
                         "95 % PI coverage"], rows, left={0, 1, 2}))
    unhealthy = [(s.name, h["sensor"]) for s in sections for h in s.sensor_health
                 if h["status"] != "OK"]
    parts.append("<p>Sensor health: " + (
        "every sensor passed the checks on every campaign." if not unhealthy else
        "<span class=\"check\">to check</span>: " +
        _e(", ".join(f"{c}/{s}" for c, s in unhealthy)) + ".") + "</p>")
    for s in sections:
        sid = _e(_slug(s.name))
        parts.append(f'<section class="campaign" id="c-{sid}">')
        parts.append(f"<h2>Campaign {_e(s.name)} ({_e(s.kind)})</h2>")
        parts.append("<h3>Summary</h3>")
        parts.append(_summary_html(s.summary))
        parts.append("<h3>Validation metrics</h3>")
        parts.append(_metrics_html(s.metrics))
        parts.extend(f"<p class=\"meta\">{_e(n)}</p>" for n in s.notes)
        parts.append("<h3>Figures</h3>")
        for key in _FIGURE_ORDER:
            if key in s.figures:
                title, png, file_name = s.figures[key]
                data = base64.b64encode(png).decode("ascii")
                parts.append(f'<figure id="{sid}-{key}" data-figure="{key}">'
                             f'<img src="data:image/png;base64,{data}" '
                             f'alt="{_e(_FIGURE_ALT[key])}">'
                             f"<figcaption>{_e(title)} (also <code>{_e(file_name)}</code>)"
                             f"</figcaption></figure>")
            else:
                parts.append(f'<p class="na" data-not-applicable="{key}">'
                             f"{_e(s.not_applicable[key])}</p>")
        parts.append("<h3>Sensor health</h3>")
        parts.append(_health_html(s))
        parts.append("</section>")
    parts.append('<section class="campaign">')
    parts.append(_model_html(model, model_path))
    parts.append("</section></body></html>")
    return "\n".join(parts)


# --------------------------------------------------------------------------------------------
# Writing
# --------------------------------------------------------------------------------------------

def _unique_slugs(names):
    seen: dict[str, int] = {}
    out = []
    for name in names:
        base = _slug(name)
        seen[base] = seen.get(base, 0) + 1
        out.append(base if seen[base] == 1 else f"{base}-{seen[base]}")
    return out


def write_report(campaigns, model, output_dir, *, model_path="", progress=None) -> Path:
    """Analyse ``campaigns`` (Campaign objects or folders) with ``model`` (an MRAModel or a
    model file path) and write ``output_dir/report.html`` plus one PNG per figure, atomically.

    Returns the path of report.html.
    """
    from fbgcomp.io.campaign import Campaign, read_campaign
    from fbgcomp.models.base import load_model

    if isinstance(model, (str, os.PathLike)):
        model_path = model_path or str(model)
        model = load_model(model)
    campaigns = [c if isinstance(c, Campaign) else read_campaign(c) for c in campaigns]
    if not campaigns:
        raise InputError("a report needs at least one campaign", file="<command line>",
                         column="CAMPAIGN")
    target = Path(output_dir)
    if target.exists() and not target.is_dir():
        raise InputError("cannot write the report: a file of that name exists", file=target)
    if target.is_dir() and any(target.iterdir()) and not (target / REPORT_FILE).is_file():
        raise InputError(f"refusing to replace a folder that is not a report folder (it has no "
                         f"{REPORT_FILE})", file=target)
    sections = []
    for campaign, slug in zip(campaigns, _unique_slugs(c.name for c in campaigns)):
        sections.append(analyse_campaign(campaign, model, slug=slug))
        if progress is not None:
            progress(campaign.name)
    document = render_html(sections, model, model_path or "<in memory>")

    target.parent.mkdir(parents=True, exist_ok=True)
    token = uuid.uuid4().hex[:12]
    staging = target.parent / f".{target.name}.tmp-{token}"
    staging.mkdir()
    try:
        for s in sections:
            for _title, png, file_name in s.figures.values():
                _write_bytes(staging / file_name, png)
        # report.html last: a folder with report.html is a complete one.
        _write_bytes(staging / REPORT_FILE, document.encode("utf-8"))
        replace_dir(staging, target, target.parent / f".{target.name}.old-{token}")
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    return target / REPORT_FILE


def _write_bytes(path: Path, data: bytes) -> None:
    with open(path, "wb") as fh:
        fh.write(data)
        fh.flush()
        os.fsync(fh.fileno())


# --------------------------------------------------------------------------------------------
# CLI
# --------------------------------------------------------------------------------------------

def register(app) -> None:
    """Add ``fbgcomp report`` to the main Typer application."""
    @app.command("report")
    def report(campaigns: List[Path] = typer.Argument(..., help="Campaign folders to report on."),
               model: Path = typer.Option(..., "--model", help="Model file (JSON) from fbgcomp fit."),
               output: Path = typer.Option(..., "-o", "--output",
                                           help="Report folder to write (report.html + PNGs).")):
        """Write a self-contained HTML report: campaign summaries, paper figs. 6-9, Table 1 per
        axis with the stepwise history, validation metrics and sensor health."""
        import matplotlib  # noqa: F401 - a clear ImportError before any work

        from fbgcomp.io.campaign import read_campaign
        from fbgcomp.models.base import load_model

        fitted = load_model(model)
        data = [read_campaign(p) for p in campaigns]
        path = write_report(data, fitted, output, model_path=str(model))
        n_fig = sum(1 for _ in output.glob("*.png"))
        typer.echo(f"report written to {path} ({len(data)} campaign(s), {n_fig} figure(s))")
