"""Transient heat conduction in the ram and its reduced-order integration.

C dtheta/dt + K theta = B u(t), theta = T - T_ref (K), on the nodes of the hexahedral mesh.
Units: mm, s, W, J. Anisotropic conduction in the CFRP (k_L along the fibres = Z, k_T across),
film convection (Robin) to the ambient on the outer and inner surfaces, spindle heat into the
housing (or any box-shaped zone), radiant fluxes on face zones. Inputs u = (ambient - T_ref [K],
then one per declared heat source: W for a volume source, W/m^2 for a radiant one; the built-in
ram: spindle heat [W], radiant flux [W/m^2]). This is the thermal load of the paper's FE study (section 2.3) and the
36 h thermal test (section 3.2).

A 36 h campaign at 1 s steps is integrated on a reduced basis: a rational Krylov projection
(transfer-function matching at log-spaced frequencies, few inputs), diagonalised into decoupled
modes, each integrated with the exact exponential for piecewise-linear inputs. (Truncated
eigenmodes of K phi = lambda C phi with a mode-acceleration correction were tried first: the thin
CFRP walls have hundreds of modes slower than 10 min, so the quasi-static correction of the
truncated ones was several per cent off after every heat step.) Outputs are linear functionals
O theta projected once onto the basis, so a campaign costs O(n_steps * n_modes).
"""

from __future__ import annotations

import numpy as np
import scipy.linalg
import scipy.sparse as sp
from skfem import Basis, BilinearForm, ElementHex1, FacetBasis, LinearForm, asm
from skfem.helpers import dot, grad

from fbgcomp.structure.elastic import INTORDER
from fbgcomp.structure.fe import Factorised

INPUT_NAMES = ("ambient_C", "spindle_heat_W", "radiant_W_per_m2")


def anisotropic_conduction(k_T_W_per_mmK: float, k_L_W_per_mmK: float) -> BilinearForm:
    """Integral k_T (dx theta dx v + dy theta dy v) + k_L dz theta dz v."""

    @BilinearForm
    def form(u, v, w):
        gu, gv = grad(u), grad(v)
        return k_T_W_per_mmK * (gu[0] * gv[0] + gu[1] * gv[1]) + k_L_W_per_mmK * gu[2] * gv[2]

    return form


def isotropic_conduction(k_W_per_mmK: float) -> BilinearForm:
    """Integral k grad theta . grad v, k in W/(mm K) (the steel housing)."""

    @BilinearForm
    def form(u, v, w):
        return k_W_per_mmK * dot(grad(u), grad(v))

    return form


def capacity(rho_c_J_per_mm3K: float) -> BilinearForm:
    """Integral rho c theta v, rho c in J/(mm³ K)."""

    @BilinearForm
    def form(u, v, w):
        return rho_c_J_per_mm3K * u * v

    return form


@BilinearForm
def film(u, v, w):
    """Integral h theta v over a surface; h enters by scaling (W/mm^2K)."""
    return u * v


@LinearForm
def unit_load(v, w):
    """Integral v: each node's share of the volume (mm³) or surface (mm²) it is assembled over."""
    return 1.0 * v


def input_names(machine) -> tuple[str, ...]:
    """Input channels of the thermal model: the ambient, then one per declared heat source."""
    return ("ambient_C", *(h.input_name for h in machine.thermal.sources))


def _volume_source_column(rm, machine, source, e) -> np.ndarray:
    """W per node per W of the source: uniform over the elements inside its zone."""
    lo, hi = machine.volume_source_box_mm(source)
    c = rm.mesh.p[:, rm.mesh.t].mean(axis=1)
    inside = np.all((c >= lo[:, None] - 1e-6) & (c <= hi[:, None] + 1e-6), axis=0)
    elements = np.nonzero(inside)[0]
    if len(elements) == 0:
        raise ValueError(f"heat source {source.name!r}: no element in its zone")
    vol = asm(unit_load, Basis(rm.mesh, e, intorder=INTORDER, elements=elements))
    return vol / vol.sum()


def _radiant_column(rm, machine, source, e) -> np.ndarray:
    """W per node per W/m^2 of incident flux on the source's face and z zone."""
    z_lo, z_hi = source.z_mm if source.z_mm is not None else (0.0, rm.length_mm)
    facets = rm.face_facets(source.face, z_lo, z_hi)
    fb = FacetBasis(rm.mesh, e, facets=facets, intorder=INTORDER)
    return 1e-6 * source.absorptivity * asm(unit_load, fb)


def assemble_thermal(rm, machine):
    """Conductance K (W/K), capacity C (J/K) and input matrix B (n_nodes x m) of the ram.

    Column units of B: W per K of ambient, then per declared heat source W per W (volume) or
    W per (W/m^2) of incident flux (radiant), in the order of :func:`input_names`.
    """
    cf, st, th = machine.materials.cfrp, machine.materials.steel, machine.thermal
    e = ElementHex1()
    cb = Basis(rm.mesh, e, intorder=INTORDER, elements=rm.cfrp_elements)
    K = asm(anisotropic_conduction(1e-3 * cf.k_T_W_per_mK, 1e-3 * cf.k_L_W_per_mK), cb)
    C = asm(capacity(1e-9 * cf.density_kg_per_m3 * cf.specific_heat_J_per_kgK), cb)
    n = rm.n_nodes
    if len(rm.steel_elements):
        sb = Basis(rm.mesh, e, intorder=INTORDER, elements=rm.steel_elements)
        K = K + asm(isotropic_conduction(1e-3 * st.k_W_per_mK), sb)
        C = C + asm(capacity(1e-9 * st.density_kg_per_m3 * st.specific_heat_J_per_kgK), sb)
    b_ambient = np.zeros(n)
    # Surfaces sharing a film coefficient are assembled together (the built-in ram: two groups).
    groups: dict[float, list] = {}
    for surface, facets in rm.film_surface_facets(machine.housing.height_mm).items():
        groups.setdefault(th.film_W_per_m2K(surface), []).append(facets)
    for h_SI, parts in groups.items():
        facets = np.concatenate(parts)
        if h_SI > 0 and len(facets):
            fb = FacetBasis(rm.mesh, e, facets=facets, intorder=INTORDER)
            K = K + 1e-6 * h_SI * asm(film, fb)
            b_ambient += 1e-6 * h_SI * asm(unit_load, fb)
    cols = [b_ambient]
    for source in th.sources:
        make = _volume_source_column if source.kind == "volume" else _radiant_column
        cols.append(make(rm, machine, source, e))
    return K.tocsr(), C.tocsr(), np.column_stack(cols)


def _foh_weights(lam_per_s: np.ndarray, h_s: float):
    """Exact one-step weights for q' = -lam q + b(t), b linear over the step.

    q1 = E q0 + g0 b0 + g1 b1. Series below lam*h = 1e-3, where the closed form cancels.
    """
    x = lam_per_s * h_s
    E = np.exp(-x)
    small = x < 1e-3
    xs = np.where(small, 1.0, x)
    one_minus_E = -np.expm1(-xs)
    g1 = h_s * (one_minus_E / xs - (one_minus_E - xs * np.exp(-xs)) / xs**2)
    g0 = h_s * one_minus_E / xs - g1
    g1 = np.where(small, h_s * (0.5 - x / 6 + x**2 / 24), g1)
    g0 = np.where(small, h_s * (0.5 - x / 3 + x**2 / 8), g0)
    return E, g0, g1


def rational_krylov_basis(
    K, C, B, shifts_per_s, factor: Factorised | None = None, moments_at_zero: int = 2
) -> np.ndarray:
    """Basis spanning (K + s C)^-1 B at each shift s (and extra moments at s = 0), orthonormal.

    Matching the transfer function (K + sC)^-1 B at log-spaced s from hours^-1 to 1 s^-1
    captures both the slow global warming and the fast local response next to the heat inputs;
    s = 0 makes the steady state (and a uniform initial temperature) exact.
    """
    blocks = []
    f0 = factor or Factorised(K)
    X = f0.solve(B)
    blocks.append(X)
    for _ in range(moments_at_zero - 1):
        X = f0.solve(C @ X)
        blocks.append(X)
    for s in shifts_per_s:
        blocks.append(Factorised((K + s * C).tocsr()).solve(B))
    V = np.hstack(blocks)
    V /= np.linalg.norm(V, axis=0)
    U, sv, _ = np.linalg.svd(V, full_matrices=False)
    return U[:, sv > 1e-10 * sv[0]]


class ReducedThermal:
    """Galerkin reduction of C theta' + K theta = B u with outputs y = O theta.

    The rational-Krylov basis V is diagonalised (V^T K V psi = lambda V^T C V psi) so that each
    reduced coordinate is a decoupled first-order mode integrated exactly; a static correction
    keeps the steady gain exact.

    Parameters
    ----------
    K, C : sparse (n, n)
    B : (n, m) input matrix
    O : (p, n) output rows
    n_shifts : number of log-spaced expansion points between 1e-5 and 1 s^-1
    factor : Factorised K (reused for the s = 0 moments and the static gain)
    """

    # Arrays that define a built reduction (what the twin cache stores; see from_arrays).
    ARRAYS = ("lam_per_s", "Phi", "PhiB", "OPhi", "PhiTC", "D", "steady_gain")

    def __init__(self, K, C, B, O, n_shifts: int = 12, factor: Factorised | None = None):  # noqa: E741 - O: the output matrix of (K, C, B, O)
        self._K = K
        self._factor: Factorised | None = factor or Factorised(K)
        shifts: np.ndarray | list[float] = np.logspace(-5, 0, int(n_shifts)) if n_shifts > 0 else []
        V = rational_krylov_basis(K, C, B, shifts, self.factor)
        Kr = V.T @ (K @ V)
        Cr = V.T @ (C @ V)
        lam, Psi = scipy.linalg.eigh(0.5 * (Kr + Kr.T), 0.5 * (Cr + Cr.T))
        Phi = V @ Psi  # C-orthonormal, K-diagonal
        self.lam_per_s = lam
        self.n_modes = len(lam)
        O = np.asarray(O.todense() if sp.issparse(O) else O)  # noqa: E741 - O: the output matrix of (K, C, B, O)
        self.PhiB = Phi.T @ B  # (N, m)
        self.OPhi = O @ Phi  # (p, N)
        self.PhiTC = (C @ Phi).T  # (N, n): initial-state projection
        self.Phi = Phi
        self._B = B
        static = O @ self.factor.solve(B)  # (p, m) exact steady gain
        self.D = static - self.OPhi @ (self.PhiB / self.lam_per_s[:, None])
        self.steady_gain = static

    @classmethod
    def from_arrays(cls, K, B, arrays: dict, factor: Factorised | None = None) -> ReducedThermal:
        """A reduction rebuilt from :meth:`arrays` (and K, B) without recomputing it; K is
        factorised only if :meth:`projected_outputs` needs it."""
        self = cls.__new__(cls)
        self._K, self._factor, self._B = K, factor, B
        for name in cls.ARRAYS:
            setattr(self, name, arrays[name])
        self.n_modes = len(self.lam_per_s)
        return self

    def arrays(self) -> dict:
        """The arrays :meth:`from_arrays` takes back."""
        return {name: getattr(self, name) for name in self.ARRAYS}

    @property
    def factor(self) -> Factorised:
        """K factorised (built on first use when the reduction came from the cache)."""
        if self._factor is None:
            self._factor = Factorised(self._K)
        return self._factor

    @property
    def slowest_time_constant_s(self) -> float:
        """Time constant of the slowest mode, s (1 / smallest eigenvalue)."""
        return float(1.0 / self.lam_per_s[0])

    def initial_modal(self, u0: np.ndarray, theta0: np.ndarray | None) -> np.ndarray:
        """Modal state at the start: the steady state under the first inputs ``u0`` when ``theta0`` is
        None, else the projection of ``theta0`` (nodal K above T_ref)."""
        if theta0 is None:
            return (self.PhiB @ u0) / self.lam_per_s  # steady state at the first input
        return self.PhiTC @ theta0

    def projected_outputs(self, O):  # noqa: E741 - O: the output matrix of (K, C, B, O)
        """(O Phi, D) for further output rows O (k, n): new functionals without a new reduction."""
        O = np.asarray(O.todense() if sp.issparse(O) else O)  # noqa: E741 - O: the output matrix of (K, C, B, O)
        OPhi = O @ self.Phi
        static = O @ self.factor.solve(self._B)
        return OPhi, static - OPhi @ (self.PhiB / self.lam_per_s[:, None])

    def simulate(self, time_s: np.ndarray, u: np.ndarray, theta0: np.ndarray | None = None, outputs=None):
        """Outputs (n_steps, p) for inputs u (n_steps, m) sampled at time_s (piecewise linear).

        ``outputs``: optional (O Phi, D) from :meth:`projected_outputs` instead of the built-in O.
        """
        t = np.asarray(time_s, dtype=float)
        u = np.asarray(u, dtype=float)
        q0 = self.initial_modal(u[0], theta0)
        b = self.PhiB @ u.T  # (N, n_steps)
        q = np.empty_like(b)
        q[:, 0] = q0
        if len(t) > 1:
            h = np.diff(t)
            if np.any(h <= 0):
                raise ValueError("time_s must be strictly increasing")
            if np.ptp(h) <= 1e-9 * h[0]:
                E, g0, g1 = _foh_weights(self.lam_per_s, h[0])
                f = g0[:, None] * b[:, :-1] + g1[:, None] * b[:, 1:]
                import scipy.signal  # noqa: PLC0415 - start-up: with scipy.stats ~0.6 s, needed by twin runs alone

                for i in range(self.n_modes):  # one C-level recursion per mode, not per sample
                    q[i, 1:], _ = scipy.signal.lfilter([1.0], [1.0, -E[i]], f[i], zi=[E[i] * q0[i]])
            else:
                # Irregular sampling: same exact update, step by step.
                for k, hk in enumerate(h):
                    E, g0, g1 = _foh_weights(self.lam_per_s, hk)
                    q[:, k + 1] = E * q[:, k] + g0 * b[:, k] + g1 * b[:, k + 1]
        OPhi, D = (self.OPhi, self.D) if outputs is None else outputs
        return (OPhi @ q).T + u @ D.T


def implicit_euler(K, C, B, O, time_s, u, theta0=None, order=None):  # noqa: E741 - O: the output matrix of (K, C, B, O)
    """Reference: full-order implicit Euler, one solve per step (uniform steps). Outputs (n, p).

    ``order``: node numbering for the banded factor (the mesh's own order is already layer-wise).
    """
    t = np.asarray(time_s, dtype=float)
    h = float(t[1] - t[0])
    fac = Factorised((C / h + K).tocsr(), order=order)
    theta = Factorised(K, order=order).solve(B @ u[0]) if theta0 is None else np.asarray(theta0, dtype=float)
    O = O.toarray() if sp.issparse(O) else np.asarray(O)  # noqa: E741 - O: the output matrix of (K, C, B, O)
    y = np.empty((len(t), O.shape[0]))
    y[0] = O @ theta
    for k in range(1, len(t)):
        theta = fac.solve(C @ theta / h + B @ u[k])
        y[k] = O @ theta
    return y
