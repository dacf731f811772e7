"""Stepwise selection from the streamed QR factor vs. refitting statsmodels OLS per candidate.

Design: N rows (default 10^6) of 5 FBG elongations (µm) and 3 temperature features (K), and
every square and pairwise product of those 8: 8 + 36 = 44 candidate terms plus the constant
(always in the model). The TTP deviation (µm) is a known combination of 10 of the terms plus
noise.

* fbgcomp: accumulate the factor once (:class:`fbgcomp.regression.QRAccumulator`, 100 000-row
  chunks), then :func:`fbgcomp.regression.stepwise` (direction "both", partial F tests), which
  never touches the rows again. The timing includes the accumulation.
* the usual recipe: the same algorithm (forward entry of the candidate with the largest partial
  F while p < p_enter, then removal of the term with the smallest partial F while p > p_remove,
  never revisiting a model), every candidate model refitted with
  ``sm.OLS(y, X[:, cols]).fit()`` and compared with ``compare_f_test``.

Both must select the same terms and the same coefficients (1e-8 relative); the script prints
both times and the ratio (target >= 50x), then one JSON line. Both use the naive i.i.d. partial
F test (fbgcomp: ``cov_type="nonrobust"``, an accumulator without lag statistics), which is
what statsmodels' ``compare_f_test`` computes: the comparison stays apples to apples although
fbgcomp's MRA model now defaults to Newey-West (HAC) tests.

    python benchmarks/bench_stepwise.py [--rows 1000000] [--p-enter 0.05] [--p-remove 0.10]

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

from fbgcomp.features import design_matrix, term_name  # noqa: E402
from fbgcomp.regression import QRAccumulator, stepwise  # noqa: E402

BASE = [f"dL_S{i}" for i in range(1, 6)] + ["dT_bulk", "dT_surf", "dT_flange"]
TRUTH = {"const": 0.3, "dL_S1": 0.40, "dL_S2": -0.35, "dL_S4": 0.25, "dT_bulk": 1.5,
         "dT_surf": -2.0, "dT_bulk^2": 0.08, "dL_S1*dT_bulk": 0.01, "dL_S3^2": 0.002,
         "dT_surf*dT_flange": -0.15}


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
    names = ["const"] + terms
    beta = np.array([TRUTH.get(n, 0.0) for n in names])
    y = X @ beta + 0.5 * rng.standard_normal(n_rows)
    return X, y, names


def fbgcomp_stepwise(X, y, names, p_enter, p_remove):
    acc = QRAccumulator(X.shape[1], 1, feature_names=names, target_names=["dx"])
    for lo in range(0, len(X), 100_000):
        acc.update(X[lo:lo + 100_000], y[lo:lo + 100_000])
    sw = stepwise(acc, include=["const"], direction="both", p_enter=p_enter, p_remove=p_remove,
                  cov_type="nonrobust")
    return sw.selected, sw.result.params, len(sw.history), acc.extended_


def statsmodels_stepwise(X, y, names, p_enter, p_remove):
    import statsmodels.api as sm

    fits = {"n": 0}

    def fit(cols):
        fits["n"] += 1
        return sm.OLS(y, X[:, sorted(cols)]).fit()

    const = 0
    cand = list(range(1, X.shape[1]))
    model: list[int] = []
    visited = {frozenset(model)}
    steps = 0
    current = fit([const])
    while True:
        best = None
        for c in cand:
            if c in model or frozenset(model + [c]) in visited:
                continue
            big = fit([const] + model + [c])
            f, p, _ = big.compare_f_test(current)
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
            for c in model:
                rest = [d for d in model if d != c]
                if frozenset(rest) in visited:
                    continue
                small = fit([const] + rest)
                f, p, _ = current.compare_f_test(small)
                if worst is None or f < worst[1]:
                    worst = (c, f, p, small)
            if worst is None or not worst[2] > p_remove:
                break
            model.remove(worst[0])
            visited.add(frozenset(model))
            current = worst[3]
            steps += 1
    cols = sorted([const] + model)
    return [names[c] for c in cols], np.asarray(current.params), steps, fits["n"]


def ram2_before_after(root: str) -> int:
    """Naive vs HAC stepwise of the paper's MRA model on ram2: one table per inference."""
    from pathlib import Path

    from fbgcomp.campaign import read_campaign
    from fbgcomp.metrics import validation_metrics
    from fbgcomp.models import AXES, MRAModel

    root = Path(root)
    train = [read_campaign(root / "thermal_a"), read_campaign(root / "static_xyz")]
    tests = {name: read_campaign(root / name) for name in ("thermal_b", "thermal_c", "static_x")}
    print("MRA eq13 stepwise, fit on thermal_a + static_xyz (balanced), held out: "
          + ", ".join(tests))
    for cov_type in ("nonrobust", "HAC"):
        model = MRAModel(features="eq13", stepwise=True, cov_type=cov_type).fit(train)
        print(f"\n== cov_type={cov_type}")
        for a in AXES:
            fit = model.axes_[a]
            extra = (f"  [{fit.hac['maxlags']} lags, lag-1 rho {fit.hac['rho1']:.3f}, "
                     f"n_eff {fit.hac['n_eff']:.0f} of {fit.nobs}]" if fit.cov_type == "HAC" else "")
            print(f"  {a}: {len(fit.terms) - 1} terms: {' '.join(fit.terms[1:])}{extra}")
        print(f"  {'campaign':<10}" + "".join(f"{a + ' max|err|':>14}{a + ' PI95':>9}" for a in AXES))
        for name, camp in tests.items():
            aligned = camp.aligned(zero_window_s=model.zero_window_s)
            pred, half = model.predict_interval(camp)
            m = validation_metrics(aligned.reference_um, pred, half)["axes"]
            print(f"  {name:<10}" + "".join(f"{m[a]['max_abs_error_um']:>14.2f}"
                                            f"{m[a]['pi95_coverage']:>9.3f}" for a in AXES))
    return 0


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--ram2", metavar="DIR", help="print the naive vs HAC table on ram2 instead")
    ap.add_argument("--rows", type=int, default=1_000_000)
    ap.add_argument("--p-enter", type=float, default=0.05)
    ap.add_argument("--p-remove", type=float, default=0.10)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    if args.ram2:
        return ram2_before_after(args.ram2)

    X, y, names = make_data(args.rows, args.seed)
    print(f"{args.rows} rows, {X.shape[1] - 1} candidate terms + const; stepwise 'both', "
          f"p_enter {args.p_enter}, p_remove {args.p_remove}; Python {platform.python_version()}, "
          f"{os.cpu_count()} cores")

    t0, c0 = time.perf_counter(), time.process_time()
    sel_f, params_f, steps_f, extended = fbgcomp_stepwise(X, y, names, args.p_enter, args.p_remove)
    t_fbg, c_fbg = time.perf_counter() - t0, time.process_time() - c0
    print(f"fbgcomp (QR factor, accumulate + stepwise): {t_fbg:8.2f} s wall, {c_fbg:8.2f} s CPU, "
          f"{steps_f} steps, "
          f"{len(sel_f)} terms{' (double-double data pass)' if extended else ''}")
    sys.stdout.flush()

    t0, c0 = time.perf_counter(), time.process_time()
    sel_s, params_s, steps_s, n_fits = statsmodels_stepwise(X, y, names, args.p_enter, args.p_remove)
    t_sm, c_sm = time.perf_counter() - t0, time.process_time() - c0
    print(f"statsmodels (sm.OLS refit per candidate): {t_sm:8.2f} s wall, {c_sm:8.2f} s CPU, "
          f"{steps_s} steps, "
          f"{n_fits} OLS fits")

    same_terms = sel_f == sel_s
    rel = float(np.max(np.abs(params_f - params_s) / np.abs(params_s))) if same_terms else None
    print(f"selected terms identical: {same_terms} ({', '.join(sel_f)})")
    if rel is not None:
        print(f"largest relative coefficient difference: {rel:.2e} (must be <= 1e-8)")
    ratio = t_sm / t_fbg
    cpu_ratio = c_sm / c_fbg
    # On a shared machine wall time depends on the neighbours' load; CPU time much less so.
    print(f"speed-up: {ratio:.1f}x wall, {cpu_ratio:.1f}x CPU (target >= 50x)")
    ok = same_terms and rel is not None and rel <= 1e-8
    print(json.dumps({"bench": "stepwise", "rows": args.rows, "candidates": X.shape[1] - 1,
                      "fbgcomp_s": round(t_fbg, 3), "statsmodels_s": round(t_sm, 3),
                      "fbgcomp_cpu_s": round(c_fbg, 3), "statsmodels_cpu_s": round(c_sm, 3),
                      "ratio": round(ratio, 1), "cpu_ratio": round(cpu_ratio, 1), "statsmodels_fits": n_fits, "steps": steps_f,
                      "same_terms": same_terms, "max_rel_coef_diff": rel, "ok": ok}))
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
