"""The default model on a third independent ram (tests/data/ram4.tar.xz): a CalculiX ram guided on
two adjacent faces (a locating rail on -X, a floating one on -Y), seven gratings of which two carry a
strain-free reference grating, a cast-iron housing heated by the bearings and the motor at once, a
radiant load on +X in thermal_b and a force along Y then Z in thermal_c; described from its data
sheet (examples/machines/ram4.yaml)."""

import numpy as np
import pytest

from fbgcomp_testing import (
    RAM4_ARCHIVE,
    RAM4_MACHINE,
    assert_twin_check,
    held_out_figures,
    read_ram4,
    unpacked,
)

HELD = ("thermal_b", "thermal_c", "static_y")


@pytest.mark.slow
def test_the_twin_of_ram4s_data_sheet_meets_the_twin_check_against_its_results():
    """`fbgcomp twin-check examples/machines/ram4.yaml --against ram4/results.json`: the unit-load
    compliances and grating responses within 3 %, the uniform +10 K dz within 2 %, on a ram held
    by rails on two adjacent faces (2026-11-29 at the description's mesh: 31 of 31; dz 0.37 %)."""
    sensors = ("S1", "S2", "S3", "S4", "S5", "S6", "S7")
    assert_twin_check(RAM4_MACHINE, unpacked(RAM4_ARCHIVE) / "results.json", sensors, 31)


@pytest.fixture(scope="session")
def ram4():
    return read_ram4("thermal_a", "static_xyz", *HELD)


@pytest.mark.slow
def test_the_default_fit_harms_no_axis_of_ram4s_held_out_campaigns(ram4):
    """``fbgcomp fit thermal_a static_xyz --machine examples/machines/ram4.yaml``, judged on the
    campaigns it never saw: no axis ends with a larger max |error| than uncompensated (+0.5 µm,
    the interferometer's noise), every axis moving over 50 µm is within 10 % of its peak, and the
    reference gratings are read (2026-11-29: thermal_b dx / dy / dz 0.98 / 2.69 / 1.50 µm on
    10.3 / 20.1 / 74.1; thermal_c dy 7.6 on 154, dz 2.3 on 71.9; static_y dy 8.7 on 294). The
    intervals cover 0.90-0.995 of the samples on every axis (2026-12-06, scaled on held-out
    halves of the training: thermal_b's dx 0.945, 0.84 when scaled in-sample, an error of
    ~0.5 µm that outlasts the radiant load by ten hours; thermal_c's dx 0.992, a few tenths over
    the issue's 0.99 on an axis of 6.3 µm: the safe side; docs/accuracy.md)."""
    from fbgcomp.models.physical import PhysicalModel

    m = PhysicalModel(machine=RAM4_MACHINE).fit([ram4["thermal_a"], ram4["static_xyz"]])
    assert {"S1_ref", "S3_ref"} <= set(m.probe_names_)
    for name in HELD:
        c = ram4[name]
        err, peak, cover = held_out_figures(m, c)
        assert (err <= peak + 0.5).all(), (name, err, peak)
        moving = peak > 50.0
        assert (err[moving] < 0.10 * peak[moving]).all(), (name, err, peak)
        assert (cover >= 0.90).all() and (cover <= 0.995).all(), (name, cover)


@pytest.mark.slow
def test_a_data_sheet_that_gets_the_fibres_expansion_wrong_is_contradicted_and_does_no_harm(ram4, tmp_path):
    """ram4 described with handbook materials (the CFRP's axial expansion 0 /K against the data
    sheet's 1.0e-6, and the other values a handbook gives): the twin then answers a warmer +X
    face with the opposite sign, and the default fit corrected thermal_b's dx to 17.2 µm off
    on 10.3 uncompensated. The training contradicts that description (likelihood-ratio test at
    1e-2), the coefficient it asks for is near the data sheet's, its map joins the consensus,
    and no axis is harmed (2026-11-29: estimated 1.45e-6 /K; thermal_b dx 7.0 µm)."""
    import yaml

    from fbgcomp.models.physical import PhysicalModel

    d = yaml.safe_load(RAM4_MACHINE.read_text())
    d["materials"]["cfrp"].update(
        {"E_L_GPa": 125.0, "E_T_GPa": 8.0, "cte_L_per_K": 0.0, "cte_T_per_K": 30.0e-6, "k_L_W_per_mK": 5.0}
    )
    d["materials"]["cfrp"]["k_T_W_per_mK"] = 0.5
    d["materials"]["housing"].update({"cte_per_K": 12.0e-6, "k_W_per_mK": 50.0})
    machine = tmp_path / "ram4-handbook.yaml"
    machine.write_text(yaml.safe_dump(d, sort_keys=False))
    m = PhysicalModel(machine=machine).fit([ram4["thermal_a"], ram4["static_xyz"]])
    cte = m.twin_map_["cte"]
    assert cte["contradicted"] and cte["deviance"] > cte["threshold"], cte
    assert cte["estimated_per_K"][0] == pytest.approx(1.0e-6, abs=0.6e-6), cte
    assert cte["estimated_per_K"][1:] == cte["described_per_K"][1:]
    assert len(m.twin_map_["cte_members"]) == 1
    for name in ("thermal_b", "thermal_c"):
        err, peak, _ = held_out_figures(m, ram4[name])
        assert (err <= peak + 0.5).all(), (name, err, peak)
    # the member travels in the model file, checked on load, and the runtime applies the same
    from fbgcomp.models.registry import load_model

    loaded = load_model(m.save(tmp_path / "m.json"))
    assert len(loaded.twin_map_["cte_members"]) == 1
    np.testing.assert_array_equal(loaded.predict(ram4["thermal_b"]), m.predict(ram4["thermal_b"]))
