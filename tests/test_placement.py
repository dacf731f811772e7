"""Sensor placement: candidate grids, the predicted worst-case TTP error, greedy + exchange."""

import json
import os
import subprocess
import sys

import numpy as np
import pytest

from fbgcomp.structure import load_machine
from fbgcomp.structure.placement import (
    candidate_grid,
    choose,
    objective_um,
    parse_grid,
    placement_design,
    predicted_error_um,
)

FBGCOMP = [sys.executable, "-m", "fbgcomp"]
GRID = {
    "faces": ("+X", "-X", "+Y", "-Y"),
    "offsets_mm": (-80.0, 0.0, 80.0),
    "length_mm": 400.0,
    "step_mm": 200.0,
}


@pytest.fixture(scope="session")
def design():
    machine = load_machine()
    return machine, placement_design(machine, candidate_grid(machine, **GRID), resolution=0.3)


def test_candidate_grid_lies_on_the_faces():
    machine = load_machine()
    cands = candidate_grid(machine, **GRID)
    assert len(cands) == 4 * 3 * 5  # faces x offsets x starts (0, 200, ..., 800)
    assert len({c.name for c in cands}) == len(cands)
    for c in cands:
        assert 0 <= c.z_start_mm < c.z_end_mm <= machine.ram.length_mm
        assert c.z_end_mm - c.z_start_mm == pytest.approx(400.0)
    assert parse_grid("faces=+X,-Y;offsets=0,50;length=300;step=100") == {
        "faces": ("+X", "-Y"),
        "offsets_mm": (0.0, 50.0),
        "length_mm": 300.0,
        "step_mm": 100.0,
    }


@pytest.mark.slow
def test_objective_is_the_estimators_worst_case_error(design):
    _, d = design
    idx = [d.names.index(s) for s in ("S1", "S2", "S3", "S4", "S5")]
    per_axis = predicted_error_um(d.elongation_um[:, idx], d.ttp_um, d.noise_um[idx])
    # Monte-Carlo check of the closed form: fit eq. 11 on noisy random load combinations.
    rng = np.random.default_rng(0)
    W = rng.standard_normal((200_000, len(d.case_names)))
    X = W @ d.elongation_um[:, idx] + d.noise_um[idx] * rng.standard_normal((len(W), len(idx)))
    B = np.linalg.lstsq(X, W @ d.ttp_um, rcond=None)[0]
    resid = np.max(np.abs(d.ttp_um - d.elongation_um[:, idx] @ B), axis=0)
    noise = np.sqrt(np.sum(B**2 * d.noise_um[idx, None] ** 2, axis=0))
    np.testing.assert_allclose(resid + 2 * noise, per_axis, rtol=0.05)
    # More paths never hurt the estimator's fit on the design.
    assert objective_um(d, [*idx, d.names.index(d.names[-1])]) <= objective_um(d, idx) + 1e-9


@pytest.mark.slow
def test_placement_beats_or_equals_the_default_layout(design):
    machine, d = design
    default = [s.name for s in machine.sensors]
    result = choose(d, 5, default=default)
    assert result.objective_um <= result.default_objective_um + 1e-9
    assert result.objective_um == pytest.approx(objective_um(d, [d.names.index(n) for n in result.chosen]))
    assert len(set(result.chosen)) == 5 and result.history[0]["step"] == "add"
    # With fewer paths the best achievable error is not better.
    assert choose(d, 3).objective_um >= result.objective_um - 1e-9


@pytest.mark.slow
def test_cli_place(tmp_path):
    out = tmp_path / "place.json"
    r = subprocess.run(
        [
            *FBGCOMP,
            "place",
            "--k",
            "5",
            "--resolution",
            "0.3",
            "--grid",
            "faces=+X,-X,+Y,-Y;offsets=0;length=500;step=250",
            "--json",
            str(out),
        ],
        capture_output=True,
        text=True,
        timeout=300,
        env={**os.environ, "PYTHONWARNINGS": "ignore"},
    )
    assert r.returncode == 0, r.stderr
    assert "default layout (S1, S2, S3, S4, S5)" in r.stdout and "predicted worst-case" in r.stdout
    res = json.loads(out.read_text())
    assert res["objective_um"] <= res["default_objective_um"] and len(res["chosen"]) == 5
    r = subprocess.run(
        [*FBGCOMP, "place", "--k", "5", "--grid", "faces=+Z"], capture_output=True, text=True, timeout=300
    )
    assert r.returncode == 2 and r.stderr.startswith("error: <command line>, column option --grid")
