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
from datetime import UTC, datetime
from pathlib import Path

from fbgcomp import __version__
from fbgcomp.atomic import staged_dir
from fbgcomp.errors import InputError
from fbgcomp.io.campaign import Campaign, read_campaign
from fbgcomp.models.features import parse_term
from fbgcomp.models.registry import load_model
from fbgcomp.report.sections import (
    MAX_JUMP_NM,
    MAX_TEMPERATURE_JUMP_C,
    NOISE_WARN_PM,
    STUCK_S,
    TEMPERATURE_NOISE_WARN_C,
    TEMPERATURE_STUCK_S,
    CampaignSection,
    analyse_campaign,
    probe_health,
    sensor_health,
    slugify,
)
from fbgcomp.units import AXES

# analyse_campaign, CampaignSection, sensor_health and probe_health live in
# fbgcomp.report.sections; they are re-exported here, where the report's callers import them.
__all__ = [
    "REPORT_FILE",
    "CampaignSection",
    "analyse_campaign",
    "probe_health",
    "render_html",
    "sensor_health",
    "term_description",
    "write_report",
]

REPORT_FILE = "report.html"

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
    head = "".join(
        f'<th class="l">{_e(h)}</th>' if i in left else f"<th>{_e(h)}</th>" for i, h in enumerate(headers)
    )
    body = []
    for row in rows:
        cells = "".join(
            f'<td class="l">{c}</td>' if i in left else f"<td>{c}</td>" for i, c in enumerate(row)
        )
        body.append(f"<tr>{cells}</tr>")
    return f"<table><thead><tr>{head}</tr></thead><tbody>{''.join(body)}</tbody></table>"


def _model_html(model, model_path) -> str:
    out = ['<h2 id="model">Model: coefficients per axis (paper Table 1)</h2>']
    info = getattr(model, "training_", None) or {}
    training = info.get("campaigns", [])
    features = getattr(model, "features", None)
    out.append(
        f'<p class="meta">Model file <code>{_e(model_path)}</code>, id '
        f"<code>{_e(model.model_id)}</code>, type {_e(getattr(model, 'model_type', '?'))}"
        + (f"; feature set <b>{_e(features)}</b>" if isinstance(features, str) else "")
        + (", stepwise selection" if getattr(model, "stepwise", False) else "")
        + f"; fitted on {info.get('n_samples', 0)} samples from "
        f"{_e(', '.join(c['name'] for c in training) or 'no campaign')}; zero state = mean "
        f"of the first {model.zero_window_s:g} s; fallback models stored: "
        f"{len(getattr(model, 'fallback_sets', []) or [])}.</p>"
    )
    axes = getattr(model, "axes_", None)
    if not axes:
        out.append(
            f'<p class="na">Table 1 not applicable: a {_e(getattr(model, "model_type", "?"))} '
            "model has no fitted regression coefficients.</p>"
        )
        return "\n".join(out)
    for axis in AXES:
        fit = axes[axis]
        rows = []
        for i, (term, p, se, t, pv) in enumerate(
            zip(fit.terms, fit.params, fit.bse, fit.tvalues, fit.pvalues)
        ):
            desc, unit = term_description(term)
            rows.append(
                [
                    f"α<sub>{i}</sub>",
                    _e(desc),
                    f"<code>{_e(term)}</code>",
                    _num(p, ".5g"),
                    _num(se, ".4g"),
                    _e(unit),
                    _num(t, ".2f"),
                    _p(pv),
                ]
            )
        out.append(f'<h3 id="table1-{axis}">Axis {axis} (TTP deviation, µm)</h3>')
        out.append(
            _table(
                ["coefficient", "description", "term", "value", "standard error", "unit", "t", "P>|t|"],
                rows,
                left={0, 1, 2, 5},
            )
        )
        out.append(
            f'<p class="meta">n = {fit.nobs}, R² = {fit.rsquared:.5f}, adjusted R² = '
            f"{fit.rsquared_adj:.5f}, residual SD = {fit.resid_sd:.4g} µm, "
            f"F = {fit.fvalue:.4g} (p {_p_relation(fit.f_pvalue)}), "
            f"residual degrees of freedom {fit.df_resid:g}.</p>"
        )
        if fit.history:
            hist = [
                [
                    _e(h.get("step", "")),
                    _e(h.get("action", "")),
                    f"<code>{_e(h.get('term', ''))}</code>",
                    _num(h.get("F", float("nan"))),
                    _p(h.get("p", float("nan"))),
                    _e(h.get("n_terms", "")),
                    _num(h.get("rsquared_adj", float("nan")), ".5f"),
                ]
                for h in fit.history
            ]
            out.append(f"<h4>Stepwise history, axis {axis}</h4>")
            out.append(
                _table(
                    ["step", "action", "term", "partial F", "p", "terms", "adjusted R²"], hist, left={1, 2}
                )
            )
        elif model.stepwise:
            out.append(f'<p class="na">Stepwise selection made no change on axis {axis}.</p>')
        else:
            out.append(
                '<p class="na">Stepwise history not applicable: the model was fitted '
                "with every candidate term (no --stepwise).</p>"
            )
    return "\n".join(out)


def _metrics_html(metrics) -> str:
    rows = []
    for axis, m in metrics["axes"].items():
        rows.append(
            [
                axis,
                _num(m["peak_um"], ".4g"),
                _num(m["max_abs_error_um"], ".4g"),
                _num(m["rms_error_um"], ".4g"),
                _num(m["error_pct_of_peak"], ".3g"),
                _num(m["compensation_ratio"], ".4f"),
                _num(m.get("pi95_coverage", float("nan")), ".3f"),
                _num(m.get("pi95_mean_halfwidth_um", float("nan")), ".3g"),
            ]
        )
    return _table(
        [
            "axis",
            "peak |real| (µm)",
            "max |error| (µm)",
            "RMS error (µm)",
            "max error (% of peak)",
            "compensation ratio",
            "95 % PI coverage",
            "mean PI half-width (µm)",
        ],
        rows,
        left={0},
    )


def _status(text) -> str:
    return f'<span class="{"ok" if text == "OK" else "check"}">{_e(text)}</span>'


def _health_html(section: CampaignSection) -> str:
    rows = [
        [
            _e(h["sensor"]),
            _status(h["status"]),
            _num(h["noise_pm"], ".3g"),
            h["jumps"],
            _num(h["longest_constant_s"], ".3g"),
            _num(100 * h["out_of_band_fraction"], ".3g"),
            _num(h["band_margin_nm"], ".3g"),
            _e("; ".join(h["problems"]) or "none"),
        ]
        for h in section.sensor_health
    ]
    out = [
        _table(
            [
                "sensor",
                "status",
                "noise (pm)",
                f"jumps > {MAX_JUMP_NM:g} nm",
                "longest constant (s)",
                "outside ±5 nm (%)",
                "band margin (nm)",
                "problems",
            ],
            rows,
            left={0, 7},
        )
    ]
    if section.probe_health:
        rows = [
            [
                _e(h["probe"]),
                _status(h["status"]),
                _num(h["noise_C"], ".3g"),
                h["jumps"],
                _num(h["longest_constant_s"], ".3g"),
                _e("; ".join(h["problems"]) or "none"),
            ]
            for h in section.probe_health
        ]
        out.append(
            _table(
                [
                    "probe",
                    "status",
                    "noise (K)",
                    f"jumps > {MAX_TEMPERATURE_JUMP_C:g} K",
                    "longest constant (s)",
                    "problems",
                ],
                rows,
                left={0, 5},
            )
        )
    out.append(
        f'<p class="meta">Checks on the raw records, each on its own clock: noise = '
        f"robust sample-to-sample standard deviation (median absolute first difference); "
        f"a jump is a step larger than {MAX_JUMP_NM:g} nm (the runtime's bound, ~80 µε); "
        f"stuck = the very same value for ≥ {STUCK_S:g} s (probes: "
        f"{TEMPERATURE_STUCK_S:g} s); CHECK also when the noise exceeds "
        f"{NOISE_WARN_PM:g} pm ({TEMPERATURE_NOISE_WARN_C:g} K for probes). Samples "
        f"outside the ±5 nm band are refused when a campaign is read, so that column is "
        f"0 for any campaign that loads; the band margin shows how close the worst sample "
        f"came to the edge.</p>"
    )
    return "\n".join(out)


def _summary_html(s: dict) -> str:
    rows = []
    for role, info in s["files"].items():
        rate = f"{info['rate_hz']:.4g}" if info.get("rate_hz") else "–"
        rows.append(
            [
                _e(role),
                info["rows"],
                _num(info["start_s"], ".6g"),
                _num(info["duration_s"], ".6g"),
                rate,
                info.get("gaps", 0),
            ]
        )
    out = [_table(["file", "rows", "start (s)", "duration (s)", "rate (Hz)", "gaps"], rows, left={0})]
    overlap = s["overlap_s"]
    out.append(
        f'<p class="meta">Start {_e(s["start"])}; folder <code>{_e(s["path"])}</code>; '
        f"aligned overlap {'{:g} to {:g} s'.format(*overlap) if overlap else 'none'}; "
        f"sensors {_e(', '.join(x['name'] for x in s['sensors']))}; probes "
        f"{_e(', '.join(s['probes']) or 'none')}.</p>"
    )
    if s["description"]:
        out.append(f"<p>{_e(s['description'])}</p>")
    if s["problems"]:
        out.append(
            "<p><b>Problems found:</b></p><ul>"
            + "".join(f"<li>{_e(p)}</li>" for p in s["problems"])
            + "</ul>"
        )
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
    generated_utc = generated_utc or datetime.now(UTC).isoformat(timespec="seconds")
    toc = "".join(
        f'<li><a href="#c-{_e(slugify(s.name))}">{_e(s.name)}</a> ({_e(s.kind)})</li>' for s in sections
    )
    parts = [
        "<!DOCTYPE html>",
        '<html lang="en"><head><meta charset="utf-8">',
        '<meta name="viewport" content="width=device-width, initial-scale=1">',
        f"<title>fbgcomp calibration report - model {_e(model.model_id)}</title>",
        f"<style>{_CSS}</style></head><body>",
        "<h1>FBG compensation: calibration report</h1>",
        f'<p class="meta">Generated {_e(generated_utc)} by fbgcomp {_e(__version__)}. Units: '
        "wavelengths nm, elongations and TTP deviations µm, temperatures °C, forces N. "
        "Figures and Table 1 follow <i>A Kinematic Model to Compensate the Structural "
        "Deformations in Machine Tools Using FBG Sensors</i> (sec. 3).</p>",
        f'<h2>Contents</h2><ul><li><a href="#summary">Validation summary</a></li>'
        f'{toc}<li><a href="#model">Model coefficients (Table 1)</a></li></ul>',
        '<h2 id="summary">Validation summary</h2>',
    ]
    rows = []
    for s in sections:
        for axis, m in s.metrics["axes"].items():
            rows.append(
                [
                    _e(s.name),
                    _e(s.kind),
                    axis,
                    _num(m["peak_um"]),
                    _num(m["max_abs_error_um"]),
                    _num(m["rms_error_um"]),
                    _num(m["error_pct_of_peak"], ".3g"),
                    _num(m["compensation_ratio"], ".4f"),
                    _num(m.get("pi95_coverage", float("nan")), ".3f"),
                ]
            )
    parts.append(
        _table(
            [
                "campaign",
                "kind",
                "axis",
                "peak |real| (µm)",
                "max |error| (µm)",
                "RMS error (µm)",
                "% of peak",
                "compensation ratio",
                "95 % PI coverage",
            ],
            rows,
            left={0, 1, 2},
        )
    )
    unhealthy = [(s.name, h["sensor"]) for s in sections for h in s.sensor_health if h["status"] != "OK"]
    parts.append(
        "<p>Sensor health: "
        + (
            "every sensor passed the checks on every campaign."
            if not unhealthy
            else '<span class="check">to check</span>: '
            + _e(", ".join(f"{c}/{s}" for c, s in unhealthy))
            + "."
        )
        + "</p>"
    )
    for s in sections:
        sid = _e(slugify(s.name))
        parts.append(f'<section class="campaign" id="c-{sid}">')
        parts.append(f"<h2>Campaign {_e(s.name)} ({_e(s.kind)})</h2>")
        parts.append("<h3>Summary</h3>")
        parts.append(_summary_html(s.summary))
        parts.append("<h3>Validation metrics</h3>")
        parts.append(_metrics_html(s.metrics))
        parts.extend(f'<p class="meta">{_e(n)}</p>' for n in s.notes)
        parts.append("<h3>Figures</h3>")
        for key in _FIGURE_ORDER:
            if key in s.figures:
                title, png, file_name = s.figures[key]
                data = base64.b64encode(png).decode("ascii")
                parts.append(
                    f'<figure id="{sid}-{key}" data-figure="{key}">'
                    f'<img src="data:image/png;base64,{data}" '
                    f'alt="{_e(_FIGURE_ALT[key])}">'
                    f"<figcaption>{_e(title)} (also <code>{_e(file_name)}</code>)"
                    f"</figcaption></figure>"
                )
            else:
                parts.append(f'<p class="na" data-not-applicable="{key}">{_e(s.not_applicable[key])}</p>')
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
        base = slugify(name)
        seen[base] = seen.get(base, 0) + 1
        out.append(base if seen[base] == 1 else f"{base}-{seen[base]}")
    return out


def write_report(campaigns, model, output_dir, *, model_path="", progress=None) -> Path:
    """Analyse ``campaigns`` (Campaign objects or folders) with ``model`` (an MRAModel or a
    model file path) and write ``output_dir/report.html`` plus one PNG per figure, atomically.
    ``progress(name)``, when given, is called as each campaign's analysis starts.

    Returns the path of report.html.
    """
    if isinstance(model, (str, os.PathLike)):
        model_path = model_path or str(model)
        model = load_model(model)
    campaigns = [c if isinstance(c, Campaign) else read_campaign(c) for c in campaigns]
    if not campaigns:
        raise InputError("a report needs at least one campaign", file="<command line>", column="CAMPAIGN")
    target = Path(output_dir)
    if target.exists() and not target.is_dir():
        raise InputError("cannot write the report: a file of that name exists", file=target)
    if target.is_dir() and any(target.iterdir()) and not (target / REPORT_FILE).is_file():
        raise InputError(
            f"refusing to replace a folder that is not a report folder (it has no {REPORT_FILE})", file=target
        )
    sections = []
    for campaign, slug in zip(campaigns, _unique_slugs(c.name for c in campaigns)):
        if progress is not None:
            progress(campaign.name)  # as each campaign's analysis starts
        sections.append(analyse_campaign(campaign, model, slug=slug))
    document = render_html(sections, model, model_path or "<in memory>")

    with staged_dir(target) as staging:
        for s in sections:
            for _title, png, file_name in s.figures.values():
                _write_bytes(staging / file_name, png)
        # report.html last: a folder with report.html is a complete one.
        _write_bytes(staging / REPORT_FILE, document.encode("utf-8"))
    return target / REPORT_FILE


def _write_bytes(path: Path, data: bytes) -> None:
    """Write a file of the staging folder durably. Not atomic on its own, and not meant to be:
    the folder swap (fbgcomp.atomic.replace_dir) is what a reader sees."""
    with open(path, "wb") as fh:
        fh.write(data)
        fh.flush()
        os.fsync(fh.fileno())
