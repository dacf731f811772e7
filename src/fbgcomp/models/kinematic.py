"""The kinematic model type: the paper's HTM chain (eq. 4-10), fit-free (``model_type`` "kinematic").

:class:`KinematicModel` builds the chain of :mod:`fbgcomp.kinematics` from the machine
description embedded in the model file; no coefficient is fitted. Its interval propagates the
interrogator noise through the chain and adds a model-form term (relative + floor), taken from
training campaigns' residuals when the model is "fitted" on campaigns (the prediction itself
never changes), else a stated default.

Like every model type it shares the model-file format of :mod:`fbgcomp.models.modelfile` and the
runtime contract of :class:`~fbgcomp.models.base.ModelFile`: ``predictor(exclude)`` returns a
pure-numpy object whose ``predict(wavelength_nm, temperature_C, wavelength_zero_nm,
temperature_zero_C, *, z_axis_mm=None, time_s=None)`` gives the TTP deviation (n, 3) µm and the
half-width (n, 3) µm of its 95 % prediction interval, plus ``expected_rms_error_um``.
"""

from __future__ import annotations

import copy

import numpy as np

from fbgcomp.errors import InputError
from fbgcomp.kinematics import CLOSURE_FACTORS, KinematicChain
from fbgcomp.models.base import (
    EstimatorParams,
    ModelFile,
    as_campaign_list,
    check_compatible,
    check_fallback_policy,
    check_predictors,
    deviation_range,
    fallback_sets,
    plain,
)
from fbgcomp.models.distributions import norm_ppf
from fbgcomp.models.features import FeatureMap, TemperatureRoles
from fbgcomp.models.machines import campaign_sensor_specs, resolve_machine
from fbgcomp.optics import elongation_noise_um
from fbgcomp.structure.machine import parse_machine
from fbgcomp.units import AXES

_Z95 = float(norm_ppf(0.975))
#: Default model-form error of the kinematic chain before any campaign (relative to the
#: prediction, and a floor in µm): the beam closure reproduces the FE twin's tool-tip
#: compliance to ~6 % (tests/test_kinematics.py); 10 % leaves room for another structure.
KINEMATIC_DEFAULT_RELATIVE = 0.10
KINEMATIC_DEFAULT_FLOOR_UM = 0.5


def per_chain(owner, name, chain, make):
    """``make()``, computed once per chain and kept in ``owner``'s dict ``name`` (keyed by the
    chain's identity; the entry holds the chain, so the key stays its own)."""
    cache = owner.__dict__.setdefault(name, {})
    hit = cache.get(id(chain))
    if hit is None or hit[0] is not chain:
        hit = cache[id(chain)] = (chain, make())
    return hit[1]


class KinematicPredictor:
    """Pure-numpy kinematic prediction for one sensor set; chains compiled per Z position."""

    def __init__(
        self,
        machine,
        sensors,
        probe_names,
        exclude,
        pi_relative,
        pi_floor_um,
        wavelength_noise_nm=0.001,
        probe_noise_C=0.1,
        closure_factors=None,
    ):
        self.machine = machine
        self.closure_factors = None if closure_factors is None else dict(closure_factors)
        self.exclude = frozenset(exclude)
        self.sensor_names = [s.name for s in sensors]
        self.probe_names = list(probe_names)
        self.feature_map = FeatureMap(sensors, self.probe_names, False)
        self._used = [i for i, s in enumerate(self.sensor_names) if s not in self.exclude]
        self._chains: dict = {}
        chain = self.chain(None)
        self._housing = (
            self.probe_names.index(chain.housing_probe) if chain.housing_probe in self.probe_names else None
        )
        self._noise_um = elongation_noise_um(sensors, wavelength_noise_nm)[self._used]
        self._probe_noise_C = probe_noise_C
        # Elongation change per K of each probe (temperature compensation, eq. 2-3): probe
        # noise moves the compensated elongations too.
        n_p = len(self.probe_names)
        if n_p:
            w0 = np.array([s.lambda0_nm for s in sensors])
            t0 = np.zeros(n_p)
            self._per_probe = (
                self.feature_map.base(np.tile(w0, (n_p, 1)), np.eye(n_p), w0, t0)[:, self._used]
            ).T  # (S_used, P) µm/K
        else:
            self._per_probe = np.zeros((len(self._used), 0))
        self._rel = np.broadcast_to(np.asarray(pi_relative, float), (3,)).copy()
        self._floor = np.broadcast_to(np.asarray(pi_floor_um, float), (3,)).copy()
        self.expected_rms_error_um = np.sqrt(self._noise_var(chain) + self._floor**2)

    def chain(self, z_axis_mm) -> KinematicChain:
        """The HTM chain of the used bars at Z position ``z_axis_mm`` (None: the description's),
        compiled once per position (rounded to 1 µm)."""
        key = None if z_axis_mm is None else round(float(z_axis_mm), 3)
        if key not in self._chains:
            self._chains[key] = KinematicChain(
                self.machine,
                [self.sensor_names[i] for i in self._used],
                z_axis_mm=key,
                closure_factors=self.closure_factors,
            )
        return self._chains[key]

    def chains_of(self, z_axis_mm, n):
        """(rows, Z, chain) for the frames at each Z position among ``z_axis_mm`` (None, a
        number or (n,) mm; NaN: the description's, given as Z None); one group of every row
        without Z positions."""
        if z_axis_mm is None:
            yield slice(None), None, self.chain(None)
            return
        zs = np.broadcast_to(np.asarray(z_axis_mm, float), (n,))
        for z in np.unique(zs):
            sel = (zs == z) if np.isfinite(z) else ~np.isfinite(zs)
            key = None if not np.isfinite(z) else float(z)
            yield sel, key, self.chain(key)

    def inconsistency_var(self, chain, elongation_um, jacobian=None):
        """Extra variance (n, 3) µm² when the bars contradict plane sections beyond their noise.

        The bar equations' residual rho = P dL (P: projector on what plane sections cannot
        explain) is zero for any deformation the chain can represent. An artefact eps on one
        bar k (a grating compensated with the wrong temperature, a local strain) leaves
        rho = eps P[:, k], so eps = rho_k / P_kk; the chain passes J[:, k] eps to the TTP. The
        residual cannot say which bar it is: the interval takes the worst single-bar
        explanation, shrunk by the part of |rho|² the interrogator and probe noise explain at
        95 % (chi² scale 3.84 on its expected power tr(P Σ P')).
        """
        n = len(elongation_um)
        terms = self._inconsistency_terms(chain)
        if terms is None:
            return np.zeros((n, 3))
        P, expected, d, ok, _ = terms
        rho = elongation_um @ P.T
        J = chain.jacobian()[0] if jacobian is None else jacobian
        if n == 1:  # one frame (a runtime batch of 1): the same arithmetic on Python floats
            r = rho[0].tolist()
            r2 = sum(v * v for v in r)
            s = max(1.0 - 3.84 * expected / max(r2, 1e-300), 0.0) if r2 > 0 else 0.0
            Jt = J.T.tolist()
            bars = [(r[k], dk, Jt[k]) for k, dk in terms[4]]
            return np.array([[max(((rk / dk) * jk[a]) ** 2 for rk, dk, jk in bars) * s for a in range(3)]])
        rho2 = np.sum(rho**2, axis=1)
        shrink = np.where(rho2 > 0, np.maximum(1.0 - 3.84 * expected / np.maximum(rho2, 1e-300), 0.0), 0.0)
        eps = rho[:, ok] / d[ok]  # (n, k) µm on one bar
        effect = np.max((eps[:, :, None] * J.T[ok][None, :, :]) ** 2, axis=1)
        return effect * shrink[:, None]

    def _inconsistency_terms(self, chain):
        """What :meth:`inconsistency_var` takes of a chain, found once per chain: the projector
        P, the noise's expected residual power tr(P Σ P'), P's diagonal, where it is not zero,
        and those bars as (index, diagonal) Python numbers (the one-frame path); None where
        plane sections explain every reading."""

        def terms():
            P = chain.inconsistency_projector
            if not P.size or np.trace(P) < 0.5:
                return None
            sigma = (
                np.diag(self._noise_um**2)
                + (self._per_probe * self._probe_noise_C) @ (self._per_probe * self._probe_noise_C).T
            )
            d = np.diag(P)
            ok = d > 1e-9
            bars = [(int(k), float(d[k])) for k in np.flatnonzero(ok)]
            return P, float(np.trace(P @ sigma @ P.T)), d, ok, bars

        return per_chain(self, "_inconsistency", chain, terms)

    def _noise_var(self, chain):
        J, Jh = chain.jacobian()
        var = (J**2) @ (self._noise_um**2)
        if chain.housing_probe is not None:
            var = var + (Jh * self._probe_noise_C) ** 2
        return var

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
        """TTP deviation (n, 3) µm and 95 % half-width (n, 3) µm (see the module docstring)."""
        w = np.atleast_2d(np.asarray(wavelength_nm, dtype=float))
        w0 = np.asarray(wavelength_zero_nm, dtype=float)
        if self.exclude:
            w = w.copy()
            cols = [i for i, s in enumerate(self.sensor_names) if s in self.exclude]
            w[:, cols] = w0[cols]
        n = w.shape[0]
        dl = self.feature_map.base(w, temperature_C, w0, temperature_zero_C)[:, self._used]
        dT = None
        if self._housing is not None:
            t = np.atleast_2d(np.asarray(temperature_C, dtype=float))
            dT = t[:, self._housing] - np.asarray(temperature_zero_C, dtype=float)[self._housing]
        dev = np.empty((n, 3))
        half = np.empty((n, 3))
        for sel, _, ch in self.chains_of(z_axis_mm, n):
            d = ch.ttp_deviation_um(dl[sel], None if dT is None else dT[sel])
            var = (
                self._noise_var(ch)[None, :]
                + self._floor**2
                + (self._rel * d) ** 2
                + self.inconsistency_var(ch, dl[sel])
            )
            dev[sel], half[sel] = d, _Z95 * np.sqrt(var)
        return dev, half


class KinematicModel(EstimatorParams, ModelFile):
    """Fit-free kinematic model (paper eq. 4-10) of a machine description.

    Parameters
    ----------
    machine : Machine, path or None
        The machine description (None: the built-in ram). Embedded in the model file.
    zero_window_s : float
    fallbacks : {"loo", "lto", "none"}
        Sensor sets without one (or two) sensors the runtime may switch to; the chain is simply
        rebuilt without those bars (segments that lose their bars are reported and closed).
    pi_relative, pi_floor_um : float, optional
        Model-form error of the 95 % interval (relative to the prediction, floor µm). None:
        estimated from the campaigns given to :meth:`fit`, else the module defaults.
    closure_factors : dict, optional
        Factors on the beam closure's compliances (:data:`fbgcomp.kinematics.CLOSURE_FACTORS`;
        None: all 1, the description's sections); set by :class:`~fbgcomp.models.calibrated.CalibratedModel`.
    """

    model_type = "kinematic"

    def __init__(
        self,
        machine=None,
        zero_window_s=10.0,
        fallbacks="loo",
        pi_relative=None,
        pi_floor_um=None,
        closure_factors=None,
    ):
        self.machine = machine
        self.closure_factors = closure_factors
        self.zero_window_s = zero_window_s
        self.fallbacks = fallbacks
        self.pi_relative = pi_relative
        self.pi_floor_um = pi_floor_um

    def _setup(self):
        """The learned state of a model without campaigns (the chain of the description, the
        default interval); :meth:`fit` and :meth:`from_dict` start from it."""
        self.machine_ = resolve_machine(self.machine)
        self.sensors_ = campaign_sensor_specs(self.machine_)
        chain = KinematicChain(self.machine_, closure_factors=self.closure_factors)
        probes = FeatureMap.required_probes(self.sensors_, False, TemperatureRoles())
        if chain.housing_probe:
            probes = list(dict.fromkeys([*probes, chain.housing_probe]))
        self.probe_names_ = probes
        self.segment_report_ = chain.report
        self.pi_relative_ = np.full(
            3, KINEMATIC_DEFAULT_RELATIVE if self.pi_relative is None else float(self.pi_relative)
        )
        self.pi_floor_um_ = np.full(
            3, KINEMATIC_DEFAULT_FLOOR_UM if self.pi_floor_um is None else float(self.pi_floor_um)
        )
        self.pi_source_ = "default"
        self.training_ = {"campaigns": [], "n_samples": 0}
        self._predictors = {}

    def fit(self, X=None, y=None, *, progress=None):
        """No coefficient is fitted. With campaigns, only the interval's model-form error is
        estimated from their residuals (per axis: e² ≈ floor² + (relative · prediction)²)."""
        self._setup()
        if X is None:
            return self
        campaigns = as_campaign_list(X)
        preds, refs, training = [], [], []
        for c in campaigns:
            if progress is not None:
                progress(c.meta.name)
            check_compatible(self, c)
            p, _ = self.predict_interval(c)
            preds.append(p)
            refs.append(c.aligned(zero_window_s=self.zero_window_s).reference_um)
            training.append(
                {
                    "name": c.meta.name,
                    "kind": c.meta.kind,
                    "n_samples": len(p),
                    **deviation_range(refs[-1]),
                }
            )
        pred, ref = np.vstack(preds), np.vstack(refs)
        if self.pi_relative is None and self.pi_floor_um is None:
            self.pi_floor_um_, self.pi_relative_ = error_model(ref - pred, pred)
            self.pi_source_ = "training campaigns"
        self.training_ = {"campaigns": training, "n_samples": len(pred)}
        self._predictors = {}
        return self

    @property
    def fallback_sets(self) -> list:
        """Excluded-sensor sets of the fallback policy (the chain is rebuilt without them)."""
        return fallback_sets(self.sensor_names, self.fallbacks)

    def _check_fitted(self):
        if not hasattr(self, "machine_"):
            raise AttributeError(
                f"this {type(self).__name__} is not fitted: call fit() first (it needs no campaign)"
            )

    def predictor(self, exclude=frozenset()) -> KinematicPredictor:
        """Compiled predictor of the full sensor set or of a fallback (KeyError if none)."""
        self._check_fitted()
        exclude = frozenset(exclude)
        if exclude and exclude not in set(self.fallback_sets):
            raise KeyError(exclude)
        if exclude not in self._predictors:
            self._predictors[exclude] = KinematicPredictor(
                self.machine_,
                self.sensors_,
                self.probe_names_,
                exclude,
                self.pi_relative_,
                self.pi_floor_um_,
                closure_factors=self.closure_factors,
            )
        return self._predictors[exclude]

    def chain(self, z_axis_mm=None, exclude=frozenset()) -> KinematicChain:
        """The chain of a sensor set at a Z position (see :meth:`KinematicPredictor.chain`)."""
        return self.predictor(exclude).chain(z_axis_mm)

    def summary(self) -> str:
        """The chain's segment report, its linearised gains and the interval's model-form error."""
        ch = self.chain()
        assert ch.sensor_names is not None  # the chain's __post_init__ fills in the default
        J, Jh = ch.jacobian()
        lines = [
            "Kinematic model (paper eq. 4-10, HTM chain; no fitted coefficient)",
            ch.format_report(),
            "TTP µm per µm of bar elongation (linearised chain):",
            f"{'':<6}"
            + "".join(f"{s:>10}" for s in ch.sensor_names)
            + (f"{'dT_' + ch.housing_probe:>14}" if ch.housing_probe else ""),
        ]
        for j, a in enumerate(AXES):
            lines.append(
                f"{a:<6}"
                + "".join(f"{v:>10.4g}" for v in J[j])
                + (f"{Jh[j]:>14.4g}" if ch.housing_probe else "")
            )
        lines.append(
            f"95 % interval model-form error ({self.pi_source_}): relative "
            + ", ".join(f"{a} {r:.3g}" for a, r in zip(AXES, self.pi_relative_))
            + "; floor "
            + ", ".join(f"{a} {f:.3g} µm" for a, f in zip(AXES, self.pi_floor_um_))
        )
        return "\n".join(lines)

    def to_dict(self) -> dict:
        """The model file's content (the machine description embedded)."""
        self._check_fitted()
        d = self._header()
        d.update(
            {
                "zero_state": {"method": "mean_of_first_window", "window_s": self.zero_window_s},
                "sensors": [s.model_dump(mode="json") for s in self.sensors_],
                "probes": list(self.probe_names_),
                "machine": self.machine_.model_dump(mode="json"),
                "kinematic": {
                    "segments": [plain(vars(r)) for r in self.segment_report_],
                    # v2-compatible addition: absent (= all 1) in files of the fit-free type
                    "closure_factors": (
                        None
                        if self.closure_factors is None
                        else {k: float(v) for k, v in self.closure_factors.items()}
                    ),
                },
                "uncertainty": {
                    "level": 0.95,
                    "method": "kinematic: sensor noise through the chain "
                    "+ model-form error (relative, floor)",
                    "source": self.pi_source_,
                    "relative": self.pi_relative_.tolist(),
                    "floor_um": self.pi_floor_um_.tolist(),
                },
                "z_axis_mm": self.machine_.supports.z_axis_mm,
                "fallback_policy": self.fallbacks,
                "training": copy.deepcopy(self.training_),
            }
        )
        return d

    @classmethod
    def from_dict(cls, d: dict, source="<dict>") -> KinematicModel:
        """The model of a model file's dict; InputError naming the field when it is malformed."""
        u = d.get("uncertainty", {})
        closure = d.get("kinematic", {}).get("closure_factors")
        if closure is not None and not (isinstance(closure, dict) and set(closure) <= set(CLOSURE_FACTORS)):
            raise InputError(
                f"closure_factors must map {', '.join(CLOSURE_FACTORS)} to numbers",
                file=source,
                column="field kinematic.closure_factors",
            )
        m = cls(
            machine=parse_machine(d["machine"], file=str(source)),
            zero_window_s=d["zero_state"]["window_s"],
            fallbacks=d.get("fallback_policy", "loo"),
            closure_factors=closure,
        )
        check_fallback_policy(m.fallbacks, file=source, column="field fallback_policy")
        m._setup()
        if "relative" in u:
            m.pi_relative_ = np.asarray(u["relative"], float)
            m.pi_floor_um_ = np.asarray(u["floor_um"], float)
            m.pi_source_ = u.get("source", "file")
            for key, value in (("relative", m.pi_relative_), ("floor_um", m.pi_floor_um_)):
                if value.shape != (3,) or not (value >= 0).all():
                    raise InputError(
                        "expected three numbers >= 0 (dx, dy, dz)",
                        file=source,
                        column=f"field uncertainty.{key}",
                    )
        m.training_ = d.get("training", m.training_)
        check_predictors(m, source)
        return m


def error_model(resid, pred):
    """Per-axis (floor µm, relative) with e² ≈ floor² + (relative · pred)², non-negative LS."""
    from scipy.optimize import nnls  # noqa: PLC0415 - start-up: fit-time only

    floor, rel = np.zeros(3), np.zeros(3)
    for j in range(3):
        A = np.column_stack([np.ones(len(pred)), pred[:, j] ** 2])
        sol, _ = nnls(A, resid[:, j] ** 2)
        floor[j], rel[j] = np.sqrt(sol)
    return floor, rel
