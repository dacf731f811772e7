"""The default model on a fourth independent ram (tests/data/ram5.tar.xz): a CalculiX ram guided on
two opposite faces, a locating rail on +Y and one on -Y floating along its normal (its carriages
let the box grow across Y), five gratings, five probes, the bearings offset towards +Y, a radiant
load on -X in thermal_b and forces along +Y and -X overlapping in thermal_c; described from its
data sheet (examples/machines/ram5.yaml). Built by a helper that did not read the product."""

import numpy as np
import pytest
import yaml

from fbgcomp_testing import (
    RAM5_ARCHIVE,
    RAM5_MACHINE,
    assert_twin_check,
    held_out_figures,
    read_ram5,
    unpacked,
)

# one worker runs the module (CONTRIBUTING): the twin check (at the description's resolution) and
# the default fit share one twin, built there once and not waited on from the other worker
pytestmark = pytest.mark.xdist_group("ram5")

HELD = ("thermal_b", "thermal_c", "static_x")


@pytest.mark.slow
def test_the_twin_of_ram5s_data_sheet_meets_the_twin_check_against_its_results():
    """`fbgcomp twin-check examples/machines/ram5.yaml --against ram5/results.json`: the unit-load
    compliances and grating responses within 3 %, the uniform +10 K dz within 2 % (2026-12-04 at
    the description's mesh: 25 of 25, dz 0.09 %; with the -Y rail described as locating, the
    closest the description came before a rail could float along its normal, 18 of 25: Fy dy
    -23.7 %). The twin is built at the description's resolution (1), not the coarser 0.5 of the
    other rams' checks: at 0.5 S5's small cross response to Fy (0.33 µm/kN, a sixth of S4's) is
    3.7 % off, at 1 it is 1.5 %."""
    results = unpacked(RAM5_ARCHIVE) / "results.json"
    assert_twin_check(RAM5_MACHINE, results, ("S1", "S2", "S3", "S4", "S5"), 25, resolution=1.0)


@pytest.fixture(scope="session")
def ram5():
    return read_ram5("thermal_a", "static_xyz", *HELD)


@pytest.mark.slow
def test_the_default_fit_harms_no_axis_of_ram5s_held_out_campaigns(ram5, tmp_path):
    """``fbgcomp fit thermal_a static_xyz --machine examples/machines/ram5.yaml``, judged on the
    campaigns it never saw: no axis ends with a larger max |error| than uncompensated (+0.5 µm),
    thermal_b's dz is within 2 µm and its lateral axes within 20 % of their peaks, and every axis
    moving over 50 µm within 10 % (2026-12-04: thermal_b dx / dy / dz 0.28 / 1.38 / 1.64 µm on
    5.35 / 17.7 / 66.7; thermal_c 3.68 / 6.96 / 1.70 on 95.2 / 193 / 54.6; static_x dx 6.3 on 254).
    thermal_c's loaded dy is within 5 % of its peak (3.6 %; the floor no causal correction goes
    below, benchmarks/bench_latency_floor.py, is 3.1 %): on its 1 s frames a transition publishes
    the line through the ramp's frames (ramp_line), not the last frame alone, which put one frame's
    noise, 200 N, on the sample that ended the 2200 N ramp (16.5 µm, 8.5 %).
    The rail floating along its normal is what the lateral drift rests on: described as
    locating, thermal_b's dy is 7.84 µm off (44 % of its peak)."""
    from fbgcomp.models.physical import PhysicalModel

    m = PhysicalModel(machine=RAM5_MACHINE).fit([ram5["thermal_a"], ram5["static_xyz"]])
    figures = {}
    for name in HELD:
        err, peak, cover = held_out_figures(m, ram5[name])
        figures[name] = err, peak, cover
        assert (err <= peak + 0.5).all(), (name, err, peak)
        moving = peak > 50.0
        assert (err[moving] < 0.10 * peak[moving]).all(), (name, err, peak)
    err_c, peak_c, cover_c = figures["thermal_c"]
    assert err_c[1] < 0.05 * peak_c[1], (err_c, peak_c)
    # thermal_c's dz is 0.4 µm off for 8 h (about 1 % of the housing's warming; not the zero
    # state's noise: docs/accuracy.md); the interval holds it since the zero state's error, 0.26 µm
    # SD on dz, entered it (0.77 covered before)
    assert 0.90 <= cover_c[2] <= 0.99, cover_c
    err, peak, cover = figures["thermal_b"]
    assert err[2] <= 2.0 and (err[:2] <= 0.2 * peak[:2]).all(), (err, peak)
    assert 0.90 <= cover[0] <= 0.99, cover
    assert ((figures["static_x"][2] >= 0.90) & (figures["static_x"][2] <= 0.99)).all(), figures["static_x"]

    d = yaml.safe_load(RAM5_MACHINE.read_text())
    d["supports"]["rails"][1] = {"face": "-Y", "across_mm": [-40.0, 40.0], "locating": True}
    pinned = tmp_path / "ram5-pinned.yaml"
    pinned.write_text(yaml.safe_dump(d, sort_keys=False))
    p = PhysicalModel(machine=pinned).fit([ram5["thermal_a"], ram5["static_xyz"]])
    err_pinned = held_out_figures(p, ram5["thermal_b"])[0]
    assert err[1] < 0.3 * err_pinned[1], (err, err_pinned)
    assert np.isfinite(err_pinned).all()
