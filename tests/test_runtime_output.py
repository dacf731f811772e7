"""Output policy: adaptive filter, per-axis maximum and rate limit, flag word (model | limits)."""

import numpy as np
import pytest

from fbgcomp.io.campaign import read_campaign
from fbgcomp.models import Predictor, load_model
from fbgcomp.runtime import health as H
from fbgcomp.runtime.output_filter import AdaptiveLevelFilter, OutputFilterConfig
from fbgcomp.runtime.pipeline import HEALTH_DEGRADED, Pipeline, PipelineConfig
from test_runtime_support import run_in_batches


@pytest.fixture(scope="session")
def setup(runtime_model_and_campaign):
    model_path, campaign_path = runtime_model_and_campaign
    campaign = read_campaign(campaign_path)
    model = load_model(model_path)
    aligned = campaign.aligned(zero_window_s=model.zero_window_s)
    w, t, _, _ = model.instrument_arrays(aligned)
    return model_path, aligned, w, t


class EnvelopePredictor(Predictor):
    """The regression predictor with a model-side output policy, as the new default model type
    will have: beyond ``limit_um`` on an axis it shrinks the deviation to the limit (SHRUNK),
    and it refuses the load part (LOAD_REFUSED) on dz whenever dy is shrunk."""

    limit_um = 0.2

    def predict(self, wavelength_nm, temperature_C, wavelength_zero_nm, temperature_zero_C):
        dev, half = super().predict(wavelength_nm, temperature_C, wavelength_zero_nm, temperature_zero_C)
        over = np.abs(dev) > self.limit_um
        flags = np.where(over, H.FLAG_SHRUNK, 0).astype(np.uint8)
        flags[:, 2] |= np.where(over[:, 1], H.FLAG_LOAD_REFUSED, 0).astype(np.uint8)
        self.last_flags = flags
        return np.clip(dev, -self.limit_um, self.limit_um), half


def _envelope_model(model_path, max_correction_um=None):
    model = load_model(model_path)
    base = type(model)

    class EnvelopeModel(base):
        # a plain attribute, so a test can set its own bound (MRAModel's is a property
        # derived from the training deviations its file records)
        max_correction_um = None

        def predictor(self, exclude=frozenset()):
            p = base.predictor(self, exclude)
            p.__class__ = EnvelopePredictor
            return p

    model.__class__ = EnvelopeModel
    if max_correction_um is not None:
        model.max_correction_um = max_correction_um
    return model


def test_defaults_bound_and_rate_limit_every_axis():
    cfg = PipelineConfig()
    assert tuple(cfg.max_correction_um) == (1000.0, 1000.0, 1000.0)
    assert tuple(cfg.max_slew_um_per_s) == (1000.0, 1000.0, 1000.0)
    assert cfg.output_filter.enabled


def test_model_flags_and_limiter_flags_reach_the_batch_result(setup):
    model_path, aligned, w, t = setup
    model = _envelope_model(model_path, max_correction_um=(5.0, 0.15, 5.0))
    raw = dict(output_filter=OutputFilterConfig(enabled=False))
    runs = [
        run_in_batches(
            Pipeline(model, PipelineConfig(max_slew_um_per_s=(0, 0.02, 0), **raw)),
            aligned.time_s,
            w,
            t,
            sizes,
        )
        for sizes in ([1], [13, 200], [10_000])
    ]
    for r in runs[1:]:
        np.testing.assert_array_equal(r["output_flags"], runs[0]["output_flags"])
        np.testing.assert_allclose(r["correction_um"], runs[0]["correction_um"], atol=1e-9)
    r = runs[0]
    flags, dev, corr = r["output_flags"], r["deviation_um"], r["correction_um"]
    shrunk = np.abs(dev) >= EnvelopePredictor.limit_um - 1e-12
    assert shrunk[:, 1].any()
    # the model's bits are carried as the predictor set them
    assert ((flags & H.FLAG_SHRUNK) > 0)[shrunk].all()
    assert ((flags[:, 2] & H.FLAG_LOAD_REFUSED) > 0)[shrunk[:, 1]].all()
    assert not (flags & H.MODEL_FLAGS)[~np.isfinite(dev).any(axis=1)].any()
    # dy: the model file's own bound (0.15 µm) is tighter than the configured 1000 µm
    assert np.abs(corr[:, 1]).max() <= 0.15 + 1e-12
    held = np.abs(dev[:, 1]) > 0.15
    assert held.any() and ((flags[held, 1] & H.FLAG_MAX_LIMITED) > 0).all()
    assert not (flags[:, 0] & H.FLAG_MAX_LIMITED).any()
    # rate limit 0.02 µm/s on dy only; flagged where it held the output back
    dt = np.diff(aligned.time_s)
    assert (np.abs(np.diff(corr[:, 1])) <= 0.02 * dt + 1e-9).all()
    rate = (flags[:, 1] & H.FLAG_RATE_LIMITED) > 0
    assert rate.any() and not (flags[:, 0] & H.FLAG_RATE_LIMITED).any()
    assert "Y:" in H.describe_flags(flags[np.argmax(rate)])
    assert "RATE_LIMITED" in H.describe_flags(flags[np.argmax(rate)])


def test_lost_grating_fallback_still_obeys_the_limits(setup):
    model_path, aligned, w, t = setup
    model = load_model(model_path)
    time_s = aligned.time_s
    wl = w.copy()
    counts = np.ones(wl.shape, np.int8)
    s3 = model.sensor_names.index("S3")
    lost = time_s >= 100.0
    wl[lost, s3] = np.nan
    counts[lost, s3] = 0
    free = run_in_batches(
        Pipeline(
            model,
            PipelineConfig(
                output_filter=OutputFilterConfig(enabled=False), max_slew_um_per_s=0, max_correction_um=0
            ),
        ),
        time_s,
        wl,
        t,
        [64],
        counts,
    )
    i = int(np.argmax(lost))
    step = np.abs(free["correction_um"][i] - free["correction_um"][i - 1])
    cap = 0.5 * np.abs(free["correction_um"][lost]).max(axis=0)  # binds after the switch
    rate = 0.5 * step.max() / 0.1
    cfg = PipelineConfig(max_correction_um=tuple(cap), max_slew_um_per_s=rate)
    runs = [
        run_in_batches(Pipeline(model, cfg), time_s, wl, t, sizes, counts)
        for sizes in ([1], [9, 64], [10_000])
    ]
    for r in runs[1:]:
        np.testing.assert_allclose(r["correction_um"], runs[0]["correction_um"], atol=1e-9)
        np.testing.assert_array_equal(r["output_flags"], runs[0]["output_flags"])
    r = runs[0]
    assert (r["health"][lost] == HEALTH_DEGRADED).all()
    corr, flags = r["correction_um"], r["output_flags"]
    assert (np.abs(corr) <= cap + 1e-12).all()
    assert (np.abs(np.diff(corr, axis=0)) <= rate * np.diff(time_s)[:, None] + 1e-9).all()
    after = flags[lost]
    assert (after & H.FLAG_MAX_LIMITED).any() and (after & H.FLAG_RATE_LIMITED).any()


def _noisy_step(rate_hz=100.0, duration_s=600.0, step_at_s=400.0, step_um=300.0, sd_um=20.0, seed=3):
    rng = np.random.default_rng(seed)
    n = int(duration_s * rate_hz)
    t = np.arange(n) / rate_hz
    # noise correlated over 1 s (a 1 Hz source interpolated), like the twin served live
    knots = rng.normal(0.0, sd_um, int(duration_s) + 2)
    noise = np.interp(t, np.arange(knots.size), knots)
    truth = np.where(t >= step_at_s, step_um, 0.0) + 0.002 * t  # + a slow drift
    x = np.column_stack([noise + truth, 0.3 * noise - truth, truth])
    return t, x, truth


def test_adaptive_filter_is_still_at_rest_and_follows_a_step():
    import pandas as pd

    t, x, truth = _noisy_step()
    f = AdaptiveLevelFilter(OutputFilterConfig(), 0.01, noise_um=np.array([5.0, 5.0, 0.01]))
    y = f.process(x)
    df = pd.DataFrame(y, index=pd.to_timedelta(t, "s"))
    dev = (df - df.rolling("60s", center=True).mean()).to_numpy()
    rest = (t > 300) & (t < 370)  # settled, 30 s clear of the step
    rms = np.sqrt((dev[rest] ** 2).mean(axis=0))
    raw = np.sqrt(((x[rest] - x[rest].mean(axis=0)) ** 2).mean(axis=0))
    assert (rms[:2] < 0.2).all() and raw[0] > 15 and raw[1] > 4.5
    # that noisy an axis averages longer than a quiet one (150 s gave it 0.22 µm RMS here)
    assert (
        f.rest_tau(0) == OutputFilterConfig().rest_tau_max_s
        and f.rest_tau(2) == OutputFilterConfig().rest_tau_s
    )
    # follows the 300 µm step to 90 % within 1 s on every axis, and does not overshoot it:
    # right after the step the level is a median of a second or so of 20 µm noise, later an
    # average of ever more of it
    for j, sign in enumerate((1, -1, 1)):
        after = t >= 400.0
        reach = t[after][np.argmax(sign * y[after, j] >= 0.9 * 300.0)] - 400.0
        assert reach < 1.0, (j, reach)
        err = np.abs(y[:, j] - sign * (300 + 0.002 * t))
        assert err[(t > 401) & (t < 410)].max() < 30 * abs(x[0, j] - truth[0] * sign) / 20 + 1
        assert err[(t > 450) & (t < 600)].max() < 10
    assert (f.restarts >= 1).all()


def _pops(rate_hz=100.0, duration_s=600.0, step_at_s=450.0, step_um=200.0, seed=5):
    """The default model served on the twin at rest: exactly still, but its load part pops
    out of the firm shrinkage ~16 times a minute for 0.3-2.3 s, by up to ~100 µm."""
    rng = np.random.default_rng(seed)
    n = int(duration_s * rate_hz)
    t = np.arange(n) / rate_hz
    x = np.full(n, 0.015)
    start = 0.0
    while True:
        start += rng.exponential(60.0 / 16)
        dur = rng.uniform(0.3, 2.3)
        if start + dur > duration_s:
            break
        sel = (t >= start) & (t < start + dur)
        x[sel] = (
            rng.choice([-1, 1]) * rng.uniform(10.0, 100.0) * np.sin(np.pi * (t[sel] - start) / dur) ** 0.3
        )
    truth = np.where(t >= step_at_s, step_um, 0.0)
    return t, np.column_stack([x + truth, x, np.zeros(n)]), truth


def test_adaptive_filter_ignores_model_pops_and_still_follows_a_step():
    import pandas as pd

    t, x, _truth = _pops()
    f = AdaptiveLevelFilter(OutputFilterConfig(), 0.01, noise_um=np.array([20.0, 20.0, 1.0]))
    y = f.process(x)
    df = pd.DataFrame(y, index=pd.to_timedelta(t, "s"))
    dev = (df - df.rolling("60s", center=True).mean()).to_numpy()
    rest = (t > 300) & (t < 420)  # after 5 min of learning what the pops look like
    rms = np.sqrt((dev[rest] ** 2).mean(axis=0))
    raw = x[rest].std(axis=0)
    assert (rms < 0.2).all() and (raw[:2] > 10).all(), (rms, raw)
    assert (f.undone[:2] >= 1).all()  # pops it did follow at first were taken back
    after = t >= 450.0
    reach = t[after][np.argmax(y[after, 0] >= 0.9 * 200.0)] - 450.0
    assert reach < 1.0, reach
    # the young level after the step averages little yet: a pop moves it a little, never
    # the pop's 10-100 µm; settled, the pops are gone again
    assert np.abs(y[(t > 455) & (t < 500), 0] - 200.0).max() < 20
    assert np.abs(y[t > 500, 0] - 200.0).max() < 5


def test_adaptive_filter_is_exact_whatever_the_batching():
    _t, x, _ = _noisy_step(duration_s=120.0, step_at_s=60.0)
    whole = AdaptiveLevelFilter(OutputFilterConfig(), 0.01, [5.0, 5.0, 0.01]).process(x)
    for sizes in ([1], [3, 250], [997]):
        f = AdaptiveLevelFilter(OutputFilterConfig(), 0.01, [5.0, 5.0, 0.01])
        parts, i, k = [], 0, 0
        while i < len(x):
            j = min(len(x), i + sizes[k % len(sizes)])
            parts.append(f.process(x[i:j]))
            i, k = j, k + 1
        np.testing.assert_array_equal(np.vstack(parts), whole)


def test_pipeline_with_default_policy_is_batch_invariant(setup):
    model_path, aligned, w, t = setup
    model = load_model(model_path)
    runs = [
        run_in_batches(Pipeline(model), aligned.time_s, w, t, sizes) for sizes in ([1], [7, 50], [10_000])
    ]
    for r in runs[1:]:
        np.testing.assert_allclose(r["correction_um"], runs[0]["correction_um"], atol=1e-9)


def test_the_short_median_is_numpys_median_bit_for_bit():
    """output_filter._median replaces np.median on the filter's short windows (its overhead was
    a third of the core's time): the same value, odd and even lengths, ties, one value."""
    from fbgcomp.runtime.output_filter import _median

    rng = np.random.default_rng(11)
    for n in (1, 2, 3, 4, 5, 20, 21, 120):
        for v in (rng.normal(0.0, 50.0, n), np.round(rng.normal(0.0, 2.0, n)), np.full(n, 0.1)):
            assert _median(v) == float(np.median(v)), (n, v)


def test_block_medians_are_numpys_bit_for_bit():
    from fbgcomp.runtime.output_filter import _block_medians

    rng = np.random.default_rng(12)
    for n in (1, 2, 5, 50, 51):
        b = rng.normal(0.0, 30.0, (4, n, 3))
        np.testing.assert_array_equal(_block_medians(b), np.median(b, axis=1))


def test_frames_the_model_follows_are_published_as_they_are_in_any_batching():
    """A model that confirmed a motion itself (a load transition: ``follow``) is not confirmed
    once more: those frames pass as they are, and the filter is at rest at the new level after
    them; the output does not depend on how the frames are batched."""
    rng = np.random.default_rng(4)
    n = 3000  # 100 Hz: a block is 5 frames
    x = 0.05 * rng.standard_normal((n, 3))
    ramp = np.clip((np.arange(n) - 1000) / 500.0, 0.0, 1.0) * 100.0  # a 5 s ramp of 100 µm on dx
    x[:, 0] += ramp
    follow = np.zeros((n, 3), bool)
    follow[1000:1520, 0] = True  # the model's transition (its step test took it a little late)
    outs = []
    for sizes in ([1], [3, 50], [n]):
        f = AdaptiveLevelFilter(OutputFilterConfig(), 0.01, 0.05)
        parts, i, k = [], 0, 0
        while i < n:
            j = min(n, i + sizes[k % len(sizes)])
            parts.append(f.process(x[i:j], follow[i:j]))
            i, k = j, k + 1
        outs.append(np.vstack(parts))
    for o in outs[1:]:
        np.testing.assert_array_equal(o, outs[0])
    out = outs[0]
    np.testing.assert_array_equal(out[follow], x[follow])  # passed as they are
    assert np.abs(out[1600:, 0] - 100.0).max() < 0.2  # at rest at the new level at once
    assert np.abs(out[1600:, 0] - out[1600, 0]).max() < 0.1  # and still there
    assert np.abs(out[:1000, 1:]).max() < 0.1  # the other axes hold still
    # without the model's flags the ramp is confirmed by the filter: it lags
    f = AdaptiveLevelFilter(OutputFilterConfig(), 0.01, 0.05)
    lagged = f.process(x)
    assert (
        np.abs(lagged[1000:1500, 0] - ramp[1000:1500]).max()
        > 2.0 * np.abs(out[1000:1500, 0] - ramp[1000:1500]).max()
    )


def test_the_rest_fit_follows_a_drift_whose_rate_changes():
    """A housing cooling after the spindle stops: the correction relaxes by 5 µm with a 20 min
    time constant, in 0.05 µm of noise at 1 frame/s. The rest fit lags a changing drift by a part
    of its time constant: with 600 s it stood 0.71 µm behind (ram2's thermal_b served dz 5.37 µm
    against 4.62 offline); with 150 s 0.32 µm (ram7's thermal_b served dz 2.98 against 1.78);
    with 30 s, 0.11."""
    rng = np.random.default_rng(1)
    t = np.arange(0.0, 7200.0, 1.0)
    truth = np.where(t < 1800.0, 5.0, 5.0 * np.exp(-(t - 1800.0) / 1200.0))
    x = np.column_stack([truth + rng.normal(0.0, 0.05, t.size), 0 * t, 0 * t])
    f = AdaptiveLevelFilter(OutputFilterConfig(), 1.0, noise_um=np.full(3, 0.05))
    y = f.process(x)
    after = t > 1800.0
    assert np.abs(y[after, 0] - truth[after]).max() < 0.15
    assert [f.rest_tau(j) for j in range(3)] == [30.0] * 3  # quiet axes keep the short fit
