"""Where to put the fibres: choose K sensor paths that minimise the predicted worst-case TTP error.

The paper closes by asking for better sensor configurations. Here every candidate path (the
machine's sensors, its ``candidate_sensors`` and/or a grid declared with :func:`candidate_grid`)
is put through the FE twin's elementary load design (:data:`fbgcomp.models.fe_calibrated.LOAD_CASES`: TTP
forces along X, Y, Z and the thermal fields, each at its typical magnitude). For a set S of K
paths with responses E_S (cases x K, µm) and TTP displacements T (cases x 3, µm), the eq. 11
estimator a campaign would give on random combinations of the cases with interrogator noise
(covariance N, diagonal) is the ridge-like

    B = (E_S' E_S + N)^-1 E_S' T,

and the **predicted worst-case TTP error** is, over axes j and load cases c,

    max_{j,c} |T - E_S B|_{cj} + 2 sqrt(sum_s B_sj^2 N_ss)        (µm)

(what the sensors cannot explain plus twice the noise the estimator passes on).

Search: greedy forward selection, then exchange passes (swap a chosen path for an unchosen
one while the objective improves), also started from the default layout when it has K paths, so
the result is never worse than the default on this objective. Why not D-/A-optimal design on
the influence matrices: those maximise information about the *loads* (det or trace of
E'E), but the quantity that matters is the TTP error; a path that is very informative about a
load case with no effect on the TTP (or a second path repeating the first) scores well in D-
optimality and is useless here. The objective is cheap (K x K solves), so optimising it directly
costs nothing; candidate evaluations of each greedy step run through
:func:`fbgcomp.cluster.map_over_cluster` when a Dask cluster is given.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import partial
from typing import Any

import numpy as np

from fbgcomp.cluster import map_over_cluster
from fbgcomp.errors import InputError
from fbgcomp.optics import elongation_noise_um
from fbgcomp.structure.loadcases import LOAD_CASES, load_case_responses
from fbgcomp.structure.machine import FACES, Sensor
from fbgcomp.tables import Column, format_table, text
from fbgcomp.units import AXES


def candidate_grid(
    machine,
    faces=FACES,
    offsets_mm=(0.0,),
    length_mm=500.0,
    step_mm=250.0,
    z_min_mm=None,
    z_max_mm=None,
    template=None,
    prefix="C",
):
    """Candidate paths on a grid: on each face, at each offset across it, paths ``length_mm`` long
    starting every ``step_mm`` between ``z_min_mm`` (default 0) and ``z_max_mm`` (default: the
    ram's length). Fibre constants come from ``template`` (default: the machine's first sensor).
    """
    template = template or machine.sensors[0]
    z0 = 0.0 if z_min_mm is None else float(z_min_mm)
    z1 = machine.ram.length_mm if z_max_mm is None else float(z_max_mm)
    out = []
    for face in faces:
        half = (machine.ram.outer_depth_mm if face[1] == "X" else machine.ram.outer_width_mm) / 2
        for off in offsets_mm:
            if abs(off) > half:
                continue
            start = z0
            while start + length_mm <= z1 + 1e-9:
                name = f"{prefix}{face}o{off:g}z{start:g}-{start + length_mm:g}"
                out.append(
                    Sensor(
                        **{
                            **template.model_dump(),
                            "name": name,
                            "face": face,
                            "offset_mm": float(off),
                            "z_start_mm": start,
                            "z_end_mm": start + length_mm,
                            "gauge_length_mm": None,
                        }
                    )
                )
                start += step_mm
    return out


@dataclass
class PlacementDesign:
    """Responses of every candidate path to the elementary load cases."""

    names: list
    case_names: list
    elongation_um: np.ndarray  # (cases, N)
    ttp_um: np.ndarray  # (cases, 3)
    noise_um: np.ndarray  # (N,) elongation noise SD
    sensors: list = field(default_factory=list)


def sensor_pool(machine, candidates=()):
    """Every path once (the machine's sensors first, in order, then its candidate paths and
    ``candidates``) and the machine description with all of them as its sensors."""
    pool, seen = [], set()
    for s in list(machine.sensors) + list(machine.candidate_sensors) + list(candidates):
        if s.name not in seen:
            pool.append(s)
            seen.add(s.name)
    return pool, machine.model_copy(update={"sensors": tuple(pool), "candidate_sensors": ()})


def placement_design(
    machine, candidates=(), *, twin=None, resolution=None, z_axis_mm=None, wavelength_noise_nm=0.001
) -> PlacementDesign:
    """One FE twin with every path (machine sensors + candidates) as a sensor; load-case responses."""
    from fbgcomp.structure import Twin  # noqa: PLC0415 - optional heavy extra: skfem (the fe extra)

    pool, m = sensor_pool(machine, candidates)
    if twin is None:
        # load cases only (static forces and temperature fields): no reduced thermal model
        twin = Twin(m, resolution=resolution, z_axis_mm=z_axis_mm, reduce_thermal=False)
    cases = load_case_responses(twin)
    names, elong, ttp = cases["names"], cases["sensor_elongation_um"], cases["ttp_um"]
    return PlacementDesign(
        [s.name for s in pool],
        names,
        np.asarray(elong),
        np.asarray(ttp),
        elongation_noise_um(pool, wavelength_noise_nm),
        pool,
    )


def predicted_error_um(elongation_um, ttp_um, noise_um):
    """Predicted worst-case TTP error (µm) of the eq. 11 estimator on these paths, per axis (3,)."""
    E = np.asarray(elongation_um, dtype=float)
    T = np.asarray(ttp_um, dtype=float)
    N = np.diag(np.asarray(noise_um, dtype=float) ** 2)
    B = np.linalg.solve(E.T @ E + N, E.T @ T) if E.shape[1] else np.zeros((0, 3))
    resid = T - E @ B
    noise = np.sqrt(np.sum(B**2 * np.asarray(noise_um, dtype=float)[:, None] ** 2, axis=0))
    return np.max(np.abs(resid), axis=0) + 2 * noise


def objective_um(design: PlacementDesign, subset) -> float:
    """The search's objective: the largest per-axis predicted worst-case TTP error (µm) of the
    paths ``subset`` (indices into ``design.names``)."""
    idx = list(subset)
    return float(
        np.max(predicted_error_um(design.elongation_um[:, idx], design.ttp_um, design.noise_um[idx]))
    )


def _score(design, subset):
    return objective_um(design, subset)


@dataclass
class PlacementResult:
    """The chosen paths and their predicted worst-case TTP error (µm, max and per axis), the
    machine's own layout's for comparison (None when it has not ``k`` paths), the search's
    steps and the number of candidates."""

    chosen: list
    objective_um: float
    per_axis_um: list
    default: list
    default_objective_um: float | None
    default_per_axis_um: list | None
    history: list
    n_candidates: int

    def to_dict(self) -> dict:
        """The result as plain data (for JSON)."""
        return dict(vars(self))

    def format(self) -> str:
        """The result for the console: the chosen paths, then a table of the predicted worst-case
        TTP error of the chosen and the default layout, then the improvement."""
        lines = [
            f"{len(self.chosen)} paths chosen from {self.n_candidates} candidates "
            "(greedy + exchange on the predicted worst-case TTP error over the FE load design "
            "with interrogator noise):"
        ]
        lines += [f"  {n}" for n in self.chosen]
        lines.append("predicted worst-case TTP error:")
        rows = [["chosen", *self.per_axis_um, self.objective_um]]
        if self.default_objective_um is not None and self.default_per_axis_um is not None:  # set together
            rows.append(
                [
                    f"default layout ({', '.join(self.default)})",
                    *self.default_per_axis_um,
                    self.default_objective_um,
                ]
            )
        lines.append(
            format_table(
                [text("layout")] + [Column(a, "µm") for a in AXES] + [Column("max", "µm")], rows, indent="  "
            )
        )
        if self.default_objective_um is not None and self.default_objective_um > 0:
            lines.append(f"improvement: {100 * (1 - self.objective_um / self.default_objective_um):.1f} %")
        return "\n".join(lines)


def choose(design: PlacementDesign, k: int, *, default=None, dask=None, max_passes=20) -> PlacementResult:
    """Greedy forward selection + exchange of ``k`` paths (indices into ``design.names``)."""
    n = len(design.names)
    if not 1 <= k <= n:
        raise ValueError(f"k must be between 1 and the number of candidates ({n})")
    score = partial(_score, design)
    history = []
    chosen: list = []
    while len(chosen) < k:
        rest = [j for j in range(n) if j not in chosen]
        vals = map_over_cluster(score, [[*chosen, j] for j in rest], dask=dask)
        best = int(np.argmin(vals))
        chosen.append(rest[best])
        history.append({"step": "add", "path": design.names[rest[best]], "objective_um": float(vals[best])})

    def exchange(start):
        cur, cur_val = list(start), score(list(start))
        for _ in range(max_passes):
            swaps = [(i, j) for i in range(len(cur)) for j in range(n) if j not in cur]
            subsets = [[*cur[:i], j, *cur[i + 1 :]] for i, j in swaps]
            vals = map_over_cluster(score, subsets, dask=dask) if subsets else []
            if not len(vals) or min(vals) >= cur_val - 1e-12:
                break
            b = int(np.argmin(vals))
            history.append(
                {
                    "step": "swap",
                    "out": design.names[cur[swaps[b][0]]],
                    "in": design.names[swaps[b][1]],
                    "objective_um": float(vals[b]),
                }
            )
            cur, cur_val = subsets[b], float(vals[b])
        return cur, cur_val

    starts = [chosen]
    default_idx = None
    if default:
        default_idx = [design.names.index(s) for s in default if s in design.names]
        if len(default_idx) == k:
            starts.append(default_idx)
    best_set, best_val = None, np.inf
    for s in starts:
        cur, val = exchange(s)
        if val < best_val:
            best_set, best_val = cur, val
    assert best_set is not None  # the objective (a finite error in µm) is below inf for some start
    per_axis = predicted_error_um(design.elongation_um[:, best_set], design.ttp_um, design.noise_um[best_set])
    d_val = d_axes = None
    if default_idx:
        d_axes = predicted_error_um(
            design.elongation_um[:, default_idx], design.ttp_um, design.noise_um[default_idx]
        ).tolist()
        d_val = float(max(d_axes))
    return PlacementResult(
        [design.names[i] for i in best_set],
        float(best_val),
        per_axis.tolist(),
        list(default or []),
        d_val,
        d_axes,
        history,
        n,
    )


def parse_grid(spec: str) -> dict:
    """``faces=+X,-X;offsets=-80,0,80;length=400;step=200;zmin=0;zmax=1200`` -> grid arguments."""
    keys = {
        "faces": "faces",
        "offsets": "offsets_mm",
        "length": "length_mm",
        "step": "step_mm",
        "zmin": "z_min_mm",
        "zmax": "z_max_mm",
    }
    out: dict[str, Any] = {}
    for item in filter(None, (p.strip() for p in spec.split(";"))):
        key, sep, value = item.partition("=")
        key = key.strip()
        if not sep or key not in keys:
            raise InputError(
                f"--grid expects {'; '.join(k + '=...' for k in keys)}, got {item!r}",
                file="<command line>",
                column="option --grid",
            )
        try:
            if key == "faces":
                faces = tuple(f.strip() for f in value.split(","))
                bad = [f for f in faces if f not in FACES]
                if bad:
                    raise ValueError(f"unknown face {bad[0]!r} (faces are {', '.join(FACES)})")
                out["faces"] = faces
            elif key == "offsets":
                out["offsets_mm"] = tuple(float(v) for v in value.split(","))
            else:
                out[keys[key]] = float(value)
        except ValueError as exc:
            raise InputError(f"--grid {key}: {exc}", file="<command line>", column="option --grid") from None
    if out.get("length_mm", 1.0) <= 0 or out.get("step_mm", 1.0) <= 0:
        raise InputError(
            "--grid length and step must be positive", file="<command line>", column="option --grid"
        )
    return out


def place(
    machine,
    k: int,
    *,
    grid=None,
    twin=None,
    resolution=None,
    z_axis_mm=None,
    dask=None,
    wavelength_noise_nm=0.001,
) -> PlacementResult:
    """Choose ``k`` paths among the machine's sensors, its candidates and an optional grid
    (a dict of :func:`candidate_grid` arguments); compare with the machine's own layout."""
    cands = candidate_grid(machine, **grid) if grid else []
    design = placement_design(
        machine,
        cands,
        twin=twin,
        resolution=resolution,
        z_axis_mm=z_axis_mm,
        wavelength_noise_nm=wavelength_noise_nm,
    )
    if k > len(design.names):
        raise InputError(
            f"--k {k} exceeds the {len(design.names)} candidate paths",
            file="<command line>",
            column="option --k",
        )
    return choose(design, k, default=[s.name for s in machine.sensors], dask=dask)


__all__ = [
    "LOAD_CASES",
    "PlacementDesign",
    "PlacementResult",
    "candidate_grid",
    "choose",
    "objective_um",
    "place",
    "placement_design",
    "predicted_error_um",
]
