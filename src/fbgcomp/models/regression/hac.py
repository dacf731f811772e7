"""Autocorrelation-robust (Newey-West, HAC) inference from streamed statistics.

Residuals of slow thermal drifts sampled every second are autocorrelated over hours; the naive
i.i.d. standard errors and F tests are then far too optimistic. A
:class:`~fbgcomp.models.regression.QRAccumulator` created with ``hac_lags`` also keeps lagged
score sums (:class:`HACStatistics`, a base class of it, whose notes hold the algebra),
from which :func:`hac_cov_scaled` forms the Newey-West sandwich of any sub-model without
re-reading the data, with the bandwidth from Andrews' AR(1) rule (:func:`andrews_bartlett_lags`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import NamedTuple, Self

import numpy as np

from fbgcomp.models.regression.factor import field_array

__all__ = [
    "COV_TYPES",
    "HAC_MAX_LAG",
    "HACStatistics",
    "andrews_bartlett_lags",
    "hac_cov_scaled",
    "hac_lag_grid",
    "resolve_cov_type",
]

# Largest Newey-West bandwidth (lags) of the default grid of an autocorrelation-robust fit.
HAC_MAX_LAG = 4096
# Rows per pass of the lagged-score accumulation: bounds its temporaries (rows + carried lags).
_HAC_BLOCK_ROWS = 8192
# Bartlett sums up to this bandwidth are formed by shifted additions (exact to a few ulps);
# wider ones through two cumulative sums over a block of at most _HAC_BLOCK_ROWS + L rows.
_HAC_DIRECT_MAX_LAG = 32
# Rows per pass of the shifted additions of the short bandwidths: in cache (~300 kB for a
# narrow design's products)
_BARTLETT_ROWS = 256
# Covariance behind a fit's inference: the Newey-West sandwich, or the textbook i.i.d. one.
COV_TYPES = ("HAC", "nonrobust")


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
            raise ValueError(
                f"hac_lags must be None, True, 'auto', an int or a sequence of ints, not {hac_lags!r}"
            ) from None
        if not lags or min(lags) < 1:
            raise ValueError(f"hac_lags must be positive, not {hac_lags!r}")
    return sorted(lags | {1})


def _bartlett_sums(w: np.ndarray, first: int, lags: Sequence[int]) -> list[np.ndarray]:
    """For each L in ``lags``: rows ``first..`` of ``sum_{l=1..L} (1 - l/(L+1)) w[i-l]``
    (rows before 0 count as zero): the Bartlett-weighted past of each row of ``w``."""
    n, c = w.shape
    m = n - first
    out = []
    p_sum = q_sum = None
    tmp = np.empty((min(_BARTLETT_ROWS, m), c))
    for lag in lags:
        if lag <= _HAC_DIRECT_MAX_LAG:
            # the shifted additions over a few hundred rows at a time, so that they work in
            # cache (each element's sum is formed in the same order: the same bits as over the
            # whole block, in half the time)
            acc = np.zeros((m, c))
            for r0 in range(0, m, _BARTLETT_ROWS):
                r1 = min(r0 + _BARTLETT_ROWS, m)
                part = acc[r0:r1]
                for j in range(1, lag + 1):
                    lo, hi = first + r0 - j, first + r1 - j  # rows i - j of these rows i
                    if hi <= 0:
                        continue
                    s = max(lo, 0)
                    t = tmp[: hi - s]
                    np.multiply(w[s:hi], lag + 1 - j, out=t)
                    part[s - lo :] += t
        else:
            if p_sum is None or q_sum is None:  # both are built on the first long lag
                # P[k] = sum_{j<k} w[j],  Q[k] = sum_{j<k} P[j]:
                # sum_{l=1..L} (L+1-l) w[i-l] = L P[i] - Q[i] + Q[max(i-L, 0)].
                p_sum = np.zeros((n + 1, c))
                np.cumsum(w, axis=0, out=p_sum[1:])
                q_sum = np.zeros((n + 2, c))
                np.cumsum(p_sum, axis=0, out=q_sum[1:])
            acc = np.multiply(p_sum[first:n], lag)
            acc -= q_sum[first:n]
            k = min(m, max(lag - first, 0))  # the rows with i - L < 0
            acc[:k] += q_sum[0]
            acc[k:] += q_sum[first + k - lag : n - lag]
        acc /= lag + 1
        out.append(acc)
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


class _HACArrays(NamedTuple):
    """The statistics of an accumulator that keeps them (``hac_lags_`` set), none of them None."""

    lags: list[int]
    g0: np.ndarray
    k: np.ndarray
    ka: np.ndarray
    tail: np.ndarray
    pilot: np.ndarray


class HACStatistics:
    """The autocorrelation statistics of a :class:`~fbgcomp.models.regression.QRAccumulator`
    (a base class of it): lagged sums of the scaled rows' products, kept relative to a pilot.

    The accumulator supplies ``n_features``, ``n_targets``, ``n_obs``, ``scale_`` and
    ``hac_lags_`` (None: no statistics kept) and starts the second pass
    (:meth:`~fbgcomp.models.regression.QRAccumulator.begin_hac`); this class holds, resets,
    adds to, re-expresses, merges and (de)serialises the statistics themselves.

    Notes
    -----
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
    second pass (:meth:`~fbgcomp.models.regression.QRAccumulator.begin_hac`,
    :meth:`~fbgcomp.models.regression.QRAccumulator.update_hac`, or
    :func:`~fbgcomp.models.regression.accumulate_series` for data in memory), with the targets
    relative to a pilot, the full model's coefficients ``P`` (``hac_pilot_``, scaled):
    ``a_i = [x_i | y_i - x_i P]``, and a sub-model's ``c`` gains ``P``. The full model's
    residual is then exact, and what remains is the rounding of any meat matrix,
    ``eps kappa^2`` relative in the design's weakest direction (statsmodels forms the same sum).
    Accumulators with different pilots still merge (an exact linear map).
    """

    n_features: int
    n_targets: int
    n_obs: int
    scale_: np.ndarray | None
    hac_lags_: list[int] | None
    # all None when hac_lags_ is None, all arrays otherwise (_hac_reset, _hac_load)
    hac_g0_: np.ndarray | None
    hac_k_: np.ndarray | None
    hac_ka_: np.ndarray | None
    hac_pilot_: np.ndarray | None
    _hac_tail: np.ndarray | None
    hac_frozen_: bool
    hac_n_obs_: int

    def _hac_arrays(self) -> _HACArrays:
        """The statistics, for code that runs only when they are kept (``hac_lags_`` set)."""
        lags, g0, k, ka = self.hac_lags_, self.hac_g0_, self.hac_k_, self.hac_ka_
        tail, pilot = self._hac_tail, self.hac_pilot_
        assert lags is not None and g0 is not None and k is not None and ka is not None
        assert tail is not None and pilot is not None
        return _HACArrays(lags, g0, k, ka, tail, pilot)

    def _hac_reset(self) -> None:
        """Empty statistics for ``hac_lags_`` (all None when it is None)."""
        p, q = self.n_features, self.n_features + self.n_targets
        if self.hac_lags_ is None:
            self.hac_g0_ = self.hac_k_ = self.hac_ka_ = self.hac_pilot_ = None
            self._hac_tail = None
            self.hac_frozen_ = False
            self.hac_n_obs_ = 0
            return
        nl = len(self.hac_lags_)
        self.hac_g0_ = np.zeros((p * q, p * q))  # sum u_i u_i^T
        self.hac_k_ = np.zeros((nl, p * q, p * q))  # sum u_i (Bartlett past of u)_i^T
        self.hac_ka_ = np.zeros((nl, q, q))  # sum a_i (Bartlett past of a)_i^T
        self._hac_tail = np.zeros((0, q))  # last max(L) scaled rows of the series
        self.hac_pilot_ = np.zeros((p, self.n_targets))  # scaled coefficients the targets are
        # kept relative to (see Notes)
        self.hac_frozen_ = False  # second pass: pilot fixed (begin_hac)
        self.hac_n_obs_ = 0  # rows in the statistics

    def _hac_update(self, a: np.ndarray) -> None:
        """Add the lagged products of the scaled rows ``a`` (m, q), targets taken relative to
        the pilot, to the HAC statistics."""
        p, q = self.n_features, self.n_features + self.n_targets
        s = self._hac_arrays()
        a = a.copy()
        a[:, p:] -= a[:, :p] @ s.pilot
        top = max(s.lags)
        g0, tail = s.g0, s.tail
        for start in range(0, a.shape[0], _HAC_BLOCK_ROWS):
            block = a[start : start + _HAC_BLOCK_ROWS]
            ext = np.vstack([tail, block])
            first = tail.shape[0]
            u = (ext[:, :p, None] * ext[:, None, :]).reshape(ext.shape[0], p * q)
            w = np.hstack([u, ext])
            u_new = u[first:]
            g0 += u_new.T @ u_new  # in place: the arrays are the accumulator's
            for i, past in enumerate(_bartlett_sums(w, first, s.lags)):
                s.k[i] += u_new.T @ past[:, : p * q]
                s.ka[i] += block.T @ past[:, p * q :]
            tail = self._hac_tail = ext[-top:].copy()
        self.hac_n_obs_ += a.shape[0]

    def _hac_move_pilot(self, pilot: np.ndarray) -> None:
        """Re-express the statistics with targets relative to ``pilot`` instead of the current
        one: ``a -> a A`` with ``A = [[I, P_old - P_new], [0, I]]``, so ``u -> u (I (x) A)``."""
        p, q = self.n_features, self.n_features + self.n_targets
        s = self._hac_arrays()
        delta = s.pilot - pilot
        self.hac_pilot_ = np.array(pilot, dtype=float)
        if not np.any(delta):
            return
        A = np.eye(q)
        A[:p, p:] = delta
        nl = len(s.lags)

        def both_sides(m: np.ndarray, count: int) -> np.ndarray:  # (I(x)A)^T m (I(x)A)
            m = m.reshape(count, p, q, p, q) @ A  # right factor, last axis
            m = np.einsum("cimjn,ma->ciajn", m, A, optimize=True)
            return m.reshape(count, p * q, p * q)

        self.hac_g0_ = both_sides(s.g0, 1)[0]
        self.hac_k_ = both_sides(s.k, nl)
        self.hac_ka_ = A.T @ s.ka @ A
        self._hac_tail = s.tail @ A

    def end_series(self) -> Self:
        """Rows added from now on start a new time series (e.g. the next campaign): no lag of
        the autocorrelation statistics links them to the rows before. Returns self."""
        if self._hac_tail is not None:
            self._hac_tail = np.zeros((0, self.n_features + self.n_targets))
        return self

    def _merge_hac(self, other: HACStatistics, weight: float) -> None:
        """Add ``other``'s autocorrelation statistics (brought to this accumulator's scales).

        The two are separate series: no lag spans them (merging pieces of one recording drops
        the few lags across the cut). If only one side has statistics, the result has none.
        """
        if self.hac_lags_ is None or other.hac_lags_ is None:
            self.hac_lags_ = None
            self._hac_reset()
            return
        if list(other.hac_lags_) != list(self.hac_lags_):
            raise ValueError(
                f"cannot merge autocorrelation statistics of different bandwidths "
                f"({other.hac_lags_} vs {self.hac_lags_})"
            )
        p = self.n_features
        assert other.scale_ is not None and self.scale_ is not None  # both hold rows (merge)
        ratio = other.scale_ / self.scale_
        r_u = (ratio[:p, None] * ratio[None, :]).reshape(-1)  # u = x (x) a
        f_u = weight**2 * np.outer(r_u, r_u)  # u scales by the weight
        # Bring other's statistics to its pilot expressed in this accumulator's scales, then
        # both to this one's pilot (exact algebra; small rounding when the pilots are close).
        theirs = other._hac_arrays()
        other_pilot = theirs.pilot * ratio[p:][None, :] / ratio[:p, None]
        mine = self._hac_arrays().pilot
        self._hac_move_pilot(other_pilot)
        mine_now = self._hac_arrays()
        g0, k, ka = mine_now.g0, mine_now.k, mine_now.ka
        g0 += theirs.g0 * f_u  # in place: the arrays are this accumulator's
        k += theirs.k * f_u[None]
        ka += theirs.ka * (weight * np.outer(ratio, ratio))[None]
        self._hac_move_pilot(mine)
        self.hac_n_obs_ += other.hac_n_obs_
        self.end_series()

    def _hac_adopt(self, other: HACStatistics, weight: float) -> None:
        """Take ``other``'s statistics (and bandwidths) as this one's, its rows weighted by
        ``weight``: the merge into an empty accumulator, whose scales are ``other``'s."""
        self.hac_lags_ = None if other.hac_lags_ is None else list(other.hac_lags_)
        self._hac_reset()
        if self.hac_lags_ is not None:
            theirs = other._hac_arrays()
            # a row's weight w scales a_i by sqrt(w), u_i = x_i (x) a_i by w
            self.hac_g0_ = theirs.g0 * weight**2
            self.hac_k_ = theirs.k * weight**2
            self.hac_ka_ = theirs.ka * weight
            self.hac_pilot_ = theirs.pilot.copy()
            self.hac_frozen_ = other.hac_frozen_
            self.hac_n_obs_ = other.hac_n_obs_

    def _hac_state(self) -> dict | None:
        """The statistics as plain JSON-able lists (the ``"hac"`` field of ``to_dict``)."""
        if self.hac_lags_ is None:
            return None
        s = self._hac_arrays()
        return {
            "lags": list(s.lags),
            "g0": s.g0.tolist(),
            "k": s.k.tolist(),
            "ka": s.ka.tolist(),
            "tail": s.tail.tolist(),
            "pilot": s.pilot.tolist(),
            "frozen": bool(self.hac_frozen_),
            "n_obs": int(self.hac_n_obs_),
        }

    def _hac_load(self, hac: dict) -> None:
        """Restore the statistics from :meth:`_hac_state` output (bandwidths already set)."""
        assert self.hac_lags_ is not None  # from_dict sets the bandwidths first
        p, q, nl = self.n_features, self.n_features + self.n_targets, len(self.hac_lags_)
        self.hac_g0_ = field_array(hac, "g0", (p * q, p * q))
        self.hac_k_ = field_array(hac, "k", (nl, p * q, p * q))
        self.hac_ka_ = field_array(hac, "ka", (nl, q, q))
        tail = np.asarray(hac.get("tail") or np.zeros((0, q)), dtype=float)
        self._hac_tail = tail.reshape(-1, q)
        if hac.get("pilot") is not None:
            self.hac_pilot_ = field_array(hac, "pilot", (self.n_features, self.n_targets))
        self.hac_frozen_ = bool(hac.get("frozen", False))
        self.hac_n_obs_ = int(hac.get("n_obs", self.n_obs))


def resolve_cov_type(acc: HACStatistics, cov_type) -> str:
    """The covariance type of a fit from ``acc``: ``cov_type`` checked, or for None "HAC" when
    the accumulator keeps autocorrelation statistics and "nonrobust" otherwise. "HAC" needs
    the statistics of every row in the factor (the second pass done)."""
    if cov_type is None:
        cov_type = "HAC" if acc.hac_lags_ is not None else "nonrobust"
    if cov_type not in COV_TYPES:
        raise ValueError(f"cov_type must be one of {COV_TYPES}, not {cov_type!r}")
    if cov_type == "HAC" and acc.hac_lags_ is None:
        raise ValueError(
            "cov_type='HAC' needs an accumulator created with hac_lags (it keeps the "
            "lagged score sums); pass cov_type='nonrobust' for naive i.i.d. inference"
        )
    if cov_type == "HAC" and acc.hac_n_obs_ != acc.n_obs:
        raise ValueError(
            f"the autocorrelation statistics cover {acc.hac_n_obs_} of the "
            f"{acc.n_obs} rows in the factor: feed every row to update_hac after "
            f"begin_hac (or use accumulate_series)"
        )
    return cov_type


def _choose_lag(acc: HACStatistics, maxlags, rho: float) -> int:
    """Bandwidth: ``maxlags`` (one of the accumulated ones), or for None/"auto" the smallest
    accumulated one at or above Andrews' AR(1) choice for the lag-1 autocorrelation ``rho``."""
    grid = acc.hac_lags_
    assert grid is not None  # resolve_cov_type let "HAC" through
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


def hac_cov_scaled(
    acc: HACStatistics,
    cols: list[int],
    t: int,
    beta_s: np.ndarray,
    r_inv: np.ndarray,
    ssr_s: float,
    maxlags=None,
) -> tuple[np.ndarray, dict]:
    """Newey-West covariance of the *scaled* coefficients of the sub-model ``cols`` on target t.

    ``beta_s``: scaled coefficients; ``r_inv``: inverse of its scaled triangular factor;
    ``ssr_s``: scaled residual sum of squares. Returns the covariance and a dict with the
    bandwidth ``maxlags``, the residual's lag-1 autocorrelation ``rho1`` and the effective
    sample size ``n_eff`` = n / (residual long-run variance / variance) at that bandwidth.
    """
    p, q = acc.n_features, acc.n_features + acc.n_targets
    s = acc._hac_arrays()
    # Targets are kept relative to the pilot P (a_y = y - x P): e = a_y + x (P - b)
    c = np.zeros(q)
    c[:p] = s.pilot[:, t]
    c[cols] -= np.asarray(beta_s, dtype=float)
    c[p + t] = 1.0
    i1 = s.lags.index(1)
    # hac_ka_ at L = 1 holds (1/2) sum a_i a_{i-1}^T
    rho = 2.0 * float(c @ s.ka[i1] @ c) / ssr_s if ssr_s > 0 else 0.0
    lag = _choose_lag(acc, maxlags, rho)
    il = s.lags.index(lag)
    lrv = ssr_s + 2.0 * float(c @ s.ka[il] @ c)
    n_eff = acc.n_obs * ssr_s / lrv if lrv > 0 else math.nan
    k = s.k[il]
    meat4 = (s.g0 + k + k.T).reshape(p, q, p, q)
    sub = meat4[np.ix_(cols, range(q), cols, range(q))]
    omega = np.einsum("imjn,m,n->ij", sub, c, c)
    bread = r_inv @ r_inv.T
    cov = bread @ omega @ bread
    info = {
        "kernel": "bartlett",
        "maxlags": int(lag),
        "rho1": float(rho),
        "n_eff": float(n_eff),
        "bandwidth": "andrews-ar1" if maxlags in (None, "auto") else "fixed",
    }
    return (cov + cov.T) / 2.0, info
