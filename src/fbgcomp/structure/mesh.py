"""Structured hexahedral mesh of the hollow CFRP ram and the solid steel housing.

A tensor grid whose lines pass through every wall face, the housing outline, the sensor path ends,
the probe heights and the support patches, with the cells of the box cavity removed. Every point
functional (sensor path ends, probes) is an exact trilinear interpolation on one cell, and every
path mean is an exact trapezoid over the grid's z-lines (the field is linear in z between them).
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from skfem import MeshHex

from fbgcomp.structure.machine import Machine, cavity_bounds_mm, walls_per_face

_TOL_MM = 1e-6


def _segment_lines(breaks_mm, step_mm: float, single_spans_mm=()) -> np.ndarray:
    """Grid lines through all ``breaks_mm`` with spacing at most ``step_mm`` between them.

    Intervals listed in ``single_spans_mm`` ((lo, hi) pairs between consecutive breaks) stay one
    element long.
    """
    b = np.unique(np.round(np.asarray(breaks_mm, dtype=float), 6))
    # Break points closer than 0.5 mm would only make sliver elements: keep the first of them.
    keep = [b[0]]
    for v in b[1:]:
        if v - keep[-1] > 0.5:
            keep.append(v)
    keep[-1] = b[-1]
    b = np.asarray(keep)
    lines = [b[:1]]
    single = [(round(lo, 6), round(hi, 6)) for lo, hi in single_spans_mm]
    for lo, hi in itertools.pairwise(b):
        n = max(1, int(np.ceil((hi - lo) / step_mm - 1e-9)))
        if (round(lo, 6), round(hi, 6)) in single:
            n = 1
        lines.append(np.linspace(lo, hi, n + 1)[1:])
    return np.concatenate(lines)


def _cross_lines(
    outer_half_mm: float, wall_lo_mm: float, wall_hi_mm: float, n_wall: int, n_span: int, extra_mm=()
) -> np.ndarray:
    """Grid lines across the section: ``n_wall`` elements through the wall at each end (its
    thickness ``wall_lo_mm`` at -outer_half, ``wall_hi_mm`` at +outer_half), ``n_span`` across
    the cavity, and the ``extra_mm`` lines (the centre 0 among them) not already on the grid."""
    lo, hi = -outer_half_mm + wall_lo_mm, outer_half_mm - wall_hi_mm
    lines = np.concatenate(
        [
            np.linspace(-outer_half_mm, lo, n_wall + 1),
            np.linspace(lo, hi, n_span + 1)[1:-1],
            np.linspace(hi, outer_half_mm, n_wall + 1),
        ]
    )
    extra = [e for e in (0.0, *extra_mm) if np.min(np.abs(lines - e)) > 1e-3]
    return np.unique(np.concatenate([lines, np.asarray(extra, dtype=float)]))


@dataclass
class RamMesh:
    """The hexahedral mesh plus the grid bookkeeping needed for exact point functionals.

    Attributes
    ----------
    mesh : skfem.MeshHex
        Coordinates in mm.
    xs_mm, ys_mm, zs_mm : ndarray
        Grid lines of the tensor grid the mesh was cut from.
    node_of : ndarray (ny, nx, nz) of int
        Mesh node at each grid point, -1 where no material is.
    steel_elements, cfrp_elements : ndarray of int
        Elements of the housing and of the ram.
    """

    mesh: MeshHex
    xs_mm: np.ndarray
    ys_mm: np.ndarray
    zs_mm: np.ndarray
    node_of: np.ndarray
    cell_kept: np.ndarray
    steel_elements: np.ndarray
    cfrp_elements: np.ndarray
    half_width_mm: float
    half_depth_mm: float
    cavity_mm: tuple[float, float, float, float]  # x_lo, x_hi, y_lo, y_hi of the box cavity
    length_mm: float

    @property
    def n_nodes(self) -> int:
        """Number of mesh nodes."""
        return self.mesh.p.shape[1]

    def _cell_of(self, x: float, y: float, z: float) -> tuple[int, int, int]:
        cands = []
        for lines, v in ((self.xs_mm, x), (self.ys_mm, y), (self.zs_mm, z)):
            i = int(np.clip(np.searchsorted(lines, v) - 1, 0, len(lines) - 2))
            opts = {i}
            # On a grid line the neighbouring cell may be the one that holds material.
            for j in (i - 1, i + 1):
                if 0 <= j <= len(lines) - 2 and lines[j] - _TOL_MM <= v <= lines[j + 1] + _TOL_MM:
                    opts.add(j)
            cands.append(sorted(opts))
        for ix in cands[0]:
            for iy in cands[1]:
                for iz in cands[2]:
                    if self.cell_kept[iy, ix, iz]:
                        return ix, iy, iz
        raise ValueError(f"point ({x:g}, {y:g}, {z:g}) mm is not in the meshed structure")

    def point_rows(self, points_mm) -> sp.csr_matrix:
        """Sparse (n_points, n_nodes) trilinear interpolation of a nodal field at points (mm)."""
        pts = np.atleast_2d(np.asarray(points_mm, dtype=float))
        rows, cols, vals = [], [], []
        for r, (x, y, z) in enumerate(pts):
            ix, iy, iz = self._cell_of(x, y, z)
            sx = np.clip((x - self.xs_mm[ix]) / (self.xs_mm[ix + 1] - self.xs_mm[ix]), 0, 1)
            sy = np.clip((y - self.ys_mm[iy]) / (self.ys_mm[iy + 1] - self.ys_mm[iy]), 0, 1)
            sz = np.clip((z - self.zs_mm[iz]) / (self.zs_mm[iz + 1] - self.zs_mm[iz]), 0, 1)
            for dx, wx in ((0, 1 - sx), (1, sx)):
                for dy, wy in ((0, 1 - sy), (1, sy)):
                    for dz, wz in ((0, 1 - sz), (1, sz)):
                        w = wx * wy * wz
                        if w > 0:
                            rows.append(r)
                            cols.append(self.node_of[iy + dy, ix + dx, iz + dz])
                            vals.append(w)
        return sp.csr_matrix((vals, (rows, cols)), shape=(len(pts), self.n_nodes))

    def face_point_mm(self, face: str, offset_mm: float, z_mm, depth_mm: float = 0.0) -> np.ndarray:
        """Points (n, 3) in a wall of the ram: ``offset_mm`` across the face, ``depth_mm`` in from
        its outer surface, at heights z."""
        z = np.atleast_1d(np.asarray(z_mm, dtype=float))
        sign = 1.0 if face[0] == "+" else -1.0
        xy = (
            (sign * (self.half_width_mm - depth_mm), offset_mm)
            if face[1] == "X"
            else (offset_mm, sign * (self.half_depth_mm - depth_mm))
        )
        return np.column_stack([np.full_like(z, xy[0]), np.full_like(z, xy[1]), z])

    def path_mean_rows(
        self, face: str, offset_mm: float, z_start_mm: float, z_end_mm: float, depth_mm: float = 0.0
    ) -> sp.csr_matrix:
        """(1, n_nodes) row: mean of a nodal field along a straight path in a wall, along z.

        Trapezoid over the grid's z-lines inside the path: exact, as the trilinear field is linear
        in z between them.
        """
        inner = self.zs_mm[(self.zs_mm > z_start_mm + _TOL_MM) & (self.zs_mm < z_end_mm - _TOL_MM)]
        z = np.concatenate([[z_start_mm], inner, [z_end_mm]])
        dz = np.diff(z)
        w = np.zeros_like(z)
        w[:-1] += dz / 2
        w[1:] += dz / 2
        w /= z_end_mm - z_start_mm
        rows = self.point_rows(self.face_point_mm(face, offset_mm, z, depth_mm))
        return sp.csr_matrix(w[None, :] @ rows)

    def facets_where(self, predicate) -> np.ndarray:
        """Boundary facets whose midpoints (3, n) in mm satisfy ``predicate``."""
        return self.mesh.facets_satisfying(predicate, boundaries_only=True)

    def in_cavity(self, x_mm: np.ndarray) -> np.ndarray:
        """True where points (3, n) in mm lie in the box cavity or on its inner surfaces."""
        x_lo, x_hi, y_lo, y_hi = self.cavity_mm
        x, y, z = x_mm[0], x_mm[1], x_mm[2]
        return (
            (x > x_lo - _TOL_MM)
            & (x < x_hi + _TOL_MM)
            & (y > y_lo - _TOL_MM)
            & (y < y_hi + _TOL_MM)
            & (z > -_TOL_MM)
            & (z < self.length_mm - _TOL_MM)
        )

    def outer_facets(self) -> np.ndarray:
        """Boundary facets exposed to the surrounding air (outside of ram and housing, end faces)."""
        return self.facets_where(lambda x: ~self.in_cavity(x))

    def inner_facets(self) -> np.ndarray:
        """Boundary facets facing the air inside the box (inner walls, housing top in the cavity)."""
        return self.facets_where(self.in_cavity)

    def face_facets(
        self, face: str, z_lo_mm: float = -np.inf, z_hi_mm: float = np.inf, across_half_mm: float = np.inf
    ) -> np.ndarray:
        """Facets on an outer ram/housing face (``+X`` ...) within a z range and a band across it."""
        return self.strip_facets(face, z_lo_mm, z_hi_mm, -across_half_mm, across_half_mm)

    def end_facets(self, z_mm: float, half_x_mm: float = np.inf, half_y_mm: float = np.inf) -> np.ndarray:
        """Boundary facets in the plane z = ``z_mm`` (e.g. the ram top or the housing bottom),
        optionally only the central |x| <= half_x_mm, |y| <= half_y_mm patch."""
        return self.facets_where(
            lambda x: (
                (np.abs(x[2] - z_mm) < _TOL_MM)
                & (np.abs(x[0]) <= half_x_mm + _TOL_MM)
                & (np.abs(x[1]) <= half_y_mm + _TOL_MM)
            )
        )

    def strip_facets(
        self, face: str, z_lo_mm: float, z_hi_mm: float, across_lo_mm: float, across_hi_mm: float
    ) -> np.ndarray:
        """Facets on an outer ram face within z_lo..z_hi and across_lo..across_hi (mm; across is
        y on the +-X faces, x on the +-Y faces): a carriage patch on a rail strip."""
        axis = 0 if face[1] == "X" else 1
        half = self.half_width_mm if axis == 0 else self.half_depth_mm
        sign = 1.0 if face[0] == "+" else -1.0
        other = 1 - axis
        return self.facets_where(
            lambda x: (
                (np.abs(x[axis] - sign * half) < _TOL_MM)
                & (x[2] >= z_lo_mm - _TOL_MM)
                & (x[2] <= z_hi_mm + _TOL_MM)
                & (x[other] >= across_lo_mm - _TOL_MM)
                & (x[other] <= across_hi_mm + _TOL_MM)
            )
        )

    def film_surface_facets(self, housing_height_mm: float) -> dict[str, np.ndarray]:
        """Boundary facets by film surface: the four outer ram faces, the cavity, the top ring
        face, the housing sides (and any housing top outside the box) and the housing bottom."""
        f = self.mesh.boundary_facets()
        mid = self.mesh.p[:, self.mesh.facets[:, f]].mean(axis=1)
        z = mid[2]
        hw, hd, L = self.half_width_mm, self.half_depth_mm, self.length_mm
        cavity = self.in_cavity(mid)
        on_ram = (z > _TOL_MM) & (z < L - _TOL_MM) & ~cavity
        out = {
            "cavity": f[cavity],
            "top": f[np.abs(z - L) < _TOL_MM],
            "housing_bottom": f[np.abs(z + housing_height_mm) < _TOL_MM],
        }
        taken = cavity | (np.abs(z - L) < _TOL_MM) | (np.abs(z + housing_height_mm) < _TOL_MM)
        for face, axis, half in (("+X", 0, hw), ("-X", 0, -hw), ("+Y", 1, hd), ("-Y", 1, -hd)):
            sel = on_ram & (np.abs(mid[axis] - half) < _TOL_MM)
            out[face] = f[sel]
            taken |= sel
        out["housing_sides"] = f[~taken]
        return out


def build_mesh(
    *,
    half_width_mm: float,
    half_depth_mm: float,
    wall_mm: float | dict[str, float],
    length_mm: float,
    housing_half_width_mm: float | None = None,
    housing_half_depth_mm: float | None = None,
    housing_height_mm: float = 0.0,
    n_wall: int = 3,
    n_span: int = 12,
    dz_mm: float = 17.0,
    z_breaks_mm=(),
    xy_breaks_mm=(),
    single_spans_mm=(),
    x_breaks_mm=(),
    y_breaks_mm=(),
) -> RamMesh:
    """Mesh a hollow box (z = 0..length) and optionally a solid block below it (z < 0).

    ``n_wall`` elements through the wall, ``n_span`` (even, so the face centre is a grid line)
    across the inner span, elements at most ``dz_mm`` long, grid lines through ``z_breaks_mm``.
    """
    n_span += n_span % 2
    has_housing = housing_height_mm > 0
    extra_x = list(xy_breaks_mm) + list(x_breaks_mm)
    extra_y = list(xy_breaks_mm) + list(y_breaks_mm)
    if has_housing:
        if housing_half_width_mm is None or housing_half_depth_mm is None:
            raise ValueError("a housing (housing_height_mm > 0) needs its half width and half depth")
        extra_x += [-housing_half_width_mm, housing_half_width_mm]
        extra_y += [-housing_half_depth_mm, housing_half_depth_mm]
    walls = walls_per_face(wall_mm)
    cavity = cavity_bounds_mm(half_width_mm, half_depth_mm, walls)
    xs = _cross_lines(half_width_mm, walls["-X"], walls["+X"], n_wall, n_span, extra_x)
    ys = _cross_lines(half_depth_mm, walls["-Y"], walls["+Y"], n_wall, n_span, extra_y)
    z0 = -housing_height_mm if has_housing else 0.0
    breaks = [z0, 0.0, length_mm] + [z for z in z_breaks_mm if z0 <= z <= length_mm]
    zs = _segment_lines(breaks, dz_mm, single_spans_mm)

    full = MeshHex.init_tensor(xs, ys, zs)
    # Cell (iy, ix, iz) of the tensor grid; keep the wall ring above z = 0 and the housing below.
    cx = 0.5 * (xs[:-1] + xs[1:])
    cy = 0.5 * (ys[:-1] + ys[1:])
    cz = 0.5 * (zs[:-1] + zs[1:])
    gy, gx, gz = np.meshgrid(cy, cx, cz, indexing="ij")
    ax, ay = np.abs(gx), np.abs(gy)
    in_ram = (
        (gz > 0)
        & (ax < half_width_mm)
        & (ay < half_depth_mm)
        & ~((gx > cavity[0]) & (gx < cavity[1]) & (gy > cavity[2]) & (gy < cavity[3]))
    )
    in_housing = np.zeros_like(in_ram)
    if has_housing:
        in_housing = (gz < 0) & (ax < housing_half_width_mm) & (ay < housing_half_depth_mm)
    kept = in_ram | in_housing

    # Map skfem's element order to grid cells through the element centroids.
    centroids = full.p[:, full.t].mean(axis=1)
    ex = np.searchsorted(cx, centroids[0] - 1e-9)
    ey = np.searchsorted(cy, centroids[1] - 1e-9)
    ez = np.searchsorted(cz, centroids[2] - 1e-9)
    keep_elements = np.nonzero(kept[ey, ex, ez])[0]
    mesh, old_nodes = full.restrict(keep_elements, return_mapping=True)

    nx, ny, nz = len(xs), len(ys), len(zs)
    node_of = -np.ones((ny, nx, nz), dtype=np.int64)
    # init_tensor numbers grid point (iy, ix, iz) as iy + ny*ix + ny*nx*iz.
    iy = old_nodes % ny
    ix = (old_nodes // ny) % nx
    iz = old_nodes // (ny * nx)
    node_of[iy, ix, iz] = np.arange(len(old_nodes))

    zc = mesh.p[:, mesh.t].mean(axis=1)[2]
    return RamMesh(
        mesh=mesh,
        xs_mm=xs,
        ys_mm=ys,
        zs_mm=zs,
        node_of=node_of,
        cell_kept=kept,
        steel_elements=np.nonzero(zc < 0)[0],
        cfrp_elements=np.nonzero(zc > 0)[0],
        half_width_mm=half_width_mm,
        half_depth_mm=half_depth_mm,
        cavity_mm=cavity,
        length_mm=length_mm,
    )


def carriage_z_mm(machine: Machine, z_axis_mm: float | None = None) -> list[float]:
    """Carriage stations in the ram frame at Z-axis position ``z_axis_mm`` (default: the YAML's).

    The carriages are fixed in the machine and the ram slides through them (Z +up), so raising the
    ram by d moves the stations d lower on the ram and lengthens the lever arm to the TTP.
    """
    s = machine.supports
    z_axis = s.z_axis_mm if z_axis_mm is None else z_axis_mm
    out = []
    for c in s.carriages:
        assert c.z_mm is not None  # Carriage._located requires z_mm or z_range_mm
        out.append(c.z_mm - z_axis)
    return out


def station_ranges_mm(machine: Machine, z_axis_mm: float | None = None) -> list[tuple[float, float]]:
    """Carriage patch z ranges (lo, hi) in the ram frame at Z-axis position ``z_axis_mm``."""
    return machine.supports.station_ranges_mm(z_axis_mm)


def machine_mesh(
    machine: Machine, resolution: float | None = None, z_axis_mm: float | None = None
) -> RamMesh:
    """The twin's mesh of ``machine``: element counts scaled by ``resolution``."""
    m = machine.mesh
    r = m.resolution if resolution is None else float(resolution)
    s = machine.supports
    breaks = [machine.supports.nut.z_mm]
    x_breaks: list[float] = []
    y_breaks: list[float] = []
    stations = s.station_ranges_mm(z_axis_mm)
    single = []
    if s.rails is None:
        # Each shoe patch is one element long: its mean-displacement constraint then couples only
        # two node layers and leaves the band of the layer-ordered stiffness matrix at one section.
        single = stations
    for lo, hi in stations:
        breaks += [lo, hi]
    for rail in s.rails or ():
        (y_breaks if rail.face[1] == "X" else x_breaks).extend(rail.across_mm)
    if machine.tool.nose_patch_mm is not None:
        x_breaks += [-machine.tool.nose_patch_mm[0] / 2, machine.tool.nose_patch_mm[0] / 2]
        y_breaks += [-machine.tool.nose_patch_mm[1] / 2, machine.tool.nose_patch_mm[1] / 2]
    for h in machine.thermal.sources:
        # Heat zones snap to grid lines, so the zone's volume or area is exact.
        breaks += list(h.z_mm or ())
        if h.kind == "volume":
            x_breaks += list(h.x_mm or ())
            y_breaks += list(h.y_mm or ())
    for sensor in machine.sensors + machine.candidate_sensors:
        breaks += [sensor.z_start_mm, sensor.z_end_mm]
    # a point probe has all three coordinates (Probe._located)
    breaks += [p.z_mm for p in machine.probes if p.kind == "point" and p.z_mm is not None]
    hw, hd = machine.ram.outer_width_mm / 2, machine.ram.outer_depth_mm / 2
    x_breaks = [v for v in x_breaks if abs(v) < hw]
    y_breaks = [v for v in y_breaks if abs(v) < hd]
    return build_mesh(
        half_width_mm=hw,
        half_depth_mm=hd,
        wall_mm=machine.ram.walls_mm,
        length_mm=machine.ram.length_mm,
        housing_half_width_mm=machine.housing.width_mm / 2,
        housing_half_depth_mm=machine.housing.depth_mm / 2,
        housing_height_mm=machine.housing.height_mm,
        n_wall=max(1, round(m.wall_elements * r)),
        n_span=max(2, round(m.span_elements * r)),
        dz_mm=m.dz_mm / r,
        z_breaks_mm=breaks,
        # Off-centre sensor paths get their own grid line; support patches snap to the grid.
        xy_breaks_mm=[s_.offset_mm for s_ in machine.sensors + machine.candidate_sensors],
        single_spans_mm=single,
        x_breaks_mm=x_breaks,
        y_breaks_mm=y_breaks,
    )
