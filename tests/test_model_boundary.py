"""Model files checked at the boundary (issue 13, finding 2): the one loader of the CLI, ``serve``
and the OPC UA reload refuses non-finite or absurd numbers, shapes that disagree, oversized and
deeply nested files with one line naming the file and field; ``save`` never replaces a good file
with an invalid model. Real files in tmp_path; the CLI side is in test_cli.py."""

from __future__ import annotations

import functools
import json
import math
import os
import tempfile
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from fbgcomp.bench.synthetic import linear_truth_campaign
from fbgcomp.errors import InputError
from fbgcomp.models.modelfile import MAX_MODEL_BYTES
from fbgcomp.models.mra import MRAModel
from fbgcomp.models.registry import load_model

# The valid models the tests mutate, each fitted once per session (functools.cache: the
# hypothesis strategies below take no fixture) as its file's JSON text, immutable; every
# test gets its own dict of it.


@functools.cache
def _mra_text() -> str:
    campaign, _ = linear_truth_campaign("boundary", seed=3, duration_s=900)
    model = MRAModel(features="eq13", stepwise=True, fallbacks="loo").fit(campaign)
    with tempfile.TemporaryDirectory() as tmp:
        return model.save(Path(tmp) / "m.json").read_text()


def _mra_dict() -> dict:
    """A small valid regression model (stepwise, leave-one-out fallbacks) as a dict."""
    return json.loads(_mra_text())


@functools.cache
def _kinematic_text() -> str:
    from fbgcomp.models.kinematic import KinematicModel

    with tempfile.TemporaryDirectory() as tmp:
        return KinematicModel().fit().save(Path(tmp) / "k.json").read_text()


def _kinematic_dict() -> dict:
    return json.loads(_kinematic_text())


def _write(path: Path, d, **dump) -> Path:
    path.write_text(json.dumps(d, **dump))
    return path


def _refused(path: Path, field: str | None = None, match: str | None = None) -> InputError:
    with pytest.raises(InputError) as info:
        load_model(path)
    err = info.value
    line = err.one_line()
    assert "\n" not in line and str(path) in line
    if field is not None:
        assert err.column == f"field {field}", line
    if match is not None:
        assert match in err.message, line
    return err


def test_the_valid_models_load(tmp_path):
    assert load_model(_write(tmp_path / "m.json", _mra_dict())).model_type == "mra"
    assert load_model(_write(tmp_path / "k.json", _kinematic_dict())).model_type == "kinematic"


def test_a_1e308_coefficient_is_refused(tmp_path):
    # It published CorrectionX = 1.5e308 um with Health OK from serve and the OPC UA reload.
    d = _mra_dict()
    d["axes"]["dx"]["params"][1] = 1e308
    _refused(_write(tmp_path / "m.json", d), "axes.dx.params[1]", "beyond the 1e+12")


def test_a_coefficient_beyond_the_limit_in_a_fallback_is_refused(tmp_path):
    d = _mra_dict()
    d["fallbacks"][2]["axes"]["dz"]["cov_params"][0][0] = -3e12
    _refused(_write(tmp_path / "m.json", d), "fallbacks[2].axes.dz.cov_params[0][0]")


@pytest.mark.parametrize("literal", ["NaN", "Infinity", "-Infinity", "1e999"])
def test_non_finite_literals_are_refused(tmp_path, literal):
    # A NaN coefficient gave a correction of exactly 0 with Health OK.
    text = json.dumps(_mra_dict(), indent=1)
    d = json.loads(text)
    d["axes"]["dy"]["params"][0] = "@@"
    path = tmp_path / "m.json"
    path.write_text(json.dumps(d).replace('"@@"', literal))
    _refused(path, "axes.dy.params[0]", "non-finite number")


def test_a_null_coefficient_is_refused_but_a_null_statistic_is_not(tmp_path):
    d = _mra_dict()
    d["axes"]["dx"]["params"][0] = None  # a NaN the writer turned into null
    _refused(_write(tmp_path / "m.json", d), "axes.dx.params[0]", "null where a number")
    d = _mra_dict()
    d["axes"]["dx"]["tvalues"][0] = None  # an infinite t of an exact fit: reported only
    d["axes"]["dx"]["fvalue"] = None
    assert load_model(_write(tmp_path / "ok.json", d)).axes_["dx"].fvalue != 0


@pytest.mark.parametrize(
    "mutate, field",
    [
        (lambda d: d["axes"]["dx"]["params"].pop(), "axes.dx.params"),
        (lambda d: d["axes"]["dy"]["cov_params"].pop(), "axes.dy.cov_params"),
        (lambda d: d["fallbacks"][0]["axes"]["dz"]["bse"].append(0.1), "fallbacks[0].axes.dz.bse"),
        (lambda d: d["axes"]["dz"]["terms"].__setitem__(1, "dL_S7"), "axes.dz.terms"),
        (lambda d: d["fallbacks"][1].__setitem__("exclude", ["S7"]), "fallbacks[1].exclude"),
        (lambda d: d["axes"]["dx"].__setitem__("resid_sd_um", -1.0), "axes.dx.resid_sd_um"),
    ],
)
def test_shapes_and_names_that_disagree_are_refused_on_loading(tmp_path, mutate, field):
    d = _mra_dict()
    mutate(d)
    _refused(_write(tmp_path / "m.json", d), field)


def test_a_fallback_whose_features_cannot_be_built_is_refused_on_loading(tmp_path):
    # Today such a file loads and fails only when the runtime first switches to that fallback.
    d = _mra_dict()
    d["probes"] = d["probes"][:1]
    _refused(_write(tmp_path / "m.json", d), match="cannot predict")


def test_kinematic_uncertainty_of_the_wrong_shape_is_refused(tmp_path):
    d = _kinematic_dict()
    d["uncertainty"]["relative"] = [0.1, 0.1]
    _refused(_write(tmp_path / "k.json", d), "uncertainty.relative")


def test_an_oversized_model_file_is_refused_without_reading_it_whole(tmp_path):
    path = tmp_path / "m.json"
    text = json.dumps(_mra_dict())
    with open(path, "w") as handle:
        handle.write(text[:-1])
        handle.write(" " * (MAX_MODEL_BYTES - len(text) + 16))
        handle.write("}")
    _refused(path, match=f"larger than {MAX_MODEL_BYTES} bytes")


@pytest.mark.parametrize("depth", [100, 200_000])
def test_deeply_nested_json_is_refused(tmp_path, depth):
    # 200 000 levels: a RecursionError traceback before; 100: under Python's limit, over ours
    path = tmp_path / "m.json"
    path.write_text(
        '{"format": "fbgcomp-model", "schema_version": 2, "model_type": "mra", "x": '
        + "[" * depth
        + "]" * depth
        + "}"
    )
    _refused(path, match="nested deeper than 64 levels")


@pytest.mark.parametrize(
    "content, match",
    [
        ('{"format": "fbgcomp-model", "schema_version": 0}', "schema_version must be"),
        ('{"format": "fbgcomp-model", "schema_version": 2, "model_type": ["mra"]}', "model_type must be"),
        ('{"format": "fbgcomp-model", "schema_version": 2, "n": ' + "9" * 5000 + "}", "not a JSON"),
        (b'\xff\xfe{"format"', "not UTF-8"),
    ],
)
def test_malformed_headers_are_one_line_errors(tmp_path, content, match):
    path = tmp_path / "m.json"
    path.write_bytes(content if isinstance(content, bytes) else content.encode())
    _refused(path, match=match)


def test_save_never_replaces_a_good_file_with_an_invalid_model(tmp_path):
    campaign, _ = linear_truth_campaign("save", seed=5, duration_s=600)
    model = MRAModel(features="eq11", fallbacks="none").fit(campaign)
    path = model.save(tmp_path / "m.json")
    good = path.read_bytes()
    model.axes_["dy"].params[0] = math.nan  # what a fit on an overflowing input gave
    with pytest.raises(InputError, match=r"not valid, so m.json was not written.*null") as info:
        model.save(path)
    assert info.value.file == str(path)
    assert path.read_bytes() == good
    assert os.listdir(tmp_path) == ["m.json"]  # no temporary file left behind
    model.axes_["dy"].params[0] = 1e300
    with pytest.raises(InputError, match="beyond"):
        model.save(tmp_path / "new.json")
    assert os.listdir(tmp_path) == ["m.json"]


def test_a_physical_model_with_an_absurd_coefficient_is_refused(tmp_path):
    # The default model type: its thermal coefficients go through the same numeric checks.
    from fbgcomp.models.physical import PhysicalModel
    from fbgcomp_testing import RAM2_DIR

    static_x = RAM2_DIR / "data" / "static_x"
    if not static_x.is_dir():
        pytest.fail(f"the independent reference data set is missing: {static_x}")
    path = PhysicalModel().fit(static_x).save(tmp_path / "p.json")
    d = json.loads(path.read_text())
    assert load_model(path).model_type == "physical"
    d["thermal"]["coef"][0][0] = 1e308
    _refused(_write(tmp_path / "bad.json", d), "thermal.coef[0][0]")
    d["thermal"]["coef"][0][0] = None
    _refused(_write(tmp_path / "bad.json", d), "thermal.coef[0][0]", "null where a number")


@functools.cache
def _physical_text() -> str:
    from fbgcomp.models.physical import PhysicalModel
    from fbgcomp_testing import RAM2_DIR, read_ram2

    r = read_ram2("thermal_a", "static_xyz")
    machine = Path(__file__).resolve().parents[1] / "examples" / "machines" / "ram2.yaml"
    model = PhysicalModel(machine=machine, twin_scenarios=8).fit([r["thermal_a"], r["static_xyz"]])
    assert RAM2_DIR.is_dir()
    with tempfile.TemporaryDirectory() as tmp:
        return model.save(Path(tmp) / "p.json").read_text()


def _physical_dict() -> dict:
    """The default model as the README fits it on ram2 (twin map, housing calibration, load
    part, interval), as a dict."""
    return json.loads(_physical_text())


@pytest.mark.parametrize(
    "mutate, field",
    [
        (lambda d: d["twin_map"]["coef"].pop(), "twin_map.coef"),
        (lambda d: d["twin_map"]["calibration"]["coef"].pop(), "twin_map.calibration.coef"),
        (
            lambda d: d["twin_map"]["calibration"].__setitem__("leads_s", [300.0, -1.0]),
            "twin_map.calibration.leads_s",
        ),
        (lambda d: d["load"]["G_um_per_N"][0].append(0.0), "load.G_um_per_N"),
        (lambda d: d["interval"]["v0_um2"].__setitem__(1, -0.1), "interval.v0_um2"),
        (lambda d: d["interval"]["dT_scale_K"].pop(), "interval.dT_scale_K"),
        (
            lambda d: d["interval"]["without_probes"][0]["probes"].__setitem__(0, "T_nowhere"),
            "interval.without_probes[0].probes",
        ),
        (
            lambda d: d["interval"]["without_probes"][0]["probes"].append(d["probes"][0]),
            "interval.without_probes[0].probes",
        ),
        (
            lambda d: d["interval"]["without_probes"][1].pop("resid_sd_um"),
            "interval.without_probes[1].resid_sd_um",
        ),
        (lambda d: d["thermal"]["coef"].append([0.0, 0.0, 0.0]), "thermal.coef"),
        (lambda d: d["housing_probes"].append("T_nowhere"), "housing_probes"),
        (lambda d: d["probes"].append(d["probes"][0]), "probes"),
    ],
)
def test_a_physical_model_whose_shapes_disagree_is_refused_on_loading(tmp_path, mutate, field):
    # Before, such a file loaded and failed (or broadcast silently) at the first prediction.
    d = _physical_dict()
    assert load_model(_write(tmp_path / "ok.json", d)).model_type == "physical"
    mutate(d)
    _refused(_write(tmp_path / "m.json", d), field)


# --------------------------------------------------------------------------------------------
# Property tests: any mutation of a valid model loads or is an InputError, never another error
# --------------------------------------------------------------------------------------------


def _paths(node, prefix=()):
    yield prefix
    if isinstance(node, dict):
        for k, v in node.items():
            yield from _paths(v, (*prefix, k))
    elif isinstance(node, list):
        for i, v in enumerate(node):
            yield from _paths(v, (*prefix, i))


_json_values = st.recursive(
    st.none()
    | st.booleans()
    | st.integers(-(10**20), 10**20)
    | st.floats(allow_nan=True, allow_infinity=True)
    | st.text(max_size=8)
    | st.sampled_from(["S1", "dL_S1", "const", "eq13", "HAC", "loo", "mra", "physical"]),
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=6), inner, max_size=3),
    max_leaves=8,
)


@st.composite
def mutations(draw, base):
    d = base()
    paths = list(_paths(d))
    for _ in range(draw(st.integers(1, 3))):
        path = draw(st.sampled_from(paths))
        if not path:
            continue
        parent = d
        try:
            for part in path[:-1]:
                parent = parent[part]
            key = path[-1]
            action = draw(st.sampled_from(["replace", "delete", "scale", "grow"]))
            if action == "delete":
                del parent[key]
            elif action == "scale" and isinstance(parent[key], (int, float)):
                parent[key] = parent[key] * draw(st.sampled_from([-1, 0, 1e6, 1e300, math.nan]))
            elif action == "grow" and isinstance(parent[key], list):
                parent[key].append(parent[key][0] if parent[key] else 0.0)
            else:
                parent[key] = draw(_json_values)
        except (KeyError, IndexError, TypeError):
            continue  # an earlier mutation removed or replaced this path
    return d


def _loads_or_input_error(d) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "m.json"
        path.write_text(json.dumps(d, allow_nan=True))
        try:
            model = load_model(path)
        except InputError as err:
            assert "\n" not in err.one_line() and len(err.one_line()) < 500 + len(tmp)
            return
        # what loaded predicts finite numbers with every sensor set the runtime may use
        w0 = np.array([s.lambda0_nm for s in model.sensors])
        t0 = np.full(len(model.probe_names), 20.0)
        for exclude in [frozenset(), *list(model.fallback_sets)]:
            dev, half = model.predictor(exclude).predict(w0[None, :] + 0.01, t0[None, :] + 0.5, w0, t0)
            assert np.isfinite(dev).all() and np.isfinite(half).all()


@settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(d=mutations(_mra_dict))
def test_any_mutation_of_a_regression_model_loads_or_is_an_input_error(d):
    _loads_or_input_error(d)


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(d=mutations(_kinematic_dict))
def test_any_mutation_of_a_kinematic_model_loads_or_is_an_input_error(d):
    _loads_or_input_error(d)


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(d=mutations(_physical_dict))
def test_any_mutation_of_a_physical_model_loads_or_is_an_input_error(d):
    _loads_or_input_error(d)
