"""Cross-campaign comparison of every model type and feature set (``fbgcomp compare``).

Each entry is fitted on the training campaigns and judged on the test campaigns it never saw,
**per held-out campaign** and pooled: per axis max |error| µm, RMS µm, max error as % of the
peak, the 95 % interval coverage where the entry gives intervals, and load-plateau errors where
a campaign has loads. Every campaign's table begins with the ``uncompensated`` row (the error of
a machine without compensation is its deviation itself) and marks every axis where an entry ends
worse than that (do-no-harm, :data:`fbgcomp.models.metrics.HARM_TOLERANCE_UM`). The pooled table is
ranked per axis by max |error|. Written as CSV (pooled; per campaign), JSON and Markdown,
each atomically.

Entries: ``physical`` (the default model of ``fbgcomp fit``); ``mra`` with eq11, eq13, eq12 and
eq13 stepwise; ``ridge`` and ``pls`` (partial least squares) on eq13, both with their complexity
(ridge penalty, number of PLS components) chosen by blocked cross-validation over contiguous time
blocks of the training data (autocorrelated samples make random folds optimistic); ``dynamic``
(eq13 + first-order filtered temperatures); ``kinematic`` (fit-free chain); ``hybrid``
(kinematic + regression, eq13 and dynamic); ``calibrated`` (hybrid with the closure's
compliances fitted on the training load plateaus).
"""

from __future__ import annotations

import csv
import io
from pathlib import Path
from typing import Any

import numpy as np

from fbgcomp.atomic import json_safe, write_bytes, write_json
from fbgcomp.models.base import campaign_weights_for
from fbgcomp.models.machines import resolve_machine
from fbgcomp.models.metrics import HARM_TOLERANCE_UM, static_level_metrics, validation_metrics
from fbgcomp.models.mra import MRAModel
from fbgcomp.models.registry import make_estimator
from fbgcomp.tables import Column, format_number, format_table, text
from fbgcomp.units import AXES

#: (name, model type, feature set, options)
ENTRIES: tuple[tuple[str, str, str, dict[str, Any]], ...] = (
    ("physical", "physical", "-", {}),
    ("mra eq11", "mra", "eq11", {}),
    ("mra eq13", "mra", "eq13", {}),
    ("mra eq12", "mra", "eq12", {}),
    ("mra eq13 stepwise", "mra", "eq13", {"stepwise": True}),
    ("ridge eq13", "ridge", "eq13", {}),
    ("pls eq13", "pls", "eq13", {}),
    ("dynamic eq13+lp", "dynamic", "eq13+lp", {"stepwise": True}),
    ("kinematic", "kinematic", "-", {}),
    ("hybrid eq13", "hybrid", "eq13", {}),
    ("hybrid dynamic", "hybrid", "dynamic", {}),
    ("calibrated eq13", "calibrated", "eq13", {}),
)


# ------------------------------------------------------------------ ridge and PLS on a design
def _blocks(n, k=5):
    edges = np.linspace(0, n, k + 1).astype(int)
    return [np.arange(edges[i], edges[i + 1]) for i in range(k)]


def _standardise(X, w):
    mu = np.average(X[:, 1:], axis=0, weights=w)
    sd = np.sqrt(np.average((X[:, 1:] - mu) ** 2, axis=0, weights=w))
    sd[sd == 0] = 1.0
    return mu, sd


#: the ridge penalties blocked cross-validation chooses from
RIDGE_LAMBDAS = np.logspace(-6, 2, 17)


def _fold_rows(n, folds):
    """The training rows (everything outside the fold) of each contiguous fold, in order."""
    return [
        np.concatenate([np.arange(0, f[0]), np.arange(f[-1] + 1, n)]) if f.size else np.arange(n)
        for f in folds
    ]


def ridge_fit(X, Y, w=None, lambdas=RIDGE_LAMBDAS):
    """Weighted ridge on standardised columns (the constant unpenalised), penalty by blocked CV.

    ``X`` (n, 1 + p) with the constant first, ``Y`` (n, 3), ``w`` (n,) row weights.
    Returns (coef (1 + p, 3), lambda (3,)).
    """
    w_all = np.ones(len(X)) if w is None else np.asarray(w, dtype=float)

    def design(Xs, ws):
        # everything of a solve that depends on the rows alone: once per fold, not per lambda
        mu, sd = _standardise(Xs, ws)
        Z = (Xs[:, 1:] - mu) / sd
        Zw = Z * ws[:, None]
        return mu, sd, Zw, Zw.T @ Z, ws

    def prepare(d, Ys):
        mu, sd, Zw, G, ws = d
        ym = np.average(Ys, axis=0, weights=ws)
        return mu, sd, ym, G, Zw.T @ (Ys - ym), ws.sum()

    def solve(prepared, lam):
        mu, sd, ym, G, rhs, ws_sum = prepared
        A = G + lam * ws_sum * np.eye(G.shape[0])
        b = np.linalg.solve(A, rhs)
        return np.vstack([ym - (mu / sd) @ b, b / sd[:, None]])

    folds = _blocks(len(X))
    prepared = [(f, prepare(design(X[t], w_all[t]), Y[t])) for f, t in zip(folds, _fold_rows(len(X), folds))]
    err = np.zeros((len(lambdas), Y.shape[1]))
    for i, lam in enumerate(lambdas):
        for f, prep in prepared:
            c = solve(prep, lam)
            err[i] += np.sum(w_all[f, None] * (X[f] @ c - Y[f]) ** 2, axis=0)
    best = np.argmin(err, axis=0)
    full = design(X, w_all)
    coef = np.column_stack(
        [solve(prepare(full, Y[:, [j]]), lambdas[best[j]])[:, 0] for j in range(Y.shape[1])]
    )
    return coef, lambdas[best]


def pls_fit(X, Y, w=None, max_components=None):
    """Weighted PLS1 (NIPALS) per axis on standardised columns, components by blocked CV.

    Returns (coef (1 + p, 3), n_components (3,)).
    """
    p = X.shape[1] - 1
    max_components = min(p, max_components or p)
    w_all = np.ones(len(X)) if w is None else np.asarray(w, dtype=float)

    def standardised(Xs, ws):
        mu, sd = _standardise(Xs, ws)
        r = np.sqrt(ws)
        # Weighted least squares = ordinary on rows scaled by sqrt(weight), after weighted centring.
        return mu, sd, r, (Xs[:, 1:] - mu) / sd * r[:, None]

    def solve_all(std, ys, k_max, ws):
        """The coefficients with 1..k_max components (NIPALS's first k components do not
        depend on how many follow: one run gives them all)."""
        mu, sd, r, Z = std
        ym = np.average(ys, weights=ws)
        E, f = Z.copy(), (ys - ym) * r
        W, P, q = [], [], []
        for _ in range(k_max):
            w = E.T @ f
            nw = np.linalg.norm(w)
            if nw == 0:
                break
            w /= nw
            t = E @ w
            tt = t @ t
            if tt == 0:
                break
            pk = E.T @ t / tt
            qk = f @ t / tt
            E = E - np.outer(t, pk)
            f = f - qk * t
            W.append(w), P.append(pk), q.append(qk)
        out = []
        for k in range(1, k_max + 1):
            m = min(k, len(W))
            if not m:
                out.append(np.concatenate([[ym], np.zeros(p)]))
                continue
            Wk, Pk, qk_ = np.array(W[:m]).T, np.array(P[:m]).T, np.array(q[:m])
            b = Wk @ np.linalg.solve(Pk.T @ Wk, qk_)
            out.append(np.concatenate([[ym - (mu / sd) @ b], b / sd]))
        return out

    folds = _blocks(len(X))
    train = _fold_rows(len(X), folds)
    fold_std = [standardised(X[t], w_all[t]) for t in train]
    full_std = standardised(X, w_all)
    coefs, ncomp = [], []
    for j in range(Y.shape[1]):
        err = np.zeros(max_components)
        for f, t, std in zip(folds, train, fold_std):
            for k, c in enumerate(solve_all(std, Y[t, j], max_components, w_all[t]), start=1):
                err[k - 1] += np.sum(w_all[f] * (X[f] @ c - Y[f, j]) ** 2)
        k = int(np.argmin(err)) + 1
        coefs.append(solve_all(full_std, Y[:, j], k, w_all)[k - 1])
        ncomp.append(k)
    return np.column_stack(coefs), np.array(ncomp)


class _DesignModel:
    """Ridge or PLS on the eq. 13 design (comparison only; no model file)."""

    def __init__(self, kind, features="eq13", zero_window_s=10.0):
        self.kind, self.features, self.zero_window_s = kind, features, zero_window_s

    def fit(self, campaigns):
        """Fit on a list of campaigns (penalty or components chosen by blocked CV)."""
        self._mra = MRAModel(features=self.features, zero_window_s=self.zero_window_s, fallbacks="none")
        self._mra.new_accumulator(list(campaigns[0].meta.sensors), None, roles_from=campaigns[0].probe_names)
        X, Y = [], []
        aligned = [c.aligned(zero_window_s=self.zero_window_s) for c in campaigns]
        # Campaigns pooled like MRAModel.fit (balanced row weights, weighted least squares).
        weights = campaign_weights_for([len(a.time_s) for a in aligned], "balanced")
        W = []
        for c, a, w in zip(campaigns, aligned, weights):
            X.append(self._mra.campaign_design(c, a))
            Y.append(a.reference_um)
            W.append(np.full(len(a.time_s), w))
        X, Y, W = np.vstack(X), np.vstack(Y), np.concatenate(W)
        if self.kind == "ridge":
            self.coef_, self.complexity_ = ridge_fit(X, Y, W)
        else:
            self.coef_, self.complexity_ = pls_fit(X, Y, W)
        return self

    def predict_interval(self, campaign):
        """Prediction (n, 3) µm on a campaign, and None (no interval)."""
        a = campaign.aligned(zero_window_s=self.zero_window_s)
        return self._mra.campaign_design(campaign, a) @ self.coef_, None


# ---------------------------------------------------------------------------- comparison
#: The row every held-out campaign is judged against: no compensation, so the error is the
#: reference deviation itself (max |error| = peak, RMS = RMS of the deviation).
UNCOMPENSATED = "uncompensated"


def _make(kind, features, options, machine, machine_given):
    if kind in ("ridge", "pls"):
        return _DesignModel(kind, features)
    # as `fbgcomp fit` with no flags, the physical model gets the machine description only when
    # one was given; the dynamic entry's "eq13+lp" names its eq13 features plus the filters
    return make_estimator(
        kind,
        machine=machine if kind != "physical" or machine_given else None,
        features="eq13" if kind == "dynamic" else features,
        where="<compare entry>",
        fallbacks="none",
        **options,
    )


def unique_name(name: str, seen: dict) -> str:
    """``name``, or with a #2, #3 suffix when ``seen`` (name -> count, updated) already holds it:
    two campaigns of one name (day1/thermal, day2/thermal) each keep their own entry."""
    seen[name] = seen.get(name, 0) + 1
    return name if seen[name] == 1 else f"{name}#{seen[name]}"


def _campaign_names(campaigns):
    """Names of the held-out campaigns (campaign.yaml ``name``), made unique (:func:`unique_name`)."""
    seen: dict = {}
    return [unique_name(c.meta.name, seen) for c in campaigns]


def _campaign_row(campaign, name, kind, features, axis, m, plateau):
    p = (plateau or {}).get("axes", {}).get(axis, {})
    return {
        "campaign": campaign,
        "axis": axis,
        "name": name,
        "model_type": kind,
        "features": features,
        "max_abs_error_um": m["max_abs_error_um"],
        "rms_error_um": m["rms_error_um"],
        "uncompensated_max_um": m["uncompensated_max_um"],
        "uncompensated_rms_um": m["uncompensated_rms_um"],
        "harm": bool(m["harm"]),
        "error_pct_of_peak": m["error_pct_of_peak"],
        "pi95_coverage": m.get("pi95_coverage"),
        "plateau_max_error_um": p.get("max_plateau_error_um"),
        "plateau_deflection_um": p.get("max_plateau_deflection_um"),
        "plateau_error_pct_of_deflection": p.get("error_pct_of_deflection"),
    }


def compare(train, test, *, machine=None, entries=ENTRIES, progress=None) -> dict:
    """Fit every entry on ``train`` campaigns, judge on each ``test`` campaign and on all pooled.

    ``machine`` (a :class:`~fbgcomp.structure.Machine`, a path or None for the built-in ram) is
    the description the kinematic types need; the physical model receives it only when given,
    as ``fbgcomp fit`` does.

    Returns ``{"train", "test", "rows", "ranking", "failures", "campaigns", "campaign_rows"}``:

    * ``rows``: pooled over the test campaigns, one per entry and axis (name, model type,
      features, axis, max_abs_error_um, rms_error_um, error_pct_of_peak, peak_um, pi95_coverage
      or None, harm, and ``per_campaign`` metrics); ``ranking`` orders them per axis;
    * ``campaign_rows``: one per test campaign, entry and axis, beginning with the
      ``uncompensated`` row (error = the reference deviation itself); ``harm`` is True where
      the entry's max |error| exceeds the uncompensated one by more than
      :data:`fbgcomp.models.metrics.HARM_TOLERANCE_UM`; load-plateau errors where the campaign has loads;
    * ``campaigns``: per test campaign, its sample count, whether it has loads, and the names of
      the entries worse than uncompensated on some axis.
    """
    machine_given = machine is not None
    machine = resolve_machine(machine)  # a bad description fails here, before any fit
    names = _campaign_names(test)
    refs = [c.aligned(zero_window_s=10.0) for c in test]
    campaign_rows, failures = [], {}
    campaigns = {
        n: {"n_samples": len(a.time_s), "has_loads": a.loads_N is not None, "harmed_by": {}}
        for n, a in zip(names, refs)
    }

    def add_campaign_rows(name, kind, features, per):
        for n, _a in zip(names, refs):
            m, plateau = per[n], per[n].get("static_levels")
            for ax in AXES:
                campaign_rows.append(_campaign_row(n, name, kind, features, ax, m["axes"][ax], plateau))
            harmed = [ax for ax in AXES if m["axes"][ax]["harm"]]
            if harmed:
                campaigns[n]["harmed_by"][name] = harmed

    def judge(predict):
        per, pooled_parts = {}, ([], [], [])
        for c, n, a in zip(test, names, refs):
            pred, half = predict(c, a)
            m = validation_metrics(a.reference_um, pred, half)
            if a.loads_N is not None:
                m["static_levels"] = static_level_metrics(a.loads_N, a.reference_um, pred)
            per[n] = m
            for part, x in zip(pooled_parts, (a.reference_um, pred, half)):
                part.append(x)
        return per, pooled_parts

    per, parts = judge(lambda c, a: (np.zeros_like(a.reference_um), None))
    add_campaign_rows(UNCOMPENSATED, "none", "-", per)
    results = [(UNCOMPENSATED, "none", "-", per, parts)]
    for name, kind, features, options in entries:
        if progress:
            progress(name)
        try:
            model = _make(kind, features, options, machine, machine_given).fit(list(train))
            per, parts = judge(lambda c, a, model=model: model.predict_interval(c))
        except Exception as exc:  # one failing entry must not hide the others
            failures[name] = f"{type(exc).__name__}: {exc}"
            continue
        add_campaign_rows(name, kind, features, per)
        results.append((name, kind, features, per, parts))

    rows = []
    for name, kind, features, per, (r, p, h) in results:
        has_pi = all(x is not None for x in h)
        pooled = validation_metrics(np.vstack(r), np.vstack(p), np.vstack(h) if has_pi else None)
        for a in AXES:
            m = pooled["axes"][a]
            rows.append(
                {
                    "name": name,
                    "model_type": kind,
                    "features": features,
                    "axis": a,
                    "peak_um": m["peak_um"],
                    "max_abs_error_um": m["max_abs_error_um"],
                    "rms_error_um": m["rms_error_um"],
                    "error_pct_of_peak": m["error_pct_of_peak"],
                    "pi95_coverage": m.get("pi95_coverage"),
                    "harm": bool(m["harm"]),
                    "per_campaign": {k: v["axes"][a] for k, v in per.items()},
                }
            )
    ranking = {
        a: [
            r["name"]
            for r in sorted((r for r in rows if r["axis"] == a), key=lambda r: r["max_abs_error_um"])
        ]
        for a in AXES
    }
    return {
        "train": [c.meta.name for c in train],
        "test": names,
        "rows": rows,
        "ranking": ranking,
        "failures": failures,
        "campaigns": campaigns,
        "campaign_rows": campaign_rows,
    }


def _cell(r):
    num = format_number
    cell = f"{num(r['max_abs_error_um'], 2)} ({num(r['rms_error_um'], 2)})"
    return cell + (" WORSE" if r["harm"] else "")


def _plateau_cell(r):
    num = format_number
    if r["plateau_max_error_um"] is None or r["plateau_deflection_um"] is None:
        return "-"
    if r["plateau_deflection_um"] >= PLATEAU_MIN_DEFLECTION_UM:
        return f"{num(r['plateau_max_error_um'], 2)} ({num(r['plateau_error_pct_of_deflection'], 2)} %)"
    return num(r["plateau_max_error_um"], 2)


#: Below this largest plateau deflection an axis is not loaded: its plateau error is given in µm
#: only (a percentage of a few hundredths of a µm says nothing).
PLATEAU_MIN_DEFLECTION_UM = 5.0


def _by_campaign(result):
    out = {}
    for r in result["campaign_rows"]:
        out.setdefault(r["campaign"], {}).setdefault(r["name"], {})[r["axis"]] = r
    return out


def format_campaign_tables(result: dict) -> str:
    """Per held-out campaign: every entry's max |error| (RMS) per axis beside the uncompensated
    row, WORSE where an axis ends worse than uncompensated (+ the harm tolerance)."""
    out = [
        f"per held-out campaign: max |error| µm (RMS µm) per axis; uncompensated = the deviation "
        f"itself; WORSE = max |error| above uncompensated + {HARM_TOLERANCE_UM:g} µm"
    ]
    for camp, models in _by_campaign(result).items():
        info = result["campaigns"][camp]
        out.append(f"\n== {camp} (held out, {info['n_samples']} samples) ==")
        cols = [text("model")] + [Column(a, "µm") for a in AXES] + [Column("PI95 cover dx/dy/dz")]
        rows = []
        for name, axes in models.items():
            covs = [axes[a]["pi95_coverage"] for a in AXES]
            cov = "-" if any(c is None for c in covs) else "/".join(f"{c:.2f}" for c in covs)
            rows.append([name] + [_cell(axes[a]) for a in AXES] + [cov])
        out.append(format_table(cols, rows, indent="  "))
        if info["has_loads"]:
            out.append(
                f"  load-plateau means: max error µm (% of the largest plateau deflection, "
                f"on axes deflected ≥ {PLATEAU_MIN_DEFLECTION_UM:g} µm)"
            )
            out.append(
                format_table(
                    [text("model")] + [Column(a, "µm") for a in AXES],
                    [[name] + [_plateau_cell(axes[a]) for a in AXES] for name, axes in models.items()],
                    indent="  ",
                )
            )
        harmed = info["harmed_by"]
        out.append(
            "  worse than uncompensated: "
            + ("; ".join(f"{n} ({', '.join(ax)})" for n, ax in harmed.items()) if harmed else "none")
        )
    return "\n".join(out)


def format_campaign_markdown(result: dict) -> str:
    """The per-campaign tables as Markdown (docs/accuracy.md)."""
    out = []
    for camp, models in _by_campaign(result).items():
        info = result["campaigns"][camp]
        legend = "max \\|error\\| µm (RMS µm); **worse** = above uncompensated + 0.5 µm"
        if info["has_loads"]:
            legend += (
                f"; plateau = largest error of the load-plateau means, µm (% of the largest plateau "
                f"deflection on axes deflected ≥ {PLATEAU_MIN_DEFLECTION_UM:g} µm)"
            )
        out.append(f"**{camp}** ({info['n_samples']} samples): {legend}\n")
        head = "| model | dx | dy | dz | PI95 dx/dy/dz |"
        if info["has_loads"]:
            head += " plateau dx | plateau dy | plateau dz |"
        out.append(head)
        out.append("|" + "---|" * (head.count("|") - 1))
        for name, axes in models.items():
            cells = [_cell(axes[a]).replace(" WORSE", " **worse**") for a in AXES]
            cov = [axes[a]["pi95_coverage"] for a in AXES]
            cells.append("-" if any(c is None for c in cov) else "/".join(f"{c:.2f}" for c in cov))
            if info["has_loads"]:
                cells += [_plateau_cell(axes[a]) for a in AXES]
            out.append(f"| {name} | " + " | ".join(cells) + " |")
        out.append("")
    return "\n".join(out)


def format_comparison(result: dict) -> str:
    """The pooled comparison as text: one table per axis, entries ranked by max |error|."""
    out = [f"trained on {', '.join(result['train'])}; judged on {', '.join(result['test'])}", ""]
    if result.get("campaign_rows"):
        out += [format_campaign_tables(result), "", "pooled over all held-out campaigns, ranked per axis:"]
    for a in AXES:
        rows = sorted((r for r in result["rows"] if r["axis"] == a), key=lambda r: r["max_abs_error_um"])
        if not rows:
            continue
        out.append(f"\n== {a} (peak {format_number(rows[0]['peak_um'])} µm) ==")
        cols = [
            Column("rank"),
            text("model"),
            Column("max|err|", "µm"),
            Column("RMS", "µm"),
            Column("max err", "% of peak", 2),
            Column("PI95 cover", "", 3),
        ]
        out.append(
            format_table(
                cols,
                [
                    [
                        i,
                        r["name"],
                        r["max_abs_error_um"],
                        r["rms_error_um"],
                        r["error_pct_of_peak"],
                        "-" if r["pi95_coverage"] is None else r["pi95_coverage"],
                    ]
                    + (["WORSE"] if r.get("harm") else [])
                    for i, r in enumerate(rows, 1)
                ],
            )
        )
    for name, why in result.get("failures", {}).items():
        out.append(f"failed: {name}: {why}")
    return "\n".join(out)


POOLED_COLUMNS = [
    "axis",
    "rank",
    "name",
    "model_type",
    "features",
    "max_abs_error_um",
    "rms_error_um",
    "error_pct_of_peak",
    "peak_um",
    "pi95_coverage",
    "harm",
]
CAMPAIGN_COLUMNS = [
    "campaign",
    "axis",
    "rank",
    "name",
    "model_type",
    "features",
    "max_abs_error_um",
    "rms_error_um",
    "uncompensated_max_um",
    "uncompensated_rms_um",
    "harm",
    "error_pct_of_peak",
    "pi95_coverage",
    "plateau_max_error_um",
    "plateau_deflection_um",
    "plateau_error_pct_of_deflection",
]


def _csv_text(rows, cols) -> str:
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=cols, extrasaction="ignore")
    w.writeheader()
    for r in rows:
        # undefined numbers (None, NaN) as empty cells, as in the JSON's null
        w.writerow({k: ("" if v is None else v) for k, v in json_safe(r).items()})
    return buf.getvalue()


def ranked_rows(result: dict):
    """Pooled rows ranked per axis by max |error| (the CSV's order), with ``rank``."""
    out = []
    for a in AXES:
        rows = sorted((r for r in result["rows"] if r["axis"] == a), key=lambda r: r["max_abs_error_um"])
        out += [{**r, "rank": i} for i, r in enumerate(rows, 1)]
    return out


def ranked_campaign_rows(result: dict):
    """Per-campaign rows in campaign, axis order, each ranked by max |error| (uncompensated included)."""
    out = []
    for camp in result.get("test", []):
        for a in AXES:
            rows = [r for r in result.get("campaign_rows", []) if r["campaign"] == camp and r["axis"] == a]
            order = sorted(range(len(rows)), key=lambda i: rows[i]["max_abs_error_um"])
            rank = {i: k for k, i in enumerate(order, 1)}
            out += [{**r, "rank": rank[i]} for i, r in enumerate(rows)]
    return out


def default_campaign_csv(csv_path) -> Path:
    """``comparison.csv`` → ``comparison_by_campaign.csv`` (beside it)."""
    p = Path(csv_path)
    return p.with_name(f"{p.stem}_by_campaign{p.suffix or '.csv'}")


def write_comparison(result: dict, csv_path=None, json_path=None, campaign_csv_path=None, markdown_path=None):
    """Pooled ranking (CSV), per-campaign table (CSV), everything (JSON), per-campaign Markdown.

    Every file is written atomically; the CSVs hold the same rows (and ranks) as the JSON's
    ``rows`` and ``campaign_rows``, undefined numbers as empty cells (null in the JSON).
    """
    texts = []
    if csv_path is not None:
        texts.append((csv_path, _csv_text(ranked_rows(result), POOLED_COLUMNS)))
    if campaign_csv_path is not None:
        texts.append((campaign_csv_path, _csv_text(ranked_campaign_rows(result), CAMPAIGN_COLUMNS)))
    if markdown_path is not None:
        texts.append((markdown_path, format_campaign_markdown(result)))
    # everything is rendered before the first file is replaced: a failure leaves the old set whole
    if json_path is not None:
        write_json(
            json_path, {**result, "rows": ranked_rows(result), "campaign_rows": ranked_campaign_rows(result)}
        )
    for path, body in texts:
        write_bytes(path, body.encode("utf-8"))
