"""Results of a least-squares fit in the statsmodels vocabulary: :class:`OLSResults`.

Estimates, standard errors (naive or Newey-West), t and p values, confidence and prediction
intervals, the ANOVA table, information criteria and a Table 1 style summary, all from the
scaled triangular factor of the fit (never from an inverted ``X^T X``), and saved to / read
from plain JSON-able dicts.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from scipy import linalg

from fbgcomp.errors import InputError
from fbgcomp.models.distributions import f_sf, t_ppf, t_sf
from fbgcomp.models.regression.factor import field_array
from fbgcomp.models.regression.hac import COV_TYPES

__all__ = ["RESULTS_KIND", "OLSResults", "fmt_p"]

# The "kind" tag of saved results (to_dict): a data-format identifier written into model files,
# kept as it was when the module was fbgcomp/regression.py.
RESULTS_KIND = "fbgcomp.regression.OLSResults"


def _pandas():
    """pandas, imported on first use: named results only."""
    import pandas  # noqa: PLC0415 - start-up: the runtime imports the models without pandas (~1 s)

    return pandas


class _TermSeries:
    """One per-term array of :class:`OLSResults` (the attribute ``source``), read-only: a pandas
    Series indexed by the term names when the fit is named, the array itself otherwise."""

    def __init__(self, source: str, doc: str):
        self.source = source
        self.__doc__ = doc

    def __set_name__(self, owner, name: str) -> None:
        self.name = name

    def __get__(self, obj, owner=None):
        if obj is None:
            return self
        values = getattr(obj, self.source)
        if not obj.named:
            return values
        return _pandas().Series(values, index=list(obj.feature_names), dtype=float)

    def __set__(self, obj, value) -> None:
        raise AttributeError(f"can't set attribute {self.name!r}")


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

    params = _TermSeries("_params", "Estimated coefficients.")
    bse = _TermSeries("_bse", 'Standard errors of the coefficients (HAC ones when ``cov_type`` is "HAC").')
    tvalues = _TermSeries("_tvalues", "t statistics of the coefficients (estimate / standard error).")
    pvalues = _TermSeries("_pvalues", "Two-sided p-values of the t statistics on ``df_resid`` df.")

    def __init__(
        self,
        params,
        r_factor,
        feature_scale,
        *,
        ssr: float,
        nobs: int,
        k_constant: int,
        centered_tss: float,
        uncentered_tss: float,
        feature_names: Sequence[str],
        target_name: str = "y",
        cov_type: str = "nonrobust",
        robust_cov=None,
        cov_kwds: dict | None = None,
        const_index: int | None = None,
        named: bool = False,
        data=None,
    ):
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
        self._robust_cov = (
            None if robust_cov is None else np.asarray(robust_cov, dtype=float).reshape(m, m).copy()
        )

        with np.errstate(divide="ignore", invalid="ignore"):
            self.mse_resid = self.ssr / self.df_resid if self.df_resid > 0 else math.nan
            self.resid_sd = math.sqrt(self.mse_resid) if self.df_resid > 0 else math.nan
            # Rows of T^-1 give sqrt(diag((X_s^T X_s)^-1)) without forming the inverse product.
            # LAPACK trtri: the triangular inverse is computed to high relative accuracy.
            self._r_inv = linalg.lapack.dtrtri(self._r, lower=0)[0] if m else np.zeros((0, 0))
            self.bse_nonrobust = self.resid_sd * np.linalg.norm(self._r_inv, axis=1) / self._scale
            self._bse = (
                self.bse_nonrobust
                if self._robust_cov is None
                else np.sqrt(np.clip(np.diag(self._robust_cov), 0.0, None))
            )
            self._tvalues = self._params / self._bse
            self._pvalues = 2.0 * t_sf(np.abs(self._tvalues), self.df_resid)
            tss = self.centered_tss if self.k_constant else self.uncentered_tss
            self.ess = tss - self.ssr
            self.rsquared = 1.0 - self.ssr / tss if tss > 0 else math.nan
            self.rsquared_adj = (
                (1.0 - (self.nobs - self.k_constant) / self.df_resid * (1.0 - self.rsquared))
                if self.df_resid > 0
                else math.nan
            )
            if self.df_model > 0 and self.df_resid > 0:
                self.mse_model = self.ess / self.df_model
                self.fvalue = float(self.mse_model / self.mse_resid)
                if self._robust_cov is not None:
                    self.fvalue = self._wald_f(self._robust_cov)
                self.f_pvalue = float(f_sf(self.fvalue, self.df_model, self.df_resid))
            else:
                self.mse_model = self.fvalue = self.f_pvalue = math.nan

    # -- statsmodels-style views -------------------------------------------------------------

    def _rows(self, values: np.ndarray):
        """Per-row values as a Series on the rows' index named after the target (named fit)."""
        if not self.named:
            return values
        return _pandas().Series(values, index=self._data[2], name=self.target_name, dtype=float)

    def _need_data(self, what: str):
        if self._data is None:
            raise AttributeError(
                f"{what} needs the fitted rows: this fit comes from an "
                f"accumulated factor (or a saved model), which keeps none; fit "
                f"with ols(X, y) or compute y - res.predict(X)"
            )
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

    def _wald_f(self, robust_cov: np.ndarray) -> float:
        """Wald F of "every non-constant coefficient is 0" with the robust covariance."""
        keep = [i for i in range(self._params.size) if i != self.const_index]
        if self.k_constant and self.const_index is None:
            return math.nan
        b = self._params[keep]
        v = robust_cov[np.ix_(keep, keep)]
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
        q = t_ppf(1.0 - alpha / 2.0, self.df_resid)
        ci = np.column_stack([self._params - q * self._bse, self._params + q * self._bse])
        if not self.named:
            return ci
        return _pandas().DataFrame(ci, index=list(self.feature_names), columns=[0, 1])

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
        half = t_ppf(1.0 - alpha / 2.0, self.df_resid) * np.sqrt(self.mse_resid + var_fit)
        yhat = X @ self._params
        return yhat - half, yhat + half

    def anova(self):
        """ANOVA table (pandas DataFrame): Regression, Residual and Total rows.

        Columns df, sum_sq, mean_sq, F, PR(>F). With a constant in the model the total is the
        centred sum of squares on n - 1 df; otherwise the uncentred one on n df. This is the
        overall test behind the paper's "stepwise regression with ANOVA" (section 3).
        """
        pd = _pandas()
        total_df = self.nobs - self.k_constant
        total_ss = self.ess + self.ssr
        return pd.DataFrame(
            {
                "df": [self.df_model, self.df_resid, total_df],
                "sum_sq": [self.ess, self.ssr, total_ss],
                "mean_sq": [self.mse_model, self.mse_resid, math.nan],
                "F": [self.fvalue, math.nan, math.nan],
                "PR(>F)": [self.f_pvalue, math.nan, math.nan],
            },
            index=["Regression", "Residual", "Total"],
        )

    def summary(self) -> str:
        """Coefficient table in the style of the paper's Table 1, plus the overall fit figures."""
        ci = np.asarray(self.conf_int())
        width = max([len("term")] + [len(n) for n in self.feature_names])
        head = (
            f"{'term':<{width}}  {'estimate':>13} {'std error':>12} {'t':>9} {'P>|t|':>9}"
            f" {'[0.025':>13} {'0.975]':>13}"
        )
        rule = "=" * len(head)
        lines = [
            f"OLS regression of {self.target_name} on {self._params.size} terms".center(len(head)),
            rule,
            head,
            "-" * len(head),
        ]
        for i, name in enumerate(self.feature_names):
            lines.append(
                f"{name:<{width}}  {self._params[i]:>13.6g} {self._bse[i]:>12.4g} "
                f"{_fmt_t(self._tvalues[i]):>9} {fmt_p(self._pvalues[i]):>9} "
                f"{ci[i, 0]:>13.6g} {ci[i, 1]:>13.6g}"
            )
        lines.append(rule)
        kind = "" if self.k_constant else " (uncentred)"
        lines.append(
            f"R-squared{kind}: {self.rsquared:.6f}   Adj. R-squared: {self.rsquared_adj:.6f}"
            f"   Residual SD: {self.resid_sd:.6g} on {self.df_resid} df"
        )
        fname = "Wald F (HAC)" if self.cov_type == "HAC" else "F-statistic"
        lines.append(
            f"{fname}: {self.fvalue:.6g} on {self.df_model} and {self.df_resid} df"
            f"   Prob(F): {fmt_p(self.f_pvalue)}   n: {self.nobs}"
        )
        lines.append("Covariance: " + self.cov_description())
        return "\n".join(lines)

    def cov_description(self) -> str:
        """One line saying which covariance the standard errors come from."""
        if self.cov_type != "HAC":
            return "nonrobust (i.i.d. errors assumed; wrong for autocorrelated residuals)"
        k = self.cov_kwds
        how = "Andrews AR(1) bandwidth" if k.get("bandwidth") == "andrews-ar1" else "fixed bandwidth"
        return (
            f"HAC (Newey-West, Bartlett kernel, {k.get('maxlags')} lags, {how}); residual "
            f"lag-1 autocorrelation {k.get('rho1', math.nan):.4f}, effective sample size "
            f"{k.get('n_eff', math.nan):.4g} of {self.nobs}"
        )

    def __repr__(self) -> str:
        return (
            f"<OLSResults {self.target_name} ~ {' + '.join(self.feature_names)}: "
            f"n={self.nobs}, R2={self.rsquared:.4g}>"
        )

    # -- serialisation -------------------------------------------------------------------------

    def to_dict(self) -> dict:
        """Plain JSON-able model (lists and floats). ``bse`` is informative; :meth:`from_dict`
        recomputes it from the stored factor (or, for HAC, the stored robust covariance)."""
        return {
            "kind": RESULTS_KIND,
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
    def from_dict(cls, state: dict) -> OLSResults:
        """Rebuild results from :meth:`to_dict` output (e.g. a saved model)."""
        try:
            names = [str(n) for n in state["feature_names"]]
            m = len(names)
            return cls(
                field_array(state, "params", (m,)),
                field_array(state, "r_factor", (m, m)),
                field_array(state, "feature_scale", (m,)),
                ssr=float(state["ssr"]),
                nobs=int(state["nobs"]),
                k_constant=int(state["k_constant"]),
                centered_tss=float(state["centered_tss"]),
                uncentered_tss=float(state["uncentered_tss"]),
                feature_names=names,
                target_name=state.get("target_name", "y"),
                cov_type=state.get("cov_type", "nonrobust"),
                robust_cov=(
                    None if state.get("robust_cov") is None else field_array(state, "robust_cov", (m, m))
                ),
                cov_kwds=state.get("cov_kwds"),
                const_index=state.get("const_index"),
                named=bool(state.get("named", False)),
            )
        except KeyError as exc:
            raise InputError(
                f"missing field {exc.args[0]!r} in regression model", column=f"field {exc.args[0]}"
            ) from None


def _fmt_t(t: float) -> str:
    """A t statistic for a table: 3 decimals, or 3 significant digits when huge."""
    return f"{t:.3f}" if abs(t) < 1e5 else f"{t:.3g}"


def fmt_p(p: float) -> str:
    """A p-value for a table: 4 decimals, or 2 significant digits below 1e-4."""
    if not np.isfinite(p):
        return "nan"
    return f"{p:.4f}" if p >= 1e-4 else f"{p:.1e}"
