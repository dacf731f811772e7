"""Temperature look-up against the wavelength clock: the one-frame path (a high frame rate)
answers exactly what the batch path answers, at, between and before the recorded samples."""

import numpy as np
import pytest

from fbgcomp.runtime.sources import TableTemperatures


@pytest.mark.parametrize("speed", [1.0, 2.5])
def test_one_frame_look_up_equals_the_batch_look_up(speed):
    rng = np.random.default_rng(2)
    t = np.cumsum(rng.uniform(5.0, 15.0, 50))  # the campaign clock, irregular
    values = 20.0 + rng.normal(0.0, 1.0, (50, 3))
    origin = 1.7e9 + 0.123456  # an epoch: float64 holds it to ~0.2 µs
    # frames: exactly at samples (on the epoch clock), just before and after, between, and
    # before the first sample (no temperature yet: NaN)
    camp = np.concatenate([t, t - 1e-4, t + 1e-4, t[:-1] + np.diff(t) / 2, [t[0] - 3.0, t[0] - 0.5]])
    frames = np.sort(origin + camp / speed)
    batch = TableTemperatures(["a", "b", "c"], t, values, speed, clock_origin_s=origin).latest(frames)
    one_by_one = TableTemperatures(["a", "b", "c"], t, values, speed, clock_origin_s=origin)
    single = np.vstack([one_by_one.latest(frames[i : i + 1]) for i in range(frames.size)])
    np.testing.assert_array_equal(single, batch)
    assert np.isnan(single[:3]).all() and np.isfinite(single[3:]).all()  # t0 - 3, - 0.5, - 1e-4 s
    # a frame stamped at a sample reads that sample, not the one before
    at = TableTemperatures(["a", "b", "c"], t, values, speed, clock_origin_s=origin)
    for i in (0, 17, 49):
        np.testing.assert_array_equal(at.latest(np.array([origin + t[i] / speed])), values[i : i + 1])
