"""The paper's kinematic model (sec. 2.3, eq. 4-10): the ram as a chain of elementary parallel
manipulators whose "bars" are the FBG sensor paths.

Over 600 lines as one unit: the paper's eq. 4-10 in one place, from the HTM core to the TTP chain,
so that it reads beside the paper.

Three layers, all pure and vectorised over time samples:

1. **HTM core** (eq. 5-9): :func:`m_a`, :func:`m_b`, :func:`m_c` exactly as the paper writes them,
   their product per segment (:func:`segment_htm`, eq. 5), the chain product M_0n
   (:func:`chain_htm`, eq. 9) and the TTP position (:func:`ttp_position_mm`, eq. 10).
2. **Segment kinematics from elongations** (eq. 4): the ram is cut into segments at every sensor
   end, support station and material change. For a segment whose end sections are joined by bars
   at cross-section positions (x_k, y_k) mm, small-deformation plane-section kinematics give

       dL_k = c + beta * x_k - alpha * y_k          (µm, rad, mm)

   **Sign convention**: the chain runs *down* the ram, from the support at the top to the TTP.
   ``alpha`` is the rotation (rad) of a segment's lower section relative to its upper section
   about +X, ``beta`` about +Y (right-handed, ram frame: Z up, z = 0 at the spindle end), ``c``
   the segment's axial elongation (µm). A positive ``alpha`` moves everything below towards +Y,
   a positive ``beta`` towards -X; a bar on the +Y face shortens when ``alpha`` > 0.
   :func:`segment_kinematics` solves (alpha, beta, c) per segment by least squares and reports
   which segments are determined (>= 3 independent bars), underdetermined or unsensed.
3. **Closure and chain** (:class:`KinematicChain`): the segments the bars do not determine
   (the paper's single S5 above S1-S4, the spans without sensors, the steel housing, the shear
   offsets ``a``, ``b`` of eq. 6-7 which axial bars cannot see) are filled by an explicit,
   reported beam closure built from the machine description: the bending the bars measure is
   attributed to a tool-tip force (moment linear in the lever arm to the TTP, section stiffness
   of the CFRP box and the steel housing, Timoshenko shear, the span between the two carriage
   stations reacting the moment), the axial strain is the bars' mean strain, and the housing
   expands with its probe temperature. The chain is then closed on the supports: a rigid base
   motion puts both carriage stations back on their guides (lateral) and the nut back on the
   screw (axial), which is where the Z position of the axis enters (it moves the carriage
   stations along the ram and so the lever arm to the TTP).

Units: geometry mm, elongations and displacements µm, angles rad, forces N, temperatures K.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, field

import numpy as np

UM_PER_MM = 1000.0
_EYE4 = np.eye(4)
_RANK_TOL = 1e-9


# --------------------------------------------------------------------------- HTM core (eq. 5-10)
def _stack(entries, shape):
    """(…, 4, 4) array from a 4x4 nested list of broadcastable entries."""
    out = np.zeros((*shape, 4, 4))
    for i in range(4):
        for j in range(4):
            out[..., i, j] = entries[i][j]
    return out


def _shape(*args):
    return np.broadcast(*args).shape  # (np.broadcast_shapes: the same, at ten times the cost)


def m_a(alpha_rad, a_mm=0.0):
    """Paper eq. 6: rotation ``alpha`` about X with translation ``a`` along X, shape (…, 4, 4)."""
    al, a = np.asarray(alpha_rad, dtype=float), np.asarray(a_mm, dtype=float)
    s = _shape(al, a)
    c, sn = np.cos(al), np.sin(al)
    return _stack([[1, 0, 0, a], [0, c, -sn, 0], [0, sn, c, 0], [0, 0, 0, 1]], s)


def m_b(beta_rad, b_mm=0.0):
    """Paper eq. 7: rotation ``beta`` about Y with translation ``b`` along Y, shape (…, 4, 4)."""
    be, b = np.asarray(beta_rad, dtype=float), np.asarray(b_mm, dtype=float)
    s = _shape(be, b)
    c, sn = np.cos(be), np.sin(be)
    return _stack([[c, 0, sn, 0], [0, 1, 0, b], [-sn, 0, c, 0], [0, 0, 0, 1]], s)


def m_c(c_mm):
    """Paper eq. 8: translation ``c`` along Z, shape (…, 4, 4)."""
    c = np.asarray(c_mm, dtype=float)
    return _stack([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, c], [0, 0, 0, 1]], c.shape)


def segment_htm(alpha_rad, beta_rad, c_mm, a_mm=0.0, b_mm=0.0):
    """Paper eq. 5: ``M_{i-1,i} = M_a(alpha, a) · M_b(beta, b) · M_c(c)``, shape (…, 4, 4).

    The product multiplied out (the same matrix to rounding, ``test_kinematics``): two batched
    4x4 products over every frame and segment were most of a campaign's chain evaluation."""
    al, be = np.asarray(alpha_rad, dtype=float), np.asarray(beta_rad, dtype=float)
    c, a, b = (np.asarray(v, dtype=float) for v in (c_mm, a_mm, b_mm))
    ca, sa, cb, sb = np.cos(al), np.sin(al), np.cos(be), np.sin(be)
    out = np.zeros((*_shape(al, be, c, a, b), 4, 4))
    out[..., 0, 0] = cb
    out[..., 0, 2] = sb
    out[..., 0, 3] = a + sb * c
    out[..., 1, 0] = sa * sb
    out[..., 1, 1] = ca
    out[..., 1, 2] = -sa * cb
    out[..., 1, 3] = ca * b - sa * cb * c
    out[..., 2, 0] = -ca * sb
    out[..., 2, 1] = sa
    out[..., 2, 2] = ca * cb
    out[..., 2, 3] = sa * b + ca * cb * c
    out[..., 3, 3] = 1.0
    return out


def chain_htm(segment_htms):
    """Paper eq. 9: ``M_0n = prod_i M_{i-1,i}`` over axis -3 of (…, n_segments, 4, 4)."""
    m = np.asarray(segment_htms, dtype=float)
    out = m[..., 0, :, :]
    for i in range(1, m.shape[-3]):
        out = out @ m[..., i, :, :]
    return out


def chain_frames(segment_htms):
    """Cumulative products M_00 (identity), M_01, …, M_0n: shape (…, n_segments + 1, 4, 4)."""
    m = np.asarray(segment_htms, dtype=float)
    out = np.empty((*m.shape[:-3], m.shape[-3] + 1, 4, 4))
    if m.ndim == 4 and m.shape[0] == 1:  # one frame: 2-D products, half the per-call cost
        o, mm = out[0], m[0]
        o[0] = _EYE4
        for i in range(mm.shape[0]):
            np.dot(o[i], mm[i], out=o[i + 1])
        return out
    out[..., 0, :, :] = _EYE4
    for i in range(m.shape[-3]):  # products written in place: no list of frames to stack
        np.matmul(out[..., i, :, :], m[..., i, :, :], out=out[..., i + 1, :, :])
    return out


def ttp_position_mm(m_0n, ttp_local_mm=(0.0, 0.0, 0.0)):
    """Paper eq. 10: the TTP (x, y, z) in mm of a point given in the last frame, (…, 3)."""
    p = np.append(np.asarray(ttp_local_mm, dtype=float), 1.0)
    return (np.asarray(m_0n) @ p)[..., :3]


# ------------------------------------------------------------------------ bars on the section
def bar_position_mm(
    face: str, offset_mm: float, half_width_mm: float, half_depth_mm: float, depth_mm: float = 0.0
):
    """Cross-section position (x, y) in mm of a path in a wall, ``depth_mm`` in from the face's
    outer surface (as the twin meshes it)."""
    sign = 1.0 if face[0] == "+" else -1.0
    if face[1] == "X":
        return sign * (half_width_mm - depth_mm), float(offset_mm)
    return float(offset_mm), sign * (half_depth_mm - depth_mm)


def bar_elongation_um(alpha_rad, beta_rad, c_um, bar_xy_mm, length_mm):
    """Exact elongations (µm) of bars joining two sections of one segment (forward model).

    The upper section is the reference frame; the lower section's frame is the segment's HTM
    (rotation placed at mid-length, see :class:`KinematicChain`). Bars join (x, y) on both.
    ``alpha``, ``beta``, ``c`` broadcast over leading axes; ``bar_xy_mm`` is (B, 2). Returns (…, B).
    """
    al, be, c = np.broadcast_arrays(*(np.asarray(v, dtype=float) for v in (alpha_rad, beta_rad, c_um)))
    xy = np.asarray(bar_xy_mm, dtype=float)
    half = length_mm / 2.0
    m = m_c(-half) @ segment_htm(al, be, -(half + c / UM_PER_MM))
    upper = np.stack([xy[:, 0], xy[:, 1], np.zeros(len(xy)), np.ones(len(xy))], axis=-1)
    lower = np.einsum("...ij,bj->...bi", m, upper)[..., :3]
    d = lower - upper[:, :3]
    return (np.sqrt(np.sum(d**2, axis=-1)) - length_mm) * UM_PER_MM


def elongation_design(bar_xy_mm, cover) -> np.ndarray:
    """Design A (B, 3K) of the plane-section relation: dL = A @ [alpha_1, beta_1, c_1, …].

    ``cover`` (B, K) is 1 where bar b spans segment k (a bar may span several segments).
    Columns per segment: alpha (rad, µm/rad = -y*1000), beta (x*1000), c (µm).
    """
    xy = np.asarray(bar_xy_mm, dtype=float)
    cover = np.asarray(cover, dtype=float)
    B, K = cover.shape
    A = np.zeros((B, 3 * K))
    A[:, 0::3] = cover * (-xy[:, 1:2] * UM_PER_MM)
    A[:, 1::3] = cover * (xy[:, 0:1] * UM_PER_MM)
    A[:, 2::3] = cover
    return A


@dataclass
class SegmentStatus:
    """What the bars tell about one segment."""

    z_lo_mm: float
    z_hi_mm: float
    material: str  # cfrp, steel, tool
    bars: list  # sensor names spanning it
    independent_bars: int  # rank of the segment's own columns over its bars
    status: str  # determined, underdetermined, unsensed, rigid
    closure: str = ""  # how the chain fills what the bars do not give

    def line(self) -> str:
        """One report line: z range (mm), material, spanning bars, independent bars, status, closure."""
        bars = ",".join(self.bars) or "-"
        return (
            f"z {self.z_lo_mm:8.1f} .. {self.z_hi_mm:8.1f} mm  {self.material:<6}"
            f" bars {bars:<16} independent {self.independent_bars}  {self.status:<15}"
            f" {self.closure}"
        )


def segment_kinematics(elongation_um, bar_xy_mm, cover):
    """Least-squares (alpha, beta, c) of every segment from bar elongations (eq. 4 + plane sections).

    Parameters
    ----------
    elongation_um : (n, B) bar elongations, µm
    bar_xy_mm : (B, 2) bar positions on the cross-section, mm
    cover : (B, K) 1 where bar b spans segment k

    Returns
    -------
    params : (n, K, 3) alpha (rad), beta (rad), c (µm); minimum-norm where not determined
    determined : (K,) bool, all three parameters identifiable from the bars
    rank : (K,) int, number of independent bar equations on each segment's own parameters
    """
    A = elongation_design(bar_xy_mm, cover)
    K = A.shape[1] // 3
    pinv, identifiable = _identifiable_pinv(A)
    params = (np.atleast_2d(elongation_um) @ pinv.T).reshape(-1, K, 3)
    rank = np.array(
        [
            np.linalg.matrix_rank(A[cover[:, k] > 0][:, 3 * k : 3 * k + 3] * _col_scale(), tol=1e-6)
            if np.any(cover[:, k] > 0)
            else 0
            for k in range(K)
        ]
    )
    return params, identifiable.reshape(K, 3).all(axis=1), rank


def _col_scale():
    # alpha, beta columns are ~1e5 µm/rad, c ~1: scale to comparable size before rank tests.
    return np.array([1e-5, 1e-5, 1.0])


def _identifiable_pinv(A):
    """Pseudo-inverse of A and which parameters are identifiable (not touched by the null space)."""
    n_par = A.shape[1]
    scale = np.tile(_col_scale(), n_par // 3)
    As = A * scale
    _u, s, vt = np.linalg.svd(As, full_matrices=True)
    tol = _RANK_TOL * (s[0] if s.size else 1.0) * max(As.shape)
    r = int(np.sum(s > tol))
    null = vt[r:].T  # (n_par, n_null)
    identifiable = np.sqrt(np.sum(null**2, axis=1)) < 1e-6
    pinv = np.linalg.pinv(As, rcond=max(tol / s[0], 1e-15) if s.size else 1e-15) * scale[:, None]
    return pinv, identifiable


# ------------------------------------------------------------------------------ section physics
@dataclass(frozen=True)
class Section:
    """Beam properties of a stretch of the structure (mm, MPa)."""

    EI_x: float  # bending about X (curvature alpha per mm), N mm^2
    EI_y: float  # bending about Y, N mm^2
    GA_x: float  # shear stiffness for forces along X, N
    GA_y: float  # shear stiffness for forces along Y, N
    cte_per_K: float  # axial thermal expansion


def ram_centroid_mm(machine) -> tuple[float, float]:
    """Centroid (x, y) in mm of the ram box's section: the axis it bends about. On the ram axis
    when opposite walls are equal; towards the thicker wall otherwise."""
    r = machine.ram
    W, D = r.outer_width_mm, r.outer_depth_mm
    x_lo, x_hi, y_lo, y_hi = r.cavity_mm
    w, d = x_hi - x_lo, y_hi - y_lo
    area = W * D - w * d
    return -w * d * 0.5 * (x_lo + x_hi) / area, -w * d * 0.5 * (y_lo + y_hi) / area


def ram_section(machine) -> Section:
    """Beam section of the hollow CFRP ram box: bending with E_L over the box's second moments
    about its centroid (:func:`ram_centroid_mm`), shear with G_LT over the two webs (N mm², N)."""
    r, m = machine.ram, machine.materials.cfrp
    W, D, t = r.outer_width_mm, r.outer_depth_mm, r.walls_mm
    x_lo, x_hi, y_lo, y_hi = r.cavity_mm
    w, d = x_hi - x_lo, y_hi - y_lo
    cx, cy = 0.5 * (x_lo + x_hi), 0.5 * (y_lo + y_hi)
    xc, yc = ram_centroid_mm(machine)
    area = W * D - w * d
    E, G = 1e3 * m.E_L_GPa, 1e3 * m.G_LT_GPa
    # Second moments about the box centre (the cavity's about its own centre moved by the
    # parallel-axis term), then about the centroid; shear is carried by the walls parallel to
    # the force (the webs: the +-Y walls for a force along X).
    i_x = (W * D**3 - w * d**3) / 12 - w * d * cy**2 - area * yc**2
    i_y = (D * W**3 - d * w**3) / 12 - w * d * cx**2 - area * xc**2
    return Section(
        EI_x=E * i_x,
        EI_y=E * i_y,
        GA_x=G * (t["+Y"] + t["-Y"]) * W,
        GA_y=G * (t["+X"] + t["-X"]) * D,
        cte_per_K=m.cte_L_per_K,
    )


def housing_section(machine) -> Section:
    """Beam section of the solid steel housing block: bending over the full rectangle, shear with
    the solid rectangle's 5/6 factor (N mm², N)."""
    h, s = machine.housing, machine.materials.steel
    E = 1e3 * s.E_GPa
    G = E / (2 * (1 + s.nu))
    A = h.width_mm * h.depth_mm
    return Section(
        EI_x=E * h.width_mm * h.depth_mm**3 / 12,
        EI_y=E * h.depth_mm * h.width_mm**3 / 12,
        GA_x=G * A * 5 / 6,
        GA_y=G * A * 5 / 6,
        cte_per_K=s.cte_per_K,
    )


# ------------------------------------------------------------------------------- the chain
@dataclass
class _Segment:
    z_lo: float
    z_hi: float
    material: str


def housing_probe(machine) -> str | None:
    """The point probe inside (or on) the steel housing, nearest to its centre; None if none
    (:meth:`fbgcomp.structure.Machine.housing_probe_names`)."""
    names = machine.housing_probe_names()
    return names[0] if names else None


#: Compliance factors of the beam closure (:class:`KinematicChain` ``closure_factors``).
CLOSURE_FACTORS = ("bending_x", "bending_y", "shear_x", "shear_y")


@dataclass
class KinematicChain:
    """Compiled kinematic model of one machine, sensor set and Z position.

    Parameters
    ----------
    machine : fbgcomp.structure.Machine
        Geometry (ram, housing, tool), materials, supports and sensor paths.
    sensor_names : list of str, optional
        Bars available (default: every sensor of the machine); the others are ignored.
    z_axis_mm : float, optional
        Z-axis position (default: the machine description's).
    closure_factors : dict, optional
        Dimensionless factors on the beam closure's compliances (default: all 1, the machine
        description's section properties): ``bending_x`` / ``bending_y`` multiply the bending
        compliance (1/EI) of the segments the closure fills, for a TTP force along X / Y;
        ``shear_x`` / ``shear_y`` the Timoshenko shear compliance (1/GA) of every segment. The
        force itself is still read from the bars with the nominal sections, so a factor of 1 is
        the fit-free closure and a factor k makes that stretch k times as compliant *relative to
        the sensed ones* (:data:`CLOSURE_FACTORS`).
    """

    machine: object
    sensor_names: list | None = None
    z_axis_mm: float | None = None
    closure_factors: dict | None = None
    segments: list = field(init=False)
    report: list = field(init=False)

    def __post_init__(self):
        m = self.machine
        if self.sensor_names is None:
            self.sensor_names = [s.name for s in m.sensors]
        by_name = {s.name: s for s in list(m.sensors) + list(m.candidate_sensors)}
        self.sensors = [by_name[n] for n in self.sensor_names]
        self.z_axis_mm = m.supports.z_axis_mm if self.z_axis_mm is None else float(self.z_axis_mm)
        s = m.supports
        # The chain's reacting span runs from the lowest to the highest carriage station (their
        # patch centres): with more than two stations the inner ones are taken as riding on that
        # span, and rails on one face are read as guides (their side does not enter the chain).
        stations = sorted(c.z_mm - self.z_axis_mm for c in s.carriages)
        self.carriage_z_mm = [stations[0], stations[-1]]
        self.nut_z_mm = s.nut.z_mm
        self.ttp_z_mm = m.ttp_z_mm
        hh, L = m.housing.height_mm, m.ram.length_mm
        top = max(L, self.nut_z_mm, self.carriage_z_mm[1])
        breaks = {top, L, 0.0, -hh, self.ttp_z_mm, *self.carriage_z_mm, self.nut_z_mm}
        for sn in self.sensors:
            breaks |= {sn.z_start_mm, sn.z_end_mm}
        z = np.array(sorted(breaks, reverse=True))
        z = z[np.concatenate([[True], np.abs(np.diff(z)) > 1e-6])]
        self.segments = []
        for hi, lo in itertools.pairwise(z):
            mat = "cfrp" if lo >= -1e-9 else ("steel" if lo >= -hh - 1e-9 else "tool")
            self.segments.append(_Segment(float(lo), float(hi), mat))
        self.top_z_mm = float(z[0])
        K = len(self.segments)
        hw, hd = m.ram.outer_width_mm / 2, m.ram.outer_depth_mm / 2
        # Bars from the section's centroid, the axis the segments bend about.
        self.bar_xy_mm = np.array(
            [bar_position_mm(sn.face, sn.offset_mm, hw, hd, sn.depth_mm) for sn in self.sensors]
        ).reshape(-1, 2) - np.asarray(ram_centroid_mm(m))
        self.cover = np.array(
            [
                [
                    1.0 if (g.z_lo >= sn.z_start_mm - 1e-6 and g.z_hi <= sn.z_end_mm + 1e-6) else 0.0
                    for g in self.segments
                ]
                for sn in self.sensors
            ]
        ).reshape(-1, K)
        self.lengths_mm = np.array([g.z_hi - g.z_lo for g in self.segments])
        self.housing_probe = housing_probe(m)
        self._compile()

    # -- closure from the machine description -------------------------------------------
    def _closure_basis(self):
        """Segment parameters per unit generalized load, (K, 5, 2 + G).

        Generalized loads: Fx, Fy (N, at the TTP) and one axial strain per sensed CFRP segment
        (G of them). Axial strain is local (temperature varies along the ram), so every
        sensed segment keeps its own and unsensed CFRP segments take the nearest sensed one's
        (the mean of both neighbours when equidistant); bending from a TTP force is global.
        Parameters per segment: alpha rad, beta rad, c µm, a µm, b µm.
        """
        ram, hs = ram_section(self.machine), housing_section(self.machine)
        z_lc, z_uc, z_t = self.carriage_z_mm[0], self.carriage_z_mm[1], self.ttp_z_mm
        sensed = [k for k, g in enumerate(self.segments) if g.material == "cfrp" and self.cover[:, k].any()]
        self.axial_groups = sensed
        G = np.zeros((len(self.segments), 5, 2 + len(sensed)))
        lever_lc = z_lc - z_t
        mids = np.array([0.5 * (g.z_lo + g.z_hi) for g in self.segments])
        for k, g in enumerate(self.segments):
            if g.material == "tool":
                continue
            sec = ram if g.material == "cfrp" else hs
            L = g.z_hi - g.z_lo
            # Moment per unit TTP force M(z) and shear V: cantilever below the lower carriage,
            # the reacting span between the carriages, nothing above the upper one.
            zm = mids[k]
            if zm <= z_lc:
                moment_int = L * (zm - z_t)  # ∫ (z - z_ttp) dz over the segment
                shear = 1.0
            elif zm <= z_uc:
                a = z_uc - z_lc
                moment_int = lever_lc * L * (z_uc - zm) / a
                shear = -lever_lc / a
            else:
                moment_int, shear = 0.0, 0.0
            G[k, 0, 1] = moment_int / sec.EI_x  # alpha from Fy
            G[k, 1, 0] = -moment_int / sec.EI_y  # beta from Fx
            G[k, 3, 0] = UM_PER_MM * shear * L / sec.GA_x  # a from Fx (µm)
            G[k, 4, 1] = UM_PER_MM * shear * L / sec.GA_y  # b from Fy (µm)
            if g.material == "cfrp" and zm <= self.nut_z_mm and sensed:
                if k in sensed:
                    G[k, 2, 2 + sensed.index(k)] = UM_PER_MM * L  # c = eps * L (µm)
                else:
                    d = np.abs(mids[sensed] - zm)
                    near = np.nonzero(d <= d.min() + 1e-6)[0]
                    G[k, 2, 2 + near] = UM_PER_MM * L / len(near)
        return G

    def _compile(self):
        K, S = len(self.segments), len(self.sensors)
        G = self._closure_basis()  # (K, 5, 2 + G)
        f = dict.fromkeys(CLOSURE_FACTORS, 1.0)
        unknown = set(self.closure_factors or {}) - set(CLOSURE_FACTORS)
        if unknown:
            raise ValueError(f"unknown closure factors {sorted(unknown)}; expected {CLOSURE_FACTORS}")
        f.update({k: float(v) for k, v in (self.closure_factors or {}).items()})
        self.closure_factors = f
        # The force is read from the bars through the nominal sections (G); the closure fills
        # segments with the factored compliances (Gf): the factors say how compliant the
        # unsensed stretches and the shear are relative to what the bars see.
        Gf = G.copy()
        Gf[:, 1, 0] *= f["bending_x"]
        Gf[:, 0, 1] *= f["bending_y"]
        Gf[:, 3, 0] *= f["shear_x"]
        Gf[:, 4, 1] *= f["shear_y"]
        params_meas = np.zeros((K, 5, S))
        if S:
            A = elongation_design(self.bar_xy_mm, self.cover)  # (S, 3K)
            pinv, ident = _identifiable_pinv(A)
            determined = ident.reshape(K, 3).all(axis=1)
            # Generalized loads from all bars: dL = A (G3 g) -> g = pinv(A G3) dL.
            AG = A @ G[:, :3, :].reshape(3 * K, G.shape[2])
            used = np.linalg.norm(AG, axis=0) > 0
            gmap = np.zeros((G.shape[2], S))
            if used.any():
                gmap[used] = (
                    np.linalg.pinv(AG[:, used] / np.linalg.norm(AG[:, used], axis=0), rcond=1e-10)
                    / np.linalg.norm(AG[:, used], axis=0)[:, None]
                )
            self.load_identifiable = used & (
                np.linalg.matrix_rank(AG[:, used]) == used.sum() if used.any() else used
            )
            closure = np.einsum("kpg,gs->kps", Gf, gmap)  # (K, 5, S)
            direct = pinv.reshape(K, 3, S)
            params_meas = closure.copy()
            params_meas[determined, :3, :] = direct[determined]
            self.load_map = gmap
        else:
            determined = np.zeros(K, bool)
            self.load_map = np.zeros((G.shape[2], 0))
            self.load_identifiable = np.zeros(G.shape[2], bool)
        self.determined = determined
        # Projector on what plane sections cannot explain (the bar equations' residual): zero
        # unless bars are redundant; large when a reading contradicts its neighbours (a grating
        # compensated with the wrong temperature, a local strain the sections do not carry).
        if S:
            self.inconsistency_projector = np.eye(S) - A @ pinv
        else:
            self.inconsistency_projector = np.zeros((0, 0))
        self.param_map = params_meas  # (K, 5, S) per µm of bar
        # Housing thermal expansion per K of its probe (steel, free expansion).
        self.param_housing = np.zeros((K, 5))
        hs = housing_section(self.machine)
        for k, g in enumerate(self.segments):
            if g.material == "steel":
                self.param_housing[k, 2] = UM_PER_MM * hs.cte_per_K * (g.z_hi - g.z_lo)
        self._nominal = self._chain(np.zeros((1, K, 5)))[0]
        self.report = self._report()

    def _report(self) -> list:
        names = self.sensor_names
        assert names is not None  # __post_init__ fills in the default
        out = []
        for k, g in enumerate(self.segments):
            bars = [names[i] for i in np.nonzero(self.cover[:, k])[0]]
            rank = 0
            if bars:
                A = elongation_design(self.bar_xy_mm, self.cover)
                rows = self.cover[:, k] > 0
                rank = int(np.linalg.matrix_rank(A[rows][:, 3 * k : 3 * k + 3] * _col_scale(), tol=1e-6))
            if g.material == "tool":
                status, closure = "rigid", "tool: rigid extension"
            elif self.determined[k]:
                status, closure = "determined", "alpha, beta, c from bars; shear a, b: beam closure"
            elif bars:
                status = "underdetermined"
                closure = (
                    f"{rank} independent bar(s) < 3: bending from beam closure (TTP force), "
                    "axial strain from its bars"
                )
            else:
                status = "unsensed"
                closure = (
                    "beam closure (TTP force), axial strain of the nearest sensed segment"
                    if g.material == "cfrp"
                    else (
                        f"steel: beam closure, thermal expansion from probe {self.housing_probe}"
                        if self.housing_probe
                        else "steel: beam closure, no housing probe: isothermal"
                    )
                )
            out.append(SegmentStatus(g.z_lo, g.z_hi, g.material, bars, rank, status, closure))
        return out

    @property
    def underdetermined(self) -> list:
        """Segments the bars do not fully determine (filled by the closure), as reports."""
        return [r for r in self.report if r.status in ("underdetermined", "unsensed")]

    def format_report(self) -> str:
        """The chain's layout (Z axis, carriages, nut, TTP in mm, ram frame) and one line per segment."""
        head = (
            f"kinematic chain at Z = {self.z_axis_mm:g} mm: carriages at "
            f"{self.carriage_z_mm[0]:g}, {self.carriage_z_mm[1]:g} mm, nut at {self.nut_z_mm:g} mm, "
            f"TTP at {self.ttp_z_mm:g} mm (ram frame)"
        )
        return "\n".join([head] + [r.line() for r in self.report])

    # -- evaluation ----------------------------------------------------------------------
    def segment_parameters(self, elongation_um, housing_dT_K=None):
        """(n, K, 5): alpha rad, beta rad, c µm, a µm, b µm of every segment."""
        dl = np.atleast_2d(np.asarray(elongation_um, dtype=float))
        p = (
            np.einsum("kps,ns->nkp", self.param_map, dl)
            if dl.shape[1]
            else np.zeros((dl.shape[0], *self.param_map.shape[:2]))
        )
        if housing_dT_K is not None:
            p = p + np.asarray(housing_dT_K, dtype=float).reshape(-1, 1, 1) * self.param_housing[None]
        return p

    def _chain(self, params):
        """Positions (n, K+1, 3) mm of the section centres, chain from the top, closed on supports."""
        al, be = params[..., 0], params[..., 1]
        c_mm, a_mm, b_mm = (params[..., i] / UM_PER_MM for i in (2, 3, 4))
        half = self.lengths_mm / 2.0
        # Each segment: half its length, then its rotation, then the other half plus its
        # stretch (eq. 5 with the rotation at mid-length, exact for a uniform curvature); going
        # down the ram, so translations along Z are negative.
        seg = segment_htm(al, be, -(half + c_mm), a_mm, b_mm)
        seg[..., 2, 3] -= half  # M_c(-half) @ seg: a translation along Z before it
        frames = chain_frames(seg)  # (n, K+1, 4, 4)
        pos = frames[..., :3, 3]
        return pos

    def support_deflection_um(self, force_N):
        """Lateral deflection (n, 2, 2) µm of the (lower, upper) carriage stations in (x, y)
        under TTP forces (n, 2) N (Fx, Fy): statics of the two stations, the machine
        description's carriage stiffness (N/µm per direction)."""
        F = np.atleast_2d(np.asarray(force_N, dtype=float))
        z_lc, z_uc = self.carriage_z_mm
        a = z_uc - z_lc
        k = self.machine.supports.carriage_stiffness_value_N_per_um  # inf: rigid carriages
        # The ram pushes on the lower station with F (z_uc - z_t) / a and pulls on the upper one
        # with F (z_lc - z_t) / a: each station yields by its load over its stiffness.
        lower = F * (z_uc - self.ttp_z_mm) / (a * k)
        upper = -F * (z_lc - self.ttp_z_mm) / (a * k)
        return np.stack([lower, upper], axis=1)

    def _stations(self):
        """Sections nearest the (lower, upper) carriage stations and the nut, and the stations'
        depths below the top point (mm): a property of the chain, found once."""
        if getattr(self, "_station_cache", None) is None:
            zb = self.top_z_mm - np.concatenate([[0.0], np.cumsum(self.lengths_mm)])
            i_lc, i_uc = (int(np.argmin(np.abs(zb - z))) for z in self.carriage_z_mm)
            i_nut = int(np.argmin(np.abs(zb - self.nut_z_mm)))
            self._station_cache = (i_lc, i_uc, i_nut, self.top_z_mm - zb[i_lc], self.top_z_mm - zb[i_uc])
        return self._station_cache

    def deflection_um(self, params, support_um=None):
        """TTP deviation (n, 3) µm from segment parameters (n, K, 5), closed on the supports.

        ``support_um`` (n, 2, 2): lateral (x, y) displacement of the (lower, upper) carriage
        stations (their guides' compliance); None: rigid guides.
        """
        pos = self._chain(params)
        if len(pos) == 1:  # one frame (a runtime batch of 1): the closure on Python floats
            return self._closure_one(pos[0], None if support_um is None else support_um[0])
        u = (pos - self._nominal[None]) * UM_PER_MM  # (n, K+1, 3)
        i_lc, i_uc, i_nut, h_lc, h_uc = self._stations()
        if support_um is not None:
            # Close on the guides' displaced positions: shift the targets by their deflection.
            u = u.copy()
            u[:, i_lc, :2] -= support_um[:, 0, :]
            u[:, i_uc, :2] -= support_um[:, 1, :]
        # Rigid base motion (small rotation phi about the top point + translation t) that puts
        # both carriage stations back on their guides and the nut on the screw. A base
        # rotation about X by phi moves a point h below the top by +h*phi in Y, about Y by -h*phi in X.
        phi_x = -(u[:, i_lc, 1] - u[:, i_uc, 1]) / ((h_lc - h_uc) * UM_PER_MM)  # rad
        t_y = -u[:, i_uc, 1] - h_uc * UM_PER_MM * phi_x  # µm
        phi_y = (u[:, i_lc, 0] - u[:, i_uc, 0]) / ((h_lc - h_uc) * UM_PER_MM)
        t_x = -u[:, i_uc, 0] + h_uc * UM_PER_MM * phi_y
        t_z = -u[:, i_nut, 2]
        base = segment_htm(phi_x, phi_y, t_z / UM_PER_MM, t_x / UM_PER_MM, t_y / UM_PER_MM)
        tip_rel = pos[:, -1, :]  # relative to the top point
        tip = np.einsum("nij,nj->ni", base[..., :3, :3], tip_rel) + base[..., :3, 3]
        return (tip - self._nominal[-1][None]) * UM_PER_MM

    def _closure_one(self, pos, support_um):
        """:meth:`deflection_um`'s closure of one frame from its section positions (K+1, 3) mm
        and carriage displacements (2, 2) µm or None: the same arithmetic on Python floats,
        where numpy's per-call cost on a dozen numbers was the time."""
        i_lc, i_uc, i_nut, h_lc, h_uc = self._stations()
        nom = self._nominal
        u_lc = ((pos[i_lc] - nom[i_lc]) * UM_PER_MM).tolist()
        u_uc = ((pos[i_uc] - nom[i_uc]) * UM_PER_MM).tolist()
        t_z = -float((pos[i_nut, 2] - nom[i_nut, 2]) * UM_PER_MM)
        if support_um is not None:
            (s_lx, s_ly), (s_ux, s_uy) = support_um.tolist()
            u_lc[0], u_lc[1], u_uc[0], u_uc[1] = (
                u_lc[0] - s_lx,
                u_lc[1] - s_ly,
                u_uc[0] - s_ux,
                u_uc[1] - s_uy,
            )
        h_lc, h_uc = float(h_lc), float(h_uc)
        phi_x = -(u_lc[1] - u_uc[1]) / ((h_lc - h_uc) * UM_PER_MM)
        t_y = -u_uc[1] - h_uc * UM_PER_MM * phi_x
        phi_y = (u_lc[0] - u_uc[0]) / ((h_lc - h_uc) * UM_PER_MM)
        t_x = -u_uc[0] + h_uc * UM_PER_MM * phi_y
        # segment_htm(phi_x, phi_y, t_z, t_x, t_y) (mm) applied to the tip, written out
        a, b, c = t_x / UM_PER_MM, t_y / UM_PER_MM, t_z / UM_PER_MM
        ca, sa, cb, sb = math.cos(phi_x), math.sin(phi_x), math.cos(phi_y), math.sin(phi_y)
        x, y, z = pos[-1].tolist()
        tip = (
            cb * x + 0.0 * y + sb * z + (a + sb * c),
            sa * sb * x + ca * y + -sa * cb * z + (ca * b - sa * cb * c),
            -ca * sb * x + sa * y + ca * cb * z + (sa * b + ca * cb * c),
        )
        n_tip = nom[-1].tolist()
        return np.array([[(tip[i] - n_tip[i]) * UM_PER_MM for i in range(3)]])

    def ttp_deviation_um(self, elongation_um, housing_dT_K=None):
        """TTP deviation (n, 3) µm from bar elongations (n, S) µm and the housing probe's ΔT (n,) K."""
        dl = np.atleast_2d(np.asarray(elongation_um, dtype=float))
        force = dl @ self.load_map[:2].T if dl.shape[1] else np.zeros((len(dl), 2))
        return self.deflection_um(
            self.segment_parameters(dl, housing_dT_K), self.support_deflection_um(force)
        )

    def jacobian(self):
        """Linear maps: TTP µm per µm of each bar (3, S) and per K of housing probe (3,)."""
        if getattr(self, "_jacobian", None) is None:
            S = len(self.sensors)
            J = self.ttp_deviation_um(np.eye(S)).T if S else np.zeros((3, 0))
            Jh = self.ttp_deviation_um(np.zeros((1, S)), np.ones(1))[0]
            self._jacobian = (J, Jh)
        return self._jacobian
