"""The FE digital twin of the ram: static tool-tip loads and thermal campaigns as linear operators.

Over 600 lines as one unit: the static, thermal and reduced operators share the mesh, the
factorisations and the output functionals.

Everything the virtual test bench reads is a linear functional of the displacement u or of the
temperature rise theta = T - T_ref: FBG path elongations (u_z(end) - u_z(start), µm, the host's
total elongation, mechanical + thermal expansion, paper eq. 4), path mean temperatures (°C),
probe temperatures (°C) and the TTP displacement (dx, dy, dz µm, a rigid extension below the
housing, paper eqs. 10-11). The elastic matrix is factorised once and solved only for the adjoint
(influence) right-hand sides: w_i = Th^T K^-1 g_i acts directly on the temperature field, so a
thermal campaign never solves the elastic problem again (section 2.3, FE load designs).
"""

from __future__ import annotations

import hashlib
import json
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import scipy.sparse as sp
from skfem import Basis, ElementHex1, FacetBasis, asm

from fbgcomp.structure import cache as twin_cache
from fbgcomp.structure import elastic, thermal
from fbgcomp.structure.fe import Factorised, layer_order
from fbgcomp.structure.machine import Machine, parse_machine
from fbgcomp.structure.mesh import RamMesh, carriage_z_mm, machine_mesh

UM_PER_MM = 1000.0


@dataclass(frozen=True)
class StaticResponse:
    """Response to forces at the TTP: one row per load case."""

    sensor_elongation_um: np.ndarray  # (n, S)
    ttp_um: np.ndarray  # (n, 3): dx, dy, dz
    sensor_names: tuple[str, ...]


@dataclass(frozen=True)
class ThermalResponse:
    """Thermal campaign outputs sampled at ``time_s``.

    Elongations and TTP displacements are measured from the stress-free state at T_ref; use
    :meth:`change_from_start` for changes since the first sample (what an FBG or a laser reads).
    """

    time_s: np.ndarray  # (n,)
    sensor_elongation_um: np.ndarray  # (n, S)
    sensor_temperature_C: np.ndarray  # (n, S): mean temperature along each path
    probe_C: np.ndarray  # (n, P): in the order of probe_names
    ttp_um: np.ndarray  # (n, 3)
    sensor_names: tuple[str, ...]
    probe_names: tuple[str, ...]

    def probe(self, name: str) -> np.ndarray:
        """Temperature history (°C) of one probe."""
        return self.probe_C[:, self.probe_names.index(name)]

    def __sub__(self, other: ThermalResponse) -> ThermalResponse:
        """The response minus ``other`` on the same clock: the twin is linear, so a campaign
        minus one input's response alone is the campaign without that input."""
        return ThermalResponse(
            self.time_s,
            self.sensor_elongation_um - other.sensor_elongation_um,
            self.sensor_temperature_C - other.sensor_temperature_C,
            self.probe_C - other.probe_C,
            self.ttp_um - other.ttp_um,
            self.sensor_names,
            self.probe_names,
        )

    def change_from_start(self) -> ThermalResponse:
        """The same response with every output referred to its first sample."""
        return ThermalResponse(
            self.time_s,
            self.sensor_elongation_um - self.sensor_elongation_um[:1],
            self.sensor_temperature_C - self.sensor_temperature_C[:1],
            self.probe_C - self.probe_C[:1],
            self.ttp_um - self.ttp_um[:1],
            self.sensor_names,
            self.probe_names,
        )


@dataclass(frozen=True)
class TemperatureLoadResponse:
    """Steady response to a prescribed temperature-rise field (FE calibration load design)."""

    sensor_elongation_um: np.ndarray  # (S,) or (n, S)
    sensor_temperature_C: np.ndarray  # temperature rise along each path, K
    probe_C: np.ndarray  # temperature rise at each probe, K (the ambient probe: 0)
    ttp_um: np.ndarray  # (3,) or (n, 3)

    def __iter__(self):
        return iter((self.sensor_elongation_um, self.sensor_temperature_C, self.probe_C, self.ttp_um))


@dataclass(frozen=True)
class Influence:
    """The twin's linear operators (µm, N, K; rows in sensor / probe order).

    sensor_per_force_um_per_N : (S, 3) elongation per TTP force component
    ttp_per_force_um_per_N : (3, 3) TTP compliance
    elastic_per_temperature : (S + 3, n_nodes) elongations then dx, dy, dz per K at each node
    sensor_temperature_rows : (S, n_nodes) path-mean temperature rows
    probe_temperature_rows : (P_points, n_nodes) rows of the point probes
    steady_per_input : (S + 3 + S + P_points, 3) steady outputs per unit input (K of ambient,
        W of spindle heat, W/m^2 of radiant flux), rows ordered like ``output_names``
    """

    sensor_per_force_um_per_N: np.ndarray
    ttp_per_force_um_per_N: np.ndarray
    elastic_per_temperature: np.ndarray
    sensor_temperature_rows: sp.csr_matrix
    probe_temperature_rows: sp.csr_matrix
    steady_per_input: np.ndarray
    output_names: tuple[str, ...]
    input_names: tuple[str, ...] = thermal.INPUT_NAMES  # ambient_C, then one per heat source


@dataclass(frozen=True)
class PathInfluence:
    """Linear operators of arbitrary FBG paths (e.g. candidate positions for sensor placement).

    per_force_um_per_N : (k, 3) elongation per TTP force component
    per_temperature_um_per_K : (k, n_nodes) elongation per K of nodal temperature rise
    temperature_rows : (k, n_nodes) path-mean temperature rows
    """

    names: tuple[str, ...]
    per_force_um_per_N: np.ndarray
    per_temperature_um_per_K: np.ndarray
    temperature_rows: sp.csr_matrix


@dataclass
class BuildTimes:
    """Wall-clock times (s) of building the twin: mesh, assembly, elastic factorisation, thermal
    reduction, and the twin cache's load and store."""

    mesh_s: float = 0.0
    assemble_s: float = 0.0
    elastic_factor_s: float = 0.0
    thermal_reduction_s: float = 0.0
    extra: dict = field(default_factory=dict)
    from_cache: bool = False  # loaded from the twin cache (nothing assembled)
    cache_load_s: float = 0.0  # reading (and checking) the cache entry, hit or miss
    cache_store_s: float = 0.0  # writing a new entry after a build
    cache_path: str | None = None


# A rigid support is a penalty this many times the stiffest diagonal entry of K: the supported
# DOF then moves by ~1e-7 of what the structure alone would let it, and the banded Cholesky
# (which sees the penalty only on the diagonal) stays accurate.
RIGID_PENALTY = 1e7

# The static half of a twin: elastic operators, adjoint responses and the instruments'
# temperature rows. None depends on the thermal description (films, heat sources) but through
# the mesh, which heat zones may refine.
_STATIC_HALF = (
    "K",
    "Th",
    "R",
    "support_rows_mm",
    "support_stiffness_N_per_mm",
    "force",
    "W",
    "W_parts",
    "Tsens",
    "Tprobe",
)
# The last twin built or loaded in this process, under its static identity (_static_key): a new
# twin of the same ram, mesh and instruments, whatever its thermal description, takes that half
# from it (the same arrays, so the same bits) instead of assembling and factorising it again:
# the physical model's generic-heat twin after the machine's own twin (demo, compare --machine,
# a script that simulates and then fits). One entry: it keeps at most one twin alive.
_last_static: list[tuple[str, Twin]] = []


def _static_key(machine: Machine, resolution: float, rm: RamMesh) -> str:
    """The identity of a twin's static half: the description without its thermal section, the
    resolution, the mesh itself and the code (twin_cache.code_version)."""
    d = machine.model_dump(mode="json")
    d.pop("thermal", None)
    h = hashlib.sha256(
        json.dumps(
            {"machine": d, "resolution": repr(float(resolution)), "code": twin_cache.code_version()},
            sort_keys=True,
            allow_nan=True,
        ).encode()
    )
    for a in (rm.mesh.p, rm.mesh.t, rm.steel_elements):
        h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest()


def _node_weights(vbasis, facets) -> tuple[np.ndarray, np.ndarray]:
    """Nodes of a facet set and their tributary area fractions (sum 1).

    The nodes are the facets' own: the assembled trace also leaves round-off (~1e-33) on the
    nodes of the elements behind them, and a rigid patch holds every node it is given, so
    selecting by ``area > 0`` held nodes inside the wall (ram6's lateral compliance was 25 %
    stiff, docs/twin.md).
    """
    fb = FacetBasis(vbasis.mesh, ElementHex1(), facets=facets, intorder=elastic.INTORDER)
    area = asm(thermal.unit_load, fb)
    nodes = np.unique(vbasis.mesh.facets[:, facets])
    return nodes, area[nodes] / area[nodes].sum()


def _stiffness_N_per_mm(value, rigid_N_per_mm: float) -> float:
    return rigid_N_per_mm if value == "rigid" else float(value) * UM_PER_MM


def nodal_support_rows(rm: RamMesh, vbasis, machine: Machine, z_axis_mm: float | None, rigid_N_per_mm: float):
    """Sparse (n_c, n_u) rows (one supported DOF each) and stiffnesses (N/mm) of rail supports.

    Every node of each carriage patch (rail strip x station z range) is held in the directions
    its rail holds (:attr:`Rail.held_axes`: the face normal, across the face on a locating rail,
    across only on a rail floating along its normal); a patch's stiffness (per direction) is
    shared among its nodes by tributary area. The nut holds u_z at its cross-section: by the
    mean (one spring) or at every node.
    """
    s = machine.supports
    assert s.rails is not None  # support_rows calls this for rail supports only
    dofs, ks = [], []
    for lo, hi in s.station_ranges_mm(z_axis_mm):
        for rail in s.rails:
            facets = rm.strip_facets(rail.face, lo, hi, *rail.across_mm)
            if len(facets) == 0:
                raise ValueError(
                    f"rail on {rail.face} at {rail.across_mm} mm: no mesh facet in "
                    f"the carriage patch z = {lo:g}..{hi:g} mm"
                )
            nodes, frac = _node_weights(vbasis, facets)
            k_patch = _stiffness_N_per_mm(s.carriage_stiffness_N_per_um, rigid_N_per_mm)
            for axis in rail.held_axes:
                dofs.append(vbasis.nodal_dofs[axis, nodes])
                ks.append(rigid_N_per_mm if k_patch == rigid_N_per_mm else k_patch * frac)
    rows = [sp.csr_matrix((np.ones(len(d)), (np.arange(len(d)), d)), shape=(len(d), vbasis.N)) for d in dofs]
    k = [np.broadcast_to(np.asarray(v, float), (len(d),)) for v, d in zip(ks, dofs)]
    layer = np.nonzero(np.abs(rm.mesh.p[2] - s.nut.z_mm) < 1e-6)[0]
    k_nut = _stiffness_N_per_mm(s.nut.stiffness_N_per_um, rigid_N_per_mm)
    if s.nut.constraint == "nodes":
        d = vbasis.nodal_dofs[2, layer]
        rows.append(sp.csr_matrix((np.ones(len(d)), (np.arange(len(d)), d)), shape=(len(d), vbasis.N)))
        k.append(np.full(len(d), k_nut))
    else:
        nut = np.zeros(vbasis.N)
        nut[vbasis.nodal_dofs[2, layer]] = 1.0 / len(layer)
        rows.append(sp.csr_matrix(nut))
        k.append(np.array([k_nut]))
    return sp.vstack(rows).tocsr(), np.concatenate(k)


def support_rows(
    rm: RamMesh, vbasis, machine: Machine, z_axis_mm: float | None, rigid_N_per_mm: float = np.inf
):
    """(6, n_u) constraint rows (mm) and stiffnesses (N/mm) of the statically determinate supports.

    Per carriage station the mean ux and the mean uy over the shoe length; each lateral direction
    acts on the pair of walls in whose plane it lies (ux on the +-Y walls, uy on the +-X walls),
    as the carriage frame loads the walls as shear panels: a normal load on a 20 mm CFRP wall
    would only measure its local plate bending. At the lower station also the twist, the
    difference of the in-plane displacement between the two shoe faces; at the nut the mean uz
    over the ram cross-section at the nut.
    """
    s = machine.supports
    if s.rails is not None:
        return nodal_support_rows(rm, vbasis, machine, z_axis_mm, rigid_N_per_mm)
    # Supports._consistent_supports requires shoe_width_mm when there are no rails
    assert s.shoe_width_mm is not None
    if s.shoe_length_mm is None:  # the shoes' patches below are centred on each station's z_mm
        raise ValueError("shoe_faces supports need supports.shoe_length_mm")
    half_width_mm, half_length_mm = s.shoe_width_mm / 2, s.shoe_length_mm / 2
    rows = []
    k_shoe = _stiffness_N_per_mm(s.carriage_stiffness_N_per_um, rigid_N_per_mm)
    stations = sorted(carriage_z_mm(machine, z_axis_mm))
    along = 1 if s.shoe_faces[0][1] == "X" else 0  # in-plane lateral component on shoe faces
    for j, zc in enumerate(stations):
        lo, hi = zc - half_length_mm, zc + half_length_mm

        def patch(face, lo=lo, hi=hi):
            return rm.face_facets(face, lo, hi, half_width_mm)

        on_y_walls = elastic.facet_mean_rows(vbasis, np.concatenate([patch("+Y"), patch("-Y")]))
        on_x_walls = elastic.facet_mean_rows(vbasis, np.concatenate([patch("+X"), patch("-X")]))
        rows += [on_y_walls[0], on_x_walls[1]]
        if j == 0:
            m0 = elastic.facet_mean_rows(vbasis, patch(s.shoe_faces[0]))
            m1 = elastic.facet_mean_rows(vbasis, patch(s.shoe_faces[1]))
            rows.append(m0[along] - m1[along])
    layer = np.nonzero(np.abs(rm.mesh.p[2] - s.nut.z_mm) < 1e-6)[0]
    nut = np.zeros(vbasis.N)
    nut[vbasis.nodal_dofs[2, layer]] = 1.0 / len(layer)
    rows.append(nut)
    k = np.array([k_shoe] * 5 + [_stiffness_N_per_mm(s.nut.stiffness_N_per_um, rigid_N_per_mm)])
    return np.vstack(rows), k


class Twin:
    """FE digital twin of ``machine`` at Z-axis position ``z_axis_mm`` (mesh, operators, factors).

    Parameters
    ----------
    machine : Machine
    resolution : float, optional
        Mesh refinement factor (default: ``machine.mesh.resolution``).
    z_axis_mm : float, optional
        Z-axis position; moves the carriage stations along the ram (default: the YAML's).
    n_shifts : int, optional
        Expansion points of the reduced thermal model (default: ``machine.mesh.thermal_shifts``).
    cache : bool, default True
        Reuse a twin of the same machine, resolution, shifts and code built before, from the
        on-disk cache (:mod:`fbgcomp.structure.cache`: the user's cache folder, moved by the
        environment variable ``FBGCOMP_CACHE_DIR``, off with ``FBGCOMP_CACHE_DIR=off``), and
        store a new build there. A reloaded twin gives bit-identical responses; its elastic
        factor is recomputed only when something needs it (``path_influence``). ``False``:
        always build, read and write nothing.
    reduce_thermal : bool, default True
        ``False``: leave the reduced thermal model (:attr:`reduced`, about a third of a build)
        until something needs it. The static operators (loads, prescribed temperature fields,
        the influence matrices and their exact steady thermal gain) are all there: what
        ``fbgcomp twin-check`` reads. Its cache entry lacks the reduction until a twin of the same
        machine that needs it reduces and completes it.
    """

    # Arrays a built twin is made of (everything else is rebuilt in milliseconds from them and
    # the machine description): what the cache stores.
    _ARRAYS = (
        "K",
        "Th",
        "R",
        "support_rows_mm",
        "support_stiffness_N_per_mm",
        "Kt",
        "Ct",
        "Bt",
        "force",
        "W",
        "W_parts",
        "Tsens",
        "Tprobe",
        "build_times_s",
        *(f"reduced_{n}" for n in thermal.ReducedThermal.ARRAYS),
    )
    # ... of which an entry stored by a twin built with reduce_thermal=False holds these
    _UNREDUCED_ARRAYS = tuple(a for a in _ARRAYS if not a.startswith("reduced_"))

    def __init__(
        self,
        machine: Machine,
        resolution: float | None = None,
        z_axis_mm: float | None = None,
        n_shifts: int | None = None,
        cache: bool = True,
        reduce_thermal: bool = True,
    ):
        if z_axis_mm is not None:
            # Re-validate: the carriage stations must stay on the ram at this axis position.
            machine = parse_machine(machine.with_z_axis(z_axis_mm).model_dump())
        self.machine = machine
        self.z_axis_mm = machine.supports.z_axis_mm
        self.times = BuildTimes()
        resolution = machine.mesh.resolution if resolution is None else float(resolution)
        n_shifts = machine.mesh.thermal_shifts if n_shifts is None else int(n_shifts)
        self.sensor_names = tuple(s.name for s in machine.sensors)
        self.probe_names = tuple(p.name for p in machine.probes)
        self._point_probes = [i for i, p in enumerate(machine.probes) if p.kind == "point"]
        self._ambient_probes = [i for i, p in enumerate(machine.probes) if p.kind == "ambient"]
        self._vbasis_built: Basis | None = None
        self._elastic_built: Factorised | None = None
        self._n_shifts = n_shifts
        self._reduced: thermal.ReducedThermal | None = None
        # the thermal matrix factorised, kept from a build for the reduction made on first use
        self._thermal_factor_kept: Factorised | None = None

        t0 = time.perf_counter()
        self.mesh = machine_mesh(machine, resolution, self.z_axis_mm)
        self.times.mesh_s = time.perf_counter() - t0
        self._static_key = _static_key(machine, resolution, self.mesh)

        # the twin's identity (machine content, resolution, shifts, code): results derived from
        # it are cached under it too (twin_cache.cached_json)
        self.cache_key = twin_cache.twin_key(machine, resolution, n_shifts)
        folder = twin_cache.cache_dir() if cache else None
        if folder is None:
            self._adopt(*self._build(n_shifts, reduce_thermal, None))
            return
        key = self.cache_key
        # one builder per twin at a time: the others wait and load its entry
        with twin_cache.build_lock(key, folder):
            self._load_or_build(folder, key, n_shifts, reduce_thermal)

    def _load_or_build(self, folder, key, n_shifts, reduce_thermal=True):
        """Adopt the cached entry of ``key`` in ``folder``, or build the twin and store it
        (``reduce_thermal=False``: without the reduction; a twin that needs it completes such an
        entry)."""
        t0 = time.perf_counter()
        arrays = twin_cache.load(key, self._UNREDUCED_ARRAYS, folder)
        if arrays is not None and not self._fits(arrays):
            arrays = None
        self.times.cache_load_s = time.perf_counter() - t0
        if arrays is not None:
            self.times.from_cache = True
            self.times.cache_path = str(folder / f"{key}{twin_cache.SUFFIX}")
            self.times.extra["cold_build_s"] = dict(
                zip(
                    ("mesh_s", "assemble_s", "elastic_factor_s", "thermal_reduction_s"),
                    (float(v) for v in arrays["build_times_s"]),
                )
            )
            self._adopt(arrays)
            if not reduce_thermal or self._reduced is not None:
                return
            # an entry a twin-check stored: reduce now and complete it
            arrays.update({f"reduced_{n}": a for n, a in self.reduced.arrays().items()})
            arrays["build_times_s"] = np.array([*arrays["build_times_s"][:3], self.times.thermal_reduction_s])
        else:
            arrays, thermal_factor = self._build(n_shifts, reduce_thermal, folder)
            self._adopt(arrays, thermal_factor)
        t0 = time.perf_counter()
        path = twin_cache.store(key, arrays, folder)
        if path is not None:
            twin_cache.record_static(self._static_key, key, folder)
        self.times.cache_store_s = time.perf_counter() - t0
        self.times.cache_path = None if path is None else str(path)

    def _fits(self, arrays) -> bool:
        """Sanity check of a cache entry against this twin's mesh and outputs (the key already
        covers machine and code; this only guards against an entry of the wrong shape)."""
        n = self.mesh.n_nodes
        return arrays["Kt"].shape == (n, n) and self._static_fits(arrays)

    def _static_fits(self, arrays) -> bool:
        """:meth:`_fits` for the static half alone."""
        n, S = self.mesh.n_nodes, len(self.sensor_names)
        return (
            arrays["K"].shape == (3 * n, 3 * n)
            and arrays["W"].shape == (S + 3, n)
            and arrays["W_parts"].shape == (len(elastic.CTE_PARTS), S + 3, n)
            and arrays["Th"].shape == (3 * n, n)
            and arrays["Tprobe"].shape == (len(self._point_probes), n)
        )

    def _build(self, n_shifts: int, reduce_thermal: bool, folder: Path | None):
        """Assemble, factorise and reduce: the expensive part, returned as plain arrays (and the
        thermal factor, kept in memory for the reduction; ``reduce_thermal=False``: no
        ``reduced_*`` arrays, the reduction is made on first use). The static half comes from
        the last twin of this process, or from the cached entry (``folder``: the cache's) of
        another twin that has it, when either is of the same ram, mesh and instruments."""
        machine, rm = self.machine, self.mesh
        shared = next((t for k, t in _last_static if k == self._static_key), None)
        if shared is None:
            part = self._cached_static(folder)
            if part is None:
                part = self._build_static()
            else:
                self.times.extra["static_half_from_cache"] = True
        else:  # the same ram, mesh and instruments: its static half as it is
            part = shared._static_part
            self._vbasis_built, self._elastic_built = shared._vbasis_built, shared._elastic_built
            self.times.extra["static_half_shared"] = True
        t0 = time.perf_counter()
        Kt, Ct, Bt = thermal.assemble_thermal(rm, machine)
        self.times.assemble_s += time.perf_counter() - t0
        O = np.vstack([part["W"], part["Tsens"].toarray(), part["Tprobe"].toarray()])  # noqa: E741 - O: the output matrix of (K, C, B, O)

        t0 = time.perf_counter()
        thermal_factor = Factorised(Kt)  # the mesh's node order is already layer-wise
        reduced = (
            thermal.ReducedThermal(Kt, Ct, Bt, O, n_shifts, factor=thermal_factor) if reduce_thermal else None
        )
        self.times.thermal_reduction_s = time.perf_counter() - t0
        b = self.times
        arrays = {
            **part,
            "Kt": Kt,
            "Ct": Ct,
            "Bt": Bt,
            "build_times_s": np.array([b.mesh_s, b.assemble_s, b.elastic_factor_s, b.thermal_reduction_s]),
        }
        if reduced is not None:
            arrays.update({f"reduced_{n}": a for n, a in reduced.arrays().items()})
        return arrays, thermal_factor

    def _cached_static(self, folder: Path | None) -> dict | None:
        """The static half of this twin, from the cached entry of another twin that holds it (one that
        differs in its thermal description only: an edited film, heat source or ambient), or
        None. Its identity covers the description but its thermal section, the mesh and the
        code, as for the sharing within a process; the shapes are checked as for a whole entry.
        The elastic factor, which no entry stores, is made again on first use, as for a twin
        loaded from its own entry."""
        if folder is None:
            return None
        other = twin_cache.static_entry(self._static_key, folder)
        arrays = None if other is None else twin_cache.load(other, _STATIC_HALF, folder)
        if arrays is None or not self._static_fits(arrays):
            return None
        return {name: arrays[name] for name in _STATIC_HALF}

    def _build_static(self) -> dict:
        """The static half (:data:`_STATIC_HALF`): assemble the elasticity, factorise it and
        solve it for the adjoint rows; the instruments' temperature rows."""
        machine, rm = self.machine, self.mesh
        t0 = time.perf_counter()
        mats = machine.materials
        # the thermal load per unit expansion coefficient of each material (d Th / d alpha_k):
        # a response is linear in the coefficients, so the twin answers for any of them
        units = [elastic.unit_cte_materials(mats.cfrp, mats.steel, part) for part in elastic.CTE_PARTS]
        if machine.mesh.element == "hex8i":
            vb, _sb, K, Th = elastic.assemble_box_elasticity(rm, mats.cfrp, mats.steel)
            # the same bases, and no stiffness matrix for the unit loads (3 of its 4 assemblies)
            Th_parts = [
                elastic.assemble_box_elasticity(rm, *u, bases=(vb, _sb), stiffness=False)[3] for u in units
            ]
        else:
            vb, _sb, K, Th = elastic.assemble_elasticity(rm, mats.cfrp, mats.steel)
            Th_parts = [elastic.assemble_elasticity(rm, *u)[3] for u in units]
        rigid = RIGID_PENALTY * float(K.diagonal().max())
        rows, k = support_rows(rm, vb, machine, self.z_axis_mm, rigid)
        K = (K + elastic.spring_matrix(rows, k)).tocsr()
        self._vbasis_built = vb
        self.times.assemble_s = time.perf_counter() - t0

        # Elastic output rows (µm per mm of nodal displacement): path elongations, then TTP.
        uz = vb.nodal_dofs[2]
        el_rows = []
        for s in machine.sensors:
            ends = rm.point_rows(
                rm.face_point_mm(s.face, s.offset_mm, [s.z_start_mm, s.z_end_mm], s.depth_mm)
            )
            d = (ends[1] - ends[0]).toarray().ravel()
            row = np.zeros(vb.N)
            row[uz] = d
            el_rows.append(row)
        patch = machine.tool.nose_patch_mm or (np.inf, np.inf)
        nose = rm.end_facets(-machine.housing.height_mm, patch[0] / 2, patch[1] / 2)
        ttp_rows = elastic.rigid_extension_rows(vb, nose, lever_mm=machine.tool.ttp_below_housing_mm)
        R = UM_PER_MM * np.vstack([*el_rows, ttp_rows])  # (S + 3, n_u)

        t0 = time.perf_counter()
        self._elastic_built = Factorised(K, order=layer_order(rm.mesh.p, vb.nodal_dofs), blocked=True)
        X = self._elastic_built.solve(R.T)  # adjoint: K^-1 g_i
        self.times.elastic_factor_s = time.perf_counter() - t0
        force = X.T @ ttp_rows.T  # (S + 3, 3) µm/N
        W = np.asarray((Th.T @ X).T)  # (S + 3, n_nodes) µm/K
        W_parts = np.stack([np.asarray((T.T @ X).T) for T in Th_parts])  # (P, S + 3, n_nodes) µm/K per 1/K

        Tsens = sp.vstack(
            [
                rm.path_mean_rows(s.face, s.offset_mm, s.z_start_mm, s.z_end_mm, s.depth_mm)
                for s in machine.sensors
            ]
        ).tocsr()
        pts = [
            [machine.probes[i].x_mm, machine.probes[i].y_mm, machine.probes[i].z_mm]
            for i in self._point_probes
        ]
        Tprobe = (rm.point_rows(pts) if pts else sp.csr_matrix((0, rm.n_nodes))).tocsr()
        return {
            "K": K,
            "Th": Th,
            "R": R,
            "support_rows_mm": rows,
            "support_stiffness_N_per_mm": k,
            "force": force,
            "W": W,
            "W_parts": W_parts,
            "Tsens": Tsens,
            "Tprobe": Tprobe,
        }

    def _adopt(self, arrays, thermal_factor: Factorised | None = None) -> None:
        """Set the twin's operators from its arrays (a fresh build or a cache entry alike)."""
        S = len(self.sensor_names)
        W, Tsens, Tprobe, force = arrays["W"], arrays["Tsens"], arrays["Tprobe"], arrays["force"]
        self.support_rows_mm = arrays["support_rows_mm"]
        self.support_stiffness_N_per_mm = arrays["support_stiffness_N_per_mm"]
        self._K_elastic, self._Th, self._R = arrays["K"], arrays["Th"], arrays["R"]
        Kt, Ct, Bt = arrays["Kt"], arrays["Ct"], arrays["Bt"]
        self._thermal_K, self._thermal_C, self._thermal_B = Kt, Ct, Bt
        self._O = np.vstack([W, Tsens.toarray(), Tprobe.toarray()])
        self._W_parts = arrays["W_parts"]
        self._static_part = {n: arrays[n] for n in _STATIC_HALF}
        _last_static[:] = [(self._static_key, self)]
        # the parts' rows projected on the reduced basis, on first use
        self._parts_outputs: tuple[np.ndarray, np.ndarray] | None = None
        if all(f"reduced_{n}" in arrays for n in thermal.ReducedThermal.ARRAYS):
            self._reduced = thermal.ReducedThermal.from_arrays(
                Kt,
                Bt,
                {n: arrays[f"reduced_{n}"] for n in thermal.ReducedThermal.ARRAYS},
                factor=thermal_factor,
            )
            steady = self._reduced.steady_gain
        else:  # reduced on first use (reduce_thermal=False); the exact steady gain as it forms it
            if thermal_factor is None:  # an entry such a twin stored
                thermal_factor = Factorised(Kt)
            self._thermal_factor_kept = thermal_factor
            steady = self._O @ thermal_factor.solve(Bt)
        names = (
            [f"{n}_elongation_um" for n in self.sensor_names]
            + ["dx_um", "dy_um", "dz_um"]
            + [f"{n}_temperature_C" for n in self.sensor_names]
            + [self.probe_names[i] for i in self._point_probes]
        )
        self.influence = Influence(
            sensor_per_force_um_per_N=force[:S],
            ttp_per_force_um_per_N=force[S:],
            elastic_per_temperature=W,
            sensor_temperature_rows=Tsens,
            probe_temperature_rows=Tprobe,
            steady_per_input=steady,
            output_names=tuple(names),
            input_names=thermal.input_names(self.machine),
        )

    # ------------------------------------------------------------- built on first use
    @property
    def _vbasis(self):
        """The vector (displacement) basis of the mesh."""
        if self._vbasis_built is None:
            self._vbasis_built = Basis(self.mesh.mesh, elastic.vector_element(), intorder=elastic.INTORDER)
        return self._vbasis_built

    @property
    def _elastic(self) -> Factorised:
        """The elastic stiffness (with its supports) factorised: kept from the build, computed
        on first use when the twin came from the cache."""
        if self._elastic_built is None:
            order = layer_order(self.mesh.mesh.p, self._vbasis.nodal_dofs)
            self._elastic_built = Factorised(self._K_elastic, order=order, blocked=True)
        return self._elastic_built

    @property
    def reduced(self) -> thermal.ReducedThermal:
        """The reduced thermal model: from the build or the cache entry, or made on first use
        (a twin built with ``reduce_thermal=False``; the same arrays as a build makes)."""
        if self._reduced is None:
            t0 = time.perf_counter()
            self._reduced = thermal.ReducedThermal(
                self._thermal_K,
                self._thermal_C,
                self._thermal_B,
                self._O,
                self._n_shifts,
                factor=self._thermal_factor_kept,
            )
            self.times.thermal_reduction_s += time.perf_counter() - t0
        return self._reduced

    # ----------------------------------------------------------------------- other paths
    def path_influence(self, sensors=None) -> PathInfluence:
        """Operators of FBG paths given like the YAML's sensors (default: candidate_sensors).

        Costs one elastic back-substitution per path; the mesh resolves the path ends by
        trilinear interpolation when they are not grid points.
        """
        sensors = self.machine.candidate_sensors if sensors is None else tuple(sensors)
        rm, vb = self.mesh, self._vbasis
        if not sensors:
            empty = np.zeros((0, rm.n_nodes))
            return PathInfluence((), np.zeros((0, 3)), empty, sp.csr_matrix(empty))
        rows = np.zeros((len(sensors), vb.N))
        for i, s in enumerate(sensors):
            ends = rm.point_rows(
                rm.face_point_mm(s.face, s.offset_mm, [s.z_start_mm, s.z_end_mm], s.depth_mm)
            )
            rows[i, vb.nodal_dofs[2]] = UM_PER_MM * (ends[1] - ends[0]).toarray().ravel()
        X = self._elastic.solve(rows.T)
        ttp_rows = self._R[-3:] / UM_PER_MM
        temps = sp.vstack(
            [rm.path_mean_rows(s.face, s.offset_mm, s.z_start_mm, s.z_end_mm, s.depth_mm) for s in sensors]
        ).tocsr()
        return PathInfluence(
            tuple(s.name for s in sensors), X.T @ ttp_rows.T, np.asarray((self._Th.T @ X).T), temps
        )

    def thermal_paths(
        self,
        paths: PathInfluence,
        time_s,
        ambient_C,
        spindle_heat_W=None,
        radiant_W_per_m2=None,
        initial_C=None,
        heat=None,
    ):
        """Elongation (n, k) µm and mean temperature (n, k) °C of extra paths in a campaign."""
        t, u = self._inputs(time_s, ambient_C, spindle_heat_W, radiant_W_per_m2, heat)
        O = np.vstack([paths.per_temperature_um_per_K, paths.temperature_rows.toarray()])  # noqa: E741 - O: the output matrix of (K, C, B, O)
        y = self.reduced.simulate(
            t, u, self._initial_theta(initial_C), outputs=self.reduced.projected_outputs(O)
        )
        k = len(paths.names)
        return y[:, :k], y[:, k:] + self.machine.reference_temperature_C

    # ----------------------------------------------------------------------------- sizes
    @property
    def n_nodes(self) -> int:
        """Number of nodes of the ram mesh."""
        return self.mesh.n_nodes

    @property
    def n_dof(self) -> int:
        """Thermo-elastic DOF: 3 displacements + 1 temperature per node."""
        return 4 * self.mesh.n_nodes

    # ---------------------------------------------------------------------------- static
    def static(self, forces_N) -> StaticResponse:
        """Response to forces (n, 3) or (3,) in N applied at the TTP (superposable)."""
        F = np.atleast_2d(np.asarray(forces_N, dtype=float))
        if F.shape[-1] != 3:
            raise ValueError("forces_N must have 3 columns (Fx, Fy, Fz)")
        inf = self.influence
        return StaticResponse(
            F @ inf.sensor_per_force_um_per_N.T, F @ inf.ttp_per_force_um_per_N.T, self.sensor_names
        )

    # --------------------------------------------------------------------------- thermal
    @property
    def input_names(self) -> tuple[str, ...]:
        """Thermal input channels: ``ambient_C``, then one per heat source (``<name>_W`` for a
        volume source, ``<name>_W_per_m2`` for a radiant one)."""
        return self.influence.input_names

    def _inputs(self, time_s, ambient_C, spindle_heat_W, radiant_W_per_m2, heat=None):
        """Input matrix (n, m). ``spindle_heat_W`` feeds the first volume source and
        ``radiant_W_per_m2`` the first radiant one; ``heat`` maps any source (by name or input
        name) to its history. Sources given nothing stay at zero; an all-zero ``spindle_heat_W``
        or ``radiant_W_per_m2`` is nothing, so it needs no such source."""
        t = np.asarray(time_s, dtype=float).ravel()
        sources = self.machine.thermal.sources
        values: dict[int, object] = {}
        for kind, v in (("volume", spindle_heat_W), ("radiant", radiant_W_per_m2)):
            first = next((i for i, h in enumerate(sources) if h.kind == kind), None)
            if v is not None and np.any(v):
                if first is None:
                    raise ValueError(f"the machine declares no {kind} heat source")
                values[first] = v
        for key, v in (heat or {}).items():
            match = [i for i, h in enumerate(sources) if key in (h.name, h.input_name)]
            if not match:
                raise ValueError(f"unknown heat source {key!r}; inputs: {self.input_names[1:]}")
            values[match[0]] = v
        cols = [
            np.broadcast_to(np.asarray(ambient_C, dtype=float), t.shape)
            - self.machine.reference_temperature_C
        ]
        for i in range(len(sources)):
            v = values.get(i)
            cols.append(np.broadcast_to(np.asarray(0.0 if v is None else v, dtype=float), t.shape))
        return t, np.column_stack(cols)

    def _initial_theta(self, initial_C):
        if initial_C is None:
            return None
        init = np.asarray(initial_C, dtype=float)
        theta = np.broadcast_to(init, (self.n_nodes,)) - self.machine.reference_temperature_C
        return np.ascontiguousarray(theta)

    def _split(self, t, u, y) -> ThermalResponse:
        S = len(self.sensor_names)
        Tref = self.machine.reference_temperature_C
        probe = np.empty((len(t), len(self.probe_names)))
        probe[:, self._point_probes] = y[:, 2 * S + 3 :] + Tref
        probe[:, self._ambient_probes] = (u[:, 0] + Tref)[:, None]
        return ThermalResponse(
            t,
            y[:, :S],
            y[:, S + 3 : 2 * S + 3] + Tref,
            probe,
            y[:, S : S + 3],
            self.sensor_names,
            self.probe_names,
        )

    def thermal(
        self, time_s, ambient_C, spindle_heat_W=None, radiant_W_per_m2=None, initial_C=None, heat=None
    ) -> ThermalResponse:
        """Thermal campaign: inputs (n,) sampled at ``time_s`` (s), piecewise linear in between.

        ``spindle_heat_W`` drives the first volume heat source, ``radiant_W_per_m2`` the first
        radiant one; ``heat`` ({source name: history}) drives any declared source.

        ``initial_C``: None starts from the steady state of the first inputs; a scalar (uniform)
        or an (n_nodes,) field sets the initial temperature.
        """
        t, u = self._inputs(time_s, ambient_C, spindle_heat_W, radiant_W_per_m2, heat)
        y = self.reduced.simulate(t, u, self._initial_theta(initial_C))
        return self._split(t, u, y)

    @property
    def cte_per_K(self) -> np.ndarray:
        """The description's expansion coefficients (per K) in
        :data:`~fbgcomp.structure.elastic.CTE_PARTS` order: :meth:`thermal_parts` weighted by
        them is :meth:`thermal`'s elongations and TTP."""
        mats = self.machine.materials
        return elastic.cte_values_per_K(mats.cfrp, mats.steel)

    def thermal_parts(
        self, time_s, ambient_C, heat=None, initial_C=None
    ) -> tuple[ThermalResponse, np.ndarray]:
        """A thermal campaign (inputs as :meth:`thermal`) and its elongations and TTP per unit
        expansion coefficient of each material, (n, P, S + 3) µm per 1/K
        (P = :data:`~fbgcomp.structure.elastic.CTE_PARTS`; the S sensors' elongations, then dx,
        dy, dz), from one simulation. The temperatures do not depend on the coefficients, so
        ``sum_k alpha_k parts[:, k]`` is the response of the same ram with coefficients alpha
        (with the description's, :attr:`cte_per_K`, the response's own)."""
        t, u = self._inputs(time_s, ambient_C, None, None, heat)
        P, m, n = self._W_parts.shape
        if self._parts_outputs is None:
            OPhi, D = self.reduced.projected_outputs(self._W_parts.reshape(P * m, n))
            self._parts_outputs = (np.vstack([self.reduced.OPhi, OPhi]), np.vstack([self.reduced.D, D]))
        y = self.reduced.simulate(t, u, self._initial_theta(initial_C), outputs=self._parts_outputs)
        k = self.reduced.OPhi.shape[0]
        return self._split(t, u, y[:, :k]), y[:, k:].reshape(len(t), P, m)

    def thermal_direct(
        self, time_s, ambient_C, spindle_heat_W=None, radiant_W_per_m2=None, initial_C=None, heat=None
    ) -> ThermalResponse:
        """Full-order implicit Euler reference of :meth:`thermal` (one sparse solve per step)."""
        t, u = self._inputs(time_s, ambient_C, spindle_heat_W, radiant_W_per_m2, heat)
        y = thermal.implicit_euler(
            self._thermal_K, self._thermal_C, self._thermal_B, self._O, t, u, self._initial_theta(initial_C)
        )
        return self._split(t, u, y)

    # ------------------------------------------------------------ temperature load designs
    FIELD_KINDS = ("uniform", "gradient_x", "gradient_y", "gradient_z", "housing")

    def temperature_field(self, field_kind: str, magnitude_C: float = 1.0) -> np.ndarray:
        """Nodal temperature rise (K) of a calibration load design.

        uniform: everywhere; gradient_x / gradient_y: linear across the ram, +X (+Y) face minus
        -X (-Y) face = magnitude, zero on the axis; gradient_z: linear along the ram, top minus
        spindle end = magnitude, zero at z = 0 (housing at 0); housing: the housing only (z <= 0).
        """
        p = self.mesh.mesh.p
        rm = self.mesh
        if field_kind == "uniform":
            shape = np.ones(rm.n_nodes)
        elif field_kind == "gradient_x":
            shape = p[0] / (2 * rm.half_width_mm)
        elif field_kind == "gradient_y":
            shape = p[1] / (2 * rm.half_depth_mm)
        elif field_kind == "gradient_z":
            shape = np.clip(p[2], 0, None) / rm.length_mm
        elif field_kind == "housing":
            shape = (p[2] <= 1e-6).astype(float)
        else:
            raise ValueError(f"unknown field_kind {field_kind!r}; one of {self.FIELD_KINDS}")
        return magnitude_C * shape

    def static_temperature_response(self, field_kind: str, magnitude_C=1.0) -> TemperatureLoadResponse:
        """Steady response to a prescribed temperature rise; ``magnitude_C`` scalar or (n,).

        Returns (sensor_elongation_um, sensor_temperature_C, probe_C, ttp_um); temperatures are
        rises above T_ref (the ambient probe reads 0).
        """
        unit = self.temperature_field(field_kind, 1.0)
        S = len(self.sensor_names)
        y = self._O @ unit  # linear in the magnitude
        mag = np.asarray(magnitude_C, dtype=float)
        probe = np.zeros(len(self.probe_names))
        probe[self._point_probes] = y[2 * S + 3 :]
        out = [y[:S], y[S + 3 : 2 * S + 3], probe, y[S : S + 3]]
        if mag.ndim == 0:
            return TemperatureLoadResponse(*(float(mag) * o for o in out))
        return TemperatureLoadResponse(*(mag[:, None] * o[None, :] for o in out))

    def elastic_response_to_field(self, theta_K: np.ndarray) -> np.ndarray:
        """Elastic outputs (S elongations, dx, dy, dz; µm) of a nodal temperature-rise field."""
        return self.influence.elastic_per_temperature @ theta_K
