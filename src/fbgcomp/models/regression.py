"""Multiple regression of the tool-tip deviation on sensor features, by streamed QR.

The compensation model of the paper (section 3, eq. 12-13) is a multiple linear regression of a
TTP deviation component (dx, dy, dz) on FBG elongations and temperatures, tuned by "stepwise
regression with ANOVA"; Table 1 reports its coefficients and standard errors. This module is the
numerical engine behind that: ordinary least squares that is accurate on ill-conditioned designs
(it passes the NIST StRD linear reference problems, Filip and Wampler included, streamed in
chunks of any size) and that streams a 36 h campaign of any length in constant memory.

Mathematics
-----------
Let ``A = [X | Y]`` (n x (p+k)): the design X exactly as given (the caller adds a column of ones
for an intercept) next to the k targets. Each column is divided by a fixed scale ``s`` (the
column's RMS in the first chunk, rounded to a power of two so that the division is exact), and
the scaled matrix is reduced to its triangular factor ``R`` (``A_s = Q R``) by Householder QR,
chunk by chunk: ``R <- qr([R; A_chunk])`` (the "TSQR" reduction). The normal equations are never
formed, so the condition number is not squared.

Because ``R^T R = A_s^T A_s``, every least-squares problem on a subset S of the columns of X and
one target j is solved *exactly* from ``R`` alone: the QR factor of the (p+k) x (|S|+1) matrix
``R[:, S + [p+j]]`` is the QR factor of ``A_s[:, S + [p+j]]``. Its leading |S| x |S| triangle
``T`` and last column ``z`` give the scaled coefficients ``T b = z``, and the square of its last
diagonal entry is the residual sum of squares. Sub-models, the ANOVA table and the whole stepwise
search therefore never re-read the data.

Precision
---------
Householder QR in double precision is backward stable: the computed factor is exact for data
perturbed by about one rounding unit u per column, so coefficients carry a relative error of
about ``kappa * u`` (kappa: condition number of the scaled design). That is 1e-12 for a typical
compensation design (eq. 12 with raw temperatures: kappa ~ 1e3) but only 1e-7 for NIST Filip
(kappa ~ 5e9), whatever the chunking. ``R`` is therefore kept in double-double arithmetic (an
unevaluated sum ``hi + lo`` of two doubles, ~32 significant digits): merges of triangles,
sub-model factors and triangular solves are always done in it (they are tiny), and the data pass
itself is done in it too when the scaled design is ill-conditioned (kappa > 1e6) or has fewer
than 2(p+k) rows so far (``precision="auto"``). Otherwise the data pass is LAPACK Householder QR
(``geqrf``) on the stacked ``[R; chunk]``, in cache-sized blocks.

Gram fast path: when the design is well conditioned, forming ``X^T X`` costs far less than QR
(one BLAS ``syrk`` pass, at the speed of the Gram/Cholesky recipe) and loses nothing that
matters. So after the first 1024 rows (QR), ``precision="auto"`` adds each chunk through its Gram
and a Cholesky of ``R^T R + G``, and keeps the result only if the equilibrated condition number of
the new factor's design part is <= 500 and each target's norm is <= 300 times its residual's
(``_KAPPA_GRAM``, ``_RESID_RATIO_GRAM``: calibrated to keep >= 7.3 correct digits in the worst
coefficient, see their notes); otherwise the same rows go through QR as above
(``gram_rows_`` counts the rows that took the Gram). Every NIST StRD design stays on QR.

Inference follows the textbook (and statsmodels) formulas: ``sigma^2 = SSR / (n - |S|)``,
``Cov(b) = sigma^2 (X^T X)^-1 = sigma^2 T^-1 T^-T`` (through the triangular inverse, then
unscaled), Student-t tests and intervals, and the overall F test with R^2 centred when the model
holds a constant column and uncentred otherwise. Those assume independent errors; for
autocorrelated ones (slow drifts sampled every second) an accumulator created with
``hac_lags`` also keeps lagged score sums, and results and stepwise tests then use the
Newey-West (HAC) sandwich, statsmodels' ``cov_type="HAC"`` (see :class:`QRAccumulator`);
``cov_type="nonrobust"`` selects the naive formulas.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy import linalg, stats

from fbgcomp.errors import InputError

__all__ = [
    "RankDeficientError",
    "QRAccumulator",
    "OLSResults",
    "StepwiseResult",
    "ols",
    "ols_from_factor",
    "stepwise",
]

_EPS = np.finfo(float).eps
# Rows per BLAS Gram product inside one update (the Gram fast path).
_BLOCK_ROWS = 65536
# Rows per LAPACK QR pass: [R; block] stays in cache (4096 x 46 doubles = 1.5 MB), which makes
# the Householder data pass ~1.7x faster than 65536-row blocks; it also bounds the extra memory
# of an update (one scaled copy of the block) whatever the caller's chunk size.
_QR_BLOCK_ROWS = 4096
# Rows per double-double Householder pass: its ~20 temporaries of this many rows stay small.
_DD_BLOCK_ROWS = 2048
# Above this condition number of the scaled design, double-precision QR would lose more than
# ~10 of the 16 digits: the "auto" precision switches the data pass to double-double.
_KAPPA_EXTENDED = 1e6
_PRECISIONS = ("auto", "double", "double-double")
# Gram fast path of the "auto" data pass (issue 16). Forming X^T X squares the condition
# number: with the columns equilibrated, the Cholesky solution of the accumulated Gram carries a
# normwise relative error of about kappa_eq(X)^2 * eps_G, eps_G the rounding of the Gram
# (about sqrt(65536) u = 2.8e-14 for a 65536-row BLAS block, probabilistically; Higham & Mary
# 2019). Small coefficients lose more, relatively. Forced through the Gram, NIST Wampler3/4
# (kappa_eq(X) 2.2e3) keep only 6.0 correct digits in their worst coefficient, Longley (4.3e4)
# 6.6, and polynomial designs of degree 2-4 on shifted abscissae 12.7 (kappa_eq 18) to 5.2
# (2.1e4): the worst coefficient's relative error stays <= 2.1e-13 kappa_eq^2 in all of them.
# kappa_eq(X) <= 500 bounds that at 5e-8, >= 7.3 digits (the NIST target is 7; the measured
# design nearest the threshold, kappa_eq 547, keeps 7.8). The error is governed by the final
# factor's conditioning (a chunk's rounding relative to the whole Gram), which only improves as
# a drift is seen longer: bench_stepwise's first 100 000 rows have kappa_eq 402, all 10^6 rows 9.
_KAPPA_GRAM = 500.0
# The residual sum of squares from a Gram is y'y - b'X'y: it loses (|y| / |e|)^2 eps_G of its
# relative accuracy to cancellation (|e| the residual norm of y on all of X). At most 300 keeps
# SSR to 2.1e-13 * 9e4 = 1.9e-8 (residual SD, R^2 and standard errors to >= 7.5 digits); a
# near-exact fit (NIST Pontius, Wampler1/2, or tiny noise on large deviations) stays on QR.
_RESID_RATIO_GRAM = 300.0
# Rows that go through Householder QR before the Gram fast path may start (the first 2(p+k) of
# them in double-double): their factor tells whether the design is well conditioned.
_GRAM_MIN_ROWS = 1024
# A refused Gram (the factor would leave the bounds above) costs its pass on top of the QR of the
# same rows; after this many refusals in a row the fast path is off for good. A refusal alone
# is not final: the first chunks of a slow drift often see too little of it to be well
# conditioned (bench_stepwise's first 100 000 rows: 3.6 h of a 36 h campaign).
_GRAM_MAX_REFUSALS = 3
# Largest Newey-West bandwidth (lags) of the default grid of an autocorrelation-robust fit.
HAC_MAX_LAG = 4096
# Rows per pass of the lagged-score accumulation: bounds its temporaries (rows + carried lags).
_HAC_BLOCK_ROWS = 8192
# Bartlett sums up to this bandwidth are formed by shifted additions (exact to a few ulps);
# wider ones through two cumulative sums over a block of at most _HAC_BLOCK_ROWS + L rows.
_HAC_DIRECT_MAX_LAG = 32
COV_TYPES = ("HAC", "nonrobust")


class RankDeficientError(InputError, ValueError):
    """The design has (numerically) linearly dependent columns.

    ``columns`` lists the names of the columns whose scaled-R diagonal is (near) zero, i.e. that
    are (nearly) linear combinations of the columns before them in the model.
    """

    def __init__(self, message: str, columns: Sequence[str] = ()):
        self.columns = list(columns)
        super().__init__(message)


# --------------------------------------------------------------------------------------------
# Double-double arithmetic (Dekker 1971; Hida, Li & Bailey 2001), vectorised over numpy arrays.
# A value is the pair (hi, lo) with |lo| <= ulp(hi) / 2; error-free transformations rely on
# IEEE round-to-nearest, which numpy's separate ufunc calls honour (no FMA contraction).
# --------------------------------------------------------------------------------------------

_DEKKER = 134217729.0  # 2**27 + 1


def _two_sum(a, b):
    s = a + b
    bb = s - a
    return s, (a - (s - bb)) + (b - bb)


def _fast_two_sum(a, b):
    s = a + b
    return s, b - (s - a)


def _split(a):
    t = _DEKKER * a
    hi = t - (t - a)
    return hi, a - hi


def _two_prod(a, b):
    p = a * b
    ah, al = _split(a)
    bh, bl = _split(b)
    return p, ((ah * bh - p) + ah * bl + al * bh) + al * bl


def _dd_add(ah, al, bh, bl):
    s, e = _two_sum(ah, bh)
    t, f = _two_sum(al, bl)
    s, e = _fast_two_sum(s, e + t)
    return _fast_two_sum(s, e + f)


def _dd_mul(ah, al, bh, bl):
    p, e = _two_prod(ah, bh)
    return _fast_two_sum(p, e + (ah * bl + al * bh))


def _dd_div(ah, al, bh, bl):
    q1 = ah / bh
    ph, pl = _dd_mul(q1, 0.0 * q1, bh, bl)
    rh, rl = _dd_add(ah, al, -ph, -pl)
    q2 = rh / bh
    ph, pl = _dd_mul(q2, 0.0 * q2, bh, bl)
    rh, _ = _dd_add(rh, rl, -ph, -pl)
    q1, q2 = _fast_two_sum(q1, q2)
    return _dd_add(q1, q2, rh / bh, 0.0 * q1)


def _dd_sqrt(ah: float, al: float) -> tuple[float, float]:
    if ah <= 0.0:
        return 0.0, 0.0
    x = math.sqrt(ah)
    p, e = _two_prod(x, x)
    return _fast_two_sum(x, ((ah - p) - e + al) / (2.0 * x))


def _dd_sum_rows(h: np.ndarray, l: np.ndarray):
    """Sum along axis 0 by a pairwise tree of double-double additions."""
    while h.shape[0] > 1:
        if h.shape[0] % 2:
            h = np.concatenate([h, np.zeros_like(h[:1])])
            l = np.concatenate([l, np.zeros_like(l[:1])])
        h, l = _dd_add(h[0::2], l[0::2], h[1::2], l[1::2])
    return h[0], l[0]


def _dd_householder(mh: np.ndarray, ml: np.ndarray, ncols: int) -> tuple[np.ndarray, np.ndarray]:
    """Apply Householder reflections in double-double to zero the first ``ncols`` columns of the
    r x c matrix mh + ml below the diagonal; returns the whole transformed matrix (hi, lo).

    Reflector ``H = I - v v^T / (sigma |v_0|)`` with ``v = x + sign(x_0) sigma e_1`` (no
    cancellation) and ``v^T v = 2 sigma |v_0|``; Householder's method in 32-digit arithmetic.
    """
    mh = np.array(mh, dtype=float)
    ml = np.array(ml, dtype=float)
    r, c = mh.shape
    for j in range(min(r, c, ncols)):
        xh, xl = mh[j:, j], ml[j:, j]
        sig_h, sig_l = _dd_sqrt(*_dd_sum_rows(*_dd_mul(xh, xl, xh, xl)))
        if sig_h == 0.0:
            continue
        sign = 1.0 if xh[0] >= 0.0 else -1.0
        vh = xh.copy()
        vl = xl.copy()
        vh[0], vl[0] = _dd_add(xh[0], xl[0], sign * sig_h, sign * sig_l)
        if j + 1 < c:
            dh, dl = _dd_mul(sig_h, sig_l, sign * vh[0], sign * vl[0])
            th, tl = mh[j:, j + 1:], ml[j:, j + 1:]
            wh, wl = _dd_sum_rows(*_dd_mul(vh[:, None], vl[:, None], th, tl))
            fh, fl = _dd_div(wh, wl, dh, dl)
            uh, ul = _dd_mul(vh[:, None], vl[:, None], fh[None, :], fl[None, :])
            mh[j:, j + 1:], ml[j:, j + 1:] = _dd_add(th, tl, -uh, -ul)
        mh[j, j], ml[j, j] = -sign * sig_h, -sign * sig_l
        mh[j + 1:, j] = 0.0
        ml[j + 1:, j] = 0.0
    return mh, ml


def _dd_qr_r(mh: np.ndarray, ml: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Householder QR in double-double: the c x c triangle R (hi, lo) of the r x c matrix mh + ml
    (zero rows appended when r < c)."""
    r, c = np.shape(mh)
    mh, ml = _dd_householder(mh, ml, c)
    k = min(r, c)
    rh = np.zeros((c, c))
    rl = np.zeros((c, c))
    rh[:k] = np.triu(mh[:k])
    rl[:k] = np.triu(ml[:k])
    return rh, rl


def _dd_solve_upper(th, tl, zh, zl) -> tuple[np.ndarray, np.ndarray]:
    """Back substitution ``T B = Z`` in double-double (T upper triangular, non-singular; Z a
    vector or a matrix of right-hand sides)."""
    n = th.shape[0]
    zh = np.asarray(zh, dtype=float)
    zl = np.asarray(zl, dtype=float)
    bh = np.zeros_like(zh)
    bl = np.zeros_like(zh)
    for i in range(n - 1, -1, -1):
        sh, sl = zh[i], zl[i]
        if i + 1 < n:
            ah = th[i, i + 1:].reshape((-1,) + (1,) * (zh.ndim - 1))
            al = tl[i, i + 1:].reshape(ah.shape)
            qh, ql = _dd_sum_rows(*_dd_mul(ah, al, bh[i + 1:], bl[i + 1:]))
            sh, sl = _dd_add(sh, sl, -qh, -ql)
        bh[i], bl[i] = _dd_div(sh, sl, th[i, i], tl[i, i])
    return bh, bl


# --------------------------------------------------------------------------------------------
# Streamed QR
# --------------------------------------------------------------------------------------------

def _power_of_two_scale(rms: np.ndarray) -> np.ndarray:
    """Column scale: the RMS rounded to the nearest power of two, 1 for an all-zero column.

    A power of two makes every division (and every rescaling between accumulators in
    :meth:`QRAccumulator.merge`) exact, so scaling adds no rounding error of its own.
    """
    scale = np.ones_like(rms)
    ok = np.isfinite(rms) & (rms > 0)
    scale[ok] = np.exp2(np.round(np.log2(rms[ok])))
    return scale


def _lapack_triangle(a: np.ndarray, ncols: int) -> np.ndarray:
    """Upper-triangular ncols x ncols QR factor of the Fortran-ordered ``a`` (overwritten)."""
    (_, _), r = linalg.qr(a, mode="raw", overwrite_a=True, check_finite=False)
    if r.shape[0] < ncols:
        r = np.vstack([r, np.zeros((ncols - r.shape[0], ncols))])
    return np.triu(r[:ncols])


def _deficient_columns(diag_abs: np.ndarray, nobs: int) -> list[int]:
    """Positions whose |R_ii| is (near) zero: <= max(n, p) * eps * max|R_ii| (LAPACK-style)."""
    if diag_abs.size == 0:
        return []
    tol = max(nobs, diag_abs.size) * _EPS * float(diag_abs.max())
    return [int(i) for i in np.flatnonzero(~(diag_abs > tol))]


def _equilibrated_cond(r: np.ndarray) -> float:
    """2-norm condition number of the triangle ``r`` with its columns scaled to unit norm: the
    conditioning that governs a Cholesky/normal-equations solution (van der Sluis), whatever the
    columns' units. inf when a column is zero."""
    norms = np.linalg.norm(r, axis=0)
    if r.size == 0:
        return 1.0
    if not (norms > 0).all():
        return math.inf
    return float(np.linalg.cond(r / norms))


def _as_2d(values: Any, ncols: int, what: str) -> np.ndarray:
    arr = np.asarray(values, dtype=float)
    if arr.ndim == 1 and ncols == 1:
        arr = arr[:, None]
    if arr.ndim != 2 or arr.shape[1] != ncols:
        raise ValueError(f"{what} must have shape (n, {ncols}), got {np.shape(values)}")
    return arr


def _check_finite(arr: np.ndarray, names: Sequence[str], first_row: int, what: str) -> None:
    if not np.isfinite(arr).all():
        bad_row, bad_col = np.argwhere(~np.isfinite(arr))[0]
        raise InputError(f"non-finite {what} value {arr[bad_row, bad_col]!r} in regression data",
                         row=first_row + int(bad_row), column=names[int(bad_col)])


def _names(names: Sequence[str] | None, count: int, default: list[str], what: str) -> list[str]:
    if names is None:
        return default
    names = [str(n) for n in names]
    if len(names) != count:
        raise ValueError(f"{what} has {len(names)} names for {count} columns")
    if len(set(names)) != len(names):
        raise ValueError(f"{what} are not unique: {names}")
    return names


def hac_lag_grid(hac_lags) -> list[int] | None:
    """Bandwidths (Newey-West lags) whose lagged score sums an accumulator keeps.

    ``None`` or ``False``: none (naive inference only). ``True`` or ``"auto"``: 1, 2, 4, ...,
    :data:`HAC_MAX_LAG`. An int L: the powers of two below L, and L. A sequence: those lags.
    Lag 1 is always included: the residual's lag-1 autocorrelation chooses the bandwidth.
    """
    if hac_lags is None or hac_lags is False:
        return None
    if hac_lags is True or (isinstance(hac_lags, str) and hac_lags == "auto"):
        hac_lags = HAC_MAX_LAG
    if isinstance(hac_lags, (int, np.integer)):
        top = int(hac_lags)
        if top < 1:
            raise ValueError(f"hac_lags must be at least 1, not {hac_lags!r}")
        lags = {1 << k for k in range(top.bit_length()) if (1 << k) <= top} | {top}
    else:
        try:
            lags = {int(v) for v in hac_lags}
        except (TypeError, ValueError):
            raise ValueError(f"hac_lags must be None, True, 'auto', an int or a sequence of "
                             f"ints, not {hac_lags!r}") from None
        if not lags or min(lags) < 1:
            raise ValueError(f"hac_lags must be positive, not {hac_lags!r}")
    return sorted(lags | {1})


def _bartlett_sums(w: np.ndarray, first: int, lags: Sequence[int]) -> list[np.ndarray]:
    """For each L in ``lags``: rows ``first..`` of ``sum_{l=1..L} (1 - l/(L+1)) w[i-l]``
    (rows before 0 count as zero): the Bartlett-weighted past of each row of ``w``."""
    n = w.shape[0]
    out = []
    p_sum = q_sum = None
    for lag in lags:
        if lag <= _HAC_DIRECT_MAX_LAG:
            acc = np.zeros((n - first, w.shape[1]))
            for l in range(1, lag + 1):
                lo = first - l
                if lo >= 0:
                    acc += (lag + 1 - l) * w[lo:n - l]
                elif n - l > 0:
                    acc[-lo:] += (lag + 1 - l) * w[:n - l]
        else:
            if p_sum is None:
                # P[k] = sum_{j<k} w[j],  Q[k] = sum_{j<k} P[j]:
                # sum_{l=1..L} (L+1-l) w[i-l] = L P[i] - Q[i] + Q[max(i-L, 0)].
                p_sum = np.zeros((n + 1, w.shape[1]))
                np.cumsum(w, axis=0, out=p_sum[1:])
                q_sum = np.zeros((n + 2, w.shape[1]))
                np.cumsum(p_sum, axis=0, out=q_sum[1:])
            rows = np.arange(first, n)
            acc = lag * p_sum[rows] - q_sum[rows] + q_sum[np.maximum(rows - lag, 0)]
        out.append(acc / (lag + 1))
    return out


def andrews_bartlett_lags(rho: float, nobs: int) -> float:
    """Andrews (1991) AR(1) plug-in bandwidth of the Bartlett kernel, in lags.

    ``alpha(1) = 4 rho^2 / ((1 - rho)^2 (1 + rho)^2)``, ``S_T = 1.1447 (alpha(1) T)^(1/3)``; the
    Newey-West weights ``1 - l/(L+1)`` are the Bartlett kernel at ``l / S_T``, so L = S_T - 1.
    """
    rho = float(np.clip(rho, -0.999999, 0.999999))
    if not np.isfinite(rho) or nobs < 2:
        return 0.0
    alpha = 4.0 * rho * rho / ((1.0 - rho) ** 2 * (1.0 + rho) ** 2)
    return max(0.0, 1.1447 * (alpha * nobs) ** (1.0 / 3.0) - 1.0)


class QRAccumulator:
    """Streamed Householder QR (TSQR) of ``[X | Y]`` plus the moments needed for inference.

    Parameters
    ----------
    n_features : int
        p, number of design columns (as given: include the column of ones for an intercept).
    n_targets : int
        k, number of targets fitted together (e.g. 3 for dx, dy, dz).
    feature_names, target_names : sequence of str, optional
        Column names, used to select columns and to label results. Default ``x0..x{p-1}`` and
        ``y`` (k = 1) or ``y0..y{k-1}``.
    precision : {"auto", "double", "double-double"}
        Arithmetic of the data pass (see the module notes). "auto" uses the Gram fast path
        while the equilibrated design is very well conditioned (kappa_eq <= 500), LAPACK
        Householder QR in double precision while the scaled design is well conditioned
        (kappa <= 1e6) and double-double otherwise; "double" is always LAPACK QR.
    hac_lags : None, True, "auto", int or sequence of int
        Also keep what autocorrelation-robust (Newey-West, HAC) inference needs, for these
        bandwidths (see :func:`hac_lag_grid`; default None: naive inference only). Rows are a
        time series in the order given; :meth:`end_series` starts a new one (another
        campaign), so no lag spans two series.

    Attributes
    ----------
    n_obs : int
        Rows accumulated so far.
    R_, R_lo_ : ndarray, (p+k, p+k)
        Upper-triangular factor of the *scaled* augmented matrix, ``R_ + R_lo_`` in
        double-double (``R_`` alone is its double rounding).
    scale_ : ndarray, (p+k,) or None
        Column scales (powers of two, fixed by the first chunk).
    extended_ : bool
        Whether the data pass has switched to double-double for good because the scaled design
        is ill-conditioned (the first 2(p+k) rows always go through double-double).
    gram_rows_ : int
        Rows that went through the Gram fast path (0: the factor is Householder QR's alone).
    column_min_, column_max_ : ndarray, (p,)
        Range of every design column until it is seen to vary (a column with min == max != 0
        is a constant: intercept); once min < max the range is no longer updated.
    target_mean_, target_css_ : ndarray, (k,)
        Weighted mean and weighted centred sum of squares of every target (Chan/Welford merge),
        for the total sum of squares without re-reading the data.
    weight_sum_ : float
        Sum of the row weights (equals ``n_obs`` when no weights were given).
    hac_lags_ : list of int or None
        Bandwidths of the autocorrelation statistics (None: not kept).

    Notes
    -----
    Row weights make it weighted least squares, as statsmodels' WLS defines it: each row enters
    the factor multiplied by ``sqrt(w)``; R² is centred on the weighted mean; ``df_resid`` is
    ``n_obs - p``, so weights are best normalised to a mean of one.

    Autocorrelation statistics (``hac_lags``): with ``a_i`` the scaled (and sqrt-weighted) row
    ``[x_i | y_i] / s`` and ``u_i = x_i (x) a_i`` (all products ``a_ij a_im``, j a design column),
    the score of any sub-model S and target t is ``g_i = x_iS e_i`` with ``e_i = a_i . c`` (c
    holds minus the coefficients on S and 1 on the target), so every entry of its lag-l
    autocovariance ``sum_i g_i g_{i-l}^T`` is a quadratic form in c of ``sum_i u_i u_{i-l}^T``.
    The accumulator keeps ``sum u_i u_i^T`` and, per bandwidth L, the Bartlett-weighted
    ``sum_i u_i (sum_{l<=L} (1 - l/(L+1)) u_{i-l})^T`` (the same for ``a_i``, which gives the
    residual's autocorrelation), carrying the last max(L) rows between chunks: the Newey-West
    sandwich of *every* sub-model, hence of every stepwise step, comes without re-reading the
    data. Memory: (1 + len(grid)) (p (p+k))^2 floats, so keep it for narrow designs. Being a
    quadratic form of raw products evaluated at the residual, the robust covariance would carry
    a relative error of about ``eps (|y| / |e|)^2``, which an ill-conditioned design (large,
    cancelling coefficients) turns into negative variances. So the statistics come in a
    second pass (:meth:`begin_hac`, :meth:`update_hac`, or :func:`accumulate_series` for data
    in memory), with the targets relative to a pilot, the full model's coefficients ``P``
    (``hac_pilot_``, scaled): ``a_i = [x_i | y_i - x_i P]``, and a sub-model's ``c`` gains
    ``P``. The full model's residual is then exact, and what remains is the rounding of any
    meat matrix, ``eps kappa^2`` relative in the design's weakest direction (statsmodels
    forms the same sum). Accumulators with different pilots still merge (an exact linear map).
    """

    def __init__(self, n_features: int, n_targets: int = 1, feature_names=None, target_names=None,
                 *, precision: str = "auto", hac_lags=None):
        if int(n_features) < 1 or int(n_targets) < 1:
            raise ValueError("n_features and n_targets must be at least 1")
        if precision not in _PRECISIONS:
            raise ValueError(f"precision must be one of {_PRECISIONS}, not {precision!r}")
        self.n_features = int(n_features)
        self.n_targets = int(n_targets)
        self.precision = precision
        self.feature_names = _names(feature_names, self.n_features,
                                    [f"x{i}" for i in range(self.n_features)], "feature_names")
        default_targets = ["y"] if self.n_targets == 1 else [f"y{j}" for j in range(self.n_targets)]
        self.target_names = _names(target_names, self.n_targets, default_targets, "target_names")
        q = self.n_features + self.n_targets
        self.n_obs = 0
        self.R_ = np.zeros((q, q))
        self.R_lo_ = np.zeros((q, q))
        self.scale_: np.ndarray | None = None
        self.extended_ = precision == "double-double"
        self.gram_rows_ = 0
        self._gram_ok = True
        self._gram_refusals = 0
        self.column_min_ = np.full(self.n_features, np.inf)
        self.column_max_ = np.full(self.n_features, -np.inf)
        self.target_mean_ = np.zeros(self.n_targets)
        self.target_css_ = np.zeros(self.n_targets)
        self.weight_sum_ = 0.0
        self.hac_lags_ = hac_lag_grid(hac_lags)
        self._hac_reset()

    def _hac_reset(self) -> None:
        p, q = self.n_features, self.n_features + self.n_targets
        if self.hac_lags_ is None:
            self.hac_g0_ = self.hac_k_ = self.hac_ka_ = self.hac_pilot_ = None
            self._hac_tail = None
            self.hac_frozen_ = False
            self.hac_n_obs_ = 0
            return
        nl = len(self.hac_lags_)
        self.hac_g0_ = np.zeros((p * q, p * q))          # sum u_i u_i^T
        self.hac_k_ = np.zeros((nl, p * q, p * q))       # sum u_i (Bartlett past of u)_i^T
        self.hac_ka_ = np.zeros((nl, q, q))              # sum a_i (Bartlett past of a)_i^T
        self._hac_tail = np.zeros((0, q))                # last max(L) scaled rows of the series
        self.hac_pilot_ = np.zeros((p, self.n_targets))  # scaled coefficients the targets are
                                                         # kept relative to (see Notes)
        self.hac_frozen_ = False                         # second pass: pilot fixed (begin_hac)
        self.hac_n_obs_ = 0                              # rows in the statistics

    # -- accumulation --------------------------------------------------------------------------

    def _rows(self, X_chunk, Y_chunk, weights, check: bool = True):
        """Validated (X, Y, w or None) of a chunk (``check=False``: finiteness not checked)."""
        p, k = self.n_features, self.n_targets
        X = _as_2d(X_chunk, p, "X_chunk")
        Y = _as_2d(Y_chunk, k, "Y_chunk")
        m = X.shape[0]
        if Y.shape[0] != m:
            raise ValueError(f"X_chunk has {m} rows but Y_chunk has {Y.shape[0]}")
        if m == 0:
            return X, Y, None
        if check:
            self._check_rows(X, Y)
        w = None
        if weights is not None:
            w = np.broadcast_to(np.asarray(weights, dtype=float), (m,))
            if not np.all(np.isfinite(w)) or np.any(w < 0):
                raise ValueError("weights must be finite and non-negative")
        return X, Y, w

    def _check_rows(self, X: np.ndarray, Y: np.ndarray, offset: int = 0) -> None:
        """InputError naming row and column of the first non-finite value (rows ``offset..``
        of the chunk being added)."""
        _check_finite(X, self.feature_names, self.n_obs + offset + 1, "feature")
        _check_finite(Y, self.target_names, self.n_obs + offset + 1, "target")

    def _gram_eligible(self) -> bool:
        return self.precision == "auto" and not self.extended_ and self._gram_ok

    def update(self, X_chunk, Y_chunk, weights=None) -> "QRAccumulator":
        """Add rows to the factor: ``X_chunk`` (m, p) and ``Y_chunk`` (m, k) (1-D allowed when
        p or k is 1).

        ``weights``: optional non-negative row weights, a scalar or (m,) (weighted least squares).
        Autocorrelation statistics come in a second pass (:meth:`begin_hac`).
        """
        p, k = self.n_features, self.n_targets
        # The Gram fast path checks finiteness on the Gram's diagonal (a NaN or inf anywhere
        # makes it non-finite) instead of a pass of its own over the chunk.
        X, Y, w = self._rows(X_chunk, Y_chunk, weights, check=not self._gram_eligible())
        m = X.shape[0]
        if m == 0:
            return self
        X_raw, Y_raw = X, Y
        if w is not None:
            root = np.sqrt(w)[:, None]
            X, Y = X * root, Y * root
        if self.scale_ is None:
            rms = np.sqrt(np.concatenate([np.einsum("ij,ij->j", X, X),
                                          np.einsum("ij,ij->j", Y, Y)]) / m)
            self.scale_ = _power_of_two_scale(rms)
        start = 0
        if self._gram_eligible():
            # Householder QR until the factor can judge the conditioning, then the Gram.
            start = min(m, max(0, max(_GRAM_MIN_ROWS, 4 * (p + k)) - self.n_obs))
            self._check_rows(X_raw[:start], Y_raw[:start])
            self._factor_rows(X[:start], Y[:start])
            if start < m and self._gram_eligible():
                if self._gram_rows(X[start:], Y[start:], X_raw[start:], Y_raw[start:], start):
                    start = m
            elif start < m:
                self._check_rows(X_raw[start:], Y_raw[start:], start)
        self._factor_rows(X[start:], Y[start:], self.n_obs + start)
        # Warm-up rows first: most columns vary there, and only the others are read after.
        self._update_range(X_raw[:_GRAM_MIN_ROWS])
        self._update_range(X_raw[_GRAM_MIN_ROWS:])
        if w is None:
            w_b = float(m)
            mean_b = Y_raw.mean(axis=0)
            css_b = np.sum((Y_raw - mean_b) ** 2, axis=0)
        else:
            w_b = float(w.sum())
            mean_b = (w @ Y_raw) / w_b if w_b > 0 else np.zeros(k)
            css_b = w @ (Y_raw - mean_b) ** 2
        self._merge_moments(w_b, mean_b, css_b)
        self.n_obs += m
        return self

    def _factor_rows(self, X: np.ndarray, Y: np.ndarray, n_before: int | None = None) -> None:
        """Householder QR of the (weighted) rows, block by block."""
        n_before = self.n_obs if n_before is None else n_before
        for start in range(0, X.shape[0], _QR_BLOCK_ROWS):
            stop = min(X.shape[0], start + _QR_BLOCK_ROWS)
            self._factor_block(X[start:stop], Y[start:stop], n_before + stop)

    def _update_range(self, X_raw: np.ndarray) -> None:
        """Column ranges for :attr:`constant_columns`. Only columns that have not varied yet
        are read: a column seen to vary can never become constant again, so its range is left
        as it was (one strided read of the few constant columns instead of two full passes)."""
        if not X_raw.shape[0]:
            return
        if not np.isfinite(self.column_min_).all():          # first rows
            self.column_min_ = np.minimum(self.column_min_, X_raw.min(axis=0))
            self.column_max_ = np.maximum(self.column_max_, X_raw.max(axis=0))
            return
        flat = np.flatnonzero(self.column_min_ == self.column_max_)
        if flat.size:
            part = X_raw[:, flat]
            self.column_min_[flat] = np.minimum(self.column_min_[flat], part.min(axis=0))
            self.column_max_[flat] = np.maximum(self.column_max_[flat], part.max(axis=0))

    def _gram_rows(self, X: np.ndarray, Y: np.ndarray, X_raw: np.ndarray,
                   Y_raw: np.ndarray, offset: int) -> bool:
        """Gram fast path: add the (weighted) rows through their Gram ``[X Y]^T [X Y]``
        (BLAS syrk/gemm, one pass at memory-bandwidth speed, 65536-row blocks) and a Cholesky
        of ``R^T R + G`` (scaled exactly by the power-of-two scales). Committed only if the
        equilibrated condition number of the new factor's design part stays <= _KAPPA_GRAM
        and every target's norm within _RESID_RATIO_GRAM times its residual's (module notes);
        otherwise nothing changes and False is returned (the caller factors the same rows by
        QR); after _GRAM_MAX_REFUSALS refusals in a row the fast path is off for good."""
        p, q = self.n_features, self.n_features + self.n_targets
        g = np.zeros((q, q))
        for start in range(0, X.shape[0], _BLOCK_ROWS):
            xb, yb = X[start:start + _BLOCK_ROWS], Y[start:start + _BLOCK_ROWS]
            g[:p, :p] += xb.T @ xb
            xy = xb.T @ yb
            g[:p, p:] += xy
            g[p:, :p] += xy.T
            g[p:, p:] += yb.T @ yb
        if not np.isfinite(np.diag(g)).all():
            self._check_rows(X_raw, Y_raw, offset)   # names the bad cell; else squares overflowed
            self._gram_ok = False
            return False
        g /= np.outer(self.scale_, self.scale_)  # exact: powers of two
        gram = self.R_.T @ self.R_ + g
        try:
            r = linalg.cholesky(gram, lower=False, check_finite=False)
            ok = (_equilibrated_cond(r[:p, :p]) <= _KAPPA_GRAM
                  and bool(np.all(np.linalg.norm(r[:, p:], axis=0)
                                  <= _RESID_RATIO_GRAM * np.linalg.norm(r[p:, p:], axis=0))))
        except linalg.LinAlgError:
            ok = False
        if not ok:
            self._gram_refusals += 1
            self._gram_ok = self._gram_refusals < _GRAM_MAX_REFUSALS
            return False
        self._gram_refusals = 0
        self.R_, self.R_lo_ = r, np.zeros((q, q))
        self.gram_rows_ += X.shape[0]
        return True

    def begin_hac(self) -> "QRAccumulator":
        """Start the second pass of the two-pass recipe; returns self.

        The pilot becomes the full model's coefficients from the factor (double-double, 0 on
        deficient columns) and stays there; the statistics restart empty. Then feed every row
        again, in the same series, with :meth:`update_hac`. For the full model the residual
        is then exactly the pilot's, and the robust covariance carries only the rounding of a
        sum of squares (relative ``eps kappa^2`` in the design's weakest direction, as any
        meat matrix), instead of the drift of a pilot that moves chunk by chunk.
        """
        if self.hac_lags_ is None:
            raise ValueError("this accumulator keeps no autocorrelation statistics (hac_lags)")
        if self.n_obs == 0:
            raise ValueError("begin_hac needs the factor of every row first (update)")
        pilot = self._exact_pilot()
        self._hac_reset()
        self.hac_pilot_ = pilot
        self.hac_frozen_ = True
        return self

    def update_hac(self, X_chunk, Y_chunk, weights=None) -> "QRAccumulator":
        """Second pass (after :meth:`begin_hac`): add rows to the autocorrelation statistics
        only, with the same weights as in the first pass. Returns self."""
        if not self.hac_frozen_:
            raise ValueError("call begin_hac after the first pass before update_hac")
        X, Y, w = self._rows(X_chunk, Y_chunk, weights)
        if X.shape[0] == 0:
            return self
        if w is not None:
            root = np.sqrt(w)[:, None]
            X, Y = X * root, Y * root
        self._hac_update(np.hstack([X, Y]) / self.scale_)
        return self

    def _exact_pilot(self) -> np.ndarray:
        """Scaled full-model coefficients (p, k), double-double solve, 0 on deficient columns."""
        p = self.n_features
        pilot = np.zeros((p, self.n_targets))
        diag = np.abs(np.diag((self.R_ + self.R_lo_)[:p, :p]))
        keep = [c for c in range(p) if c not in set(_deficient_columns(diag, self.n_obs))]
        for t in range(self.n_targets):
            th, tl, zh, zl, _ = self._subset_factor(keep, t)
            bad = _deficient_columns(np.abs(np.diag(th)), self.n_obs)
            cols = [c for i, c in enumerate(keep) if i not in set(bad)]
            if bad:
                th, tl, zh, zl, _ = self._subset_factor(cols, t)
            if cols:
                bh, bl = _dd_solve_upper(th, tl, zh, zl)
                pilot[cols, t] = bh + bl
        return pilot

    def _hac_update(self, a: np.ndarray) -> None:
        """Add the lagged products of the scaled rows ``a`` (m, q), targets taken relative to
        the pilot, to the HAC statistics."""
        p, q = self.n_features, self.n_features + self.n_targets
        a = a.copy()
        a[:, p:] -= a[:, :p] @ self.hac_pilot_
        top = max(self.hac_lags_)
        for start in range(0, a.shape[0], _HAC_BLOCK_ROWS):
            block = a[start:start + _HAC_BLOCK_ROWS]
            ext = np.vstack([self._hac_tail, block])
            first = self._hac_tail.shape[0]
            u = (ext[:, :p, None] * ext[:, None, :]).reshape(ext.shape[0], p * q)
            w = np.hstack([u, ext])
            u_new = u[first:]
            self.hac_g0_ += u_new.T @ u_new
            for i, past in enumerate(_bartlett_sums(w, first, self.hac_lags_)):
                self.hac_k_[i] += u_new.T @ past[:, :p * q]
                self.hac_ka_[i] += block.T @ past[:, p * q:]
            self._hac_tail = ext[-top:].copy()
        self.hac_n_obs_ += a.shape[0]

    def _hac_move_pilot(self, pilot: np.ndarray) -> None:
        """Re-express the statistics with targets relative to ``pilot`` instead of the current
        one: ``a -> a A`` with ``A = [[I, P_old - P_new], [0, I]]``, so ``u -> u (I (x) A)``."""
        p, q = self.n_features, self.n_features + self.n_targets
        delta = self.hac_pilot_ - pilot
        self.hac_pilot_ = np.array(pilot, dtype=float)
        if not np.any(delta):
            return
        A = np.eye(q)
        A[:p, p:] = delta
        nl = len(self.hac_lags_)

        def both_sides(m: np.ndarray, count: int) -> np.ndarray:   # (I(x)A)^T m (I(x)A)
            m = m.reshape(count, p, q, p, q) @ A                  # right factor, last axis
            m = np.einsum("cimjn,ma->ciajn", m, A, optimize=True)
            return m.reshape(count, p * q, p * q)

        self.hac_g0_ = both_sides(self.hac_g0_, 1)[0]
        self.hac_k_ = both_sides(self.hac_k_, nl)
        self.hac_ka_ = A.T @ self.hac_ka_ @ A
        self._hac_tail = self._hac_tail @ A

    def end_series(self) -> "QRAccumulator":
        """Rows added from now on start a new time series (e.g. the next campaign): no lag of
        the autocorrelation statistics links them to the rows before. Returns self."""
        if self._hac_tail is not None:
            self._hac_tail = np.zeros((0, self.n_features + self.n_targets))
        return self

    def _scaled_block(self, X: np.ndarray, Y: np.ndarray, top: np.ndarray) -> np.ndarray:
        """Fortran-ordered ``[top; [X Y] / scale]`` (exact: the scales are powers of two)."""
        p, q = self.n_features, self.n_features + self.n_targets
        t = top.shape[0]
        block = np.empty((t + X.shape[0], q), order="F")
        block[:t] = top
        np.divide(X, self.scale_[:p], out=block[t:, :p])
        np.divide(Y, self.scale_[p:], out=block[t:, p:])
        return block

    def _factor_block(self, X: np.ndarray, Y: np.ndarray, n_after: int) -> None:
        q = self.n_features + self.n_targets
        extended = self.extended_ or (self.precision == "auto" and n_after < 2 * q)
        if not extended:
            candidate = _lapack_triangle(self._scaled_block(X, Y, self.R_), q)
            if self.precision == "auto" and self._ill_conditioned(candidate, n_after):
                self.extended_ = extended = True
            else:
                self.R_, self.R_lo_ = candidate, np.zeros((q, q))
        if extended:
            rh, rl = self.R_, self.R_lo_
            for start in range(0, X.shape[0], _DD_BLOCK_ROWS):
                stop = min(X.shape[0], start + _DD_BLOCK_ROWS)
                block = self._scaled_block(X[start:stop], Y[start:stop], rh)
                lo = np.zeros_like(block)
                lo[:q] = rl
                rh, rl = _dd_qr_r(block, lo)
            self.R_, self.R_lo_ = rh, rl

    def _ill_conditioned(self, r: np.ndarray, nobs: int) -> bool:
        """kappa_2 of the scaled design's triangle above the threshold (deficient columns aside)."""
        p = self.n_features
        t = r[:p, :p]
        keep = np.ones(p, dtype=bool)
        keep[_deficient_columns(np.abs(np.diag(t)), nobs)] = False
        if not keep.any():
            return False
        return bool(np.linalg.cond(t[np.ix_(keep, keep)]) > _KAPPA_EXTENDED)

    def _merge_moments(self, w_b: float, mean_b: np.ndarray, css_b: np.ndarray) -> None:
        """Chan et al. pairwise update of the weighted mean and centred sum of squares."""
        w_a = self.weight_sum_
        w = w_a + w_b
        if w <= 0:
            return
        delta = mean_b - self.target_mean_
        self.target_mean_ = self.target_mean_ + delta * (w_b / w)
        self.target_css_ = self.target_css_ + css_b + delta * delta * (w_a * w_b / w)
        self.weight_sum_ = w

    def merge(self, other: "QRAccumulator", weight: float = 1.0) -> "QRAccumulator":
        """Fold ``other`` (same columns) into this accumulator and return self.

        ``weight`` multiplies the weight of every row of ``other`` (e.g. to pool campaigns with
        equal total weight after accumulating each one on its own).

        The two triangles are stacked and re-factored in double-double; ``other``'s columns are
        first brought to this accumulator's scales (an exact power-of-two rescaling). The order
        of merging does not matter beyond double-double rounding. This is the combine step of a
        reduction over data partitions (e.g. Dask), with :meth:`to_dict` / :meth:`from_dict` to
        ship the state.
        """
        if (other.n_features, other.n_targets) != (self.n_features, self.n_targets):
            raise ValueError("cannot merge accumulators with different numbers of columns")
        if other.feature_names != self.feature_names or other.target_names != self.target_names:
            raise ValueError("cannot merge accumulators with different column names")
        if not (np.isfinite(weight) and weight >= 0):
            raise ValueError("weight must be finite and non-negative")
        if other.n_obs == 0:
            return self
        self.extended_ = self.extended_ or other.extended_
        root = float(np.sqrt(weight))
        if self.n_obs == 0:
            for name in ("R_", "R_lo_", "scale_", "column_min_", "column_max_", "target_mean_",
                         "target_css_"):
                setattr(self, name, getattr(other, name).copy())
            self.n_obs = other.n_obs
            self.gram_rows_ = other.gram_rows_
            self.weight_sum_ = other.weight_sum_ * weight
            self.target_css_ = self.target_css_ * weight
            self.R_, self.R_lo_ = self.R_ * root, self.R_lo_ * root
            self.hac_lags_ = None if other.hac_lags_ is None else list(other.hac_lags_)
            self._hac_reset()
            if self.hac_lags_ is not None:
                # a row's weight w scales a_i by sqrt(w), u_i = x_i (x) a_i by w
                self.hac_g0_ = other.hac_g0_ * weight ** 2
                self.hac_k_ = other.hac_k_ * weight ** 2
                self.hac_ka_ = other.hac_ka_ * weight
                self.hac_pilot_ = other.hac_pilot_.copy()
                self.hac_frozen_ = other.hac_frozen_
                self.hac_n_obs_ = other.hac_n_obs_
            return self
        self._merge_hac(other, weight)
        ratio = root * other.scale_ / self.scale_
        self.R_, self.R_lo_ = _dd_qr_r(np.vstack([self.R_, other.R_ * ratio]),
                                       np.vstack([self.R_lo_, other.R_lo_ * ratio]))
        self.column_min_ = np.minimum(self.column_min_, other.column_min_)
        self.column_max_ = np.maximum(self.column_max_, other.column_max_)
        self._merge_moments(other.weight_sum_ * weight, other.target_mean_, other.target_css_ * weight)
        self.n_obs += other.n_obs
        self.gram_rows_ += other.gram_rows_
        return self

    def _merge_hac(self, other: "QRAccumulator", weight: float) -> None:
        """Add ``other``'s autocorrelation statistics (brought to this accumulator's scales).

        The two are separate series: no lag spans them (merging pieces of one recording drops
        the few lags across the cut). If only one side has statistics, the result has none.
        """
        if self.hac_lags_ is None or other.hac_lags_ is None:
            self.hac_lags_ = None
            self._hac_reset()
            return
        if list(other.hac_lags_) != list(self.hac_lags_):
            raise ValueError(f"cannot merge autocorrelation statistics of different bandwidths "
                             f"({other.hac_lags_} vs {self.hac_lags_})")
        p = self.n_features
        ratio = other.scale_ / self.scale_
        r_u = (ratio[:p, None] * ratio[None, :]).reshape(-1)       # u = x (x) a
        f_u = weight ** 2 * np.outer(r_u, r_u)                    # u scales by the weight
        # Bring other's statistics to its pilot expressed in this accumulator's scales, then
        # both to this one's pilot (exact algebra; small rounding when the pilots are close).
        other_pilot = other.hac_pilot_ * ratio[p:][None, :] / ratio[:p, None]
        mine = self.hac_pilot_
        self._hac_move_pilot(other_pilot)
        self.hac_g0_ += other.hac_g0_ * f_u
        self.hac_k_ += other.hac_k_ * f_u[None]
        self.hac_ka_ += other.hac_ka_ * (weight * np.outer(ratio, ratio))[None]
        self._hac_move_pilot(mine)
        self.hac_n_obs_ += other.hac_n_obs_
        self.end_series()

    def copy(self) -> "QRAccumulator":
        return QRAccumulator.from_dict(self.to_dict())

    # -- column bookkeeping --------------------------------------------------------------------

    @property
    def constant_columns(self) -> list[int]:
        """Indices of design columns that are constant and non-zero over all rows seen."""
        if self.n_obs == 0:
            return []
        const = (self.column_min_ == self.column_max_) & (self.column_max_ != 0)
        return [int(i) for i in np.flatnonzero(const)]

    def column_index(self, column) -> int:
        """Index of a design column given by index or name."""
        if isinstance(column, (bool, np.bool_)):
            raise TypeError(f"column must be an index or a name, not {column!r}")
        if isinstance(column, (int, np.integer)):
            if not 0 <= int(column) < self.n_features:
                raise ValueError(f"column index {column} out of range 0..{self.n_features - 1}")
            return int(column)
        try:
            return self.feature_names.index(str(column))
        except ValueError:
            raise ValueError(f"unknown column {column!r}; columns are {self.feature_names}") from None

    def column_indices(self, columns) -> list[int]:
        """Indices for ``columns`` (None = all, one index/name, or a sequence), in the given order."""
        if columns is None:
            return list(range(self.n_features))
        if isinstance(columns, (str, int, np.integer)):
            columns = [columns]
        idx = [self.column_index(c) for c in columns]
        if len(set(idx)) != len(idx):
            raise ValueError(f"duplicate columns in {list(columns)}")
        return idx

    def target_index(self, target) -> int:
        """Index of a target given by index or name."""
        if isinstance(target, (int, np.integer)) and not isinstance(target, (bool, np.bool_)):
            if not 0 <= int(target) < self.n_targets:
                raise ValueError(f"target index {target} out of range 0..{self.n_targets - 1}")
            return int(target)
        try:
            return self.target_names.index(str(target))
        except ValueError:
            raise ValueError(f"unknown target {target!r}; targets are {self.target_names}") from None

    # -- sub-model factors ---------------------------------------------------------------------

    def _subset_factor(self, cols: list[int], t: int):
        """Double-double QR factor of the scaled ``[X_S | y_t]``, from R alone.

        Returns (T_hi, T_lo, z_hi, z_lo, rho) with ``T b = z`` the scaled normal solution and
        ``rho^2`` the scaled residual sum of squares.
        """
        m = len(cols)
        sel = cols + [self.n_features + t]
        rh, rl = _dd_qr_r(self.R_[:, sel], self.R_lo_[:, sel])
        return rh[:m, :m], rl[:m, :m], rh[:m, m], rl[:m, m], float(abs(rh[m, m]))

    def _well_conditioned(self, limit: float = _KAPPA_EXTENDED) -> bool:
        """Whether the factor is well conditioned enough for double-precision sub-model
        statistics (Householder QR of the factor's columns: relative error ~ kappa u, 1e-10 at
        the limit, far below anything a partial F test resolves): equilibrated kappa of R
        (design and targets) <= ``limit`` and the data pass never needed double-double."""
        return (not self.extended_ and self.n_obs > 0
                and _equilibrated_cond(self.R_ + self.R_lo_) <= limit)

    def _tss(self, t: int) -> tuple[float, float]:
        """(centred, uncentred) total sum of squares of target t."""
        css = float(self.target_css_[t])
        return css, css + self.weight_sum_ * float(self.target_mean_[t]) ** 2

    def ols(self, columns=None, target=0) -> "OLSResults":
        """Shorthand for :func:`ols_from_factor` on this accumulator."""
        return ols_from_factor(self, columns, target)

    # -- serialisation -------------------------------------------------------------------------

    def to_dict(self) -> dict:
        """Plain JSON-able state (lists, floats, ints, strings, bools): see :meth:`from_dict`."""
        return {
            "kind": "fbgcomp.regression.QRAccumulator",
            "version": 1,
            "n_features": self.n_features,
            "n_targets": self.n_targets,
            "feature_names": list(self.feature_names),
            "target_names": list(self.target_names),
            "precision": self.precision,
            "extended": bool(self.extended_),
            "gram_rows": int(self.gram_rows_),
            "n_obs": int(self.n_obs),
            "scale": None if self.scale_ is None else self.scale_.tolist(),
            "R": self.R_.tolist(),
            "R_lo": self.R_lo_.tolist(),
            "column_min": self.column_min_.tolist() if self.n_obs else None,
            "column_max": self.column_max_.tolist() if self.n_obs else None,
            "target_mean": self.target_mean_.tolist(),
            "target_css": self.target_css_.tolist(),
            "weight_sum": float(self.weight_sum_),
            "hac": None if self.hac_lags_ is None else {
                "lags": list(self.hac_lags_), "g0": self.hac_g0_.tolist(),
                "k": self.hac_k_.tolist(), "ka": self.hac_ka_.tolist(),
                "tail": self._hac_tail.tolist(), "pilot": self.hac_pilot_.tolist(),
                "frozen": bool(self.hac_frozen_), "n_obs": int(self.hac_n_obs_)},
        }

    @classmethod
    def from_dict(cls, state: dict) -> "QRAccumulator":
        """Rebuild an accumulator from :meth:`to_dict` output (e.g. after a JSON round trip)."""
        try:
            hac = state.get("hac")
            acc = cls(state["n_features"], state["n_targets"], state["feature_names"],
                      state["target_names"], precision=state.get("precision", "auto"),
                      hac_lags=None if hac is None else hac["lags"])
            q = acc.n_features + acc.n_targets
            acc.n_obs = int(state["n_obs"])
            acc.extended_ = bool(state.get("extended", acc.extended_))
            acc.gram_rows_ = int(state.get("gram_rows", 0))
            acc.R_ = _field_array(state, "R", (q, q))
            acc.R_lo_ = (_field_array(state, "R_lo", (q, q)) if state.get("R_lo") is not None
                         else np.zeros((q, q)))
            if acc.n_obs:
                acc.scale_ = _field_array(state, "scale", (q,))
                acc.column_min_ = _field_array(state, "column_min", (acc.n_features,))
                acc.column_max_ = _field_array(state, "column_max", (acc.n_features,))
            acc.target_mean_ = _field_array(state, "target_mean", (acc.n_targets,))
            acc.target_css_ = _field_array(state, "target_css", (acc.n_targets,))
            acc.weight_sum_ = float(state.get("weight_sum", acc.n_obs))
            if hac is not None:
                p, q, nl = acc.n_features, q, len(acc.hac_lags_)
                acc.hac_g0_ = _field_array(hac, "g0", (p * q, p * q))
                acc.hac_k_ = _field_array(hac, "k", (nl, p * q, p * q))
                acc.hac_ka_ = _field_array(hac, "ka", (nl, q, q))
                tail = np.asarray(hac.get("tail") or np.zeros((0, q)), dtype=float)
                acc._hac_tail = tail.reshape(-1, q)
                if hac.get("pilot") is not None:
                    acc.hac_pilot_ = _field_array(hac, "pilot", (acc.n_features, acc.n_targets))
                acc.hac_frozen_ = bool(hac.get("frozen", False))
                acc.hac_n_obs_ = int(hac.get("n_obs", acc.n_obs))
        except KeyError as exc:
            raise InputError(f"missing field {exc.args[0]!r} in accumulator state",
                             column=f"field {exc.args[0]}") from None
        return acc

    def __repr__(self) -> str:
        return (f"QRAccumulator(n_features={self.n_features}, n_targets={self.n_targets}, "
                f"n_obs={self.n_obs})")


def _field_array(state: dict, key: str, shape: tuple[int, ...]) -> np.ndarray:
    try:
        arr = np.asarray(state[key], dtype=float)
    except (TypeError, ValueError):
        raise InputError(f"field {key!r} is not numeric", column=f"field {key}") from None
    if arr.shape != shape:
        raise InputError(f"field {key!r} has shape {arr.shape}, expected {shape}",
                         column=f"field {key}")
    return arr


# --------------------------------------------------------------------------------------------
# Autocorrelation-robust (Newey-West) covariance from the accumulated statistics
# --------------------------------------------------------------------------------------------

def accumulate_series(acc: QRAccumulator, series, chunk_rows: int = 100_000) -> QRAccumulator:
    """Fill ``acc`` from in-memory time series, in the two passes its statistics need.

    ``series``: a sequence of ``(X (n, p), Y (n, k), weight)`` (weight a scalar, (n,) or None),
    one per independent recording (e.g. campaign). Pass one adds every row to the factor; when
    the accumulator keeps autocorrelation statistics, pass two adds them relative to the full
    model's coefficients (:meth:`QRAccumulator.begin_hac`), no lag spanning two series.
    """
    series = list(series)

    def chunks():
        for X, Y, w in series:
            for lo in range(0, len(X), chunk_rows):
                part = w if w is None or np.ndim(w) == 0 else w[lo:lo + chunk_rows]
                yield X[lo:lo + chunk_rows], Y[lo:lo + chunk_rows], part
            yield None

    for chunk in chunks():
        if chunk is not None:
            acc.update(*chunk[:2], weights=chunk[2])
    if acc.hac_lags_ is not None and acc.n_obs:
        acc.begin_hac()
        for chunk in chunks():
            if chunk is None:
                acc.end_series()
            else:
                acc.update_hac(*chunk[:2], weights=chunk[2])
    return acc


def _resolve_cov_type(acc: "QRAccumulator", cov_type) -> str:
    if cov_type is None:
        cov_type = "HAC" if acc.hac_lags_ is not None else "nonrobust"
    if cov_type not in COV_TYPES:
        raise ValueError(f"cov_type must be one of {COV_TYPES}, not {cov_type!r}")
    if cov_type == "HAC" and acc.hac_lags_ is None:
        raise ValueError("cov_type='HAC' needs an accumulator created with hac_lags (it keeps the "
                         "lagged score sums); pass cov_type='nonrobust' for naive i.i.d. inference")
    if cov_type == "HAC" and acc.hac_n_obs_ != acc.n_obs:
        raise ValueError(f"the autocorrelation statistics cover {acc.hac_n_obs_} of the "
                         f"{acc.n_obs} rows in the factor: feed every row to update_hac after "
                         f"begin_hac (or use accumulate_series)")
    return cov_type


def _choose_lag(acc: "QRAccumulator", maxlags, rho: float) -> int:
    grid = acc.hac_lags_
    if maxlags is None or (isinstance(maxlags, str) and maxlags == "auto"):
        want = andrews_bartlett_lags(rho, acc.n_obs)
        for lag in grid:
            if lag >= want:
                return lag
        return grid[-1]
    lag = int(maxlags)
    if lag not in grid:
        raise ValueError(f"maxlags {lag} is not among the accumulated bandwidths {grid}")
    return lag


def _hac_cov_scaled(acc: "QRAccumulator", cols: list[int], t: int, beta_s: np.ndarray,
                    r_inv: np.ndarray, ssr_s: float, maxlags=None) -> tuple[np.ndarray, dict]:
    """Newey-West covariance of the *scaled* coefficients of the sub-model ``cols`` on target t.

    ``beta_s``: scaled coefficients; ``r_inv``: inverse of its scaled triangular factor;
    ``ssr_s``: scaled residual sum of squares. Returns the covariance and a dict with the
    bandwidth ``maxlags``, the residual's lag-1 autocorrelation ``rho1`` and the effective
    sample size ``n_eff`` = n / (residual long-run variance / variance) at that bandwidth.
    """
    p, q = acc.n_features, acc.n_features + acc.n_targets
    # Targets are kept relative to the pilot P (a_y = y - x P): e = a_y + x (P - b)
    c = np.zeros(q)
    c[:p] = acc.hac_pilot_[:, t]
    c[cols] -= np.asarray(beta_s, dtype=float)
    c[p + t] = 1.0
    i1 = acc.hac_lags_.index(1)
    # hac_ka_ at L = 1 holds (1/2) sum a_i a_{i-1}^T
    rho = 2.0 * float(c @ acc.hac_ka_[i1] @ c) / ssr_s if ssr_s > 0 else 0.0
    lag = _choose_lag(acc, maxlags, rho)
    il = acc.hac_lags_.index(lag)
    lrv = ssr_s + 2.0 * float(c @ acc.hac_ka_[il] @ c)
    n_eff = acc.n_obs * ssr_s / lrv if lrv > 0 else math.nan
    k = acc.hac_k_[il]
    meat4 = (acc.hac_g0_ + k + k.T).reshape(p, q, p, q)
    sub = meat4[np.ix_(cols, range(q), cols, range(q))]
    omega = np.einsum("imjn,m,n->ij", sub, c, c)
    bread = r_inv @ r_inv.T
    cov = bread @ omega @ bread
    info = {"kernel": "bartlett", "maxlags": int(lag), "rho1": float(rho),
            "n_eff": float(n_eff), "bandwidth": "andrews-ar1" if maxlags in (None, "auto")
            else "fixed"}
    return (cov + cov.T) / 2.0, info


def _double_subset(acc: "QRAccumulator", cols: list[int], t: int):
    """Double-precision factor of the sub-model: (T, scaled beta, T^-1, scaled SSR).

    Enough for test statistics (the double-double path is kept for reported coefficients)."""
    m = len(cols)
    sel = cols + [acc.n_features + t]
    r = np.linalg.qr(acc.R_[:, sel] + acc.R_lo_[:, sel], mode="r")
    if r.shape[0] < m + 1:
        r = np.vstack([r, np.zeros((m + 1 - r.shape[0], m + 1))])
    tri = np.triu(r[:m, :m])
    r_inv = linalg.lapack.dtrtri(tri, lower=0)[0]
    beta = r_inv @ r[:m, m]
    return tri, beta, r_inv, float(r[m, m]) ** 2


# --------------------------------------------------------------------------------------------
# Results
# --------------------------------------------------------------------------------------------

class OLSResults:
    """Results of an OLS fit, in the statsmodels vocabulary (paper Table 1 style summary).

    Built from the scaled triangular factor ``r_factor`` (T, with ``T^T T = X_s^T X_s`` and
    ``X_s = X / feature_scale``), so covariances and prediction variances are computed through
    the triangular inverse ``T^-1`` (``(X_s^T X_s)^-1 = T^-1 T^-T``), never by inverting
    ``X^T X``. The summary is the coefficient table of the paper's Table 1 (estimate, standard
    error) with t, p and confidence limits added. Normally obtained from
    :func:`ols`, :func:`ols_from_factor` or :meth:`from_dict`.

    ``cov_type``: "nonrobust" is the textbook ``sigma^2 (X^T X)^-1``, right only for independent
    errors. "HAC" (given ``robust_cov``, the Newey-West sandwich, statsmodels'
    ``cov_type='HAC'`` without small-sample correction) is right for autocorrelated errors
    (slow thermal drifts sampled every second): ``bse``, t, p, confidence and prediction
    intervals and the overall test (then a Wald F on the non-constant terms) all use it;
    ``cov_kwds`` holds its bandwidth, the residual's lag-1 autocorrelation and the effective
    sample size.

    Attributes
    ----------
    params, bse, tvalues, pvalues : ndarray or pandas Series
        Estimates, standard errors, t statistics and two-sided p-values: a pandas Series
        indexed by the term names when the fit was given names (:func:`ols` with a DataFrame
        or ``feature_names``), as statsmodels does for pandas input; plain arrays otherwise.
    resid, fittedvalues : ndarray or pandas Series
        Residuals and fitted values of the rows fitted; only when the rows were given in
        memory (:func:`ols`): a fit from the accumulated factor holds no rows.
    llf, aic, bic : float
        Gaussian log-likelihood ``-n/2 (log(2 pi SSR/n) + 1)`` and the information criteria
        ``-2 llf + 2 k``, ``-2 llf + log(n) k`` with ``k = df_model + k_constant`` (the number
        of coefficients), statsmodels OLS's definitions. For a weighted accumulator they are
        those of the sqrt(w)-scaled rows (statsmodels' WLS adds ``sum log(w) / 2`` to llf).
    ssr, ess, centered_tss, uncentered_tss : float
        Residual, explained and total sums of squares (ESS is relative to the centred total
        when the model has a constant column, to the uncentred one otherwise, as statsmodels).
    rsquared, rsquared_adj, fvalue, f_pvalue : float
    resid_sd : float
        sqrt(SSR / df_resid), the residual standard deviation ("standard error of regression").
    df_model, df_resid, nobs : int
    k_constant : int
        1 if the design contains a constant column, else 0.
    """

    def __init__(self, params, r_factor, feature_scale, *, ssr: float, nobs: int, k_constant: int,
                 centered_tss: float, uncentered_tss: float, feature_names: Sequence[str],
                 target_name: str = "y", cov_type: str = "nonrobust", robust_cov=None,
                 cov_kwds: dict | None = None, const_index: int | None = None,
                 named: bool = False, data=None):
        self._params = np.asarray(params, dtype=float).copy()
        # named: params & co. as pandas Series; data: (X, y, row index or None) of ols()
        self.named = bool(named)
        self._data = data
        self._r = np.triu(np.asarray(r_factor, dtype=float))
        self._scale = np.asarray(feature_scale, dtype=float).copy()
        m = self._params.size
        if self._r.shape != (m, m) or self._scale.shape != (m,):
            raise ValueError("params, r_factor and feature_scale sizes disagree")
        self.feature_names = list(feature_names)
        self.target_name = str(target_name)
        self.nobs = int(nobs)
        self.k_constant = int(k_constant)
        self.ssr = float(ssr)
        self.centered_tss = float(centered_tss)
        self.uncentered_tss = float(uncentered_tss)
        self.df_resid = self.nobs - m
        self.df_model = m - self.k_constant
        if cov_type not in COV_TYPES:
            raise ValueError(f"cov_type must be one of {COV_TYPES}, not {cov_type!r}")
        if (cov_type == "HAC") != (robust_cov is not None):
            raise ValueError("cov_type 'HAC' goes with a robust_cov matrix, 'nonrobust' without")
        self.cov_type = cov_type
        self.cov_kwds = dict(cov_kwds or {})
        self.const_index = None if const_index is None else int(const_index)
        self._robust_cov = (None if robust_cov is None
                            else np.asarray(robust_cov, dtype=float).reshape(m, m).copy())

        with np.errstate(divide="ignore", invalid="ignore"):
            self.mse_resid = self.ssr / self.df_resid if self.df_resid > 0 else math.nan
            self.resid_sd = math.sqrt(self.mse_resid) if self.df_resid > 0 else math.nan
            # Rows of T^-1 give sqrt(diag((X_s^T X_s)^-1)) without forming the inverse product.
            # LAPACK trtri: the triangular inverse is computed to high relative accuracy.
            self._r_inv = linalg.lapack.dtrtri(self._r, lower=0)[0] if m else np.zeros((0, 0))
            self.bse_nonrobust = self.resid_sd * np.linalg.norm(self._r_inv, axis=1) / self._scale
            self._bse = (self.bse_nonrobust if self._robust_cov is None
                        else np.sqrt(np.clip(np.diag(self._robust_cov), 0.0, None)))
            self._tvalues = self._params / self._bse
            self._pvalues = 2.0 * stats.t.sf(np.abs(self._tvalues), self.df_resid)
            tss = self.centered_tss if self.k_constant else self.uncentered_tss
            self.ess = tss - self.ssr
            self.rsquared = 1.0 - self.ssr / tss if tss > 0 else math.nan
            self.rsquared_adj = (1.0 - (self.nobs - self.k_constant) / self.df_resid
                                 * (1.0 - self.rsquared)) if self.df_resid > 0 else math.nan
            if self.df_model > 0 and self.df_resid > 0:
                self.mse_model = self.ess / self.df_model
                self.fvalue = float(self.mse_model / self.mse_resid)
                if self._robust_cov is not None:
                    self.fvalue = self._wald_f()
                self.f_pvalue = float(stats.f.sf(self.fvalue, self.df_model, self.df_resid))
            else:
                self.mse_model = self.fvalue = self.f_pvalue = math.nan

    # -- statsmodels-style views -------------------------------------------------------------

    def _series(self, values: np.ndarray):
        if not self.named:
            return values
        import pandas as pd

        return pd.Series(values, index=list(self.feature_names), dtype=float)

    @property
    def params(self):
        return self._series(self._params)

    @property
    def bse(self):
        return self._series(self._bse)

    @property
    def tvalues(self):
        return self._series(self._tvalues)

    @property
    def pvalues(self):
        return self._series(self._pvalues)

    def _rows(self, values: np.ndarray):
        if not self.named:
            return values
        import pandas as pd

        index = self._data[2]
        return pd.Series(values, index=index, name=self.target_name, dtype=float)

    def _need_data(self, what: str):
        if self._data is None:
            raise AttributeError(f"{what} needs the fitted rows: this fit comes from an "
                                 f"accumulated factor (or a saved model), which keeps none; fit "
                                 f"with ols(X, y) or compute y - res.predict(X)")
        return self._data

    @property
    def fittedvalues(self):
        """Fitted values of the rows fitted (``X @ params``)."""
        X, _, _ = self._need_data("fittedvalues")
        return self._rows(X @ self._params)

    @property
    def resid(self):
        """Residuals ``y - X @ params`` of the rows fitted."""
        X, y, _ = self._need_data("resid")
        return self._rows(y - X @ self._params)

    @property
    def llf(self) -> float:
        """Gaussian log-likelihood at the estimates (statsmodels OLS ``llf``)."""
        n = self.nobs
        if n <= 0 or self.ssr <= 0:
            return math.inf if n > 0 else math.nan
        return -0.5 * n * (math.log(2.0 * math.pi * self.ssr / n) + 1.0)

    @property
    def aic(self) -> float:
        """Akaike information criterion ``-2 llf + 2 k``, k the number of coefficients."""
        return -2.0 * self.llf + 2.0 * (self.df_model + self.k_constant)

    @property
    def bic(self) -> float:
        """Bayesian information criterion ``-2 llf + log(n) k``."""
        return -2.0 * self.llf + math.log(self.nobs) * (self.df_model + self.k_constant)

    def _wald_f(self) -> float:
        """Wald F of "every non-constant coefficient is 0" with the robust covariance."""
        keep = [i for i in range(self._params.size) if i != self.const_index]
        if self.k_constant and self.const_index is None:
            return math.nan
        b = self._params[keep]
        v = self._robust_cov[np.ix_(keep, keep)]
        try:
            stat = float(b @ np.linalg.solve(v, b))
        except np.linalg.LinAlgError:
            return math.nan
        return stat / len(keep)

    # -- inference -----------------------------------------------------------------------------

    def cov_params(self) -> np.ndarray:
        """Covariance of the coefficients: the Newey-West sandwich when ``cov_type`` is "HAC",
        else sigma^2 (X^T X)^-1 = sigma^2 T^-1 T^-T, unscaled."""
        if self._robust_cov is not None:
            return self._robust_cov.copy()
        return self.cov_params_nonrobust()

    def cov_params_nonrobust(self) -> np.ndarray:
        """The naive i.i.d. covariance sigma^2 (X^T X)^-1, whatever ``cov_type``."""
        g = self._r_inv @ self._r_inv.T
        return self.mse_resid * g / np.outer(self._scale, self._scale)

    def conf_int(self, alpha: float = 0.05):
        """(m, 2) two-sided 1 - alpha Student-t intervals for the coefficients: an array, or a
        DataFrame indexed by the term names with columns 0 and 1 when the fit is named (as
        statsmodels)."""
        q = stats.t.ppf(1.0 - alpha / 2.0, self.df_resid)
        ci = np.column_stack([self._params - q * self._bse, self._params + q * self._bse])
        if not self.named:
            return ci
        import pandas as pd

        return pd.DataFrame(ci, index=list(self.feature_names), columns=[0, 1])

    def _design(self, X) -> np.ndarray:
        X = np.asarray(X, dtype=float)
        m = self._params.size
        if X.ndim == 1:
            X = X[:, None] if m == 1 else X[None, :]
        if X.ndim != 2 or X.shape[1] != m:
            raise ValueError(f"X must have {m} columns ({self.feature_names}), got shape {X.shape}")
        return X

    def predict(self, X) -> np.ndarray:
        """Fitted values ``X @ params`` for design rows X (n, m); 1-D X is one row (or column if m = 1)."""
        return self._design(X) @ self._params

    def prediction_interval(self, X, alpha: float = 0.05) -> tuple[np.ndarray, np.ndarray]:
        """(lower, upper) bounds containing a *new* observation with probability 1 - alpha.

        ``yhat +- t_{1-alpha/2, df_resid} * sqrt(s^2 + x Cov x^T)``. Naive: ``x Cov x^T =
        s^2 ||(x / scale) T^-1||^2``, the squared norm of the row ``x T^-1`` (never
        ``x (X^T X)^-1 x^T``), stable on ill-conditioned designs. HAC: the robust covariance,
        applied to the scaled row.
        """
        X = self._design(X)
        zs = X / self._scale
        if self._robust_cov is None:
            z = zs @ self._r_inv
            var_fit = self.mse_resid * np.sum(z * z, axis=1)
        else:
            cov_s = self._robust_cov * np.outer(self._scale, self._scale)
            var_fit = np.clip(np.einsum("ni,ij,nj->n", zs, cov_s, zs), 0.0, None)
        half = (stats.t.ppf(1.0 - alpha / 2.0, self.df_resid)
                * np.sqrt(self.mse_resid + var_fit))
        yhat = X @ self._params
        return yhat - half, yhat + half

    def anova(self):
        """ANOVA table (pandas DataFrame): Regression, Residual and Total rows.

        Columns df, sum_sq, mean_sq, F, PR(>F). With a constant in the model the total is the
        centred sum of squares on n - 1 df; otherwise the uncentred one on n df. This is the
        overall test behind the paper's "stepwise regression with ANOVA" (section 3).
        """
        import pandas as pd

        total_df = self.nobs - self.k_constant
        total_ss = self.ess + self.ssr
        return pd.DataFrame(
            {"df": [self.df_model, self.df_resid, total_df],
             "sum_sq": [self.ess, self.ssr, total_ss],
             "mean_sq": [self.mse_model, self.mse_resid, math.nan],
             "F": [self.fvalue, math.nan, math.nan],
             "PR(>F)": [self.f_pvalue, math.nan, math.nan]},
            index=["Regression", "Residual", "Total"])

    def summary(self) -> str:
        """Coefficient table in the style of the paper's Table 1, plus the overall fit figures."""
        ci = np.asarray(self.conf_int())
        width = max([len("term")] + [len(n) for n in self.feature_names])
        head = (f"{'term':<{width}}  {'estimate':>13} {'std error':>12} {'t':>9} {'P>|t|':>9}"
                f" {'[0.025':>13} {'0.975]':>13}")
        rule = "=" * len(head)
        lines = [f"OLS regression of {self.target_name} on {self._params.size} terms".center(len(head)),
                 rule, head, "-" * len(head)]
        for i, name in enumerate(self.feature_names):
            lines.append(f"{name:<{width}}  {self._params[i]:>13.6g} {self._bse[i]:>12.4g} "
                         f"{_fmt_t(self._tvalues[i]):>9} {_fmt_p(self._pvalues[i]):>9} "
                         f"{ci[i, 0]:>13.6g} {ci[i, 1]:>13.6g}")
        lines.append(rule)
        kind = "" if self.k_constant else " (uncentred)"
        lines.append(f"R-squared{kind}: {self.rsquared:.6f}   Adj. R-squared: {self.rsquared_adj:.6f}"
                     f"   Residual SD: {self.resid_sd:.6g} on {self.df_resid} df")
        fname = "Wald F (HAC)" if self.cov_type == "HAC" else "F-statistic"
        lines.append(f"{fname}: {self.fvalue:.6g} on {self.df_model} and {self.df_resid} df"
                     f"   Prob(F): {_fmt_p(self.f_pvalue)}   n: {self.nobs}")
        lines.append("Covariance: " + self.cov_description())
        return "\n".join(lines)

    def cov_description(self) -> str:
        """One line saying which covariance the standard errors come from."""
        if self.cov_type != "HAC":
            return "nonrobust (i.i.d. errors assumed; wrong for autocorrelated residuals)"
        k = self.cov_kwds
        how = ("Andrews AR(1) bandwidth" if k.get("bandwidth") == "andrews-ar1"
               else "fixed bandwidth")
        return (f"HAC (Newey-West, Bartlett kernel, {k.get('maxlags')} lags, {how}); residual "
                f"lag-1 autocorrelation {k.get('rho1', math.nan):.4f}, effective sample size "
                f"{k.get('n_eff', math.nan):.4g} of {self.nobs}")

    def __repr__(self) -> str:
        return (f"<OLSResults {self.target_name} ~ {' + '.join(self.feature_names)}: "
                f"n={self.nobs}, R2={self.rsquared:.4g}>")

    # -- serialisation -------------------------------------------------------------------------

    def to_dict(self) -> dict:
        """Plain JSON-able model (lists and floats). ``bse`` is informative; :meth:`from_dict`
        recomputes it from the stored factor (or, for HAC, the stored robust covariance)."""
        return {
            "kind": "fbgcomp.regression.OLSResults",
            "version": 1,
            "target_name": self.target_name,
            "feature_names": list(self.feature_names),
            "params": self._params.tolist(),
            "bse": self._bse.tolist(),
            "nobs": self.nobs,
            "k_constant": self.k_constant,
            "ssr": self.ssr,
            "centered_tss": self.centered_tss,
            "uncentered_tss": self.uncentered_tss,
            "r_factor": self._r.tolist(),
            "feature_scale": self._scale.tolist(),
            "cov_type": self.cov_type,
            "robust_cov": None if self._robust_cov is None else self._robust_cov.tolist(),
            "cov_kwds": self.cov_kwds,
            "const_index": self.const_index,
            "named": self.named,
        }

    @classmethod
    def from_dict(cls, state: dict) -> "OLSResults":
        try:
            names = [str(n) for n in state["feature_names"]]
            m = len(names)
            return cls(_field_array(state, "params", (m,)), _field_array(state, "r_factor", (m, m)),
                       _field_array(state, "feature_scale", (m,)), ssr=float(state["ssr"]),
                       nobs=int(state["nobs"]), k_constant=int(state["k_constant"]),
                       centered_tss=float(state["centered_tss"]),
                       uncentered_tss=float(state["uncentered_tss"]),
                       feature_names=names, target_name=state.get("target_name", "y"),
                       cov_type=state.get("cov_type", "nonrobust"),
                       robust_cov=(None if state.get("robust_cov") is None
                                   else _field_array(state, "robust_cov", (m, m))),
                       cov_kwds=state.get("cov_kwds"), const_index=state.get("const_index"),
                       named=bool(state.get("named", False)))
        except KeyError as exc:
            raise InputError(f"missing field {exc.args[0]!r} in regression model",
                             column=f"field {exc.args[0]}") from None


def _fmt_t(t: float) -> str:
    return f"{t:.3f}" if abs(t) < 1e5 else f"{t:.3g}"


def _fmt_p(p: float) -> str:
    if not np.isfinite(p):
        return "nan"
    return f"{p:.4f}" if p >= 1e-4 else f"{p:.1e}"


# --------------------------------------------------------------------------------------------
# Fitting
# --------------------------------------------------------------------------------------------

def ols_from_factor(acc: QRAccumulator, columns=None, target=0, *, cov_type=None,
                    maxlags=None) -> OLSResults:
    """OLS of one target on a subset of the design columns, from the accumulated factor only.

    Parameters
    ----------
    acc : QRAccumulator
    columns : None, index, name or sequence of them
        Model columns, in the order wanted for the results (None: all, in design order).
    target : int or str
        Target index or name.
    cov_type : {None, "HAC", "nonrobust"}
        Covariance behind standard errors, tests and intervals. None: "HAC" (Newey-West) when
        the accumulator keeps autocorrelation statistics (``hac_lags``), else "nonrobust".
    maxlags : None, "auto" or int
        HAC bandwidth: None/"auto" chooses it by Andrews' AR(1) rule from the residual's lag-1
        autocorrelation (the smallest accumulated bandwidth at or above it); an int must be one
        of ``acc.hac_lags_``.

    Raises
    ------
    RankDeficientError
        A column's scaled-R diagonal is <= max(n, p) * eps * max|diag|: it is (nearly) a linear
        combination of the columns before it (or there are fewer rows than columns).
    """
    if acc.n_obs == 0:
        raise ValueError("no data accumulated yet")
    cols = acc.column_indices(columns)
    if not cols:
        raise ValueError("a model needs at least one column")
    t = acc.target_index(target)
    th, tl, zh, zl, rho = acc._subset_factor(cols, t)
    bad = _deficient_columns(np.abs(np.diag(th)), acc.n_obs)
    names = [acc.feature_names[c] for c in cols]
    if bad:
        culprits = [names[i] for i in bad]
        extra = (f" (only {acc.n_obs} rows for {len(cols)} columns)"
                 if acc.n_obs < len(cols) else "")
        raise RankDeficientError(
            f"design is rank deficient{extra}: column(s) {', '.join(map(repr, culprits))} "
            f"are (nearly) linear combinations of the columns before them; drop them or "
            f"reparametrise", culprits)
    p = acc.n_features
    sx = acc.scale_[cols]
    sy = float(acc.scale_[p + t])
    # Powers of two: unscaling the double-double solution is exact before the final rounding.
    bh, bl = _dd_solve_upper(th, tl, zh, zl)
    beta = (bh * sy / sx) + (bl * sy / sx)
    const = set(acc.constant_columns)
    centred, uncentred = acc._tss(t)
    cov_type = _resolve_cov_type(acc, cov_type)
    robust, info = None, None
    if cov_type == "HAC":
        r_inv = linalg.lapack.dtrtri(th, lower=0)[0]
        cov_s, info = _hac_cov_scaled(acc, cols, t, bh + bl, r_inv, rho * rho, maxlags)
        robust = cov_s * sy * sy / np.outer(sx, sx)
    const_pos = [i for i, c in enumerate(cols) if c in const]
    return OLSResults(beta, th, sx, ssr=(rho * sy) ** 2, nobs=acc.n_obs,
                      k_constant=int(bool(const_pos)), centered_tss=centred,
                      uncentered_tss=uncentred, feature_names=names,
                      target_name=acc.target_names[t], cov_type=cov_type, robust_cov=robust,
                      cov_kwds=info, const_index=const_pos[0] if const_pos else None)


def ols(X, y, *, feature_names=None, target_name: str | None = None, cov_type: str = "HAC",
        maxlags=None) -> OLSResults:
    """Ordinary least squares of ``y`` (n,) on the design ``X`` (n, p) exactly as given.

    Add a column of ones yourself for an intercept. Column names default to those of a
    DataFrame ``X``, else ``x0..x{p-1}``. Computed by Householder QR (one-chunk
    :class:`QRAccumulator`), never through the normal equations.

    Rows are one time series in order. ``cov_type="HAC"`` (default): Newey-West standard errors
    (``maxlags`` an int, as statsmodels' ``cov_kwds={"maxlags": L}``, or None for Andrews'
    AR(1) choice); ``"nonrobust"``: the textbook i.i.d. ones.

    Given names (a DataFrame ``X`` or ``feature_names``), ``params``, ``bse``, ``tvalues``,
    ``pvalues``, ``resid`` and ``fittedvalues`` are pandas Series (indexed by the names, or by
    the rows' index) and ``conf_int()`` a DataFrame, as statsmodels gives for pandas input;
    otherwise plain arrays. ``target_name`` defaults to the name of a Series ``y``, else "y".
    """
    named = feature_names is not None or hasattr(X, "columns")
    if feature_names is None and hasattr(X, "columns"):
        feature_names = [str(c) for c in X.columns]
    index = getattr(X, "index", None)
    if index is None:
        index = getattr(y, "index", None)
    if target_name is None:
        target_name = str(y.name) if getattr(y, "name", None) is not None else "y"
    X = np.asarray(X, dtype=float)
    if X.ndim == 1:
        X = X[:, None]
    y = np.asarray(y, dtype=float)
    if y.ndim == 2 and y.shape[1] == 1:
        y = y[:, 0]
    if y.ndim != 1:
        raise ValueError(f"y must be one target (n,) or (n, 1), got shape {y.shape}")
    if X.ndim != 2 or X.shape[0] != y.shape[0]:
        raise ValueError(f"X must be (n, p) with n = len(y) = {y.shape[0]}, got {X.shape}")
    if cov_type not in COV_TYPES:
        raise ValueError(f"cov_type must be one of {COV_TYPES}, not {cov_type!r}")
    lags = None
    if cov_type == "HAC":
        lags = (max(1, min(HAC_MAX_LAG, X.shape[0] - 1)) if maxlags in (None, "auto")
                else [int(maxlags)])
    acc = accumulate_series(QRAccumulator(X.shape[1], 1, feature_names, [target_name],
                                          hac_lags=lags), [(X, y, None)], chunk_rows=len(X) or 1)
    res = ols_from_factor(acc, cov_type=cov_type, maxlags=maxlags)
    res.named = named
    res._data = (X, y, index)
    return res


# --------------------------------------------------------------------------------------------
# Stepwise selection
# --------------------------------------------------------------------------------------------

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
        how = ("Newey-West (HAC) Wald tests" if self.cov_type == "HAC"
               else "partial F tests, i.i.d. errors")
        lines = [f"Stepwise regression of {self.target_name} ({how})",
                 f"{'step':>4}  {'action':<6} {'term':<16} {'F':>12} {'p':>10} {'terms':>5} "
                 f"{'SSR':>13} {'adj. R2':>9}"]
        for h in self.history:
            lines.append(f"{h['step']:>4}  {h['action']:<6} {h['term']:<16} {h['F']:>12.5g} "
                         f"{_fmt_p(h['p']):>10} {h['n_terms']:>5} {h['ssr']:>13.6g} "
                         f"{h['rsquared_adj']:>9.5f}")
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


def _partial_f(ssr_drop: float, ssr_big: float, df_big: int) -> tuple[float, float]:
    """Partial F = (SSR_small - SSR_big) / (SSR_big / df_big) on (1, df_big) dof, and its p."""
    if df_big <= 0:
        return math.nan, math.nan
    ssr_drop = max(ssr_drop, 0.0)
    if ssr_big <= 0.0:
        f = math.inf if ssr_drop > 0 else math.nan
    else:
        f = ssr_drop / (ssr_big / df_big)
    return f, (float(stats.f.sf(f, 1, df_big)) if not math.isnan(f) else math.nan)


class _StepState:
    """One double-double factorisation of ``R[:, model + others + [y]]`` with the model columns
    reduced: it yields the SSR of the model, of the model plus each other column, and of the
    model minus each of its columns, without subtracting two large sums of squares.

    Entry: with ``w_c``, ``w_y`` the candidate and target residualised on the model (trailing
    rows), ``SSR(S) - SSR(S + c) = (w_c . w_y)^2 / |w_c|^2``. Removal: with ``T b = z`` the model
    solution, ``SSR(S - s) - SSR(S) = b_s^2 / [(X^T X)^-1]_ss`` and ``(X^T X)^-1 = T^-1 T^-T``.
    """

    def __init__(self, acc: QRAccumulator, model: list[int], others: list[int], t: int,
                 exact: bool = True):
        p = acc.n_features
        m = len(model)
        sel = model + others + [p + t]
        self.exact = exact
        sy2 = float(acc.scale_[p + t]) ** 2
        if not exact:
            self._init_double(acc, model, others, sel, sy2)
            return
        mh, ml = _dd_householder(acc.R_[:, sel], acc.R_lo_[:, sel], m)
        self.nobs = acc.n_obs
        self.model, self.others, self.sy2 = model, others, sy2
        th, tl = mh[:m, :m], ml[:m, :m]
        self.diag = np.abs(np.diag(th))
        self.full_rank = not _deficient_columns(self.diag, acc.n_obs)
        yh, yl = mh[m:, -1], ml[m:, -1]
        ssr_h, ssr_l = _dd_sum_rows(*_dd_mul(yh, yl, yh, yl))
        self.ssr = float(ssr_h) * sy2
        self._ssr_dd = (ssr_h, ssr_l)
        self._trail = (mh[m:, m:-1], ml[m:, m:-1], yh, yl)
        self._tri = (th, tl, mh[:m, -1], ml[:m, -1])

    def _init_double(self, acc, model, others, sel, sy2) -> None:
        """The same quantities in double precision (LAPACK Householder QR of the model columns
        of R, its reflections applied to the rest): for a well-conditioned factor
        (kappa_eq <= _KAPPA_EXTENDED) they carry a relative error of about kappa u, far below any
        difference a partial F test can resolve."""
        m = len(model)
        a = acc.R_[:, sel] + acc.R_lo_[:, sel]
        self.nobs = acc.n_obs
        self.model, self.others, self.sy2 = model, others, sy2
        if m:
            qr_a, tau = linalg.lapack.dgeqrf(np.asfortranarray(a[:, :m]))[:2]
            rest, _, info = linalg.lapack.dormqr("L", "T", qr_a, tau,
                                                 np.asfortranarray(a[:, m:]), a.shape[1])
            if info != 0:
                raise np.linalg.LinAlgError(f"dormqr failed ({info})")
            tri = np.triu(qr_a[:m, :m])
            head, trail = rest[:m], rest[m:]
        else:
            tri, head, trail = np.zeros((0, 0)), a[:0], a
        self.diag = np.abs(np.diag(tri))
        self.full_rank = not _deficient_columns(self.diag, acc.n_obs)
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
            return (cols, np.array([o[1] for o in out]), np.array([o[2] for o in out]),
                    np.array([o[3] for o in out], dtype=bool))
        w, y, ssr_s = self._d_trail
        norm2 = np.einsum("ij,ij->j", w, w)
        dot = w.T @ y
        with np.errstate(divide="ignore", invalid="ignore"):
            drop = dot * dot / norm2
        after = np.maximum(ssr_s - drop, 0.0) * self.sy2
        # rank: the new column's diagonal sqrt(norm2) against the model's (as _deficient_columns)
        new_diag = np.sqrt(np.maximum(norm2, 0.0))
        top = np.maximum(self.diag.max() if self.diag.size else 0.0, new_diag)
        ok = self.full_rank & (new_diag > max(self.nobs, self.diag.size + 1) * _EPS * top)
        if self.diag.size:
            ok &= self.diag.min() > max(self.nobs, self.diag.size + 1) * _EPS * top
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
        g = np.einsum("ij,ij->i", t_inv, t_inv)             # diag of T^-1 T^-T
        rise = b * b / g * self.sy2
        return cols, rise, self.ssr + rise

    def entries(self) -> list[tuple[int, float, float, bool]]:
        """(column, SSR drop, SSR after entry, full rank) for every other column."""
        if not self.others:
            return []
        if not self.exact:
            cols, drop, after, ok = self.entries_arrays()
            return [(int(c), float(d), float(a), bool(o))
                    for c, d, a, o in zip(cols, drop, after, ok)]
        wh, wl, yh, yl = self._trail
        nh, nl = _dd_sum_rows(*_dd_mul(wh, wl, wh, wl))
        dh, dl = _dd_sum_rows(*_dd_mul(wh, wl, yh[:, None], yl[:, None]))
        with np.errstate(divide="ignore", invalid="ignore"):
            eh, el = _dd_div(*_dd_mul(dh, dl, dh, dl), nh, nl)
            after_h, _ = _dd_add(self._ssr_dd[0], self._ssr_dd[1], -eh, -el)
        out = []
        for i, c in enumerate(self.others):
            new_diag = math.sqrt(max(float(nh[i]), 0.0))
            ok = self.full_rank and not _deficient_columns(np.append(self.diag, new_diag),
                                                           self.nobs)
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
        bh, bl = _dd_solve_upper(th, tl, zh, zl)
        ih, il = _dd_solve_upper(th, tl, np.eye(m), np.zeros((m, m)))
        gh, gl = _dd_sum_rows(*_dd_mul(ih.T, il.T, ih.T, il.T))        # diag of T^-1 T^-T
        rh, _ = _dd_div(*_dd_mul(bh, bl, bh, bl), gh, gl)
        return [(c, float(rh[i]) * self.sy2, self.ssr + float(rh[i]) * self.sy2)
                for i, c in enumerate(self.model)]


def stepwise(acc: QRAccumulator, candidates=None, *, target=0, direction: str = "both",
             p_enter: float = 0.05, p_remove: float = 0.10, max_terms: int | None = None,
             include: Iterable = (), start=None, cov_type=None, maxlags=None) -> StepwiseResult:
    """Stepwise selection by partial F (or HAC Wald) tests, from the accumulated factor only.

    The paper tunes its regression "with a stepwise regression ... counting or removing a
    factor using ANOVA" (section 3; final model in Table 1). Each step compares two nested
    models differing by one term: ``F = (SSR_small - SSR_big) / (SSR_big / df_resid_big)`` on
    (1, df_resid_big) degrees of freedom. Every step costs one small double-double QR of the
    factor (see :class:`_StepState`), never a pass over the data.

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
        raise ValueError(f"p_enter ({p_enter}) must not exceed p_remove ({p_remove}): "
                         "a term could enter and leave forever")
    if acc.n_obs == 0:
        raise ValueError("no data accumulated yet")
    cov_type = _resolve_cov_type(acc, cov_type)
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
        return _StepState(acc, cols, [c for c in cand if c not in model], t, exact)

    def f_sf(f: float, df: int) -> float:
        return float(stats.f.sf(f, 1, df)) if df > 0 and not math.isnan(f) else math.nan

    def partial_f(diff: np.ndarray, ssr_big, df_big: int) -> np.ndarray:
        """Vectorised _partial_f (F only; p is monotone in F at a fixed df)."""
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
        raise RankDeficientError("the starting model of the stepwise search is rank deficient",
                                 [acc.feature_names[c] for c in ordered(model)])
    history: list[dict] = []
    visited = {frozenset(model)}

    def wald(cols):
        """HAC Wald F of every term of the model ``cols`` (dict by column), and its HAC info."""
        _, beta, r_inv, ssr_s = _double_subset(acc, cols, t)
        cov, info = _hac_cov_scaled(acc, cols, t, beta, r_inv, ssr_s, maxlags)
        with np.errstate(divide="ignore", invalid="ignore"):
            f = beta * beta / np.diag(cov)
        return {c: float(f[i]) for i, c in enumerate(cols)}, info

    def record(action, term, f, pval, ssr, info=None):
        cols = ordered(model)
        entry = {"step": len(history) + 1, "action": action,
                 "term": acc.feature_names[term], "F": float(f), "p": float(pval),
                 "n_terms": len(cols), "ssr": float(ssr),
                 "rsquared_adj": _adj_r2(acc, cols, t, ssr)}
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
        keep = np.array([bool(o) and frozenset(model + [int(c)]) not in visited
                         for c, o in zip(cols, ok)], dtype=bool)
        # collinear with the model (no new information), or a loop
        cols, drop, after = cols[keep], drop[keep], after[keep]
        infos = [None] * len(cols)
        if robust:
            f = np.empty(len(cols))
            for i, c in enumerate(cols):
                fs, infos[i] = wald(ordered(model + [int(c)]))
                f[i] = fs[int(c)]
        else:
            f = partial_f(drop, after, df_big)
        i = pick(f, largest=True)
        if i is None:
            return False
        pval = f_sf(float(f[i]), df_big)
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
        cols, rise, after = current.removals_arrays()
        keep = np.array([int(c) not in forced and not (
            direction == "both" and frozenset(d for d in model if d != int(c)) in visited)
            for c in cols], dtype=bool)
        cols, rise = cols[keep], rise[keep]
        if robust:
            f = np.array([fs[int(c)] for c in cols], dtype=float)
        else:
            f = partial_f(rise, current.ssr, df_big)
        i = pick(f, largest=False)
        if i is None:
            return False
        pval = f_sf(float(f[i]), df_big)
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
    return StepwiseResult(selected=[acc.feature_names[c] for c in final], history=history,
                          result=result, target_name=acc.target_names[t], cov_type=cov_type)
