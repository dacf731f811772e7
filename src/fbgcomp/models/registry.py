"""Which model types exist: load any model file, build any type's estimator.

The registry imports every model type module (:mod:`~fbgcomp.models.mra`,
:mod:`~fbgcomp.models.kinematic`, :mod:`~fbgcomp.models.hybrid`, :mod:`~fbgcomp.models.calibrated`,
:mod:`~fbgcomp.models.dynamic`, :mod:`~fbgcomp.models.physical`); none of them imports it.

* :func:`load_model` is the one loader of the CLI, ``serve`` and the OPC UA reload: the file's
  checks (:func:`fbgcomp.models.modelfile.read_model_dict`: size, nesting, finite and bounded
  numbers, schema version and migrations), then the class its ``model_type`` names builds it
  (arrays whose shapes agree with their terms; every predictor the runtime may switch to
  predicting finite numbers).
* :func:`make_estimator` is the one factory of an unfitted estimator from the options the CLI and
  ``fbgcomp compare`` give; :func:`fit_from_cli` fits it (``fbgcomp fit --model ...``).
"""

from __future__ import annotations

from pathlib import Path

from fbgcomp.errors import InputError
from fbgcomp.models.base import check_fallback_policy
from fbgcomp.models.calibrated import CalibratedModel
from fbgcomp.models.dynamic import DynamicModel
from fbgcomp.models.hybrid import HybridModel
from fbgcomp.models.kinematic import KinematicModel
from fbgcomp.models.machines import resolve_machine
from fbgcomp.models.modelfile import build_model, read_model_dict, short_text
from fbgcomp.models.mra import MRAModel
from fbgcomp.models.physical import PhysicalModel

_MODEL_TYPES = {
    cls.model_type: cls
    for cls in (MRAModel, KinematicModel, HybridModel, CalibratedModel, DynamicModel, PhysicalModel)
}
#: The model types of the CLI's ``fit --model`` (the registered ones; "physical" is the default).
MODEL_TYPES = tuple(_MODEL_TYPES)
#: Types whose ``machine`` is the description of the kinematic chain (None: the built-in ram);
#: the physical model's ``machine`` is optional (None: no description) and passed as given.
_CHAIN_TYPES = ("kinematic", "hybrid", "calibrated")


def register_model_type(name: str, cls) -> None:
    """Make :func:`load_model` and :func:`make_estimator` know another model type ``name``."""
    _MODEL_TYPES[name] = cls


def model_class(name: str):
    """The estimator class of a registered model type (KeyError for an unknown one)."""
    return _MODEL_TYPES[name]


def load_model(path):
    """Read a model file, migrating older schema versions; InputError on anything wrong.

    The one loader of the CLI, ``serve`` and the OPC UA reload. Refuses, with one line naming
    the file and field: files over :data:`~fbgcomp.models.modelfile.MAX_MODEL_BYTES`, JSON nested
    deeper than :data:`~fbgcomp.models.modelfile.MAX_MODEL_DEPTH`, non-finite or absurd numbers
    (:func:`~fbgcomp.models.modelfile.check_model_numbers`), unknown model types, arrays whose
    shapes disagree, and models whose predictors cannot predict finite numbers.
    """
    path = Path(path)
    d = read_model_dict(path)
    kind = d["model_type"]
    if kind not in _MODEL_TYPES:
        raise InputError(
            f"unknown model_type {short_text(repr(kind), 40)}; known: {', '.join(_MODEL_TYPES)}",
            file=path,
            column="field model_type",
        )
    return build_model(_MODEL_TYPES[kind], d, path)


def make_estimator(model_type: str, *, machine=None, features="eq13", where="<command line>", **options):
    """An unfitted estimator of ``model_type``; InputError naming the option of ``where`` that is wrong.

    ``machine`` is resolved for the types built on the kinematic chain (a path or None: the
    built-in ram) and passed as given to the physical model; ``features`` goes to the types that
    take it (hybrid and calibrated: eq13 or dynamic; dynamic: eq13 only). Every other option is a
    hyper-parameter (``stepwise``, ``direction``, ``p_enter``, ``p_remove``, ``max_terms``,
    ``roles``, ``zero_window_s``, ``fallbacks``, ...) passed to the types whose ``__init__`` takes
    it, each other type keeping its own default; an option no type takes is a TypeError.
    """
    if model_type not in _MODEL_TYPES:
        raise InputError(
            f"unknown model type {short_text(repr(model_type), 40)}; expected {', '.join(_MODEL_TYPES)}",
            file=where,
            column="option --model",
        )
    known = {p for cls in _MODEL_TYPES.values() for p in cls._param_names()}
    unknown = sorted(set(options) - known)
    if unknown:
        raise TypeError(f"no model type takes the option(s) {', '.join(unknown)}")
    if "fallbacks" in options:
        check_fallback_policy(options["fallbacks"], file=where, column="option --fallbacks")
    if model_type in ("hybrid", "calibrated") and features not in ("eq13", "dynamic"):
        raise InputError(
            f"--model {model_type} takes --features eq13 or dynamic, not {features!r}",
            file=where,
            column="option --features",
        )
    if model_type == "dynamic" and features != "eq13":
        raise InputError(
            "--model dynamic uses eq13 plus filtered temperatures: give --features eq13",
            file=where,
            column="option --features",
        )
    cls = _MODEL_TYPES[model_type]
    takes = set(cls._param_names())
    params = {k: v for k, v in options.items() if k in takes}
    if "machine" in takes:
        params["machine"] = resolve_machine(machine) if model_type in _CHAIN_TYPES else machine
    if "features" in takes:
        params["features"] = features
    return cls(**params)


def fit_from_cli(
    model_type,
    campaigns,
    *,
    machine=None,
    features="eq13",
    stepwise=False,
    direction="both",
    p_enter=0.05,
    p_remove=0.10,
    max_terms=None,
    roles=None,
    zero_window_s=10.0,
    fallbacks="loo",
):
    """``fbgcomp fit --model kinematic|hybrid|calibrated|dynamic``: check the options, fit on
    ``campaigns``, return the fitted model (:func:`make_estimator`, then ``fit``)."""
    model = make_estimator(
        model_type,
        machine=machine,
        features=features,
        stepwise=stepwise,
        direction=direction,
        p_enter=p_enter,
        p_remove=p_remove,
        max_terms=max_terms,
        roles=roles,
        zero_window_s=zero_window_s,
        fallbacks=fallbacks,
    )
    return model.fit(campaigns)
