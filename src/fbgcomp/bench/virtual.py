"""Virtual test bench: scenarios run on the FE twin, measured by simulated instruments.

A scenario (YAML, see ``data/scenarios/``) describes what happens to the machine — ambient
temperature history, spindle heat duty cycles, radiant load, forces held at the tool tip, the
Z-axis position — and how it is measured. The twin (:mod:`fbgcomp.structure`) gives the true
sensor-path elongations, sensor temperatures, probe temperatures and TTP displacement; the
measurement layer then does what real instruments do, each on its own clock:

* interrogator: the bonded-FBG wavelength (paper eq. 2-4, :func:`fbgcomp.optics.wavelength_nm`)
  from the path's total elongation and the grating's own temperature taken from the FE field
  (not from a probe), an installation offset of the initial wavelength, ~1 pm white noise and an
  optional slow drift;
* temperature probes: the FE temperature at the probe point plus a fixed calibration offset
  (±0.3 °C), 0.1 °C noise and 0.1 °C quantisation;
* interferometer: the TTP displacement since the start plus 0.05 µm noise;
* load cell: the applied force plus noise.

The output is a campaign folder in exactly the format :mod:`fbgcomp.io.campaign` reads.
"""

from __future__ import annotations

from datetime import UTC, datetime, timedelta
from importlib import resources
from pathlib import Path
from typing import Literal

import numpy as np
import pandas as pd
import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from fbgcomp import optics
from fbgcomp.errors import InputError
from fbgcomp.io.campaign import Campaign, CampaignMeta
from fbgcomp.units import AXES


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid")


class Cycle(_Strict):
    """A sinusoidal component: ``amplitude * sin(2 pi (t - phase) / period)``."""

    amplitude: float
    period_h: float = Field(gt=0)
    phase_h: float = 0.0


class RandomPart(_Strict):
    """A smooth random component (Gaussian-filtered white noise), seeded by the run's seed."""

    sd: float = Field(ge=0)
    correlation_h: float = Field(gt=0)


class Duty(_Strict):
    """Level ``level`` between ``start_h`` and ``end_h``, optionally switched on/off in cycles."""

    start_h: float
    end_h: float
    level: float
    on_min: float | None = Field(default=None, gt=0)
    off_min: float | None = Field(default=None, ge=0)


class History(_Strict):
    """A scalar input history: base + piecewise-linear knots + cycles + duty + random part."""

    base: float = 0.0
    knots_h: list[tuple[float, float]] = []  # (time h, value) added, linearly interpolated
    cycles: list[Cycle] = []
    duty: list[Duty] = []
    edge_s: float = Field(default=120.0, ge=0)  # duty switching is smoothed over this time
    random: RandomPart | None = None

    def sample(self, time_s: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """The history at ``time_s`` (s), its random part drawn from ``rng``."""
        t_h = time_s / 3600.0
        out = np.full_like(time_s, self.base, dtype=float)
        if self.knots_h:
            k = np.array(self.knots_h, dtype=float)
            out += np.interp(t_h, k[:, 0], k[:, 1])
        for c in self.cycles:
            out += c.amplitude * np.sin(2 * np.pi * (t_h - c.phase_h) / c.period_h)
        for d in self.duty:
            on = (t_h >= d.start_h) & (t_h < d.end_h)
            if d.on_min is not None:
                period_h = (d.on_min + (d.off_min or 0.0)) / 60.0
                on &= ((t_h - d.start_h) % period_h) < d.on_min / 60.0
            out += d.level * _smooth_edges(on.astype(float), time_s, self.edge_s)
        if self.random is not None and self.random.sd > 0:
            out += _smooth_noise(time_s, self.random.sd, self.random.correlation_h * 3600.0, rng)
        return out


class LoadStep(_Strict):
    """A force (N, X Y Z) held at the TTP for ``hold_s``."""

    force_N: tuple[float, float, float]
    hold_s: float = Field(gt=0)


class Fbg(_Strict):
    """The simulated interrogator: sample step, clock offset, noise, drift, installation offset."""

    dt_s: float = Field(default=1.0, gt=0)
    clock_offset_s: float = 0.0
    noise_nm: float = Field(default=0.001, ge=0)  # ~1 pm, ≈ 0.8 µε at 1550 nm
    drift_nm_per_h: float = 0.0  # slow interrogator drift (per channel, random sign)
    install_offset_nm: float = Field(default=0.3, ge=0)  # initial wavelength = lambda0 ± this (pre-strain)


class Probes(_Strict):
    """The simulated temperature probes: sample step, clock offset, calibration offset, noise,
    quantisation."""

    dt_s: float = Field(default=10.0, gt=0)
    clock_offset_s: float = 0.0
    offset_C: float = Field(default=0.3, ge=0)  # fixed calibration offset, uniform ±
    noise_C: float = Field(default=0.1, ge=0)
    quantum_C: float = Field(default=0.1, ge=0)


class Interferometer(_Strict):
    """The simulated TTP reference: sample step, clock offset, noise."""

    dt_s: float = Field(default=1.0, gt=0)
    clock_offset_s: float = 0.0
    noise_um: float = Field(default=0.05, ge=0)


class LoadCell(_Strict):
    """The simulated load cell: sample step, clock offset, noise."""

    dt_s: float = Field(default=1.0, gt=0)
    clock_offset_s: float = 0.0
    noise_N: float = Field(default=1.0, ge=0)


class Instruments(_Strict):
    """How a scenario is measured: one entry per simulated instrument."""

    fbg: Fbg = Fbg()
    probes: Probes = Probes()
    interferometer: Interferometer = Interferometer()
    load_cell: LoadCell = LoadCell()


class Scenario(_Strict):
    """What happens to the machine and how it is measured (every field has a unit in its name)."""

    name: str
    kind: Literal["thermal", "static", "combined"]
    description: str = ""
    duration_h: float | None = Field(default=None, gt=0)  # static: from the load steps
    rest_s: float = Field(default=600.0, ge=0)  # nothing changes for this long at the start
    solver_dt_s: float = Field(default=1.0, gt=0)  # step of the FE history
    z_axis_mm: float | None = None
    initial_C: float = 30.0
    ambient_C: History = History(base=0.0)  # added to initial_C
    spindle_W: History = History()
    radiant_W_per_m2: History = History()
    loads: list[LoadStep] = []
    load_start_h: float = 0.0  # loads start after rest_s + this
    load_ramp_s: float = Field(default=2.0, ge=0)
    instruments: Instruments = Instruments()

    def compressed(self, hours: float) -> Scenario:
        """The same histories squeezed into ``hours``: every time in the inputs (temperature and
        heat histories, load start and hold times) scaled by the same factor."""
        if self.duration_h is None or self.duration_h <= hours:
            return self
        scale = hours / self.duration_h
        data = self.model_dump()
        data["duration_h"] = hours
        for key in ("ambient_C", "spindle_W", "radiant_W_per_m2"):
            h = data[key]
            h["knots_h"] = [(t * scale, v) for t, v in h["knots_h"]]
            for d in h["duty"]:
                d["start_h"] *= scale
                d["end_h"] *= scale
                for k in ("on_min", "off_min"):
                    if d[k]:
                        d[k] *= scale
            for c in h["cycles"]:
                c["period_h"] *= scale
                c["phase_h"] *= scale
            if h["random"]:
                h["random"]["correlation_h"] *= scale
        data["load_start_h"] *= scale
        for step in data["loads"]:
            step["hold_s"] *= scale
        return type(self).model_validate(data)

    def duration_s(self) -> float:
        """Length of the scenario, s: ``duration_h``, else the rest, the load start and the
        load steps plus a minute."""
        if self.duration_h is not None:
            return self.duration_h * 3600.0
        return self.rest_s + self.load_start_h * 3600.0 + sum(s.hold_s for s in self.loads) + 60.0


BUILTIN_SCENARIOS = ("static-y", "static-xyz", "thermal-36h", "thermal-36h-b", "combined")


def load_scenario(name_or_path) -> Scenario:
    """A built-in scenario by name, or a scenario YAML file; InputError names the field."""
    path = Path(str(name_or_path))
    if str(name_or_path) in BUILTIN_SCENARIOS and not path.exists():
        text = resources.files("fbgcomp").joinpath("data", "scenarios", f"{name_or_path}.yaml").read_text()
        where = f"<built-in scenario {name_or_path}>"
    else:
        if not path.is_file():
            raise InputError(
                f"no such scenario file (built-in scenarios: {', '.join(BUILTIN_SCENARIOS)})", file=path
            )
        text, where = path.read_text(encoding="utf-8"), str(path)
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        line = getattr(getattr(exc, "problem_mark", None), "line", None)
        raise InputError(
            f"invalid YAML: {getattr(exc, 'problem', exc)}", file=where, row=None if line is None else line
        ) from None
    try:
        return Scenario.model_validate(data)
    except ValidationError as exc:
        err = exc.errors()[0]
        field = ".".join(str(p) for p in err["loc"])
        raise InputError(err["msg"], file=where, column=f"field {field}") from None


def _smooth_edges(values, time_s, edge_s):
    """Soften on/off switching over ``edge_s`` (a moving average), so heat inputs ramp."""
    if edge_s <= 0 or len(time_s) < 2:
        return values
    dt = float(np.median(np.diff(time_s)))
    n = max(1, round(edge_s / dt))
    if n == 1:
        return values
    kernel = np.ones(n) / n
    padded = np.concatenate([np.full(n, values[0]), values, np.full(n, values[-1])])
    return np.convolve(padded, kernel, mode="same")[n:-n]


def _smooth_noise(time_s, sd, correlation_s, rng):
    """Stationary smooth noise of standard deviation ``sd`` and correlation time ``correlation_s``."""
    grid_dt = max(correlation_s / 20.0, float(time_s[1] - time_s[0]) if len(time_s) > 1 else 1.0)
    grid = np.arange(time_s[0] - 4 * correlation_s, time_s[-1] + 4 * correlation_s + grid_dt, grid_dt)
    white = rng.standard_normal(len(grid))
    half = int(np.ceil(3 * correlation_s / grid_dt))
    k = np.exp(-0.5 * (np.arange(-half, half + 1) * grid_dt / correlation_s) ** 2)
    smooth = np.convolve(white, k / np.sqrt(np.sum(k**2)), mode="same")
    return sd * np.interp(time_s, grid, smooth)


def force_history_N(scenario: Scenario, time_s: np.ndarray) -> np.ndarray:
    """Applied TTP force (n, 3) in N: each step held, with a short linear ramp between steps."""
    if not scenario.loads:
        return np.zeros((len(time_s), 3))
    t0 = scenario.rest_s + scenario.load_start_h * 3600.0
    knots_t, knots_f = [0.0, t0], [np.zeros(3), np.zeros(3)]
    t = t0
    for step in scenario.loads:
        knots_t += [t + scenario.load_ramp_s, t + step.hold_s]
        knots_f += [np.array(step.force_N), np.array(step.force_N)]
        t += step.hold_s
    knots_t.append(t + scenario.load_ramp_s)
    knots_f.append(np.zeros(3))
    kt, kf = np.array(knots_t), np.array(knots_f)
    return np.column_stack([np.interp(time_s, kt, kf[:, j]) for j in range(3)])


def true_response(twin, scenario: Scenario, seed: int = 0):
    """The twin's noise-free history on the solver grid.

    Returns a dict with ``time_s``, ``sensor_elongation_um`` (n, S) total host elongation since
    the start, ``sensor_temperature_C`` (n, S), ``probe_C`` (n, P, ambient included),
    ``ttp_um`` (n, 3) since the start, ``force_N`` (n, 3), ``ambient_C`` (n,).
    """
    rng = np.random.default_rng([seed, 1])
    duration = scenario.duration_s()
    time_s = np.arange(0.0, duration + scenario.solver_dt_s / 2, scenario.solver_dt_s)
    moving = np.maximum(time_s - scenario.rest_s, 0.0)
    ambient = scenario.initial_C + scenario.ambient_C.sample(moving, rng)
    spindle = np.maximum(scenario.spindle_W.sample(moving, rng), 0.0)
    radiant = np.maximum(scenario.radiant_W_per_m2.sample(moving, rng), 0.0)
    # Before rest_s nothing moves: hold the inputs at their first value.
    at_rest = time_s < scenario.rest_s
    ambient[at_rest], spindle[at_rest], radiant[at_rest] = ambient[~at_rest][0], 0.0, 0.0
    force = force_history_N(scenario, time_s)

    S, P = len(twin.sensor_names), len(twin.probe_names)
    quiet = np.ptp(ambient) == 0 and not spindle.any() and not radiant.any()
    if quiet:
        elong = np.zeros((len(time_s), S))
        sensor_t = np.full((len(time_s), S), scenario.initial_C)
        probe_t = np.full((len(time_s), P), scenario.initial_C)
        ttp = np.zeros((len(time_s), 3))
    else:
        kinds = {h.kind for h in twin.machine.thermal.sources}
        for field, kind, v in (("spindle_W", "volume", spindle), ("radiant_W_per_m2", "radiant", radiant)):
            if v.any() and kind not in kinds:
                raise InputError(
                    f"the scenario drives a {kind} heat source, which the machine description does not "
                    "declare (add one under thermal.heat_sources, or leave this history out)",
                    file=f"<scenario {scenario.name}>",
                    column=f"field {field}",
                )
        h = twin.thermal(time_s, ambient, spindle, radiant_W_per_m2=radiant, initial_C=scenario.initial_C)
        elong = np.asarray(h.sensor_elongation_um)
        sensor_t = np.asarray(h.sensor_temperature_C)
        probe_t = _probe_matrix(h.probe_C, twin.probe_names)
        ttp = np.asarray(h.ttp_um)
    if force.any():
        st = twin.static(force)
        elong = elong + np.asarray(st.sensor_elongation_um)
        ttp = ttp + np.asarray(st.ttp_um)
    return {
        "time_s": time_s,
        "sensor_elongation_um": elong - elong[0],
        "sensor_temperature_C": sensor_t,
        "probe_C": probe_t,
        "ttp_um": ttp - ttp[0],
        "force_N": force,
        "ambient_C": ambient,
    }


def _probe_matrix(probe_C, names):
    if isinstance(probe_C, dict):
        return np.column_stack([np.asarray(probe_C[n], dtype=float) for n in names])
    return np.asarray(probe_C, dtype=float)


def _clock(duration_s, dt_s, offset_s):
    start = offset_s % dt_s
    return np.arange(start, duration_s + 1e-9, dt_s)


def _at(t_new, t, values):
    values = np.asarray(values, dtype=float)
    if values.ndim == 1:
        return np.interp(t_new, t, values)
    return np.column_stack([np.interp(t_new, t, values[:, j]) for j in range(values.shape[1])])


def measure(machine, scenario: Scenario, truth: dict, seed: int = 0, start=None):
    """Turn the twin's true history into a :class:`~fbgcomp.io.campaign.Campaign` (measurement layer)."""
    rng = np.random.default_rng([seed, 2])
    inst = scenario.instruments
    t, duration = truth["time_s"], truth["time_s"][-1]
    sensors = machine.sensors
    S = len(sensors)

    # Interrogator: the grating sees the host elongation and its own temperature (FE field).
    f = inst.fbg
    t_fbg = _clock(duration, f.dt_s, f.clock_offset_s)
    lam_init = np.array([s.lambda0_nm for s in sensors]) + rng.uniform(-1, 1, S) * f.install_offset_nm
    gauge = np.array([s.gauge_length for s in sensors])
    d_temp = _at(t_fbg, t, truth["sensor_temperature_C"] - truth["sensor_temperature_C"][0])
    lam = optics.wavelength_nm(
        _at(t_fbg, t, truth["sensor_elongation_um"]),
        lam_init,
        gauge,
        d_temp,
        photoelastic=np.array([s.photoelastic for s in sensors]),
        thermo_optic_per_K=np.array([s.thermo_optic_per_K for s in sensors]),
        fibre_cte_per_K=np.array([s.fibre_cte_per_K for s in sensors]),
    )
    lam += f.noise_nm * rng.standard_normal(lam.shape)
    lam += rng.choice([-1.0, 1.0], S) * f.drift_nm_per_h * (t_fbg[:, None] / 3600.0)
    fbg = pd.DataFrame(lam, columns=[f"{s.name}_nm" for s in sensors])
    fbg.insert(0, "time_s", t_fbg)
    # Strain-free reference gratings: the same gauge temperature, no strain (eq. 3).
    for j, s in enumerate(sensors):
        if s.reference_lambda0_nm is not None:
            lam_ref = optics.free_grating_wavelength_nm(
                d_temp[:, j],
                s.reference_lambda0_nm + rng.uniform(-1, 1) * f.install_offset_nm,
                thermo_optic_per_K=s.thermo_optic_per_K,
                fibre_cte_per_K=s.fibre_cte_per_K,
            )
            lam_ref = lam_ref + f.noise_nm * rng.standard_normal(lam_ref.shape)
            fbg[f"{s.name}_ref_nm"] = lam_ref

    # Probes: FE temperature + fixed offset + noise, quantised.
    p = inst.probes
    t_tmp = _clock(duration, p.dt_s, p.clock_offset_s)
    probes = list(machine.probes)
    true_p = _at(t_tmp, t, truth["probe_C"])
    if true_p.ndim == 1:
        true_p = true_p[:, None]
    read = (
        true_p + rng.uniform(-1, 1, len(probes)) * p.offset_C + p.noise_C * rng.standard_normal(true_p.shape)
    )
    if p.quantum_C > 0:
        read = np.round(read / p.quantum_C) * p.quantum_C
    temperatures = pd.DataFrame(read, columns=[f"{pr.name}_C" for pr in probes])
    temperatures.insert(0, "time_s", t_tmp)

    # Interferometer: TTP displacement since the start.
    i = inst.interferometer
    t_ref = _clock(duration, i.dt_s, i.clock_offset_s)
    ref = _at(t_ref, t, truth["ttp_um"]) + i.noise_um * rng.standard_normal((len(t_ref), 3))
    reference = pd.DataFrame(ref, columns=[f"{a}_um" for a in AXES])
    reference.insert(0, "time_s", t_ref)

    loads = None
    if truth["force_N"].any():
        lc = inst.load_cell
        t_load = _clock(duration, lc.dt_s, lc.clock_offset_s)
        fl = _at(t_load, t, truth["force_N"]) + lc.noise_N * rng.standard_normal((len(t_load), 3))
        loads = pd.DataFrame(fl, columns=["fx_N", "fy_N", "fz_N"])
        loads.insert(0, "time_s", t_load)

    meta = CampaignMeta(**campaign_meta(machine, scenario, seed, start))
    return Campaign.from_arrays(meta, fbg=fbg, temperatures=temperatures, reference=reference, loads=loads)


def campaign_meta(machine, scenario: Scenario, seed: int, start=None) -> dict:
    """campaign.yaml content for a simulated campaign."""

    def where(pr):
        if pr.kind == "ambient":
            return "ambient air"
        return f"FE point ({pr.x_mm:g}, {pr.y_mm:g}, {pr.z_mm:g}) mm"

    return {
        "name": scenario.name,
        "kind": scenario.kind,
        "description": scenario.description or f"virtual test bench: scenario {scenario.name}",
        "start": start or datetime(2026, 1, 12, 8, 0, tzinfo=UTC) + timedelta(days=seed % 365),
        "sensors": [
            {
                "name": s.name,
                "lambda0_nm": s.lambda0_nm,
                "gauge_length_mm": s.gauge_length,
                "photoelastic": s.photoelastic,
                "thermo_optic_per_K": s.thermo_optic_per_K,
                "fibre_cte_per_K": s.fibre_cte_per_K,
                "face": s.face,
                "z_start_mm": s.z_start_mm,
                "z_end_mm": s.z_end_mm,
                **({"depth_mm": s.depth_mm} if s.depth_mm else {}),
                "temperature_probe": s.temperature_probe,
                **(
                    {"reference_lambda0_nm": s.reference_lambda0_nm}
                    if s.reference_lambda0_nm is not None
                    else {}
                ),
            }
            for s in machine.sensors
        ],
        "temperature_probes": [{"name": pr.name, "location": where(pr)} for pr in machine.probes],
        "reference": {"instrument": "laser interferometer (simulated)", "point": "TTP", "units": "um"},
        "scenario": scenario.name,
        "seed": seed,
        "source": "fbgcomp virtual test bench",
        "z_axis_mm": scenario.z_axis_mm if scenario.z_axis_mm is not None else machine.supports.z_axis_mm,
    }


def simulate(machine, scenario: Scenario, seed: int = 0, twin=None):
    """Run a scenario on the twin and measure it: returns (Campaign, truth dict)."""
    if twin is None:
        from fbgcomp.structure import Twin  # noqa: PLC0415 - optional heavy extra: skfem (the fe extra)

        twin = Twin(machine, z_axis_mm=scenario.z_axis_mm)
    truth = true_response(twin, scenario, seed)
    return measure(machine, scenario, truth, seed), truth
