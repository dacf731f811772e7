"""Thermal scenarios of the twin: the population a default model learns thermal physics from.

Measured campaigns cannot teach what a face-to-face gradient does to the TTP when no training
campaign heats one face more than the opposite one (ram2's ``thermal_a`` never does). The twin
of the machine description can: this module drives it with a generic, seeded design of heat
inputs that every ram sees in a shop, whatever its data sheet declares:

* the ambient: a day cycle of random phase and amplitude plus a slow random walk;
* every declared volume source (spindle bearings): duty cycles of random levels and lengths;
* a radiant load on each of the four outer faces (sun through a window, a neighbouring
  machine, a hall heater): occasional half-sine pulses of random height and width;
* every declared radiant source: the same kind of pulses.

The scenarios are not fitted to any measured campaign; they are a prior over thermal states.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fbgcomp.structure.machine import FACES, Machine, parse_machine

#: Name prefix of the undeclared sources :func:`generic_heat_machine` adds.
GENERIC_PREFIX = "generic_"


def generic_heat_machine(machine: Machine, flux_W_per_m2: float = 60.0) -> Machine:
    """``machine`` with one whole-face radiant source per outer face added to its declared
    heat sources (names ``generic_radiant_pX`` ...)."""
    d = machine.model_dump()
    # the effective sources: a description without heat_sources has the default two
    sources = [h.model_dump() for h in machine.thermal.sources]
    for face in FACES:
        tag = ("p" if face[0] == "+" else "m") + face[1]
        sources.append(
            {
                "name": f"{GENERIC_PREFIX}radiant_{tag}",
                "kind": "radiant",
                "face": face,
                "z_mm": None,
                "absorptivity": 1.0,
                "nominal_W_per_m2": flux_W_per_m2,
            }
        )
    d["thermal"]["heat_sources"] = sources
    return parse_machine(d)


@dataclass(frozen=True)
class ScenarioDesign:
    """Ranges of the generic heat-input design (defaults: a shop floor)."""

    duration_s: float = 36 * 3600.0
    step_s: float = 60.0
    ambient_day_amplitude_K: float = 1.5
    ambient_walk_K: float = 0.5
    duty_fraction_levels: tuple[float, ...] = (0.0, 0.33, 0.5, 0.75, 1.0, 1.25)
    duty_steps: tuple[int, int] = (20, 240)  # length of a duty level, in steps
    radiant_peak_W_per_m2: float = 120.0
    radiant_probability: float = 0.5  # chance that a face sees a pulse at all
    radiant_width_steps: tuple[int, int] = (60, 600)

    @property
    def mean_duty_fraction(self) -> float:
        """The duty levels' mean: a volume source runs at this fraction of its nominal power on
        average over the scenarios."""
        return float(np.mean(self.duty_fraction_levels))


def _day_cycle(rng, t, design):
    amp = design.ambient_day_amplitude_K
    period = 86400.0 * rng.uniform(0.8, 1.2)
    x = amp * np.sin(2 * np.pi * t / period + rng.uniform(0, 2 * np.pi))
    walk = np.cumsum(rng.normal(0.0, 1.0, t.size))
    k = np.exp(-np.arange(150) / 30.0)
    walk = np.convolve(walk, k / k.sum())[: t.size]
    walk = design.ambient_walk_K * (walk - walk[0]) / max(np.std(walk), 1e-9)
    x = x + walk
    return x - x[0]


def _duty(rng, n, nominal, design):
    out = np.zeros(n)
    i = 0
    lo, hi = design.duty_steps
    while i < n:
        k = int(rng.integers(lo, hi))
        out[i : i + k] = nominal * rng.choice(design.duty_fraction_levels)
        i += k
    return out


def _pulses(rng, n, design):
    out = np.zeros(n)
    if rng.random() >= design.radiant_probability:
        return out
    lo, hi = design.radiant_width_steps
    c, w = int(rng.integers(0, n)), int(rng.integers(lo, hi))
    idx = np.arange(max(0, c - w // 2), min(n, c + w // 2))
    out[idx] = rng.uniform(0, design.radiant_peak_W_per_m2) * np.sin(np.pi * (idx - c + w // 2) / w)
    return out


def thermal_scenarios(
    twin,
    n_scenarios: int = 40,
    seed: int = 0,
    design: ScenarioDesign = ScenarioDesign(),
    nominal_W=None,
    parts: bool = False,
):
    """Yield ``(inputs, ThermalResponse)`` for ``n_scenarios`` seeded scenarios of ``twin``
    (built on :func:`generic_heat_machine`), each from the uniform reference temperature;
    with ``parts``, ``(inputs, (ThermalResponse, parts))`` with the response per unit expansion
    coefficient of each material (:meth:`~fbgcomp.structure.twin.Twin.thermal_parts`).

    ``nominal_W`` ({volume source name: W}) sets the power a source's duty levels scale with in
    place of its declared ``nominal_W`` (for one a training campaign showed)."""
    given = dict(nominal_W or {})
    rng = np.random.default_rng(seed)
    machine = twin.machine
    Tref = machine.reference_temperature_C
    t = np.arange(0.0, design.duration_s + design.step_s / 2, design.step_s)
    for _ in range(n_scenarios):
        heat = {}
        for h in machine.thermal.sources:
            if h.kind == "volume":
                heat[h.name] = _duty(rng, t.size, given.get(h.name) or h.nominal_W or 100.0, design)
            else:
                heat[h.name] = _pulses(rng, t.size, design)
        ambient = Tref + _day_cycle(rng, t, design)
        inputs = {"time_s": t, "ambient_C": ambient, "heat": heat}
        if parts:
            yield inputs, twin.thermal_parts(t, ambient, heat=heat, initial_C=Tref)
        else:
            yield inputs, twin.thermal(t, ambient, heat=heat, initial_C=Tref)
