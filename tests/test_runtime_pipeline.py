"""Core pipeline against the offline model: same numbers, fallbacks, hold and ramp, checks."""

import numpy as np
import pytest

from fbgcomp.io.campaign import read_campaign
from fbgcomp.models.registry import load_model
from fbgcomp.runtime import health as H
from fbgcomp.runtime.output_filter import OutputFilterConfig
from fbgcomp.runtime.pipeline import (
    HEALTH_ALARM,
    HEALTH_DEGRADED,
    HEALTH_OK,
    HEALTH_ZEROING,
    Pipeline,
    PipelineConfig,
)
from test_runtime_support import run_in_batches

# Output policy off: the published correction is exactly - prediction (the model path itself).
RAW = dict(output_filter=OutputFilterConfig(enabled=False), max_slew_um_per_s=0, max_correction_um=0)


@pytest.fixture(scope="session")
def setup(runtime_model_and_campaign):
    model_path, campaign_path = runtime_model_and_campaign
    model = load_model(model_path)
    campaign = read_campaign(campaign_path)
    aligned = campaign.aligned(zero_window_s=model.zero_window_s)
    w, t, _w0, _t0 = model.instrument_arrays(aligned)
    return model, campaign, aligned, w, t


def test_same_prediction_as_the_offline_model_whatever_the_batching(setup):
    model, campaign, aligned, w, t = setup
    offline_dev, offline_half = model.predict_interval(campaign)
    for sizes in ([1], [7, 1, 50], [10_000]):
        r = run_in_batches(Pipeline(model, PipelineConfig(**RAW)), aligned.time_s, w, t, sizes)
        zeroing = r["health"] == HEALTH_ZEROING
        # zero state from the first zero_window_s seconds, as offline
        assert zeroing.sum() == np.searchsorted(aligned.time_s, aligned.time_s[0] + 0.5, "right")
        ok = ~zeroing
        assert (r["health"][ok] == HEALTH_OK).all()
        np.testing.assert_allclose(r["deviation_um"][ok], offline_dev[ok], rtol=0, atol=1e-9)
        np.testing.assert_allclose(r["half_width_um"][ok], offline_half[ok], rtol=0, atol=1e-9)
        np.testing.assert_allclose(r["correction_um"][ok], -offline_dev[ok], atol=1e-9)
        assert (r["correction_um"][zeroing] == 0).all()


def test_fault_switches_to_fallback_on_the_same_sample_and_readmits_after_stable(setup):
    model, _campaign, aligned, w, t = setup
    time_s = aligned.time_s
    wl = w.copy()
    counts = np.ones(wl.shape, np.int8)
    s3 = model.sensor_names.index("S3")
    lost = (time_s >= 100.0) & (time_s < 150.0)
    wl[lost, s3] = np.nan
    counts[lost, s3] = 0
    cfg = PipelineConfig(health=H.HealthConfig(recover_s=5.0), **RAW)
    r = run_in_batches(Pipeline(model, cfg), time_s, wl, t, [33], counts)
    first_bad = np.argmax(lost)
    assert r["health"][first_bad - 1] == HEALTH_OK
    assert r["health"][first_bad] == HEALTH_DEGRADED  # within one sample
    assert r["sensor_status"][first_bad, s3] == H.MISSING
    fallback = model.predictor(frozenset({"S3"}))
    dev, _ = fallback.predict(wl[lost], t[lost], *_zero(aligned, model))
    np.testing.assert_allclose(r["deviation_um"][lost], dev, atol=1e-9)
    np.testing.assert_allclose(
        r["expected_rms_um"][lost], np.broadcast_to(fallback.expected_rms_error_um, dev.shape)
    )
    last_bad = time_s[lost][-1]
    stable = (time_s > last_bad) & (time_s < last_bad + 5.0 - 1e-9)
    assert stable.sum() >= 45
    assert (r["health"][stable] == HEALTH_DEGRADED).all()  # recovering, not re-admitted
    assert (r["sensor_status"][stable, s3] == H.RECOVERING).all()
    assert (r["health"][time_s >= last_bad + 5.0 + 1e-9] == HEALTH_OK).all()


def _zero(aligned, model):
    _, _, w0, t0 = model.instrument_arrays(aligned)
    return w0, t0


def test_no_usable_model_holds_then_ramps_to_zero(setup):
    model, _campaign, aligned, w, t = setup
    time_s = aligned.time_s
    wl = w.copy()
    counts = np.ones(wl.shape, np.int8)
    lost = time_s >= 50.0
    for name in ("S1", "S2"):  # only leave-one-out models are stored
        j = model.sensor_names.index(name)
        wl[lost, j] = np.nan
        counts[lost, j] = 0
    r = run_in_batches(Pipeline(model, PipelineConfig(ramp_s=2.0, **RAW)), time_s, wl, t, [16], counts)
    i = np.argmax(lost)
    held = r["correction_um"][i - 1]
    assert np.abs(held).max() > 0
    assert (r["health"][lost] == HEALTH_ALARM).all()
    frac = np.clip(1 - (time_s[lost] - time_s[i]) / 2.0, 0, 1)
    np.testing.assert_allclose(r["correction_um"][lost], held * frac[:, None], atol=1e-12)
    assert (r["correction_um"][time_s >= 52.0] == 0).all()


def test_jump_stuck_and_doubled_are_faults(setup):
    model, _campaign, aligned, w, t = setup
    time_s = aligned.time_s[:400]
    wl, temp = w[:400].copy(), t[:400]
    counts = np.ones(wl.shape, np.int8)
    wl[100, 0] += 0.5  # 0.5 nm in one sample: not physical
    wl[200:, 1] = wl[200, 1]  # S2 frozen from t = 20 s
    counts[300, 4] = 2  # S5 doubled once
    wl[300, 4] = np.nan
    r = run_in_batches(Pipeline(model), time_s, wl, temp, [25], counts)
    st = r["sensor_status"]
    assert st[100, 0] == H.JUMP and st[101, 0] == H.JUMP  # jump there and back
    assert st[99, 0] == H.OK
    stuck_from = np.searchsorted(time_s, time_s[200] + 2.0)
    assert (st[stuck_from:, 1] == H.STUCK).all() and (st[200 : stuck_from - 1, 1] != H.STUCK).all()
    assert st[300, 4] == H.DOUBLED
    # S2 stuck and S5 doubled at once: no leave-two-out model stored -> alarm
    assert r["model_set"][300] == -1 and r["health"][300] == HEALTH_ALARM
    assert r["health"][stuck_from + 1] == HEALTH_DEGRADED


def test_smoothing_is_an_exponential_filter(setup):
    model, _campaign, aligned, w, t = setup
    raw = run_in_batches(Pipeline(model, PipelineConfig(**RAW)), aligned.time_s, w, t, [64])
    sm = run_in_batches(
        Pipeline(model, PipelineConfig(smoothing_tau_s=1.0, **RAW)), aligned.time_s, w, t, [64]
    )
    a = np.exp(-0.1 / 1.0)
    x, y = raw["correction_um"], sm["correction_um"]
    np.testing.assert_allclose(y[1:], a * y[:-1] + (1 - a) * x[1:], atol=1e-9)


def test_slew_limit_turns_a_fallback_switch_into_a_ramp(setup):
    model, _campaign, aligned, w, t = setup
    time_s = aligned.time_s
    wl = w.copy()
    counts = np.ones(wl.shape, np.int8)
    s3 = model.sensor_names.index("S3")
    lost = time_s >= 100.0
    wl[lost, s3] = np.nan
    counts[lost, s3] = 0
    free = run_in_batches(Pipeline(model, PipelineConfig(**RAW)), time_s, wl, t, [64], counts)[
        "correction_um"
    ]
    i = int(np.argmax(lost))
    jump = np.abs(free[i] - free[i - 1]).max()  # the switch is a step
    normal = np.abs(np.diff(free[time_s < 99.0], axis=0)).max() / 0.1  # µm/s otherwise
    assert jump > 20 * normal * 0.1
    rate = 2 * normal  # µm/s
    cfg = dict(RAW, max_slew_um_per_s=rate)
    outs = [
        run_in_batches(Pipeline(model, PipelineConfig(**cfg)), time_s, wl, t, sizes, counts)["correction_um"]
        for sizes in ([1], [7, 50], [10_000])
    ]
    for lim in outs[1:]:
        np.testing.assert_allclose(lim, outs[0], atol=1e-12)  # whatever the batching
    lim = outs[0]
    dt = np.diff(time_s)[:, None]
    assert (np.abs(np.diff(lim, axis=0)) <= rate * dt + 1e-9).all()
    assert np.abs(lim[i] - lim[i - 1]).max() <= rate * 0.1 + 1e-9  # limited to a ramp
    calm = time_s < 99.0
    np.testing.assert_allclose(lim[calm], free[calm], atol=1e-12)  # untouched elsewhere
    assert np.abs(lim[-1] - free[-1]).max() < 1e-9  # caught up again


def test_link_loss_ticks_hold_then_ramp_and_data_resumes(setup):
    model, _campaign, aligned, w, t = setup
    n = 400
    pipe = Pipeline(model, PipelineConfig(ramp_s=1.0, **RAW))
    r = run_in_batches(pipe, aligned.time_s[:n], w[:n], t[:n], [50])
    held = r["correction_um"][-1]
    t_last = aligned.time_s[n - 1]
    ticks = [pipe.no_data(t_last + dt) for dt in (0.1, 0.35, 0.6, 1.2, 1.5)]
    # the hold starts at the first tick: 1 - (t - t_first_tick) / ramp_s
    for tick, dt in zip(ticks, (0.1, 0.35, 0.6, 1.2, 1.5)):
        frac = max(0.0, 1.0 - (dt - 0.1) / 1.0)
        np.testing.assert_allclose(tick.correction_um[0], held * frac, atol=1e-12)
        assert tick.health[0] == HEALTH_ALARM
    back = pipe.process(
        aligned.time_s[n : n + 5],
        w[n : n + 5],
        np.ones((5, 5), np.int8),
        np.zeros((5, 5), np.int8),
        t[n : n + 5],
    )
    assert (back.health == HEALTH_OK).all()


def test_a_hold_never_ramps_back_up_when_late_frames_follow_a_no_data_tick(setup):
    """The frames that arrive after a stall carry older instrument times than the no-data tick
    published during it (timed by the wall clock): the held correction must not grow back."""
    model, _campaign, aligned, w, t = setup
    n, ramp_s = 400, 5.0
    time_s = aligned.time_s
    pipe = Pipeline(model, PipelineConfig(ramp_s=ramp_s, **RAW))
    held = run_in_batches(pipe, time_s[:n], w[:n], t[:n], [50])["correction_um"][-1]
    assert np.abs(held).max() > 0.1

    def lost(a, b):  # every grating lost: no model usable, ALARM
        k = b - a
        nan = np.full((k, w.shape[1]), np.nan)
        zeros = np.zeros((k, w.shape[1]), np.int8)
        return pipe.process(time_s[a:b], nan, zeros, zeros, t[a:b])

    first = lost(n, n + 10)
    tick = pipe.no_data(float(time_s[n + 20]))  # the stall's tick, ahead of the late frames
    late = lost(n + 10, n + 30)
    corr = np.vstack([first.correction_um, tick.correction_um, late.correction_um])
    assert (np.concatenate([first.health, tick.health, late.health]) == HEALTH_ALARM).all()
    frac = 1.0 - (time_s[n + 20] - time_s[n]) / ramp_s
    assert 0.3 < frac < 0.9
    np.testing.assert_allclose(tick.correction_um[0], held * frac, atol=1e-12)
    assert np.all(np.diff(np.abs(corr), axis=0) <= 1e-12)  # never grows while held
    # the late frames stay at the tick's value until their time passes it, then ramp on
    behind = time_s[n + 10 : n + 30] <= time_s[n + 20]
    np.testing.assert_allclose(
        late.correction_um[behind], np.tile(held * frac, (behind.sum(), 1)), atol=1e-12
    )
    last_frac = 1.0 - (time_s[n + 29] - time_s[n]) / ramp_s
    np.testing.assert_allclose(late.correction_um[-1], held * last_frac, atol=1e-12)


def test_model_reload_keeps_the_re_admission_check(setup, runtime_model_and_campaign):
    """A model reload (``Service.reload``, as OPC UA ReloadModel calls it) in the middle of a
    refused re-admission changes nothing: the grating back shifted from a gap stays
    INCONSISTENT (not RECOVERING), and a reload just before the frame it would come back on
    does not let it in unchecked - the run with a reload before every frame around the gap is
    frame for frame the run without any, with the default output policy."""
    import asyncio

    from fbgcomp.runtime.service import RuntimeConfig, Service

    model, _campaign, aligned, w, t = setup
    model_path, _ = runtime_model_and_campaign
    time_s = aligned.time_s
    s3 = model.sensor_names.index("S3")
    wl, counts = w.copy(), np.ones(w.shape, np.int8)
    gap = (time_s >= 100.0) & (time_s < 102.0)  # S3 lost for 2 s ...
    wl[gap, s3], counts[gap, s3] = np.nan, 0
    wl[time_s >= 102.0, s3] += 0.5  # ... and back 0.5 nm off
    stop = int(np.searchsorted(time_s, 110.0))
    time_s, wl, counts, t = time_s[:stop], wl[:stop], counts[:stop], t[:stop]
    plain = Pipeline(model)
    ref = run_in_batches(plain, time_s, wl, t, [1], counts)
    assert plain.readmissions_refused >= 3  # refused, re-checked, refused ...
    assert (ref["sensor_status"][time_s >= 104.0, s3] == H.INCONSISTENT).all()

    svc = Service(RuntimeConfig(model=str(model_path), opcua_enabled=False))
    first = int(np.searchsorted(time_s, 101.0))
    out = [run_in_batches(svc.pipeline, time_s[:first], wl[:first], t[:first], [first], counts[:first])]
    reloads = 0
    for i in range(first, time_s.size):
        if time_s[i] < 107.0:  # every frame around the gap
            asyncio.run(svc.reload(str(model_path)))
            reloads += 1
        out.append(
            run_in_batches(
                svc.pipeline, time_s[i : i + 1], wl[i : i + 1], t[i : i + 1], [1], counts[i : i + 1]
            )
        )
    got = {k: np.concatenate([o[k] for o in out]) for k in ref}
    assert reloads >= 50
    np.testing.assert_array_equal(got["sensor_status"], ref["sensor_status"])
    np.testing.assert_array_equal(got["health"], ref["health"])
    np.testing.assert_array_equal(got["model_set"], ref["model_set"])
    np.testing.assert_allclose(got["correction_um"], ref["correction_um"], rtol=0, atol=1e-9)
    assert svc.pipeline.readmissions_refused == plain.readmissions_refused


def test_frames_older_than_the_last_link_loss_tick_are_dropped_unless_the_clock_was_set_back(
    runtime_model_and_campaign, runtime_model_and_arrays
):
    """serve's side of a lost link (the frames it runs without gratings are tested end to end in
    test_runtime_live_inputs.py): once the link is back, frames stamped before the last frame
    run without gratings are dropped (the model's filters never run back in time), and frames
    more than CLOCK_SET_BACK_S older are an instrument clock set back, taken as before."""
    from fbgcomp.runtime.service import CLOCK_SET_BACK_S, RuntimeConfig, Service
    from fbgcomp.runtime.sources import ConstantTemperatures
    from fbgcomp.runtime.windows import SensorBatch

    model_path, _ = runtime_model_and_campaign
    model, time_s, w, t = runtime_model_and_arrays
    svc = Service(RuntimeConfig(model=str(model_path), opcua_enabled=False))
    svc.temps = ConstantTemperatures(list(model.probe_names), dict(zip(model.probe_names, t[0])))
    S = w.shape[1]

    def batch(rows):
        ones = np.ones((rows.size, S), np.int8)
        return SensorBatch(time_s[rows], w[rows], ones, np.zeros_like(ones), 0.0)

    first = int(np.searchsorted(time_s, 20.0))
    svc._process(batch(np.arange(first)))
    assert svc.frames == first and svc.pipeline.zeroed
    # a frame without gratings ran at time_s[first + 5] while the link was lost
    svc._tick_t = float(time_s[first + 5])
    svc._process(batch(np.arange(first, first + 10)))
    assert svc.frames == first + 4 and svc._tick_t is None  # the 4 frames after it
    assert svc.last_result.time_s.tolist() == time_s[first + 6 : first + 10].tolist()
    # an instrument clock set back beyond CLOCK_SET_BACK_S: its frames are taken
    late = float(time_s[first + 9])
    svc._tick_t = late + CLOCK_SET_BACK_S + 5.0
    svc._process(batch(np.arange(first + 10, first + 20)))
    assert svc.frames == first + 14 and svc._tick_t is None


class _LiveProbes:
    """A temperature source whose every probe is a live input (what ``LiveTemperatures`` is with
    OPC UA or Modbus behind it; test_runtime_live_inputs.py runs the real one): fixed values."""

    all_live = True

    def __init__(self, values_C):
        self.values_C = np.asarray(values_C, float)

    def latest(self, time_s):
        return np.tile(self.values_C, (np.size(time_s), 1))


@pytest.mark.parametrize("carry", [True, False])
def test_a_lost_link_runs_the_set_without_gratings_only_when_configured(
    tmp_path, runtime_model_and_campaign, runtime_model_and_arrays, carry
):
    """serve's no-data tick with every probe live: with ``probes_on_link_loss`` (the default) one
    frame without gratings runs on the probes, on the physical model's set without every
    grating; with it false, and for a model without such a set (the regression of the runtime
    tests), the hold and ramp to zero of before (ALARM)."""
    import pandas as pd

    from fbgcomp.bench.synthetic import linear_truth_campaign
    from fbgcomp.models.physical import PhysicalModel
    from fbgcomp.runtime.pipeline import HEALTH_ALARM, HEALTH_DEGRADED
    from fbgcomp.runtime.service import RuntimeConfig, Service
    from fbgcomp.runtime.windows import SensorBatch

    regression, time_s, w, _ = runtime_model_and_arrays
    first = pd.read_csv(runtime_model_and_campaign[1] / "temperatures.csv").iloc[0]
    train, _ = linear_truth_campaign("train", seed=1, duration_s=2 * 3600, noise_um=0.05)
    physical = PhysicalModel(zero_window_s=0.5).fit([train]).save(tmp_path / "physical.json")
    for path, has_set in ((physical, True), (None, False)):
        cfg = RuntimeConfig(model=str(path) if path else "", opcua_enabled=False)
        cfg.source.probes_on_link_loss = carry
        svc = Service(cfg, model=None if path else regression)
        svc.temps = _LiveProbes([first[f"{p}_C"] + 2.0 for p in svc.pipeline.probe_names])
        n = int(np.searchsorted(time_s, 20.0))
        ones = np.ones((n, w.shape[1]), np.int8)
        svc._process(SensorBatch(time_s[:n], w[:n], ones, np.zeros_like(ones), 0.0))
        svc._no_data()
        ran = carry and has_set
        assert svc.ticks == int(ran) and svc.frames == n
        res = svc.last_result
        assert int(res.health[-1]) == (HEALTH_DEGRADED if ran else HEALTH_ALARM)
        if ran:
            everything = frozenset(svc.pipeline.sensor_names)
            assert svc.pipeline.model_sets[int(res.model_set[-1])] == everything
            assert np.isfinite(res.deviation_um[-1]).all()
        else:
            assert int(res.model_set[-1]) == -1 and np.isnan(res.deviation_um[-1]).all()
