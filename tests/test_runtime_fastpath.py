"""The runtime's steady-state path (Pipeline._process_steady, SensorChecks.all_good, the output
filter's no-block-closes branch, the one-frame rate-limit test) gives the same results, to the
bit, as the general path it shortcuts - batch by batch, through faults, mode hops, a stuck
channel, missing probes, the envelope and the rate limit - and the same whatever the batching."""

import numpy as np
import pytest

from fbgcomp.bench.served import BATCH_FIELDS as FIELDS
from fbgcomp.runtime import health as H
from fbgcomp.runtime.pipeline import Pipeline, PipelineConfig
from test_runtime_support import run_in_batches


class GeneralOnly(Pipeline):
    """The pipeline with its steady-state path switched off (the reference)."""

    def _process_steady(self, *args, **kwargs):
        return None


@pytest.fixture(scope="session")
def setup(runtime_model_and_arrays):
    model, time_s, w, t = runtime_model_and_arrays
    rng = np.random.default_rng(4)
    # noise of a live grating (a noise-free replay repeats values: the stuck check's case)
    w = w + 3e-4 * rng.standard_normal(w.shape)
    return model, time_s, w, t


def _faulted(model, time_s, w, t):
    """Every fault the runtime handles, one after the other."""
    w, t = w.copy(), t.copy()
    counts = np.ones(w.shape, np.int8)
    s = {name: model.sensor_names.index(name) for name in model.sensor_names}
    lost = (time_s >= 40.0) & (time_s < 55.0)
    w[lost, s["S3"]] = np.nan
    counts[lost, s["S3"]] = 0
    doubled = (time_s >= 70.0) & (time_s < 71.0)
    counts[doubled, s["S1"]] = 2
    w[doubled, s["S1"]] = np.nan
    w[time_s >= 90.0, s["S2"]] += 0.4  # a mode hop, kept
    stuck = (time_s >= 120.0) & (time_s < 125.0)
    w[stuck, s["S4"]] = w[np.argmax(stuck), s["S4"]]
    t[(time_s >= 140.0) & (time_s < 141.0), 0] = np.nan  # a probe lost for a second
    w[(time_s >= 160.0) & (time_s < 161.0), :] += 2.0  # every grating, a huge step
    return w, t, counts


def _assert_same(a, b):
    for f in FIELDS:
        np.testing.assert_array_equal(a[f], b[f], err_msg=f)


@pytest.mark.parametrize("sizes", [[1], [3, 1, 50], [100], [1000]])
def test_steady_path_equals_general_path_through_faults(setup, sizes):
    model, time_s, w, t = setup
    n = int(np.searchsorted(time_s, 200.0))
    wf, tf, counts = _faulted(model, time_s[:n], w[:n], t[:n])
    cfg = dict(max_slew_um_per_s=(50.0, 50.0, 50.0), max_correction_um=(400.0, 400.0, 400.0))
    fast = run_in_batches(Pipeline(model, PipelineConfig(**cfg)), time_s[:n], wf, tf, sizes, counts)
    ref = run_in_batches(GeneralOnly(model, PipelineConfig(**cfg)), time_s[:n], wf, tf, sizes, counts)
    _assert_same(fast, ref)
    # the faults did happen (else the test would compare two steady runs only)
    assert (fast["sensor_status"] == H.MISSING).any() and (fast["sensor_status"] == H.STUCK).any()
    assert (fast["output_flags"] & H.FLAG_RATE_LIMITED).any()
    assert (fast["health"] == 2).any()  # ALARM (the probe lost)


def test_steady_path_is_taken_and_results_do_not_depend_on_batching(setup):
    model, time_s, w, t = setup
    n = int(np.searchsorted(time_s, 120.0))
    pipe = Pipeline(model)
    calls = {"steady": 0}
    steady = pipe._process_steady

    def counting(*args):
        r = steady(*args)
        calls["steady"] += r is not None
        return r

    pipe._process_steady = counting
    one = run_in_batches(pipe, time_s[:n], w[:n], t[:n], [1])
    zero_frames = int(np.searchsorted(time_s, time_s[0] + model.zero_window_s, "right"))
    # every frame after the zero window but the first takes the steady path
    assert calls["steady"] >= n - zero_frames - 2
    for sizes in ([7, 100, 1], [5000]):
        other = run_in_batches(Pipeline(model), time_s[:n], w[:n], t[:n], sizes)
        for f in FIELDS:
            if other[f].dtype.kind == "f":
                # the model's matrix products round their last bits by the batch's shape
                np.testing.assert_allclose(one[f], other[f], rtol=0, atol=1e-12, err_msg=f)
            else:
                np.testing.assert_array_equal(one[f], other[f], err_msg=f)


def test_all_good_carries_the_same_state_as_check():
    rng = np.random.default_rng(1)
    S = 4
    t = 1.7e9 + np.arange(50) * 1e-3
    w = 1530.0 + np.cumsum(1e-4 * rng.standard_normal((50, S)), axis=0)
    counts = np.ones((50, S), np.int8)
    a, b = H.SensorChecks(S), H.SensorChecks(S)
    a.check(t[:10], w[:10], counts[:10], counts[:10] * 0)
    b.check(t[:10], w[:10], counts[:10], counts[:10] * 0)
    a.offset_nm[:] = b.offset_nm[:] = [0.0, 0.3, 0.0, 0.0]
    for lo, hi in ((10, 11), (11, 30), (30, 50)):
        assert a.all_good(t[lo:hi], w[lo:hi], counts[lo:hi])
        status, faulted = b.check(t[lo:hi], w[lo:hi], counts[lo:hi], counts[lo:hi] * 0)
        assert not status.any() and not faulted.any()
        for name in ("last_value", "last_raw", "last_change_s", "last_bad_s", "offset_nm", "row_offset_nm"):
            np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
    # a repeated value, a missing peak, a jump: not for the steady path, state untouched
    before = a.last_value.copy()
    assert not a.all_good(t[:1] + 1, a.last_value[None, :].copy(), counts[:1])
    assert not a.all_good(t[:1] + 1, before[None, :] + 1e-4, counts[:1] * 0)
    assert not a.all_good(t[:1] + 1, before[None, :] + 0.2, counts[:1])
    np.testing.assert_array_equal(a.last_value, before)
