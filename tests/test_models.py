import json

import numpy as np
import pandas as pd
import pytest
from scipy import stats

from fbgcomp.bench.synthetic import linear_truth_campaign
from fbgcomp.errors import InputError
from fbgcomp.io.campaign import read_campaign, write_campaign
from fbgcomp.models.features import TemperatureRoles, candidate_terms, resolve_roles
from fbgcomp.models.metrics import validation_metrics
from fbgcomp.models.modelfile import SCHEMA_VERSION
from fbgcomp.models.mra import MRAModel
from fbgcomp.models.registry import load_model
from fbgcomp.units import AXES


@pytest.fixture(scope="session")
def truth_campaign(tmp_path_factory):
    c, truth = linear_truth_campaign("truth", seed=1, duration_s=4 * 3600, noise_um=0.05)
    path = write_campaign(c, tmp_path_factory.mktemp("c") / "truth")
    return read_campaign(path), truth


def _slope_z_scores(model, truth):
    """(estimate - truth) / standard error of every slope (the zero state moves the intercept)."""
    z = []
    for a in AXES:
        fit = model.axes_[a]
        for name, est, se in zip(fit.terms, fit.params, fit.bse):
            if name != "const":
                z.append((est - truth["coefficients"][a].get(name, 0.0)) / se)
    return np.array(z)


def test_every_true_coefficient_inside_its_95pct_ci(truth_campaign):
    # 24 slopes: asking all 24 individual 95 % intervals to hold would fail by chance 71 % of
    # the time, so a single campaign is judged with simultaneous (Bonferroni) 95 % intervals ...
    campaign, truth = truth_campaign
    model = MRAModel(features="eq13", fallbacks="none").fit(campaign)
    z = _slope_z_scores(model, truth)
    assert len(z) == 3 * 8
    df = model.axes_["dx"].df_resid
    assert np.all(np.abs(z) <= stats.t.ppf(1 - 0.025 / len(z), df)), z


def test_95pct_confidence_intervals_cover_the_truth_95pct_of_the_time():
    # ... and the individual 95 % intervals are checked for what they promise: coverage.
    z = np.concatenate(
        [
            _slope_z_scores(MRAModel(features="eq13", fallbacks="none").fit(c), truth)
            for c, truth in (linear_truth_campaign("rep", seed=100 + i, duration_s=1800) for i in range(20))
        ]
    )
    coverage = np.mean(np.abs(z) <= 1.96)
    assert 0.92 <= coverage <= 0.98, coverage  # 480 draws: binomial SD 1 %
    # The 24 slopes of one campaign share its design, so their z-scores are correlated and the
    # sample mean and SD spread more than for 480 independent draws: loose bounds on those two.
    assert abs(np.mean(z)) < 0.25 and 0.8 < np.std(z) < 1.25


def test_stepwise_selects_exactly_the_true_terms(truth_campaign):
    campaign, truth = truth_campaign
    for direction in ("forward", "backward", "both"):
        model = MRAModel(
            features="eq13", stepwise=True, direction=direction, p_enter=1e-4, p_remove=1e-3, fallbacks="none"
        ).fit(campaign)
        for a in AXES:
            want = {k for k, v in truth["coefficients"][a].items() if k != "const" and v != 0}
            got = set(model.axes_[a].terms) - {"const"}
            assert got == want, (direction, a, got, want)
            if direction != "backward":
                assert [h["term"] for h in model.axes_[a].history if h["action"] == "enter"]


def test_validation_on_a_held_out_campaign_is_at_noise_level(truth_campaign):
    campaign, _truth = truth_campaign
    model = MRAModel(features="eq13").fit(campaign)
    other, _ = linear_truth_campaign("other", seed=7, duration_s=2 * 3600, noise_um=0.05)
    pred, half = model.predict_interval(other)
    ref = other.aligned().reference_um
    m = validation_metrics(ref, pred, half)
    for a in AXES:
        assert m["axes"][a]["rms_error_um"] < 0.08
        assert 0.90 < m["axes"][a]["pi95_coverage"] <= 1.0
        assert m["axes"][a]["compensation_ratio"] > 0.95


def test_model_file_round_trip(truth_campaign, tmp_path):
    campaign, _ = truth_campaign
    model = MRAModel(features="eq12", stepwise=True, fallbacks="lto").fit(campaign)
    path = model.save(tmp_path / "model.json")
    d = json.loads(path.read_text())
    assert (
        d["schema_version"] == SCHEMA_VERSION and d["model_type"] == "mra" and d["model_id"] == model.model_id
    )
    assert d["zero_state"] == {"method": "mean_of_first_window", "window_s": 10.0}
    assert [s["name"] for s in d["sensors"]] == ["S1", "S2", "S3", "S4", "S5"]
    assert d["training"]["campaigns"][0]["name"] == "truth"
    loaded = load_model(path)
    assert loaded.model_id == model.model_id
    np.testing.assert_array_equal(loaded.predict(campaign), model.predict(campaign))
    assert len(loaded.fallback_sets) == 5 + 10
    for a in AXES:
        assert loaded.axes_[a].terms == model.axes_[a].terms
        np.testing.assert_array_equal(loaded.axes_[a].bse, model.axes_[a].bse)


def test_fallback_without_a_sensor_ignores_its_wavelength(truth_campaign):
    campaign, _ = truth_campaign
    model = MRAModel(features="eq13").fit(campaign)
    aligned = campaign.aligned()
    w, t, w0, t0 = model.instrument_arrays(aligned)
    p = model.predictor(exclude={"S3"})
    assert all("S3" not in term for term in p.terms)
    broken = w.copy()
    broken[:, 2] = np.nan
    dev, half = p.predict(broken, t, w0, t0)
    assert np.isfinite(dev).all() and np.isfinite(half).all()
    full, _ = model.predictor().predict(w, t, w0, t0)
    # dy depends on S3 in the truth: the fallback is worse there but still usable.
    assert np.sqrt(np.mean((dev - full) ** 2, axis=0))[1] > 0
    with pytest.raises(KeyError):
        model.predictor(exclude={"S3", "S4"})


def test_predictor_matches_model_predict_sample_by_sample(truth_campaign):
    campaign, _ = truth_campaign
    model = MRAModel(features="eq12").fit(campaign)
    aligned = campaign.aligned()
    w, t, w0, t0 = model.instrument_arrays(aligned)
    batch, _ = model.predictor().predict(w[:50], t[:50], w0, t0)
    single = np.vstack([model.predictor().predict(w[i], t[i], w0, t0)[0] for i in range(50)])
    np.testing.assert_allclose(single, batch, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(model.predict(campaign)[:50], batch, rtol=1e-12)


def test_fit_on_arrays_matches_fit_on_campaign(truth_campaign):
    campaign, _ = truth_campaign
    model = MRAModel(features="eq13", fallbacks="none").fit(campaign)
    aligned = campaign.aligned()
    base = model._feature_map().base(*model.instrument_arrays(aligned))
    X = pd.DataFrame(base, columns=model._feature_map().base_names)
    other = MRAModel(features="eq13", fallbacks="none").fit(X, aligned.reference_um)
    for a in AXES:
        np.testing.assert_allclose(other.axes_[a].params, model.axes_[a].params, rtol=1e-10)
    np.testing.assert_allclose(other.predict(X), model.predict(campaign), rtol=1e-9, atol=1e-9)


def test_model_with_sensors_the_campaign_lacks_is_a_clear_error(truth_campaign, tmp_path):
    campaign, _ = truth_campaign
    path = MRAModel(features="eq11").fit(campaign).save(tmp_path / "m.json")
    # S1 renamed S9 throughout (its terms and fallbacks too): a consistent model of other sensors
    d = json.loads(path.read_text().replace('"S1"', '"S9"').replace("dL_S1", "dL_S9"))
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps(d))
    with pytest.raises(InputError, match="sensor S9"):
        load_model(bad).predict(campaign)
    # renamed in the sensor list only, the file disagrees with itself and is refused on loading
    d = json.loads(path.read_text())
    d["sensors"][0]["name"] = "S9"
    bad.write_text(json.dumps(d))
    with pytest.raises(InputError, match=r"field fallbacks\[0\].exclude"):
        load_model(bad)


@pytest.mark.parametrize(
    "content, match",
    [
        ("{not json", "not a JSON model file"),
        ('{"format": "other"}', "not an fbgcomp model file"),
        ('{"format": "fbgcomp-model", "schema_version": 99}', "newer than this fbgcomp"),
        (
            f'{{"format": "fbgcomp-model", "schema_version": {SCHEMA_VERSION}, "model_type": "mra"}}',
            "missing field",
        ),
    ],
)
def test_bad_model_files(tmp_path, content, match):
    p = tmp_path / "m.json"
    p.write_text(content)
    with pytest.raises(InputError, match=match) as exc:
        load_model(p)
    assert str(p) in exc.value.one_line()


def test_candidate_terms_of_each_feature_set():
    s = ["S1", "S2"]
    assert candidate_terms("eq11", s) == ["dL_S1", "dL_S2"]
    assert candidate_terms("eq13", s) == ["dL_S1", "dL_S2", "dT_bulk", "dT_surf", "dT_flange"]
    eq12 = candidate_terms("eq12", s)
    assert len(eq12) == 2 + 3 + 6
    assert "dT_bulk^2" in eq12 and "dT_surf*dT_flange" in eq12


def test_static_plateau_metrics_average_out_noise_and_skip_ramps():
    from fbgcomp.models.metrics import load_plateaus, static_level_metrics

    t = np.arange(0, 300.0)
    fy = np.interp(
        t, [0, 60, 62, 120, 122, 180, 182, 240, 242, 300], [0, 0, 1000, 1000, 2000, 2000, 1000, 1000, 0, 0]
    )
    loads = np.column_stack([np.zeros_like(t), fy, np.zeros_like(t)])
    rng = np.random.default_rng(0)
    ref = np.column_stack([np.zeros_like(t), 0.2 * fy, np.zeros_like(t)])
    pred = ref * 1.02 + rng.normal(0, 5.0, ref.shape)  # 2 % gain error + noise
    runs = load_plateaus(loads)
    assert len(runs) == 5 and all(len(r) >= 50 for r in runs)
    assert all(np.ptp(fy[r]) == 0 for r in runs)  # no ramp sample inside a plateau
    m = static_level_metrics(loads, ref, pred)
    assert m["n_levels"] == 5
    assert m["axes"]["dy"]["max_plateau_deflection_um"] == pytest.approx(400.0)
    assert 1.0 < m["axes"]["dy"]["error_pct_of_deflection"] < 3.0  # the gain error, not the noise


def test_scikit_learn_clone_and_params(truth_campaign):
    from sklearn.base import clone

    campaign, _ = truth_campaign
    model = MRAModel(features="eq12", stepwise=True, p_enter=0.01).fit(campaign)
    copy = clone(model)
    assert copy.get_params() == model.get_params()
    assert not hasattr(copy, "axes_")  # learned state is not cloned
    copy.set_params(features="eq11", stepwise=False)
    assert copy.fit(campaign).axes_["dx"].terms == ["const", "dL_S1", "dL_S2", "dL_S3", "dL_S4", "dL_S5"]
    with pytest.raises(ValueError, match="invalid parameter"):
        copy.set_params(nonsense=1)
    assert "MRAModel(features='eq11'" in repr(copy)


def test_balanced_pooling_keeps_a_short_informative_campaign_from_being_diluted():
    """Errors in variables: a long campaign whose dL_S3 - dL_S4 is pure sensor noise pooled
    with a short one where it carries the signal. OLS shrinks the gain; balancing does not."""
    coef = {"dx": {}, "dy": {"dL_S3": 30.0, "dL_S4": -30.0}, "dz": {}}
    quiet = {"dx": {}, "dy": {}, "dz": {}}
    short, _ = linear_truth_campaign(
        "short", seed=21, duration_s=600, coefficients=coef, wavelength_noise_nm=1e-3, settle_s=10
    )
    long_, _ = linear_truth_campaign(
        "long", seed=22, duration_s=30 * 3600, coefficients=quiet, wavelength_noise_nm=1e-3, settle_s=10
    )
    # the long campaign's elongations: noise only (no signal in S3/S4)
    fbg = long_.fbg.copy()
    rng = np.random.default_rng(3)
    for s, lam0 in (("S3", 1540.0), ("S4", 1545.0)):
        fbg[f"{s}_nm"] = lam0 + 1e-3 * rng.standard_normal(len(fbg))
    long_ = type(long_).from_arrays(
        long_.meta, fbg=fbg, temperatures=long_.temperatures, reference=long_.reference
    )
    gains = {}
    for mode in ("samples", "balanced"):
        m = MRAModel(features="eq11", fallbacks="none", campaign_weights=mode).fit([long_, short])
        gains[mode] = dict(zip(m.axes_["dy"].terms, m.axes_["dy"].params))["dL_S3"]
    assert gains["samples"] < 0.9 * 30.0  # attenuated by the pooled noise (~14 %)
    assert gains["balanced"] == pytest.approx(30.0, rel=0.03)  # 29.6: balanced weights keep it


# --------------------------------------------------------------------------------------------
# Autocorrelation-robust inference (issue 12)
# --------------------------------------------------------------------------------------------


def test_mra_inference_is_newey_west_by_default_and_the_naive_one_stays_available(truth_campaign, tmp_path):
    campaign, _ = truth_campaign
    hac = MRAModel(features="eq13", fallbacks="none").fit(campaign)
    naive = MRAModel(features="eq13", fallbacks="none", cov_type="nonrobust").fit(campaign)
    for a in AXES:
        h, n = hac.axes_[a], naive.axes_[a]
        assert h.cov_type == "HAC" and n.cov_type == "nonrobust"
        assert h.hac["maxlags"] >= 1 and h.hac["n_eff"] > 0
        np.testing.assert_allclose(h.params, n.params, rtol=1e-12)  # same estimates
        np.testing.assert_allclose(np.sqrt(np.diag(h.cov)), h.bse, rtol=1e-12)
        assert not np.allclose(h.bse, n.bse)
    assert "HAC inference" in hac.summary() and "Newey-West" in hac.summary()
    assert "nonrobust" in naive.summary()
    # the file keeps the inference; files written before it were naive and load as such
    path = hac.save(tmp_path / "hac.json")
    d = json.loads(path.read_text())
    assert d["inference"]["cov_type"] == "HAC" and d["axes"]["dz"]["cov_type"] == "HAC"
    loaded = load_model(path)
    assert loaded.cov_type == "HAC" and loaded.axes_["dz"].hac == hac.axes_["dz"].hac
    np.testing.assert_array_equal(loaded.predict_interval(campaign)[1], hac.predict_interval(campaign)[1])
    old = tmp_path / "old.json"
    d = json.loads(naive.save(tmp_path / "naive.json").read_text())
    del d["inference"]
    for a in AXES:
        del d["axes"][a]["cov_type"], d["axes"][a]["hac"]
    old.write_text(json.dumps(d))
    again = load_model(old)
    assert again.cov_type == "nonrobust" and again.axes_["dx"].cov_type == "nonrobust"
    np.testing.assert_array_equal(again.axes_["dx"].bse, naive.axes_["dx"].bse)
    with pytest.raises(ValueError, match="cov_type"):
        MRAModel(cov_type="HC0").fit(campaign)


def test_campaigns_are_separate_series_in_fit_and_in_the_distributed_reduction(truth_campaign, tmp_path):
    """fit() ends a series after each campaign, so its HAC statistics equal those of campaigns
    accumulated apart and merged (fbgcomp.models.distributed), with balanced weights."""
    from fbgcomp.models.distributed import accumulate_paths

    campaign, _ = truth_campaign
    other, _ = linear_truth_campaign("other", seed=9, duration_s=1800, noise_um=0.05)
    other_path = write_campaign(other, tmp_path / "other")
    fitted = MRAModel(features="eq13", fallbacks="none", hac_maxlags=64).fit(
        [campaign, read_campaign(other_path)]
    )
    reducer = MRAModel(features="eq13", fallbacks="none", hac_maxlags=64)
    acc, training = accumulate_paths(reducer, [campaign.path, other_path])
    reduced = reducer.fit_factor(acc, training)
    for a in AXES:
        assert fitted.axes_[a].hac["maxlags"] == 64
        np.testing.assert_allclose(reduced.axes_[a].params, fitted.axes_[a].params, rtol=1e-9)
        # The meat is a quadratic form of raw products in the residual: on this near-exact fit
        # (noise 0.05 um on deviations of tens of um) it keeps ~eps (|y| / |e|)^2, about 1e-8.
        np.testing.assert_allclose(reduced.axes_[a].bse, fitted.axes_[a].bse, rtol=1e-6)


def test_stepwise_on_autocorrelated_drift_keeps_fewer_spurious_terms_than_naive_f_tests():
    """Arrays API: dz is a slow linear function of dT_flange and dL_S1 plus an AR(1) drift
    residual (phi 0.995 at 1 s: minutes of memory, as an unmodelled thermal lag leaves); the
    other eq13 regressors are independent slow random walks. Naive partial F tests pick up
    several of them; the default HAC tests select the two true terms."""
    rng = np.random.default_rng(4)
    n = 20000
    t = np.arange(n)
    base = {f"dL_S{i}": np.cumsum(rng.normal(scale=0.01, size=n)) for i in range(2, 6)}
    base["dL_S1"] = np.sin(2 * np.pi * t / 7000.0) + 0.01 * rng.normal(size=n)
    base["dT_bulk"] = np.cumsum(rng.normal(scale=0.02, size=n))
    base["dT_surf"] = np.cumsum(rng.normal(scale=0.02, size=n))
    base["dT_flange"] = 5 * (1 - np.cos(2 * np.pi * t / 11000.0)) + 0.05 * rng.normal(size=n)
    X = pd.DataFrame(
        {k: base[k] for k in ["dL_S1", "dL_S2", "dL_S3", "dL_S4", "dL_S5", "dT_bulk", "dT_surf", "dT_flange"]}
    )
    drift = np.zeros(n)
    shocks = rng.normal(scale=0.05, size=n)
    for i in range(1, n):
        drift[i] = 0.995 * drift[i - 1] + shocks[i]
    dz = 3.0 * base["dL_S1"] - 2.5 * base["dT_flange"] + drift
    y = np.column_stack([drift, drift, dz])
    chosen = {}
    for cov_type in ("nonrobust", "HAC"):
        m = MRAModel(features="eq13", stepwise=True, fallbacks="none", cov_type=cov_type).fit(X, y)
        chosen[cov_type] = set(m.axes_["dz"].terms) - {"const"}
    assert {"dL_S1", "dT_flange"} <= chosen["HAC"]
    spurious = {k: len(v - {"dL_S1", "dT_flange"}) for k, v in chosen.items()}
    assert spurious["HAC"] < spurious["nonrobust"], chosen
    assert spurious["HAC"] <= 1, chosen


def _renamed_probes(campaign, names):
    """The campaign with its probes renamed (``names``: old -> new) in every file."""
    meta = campaign.meta.model_dump()
    for p in meta["temperature_probes"]:
        p["name"] = names.get(p["name"], p["name"])
    for s in meta["sensors"]:
        if s.get("temperature_probe"):
            s["temperature_probe"] = names.get(s["temperature_probe"], s["temperature_probe"])
    return campaign.replaced(
        meta=meta,
        temperatures=campaign.temperatures.rename(columns={f"{o}_C": f"{n}_C" for o, n in names.items()}),
    )


def test_eq13_roles_follow_a_ram_whose_probes_do_not_carry_the_paper_names(truth_campaign, tmp_path):
    # A data sheet that calls its probes P_wall, P_skin, P_spindle, P_air: eq. 13 failed with
    # "model needs temperature probe T_flange" (ridge and PLS with a ValueError) for every type
    # but the physical and kinematic ones. Renaming the probes must not change the model.
    campaign, _ = truth_campaign
    names = {"T_bulk": "P_wall", "T_surf": "P_skin", "T_flange": "P_spindle"}
    renamed = _renamed_probes(campaign, names)
    assert not {"T_bulk", "T_surf", "T_flange"} & set(renamed.probe_names)
    ref = MRAModel(features="eq13").fit(campaign)
    model = MRAModel(features="eq13").fit(renamed)
    assert model.roles_ == TemperatureRoles(bulk="P_wall", surf="P_skin", flange="P_spindle")
    loaded = load_model(model.save(tmp_path / "m.json"))
    np.testing.assert_allclose(loaded.predict(renamed), ref.predict(campaign), rtol=0, atol=1e-9)
    # explicit roles win over the names
    swapped = MRAModel(features="eq13", roles={"bulk": "P_skin", "surf": "P_wall", "flange": "P_spindle"})
    assert swapped.fit(renamed).roles_.bulk == "P_skin"


def test_roles_by_position_in_the_description_then_by_name_then_what_is_left():
    from fbgcomp.structure import load_machine

    machine = load_machine()  # the built-in ram: T_bulk in the wall, T_surf on it, T_flange below
    pos = {p.name: p for p in machine.probes}
    renamed = machine.model_copy(
        update={
            "probes": [
                p.model_copy(
                    update={"name": {"T_bulk": "A", "T_surf": "B", "T_flange": "C"}.get(p.name, p.name)}
                )
                for p in machine.probes
            ]
        }
    )
    assert "T_bulk" in pos and "T_flange" in pos
    # by position, whatever the names and their order
    assert resolve_roles(["C", "B", "A"], renamed) == TemperatureRoles(bulk="A", surf="B", flange="C")
    # by name without a description
    assert resolve_roles(["air", "head_T", "skin", "core"]) == TemperatureRoles(
        bulk="core", surf="skin", flange="head_T"
    )
    # no housing probe: the air plays the flange, the last resort
    assert resolve_roles(["T_bulk", "T_surf", "T_amb"]) == TemperatureRoles(flange="T_amb")
    # nothing fits by position or name: the campaign's order, probes before the air
    assert resolve_roles(["T_room", "P1", "P2", "P3"]) == TemperatureRoles(bulk="P1", surf="P2", flange="P3")
    with pytest.raises(ValueError, match="no temperature probe is left for the"):
        resolve_roles(["P1", "P2"])


def test_every_model_takes_the_same_housing_probe():
    # Three rules used to decide which probe is "on the housing" (nearest its centre in the
    # kinematic chain, z < 0 then a name in the physical model, z <= 0 and the campaign's order in
    # eq. 13's roles); with two housing probes they picked different ones.
    from fbgcomp.kinematics import housing_probe
    from fbgcomp.models.physical.thermal import housing_probe_names
    from fbgcomp.structure import load_machine

    machine = load_machine()
    h = machine.housing
    extra = machine.probes[0].model_copy(
        update={"name": "P_core", "kind": "point", "x_mm": 10.0, "y_mm": 0.0, "z_mm": -h.height_mm / 2}
    )
    two = machine.model_copy(update={"probes": [*machine.probes, extra]})
    names = ["T_bulk", "T_surf", "T_flange", "P_core", "T_amb"]
    # nearest the housing's centre first; the flange face (z = 0) counts as the housing
    assert two.housing_probe_names() == ["P_core", "T_flange"]
    assert housing_probe(two) == "P_core"
    assert housing_probe_names(names, two) == ["P_core", "T_flange"]
    renamed = {"T_flange": "A", "P_core": "B"}
    probes = [p.model_copy(update={"name": renamed.get(p.name, p.name)}) for p in two.probes]
    described = two.model_copy(update={"probes": probes})
    assert resolve_roles(["T_bulk", "T_surf", "A", "B", "T_amb"], described).flange == "B"
    # a probe in the ram wall is never a housing probe
    assert "T_bulk" not in two.housing_probe_names()
