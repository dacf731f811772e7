"""TTP-deviation models: the multiple-regression estimator and its JSON model file.

:class:`MRAModel` is the paper's multiple regression analysis (sec. 3, eq. 11-13, Table 1): one
linear model per TTP axis (dx, dy, dz) on the regressors of :mod:`fbgcomp.models.features`, optionally
with stepwise selection (ANOVA partial F-tests). It follows the scikit-learn contract
(hyper-parameters in ``__init__``, learned state with a trailing underscore, ``fit`` returns
``self``) and fits from campaigns streamed in chunks through one QR factor, from which the
stepwise search and the fallback models (fitted without one or two sensors, used by the runtime
when a fibre fails) are all derived without re-reading the data.

The model file is JSON (never pickle): feature definitions, coefficients with standard errors
and covariance per axis, the zero-state convention, the sensors it expects, the training
campaigns and fit statistics, and a schema version.

Every model file goes through :func:`load_model` (the CLI, ``serve`` and the OPC UA reload), which
checks it at this boundary: at most :data:`MAX_MODEL_BYTES` and :data:`MAX_MODEL_DEPTH` levels of
nesting; no NaN or infinity anywhere; outside the descriptive statistics (:data:`STATISTICS`) no
null inside an array and no number beyond :data:`MAX_MODEL_VALUE`; arrays whose shapes agree with
their terms; and, for the regression and kinematic types, every predictor the runtime may switch
to (full set and fallbacks) predicting finite numbers. :meth:`ModelFile.save` writes a model only
once the written file passes the same checks, so a failed fit never replaces a good file.
"""

from __future__ import annotations

import hashlib
import inspect
import json
import math
from dataclasses import dataclass, field
from datetime import datetime, timezone
from itertools import combinations
from pathlib import Path

import numpy as np
from scipy import stats

from fbgcomp import __version__
from fbgcomp.atomic import write_json
from fbgcomp.errors import InputError, read_bounded
from fbgcomp.models.features import (CONSTANT, FEATURE_SETS, FeatureMap, TemperatureRoles, candidate_terms,
                       design_matrix)
from fbgcomp.models.regression import accumulate_series
from fbgcomp.units import AXES, REFERENCE_COLUMNS

#: Largest model file read, bytes (one with every fallback of a dozen gratings is ~1 MB).
MAX_MODEL_BYTES = 64 << 20
#: Deepest nesting of JSON objects and arrays in a model file (the deepest real one is ~10).
MAX_MODEL_DEPTH = 64
#: Largest magnitude of a number a model predicts with (coefficients in µm per µm or per K,
#: covariances, bounds, machine dimensions): a larger one is a corrupted or hostile file.
MAX_MODEL_VALUE = 1e12
#: Fields holding descriptive statistics, reported and never used to predict: inside them a
#: null (an undefined F, an infinite t of an exact fit) or a large number (a sum of squares) is
#: allowed. NaN and infinity are refused everywhere.
STATISTICS = frozenset({"fvalue", "f_pvalue", "tvalues", "pvalues", "bse", "rsquared",
                        "rsquared_adj", "stepwise_history", "hac", "training"})

MODEL_FORMAT = "fbgcomp-model"
SCHEMA_VERSION = 2
#: Upgrades of older model files, ``{from_version: function(dict) -> dict of from_version + 1}``.
MIGRATIONS: dict = {}


def _migrate_v1_to_v2(d: dict) -> dict:
    """v2 (model types kinematic, hybrid, dynamic) adds to every file the prediction-interval
    description ``uncertainty`` and the Z-axis position ``z_axis_mm`` the model assumes when the
    caller gives none (v1 files are regressions: their interval is the regression's, no Z)."""
    d = dict(d)
    d.setdefault("model_type", "mra")
    d.setdefault("uncertainty", {"level": 0.95, "method": "regression: covariance + residual variance"})
    d.setdefault("z_axis_mm", None)
    d["schema_version"] = 2
    return d


MIGRATIONS[1] = _migrate_v1_to_v2
_CHUNK_ROWS = 100_000
CAMPAIGN_WEIGHTS = ("balanced", "samples")


def campaign_weights_for(n_rows, mode="balanced") -> np.ndarray:
    """Row weight of each campaign in a pooled fit (weighted least squares).

    ``"samples"``: ordinary least squares, every row weight 1, so a 36 h campaign at 1 s
    outweighs a 10 min static test 200 to 1. ``"balanced"``: every campaign carries the same
    total weight (rows weighted ``N / (k n_c)``, total N). The sensors' noise enters the
    regressors; pooled unweighted, a long campaign whose elongations are mostly noise for some
    term dilutes the short campaign in which that term has signal and biases its coefficient
    towards zero (errors in variables: on the default bench, the dy gain under static loads came
    out at 60 % of its true value). Balancing keeps each experiment's information.
    """
    n_rows = np.asarray(n_rows, dtype=float)
    if mode == "samples" or n_rows.size == 0:
        return np.ones_like(n_rows)
    if mode != "balanced":
        raise ValueError(f"campaign_weights must be one of {', '.join(CAMPAIGN_WEIGHTS)}, not {mode!r}")
    return n_rows.sum() / (n_rows.size * np.maximum(n_rows, 1.0))


@dataclass
class AxisFit:
    """The fitted linear model of one TTP axis, as stored in the model file."""

    terms: list            # term names, "const" first
    params: np.ndarray     # µm per unit of each term
    bse: np.ndarray
    tvalues: np.ndarray
    pvalues: np.ndarray
    cov: np.ndarray        # covariance of params
    resid_sd: float        # µm
    df_resid: float
    nobs: int
    rsquared: float
    rsquared_adj: float
    fvalue: float
    f_pvalue: float
    history: list = field(default_factory=list)   # stepwise steps
    cov_type: str = "nonrobust"                   # "HAC": Newey-West bse, cov, tests
    hac: dict = field(default_factory=dict)       # HAC bandwidth, lag-1 rho, n_eff

    @classmethod
    def from_result(cls, result, history=()):
        return cls(terms=list(result.feature_names), params=np.asarray(result.params, float),
                   bse=np.asarray(result.bse, float), tvalues=np.asarray(result.tvalues, float),
                   pvalues=np.asarray(result.pvalues, float),
                   cov=np.asarray(result.cov_params(), float), resid_sd=float(result.resid_sd),
                   df_resid=float(result.df_resid), nobs=int(result.nobs),
                   rsquared=float(result.rsquared), rsquared_adj=float(result.rsquared_adj),
                   fvalue=float(result.fvalue), f_pvalue=float(result.f_pvalue),
                   history=[_plain(h) for h in history],
                   cov_type=getattr(result, "cov_type", "nonrobust"),
                   hac=_plain(dict(getattr(result, "cov_kwds", {}) or {})))

    def to_dict(self) -> dict:
        return {"terms": self.terms, "params": self.params.tolist(), "bse": self.bse.tolist(),
                "tvalues": self.tvalues.tolist(), "pvalues": self.pvalues.tolist(),
                "cov_params": self.cov.tolist(), "resid_sd_um": self.resid_sd,
                "df_resid": self.df_resid, "nobs": self.nobs, "rsquared": self.rsquared,
                "rsquared_adj": self.rsquared_adj, "fvalue": self.fvalue, "f_pvalue": self.f_pvalue,
                "stepwise_history": self.history, "cov_type": self.cov_type, "hac": self.hac}

    @classmethod
    def from_dict(cls, d: dict, where: str = "axes", source="<dict>") -> "AxisFit":
        """An axis of a model file; InputError naming ``where`` (its field path) when its
        arrays disagree with its terms or its residual statistics cannot predict."""
        terms = d["terms"]
        if not isinstance(terms, list) or not all(isinstance(t, str) for t in terms) or not terms:
            raise InputError("terms must be a non-empty list of names", file=source,
                             column=f"field {where}.terms")
        k = len(terms)

        def arr(key, shape):
            try:
                value = np.asarray(d[key], dtype=float)
            except (TypeError, ValueError):
                raise InputError("expected an array of numbers", file=source,
                                 column=f"field {where}.{key}") from None
            if value.shape != shape:
                raise InputError(f"shape {value.shape} disagrees with the {k} terms (expected "
                                 f"{shape})", file=source, column=f"field {where}.{key}")
            return value

        cov = arr("cov_params", (k, k))
        resid_sd, df_resid = float(d["resid_sd_um"]), float(d["df_resid"])
        if not (math.isfinite(resid_sd) and resid_sd >= 0):
            raise InputError(f"residual SD must be a finite number >= 0, not {resid_sd!r}",
                             file=source, column=f"field {where}.resid_sd_um")
        if not (math.isfinite(df_resid) and df_resid > 0):
            raise InputError(f"residual degrees of freedom must be > 0, not {df_resid!r}",
                             file=source, column=f"field {where}.df_resid")
        return cls(terms=list(terms), params=arr("params", (k,)), bse=arr("bse", (k,)),
                   tvalues=arr("tvalues", (k,)), pvalues=arr("pvalues", (k,)),
                   cov=cov, resid_sd=resid_sd, df_resid=df_resid,
                   nobs=int(d["nobs"]), rsquared=float(d["rsquared"]),
                   rsquared_adj=float(d["rsquared_adj"]), fvalue=_float_or_nan(d["fvalue"]),
                   f_pvalue=_float_or_nan(d["f_pvalue"]), history=list(d.get("stepwise_history", [])),
                   cov_type=d.get("cov_type", "nonrobust"), hac=dict(d.get("hac") or {}))

    def table(self) -> str:
        """Paper Table 1 style coefficient table."""
        # one space at least between columns, whatever the width a number takes
        lines = [f"{'term':<22} {'estimate':>12} {'std err':>11} {'t':>8} {'P>|t|':>9}"]
        for name, p, se, t, pv in zip(self.terms, self.params, self.bse, self.tvalues, self.pvalues):
            lines.append(f"{name:<22} {p:>12.5g} {se:>11.4g} {t:>8.2f} {pv:>9.3g}")
        lines.append(f"n = {self.nobs}, R² = {self.rsquared:.5f}, adj. R² = {self.rsquared_adj:.5f}, "
                     f"residual SD = {self.resid_sd:.4g} µm, "
                     f"{'Wald F (HAC)' if self.cov_type == 'HAC' else 'F'} = {self.fvalue:.4g} "
                     f"(p = {self.f_pvalue:.3g})")
        if self.cov_type == "HAC":
            h = self.hac
            lines.append(f"std errors: HAC (Newey-West, Bartlett, {h.get('maxlags')} lags); "
                         f"residual lag-1 autocorrelation {h.get('rho1', float('nan')):.4f}, "
                         f"effective sample size {h.get('n_eff', float('nan')):.4g} of {self.nobs}")
        else:
            lines.append("std errors: nonrobust (i.i.d. errors assumed)")
        return "\n".join(lines)


def _float_or_nan(value) -> float:
    """JSON has no NaN: an undefined statistic (F of a constant-only model) is stored as null."""
    return float("nan") if value is None else float(value)


def _plain(obj):
    """JSON-able copy of a stepwise history entry (numpy scalars -> Python)."""
    if isinstance(obj, dict):
        return {k: _plain(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_plain(v) for v in obj]
    if isinstance(obj, np.generic):
        return obj.item()
    return obj


class Predictor:
    """Pure-numpy prediction of the TTP deviation for one sensor set (full or fallback).

    Compiled once; :meth:`predict` is vectorised over frames and used by both the offline
    validation and the real-time runtime, so there is a single implementation.
    """

    def __init__(self, feature_map: FeatureMap, axes: dict, exclude=frozenset(), alpha=0.05):
        self.feature_map = feature_map
        self.exclude = frozenset(exclude)
        self.sensor_names = feature_map.sensor_names
        self.probe_names = list(feature_map.probe_names)
        terms = []
        for a in AXES:
            terms += [t for t in axes[a].terms if t != CONSTANT]
        self.terms = list(dict.fromkeys(terms))
        n_terms = 1 + len(self.terms)
        position = {CONSTANT: 0, **{t: i + 1 for i, t in enumerate(self.terms)}}
        self.coef = np.zeros((n_terms, len(AXES)))
        self._cov_sqrt = np.zeros((len(AXES), n_terms, n_terms))
        self._resid_var = np.zeros(len(AXES))
        self._t = np.zeros(len(AXES))
        for j, a in enumerate(AXES):
            fit = axes[a]
            idx = [position[t] for t in fit.terms]
            self.coef[idx, j] = fit.params
            w, v = np.linalg.eigh((fit.cov + fit.cov.T) / 2)
            root = v * np.sqrt(np.clip(w, 0.0, None))
            self._cov_sqrt[j][np.ix_(idx, range(len(idx)))] = root
            self._resid_var[j] = fit.resid_sd ** 2
            self._t[j] = stats.t.ppf(1 - alpha / 2, fit.df_resid)
        self.expected_rms_error_um = np.sqrt(self._resid_var)
        self._compile()

    def _compile(self):
        """Index form of the terms and the stacked covariance roots, so that a batch costs a
        few array operations whatever the number of terms (per-frame work at run time).

        ``_factors`` (terms, k): the base columns each term multiplies, padded with the index
        of a column of ones (a product with 1.0 is exact: the same numbers as
        :func:`design_matrix`); ``_cov_stack`` (K, 3K): the three axes' roots side by side,
        one matrix product for the whole interval."""
        from fbgcomp.models.features import parse_term

        names = list(self.feature_map.base_names)
        index = {name: i for i, name in enumerate(names)}
        factors = []
        for term in self.terms:
            fs = parse_term(term)
            missing = [f for f in fs if f not in index]
            if missing:
                factors = None     # design_matrix names the missing feature at predict time
                break
            factors.append([index[f] for f in fs])
        if factors:
            k = max(len(f) for f in factors)
            self._factors = np.array([f + [len(names)] * (k - len(f)) for f in factors])
        else:
            self._factors = None if factors is None else np.zeros((0, 1), int)
        self._cov_stack = np.concatenate(list(self._cov_sqrt), axis=1)

    def _design_from_base(self, base) -> np.ndarray:
        base = np.atleast_2d(np.asarray(base, dtype=float))
        fac = getattr(self, "_factors", None)
        if fac is None:
            return design_matrix(base, self.feature_map.base_names, self.terms)
        n, width = base.shape
        out = np.empty((n, 1 + fac.shape[0]))
        out[:, 0] = 1.0
        if fac.shape[0]:
            ext = np.empty((n, width + 1))
            ext[:, :width] = base
            ext[:, width] = 1.0
            cols = ext[:, fac]                                   # (n, terms, k)
            out[:, 1:] = cols[:, :, 0]
            for c in range(1, fac.shape[1]):
                out[:, 1:] *= cols[:, :, c]
        return out

    def _interval_var(self, d) -> np.ndarray:
        """Residual variance plus the parameter part x' C x per frame and axis (n, 3): one
        matrix product with the stacked roots (the same sum as the per-axis einsum)."""
        stack = getattr(self, "_cov_stack", None)
        if stack is None:
            self._compile()
            stack = self._cov_stack
        spread = d @ stack
        spread *= spread
        K = self._cov_sqrt.shape[1]
        return self._resid_var[None, :] + spread.reshape(d.shape[0], len(AXES), K).sum(axis=2)

    def design(self, wavelength_nm, temperature_C, wavelength_zero_nm, temperature_zero_C):
        base = self.feature_map.base(wavelength_nm, temperature_C, wavelength_zero_nm, temperature_zero_C)
        return self._design_from_base(base)

    def predict(self, wavelength_nm, temperature_C, wavelength_zero_nm, temperature_zero_C, *,
                time_s=None):
        """TTP deviation (n, 3) µm and the half-width (n, 3) µm of its 95 % prediction interval.

        Parameters
        ----------
        wavelength_nm : ndarray, shape (n, S)
            Bragg wavelengths in the model's sensor order, nm. Columns of excluded sensors are
            ignored (they may be NaN).
        temperature_C : ndarray, shape (n, P)
            Probe temperatures in the model's probe order, °C.
        wavelength_zero_nm, temperature_zero_C : ndarray
            Zero state (S,) and (P,).
        time_s : ndarray, shape (n,), optional
            Frame times, s. A static regression has no memory, so they are not used; the
            keyword is every predictor's, so the runtime passes the clock to all alike.
        """
        wavelength_nm = np.atleast_2d(np.asarray(wavelength_nm, dtype=float))
        if self.exclude:
            # Excluded gratings carry no coefficient; keep NaN from spreading through 0 * NaN.
            cols = [i for i, s in enumerate(self.sensor_names) if s in self.exclude]
            wavelength_nm = wavelength_nm.copy()
            wavelength_nm[:, cols] = np.asarray(wavelength_zero_nm, dtype=float)[cols]
        d = self.design(wavelength_nm, temperature_C, wavelength_zero_nm, temperature_zero_C)
        deviation = d @ self.coef
        return deviation, self._t[None, :] * np.sqrt(self._interval_var(d))


class EstimatorParams:
    """scikit-learn's parameter protocol (``get_params`` / ``set_params``) from ``__init__``.

    Lets ``sklearn.base.clone``, grid searches and pipelines handle fbgcomp's estimators without
    making scikit-learn a dependency of the package.
    """

    @classmethod
    def _param_names(cls):
        import inspect

        sig = inspect.signature(cls.__init__)
        return [p.name for p in sig.parameters.values()
                if p.name != "self" and p.kind not in (p.VAR_POSITIONAL, p.VAR_KEYWORD)]

    def get_params(self, deep=True) -> dict:
        return {name: getattr(self, name) for name in self._param_names()}

    def set_params(self, **params):
        valid = set(self._param_names())
        for key, value in params.items():
            if key not in valid:
                raise ValueError(f"invalid parameter {key!r} for {type(self).__name__}; "
                                 f"valid: {', '.join(sorted(valid))}")
            setattr(self, key, value)
        return self

    def __repr__(self) -> str:
        args = ", ".join(f"{k}={v!r}" for k, v in self.get_params().items())
        return f"{type(self).__name__}({args})"


def deviation_range(reference_um) -> dict:
    """The range of TTP deviations (n, 3) µm a training campaign showed, as its entry in a model
    file's ``training.campaigns`` records it (the envelope of :attr:`ModelFile.max_correction_um`)."""
    ref = np.asarray(reference_um, float)
    return {"deviation_low_um": np.min(ref, axis=0).tolist(), "deviation_high_um": np.max(ref, axis=0).tolist()}


class ModelFile:
    """What every model type shares: the sensors and probes it expects, its id and its file.

    Subclasses define ``model_type``, ``to_dict()`` and a ``from_dict`` classmethod, and set
    ``sensors_`` and ``probe_names_`` when fitted.
    """

    @property
    def sensors(self):
        return self.sensors_

    @property
    def sensor_names(self) -> list:
        return [s.name for s in self.sensors_]

    @property
    def probe_names(self) -> list:
        return list(self.probe_names_)

    @property
    def model_id(self) -> str:
        return model_id(self.to_dict())

    def _header(self) -> dict:
        return {"format": MODEL_FORMAT, "schema_version": SCHEMA_VERSION,
                "model_type": self.model_type, "fbgcomp_version": __version__}

    def save(self, path) -> Path:
        """Write the model file atomically, with its id and creation time.

        The file is written under a temporary name and loaded back with :func:`load_model`; only
        a model that passes every check replaces ``path``. Otherwise InputError, and an existing
        file at ``path`` is left as it was (a fit on bad data never overwrites a good model).
        """
        path = Path(path)
        d = self.to_dict()
        d["model_id"] = model_id(d)
        d["created_utc"] = datetime.now(timezone.utc).isoformat(timespec="seconds")

        def loads_back(written: Path) -> None:
            try:
                load_model(written)
            except InputError as err:
                raise InputError(f"the model is not valid, so {path.name} was not written "
                                 f"(an existing one is unchanged): {err.message}", file=path,
                                 column=err.column) from None

        return write_json(path, d, check=loads_back)

    #: Margin on the training deviations within which a correction counts as validated: the
    #: runtime clamps beyond ``ENVELOPE_MARGIN`` x the largest |deviation| of an axis in training
    #: (DEGRADED) and holds beyond 3x that (ALARM).
    ENVELOPE_MARGIN = 1.5

    @property
    def max_correction_um(self):
        """Largest |correction| per axis this model was validated for: ``ENVELOPE_MARGIN`` x the
        largest |TTP deviation| each axis showed in the training campaigns (µm), or None when the
        model file does not record them (fitted from arrays or statistics, or an older file)."""
        runs = (getattr(self, "training_", None) or {}).get("campaigns", [])
        if not runs or any("deviation_low_um" not in r or "deviation_high_um" not in r for r in runs):
            return None
        lo = np.min([np.asarray(r["deviation_low_um"], float) for r in runs], axis=0)
        hi = np.max([np.asarray(r["deviation_high_um"], float) for r in runs], axis=0)
        peak = np.maximum(np.abs(lo), np.abs(hi))
        if peak.shape != (3,) or not np.all(np.isfinite(peak)):
            return None
        return [float(v) for v in self.ENVELOPE_MARGIN * peak]

    def predict(self, X):
        """Predicted TTP deviation (n, 3) in µm."""
        return self.predict_interval(X)[0]

    def instrument_arrays(self, aligned):
        """Wavelengths, temperatures and zero states of an aligned campaign in the model's order."""
        s_idx = [list(aligned.sensor_names).index(s) for s in self.sensor_names]
        p_idx = [list(aligned.probe_names).index(p) for p in self.probe_names_]
        return (aligned.wavelength_nm[:, s_idx], aligned.temperature_C[:, p_idx],
                aligned.wavelength_zero_nm[s_idx], aligned.temperature_zero_C[p_idx])


class MRAModel(EstimatorParams, ModelFile):
    """Multiple regression of the TTP deviation on sensor elongations and temperatures.

    Parameters
    ----------
    features : {"eq11", "eq13", "eq12"}
        Candidate regressors (see :mod:`fbgcomp.models.features`).
    stepwise : bool
        Select terms per axis by stepwise regression with partial F-tests.
    direction : {"both", "forward", "backward"}
    p_enter, p_remove : float
        Stepwise thresholds.
    max_terms : int, optional
        Upper bound on selected terms (constant excluded).
    roles : TemperatureRoles or dict, optional
        Probes playing bulk / surface / flange (default T_bulk, T_surf, T_flange).
    zero_window_s : float
        Zero state = mean over the first ``zero_window_s`` seconds of each signal.
    fallbacks : {"loo", "lto", "none"}
        Also fit models without each sensor ("loo") or each pair of sensors ("lto", implies loo)
        for the runtime's sensor-fault fallback.
    campaign_weights : {"balanced", "samples"}
        How campaigns of different lengths are pooled (see :func:`campaign_weights_for`): equal
        total weight per campaign (weighted least squares), or one weight per sample (OLS).
    cov_type : {"HAC", "nonrobust"}
        Inference behind the stepwise tests, the coefficient tables and the prediction
        intervals. "HAC" (default): Newey-West, robust to the residuals' autocorrelation (each
        campaign a separate series; samples of slow drifts are far from independent).
        "nonrobust": the paper's i.i.d. partial F tests (its Table 1).
    hac_maxlags : "auto" or int
        Newey-West bandwidth: "auto" chooses it per model by Andrews' AR(1) rule among
        1, 2, 4, ..., 4096 lags; an int fixes it.
    """

    model_type = "mra"

    def __init__(self, features="eq13", stepwise=False, direction="both", p_enter=0.05,
                 p_remove=0.10, max_terms=None, roles=None, zero_window_s=10.0, fallbacks="loo",
                 campaign_weights="balanced", cov_type="HAC", hac_maxlags="auto"):
        self.features = features
        self.stepwise = stepwise
        self.direction = direction
        self.p_enter = p_enter
        self.p_remove = p_remove
        self.max_terms = max_terms
        self.roles = roles
        self.zero_window_s = zero_window_s
        self.fallbacks = fallbacks
        self.campaign_weights = campaign_weights
        self.cov_type = cov_type
        self.hac_maxlags = hac_maxlags

    # -- fitting -------------------------------------------------------------------------
    def _roles(self) -> TemperatureRoles:
        if self.roles is None:
            return TemperatureRoles()
        if isinstance(self.roles, TemperatureRoles):
            return self.roles
        return TemperatureRoles(**self.roles)

    def _check_params(self):
        if self.features not in FEATURE_SETS:
            raise ValueError(f"features must be one of {', '.join(FEATURE_SETS)}, not {self.features!r}")
        if self.direction not in ("both", "forward", "backward"):
            raise ValueError(f"direction must be both, forward or backward, not {self.direction!r}")
        if self.fallbacks not in ("loo", "lto", "none"):
            raise ValueError(f"fallbacks must be loo, lto or none, not {self.fallbacks!r}")
        if getattr(self, "campaign_weights", "samples") not in CAMPAIGN_WEIGHTS:
            raise ValueError(f"campaign_weights must be one of {', '.join(CAMPAIGN_WEIGHTS)}, "
                             f"not {self.campaign_weights!r}")
        if getattr(self, "cov_type", "nonrobust") not in ("HAC", "nonrobust"):
            raise ValueError(f"cov_type must be HAC or nonrobust, not {self.cov_type!r}")
        lags = getattr(self, "hac_maxlags", "auto")
        if lags != "auto" and not (isinstance(lags, (int, np.integer)) and not isinstance(lags, bool)
                                   and lags >= 1):
            raise ValueError(f"hac_maxlags must be 'auto' or a positive int, not {lags!r}")

    def _hac_lags(self):
        """Bandwidths the accumulator must keep (None for naive inference)."""
        if getattr(self, "cov_type", "nonrobust") != "HAC":
            return None
        lags = getattr(self, "hac_maxlags", "auto")
        return "auto" if lags == "auto" else [int(lags)]

    def _new_qr(self, names):
        from fbgcomp.models.regression import QRAccumulator

        return QRAccumulator(len(names), len(AXES), feature_names=names, target_names=list(AXES),
                             hac_lags=self._hac_lags())

    def fit(self, X, y=None, *, progress=None):
        """Fit on campaigns (``X`` a campaign, a path or a list of them, ``y`` None) or on arrays.

        With arrays, ``X`` is a pandas DataFrame of base features (columns ``dL_<sensor>`` and,
        for eq12/eq13, ``dT_bulk``, ``dT_surf``, ``dT_flange``) and ``y`` an (n, 3) array of
        TTP deviations in µm (dx, dy, dz).
        """
        self._check_params()
        if y is not None:
            return self._fit_arrays(X, y)
        campaigns = _as_campaign_list(X)
        if not campaigns:
            raise ValueError("fit needs at least one campaign")
        sensors = list(campaigns[0].meta.sensors)
        self.sensors_ = sensors
        uses_t = self.features != "eq11"
        self.probe_names_ = FeatureMap.required_probes(sensors, uses_t, self._roles())
        self.candidates_ = candidate_terms(self.features, [s.name for s in sensors])
        names = [CONSTANT] + self.candidates_
        acc = self._new_qr(names)
        training = []
        for c in campaigns:
            check_compatible(self, c)
        # Row counts first: the weights of a balanced pool depend on every campaign's length.
        aligned_all = [c.aligned(zero_window_s=self.zero_window_s) for c in campaigns]
        weights = campaign_weights_for([len(a.time_s) for a in aligned_all],
                                       getattr(self, "campaign_weights", "samples"))
        series = []
        for c, aligned, weight in zip(campaigns, aligned_all, weights):
            design = self._campaign_design(c, aligned)
            check_finite_fit_data(c, aligned, design, names)
            series.append((design, aligned.reference_um, weight))
            ref = aligned.reference_um
            training.append({"name": c.meta.name, "kind": c.meta.kind,
                             "path": None if c.path is None else str(c.path),
                             "n_samples": int(len(design)), "row_weight": float(weight),
                             "dropped": _plain(aligned.dropped),
                             **deviation_range(ref)})
            if progress is not None:
                progress(c.meta.name)
        # Two passes (factor, then autocorrelation statistics about the full model's
        # coefficients); no autocorrelation lag spans two campaigns.
        accumulate_series(acc, series, chunk_rows=_CHUNK_ROWS)
        self.training_ = {"campaigns": training, "n_samples": int(sum(t["n_samples"] for t in training))}
        return self._fit_factor(acc)

    # -- fitting from statistics reduced elsewhere (fbgcomp.io.dataset, fbgcomp.io.distributed) ------
    def new_accumulator(self, sensors, probe_names=None):
        """Fix the sensor set (``SensorSpec`` list) and return an empty QR accumulator whose
        columns are this model's terms (``const`` first) and whose targets are dx, dy, dz.

        ``probe_names`` lists the probes the data offers; a missing required probe is an
        InputError. Partitions accumulated on other processes with an estimator configured the
        same way merge into it (:meth:`fbgcomp.models.regression.QRAccumulator.merge`).
        """
        self._check_params()
        self.sensors_ = list(sensors)
        self.probe_names_ = FeatureMap.required_probes(self.sensors_, self.features != "eq11",
                                                       self._roles())
        if probe_names is not None:
            missing = [p for p in self.probe_names_ if p not in set(probe_names)]
            if missing:
                raise InputError(f"the data lacks temperature probe(s) {', '.join(missing)} "
                                 f"needed by features {self.features}",
                                 column="field temperature_probes")
        self.candidates_ = candidate_terms(self.features, [s.name for s in self.sensors_])
        names = [CONSTANT] + self.candidates_
        return self._new_qr(names)

    def design_from_arrays(self, wavelength_nm, temperature_C, wavelength_zero_nm,
                           temperature_zero_C):
        """Design matrix (n, 1 + terms) from raw instrument arrays in the model's sensor and
        probe order (nm, °C, zero states nm and °C); after :meth:`new_accumulator`."""
        fmap = self._feature_map()
        base = fmap.base(wavelength_nm, temperature_C, wavelength_zero_nm, temperature_zero_C)
        return design_matrix(base, fmap.base_names, self.candidates_)

    def fit_factor(self, acc, training=None):
        """Finish a fit from an accumulator filled elsewhere (after :meth:`new_accumulator`):
        selection, fallbacks and results exactly as :meth:`fit`, without reading any data.

        ``training`` is the description stored in the model file (``{"campaigns": [...],
        "n_samples": n}``); by default the accumulator's row count and no campaign list.
        """
        self._check_params()
        if getattr(self, "candidates_", None) is None:
            raise ValueError("call new_accumulator(sensors) before fit_factor")
        if list(acc.feature_names) != [CONSTANT] + list(self.candidates_):
            raise ValueError("the accumulator's columns are not this model's terms")
        self.training_ = (dict(training) if training is not None
                          else {"campaigns": [], "n_samples": int(acc.n_obs)})
        return self._fit_factor(acc)

    def _fit_arrays(self, X, y):
        base_names = list(X.columns)
        sensor_names = [c[3:] for c in base_names if c.startswith("dL_")]
        self.sensors_ = None
        self.probe_names_ = []
        self.candidates_ = candidate_terms(self.features, sensor_names)
        self._array_base_names = base_names
        names = [CONSTANT] + self.candidates_
        design = design_matrix(X.to_numpy(dtype=float), base_names, self.candidates_)
        acc = self._new_qr(names)
        y = np.asarray(y, dtype=float).reshape(len(design), len(AXES))
        accumulate_series(acc, [(design, y, None)], chunk_rows=_CHUNK_ROWS)
        self.training_ = {"campaigns": [], "n_samples": int(len(design))}
        return self._fit_factor(acc)

    def _fit_factor(self, acc):
        self.axes_ = self._select(acc, exclude=frozenset())
        self.fallbacks_ = {}
        sensor_names = [t[3:] for t in self.candidates_ if t.startswith("dL_")]
        sizes = {"none": (), "loo": (1,), "lto": (1, 2)}[self.fallbacks]
        for k in sizes:
            for drop in combinations(sensor_names, k):
                if len(sensor_names) - k < 1:
                    continue
                self.fallbacks_[frozenset(drop)] = self._select(acc, exclude=frozenset(drop))
        self.results_ = {a: f for a, f in self.axes_.items()}
        self.coef_ = {a: dict(zip(f.terms, f.params)) for a, f in self.axes_.items()}
        self._predictors = {}
        return self

    def _select(self, acc, exclude) -> dict:
        from fbgcomp.models.regression import ols_from_factor, stepwise

        candidates = [t for t in self.candidates_ if not any(f"dL_{s}" == t for s in exclude)]
        # HAC needs the accumulator's lagged score sums; subclasses that build their own plain
        # accumulator (dynamic, hybrid) keep the naive inference, and say so in each AxisFit.
        cov_type = getattr(self, "cov_type", "nonrobust")
        if getattr(acc, "hac_lags_", None) is None:
            cov_type = "nonrobust"
        maxlags = getattr(self, "hac_maxlags", "auto") if cov_type == "HAC" else None
        axes = {}
        for j, a in enumerate(AXES):
            if self.stepwise:
                sw = stepwise(acc, candidates, target=j, direction=self.direction,
                              p_enter=self.p_enter, p_remove=self.p_remove,
                              max_terms=self.max_terms, include=[CONSTANT],
                              cov_type=cov_type, maxlags=maxlags)
                history = sw.history.to_dict("records") if hasattr(sw.history, "to_dict") else list(sw.history)
                axes[a] = AxisFit.from_result(sw.result, history)
            else:
                axes[a] = AxisFit.from_result(ols_from_factor(acc, [CONSTANT] + candidates, target=j,
                                                              cov_type=cov_type, maxlags=maxlags))
        return axes

    def _campaign_design(self, campaign, aligned):
        fmap = self._feature_map()
        probe_cols = [list(aligned.probe_names).index(p) for p in self.probe_names_]
        base = fmap.base(aligned.wavelength_nm[:, [list(aligned.sensor_names).index(s) for s in fmap.sensor_names]],
                         aligned.temperature_C[:, probe_cols],
                         aligned.wavelength_zero_nm[[list(aligned.sensor_names).index(s) for s in fmap.sensor_names]],
                         aligned.temperature_zero_C[probe_cols])
        return design_matrix(base, fmap.base_names, self.candidates_)

    # -- prediction ----------------------------------------------------------------------
    def _feature_map(self) -> FeatureMap:
        return FeatureMap(self.sensors_, self.probe_names_, self.features != "eq11", self._roles())

    @property
    def fallback_sets(self) -> list:
        return list(self.fallbacks_)

    def predictor(self, exclude=frozenset()) -> Predictor:
        """Compiled predictor for the full sensor set or a stored fallback (KeyError if none)."""
        exclude = frozenset(exclude)
        if exclude not in self._predictors:
            axes = self.axes_ if not exclude else self.fallbacks_[exclude]
            self._predictors[exclude] = Predictor(self._feature_map(), axes, exclude)
        return self._predictors[exclude]

    def predict_interval(self, X, exclude=frozenset()):
        """Prediction (n, 3) µm and half-width (n, 3) µm of its 95 % prediction interval."""
        if hasattr(X, "columns"):
            pred = Predictor(_IdentityMap(list(X.columns)), self.axes_ if not exclude else self.fallbacks_[frozenset(exclude)])
            return pred.predict(X.to_numpy(dtype=float), None, None, None)
        (campaign,) = _as_campaign_list(X)
        check_compatible(self, campaign)
        aligned = campaign.aligned(zero_window_s=self.zero_window_s)
        p = self.predictor(exclude)
        w, t, w0, t0 = self.instrument_arrays(aligned)
        return p.predict(w, t, w0, t0)

    # -- reporting and persistence ------------------------------------------------------
    def summary(self) -> str:
        """Table 1 style coefficient table per axis, with the stepwise history."""
        out = [f"MRA model ({self.features}{', stepwise' if self.stepwise else ''}, "
               f"{self.axes_['dx'].cov_type} inference), "
               f"{self.training_['n_samples']} samples from "
               f"{', '.join(c['name'] for c in self.training_['campaigns']) or 'arrays'}"]
        for a in AXES:
            fit = self.axes_[a]
            out.append(f"\n== {a} (µm) ==")
            out.append(fit.table())
            if fit.history:
                out.append("stepwise history:")
                out.append(f"  {'step':>4} {'action':<7}{'term':<22}{'F':>10}{'p':>10}{'terms':>6}")
                for h in fit.history:
                    out.append(f"  {h.get('step', ''):>4} {h.get('action', ''):<7}{str(h.get('term', '')):<22}"
                               f"{h.get('F', float('nan')):>10.4g}{h.get('p', float('nan')):>10.3g}"
                               f"{h.get('n_terms', ''):>6}")
        return "\n".join(out)

    def to_dict(self) -> dict:
        d = {
            "format": MODEL_FORMAT,
            "schema_version": SCHEMA_VERSION,
            "model_type": self.model_type,
            "fbgcomp_version": __version__,
            "features": {"set": self.features, "candidates": list(self.candidates_),
                         "roles": self._roles().as_dict(),
                         "stepwise": ({"direction": self.direction, "p_enter": self.p_enter,
                                       "p_remove": self.p_remove, "max_terms": self.max_terms}
                                      if self.stepwise else None)},
            "zero_state": {"method": "mean_of_first_window", "window_s": self.zero_window_s},
            "sensors": [s.model_dump(mode="json") for s in self.sensors_] if self.sensors_ else [],
            "probes": list(self.probe_names_),
            "axes": {a: f.to_dict() for a, f in self.axes_.items()},
            "fallbacks": [{"exclude": sorted(k), "axes": {a: f.to_dict() for a, f in v.items()}}
                          for k, v in self.fallbacks_.items()],
            "fallback_policy": self.fallbacks,
            "campaign_weights": getattr(self, "campaign_weights", "samples"),
            "training": self.training_,
            "inference": {"cov_type": getattr(self, "cov_type", "nonrobust"),
                          "hac_maxlags": getattr(self, "hac_maxlags", "auto")},
            "uncertainty": {"level": 0.95, "method": ("regression: HAC (Newey-West) covariance + residual variance"
                                                      if self.axes_["dx"].cov_type == "HAC" else
                                                      "regression: covariance + residual variance")},
            "z_axis_mm": None,
        }
        return d

    @classmethod
    def from_dict(cls, d: dict, source="<dict>", check=True) -> "MRAModel":
        """The model of a model file's dict; ``check=False`` skips :func:`check_predictors`
        (for a subclass that builds on this one and checks its own predictors)."""
        f = d["features"]
        sw = f.get("stepwise")
        m = cls(features=f["set"], stepwise=sw is not None,
                **({k: sw[k] for k in ("direction", "p_enter", "p_remove", "max_terms")} if sw else {}),
                roles=f.get("roles"), zero_window_s=d["zero_state"]["window_s"],
                fallbacks=d.get("fallback_policy", "none"),
                campaign_weights=d.get("campaign_weights", "samples"),
                # files written before issue 12 were fitted with naive inference
                cov_type=d.get("inference", {}).get("cov_type", "nonrobust"),
                hac_maxlags=d.get("inference", {}).get("hac_maxlags", "auto"))
        m._check_params()
        m.candidates_ = list(f["candidates"])
        m.sensors_ = _sensor_specs(d["sensors"], source)
        m.probe_names_ = list(d["probes"])
        m.axes_ = {a: AxisFit.from_dict(d["axes"][a], f"axes.{a}", source) for a in AXES}
        m.fallbacks_ = {}
        for i, fb in enumerate(d.get("fallbacks", [])):
            exclude = frozenset(fb["exclude"])
            if not exclude <= set(m.sensor_names):
                raise InputError("a fallback excludes sensors the model does not have",
                                 file=source, column=f"field fallbacks[{i}].exclude")
            m.fallbacks_[exclude] = {a: AxisFit.from_dict(fb["axes"][a], f"fallbacks[{i}].axes.{a}",
                                                          source) for a in AXES}
        known = {CONSTANT, *m.candidates_}
        for where, axes in [("axes", m.axes_)] + [(f"fallbacks[{i}].axes", v) for i, v in
                                                  enumerate(m.fallbacks_.values())]:
            for a, fit in axes.items():
                unknown = [t for t in fit.terms if t not in known]
                if unknown:
                    raise InputError(f"term {_short_text(unknown[0])} is not among the model's "
                                     "candidates", file=source, column=f"field {where}.{a}.terms")
        m.training_ = d.get("training", {"campaigns": [], "n_samples": 0})
        m.results_ = dict(m.axes_)
        m.coef_ = {a: dict(zip(fit.terms, fit.params)) for a, fit in m.axes_.items()}
        m._predictors = {}
        if check:
            check_predictors(m, source)
        return m


def _sensor_specs(items, source) -> list:
    """The model file's sensor list as SensorSpec; InputError naming the entry otherwise."""
    from pydantic import ValidationError

    from fbgcomp.io.campaign import SensorSpec

    if not isinstance(items, list) or not items:
        raise InputError("expected a non-empty list of sensors", file=source, column="field sensors")
    specs = []
    for i, item in enumerate(items):
        try:
            specs.append(SensorSpec.model_validate(item))
        except ValidationError as exc:
            err = exc.errors()[0]
            where = ".".join(str(p) for p in err["loc"])
            raise InputError(_short_text(err["msg"]), file=source,
                             column=f"field sensors[{i}]" + (f".{where}" if where else "")) from None
    return specs


def check_finite_fit_data(campaign, aligned, design, names) -> None:
    """InputError naming the campaign unless its design and TTP deviations are finite.

    The campaign reader bounds every input, so this fires only when a feature of bounded
    inputs still overflows; the regression would otherwise fit NaN and write a model of nulls.
    """
    where = campaign.path if campaign.path is not None else campaign.meta.name
    for what, values, columns in (("design", design, names),
                                  ("reference deviation", aligned.reference_um, REFERENCE_COLUMNS)):
        bad = ~np.isfinite(values)
        if bad.any():
            row, col = np.argwhere(bad)[0]
            raise InputError(f"the {what} built from this campaign is not finite at t = "
                             f"{aligned.time_s[row]:g} s (term {columns[col]}): an input is out of "
                             "range; nothing was fitted", file=where)


def _zero_state_frames(model):
    """Two frames for :func:`check_predictors`: at rest, and 0.05 nm / 1 K off it."""
    w0 = np.array([s.lambda0_nm for s in model.sensors], dtype=float)
    t0 = np.full(len(model.probe_names), 20.0)
    return np.vstack([w0, w0 + 0.05]), np.vstack([t0, t0 + 1.0]), w0, t0


def check_predictors(model, source="<dict>") -> None:
    """Compile every predictor the runtime may switch to (the full sensor set and each stored
    fallback) and run it on two frames: InputError naming the file unless each gives finite
    (2, 3) deviations and half-widths. Catches terms, coefficients and sensors that disagree,
    which would otherwise surface only when the runtime first needs that fallback."""
    sets = [frozenset()] + [frozenset(s) for s in getattr(model, "fallback_sets", ())]
    w, t, w0, t0 = _zero_state_frames(model)
    for exclude in sets:
        label = ("the full sensor set" if not exclude
                 else f"the fallback without {', '.join(sorted(exclude))}")
        field = "field axes" if not exclude else "field fallbacks"
        try:
            p = model.predictor(exclude)
            takes_time = "time_s" in inspect.signature(p.predict).parameters
            if hasattr(p, "reset"):
                p.reset()
            out = p.predict(w, t, w0, t0, **({"time_s": np.array([0.0, 1.0])} if takes_time else {}))
            dev, half = (np.asarray(v, dtype=float) for v in out)
        except InputError:
            raise
        except Exception as exc:  # noqa: BLE001 - any failure: the file's parts disagree
            raise InputError(f"{label} cannot predict: its terms, coefficients and sensors "
                             f"disagree ({type(exc).__name__}: {_short_text(str(exc))})",
                             file=source, column=field) from None
        if dev.shape != (2, 3) or half.shape != (2, 3) or not (np.isfinite(dev).all()
                                                                and np.isfinite(half).all()):
            raise InputError(f"{label} predicts non-finite or misshapen numbers", file=source,
                             column=field)
    if hasattr(model, "_predictors"):
        model._predictors = {}   # the runtime starts from fresh predictors, not the check's


def _short_text(text, limit: int = 80) -> str:
    text = " ".join(str(text).split())
    return text if len(text) <= limit else text[: limit - 3] + "..."


class _IdentityMap:
    """Feature map for callers that pass base features directly (arrays API)."""

    def __init__(self, base_names):
        self.base_names = base_names
        self.sensor_names = [c[3:] for c in base_names if c.startswith("dL_")]
        self.probe_names = []

    def base(self, base, *_):
        return np.atleast_2d(np.asarray(base, dtype=float))


def _as_campaign_list(X) -> list:
    from fbgcomp.io.campaign import Campaign, read_campaign

    items = X if isinstance(X, (list, tuple)) else [X]
    return [c if isinstance(c, Campaign) else read_campaign(c) for c in items]


def check_compatible(model, campaign) -> None:
    """Raise InputError when a campaign lacks what the model needs (sensors, probes)."""
    where = (campaign.path / "campaign.yaml") if campaign.path is not None else campaign.meta.name
    have = {s.name: s for s in campaign.meta.sensors}
    for s in model.sensors_:
        if s.name not in have:
            raise InputError(f"model expects sensor {s.name} but the campaign has "
                             f"{', '.join(have) or 'none'}", file=where, column="field sensors")
        c = have[s.name]
        if abs(c.gauge_length_mm - s.gauge_length_mm) > 1e-6 * max(1.0, s.gauge_length_mm):
            raise InputError(f"sensor {s.name} has gauge_length_mm {c.gauge_length_mm} but the model "
                             f"was fitted with {s.gauge_length_mm}", file=where, column="field sensors")
        if abs(c.lambda0_nm - s.lambda0_nm) > 5.0:
            raise InputError(f"sensor {s.name} has lambda0_nm {c.lambda0_nm} but the model expects "
                             f"{s.lambda0_nm} ± 5 nm", file=where, column="field sensors")
    probes = set(campaign.meta.probe_names) | set(getattr(campaign, "undeclared_probes", ()))
    for p in model.probe_names_:
        if p not in probes and p not in campaign.temperatures.columns.str.removesuffix("_C"):
            raise InputError(f"model needs temperature probe {p} which the campaign does not have",
                             file=where, column="field temperature_probes")


def model_id(d: dict) -> str:
    """Short stable hash of a model's content (ignores its id and creation time)."""
    content = {k: v for k, v in d.items() if k not in ("model_id", "created_utc")}
    blob = json.dumps(content, sort_keys=True, separators=(",", ":")).encode()
    return hashlib.sha256(blob).hexdigest()[:12]


_MODEL_TYPES = {"mra": MRAModel}


def register_model_type(name: str, cls) -> None:
    """Make :func:`load_model` know another model type (kinematic, hybrid, dynamic …)."""
    _MODEL_TYPES[name] = cls


class _NonFinite:
    """A NaN, infinity or overflowing literal met while parsing (reported with its field)."""

    __slots__ = ("text",)

    def __init__(self, text):
        self.text = text


def _parse_float(text):
    value = float(text)
    return value if math.isfinite(value) else _NonFinite(text)


def _read_model_json(path: Path):
    if not path.exists():
        raise InputError("model file not found", file=path)
    if not path.is_file():
        raise InputError("not a regular file", file=path)
    raw = read_bounded(path, MAX_MODEL_BYTES, what="a model file", unreadable="cannot read model file")
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise InputError(f"not UTF-8 text: byte 0x{raw[exc.start]:02x} at offset {exc.start}",
                         file=path) from None
    try:
        return json.loads(text, parse_float=_parse_float, parse_constant=_NonFinite)
    except json.JSONDecodeError as exc:
        raise InputError(f"not a JSON model file: {exc.msg} at line {exc.lineno}, column {exc.colno}",
                         file=path) from None
    except RecursionError:
        raise InputError(f"JSON nested deeper than {MAX_MODEL_DEPTH} levels: not a model file",
                         file=path) from None
    except ValueError as exc:  # e.g. an integer literal of thousands of digits
        raise InputError(f"not a JSON model file: {_short_text(exc)}", file=path) from None


def _field_text(parts) -> str:
    out = ""
    for part in parts:
        if isinstance(part, int):
            out += f"[{part}]"
        else:
            name = part if part.isprintable() and len(part) <= 40 else "<key>"
            out += f".{name}" if out else name
    return out or "<top level>"


def check_model_numbers(d, source="<dict>") -> None:
    """The checks :func:`load_model` applies to every model type before building it: nesting at
    most :data:`MAX_MODEL_DEPTH`, no NaN or infinity anywhere, and outside :data:`STATISTICS` no
    null inside an array and no number beyond :data:`MAX_MODEL_VALUE`. InputError names the
    first offending field (in file order)."""
    stack = [(d, (), False)]
    while stack:
        node, parts, statistic = stack.pop()
        if len(parts) > MAX_MODEL_DEPTH:
            raise InputError(f"nested deeper than {MAX_MODEL_DEPTH} levels: not a model file",
                             file=source, column=f"field {_field_text(parts[:8])}...")
        if isinstance(node, dict):
            stack.extend((v, parts + (k,), statistic or k in STATISTICS)
                         for k, v in reversed(list(node.items())))
        elif isinstance(node, list):
            if not statistic and any(v is None for v in node):
                i = next(i for i, v in enumerate(node) if v is None)
                raise InputError("null where a number is expected (a NaN written out?)",
                                 file=source, column=f"field {_field_text(parts + (i,))}")
            stack.extend((v, parts + (i,), statistic) for i, v in reversed(list(enumerate(node))))
        elif isinstance(node, _NonFinite):
            raise InputError(f"non-finite number {_short_text(node.text, 24)}; a model holds finite "
                             "numbers only", file=source, column=f"field {_field_text(parts)}")
        elif (isinstance(node, (int, float)) and not isinstance(node, bool) and not statistic
              and abs(node) > MAX_MODEL_VALUE):
            shown = f"{node:.3g}" if isinstance(node, float) or abs(node) < 10 ** 300 else "an integer of over 300 digits"
            raise InputError(f"{shown} is beyond the {MAX_MODEL_VALUE:g} a model may hold "
                             "(a corrupted or hostile file?)", file=source,
                             column=f"field {_field_text(parts)}")


def load_model(path):
    """Read a model file, migrating older schema versions; InputError on anything wrong.

    The one loader of the CLI, ``serve`` and the OPC UA reload. Refuses, with one line naming
    the file and field: files over :data:`MAX_MODEL_BYTES`, JSON nested deeper than
    :data:`MAX_MODEL_DEPTH`, non-finite or absurd numbers (:func:`check_model_numbers`), arrays
    whose shapes disagree, and models whose predictors cannot predict finite numbers.
    """
    path = Path(path)
    d = _read_model_json(path)
    if not isinstance(d, dict) or d.get("format") != MODEL_FORMAT:
        raise InputError(f"not an fbgcomp model file (field 'format' must be {MODEL_FORMAT!r})",
                         file=path, column="field format")
    check_model_numbers(d, path)
    version = d.get("schema_version")
    if not isinstance(version, int) or isinstance(version, bool) or version < 1:
        raise InputError("schema_version must be an integer >= 1", file=path,
                         column="field schema_version")
    if version > SCHEMA_VERSION:
        raise InputError(f"model schema version {version} is newer than this fbgcomp supports "
                         f"({SCHEMA_VERSION}); upgrade fbgcomp", file=path, column="field schema_version")
    while version < SCHEMA_VERSION:
        d = MIGRATIONS[version](d)
        version = d["schema_version"]
    kind = d.get("model_type")
    if not isinstance(kind, str):
        raise InputError("model_type must be a name", file=path, column="field model_type")
    if kind not in _MODEL_TYPES:
        from fbgcomp.models import model_types
        from fbgcomp.models import physical  # noqa: F401  (register kinematic, hybrid, dynamic, physical)
    if kind not in _MODEL_TYPES:
        raise InputError(f"unknown model_type {_short_text(repr(kind), 40)}; known: "
                         f"{', '.join(_MODEL_TYPES)}", file=path, column="field model_type")
    try:
        return _MODEL_TYPES[kind].from_dict(d, source=path)
    except InputError:
        raise
    except KeyError as exc:
        raise InputError(f"missing field {_short_text(repr(exc.args[0]), 40)}", file=path) from None
    except Exception as exc:  # noqa: BLE001 - whatever a malformed file makes fail is its fault
        raise InputError(f"malformed model file: {type(exc).__name__}: {_short_text(exc)}",
                         file=path) from None
