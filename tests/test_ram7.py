"""The default model on a sixth independent ram (tests/data/ram7.tar.xz): a CalculiX model of a
long (1600 mm) square CFRP box with a small positive axial expansion, guided on two opposite faces
(+X and -X, both rails locating, three carriage stations each), five gratings, a probe on an
aluminium spindle housing, one in the +X wall and one in the air, the bearings centred, a radiant
load on -Y in thermal_b and forces along +Y and -Z in thermal_c; described from its data sheet
(examples/machines/ram7.yaml). Built by a helper that did not read the product.

Symmetric about both axes: nothing thermal moves its TTP along X, and only the radiant load moves
it along Y. Its held-out campaigns check that a model does not invent lateral drift where there is
none, on a ram whose description was written once, from the data sheet, and not revised."""

import numpy as np
import pytest

from fbgcomp_testing import (
    RAM7_ARCHIVE,
    RAM7_MACHINE,
    assert_data_sheet_describes,
    assert_twin_check,
    held_out_figures,
    read_ram7,
    unpacked,
)

# one worker runs the module (CONTRIBUTING): ram7_model is fitted once; on two workers each fitted
# it and one waited ~40 s on the other's twin build (2026-12-07)
pytestmark = pytest.mark.xdist_group("ram7")

HELD = ("thermal_b", "thermal_c", "static_x")


@pytest.mark.slow
def test_the_twin_of_ram7s_data_sheet_meets_the_twin_check_against_its_results():
    """`fbgcomp twin-check examples/machines/ram7.yaml --against ram7/results.json`: the unit-load
    compliances and grating responses within 3 %, the uniform +10 K dz within 2 % (2026-12-06:
    25 of 25 on the first description, Fx dx 144.3 µm/kN), and the 36 h steps within 5 %."""
    assert_twin_check(
        RAM7_MACHINE, unpacked(RAM7_ARCHIVE) / "results.json", ("S1", "S2", "S3", "S4", "S5"), 25
    )


@pytest.fixture(scope="session")
def ram7():
    return read_ram7("thermal_a", "static_xyz", *HELD)


@pytest.fixture(scope="session")
def ram7_model(ram7):
    """``fbgcomp fit thermal_a static_xyz --machine examples/machines/ram7.yaml``."""
    from fbgcomp.models.physical import PhysicalModel

    return PhysicalModel(machine=RAM7_MACHINE).fit([ram7["thermal_a"], ram7["static_xyz"]])


def test_ram7s_data_sheet_describes_what_its_campaigns_carry():
    """The archive holds the data sheet, the checks and every campaign the description names."""
    assert_data_sheet_describes(
        RAM7_ARCHIVE, RAM7_MACHINE, ("thermal_a", "static_xyz", *HELD), "both locating"
    )


@pytest.mark.slow
def test_the_default_fit_meets_the_dz_targets_and_harms_no_axis_of_ram7(ram7, ram7_model):
    """``fbgcomp fit thermal_a static_xyz --machine examples/machines/ram7.yaml``, judged on the
    campaigns it never saw: no axis ends with a larger max |error| than uncompensated (+0.5 µm),
    dx included, which no thermal input moves; the issue's dz target (2 µm) on thermal_b and
    thermal_c; thermal_b's radiant dy within 20 % of its peak; the loaded axes within 5 %
    (2026-12-06: thermal_b dx / dy / dz 0.23 / 0.26 / 1.78 µm on 0.2 / 7.5 / 103.0; thermal_c
    0.19 / 5.31 / 1.69 on 0.2 / 177.4 / 82.4; static_x dx 15.29 on 577.4)."""
    figures = {}
    for name in HELD:
        err, peak, cover = held_out_figures(ram7_model, ram7[name])
        figures[name] = err, peak
        assert (err <= peak + 0.5).all(), (name, err, peak)
        assert np.isfinite(cover).all()
    err, peak = figures["thermal_b"]
    assert err[2] <= 2.0 and err[1] <= 0.2 * peak[1], (err, peak)
    err, peak = figures["thermal_c"]
    assert err[2] <= 2.0 and err[1] <= 0.05 * peak[1], (err, peak)
    err, peak = figures["static_x"]
    assert err[0] <= 0.05 * peak[0], (err, peak)


@pytest.mark.slow
def test_the_correction_served_through_the_runtime_meets_the_dz_target_too(ram7, ram7_model):
    """thermal_b's interrogator frames fed to the runtime core (output filter, limits, health),
    as the CNC would receive the correction: dz within the issue's 2 µm, as offline. The
    aluminium housing turns dz over fast where the spindle stops; the output filter's rest fit
    lagged that turn by a part of its time constant: 2.98 µm with 150 s against 1.78 offline
    (2026-12-06), 1.92 with 30 s."""
    from fbgcomp.bench.served import served

    published, reference, _ = served(ram7_model, ram7["thermal_b"])
    err = np.abs(reference + published).max(axis=0)  # the correction undoes the deviation
    assert err[2] <= 2.0, err
    assert (err <= np.abs(reference).max(axis=0) + 0.5).all(), err
