"""Do-no-harm policy: what part of a predicted TTP deviation is safe to apply.

A compensation model is only validated inside the conditions it was fitted on. These pure,
vectorised functions turn an applicability check into the correction actually applied, per frame
and per axis:

* :func:`clip_to_envelope` keeps thermal regressors inside the training envelope (plus a margin),
  so a heat source absent from training can never drive a regression term into extrapolation;
* :func:`firm` shrinks an estimated load component to zero unless it stands clear of its own
  uncertainty (continuous, unbiased for large loads, zero for noise);
* :func:`contradiction` flags frames whose gratings disagree with every load the structure can
  carry (a chi-square test of the generalised least-squares residual);
* :func:`clamp_axes` bounds each axis' correction to what was validated.

Flags are per frame and axis, a uint8 bit word shared with the runtime
(:mod:`fbgcomp.runtime.health`): ``SHRUNK`` (inputs outside the training envelope),
``CLAMPED`` (bounded to the model's maximum), ``LOAD_REFUSED`` (the gratings contradict each
other; the load part was dropped).
"""

from __future__ import annotations

import numpy as np

from fbgcomp.models.distributions import chi2_ppf

SHRUNK = np.uint8(1)
CLAMPED = np.uint8(2)
LOAD_REFUSED = np.uint8(4)


def clip_to_envelope(x, low, high, margin=0.1):
    """Clip columns of ``x`` (n, m) to ``[low - margin*span, high + margin*span]``.

    Returns the clipped array and a boolean (n,) that is True where any column was clipped.
    ``low`` and ``high`` are the training minimum and maximum of each column (same units as x).
    """
    x = np.atleast_2d(np.asarray(x, dtype=float))
    if x.shape[0] == 1:  # one frame (a runtime batch of 1): the same arithmetic on Python floats
        out, outside = [], False
        for v, a, b in zip(x[0].tolist(), np.ravel(low).tolist(), np.ravel(high).tolist()):
            span = max(b - a, 0.0)
            lo, hi = a - margin * span, b + margin * span
            outside = outside or v < lo or v > hi
            out.append(min(max(v, lo), hi))
        return np.array([out]), np.array([outside])
    low, high = np.asarray(low, dtype=float), np.asarray(high, dtype=float)
    span = np.maximum(high - low, 0.0)
    lo, hi = low - margin * span, high + margin * span
    clipped = np.clip(x, lo, hi)
    outside = np.any((x < lo) | (x > hi), axis=1) if x.shape[1] else np.zeros(x.shape[0], bool)
    return clipped, outside


# at most this many numbers go through firm's Python-float path
_FLOAT_PATH = 8


def firm(estimate, sigma, k_low=3.0, k_high=6.0):
    """Firm shrinkage (Gao & Bruce 1997), element-wise: zero within ``k_low`` sigma, the
    estimate itself beyond ``k_high`` sigma, a linear ramp in between.

    Unlike the garrote it leaves a clearly significant load unbiased (a static plateau keeps its
    full value) while noise and thermal mismatch below ``k_low`` sigma are never applied.
    """
    x = np.asarray(estimate, dtype=float)
    # On Python floats, where numpy's per-call cost on a few numbers was the time (the same
    # arithmetic, firm1): one frame (1, n) with a sigma per column (a runtime batch of one), or
    # a vector of a few numbers with one sigma or one each (the load tracker's three force
    # components, each frame of a load transition)
    one_frame = x.ndim == 2 and x.shape[0] == 1 and np.ndim(sigma) == 1
    few = x.ndim == 1 and x.size <= _FLOAT_PATH and np.shape(sigma) in ((), x.shape)
    if one_frame or few:
        v = x.ravel().tolist()
        sd = [float(sigma)] * len(v) if np.ndim(sigma) == 0 else np.asarray(sigma, float).tolist()
        return np.array([firm1(a, b, k_low, k_high) for a, b in zip(v, sd)]).reshape(*x.shape[:-1], -1)
    s = np.asarray(sigma, dtype=float)
    lo, hi = k_low * s, k_high * s
    with np.errstate(divide="ignore", invalid="ignore"):
        ramp = np.where(hi > lo, (np.abs(x) - lo) / (hi - lo), 1.0)
        factor = np.where(
            np.abs(x) <= lo, 0.0, np.clip(ramp * hi / np.where(x == 0, 1.0, np.abs(x)), 0.0, 1.0)
        )
    factor = np.where(np.abs(x) >= hi, 1.0, factor)
    return x * factor


def firm1(x, s, k_low, k_high):
    """:func:`firm` of one number ``x`` with its sigma ``s``, on Python floats (the same
    arithmetic): the load tracker's per-frame path."""
    lo, hi = k_low * s, k_high * s
    a = abs(x)
    if a >= hi:
        return x
    if a <= lo:
        return x * 0.0
    ramp = (a - lo) / (hi - lo) if hi > lo else 1.0
    return x * min(max(ramp * hi / (a if x != 0 else 1.0), 0.0), 1.0)


def contradiction(chi2, dof, p_value=1e-3, inflation=1.0):
    """True where a chi-square statistic with ``dof`` degrees of freedom exceeds its
    ``1 - p_value`` quantile times ``inflation`` (never true without degrees of freedom)."""
    chi2 = np.asarray(chi2, dtype=float)
    if dof < 1:
        return np.zeros(chi2.shape, bool)
    return chi2 > inflation * chi2_ppf(1.0 - p_value, dof)


def clamp_axes(deviation_um, low_um, high_um):
    """Clamp each axis (columns of an (n, 3) array) to ``[low_um, high_um]``; returns the
    clamped array and a boolean (n, 3) of clamped entries."""
    d = np.atleast_2d(np.asarray(deviation_um, dtype=float))
    out = np.clip(d, low_um, high_um)
    return out, out != d
