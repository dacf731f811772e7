"""Quantiles and tail probabilities of the normal, Student t, chi-square and F distributions.

Each is the :mod:`scipy.special` function that :mod:`scipy.stats` itself evaluates for that
distribution (``norm.ppf`` is ``ndtri``, ``t.sf`` is ``stdtr(df, -x)``, ...), with its handling of
invalid parameters and of the support's ends, so the values are the same to the bit
(tests/test_distributions.py checks it on grids with the edge cases). What they spare is the
import: without scipy.stats and scipy.signal (which imports it), scipy.optimize and
scipy.ndimage, the imports of the commands that load a model take 1.52 s instead of 2.27
(``benchmarks/bench_startup.py``).

Arguments broadcast like numpy's; a 0-d result comes back as a numpy float, as scipy.stats
returns it.
"""

from __future__ import annotations

import numpy as np
from scipy import special

__all__ = ["chi2_ppf", "f_sf", "norm_isf", "norm_ppf", "t_ppf", "t_sf"]


def _out(a: np.ndarray):
    return a[()] if a.ndim == 0 else a


def _quantile(q, ok, inner, lo, hi):
    """scipy.stats' ppf around ``inner`` (the distribution's _ppf on the valid interior):
    ``lo`` at q = 0, ``hi`` at q = 1, NaN for q outside [0, 1] or invalid parameters."""
    q = np.asarray(q, dtype=float)
    shape = np.broadcast(q, ok).shape
    q, ok = np.broadcast_to(q, shape), np.broadcast_to(ok, shape)
    out = np.full(shape, np.nan)
    inside = ok & (q > 0) & (q < 1)
    out[ok & (q == 0)] = lo
    out[ok & (q == 1)] = hi
    if inside.any():
        out[inside] = inner(inside)
    return _out(out)


def norm_ppf(q):
    """Standard normal quantile (``scipy.stats.norm.ppf``)."""
    q = np.asarray(q, dtype=float)
    return _quantile(q, np.ones(q.shape, bool), lambda m: special.ndtri(q[m]), -np.inf, np.inf)


def norm_isf(q):
    """Standard normal upper quantile: the x with P(X > x) = q (``scipy.stats.norm.isf``)."""
    q = np.asarray(q, dtype=float)
    return _quantile(q, np.ones(q.shape, bool), lambda m: -special.ndtri(q[m]), np.inf, -np.inf)


def _valid_df(*dfs):
    """Degrees of freedom scipy.stats accepts: > 0 (inf included), not NaN."""
    return np.logical_and.reduce([np.asarray(d, dtype=float) > 0 for d in dfs])


def chi2_ppf(q, df):
    """Chi-square quantile with ``df`` degrees of freedom (``scipy.stats.chi2.ppf``)."""
    q, df = np.broadcast_arrays(np.asarray(q, dtype=float), np.asarray(df, dtype=float))
    return _quantile(q, _valid_df(df), lambda m: 2 * special.gammaincinv(df[m] / 2, q[m]), 0.0, np.inf)


def t_ppf(q, df):
    """Student t quantile with ``df`` degrees of freedom (``scipy.stats.t.ppf``)."""
    q, df = np.broadcast_arrays(np.asarray(q, dtype=float), np.asarray(df, dtype=float))
    return _quantile(q, _valid_df(df), lambda m: special.stdtrit(df[m], q[m]), -np.inf, np.inf)


def _tail(x, ok, inner, below, above, a, b):
    """scipy.stats' sf around ``inner`` (the _sf on the open support (a, b)): ``below`` for
    x <= a, ``above`` for x >= b, NaN for NaN x or invalid parameters."""
    x = np.asarray(x, dtype=float)
    shape = np.broadcast(x, ok).shape
    x, ok = np.broadcast_to(x, shape), np.broadcast_to(ok, shape)
    out = np.full(shape, np.nan)
    inside = ok & (x > a) & (x < b)
    out[ok & (x <= a)] = below
    out[ok & (x >= b)] = above
    if inside.any():
        out[inside] = inner(inside)
    return _out(out)


def t_sf(x, df):
    """Student t survival function P(T > x) (``scipy.stats.t.sf``)."""
    x, df = np.broadcast_arrays(np.asarray(x, dtype=float), np.asarray(df, dtype=float))
    return _tail(x, _valid_df(df), lambda m: special.stdtr(df[m], -x[m]), 1.0, 0.0, -np.inf, np.inf)


def f_sf(x, dfn, dfd):
    """F survival function P(F > x) with (dfn, dfd) degrees of freedom (``scipy.stats.f.sf``)."""
    x, dfn, dfd = np.broadcast_arrays(*(np.asarray(v, dtype=float) for v in (x, dfn, dfd)))
    return _tail(x, _valid_df(dfn, dfd), lambda m: special.fdtrc(dfn[m], dfd[m], x[m]), 1.0, 0.0, 0.0, np.inf)
