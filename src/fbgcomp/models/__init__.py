"""TTP-deviation models (paper eq. 11-13): features, regression, model types, policy and metrics.

The public API is re-exported here: the model types (:class:`MRAModel`, :class:`KinematicModel`,
:class:`HybridModel`, :class:`CalibratedModel`, :class:`DynamicModel`, :class:`PhysicalModel`),
the one loader :func:`load_model` and factory :func:`make_estimator`, and the model-file base
:class:`ModelFile`. Layers, lowest first: :mod:`~fbgcomp.models.features`,
:mod:`~fbgcomp.models.regression`, :mod:`~fbgcomp.models.filters`, :mod:`~fbgcomp.models.policy`,
:mod:`~fbgcomp.models.metrics`, :mod:`~fbgcomp.models.modelfile`; :mod:`~fbgcomp.models.base` (what
every type shares) and :mod:`~fbgcomp.models.machines`; the type modules, each importing only
those; :mod:`~fbgcomp.models.registry`, which imports every type; and the users of the registry
(:mod:`~fbgcomp.models.fe_calibrated`, :mod:`~fbgcomp.models.compare`).
"""

from fbgcomp.models.base import ModelFile, Predictor
from fbgcomp.models.calibrated import CalibratedModel
from fbgcomp.models.dynamic import DynamicModel
from fbgcomp.models.hybrid import HybridModel
from fbgcomp.models.kinematic import KinematicModel
from fbgcomp.models.mra import MRAModel
from fbgcomp.models.physical import PhysicalModel
from fbgcomp.models.registry import MODEL_TYPES, load_model, make_estimator, register_model_type

__all__ = [
    "MODEL_TYPES",
    "CalibratedModel",
    "DynamicModel",
    "HybridModel",
    "KinematicModel",
    "MRAModel",
    "ModelFile",
    "PhysicalModel",
    "Predictor",
    "load_model",
    "make_estimator",
    "register_model_type",
]
