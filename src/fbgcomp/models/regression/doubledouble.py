"""Double-double arithmetic (Dekker 1971; Hida, Li & Bailey 2001), vectorised over numpy arrays.

A value is the pair (hi, lo) with |lo| <= ulp(hi) / 2, an unevaluated sum of two doubles (~32
significant digits). Error-free transformations rely on IEEE round-to-nearest, which numpy's
separate ufunc calls honour (no FMA contraction). On top of the four operations and the square
root: pairwise sums, Householder QR and triangular back substitution, which keep the streamed
factor of :mod:`fbgcomp.models.regression` accurate on ill-conditioned designs (NIST Filip).
"""

from __future__ import annotations

import math

import numpy as np

__all__ = [
    "dd_add",
    "dd_div",
    "dd_householder",
    "dd_mul",
    "dd_qr_r",
    "dd_solve_upper",
    "dd_sqrt",
    "dd_sum_rows",
]

_DEKKER = 134217729.0  # 2**27 + 1


def _two_sum(a, b):
    """Error-free sum (Knuth): ``s + e == a + b`` exactly, ``s = fl(a + b)``."""
    s = a + b
    bb = s - a
    return s, (a - (s - bb)) + (b - bb)


def _fast_two_sum(a, b):
    """Error-free sum for ``|a| >= |b|`` (Dekker): ``s + e == a + b`` exactly."""
    s = a + b
    return s, b - (s - a)


def _split(a):
    """Veltkamp split of ``a`` into two 26-bit halves, ``hi + lo == a``."""
    t = _DEKKER * a
    hi = t - (t - a)
    return hi, a - hi


def _two_prod(a, b):
    """Error-free product (Dekker): ``p + e == a * b`` exactly, ``p = fl(a * b)``."""
    p = a * b
    ah, al = _split(a)
    bh, bl = _split(b)
    return p, ((ah * bh - p) + ah * bl + al * bh) + al * bl


def dd_add(ah, al, bh, bl):
    """Double-double sum ``(ah + al) + (bh + bl)`` as (hi, lo)."""
    s, e = _two_sum(ah, bh)
    t, f = _two_sum(al, bl)
    s, e = _fast_two_sum(s, e + t)
    return _fast_two_sum(s, e + f)


def dd_mul(ah, al, bh, bl):
    """Double-double product ``(ah + al) * (bh + bl)`` as (hi, lo)."""
    p, e = _two_prod(ah, bh)
    return _fast_two_sum(p, e + (ah * bl + al * bh))


def dd_div(ah, al, bh, bl):
    """Double-double quotient ``(ah + al) / (bh + bl)`` as (hi, lo) (two correction steps)."""
    q1 = ah / bh
    ph, pl = dd_mul(q1, 0.0 * q1, bh, bl)
    rh, rl = dd_add(ah, al, -ph, -pl)
    q2 = rh / bh
    ph, pl = dd_mul(q2, 0.0 * q2, bh, bl)
    rh, _ = dd_add(rh, rl, -ph, -pl)
    q1, q2 = _fast_two_sum(q1, q2)
    return dd_add(q1, q2, rh / bh, 0.0 * q1)


def dd_sqrt(ah: float, al: float) -> tuple[float, float]:
    """Double-double square root of the scalar ``ah + al`` (0 for a non-positive value)."""
    if ah <= 0.0:
        return 0.0, 0.0
    x = math.sqrt(ah)
    p, e = _two_prod(x, x)
    return _fast_two_sum(x, ((ah - p) - e + al) / (2.0 * x))


def dd_sum_rows(h: np.ndarray, lo: np.ndarray):
    """Sum along axis 0 by a pairwise tree of double-double additions."""
    while h.shape[0] > 1:
        if h.shape[0] % 2:
            h = np.concatenate([h, np.zeros_like(h[:1])])
            lo = np.concatenate([lo, np.zeros_like(lo[:1])])
        h, lo = dd_add(h[0::2], lo[0::2], h[1::2], lo[1::2])
    return h[0], lo[0]


def dd_householder(mh: np.ndarray, ml: np.ndarray, ncols: int) -> tuple[np.ndarray, np.ndarray]:
    """Apply Householder reflections in double-double to zero the first ``ncols`` columns of the
    r x c matrix mh + ml below the diagonal; returns the whole transformed matrix (hi, lo).

    Reflector ``H = I - v v^T / (sigma |v_0|)`` with ``v = x + sign(x_0) sigma e_1`` (no
    cancellation) and ``v^T v = 2 sigma |v_0|``; Householder's method in 32-digit arithmetic.
    """
    mh = np.array(mh, dtype=float)
    ml = np.array(ml, dtype=float)
    r, c = mh.shape
    for j in range(min(r, c, ncols)):
        xh, xl = mh[j:, j], ml[j:, j]
        sig_h, sig_l = dd_sqrt(*dd_sum_rows(*dd_mul(xh, xl, xh, xl)))
        if sig_h == 0.0:
            continue
        sign = 1.0 if xh[0] >= 0.0 else -1.0
        vh = xh.copy()
        vl = xl.copy()
        vh[0], vl[0] = dd_add(xh[0], xl[0], sign * sig_h, sign * sig_l)
        if j + 1 < c:
            dh, dl = dd_mul(sig_h, sig_l, sign * vh[0], sign * vl[0])
            th, tl = mh[j:, j + 1 :], ml[j:, j + 1 :]
            wh, wl = dd_sum_rows(*dd_mul(vh[:, None], vl[:, None], th, tl))
            fh, fl = dd_div(wh, wl, dh, dl)
            uh, ul = dd_mul(vh[:, None], vl[:, None], fh[None, :], fl[None, :])
            mh[j:, j + 1 :], ml[j:, j + 1 :] = dd_add(th, tl, -uh, -ul)
        mh[j, j], ml[j, j] = -sign * sig_h, -sign * sig_l
        mh[j + 1 :, j] = 0.0
        ml[j + 1 :, j] = 0.0
    return mh, ml


def dd_qr_r(mh: np.ndarray, ml: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Householder QR in double-double: the c x c triangle R (hi, lo) of the r x c matrix mh + ml
    (zero rows appended when r < c)."""
    r, c = np.shape(mh)
    mh, ml = dd_householder(mh, ml, c)
    k = min(r, c)
    rh = np.zeros((c, c))
    rl = np.zeros((c, c))
    rh[:k] = np.triu(mh[:k])
    rl[:k] = np.triu(ml[:k])
    return rh, rl


def dd_solve_upper(th, tl, zh, zl) -> tuple[np.ndarray, np.ndarray]:
    """Back substitution ``T B = Z`` in double-double (T upper triangular, non-singular; Z a
    vector or a matrix of right-hand sides)."""
    n = th.shape[0]
    zh = np.asarray(zh, dtype=float)
    zl = np.asarray(zl, dtype=float)
    bh = np.zeros_like(zh)
    bl = np.zeros_like(zh)
    for i in range(n - 1, -1, -1):
        sh, sl = zh[i], zl[i]
        if i + 1 < n:
            ah = th[i, i + 1 :].reshape((-1,) + (1,) * (zh.ndim - 1))
            al = tl[i, i + 1 :].reshape(ah.shape)
            qh, ql = dd_sum_rows(*dd_mul(ah, al, bh[i + 1 :], bl[i + 1 :]))
            sh, sl = dd_add(sh, sl, -qh, -ql)
        bh[i], bl[i] = dd_div(sh, sl, th[i, i], tl[i, i])
    return bh, bl
