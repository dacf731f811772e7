"""The dynamic model type: the regression with first-order filtered temperatures (``model_type`` "dynamic").

:class:`DynamicModel` is :class:`~fbgcomp.models.mra.MRAModel` on eq. 13 plus first-order
low-pass filtered temperature features (thermal lag, :mod:`fbgcomp.models.filters`). Its
predictor carries the filter state between calls (``reset()`` starts over); offline validation
runs exactly that streaming code from the first sample of a campaign. The hybrid's residual
regression is a DynamicModel (with no filter for ``features="eq13"``).
"""

from __future__ import annotations

import numpy as np

from fbgcomp.models.base import ModelFile, Predictor, check_predictors
from fbgcomp.models.features import CONSTANT, TEMPERATURE_FEATURES, FeatureMap, candidate_terms, design_matrix
from fbgcomp.models.filters import first_order_filter, lowpass_name
from fbgcomp.models.mra import MRAModel
from fbgcomp.models.regression import QRAccumulator
from fbgcomp.units import AXES

#: Time constants (s) of the dynamic model's first-order filters.
DEFAULT_TAUS_S = (3600.0,)


class FilteredFeatureMap(FeatureMap):
    """eq. 13 base features plus low-pass filtered temperature features (stateless here; the
    state lives in :class:`DynamicPredictor`)."""

    def __init__(self, sensors, probe_names, roles, taus_s):
        super().__init__(sensors, probe_names, True, roles)
        self.taus_s = tuple(float(t) for t in taus_s)
        self.static_names = list(self.base_names)
        self.base_names = self.static_names + [
            lowpass_name(t, b) for t in self.taus_s for b in TEMPERATURE_FEATURES
        ]

    def base_filtered(
        self,
        wavelength_nm,
        temperature_C,
        wavelength_zero_nm,
        temperature_zero_C,
        time_s=None,
        state=None,
        nominal_dt_s=1.0,
    ):
        """Base features (n, k) with the filtered temperature features appended, and the filters'
        new state (``{tau: state}``), from raw instrument arrays; ``state`` from the last call."""
        static = FeatureMap.base(self, wavelength_nm, temperature_C, wavelength_zero_nm, temperature_zero_C)
        temps = static[:, -len(TEMPERATURE_FEATURES) :]
        state = state or {}
        cols, new_state = [static], {}
        for tau in self.taus_s:
            y, new_state[tau] = first_order_filter(temps, time_s, tau, state.get(tau), nominal_dt_s)
            cols.append(y)
        return np.hstack(cols), new_state


class DynamicPredictor(Predictor):
    """Regression predictor with filter state carried between calls (streaming form).

    ``predict`` on consecutive batches of one stream equals ``predict`` on the concatenation;
    ``reset()`` forgets the state (a new zero state, a new campaign). Without ``time_s`` the
    samples are taken as evenly spaced at the training data's median interval.
    """

    def __init__(self, feature_map, axes, exclude, nominal_dt_s):
        super().__init__(feature_map, axes, exclude)
        self.nominal_dt_s = float(nominal_dt_s)
        self.state = None

    def reset(self):
        """Forget the filter state (the next call starts from its first sample)."""
        self.state = None

    def design(self, wavelength_nm, temperature_C, wavelength_zero_nm, temperature_zero_C, time_s=None):
        """Design matrix (n, 1 + terms), advancing the filter state (``last_base`` keeps the
        base features of the call)."""
        base, self.state = self.feature_map.base_filtered(
            wavelength_nm,
            temperature_C,
            wavelength_zero_nm,
            temperature_zero_C,
            time_s,
            self.state,
            self.nominal_dt_s,
        )
        self.last_base = base
        return self._design_from_base(base)

    def predict(
        self,
        wavelength_nm,
        temperature_C,
        wavelength_zero_nm,
        temperature_zero_C,
        *,
        z_axis_mm=None,
        time_s=None,
    ):
        """TTP deviation (n, 3) µm and 95 % half-width (n, 3) µm, continuing the stream (see
        :meth:`fbgcomp.models.base.Predictor.predict`; ``z_axis_mm`` is not used)."""
        wavelength_nm = np.atleast_2d(np.asarray(wavelength_nm, dtype=float))
        if self.exclude:
            cols = [i for i, s in enumerate(self.sensor_names) if s in self.exclude]
            wavelength_nm = wavelength_nm.copy()
            wavelength_nm[:, cols] = np.asarray(wavelength_zero_nm, dtype=float)[cols]
        d = self.design(wavelength_nm, temperature_C, wavelength_zero_nm, temperature_zero_C, time_s)
        deviation = d @ self.coef
        return deviation, self._t[None, :] * np.sqrt(self._interval_var(d))


class DynamicModel(MRAModel):
    """Regression with first-order filtered temperature features (thermal lag).

    Parameters as :class:`~fbgcomp.models.mra.MRAModel` (features fixed to eq13 + filters) plus
    ``taus_s``: the filters' time constants in s, and ``elongation_axes``: the axes regressed on
    the elongations too (None: every axis; the others on temperature terms only).
    """

    model_type = "dynamic"
    # Fixed for this type, not hyper-parameters: the features are eq13's plus the filters; its
    # accumulator keeps no autocorrelation statistics, so the fit's inference is naive (each
    # AxisFit says so) while the file records MRAModel's default inference, as it always has.
    features = "eq13"
    cov_type = "HAC"
    hac_maxlags = "auto"
    records_frame_interval = True

    def __init__(
        self,
        taus_s=DEFAULT_TAUS_S,
        stepwise=True,
        direction="both",
        p_enter=0.05,
        p_remove=0.10,
        max_terms=None,
        roles=None,
        zero_window_s=10.0,
        fallbacks="loo",
        elongation_axes=None,
        campaign_weights="balanced",
    ):
        self.taus_s = taus_s
        self.stepwise = stepwise
        self.direction = direction
        self.p_enter = p_enter
        self.p_remove = p_remove
        self.max_terms = max_terms
        self.roles = roles
        self.zero_window_s = zero_window_s
        self.fallbacks = fallbacks
        self.elongation_axes = elongation_axes
        self.campaign_weights = campaign_weights

    def _feature_map(self):
        return FilteredFeatureMap(self.sensors_, self.probe_names_, self._roles(), tuple(self.taus_s))

    def _candidates(self, sensor_names):
        terms = candidate_terms("eq13", sensor_names) + [
            lowpass_name(t, b) for t in tuple(self.taus_s) for b in TEMPERATURE_FEATURES
        ]
        return terms

    def _select(self, acc, exclude) -> dict:
        # Axes outside ``elongation_axes`` are regressed on temperature terms only.
        if self.elongation_axes is None:
            return super()._select(acc, exclude)
        saved = self.candidates_
        try:
            with_dl = super()._select(acc, exclude)
            self.candidates_ = [t for t in saved if not t.startswith("dL_")]
            without = super()._select(acc, exclude)
        finally:
            self.candidates_ = saved
        return {a: (with_dl[a] if a in self.elongation_axes else without[a]) for a in AXES}

    def new_accumulator(self, sensors, probe_names=None, *, roles_from=None, machine=None):
        """As :meth:`MRAModel.new_accumulator`, with the filtered terms and naive inference."""
        super().new_accumulator(sensors, probe_names, roles_from=roles_from, machine=machine)
        self.candidates_ = self._candidates([s.name for s in self.sensors_])
        names = [CONSTANT, *self.candidates_]
        return QRAccumulator(len(names), len(AXES), feature_names=names, target_names=list(AXES))

    def campaign_design(self, campaign, aligned):
        """Design (n, 1 + terms) of a campaign, filters run from its first sample."""
        w, t, w0, t0 = self.instrument_arrays(aligned)
        base, _ = self._feature_map().base_filtered(w, t, w0, t0, aligned.time_s)
        return design_matrix(base, self._feature_map().base_names, self.candidates_)

    def fit(self, X, y=None, *, progress=None, targets=None):
        """Fit on campaigns (``y`` must be None); ``targets`` (optional) maps a campaign index to
        the (n, 3) µm to fit instead of its reference (the hybrid fits the kinematic residual)."""
        if y is not None:
            raise ValueError("DynamicModel fits on campaigns (y must be None): its filters need time series")
        self._check_params()
        return self.fit_campaigns(X, progress=progress, targets=targets)

    def predictor(self, exclude=frozenset()) -> DynamicPredictor:
        """Compiled streaming predictor of the full sensor set or a stored fallback."""
        exclude = frozenset(exclude)
        if exclude not in self._predictors:
            axes = self.axes_ if not exclude else self.fallbacks_[exclude]
            self._predictors[exclude] = DynamicPredictor(
                self._feature_map(), axes, exclude, self.training_.get("dt_s", 1.0)
            )
        return self._predictors[exclude]

    def predict_interval(self, X, exclude=frozenset()):
        """Prediction and 95 % half-width on a campaign, filters run from its first sample."""
        return ModelFile.predict_interval(self, X, exclude)

    def to_dict(self) -> dict:
        """The regression's model file plus the filters (``dynamic``)."""
        d = super().to_dict()
        d["dynamic"] = {
            "taus_s": list(self.taus_s),
            "filtered": list(TEMPERATURE_FEATURES),
            "elongation_axes": None if self.elongation_axes is None else list(self.elongation_axes),
            "filter": "first-order low-pass, exact for inputs held between samples",
        }
        return d

    @classmethod
    def from_dict(cls, d: dict, source="<dict>", check=True) -> DynamicModel:
        """The model of a model file's dict (``check=False``: the caller checks the predictors)."""
        base = MRAModel.from_dict(d, source, check=False)
        m = cls(
            taus_s=d["dynamic"]["taus_s"],
            stepwise=base.stepwise,
            direction=base.direction,
            p_enter=base.p_enter,
            p_remove=base.p_remove,
            max_terms=base.max_terms,
            roles=base.roles,
            zero_window_s=base.zero_window_s,
            fallbacks=base.fallbacks,
            elongation_axes=d["dynamic"].get("elongation_axes"),
            campaign_weights=getattr(base, "campaign_weights", "samples"),
        )
        for k in ("candidates_", "sensors_", "probe_names_", "axes_", "fallbacks_", "training_", "coef_"):
            setattr(m, k, getattr(base, k))
        m._predictors = {}
        if check:
            check_predictors(m, source)
        return m
