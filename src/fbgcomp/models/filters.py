"""First-order low-pass filters of time series, exact for inputs held between samples.

The thermal lag of the dynamic model's temperature features (:mod:`fbgcomp.models.dynamic`) and
the physical model's probe smoothing, housing leads and load tracking
(:mod:`fbgcomp.models.physical`) all run through these two functions, in streaming form (a state
carried between batches) or over a whole campaign.
"""

from __future__ import annotations

import math

import numpy as np

# Rows per block of :func:`decay_scan`: each block's response is one product with the block's
# lower-triangular matrix of decay powers; a short run is a plain loop.
_SCAN_BLOCK = 64


def lowpass_name(tau_s: float, base: str) -> str:
    """Name of the feature ``base`` low-passed with time constant ``tau_s`` s (``lp3600s_dT_bulk``)."""
    return f"lp{round(tau_s)}s_{base}"


def first_order_recursion(x, u, y0, gain=True):
    """First-order recursion over rows with a per-row decay ``c = exp(-x)`` (x >= 0, e.g. the
    frame interval over a time constant): ``y_i = c_i y_{i-1} + (1 - c_i) u_i`` (``gain=False``:
    ``+ u_i``), from ``y0``; (n, k) from (n, k) ``u``. Closed form per stretch whose summed
    decay stays below e^-600 (so that no weight overflows); every weight is positive, so no
    cancellation beyond the recursion's own."""
    if len(x) == 1:  # one frame (a runtime batch of 1): the recursion's single step, no setup
        u0, y = np.asarray(u, float)[0].tolist(), np.asarray(y0, float).tolist()
        return np.array([first_order_step(float(x[0]), u0, y, gain)])
    x = np.minimum(np.asarray(x, float), 600.0)  # exp(-600): no memory left either way
    u = np.asarray(u, float)
    w = -np.expm1(-x)[:, None] * u if gain else u
    y_prev = np.asarray(y0, float)
    L = np.cumsum(x)
    n = len(x)
    if n and L[-1] <= 600.0:  # one stretch (every runtime batch): the loop below, once
        acc = np.cumsum(np.exp(L)[:, None] * w, axis=0)
        return np.exp(-L)[:, None] * (y_prev[None, :] + acc)
    out = np.empty_like(w)
    start = 0
    while start < n:
        base = L[start - 1] if start else 0.0
        stop = int(np.searchsorted(L, base + 600.0, side="right"))
        stop = min(max(stop, start + 1), n)
        Ls = L[start:stop] - base  # >= 0, <= 600 (or one row)
        acc = np.cumsum(np.exp(Ls)[:, None] * w[start:stop], axis=0)
        out[start:stop] = np.exp(-Ls)[:, None] * (y_prev[None, :] + acc)
        y_prev = out[stop - 1]
        start = stop
    return out


def decay_scan(a: float, b: np.ndarray, y0: np.ndarray) -> np.ndarray:
    """``y_i = a y_{i-1} + b_i`` over the rows of ``b`` (n, k) from ``y_{-1} = y0`` (k,), for a
    decay ``0 <= a <= 1``: what ``scipy.signal.lfilter([1], [1, -a], b, axis=0, zi=a y0)``
    computes, as accurately (each row a sum of at most 64 decayed terms and the carried state,
    ~1e-15 relative against an extended-precision recursion; tests/test_distributions.py),
    without scipy.signal, whose import (with scipy.stats, which it imports) was most of the
    0.75 s that the model stack's imports lost (``benchmarks/bench_startup.py``).

    Blocks of :data:`_SCAN_BLOCK` rows: inside a block the response from rest is one product with
    the matrix ``T[i, j] = a^(i-j)`` (i >= j); the states at the blocks' ends follow the same
    recursion with decay ``a^64``, solved the same way, and each block adds its start state's
    decay ``a^(i+1) s``."""
    b = np.asarray(b, dtype=float)
    y_prev = np.asarray(y0, dtype=float)
    n = b.shape[0]
    B = _SCAN_BLOCK
    if n <= B // 2:
        out = np.empty_like(b)
        for i in range(n):
            y_prev = a * y_prev + b[i]
            out[i] = y_prev
        return out
    m = -(-n // B)
    k = b.shape[1]
    cols = np.zeros((k, m * B))  # column by column, each block's rows contiguous
    cols[:, :n] = b.T
    powers = a ** np.arange(B + 1, dtype=float)  # a^0 .. a^B
    lag = np.subtract.outer(np.arange(B), np.arange(B))
    T = np.where(lag >= 0, powers[np.clip(lag, 0, B)], 0.0)
    z = (cols.reshape(k * m, B) @ T.T).reshape(k, m, B)  # every block from rest: one product
    ends = decay_scan(float(powers[B]), z[:, :, -1].T, y_prev)  # the state at each block's end
    starts = np.vstack([y_prev[None, :], ends[:-1]])  # and at its start (m, k)
    z += starts.T[:, :, None] * powers[None, None, 1:]
    return np.ascontiguousarray(z.reshape(k, m * B)[:, :n].T)


def first_order_step(x, u, y0, gain=True):
    """One row of :func:`first_order_recursion` on Python floats: ``c y0 + (1 - c) u``
    (``gain=False``: ``c y0 + u``) with ``c = exp(-x)``, for sequences ``u`` and ``y0``; a list.
    The runtime's batches of one frame take it where numpy's per-call cost on a few numbers
    was the time; every one-row step of a first-order filter is this arithmetic."""
    c = math.exp(-min(x, 600.0))  # exp(-600): no memory left either way
    if gain:
        return [c * a + (1.0 - c) * b for a, b in zip(y0, u)]
    return [c * a + b for a, b in zip(y0, u)]


def first_order_filter(x, time_s, tau_s, state=None, nominal_dt_s=1.0):
    """First-order low-pass ``tau dy/dt = x - y`` of the columns of x (n, m), exact when each
    input sample holds over the interval that ends at it; returns (y (n, m), state). ``state`` is
    ``(y_last (m,), t_last)`` or None (start at the first sample's value). Vectorised
    (:func:`decay_scan`) when samples are evenly spaced; ``time_s`` None means evenly spaced at ``nominal_dt_s``.
    """
    x = np.atleast_2d(np.asarray(x, dtype=float))
    n = x.shape[0]
    if n == 0:
        return x.copy(), state
    if n == 1 and state is not None and state[1] is not None and time_s is not None:
        # one frame (a runtime batch of 1): the recursion's single step, without the interval
        # arrays below (the same arithmetic)
        y_prev, t_prev = state
        t1 = float(np.ravel(time_s)[0])
        y = first_order_recursion((max(t1 - t_prev, 0.0) / tau_s,), x, y_prev)
        return y, (y[-1].copy(), t1)
    if state is None:
        y_prev, t_prev = x[0].copy(), None
    else:
        y_prev, t_prev = state
    if time_s is None:
        dt = np.full(n, nominal_dt_s)
        t_end = (0.0 if t_prev is None else t_prev) + n * nominal_dt_s
    else:
        t = np.asarray(time_s, dtype=float).ravel()
        first = (t[0] - t_prev) if t_prev is not None else 0.0
        dt = np.concatenate([[first], np.diff(t)])
        t_end = t[-1]
    # evenly spaced (np.allclose's tolerance, without its generic overhead on every batch)
    dev = np.abs(dt[1:] - dt[1]).max() if n > 1 else 0.0
    if n > 1 and dev <= 1e-8 + 1e-5 * abs(dt[1]):
        e = np.exp(-dt[1] / tau_s)
        e0 = np.exp(-max(dt[0], 0.0) / tau_s)
        y0 = e0 * y_prev + (1 - e0) * x[0]
        if n > 1:
            rest = decay_scan(float(e), (1 - e) * x[1:], y0)
            y = np.vstack([y0[None, :], rest])
        else:
            y = y0[None, :]
    else:
        # uneven intervals (a clock's jitter, an epoch's float rounding): the same recursion
        # with a decay per sample, in closed form
        y = first_order_recursion(np.maximum(dt, 0.0) / tau_s, x, y_prev)
    return y, (y[-1].copy(), t_end)
