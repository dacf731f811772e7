"""The machine description as the model types take it.

:func:`resolve_machine` accepts what a user gives (a :class:`~fbgcomp.structure.Machine`, the path
of a YAML description, or None for the built-in ram) and :func:`campaign_sensor_specs` turns the
description's gratings into the campaign's :class:`~fbgcomp.io.campaign.SensorSpec`, the sensor
record every model file stores. It lives here, not in :mod:`fbgcomp.structure`, because the
structure layer does not know campaigns (:mod:`fbgcomp.io`), and the models are the first layer
that knows both.
"""

from __future__ import annotations

from fbgcomp.io.campaign import SensorSpec
from fbgcomp.structure.machine import Machine, load_machine


def resolve_machine(machine) -> Machine:
    """The machine description ``machine`` names: a Machine as is, a path (str, bytes or
    path-like) read with :func:`~fbgcomp.structure.load_machine`, None the built-in ram;
    TypeError for anything else. A bad description fails here (InputError), before any fit."""
    if machine is None or isinstance(machine, (str, bytes)) or hasattr(machine, "__fspath__"):
        return load_machine(machine)
    if isinstance(machine, Machine):
        return machine
    raise TypeError("machine must be a Machine, a path or None (the built-in ram)")


def campaign_sensor_specs(machine: Machine) -> list:
    """The machine description's gratings as campaign sensor records (``SensorSpec``), in order."""
    return [
        SensorSpec(
            name=s.name,
            lambda0_nm=s.lambda0_nm,
            gauge_length_mm=s.gauge_length,
            photoelastic=s.photoelastic,
            thermo_optic_per_K=s.thermo_optic_per_K,
            fibre_cte_per_K=s.fibre_cte_per_K,
            face=s.face,
            z_start_mm=s.z_start_mm,
            z_end_mm=s.z_end_mm,
            depth_mm=s.depth_mm or None,
            temperature_probe=s.temperature_probe,
        )
        for s in machine.sensors
    ]
