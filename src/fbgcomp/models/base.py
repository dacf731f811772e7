"""What every TTP-deviation model type shares: the model-file contract and the fitting helpers.

* :class:`ModelFile`: the sensors and probes a model expects, its id, ``save`` (atomic, and only
  a file that loads back replaces an existing one), the validated correction envelope;
* :class:`Predictor`: the pure-numpy, vectorised prediction of a linear model on the regressors
  of :mod:`fbgcomp.models.features` (offline validation and the runtime share it);
* :class:`EstimatorParams`: scikit-learn's ``get_params`` / ``set_params`` protocol;
* the helpers the model types share: campaign weights of a pooled fit, the fallback policy
  (sensor sets the runtime may switch to), campaigns from paths, the compatibility and
  predictor checks, :func:`deviation_range` and :func:`plain`.

The model types themselves live in their own modules (:mod:`~fbgcomp.models.mra`,
:mod:`~fbgcomp.models.kinematic`, :mod:`~fbgcomp.models.dynamic`, :mod:`~fbgcomp.models.hybrid`,
:mod:`~fbgcomp.models.calibrated`, :mod:`~fbgcomp.models.physical`), which import this module and
nothing above it; :mod:`fbgcomp.models.registry` knows them all and loads any model file.
"""

from __future__ import annotations

import inspect
from datetime import UTC, datetime
from itertools import combinations
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from pydantic import ValidationError

from fbgcomp import __version__
from fbgcomp.atomic import write_json
from fbgcomp.errors import InputError
from fbgcomp.io.campaign import Campaign, SensorSpec, check_sensors_match, read_campaign
from fbgcomp.models.distributions import t_ppf
from fbgcomp.models.features import CONSTANT, FeatureMap, as_frames, design_matrix, parse_term
from fbgcomp.models.modelfile import (
    MODEL_FORMAT,
    SCHEMA_VERSION,
    build_model,
    model_id,
    read_model_dict,
    short_text,
)
from fbgcomp.units import AXES, REFERENCE_COLUMNS

#: Rows of a campaign's design added to a QR factor at a time (bounds the memory of a fit).
CHUNK_ROWS = 100_000
#: How campaigns of different lengths are pooled in a fit (see :func:`campaign_weights_for`).
CAMPAIGN_WEIGHTS = ("balanced", "samples")
#: Fallback policies: sensor sets without one ("loo") or one or two ("lto") sensors, or none.
FALLBACK_POLICIES = ("loo", "lto", "none")
_FALLBACK_SIZES = {"none": (), "loo": (1,), "lto": (1, 2)}


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


def check_fallback_policy(policy, *, file=None, column=None):
    """``policy`` if it is one of :data:`FALLBACK_POLICIES`; else ValueError (a bad estimator
    parameter) or, with ``file``, an InputError naming ``file`` and ``column``."""
    if isinstance(policy, str) and policy in FALLBACK_POLICIES:
        return policy
    message = f"fallbacks must be loo, lto or none, not {short_text(repr(policy), 40)}"
    if file is None:
        raise ValueError(message)
    raise InputError(message, file=file, column=column)


def fallback_sets(sensor_names, policy) -> list:
    """The sensor sets (as frozensets of excluded names) a fallback ``policy`` asks for: each
    sensor ("loo"), each sensor and each pair ("lto"), none ("none"); at least one sensor stays."""
    names = list(sensor_names)
    return [
        frozenset(c)
        for k in _FALLBACK_SIZES[check_fallback_policy(policy)]
        for c in combinations(names, k)
        if len(names) - k >= 1
    ]


def plain(obj):
    """JSON-able copy of nested dicts and lists (numpy scalars -> Python), e.g. a stepwise
    history entry or a campaign's ``dropped`` record."""
    if isinstance(obj, dict):
        return {k: plain(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [plain(v) for v in obj]
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
            self._resid_var[j] = fit.resid_sd**2
            self._t[j] = t_ppf(1 - alpha / 2, fit.df_resid)
        self.expected_rms_error_um = np.sqrt(self._resid_var)
        self._compile()

    def _compile(self):
        """Index form of the terms and the stacked covariance roots, so that a batch costs a
        few array operations whatever the number of terms (per-frame work at run time).

        ``_factors`` (terms, k): the base columns each term multiplies, padded with the index
        of a column of ones (a product with 1.0 is exact: the same numbers as
        :func:`design_matrix`); ``_cov_stack`` (K, 3K): the three axes' roots side by side,
        one matrix product for the whole interval."""
        names = list(self.feature_map.base_names)
        index = {name: i for i, name in enumerate(names)}
        factors = []
        for term in self.terms:
            fs = parse_term(term)
            missing = [f for f in fs if f not in index]
            if missing:
                factors = None  # design_matrix names the missing feature at predict time
                break
            factors.append([index[f] for f in fs])
        if factors:
            k = max(len(f) for f in factors)
            self._factors = np.array([f + [len(names)] * (k - len(f)) for f in factors])
        else:
            self._factors = None if factors is None else np.zeros((0, 1), int)
        self._cov_stack = np.concatenate(list(self._cov_sqrt), axis=1)

    def _design_from_base(self, base) -> np.ndarray:
        base = as_frames(base)
        fac = getattr(self, "_factors", None)
        if fac is None:
            return design_matrix(base, self.feature_map.base_names, self.terms)
        n, width = base.shape
        out = np.empty((n, 1 + fac.shape[0]))
        out[:, 0] = 1.0
        if fac.shape[0] and fac.shape[1] == 1:  # every term one base feature (eq. 11, 13)
            out[:, 1:] = base.take(fac[:, 0], axis=1)
        elif fac.shape[0]:
            ext = np.empty((n, width + 1))
            ext[:, :width] = base
            ext[:, width] = 1.0
            cols = ext[:, fac]  # (n, terms, k)
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
        return self._resid_var[None, :] + np.add.reduce(spread.reshape(d.shape[0], len(AXES), K), axis=2)

    def design(self, wavelength_nm, temperature_C, wavelength_zero_nm, temperature_zero_C):
        """Design matrix (n, 1 + terms) of raw instrument arrays (nm, °C, zero states)."""
        base = self.feature_map.base(wavelength_nm, temperature_C, wavelength_zero_nm, temperature_zero_C)
        return self._design_from_base(base)

    def predict(self, wavelength_nm, temperature_C, wavelength_zero_nm, temperature_zero_C, *, time_s=None):
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
        wavelength_nm = as_frames(wavelength_nm)
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
        sig = inspect.signature(cls.__init__)
        return [
            p.name
            for p in sig.parameters.values()
            if p.name != "self" and p.kind not in (p.VAR_POSITIONAL, p.VAR_KEYWORD)
        ]

    def get_params(self, deep=True) -> dict:
        """The estimator's hyper-parameters (``__init__``'s arguments) by name."""
        return {name: getattr(self, name) for name in self._param_names()}

    def set_params(self, **params):
        """Set hyper-parameters by name (ValueError for a name ``__init__`` does not take)."""
        valid = set(self._param_names())
        for key, value in params.items():
            if key not in valid:
                raise ValueError(
                    f"invalid parameter {key!r} for {type(self).__name__}; valid: {', '.join(sorted(valid))}"
                )
            setattr(self, key, value)
        return self

    def __repr__(self) -> str:
        args = ", ".join(f"{k}={v!r}" for k, v in self.get_params().items())
        return f"{type(self).__name__}({args})"


def deviation_range(reference_um) -> dict:
    """The range of TTP deviations (n, 3) µm a training campaign showed, as its entry in a model
    file's ``training.campaigns`` records it (the envelope of :attr:`ModelFile.max_correction_um`)."""
    ref = np.asarray(reference_um, float)
    return {
        "deviation_low_um": np.min(ref, axis=0).tolist(),
        "deviation_high_um": np.max(ref, axis=0).tolist(),
    }


class ModelFile:
    """What every model type shares: the sensors and probes it expects, its id and its file.

    Subclasses define ``model_type``, ``to_dict()`` and a ``from_dict`` classmethod, and set
    ``sensors_`` and ``probe_names_`` when fitted.
    """

    model_type: str
    sensors_: list[SensorSpec]
    probe_names_: list[str]

    if TYPE_CHECKING:  # defined by every subclass

        def to_dict(self) -> dict: ...

    @property
    def sensors(self):
        """The gratings the model reads (``SensorSpec``), in its order."""
        return self.sensors_

    @property
    def sensor_names(self) -> list:
        """Names of :attr:`sensors`."""
        return [s.name for s in self.sensors_]

    @property
    def probe_names(self) -> list:
        """Temperature probes the model reads, in its order."""
        return list(self.probe_names_)

    @property
    def model_id(self) -> str:
        """Short stable hash of the model's content (:func:`fbgcomp.models.modelfile.model_id`)."""
        return model_id(self.to_dict())

    def _header(self) -> dict:
        return {
            "format": MODEL_FORMAT,
            "schema_version": SCHEMA_VERSION,
            "model_type": self.model_type,
            "fbgcomp_version": __version__,
        }

    def save(self, path) -> Path:
        """Write the model file atomically, with its id and creation time.

        The file is written under a temporary name and read back through the checks of
        :func:`fbgcomp.models.registry.load_model` (:func:`~fbgcomp.models.modelfile.read_model_dict`,
        then this class's ``from_dict``, which checks its predictors); only a model that passes
        every check replaces ``path``. Otherwise InputError, and an existing
        file at ``path`` is left as it was (a fit on bad data never overwrites a good model).
        """
        path = Path(path)
        d = self.to_dict()
        d["model_id"] = model_id(d)
        d["created_utc"] = datetime.now(UTC).isoformat(timespec="seconds")

        def loads_back(written: Path) -> None:
            try:
                build_model(type(self), read_model_dict(written), written)
            except InputError as err:
                raise InputError(
                    f"the model is not valid, so {path.name} was not written "
                    f"(an existing one is unchanged): {err.message}",
                    file=path,
                    column=err.column,
                ) from None

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

    def predict_interval(self, X, exclude=frozenset()):
        """Prediction (n, 3) µm and 95 % half-width (n, 3) µm on a campaign (or its path), with
        the predictor of the sensor set without ``exclude``, run from its first sample (the
        campaign's Z position, if it records one, and its sample times passed along)."""
        (campaign,) = as_campaign_list(X)
        check_compatible(self, campaign)
        aligned = campaign.aligned(zero_window_s=self.zero_window_s)
        p = self.predictor(exclude)
        if hasattr(p, "reset"):
            p.reset()
        w, t, w0, t0 = self.instrument_arrays(aligned)
        return p.predict(w, t, w0, t0, z_axis_mm=campaign_z_axis_mm(campaign), time_s=aligned.time_s)

    def instrument_arrays(self, aligned):
        """Wavelengths, temperatures and zero states of an aligned campaign in the model's order."""
        s_idx = [list(aligned.sensor_names).index(s) for s in self.sensor_names]
        p_idx = [list(aligned.probe_names).index(p) for p in self.probe_names_]
        return (
            aligned.wavelength_nm[:, s_idx],
            aligned.temperature_C[:, p_idx],
            aligned.wavelength_zero_nm[s_idx],
            aligned.temperature_zero_C[p_idx],
        )


def as_campaign_list(X) -> list:
    """``X`` (a campaign, a campaign folder's path, or a list or tuple of them) as a list of
    :class:`~fbgcomp.io.campaign.Campaign`, paths read."""
    items = X if isinstance(X, (list, tuple)) else [X]
    return [c if isinstance(c, Campaign) else read_campaign(c) for c in items]


def campaign_z_axis_mm(campaign):
    """Z-axis position recorded in a campaign's metadata (``z_axis_mm``), or None."""
    extra = getattr(campaign.meta, "model_extra", None) or {}
    z = extra.get("z_axis_mm", getattr(campaign.meta, "z_axis_mm", None))
    return None if z is None else float(z)


def check_compatible(model, campaign) -> None:
    """Raise InputError when a campaign lacks what the model needs (sensors, probes)."""
    where = (campaign.path / "campaign.yaml") if campaign.path is not None else campaign.meta.name
    check_sensors_match(model.sensors_, campaign.meta.sensors, where)
    probes = set(campaign.meta.probe_names) | set(getattr(campaign, "undeclared_probes", ()))
    for p in model.probe_names_:
        if p not in probes and p not in campaign.temperatures.columns.str.removesuffix("_C"):
            raise InputError(
                f"model needs temperature probe {p} which the campaign does not have",
                file=where,
                column="field temperature_probes",
            )


def sensor_specs_from_file(items, source) -> list:
    """The model file's sensor list as SensorSpec; InputError naming the entry otherwise."""
    if not isinstance(items, list) or not items:
        raise InputError("expected a non-empty list of sensors", file=source, column="field sensors")
    specs = []
    for i, item in enumerate(items):
        try:
            specs.append(SensorSpec.model_validate(item))
        except ValidationError as exc:
            err = exc.errors()[0]
            where = ".".join(str(p) for p in err["loc"])
            raise InputError(
                short_text(err["msg"]),
                file=source,
                column=f"field sensors[{i}]" + (f".{where}" if where else ""),
            ) from None
    return specs


def check_finite_fit_data(campaign, aligned, design, names) -> None:
    """InputError naming the campaign unless its design and TTP deviations are finite.

    The campaign reader bounds every input, so this fires only when a feature of bounded
    inputs still overflows; the regression would otherwise fit NaN and write a model of nulls.
    """
    where = campaign.path if campaign.path is not None else campaign.meta.name
    for what, values, columns in (
        ("design", design, names),
        ("reference deviation", aligned.reference_um, REFERENCE_COLUMNS),
    ):
        bad = ~np.isfinite(values)
        if bad.any():
            row, col = np.argwhere(bad)[0]
            raise InputError(
                f"the {what} built from this campaign is not finite at t = "
                f"{aligned.time_s[row]:g} s (term {columns[col]}): an input is out of "
                "range; nothing was fitted",
                file=where,
            )


def zero_state_frames(model):
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
    w, t, w0, t0 = zero_state_frames(model)
    for exclude in sets:
        label = "the full sensor set" if not exclude else f"the fallback without {', '.join(sorted(exclude))}"
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
        except Exception as exc:
            raise InputError(
                f"{label} cannot predict: its terms, coefficients and sensors "
                f"disagree ({type(exc).__name__}: {short_text(str(exc))})",
                file=source,
                column=field,
            ) from None
        if (
            dev.shape != (2, 3)
            or half.shape != (2, 3)
            or not (np.isfinite(dev).all() and np.isfinite(half).all())
        ):
            raise InputError(f"{label} predicts non-finite or misshapen numbers", file=source, column=field)
    if hasattr(model, "_predictors"):
        model._predictors = {}  # the runtime starts from fresh predictors, not the check's
