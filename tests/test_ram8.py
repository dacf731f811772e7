"""The default model on a seventh independent ram (tests/data/ram8.tar.xz): a CalculiX model of a
CFRP box whose +X wall, the face both guide rails are mounted on, is 28 mm thick against the -X
wall's 16 mm (the Y walls 14 mm), both rails on that face (one locating, one floating along Y),
six gratings, a probe on the steel spindle housing, one inside the -X wall and one in the air, a
radiant load on the thin -X wall in thermal_b and forces along -X and +Y in thermal_c; described
from its data sheet with a wall per face (examples/machines/ram8.yaml). Built by a helper that
did not read the product.

Its section is asymmetric in X: it bends about a centroid 19 mm towards the thick wall, and a
uniform warming of the box moves the axis sideways from the rails' face."""

import numpy as np
import pytest

from fbgcomp_testing import (
    RAM8_ARCHIVE,
    RAM8_MACHINE,
    assert_data_sheet_describes,
    assert_twin_check,
    held_out_figures,
    read_ram8,
    unpacked,
)

# one worker runs the module (CONTRIBUTING): ram8_model is fitted once
pytestmark = pytest.mark.xdist_group("ram8")

HELD = ("thermal_b", "thermal_c", "static_x")


@pytest.mark.slow
def test_the_twin_of_ram8s_data_sheet_meets_the_twin_check_against_its_results():
    """`fbgcomp twin-check examples/machines/ram8.yaml --against ram8/results.json`: the unit-load
    compliances and grating responses within 3 %, the uniform +10 K dz within 2 %, and the 36 h
    steps within 5 %, with the walls described per face (2026-12-08: 28 of 28 on the first
    description; Fx dx 64.23 against 63.70 µm/kN, S1 / S2 under Fx -1.487 / 2.313 against
    -1.491 / 2.312, the section bending about its centroid 19 mm towards the thick wall)."""
    assert_twin_check(
        RAM8_MACHINE, unpacked(RAM8_ARCHIVE) / "results.json", ("S1", "S2", "S3", "S4", "S5", "S6"), 28
    )


@pytest.mark.slow
def test_one_wall_thickness_for_ram8s_four_walls_misses_the_twin_check(tmp_path):
    """The same description with the four walls averaged to one 18 mm thickness, as the schema
    forced before a wall per face: the twin no longer bends where ram8 does. The X gratings'
    response to Fx is 30 % and 7 % off (resolution 1, 2026-12-08: 11 of 28 judged quantities
    within target against 28 of 28 per face)."""
    import yaml

    from fbgcomp.structure import Twin, load_machine, twin_check

    data = yaml.safe_load(RAM8_MACHINE.read_text())
    data["ram"]["wall_mm"] = sum(data["ram"]["wall_mm"].values()) / 4
    averaged = tmp_path / "ram8-one-wall.yaml"
    averaged.write_text(yaml.safe_dump(data))
    reference = twin_check.load_reference(unpacked(RAM8_ARCHIVE) / "results.json")
    rows = twin_check.compare(Twin(load_machine(averaged), resolution=0.5, reduce_thermal=False), reference)
    by_name = {r.quantity: r for r in rows}
    assert not by_name["Fx S1 (um/kN)"].passed and not by_name["Fx S2 (um/kN)"].passed
    assert by_name["Fx S1 (um/kN)"].twin / by_name["Fx S1 (um/kN)"].independent > 1.2
    assert sum(bool(r.passed) for r in rows if r.passed is not None) < 20


@pytest.fixture(scope="session")
def ram8():
    return read_ram8("thermal_a", "static_xyz", *HELD)


@pytest.fixture(scope="session")
def ram8_model(ram8):
    """``fbgcomp fit thermal_a static_xyz --machine examples/machines/ram8.yaml``."""
    from fbgcomp.models.physical import PhysicalModel

    return PhysicalModel(machine=RAM8_MACHINE).fit([ram8["thermal_a"], ram8["static_xyz"]])


def test_ram8s_data_sheet_describes_what_its_campaigns_carry():
    """The archive holds the data sheet, the checks and every campaign the description names."""
    assert_data_sheet_describes(RAM8_ARCHIVE, RAM8_MACHINE, ("thermal_a", "static_xyz", *HELD), "28 mm")


@pytest.mark.slow
def test_the_default_fit_harms_no_axis_of_ram8s_held_out_campaigns(ram8, ram8_model):
    """``fbgcomp fit thermal_a static_xyz --machine examples/machines/ram8.yaml``, judged on the
    campaigns it never saw: no axis ends with a larger max |error| than uncompensated (+0.5 µm);
    the issue's dz target (2 µm) on thermal_b and thermal_c, and the loaded axes within 5 %
    (2026-12-08: thermal_b dx / dy / dz 0.70 / 0.65 / 1.56 µm on 7.15 / 3.29 / 50.64; thermal_c
    4.77 / 5.51 / 1.69 on 159.9 / 193.5 / 43.9, 2.98 % and 2.85 %; static_x dx 6.90 on 254.9)."""
    figures = {}
    for name in HELD:
        err, peak, cover = held_out_figures(ram8_model, ram8[name])
        figures[name] = err, peak
        assert (err <= peak + 0.5).all(), (name, err, peak)
        assert np.isfinite(cover).all()
    err, peak = figures["thermal_b"]
    assert err[2] <= 2.0 and (err[:2] <= 0.5 * peak[:2]).all(), (err, peak)
    err, peak = figures["thermal_c"]
    assert err[2] <= 2.0 and (err[:2] <= 0.05 * peak[:2]).all(), (err, peak)
    err, peak = figures["static_x"]
    assert err[0] <= 0.05 * peak[0], (err, peak)
