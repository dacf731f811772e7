"""Shared FE numerics: one factorisation of an SPD matrix, reused for every right-hand side.

The ram is long and slender, so numbering the nodes layer by layer along Z gives a band of about
one cross-section: a banded Cholesky (LAPACK) then factorises the 44k-DOF elastic matrix of the
default mesh (59k thermo-elastic DOF) in ~5 s and back-substitutes in ~0.08 s, on par with or
ahead of CHOLMOD (6.8 s / 0.095 s measured on the same matrix) and ~5x faster than SuperLU with
COLAMD. CHOLMOD (scikit-sparse), then SuperLU, take over when the band would be too wide.

The band must reach across two node layers wherever a support's mean constraint couples them,
while the matrix is block tridiagonal in blocks of about one layer: ``Factorised(blocked=True)``
(the twin's elastic matrix) factorises those blocks with dense LAPACK instead, ~2x faster
(1.6 s for the default twin's factor and its 8 adjoint solves), and 1.5x on the independent
rams' twins, whose blocks cost a little more flops than their band (benchmarks/bench_factor.py).
"""

from __future__ import annotations

import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from fbgcomp.threads import one_blas_thread

# Above this many band entries (8 bytes each) the banded factor would not fit comfortably.
_MAX_BAND_ENTRIES = 400_000_000
# Factorised(blocked=True) takes the block-by-block factor while its flop count is below this
# multiple of the band's (n bw^2): dense LAPACK on whole blocks runs faster per flop than the
# banded dpbtrf. benchmarks/bench_factor.py (2026-11-30): ram2's twin at a ratio of 1.12
# factorises 1.5x faster by blocks (9.1 -> 6.0 s), ram3's and ram4's at 0.95-0.96 1.6-1.7x; 0.8
# (the rule before) left all three banded.
_BLOCKED_WORK_RATIO = 1.25


def layer_order(points_mm: np.ndarray, dofs_per_node: np.ndarray | None = None) -> np.ndarray:
    """DOF permutation numbering nodes layer by layer along z (then y, then x).

    ``points_mm`` (3, n_nodes); ``dofs_per_node`` (d, n_nodes) from a vector basis's
    ``nodal_dofs`` (``None``: one DOF per node, numbered like the nodes).
    """
    order = np.lexsort((points_mm[0], points_mm[1], points_mm[2]))
    if dofs_per_node is None:
        return order
    return dofs_per_node[:, order].T.ravel()


def block_partition(row: np.ndarray, col: np.ndarray, n: int, min_block: int = 64) -> np.ndarray:
    """Boundaries of the finest consecutive blocks in which a symmetric matrix is block
    tridiagonal (entry (r, c), r >= c, only within a block or between neighbouring blocks).

    ``row``, ``col``: the lower-triangle entries (r >= c). Block k+1 starts after the last row
    coupled to any column before block k's start (greedy, so the blocks follow the coupling
    range: about one node layer of a layer-ordered mesh).
    """
    first = np.arange(n)  # first column of each row
    np.minimum.at(first, row, col)
    last_row = np.full(n + 1, -1)
    np.maximum.at(last_row, first + 1, np.arange(n))
    reach = np.maximum.accumulate(last_row)  # reach[s] = max{r : first(r) < s}
    bounds = [0]
    while bounds[-1] < n:
        s = bounds[-1]
        bounds.append(min(n, max(int(reach[s]) + 1, s + min_block)))
    return np.asarray(bounds)


class _BlockTridiagonalCholesky:
    """Dense Cholesky of a block-tridiagonal SPD matrix (given permuted, as CSR), block by block.

    Only the diagonal factors L_k are kept; the coupling blocks stay sparse and the solve
    applies L_{k+1,k} = A_{k+1,k} L_k^-T through one more triangular solve per block, so the
    factor takes about the memory of the banded one. LAPACK potrf/trsm on blocks of ~one node
    layer run ~2x faster than the banded dpbtrf, whose band must cover the widest coupling.
    """

    def __init__(self, Ap: sp.csr_matrix, bounds: np.ndarray):
        self.bounds = bounds
        self.L, self.C = [], []  # L_k; A_{k,k-1} (sparse, CSR)
        prev = None
        for k in range(len(bounds) - 1):
            a, b = bounds[k], bounds[k + 1]
            Akk = Ap[a:b, a:b].toarray()
            if k:
                C = Ap[a:b, bounds[k - 1] : a].tocsr()
                self.C.append(C)
                # B = A_{k,k-1} L_{k-1}^-T; A_kk -= B B^T
                Bt = sla.solve_triangular(prev, C.T.toarray(), lower=True, check_finite=False)
                Akk -= Bt.T @ Bt
            prev = sla.cholesky(Akk, lower=True, overwrite_a=True, check_finite=False)
            self.L.append(prev)

    def solve(self, b: np.ndarray) -> np.ndarray:
        bounds, L, C = self.bounds, self.L, self.C
        m = len(L)
        y: list[np.ndarray] = []
        for k in range(m):
            v = b[bounds[k] : bounds[k + 1]]
            if k:  # - L_{k,k-1} y_{k-1} = - A_{k,k-1} L_{k-1}^-T y_{k-1}
                v = v - C[k - 1] @ sla.solve_triangular(
                    L[k - 1], y[-1], lower=True, trans="T", check_finite=False
                )
            y.append(sla.solve_triangular(L[k], v, lower=True, check_finite=False))
        x: list[np.ndarray] = [np.empty(0)] * m  # every block is filled below, last to first
        for k in reversed(range(m)):
            v = y[k]
            if k + 1 < m:  # - L_{k+1,k}^T x_{k+1} = - L_k^-1 A_{k+1,k}^T x_{k+1}
                v = v - sla.solve_triangular(L[k], C[k].T @ x[k + 1], lower=True, check_finite=False)
            x[k] = sla.solve_triangular(L[k], v, lower=True, trans="T", check_finite=False)
        return np.concatenate(x)


class Factorised:
    """An SPD sparse matrix factorised once; ``solve(b)`` back-substitutes (b: (n,) or (n, k)).

    ``blocked=True``: if the permuted matrix is block tridiagonal with blocks clearly smaller
    than its band (the layer-ordered elastic matrix: one node layer each), factorise it block by
    block (dense LAPACK on each block, ~2x faster than the banded factor on the default twin);
    worth it for few solves with many right-hand sides, as each solve walks the blocks in Python.
    """

    def __init__(self, A: sp.spmatrix, order: np.ndarray | None = None, blocked: bool = False):
        A = sp.csr_matrix(A)
        self.shape = A.shape
        n = A.shape[0]
        self.backend: str  # set by whichever factorisation below is used
        perm = np.arange(n) if order is None else np.asarray(order)
        # A[perm][:, perm] by renumbering the entries (no sparse fancy indexing): entry (i, j)
        # of A goes to (inv[i], inv[j]).
        inv = np.empty_like(perm)
        inv[perm] = np.arange(n)
        Ac = A.tocoo()
        row, col = inv[Ac.row], inv[Ac.col]
        upper = col >= row
        row, col, data = row[upper], col[upper], Ac.data[upper]
        bw = int(np.max(col - row)) if len(row) else 0
        self.bandwidth = bw
        if blocked and n > 1:
            bounds = block_partition(col, row, n)  # (col, row) of the upper = lower
            m = np.diff(bounds).astype(float)
            # flops: potrf m^3/3 + trsm and update m_k m_{k-1}^2 + m_k^2 m_{k-1} per block,
            # against n bw^2 for the band
            work = (m**3 / 3).sum() + (m[1:] * m[:-1] ** 2 + m[1:] ** 2 * m[:-1]).sum()
            if work < _BLOCKED_WORK_RATIO * n * float(bw) ** 2:
                Ap = sp.csr_matrix((data, (col, row)), shape=A.shape)  # lower triangle
                Ap = (Ap + sp.triu(Ap.T, k=1)).tocsr()
                self._perm = perm
                self._inv = inv
                with one_blas_thread():
                    self._blocks = _BlockTridiagonalCholesky(Ap, bounds)
                self.backend = f"block-cholesky({len(m)} blocks <= {int(m.max())})"
                return
        if (bw + 1) * n <= _MAX_BAND_ENTRIES:
            ab = np.zeros((bw + 1, n))
            ab[bw + row - col, col] = data
            with one_blas_thread():
                self._band = sla.cholesky_banded(ab, lower=False, overwrite_ab=True, check_finite=False)
            self._perm = perm
            self._inv = inv
            self.backend = f"banded-cholesky(bw={bw})"
            return
        try:
            from sksparse.cholmod import cholesky  # noqa: PLC0415 - optional heavy extra: sksparse

            self._chol = cholesky(A.tocsc())
            self.backend = "cholmod"
        except ImportError:
            self._lu = spla.splu(A.tocsc(), permc_spec="COLAMD")
            self.backend = "superlu"

    def solve(self, b: np.ndarray) -> np.ndarray:
        """A^-1 b for b (n,) or (n, k), by back-substitution in the backend's factor."""
        b = np.asarray(b, dtype=float)
        if self.backend == "cholmod":
            return self._chol(b)
        if self.backend == "superlu":
            return self._lu.solve(b)
        if self.backend.startswith("block"):
            with one_blas_thread():
                return self._blocks.solve(b[self._perm])[self._inv]
        x = sla.cho_solve_banded((self._band, False), b[self._perm], check_finite=False)
        return x[self._inv]

    def as_operator(self) -> spla.LinearOperator:
        """A^-1 as a scipy ``LinearOperator`` (its matvec is :meth:`solve`)."""
        return spla.LinearOperator(self.shape, matvec=self.solve, dtype=float)
