"""Strain-free reference gratings in ``serve``, end to end with real processes on loopback:
``fbgcomp fit`` on a campaign whose S1 and S3 carry reference gratings (the model reads them as
probes ``S1_ref``, ``S3_ref``), ``sim-interrogator`` serving the sensors' and the reference
gratings' peaks, ``serve --log`` with a real asyncua client (Basic256Sha256 Sign & Encrypt)
watching. The temperature source is the campaign folder, whose temperatures.csv has no
``<S>_ref_C`` column: the reference temperatures come from the peaks only.

The published correction is compared frame by frame with the offline model on the same frames,
computed independently of the runtime: the wavelengths the simulator interpolates from fbg.csv
at each frame's campaign time, the probes held from temperatures.csv, and the reference
temperatures of ``Campaign.thermometers()`` (eq. 3 inverted, relative to the grating's first
sample). The runtime reads a reference grating relative to its nominal ``reference_lambda0_nm``
instead; that offset cancels in the zero state up to the ratio of the two wavelengths, which
scales the reference temperature changes by lambda_first / reference_lambda0_nm (here 1 + 2.6e-4).
So the exact expectation is the offline model with the reference temperatures scaled by that
ratio (to the float rounding of the zero-state sums, 1e-6 µm), and the size of the scaling's
effect is bounded separately.

Then S1's reference grating disappears (``drop:S1_ref@4``): a missing temperature for the
model, handled as a missing probe is (no usable model: ALARM, the correction held and ramped to
zero), and visible on OPC UA.
"""

import asyncio
import time

import numpy as np
import pytest

import fbgcomp_testing
from test_runtime_support import fbgcomp_process, serve_with_simulator

ENV = {"FBGCOMP_OPCUA_USER": "operator", "FBGCOMP_OPCUA_PASSWORD": "refgrating-pass-123"}
NAMES = ["CorrectionX_um", "CorrectionY_um", "CorrectionZ_um", "Health", "Alarm"]
REFS = {"S1": 1560.0, "S3": 1570.0}  # reference_lambda0_nm, clear of every sensor window
INSTALL_OFFSET_NM = 0.4  # the gratings' actual zero sits this far above it
DROP_AT_S = 4.0
RATE_HZ = 1000
SPEED = 20.0  # campaign seconds per second: ~1.5 K of gauge heat


def with_reference_gratings(campaign, seed):
    """``campaign`` (synthetic, sensors compensated by T_surf) with strain-free reference
    gratings beside S1 and S3. Their gauges run warmer than T_surf by a slow extra signal, so the
    reference temperatures carry what no probe has; the bonded gratings see that temperature."""
    from fbgcomp import optics
    from fbgcomp.io.campaign import Campaign, CampaignMeta

    rng = np.random.default_rng(seed)
    meta = campaign.meta.model_dump()
    fbg = campaign.fbg.copy()
    t = fbg["time_s"].to_numpy()
    temps = campaign.temperatures
    surf = np.interp(t, temps["time_s"].to_numpy(), temps["T_surf_C"].to_numpy())
    for s in meta["sensors"]:
        if s["name"] not in REFS:
            continue
        old_dt = surf - surf[0]
        new_dt = old_dt + 1.5 * np.sin(2 * np.pi * t / rng.uniform(200, 400) + rng.uniform(0, 6))
        new_dt -= new_dt[0]
        kw = dict(
            photoelastic=s["photoelastic"],
            thermo_optic_per_K=s["thermo_optic_per_K"],
            fibre_cte_per_K=s["fibre_cte_per_K"],
        )
        col = f"{s['name']}_nm"
        elong = optics.elongation_um(fbg[col].to_numpy(), s["lambda0_nm"], s["gauge_length_mm"], old_dt, **kw)
        fbg[col] = optics.wavelength_nm(elong, s["lambda0_nm"], s["gauge_length_mm"], new_dt, **kw)
        fbg[f"{s['name']}_ref_nm"] = optics.free_grating_wavelength_nm(
            new_dt,
            REFS[s["name"]] + INSTALL_OFFSET_NM,
            thermo_optic_per_K=s["thermo_optic_per_K"],
            fibre_cte_per_K=s["fibre_cte_per_K"],
        )
        s["reference_lambda0_nm"] = REFS[s["name"]]
        s["temperature_probe"] = None  # compensated by its own reference grating
    return Campaign.from_arrays(
        CampaignMeta(**meta), fbg=fbg, temperatures=temps, reference=campaign.reference
    )


@pytest.fixture(scope="session")
def campaigns(tmp_path_factory):
    from fbgcomp.bench.synthetic import linear_truth_campaign
    from fbgcomp.io.campaign import write_campaign

    base = tmp_path_factory.mktemp("refgratings")
    train, _ = linear_truth_campaign("train", seed=1, duration_s=2 * 3600, noise_um=0.05)
    serve, _ = linear_truth_campaign(
        "serve", seed=2, duration_s=300, fbg_dt_s=0.1, temperature_dt_s=0.1, reference_dt_s=0.1, settle_s=0.0
    )
    train_dir = write_campaign(with_reference_gratings(train, 1), base / "train")
    serve_dir = write_campaign(with_reference_gratings(serve, 2), base / "serve")
    model = base / "model.json"
    fit = fbgcomp_process(
        "fit", train_dir, "--features", "eq13", "--zero-window", 0.5, "--fallbacks", "loo", "-o", model
    )
    _out, err = fit.communicate(timeout=600)
    assert fit.returncode == 0, err.decode()[-3000:]
    return dict(base=base, train=train_dir, serve=serve_dir, model=model)


@pytest.fixture(scope="session")
def served(campaigns, tmp_path_factory):
    fbgcomp_testing.require("asyncua")
    fbgcomp_testing.require("pyarrow")
    from fbgcomp.runtime.log import read_log

    tmp = tmp_path_factory.mktemp("refgratings_serve")
    # output policy off: the published correction is the model's own, frame by frame.
    # no_data_s: a loaded machine pausing the stream must not add no-data ALARM ticks
    # speed: temperatures.csv replayed at the simulator's pace
    config = (
        f"[source]\nbackoff_initial_s = 0.05\nbackoff_max_s = 0.4\nspeed = {SPEED}\n"
        "no_data_s = 5.0\n\n[pipeline]\nramp_s = 0.5\n"
        "max_slew_um_per_s = 0\nmax_correction_um = [0, 0, 0]\n"
        "[pipeline.output_filter]\nenabled = false\n"
    )
    with serve_with_simulator(
        tmp,
        config,
        campaigns["model"],
        campaigns["serve"],
        ENV,
        ("--rate", RATE_HZ, "--speed", SPEED, "--fault", f"drop:S1_ref@{DROP_AT_S:g}"),
    ) as run:

        def done(seen):
            ok = [r for n, v, _, r in seen if n == "Health" and v == "OK"]
            alarm = [r for n, v, _, r in seen if n == "Health" and v == "ALARM"]
            return bool(ok) and bool(alarm) and time.time() - alarm[0] > 1.5

        seen = run.watch(NAMES, 60.0, done)
        alive = run.serve.poll() is None
    meta, log = read_log(tmp / "log")
    return dict(seen=seen, alive=alive, meta=meta, log=log)


def _campaign_times(log, fbg):
    """Campaign time of every logged frame: the simulator stamps frame k at t0 + k / rate and
    serves fbg.csv interpolated at k * speed / rate. serve connects after the simulator
    started, so the first logged k is found by matching the noise-free wavelengths."""
    t = log["time_s"].to_numpy()
    steps = np.round((t - t[0]) * RATE_HZ).astype(np.int64)
    assert np.abs((t - t[0]) * RATE_HZ - steps).max() < 0.01  # on the frame grid
    ft = fbg["time_s"].to_numpy()
    cols = ["S1_nm", "S2_nm", "S3_nm", "S4_nm", "S5_nm"]
    first = log[cols].to_numpy()[:50]
    k = np.arange(0, 20 * RATE_HZ)
    err = sum(
        (
            (
                np.interp((k[:, None] + steps[None, :50]) * SPEED / RATE_HZ, ft, fbg[c].to_numpy())
                - first[:, j][None, :]
            )
            ** 2
        ).sum(axis=1)
        for j, c in enumerate(cols)
    )
    k0 = int(np.argmin(err))
    return (k0 + steps) * SPEED / RATE_HZ


def test_the_correction_is_the_offline_models_on_the_same_frames(served, campaigns):
    from fbgcomp.io.campaign import read_campaign
    from fbgcomp.models.registry import load_model

    assert served["alive"]
    model = load_model(campaigns["model"])
    assert {"S1_ref", "S3_ref"} <= set(model.probe_names)
    camp = read_campaign(campaigns["serve"])
    assert not any(c.endswith("_ref_C") for c in camp.temperatures.columns)
    log = served["log"]
    t = log["time_s"].to_numpy()
    c_t = _campaign_times(log, camp.fbg)
    ft = camp.fbg["time_s"].to_numpy()
    # the frames serve logged are the simulator's, sensor by sensor
    w = np.column_stack([np.interp(c_t, ft, camp.fbg[f"{s}_nm"].to_numpy()) for s in model.sensor_names])
    np.testing.assert_allclose(log[[f"{s}_nm" for s in model.sensor_names]].to_numpy(), w, rtol=0, atol=1e-9)
    # probes: temperatures.csv replayed from serve's first frame on, latest value held (the
    # frames are 0.02 campaign s apart: 1e-3 s settles the epoch clock's rounding either way)
    temp = np.empty((t.size, len(model.probe_names)))
    tt = camp.temperatures["time_s"].to_numpy()
    held = np.searchsorted(tt, (t - t[0]) * SPEED + 1e-3, side="right") - 1
    thermo = {}
    for names, (src_t, src_v) in camp.thermometers().items():
        for j, p in enumerate(names):
            thermo[p] = (src_t, src_v[:, j])
    ratio = np.ones(len(model.probe_names))
    for k, p in enumerate(model.probe_names):
        if p.endswith("_ref"):  # eq. 3 inverted, relative to the first sample
            temp[:, k] = np.interp(c_t, *thermo[p])
            first = camp.fbg[f"{p}_nm"].to_numpy()[0]
            ratio[k] = first / model.sensors[model.sensor_names.index(p[:-4])].reference_lambda0_nm
        else:
            temp[:, k] = camp.temperatures[f"{p}_C"].to_numpy()[held]
    real = [k for k, p in enumerate(model.probe_names) if not p.endswith("_ref")]
    logged_T = log[[f"{p}_C" for p in model.probe_names]].to_numpy()
    np.testing.assert_array_equal(logged_T[:, real], temp[:, real])
    assert 2.5e-4 < ratio.max() - 1 < 2.7e-4

    zero = t <= t[0] + model.zero_window_s
    health = log["health"].to_numpy()
    ok = health == 0
    before = t < t[0] + 3.0  # S1_ref is dropped 4 s after the simulator started
    assert (c_t[ok] - c_t[0]).max() > 50.0
    assert (ok & before).sum() > 1500, (ok & before).sum()

    def offline(T):
        dev, _ = model.predictor().predict(w[ok], T[ok], w[zero].mean(axis=0), T[zero].mean(axis=0))
        return dev

    exact = offline(temp * ratio)  # the runtime's reading: relative to reference_lambda0_nm
    plain = offline(temp)  # Campaign.thermometers(): relative to the first sample
    corr = log[["corr_dx_um", "corr_dy_um", "corr_dz_um"]].to_numpy()[ok]
    np.testing.assert_allclose(corr, -exact, rtol=0, atol=1e-6)
    # the nominal-vs-actual zero of the reference gratings: a scale of 2.6e-4 on their
    # temperature changes, here hundredths of a µm at most (measured in the report)
    offset_effect = np.abs(exact - plain).max(axis=0)
    assert (offset_effect < 0.05).all(), offset_effect
    assert (np.abs(corr + plain).max(axis=0) <= offset_effect + 1e-6).all()
    # and the reference gratings matter: read as T_surf (their sensors' old probe) instead,
    # the model predicts something else by far more than that
    k_surf = model.probe_names.index("T_surf")
    as_probe = temp.copy()
    for k, p in enumerate(model.probe_names):
        if p.endswith("_ref"):
            as_probe[:, k] = temp[:, k_surf]
    assert np.abs(offline(as_probe) - exact).max() > 100 * offset_effect.max() + 0.1


def test_a_lost_reference_grating_is_a_missing_temperature(served, campaigns):
    from fbgcomp.models.registry import load_model

    model = load_model(campaigns["model"])
    log, seen = served["log"], served["seen"]
    t = log["time_s"].to_numpy()
    ref = log["S1_ref_C"].to_numpy()
    lost = ~np.isfinite(ref)
    assert lost.any() and np.isfinite(log["S3_ref_C"].to_numpy()).all()
    first = int(np.argmax(lost))
    assert lost[first:].all()  # gone for good from the drop on
    assert (t[lost] - t[0]).max() > 1.0
    health = log["health"].to_numpy()
    assert health[first - 1] == 0 and (health[first:] == 2).all()  # ALARM on that frame
    # every grating itself is fine: the sensors stay OK, no fallback can stand in for a probe
    for s in model.sensor_names:
        assert (log[f"{s}_status"].to_numpy()[first:] == 0).all()
    assert (log["model_set"].to_numpy()[first:] == -1).all()
    # the last correction held, then ramped to zero over ramp_s = 0.5 s
    corr = log[["corr_dx_um", "corr_dy_um", "corr_dz_um"]].to_numpy()
    held = corr[first - 1]
    assert np.abs(held).max() > 0
    frac = np.clip(1 - (t[first:] - t[first]) / 0.5, 0, 1)
    np.testing.assert_allclose(corr[first:], held * frac[:, None], rtol=0, atol=1e-9)
    # OPC UA showed it
    states = [v for n, v, *_ in seen if n == "Health"]
    assert "OK" in states and states[-1] == "ALARM"
    assert [v for n, v, *_ in seen if n == "Alarm"][-1] is True
    assert [v for n, v, *_ in seen if n == "CorrectionY_um"][-1] == 0.0


def test_replay_reads_the_reference_gratings_from_fbg_csv(campaigns, tmp_path):
    """replay:// (in process): the reference temperatures come from fbg.csv's <S>_ref_nm, the
    probes from temperatures.csv, and the model runs with health OK on them."""
    fbgcomp_testing.require("pyarrow")
    from fbgcomp import optics
    from fbgcomp.io.campaign import read_campaign
    from fbgcomp.runtime.log import read_log
    from fbgcomp.runtime.service import RuntimeConfig, Service

    cfg = RuntimeConfig(model=str(campaigns["model"]), opcua_enabled=False)
    cfg.source.url = f"replay://{campaigns['serve']}?speed=20"
    cfg.log.dir = str(tmp_path / "log")
    svc = Service(cfg)
    asyncio.run(svc.run(2.0))
    _, log = read_log(tmp_path / "log")
    camp = read_campaign(campaigns["serve"])
    assert len(log) > 100 and (log["health"].iloc[-50:] == 0).all()
    # replayed rows are fbg.csv's rows: each frame's S3_ref_C is its row's S3_ref_nm read
    rows = [int(np.flatnonzero(camp.fbg["S2_nm"].to_numpy() == v)[0]) for v in log["S2_nm"]]
    s3 = camp.meta.sensor("S3")
    expect = optics.grating_temperature_change_K(
        camp.fbg["S3_ref_nm"].to_numpy()[rows],
        s3.reference_lambda0_nm,
        thermo_optic_per_K=s3.thermo_optic_per_K,
        fibre_cte_per_K=s3.fibre_cte_per_K,
    )
    np.testing.assert_allclose(log["S3_ref_C"].to_numpy(), expect, rtol=0, atol=1e-12)
    # `fbgcomp log export` gives the reference gratings back as the wavelengths they read
    # (it refused before: 'S1_ref' was written as a probe, a name the reference grating holds)
    from fbgcomp.runtime.log import export_campaign

    out = export_campaign(tmp_path / "log", tmp_path / "exported")
    again = read_campaign(tmp_path / "exported")
    assert not any(c.endswith("_ref_C") for c in again.temperatures.columns)
    np.testing.assert_allclose(
        again.fbg["S3_ref_nm"].to_numpy(),
        camp.fbg["S3_ref_nm"].to_numpy()[rows][
            np.isin(log["time_s"].to_numpy() - log["time_s"].iloc[0], again.fbg["time_s"].to_numpy())
        ],
        rtol=0,
        atol=1e-9,
    )
    assert out.meta.sensor("S3").reference_lambda0_nm == s3.reference_lambda0_nm
