"""The default (physical) model on the independent ram2 data set and its do-no-harm policy."""

from pathlib import Path

import numpy as np
import pytest

from fbgcomp.io.campaign import Campaign
from fbgcomp.kinematics import housing_probe
from fbgcomp.models import policy as P
from fbgcomp.models.filters import first_order_filter as lowpass
from fbgcomp.models.metrics import static_level_metrics, validation_metrics
from fbgcomp.models.physical import PhysicalModel, PhysicalPredictor
from fbgcomp.models.registry import load_model
from fbgcomp_testing import RAM2_DIR, read_ram2


@pytest.fixture(scope="session")
def ram2():
    return read_ram2("thermal_a", "static_xyz", "thermal_b", "static_x", "thermal_c")


@pytest.fixture(scope="session")
def model(ram2):
    return PhysicalModel().fit([ram2["thermal_a"], ram2["static_xyz"]])


@pytest.fixture(scope="session")
def twin_model(ram2_default_model):
    """The default fit as the README gives it: with the machine description (twin-learned
    thermal map; conftest's session fixture)."""
    return ram2_default_model


def _metrics(model, campaign, exclude=frozenset()):
    pred, half = model.predict_interval(campaign, exclude=exclude)
    ref = campaign.aligned(zero_window_s=model.zero_window_s).reference_um
    return validation_metrics(ref, pred, half)


def test_firm_shrinkage_is_zero_for_noise_and_unbiased_for_loads():
    out = P.firm(np.array([0.0, 2.9, 4.0, 6.0, 50.0, -50.0]), 1.0, 3.0, 6.0)
    np.testing.assert_allclose(out, [0.0, 0.0, 2.0, 6.0, 50.0, -50.0])


def test_clip_to_envelope_flags_extrapolation():
    x = np.array([[0.5, 0.5], [1.5, 0.0], [-0.2, 0.0]])
    clipped, outside = P.clip_to_envelope(x, [0.0, 0.0], [1.0, 1.0], margin=0.1)
    np.testing.assert_allclose(clipped[1], [1.1, 0.0])
    np.testing.assert_allclose(clipped[2], [-0.1, 0.0])
    assert outside.tolist() == [False, True, True]


def test_the_policy_on_one_frame_is_the_array_arithmetic_to_the_bit():
    """A runtime batch of one frame takes the policy's Python-float path: the same numbers, bit
    for bit, as the frame taken inside a larger batch, at the edges too (zero, NaN, ±inf, on
    a threshold or a bound, a zero and an infinite sigma)."""
    rng = np.random.default_rng(3)
    sigma = np.array([1.0, 0.0, np.inf, 0.5, 2.0, 1e-300])
    edge = np.array([0.0, -0.0, np.nan, np.inf, -np.inf, 3.0, 6.0, -3.0, 1.1, -0.1])
    x = np.concatenate([rng.normal(0, 4, (40, 6)), np.resize(edge, (10, 6))])
    whole = P.firm(x, sigma, 3.0, 6.0)
    for i in range(len(x)):
        np.testing.assert_array_equal(P.firm(x[i : i + 1], sigma, 3.0, 6.0), whole[i : i + 1])
        # a row as a vector of a few numbers (the load tracker's forces in a transition), with
        # its sigmas or one for all: the float path too
        np.testing.assert_array_equal(P.firm(x[i], sigma, 3.0, 6.0), whole[i])
        one = P.firm(x[i : i + 1], np.full(6, 0.7), 3.0, 6.0)[0]
        np.testing.assert_array_equal(P.firm(x[i], 0.7, 3.0, 6.0), one)
    low, high = np.array([0, -1, 0, 2, 0, 0.0]), np.array([1, 1, 0, 2, 10, 1e300])
    clipped, outside = P.clip_to_envelope(x, low, high, margin=0.1)
    for i in range(len(x)):
        c1, o1 = P.clip_to_envelope(x[i : i + 1], low, high, margin=0.1)
        np.testing.assert_array_equal(c1, clipped[i : i + 1])
        assert o1.tolist() == outside[i : i + 1].tolist()


def test_the_thermal_map_features_of_one_frame_equal_the_array_path():
    """map_features on one frame at a time (the runtime's batch of 1, Python floats) follows
    the same filters as on a batch, on a jittered clock with a repeated and a backward time."""
    from fbgcomp.models.physical.thermal import map_features

    rng = np.random.default_rng(5)
    n = 300
    t = np.cumsum(rng.uniform(0.05, 3.0, n)) + 1.7e9
    t[100], t[200] = t[99], t[199] - 0.5
    e, dT = rng.normal(0, 2, (n, 6)), rng.normal(0, 1, (n, 4))
    whole, _ = map_features(e, dT, [2], t, None)
    X, state = map_features(e[:1], dT[:1], [2], t[:1], None)
    rows = [X]
    for i in range(1, n):
        X, state = map_features(e[i : i + 1], dT[i : i + 1], [2], t[i : i + 1], state)
        rows.append(X)
    np.testing.assert_allclose(np.vstack(rows), whole, rtol=0, atol=1e-12)


def test_lowpass_streams_like_one_call():
    rng = np.random.default_rng(0)
    x = rng.normal(size=(50, 2))
    t = np.arange(50.0)
    whole, _ = lowpass(x, t, 7.0)
    a, st = lowpass(x[:17], t[:17], 7.0)
    b, _ = lowpass(x[17:], t[17:], 7.0, st)
    np.testing.assert_allclose(np.vstack([a, b]), whole, rtol=1e-12, atol=1e-12)
    # one frame per call (the runtime at batch 1 takes a one-step path): the same values
    ones, st = [lowpass(x[:1], t[:1], 7.0)[0]], lowpass(x[:1], t[:1], 7.0)[1]
    for i in range(1, 50):
        y, st = lowpass(x[i : i + 1], t[i : i + 1], 7.0, st)
        ones.append(y)
    np.testing.assert_allclose(np.vstack(ones), whole, rtol=1e-12, atol=1e-12)


def test_static_load_is_read_through_the_load_signature(model, ram2):
    from fbgcomp.models.metrics import static_level_metrics

    c = ram2["static_x"]
    pred, _ = model.predict_interval(c)
    al = c.aligned(zero_window_s=model.zero_window_s)
    st = static_level_metrics(al.loads_N, al.reference_um, pred)
    # plateau error of the loaded axis within 1.5 % of its deflection (558 µm at 4 kN)
    assert st["axes"]["dx"]["error_pct_of_deflection"] < 1.5
    # the unloaded axes get no load correction worth the name on the plateaus
    assert st["axes"]["dy"]["max_plateau_error_um"] < 1.0


def test_a_force_the_gratings_cannot_read_is_said_by_fit_and_validate(twin_model, tmp_path):
    """On ram2 Fz compresses every grating alike, as a warming does: the fit leaves it unread.
    The displacement it moves is then in neither the correction nor its interval (static_xyz's
    dz: 3.4 µm off, 0.43 covered), and the user is told so, with the size, by the fit's summary
    and by validate on each campaign that applies it (none on static_x, which loads X only)."""
    import json
    import subprocess
    import sys

    assert twin_model.load_["not_separable"] == ["fz"]
    assert "fz is not read: its signature is the gratings' warming pattern" in twin_model.summary()
    path = tmp_path / "model.json"
    twin_model.save(path)
    data = RAM2_DIR / "data"
    args = ["validate", path, data / "static_xyz", data / "static_x", "--json", tmp_path / "v.json"]
    r = subprocess.run(
        [sys.executable, "-m", "fbgcomp", *args],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert r.returncode == 0, r.stderr[-2000:]
    notes = [ln for ln in r.stdout.splitlines() if ln.startswith("note: fz")]
    assert len(notes) == 1 and "neither the correction nor its interval" in notes[0], r.stdout
    got = json.loads((tmp_path / "v.json").read_text())["campaigns"]
    assert "unread_forces" not in got["static_x"]
    fz = got["static_xyz"]["unread_forces"]["fz"]
    assert fz["max_abs_N"] == pytest.approx(4000.0, rel=0.01)
    # what the note says Fz moves is what the model missed on the plateaus: all of dz
    missed = got["static_xyz"]["static_levels"]["axes"]["dz"]["max_plateau_error_um"]
    assert fz["ttp_um"]["dz"] == pytest.approx(missed, rel=0.1), (fz, missed)
    assert max(fz["ttp_um"]["dx"], fz["ttp_um"]["dy"]) < 0.05 * fz["ttp_um"]["dz"]


def test_unseen_radiant_load_does_no_harm_on_dx_and_dz(model, ram2):
    """thermal_b's radiant load takes the +X wall 8 K beyond training: the gratings' thermal
    reading leaves its envelope, the load part is refused and the thermal part is clipped."""
    m = _metrics(model, ram2["thermal_b"])
    for axis in ("dx", "dz"):
        assert not m["axes"][axis]["harm"], (axis, m["axes"][axis])
    assert m["axes"]["dz"]["max_abs_error_um"] < 0.15 * m["axes"]["dz"]["peak_um"]
    # the slow thermal drift of the gratings is never read as a load
    assert not (model.last_flags_ & P.LOAD_REFUSED).any()


def test_twin_learned_thermal_map_meets_the_lateral_targets(twin_model, ram2):
    """thermal_a never heats one face more than the opposite one; the face-gradient physics
    comes from the twin of ram2.yaml. Issue 12 targets: max <= 50 %, RMS <= 30 % of the peak."""
    m = _metrics(twin_model, ram2["thermal_b"])
    for axis in ("dx", "dy"):
        a = m["axes"][axis]
        assert a["max_abs_error_um"] <= 0.5 * a["peak_um"], (axis, a)
        assert a["rms_error_um"] <= 0.3 * a["peak_um"], (axis, a)
    for name in ("thermal_b", "static_x"):
        m = _metrics(twin_model, ram2[name])
        for axis, a in m["axes"].items():
            assert not a["harm"], (name, axis, a)


def test_default_beats_the_simplest_physical_model_on_dz(twin_model, ram2):
    """Issue 12's baseline: dz = a + b dT_flange + c dT_amb by least squares on thermal_a,
    judged on thermal_b. The twin map's housing transient is calibrated on thermal_a (how late
    the flange probe sees the bearings' heat), so the default must do better on dz."""

    def design(c):
        al = c.aligned(zero_window_s=10.0)
        names = list(al.probe_names)
        dT = al.temperature_C - al.temperature_zero_C
        X = np.column_stack([np.ones(len(dT)), dT[:, names.index("T_flange")], dT[:, names.index("T_amb")]])
        return X, al.reference_um[:, 2]

    X, y = design(ram2["thermal_a"])
    coef = np.linalg.lstsq(X, y, rcond=None)[0]
    Xb, yb = design(ram2["thermal_b"])
    baseline = np.abs(Xb @ coef - yb).max()
    cal = twin_model.twin_map_["calibration"]
    # the housing's ΔT, its leads and (ram2 has an ambient probe) the ambient's hour low-pass
    assert cal["ambient_tau_s"] > 0
    assert np.asarray(cal["coef"]).shape == (2 + len(cal["leads_s"]), 3)
    got = _metrics(twin_model, ram2["thermal_b"])["axes"]["dz"]["max_abs_error_um"]
    assert got < 0.95 * baseline, (got, baseline)


def _streamed_like_offline(model, loaded, c, batch):
    """The loaded file predicts as the fitted model, and the interrogator's frames streamed in
    batches through one predictor, read at the reference times, equal the offline call.
    Returns the predictor and the last batch's length."""
    a, _ = model.predict_interval(c)
    np.testing.assert_allclose(loaded.predict_interval(c)[0], a, rtol=1e-10, atol=1e-9)
    al = c.aligned(zero_window_s=loaded.zero_window_s)
    _, _, w0, t0 = loaded.instrument_arrays(al)
    ft, w, t = loaded.frame_arrays(c, al)
    p = loaded.predictor()
    parts = [
        p.predict(w[i : i + batch], t[i : i + batch], w0, t0, time_s=ft[i : i + batch])[0]
        for i in range(0, len(w), batch)
    ]
    at = np.clip(np.searchsorted(ft, al.time_s, side="right") - 1, 0, None)
    np.testing.assert_allclose(np.vstack(parts)[at], a, rtol=1e-9, atol=1e-8)
    return p, len(w) - batch * ((len(w) - 1) // batch)


def test_calibrated_map_streams_and_round_trips(twin_model, ram2, tmp_path):
    _streamed_like_offline(
        twin_model, load_model(twin_model.save(tmp_path / "m.json")), ram2["thermal_b"], 4000
    )


def test_interval_is_the_interferometers_at_rest_and_grows_with_the_thermal_state(twin_model, ram2):
    """At rest and zeroed the thermal part has no error, so the 95 % interval of an axis that
    does not move is the reference instrument's (ram2: 0.05 um); on the held-out thermal_b
    (radiant load, ambient drop) it covers at least 90 % of the samples on every axis, and no
    more than 99.5 % (issue 12's band is 90-99 %: bench_accuracy measures it, and thermal_b's dx
    is at 99.3 % since the interval carries the finite-sample correction of its few effective
    training samples; over-covering by a few tenths is the safe side, under-covering is not)."""
    iv = twin_model.interval_
    np.testing.assert_allclose(np.sqrt(iv["v0_um2"]), 0.05, rtol=0.4)
    _, half = twin_model.predict_interval(ram2["static_x"])
    assert np.median(half[:, 1:], axis=0).max() < 0.5, np.median(half, axis=0)
    for name in ("thermal_b", "static_x"):
        for axis, a in _metrics(twin_model, ram2[name])["axes"].items():
            assert 0.90 <= a["pi95_coverage"] <= 0.995, (name, axis, a["pi95_coverage"])


def test_the_quick_and_fast_readings_differ_by_the_noise_their_filters_leave():
    from fbgcomp.models.physical.predictor import LOAD_FAST_S, LOAD_FOLLOW_S, quick_fast_noise

    rng = np.random.default_rng(1)
    x = rng.standard_normal(400_000)
    for dt in (0.1, 1.0):
        bq, bf = 1.0 - np.exp(-dt / LOAD_FOLLOW_S), 1.0 - np.exp(-dt / LOAD_FAST_S)
        q, f = np.zeros_like(x), np.zeros_like(x)
        yq = yf = 0.0
        for i, v in enumerate(x[:100_000]):
            yq += bq * (v - yq)
            yf += bf * (v - yf)
            q[i], f[i] = yq, yf
        d = (q - f)[1000:100_000]
        assert abs(d.var() / quick_fast_noise(bq, bf) - 1.0) < 0.05, (dt, d.var(), quick_fast_noise(bq, bf))


def test_the_ramp_line_averages_a_ramps_frames_and_restarts_where_the_ramp_ends():
    """ramp_line on 1 s frames of a 220 N/s ramp (ram5's thermal_c) with 66 N of frame noise:
    on the ramp its value at the last frame carries (4n - 2) / (n (n + 1)) of a frame's variance
    (0.35 at ten frames); the first frame after the ramp ends leaves the line by ~3 sigma and
    starts it anew, so the flat frames after it are not read on the ramp's slope (the slope run
    on would put them 220 N further off per frame)."""
    from fbgcomp.models.physical.predictor import RAMP_LINE_MIN, ramp_line

    rng = np.random.default_rng(3)
    sd, n_ramp, reps = 66.0, 10, 2000
    on = np.array([False, True, False])
    last, raw, after = [], [], []
    for _ in range(reps):
        line = np.zeros((3, 6))
        t = np.arange(n_ramp + 4, dtype=float)
        truth = np.minimum(220.0 * t, 220.0 * (n_ramp - 1))
        y = truth + rng.normal(0.0, sd, len(t))
        est, count = [], []
        for ti, yi in zip(t, y, strict=True):
            e, line = ramp_line(line, on, ti, np.array([0.0, yi, 0.0]), np.full(3, sd), 3.0)
            est.append(e[1])
            count.append(line[1, 0])
            assert np.isnan(e[[0, 2]]).all()
        if count[n_ramp - 1] == n_ramp:  # no noisy frame restarted it on the ramp (~2 %)
            last.append(est[n_ramp - 1] - truth[n_ramp - 1])
            raw.append(y[n_ramp - 1] - truth[n_ramp - 1])
        after.append(est[-1] - truth[-1])
        assert np.isnan(est[: RAMP_LINE_MIN - 1]).all()
    assert len(last) > 0.9 * reps, len(last)
    ratio = np.var(last) / np.var(raw)
    assert abs(ratio - (4 * n_ramp - 2) / (n_ramp * (n_ramp + 1))) < 0.05, ratio
    # four flat frames after the end: restarted, the line there is the flat frames' (or NaN
    # where the restart came late and fewer than RAMP_LINE_MIN frames are on it), not the slope's
    after = np.asarray(after)
    ok = np.isfinite(after)
    far = np.abs(after[ok])
    assert ok.mean() > 0.9 and np.sqrt(np.mean(far**2)) < sd and (far > 440.0).mean() < 0.005, (
        ok.mean(),
        np.sqrt(np.mean(far**2)),
        (far > 440.0).mean(),
    )


def test_a_load_ramp_is_followed_without_the_fast_readings_lag(twin_model, ram2):
    """static_x's 5 s ramps of 200 N/s, read at 10 Hz: the 0.5 s low-pass the step test judges
    on lagged them by 0.48 s, 13.9 µm of dx at the samples on a ramp. While the load moves the
    transition follows a 0.1 s reading; what is left is the ramp's first frames, before the step
    test fires. The interval's load terms are scaled to what static_xyz showed (their 3 %
    signature error prior made +-18.7 µm of dx around plateau errors of 0.3 µm), and static_x's
    coverage stays in issue 12's band, with its plateaus as they were."""
    c = ram2["static_x"]
    pred, half = twin_model.predict_interval(c)
    al = c.aligned(zero_window_s=twin_model.zero_window_s)
    err = np.abs(pred - al.reference_um)
    assert err[:, 0].max() < 9.0, err[:, 0].max()  # 13.85 µm with the 0.5 s reading
    ramp = np.abs(np.gradient(al.loads_N[:, 0], al.time_s)) > 50.0
    assert ramp.sum() > 10 and np.median(err[ramp, 0]) < 5.0, np.median(err[ramp, 0])
    m = _metrics(twin_model, c)
    assert 0.90 <= m["axes"]["dx"]["pi95_coverage"] <= 0.99, m["axes"]["dx"]
    levels = static_level_metrics(al.loads_N, al.reference_um, pred)
    assert levels["axes"]["dx"]["error_pct_of_deflection"] < 0.1, levels["axes"]["dx"]  # 0.05 %
    scale = np.asarray(twin_model.load_["interval_scale"])
    assert scale[0] < 0.5 and np.all(scale <= 1.0), scale
    held = (np.abs(al.loads_N[:, 0]) > 1500.0) & ~ramp
    # held at 2-4 kN: the priors gave +-19 to 33 µm of dx around plateau errors of 0.3 µm
    assert np.median(half[held, 0]) < 10.0, np.median(half[held, 0])


@pytest.mark.slow
def test_a_force_the_training_never_applied_keeps_its_interval_prior(ram2):
    """Trained under Fx alone (static_x), judged on static_xyz: the load terms' scale is learnt
    per axis on the forces the training applied, and dy's came out 0.001 from the tenths of a
    µm Fx moves it. Applied to Fy's terms as well, it made dy's interval that of the
    interferometer at rest under 300 µm of Fy deflection: 0.489 covered (the correction itself
    0.2 % off on the plateaus). A component the training never applied keeps its prior."""
    machine = Path(__file__).resolve().parents[1] / "examples" / "machines" / "ram2.yaml"
    m = PhysicalModel(machine=machine).fit([ram2["thermal_a"], ram2["static_x"]])
    assert m.load_["interval_trained"] == [True, False, False], m.load_
    assert m.load_["interval_scale"][1] < 0.01, m.load_["interval_scale"]
    fig = _metrics(m, ram2["static_xyz"])["axes"]
    for a in ("dx", "dy"):
        assert 0.90 <= fig[a]["pi95_coverage"] <= 0.99, (a, fig[a])  # dx 0.924, dy 0.972


def test_a_grating_that_jumps_alone_is_not_read_as_a_load(twin_model, ram2):
    """A step on one grating (a fibre slipping in its bond) matches no load: refused, flagged,
    and the unloaded axes keep their tiny error."""
    c = ram2["static_x"]
    al = c.aligned(zero_window_s=twin_model.zero_window_s)
    w, t, w0, t0 = twin_model.instrument_arrays(al)
    w = w.copy()
    j = twin_model.sensor_names.index("S3")
    w[len(w) // 2 :, j] += 0.006  # +6 pm on S3 alone: ~3 µm of false elongation
    p = twin_model.predictor()
    pred, _ = p.predict(w, t, w0, t0, time_s=al.time_s)
    assert (p.last_flags[:, 1] & P.LOAD_REFUSED).any()
    assert np.abs(pred[:, 1] - al.reference_um[:, 1]).max() < 1.0


def _raw_frames(model, campaign, rate_hz, seed=0):
    """The campaign's own interrogator frames (10 Hz on ram2's static campaigns), resampled to
    ``rate_hz`` with fresh white noise of the frames' own level, and the probes interpolated."""
    fbg, temps = campaign.fbg, campaign.temperatures
    t_in = fbg["time_s"].to_numpy()
    w_in = fbg[[f"{s}_nm" for s in model.sensor_names]].to_numpy()
    t = np.arange(0.0, t_in[-1], 1.0 / rate_hz)
    w = np.column_stack([np.interp(t, t_in, w_in[:, j]) for j in range(w_in.shape[1])])
    if rate_hz != 10.0:
        sd = np.std(np.diff(w_in[:100], axis=0), axis=0) / np.sqrt(2)
        w += np.random.default_rng(seed).normal(0.0, sd, w.shape)
    T = np.column_stack([np.interp(t, temps["time_s"], temps[f"{p}_C"]) for p in model.probe_names_])
    zero = t < model.zero_window_s
    return t, w, T, w[zero].mean(axis=0), T[zero].mean(axis=0)


@pytest.mark.parametrize("rate_hz", [10.0, 100.0])
def test_the_served_correction_does_not_depend_on_frame_rate_or_batching(twin_model, ram2, rate_hz):
    """As served live (one frame per call, or any batch), the load part sees the same loads at
    10 Hz and 100 Hz as the campaign fit: decisions are on time constants and on the noise
    left at the actual frame interval, not per frame. ram2 static_x holds 1-4 kN along X."""
    c = ram2["static_x"]
    t, w, T, w0, t0 = _raw_frames(twin_model, c, rate_hz)
    ref = c.reference
    outs = []
    # batching is covered at 10 Hz (one frame per call = 7 = 100); at 100 Hz batches of 100 (one
    # frame per call there took 76 s of the suite for the 58 000 frames, and the one-frame path
    # equals the vectorised one: test_the_one_frame_steady_step_is_the_vectorised_step)
    for batch in (1, 7, 100) if rate_hz == 10.0 else (100,):
        p = PhysicalPredictor(twin_model)
        parts = []
        for lo in range(0, len(t), batch):
            d, _ = p.predict(w[lo : lo + batch], T[lo : lo + batch], w0, t0, time_s=t[lo : lo + batch])
            parts.append(d)
        outs.append(np.vstack(parts))
    for other in outs[1:]:
        np.testing.assert_allclose(other, outs[0], rtol=0, atol=1e-9)
    d = outs[0]
    at = lambda s: d[np.searchsorted(t, s), 0]  # noqa: E731
    true = lambda s: ref["dx_um"].to_numpy()[np.argmin(np.abs(ref["time_s"].to_numpy() - s))]  # noqa: E731
    # mid-hold of every level (0, 1, 2, 3, 4, 3, 2, 1 kN, 0): within 1.5 % of the deflection
    for s in (30, 100, 165, 230, 295, 360, 425, 490, 555):
        assert abs(at(s) - true(s)) <= 0.015 * 558.0, (s, at(s), true(s))
    # the unloaded axes get nothing beyond their sub-micrometre truth
    assert np.abs(d[:, 1]).max() < 0.5 and np.abs(d[:, 2]).max() < 0.5


def _interpolated_frames(model, campaign, rate_hz, every=1, t_from_s=0.0, t_to_s=np.inf):
    """The campaign's frames (every ``every``-th) linearly interpolated to ``rate_hz``, as
    ``fbgcomp sim-interrogator`` serves a campaign: no fresh noise, so the frames' own noise is
    correlated over the recorded frame interval, which no training campaign showed."""
    fbg, temps = campaign.fbg.iloc[::every], campaign.temperatures
    t_in = fbg["time_s"].to_numpy()
    w_in = fbg[[f"{s}_nm" for s in model.sensor_names]].to_numpy()
    t = np.arange(max(t_from_s, t_in[0]), min(t_to_s, t_in[-1]), 1.0 / rate_hz)
    w = np.column_stack([np.interp(t, t_in, w_in[:, j]) for j in range(w_in.shape[1])])
    T = np.column_stack([np.interp(t, temps["time_s"], temps[f"{p}_C"]) for p in model.probe_names_])
    zero = t < t[0] + model.zero_window_s
    return t, w, T, w[zero].mean(axis=0), T[zero].mean(axis=0)


def _forces(model, t, w, T, w0, t0, batch=50):
    p = PhysicalPredictor(model)
    out, forces = [], []
    for lo in range(0, len(t), batch):
        d, _ = p.predict(w[lo : lo + batch], T[lo : lo + batch], w0, t0, time_s=t[lo : lo + batch])
        out.append(d)
        forces.append(p.last_force_N)
    return np.vstack(out), np.vstack(forces), p


def test_noise_correlated_over_many_frames_starts_no_false_loads(twin_model, ram2):
    """thermal_b's 1 s frames served at 100 frames/s (interpolated, as sim-interrogator does):
    the low-passed noise is about twice what the training's 10 Hz frames predict at that rate.
    Judged against the training noise, the step test started false loads that held the heat
    drift as a force: on this stretch dx went to -15 um against +2.2 um of truth. The test
    learns the stream's own noise: no load is started, and dx follows the heat."""
    c = ram2["thermal_b"]
    t, w, T, w0, t0 = _interpolated_frames(twin_model, c, 100.0, t_from_s=28800.0, t_to_s=28800.0 + 840.0)
    d, forces, p = _forces(twin_model, t, w, T, w0, t0)
    assert not forces.any(), np.abs(forces).max(axis=0)
    learnt = p.state["load"]["noise"]
    assert (learnt[:3] / learnt[3])[p.active].max() > 2.0  # it did learn a noisier stream
    ref = c.reference
    r = ref[(ref["time_s"] >= t[0]) & (ref["time_s"] <= t[-1])]
    true_dx = np.interp(t, r["time_s"], r["dx_um"]) - np.interp(t[0], r["time_s"], r["dx_um"])
    assert np.abs(d[:, 0] - true_dx).max() <= np.abs(true_dx).max(), "dx worse than uncompensated"


def test_load_steps_are_followed_in_noise_correlated_over_many_frames(twin_model, ram2):
    """static_x decimated to 1 s frames and served at 100 frames/s: the noise the step test
    learns raises its threshold, and every 1 kN level is still read within 1.5 %."""
    c = ram2["static_x"]
    t, w, T, w0, t0 = _interpolated_frames(twin_model, c, 100.0, every=10)
    d, forces, p = _forces(twin_model, t, w, T, w0, t0)
    learnt = p.state["load"]["noise"]
    assert (learnt[:3] / learnt[3])[p.active].max() > 1.5
    ref = c.reference
    assert not forces[t < 55.0].any()  # nothing before the first load
    for s in (100, 165, 230, 295, 360, 425, 490):
        i = np.searchsorted(t, s)
        true = ref["dx_um"].to_numpy()[np.argmin(np.abs(ref["time_s"].to_numpy() - s))]
        assert abs(d[i, 0] - true) <= 0.015 * 558.0, (s, d[i, 0], true)


def test_a_lost_grating_keeps_the_load_part(model, ram2):
    full = _metrics(model, ram2["static_x"])
    lost = _metrics(model, ram2["static_x"], exclude={"S1"})
    assert lost["axes"]["dx"]["max_abs_error_um"] < 0.1 * full["axes"]["dx"]["peak_um"]
    # without five of six gratings only the thermal part remains: never a wild correction
    few = _metrics(model, ram2["thermal_b"], exclude={"S1", "S2", "S3", "S4", "S5"})
    assert few["axes"]["dz"]["max_abs_error_um"] < 10.0


def test_model_file_round_trip_and_runtime_predictor(model, ram2, tmp_path):
    path = model.save(tmp_path / "m.json")
    p, last = _streamed_like_offline(model, load_model(path), ram2["thermal_b"], 500)
    assert p.last_flags.dtype == np.uint8 and p.last_flags.shape == (last, 3)


def test_non_finite_coefficient_is_refused(model, tmp_path):
    import json

    from fbgcomp.errors import InputError

    d = model.to_dict()
    d["thermal"]["coef"][1][2] = 1e400  # json writes Infinity
    path = tmp_path / "bad.json"
    path.write_text(json.dumps(d))
    with pytest.raises(InputError, match="non-finite"):
        load_model(path)


def test_the_population_moments_at_other_expansion_coefficients_are_those_of_its_responses():
    """population_at: the features are Z0 + sum_j alpha_j Z_j and the TTP sum_j alpha_j Y_j; the
    moments it assembles from the per-part blocks are those of the features and TTP themselves."""
    from fbgcomp.models.physical.thermal import population_at

    rng = np.random.default_rng(3)
    n, k, P_ = 200, 5, 3
    Z = rng.normal(size=(1 + P_, n, k))
    Y = rng.normal(size=(P_, n, 3))
    Ya = rng.normal(size=(P_, n, 3))

    def blocks(Z, Y, Ya):
        return {
            "zz": np.einsum("inK,jnL->ijKL", Z, Z) / n,
            "zy": np.einsum("inK,jna->ijKa", Z, Y) / n,
            "yy": np.einsum("ina,jna->ija", Y, Y) / n,
            "alone_yy": np.einsum("ina,jna->ija", Ya, Ya) / n,
        }

    tm = {"cte": {"blocks": blocks(Z, Y, Ya), "without": [blocks(Z[::-1], Y, Ya)]}}
    alpha = np.array([1.0e-6, 24e-6, 10.5e-6]) * 1e5
    X = Z[0] + np.tensordot(alpha, Z[1:], axes=1)
    T = np.tensordot(alpha, Y, axes=1)
    got = population_at(tm, alpha)
    np.testing.assert_allclose(got["gram"], X.T @ X / n, rtol=1e-12)
    np.testing.assert_allclose(got["xty"], X.T @ T / n, rtol=1e-12)
    np.testing.assert_allclose(got["ttp_ms_um2"], (T**2).mean(axis=0), rtol=1e-12)
    np.testing.assert_allclose(got["scale"], np.sqrt((X**2).mean(axis=0)), rtol=1e-12)
    Ta = np.tensordot(alpha, Ya, axes=1)
    np.testing.assert_allclose(got["without"][0]["ttp_ms_um2"], (Ta**2).mean(axis=0), rtol=1e-12)


def test_a_description_the_training_does_not_contradict_keeps_its_expansion(twin_model):
    """ram2 as published: the CFRP's axial expansion the training asks for is within what its
    noise allows of the data sheet's, so the map is the description's alone (ram2's thermal_b
    dx went from 2.3 to 9.1 µm when the estimate, 0.09e-6 against 0.4e-6 /K, replaced it)."""
    cte = twin_model.twin_map_["cte"]
    assert cte["parts"] == ["cfrp_L", "cfrp_T", "steel"]
    assert not cte["contradicted"] and cte["deviance"] < cte["threshold"], cte
    assert cte["described_per_K"] == pytest.approx([0.4e-6, 26.0e-6, 11.5e-6])
    assert np.isfinite(cte["estimated_per_K"]).all()
    assert "cte_members" not in twin_model.twin_map_  # the map's consensus is the description's


def test_a_fit_without_the_expansion_test_skips_the_moments_per_material(twin_model):
    # calibrate_cte=False: the population's moments per material serve nothing, and cost most
    # of its time; without them every moment the map and its members use is the same (to a
    # multi-threaded BLAS's rounding: bitwise with one thread)
    from fbgcomp.models.physical.thermal import twin_thermal_population
    from fbgcomp.structure import Twin, load_machine
    from fbgcomp.structure.scenarios import generic_heat_machine

    machine = load_machine(twin_model.machine)
    twin = Twin(generic_heat_machine(machine))
    args = (machine, twin_model.sensors_, twin_model.probe_names_, twin_model.housing_probes_)
    kw = {"n_scenarios": 6, "twin": twin, "nominal_W": twin_model.twin_map_["heat_prior_W"]}
    full = twin_thermal_population(*args, **kw)
    lean = twin_thermal_population(*args, per_material=False, **kw)
    assert "cte" in full and "cte" not in lean
    for key in ("gram", "xty", "ttp_ms_um2", "noise_gram", "envelope_low", "envelope_high"):
        np.testing.assert_allclose(lean[key], full[key], rtol=1e-12, atol=1e-12, err_msg=key)
    assert [w["source"] for w in lean["without"]] == [w["source"] for w in full["without"]]
    for a, b in zip(lean["without"], full["without"], strict=True):
        for key in ("gram", "xty", "ttp_ms_um2"):
            np.testing.assert_allclose(a[key], b[key], rtol=1e-12, atol=1e-12, err_msg=(a["source"], key))


def test_a_second_fit_reads_the_population_from_the_twin_cache(twin_model, tmp_path, monkeypatch):
    # the scenarios' moments are the same for every fit of this machine, gratings, probes and
    # heat prior: the second computation is a read, and gives the first's numbers to the bit
    from fbgcomp.models.physical import thermal
    from fbgcomp.structure import Twin, load_machine
    from fbgcomp.structure.scenarios import generic_heat_machine

    machine = load_machine(twin_model.machine)
    twin = Twin(generic_heat_machine(machine))  # from the session's cache, before it moves
    monkeypatch.setenv("FBGCOMP_CACHE_DIR", str(tmp_path / "cache"))
    args = (machine, twin_model.sensors_, twin_model.probe_names_, twin_model.housing_probes_)
    kw = {"n_scenarios": 3, "twin": twin, "nominal_W": twin_model.twin_map_["heat_prior_W"]}
    calls = []
    compute = thermal._population
    monkeypatch.setattr(thermal, "_population", lambda *a: calls.append(1) or compute(*a))
    cold = thermal.twin_thermal_population(*args, **kw)
    warm = thermal.twin_thermal_population(*args, **kw)
    assert len(calls) == 1 and len(list((tmp_path / "cache" / "derived").glob("*.twin"))) == 1

    def same(a, b, where="pop"):
        assert type(a) is type(b), where
        if isinstance(a, dict):
            assert a.keys() == b.keys(), where
            for k in a:
                same(a[k], b[k], f"{where}.{k}")
        elif isinstance(a, list):
            assert len(a) == len(b), where
            for i, (x, y) in enumerate(zip(a, b)):
                same(x, y, f"{where}[{i}]")
        elif isinstance(a, np.ndarray):
            assert a.dtype == b.dtype and np.array_equal(a, b), where
        else:
            assert a == b or (a != a and b != b), where  # NaN stays NaN

    same(cold, warm)
    assert isinstance(warm["cte"]["blocks"]["zz"], np.ndarray)
    # another seed or heat prior is another population
    thermal.twin_thermal_population(*args, **{**kw, "seed": 1})
    assert len(calls) == 2


def test_a_second_fit_reads_the_heat_priors_observer_run_from_the_twin_cache(
    twin_model, ram2, tmp_path, monkeypatch
):
    # the heat prior's Kalman filter over thermal_a (12 960 steps) gives the same sums for the
    # same observer and data: the second prior reads them, the same watts to the bit
    from fbgcomp.models.physical.observer import ThermalObserver
    from fbgcomp.structure import Twin, load_machine
    from fbgcomp.structure.scenarios import generic_heat_machine

    machine = load_machine(twin_model.machine)
    twin = Twin(generic_heat_machine(machine))  # from the session's cache, before it moves
    monkeypatch.setenv("FBGCOMP_CACHE_DIR", str(tmp_path / "cache"))
    runs = []
    real = ThermalObserver.run
    monkeypatch.setattr(ThermalObserver, "run", lambda self, *a: runs.append(1) or real(self, *a))
    campaigns = [ram2["thermal_a"], ram2["static_xyz"]]
    rows = [{"loaded": False}, {"loaded": True}]
    first = twin_model._heat_prior(machine, campaigns, rows, twin)
    assert len(runs) == 1  # the load-free campaign only
    again = twin_model._heat_prior(machine, campaigns, rows, twin)
    assert len(runs) == 1 and again == first == twin_model.twin_map_["heat_prior_W"] and first
    # other data is another run
    twin_model._heat_prior(machine, [ram2["thermal_b"], ram2["static_xyz"]], rows, twin)
    assert len(runs) == 2


def test_the_map_members_are_stored_and_checked(twin_model, tmp_path):
    import json

    from fbgcomp.errors import InputError

    d = twin_model.to_dict()  # the model's file content, a copy: editing it leaves the model alone
    assert [w["source"] for w in d["twin_map"]["without"]] == [
        f"generic_radiant_{t}" for t in ("pX", "mX", "pY", "mY")
    ]
    loaded = load_model(twin_model.save(tmp_path / "m.json"))
    assert loaded.predictor().map["n_members"] == 5
    d["twin_map"]["without"][1]["gram"] = d["twin_map"]["without"][1]["gram"][:-1]
    path = tmp_path / "bad.json"
    path.write_text(json.dumps(d))
    with pytest.raises(InputError, match=r"twin_map.without\[1\].gram"):
        load_model(path)
    assert twin_model.to_dict()["twin_map"] == loaded.to_dict()["twin_map"]


def test_the_unseen_part_is_what_the_map_makes_of_directions_the_training_never_moved_along():
    from fbgcomp.models.physical.thermal import unseen_basis, unseen_operator

    rng = np.random.default_rng(0)
    scale = np.array([2.0, 0.5, 1.0, 0.0])  # the last column: one the twin never moves
    # training frames move the first two features together and the third alone, never their
    # difference: (1, -1, 0) in standardised units is unseen (and the dead column carries nothing)
    a, b = rng.normal(size=(2, 500))
    X = np.column_stack([2.0 * a, 0.5 * a, b, np.zeros(500)])
    U = unseen_basis(X, np.ones(500), scale)
    assert U.shape == (4, 1)
    np.testing.assert_allclose(np.abs(U[:, 0]), [np.sqrt(0.5), np.sqrt(0.5), 0.0, 0.0], atol=1e-9)
    coef = rng.normal(size=(4, 3))
    W = unseen_operator(U, scale, coef)
    # nothing of a trained state, all of the untrained direction's share
    np.testing.assert_allclose(X @ W, 0.0, atol=1e-9)
    x = np.array([[2.0, -0.5, 0.0, 0.0]])  # (1, -1, 0, 0) standardised
    np.testing.assert_allclose(x @ W, x @ coef, atol=1e-12)
    # a well-spread training leaves nothing unseen
    assert unseen_basis(rng.normal(size=(500, 4)) * [1, 1, 1, 0], np.ones(500), scale).shape == (4, 0)


def test_the_interval_carries_the_part_of_the_correction_the_training_never_checked(twin_model, ram2):
    # thermal_a never heats one face more than the opposite one; thermal_b's radiant load does,
    # and the map's answer to it comes from the twin alone. ram2's thermal_a leaves 7 of the 12
    # standardised feature directions unseen; on thermal_b the unseen part reaches tens of µm
    # on dx, on thermal_a it stays within the noise.
    tm = twin_model.twin_map_
    assert np.asarray(tm["unseen_basis"]).shape == (12, 7)
    text = twin_model.summary()
    assert "unseen by the training: 7 of 12 feature directions" in text
    assert "ambient3600s" in text  # every calibrated term is listed, the ambient's too
    # the bearings' power the scenarios ran at, inferred on thermal_a (ram2's truth: 70.6 W
    # mean, at a mean duty level of 0.64 -> about 110 W nominal)
    prior = tm["heat_prior_W"]["spindle_heat"]
    assert 90.0 <= prior <= 140.0, prior
    assert f"spindle_heat {prior:.1f} W nominal" in text
    for name, lo, hi in (("thermal_a", 0.0, 0.5), ("thermal_b", 10.0, 100.0)):
        _, _, p, at = twin_model._served(ram2[name])
        u = np.abs(p.last_unseen[at]).max(axis=0)
        assert lo <= u[0] <= hi, (name, u)
    a = _metrics(twin_model, ram2["thermal_b"])["axes"]
    assert all(0.95 <= a[k]["pi95_coverage"] <= 0.995 for k in ("dx", "dy", "dz")), a


def test_generic_scenarios_work_on_a_machine_that_declares_no_heat_sources():
    # The built-in machine relies on the default sources (spindle heat in the housing and a
    # radiant face); `fbgcomp fit --machine` crashed on it with a TypeError.
    from fbgcomp.structure import load_machine
    from fbgcomp.structure.scenarios import FACES, generic_heat_machine

    machine = load_machine()
    assert machine.thermal.heat_sources is None
    names = [h.name for h in generic_heat_machine(machine).thermal.sources]
    assert names[:2] == [h.name for h in machine.thermal.sources]
    assert len(names) == 2 + len(FACES)


def test_a_force_the_training_never_applied_is_read_over_the_trained_range(ram2):
    # Trained with loads along X only (static_x): the Y signature comes from the twin of the
    # machine description, and a Y load must not be clamped to 1.5x the load cell's noise in
    # static_x's fy column (it was: 2.3 N on our twin, so every Y load was lost).
    xyz = read_ram2("static_xyz")["static_xyz"]
    machine = Path(__file__).resolve().parents[1] / "examples" / "machines" / "ram2.yaml"
    m = PhysicalModel(machine=machine, twin_scenarios=8).fit([ram2["thermal_a"], ram2["static_x"]])
    assert "from the FE twin" in m.load_["source"]
    fmax = np.asarray(m.load_["max_force_N"])
    assert fmax[1] == pytest.approx(fmax[0]) and fmax[0] > 3900.0
    a = _metrics(m, xyz)["axes"]["dy"]
    assert a["max_abs_error_um"] < 0.2 * a["peak_um"], a


def test_consensus_applies_what_every_member_agrees_on():
    from fbgcomp.models.physical.thermal import consensus

    m = np.array([[[3.0, -2.0, 1.0]], [[1.0, -5.0, -1.0]], [[2.0, -0.5, 4.0]]])  # (members, n, axes)
    np.testing.assert_array_equal(consensus(m), [[1.0, -0.5, 0.0]])
    # never larger than the full map (member 0) nor of the other sign: the applied correction is
    # the full map's shrunk towards zero, so it cannot end worse than both the full map and no
    # compensation
    rng = np.random.default_rng(0)
    x = rng.normal(size=(5, 1000, 3))
    c = consensus(x)
    assert np.all(np.abs(c) <= np.abs(x[0])) and np.all(c * x[0] >= 0)
    np.testing.assert_array_equal(consensus(x[:1]), x[0])


@pytest.mark.slow
def test_a_declared_zone_on_a_face_with_one_grating_does_no_harm():
    # ram2 as a user would describe it with its radiant load on the lower half of -X, where only
    # S2 sits: S2 reads the same whether that zone or the whole face warms (the twin's generic
    # whole-face pulses), and the TTP moves differently for each. With the one map of the whole
    # population, the twin's own thermal-36h-b (the declared zone warmed for 6 h) ended at dx
    # 10.45 µm against 8.19 uncompensated. The consensus of the maps without each undeclared
    # source keeps it below.
    import yaml

    from fbgcomp.bench.virtual import load_scenario, simulate
    from fbgcomp.structure import Twin, parse_machine

    src = Path(__file__).resolve().parents[1] / "examples" / "machines" / "ram2.yaml"
    d = yaml.safe_load(src.read_text())
    for h in d["thermal"]["heat_sources"]:
        if h["kind"] == "radiant":
            h.update(face="-X", z_mm=[0.0, 700.0], absorptivity=0.8, nominal_W_per_m2=120.0)
    machine = parse_machine(d)
    twin = Twin(machine)
    train = [simulate(machine, load_scenario(n), seed=0, twin=twin)[0] for n in ("thermal-36h", "static-xyz")]
    held, _ = simulate(machine, load_scenario("thermal-36h-b"), seed=1, twin=twin)
    m = PhysicalModel(machine=machine).fit(train)
    assert len(m.twin_map_["without"]) == 4  # one member per generic face
    for axis, a in _metrics(m, held)["axes"].items():
        assert a["max_abs_error_um"] <= a["peak_um"] + 0.5, (axis, a)
    # Trained on the thermal campaign alone (no loads): the gratings' frame noise was only read
    # on loaded campaigns, the step test fell back to 0.05 µm (a sixth of this noise) and noise
    # started loads on every frame: dx 471 µm here, 1123 µm on the built-in twin.
    alone = PhysicalModel(machine=machine).fit(train[:1])
    np.testing.assert_allclose(alone.load_["noise_var_um2"], m.load_["noise_var_um2"], rtol=0.5)
    for axis, a in _metrics(alone, held)["axes"].items():
        assert a["max_abs_error_um"] <= a["peak_um"] + 0.5, (axis, a)


def _without_probe(campaign, probe):
    """The campaign as if the probe had never been installed (its column and declaration gone)."""
    meta = campaign.meta.model_dump()
    meta["temperature_probes"] = [p for p in meta["temperature_probes"] if p["name"] != probe]
    return campaign.replaced(meta=meta, temperatures=campaign.temperatures.drop(columns=[f"{probe}_C"]))


def test_a_machine_without_a_housing_probe_is_fitted_and_does_no_harm(ram2, tmp_path):
    # A ram whose data sheet lists no probe on the spindle housing: the twin map's housing leads
    # are zero in every scenario, and the default fit crashed on their zero scale (NaN ridge,
    # then "array must not contain infs or NaNs" in the interval's NNLS).
    import yaml

    from fbgcomp.structure import load_machine

    src = Path(__file__).resolve().parents[1] / "examples" / "machines" / "ram2.yaml"
    desc = yaml.safe_load(src.read_text())
    desc["probes"] = [p for p in desc["probes"] if p["name"] != "T_flange"]
    path = tmp_path / "ram2-no-housing-probe.yaml"
    path.write_text(yaml.safe_dump(desc))
    machine = load_machine(path)
    assert housing_probe(machine) is None
    a, xyz, b = (_without_probe(ram2[n], "T_flange") for n in ("thermal_a", "static_xyz", "thermal_b"))
    m = PhysicalModel(machine=machine, twin_scenarios=8).fit([a, xyz])
    assert m.housing_probes_ == [] and m.twin_map_ is not None
    coef = np.asarray(m.twin_map_["coef"])
    assert np.isfinite(coef).all() and not coef[-2:].any()  # the leads carry nothing
    assert m.twin_map_.get("calibration") is None  # no housing transient to calibrate
    # no probe reads the housing, so the bearings' power in training cannot be told from the
    # other heat inputs' (the observer makes 20.8 W of ram2's 70.6): the declared nominal stays
    assert m.twin_map_["heat_prior_W"] == {}
    assert "their declared nominal power" in m.summary()
    out = tmp_path / "m.json"
    m.save(out)
    served = load_model(out)
    for axis, a_ in _metrics(served, b)["axes"].items():
        assert a_["max_abs_error_um"] <= a_["peak_um"] + 0.5, (axis, a_)


def _served(model, t, w, T, w0, t0, batch, fast):
    p = PhysicalPredictor(model)
    p.steady_fast_path = fast
    parts = [
        p.predict(w[lo : lo + batch], T[lo : lo + batch], w0, t0, time_s=t[lo : lo + batch])
        for lo in range(0, len(t), batch)
    ]
    return (
        np.vstack([d for d, _ in parts]),
        np.vstack([h for _, h in parts]),
        np.vstack([p.last_flags]) if batch >= len(t) else None,
    )


@pytest.mark.parametrize("batch", [1, 100, 10**9])
def test_the_vectorised_steady_stretches_equal_the_per_frame_recursion(twin_model, ram2, batch):
    """PhysicalPredictor._steady_run runs the stretches without a load transition vectorised:
    the same corrections and intervals as the per-frame recursion (to rounding), through load
    steps at 10 Hz (static_x), a grating that jumps alone (refused: the fast stretch stops at
    once and backs off) and 100 Hz frames with fresh noise. static_x's first 330 s: the zero
    window, four steps up to 4 kN and the first step down (the whole 580 s took 95 s here)."""
    for rate_hz, jump in ((10.0, False), (10.0, True), (100.0, False)):
        t, w, T, w0, t0 = _raw_frames(twin_model, ram2["static_x"], rate_hz)
        keep = t < 330.0
        t, w, T = t[keep], w[keep], T[keep]
        if jump:
            w = w.copy()
            w[len(w) // 3 :, twin_model.sensor_names.index("S3")] += 0.006
        if batch == 1 and rate_hz == 100.0:
            # the first 90 s: the zero window, the hold at 0 and the step to 1 kN (one frame per
            # call through 200 s took 60 of this test's 92 s)
            t, w, T = t[:9000], w[:9000], T[:9000]
        slow = _served(twin_model, t, w, T, w0, t0, batch, False)
        fast = _served(twin_model, t, w, T, w0, t0, batch, True)
        np.testing.assert_allclose(fast[0], slow[0], rtol=0, atol=1e-8)
        np.testing.assert_allclose(fast[1], slow[1], rtol=0, atol=1e-8)
        if fast[2] is not None:
            np.testing.assert_array_equal(fast[2], slow[2])  # the same frames refused
            assert not jump or (fast[2][:, 1] & P.LOAD_REFUSED).any()


def test_the_one_frame_steady_step_is_the_vectorised_step(twin_model, ram2, monkeypatch):
    """A batch of one frame without a load transition runs on Python floats
    (PhysicalPredictor._steady_frame): the same corrections, intervals and refused frames as
    the vectorised steady run of that one frame, through load steps and a grating that jumps
    alone, at 10 Hz."""
    t, w, T, w0, t0 = _raw_frames(twin_model, ram2["static_x"], 10.0)
    w = w.copy()
    w[2 * len(w) // 3 :, twin_model.sensor_names.index("S3")] += 0.006
    taken = []
    real = PhysicalPredictor._steady_frame

    def counted(self, *a):
        out = real(self, *a)
        taken.append(out is not None)
        return out

    def served():
        p = PhysicalPredictor(twin_model)
        parts, flags = [], []
        for i in range(len(t)):
            parts.append(p.predict(w[i : i + 1], T[i : i + 1], w0, t0, time_s=t[i : i + 1]))
            flags.append(p.last_flags)
        return np.vstack([d for d, _ in parts]), np.vstack([h for _, h in parts]), np.vstack(flags)

    monkeypatch.setattr(PhysicalPredictor, "_steady_frame", counted)
    fast = served()
    # the held loads' frames and the quiet ones between them, not the transitions
    assert 0.4 * len(t) < sum(taken) < len(t)
    monkeypatch.setattr(PhysicalPredictor, "_steady_frame", lambda self, *a: None)
    slow = served()
    np.testing.assert_allclose(fast[0], slow[0], rtol=0, atol=1e-10)
    np.testing.assert_allclose(fast[1], slow[1], rtol=0, atol=1e-10)
    np.testing.assert_array_equal(fast[2], slow[2])
    assert (fast[2][:, 1] & P.LOAD_REFUSED).any()  # the jump was met and refused


def test_a_fits_served_predictions_share_the_load_trackers_run_to_the_bit(twin_model, ram2, monkeypatch):
    """During a fit, served predictions of one campaign take the load tracker's run from rest
    once for each set of gratings (PhysicalModel.fit's memo): the tracker reads them
    uncompensated, so a lost probe shares the full set's run, and a lost grating does not. What
    they serve, and the tracker's state and transitions they go on from, are those of runs
    of their own, bit for bit."""
    import copy

    m = copy.copy(twin_model)  # the session's model stays as it is
    c = ram2["thermal_c"]  # heat, and a load on and off: transitions
    runs = []
    real = PhysicalPredictor._track_load

    def counted(self, *a, **k):
        runs.append(1)
        return real(self, *a, **k)

    monkeypatch.setattr(PhysicalPredictor, "_track_load", counted)
    sets = [frozenset(), frozenset({"T_amb"}), frozenset({"T_surf"}), frozenset({"S2"}), frozenset()]

    def serve_each():
        out = []
        for ex in sets:
            mean, half, p, _ = m._served(c, ex)
            out.append((mean, half, p.state["load"], p.last_transition, p.last_flags, p.last_force_N))
        return out

    own = serve_each()
    assert len(runs) == len(sets)
    runs.clear()
    m._served_memo = {"frames": {}, "load": {}}
    shared = serve_each()
    assert len(runs) == 2  # the full set's and that without S2
    assert own[0][5].any() and own[0][3].any()  # a load applied, transitions met
    for a, b in zip(own, shared):
        for x, y in zip(a, b):
            if isinstance(x, dict):
                assert x.keys() == y.keys()
                assert x["names"] == y["names"]  # the gratings the arrays are of
                for k in x.keys() - {"names"}:
                    np.testing.assert_array_equal(np.asarray(x[k], float), np.asarray(y[k], float))
            else:
                np.testing.assert_array_equal(x, y)
    # a memo's state is the caller's own: going on from it leaves the memo as it was
    shared[1][2]["offset"] += 1.0
    shared[1][3][:] = False
    again = m._served(c, sets[1])[2]
    np.testing.assert_array_equal(again.state["load"]["offset"], own[1][2]["offset"])
    np.testing.assert_array_equal(again.last_transition, own[1][3])


def test_first_order_closed_form_equals_the_recursion_across_stretches_and_gaps():
    from fbgcomp.models.filters import first_order_recursion as _first_order

    rng = np.random.default_rng(3)
    x = rng.uniform(0.0, 3.0, 2000)  # summed decay ~3000: five closed-form stretches
    x[[10, 500]] = [0.0, 5000.0]  # no time passes; a gap far beyond any memory
    u = rng.normal(size=(2000, 3)) * 10.0
    for gain in (True, False):
        y, ref = np.array([1.0, -2.0, 3.0]), []
        for xi, ui in zip(x, u):
            c = np.exp(-xi)
            y = c * y + ((1 - c) * ui if gain else ui)
            ref.append(y)
        np.testing.assert_allclose(
            _first_order(x, u, [1.0, -2.0, 3.0], gain=gain),
            np.array(ref),
            rtol=0,
            atol=1e-11 * np.abs(u).max(),
        )  # rounding of the input scale
        # one row per call (the runtime at batch 1), chained: the same recursion
        y, rows = np.array([1.0, -2.0, 3.0]), []
        for xi, ui in zip(x, u):
            y = _first_order(xi[None], ui[None, :], y, gain=gain)[0]
            rows.append(y)
        np.testing.assert_allclose(np.array(rows), np.array(ref), rtol=0, atol=1e-11 * np.abs(u).max())


def test_lowpass_on_a_jittered_clock_is_the_per_sample_recursion():
    """first_order_filter on an epoch clock (float rounding jitters its 1 ms steps) takes the
    closed form, not a per-sample loop: the same values as that loop."""
    rng = np.random.default_rng(5)
    t = 1.7e9 + np.arange(3000) * 1e-3
    assert not np.allclose(np.diff(t)[1:], np.diff(t)[1])  # the jitter is real
    x = rng.normal(size=(3000, 4))
    y, state = lowpass(x, t, 0.5, state=(np.ones(4), t[0] - 1e-3))
    ref, yp, tp = [], np.ones(4), t[0] - 1e-3
    for ti, xi in zip(t, x):
        e = np.exp(-max(ti - tp, 0.0) / 0.5)
        yp, tp = e * yp + (1 - e) * xi, ti
        ref.append(yp)
    np.testing.assert_allclose(y, np.array(ref), rtol=0, atol=1e-11)
    assert state[1] == t[-1]


def test_a_training_set_too_short_to_read_the_grating_noise_is_refused(tmp_path):
    """The step test needs each grating's frame noise; with fewer than 10 interrogator frames in
    every training campaign it was taken as zero, so every frame's noise would count as a load."""
    import shutil

    from fbgcomp.errors import InputError
    from fbgcomp.io.campaign import read_campaign
    from fbgcomp_testing import RAM2_DIR

    src = RAM2_DIR / "data" / "static_x"
    tiny = tmp_path / "tiny"
    tiny.mkdir()
    shutil.copy(src / "campaign.yaml", tiny)
    for name, rows in (("fbg", 9), ("loads", 9), ("temperatures", 3), ("reference", 3)):
        lines = (src / f"{name}.csv").read_text().splitlines()[:rows]
        (tiny / f"{name}.csv").write_text("\n".join(lines) + "\n")
    with pytest.raises(
        InputError, match=r"tiny/fbg.csv: the physical model .* at least 10 interrogator frames"
    ):
        PhysicalModel().fit(read_campaign(tiny))


def test_a_static_campaign_without_its_loads_file_is_kept_out_of_the_thermal_part(ram2, tmp_path):
    # A user whose static campaign has no load-cell record (no loads.csv): its 558 µm of load
    # deflection were taken for thermal drift, the housing transient was calibrated on them
    # (residual 189 µm) and thermal_b came out 348 µm off on dy against 18 uncompensated.
    from fbgcomp.io.campaign import read_campaign, write_campaign
    from fbgcomp.models.metrics import static_level_metrics

    xyz = ram2["static_xyz"]
    meta = xyz.meta.model_dump()
    assert meta["kind"] == "static" and xyz.loads is not None
    unrecorded = Campaign.from_arrays(
        meta, fbg=xyz.fbg, temperatures=xyz.temperatures, reference=xyz.reference, loads=None
    )
    write_campaign(unrecorded, tmp_path / "static_xyz")
    assert not (tmp_path / "static_xyz" / "loads.csv").exists()
    unrecorded = read_campaign(tmp_path / "static_xyz")
    machine = Path(__file__).resolve().parents[1] / "examples" / "machines" / "ram2.yaml"
    m = PhysicalModel(machine=machine, twin_scenarios=8).fit([ram2["thermal_a"], unrecorded])
    runs = {r["name"]: r for r in m.training_["campaigns"]}
    assert runs["static_xyz"]["loaded"] and runs["static_xyz"]["forces_unknown"]
    assert "forces_unknown" not in runs["thermal_a"]
    assert "static_xyz: static or combined without loads.csv" in m.summary()
    # the load signature comes from the twin alone, and reads the held-out static campaign
    c = ram2["static_x"]
    pred, _ = m.predict_interval(c)
    al = c.aligned(zero_window_s=m.zero_window_s)
    assert (
        static_level_metrics(al.loads_N, al.reference_um, pred)["axes"]["dx"]["error_pct_of_deflection"] < 1.0
    )
    for name in ("thermal_b", "static_x"):
        for axis, a in _metrics(m, ram2[name])["axes"].items():
            assert a["max_abs_error_um"] <= a["peak_um"] + 0.5, (name, axis, a)


def test_an_interrogators_epoch_clock_gives_the_same_correction(twin_model, ram2):
    # Many interrogators log Unix time: every file of ram2's thermal_b shifted by 1.773e9 s (a
    # date in 2026) must give the same correction and interval as the campaign's own clock.
    b = ram2["thermal_b"]
    shift = 1.773e9

    def shifted(df):
        return df.assign(time_s=df["time_s"] + shift)

    epoch = Campaign.from_arrays(
        b.meta.model_dump(),
        fbg=shifted(b.fbg),
        temperatures=shifted(b.temperatures),
        reference=shifted(b.reference),
        loads=None if b.loads is None else shifted(b.loads),
    )
    pred, half = twin_model.predict_interval(b)
    pred_e, half_e = twin_model.predict_interval(epoch)
    np.testing.assert_allclose(pred_e, pred, rtol=0, atol=1e-3)
    np.testing.assert_allclose(half_e, half, rtol=0, atol=1e-3)


def test_a_released_load_leaves_nothing_applied(twin_model, ram2):
    # thermal_c releases its -2500 N along X after 7 h. The tracker ended the release at the
    # mean of the force reading over its settling time, -10 N of noise on ram2 (117 N of
    # correlated noise on the twin's 2000 N release), and held it for good: dx stayed 1.37 µm
    # off on average for the remaining 5 h (the twin: 24.6 µm of dy for 6 h). A level the step
    # test could not tell from zero is zero.
    c = ram2["thermal_c"]
    pred, _ = twin_model.predict_interval(c)
    al = c.aligned(zero_window_s=twin_model.zero_window_s)
    t, F = al.time_s, al.loads_N
    release = t[np.abs(F[:, 0]) > 1000.0].max()
    after = t > release + 120.0
    assert after.sum() > 1000
    bias = (pred - al.reference_um)[after].mean(axis=0)
    assert abs(bias[0]) < 0.5, bias


def test_a_small_load_under_thermal_drift_ends_at_its_level(twin_model, ram2):
    # thermal_b at 10 h, under its radiant load: the gratings drift by -1 N/s of Fx. A 300 N
    # Fx step ended 46 N low, 6.2 µm of dx held for its half hour: the level was the mean
    # reading of its transition, which held the ramp, the thermal offset's lag behind the
    # drift (r x offset_tau_s) and the drift while the offset was frozen.
    import json

    from fbgcomp.bench.superpose import ram2_unit_responses, superpose_loads

    C, G = ram2_unit_responses(json.loads((RAM2_DIR / "results.json").read_text()))
    # exact: ram2 is linear (its README), the loads superpose on the thermal solution
    c = superpose_loads(ram2["thermal_b"], C, G, [(10.0, 10.5, (300.0, 0.0, 0.0))])
    pred, _ = twin_model.predict_interval(c)
    al = c.aligned(zero_window_s=twin_model.zero_window_s)
    t = al.time_s
    plateau = (t > 10.0 * 3600 + 60.0) & (t < 10.5 * 3600 - 10.0)
    assert plateau.sum() > 50 and np.allclose(al.loads_N[plateau, 0], 300.0, atol=3.0)
    err = (pred - al.reference_um)[plateau]
    assert np.abs(err[:, 0]).max() < 2.0, np.abs(err).max(axis=0)  # 300 N is 41.9 µm of dx
    # dy and dz: thermal_b's own errors there (a spindle change at 10 h), nothing added
    b = ram2["thermal_b"]
    base = (
        twin_model.predict_interval(b)[0] - b.aligned(zero_window_s=twin_model.zero_window_s).reference_um
    )[plateau]
    assert (np.abs(err[:, 1:]).max(axis=0) <= np.abs(base[:, 1:]).max(axis=0) + 0.3).all()


def test_the_housing_rest_level_is_the_mean_of_its_window_in_any_batching():
    from fbgcomp.models.physical.thermal import HOUSING_REST_S, housing_rest

    rng = np.random.default_rng(3)
    t = np.arange(0.0, 600.0, 1.0)
    raw = 0.1 * rng.standard_normal(t.size)
    smooth = np.cumsum(raw)[:, None] / np.arange(1, t.size + 1)[:, None]  # any smooth signal
    whole, past = housing_rest(raw, smooth, t, {}, {})
    inside = t - t[0] <= HOUSING_REST_S
    assert not past[inside].any() and past[~inside].all()
    assert not whole[inside].any()  # no lead is formed from the zero state's noise
    np.testing.assert_allclose(whole[~inside, 0], smooth[~inside, 0] - raw[inside].mean(), atol=1e-12)
    for batch in (1, 7, 100):
        state, parts = {}, []
        for lo in range(0, t.size, batch):
            new = {}
            rel, _ = housing_rest(
                raw[lo : lo + batch], smooth[lo : lo + batch], t[lo : lo + batch], state, new
            )
            state = new
            parts.append(rel)
        np.testing.assert_allclose(np.vstack(parts), whole, atol=1e-12)


@pytest.mark.slow
def test_a_noisy_zero_of_the_housing_probe_is_no_spindle_start(tmp_path):
    # ram2's description on the twin: a static campaign along X (seed 3) whose housing probe's
    # one zero-window sample sits 0.26 K (2.6 sigma) below its level. The calibrated housing
    # leads (11 µm of dz per K) read the step as a spindle start: dz 1.71 µm on an axis that
    # moves 0.23 µm (harm). Past a 300 s rest window the leads start from the housing's rest
    # level.
    import yaml

    from fbgcomp.bench.virtual import load_scenario, simulate
    from fbgcomp.structure import load_machine

    machine = load_machine(Path(__file__).resolve().parents[1] / "examples" / "machines" / "ram2.yaml")
    static_x = {
        "name": "static-x",
        "kind": "static",
        "description": "0-4000 N along X, 5 s ramps, each held 240 s",
        "rest_s": 60.0,
        "solver_dt_s": 0.5,
        "load_ramp_s": 5.0,
        "loads": [{"force_N": [f, 0, 0], "hold_s": 240} for f in (1000, 2000, 4000, 2000, 0)],
        "instruments": {
            "fbg": {"dt_s": 0.1},
            "interferometer": {"dt_s": 1.0, "clock_offset_s": 0.35},
            "probes": {"dt_s": 10.0, "clock_offset_s": 2.0},
            "load_cell": {"dt_s": 0.5, "clock_offset_s": 0.1},
        },
    }
    path = tmp_path / "static-x.yaml"
    path.write_text(yaml.safe_dump(static_x))
    train = [simulate(machine, load_scenario(n), seed=0)[0] for n in ("thermal-36h", "static-xyz")]
    held_out, _ = simulate(machine, load_scenario(path), seed=3)
    T = held_out.temperatures["T_flange_C"].to_numpy()
    assert T[0] < T.mean() - 0.2  # the zero sample is low
    m = PhysicalModel(machine=machine, twin_scenarios=8).fit(train)
    for axis, a in _metrics(m, held_out)["axes"].items():
        assert a["max_abs_error_um"] <= a["peak_um"] + 0.5, (axis, a)
    # Seed 16: the load tracker's low-pass started at the first raw frame, whose whole frame
    # noise the step test (judging low-passed noise) took for -40 N of Fy at 2 s, held for the
    # whole campaign: dy -8.5 to +4 µm on 0.23. It now starts at the zero state.
    held_out, _ = simulate(machine, load_scenario(path), seed=16)
    for axis, a in _metrics(m, held_out)["axes"].items():
        assert a["max_abs_error_um"] <= a["peak_um"] + 0.5, (axis, a)


def test_a_combined_campaign_gives_its_load_signature_from_the_load_changes(ram2):
    # A user with a thermal and a combined campaign but no static one: thermal_c heats while its
    # -2500 N Fx is held for 4 h, and the gratings' thermal reading that no probe sees went into
    # the Fx signature (0.18 and 0.29 µm/kN on S3 and S4, which see none of it; ram2's unit
    # responses: 0.009 and 0.039). thermal_c's own dy came out 5.8 µm off on 3.7, static_x's dz
    # 0.89 on 0.21: harm. The signature of a combined campaign is read from its load changes.
    import json

    machine = Path(__file__).resolve().parents[1] / "examples" / "machines" / "ram2.yaml"
    m = PhysicalModel(machine=machine).fit([ram2["thermal_a"], ram2["thermal_c"]])
    G = np.asarray(m.load_["G_um_per_N"]) * 1e3  # µm per kN
    true = (
        np.asarray(json.loads((RAM2_DIR / "results.json").read_text())["unit_response_um_per_N"]["x"][3:])
        * 1e3
    )
    # S3 and S4 (on the Y faces) see no Fx; the others within 5 % (two load changes, each one
    # reference sample of 10 s against a 5 s ramp)
    assert np.abs(G[2:4, 0] - true[2:4]).max() < 0.05, (G[:, 0], true)
    assert np.abs(G[[0, 1, 4], 0] / true[[0, 1, 4]] - 1.0).max() < 0.05, (G[:, 0], true)
    for name in ("thermal_c", "static_x", "thermal_b"):
        for axis, a in _metrics(m, ram2[name])["axes"].items():
            assert a["max_abs_error_um"] <= a["peak_um"] + 0.5, (name, axis, a)


def test_the_load_free_samples_keep_their_margin_from_any_force_or_gap():
    from fbgcomp.models.physical.model import load_free_samples

    t = np.arange(0.0, 1000.0, 10.0)
    F = np.zeros((t.size, 3))
    F[(t >= 300) & (t < 400), 1] = -2500.0  # held from 300 s to 390 s
    F[t == 800, 2] = np.nan  # a gap in the load cell's record
    free = load_free_samples(F, t, margin_s=120.0)
    np.testing.assert_array_equal(t[~free], t[((t > 170) & (t < 520)) | ((t >= 680) & (t <= 920))])
    assert load_free_samples(np.zeros((5, 3)), np.arange(5.0)).all()
    assert not load_free_samples(np.full((5, 3), 60.0), np.arange(5.0)).any()


@pytest.mark.slow
def test_a_combined_campaign_is_thermal_training_where_no_force_acts(ram2):
    """thermal_c (spindle heat, -2500 N of Fx from 3 h to 7 h of 12) and static_xyz as the only
    training: a combined campaign with known forces was no thermal training at all, so the model
    had no thermal part, left every axis of thermal_b uncompensated and gave it the 0.1 µm
    interval of a model with nothing to say (dz covered 0.012). Its samples 120 s or more from
    any force are thermal training now: thermal_b 2.35 / 0.69 / 4.73 µm on 30.6 / 18.2 / 59.9,
    as with thermal_a (2.30 / 0.61 / 4.62); the intervals on the wide side (0.995-0.997 covered:
    8 h of training hold few independent errors)."""
    machine = Path(__file__).resolve().parents[1] / "examples" / "machines" / "ram2.yaml"
    m = PhysicalModel(machine=machine).fit([ram2["thermal_c"], ram2["static_xyz"]])
    (c,) = [c for c in m.training_["campaigns"] if c["name"] == "thermal_c"]
    n = c["n_samples"]
    assert 0.6 * n < c["thermal_samples"] < 0.7 * n, c  # 8 h of 12, less the margins
    assert "thermal_c: combined, its thermal training" in m.summary()
    for name in ("thermal_b", "thermal_a", "static_x"):
        fig = _metrics(m, ram2[name])["axes"]
        for axis, a in fig.items():
            assert a["max_abs_error_um"] <= a["peak_um"] + 0.5, (name, axis, a)
            assert a["pi95_coverage"] >= 0.90, (name, axis, a)
        if name != "static_x":
            assert fig["dz"]["max_abs_error_um"] < 0.1 * fig["dz"]["peak_um"], (name, fig["dz"])
    fig = _metrics(m, ram2["thermal_b"])["axes"]
    assert fig["dx"]["max_abs_error_um"] < 0.1 * fig["dx"]["peak_um"], fig["dx"]
    assert fig["dy"]["max_abs_error_um"] < 0.1 * fig["dy"]["peak_um"], fig["dy"]


def test_a_fallback_holds_back_what_its_lost_gratings_told_the_full_map():
    """Without S4 the built-in twin's map errs on dy by 0.77 µm more over its population (the
    -Y face is then read from +Y alone). On the twin's thermal-36h-b, whose dy moves 0.19 µm, the
    fallback published -0.77 µm of dy where the truth was +0.12: worse than no compensation. The
    policy now counts that lost information as it counts the noise, and the interval and the
    expected error carry it; the full set's figures do not change."""
    from fbgcomp.bench.virtual import load_scenario, simulate
    from fbgcomp.structure import Twin, load_machine

    machine = load_machine()
    twin = Twin(machine)
    runs = {
        n: simulate(machine, load_scenario(n), seed=0, twin=twin)[0]
        for n in ("thermal-36h", "static-y", "thermal-36h-b")
    }
    m = PhysicalModel(machine=machine).fit([runs["thermal-36h"], runs["static-y"]])
    full, lost = m.predictor(), m.predictor(frozenset({"S4"}))
    np.testing.assert_array_equal(full.map_lost_sd_um, 0.0)
    assert lost.map_lost_sd_um[1] > 0.5 and (lost.expected_rms_error_um >= full.expected_rms_error_um).all()
    for exclude in (frozenset(), frozenset({"S4"}), frozenset({"S2"})):
        for axis, a in _metrics(m, runs["thermal-36h-b"], exclude)["axes"].items():
            assert a["max_abs_error_um"] <= a["peak_um"] + 0.5, (set(exclude), axis, a)


def test_a_load_that_stopped_is_published_at_its_settled_level_not_a_frames_noise(twin_model, ram2):
    """thermal_c recorded by a noisier interrogator (1 pm more white noise a frame, a common
    instrument's figure): ~130 N of Fx a frame at 1 frame/s. Once the -2500 N release has
    stopped, the tracker published the fast reading, a frame's noise, for its whole settling
    time (dx 14 µm off 10 s after the release, the twin's combined dy 27-68 µm for 15 s); it now
    publishes the level the frames since the stop give, zero for a release to a level the step
    test cannot tell from zero."""
    c = ram2["thermal_c"]
    t, w, T, w0, t0 = _interpolated_frames(twin_model, c, 1.0, t_to_s=26000.0)
    w = w + np.random.default_rng(5).normal(0.0, 1e-3, w.shape)
    _, forces, _ = _forces(twin_model, t, w, T, w0, t0)
    F = np.interp(t, c.loads["time_s"], c.loads["fx_N"])
    stopped = t[np.abs(F) > 10.0].max()  # the release's last frame under load
    assert (forces[(t > 11000.0) & (t < stopped - 20.0), 0] < -2000.0).all()  # the load was held
    after = (t >= stopped + 5.0) & (t <= stopped + 120.0)
    assert after.sum() > 100
    assert (forces[after, 0] == 0.0).all(), forces[after, 0][forces[after, 0] != 0.0][:5]


def _at_z(tmp_path, name, z_axis_mm):
    """ram2's campaign ``name`` copied with its campaign.yaml saying it ran at ``z_axis_mm``."""
    import shutil

    import yaml

    from fbgcomp.io.campaign import read_campaign

    folder = tmp_path / f"{name}-z{z_axis_mm:g}"
    shutil.copytree(RAM2_DIR / "data" / name, folder)
    meta = yaml.safe_load((folder / "campaign.yaml").read_text())
    meta["z_axis_mm"] = z_axis_mm
    (folder / "campaign.yaml").write_text(yaml.safe_dump(meta, sort_keys=False))
    return read_campaign(folder)


def test_the_lateral_correction_at_a_z_the_training_never_saw_is_held_back(twin_model, ram2, tmp_path):
    # The ram slides through its carriages: at another Z its overhang, and with it the TTP's
    # compliance, are not the trained ones (ram2's twin: 139 -> 92 µm/kN along X from Z = 0 to
    # 300 mm, the gratings' reading -5 %), and a load part applied there overshot (the built-in
    # twin trained at Z = 0: static-xyz at Z = 300 dx 564 µm off on 467 uncompensated).
    m = twin_model
    assert m.trained_z_axis_mm_ == [0.0]  # ram2 records no Z: the description's
    assert PhysicalModel.from_dict(m.to_dict()).trained_z_axis_mm_ == [0.0]
    here, _ = m.predict_interval(ram2["static_x"])
    for z, same in ((0.0, True), (8.0, True), (300.0, False)):
        c = _at_z(tmp_path, "static_x", z)
        pred, half = m.predict_interval(c)
        flags = m.last_flags_
        if same:  # within z_tolerance_mm (10 mm) of the trained position: as without a Z
            np.testing.assert_array_equal(pred, here)
            continue
        ref = c.aligned(zero_window_s=m.zero_window_s).reference_um
        loaded = np.abs(ref[:, 0]) > 100.0
        # the 558 µm along X is not corrected, dx and dy are held back (dz, which the nut
        # travelling with the ram keeps from Z, is not), no axis is worse than uncompensated,
        # the interval takes in the deflection left, and the frames say why
        assert not pred[:, :2].any()
        np.testing.assert_array_equal(pred[:, 2], here[:, 2])
        assert (np.abs(ref - pred).max(axis=0) <= np.abs(ref).max(axis=0) + 0.5).all()
        assert np.mean(np.abs(ref[loaded, 0] - pred[loaded, 0]) <= half[loaded, 0]) > 0.95
        assert (flags[:, :2] & P.SHRUNK).all()


def test_the_runtime_holds_the_lateral_correction_at_a_live_z_the_training_never_saw(twin_model, ram2):
    from fbgcomp.runtime.pipeline import Pipeline

    c = ram2["static_x"]
    m = twin_model
    al = c.aligned(zero_window_s=m.zero_window_s)
    ft, w, t = m.frame_arrays(c, al)
    ones = np.ones(w.shape, np.int8)
    out = {}
    for z in (None, 300.0, np.nan):
        pipe = Pipeline(m)
        res = [
            pipe.process(
                ft[i : i + 100],
                w[i : i + 100],
                ones[i : i + 100],
                ones[i : i + 100],
                t[i : i + 100],
                z_axis_mm=z,
            )
            for i in range(0, len(ft), 100)
        ]
        out[z] = np.vstack([r.correction_um for r in res])
    # 4000 N along X: the correction follows it at the trained Z (no position source) and is
    # held back at Z = 300 and at a Z gone stale (NaN: the machine may be anywhere)
    assert np.abs(out[None][:, 0]).max() > 400.0
    assert np.abs(out[300.0][:, 0]).max() < 1.0
    assert np.abs(out[np.nan][:, 0]).max() < 1.0
    # and serve says so when a position source is configured
    assert "trained at Z = 0 mm" in Pipeline(m).z_note


def test_the_interval_carries_the_whole_thermal_correction_at_its_relative_error(twin_model, ram2):
    # The training's residuals cannot show the error a heat taking another path leaves; the
    # interval takes the whole thermal correction at thermal_relative_error of itself, in
    # quadrature, after the scaling on the training (so the rest of the interval is unchanged).
    import copy

    from fbgcomp.models.distributions import norm_ppf

    rho = twin_model.thermal_relative_error
    assert rho == 0.005
    assert "the whole thermal correction enters the interval at 0.5 % of itself" in twin_model.summary()
    d = copy.deepcopy(twin_model.to_dict())
    del d["params"]["thermal_relative_error"]  # a model file from before the term
    before = PhysicalModel.from_dict(d)
    assert before.thermal_relative_error == 0.0
    c = ram2["thermal_b"]
    mean, half, p, at = twin_model._served(c)
    mean0, half0, _, _ = before._served(c)
    np.testing.assert_array_equal(mean, mean0)  # the correction is not touched
    thermal = p.last_thermal[at]
    assert np.abs(thermal[:, 2]).max() > 40.0  # thermal_b's dz drift, 59.9 µm
    np.testing.assert_allclose(
        half**2 - half0**2, (norm_ppf(0.975) * rho * thermal) ** 2, rtol=1e-9, atol=1e-9
    )
    # where the housing has warmed by 40 µm of dz, the term alone is a half-width of 0.4 µm
    hot = np.abs(thermal[:, 2]) > 40.0
    assert np.all(np.sqrt(half[hot, 2] ** 2 - half0[hot, 2] ** 2) >= 0.39)
    assert np.all(half[hot, 2] > half0[hot, 2])


@pytest.mark.slow
def test_an_hour_without_the_interrogator_is_predicted_without_a_warning_and_without_harm(ram2, twin_model):
    """ram2's thermal_b with fbg.csv missing from 10 h to 11 h (an interrogator stopped): the
    frame after the gap is an hour away, so the load tracker's fast and slow readings are the same
    frame and its noise test has nothing to learn there. The unread Fz's infinite noise times
    that zero made a NaN, which the test takes as no information, and a RuntimeWarning printed on
    every ``validate`` of such a campaign. The model goes on from the frame before the gap (the
    validation's note names those samples); no axis is worse there than uncompensated."""
    import warnings

    c = ram2["thermal_b"]
    t = c.fbg["time_s"].to_numpy()
    gapped = c.replaced(fbg=c.fbg[(t < 36000.0) | (t >= 39600.0)])
    assert gapped.gaps() == {"fbg.csv": [(35999.0, 39600.0)]}
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        pred, _ = twin_model.predict_interval(gapped)
    al = gapped.aligned(zero_window_s=twin_model.zero_window_s)
    ref = al.reference_um
    err, peak = np.abs(pred - ref).max(axis=0), np.abs(ref).max(axis=0)
    assert (err <= 0.5 * peak).all(), (err, peak)  # 10.5 / 3.7 / 4.6 µm on 30.6 / 18.2 / 59.9
    # away from the gap, the prediction is the unbroken campaign's: the hour left no trace
    whole = twin_model.predict(c)
    later = al.time_s > 39600.0 + 3600.0
    assert np.abs(pred[later] - whole[later]).max() < 0.5
