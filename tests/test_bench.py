"""Virtual test bench, FE calibration, resolution check and the demo, on a coarse twin."""

import json
import subprocess
import sys

import numpy as np
import pytest

from fbgcomp import optics
from fbgcomp.bench.virtual import load_scenario, simulate, true_response
from fbgcomp.errors import InputError
from fbgcomp.io.campaign import read_campaign, write_campaign
from fbgcomp.models.fe_calibrated import fe_calibrate, resolution_report
from fbgcomp.structure import Twin, load_machine

COARSE = 0.4


@pytest.fixture(scope="session")
def machine():
    return load_machine(None)


@pytest.fixture(scope="session")
def twin(machine):
    return Twin(machine, resolution=COARSE)


@pytest.fixture(scope="session")
def static_y(machine, twin, tmp_path_factory):
    campaign, truth = simulate(machine, load_scenario("static-y"), seed=3, twin=twin)
    path = write_campaign(campaign, tmp_path_factory.mktemp("bench") / "static-y")
    return read_campaign(path), truth


def _rate(frame):
    return float(np.median(np.diff(frame["time_s"])))


@pytest.mark.slow
def test_static_campaign_is_valid_with_independent_clocks(static_y):
    c, truth = static_y
    assert c.meta.kind == "static" and c.meta.name == "static-y"
    assert c.meta.sensor_names == ["S1", "S2", "S3", "S4", "S5"]
    assert _rate(c.fbg) == pytest.approx(0.1) and _rate(c.reference) == pytest.approx(1.0)
    assert _rate(c.temperatures) == pytest.approx(10.0) and _rate(c.loads) == pytest.approx(0.5)
    assert c.reference["time_s"].iloc[0] == pytest.approx(0.35)  # its own clock offset
    # Load steps 0, 1000 ... 4000 N along Y and back, held 60 s each (load-cell noise 1 N).
    fy = c.loads["fy_N"].to_numpy()
    levels = np.unique(np.round(fy / 1000.0))
    assert set(levels) == {0.0, 1.0, 2.0, 3.0, 4.0}
    assert np.abs(c.loads["fx_N"]).max() < 6 and np.abs(c.loads["fz_N"]).max() < 6
    # Deflection in Y only, growing with the load.
    assert np.abs(truth["ttp_um"][:, 1]).max() > 100 * np.abs(truth["ttp_um"][:, [0, 2]]).max()


@pytest.mark.slow
def test_wavelengths_follow_the_bonded_fbg_formula_with_1pm_noise(machine, twin):
    sc = load_scenario("static-y")
    truth = true_response(twin, sc, seed=1)
    c, _ = simulate(machine, sc, seed=1, twin=twin)
    t = c.fbg["time_s"].to_numpy()
    lam = c.fbg[[f"{s}_nm" for s in c.meta.sensor_names]].to_numpy()
    lam_init = lam[:100].mean(axis=0)  # at rest: the installed wavelength + noise
    gauge = np.array([s.gauge_length for s in machine.sensors])
    elong = optics.elongation_um(lam, lam_init, gauge)  # isothermal: no compensation needed
    true = np.column_stack(
        [np.interp(t, truth["time_s"], truth["sensor_elongation_um"][:, j]) for j in range(5)]
    )
    resid_nm = (elong - true) / (gauge * 1e3) * optics.strain_sensitivity_nm(lam_init)
    assert 0.7e-3 < np.std(resid_nm) < 1.3e-3  # ~1 pm white noise
    # installation offsets: within ±0.3 nm of lambda0, not equal to it
    lam0 = np.array([s.lambda0_nm for s in machine.sensors])
    assert np.all(np.abs(lam_init - lam0) < 0.31) and np.all(np.abs(lam_init - lam0) > 1e-4)


@pytest.mark.slow
def test_thermal_bench_is_honest(machine, twin):
    """Sensor temperature comes from the FE field, probes have offsets and are quantised."""
    sc = load_scenario("thermal-36h")
    truth = true_response(twin, sc, seed=0)
    probes = [p.name for p in machine.probes]
    surf = truth["probe_C"][:, probes.index("T_surf")]
    # S1 uses the T_surf probe for compensation, but its grating sees its own path's temperature.
    assert np.max(np.abs(truth["sensor_temperature_C"][:, 0] - surf)) > 0.1
    c, _ = simulate(machine, sc, seed=0, twin=twin)
    read = c.temperatures["T_bulk_C"].to_numpy()
    np.testing.assert_allclose(read * 10, np.round(read * 10), atol=1e-6)  # 0.1 °C quantum
    peak = np.abs(truth["ttp_um"]).max(axis=0)
    assert 5 < peak[2] < 100  # thermal drift of the paper's order (51 µm), mostly along Z
    assert c.aligned().reference_um.shape[1] == 3


@pytest.mark.slow
def test_same_seed_same_campaign_other_seed_other_noise(machine, twin):
    sc = load_scenario("static-y")
    a, _ = simulate(machine, sc, seed=5, twin=twin)
    b, _ = simulate(machine, sc, seed=5, twin=twin)
    d, _ = simulate(machine, sc, seed=6, twin=twin)
    assert a.fbg.equals(b.fbg) and a.reference.equals(b.reference)
    assert not a.fbg.equals(d.fbg)


def test_a_scenario_that_drives_a_source_the_machine_lacks_is_a_clear_error():
    # A ram whose data sheet declares only its spindle heat: thermal-36h (no radiant history)
    # crashed with a ValueError traceback because its all-zero radiant history was still fed to
    # the twin; thermal-36h-b, whose radiant load is real, must name the scenario and field.
    from pathlib import Path

    import yaml

    from fbgcomp.structure import parse_machine

    path = Path(__file__).resolve().parents[1] / "examples" / "machines" / "ram2.yaml"
    d = yaml.safe_load(path.read_text())
    d["thermal"]["heat_sources"] = [h for h in d["thermal"]["heat_sources"] if h["kind"] != "radiant"]
    twin = Twin(parse_machine(d), resolution=COARSE)
    truth = true_response(twin, load_scenario("thermal-36h"), seed=0)
    assert np.abs(truth["ttp_um"][:, 2]).max() > 5.0  # the spindle heat still drives it
    with pytest.raises(InputError, match="field radiant_W_per_m2") as e:
        true_response(twin, load_scenario("thermal-36h-b"), seed=0)
    assert "<scenario thermal-36h-b>" in e.value.one_line()


def test_scenario_errors_name_the_field(tmp_path):
    bad = tmp_path / "s.yaml"
    bad.write_text("name: x\nkind: thermal\nduration_h: -1\n")
    with pytest.raises(InputError, match="duration_h") as e:
        load_scenario(bad)
    assert str(bad) in e.value.one_line()
    bad.write_text("name: x\nkind: nonsense\n")
    with pytest.raises(InputError, match="field kind"):
        load_scenario(bad)
    with pytest.raises(InputError, match="built-in scenarios"):
        load_scenario(tmp_path / "missing.yaml")


@pytest.mark.slow
def test_fe_calibrated_model_and_resolution(machine, twin, static_y, tmp_path):
    model, _cases = fe_calibrate(machine, twin, features="eq13")
    path = model.save(tmp_path / "fe.json")
    assert json.loads(path.read_text())["training"]["fe_design"]["n_samples"] == 2000
    c, _truth = static_y
    pred = model.predict(c)
    ref = c.aligned().reference_um
    # The FE-calibrated model knows the force path: dy tracks the deflection (per-sample error is
    # dominated by the 1 pm interrogator noise, amplified by the ram's lever arm).
    assert np.corrcoef(pred[:, 1], ref[:, 1])[0, 1] > 0.97
    rep = resolution_report(machine, twin)
    assert rep["rank"] == 3 and len(rep["unobservable_combinations"]) == 2
    # The squaring mode of the box (S1 + S2 - S3 - S4) is excited by no load case.
    square = rep["unobservable_combinations"]
    assert any(
        abs(abs(v["S1"]) - 0.5) < 0.05 and abs(v["S1"] - v["S2"]) < 0.05 and abs(v["S1"] + v["S3"]) < 0.05
        for v in square
    )
    for a in ("dx", "dy", "dz"):
        assert np.isfinite(rep["axes"][a]["resolution_um"])
    assert rep["axes"]["dz"]["resolution_um"] < rep["axes"]["dy"]["resolution_um"]


@pytest.mark.slow
def test_demo_runs_end_to_end(tmp_path):
    """``fbgcomp demo`` (quick, coarse mesh): the twin's models and their table, then the
    independent check on ram2 beside it (the default fit on thermal_a + static_xyz, judged on
    the campaigns it never saw)."""
    from fbgcomp.cli.demo import RAM2_HELD_OUT
    from fbgcomp_testing import RAM2_DIR

    if not (RAM2_DIR / "data").is_dir():
        pytest.fail(f"the independent reference data set is missing: {RAM2_DIR / 'data'}")
    out = tmp_path / "demo"
    r = subprocess.run(
        [
            sys.executable,
            "-m",
            "fbgcomp",
            "demo",
            "--quick",
            "--mesh-resolution",
            str(COARSE),
            "--ram2",
            str(RAM2_DIR),
            "-o",
            str(out),
        ],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert r.returncode == 0, r.stderr[-2000:]
    m = json.loads((out / "metrics.json").read_text())
    assert set(m["models"]) == {"default", "regression", "calibrated", "fe_model"}
    assert m["models"]["default"]["type"] == "physical"  # what `fbgcomp fit` gives, on the twin too
    for key in ("default", "regression", "calibrated"):
        v = m["models"][key]["validation"]
        assert set(v) == {"thermal-36h-b", "static-xyz"}
        assert v["thermal-36h-b"]["axes"]["dz"]["compensation_ratio"] > 0.8  # drift mostly compensated
        assert v["static-xyz"]["static_levels"]["n_levels"] >= 20
    assert json.loads((out / "calibrated_model.json").read_text())["model_type"] == "calibrated"
    assert json.loads((out / "regression_model.json").read_text())["model_type"] == "mra"
    for f in (
        "default_model.json",
        "calibrated_model.json",
        "regression_model.json",
        "fe_model.json",
        "coefficients.txt",
        "calibrated_model.txt",
        "resolution.txt",
        "report/report.html",
    ):
        assert (out / f).exists(), f
    assert "calibrated kinematic" in r.stdout and "thermal-36h-b dx" in r.stdout
    assert "default (physical)" in r.stdout.split("independent check")[0]  # in the twin's table
    for name in ("thermal-36h", "static-y", "thermal-36h-b", "static-xyz"):
        read_campaign(out / "campaigns" / name)
    # the independent check: every held-out campaign of ram2 judged, with its own table
    got = m["ram2"]
    assert "skipped" not in got and set(got["validation"]) == set(RAM2_HELD_OUT)
    assert got["model_type"] == "physical" and (out / "ram2_model.json").exists()
    text = r.stdout.split("independent check — ram2", 1)[1]
    for camp in RAM2_HELD_OUT:
        assert f"{camp} dx" in text
    # static_x: plateau means, the uncompensated row is 100 % of the largest plateau deflection
    assert any(ln.strip().startswith("uncompensated") and "100 % of 558" in ln for ln in text.splitlines())
    harmed = [f"{c} {a}" for c, v in got["validation"].items() for a, x in v["axes"].items() if x["harm"]]
    assert ("worse than uncompensated per sample: none" in text) == (not harmed)


@pytest.mark.slow
def test_the_scenario_example_in_the_docs_runs(machine, twin):
    """docs/bench.md shows how to write a scenario: that example must validate and simulate."""
    import re
    from pathlib import Path

    import yaml

    from fbgcomp.bench.virtual import Scenario

    text = (Path(__file__).parent.parent / "docs" / "bench.md").read_text(encoding="utf-8")
    example = yaml.safe_load(re.search(r"```yaml\n(.*?)```", text, re.S).group(1))
    example["z_axis_mm"] = None  # the coarse test twin is built at the default Z
    scenario = Scenario.model_validate(example).compressed(2.0)
    campaign, truth = simulate(machine, scenario, seed=2, twin=twin)
    assert campaign.meta.kind == "thermal" and campaign.loads is not None
    assert np.abs(truth["force_N"][:, 1]).max() == pytest.approx(2000.0)
    assert campaign.aligned().reference_um.shape[0] > 1000


def test_loads_superposed_on_a_campaign_are_read_back_exactly():
    # a linear structure's load response adds to what the campaign recorded: the gratings read
    # its elongation through eq. 2-4, the reference its deflection, loads.csv its forces
    from fbgcomp.bench.superpose import force_history_N, superpose_loads
    from fbgcomp.bench.synthetic import linear_truth_campaign

    base, _ = linear_truth_campaign(duration_s=3 * 3600.0, seed=2)
    sensors = base.meta.sensors
    rng = np.random.default_rng(0)
    C, G = rng.normal(0, 0.1, (3, 3)), rng.normal(0, 0.003, (3, len(sensors)))
    steps = [(0.5, 1.0, (1000.0, 0.0, 0.0)), (0.8, 2.0, (0.0, -500.0, 200.0))]
    c = superpose_loads(base, C, G, steps, load_noise_N=0.0)
    assert c.meta.kind == "combined" and c.meta.name.endswith("-loaded")
    t = c.fbg["time_s"].to_numpy(float)
    F = force_history_N(t, steps)
    assert F[np.searchsorted(t, 0.9 * 3600)].tolist() == [1000.0, -500.0, 200.0]
    for j, s in enumerate(sensors):
        col = f"{s.name}_nm"
        de = [
            optics.elongation_um(c_.fbg[col], s.lambda0_nm, s.gauge_length_mm, photoelastic=s.photoelastic)
            for c_ in (c, base)
        ]
        de = de[0] - de[1]  # eq. 2-4 are linear in the shift from the zero state's wavelength
        np.testing.assert_allclose(de, F @ G[:, j], atol=1e-6)
    tr = c.reference["time_s"].to_numpy(float)
    got = (
        c.reference[["dx_um", "dy_um", "dz_um"]].to_numpy()
        - base.reference[["dx_um", "dy_um", "dz_um"]].to_numpy()
    )
    np.testing.assert_allclose(got, force_history_N(tr, steps) @ C, atol=1e-9)
    np.testing.assert_allclose(c.loads[["fx_N", "fy_N", "fz_N"]].to_numpy(), F)
    with pytest.raises(ValueError, match="unit responses"):
        superpose_loads(base, C, G[:, :2], steps)
