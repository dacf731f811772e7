"""The streamed factor: :class:`QRAccumulator` (TSQR of ``[X | Y]`` plus the moments inference
needs), :func:`accumulate_series` to fill one from series in memory, and :func:`ols`, the
one-call fit of data in memory. The mathematics and the precision rules are in the notes of
:mod:`fbgcomp.models.regression`.

Over 600 lines as one unit: the factor's update, merge, weighting and serialisation act on the same
arrays.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
from scipy import linalg

from fbgcomp.errors import InputError
from fbgcomp.models.regression.doubledouble import dd_qr_r
from fbgcomp.models.regression.factor import KAPPA_EXTENDED, deficient_columns, field_array
from fbgcomp.models.regression.fit import AccumulatedFactor, ols_from_factor
from fbgcomp.models.regression.gram import GRAM_MAX_REFUSALS, GRAM_MIN_ROWS, gram, gram_factor
from fbgcomp.models.regression.hac import COV_TYPES, HAC_MAX_LAG, hac_lag_grid
from fbgcomp.models.regression.results import OLSResults

__all__ = ["ACCUMULATOR_KIND", "QRAccumulator", "accumulate_series", "ols"]

# The "kind" tag of a saved accumulator state (to_dict): a data-format identifier written into
# files, kept as it was when the module was fbgcomp/regression.py.
ACCUMULATOR_KIND = "fbgcomp.regression.QRAccumulator"

# Rows per LAPACK QR pass: [R; block] stays in cache (4096 x 46 doubles = 1.5 MB), which makes
# the Householder data pass ~1.7x faster than 65536-row blocks; it also bounds the extra memory
# of an update (one scaled copy of the block) whatever the caller's chunk size.
_QR_BLOCK_ROWS = 4096
# Rows per double-double Householder pass: its ~20 temporaries of this many rows stay small.
_DD_BLOCK_ROWS = 2048
_PRECISIONS = ("auto", "double", "double-double")


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


def _as_2d(values: Any, ncols: int, what: str) -> np.ndarray:
    """``values`` as a float (n, ncols) array (1-D allowed when ncols is 1)."""
    arr = np.asarray(values, dtype=float)
    if arr.ndim == 1 and ncols == 1:
        arr = arr[:, None]
    if arr.ndim != 2 or arr.shape[1] != ncols:
        raise ValueError(f"{what} must have shape (n, {ncols}), got {np.shape(values)}")
    return arr


def _check_finite(arr: np.ndarray, names: Sequence[str], first_row: int, what: str) -> None:
    """InputError naming the (1-based) row and the column of the first non-finite value."""
    if not np.isfinite(arr).all():
        bad_row, bad_col = np.argwhere(~np.isfinite(arr))[0]
        raise InputError(
            f"non-finite {what} value {arr[bad_row, bad_col]!r} in regression data",
            row=first_row + int(bad_row),
            column=names[int(bad_col)],
        )


def _names(names: Sequence[str] | None, count: int, default: list[str], what: str) -> list[str]:
    """``count`` unique column names as strings, ``default`` when None."""
    if names is None:
        return default
    names = [str(n) for n in names]
    if len(names) != count:
        raise ValueError(f"{what} has {len(names)} names for {count} columns")
    if len(set(names)) != len(names):
        raise ValueError(f"{what} are not unique: {names}")
    return names


class QRAccumulator(AccumulatedFactor):
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
        Arithmetic of the data pass (see the package notes). "auto" uses the Gram fast path
        while the equilibrated design is very well conditioned (kappa_eq <= 500), LAPACK
        Householder QR in double precision while the scaled design is well conditioned
        (kappa <= 1e6) and double-double otherwise; "double" is always LAPACK QR.
    hac_lags : None, True, "auto", int or sequence of int
        Also keep what autocorrelation-robust (Newey-West, HAC) inference needs, for these
        bandwidths (see :func:`~fbgcomp.models.regression.hac.hac_lag_grid`; default None:
        naive inference only). Rows are a time series in the order given; :meth:`end_series`
        starts a new one (another campaign), so no lag spans two series.

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

    Autocorrelation statistics (``hac_lags``) come in a second pass (:meth:`begin_hac`,
    :meth:`update_hac`, or :func:`accumulate_series` for data in memory): see
    :class:`~fbgcomp.models.regression.hac.HACStatistics` for what is kept and why.
    """

    def __init__(
        self,
        n_features: int,
        n_targets: int = 1,
        feature_names=None,
        target_names=None,
        *,
        precision: str = "auto",
        hac_lags=None,
    ):
        if int(n_features) < 1 or int(n_targets) < 1:
            raise ValueError("n_features and n_targets must be at least 1")
        if precision not in _PRECISIONS:
            raise ValueError(f"precision must be one of {_PRECISIONS}, not {precision!r}")
        self.n_features = int(n_features)
        self.n_targets = int(n_targets)
        self.precision = precision
        self.feature_names = _names(
            feature_names, self.n_features, [f"x{i}" for i in range(self.n_features)], "feature_names"
        )
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

    def update(self, X_chunk, Y_chunk, weights=None) -> QRAccumulator:
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
            rms = np.sqrt(np.concatenate([np.einsum("ij,ij->j", X, X), np.einsum("ij,ij->j", Y, Y)]) / m)
            self.scale_ = _power_of_two_scale(rms)
        start = 0
        if self._gram_eligible():
            # Householder QR until the factor can judge the conditioning, then the Gram.
            start = min(m, max(0, max(GRAM_MIN_ROWS, 4 * (p + k)) - self.n_obs))
            self._check_rows(X_raw[:start], Y_raw[:start])
            self._factor_rows(X[:start], Y[:start])
            if start < m and self._gram_eligible():
                if self._gram_rows(X[start:], Y[start:], X_raw[start:], Y_raw[start:], start):
                    start = m
            elif start < m:
                self._check_rows(X_raw[start:], Y_raw[start:], start)
        self._factor_rows(X[start:], Y[start:], self.n_obs + start)
        # Warm-up rows first: most columns vary there, and only the others are read after.
        self._update_range(X_raw[:GRAM_MIN_ROWS])
        self._update_range(X_raw[GRAM_MIN_ROWS:])
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
        if not np.isfinite(self.column_min_).all():  # first rows
            self.column_min_ = np.minimum(self.column_min_, X_raw.min(axis=0))
            self.column_max_ = np.maximum(self.column_max_, X_raw.max(axis=0))
            return
        flat = np.flatnonzero(self.column_min_ == self.column_max_)
        if flat.size:
            part = X_raw[:, flat]
            self.column_min_[flat] = np.minimum(self.column_min_[flat], part.min(axis=0))
            self.column_max_[flat] = np.maximum(self.column_max_[flat], part.max(axis=0))

    def _gram_rows(
        self, X: np.ndarray, Y: np.ndarray, X_raw: np.ndarray, Y_raw: np.ndarray, offset: int
    ) -> bool:
        """Gram fast path: add the (weighted) rows through their Gram ``[X Y]^T [X Y]``
        and a Cholesky of ``R^T R + G`` (scaled exactly by the power-of-two scales), committed
        only if :func:`~fbgcomp.models.regression.gram.gram_factor` accepts the new factor;
        otherwise nothing changes and False is returned (the caller factors the same rows by
        QR); after GRAM_MAX_REFUSALS refusals in a row the fast path is off for good."""
        q = self.n_features + self.n_targets
        g = gram(X, Y)
        if not np.isfinite(np.diag(g)).all():
            self._check_rows(X_raw, Y_raw, offset)  # names the bad cell; else squares overflowed
            self._gram_ok = False
            return False
        assert self.scale_ is not None  # update sets it before any rows are factored
        g /= np.outer(self.scale_, self.scale_)  # exact: powers of two
        r = gram_factor(self.R_, g, self.n_features)
        if r is None:
            self._gram_refusals += 1
            self._gram_ok = self._gram_refusals < GRAM_MAX_REFUSALS
            return False
        self._gram_refusals = 0
        self.R_, self.R_lo_ = r, np.zeros((q, q))
        self.gram_rows_ += X.shape[0]
        return True

    def begin_hac(self) -> QRAccumulator:
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

    def update_hac(self, X_chunk, Y_chunk, weights=None) -> QRAccumulator:
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

    def _scaled_block(self, X: np.ndarray, Y: np.ndarray, top: np.ndarray) -> np.ndarray:
        """Fortran-ordered ``[top; [X Y] / scale]`` (exact: the scales are powers of two)."""
        p, q = self.n_features, self.n_features + self.n_targets
        t = top.shape[0]
        block = np.empty((t + X.shape[0], q), order="F")
        block[:t] = top
        assert self.scale_ is not None  # update sets it before any rows are factored
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
                rh, rl = dd_qr_r(block, lo)
            self.R_, self.R_lo_ = rh, rl

    def _ill_conditioned(self, r: np.ndarray, nobs: int) -> bool:
        """kappa_2 of the scaled design's triangle above the threshold (deficient columns aside)."""
        p = self.n_features
        t = r[:p, :p]
        keep = np.ones(p, dtype=bool)
        keep[deficient_columns(np.abs(np.diag(t)), nobs)] = False
        if not keep.any():
            return False
        return bool(np.linalg.cond(t[np.ix_(keep, keep)]) > KAPPA_EXTENDED)

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

    def merge(self, other: QRAccumulator, weight: float = 1.0) -> QRAccumulator:
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
            for name in (
                "R_",
                "R_lo_",
                "scale_",
                "column_min_",
                "column_max_",
                "target_mean_",
                "target_css_",
            ):
                setattr(self, name, getattr(other, name).copy())
            self.n_obs = other.n_obs
            self.gram_rows_ = other.gram_rows_
            self.weight_sum_ = other.weight_sum_ * weight
            self.target_css_ = self.target_css_ * weight
            self.R_, self.R_lo_ = self.R_ * root, self.R_lo_ * root
            self._hac_adopt(other, weight)
            return self
        self._merge_hac(other, weight)
        assert other.scale_ is not None and self.scale_ is not None  # both hold rows
        ratio = root * other.scale_ / self.scale_
        self.R_, self.R_lo_ = dd_qr_r(
            np.vstack([self.R_, other.R_ * ratio]), np.vstack([self.R_lo_, other.R_lo_ * ratio])
        )
        self.column_min_ = np.minimum(self.column_min_, other.column_min_)
        self.column_max_ = np.maximum(self.column_max_, other.column_max_)
        self._merge_moments(other.weight_sum_ * weight, other.target_mean_, other.target_css_ * weight)
        self.n_obs += other.n_obs
        self.gram_rows_ += other.gram_rows_
        return self

    def copy(self) -> QRAccumulator:
        """An independent copy (through :meth:`to_dict` / :meth:`from_dict`)."""
        return QRAccumulator.from_dict(self.to_dict())

    # -- serialisation -------------------------------------------------------------------------

    def to_dict(self) -> dict:
        """Plain JSON-able state (lists, floats, ints, strings, bools): see :meth:`from_dict`."""
        return {
            "kind": ACCUMULATOR_KIND,
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
            "hac": self._hac_state(),
        }

    @classmethod
    def from_dict(cls, state: dict) -> QRAccumulator:
        """Rebuild an accumulator from :meth:`to_dict` output (e.g. after a JSON round trip)."""
        try:
            hac = state.get("hac")
            acc = cls(
                state["n_features"],
                state["n_targets"],
                state["feature_names"],
                state["target_names"],
                precision=state.get("precision", "auto"),
                hac_lags=None if hac is None else hac["lags"],
            )
            q = acc.n_features + acc.n_targets
            acc.n_obs = int(state["n_obs"])
            acc.extended_ = bool(state.get("extended", acc.extended_))
            acc.gram_rows_ = int(state.get("gram_rows", 0))
            acc.R_ = field_array(state, "R", (q, q))
            acc.R_lo_ = (
                field_array(state, "R_lo", (q, q)) if state.get("R_lo") is not None else np.zeros((q, q))
            )
            if acc.n_obs:
                acc.scale_ = field_array(state, "scale", (q,))
                acc.column_min_ = field_array(state, "column_min", (acc.n_features,))
                acc.column_max_ = field_array(state, "column_max", (acc.n_features,))
            acc.target_mean_ = field_array(state, "target_mean", (acc.n_targets,))
            acc.target_css_ = field_array(state, "target_css", (acc.n_targets,))
            acc.weight_sum_ = float(state.get("weight_sum", acc.n_obs))
            if hac is not None:
                acc._hac_load(hac)
        except KeyError as exc:
            raise InputError(
                f"missing field {exc.args[0]!r} in accumulator state", column=f"field {exc.args[0]}"
            ) from None
        return acc

    def __repr__(self) -> str:
        return f"QRAccumulator(n_features={self.n_features}, n_targets={self.n_targets}, n_obs={self.n_obs})"


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
                part = w if w is None or np.ndim(w) == 0 else w[lo : lo + chunk_rows]
                yield X[lo : lo + chunk_rows], Y[lo : lo + chunk_rows], part
            yield None

    for chunk in chunks():
        if chunk is not None:
            X, Y, w = chunk
            acc.update(X, Y, weights=w)
    if acc.hac_lags_ is not None and acc.n_obs:
        acc.begin_hac()
        for chunk in chunks():
            if chunk is None:
                acc.end_series()
            else:
                X, Y, w = chunk
                acc.update_hac(X, Y, weights=w)
    return acc


def ols(
    X, y, *, feature_names=None, target_name: str | None = None, cov_type: str = "HAC", maxlags=None
) -> OLSResults:
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
        lags = max(1, min(HAC_MAX_LAG, X.shape[0] - 1)) if maxlags in (None, "auto") else [int(maxlags)]
    acc = accumulate_series(
        QRAccumulator(X.shape[1], 1, feature_names, [target_name], hac_lags=lags),
        [(X, y, None)],
        chunk_rows=len(X) or 1,
    )
    res = ols_from_factor(acc, cov_type=cov_type, maxlags=maxlags)
    res.named = named
    res._data = (X, y, index)
    return res
