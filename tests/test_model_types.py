"""Model types kinematic, hybrid, dynamic: fit, model file (schema v2 + migration), runtime
contract, streaming filters, prediction intervals on held-out campaigns, CLI."""

import json

import numpy as np
import pytest
from sklearn.base import clone
from sklearn.utils.estimator_checks import (
    check_get_params_invariance,
    check_no_attributes_set_in_init,
    check_set_params,
)

from fbgcomp.bench.virtual import Scenario, load_scenario, simulate
from fbgcomp.io.campaign import read_campaign, write_campaign
from fbgcomp.models import (
    CalibratedModel,
    DynamicModel,
    HybridModel,
    KinematicModel,
    MRAModel,
    PhysicalModel,
    load_model,
)
from fbgcomp.models.filters import first_order_filter
from fbgcomp.models.metrics import static_level_metrics, validation_metrics
from fbgcomp.structure import Twin, load_machine
from fbgcomp_testing import cli

HOURS = 3.0


def _short(name, hours=HOURS, **update):
    """A built-in thermal scenario compressed in time to ``hours`` (same shapes, faster)."""
    data = load_scenario(name).compressed(hours).model_dump()
    data["instruments"]["fbg"]["dt_s"] = 5.0
    data["instruments"]["interferometer"]["dt_s"] = 10.0
    data["solver_dt_s"] = 5.0
    data.update(update)
    return Scenario.model_validate(data)


@pytest.fixture(scope="session")
def campaigns(tmp_path_factory):
    root = tmp_path_factory.mktemp("bench")
    machine = load_machine()
    twin = Twin(machine, resolution=0.3)
    out = {}
    for i, (name, sc) in enumerate(
        [
            ("thermal-a", _short("thermal-36h")),
            ("thermal-b", _short("thermal-36h-b")),
            ("static-y", load_scenario("static-y")),
            ("static-xyz", load_scenario("static-xyz")),
        ]
    ):
        c, _ = simulate(machine, sc, seed=10 + i, twin=twin)
        out[name] = read_campaign(write_campaign(c, root / name))
    tw300 = Twin(machine, resolution=0.3, z_axis_mm=300.0)
    sc = load_scenario("static-y").model_copy(update={"z_axis_mm": 300.0})
    c, _ = simulate(machine, sc, seed=20, twin=tw300)
    out["static-y-z300"] = read_campaign(write_campaign(c, root / "static-y-z300"))
    return out


def _metrics(model, campaign):
    pred, half = model.predict_interval(campaign)
    return validation_metrics(campaign.aligned().reference_um, pred, half), pred, half


def test_kinematic_model_needs_no_campaign_and_follows_z(campaigns):
    model = KinematicModel().fit()
    assert model.training_["n_samples"] == 0 and model.pi_source_ == "default"
    for name in ("static-y", "static-y-z300"):
        c = campaigns[name]
        m, pred, _half = _metrics(model, c)
        ref = c.aligned().reference_um
        loaded = np.abs(ref[:, 1]) > 0.5 * np.abs(ref[:, 1]).max()
        ratio = np.median(pred[loaded, 1] / ref[loaded, 1])
        assert ratio == pytest.approx(1.0, abs=0.2), name
        assert 0.8 <= m["axes"]["dy"]["pi95_coverage"] <= 1.0
    assert "underdetermined" in model.summary()


@pytest.mark.parametrize(
    "make",
    [
        lambda: KinematicModel(),
        lambda: HybridModel(features="eq13"),
        lambda: HybridModel(features="dynamic", stepwise=False),
        lambda: CalibratedModel(features="eq13"),
        lambda: DynamicModel(stepwise=True),
    ],
)
def test_model_file_round_trip_and_runtime_contract(campaigns, tmp_path, make):
    model = make().fit([campaigns["thermal-a"], campaigns["static-y"]])
    path = model.save(tmp_path / "m.json")
    d = json.loads(path.read_text())
    assert d["schema_version"] == 2 and d["model_type"] == model.model_type
    assert d["uncertainty"]["level"] == 0.95
    back = load_model(path)
    assert type(back) is type(model) and back.model_id == model.model_id
    c = campaigns["thermal-b"]
    p1, h1 = model.predict_interval(c)
    p2, h2 = back.predict_interval(c)
    np.testing.assert_allclose(p2, p1, atol=1e-9)
    np.testing.assert_allclose(h2, h1, atol=1e-9)
    assert np.all(h1 > 0)
    # Runtime contract: attributes, fallbacks, predictor on raw arrays.
    assert back.sensor_names == ["S1", "S2", "S3", "S4", "S5"] and back.zero_window_s == 10.0
    assert back.probe_names and back.fallback_sets
    a = c.aligned()
    w, t, w0, t0 = back.instrument_arrays(a)
    pred = back.predictor(back.fallback_sets[0])
    if hasattr(pred, "reset"):
        pred.reset()
    w_nan = w.copy()
    w_nan[:, back.sensor_names.index(sorted(back.fallback_sets[0])[0])] = np.nan
    dev, half = pred.predict(w_nan, t, w0, t0, time_s=a.time_s)
    assert dev.shape == (len(w), 3) and np.isfinite(dev).all() and np.isfinite(half).all()
    assert np.asarray(pred.expected_rms_error_um).shape == (3,)
    if back.model_type != "dynamic":
        # per-frame Z positions (NaN: the description's) give each frame its own Z's chain
        zs = np.resize([np.nan, 0.0, 300.0, 150.0], len(w))
        pred.reset() if hasattr(pred, "reset") else None
        mixed = pred.predict(w, t, w0, t0, time_s=a.time_s, z_axis_mm=zs)
        for z in (np.nan, 0.0, 300.0, 150.0):
            pred.reset() if hasattr(pred, "reset") else None
            alone = pred.predict(w, t, w0, t0, time_s=a.time_s, z_axis_mm=None if np.isnan(z) else z)
            rows = np.isnan(zs) if np.isnan(z) else zs == z
            for got, want in zip(mixed, alone):
                np.testing.assert_allclose(got[rows], want[rows], rtol=1e-12, atol=1e-12)
        assert not np.array_equal(mixed[0][zs == 0.0], mixed[0][zs == 300.0])
    # Issue 13 deliver 1: every type records the deviations it was fitted on, per axis and
    # campaign, and bounds the runtime's correction by them.
    refs = [
        campaigns[n].aligned(zero_window_s=back.zero_window_s).reference_um for n in ("thermal-a", "static-y")
    ]
    for run, ref in zip(d["training"]["campaigns"], refs):
        np.testing.assert_allclose(run["deviation_low_um"], ref.min(axis=0))
        np.testing.assert_allclose(run["deviation_high_um"], ref.max(axis=0))
    peak = np.abs(np.vstack(refs)).max(axis=0)
    np.testing.assert_allclose(back.max_correction_um, back.ENVELOPE_MARGIN * peak)


def test_dynamic_predictor_streams_exactly_like_the_offline_path(campaigns):
    model = DynamicModel(stepwise=False).fit([campaigns["thermal-a"]])
    a = campaigns["thermal-b"].aligned()
    w, t, w0, t0 = model.instrument_arrays(a)
    p = model.predictor()
    p.reset()
    whole, _ = p.predict(w, t, w0, t0, time_s=a.time_s)
    p.reset()
    parts = [
        p.predict(w[s], t[s], w0, t0, time_s=a.time_s[s])[0]
        for s in (slice(0, 7), slice(7, 300), slice(300, None))
    ]
    np.testing.assert_allclose(np.vstack(parts), whole, atol=1e-9)
    offline, _ = model.predict_interval(campaigns["thermal-b"])
    np.testing.assert_allclose(offline, whole, atol=1e-9)
    # The filter itself: the input is held at each sample's value over the interval ending there,
    # so a step that arrives at t = 1 s reaches 1 - exp(-1) one time constant after t = 0.
    y, _ = first_order_filter(np.r_[0.0, np.ones(100)][:, None], np.arange(101.0), 50.0)
    assert y[50, 0] == pytest.approx(1 - np.exp(-1), rel=1e-9)


def test_hybrid_keeps_the_physics_where_regression_cannot_extrapolate(campaigns):
    train = [campaigns["thermal-a"], campaigns["static-y"]]
    hybrid = HybridModel(features="eq13").fit(train)
    mra = MRAModel(features="eq13").fit(train)
    # static-xyz has X forces and static-y-z300 another lever arm: neither is in the training set.
    for name, axis in (("static-xyz", "dx"), ("static-y-z300", "dy")):
        mh, _, _ = _metrics(hybrid, campaigns[name])
        mm, _, _ = _metrics(mra, campaigns[name])
        assert mh["axes"][axis]["rms_error_um"] < 0.5 * mm["axes"][axis]["rms_error_um"], name
    # Held-out thermal campaign (compressed to 3 h, so smaller and faster than the 36 h one):
    # the dominant axis dz is compensated, and the interval is not a blanket.
    m, _, _ = _metrics(hybrid, campaigns["thermal-b"])
    dz = m["axes"]["dz"]
    assert dz["peak_um"] > 5 and dz["compensation_ratio"] > 0.85
    assert 0.5 <= dz["pi95_coverage"] <= 1.0 and dz["pi95_mean_halfwidth_um"] < 0.2 * dz["peak_um"]


def test_v1_model_file_is_migrated(campaigns, tmp_path):
    model = MRAModel(features="eq13").fit([campaigns["thermal-a"]])
    d = model.to_dict()
    d["schema_version"] = 1
    for key in ("uncertainty", "z_axis_mm"):
        d.pop(key)
    old = tmp_path / "v1.json"
    old.write_text(json.dumps(d))
    back = load_model(old)
    assert back.to_dict()["schema_version"] == 2
    np.testing.assert_allclose(back.predict(campaigns["thermal-b"]), model.predict(campaigns["thermal-b"]))


def run(*args):
    return cli(*args)


def test_cli_fit_model_types_and_validate_prints_coverage(campaigns, tmp_path):
    a, s, b = (campaigns[n].path for n in ("thermal-a", "static-y", "thermal-b"))
    for kind in ("kinematic", "hybrid", "calibrated"):
        out = tmp_path / f"{kind}.json"
        r = run("fit", a, s, "--model", kind, "-o", out)
        assert r.returncode == 0, r.stderr
        assert f"({kind}) written" in r.stdout
        r = run("validate", out, b)
        assert r.returncode == 0, r.stderr
        assert "PI95 cover" in r.stdout
    r = run("fit", a, "--model", "hybrid", "--features", "eq11", "-o", tmp_path / "x.json")
    assert r.returncode == 2 and r.stderr.startswith("error: <command line>") and "Traceback" not in r.stderr
    r = run("fit", a, "--model", "neural", "-o", tmp_path / "x.json")
    assert r.returncode == 2 and "unknown model type" in r.stderr


def test_cli_compare_writes_ranked_tables(campaigns, tmp_path):
    csv_path, json_path = tmp_path / "c.csv", tmp_path / "c.json"
    r = run(
        "compare",
        "--train",
        campaigns["thermal-a"].path,
        "--train",
        campaigns["static-y"].path,
        "--test",
        campaigns["thermal-b"].path,
        "--csv",
        csv_path,
        "--json",
        json_path,
    )
    assert r.returncode == 0, r.stderr
    result = json.loads(json_path.read_text())
    names = {row["name"] for row in result["rows"]}
    assert {
        "mra eq11",
        "mra eq13",
        "mra eq12",
        "mra eq13 stepwise",
        "ridge eq13",
        "pls eq13",
        "dynamic eq13+lp",
        "kinematic",
        "hybrid eq13",
        "calibrated eq13",
    } <= names
    lines = csv_path.read_text().splitlines()
    assert lines[0].startswith("axis,rank,name")
    dz = [ln.split(",") for ln in lines[1:] if ln.startswith("dz,")]
    errs = [float(x[5]) for x in dz]
    assert errs == sorted(errs) and "== dz" in r.stdout


@pytest.mark.parametrize(
    "make",
    [
        lambda: KinematicModel(),
        lambda: HybridModel(features="eq13"),
        lambda: CalibratedModel(features="eq13"),
    ],
)
def test_runtime_pipeline_gives_the_offline_numbers(campaigns, tmp_path, make):
    from fbgcomp.runtime.pipeline import HEALTH_ZEROING, Pipeline

    model = load_model(make().fit([campaigns["thermal-a"], campaigns["static-y"]]).save(tmp_path / "m.json"))
    c = campaigns["static-xyz"]
    a = c.aligned(zero_window_s=model.zero_window_s)
    w, t, _, _ = model.instrument_arrays(a)
    pipe = Pipeline(model)
    out = [
        pipe.process(
            a.time_s[i : i + 37],
            w[i : i + 37],
            np.ones(w[i : i + 37].shape, np.int8),
            np.zeros(w[i : i + 37].shape, np.int8),
            t[i : i + 37],
        )
        for i in range(0, len(w), 37)
    ]
    dev = np.concatenate([r.deviation_um for r in out])
    half = np.concatenate([r.half_width_um for r in out])
    ok = np.concatenate([r.health for r in out]) != HEALTH_ZEROING
    assert ok.sum() > 0.9 * len(ok)
    # The runtime's zero state comes from the stream on the reference clock; with it, the
    # offline predictor gives the same numbers (the lateral gains of ~56 µm/µm would turn the
    # small difference between the two zero-state conventions into µm).
    p = model.predictor()
    if hasattr(p, "reset"):
        p.reset()
    offline, offline_half = p.predict(w, t, pipe.wavelength_zero_nm, pipe.temperature_zero_C)
    np.testing.assert_allclose(dev[ok], offline[ok], atol=1e-6)
    np.testing.assert_allclose(half[ok], offline_half[ok], atol=1e-6)


# ------------------------------------------------------------------ calibrated force closure
def _box(machine, width_mm, wall_mm):
    """The default machine with a square ram box (and housing) of another size; probes moved
    onto the new walls."""
    from fbgcomp.structure.machine import Machine

    d = machine.model_dump()
    d["ram"].update(outer_width_mm=width_mm, outer_depth_mm=width_mm, wall_mm=wall_mm)
    d["housing"].update(width_mm=width_mm, depth_mm=width_mm)
    d["supports"]["shoe_width_mm"] = width_mm
    d["candidate_sensors"] = []
    for p in d["probes"]:
        if p["name"] == "T_bulk":
            p["y_mm"] = width_mm / 2 - wall_mm / 2
        elif p["name"] in ("T_surf", "T_flange"):
            p["x_mm"] = width_mm / 2
    return Machine.model_validate(d)


@pytest.fixture(scope="session")
def closure_campaigns(tmp_path_factory):
    """Full-length thermal-36h + static-y (+ static-xyz) on a coarse twin (0.5) of the default
    box and of a slender one. The thermal campaign is the built-in one, not compressed: the
    thermal correction fitted on a 3 h compression is poorly conditioned and leaves ~10 µm of
    spurious bending on the static plateaus (measured), which is not what this checks."""
    root = tmp_path_factory.mktemp("closure")
    out = {}
    for box, machine in (("default", load_machine()), ("slender", _box(load_machine(), 150.0, 10.0))):
        twin = Twin(machine, resolution=0.5)
        names = ("thermal-36h", "static-y", "static-xyz") if box == "default" else ("thermal-36h", "static-y")
        for i, name in enumerate(names):
            c, _ = simulate(machine, load_scenario(name), seed=30 + i, twin=twin)
            out[box, name] = read_campaign(write_campaign(c, root / f"{box}-{name}"))
        out[box] = machine
    return out


def _plateau_pct(model, campaign):
    pred, _ = model.predict_interval(campaign)
    a = campaign.aligned(zero_window_s=model.zero_window_s)
    m = static_level_metrics(a.loads_N, a.reference_um, pred)
    return np.array([m["axes"][ax]["error_pct_of_deflection"] for ax in ("dx", "dy")])


def test_calibrated_closure_recovers_unseen_x_loads_from_y_loads(closure_campaigns):
    cc = closure_campaigns
    train = [cc["default", "thermal-36h"], cc["default", "static-y"]]
    cal = CalibratedModel(cc["default"], stepwise=False).fit(train)
    pct_cal = _plateau_pct(cal, cc["default", "static-xyz"])
    # Measured: dx 1.21 %, dy 0.43 %; what is left on dx is mostly the test campaign's zero
    # state (mean of 10 samples with ~10 µm of lateral noise each), an offset on every plateau.
    assert np.all(pct_cal < 1.5), pct_cal
    # With a zero state averaged over 50 s (the bench holds each level 60 s) the closure itself
    # shows: measured dx 0.79 %, dy 0.62 % against the fit-free closure's 2.2 %, 3.5 %.
    cal50 = CalibratedModel(cc["default"], stepwise=False, zero_window_s=50.0).fit(train)
    hyb50 = HybridModel(cc["default"], stepwise=False, zero_window_s=50.0).fit(train)
    pct_cal50 = _plateau_pct(cal50, cc["default", "static-xyz"])
    pct_hyb50 = _plateau_pct(hyb50, cc["default", "static-xyz"])
    assert np.all(pct_cal50 < 1.0), pct_cal50
    assert np.all(pct_cal50 < 0.5 * pct_hyb50), (pct_cal50, pct_hyb50)
    c = cal.calibration_
    assert c["shared_axes"] and c["parameters"] == ["bending", "shear"]
    assert c["campaigns"] == [
        {"name": cc["default", "static-y"].meta.name, "z_axis_mm": 0.0, "n_plateaus": c["n_plateaus"]}
    ]
    # One Z position: only the shear (the larger compliance) is pinned by the loads; the
    # bending factor stays at its prior's width and the summary says so.
    assert c["identified"] == [False, True]
    assert c["standard_errors"][0] > 0.4 and c["standard_errors"][1] < 0.1
    assert "not separated by the loads" in cal.summary()


def test_calibrated_factors_are_near_one_where_the_beam_closure_holds(closure_campaigns):
    cc = closure_campaigns
    cal = CalibratedModel(cc["slender"], stepwise=False).fit(
        [cc["slender", "thermal-36h"], cc["slender", "static-y"]]
    )
    f = dict(zip(cal.calibration_["parameters"], cal.calibration_["factors"]))
    se = dict(zip(cal.calibration_["parameters"], cal.calibration_["standard_errors"]))
    # A slender box bends like a beam: the fitted shear compliance is the nominal one within
    # its standard error (measured 0.96 ± 0.17); the default box's webs are 3-5 % softer.
    assert abs(f["shear"] - 1.0) < max(2 * se["shear"], 0.1), (f, se)
    assert abs(f["bending"] - 1.0) < 0.1


def test_calibrated_without_loads_keeps_the_nominal_closure(closure_campaigns):
    cc = closure_campaigns
    cal = CalibratedModel(cc["default"], stepwise=False).fit([cc["default", "thermal-36h"]])
    assert cal.calibration_["factors"] == [1.0, 1.0]
    assert cal.calibration_["status"].startswith("not calibrated")
    hyb = HybridModel(cc["default"], stepwise=False).fit([cc["default", "thermal-36h"]])
    c = cc["default", "static-y"]
    np.testing.assert_allclose(cal.predict_interval(c)[0], hyb.predict_interval(c)[0], atol=1e-9)


def test_closure_factors_are_per_axis_unless_the_sections_are_square():
    from fbgcomp.models.calibrated import closure_parameter_groups
    from fbgcomp.structure.machine import Machine

    assert list(closure_parameter_groups(load_machine())) == ["bending", "shear"]
    d = load_machine().model_dump()
    d["ram"]["outer_depth_mm"] = 300.0
    d["candidate_sensors"] = []
    for p in d["probes"]:
        if p["name"] == "T_bulk":
            p["y_mm"] = 140.0
    groups = closure_parameter_groups(Machine.model_validate(d))
    assert groups == {k: (k,) for k in ("bending_x", "bending_y", "shear_x", "shear_y")}


def test_closure_factor_fit_leaves_unexcited_factors_at_their_prior():
    from fbgcomp.models.calibrated import fit_closure_factors

    rng = np.random.default_rng(0)
    load = np.repeat(np.arange(5.0), 2)  # Y plateaus only, two campaigns
    X = np.zeros((10, 4))  # bending_x, bending_y, shear_x, shear_y
    X[:, 1], X[:, 3] = 20.0 * load, 170.0 * load
    offset = np.tile([0, 1], 5)
    y = X[:, 1] * 1.0 + X[:, 3] * 1.05 + np.where(offset, 3.0, -2.0) + 0.5 * rng.standard_normal(10)
    f, _cov, sd, ratio = fit_closure_factors(X, y, offset, prior_sd=0.5)
    assert (
        f[0] == pytest.approx(1.0)
        and f[2] == pytest.approx(1.0)
        and ratio[0] == pytest.approx(1.0)
        and ratio[2] == pytest.approx(1.0)
    )
    # The Y pair is only known as a weighted sum: 20 f_by + 170 f_sy ~= 20 + 178.5
    assert 20 * f[1] + 170 * f[3] == pytest.approx(198.5, abs=0.5)
    assert sd < 2.0


# ------------------------------------------------------------------ scikit-learn estimator contract
ESTIMATORS = {
    "mra": MRAModel,
    "kinematic": KinematicModel,
    "hybrid": HybridModel,
    "calibrated": CalibratedModel,
    "dynamic": DynamicModel,
    "physical": PhysicalModel,
}


@pytest.mark.parametrize("kind", list(ESTIMATORS))
def test_every_model_type_is_a_scikit_learn_estimator(kind):
    """Every model type follows scikit-learn's estimator contract: ``sklearn.base.clone`` works,
    ``get_params`` / ``set_params`` round-trip, hyper-parameters are stored unchanged in
    ``__init__`` and nothing else is set there.

    Of ``sklearn.utils.estimator_checks`` this runs the checks that take the estimator alone:
    ``check_get_params_invariance``, ``check_set_params`` and ``check_no_attributes_set_in_init``.
    ``check_dont_overwrite_parameters`` and every other check fit on random numeric arrays
    (``X`` (n, 3), integer ``y``); these estimators fit on campaigns (time series of wavelengths,
    temperatures and reference deviations, aligned by their clocks), so those checks do not apply
    as written: :func:`test_fit_sets_only_learned_state` applies the first one's rule to a fit on
    campaigns instead.
    """
    cls = ESTIMATORS[kind]
    est = cls()
    assert est.model_type == kind
    copy = clone(est)
    assert type(copy) is cls and copy is not est and copy.get_params() == est.get_params()
    params = est.get_params()
    assert est.set_params(**params) is est and est.get_params() == params
    est.set_params(zero_window_s=5.0)
    assert est.zero_window_s == 5.0 and clone(est).get_params()["zero_window_s"] == 5.0
    with pytest.raises(ValueError, match="invalid parameter"):
        est.set_params(no_such_parameter=1)
    for check in (check_get_params_invariance, check_set_params, check_no_attributes_set_in_init):
        check(cls.__name__, cls())
    # a tuple hyper-parameter is stored as given (clone checks identity), not converted
    if "taus_s" in params:
        taus = [600.0, 3600.0]
        assert cls(taus_s=taus).taus_s is taus and clone(cls(taus_s=taus)).taus_s == taus


@pytest.mark.parametrize("kind", list(ESTIMATORS))
def test_fit_sets_only_learned_state(campaigns, kind):
    """``check_dont_overwrite_parameters``' rule on a fit on campaigns: ``fit`` adds or changes
    no public attribute other than learned state (trailing underscore), and returns the model."""
    est = clone(ESTIMATORS[kind]())
    before = dict(vars(est))
    assert est.fit([campaigns["thermal-a"], campaigns["static-y"]]) is est
    after = vars(est)
    public = [k for k in after if not k.startswith("_") and not k.endswith("_")]
    assert [k for k in public if k not in before] == []
    assert [k for k in public if after[k] is not before[k]] == []
    assert "sensors_" in after and "training_" in after


def test_unfitted_kinematic_model_has_no_learned_state():
    """The kinematic model's chain is built by ``fit`` (which needs no campaign), not lazily."""
    model = KinematicModel()
    assert not [k for k in vars(model) if k.endswith("_")]
    with pytest.raises(AttributeError, match="not fitted"):
        model.predictor()
    assert model.fit().predictor().sensor_names == ["S1", "S2", "S3", "S4", "S5"]
