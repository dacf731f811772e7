"""Finite-element digital twin of the CFRP ram (paper sections 2.3-2.4).

``load_machine`` reads the machine description (YAML, validated); ``Twin`` meshes and assembles the
ram once and exposes static tool-tip loads and thermal campaigns as linear operators. The twin
needs scikit-fem (the ``fe`` extra); the machine description does not, so the twin's names are
imported on first use.
"""

from fbgcomp.structure.machine import Machine, load_machine, parse_machine

_TWIN_NAMES = (
    "Twin",
    "Influence",
    "PathInfluence",
    "StaticResponse",
    "ThermalResponse",
    "TemperatureLoadResponse",
)

__all__ = ["Machine", "load_machine", "parse_machine", *_TWIN_NAMES]


def __getattr__(name):
    if name in _TWIN_NAMES:
        from fbgcomp.structure import twin  # noqa: PLC0415 - optional heavy extra: skfem (the fe extra)

        return getattr(twin, name)
    raise AttributeError(f"module 'fbgcomp.structure' has no attribute {name!r}")
