"""Finite-element digital twin of the CFRP ram (paper sections 2.3-2.4).

``load_machine`` reads the machine description (YAML, validated); ``Twin`` meshes and assembles the
ram once and exposes static tool-tip loads and thermal campaigns as linear operators.
"""

from fbgcomp.structure.machine import Machine, load_machine, parse_machine
from fbgcomp.structure.twin import (Influence, PathInfluence, StaticResponse,
                                    TemperatureLoadResponse, ThermalResponse, Twin)

__all__ = ["Machine", "load_machine", "parse_machine", "Twin", "Influence", "PathInfluence",
           "StaticResponse", "ThermalResponse", "TemperatureLoadResponse"]
