"""The paper's multiple regression analysis (sec. 3, eq. 11-13, Table 1): :class:`MRAModel`.

Over 600 lines as one unit: the estimator's three fit paths (campaigns, arrays, an accumulated
factor), its stepwise selection, fallbacks and model file act on the same learned state.

One linear model per TTP axis (dx, dy, dz) on the regressors of :mod:`fbgcomp.models.features`,
optionally with stepwise selection (ANOVA partial F-tests, or HAC Wald tests). It follows the
scikit-learn contract (hyper-parameters in ``__init__``, learned state with a trailing
underscore, ``fit`` returns ``self``) and fits from campaigns streamed in chunks through one QR
factor, from which the stepwise search and the fallback models (fitted without one or two
sensors, used by the runtime when a fibre fails) are all derived without re-reading the data.
Its :meth:`MRAModel.fit_campaigns` is the one fitting loop of every regression type (the dynamic
model and the hybrid's residual regression extend it).

The model file (``model_type`` "mra") holds the feature definitions, the coefficients with
standard errors and covariance per axis (:class:`AxisFit`), the zero-state convention, the
sensors it expects, the training campaigns and fit statistics.
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass, field

import numpy as np

from fbgcomp import __version__
from fbgcomp.errors import InputError
from fbgcomp.models.base import (
    CAMPAIGN_WEIGHTS,
    CHUNK_ROWS,
    EstimatorParams,
    ModelFile,
    Predictor,
    as_campaign_list,
    campaign_weights_for,
    check_compatible,
    check_fallback_policy,
    check_finite_fit_data,
    check_predictors,
    deviation_range,
    fallback_sets,
    plain,
    sensor_specs_from_file,
)
from fbgcomp.models.features import (
    CONSTANT,
    FEATURE_SETS,
    FeatureMap,
    TemperatureRoles,
    candidate_terms,
    design_matrix,
    resolve_roles,
)
from fbgcomp.models.modelfile import MODEL_FORMAT, SCHEMA_VERSION, short_text
from fbgcomp.models.regression import QRAccumulator, accumulate_series, ols_from_factor, stepwise
from fbgcomp.units import AXES


@dataclass
class AxisFit:
    """The fitted linear model of one TTP axis, as stored in the model file."""

    terms: list  # term names, "const" first
    params: np.ndarray  # µm per unit of each term
    bse: np.ndarray
    tvalues: np.ndarray
    pvalues: np.ndarray
    cov: np.ndarray  # covariance of params
    resid_sd: float  # µm
    df_resid: float
    nobs: int
    rsquared: float
    rsquared_adj: float
    fvalue: float
    f_pvalue: float
    history: list = field(default_factory=list)  # stepwise steps
    cov_type: str = "nonrobust"  # "HAC": Newey-West bse, cov, tests
    hac: dict = field(default_factory=dict)  # HAC bandwidth, lag-1 rho, n_eff

    @classmethod
    def from_result(cls, result, history=()):
        """The axis of a regression result (:mod:`fbgcomp.models.regression`), with its stepwise
        ``history`` (a list of step records)."""
        return cls(
            terms=list(result.feature_names),
            params=np.asarray(result.params, float),
            bse=np.asarray(result.bse, float),
            tvalues=np.asarray(result.tvalues, float),
            pvalues=np.asarray(result.pvalues, float),
            cov=np.asarray(result.cov_params(), float),
            resid_sd=float(result.resid_sd),
            df_resid=float(result.df_resid),
            nobs=int(result.nobs),
            rsquared=float(result.rsquared),
            rsquared_adj=float(result.rsquared_adj),
            fvalue=float(result.fvalue),
            f_pvalue=float(result.f_pvalue),
            history=[plain(h) for h in history],
            cov_type=getattr(result, "cov_type", "nonrobust"),
            hac=plain(dict(getattr(result, "cov_kwds", {}) or {})),
        )

    def to_dict(self) -> dict:
        """The axis as the model file stores it."""
        return {
            "terms": self.terms,
            "params": self.params.tolist(),
            "bse": self.bse.tolist(),
            "tvalues": self.tvalues.tolist(),
            "pvalues": self.pvalues.tolist(),
            "cov_params": self.cov.tolist(),
            "resid_sd_um": self.resid_sd,
            "df_resid": self.df_resid,
            "nobs": self.nobs,
            "rsquared": self.rsquared,
            "rsquared_adj": self.rsquared_adj,
            "fvalue": self.fvalue,
            "f_pvalue": self.f_pvalue,
            "stepwise_history": self.history,
            "cov_type": self.cov_type,
            "hac": self.hac,
        }

    @classmethod
    def from_dict(cls, d: dict, where: str = "axes", source="<dict>") -> AxisFit:
        """An axis of a model file; InputError naming ``where`` (its field path) when its
        arrays disagree with its terms or its residual statistics cannot predict."""
        terms = d["terms"]
        if not isinstance(terms, list) or not all(isinstance(t, str) for t in terms) or not terms:
            raise InputError(
                "terms must be a non-empty list of names", file=source, column=f"field {where}.terms"
            )
        k = len(terms)

        def arr(key, shape):
            try:
                value = np.asarray(d[key], dtype=float)
            except (TypeError, ValueError):
                raise InputError(
                    "expected an array of numbers", file=source, column=f"field {where}.{key}"
                ) from None
            if value.shape != shape:
                raise InputError(
                    f"shape {value.shape} disagrees with the {k} terms (expected {shape})",
                    file=source,
                    column=f"field {where}.{key}",
                )
            return value

        cov = arr("cov_params", (k, k))
        resid_sd, df_resid = float(d["resid_sd_um"]), float(d["df_resid"])
        if not (math.isfinite(resid_sd) and resid_sd >= 0):
            raise InputError(
                f"residual SD must be a finite number >= 0, not {resid_sd!r}",
                file=source,
                column=f"field {where}.resid_sd_um",
            )
        if not (math.isfinite(df_resid) and df_resid > 0):
            raise InputError(
                f"residual degrees of freedom must be > 0, not {df_resid!r}",
                file=source,
                column=f"field {where}.df_resid",
            )
        return cls(
            terms=list(terms),
            params=arr("params", (k,)),
            bse=arr("bse", (k,)),
            tvalues=arr("tvalues", (k,)),
            pvalues=arr("pvalues", (k,)),
            cov=cov,
            resid_sd=resid_sd,
            df_resid=df_resid,
            nobs=int(d["nobs"]),
            rsquared=float(d["rsquared"]),
            rsquared_adj=float(d["rsquared_adj"]),
            fvalue=float_or_nan(d["fvalue"]),
            f_pvalue=float_or_nan(d["f_pvalue"]),
            history=list(d.get("stepwise_history", [])),
            cov_type=d.get("cov_type", "nonrobust"),
            hac=dict(d.get("hac") or {}),
        )

    def table(self) -> str:
        """Paper Table 1 style coefficient table."""
        # one space at least between columns, whatever the width a number takes
        lines = [f"{'term':<22} {'estimate':>12} {'std err':>11} {'t':>8} {'P>|t|':>9}"]
        for name, p, se, t, pv in zip(self.terms, self.params, self.bse, self.tvalues, self.pvalues):
            lines.append(f"{name:<22} {p:>12.5g} {se:>11.4g} {t:>8.2f} {pv:>9.3g}")
        lines.append(
            f"n = {self.nobs}, R² = {self.rsquared:.5f}, adj. R² = {self.rsquared_adj:.5f}, "
            f"residual SD = {self.resid_sd:.4g} µm, "
            f"{'Wald F (HAC)' if self.cov_type == 'HAC' else 'F'} = {self.fvalue:.4g} "
            f"(p = {self.f_pvalue:.3g})"
        )
        if self.cov_type == "HAC":
            h = self.hac
            lines.append(
                f"std errors: HAC (Newey-West, Bartlett, {h.get('maxlags')} lags); "
                f"residual lag-1 autocorrelation {h.get('rho1', float('nan')):.4f}, "
                f"effective sample size {h.get('n_eff', float('nan')):.4g} of {self.nobs}"
            )
        else:
            lines.append("std errors: nonrobust (i.i.d. errors assumed)")
        return "\n".join(lines)


def float_or_nan(value) -> float:
    """JSON has no NaN: an undefined statistic (F of a constant-only model) is stored as null."""
    return float("nan") if value is None else float(value)


class IdentityMap:
    """Feature map for callers that pass base features directly (arrays API)."""

    def __init__(self, base_names):
        self.base_names = base_names
        self.sensor_names = [c[3:] for c in base_names if c.startswith("dL_")]
        self.probe_names = []

    def base(self, base, *_):
        """The base features as given, (n, k)."""
        return np.atleast_2d(np.asarray(base, dtype=float))


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

    def __init__(
        self,
        features="eq13",
        stepwise=False,
        direction="both",
        p_enter=0.05,
        p_remove=0.10,
        max_terms=None,
        roles=None,
        zero_window_s=10.0,
        fallbacks="loo",
        campaign_weights="balanced",
        cov_type="HAC",
        hac_maxlags="auto",
    ):
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
        """The eq. 13 roles: those resolved at fit time (``roles_``), else :meth:`_given_roles`."""
        return getattr(self, "roles_", None) or self._given_roles()

    def _given_roles(self) -> TemperatureRoles:
        """The ``roles`` hyper-parameter as :class:`TemperatureRoles` (None: the paper's names)."""
        if self.roles is None:
            return TemperatureRoles()
        if isinstance(self.roles, TemperatureRoles):
            return self.roles
        return TemperatureRoles(**self.roles)

    def _resolve_roles(self, probe_names, machine=None) -> TemperatureRoles:
        """``roles`` when given; else the probes of ``probe_names`` that play eq. 13's roles
        (:func:`~fbgcomp.models.features.resolve_roles`, by the machine description's probe
        positions when one is given): a ram whose probes do not carry the paper's names gets
        its eq. 13 features too."""
        if self.roles is not None or probe_names is None or self.features == "eq11":
            return self._given_roles()
        try:
            return resolve_roles(probe_names, machine)
        except ValueError as exc:
            raise InputError(str(exc), column="field temperature_probes") from None

    def _check_params(self):
        if self.features not in FEATURE_SETS:
            raise ValueError(f"features must be one of {', '.join(FEATURE_SETS)}, not {self.features!r}")
        if self.direction not in ("both", "forward", "backward"):
            raise ValueError(f"direction must be both, forward or backward, not {self.direction!r}")
        check_fallback_policy(self.fallbacks)
        if getattr(self, "campaign_weights", "samples") not in CAMPAIGN_WEIGHTS:
            raise ValueError(
                f"campaign_weights must be one of {', '.join(CAMPAIGN_WEIGHTS)}, "
                f"not {self.campaign_weights!r}"
            )
        if getattr(self, "cov_type", "nonrobust") not in ("HAC", "nonrobust"):
            raise ValueError(f"cov_type must be HAC or nonrobust, not {self.cov_type!r}")
        lags = getattr(self, "hac_maxlags", "auto")
        if lags != "auto" and not (
            isinstance(lags, (int, np.integer)) and not isinstance(lags, bool) and lags >= 1
        ):
            raise ValueError(f"hac_maxlags must be 'auto' or a positive int, not {lags!r}")

    def _hac_lags(self):
        """Bandwidths the accumulator must keep (None for naive inference)."""
        if getattr(self, "cov_type", "nonrobust") != "HAC":
            return None
        lags = getattr(self, "hac_maxlags", "auto")
        return "auto" if lags == "auto" else [int(lags)]

    def _new_qr(self, names):
        return QRAccumulator(
            len(names), len(AXES), feature_names=names, target_names=list(AXES), hac_lags=self._hac_lags()
        )

    def fit(self, X, y=None, *, progress=None):
        """Fit on campaigns (``X`` a campaign, a path or a list of them, ``y`` None) or on arrays.

        With arrays, ``X`` is a pandas DataFrame of base features (columns ``dL_<sensor>`` and,
        for eq12/eq13, ``dT_bulk``, ``dT_surf``, ``dT_flange``) and ``y`` an (n, 3) array of
        TTP deviations in µm (dx, dy, dz).
        """
        self._check_params()
        if y is not None:
            return self._fit_arrays(X, y)
        return self.fit_campaigns(X, progress=progress)

    #: Whether the fit records the campaigns' median frame interval (``training.dt_s``), which a
    #: predictor with memory needs when it is given no sample times.
    records_frame_interval = False

    def fit_campaigns(self, X, *, progress=None, targets=None):
        """The one fitting loop of the regression types: stream campaigns into the QR factor.

        Campaigns are pooled with :func:`~fbgcomp.models.base.campaign_weights_for` (row counts
        first: a balanced pool's weights depend on every campaign's length), each design built
        by :meth:`campaign_design` and added in chunks of :data:`~fbgcomp.models.base.CHUNK_ROWS`
        rows, in two passes (the factor, then autocorrelation statistics about the full model's
        coefficients; no lag spans two campaigns); then :meth:`fit_factor`. ``targets``
        (optional) maps a campaign's index to the (n, 3) µm to fit instead of its reference
        deviation (the hybrid fits the kinematic chain's residual).
        """
        campaigns = as_campaign_list(X)
        if not campaigns:
            raise ValueError("fit needs at least one campaign")
        acc = self.new_accumulator(list(campaigns[0].meta.sensors), None, roles_from=campaigns[0].probe_names)
        names = list(acc.feature_names)
        for c in campaigns:
            check_compatible(self, c)
        aligned_all = [c.aligned(zero_window_s=self.zero_window_s) for c in campaigns]
        weights = campaign_weights_for(
            [len(a.time_s) for a in aligned_all], getattr(self, "campaign_weights", "samples")
        )
        series, training, dts = [], [], []
        for i, (c, aligned, weight) in enumerate(zip(campaigns, aligned_all, weights)):
            design = self.campaign_design(c, aligned)
            check_finite_fit_data(c, aligned, design, names)
            y = aligned.reference_um if targets is None or i not in targets else targets[i]
            series.append((design, y, weight))
            if len(aligned.time_s) > 1:
                dts.append(float(np.median(np.diff(aligned.time_s))))
            training.append(
                {
                    "name": c.meta.name,
                    "kind": c.meta.kind,
                    "path": None if c.path is None else str(c.path),
                    "n_samples": len(design),
                    "row_weight": float(weight),
                    "dropped": plain(aligned.dropped),
                    **deviation_range(aligned.reference_um),
                }
            )
            if progress is not None:
                progress(c.meta.name)
        accumulate_series(acc, series, chunk_rows=CHUNK_ROWS)
        info = {"campaigns": training, "n_samples": int(sum(t["n_samples"] for t in training))}
        if dts and self.records_frame_interval:
            info["dt_s"] = float(np.median(dts))
        return self.fit_factor(acc, info)

    # -- fitting from statistics reduced elsewhere (fbgcomp.io.dataset, fbgcomp.models.distributed) ------
    def new_accumulator(self, sensors, probe_names=None, *, roles_from=None, machine=None):
        """Fix the sensor set (``SensorSpec`` list) and return an empty QR accumulator whose
        columns are this model's terms (``const`` first) and whose targets are dx, dy, dz.

        ``probe_names`` lists the probes the data offers; a missing required probe is an
        InputError. The eq. 13 roles (``roles_``) are resolved among ``roles_from`` (default:
        ``probe_names``), by the ``machine`` description's probe positions when given.
        Partitions accumulated on other processes with an estimator configured the same way
        merge into it (:meth:`fbgcomp.models.regression.QRAccumulator.merge`).
        """
        self._check_params()
        self.roles_ = self._resolve_roles(probe_names if roles_from is None else roles_from, machine)
        self.sensors_ = list(sensors)
        self.probe_names_ = FeatureMap.required_probes(self.sensors_, self.features != "eq11", self._roles())
        if probe_names is not None:
            missing = [p for p in self.probe_names_ if p not in set(probe_names)]
            if missing:
                raise InputError(
                    f"the data lacks temperature probe(s) {', '.join(missing)} "
                    f"needed by features {self.features}",
                    column="field temperature_probes",
                )
        self.candidates_ = candidate_terms(self.features, [s.name for s in self.sensors_])
        names = [CONSTANT, *self.candidates_]
        return self._new_qr(names)

    def design_from_arrays(self, wavelength_nm, temperature_C, wavelength_zero_nm, temperature_zero_C):
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
        if list(acc.feature_names) != [CONSTANT, *self.candidates_]:
            raise ValueError("the accumulator's columns are not this model's terms")
        self.training_ = (
            dict(training) if training is not None else {"campaigns": [], "n_samples": int(acc.n_obs)}
        )
        return self._fit_factor(acc)

    def _fit_arrays(self, X, y):
        base_names = list(X.columns)
        sensor_names = [c[3:] for c in base_names if c.startswith("dL_")]
        self.sensors_ = None
        self.probe_names_ = []
        self.candidates_ = candidate_terms(self.features, sensor_names)
        names = [CONSTANT, *self.candidates_]
        design = design_matrix(X.to_numpy(dtype=float), base_names, self.candidates_)
        acc = self._new_qr(names)
        y = np.asarray(y, dtype=float).reshape(len(design), len(AXES))
        accumulate_series(acc, [(design, y, None)], chunk_rows=CHUNK_ROWS)
        self.training_ = {"campaigns": [], "n_samples": len(design)}
        return self._fit_factor(acc)

    def _fit_factor(self, acc):
        self.axes_ = self._select(acc, exclude=frozenset())
        self.fallbacks_ = {}
        sensor_names = [t[3:] for t in self.candidates_ if t.startswith("dL_")]
        for drop in fallback_sets(sensor_names, self.fallbacks):
            self.fallbacks_[drop] = self._select(acc, exclude=drop)
        self.coef_ = {a: dict(zip(f.terms, f.params)) for a, f in self.axes_.items()}
        self._predictors = {}
        return self

    def _select(self, acc, exclude) -> dict:
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
                sw = stepwise(
                    acc,
                    candidates,
                    target=j,
                    direction=self.direction,
                    p_enter=self.p_enter,
                    p_remove=self.p_remove,
                    max_terms=self.max_terms,
                    include=[CONSTANT],
                    cov_type=cov_type,
                    maxlags=maxlags,
                )
                history = (
                    sw.history.to_dict("records") if hasattr(sw.history, "to_dict") else list(sw.history)
                )
                axes[a] = AxisFit.from_result(sw.result, history)
            else:
                axes[a] = AxisFit.from_result(
                    ols_from_factor(
                        acc, [CONSTANT, *candidates], target=j, cov_type=cov_type, maxlags=maxlags
                    )
                )
        return axes

    def campaign_design(self, campaign, aligned):
        """Design matrix (n, 1 + terms) of an aligned campaign (after :meth:`new_accumulator`)."""
        fmap = self._feature_map()
        probe_cols = [list(aligned.probe_names).index(p) for p in self.probe_names_]
        base = fmap.base(
            aligned.wavelength_nm[:, [list(aligned.sensor_names).index(s) for s in fmap.sensor_names]],
            aligned.temperature_C[:, probe_cols],
            aligned.wavelength_zero_nm[[list(aligned.sensor_names).index(s) for s in fmap.sensor_names]],
            aligned.temperature_zero_C[probe_cols],
        )
        return design_matrix(base, fmap.base_names, self.candidates_)

    # -- prediction ----------------------------------------------------------------------
    def _feature_map(self) -> FeatureMap:
        return FeatureMap(self.sensors_, self.probe_names_, self.features != "eq11", self._roles())

    @property
    def fallback_sets(self) -> list:
        """The excluded-sensor sets of the stored fallback models."""
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
            pred = Predictor(
                IdentityMap(list(X.columns)),
                self.axes_ if not exclude else self.fallbacks_[frozenset(exclude)],
            )
            return pred.predict(X.to_numpy(dtype=float), None, None, None)
        (campaign,) = as_campaign_list(X)
        check_compatible(self, campaign)
        aligned = campaign.aligned(zero_window_s=self.zero_window_s)
        p = self.predictor(exclude)
        w, t, w0, t0 = self.instrument_arrays(aligned)
        return p.predict(w, t, w0, t0)

    # -- reporting and persistence ------------------------------------------------------
    def summary(self) -> str:
        """Table 1 style coefficient table per axis, with the stepwise history."""
        out = [
            f"MRA model ({self.features}{', stepwise' if self.stepwise else ''}, "
            f"{self.axes_['dx'].cov_type} inference), "
            f"{self.training_['n_samples']} samples from "
            f"{', '.join(c['name'] for c in self.training_['campaigns']) or 'arrays'}"
        ]
        for a in AXES:
            fit = self.axes_[a]
            out.append(f"\n== {a} (µm) ==")
            out.append(fit.table())
            if fit.history:
                out.append("stepwise history:")
                out.append(f"  {'step':>4} {'action':<7}{'term':<22}{'F':>10}{'p':>10}{'terms':>6}")
                for h in fit.history:
                    out.append(
                        f"  {h.get('step', ''):>4} {h.get('action', ''):<7}{h.get('term', '')!s:<22}"
                        f"{h.get('F', float('nan')):>10.4g}{h.get('p', float('nan')):>10.3g}"
                        f"{h.get('n_terms', ''):>6}"
                    )
        return "\n".join(out)

    def to_dict(self) -> dict:
        """The model file's content (without ``model_id`` and ``created_utc``, added by ``save``)."""
        d = {
            "format": MODEL_FORMAT,
            "schema_version": SCHEMA_VERSION,
            "model_type": self.model_type,
            "fbgcomp_version": __version__,
            "features": {
                "set": self.features,
                "candidates": list(self.candidates_),
                "roles": self._roles().as_dict(),
                "stepwise": (
                    {
                        "direction": self.direction,
                        "p_enter": self.p_enter,
                        "p_remove": self.p_remove,
                        "max_terms": self.max_terms,
                    }
                    if self.stepwise
                    else None
                ),
            },
            "zero_state": {"method": "mean_of_first_window", "window_s": self.zero_window_s},
            "sensors": [s.model_dump(mode="json") for s in self.sensors_] if self.sensors_ else [],
            "probes": list(self.probe_names_),
            "axes": {a: f.to_dict() for a, f in self.axes_.items()},
            "fallbacks": [
                {"exclude": sorted(k), "axes": {a: f.to_dict() for a, f in v.items()}}
                for k, v in self.fallbacks_.items()
            ],
            "fallback_policy": self.fallbacks,
            "campaign_weights": getattr(self, "campaign_weights", "samples"),
            "training": copy.deepcopy(self.training_),
            "inference": {
                "cov_type": getattr(self, "cov_type", "nonrobust"),
                "hac_maxlags": getattr(self, "hac_maxlags", "auto"),
            },
            "uncertainty": {
                "level": 0.95,
                "method": (
                    "regression: HAC (Newey-West) covariance + residual variance"
                    if self.axes_["dx"].cov_type == "HAC"
                    else "regression: covariance + residual variance"
                ),
            },
            "z_axis_mm": None,
        }
        return d

    @classmethod
    def from_dict(cls, d: dict, source="<dict>", check=True) -> MRAModel:
        """The model of a model file's dict; ``check=False`` skips :func:`check_predictors`
        (for a subclass that builds on this one and checks its own predictors)."""
        f = d["features"]
        sw = f.get("stepwise")
        m = cls(
            features=f["set"],
            stepwise=sw is not None,
            **({k: sw[k] for k in ("direction", "p_enter", "p_remove", "max_terms")} if sw else {}),
            roles=f.get("roles"),
            zero_window_s=d["zero_state"]["window_s"],
            fallbacks=d.get("fallback_policy", "none"),
            campaign_weights=d.get("campaign_weights", "samples"),
            # files written before issue 12 were fitted with naive inference
            cov_type=d.get("inference", {}).get("cov_type", "nonrobust"),
            hac_maxlags=d.get("inference", {}).get("hac_maxlags", "auto"),
        )
        m._check_params()
        m.candidates_ = list(f["candidates"])
        m.sensors_ = sensor_specs_from_file(d["sensors"], source)
        m.probe_names_ = list(d["probes"])
        m.axes_ = {a: AxisFit.from_dict(d["axes"][a], f"axes.{a}", source) for a in AXES}
        m.fallbacks_ = {}
        for i, fb in enumerate(d.get("fallbacks", [])):
            exclude = frozenset(fb["exclude"])
            if not exclude <= set(m.sensor_names):
                raise InputError(
                    "a fallback excludes sensors the model does not have",
                    file=source,
                    column=f"field fallbacks[{i}].exclude",
                )
            m.fallbacks_[exclude] = {
                a: AxisFit.from_dict(fb["axes"][a], f"fallbacks[{i}].axes.{a}", source) for a in AXES
            }
        known = {CONSTANT, *m.candidates_}
        for where, axes in [("axes", m.axes_)] + [
            (f"fallbacks[{i}].axes", v) for i, v in enumerate(m.fallbacks_.values())
        ]:
            for a, fit in axes.items():
                unknown = [t for t in fit.terms if t not in known]
                if unknown:
                    raise InputError(
                        f"term {short_text(unknown[0])} is not among the model's candidates",
                        file=source,
                        column=f"field {where}.{a}.terms",
                    )
        m.training_ = d.get("training", {"campaigns": [], "n_samples": 0})
        m.coef_ = {a: dict(zip(fit.terms, fit.params)) for a, fit in m.axes_.items()}
        m._predictors = {}
        if check:
            check_predictors(m, source)
        return m
