"""Before buying hardware: what TTP accuracy can this layout and this interrogator give?

``fbgcomp plan`` answers it from the machine description alone, on the figure sensor placement
already optimises (:mod:`fbgcomp.structure.placement`): the FE twin's elementary load design
(:data:`fbgcomp.models.fe_calibrated.LOAD_CASES`: 4000 N at the TTP along X, Y, Z; a 5 K uniform rise, 1 K
gradients across X, Y and along Z, a 5 K housing rise), the eq. 11 estimator a campaign would
give on random combinations of them with the interrogator's noise, and per axis its
**predicted worst-case TTP error**

    loads_noise = max_c |T - E B|_c + 2 sqrt(sum_s B_s^2 sigma_s^2)           (µm)

(what the gratings cannot explain plus twice the noise the estimator passes on), exactly
:func:`fbgcomp.structure.placement.predicted_error_um`. To it the plan adds the **thermal compensation
error** of the same design's temperature fields, which placement leaves out because it works on
the host's true elongations:

* a grating compensated by a probe (``temperature_probe``) reads a false elongation
  ``e_K (T_gauge - T_probe)`` where its gauge and the probe differ (``e_K``: the elongation a
  grating 1 K warmer than its compensation reads, paper eq. 2-4; about 5 µm/K over 600 mm of
  CFRP); through the estimator it moves the TTP by ``F B`` (worst case over the thermal cases);
* a grating with a strain-free reference beside it (``reference_lambda0_nm``) has no mismatch but
  the reference's own wavelength noise, ``sigma / (dlambda/dT)`` K (eq. 3), becomes elongation
  noise ``e_K sigma_T`` passed on as above (2 sigma).

The sum is a bound (the worst cases are added, not combined), compared with the user's target
per axis. What would close a gap is computed, not guessed: the interrogator noise the axis
would need, the figure with a reference grating beside every sensor, and the best layouts of
more paths chosen by :func:`fbgcomp.structure.placement.choose` on the machine's candidate paths or a
grid.

What the figure does not cover: transients (a probe that sees the spindle's heat late: on ram2
that alone leaves 3.6 µm of dz, docs/accuracy.md), heat the design's fields do not contain, the
twin's own model error and the reference instrument. It is a floor to compare a target with
before buying, not the accuracy a campaign will measure.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

import numpy as np

from fbgcomp import optics
from fbgcomp.errors import InputError
from fbgcomp.optics import elongation_noise_um
from fbgcomp.structure.loadcases import LOAD_CASES, load_case_responses
from fbgcomp.structure.placement import (
    PlacementDesign,
    candidate_grid,
    choose,
    predicted_error_um,
    sensor_pool,
)
from fbgcomp.tables import Column, format_number, format_table, text
from fbgcomp.units import AXES


def false_elongation_per_K_um(sensors) -> np.ndarray:
    """Elongation (µm) a bonded grating reads when its gauge is 1 K warmer than the temperature
    its compensation uses (paper eq. 2-4), per sensor (S,)."""
    lam0 = np.array([s.lambda0_nm for s in sensors], dtype=float)
    gauge = np.array([s.gauge_length for s in sensors], dtype=float)
    consts = dict(
        photoelastic=np.array([s.photoelastic for s in sensors], dtype=float),
        thermo_optic_per_K=np.array([s.thermo_optic_per_K for s in sensors], dtype=float),
        fibre_cte_per_K=np.array([s.fibre_cte_per_K for s in sensors], dtype=float),
    )
    warm = optics.wavelength_nm(np.zeros_like(lam0), lam0, gauge, 1.0, **consts)
    return optics.elongation_um(warm, lam0, gauge, 0.0, **consts)


def reference_temperature_noise_K(sensors, wavelength_noise_nm=0.001) -> np.ndarray:
    """Temperature noise (K, SD) of a strain-free reference grating beside each sensor (eq. 3):
    the interrogator's wavelength noise over the free grating's sensitivity. A sensor without a
    declared ``reference_lambda0_nm`` is given one at its own wavelength."""
    lam = np.array([s.reference_lambda0_nm or s.lambda0_nm for s in sensors], dtype=float)
    sens = optics.temperature_sensitivity_nm_per_K(
        lam,
        thermo_optic_per_K=np.array([s.thermo_optic_per_K for s in sensors], dtype=float),
        fibre_cte_per_K=np.array([s.fibre_cte_per_K for s in sensors], dtype=float),
    )
    return wavelength_noise_nm / sens


def probe_mismatch_K(sensor_temperature_C, probe_C, sensors, probe_names, *, references=None):
    """Gauge temperature minus compensating temperature per load case and sensor (C, S), K.

    ``references`` (S,) bool: the sensor is compensated by a strain-free grating on its own gauge
    (mismatch 0); default: the sensors that declare ``reference_lambda0_nm``. A sensor with
    neither a reference nor a probe is uncompensated (its whole gauge temperature).
    """
    st = np.asarray(sensor_temperature_C, dtype=float)
    pc = np.asarray(probe_C, dtype=float)
    if references is None:
        references = np.array([s.reference_lambda0_nm is not None for s in sensors])
    out = np.empty_like(st)
    for j, s in enumerate(sensors):
        if references[j]:
            out[:, j] = 0.0
        elif s.temperature_probe:
            out[:, j] = st[:, j] - pc[:, list(probe_names).index(s.temperature_probe)]
        else:
            out[:, j] = st[:, j]
    return out


def estimator(elongation_um, ttp_um, noise_um) -> np.ndarray:
    """The eq. 11 map (S, 3) of :func:`fbgcomp.structure.placement.predicted_error_um`:
    ``B = (E'E + N)^-1 E'T`` with N the elongation noise variances."""
    E = np.asarray(elongation_um, dtype=float)
    noise = np.asarray(noise_um, dtype=float)
    return np.linalg.solve(E.T @ E + np.diag(noise**2), E.T @ np.asarray(ttp_um, dtype=float))


@dataclass
class PlanDesign:
    """The placement design plus the temperatures the thermal cases put on gauges and probes."""

    design: PlacementDesign
    sensor_temperature_C: np.ndarray  # (cases, N) mean gauge temperature rise
    probe_C: np.ndarray  # (cases, P) probe rises (ambient 0)
    probe_names: list
    wavelength_noise_nm: float


def plan_design(
    machine, candidates=(), *, twin=None, resolution=None, z_axis_mm=None, wavelength_noise_nm=0.001
) -> PlanDesign:
    """One FE twin with the machine's sensors (first, in order) and the candidate paths."""
    from fbgcomp.structure import Twin  # noqa: PLC0415 - optional heavy extra: skfem (the fe extra)

    pool, m = sensor_pool(machine, candidates)
    # load cases only (static forces and temperature fields): no reduced thermal model
    twin = twin or Twin(m, resolution=resolution, z_axis_mm=z_axis_mm, reduce_thermal=False)
    cases = load_case_responses(twin)
    design = PlacementDesign(
        [s.name for s in pool],
        cases["names"],
        np.asarray(cases["sensor_elongation_um"]),
        np.asarray(cases["ttp_um"]),
        elongation_noise_um(pool, wavelength_noise_nm),
        pool,
    )
    return PlanDesign(
        design,
        np.asarray(cases["sensor_temperature_C"]),
        np.asarray(cases["probe_C"]),
        list(twin.probe_names),
        wavelength_noise_nm,
    )


def layout_error_um(pdes: PlanDesign, subset, *, noise_scale=1.0, references=None) -> dict:
    """Per-axis parts (3,) of the predicted worst-case TTP error of the paths ``subset``.

    ``noise_scale`` scales the interrogator's noise (the design's is ``pdes.wavelength_noise_nm``);
    ``references`` (len(subset),) bool overrides which sensors are compensated by a strain-free
    grating. Returns ``unexplained_um``, ``noise_um`` (2 sigma), ``loads_noise_um`` (their sum:
    placement's objective), ``probe_mismatch_um``, ``reference_noise_um`` (2 sigma),
    ``thermal_um`` and ``total_um``.
    """
    d = pdes.design
    idx = list(subset)
    sensors = [d.sensors[i] for i in idx]
    E, T = d.elongation_um[:, idx], d.ttp_um
    noise = d.noise_um[idx] * noise_scale
    B = estimator(E, T, noise)
    unexplained = np.max(np.abs(T - E @ B), axis=0)
    noise_part = 2 * np.sqrt(np.sum(B**2 * noise[:, None] ** 2, axis=0))
    if references is None:
        references = np.array([s.reference_lambda0_nm is not None for s in sensors])
    references = np.asarray(references, dtype=bool)
    e_K = false_elongation_per_K_um(sensors)
    mismatch = probe_mismatch_K(
        pdes.sensor_temperature_C[:, idx], pdes.probe_C, sensors, pdes.probe_names, references=references
    )
    probe_part = np.max(np.abs((mismatch * e_K) @ B), axis=0)
    ref_sd_um = np.where(
        references, e_K * reference_temperature_noise_K(sensors, pdes.wavelength_noise_nm * noise_scale), 0.0
    )
    ref_part = 2 * np.sqrt(np.sum(B**2 * ref_sd_um[:, None] ** 2, axis=0))
    loads_noise = unexplained + noise_part
    thermal = probe_part + ref_part
    return {
        "unexplained_um": unexplained,
        "noise_um": noise_part,
        "loads_noise_um": loads_noise,
        "probe_mismatch_um": probe_part,
        "reference_noise_um": ref_part,
        "thermal_um": thermal,
        "total_um": loads_noise + thermal,
    }


def noise_scan(pdes: PlanDesign, subset, axis: int, *, floor_pm=1e-3, n=61):
    """The layout's total error on ``axis`` (µm) at interrogator noises from ``floor_pm`` to the
    design's, log-spaced: (noise_pm (n,), total_um (n,)). Not monotone: a quieter interrogator
    shrinks the noise passed on but lets the estimator trust the paths more, which amplifies
    the probe mismatch."""
    base_pm = pdes.wavelength_noise_nm * 1e3
    pm = np.geomspace(min(floor_pm, base_pm), base_pm, n)
    total = np.array([layout_error_um(pdes, subset, noise_scale=p / base_pm)["total_um"][axis] for p in pm])
    return pm, total


def noise_needed_pm(pdes: PlanDesign, subset, axis: int, target_um: float, *, floor_pm=1e-3):
    """Largest interrogator noise (pm) of :func:`noise_scan` at which ``axis`` meets the target,
    or None; and the best total (µm) the scan found with the noise it needs."""
    pm, total = noise_scan(pdes, subset, axis, floor_pm=floor_pm)
    ok = np.flatnonzero(total <= target_um)
    best = int(np.argmin(total))
    return (float(pm[ok[-1]]) if ok.size else None), float(total[best]), float(pm[best])


@dataclass
class AxisPlan:
    """One axis of the plan: the parts of its predicted worst-case TTP error (µm), whether it
    meets the target, and what would close a gap."""

    axis: str
    target_um: float
    unexplained_um: float
    noise_um: float
    loads_noise_um: float
    probe_mismatch_um: float
    reference_noise_um: float
    thermal_um: float
    total_um: float
    meets: bool
    meets_loads_noise: bool  # the placement figure alone (no compensation error)
    margin_um: float  # target - total: > 0 spare, < 0 missed by -margin
    noise_needed_pm: float | None  # largest scanned noise that meets the target
    best_noise_total_um: float | None  # the lowest total over the noise scan ...
    best_noise_pm: float | None  # ... and its noise
    with_references_um: float


@dataclass
class Plan:
    """The plan of a machine description's layout against a target (see the module docstring)."""

    machine: str
    sensors: list
    probes_compensating: dict
    wavelength_noise_pm: float
    target_um: float
    load_cases: list
    false_elongation_per_K_um: dict
    reference_temperature_noise_K: dict
    axes: list
    larger_layouts: list = field(default_factory=list)
    covers: str = (
        "TTP forces of 4000 N along X, Y, Z and steady temperature fields (5 K uniform, "
        "1 K gradients across X, Y and along Z, 5 K housing) on the machine description's "
        "FE twin; the interrogator's noise; the gratings' compensation error in those "
        "fields. Not transients (probe lag), not the twin's model error, not the "
        "reference instrument."
    )

    @property
    def meets(self) -> bool:
        """Every judged axis meets the target."""
        return all(a.meets for a in self.axes)

    def to_dict(self) -> dict:
        """The plan as plain data (for JSON), with :attr:`meets`."""
        out = asdict(self)
        out["meets"] = self.meets
        return out

    def format(self) -> str:
        """The plan for the console: per axis the parts of the predicted error against the
        target, what the thermal part covers, the verdict and what would close a gap."""
        lines = [
            f"plan for {self.machine}: {len(self.sensors)} gratings ({', '.join(self.sensors)}), "
            f"interrogator noise {self.wavelength_noise_pm:g} pm, target {self.target_um:g} µm",
            "predicted worst-case TTP error over the FE load design (eq. 11 estimator, as fbgcomp place):",
        ]
        rows = []
        for a in self.axes:
            verdict = (
                f"meets ({format_number(a.margin_um, 2)} µm spare)"
                if a.meets
                else f"MISSES by {format_number(-a.margin_um, 2)} µm"
                + (" (loads+noise alone would meet)" if a.meets_loads_noise else "")
            )
            rows.append(
                [
                    a.axis,
                    a.loads_noise_um,
                    a.unexplained_um,
                    a.noise_um,
                    a.thermal_um,
                    a.total_um,
                    a.target_um,
                    verdict,
                ]
            )
        lines.append(
            format_table(
                [text("axis")]
                + [
                    Column(name, "µm", 2)
                    for name in ("loads+noise", "unexplained", "noise 2σ", "thermal", "total", "target")
                ]
                + [text("verdict")],
                rows,
            )
        )
        comp = ", ".join(f"{s}: {how}" for s, how in self.probes_compensating.items())
        lines.append(
            "thermal = what the same eq. 11 map makes of the gratings' compensation error in "
            f"the design's temperature fields ({comp}; the paper's recipe: the default "
            "physical model reads the gratings' thermal signal instead, docs/accuracy.md); "
            "false elongation per K of gauge-to-probe mismatch: "
            + ", ".join(f"{s} {v:.2f}" for s, v in self.false_elongation_per_K_um.items())
            + " µm/K"
        )
        lines.append(f"covers: {self.covers}")
        missed = [a for a in self.axes if not a.meets]
        if not missed:
            lines.append(
                f"verdict: the layout meets {self.target_um:g} µm on "
                f"{', '.join(a.axis for a in self.axes)} in this design."
            )
            return "\n".join(lines)
        lines.append(
            f"verdict: misses {self.target_um:g} µm on {', '.join(a.axis for a in missed)}. "
            "What would help (computed on the same design):"
        )
        for a in missed:
            if a.noise_needed_pm is None:
                lines.append(
                    f"  {a.axis}: no interrogator noise from 0.001 pm to {self.wavelength_noise_pm:g} pm "
                    f"meets it (best {a.best_noise_total_um:.2f} µm at {a.best_noise_pm:.3g} pm)"
                )
            else:
                lines.append(
                    f"  {a.axis}: interrogator noise ≤ {a.noise_needed_pm:.3g} pm "
                    f"(now {self.wavelength_noise_pm:g} pm)"
                )
            if a.with_references_um < a.total_um - 1e-9:
                lines.append(
                    f"  {a.axis}: a strain-free reference grating beside every sensor: "
                    f"{a.with_references_um:.2f} µm (thermal {a.thermal_um:.2f} µm → "
                    "the references' noise only)"
                )
        if self.larger_layouts:
            lines.append(
                "  layouts chosen by `fbgcomp place` (on the loads+noise figure; "
                + ("the default grid" if self.larger_layouts[0]["grid"] else "the machine's candidate paths")
                + "), total µm:"
            )
            for lay in self.larger_layouts:
                per = ", ".join(
                    f"{a.axis} {format_number(lay['total_um'][AXES.index(a.axis)], 2)}"
                    + (" meets" if lay["total_um"][AXES.index(a.axis)] <= a.target_um else "")
                    for a in self.axes
                )
                lines.append(f"    --k {lay['k']}: {per} [{', '.join(lay['paths'])}]")
        return "\n".join(lines)


def plan(
    machine,
    target_um: float,
    *,
    axes=AXES,
    wavelength_noise_nm=0.001,
    grid=None,
    extra_sensors=2,
    twin=None,
    resolution=None,
    z_axis_mm=None,
    machine_name="the built-in ram",
):
    """Predicted TTP accuracy of the machine description's layout against ``target_um`` (µm).

    The layout's figures come from a twin of the machine as described (as ``fbgcomp resolution``
    builds it). ``grid``: :func:`fbgcomp.structure.placement.candidate_grid` arguments for the larger
    layouts (default none: only the machine's ``candidate_sensors``); ``extra_sensors``: layouts
    of K = n .. n + extra_sensors paths are chosen by :func:`fbgcomp.structure.placement.choose` (0: none)
    on a twin meshed with the candidates too, as ``fbgcomp place`` does.
    """
    pdes = plan_design(
        machine,
        twin=twin,
        resolution=resolution,
        z_axis_mm=z_axis_mm,
        wavelength_noise_nm=wavelength_noise_nm,
    )
    n = len(machine.sensors)
    own = list(range(n))
    parts = layout_error_um(pdes, own)
    with_refs = layout_error_um(pdes, own, references=np.ones(n, dtype=bool))["total_um"]
    rows = []
    for a in axes:
        j = AXES.index(a)
        total = float(parts["total_um"][j])
        needed = best = best_pm = None
        if total > target_um:
            needed, best, best_pm = noise_needed_pm(pdes, own, j, target_um)
        rows.append(
            AxisPlan(
                axis=a,
                target_um=float(target_um),
                **{
                    k: float(parts[k][j])
                    for k in (
                        "unexplained_um",
                        "noise_um",
                        "loads_noise_um",
                        "probe_mismatch_um",
                        "reference_noise_um",
                        "thermal_um",
                    )
                },
                total_um=total,
                meets=total <= target_um,
                meets_loads_noise=float(parts["loads_noise_um"][j]) <= target_um,
                margin_um=float(target_um - total),
                noise_needed_pm=needed,
                best_noise_total_um=best,
                best_noise_pm=best_pm,
                with_references_um=float(with_refs[j]),
            )
        )
    larger = []
    cands = candidate_grid(machine, **grid) if grid else []
    if extra_sensors > 0 and (cands or machine.candidate_sensors):
        # A twin meshed with the candidate paths too, as `fbgcomp place` builds it (the mesh
        # follows the paths' ends, so its figures differ slightly from the layout's own twin).
        pool = plan_design(
            machine,
            cands,
            resolution=resolution,
            z_axis_mm=z_axis_mm,
            wavelength_noise_nm=wavelength_noise_nm,
        )
        default = [s.name for s in machine.sensors]
        for k in range(n, min(n + extra_sensors, len(pool.design.names)) + 1):
            res = choose(pool.design, k, default=default)
            idx = [pool.design.names.index(p) for p in res.chosen]
            total = layout_error_um(pool, idx)["total_um"]
            larger.append(
                {
                    "k": k,
                    "paths": res.chosen,
                    "grid": bool(grid),
                    "loads_noise_um": list(res.per_axis_um),
                    "total_um": total.tolist(),
                }
            )
    sensors = list(machine.sensors)
    return Plan(
        machine=machine_name,
        sensors=[s.name for s in sensors],
        probes_compensating={
            s.name: (
                "reference grating"
                if s.reference_lambda0_nm is not None
                else (s.temperature_probe or "uncompensated")
            )
            for s in sensors
        },
        wavelength_noise_pm=wavelength_noise_nm * 1e3,
        target_um=float(target_um),
        load_cases=[{"name": nm, "magnitude": mg, "unit": u} for nm, mg, u in LOAD_CASES],
        false_elongation_per_K_um=dict(
            zip([s.name for s in sensors], false_elongation_per_K_um(sensors).round(6).tolist())
        ),
        reference_temperature_noise_K=dict(
            zip(
                [s.name for s in sensors],
                reference_temperature_noise_K(sensors, wavelength_noise_nm).round(6).tolist(),
            )
        ),
        axes=rows,
        larger_layouts=larger,
    )


def parse_axes(spec: str) -> tuple:
    """``dx,dz`` -> ("dx", "dz"); an unknown or repeated axis is a one-line command-line error."""
    axes = tuple(a.strip() for a in spec.split(",") if a.strip())
    bad = [a for a in axes if a not in AXES]
    if not axes or bad:
        raise InputError(
            f"--axes expects a comma-separated subset of {','.join(AXES)}, got {(bad[0] if bad else spec)!r}",
            file="<command line>",
            column="option --axes",
        )
    if len(set(axes)) != len(axes):
        raise InputError(
            f"--axes names an axis twice: {spec!r}", file="<command line>", column="option --axes"
        )
    return axes


__all__ = [
    "AxisPlan",
    "Plan",
    "estimator",
    "false_elongation_per_K_um",
    "layout_error_um",
    "noise_needed_pm",
    "noise_scan",
    "parse_axes",
    "plan",
    "plan_design",
    "predicted_error_um",
    "probe_mismatch_K",
    "reference_temperature_noise_K",
]
