"""The hybrid model type: kinematic chain for the loads + regression for the rest (``model_type`` "hybrid").

:class:`HybridModel` is the kinematic prediction (:mod:`fbgcomp.models.kinematic`) on thermally
corrected elongations plus a regression (eq. 13, optionally stepwise or with the dynamic filters
of :mod:`fbgcomp.models.dynamic`) on its residual. Its interval is the residual regression's
(covariance + residual variance), which covers the whole model error, widened where the bars
contradict plane sections. :mod:`fbgcomp.models.calibrated` extends it with a fitted closure.
"""

from __future__ import annotations

import copy
from typing import Self

import numpy as np

from fbgcomp.errors import InputError
from fbgcomp.models.base import (
    EstimatorParams,
    ModelFile,
    as_campaign_list,
    campaign_z_axis_mm,
    check_compatible,
    check_predictors,
)
from fbgcomp.models.dynamic import DEFAULT_TAUS_S, DynamicModel, DynamicPredictor
from fbgcomp.models.kinematic import KinematicModel, KinematicPredictor, per_chain


def hybrid_chain_part(chain, elongation_um, housing_dT_K):
    """The chain's share of a hybrid prediction (n, 3) µm: dx, dy from the bars (the load path,
    Z-aware); dz only from the housing's probe expansion, because on dz the bars' axial
    readings are dominated by the gratings' thermal cross-sensitivity, and the residual
    regression takes them as regressors instead (a chain term it would only cancel at the
    training Z position). The housing alone moves dz in proportion to its ΔT (the chain's
    housing Jacobian; the chain itself evaluated on the housing alone agrees to 4e-9 relative,
    its own rounding at mm scale, from 0.01 to 50 K)."""
    el = np.atleast_2d(np.asarray(elongation_um, dtype=float))
    out = chain.ttp_deviation_um(el, housing_dT_K)
    out[:, 2] = (
        0.0
        if housing_dT_K is None
        else np.asarray(housing_dT_K, dtype=float).ravel() * chain.jacobian()[1][2]
    )
    return out


def _probe_columns(t, t0, cols):
    """Probe readings (n, P) and zero readings (P,) of the columns ``cols`` (None: all)."""
    return (t, t0) if cols is None else (t[:, cols], t0[cols])


class HybridPredictor:
    """Thermally corrected kinematic chain + temperature regression (see :class:`HybridModel`)."""

    def __init__(self, kinematic: KinematicPredictor, residual: DynamicPredictor, correction, probe_names):
        self.kinematic, self.residual = kinematic, residual
        self.exclude = kinematic.exclude
        self.sensor_names = kinematic.sensor_names
        self.probe_names = list(probe_names)
        self._k_probe = [self.probe_names.index(p) for p in kinematic.probe_names]
        self._r_probe = [self.probe_names.index(p) for p in residual.probe_names]
        # (the usual case: each part reads every probe in order, and no copy is made)
        every = list(range(len(self.probe_names)))
        self._k_cols = None if self._k_probe == every else self._k_probe
        self._r_cols = None if self._r_probe == every else self._r_probe
        self._correction = np.asarray(correction, dtype=float)  # (T, S) µm per feature
        self.expected_rms_error_um = residual.expected_rms_error_um
        self._used = kinematic._used

    def reset(self):
        """Forget the residual regression's filter state."""
        self.residual.reset()

    def _total_jacobian(self, chain):
        """TTP µm per µm of each used bar: the chain's plus the residual regression's own
        elongation terms (which, on dz, largely replace the chain's axial path); found once per
        chain."""
        return per_chain(self, "_total_J", chain, lambda: self._jacobian_of(chain))

    def _jacobian_of(self, chain):
        J = chain.jacobian()[0].copy()
        J[2] = 0.0  # dz: no bar path in the chain's share
        for i, name in enumerate(self.residual.terms, start=1):
            if name.startswith("dL_") and name[3:] in self.sensor_names:
                col = self.sensor_names.index(name[3:])
                if col in self._used:
                    J[:, self._used.index(col)] += self.residual.coef[i]
        return J

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
        """TTP deviation (n, 3) µm and 95 % half-width (n, 3) µm: the chain on the thermally
        corrected elongations (at ``z_axis_mm``) plus the residual regression (over ``time_s``)."""
        w = np.atleast_2d(np.asarray(wavelength_nm, dtype=float))
        w0 = np.asarray(wavelength_zero_nm, dtype=float)
        t = np.atleast_2d(np.asarray(temperature_C, dtype=float))
        t0 = np.asarray(temperature_zero_C, dtype=float)
        if self.exclude:
            w = w.copy()
            cols = [i for i, s in enumerate(self.sensor_names) if s in self.exclude]
            w[:, cols] = w0[cols]
        tr, tr0 = _probe_columns(t, t0, self._r_cols)
        design = self.residual.design(w, tr, w0, tr0, time_s)  # const + temperature terms
        dr = design @ self.residual.coef
        var = self.residual._interval_var(design)
        # Elongations minus their temperature-explained part: what the structure's loads did.
        base = self.residual.last_base
        temps = base[:, len(self.residual.feature_map.sensor_names) :]
        k = self.kinematic
        tk, tk0 = _probe_columns(t, t0, self._k_cols)
        dl = k.feature_map.base(w, tk, w0, tk0)
        dl = dl - temps @ self._correction
        dT = None
        if k._housing is not None:
            h = self._k_probe[k._housing]
            dT = t[:, h] - t0[h]
        n = len(dl)
        dk = np.empty((n, 3))
        for sel, z, ch in k.chains_of(z_axis_mm, n):
            dk[sel] = hybrid_chain_part(ch, dl[sel][:, self._used], None if dT is None else dT[sel])
            # The residual regression never saw what the training campaigns did not excite:
            # bars contradicting plane sections widen the interval (see KinematicPredictor).
            var[sel] += k.inconsistency_var(ch, dl[sel][:, self._used], self._total_jacobian(ch))
            var[sel] += self._closure_var(z, dl[sel][:, self._used])
        return dk + dr, self.residual._t[None, :] * np.sqrt(var)

    def _closure_var(self, z_axis_mm, elongation_um):
        """Variance (n, 3) µm² from the closure's own parameters at Z ``z_axis_mm`` (None: the
        description's); none here: fit-free."""
        return 0.0


class HybridModel(EstimatorParams, ModelFile):
    """Kinematic chain (physics for the loads, Z-aware) + regression for what it misses.

    Fitting, on the training campaigns:

    1. each sensor's elongation is regressed on the temperature features (eq. 13 and, with
       ``features="dynamic"``, their low-pass filtered versions): that part is the gratings'
       thermal cross-sensitivity and the free thermal strain, which the chain would otherwise
       read as bending caused by a tool-tip force and amplify through the support lever arms;
    2. the chain runs on the corrected elongations (plus the housing's probe expansion);
    3. the TTP residual is regressed on the temperature features (stepwise optional).

    Why this form and not the segment poses (or the elongations) as regressors: on thermal
    campaigns the lateral TTP deviation is ~0 while the elongations carry interrogator noise, so
    any regression on elongations learns to *cancel* the force response (errors in variables)
    and then fails on loads and on other Z positions; keeping the force path physical and letting
    the regression see only temperatures keeps the chain's load and Z behaviour intact
    (docs/models.md has the comparison).
    """

    model_type = "hybrid"

    def __init__(
        self,
        machine=None,
        features="eq13",
        stepwise=True,
        taus_s=DEFAULT_TAUS_S,
        p_enter=0.05,
        p_remove=0.10,
        max_terms=None,
        roles=None,
        zero_window_s=10.0,
        fallbacks="loo",
        elongation_axes=("dz",),
        campaign_weights="balanced",
    ):
        self.machine = machine
        self.campaign_weights = campaign_weights
        self.elongation_axes = elongation_axes
        self.features = features
        self.stepwise = stepwise
        self.taus_s = taus_s
        self.p_enter, self.p_remove, self.max_terms = p_enter, p_remove, max_terms
        self.roles = roles
        self.zero_window_s = zero_window_s
        self.fallbacks = fallbacks

    def _residual_estimator(self):
        if self.features not in ("eq13", "dynamic"):
            raise ValueError(f"hybrid features must be eq13 or dynamic, not {self.features!r}")
        return DynamicModel(
            taus_s=self.taus_s if self.features == "dynamic" else (),
            stepwise=self.stepwise,
            p_enter=self.p_enter,
            p_remove=self.p_remove,
            max_terms=self.max_terms,
            roles=self.roles,
            zero_window_s=self.zero_window_s,
            fallbacks=self.fallbacks,
            elongation_axes=self.elongation_axes,
            campaign_weights=self.campaign_weights,
        )

    def fit(self, X, y=None, *, progress=None):
        """Fit on campaigns (``y`` None): thermal correction, chain, residual regression."""
        campaigns = as_campaign_list(X)
        if not campaigns:
            raise ValueError("fit needs at least one campaign")
        self.kinematic_ = KinematicModel(
            self.machine, zero_window_s=self.zero_window_s, fallbacks=self.fallbacks
        ).fit()
        res = self._residual_estimator()
        res.new_accumulator(
            list(campaigns[0].meta.sensors),
            None,
            roles_from=campaigns[0].probe_names,
            machine=self.kinematic_.machine_,
        )
        self.residual_ = res
        self.sensors_ = self.kinematic_.sensors_
        self.probe_names_ = list(dict.fromkeys(list(res.probe_names_) + list(self.kinematic_.probe_names_)))
        kin = self.kinematic_.predictor()
        fmap = res._feature_map()
        # 1. thermal part of each elongation (pooled least squares over all campaigns)
        xtx, xty, cache = 0.0, 0.0, []
        for c in campaigns:
            check_compatible(self, c)
            a = c.aligned(zero_window_s=self.zero_window_s)
            w, t, w0, t0 = self.instrument_arrays(a)
            rp = [self.probe_names_.index(p) for p in res.probe_names_]
            kp = [self.probe_names_.index(p) for p in kin.probe_names]
            base, _ = fmap.base_filtered(w, t[:, rp], w0, t0[rp], a.time_s)
            # Through the origin: at the zero state both sides are zero by definition, and a
            # constant would absorb the mean elongation of load campaigns (ΔT = 0 there).
            temps = base[:, len(fmap.sensor_names) :]
            dl = kin.feature_map.base(w, t[:, kp], w0, t0[kp])
            xtx = xtx + temps.T @ temps
            xty = xty + temps.T @ dl
            cache.append((c, a, temps, dl, t[:, kp], t0[kp]))
        self.correction_ = np.linalg.lstsq(xtx, xty, rcond=None)[0]  # (T, S)
        kin = self._calibrate_closure(kin, cache)
        # 2-3. chain on corrected elongations, regression of the residual on temperatures
        targets = {}
        for i, (c, a, temps, dl, tk, tk0) in enumerate(cache):
            corrected = dl - temps @ self.correction_
            dT = None if kin._housing is None else tk[:, kin._housing] - tk0[kin._housing]
            pk = hybrid_chain_part(kin.chain(campaign_z_axis_mm(c)), corrected, dT)
            targets[i] = a.reference_um - pk
        self.residual_ = res.fit(campaigns, progress=progress, targets=targets)
        self.training_ = self.residual_.training_
        self._predictors = {}
        return self

    def _calibrate_closure(self, kin, cache):
        """Hook between the thermal correction and the residual regression (the hybrid keeps
        the fit-free closure); returns the kinematic predictor to use."""
        return kin

    @property
    def fallback_sets(self) -> list:
        """Excluded-sensor sets of the fallback policy (the chain's and the regression's)."""
        return self.kinematic_.fallback_sets

    def predictor(self, exclude=frozenset()) -> HybridPredictor:
        """Compiled predictor of the full sensor set or of a fallback."""
        exclude = frozenset(exclude)
        if exclude not in self._predictors:
            kin = self.kinematic_.predictor(exclude)
            res = self.residual_.predictor(exclude)
            self._predictors[exclude] = HybridPredictor(kin, res, self.correction_, self.probe_names_)
        return self._predictors[exclude]

    def summary(self) -> str:
        """The chain's summary, the thermal correction of the elongations and the regression's tables."""
        names = self.residual_._feature_map().base_names[len(self.sensors_) :]
        lines = [
            "Hybrid model: thermally corrected kinematic chain + temperature regression",
            "",
            self.kinematic_.summary(),
            "",
            "Thermal part of the elongations (µm per unit feature):",
            f"{'':<24}" + "".join(f"{s.name:>10}" for s in self.sensors_),
        ]
        for name, row in zip(names, self.correction_):
            lines.append(f"{name:<24}" + "".join(f"{v:>10.4g}" for v in row))
        lines += ["", "Regression of the chain's residual", self.residual_.summary()]
        return "\n".join(lines)

    def to_dict(self) -> dict:
        """The model file's content (the chain's and the regression's files embedded)."""
        d = self._header()
        d.update(
            {
                "zero_state": {"method": "mean_of_first_window", "window_s": self.zero_window_s},
                "sensors": [s.model_dump(mode="json") for s in self.sensors_],
                "probes": list(self.probe_names_),
                "hybrid": {
                    "features": self.features,
                    "kinematic": self.kinematic_.to_dict(),
                    "thermal_correction_um": self.correction_.tolist(),
                    "residual": self.residual_.to_dict(),
                },
                "uncertainty": {
                    "level": 0.95,
                    "method": "residual regression: covariance + residual variance",
                },
                "z_axis_mm": self.kinematic_.machine_.supports.z_axis_mm,
                "fallback_policy": self.fallbacks,
                "training": copy.deepcopy(self.training_),
            }
        )
        return d

    @classmethod
    def from_dict(cls, d: dict, source="<dict>", check=True) -> Self:
        """The model of a model file's dict (``check=False``: the caller checks the predictors)."""
        h = d["hybrid"]
        kin = KinematicModel.from_dict(h["kinematic"], source)
        res = DynamicModel.from_dict(h["residual"], source)
        m = cls(
            machine=kin.machine_,
            features=h["features"],
            zero_window_s=d["zero_state"]["window_s"],
            fallbacks=d.get("fallback_policy", "loo"),
            taus_s=res.taus_s,
            elongation_axes=res.elongation_axes,
            campaign_weights=res.campaign_weights,
        )
        m.kinematic_, m.residual_ = kin, res
        m.correction_ = np.asarray(h["thermal_correction_um"], dtype=float)
        if m.correction_.ndim != 2 or m.correction_.shape[1] != len(kin.sensors_):
            raise InputError(
                f"shape {m.correction_.shape} disagrees with the model's {len(kin.sensors_)} sensors",
                file=source,
                column="field hybrid.thermal_correction_um",
            )
        m.sensors_ = kin.sensors_
        m.probe_names_ = list(d["probes"])
        m.training_ = d.get("training", res.training_)
        m._predictors = {}
        if check:
            check_predictors(m, source)
        return m
