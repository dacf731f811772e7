"""The default model on a second independent ram (tests/data/ram3.tar.xz): a CalculiX ram unlike
ram2 (both rails on -X, five gratings, the housing probe on +Y, a radiant load on +Y in
thermal_b, a force along Y in thermal_c), described from its data sheet
(examples/machines/ram3.yaml). What is tuned to ram2's particulars shows here."""

import numpy as np
import pytest

from fbgcomp_testing import RAM3_MACHINE, held_out_figures, read_ram3

# one worker runs the module (CONTRIBUTING): the default fit and the observer's share one twin,
# built there once and not waited on from the other worker
pytestmark = pytest.mark.xdist_group("ram3")

HELD = ("thermal_b", "thermal_c", "static_y")


@pytest.fixture(scope="session")
def ram3():
    return read_ram3("thermal_a", "static_xyz", *HELD)


@pytest.fixture(scope="session")
def default_model(ram3):
    """``fbgcomp fit thermal_a static_xyz --machine examples/machines/ram3.yaml``."""
    from fbgcomp.models.physical import PhysicalModel

    return PhysicalModel(machine=RAM3_MACHINE).fit([ram3["thermal_a"], ram3["static_xyz"]])


@pytest.mark.slow
def test_the_default_fit_harms_no_axis_of_ram3s_held_out_campaigns(ram3, default_model):
    """Do no harm on data we did not make: no axis of any held-out campaign ends with a larger
    max |error| than uncompensated (+0.5 µm, the interferometer's noise), the intervals cover
    0.90-0.99 of the samples but thermal_b's dx (0.92 measured), and each campaign gains where
    it moves: every axis moving over 50 µm within 15 % of its peak (2026-11-28: thermal_b dx /
    dy / dz 0.64 / 7.46 / 7.40 µm on 20.9 / 15.1 / 56.6; thermal_c dy 8.27 on 338, dz 6.85 on 53.4;
    static_y dy 14.75 on 435)."""
    for name in HELD:
        c = ram3[name]
        err, peak, cover = held_out_figures(default_model, c)
        assert (err <= peak + 0.5).all(), (name, err, peak)
        assert (cover >= 0.90).all() and (cover <= 0.99).all(), (name, cover)
        moving = peak > 50.0
        assert (err[moving] < 0.15 * peak[moving]).all(), (name, err, peak)


@pytest.mark.slow
def test_the_observer_option_harms_no_axis_of_ram3_either(ram3):
    """``fit --observer`` on ram3: no axis worse than uncompensated; its dy on the loaded thermal
    campaign is worse than the default's (9.17 against 8.27 µm measured), which is why it is
    not the default (docs/accuracy.md)."""
    from fbgcomp.models.physical import PhysicalModel

    m = PhysicalModel(machine=RAM3_MACHINE, observer=True).fit([ram3["thermal_a"], ram3["static_xyz"]])
    for name in HELD:
        c = ram3[name]
        ref = c.aligned(zero_window_s=m.zero_window_s).reference_um
        err = np.abs(m.predict_interval(c)[0] - ref).max(axis=0)
        assert (err <= np.abs(ref).max(axis=0) + 0.5).all(), (name, err)


@pytest.mark.slow
def test_the_twin_of_ram3s_description_meets_the_twin_check_against_its_results():
    """`fbgcomp twin-check examples/machines/ram3.yaml --against ram3/results.json`: the unit-load
    compliances and grating responses within 3 %, the uniform +10 K dz within 2 % (issue 12's
    targets), on a ram whose rails are both on one face and whose gauges are 500-600 mm."""
    from fbgcomp_testing import assert_twin_check, ram3_dir

    assert_twin_check(RAM3_MACHINE, ram3_dir() / "results.json", ("S1", "S2", "S3", "S4", "S5"), 25)
