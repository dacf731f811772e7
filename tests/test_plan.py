"""fbgcomp plan: predicted TTP accuracy of a machine description's layout against a target,
through the CLI (``fbgcomp plan``, run in the test's process: fbgcomp_testing.cli) on the built-in ram and on
examples/machines/ram2.yaml (the independent ram2 data sheet, written as a user would)."""

import json
import math
from pathlib import Path

import pytest
import yaml

from fbgcomp.structure import load_machine
from fbgcomp.structure.placement import placement_design, predicted_error_um
from fbgcomp.structure.plan import noise_scan, plan_design
from fbgcomp_testing import cli

ROOT = Path(__file__).resolve().parents[1]
RAM2 = ROOT / "examples" / "machines" / "ram2.yaml"
BUILTIN = ROOT / "src" / "fbgcomp" / "data" / "ram.yaml"
AXES = ("dx", "dy", "dz")

# every test here runs `fbgcomp plan` (1-26 s each under load)
pytestmark = pytest.mark.slow


def run_plan(*args, check=True):
    proc = cli("plan", *args, cwd=ROOT)
    if check:
        assert proc.returncode == 0, proc.stderr
    return proc


def plan_json(*args):
    return json.loads(run_plan(*args, "--json").stdout)


def placement_figure(machine_path):
    """Placement's own worst-case TTP error of the machine's layout (fbgcomp.structure.placement)."""
    machine = load_machine(machine_path)
    d = placement_design(machine)
    idx = [d.names.index(s.name) for s in machine.sensors]
    return predicted_error_um(d.elongation_um[:, idx], d.ttp_um, d.noise_um[idx])


def false_elongation_closed_form_um(sensor):
    """A grating 1 K warmer than its compensation, no strain: the shift (xi + p_e alpha_f) read as
    strain over (1 - p_e), times the gauge (paper eq. 2-4), µm."""
    xi, pe, af = sensor.thermo_optic_per_K, sensor.photoelastic, sensor.fibre_cte_per_K
    return (xi + pe * af) / (1 - pe) * sensor.gauge_length * 1e3


@pytest.mark.parametrize(
    "machine_args, machine_path", [((), None), (("--machine", RAM2), RAM2)], ids=["builtin", "ram2"]
)
def test_plan_agrees_with_placement_and_a_looser_target_flips_the_verdict(machine_args, machine_path):
    tight = plan_json("--target-um", 5, "--extra-sensors", 0, *machine_args)
    expected = placement_figure(machine_path)
    rows = {a["axis"]: a for a in tight["axes"]}
    assert list(rows) == list(AXES)
    for j, axis in enumerate(AXES):
        r = rows[axis]
        assert r["loads_noise_um"] == pytest.approx(expected[j], rel=1e-9)
        assert r["loads_noise_um"] == pytest.approx(r["unexplained_um"] + r["noise_um"], rel=1e-12)
        assert r["total_um"] == pytest.approx(r["loads_noise_um"] + r["thermal_um"], rel=1e-12)
        assert r["margin_um"] == pytest.approx(5 - r["total_um"])
        assert r["meets"] == (r["total_um"] <= 5)
    machine = load_machine(machine_path)
    for s in machine.sensors:
        assert tight["false_elongation_per_K_um"][s.name] == pytest.approx(
            false_elongation_closed_form_um(s), rel=1e-6
        )
    # Neither layout reaches 5 µm on the 4000 N design: the verdict says so.
    assert not tight["meets"]

    loose_target = math.ceil(max(r["total_um"] for r in tight["axes"])) + 1
    loose = run_plan("--target-um", loose_target, "--extra-sensors", 0, *machine_args)
    out = loose.stdout
    assert f"meets {loose_target:g} µm on dx, dy, dz" in out and "MISSES" not in out
    data = plan_json("--target-um", loose_target, "--extra-sensors", 0, *machine_args)
    assert data["meets"] and all(a["meets"] for a in data["axes"])
    assert [a["total_um"] for a in data["axes"]] == [a["total_um"] for a in tight["axes"]]


@pytest.mark.parametrize("machine_path", [None, RAM2], ids=["builtin", "ram2"])
def test_the_noise_it_asks_for_meets_the_target(machine_path):
    machine = load_machine(machine_path)
    pdes = plan_design(machine)
    own = range(len(machine.sensors))
    # Not monotone: a quieter interrogator lets the estimator amplify the probe mismatch.
    _pm, total = noise_scan(pdes, own, 2)
    now, best = total[-1], total.min()
    machine_args = ("--machine", machine_path) if machine_path else ()
    if best >= now:  # noise does not help this axis (built-in dz): the plan must say so
        assert machine_path is None
        data = plan_json("--target-um", 0.5 * now, "--axes", "dz", "--extra-sensors", 0, *machine_args)
        assert data["axes"][0]["noise_needed_pm"] is None
        assert data["axes"][0]["best_noise_total_um"] == pytest.approx(best, rel=1e-9)
        return
    target = 0.5 * (best + now)  # reachable with a quieter interrogator only
    data = plan_json("--target-um", target, "--axes", "dz", "--extra-sensors", 0, *machine_args)
    (dz,) = data["axes"]
    assert dz["axis"] == "dz" and not dz["meets"]
    needed = dz["noise_needed_pm"]
    assert needed is not None and 1e-3 <= needed < 1.0
    quieter = plan_json(
        "--target-um", target, "--axes", "dz", "--extra-sensors", 0, "--noise-pm", needed, *machine_args
    )
    assert quieter["axes"][0]["meets"]
    assert quieter["axes"][0]["total_um"] <= target < dz["total_um"]
    text = run_plan("--target-um", target, "--axes", "dz", "--extra-sensors", 0, *machine_args).stdout
    assert f"interrogator noise ≤ {needed:.3g} pm" in text


def test_reference_gratings_remove_the_probe_mismatch(tmp_path):
    plain = plan_json("--target-um", 5, "--extra-sensors", 0)
    spec = yaml.safe_load(BUILTIN.read_text())
    for s in spec["sensors"]:
        s["reference_lambda0_nm"] = s["lambda0_nm"] + 3.0
    machine_file = tmp_path / "ram_refs.yaml"
    machine_file.write_text(yaml.safe_dump(spec))
    refs = plan_json("--target-um", 5, "--extra-sensors", 0, "--machine", machine_file)
    assert set(refs["probes_compensating"].values()) == {"reference grating"}
    for a_plain, a_ref in zip(plain["axes"], refs["axes"]):
        assert a_plain["probe_mismatch_um"] > 0
        assert a_ref["probe_mismatch_um"] == 0
        assert a_ref["reference_noise_um"] > 0
        assert a_ref["loads_noise_um"] == pytest.approx(a_plain["loads_noise_um"], rel=1e-9)
        # what the plain plan predicted for "a reference grating beside every sensor" (it puts
        # them at the sensor's own wavelength: 3 nm off changes their sensitivity by 0.2 %)
        assert a_ref["total_um"] == pytest.approx(a_plain["with_references_um"], rel=3e-3)
        assert a_ref["total_um"] != a_plain["total_um"]


def test_larger_layouts_never_lose_to_the_machines_own_on_the_placement_figure():
    data = plan_json("--target-um", 5, "--extra-sensors", 1)
    own = max(a["loads_noise_um"] for a in data["axes"])
    ks = [lay["k"] for lay in data["larger_layouts"]]
    assert ks == [5, 6]
    for lay in data["larger_layouts"]:
        assert len(lay["paths"]) == lay["k"] == len(set(lay["paths"]))
        assert max(lay["loads_noise_um"]) <= own + 1e-9
    text = run_plan("--target-um", 5, "--extra-sensors", 1).stdout
    assert "--k 6:" in text and "MISSES by" in text


@pytest.mark.parametrize(
    "args, field",
    [
        (("--target-um", 5, "--axes", "dx,dq"), "--axes"),
        (("--target-um", 5, "--axes", "dx,dx"), "--axes"),
        (("--target-um", -1), "--target-um"),
        (("--target-um", 0), "--target-um"),
        (("--target-um", "nan"), "--target-um"),
        (("--target-um", 5, "--noise-pm", -0.5), "--noise-pm"),
        (("--target-um", 5, "--extra-sensors", -1), "--extra-sensors"),
    ],
)
def test_bad_input_is_one_line_and_exit_2(args, field):
    proc = run_plan(*args, check=False)
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and field in lines[0]
    assert "Traceback" not in proc.stderr and proc.stdout == ""
