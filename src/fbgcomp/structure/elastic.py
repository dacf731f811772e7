"""Linear thermo-elasticity of the ram: transversely isotropic CFRP (fibre along Z), isotropic steel.

Units: mm, N, MPa (N/mm^2), K. Weak form: a(u, v) = f(v) + integral eps(v) : C : alpha * theta, with
theta = T - T_ref the temperature above the stress-free state (paper section 2.3: the FE of the ram
under static tool-tip loads and thermal loads feeds the regression of eqs. 11 and 13).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from skfem import Basis, BilinearForm, ElementHex1, ElementVector, FacetBasis, LinearForm, asm
from skfem.helpers import sym_grad

from fbgcomp.structure.machine import CFRP, Steel

# 2x2x2 Gauss points integrate the Hex1 stiffness and mass exactly on box-shaped elements.
INTORDER = 3


def transversely_isotropic_stiffness_MPa(E_L_GPa, E_T_GPa, G_LT_GPa, nu_LT, nu_TT) -> np.ndarray:
    """6x6 Voigt stiffness (xx, yy, zz, yz, xz, xy; engineering shears), fibre axis along Z."""
    EL, ET, GLT = 1e3 * E_L_GPa, 1e3 * E_T_GPa, 1e3 * G_LT_GPa
    S = np.zeros((6, 6))
    S[0, 0] = S[1, 1] = 1 / ET
    S[2, 2] = 1 / EL
    S[0, 1] = S[1, 0] = -nu_TT / ET
    S[0, 2] = S[2, 0] = S[1, 2] = S[2, 1] = -nu_LT / EL
    S[3, 3] = S[4, 4] = 1 / GLT
    S[5, 5] = 2 * (1 + nu_TT) / ET
    return np.linalg.inv(S)


def isotropic_stiffness_MPa(E_GPa, nu) -> np.ndarray:
    """6x6 Voigt stiffness of an isotropic material."""
    E = 1e3 * E_GPa
    lam = E * nu / ((1 + nu) * (1 - 2 * nu))
    mu = E / (2 * (1 + nu))
    C = np.zeros((6, 6))
    C[:3, :3] = lam
    C[[0, 1, 2], [0, 1, 2]] += 2 * mu
    C[[3, 4, 5], [3, 4, 5]] = mu
    return C


def cfrp_stiffness_MPa(m: CFRP) -> np.ndarray:
    """6x6 Voigt stiffness of the CFRP (MPa), fibre axis along Z."""
    return transversely_isotropic_stiffness_MPa(m.E_L_GPa, m.E_T_GPa, m.G_LT_GPa, m.nu_LT, m.nu_TT)


def steel_stiffness_MPa(m: Steel) -> np.ndarray:
    """6x6 Voigt stiffness of the steel (MPa)."""
    return isotropic_stiffness_MPa(m.E_GPa, m.nu)


def cfrp_cte_voigt_per_K(m: CFRP) -> np.ndarray:
    """Thermal expansion of the CFRP as a Voigt vector (per K): transverse in xx, yy, longitudinal in
    zz, no shear."""
    return np.array([m.cte_T_per_K, m.cte_T_per_K, m.cte_L_per_K, 0.0, 0.0, 0.0])


def steel_cte_voigt_per_K(m: Steel) -> np.ndarray:
    """Thermal expansion of the steel as a Voigt vector (per K): the same in xx, yy, zz, no shear."""
    return np.array([m.cte_per_K] * 3 + [0.0] * 3)


#: The expansion coefficients a thermo-elastic response is linear in: the CFRP's along its fibres
#: (Z) and across them, and the housing steel's. A displacement is sum_k alpha_k u_k, u_k the
#: response with alpha_k = 1 /K and the others 0 (same stiffness).
CTE_PARTS = ("cfrp_L", "cfrp_T", "steel")


def cte_values_per_K(cfrp: CFRP, steel: Steel) -> np.ndarray:
    """The materials' expansion coefficients (per K) in :data:`CTE_PARTS` order."""
    return np.array([cfrp.cte_L_per_K, cfrp.cte_T_per_K, steel.cte_per_K])


def unit_cte_materials(cfrp: CFRP, steel: Steel, part: str) -> tuple[CFRP, Steel]:
    """The two materials with expansion 1 /K in ``part`` (one of :data:`CTE_PARTS`) and none
    elsewhere, stiffness unchanged: their thermal load operator is d Th / d alpha_part."""
    unit = dict.fromkeys(CTE_PARTS, 0.0) | {part: 1.0}
    return (
        cfrp.model_copy(update={"cte_L_per_K": unit["cfrp_L"], "cte_T_per_K": unit["cfrp_T"]}),
        steel.model_copy(update={"cte_per_K": unit["steel"]}),
    )


def _voigt(e):
    return (e[0, 0], e[1, 1], e[2, 2], 2 * e[1, 2], 2 * e[0, 2], 2 * e[0, 1])


def anisotropic_elasticity(C_MPa: np.ndarray) -> BilinearForm:
    """a(u, v) = integral eps(v) . C . eps(u) with a constant 6x6 Voigt stiffness."""
    pairs = [(i, j, float(C_MPa[i, j])) for i in range(6) for j in range(6) if C_MPa[i, j] != 0]

    @BilinearForm
    def form(u, v, w):
        eu, ev = _voigt(sym_grad(u)), _voigt(sym_grad(v))
        return sum(c * ev[i] * eu[j] for i, j, c in pairs)

    return form


def thermal_stress_load(beta_MPa_per_K: np.ndarray) -> BilinearForm:
    """b(theta, v) = integral eps(v) . beta * theta, beta = C . alpha (trial: temperature)."""
    terms = [(i, float(b)) for i, b in enumerate(beta_MPa_per_K) if b != 0]

    @BilinearForm
    def form(theta, v, w):
        ev = _voigt(sym_grad(v))
        return theta * sum(b * ev[i] for i, b in terms)

    return form


@LinearForm
def _unit_x(v, w):
    return v[0]


@LinearForm
def _unit_y(v, w):
    return v[1]


@LinearForm
def _unit_z(v, w):
    return v[2]


@LinearForm
def _z_times_x(v, w):
    return v[2] * w.x[0]


@LinearForm
def _z_times_y(v, w):
    return v[2] * w.x[1]


@LinearForm
def _area(v, w):
    return v * 1.0


def vector_element():
    """The displacement element: a trilinear hexahedron (Hex1) for each of ux, uy, uz."""
    return ElementVector(ElementHex1())


def facet_mean_rows(vbasis: Basis, facets) -> np.ndarray:
    """(3, n_u) rows: mean ux, uy, uz over a set of boundary facets (area weighted)."""
    fb = FacetBasis(vbasis.mesh, vbasis.elem, facets=facets, intorder=INTORDER)
    sb = FacetBasis(vbasis.mesh, ElementHex1(), facets=facets, intorder=INTORDER)
    area = asm(_area, sb).sum()
    return np.vstack([asm(f, fb) for f in (_unit_x, _unit_y, _unit_z)]) / area


def rigid_extension_rows(vbasis: Basis, facets, centre_xy_mm=(0.0, 0.0), lever_mm: float = 0.0) -> np.ndarray:
    """(3, n_u) rows: displacement (dx, dy, dz) of a point ``lever_mm`` below a plane face.

    The point sits on a rigid extension of the face: mean face translation plus the face's
    best-fit rotation (least squares on uz) times the lever arm. By reciprocity the transposed rows
    are the consistent load of a force applied at that point.
    """
    fb = FacetBasis(vbasis.mesh, vbasis.elem, facets=facets, intorder=INTORDER)
    sb = FacetBasis(vbasis.mesh, ElementHex1(), facets=facets, intorder=INTORDER)
    mean = facet_mean_rows(vbasis, facets)
    x0, y0 = centre_xy_mm

    @LinearForm
    def second_moment_x(v, w):
        return v * (w.x[0] - x0) ** 2

    @LinearForm
    def second_moment_y(v, w):
        return v * (w.x[1] - y0) ** 2

    Ixx = asm(second_moment_x, sb).sum()
    Iyy = asm(second_moment_y, sb).sum()
    area = asm(_area, sb).sum()
    zx = asm(_z_times_x, fb) - x0 * mean[2] * area
    zy = asm(_z_times_y, fb) - y0 * mean[2] * area
    rot_x = zy / Iyy  # uz = rot_x * y - rot_y * x for a rigid rotation
    rot_y = -zx / Ixx
    return np.vstack([mean[0] - lever_mm * rot_y, mean[1] + lever_mm * rot_x, mean[2]])


def assemble_elasticity(rm, cfrp: CFRP, steel: Steel):
    """Stiffness K (n_u x n_u, N/mm) and thermal load matrix Th (n_u x n_nodes, N/K).

    Returns (vbasis, sbasis, K, Th); K u = f + Th theta. On a mesh of axis-aligned boxes (every
    mesh :func:`~fbgcomp.structure.mesh.build_mesh` makes) the element matrices are computed in
    closed form for all elements at once (:func:`assemble_hex8_box`, ~20x faster); otherwise
    with scikit-fem's forms (:func:`assemble_elasticity_forms`). Both integrate the same
    2x2x2 Gauss rule and agree to round-off.
    """
    signs, h = _box_geometry(rm.mesh.p, rm.mesh.t)
    if signs is not None:
        return assemble_hex8_box(rm, cfrp, steel, signs, h)
    return assemble_elasticity_forms(rm, cfrp, steel)


def assemble_elasticity_forms(rm, cfrp: CFRP, steel: Steel):
    """:func:`assemble_elasticity` through scikit-fem's weak forms (any hexahedral mesh; the
    reference the closed-form box assembly is tested against)."""
    e = vector_element()
    vbasis = Basis(rm.mesh, e, intorder=INTORDER)
    sbasis = Basis(rm.mesh, ElementHex1(), intorder=INTORDER)
    K = None
    Th = None
    for elements, C, alpha in (
        (rm.cfrp_elements, cfrp_stiffness_MPa(cfrp), cfrp_cte_voigt_per_K(cfrp)),
        (rm.steel_elements, steel_stiffness_MPa(steel), steel_cte_voigt_per_K(steel)),
    ):
        if len(elements) == 0:
            continue
        vb = Basis(rm.mesh, e, intorder=INTORDER, elements=elements)
        sb = Basis(rm.mesh, ElementHex1(), intorder=INTORDER, elements=elements)
        Ki = asm(anisotropic_elasticity(C), vb)
        Thi = asm(thermal_stress_load(C @ alpha), sb, vb)
        K = Ki if K is None else K + Ki
        Th = Thi if Th is None else Th + Thi
    assert K is not None and Th is not None  # the ram's CFRP wall always has elements
    return vbasis, sbasis, K.tocsc(), Th.tocsr()


def _box_geometry(p: np.ndarray, t: np.ndarray):
    """Reference-corner signs (n_e, 8, 3) and edge lengths (n_e, 3) of hexahedra that are
    axis-aligned boxes with their 8 nodes on distinct corners; (None, None) if any is not."""
    xyz = p[:, t]  # (3, 8, n_e)
    lo, hi = xyz.min(axis=1), xyz.max(axis=1)
    h = hi - lo  # (3, n_e)
    tol = 1e-9 * np.maximum(np.abs(lo), np.abs(hi)) + 1e-12
    on_lo = np.abs(xyz - lo[:, None, :]) <= tol[:, None, :]
    on_hi = np.abs(xyz - hi[:, None, :]) <= tol[:, None, :]
    if not np.all(on_lo ^ on_hi) or not np.all(h > 0):
        return None, None
    signs = np.where(on_hi, 1.0, -1.0)  # (3, 8, n_e)
    corner = ((signs > 0) * np.array([1, 2, 4])[:, None, None]).sum(axis=0)  # (8, n_e)
    if not np.all(np.sort(corner, axis=0) == np.arange(8)[:, None]):
        return None, None
    return signs.transpose(2, 1, 0), h.T


def _hex8_box_element_matrices(
    signs: np.ndarray, h_mm: np.ndarray, C_MPa: np.ndarray, beta_MPa_per_K: np.ndarray
):
    """Stiffness (n_e, 24, 24) N/mm and thermal load (n_e, 24, 8) N/K of trilinear box
    hexahedra, 2x2x2 Gauss rule (exact on boxes), all elements at once.

    ``signs`` (n_e, 8, 3): reference coordinates (+-1) of each element's local nodes; ``h_mm``
    (n_e, 3): edge lengths. Local DOF 3 i + a is component a of node i, strains in Voigt order
    (xx, yy, zz, yz, xz, xy; engineering shears) as in :func:`anisotropic_elasticity`.
    """
    n_e = signs.shape[0]
    scale = 2.0 / h_mm  # (n_e, 3) d(xi)/dx per axis
    detJ = np.prod(h_mm, axis=1) / 8.0  # (n_e,)
    Ke = np.zeros((n_e, 24, 24))
    Te = np.zeros((n_e, 24, 8))
    B = np.zeros((n_e, 6, 24))
    for gx in _GAUSS:
        for gy in _GAUSS:
            for gz in _GAUSS:
                f = 1.0 + signs * np.array([gx, gy, gz])  # (n_e, 8, 3)
                N = np.prod(f, axis=2) / 8.0  # (n_e, 8)
                dN = np.empty_like(f)
                dN[..., 0] = signs[..., 0] * f[..., 1] * f[..., 2]
                dN[..., 1] = signs[..., 1] * f[..., 0] * f[..., 2]
                dN[..., 2] = signs[..., 2] * f[..., 0] * f[..., 1]
                dN *= scale[:, None, :] / 8.0
                x, y, z = dN[..., 0], dN[..., 1], dN[..., 2]
                B[:, 0, 0::3], B[:, 1, 1::3], B[:, 2, 2::3] = x, y, z
                B[:, 3, 1::3], B[:, 3, 2::3] = z, y
                B[:, 4, 0::3], B[:, 4, 2::3] = z, x
                B[:, 5, 0::3], B[:, 5, 1::3] = y, x
                Bw = B * detJ[:, None, None]
                Ke += np.matmul(Bw.transpose(0, 2, 1), np.matmul(C_MPa, B))
                Te += (Bw.transpose(0, 2, 1) @ beta_MPa_per_K)[:, :, None] * N[:, None, :]
    return Ke, Te


def assemble_hex8_box(rm, cfrp: CFRP, steel: Steel, signs=None, h_mm=None):
    """:func:`assemble_elasticity` on box-shaped elements with closed-form element matrices
    computed for all elements at once (no per-quadrature-point Python forms); DOFs numbered by
    the same vector basis. Returns (vbasis, sbasis, K, Th)."""
    p, t = rm.mesh.p, rm.mesh.t
    if signs is None:
        signs, h_mm = _box_geometry(p, t)
        if signs is None:
            raise ValueError("the mesh has elements that are not axis-aligned boxes")
    e = vector_element()
    vbasis = Basis(rm.mesh, e, intorder=INTORDER)
    sbasis = Basis(rm.mesh, ElementHex1(), intorder=INTORDER)
    G = vbasis.nodal_dofs[:, t].transpose(2, 1, 0).reshape(t.shape[1], 24)  # (n_e, 24)
    n_u, n = vbasis.N, rm.n_nodes
    rows_K, cols_K, vals_K, rows_T, cols_T, vals_T = [], [], [], [], [], []
    for elements, C, alpha in (
        (rm.cfrp_elements, cfrp_stiffness_MPa(cfrp), cfrp_cte_voigt_per_K(cfrp)),
        (rm.steel_elements, steel_stiffness_MPa(steel), steel_cte_voigt_per_K(steel)),
    ):
        if len(elements) == 0:
            continue
        Ke, Te = _hex8_box_element_matrices(signs[elements], h_mm[elements], C, C @ alpha)
        g = G[elements]
        rows_K.append(np.repeat(g, 24, axis=1).ravel())
        cols_K.append(np.tile(g, (1, 24)).ravel())
        vals_K.append(Ke.ravel())
        rows_T.append(np.repeat(g, 8, axis=1).ravel())
        cols_T.append(np.tile(t[:, elements].T, (1, 24)).ravel())
        vals_T.append(Te.ravel())
    K = sp.coo_matrix(
        (np.concatenate(vals_K), (np.concatenate(rows_K), np.concatenate(cols_K))), shape=(n_u, n_u)
    )
    Th = sp.coo_matrix(
        (np.concatenate(vals_T), (np.concatenate(rows_T), np.concatenate(cols_T))), shape=(n_u, n)
    )
    K, Th = K.tocsc(), Th.tocsr()
    K.eliminate_zeros()  # exact zeros of the closed form (skfem leaves round-off there)
    Th.eliminate_zeros()
    return vbasis, sbasis, K, Th


def spring_matrix(rows: np.ndarray, stiffness_N_per_mm) -> sp.csc_matrix:
    """Sum of k c c^T for constraint rows c (n_c, n): elastic supports on mean displacements."""
    R = sp.csr_matrix(rows if sp.issparse(rows) else np.atleast_2d(rows))
    k = np.broadcast_to(np.asarray(stiffness_N_per_mm, dtype=float), (R.shape[0],))
    return (R.T @ sp.diags(k) @ R).tocsc()


# ------------------------------------------------------------------ incompatible-mode hexahedra
_GAUSS = np.array([-1.0, 1.0]) / np.sqrt(3.0)


def _box_element_matrices(
    signs: np.ndarray, h_mm: np.ndarray, C_MPa: np.ndarray, beta_MPa_per_K: np.ndarray, incompatible: bool
):
    """Stiffness (24, 24) N/mm and thermal load (24, 8) N/K of one box-shaped 8-node hexahedron.

    ``signs`` (8, 3): reference coordinates (+-1) of the local nodes; ``h_mm`` (3,): edge lengths.
    Local DOF 3 i + a is component a of node i. With ``incompatible`` the element carries
    Wilson-Taylor incompatible modes (1 - xi^2, 1 - eta^2, 1 - zeta^2 per component, as in
    CalculiX's C3D8I), condensed out: pure bending is then represented without parasitic shear,
    which a plain trilinear hexahedron locks on. On a box the Jacobian is constant, so no
    patch-test correction is needed.
    """
    scale = 2.0 / h_mm  # d(xi)/dx per axis
    detJ = np.prod(h_mm) / 8.0
    Kuu = np.zeros((24, 24))
    Kua = np.zeros((24, 9))
    Kaa = np.zeros((9, 9))
    Tu = np.zeros((24, 8))
    Ta = np.zeros((9, 8))
    for gx in _GAUSS:
        for gy in _GAUSS:
            for gz in _GAUSS:
                g = np.array([gx, gy, gz])
                f = 1.0 + signs * g  # (8, 3)
                N = np.prod(f, axis=1) / 8.0
                dN = np.empty((8, 3))
                for a in range(3):
                    others = np.prod(np.delete(f, a, axis=1), axis=1)
                    dN[:, a] = signs[:, a] * others / 8.0 * scale[a]
                Bu = _strain_matrix(dN)  # (6, 24)
                dP = np.diag(-2.0 * g * scale)  # mode b depends on coordinate b only
                Ba = _strain_matrix(dP)  # (6, 9)
                w = detJ
                Kuu += w * Bu.T @ C_MPa @ Bu
                Tu += w * np.outer(Bu.T @ beta_MPa_per_K, N)
                if incompatible:
                    Kua += w * Bu.T @ C_MPa @ Ba
                    Kaa += w * Ba.T @ C_MPa @ Ba
                    Ta += w * np.outer(Ba.T @ beta_MPa_per_K, N)
    if not incompatible:
        return Kuu, Tu
    X = np.linalg.solve(Kaa, np.hstack([Kua.T, Ta]))  # K_aa^-1 [K_au, T_a]
    return Kuu - Kua @ X[:, :24], Tu - Kua @ X[:, 24:]


def _strain_matrix(dN: np.ndarray) -> np.ndarray:
    """Voigt strain-displacement matrix (6, 3 n) of shape-function gradients dN (n, 3)."""
    n = dN.shape[0]
    B = np.zeros((6, 3 * n))
    x, y, z = dN[:, 0], dN[:, 1], dN[:, 2]
    B[0, 0::3], B[1, 1::3], B[2, 2::3] = x, y, z
    B[3, 1::3], B[3, 2::3] = z, y
    B[4, 0::3], B[4, 2::3] = z, x
    B[5, 0::3], B[5, 1::3] = y, x
    return B


def assemble_box_elasticity(
    rm, cfrp: CFRP, steel: Steel, incompatible: bool = True, *, bases=None, stiffness: bool = True
):
    """K (n_u x n_u, N/mm) and Th (n_u x n_nodes, N/K) of the structured box mesh, assembled from
    closed-form element matrices (one per element size and material), DOFs numbered like
    :func:`assemble_elasticity`'s vector basis. Returns (vbasis, sbasis, K, Th).

    ``bases``: the (vbasis, sbasis) of an earlier call on the same mesh, reused; ``stiffness``
    False: Th alone (K None), for the thermal load of other expansion coefficients (the global
    K is most of the cost)."""
    if bases is None:
        vbasis = Basis(rm.mesh, vector_element(), intorder=INTORDER)
        sbasis = Basis(rm.mesh, ElementHex1(), intorder=INTORDER)
    else:
        vbasis, sbasis = bases
    p, t = rm.mesh.p, rm.mesh.t
    xyz = p[:, t]  # (3, 8, n_e)
    lo, hi = xyz.min(axis=1), xyz.max(axis=1)
    h = (hi - lo).T  # (n_e, 3)
    signs = np.sign(xyz - 0.5 * (lo + hi)[:, None, :]).transpose(2, 1, 0)  # (n_e, 8, 3)
    material = np.zeros(t.shape[1], dtype=np.int64)
    material[rm.steel_elements] = 1
    props = [
        (cfrp_stiffness_MPa(cfrp), cfrp_cte_voigt_per_K(cfrp)),
        (steel_stiffness_MPa(steel), steel_cte_voigt_per_K(steel)),
    ]
    key = np.column_stack([material, np.round(h, 6), signs.reshape(len(h), -1)])
    kinds, kind_of = np.unique(key, axis=0, return_inverse=True)
    Ke = np.empty((len(kinds), 24, 24))
    Te = np.empty((len(kinds), 24, 8))
    for j, k in enumerate(kinds):
        C, alpha = props[int(k[0])]
        Ke[j], Te[j] = _box_element_matrices(k[4:].reshape(8, 3), k[1:4], C, C @ alpha, incompatible)
    G = vbasis.nodal_dofs[:, t].transpose(2, 1, 0).reshape(t.shape[1], 24)  # (n_e, 24)
    kind_of = kind_of.ravel()
    n_u, n = vbasis.N, rm.n_nodes
    K = None
    if stiffness:
        K = sp.coo_matrix(
            (Ke[kind_of].ravel(), (np.repeat(G, 24, axis=1).ravel(), np.tile(G, (1, 24)).ravel())),
            shape=(n_u, n_u),
        ).tocsc()
    Th = sp.coo_matrix(
        (Te[kind_of].ravel(), (np.repeat(G, 8, axis=1).ravel(), np.tile(t.T, (1, 24)).ravel())),
        shape=(n_u, n),
    )
    return vbasis, sbasis, K, Th.tocsr()
