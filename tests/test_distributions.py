"""The distributions the models' inference uses, without scipy.stats, and the first-order
recursion without scipy.signal: the same values as scipy's to the bit (quantiles, tail
probabilities) or as accurate (the recursion, against an extended-precision reference)."""

import sys

import numpy as np
import pytest
from scipy import signal, stats

from fbgcomp.models import distributions as d
from fbgcomp.models.filters import decay_scan, first_order_filter

Q = np.r_[
    0.0, 1e-300, 1e-12, 1e-3, 0.025, 0.5, 0.975, 1 - 1e-12, 1.0, -0.1, 1.1, np.nan, np.linspace(0.01, 0.99, 7)
]
DF = np.r_[0.0, -1.0, 0.5, 1.0, 2.0, 3.5, 7.0, 30.0, 1e6, np.inf, np.nan]
X = np.r_[-np.inf, -50.0, -3.0, -1e-9, 0.0, 1e-9, 0.7, 2.0, 3.0, 50.0, np.inf, np.nan]


def _same(a, b):
    a, b = np.asarray(a), np.asarray(b)
    return a.shape == b.shape and a.dtype == b.dtype and np.array_equal(a, b, equal_nan=True)


@pytest.mark.parametrize(
    "ours, theirs, grid",
    [
        (d.norm_ppf, stats.norm.ppf, (Q,)),
        (d.norm_isf, stats.norm.isf, (Q,)),
        (d.chi2_ppf, stats.chi2.ppf, (Q, DF)),
        (d.t_ppf, stats.t.ppf, (Q, DF)),
        (d.t_sf, stats.t.sf, (X, DF)),
        (d.f_sf, stats.f.sf, (X, DF, DF)),
    ],
    ids=["norm.ppf", "norm.isf", "chi2.ppf", "t.ppf", "t.sf", "f.sf"],
)
def test_each_is_scipy_stats_to_the_bit_on_every_edge(ours, theirs, grid):
    # every combination, as arrays (broadcast) and one scalar at a time (0-d results)
    mesh = np.meshgrid(*grid, indexing="ij")
    assert _same(ours(*mesh), theirs(*mesh))
    for args in zip(*(m.ravel() for m in mesh)):
        got, want = ours(*args), theirs(*args)
        assert type(got) is type(want) and _same(got, want), (args, got, want)


def test_the_model_stack_loads_without_scipys_heavy_subpackages():
    # scipy.signal (which imports scipy.stats), scipy.optimize and scipy.ndimage were ~0.75 s of
    # every command's start-up (benchmarks/bench_startup.py); only fits and twin runs need them
    import subprocess

    code = (
        "import sys\n"
        "import fbgcomp.models.registry, fbgcomp.models.physical, fbgcomp.models.compare\n"
        "import fbgcomp.runtime.pipeline, fbgcomp.runtime.service, fbgcomp.cli.offline\n"
        "heavy = ('scipy.stats', 'scipy.signal', 'scipy.optimize', 'scipy.ndimage')\n"
        "print(sorted(m for m in heavy if m in sys.modules))\n"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert r.stdout.strip() == "[]", r.stdout + r.stderr


@pytest.mark.parametrize("n", [0, 1, 5, 32, 33, 64, 65, 1000, 4097, 20000])
@pytest.mark.parametrize("a", [0.0, 0.5, float(np.exp(-1 / 60)), float(np.exp(-1 / 3600)), 1.0])
def test_decay_scan_is_the_recursion_lfilter_computes(n, a):
    rng = np.random.default_rng(n)
    b, y0 = rng.normal(size=(n, 3)), rng.normal(size=3)
    got = decay_scan(a, b, y0)
    assert got.shape == (n, 3) and got.flags.c_contiguous
    if n:
        want, _ = signal.lfilter([1.0], [1.0, -a], b, axis=0, zi=(a * y0)[None, :])
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-13 * np.abs(want).max())


@pytest.mark.parametrize("tau_s", [60.0, 3600.0])
def test_a_day_of_one_second_frames_low_passed_as_accurately_as_in_extended_precision(tau_s):
    rng = np.random.default_rng(1)
    n = 86_400
    x = np.cumsum(rng.normal(size=(n, 2)), axis=0) + 20.0
    y, state = first_order_filter(x, np.arange(n, dtype=float), tau_s)
    c = np.exp(-np.longdouble(1) / np.longdouble(tau_s))
    ref = np.empty((n, 2), dtype=np.longdouble)
    acc = x[0].astype(np.longdouble)
    for i, row in enumerate(x.astype(np.longdouble)):
        acc = c * acc + (1 - c) * row
        ref[i] = acc
    err = np.abs(y - ref).max() / np.abs(ref).max()
    assert err < 1e-14, err  # lfilter's own: 1e-15 to 1e-14
    np.testing.assert_array_equal(state[0], y[-1])
