"""Gram fast path of the accumulator's "auto" data pass (issue 16).

When the design is well conditioned, adding a chunk through its Gram ``[X Y]^T [X Y]`` (one BLAS
syrk/gemm pass at memory-bandwidth speed) and a Cholesky of ``R^T R + G`` costs far less than
Householder QR and loses nothing that matters. The new factor is kept only if it stays within
the accuracy bounds below; otherwise :class:`~fbgcomp.models.regression.QRAccumulator` factors
the same rows by QR.
"""

from __future__ import annotations

import numpy as np
from scipy import linalg

from fbgcomp.models.regression.factor import equilibrated_cond

__all__ = [
    "GRAM_BLOCK_ROWS",
    "GRAM_MAX_REFUSALS",
    "GRAM_MIN_ROWS",
    "KAPPA_GRAM",
    "RESID_RATIO_GRAM",
    "gram",
    "gram_factor",
]

# Rows per BLAS Gram product.
GRAM_BLOCK_ROWS = 65536
# Gram fast path of the "auto" data pass (issue 16). Forming X^T X squares the condition
# number: with the columns equilibrated, the Cholesky solution of the accumulated Gram carries a
# normwise relative error of about kappa_eq(X)^2 * eps_G, eps_G the rounding of the Gram
# (about sqrt(65536) u = 2.8e-14 for a 65536-row BLAS block, probabilistically; Higham & Mary
# 2019). Small coefficients lose more, relatively. Forced through the Gram, NIST Wampler3/4
# (kappa_eq(X) 2.2e3) keep only 6.0 correct digits in their worst coefficient, Longley (4.3e4)
# 6.6, and polynomial designs of degree 2-4 on shifted abscissae 12.7 (kappa_eq 18) to 5.2
# (2.1e4): the worst coefficient's relative error stays <= 2.1e-13 kappa_eq^2 in all of them.
# kappa_eq(X) <= 500 bounds that at 5e-8, >= 7.3 digits (the NIST target is 7; the measured
# design nearest the threshold, kappa_eq 547, keeps 7.8). The error is governed by the final
# factor's conditioning (a chunk's rounding relative to the whole Gram), which only improves as
# a drift is seen longer: bench_stepwise's first 100 000 rows have kappa_eq 402, all 10^6 rows 9.
KAPPA_GRAM = 500.0
# The residual sum of squares from a Gram is y'y - b'X'y: it loses (|y| / |e|)^2 eps_G of its
# relative accuracy to cancellation (|e| the residual norm of y on all of X). At most 300 keeps
# SSR to 2.1e-13 * 9e4 = 1.9e-8 (residual SD, R^2 and standard errors to >= 7.5 digits); a
# near-exact fit (NIST Pontius, Wampler1/2, or tiny noise on large deviations) stays on QR.
RESID_RATIO_GRAM = 300.0
# Rows that go through Householder QR before the Gram fast path may start (the first 2(p+k) of
# them in double-double): their factor tells whether the design is well conditioned.
GRAM_MIN_ROWS = 1024
# A refused Gram (the factor would leave the bounds above) costs its pass on top of the QR of the
# same rows; after this many refusals in a row the fast path is off for good. A refusal alone
# is not final: the first chunks of a slow drift often see too little of it to be well
# conditioned (bench_stepwise's first 100 000 rows: 3.6 h of a 36 h campaign).
GRAM_MAX_REFUSALS = 3


def gram(X: np.ndarray, Y: np.ndarray) -> np.ndarray:
    """The Gram ``[X Y]^T [X Y]`` of the rows, in GRAM_BLOCK_ROWS-row blocks (BLAS syrk/gemm)."""
    p, q = X.shape[1], X.shape[1] + Y.shape[1]
    g = np.zeros((q, q))
    for start in range(0, X.shape[0], GRAM_BLOCK_ROWS):
        xb, yb = X[start : start + GRAM_BLOCK_ROWS], Y[start : start + GRAM_BLOCK_ROWS]
        g[:p, :p] += xb.T @ xb
        xy = xb.T @ yb
        g[:p, p:] += xy
        g[p:, :p] += xy.T
        g[p:, p:] += yb.T @ yb
    return g


def gram_factor(r: np.ndarray, g: np.ndarray, p: int) -> np.ndarray | None:
    """Upper Cholesky factor of ``r^T r + g`` (r the current triangle, g a Gram in the same
    scales, p the number of design columns), or None when it is refused: the equilibrated
    condition number of its design part is above KAPPA_GRAM, a target's norm is above
    RESID_RATIO_GRAM times its residual's, or the sum is not positive definite."""
    try:
        new = linalg.cholesky(r.T @ r + g, lower=False, check_finite=False)
        ok = equilibrated_cond(new[:p, :p]) <= KAPPA_GRAM and bool(
            np.all(
                np.linalg.norm(new[:, p:], axis=0) <= RESID_RATIO_GRAM * np.linalg.norm(new[p:, p:], axis=0)
            )
        )
    except linalg.LinAlgError:
        return None
    return new if ok else None
