"""Cross-campaign comparison of every model type and feature set (``fbgcomp compare``).

Each entry is fitted on the training campaigns and judged on the test campaigns it never saw
(pooled samples): per axis max |error| µm, RMS µm, max error as % of the peak, and the 95 %
interval coverage where the entry gives intervals. The table is ranked per axis by max |error|
and written as CSV and JSON (atomically).

Entries: ``mra`` with eq11, eq13, eq12 and eq13 stepwise; ``ridge`` and ``pls`` (partial least
squares) on eq13, both with their complexity (ridge penalty, number of PLS components) chosen by
blocked cross-validation over contiguous time blocks of the training data (autocorrelated
samples make random folds optimistic); ``dynamic`` (eq13 + first-order filtered temperatures);
``kinematic`` (fit-free chain); ``hybrid`` (kinematic + regression, eq13 and dynamic);
``calibrated`` (hybrid with the closure's compliances fitted on the training load plateaus).
"""

from __future__ import annotations

import csv
import io
import os
import tempfile
from pathlib import Path

import numpy as np

from .metrics import validation_metrics
from .atomic import write_json
from .models import AXES, MRAModel

#: (name, model type, feature set, options)
ENTRIES = (
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


def ridge_fit(X, Y, w=None, lambdas=np.logspace(-6, 2, 17)):
    """Weighted ridge on standardised columns (the constant unpenalised), penalty by blocked CV.

    ``X`` (n, 1 + p) with the constant first, ``Y`` (n, 3), ``w`` (n,) row weights.
    Returns (coef (1 + p, 3), lambda (3,)).
    """
    w_all = np.ones(len(X)) if w is None else np.asarray(w, dtype=float)

    def solve(Xs, Ys, lam, ws):
        mu, sd = _standardise(Xs, ws)
        Z = (Xs[:, 1:] - mu) / sd
        ym = np.average(Ys, axis=0, weights=ws)
        A = (Z * ws[:, None]).T @ Z + lam * ws.sum() * np.eye(Z.shape[1])
        b = np.linalg.solve(A, (Z * ws[:, None]).T @ (Ys - ym))
        coef = np.vstack([ym - (mu / sd) @ b, b / sd[:, None]])
        return coef

    folds = _blocks(len(X))
    err = np.zeros((len(lambdas), Y.shape[1]))
    for i, lam in enumerate(lambdas):
        for f in folds:
            train = np.setdiff1d(np.arange(len(X)), f)
            c = solve(X[train], Y[train], lam, w_all[train])
            err[i] += np.sum(w_all[f, None] * (X[f] @ c - Y[f]) ** 2, axis=0)
    best = np.argmin(err, axis=0)
    coef = np.column_stack([solve(X, Y[:, [j]], lambdas[best[j]], w_all)[:, 0]
                            for j in range(Y.shape[1])])
    return coef, lambdas[best]


def pls_fit(X, Y, w=None, max_components=None):
    """Weighted PLS1 (NIPALS) per axis on standardised columns, components by blocked CV.

    Returns (coef (1 + p, 3), n_components (3,)).
    """
    p = X.shape[1] - 1
    max_components = min(p, max_components or p)
    w_all = np.ones(len(X)) if w is None else np.asarray(w, dtype=float)

    def solve(Xs, ys, k, ws):
        mu, sd = _standardise(Xs, ws)
        r = np.sqrt(ws)
        # Weighted least squares = ordinary on rows scaled by sqrt(weight), after weighted centring.
        Z = (Xs[:, 1:] - mu) / sd * r[:, None]
        ym = np.average(ys, weights=ws)
        E, f = Z.copy(), (ys - ym) * r
        W, P, q = [], [], []
        for _ in range(k):
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
        if not W:
            return np.concatenate([[ym], np.zeros(p)])
        W, P, q = np.array(W).T, np.array(P).T, np.array(q)
        b = W @ np.linalg.solve(P.T @ W, q)
        return np.concatenate([[ym - (mu / sd) @ b], b / sd])

    folds = _blocks(len(X))
    coefs, ncomp = [], []
    for j in range(Y.shape[1]):
        err = np.zeros(max_components)
        for k in range(1, max_components + 1):
            for f in folds:
                train = np.setdiff1d(np.arange(len(X)), f)
                c = solve(X[train], Y[train, j], k, w_all[train])
                err[k - 1] += np.sum(w_all[f] * (X[f] @ c - Y[f, j]) ** 2)
        k = int(np.argmin(err)) + 1
        coefs.append(solve(X, Y[:, j], k, w_all))
        ncomp.append(k)
    return np.column_stack(coefs), np.array(ncomp)


class _DesignModel:
    """Ridge or PLS on the eq. 13 design (comparison only; no model file)."""

    def __init__(self, kind, features="eq13", zero_window_s=10.0):
        self.kind, self.features, self.zero_window_s = kind, features, zero_window_s

    def fit(self, campaigns):
        self._mra = MRAModel(features=self.features, zero_window_s=self.zero_window_s, fallbacks="none")
        self._mra.new_accumulator(list(campaigns[0].meta.sensors), None)
        from .models import campaign_weights_for

        X, Y = [], []
        aligned = [c.aligned(zero_window_s=self.zero_window_s) for c in campaigns]
        # Campaigns pooled like MRAModel.fit (balanced row weights, weighted least squares).
        weights = campaign_weights_for([len(a.time_s) for a in aligned], "balanced")
        W = []
        for c, a, w in zip(campaigns, aligned, weights):
            X.append(self._mra._campaign_design(c, a))
            Y.append(a.reference_um)
            W.append(np.full(len(a.time_s), w))
        X, Y, W = np.vstack(X), np.vstack(Y), np.concatenate(W)
        if self.kind == "ridge":
            self.coef_, self.complexity_ = ridge_fit(X, Y, W)
        else:
            self.coef_, self.complexity_ = pls_fit(X, Y, W)
        return self

    def predict_interval(self, campaign):
        a = campaign.aligned(zero_window_s=self.zero_window_s)
        return self._mra._campaign_design(campaign, a) @ self.coef_, None


# ---------------------------------------------------------------------------- comparison
def _make(kind, features, options, machine):
    from .model_types import CalibratedModel, DynamicModel, HybridModel, KinematicModel

    if kind == "mra":
        return MRAModel(features=features, fallbacks="none", **options)
    if kind in ("ridge", "pls"):
        return _DesignModel(kind, features)
    if kind == "dynamic":
        return DynamicModel(fallbacks="none", **options)
    if kind == "kinematic":
        return KinematicModel(machine, fallbacks="none")
    if kind == "hybrid":
        return HybridModel(machine, features=features, fallbacks="none", **options)
    if kind == "calibrated":
        return CalibratedModel(machine, features=features, fallbacks="none", **options)
    raise ValueError(kind)


def compare(train, test, *, machine=None, entries=ENTRIES, progress=None) -> dict:
    """Fit every entry on ``train`` campaigns, judge on ``test`` campaigns.

    Returns ``{"train": [...], "test": [...], "rows": [...], "ranking": {axis: [names]}}``;
    each row has name, model type, features, axis, max_abs_error_um, rms_error_um,
    error_pct_of_peak, peak_um, pi95_coverage (or None), and per-campaign metrics.
    """
    rows, failures = [], {}
    for name, kind, features, options in entries:
        if progress:
            progress(name)
        try:
            model = _make(kind, features, options, machine).fit(list(train))
        except Exception as exc:        # one failing entry must not hide the others
            failures[name] = f"{type(exc).__name__}: {exc}"
            continue
        refs, preds, halves, per = [], [], [], {}
        for c in test:
            pred, half = model.predict_interval(c)
            ref = c.aligned(zero_window_s=10.0).reference_um
            per[c.meta.name] = validation_metrics(ref, pred, half)
            refs.append(ref), preds.append(pred), halves.append(half)
        has_pi = all(h is not None for h in halves)
        pooled = validation_metrics(np.vstack(refs), np.vstack(preds),
                                    np.vstack(halves) if has_pi else None)
        for a in AXES:
            m = pooled["axes"][a]
            rows.append({"name": name, "model_type": kind, "features": features, "axis": a,
                         "peak_um": m["peak_um"], "max_abs_error_um": m["max_abs_error_um"],
                         "rms_error_um": m["rms_error_um"], "error_pct_of_peak": m["error_pct_of_peak"],
                         "pi95_coverage": m.get("pi95_coverage"),
                         "per_campaign": {k: v["axes"][a] for k, v in per.items()}})
    ranking = {a: [r["name"] for r in sorted((r for r in rows if r["axis"] == a),
                                             key=lambda r: r["max_abs_error_um"])] for a in AXES}
    return {"train": [c.meta.name for c in train], "test": [c.meta.name for c in test],
            "rows": rows, "ranking": ranking, "failures": failures}


def format_comparison(result: dict) -> str:
    out = [f"trained on {', '.join(result['train'])}; judged on {', '.join(result['test'])}"]
    for a in AXES:
        rows = sorted((r for r in result["rows"] if r["axis"] == a), key=lambda r: r["max_abs_error_um"])
        if not rows:
            continue
        out.append(f"\n== {a} (peak {rows[0]['peak_um']:.3f} µm) ==")
        out.append(f"{'rank':>4}  {'model':<20}{'max|err| µm':>12}{'RMS µm':>10}{'% of peak':>11}{'PI95 cover':>11}")
        for i, r in enumerate(rows, 1):
            cov = "-" if r["pi95_coverage"] is None else f"{r['pi95_coverage']:.3f}"
            out.append(f"{i:>4}  {r['name']:<20}{r['max_abs_error_um']:>12.3f}{r['rms_error_um']:>10.3f}"
                       f"{r['error_pct_of_peak']:>11.2f}{cov:>11}")
    for name, why in result.get("failures", {}).items():
        out.append(f"failed: {name}: {why}")
    return "\n".join(out)


def write_comparison(result: dict, csv_path=None, json_path=None):
    """CSV (one row per entry and axis, ranked) and JSON (everything), written atomically."""
    if json_path is not None:
        write_json(json_path, result)
    if csv_path is not None:
        buf = io.StringIO()
        cols = ["axis", "rank", "name", "model_type", "features", "max_abs_error_um", "rms_error_um",
                "error_pct_of_peak", "peak_um", "pi95_coverage"]
        w = csv.DictWriter(buf, fieldnames=cols, extrasaction="ignore")
        w.writeheader()
        for a in AXES:
            rows = sorted((r for r in result["rows"] if r["axis"] == a), key=lambda r: r["max_abs_error_um"])
            for i, r in enumerate(rows, 1):
                w.writerow({**r, "rank": i, "pi95_coverage": "" if r["pi95_coverage"] is None else r["pi95_coverage"]})
        path = Path(csv_path)
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
        try:
            with os.fdopen(fd, "w", encoding="utf-8", newline="") as fh:
                fh.write(buf.getvalue())
            os.replace(tmp, path)
        except BaseException:
            Path(tmp).unlink(missing_ok=True)
            raise


