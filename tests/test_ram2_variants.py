"""ram2's independent data turned, mirrored, with fewer instruments and with loads superposed.

Runs ``benchmarks/bench_ram2_variants.py`` as a user would (it rewrites the campaign files and the
description, then ``fbgcomp fit`` and judges): a ram that stands otherwise in its frame has the
same physics, so the default must give ram2's figures with the axes exchanged; with fewer
instruments it may do less, never harm.
"""

import json
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from fbgcomp_testing import RAM2_DIR

# one worker runs the module: its fixture (eight fits of ram2, ~3 min) is built once per worker
# that runs a test of it, and pytest-xdist had sent the tests to both
pytestmark = [pytest.mark.slow, pytest.mark.xdist_group("ram2_variants")]

REPO = Path(__file__).resolve().parents[1]
AXES = ("dx", "dy", "dz")
HELD = ("thermal_b", "thermal_c", "static_x")


# session scope: the module's tests share one worker (xdist_group), but the worker may run other
# modules' tests between them, and a module-scoped fixture was then built again (CI of
# 2026-11-29: twice: 337 and 291 s)
@pytest.fixture(scope="session")
def bench(tmp_path_factory):
    if not (RAM2_DIR / "data").is_dir():
        pytest.fail(f"the independent reference data set is missing: {RAM2_DIR / 'data'}")
    work = tmp_path_factory.mktemp("ram2-variants")
    r = subprocess.run(
        [
            sys.executable,
            str(REPO / "benchmarks" / "bench_ram2_variants.py"),
            "--ram2",
            str(RAM2_DIR),
            "--work",
            str(work),
            "--only",
            "as-published",
            "turned-90",
            "mirrored",
            "four-gratings",
            "no-T_flange",
            "spindle-centred",
            "rails-both-locating",
            "no-radiant-declared",
            "two-faces",
        ],
        capture_output=True,
        text=True,
        cwd=REPO,
    )
    assert r.returncode == 0, r.stderr[-3000:]
    return json.loads(r.stdout.strip().splitlines()[-1]), work


@pytest.mark.parametrize("variant", ["turned-90", "mirrored"])
def test_a_ram_turned_or_mirrored_in_its_frame_gets_the_same_correction(bench, variant):
    out, work = bench
    base, other = out["results"]["as-published"], out["results"][variant]
    # the description stands otherwise: the rails on +X when turned, the heat towards -X when mirrored
    desc = yaml.safe_load((work / variant / "machine.yaml").read_text())
    if variant == "turned-90":
        assert {r["face"] for r in desc["supports"]["rails"]} == {"+X"}
    else:
        assert desc["thermal"]["heat_sources"][0]["x_mm"] == [-67.5, 22.5]
    # and the files: the same uncompensated deviations, axis for axis in ram2's frame
    for held in HELD:
        for a in AXES:
            b, v = base[held]["axes"][a], other[held]["axes"][a]
            assert abs(v["peak_um"] - b["peak_um"]) < 1e-6, (held, a, v, b)
            # the twin's mesh is not exactly symmetric: a few hundredths of a µm
            assert abs(v["max_abs_error_um"] - b["max_abs_error_um"]) < 0.1, (held, a, v, b)
            assert abs(v["pi95_coverage"] - b["pi95_coverage"]) < 0.02, (held, a, v, b)
            assert not v["harm"], (held, a, v)


@pytest.mark.parametrize("variant", ["four-gratings", "no-T_flange"])
def test_a_ram_with_fewer_instruments_is_compensated_without_harm(bench, variant):
    out, _ = bench
    fig, base = out["results"][variant], out["results"]["as-published"]
    for held in HELD:
        for a in AXES:
            v = fig[held]["axes"][a]
            assert v["max_abs_error_um"] <= v["peak_um"] + 0.5, (variant, held, a, v)
    # and it still compensates: thermal_b's lateral drift and dz at least halved
    for a in AXES:
        v = fig["thermal_b"]["axes"][a]
        assert v["max_abs_error_um"] <= 0.5 * v["peak_um"], (variant, a, v)
    assert fig["thermal_b"]["axes"]["dz"]["peak_um"] == base["thermal_b"]["axes"]["dz"]["peak_um"]


def test_an_interval_blind_to_the_spindle_housing_stays_the_size_of_the_drift(bench):
    # Without T_flange nothing the model reads sees a spindle start: the TTP moves while no
    # state of the interval does, and the few samples of each start scaled its state terms
    # 1000x (a mean dz half-width of ~400 µm on thermal_b's 59.9, and 0.80 coverage on
    # thermal_c all the same). Such a model's interval carries a constant term.
    fig = bench[0]["results"]["no-T_flange"]
    for held in ("thermal_b", "thermal_c"):
        for a in AXES:
            v = fig[held]["axes"][a]
            assert v["pi95_mean_halfwidth_um"] <= 0.5 * v["peak_um"], (held, a, v)
            assert v["pi95_coverage"] >= 0.83, (held, a, v)
    # a model that sees the housing keeps its interval: the interferometer's at rest
    base = bench[0]["results"]["as-published"]["static_x"]["axes"]["dz"]
    assert base["pi95_mean_halfwidth_um"] <= 0.5, base


def test_a_rougher_description_of_the_same_ram_does_no_harm(bench):
    # The bearing heat described centred in the housing (a data sheet rarely places it): the map
    # leaves the housing transient to the calibration, whose 300 s lead then takes 18.7 µm/K of
    # dz (11.5 as described) and amplifies the flange probe's 0.1 K scatter; the policy's noise
    # floor knew the map alone (0.29 µm) and let 1.8 µm through on static_x, whose dz moves
    # 0.2 µm. It is now the whole thermal part's noise, calibration included.
    fig = bench[0]["results"]["spindle-centred"]
    for held in HELD:
        for a in AXES:
            v = fig[held]["axes"][a]
            assert v["max_abs_error_um"] <= v["peak_um"] + 0.5, (held, a, v)
    assert fig["static_x"]["axes"]["dz"]["max_abs_error_um"] < 0.5, fig["static_x"]["axes"]["dz"]


def test_a_uniform_warming_the_description_gets_wrong_is_learnt_from_the_ambient(bench):
    # Both rails described as locating (one floats in ram2): the twin's lateral drift under a
    # uniform warming is wrong, and thermal_b's dx error tracked the hall's temperature (-3.3
    # µm/K, correlation -0.97, as on thermal_a): 10.85 µm on 30.56. thermal_a's day cycle
    # teaches it through the calibration's ambient term; the air follows no heat source.
    fig = bench[0]["results"]["rails-both-locating"]["thermal_b"]["axes"]["dx"]
    assert fig["max_abs_error_um"] <= 0.25 * fig["peak_um"], fig
    base = bench[0]["results"]["as-published"]["thermal_b"]["axes"]["dx"]
    assert base["max_abs_error_um"] <= 0.1 * base["peak_um"], base


def test_the_interval_widens_where_the_gratings_cannot_tell_the_heat_sources_apart(bench):
    # Without S5 and S6 the radiant load on thermal_b's +X face is seen by S1 alone, and the
    # twin map's members (each without one undeclared source) disagree on what it does to dx
    # and dy; the training campaign never showed that ambiguity, so an interval fitted on its
    # residuals alone covered 0.90 of dx and 0.81 of dy. The members' spread is a half-width.
    # (dy covers 0.98 since the unseen part of the correction entered the interval, below)
    fig = bench[0]["results"]["four-gratings"]["thermal_b"]["axes"]
    assert fig["dx"]["pi95_coverage"] >= 0.95, fig["dx"]
    assert fig["dy"]["pi95_coverage"] >= 0.95, fig["dy"]
    # and ram2 as published, where the members agree, keeps its interval
    base = bench[0]["results"]["as-published"]["thermal_b"]["axes"]
    assert all(0.95 <= base[a]["pi95_coverage"] <= 0.995 for a in AXES), base


def test_the_interval_holds_where_the_description_misses_a_heat_source(bench):
    # The data sheet lists the spindle only: thermal_b's radiant load is read through the
    # twin's generic face sources, which warm S1's gauge alike but move the TTP otherwise
    # (dx 11.7 and dz 12.5 µm off). An interval fitted on thermal_a's residuals, which never
    # saw a face warmer than its opposite, covered 0.86 of dx and 0.815 of dz. The part of the
    # correction resting on directions the training never moved along enters it at 20 %.
    # Scaled on held-out halves of the training since 2026-12-06, dx covers 0.992:
    # a few tenths over the 0.99 is the safe side, under 0.90 is not.
    fig = bench[0]["results"]["no-radiant-declared"]
    for a in AXES:
        v = fig["thermal_b"]["axes"][a]
        assert 0.90 <= v["pi95_coverage"] <= 0.995, (a, v)
    for held in HELD:
        for a in AXES:
            v = fig[held]["axes"][a]
            assert v["max_abs_error_um"] <= v["peak_um"] + 0.5, (held, a, v)


def test_an_expansion_one_axis_contradicts_is_not_taken_for_the_descriptions(bench):
    # The missing radiant source also leaves thermal_a a misfit that a CFRP axial expansion of
    # -1.0e-6 /K (0.4e-6 described and true) absorbs on dx and dz (deviances +9.8, +9.6) while
    # it fits dy worse by more than the test asks of the description (-11.9, dy's training RMS
    # 0.13 -> 0.36 µm). One coefficient for every axis: that estimate is not one the training
    # asks for. Taken into the consensus (2026-11-29 to 2026-12-06) it held thermal_b's dx at
    # its uncompensated 30.56 µm and took dz to 18.8 and dy's coverage to 0.898.
    from fbgcomp.models.registry import load_model

    work = bench[1]
    cte = load_model(work / "no-radiant-declared" / "model.json").twin_map_["cte"]
    assert cte["deviance"] > cte["threshold"], cte  # the sum alone would reject the description
    assert min(cte["deviance_per_axis"]) < -cte["threshold"], cte
    assert not cte["contradicted"], cte
    v = bench[0]["results"]["no-radiant-declared"]["thermal_b"]["axes"]["dx"]
    assert v["max_abs_error_um"] <= 0.5 * v["peak_um"], v


def test_an_estimated_expansion_speaks_only_for_the_axes_it_fits_better(bench):
    # Without S2 and S4 the training contradicts the description (deviance 21 from dx and dy)
    # but fits dz a little worse at the estimate (-2.4): its map joins the consensus on dx and
    # dy only, and dz keeps the description's answer (thermal_b 6.83 µm when it joined on dz
    # too, 4.62 as published)
    from fbgcomp.models.registry import load_model

    work, res = bench[1], bench[0]["results"]
    m = load_model(work / "two-faces" / "model.json")
    cte = m.twin_map_["cte"]
    assert cte["contradicted"], cte
    (member,) = m.twin_map_["cte_members"]
    assert member["axes"] == [v > 0 for v in cte["deviance_per_axis"]] == [True, True, False], cte
    dz = res["two-faces"]["thermal_b"]["axes"]["dz"]["max_abs_error_um"]
    assert dz == pytest.approx(res["as-published"]["thermal_b"]["axes"]["dz"]["max_abs_error_um"], abs=0.1)
    for held in HELD:
        for a in AXES:
            v = res["two-faces"][held]["axes"][a]
            assert v["max_abs_error_um"] <= v["peak_um"] + 0.5, (held, a, v)


def test_loads_superposed_on_ram2s_thermal_drift_are_followed_without_harm(bench):
    # ram2 is linear: its thermal campaigns with load histories added through its unit responses
    # are exact combined campaigns, with thermal drift we did not simulate
    out, _ = bench
    loaded = out["loaded"]
    assert {"b+300N-radiant", "b+steps", "b+Fz", "c+Fy"} <= set(loaded)
    for name, r in loaded.items():
        for a in AXES:
            v = r["axes"][a]
            assert v["max_abs_error_um"] <= v["peak_um"] + 0.5, (name, a, v)
    # a 300 N Fx under thermal_b's radiant drift (-1 N/s of Fx): 41.9 µm of dx, held within
    # 1.5 µm (it ended 46 N low, 6.2 µm, when the level took in the lag and the drift)
    r = out["loaded"]["b+300N-radiant"]
    assert r["plateau_error_um"]["dx"] < 1.5, r
    # every step from 150 to 2000 N, along X and Y, within 1.5 µm on its plateau
    assert max(loaded["b+steps"]["plateau_error_um"][a] for a in ("dx", "dy")) < 1.5
