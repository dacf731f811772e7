"""Stepwise selection of the regression's terms from the accumulated factor only.

The paper tunes its compensation regression "with a stepwise regression ... counting or
removing a factor using ANOVA" (section 3; final model in Table 1). :func:`stepwise` does that
by partial F tests, or by Newey-West (HAC) Wald tests for autocorrelated residuals, each step one
small QR of the accumulated factor (:class:`StepState`), never a pass over the data.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import cast

import numpy as np
from scipy import linalg

from fbgcomp.models.distributions import f_sf
from fbgcomp.models.regression.accumulator import QRAccumulator
from fbgcomp.models.regression.doubledouble import (
    dd_add,
    dd_div,
    dd_householder,
    dd_mul,
    dd_solve_upper,
    dd_sum_rows,
)
from fbgcomp.models.regression.factor import EPS, RankDeficientError, deficient_columns
from fbgcomp.models.regression.fit import ols_from_factor
from fbgcomp.models.regression.hac import hac_cov_scaled, resolve_cov_type
from fbgcomp.models.regression.results import OLSResults, fmt_p

__all__ = ["StepState", "StepwiseResult", "stepwise"]


@dataclass
class StepwiseResult:
    """Outcome of :func:`stepwise`.

    Attributes
    ----------
    selected : list of str
        Terms of the final model (forced ``include`` terms too), in model order, which is
        design-column order; equals ``result.feature_names``.
    history : list of dict
        One dict per step: step, action ('enter' / 'remove'), term, F, p (partial F test, or
        with ``cov_type="HAC"`` the Newey-West Wald test of the term, on 1 and df_resid(bigger
        model) degrees of freedom), n_terms, ssr, rsquared_adj (of the model after the step);
        HAC steps also hold the bandwidth ``maxlags`` and effective sample size ``n_eff`` of
        the bigger model.
    result : OLSResults or None
        Fit of the final model (None if it is empty).
    """

    selected: list[str]
    history: list[dict] = field(default_factory=list)
    result: OLSResults | None = None
    target_name: str = "y"
    cov_type: str = "nonrobust"

    def summary(self) -> str:
        """The step history table, then the final model's summary."""
        how = "Newey-West (HAC) Wald tests" if self.cov_type == "HAC" else "partial F tests, i.i.d. errors"
        lines = [
            f"Stepwise regression of {self.target_name} ({how})",
            f"{'step':>4}  {'action':<6} {'term':<16} {'F':>12} {'p':>10} {'terms':>5} "
            f"{'SSR':>13} {'adj. R2':>9}",
        ]
        for h in self.history:
            lines.append(
                f"{h['step']:>4}  {h['action']:<6} {h['term']:<16} {h['F']:>12.5g} "
                f"{fmt_p(h['p']):>10} {h['n_terms']:>5} {h['ssr']:>13.6g} "
                f"{h['rsquared_adj']:>9.5f}"
            )
        if not self.history:
            lines.append("  (no step taken)")
        lines.append("")
        lines.append(self.result.summary() if self.result is not None else "empty model: no term selected")
        return "\n".join(lines)


def _adj_r2(acc: QRAccumulator, cols: list[int], t: int, ssr: float) -> float:
    k_const = int(any(c in set(acc.constant_columns) for c in cols))
    centred, uncentred = acc._tss(t)
    tss = centred if k_const else uncentred
    df_resid = acc.n_obs - len(cols)
    if df_resid <= 0 or tss <= 0:
        return math.nan
    return 1.0 - (acc.n_obs - k_const) / df_resid * (ssr / tss)


def _double_subset(acc: QRAccumulator, cols: list[int], t: int):
    """Double-precision factor of the sub-model: (T, scaled beta, T^-1, scaled SSR).

    Enough for test statistics (the double-double path is kept for reported coefficients)."""
    m = len(cols)
    sel = [*cols, acc.n_features + t]
    # numpy's stubs type every mode as QRResult; mode="r" returns the triangle alone
    r = cast(np.ndarray, np.linalg.qr(acc.R_[:, sel] + acc.R_lo_[:, sel], mode="r"))
    if r.shape[0] < m + 1:
        r = np.vstack([r, np.zeros((m + 1 - r.shape[0], m + 1))])
    tri = np.triu(r[:m, :m])
    r_inv = linalg.lapack.dtrtri(tri, lower=0)[0]
    beta = r_inv @ r[:m, m]
    return tri, beta, r_inv, float(r[m, m]) ** 2


class StepState:
    """One double-double factorisation of ``R[:, model + others + [y]]`` with the model columns
    reduced: it yields the SSR of the model, of the model plus each other column, and of the
    model minus each of its columns, without subtracting two large sums of squares.

    Entry: with ``w_c``, ``w_y`` the candidate and target residualised on the model (trailing
    rows), ``SSR(S) - SSR(S + c) = (w_c . w_y)^2 / |w_c|^2``. Removal: with ``T b = z`` the model
    solution, ``SSR(S - s) - SSR(S) = b_s^2 / [(X^T X)^-1]_ss`` and ``(X^T X)^-1 = T^-1 T^-T``.
    """

    def __init__(self, acc: QRAccumulator, model: list[int], others: list[int], t: int, exact: bool = True):
        p = acc.n_features
        m = len(model)
        sel = model + others + [p + t]
        self.exact = exact
        assert acc.scale_ is not None  # stepwise starts only on an accumulator with rows
        sy2 = float(acc.scale_[p + t]) ** 2
        if not exact:
            self._init_double(acc, model, others, sel, sy2)
            return
        mh, ml = dd_householder(acc.R_[:, sel], acc.R_lo_[:, sel], m)
        self.nobs = acc.n_obs
        self.model, self.others, self.sy2 = model, others, sy2
        th, tl = mh[:m, :m], ml[:m, :m]
        self.diag = np.abs(np.diag(th))
        self.full_rank = not deficient_columns(self.diag, acc.n_obs)
        yh, yl = mh[m:, -1], ml[m:, -1]
        ssr_h, ssr_l = dd_sum_rows(*dd_mul(yh, yl, yh, yl))
        self.ssr = float(ssr_h) * sy2
        self._ssr_dd = (ssr_h, ssr_l)
        self._trail = (mh[m:, m:-1], ml[m:, m:-1], yh, yl)
        self._tri = (th, tl, mh[:m, -1], ml[:m, -1])

    def _init_double(self, acc, model, others, sel, sy2) -> None:
        """The same quantities in double precision (LAPACK Householder QR of the model columns
        of R, its reflections applied to the rest): for a well-conditioned factor
        (kappa_eq <= KAPPA_EXTENDED) they carry a relative error of about kappa u, far below any
        difference a partial F test can resolve."""
        m = len(model)
        a = acc.R_[:, sel] + acc.R_lo_[:, sel]
        self.nobs = acc.n_obs
        self.model, self.others, self.sy2 = model, others, sy2
        if m:
            qr_a, tau = linalg.lapack.dgeqrf(np.asfortranarray(a[:, :m]))[:2]
            rest, _, info = linalg.lapack.dormqr("L", "T", qr_a, tau, np.asfortranarray(a[:, m:]), a.shape[1])
            if info != 0:
                raise np.linalg.LinAlgError(f"dormqr failed ({info})")
            tri = np.triu(qr_a[:m, :m])
            head, trail = rest[:m], rest[m:]
        else:
            tri, head, trail = np.zeros((0, 0)), a[:0], a
        self.diag = np.abs(np.diag(tri))
        self.full_rank = not deficient_columns(self.diag, acc.n_obs)
        y = trail[:, -1]
        ssr_s = float(y @ y)
        self.ssr = ssr_s * sy2
        self._d_trail = (trail[:, :-1], y, ssr_s)
        self._d_tri = (tri, head[:, -1])

    def entries_arrays(self):
        """Vectorised :meth:`entries`: (columns, SSR drop, SSR after entry, full rank) arrays."""
        cols = np.asarray(self.others, dtype=int)
        if not self.others:
            return cols, np.zeros(0), np.zeros(0), np.zeros(0, dtype=bool)
        if self.exact:
            out = self.entries()
            return (
                cols,
                np.array([o[1] for o in out]),
                np.array([o[2] for o in out]),
                np.array([o[3] for o in out], dtype=bool),
            )
        w, y, ssr_s = self._d_trail
        norm2 = np.einsum("ij,ij->j", w, w)
        dot = w.T @ y
        with np.errstate(divide="ignore", invalid="ignore"):
            drop = dot * dot / norm2
        after = np.maximum(ssr_s - drop, 0.0) * self.sy2
        # rank: the new column's diagonal sqrt(norm2) against the model's (as deficient_columns)
        new_diag = np.sqrt(np.maximum(norm2, 0.0))
        top = np.maximum(self.diag.max() if self.diag.size else 0.0, new_diag)
        ok = self.full_rank & (new_diag > max(self.nobs, self.diag.size + 1) * EPS * top)
        if self.diag.size:
            ok &= self.diag.min() > max(self.nobs, self.diag.size + 1) * EPS * top
        drop = np.where(ok, drop * self.sy2, np.nan)
        return cols, drop, after, ok

    def removals_arrays(self):
        """Vectorised :meth:`removals`: (columns, SSR rise, SSR after removal) arrays."""
        cols = np.asarray(self.model, dtype=int)
        if not self.model:
            return cols, np.zeros(0), np.zeros(0)
        if self.exact:
            out = self.removals()
            return cols, np.array([o[1] for o in out]), np.array([o[2] for o in out])
        tri, z = self._d_tri
        t_inv = linalg.lapack.dtrtri(tri, lower=0)[0]
        b = t_inv @ z
        g = np.einsum("ij,ij->i", t_inv, t_inv)  # diag of T^-1 T^-T
        rise = b * b / g * self.sy2
        return cols, rise, self.ssr + rise

    def entries(self) -> list[tuple[int, float, float, bool]]:
        """(column, SSR drop, SSR after entry, full rank) for every other column."""
        if not self.others:
            return []
        if not self.exact:
            cols, drop, after, ok = self.entries_arrays()
            return [(int(c), float(d), float(a), bool(o)) for c, d, a, o in zip(cols, drop, after, ok)]
        wh, wl, yh, yl = self._trail
        nh, nl = dd_sum_rows(*dd_mul(wh, wl, wh, wl))
        dh, dl = dd_sum_rows(*dd_mul(wh, wl, yh[:, None], yl[:, None]))
        with np.errstate(divide="ignore", invalid="ignore"):
            sh, sl = dd_mul(dh, dl, dh, dl)
            eh, el = dd_div(sh, sl, nh, nl)
            after_h, _ = dd_add(self._ssr_dd[0], self._ssr_dd[1], -eh, -el)
        out = []
        for i, c in enumerate(self.others):
            new_diag = math.sqrt(max(float(nh[i]), 0.0))
            ok = self.full_rank and not deficient_columns(np.append(self.diag, new_diag), self.nobs)
            drop = float(eh[i]) * self.sy2 if ok else math.nan
            out.append((c, drop, max(float(after_h[i]), 0.0) * self.sy2, ok))
        return out

    def removals(self) -> list[tuple[int, float, float]]:
        """(column, SSR rise, SSR after removal) for every model column."""
        if not self.exact:
            cols, rise, after = self.removals_arrays()
            return [(int(c), float(r), float(a)) for c, r, a in zip(cols, rise, after)]
        th, tl, zh, zl = self._tri
        m = len(self.model)
        if m == 0:
            return []
        bh, bl = dd_solve_upper(th, tl, zh, zl)
        ih, il = dd_solve_upper(th, tl, np.eye(m), np.zeros((m, m)))
        gh, gl = dd_sum_rows(*dd_mul(ih.T, il.T, ih.T, il.T))  # diag of T^-1 T^-T
        sh, sl = dd_mul(bh, bl, bh, bl)
        rh, _ = dd_div(sh, sl, gh, gl)
        return [
            (c, float(rh[i]) * self.sy2, self.ssr + float(rh[i]) * self.sy2) for i, c in enumerate(self.model)
        ]


def stepwise(
    acc: QRAccumulator,
    candidates=None,
    *,
    target=0,
    direction: str = "both",
    p_enter: float = 0.05,
    p_remove: float = 0.10,
    max_terms: int | None = None,
    include: Iterable = (),
    start=None,
    cov_type=None,
    maxlags=None,
) -> StepwiseResult:
    """Stepwise selection by partial F (or HAC Wald) tests, from the accumulated factor only.

    The paper tunes its regression "with a stepwise regression ... counting or removing a
    factor using ANOVA" (section 3; final model in Table 1). Each step compares two nested
    models differing by one term: ``F = (SSR_small - SSR_big) / (SSR_big / df_resid_big)`` on
    (1, df_resid_big) degrees of freedom. Every step costs one small double-double QR of the
    factor (see :class:`StepState`), never a pass over the data.

    That F test assumes independent errors. Residuals of slow thermal drifts sampled every
    second are autocorrelated over hours, and it then gives p ~ 0 to nearly every term.
    ``cov_type="HAC"`` (the default when the accumulator keeps autocorrelation statistics)
    tests the term instead by its Newey-West Wald statistic ``b^2 / Var_HAC(b)`` in the bigger
    model (same F(1, df_resid) reference; bandwidth ``maxlags``, by default Andrews' AR(1)
    rule per model; see :func:`ols_from_factor`), still from the accumulated statistics only.
    ``cov_type="nonrobust"`` is the paper's partial F test.

    Parameters
    ----------
    candidates : None or sequence of column indices / names
        Terms that may enter or leave (default: every column not in ``include``).
    include : sequence of column indices / names
        Terms always in the model (typically the intercept); never tested.
    direction : {"forward", "backward", "both"}
        forward: from ``start`` (default empty), add the best term while its p < p_enter.
        backward: from ``start`` (default all candidates), drop the worst while its p > p_remove.
        both: forward, and after every entry drop terms whose p > p_remove; a model already
        visited is never revisited, so the search cannot cycle.
    max_terms : int, optional
        Maximum number of candidate terms (not counting ``include``) in the model.

    A candidate that is (numerically) a linear combination of the model's terms is skipped.
    """
    if direction not in ("forward", "backward", "both"):
        raise ValueError(f"direction must be 'forward', 'backward' or 'both', not {direction!r}")
    if direction == "both" and p_enter > p_remove:
        raise ValueError(
            f"p_enter ({p_enter}) must not exceed p_remove ({p_remove}): a term could enter and leave forever"
        )
    if acc.n_obs == 0:
        raise ValueError("no data accumulated yet")
    cov_type = resolve_cov_type(acc, cov_type)
    robust = cov_type == "HAC"
    t = acc.target_index(target)
    forced = acc.column_indices(list(include))
    if candidates is None:
        cand = [c for c in range(acc.n_features) if c not in forced]
    else:
        cand = [c for c in acc.column_indices(candidates) if c not in forced]
    if start is None:
        model = list(cand) if direction == "backward" else []
    else:
        model = [c for c in acc.column_indices(start) if c not in forced]
        stray = [acc.feature_names[c] for c in model if c not in cand]
        if stray:
            raise ValueError(f"start terms {stray} are not candidates")
    limit = len(cand) if max_terms is None else int(max_terms)

    def ordered(terms):
        return sorted(set(forced) | set(terms))

    # Double-precision steps when the factor is well conditioned (kappa_eq <= 1e6, where the
    # data pass also stays in double); double-double otherwise. Reported coefficients always
    # come from the double-double solve of ols_from_factor.
    exact = not acc._well_conditioned()

    def state():
        cols = ordered(model)
        return StepState(acc, cols, [c for c in cand if c not in model], t, exact)

    def partial_f(diff: np.ndarray, ssr_big, df_big: int) -> np.ndarray:
        """Partial F = (SSR_small - SSR_big) / (SSR_big / df_big), vectorised over the
        candidates (F only; p is monotone in F at a fixed df)."""
        diff = np.maximum(np.asarray(diff, dtype=float), 0.0)
        ssr_big = np.broadcast_to(np.asarray(ssr_big, dtype=float), diff.shape)
        if df_big <= 0:
            return np.full(diff.shape, math.nan)
        with np.errstate(divide="ignore", invalid="ignore"):
            f = diff / (ssr_big / df_big)
        return np.where(ssr_big <= 0.0, np.where(diff > 0, math.inf, math.nan), f)

    def pick(f: np.ndarray, largest: bool) -> int | None:
        """Position of the first largest (smallest) non-NaN F, as the scalar loop chose it."""
        idx = np.flatnonzero(~np.isnan(f))
        if not idx.size:
            return None
        return int(idx[np.argmax(f[idx]) if largest else np.argmin(f[idx])])

    current = state()
    if not current.full_rank:
        raise RankDeficientError(
            "the starting model of the stepwise search is rank deficient",
            [acc.feature_names[c] for c in ordered(model)],
        )
    history: list[dict] = []
    visited = {frozenset(model)}

    def wald(cols):
        """HAC Wald F of every term of the model ``cols`` (dict by column), and its HAC info."""
        _, beta, r_inv, ssr_s = _double_subset(acc, cols, t)
        cov, info = hac_cov_scaled(acc, cols, t, beta, r_inv, ssr_s, maxlags)
        with np.errstate(divide="ignore", invalid="ignore"):
            f = beta * beta / np.diag(cov)
        return {c: float(f[i]) for i, c in enumerate(cols)}, info

    def record(action, term, f, pval, ssr, info=None):
        cols = ordered(model)
        entry = {
            "step": len(history) + 1,
            "action": action,
            "term": acc.feature_names[term],
            "F": float(f),
            "p": float(pval),
            "n_terms": len(cols),
            "ssr": float(ssr),
            "rsquared_adj": _adj_r2(acc, cols, t, ssr),
        }
        if info is not None:
            entry["maxlags"] = info["maxlags"]
            entry["n_eff"] = info["n_eff"]
        history.append(entry)

    def try_enter() -> bool:
        nonlocal current
        if len(model) >= limit:
            return False
        df_big = acc.n_obs - len(current.model) - 1
        cols, drop, after, ok = current.entries_arrays()
        keep = np.array(
            [bool(o) and frozenset([*model, int(c)]) not in visited for c, o in zip(cols, ok)], dtype=bool
        )
        # collinear with the model (no new information), or a loop
        cols, drop, after = cols[keep], drop[keep], after[keep]
        infos = [None] * len(cols)
        if robust:
            f = np.empty(len(cols))
            for k, c in enumerate(cols):
                fs, infos[k] = wald(ordered([*model, int(c)]))
                f[k] = fs[int(c)]
        else:
            f = partial_f(drop, after, df_big)
        i = pick(f, largest=True)
        if i is None:
            return False
        pval = float(f_sf(f[i], 1, df_big))  # NaN where df_big < 1 or F is NaN
        if not pval < p_enter:
            return False
        model.append(int(cols[i]))
        visited.add(frozenset(model))
        current = state()
        record("enter", int(cols[i]), float(f[i]), pval, current.ssr, infos[i])
        return True

    def try_remove() -> bool:
        nonlocal current
        if not model:
            return False
        df_big = acc.n_obs - len(current.model)
        fs, info = wald(current.model) if robust else (None, None)
        cols, rise, _after = current.removals_arrays()
        keep = np.array(
            [
                int(c) not in forced
                and not (direction == "both" and frozenset(d for d in model if d != int(c)) in visited)
                for c in cols
            ],
            dtype=bool,
        )
        cols, rise = cols[keep], rise[keep]
        # fs is None exactly when the search is not robust
        f = (
            np.array([fs[int(c)] for c in cols], dtype=float)
            if fs is not None
            else partial_f(rise, current.ssr, df_big)
        )
        i = pick(f, largest=False)
        if i is None:
            return False
        pval = float(f_sf(f[i], 1, df_big))  # NaN where df_big < 1 or F is NaN
        if not pval > p_remove:
            return False
        model.remove(int(cols[i]))
        visited.add(frozenset(model))
        current = state()
        record("remove", int(cols[i]), float(f[i]), pval, current.ssr, info)
        return True

    if direction == "backward":
        while try_remove():
            pass
    else:
        while try_enter():
            if direction == "both":
                while try_remove():
                    pass

    final = ordered(model)
    result = ols_from_factor(acc, final, t, cov_type=cov_type, maxlags=maxlags) if final else None
    return StepwiseResult(
        selected=[acc.feature_names[c] for c in final],
        history=history,
        result=result,
        target_name=acc.target_names[t],
        cov_type=cov_type,
    )
