"""Least-squares fits read from an accumulated factor, without re-reading the data.

Because ``R^T R = A_s^T A_s``, every least-squares problem on a subset S of the design columns
and one target is solved exactly from the accumulated triangle alone (package notes):
:class:`AccumulatedFactor` is that read side of :class:`~fbgcomp.models.regression.QRAccumulator`
(column lookup, the double-double factor of any sub-model, total sums of squares), and
:func:`ols_from_factor` turns a sub-model into :class:`~fbgcomp.models.regression.OLSResults`.
"""

from __future__ import annotations

import numpy as np
from scipy import linalg

from fbgcomp.models.regression.doubledouble import dd_qr_r, dd_solve_upper
from fbgcomp.models.regression.factor import (
    KAPPA_EXTENDED,
    RankDeficientError,
    deficient_columns,
    equilibrated_cond,
)
from fbgcomp.models.regression.hac import HACStatistics, hac_cov_scaled, resolve_cov_type
from fbgcomp.models.regression.results import OLSResults

__all__ = ["AccumulatedFactor", "ols_from_factor"]


class AccumulatedFactor(HACStatistics):
    """What fits read from a :class:`~fbgcomp.models.regression.QRAccumulator` (its base class):
    columns by index or name, the exact factor of any sub-model, total sums of squares.

    The accumulator (the write side: data pass, merge, serialisation) holds the attributes
    declared here; see its documentation for their meaning.
    """

    feature_names: list[str]
    target_names: list[str]
    R_: np.ndarray
    R_lo_: np.ndarray
    extended_: bool
    column_min_: np.ndarray
    column_max_: np.ndarray
    target_mean_: np.ndarray
    target_css_: np.ndarray
    weight_sum_: float

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

    def _exact_pilot(self) -> np.ndarray:
        """Scaled full-model coefficients (p, k), double-double solve, 0 on deficient columns."""
        p = self.n_features
        pilot = np.zeros((p, self.n_targets))
        diag = np.abs(np.diag((self.R_ + self.R_lo_)[:p, :p]))
        keep = [c for c in range(p) if c not in set(deficient_columns(diag, self.n_obs))]
        for t in range(self.n_targets):
            th, tl, zh, zl, _ = self._subset_factor(keep, t)
            bad = deficient_columns(np.abs(np.diag(th)), self.n_obs)
            cols = [c for i, c in enumerate(keep) if i not in set(bad)]
            if bad:
                th, tl, zh, zl, _ = self._subset_factor(cols, t)
            if cols:
                bh, bl = dd_solve_upper(th, tl, zh, zl)
                pilot[cols, t] = bh + bl
        return pilot

    def _subset_factor(self, cols: list[int], t: int):
        """Double-double QR factor of the scaled ``[X_S | y_t]``, from R alone.

        Returns (T_hi, T_lo, z_hi, z_lo, rho) with ``T b = z`` the scaled normal solution and
        ``rho^2`` the scaled residual sum of squares.
        """
        m = len(cols)
        sel = [*cols, self.n_features + t]
        rh, rl = dd_qr_r(self.R_[:, sel], self.R_lo_[:, sel])
        return rh[:m, :m], rl[:m, :m], rh[:m, m], rl[:m, m], float(abs(rh[m, m]))

    def _well_conditioned(self, limit: float = KAPPA_EXTENDED) -> bool:
        """Whether the factor is well conditioned enough for double-precision sub-model
        statistics (Householder QR of the factor's columns: relative error ~ kappa u, 1e-10 at
        the limit, far below anything a partial F test resolves): equilibrated kappa of R
        (design and targets) <= ``limit`` and the data pass never needed double-double."""
        return not self.extended_ and self.n_obs > 0 and equilibrated_cond(self.R_ + self.R_lo_) <= limit

    def _tss(self, t: int) -> tuple[float, float]:
        """(centred, uncentred) total sum of squares of target t."""
        css = float(self.target_css_[t])
        return css, css + self.weight_sum_ * float(self.target_mean_[t]) ** 2

    def ols(self, columns=None, target=0) -> OLSResults:
        """Shorthand for :func:`ols_from_factor` on this accumulator."""
        return ols_from_factor(self, columns, target)


def ols_from_factor(
    acc: AccumulatedFactor, columns=None, target=0, *, cov_type=None, maxlags=None
) -> OLSResults:
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
    bad = deficient_columns(np.abs(np.diag(th)), acc.n_obs)
    names = [acc.feature_names[c] for c in cols]
    if bad:
        culprits = [names[i] for i in bad]
        extra = f" (only {acc.n_obs} rows for {len(cols)} columns)" if acc.n_obs < len(cols) else ""
        raise RankDeficientError(
            f"design is rank deficient{extra}: column(s) {', '.join(map(repr, culprits))} "
            f"are (nearly) linear combinations of the columns before them; drop them or "
            f"reparametrise",
            culprits,
        )
    p = acc.n_features
    assert acc.scale_ is not None  # set by the first rows (n_obs > 0 above)
    sx = acc.scale_[cols]
    sy = float(acc.scale_[p + t])
    # Powers of two: unscaling the double-double solution is exact before the final rounding.
    bh, bl = dd_solve_upper(th, tl, zh, zl)
    beta = (bh * sy / sx) + (bl * sy / sx)
    const = set(acc.constant_columns)
    centred, uncentred = acc._tss(t)
    cov_type = resolve_cov_type(acc, cov_type)
    robust, info = None, None
    if cov_type == "HAC":
        r_inv = linalg.lapack.dtrtri(th, lower=0)[0]
        cov_s, info = hac_cov_scaled(acc, cols, t, bh + bl, r_inv, rho * rho, maxlags)
        robust = cov_s * sy * sy / np.outer(sx, sx)
    const_pos = [i for i, c in enumerate(cols) if c in const]
    return OLSResults(
        beta,
        th,
        sx,
        ssr=(rho * sy) ** 2,
        nobs=acc.n_obs,
        k_constant=int(bool(const_pos)),
        centered_tss=centred,
        uncentered_tss=uncentred,
        feature_names=names,
        target_name=acc.target_names[t],
        cov_type=cov_type,
        robust_cov=robust,
        cov_kwds=info,
        const_index=const_pos[0] if const_pos else None,
    )
