"""Stepwise selection: fbgcomp vs. the Gram/Cholesky recipe and vs. statsmodels, side by side.

Design: N rows (default 10^6, then 10^5) of 5 FBG elongations (µm) and 3 temperature features
(K), and every square and pairwise product of those 8: 8 + 36 = 44 candidate terms plus the
constant (always in the model). The TTP deviation (µm) is a known combination of 10 of the terms
plus noise.

* fbgcomp: accumulate the factor once (:class:`fbgcomp.models.regression.QRAccumulator`, 100 000-row
  chunks, as a stream would arrive), then :func:`fbgcomp.models.regression.stepwise` (direction
  "both", naive partial F tests), which never touches the rows again. The timing includes the
  accumulation.
* the Gram/Cholesky recipe (the fair baseline, issue 16): form X'X, X'y and y'y once, then take
  a Cholesky of the sub-Gram of every candidate model and apply the same rules (enter the
  largest partial F while p < p_enter, after each entry remove the smallest while
  p > p_remove, never revisit a model).
* statsmodels, the recipe most users start from: the same search, every candidate model
  refitted with ``sm.OLS(y, X[:, cols]).fit()``.

fbgcomp and the Gram recipe run interleaved (the order alternating), ``--runs`` times per size;
statsmodels ``--sm-runs`` times (it takes minutes at 10^6 rows). Medians, the load average and
the ratios (baseline time / fbgcomp time; targets >= 1.0x Gram, >= 50x statsmodels) are printed;
all three must select the same terms with coefficients equal to 1e-8 relative. Last line: one
JSON object. Both sides use the naive i.i.d. partial F test (fbgcomp: ``cov_type="nonrobust"``),
although fbgcomp's MRA model defaults to Newey-West (HAC) tests.

    python benchmarks/bench_stepwise.py [--rows 1000000 100000] [--runs 5] [--sm-runs 1]

``--ram2 DIR`` instead prints the before/after table of docs/models.md (issue 12): the paper's
MRA model (eq13, stepwise) fitted on DIR/thermal_a + DIR/static_xyz with naive and with HAC
inference, judged on thermal_b, thermal_c and static_x (terms, max |error|, PI95 coverage).

    python benchmarks/bench_stepwise.py --ram2 ../shared/reference/ram2/data
"""

from __future__ import annotations

import os

# Same rule as bench_fit.py: single-threaded BLAS on a shared machine, for both contenders.
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import json  # noqa: E402
import platform  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from itertools import combinations_with_replacement  # noqa: E402

import numpy as np  # noqa: E402

from fbgcomp.models.features import design_matrix, term_name  # noqa: E402
from fbgcomp.models.regression import QRAccumulator, stepwise  # noqa: E402

BASE = [f"dL_S{i}" for i in range(1, 6)] + ["dT_bulk", "dT_surf", "dT_flange"]
TRUTH = {
    "const": 0.3,
    "dL_S1": 0.40,
    "dL_S2": -0.35,
    "dL_S4": 0.25,
    "dT_bulk": 1.5,
    "dT_surf": -2.0,
    "dT_bulk^2": 0.08,
    "dL_S1*dT_bulk": 0.01,
    "dL_S3^2": 0.002,
    "dT_surf*dT_flange": -0.15,
}


def make_data(n_rows: int, seed: int):
    rng = np.random.default_rng(seed)
    t = np.linspace(0.0, 36 * 3600.0, n_rows)
    base = np.empty((n_rows, len(BASE)))
    for j in range(len(BASE)):
        amp = 20.0 if j < 5 else 1.5
        period = rng.uniform(2000.0, 20000.0, size=3)
        phase = rng.uniform(0, 2 * np.pi, size=3)
        base[:, j] = amp * sum(np.sin(2 * np.pi * t / p + f) for p, f in zip(period, phase)) / 3
        base[:, j] += 0.05 * amp * rng.standard_normal(n_rows)
    terms = BASE + [term_name(p) for p in combinations_with_replacement(BASE, 2)]
    X = design_matrix(base, BASE, terms)
    names = ["const", *terms]
    beta = np.array([TRUTH.get(n, 0.0) for n in names])
    y = X @ beta + 0.5 * rng.standard_normal(n_rows)
    return X, y, names


def fbgcomp_stepwise(X, y, names, p_enter, p_remove):
    acc = QRAccumulator(X.shape[1], 1, feature_names=names, target_names=["dx"])
    for lo in range(0, len(X), 100_000):
        acc.update(X[lo : lo + 100_000], y[lo : lo + 100_000])
    sw = stepwise(
        acc, include=["const"], direction="both", p_enter=p_enter, p_remove=p_remove, cov_type="nonrobust"
    )
    path = "double-double" if acc.extended_ else "gram" if getattr(acc, "gram_rows_", 0) else "qr"
    return sw.selected, np.asarray(sw.result.params), len(sw.history), path


def _search(n_cand, p_enter, p_remove, df_of, fit):
    """The stepwise rules of fbgcomp.models.regression.stepwise (direction "both", constant forced):
    enter the candidate of largest partial F while p < p_enter, after each entry remove the term
    of smallest partial F while p > p_remove, never revisit a model. ``fit(cols)`` returns
    (ssr, params) or None when the sub-model is (numerically) singular."""
    from scipy import stats

    def partial_f(ssr_small, ssr_big, df_big):
        f = max(ssr_small - ssr_big, 0.0) / (ssr_big / df_big)
        return f, float(stats.f.sf(f, 1, df_big))

    model: list[int] = []
    visited = {frozenset(model)}
    current = fit([0])
    steps = 0
    while True:
        best = None
        df_big = df_of(len(model) + 2)
        for c in range(1, n_cand + 1):
            if c in model or frozenset([*model, c]) in visited:
                continue
            big = fit([0, *model, c])
            if big is None:
                continue
            f, p = partial_f(current[0], big[0], df_big)
            if best is None or f > best[1]:
                best = (c, f, p, big)
        if best is None or not best[2] < p_enter:
            break
        model.append(best[0])
        visited.add(frozenset(model))
        current = best[3]
        steps += 1
        while model:
            worst = None
            df_big = df_of(len(model) + 1)
            for c in model:
                rest = [d for d in model if d != c]
                if frozenset(rest) in visited:
                    continue
                small = fit([0, *rest])
                f, p = partial_f(small[0], current[0], df_big)
                if worst is None or f < worst[1]:
                    worst = (c, f, p, small)
            if worst is None or not worst[2] > p_remove:
                break
            model.remove(worst[0])
            visited.add(frozenset(model))
            current = worst[3]
            steps += 1
    return sorted([0, *model]), current, steps


def gram_stepwise(X, y, names, p_enter, p_remove):
    """The standard recipe: X'X, X'y and y'y formed once, then a Cholesky of the sub-Gram of
    every candidate model (scipy cho_factor / cho_solve), SSR = y'y - b'X'y."""
    from scipy import linalg

    n = X.shape[0]
    G = X.T @ X
    g = X.T @ y
    yy = float(y @ y)
    fits = {"n": 0}

    def fit(cols):
        fits["n"] += 1
        idx = sorted(cols)
        try:
            factor = linalg.cho_factor(G[np.ix_(idx, idx)], check_finite=False)
        except linalg.LinAlgError:
            return None
        beta = linalg.cho_solve(factor, g[idx], check_finite=False)
        return yy - float(g[idx] @ beta), beta

    cols, (_, params), steps = _search(X.shape[1] - 1, p_enter, p_remove, lambda m: n - m, fit)
    return [names[c] for c in cols], np.asarray(params), steps, fits["n"]


def statsmodels_stepwise(X, y, names, p_enter, p_remove):
    """What most users start from: refit ``sm.OLS(y, X[:, cols])`` for every candidate model."""
    import statsmodels.api as sm

    n = X.shape[0]
    fits = {"n": 0}

    def fit(cols):
        fits["n"] += 1
        res = sm.OLS(y, X[:, sorted(cols)]).fit()
        return float(res.ssr), np.asarray(res.params)

    cols, (_, params), steps = _search(X.shape[1] - 1, p_enter, p_remove, lambda m: n - m, fit)
    return [names[c] for c in cols], np.asarray(params), steps, fits["n"]


def _timed(fn, *args):
    t0, c0 = time.perf_counter(), time.process_time()
    out = fn(*args)
    return out, time.perf_counter() - t0, time.process_time() - c0


def _rel_diff(a, b) -> float:
    return float(np.max(np.abs(np.asarray(a) - np.asarray(b)) / np.abs(np.asarray(b))))


def bench_size(n_rows, args) -> dict:
    X, y, names = make_data(n_rows, args.seed)
    rules = (names, args.p_enter, args.p_remove)
    print(f"\n== {n_rows} rows, {X.shape[1] - 1} candidate terms + const; load average {_load()}")
    runs = {"fbgcomp": [], "gram": [], "statsmodels": []}
    out = {}
    for r in range(args.runs):
        # Interleaved A/B, the order alternating run by run so neither side always goes first.
        order = ["fbgcomp", "gram"] if r % 2 == 0 else ["gram", "fbgcomp"]
        if r < args.sm_runs:
            order.append("statsmodels")
        for who in order:
            fn = {"fbgcomp": fbgcomp_stepwise, "gram": gram_stepwise, "statsmodels": statsmodels_stepwise}[
                who
            ]
            out[who], wall, cpu = _timed(fn, X, y, *rules)
            runs[who].append((wall, cpu))
        print(
            f"  run {r + 1}: "
            + ", ".join(f"{w} {runs[w][-1][0]:.3f} s" for w in order)
            + f"  (load {_load()})"
        )
        sys.stdout.flush()
    med = {
        w: (float(np.median([t[0] for t in v])), float(np.median([t[1] for t in v])))
        for w, v in runs.items()
        if v
    }
    sel_f, par_f, steps_f, path = out["fbgcomp"]
    sel_g, par_g, _steps_g, fits_g = out["gram"]
    print(
        f"  fbgcomp (one pass, {path} data path, then stepwise on the factor): "
        f"median {med['fbgcomp'][0]:.3f} s wall / {med['fbgcomp'][1]:.3f} s CPU of "
        f"{len(runs['fbgcomp'])}; {steps_f} steps, {len(sel_f)} terms"
    )
    print(
        f"  Gram/Cholesky recipe (X'X once, {fits_g} sub-Gram Choleskys): median "
        f"{med['gram'][0]:.3f} s wall / {med['gram'][1]:.3f} s CPU of {len(runs['gram'])}"
    )
    res = {
        "rows": n_rows,
        "candidates": X.shape[1] - 1,
        "runs": args.runs,
        "fbgcomp_path": path,
        "fbgcomp_s": round(med["fbgcomp"][0], 4),
        "gram_s": round(med["gram"][0], 4),
        "fbgcomp_cpu_s": round(med["fbgcomp"][1], 4),
        "gram_cpu_s": round(med["gram"][1], 4),
        "steps": steps_f,
        "terms": len(sel_f),
        "same_terms_gram": sel_f == sel_g,
        "max_rel_coef_diff_gram": _rel_diff(par_f, par_g) if sel_f == sel_g else None,
        "ratio_gram": round(med["gram"][0] / med["fbgcomp"][0], 2),
        "cpu_ratio_gram": round(med["gram"][1] / med["fbgcomp"][1], 2),
    }
    if runs["statsmodels"]:
        sel_s, par_s, _, fits_s = out["statsmodels"]
        print(
            f"  statsmodels (sm.OLS refit per candidate, {fits_s} fits): median "
            f"{med['statsmodels'][0]:.3f} s wall / {med['statsmodels'][1]:.3f} s CPU of "
            f"{len(runs['statsmodels'])}"
        )
        res.update(
            {
                "statsmodels_s": round(med["statsmodels"][0], 3),
                "statsmodels_cpu_s": round(med["statsmodels"][1], 3),
                "same_terms_statsmodels": sel_f == sel_s,
                "max_rel_coef_diff_statsmodels": (_rel_diff(par_f, par_s) if sel_f == sel_s else None),
                "ratio_statsmodels": round(med["statsmodels"][0] / med["fbgcomp"][0], 1),
                "cpu_ratio_statsmodels": round(med["statsmodels"][1] / med["fbgcomp"][1], 1),
            }
        )
    print(
        f"  selected terms identical to the Gram recipe: {res['same_terms_gram']}"
        + (f", to statsmodels: {res['same_terms_statsmodels']}" if runs["statsmodels"] else "")
        + f" ({', '.join(sel_f)})"
    )
    print(
        f"  max relative coefficient difference: vs Gram recipe "
        f"{res['max_rel_coef_diff_gram']!s}"
        + (f", vs statsmodels {res['max_rel_coef_diff_statsmodels']!s}" if runs["statsmodels"] else "")
        + " (must be <= 1e-8)"
    )
    print(
        f"  ratio (baseline time / fbgcomp time): Gram recipe {res['ratio_gram']:.2f}x wall, "
        f"{res['cpu_ratio_gram']:.2f}x CPU (target >= 1.0x)"
        + (
            f"; statsmodels {res['ratio_statsmodels']:.1f}x wall, "
            f"{res['cpu_ratio_statsmodels']:.1f}x CPU (target >= 50x)"
            if runs["statsmodels"]
            else ""
        )
    )
    ok = (
        res["same_terms_gram"]
        and res["max_rel_coef_diff_gram"] is not None
        and res["max_rel_coef_diff_gram"] <= 1e-8
    )
    if runs["statsmodels"]:
        ok = (
            ok
            and res["same_terms_statsmodels"]
            and res["max_rel_coef_diff_statsmodels"] is not None
            and res["max_rel_coef_diff_statsmodels"] <= 1e-8
        )
    res["ok"] = bool(ok)
    res["load_average_after"] = _load()
    return res


def _load() -> str:
    try:
        return " ".join(f"{v:.2f}" for v in os.getloadavg())
    except OSError:
        return "n/a"


def ram2_before_after(root: str) -> int:
    """Naive vs HAC stepwise of the paper's MRA model on ram2: one table per inference."""
    from pathlib import Path

    from fbgcomp.io.campaign import read_campaign
    from fbgcomp.models.metrics import validation_metrics
    from fbgcomp.models.mra import MRAModel
    from fbgcomp.units import AXES

    root = Path(root)
    train = [read_campaign(root / "thermal_a"), read_campaign(root / "static_xyz")]
    tests = {name: read_campaign(root / name) for name in ("thermal_b", "thermal_c", "static_x")}
    print("MRA eq13 stepwise, fit on thermal_a + static_xyz (balanced), held out: " + ", ".join(tests))
    for cov_type in ("nonrobust", "HAC"):
        model = MRAModel(features="eq13", stepwise=True, cov_type=cov_type).fit(train)
        print(f"\n== cov_type={cov_type}")
        for a in AXES:
            fit = model.axes_[a]
            extra = (
                f"  [{fit.hac['maxlags']} lags, lag-1 rho {fit.hac['rho1']:.3f}, "
                f"n_eff {fit.hac['n_eff']:.0f} of {fit.nobs}]"
                if fit.cov_type == "HAC"
                else ""
            )
            print(f"  {a}: {len(fit.terms) - 1} terms: {' '.join(fit.terms[1:])}{extra}")
        print(f"  {'campaign':<10}" + "".join(f"{a + ' max|err|':>14}{a + ' PI95':>9}" for a in AXES))
        for name, camp in tests.items():
            aligned = camp.aligned(zero_window_s=model.zero_window_s)
            pred, half = model.predict_interval(camp)
            m = validation_metrics(aligned.reference_um, pred, half)["axes"]
            print(
                f"  {name:<10}"
                + "".join(f"{m[a]['max_abs_error_um']:>14.2f}{m[a]['pi95_coverage']:>9.3f}" for a in AXES)
            )
    return 0


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--ram2", metavar="DIR", help="print the naive vs HAC table on ram2 instead")
    ap.add_argument("--rows", type=int, nargs="+", default=[1_000_000, 100_000])
    ap.add_argument(
        "--runs",
        type=int,
        default=5,
        help="interleaved runs of fbgcomp and the Gram recipe per size (median reported)",
    )
    ap.add_argument(
        "--sm-runs",
        type=int,
        default=1,
        help="statsmodels runs per size (it takes minutes at 10^6 rows; 0 skips it)",
    )
    ap.add_argument("--p-enter", type=float, default=0.05)
    ap.add_argument("--p-remove", type=float, default=0.10)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    if args.ram2:
        return ram2_before_after(args.ram2)
    import scipy
    import statsmodels

    print(
        f"stepwise 'both', p_enter {args.p_enter}, p_remove {args.p_remove}; Python "
        f"{platform.python_version()}, numpy {np.__version__}, scipy {scipy.__version__}, "
        f"statsmodels {statsmodels.__version__}, {os.cpu_count()} cores, "
        f"OPENBLAS_NUM_THREADS={os.environ.get('OPENBLAS_NUM_THREADS')}"
    )
    results = [bench_size(n, args) for n in args.rows]
    ok = all(r["ok"] for r in results)
    print(json.dumps({"bench": "stepwise", "sizes": results, "ok": ok}))
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
