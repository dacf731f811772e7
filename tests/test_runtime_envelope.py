"""The published correction is never absurd (issue 13, findings 1 and 7): a mode hop on one
grating, an absurd model and a reconnect, each fed as real frames to a real pipeline."""

import numpy as np
import pytest

from fbgcomp.runtime import health as H
from fbgcomp.runtime.pipeline import HEALTH_ALARM, HEALTH_OK, Pipeline, PipelineConfig
from test_runtime_support import run_in_batches


@pytest.fixture(scope="session")
def setup(runtime_model_and_arrays):
    return runtime_model_and_arrays


@pytest.mark.parametrize("sizes", [[1], [10], [10_000]])
def test_mode_hop_inside_the_window_is_re_zeroed_not_readmitted_as_truth(setup, sizes):
    """sim-interrogator --fault shift:S3@8:+2 published 48,800 µm with Health OK."""
    model, time_s, w, t = setup
    s3 = model.sensor_names.index("S3")
    hopped = w.copy()
    hopped[time_s >= 100.0, s3] += 2.0  # 2 nm: inside the window, 20x max_jump_nm
    clean = run_in_batches(Pipeline(model), time_s, w, t, sizes)
    pipe = Pipeline(model)
    r = run_in_batches(pipe, time_s, hopped, t, sizes)
    at = int(np.searchsorted(time_s, 100.0))
    assert r["sensor_status"][at, s3] == H.JUMP
    ok = r["health"] == HEALTH_OK
    assert not (ok[:, None] & (np.abs(r["correction_um"]) > pipe.max_correction_um)).any()
    after = time_s > 100.0 + pipe.config.health.recover_s + 1.0
    assert (r["health"][after] == HEALTH_OK).all()  # re-admitted ...
    # ... against its new zero: the correction is the fault-free one (a few µm is the
    # fallback model's own difference while S3 was out, and the filter)
    assert np.abs(r["correction_um"][after] - clean["correction_um"][after]).max() < 2.0


class _Absurd:
    """A real model whose predictions are multiplied by 1e6 (a coefficient gone wrong)."""

    def __init__(self, model):
        self._model = model

    def __getattr__(self, name):
        return getattr(self._model, name)

    def predictor(self, exclude=frozenset()):
        return _AbsurdPredictor(self._model.predictor(exclude=exclude))


class _AbsurdPredictor:
    def __init__(self, p):
        self._p = p
        self.expected_rms_error_um = p.expected_rms_error_um

    def predict(self, *args, **kw):
        d, h = self._p.predict(*args, **kw)
        return d * 1e6, h * 1e6


def test_absurd_model_is_never_published_with_health_ok(setup):
    model, time_s, w, t = setup
    pipe = Pipeline(_Absurd(model))
    r = run_in_batches(pipe, time_s, w, t, [7, 100])
    bound = pipe.max_correction_um
    assert np.all(np.isfinite(bound)) and np.all(np.abs(r["correction_um"]) <= bound)
    predicted = np.isfinite(r["deviation_um"]).all(axis=1)
    beyond = predicted & (np.abs(r["deviation_um"]) > bound).any(axis=1)
    assert beyond.sum() > 0.9 * predicted.sum()
    assert (r["health"][beyond] == HEALTH_ALARM).all()
    assert (r["output_flags"][beyond] & H.FLAG_MAX_LIMITED).any(axis=1).all()
    # nothing of the absurd value is published: it holds the last trusted value (0 here)
    assert np.abs(r["correction_um"][beyond]).max() < 1.0


def test_prediction_beyond_the_bound_is_clamped_and_not_ok(setup):
    model, time_s, w, t = setup
    clean = run_in_batches(Pipeline(model), time_s, w, t, [10])
    cap = 0.7 * np.abs(clean["correction_um"]).max(axis=0)  # within ABSURD_FACTOR x cap
    r = run_in_batches(Pipeline(model, PipelineConfig(max_correction_um=tuple(cap))), time_s, w, t, [10])
    over = (np.abs(r["deviation_um"]) > cap).any(axis=1)
    assert over.sum() > 10
    assert (np.abs(r["correction_um"]) <= cap + 1e-9).all()
    assert not (r["health"][over] == HEALTH_OK).any()
    assert (r["output_flags"][over] & H.FLAG_MAX_LIMITED).any(axis=1).all()


def test_reconnect_cannot_step_the_correction(setup):
    """After a reconnect the correction stepped 0 -> 201 µm in one sample."""
    model, time_s, w, t = setup
    rate = 5.0  # µm/s: 0.5 µm per 0.1 s frame
    pipe = Pipeline(model, PipelineConfig(max_slew_um_per_s=rate, ramp_s=0.5))
    before = time_s < 150.0
    back = time_s >= 200.0
    r1 = run_in_batches(pipe, time_s[before], w[before], t[before], [10])
    # the link is lost: the service ticks no_data (50 Hz) for a while, ramping to zero ...
    ticks = [pipe.no_data(ts) for ts in np.arange(150.0, 152.0, 0.02)]
    # ... then the ticks stop (the service was busy reconnecting) and frames resume at 200 s
    last = ticks[-1].correction_um[-1]
    assert np.abs(last).max() < 1e-9
    r2 = run_in_batches(pipe, time_s[back], w[back], t[back], [1])
    out = np.vstack([last[None, :], r2["correction_um"]])
    dt = np.median(np.diff(time_s))
    assert np.abs(np.diff(out, axis=0)).max() <= 2 * rate * dt + 1e-6
    # the correction before the link loss was well beyond that step
    assert np.abs(r1["correction_um"][-1]).max() > 4 * rate * dt


def test_the_model_file_records_its_training_deviations_and_bounds_the_correction(setup, tmp_path):
    """Deliver 1: the model file records the deviations it was validated on, per axis; the
    runtime never publishes beyond ENVELOPE_MARGIN x their peak with Health OK."""
    model, time_s, w, t = setup
    runs = model.training_["campaigns"]
    peak = np.max(
        [np.maximum(np.abs(r["deviation_low_um"]), np.abs(r["deviation_high_um"])) for r in runs], axis=0
    )
    np.testing.assert_allclose(model.max_correction_um, model.ENVELOPE_MARGIN * peak)
    pipe = Pipeline(model)
    np.testing.assert_allclose(pipe.max_correction_um, np.minimum(1000.0, model.ENVELOPE_MARGIN * peak))
    # the same model with a training that saw a third of it: its own bound clamps and degrades
    d = model.to_dict()
    for r in d["training"]["campaigns"]:
        r["deviation_low_um"] = (np.asarray(r["deviation_low_um"]) / 6.0).tolist()
        r["deviation_high_um"] = (np.asarray(r["deviation_high_um"]) / 6.0).tolist()
    narrow = type(model).from_dict(d)
    pipe = Pipeline(narrow)
    r = run_in_batches(pipe, time_s, w, t, [10])
    over = (np.abs(r["deviation_um"]) > pipe.max_correction_um).any(axis=1)
    assert over.sum() > 10
    assert (np.abs(r["correction_um"]) <= pipe.max_correction_um + 1e-9).all()
    assert not (r["health"][over] == HEALTH_OK).any()
