"""Strain-free reference gratings: an optional fbg.csv column per sensor that compensates the
sensor with the temperature of its own gauge (eq. 3 inverted), read, aligned, used by the models
and simulated by the virtual test bench."""

from __future__ import annotations

import numpy as np
import pytest

from fbgcomp import optics
from fbgcomp.bench import virtual as bench
from fbgcomp.errors import InputError
from fbgcomp.io.campaign import read_campaign, write_campaign
from fbgcomp.models.features import FeatureMap
from fbgcomp.structure import load_machine
from test_campaign import META_YAML, default_tables, make_folder

REF_META = META_YAML.replace(
    "  - {name: S3, lambda0_nm: 1550.0, gauge_length_mm: 400}",
    "  - {name: S3, lambda0_nm: 1550.0, gauge_length_mm: 400, reference_lambda0_nm: 1552.0}",
)


def _tables_with_reference(gauge_dT):
    tables = default_tables()
    t = tables["fbg.csv"]["time_s"]
    # S3's gauge warms; its bonded grating reads that as strain, its reference grating as heat
    lam_s3 = optics.wavelength_nm(0.0 * t, 1550.0, 400.0, gauge_dT(t))
    tables["fbg.csv"]["S3_nm"] = lam_s3
    tables["fbg.csv"]["S3_ref_nm"] = optics.free_grating_wavelength_nm(gauge_dT(t), 1552.0)
    return tables


def test_free_grating_round_trip():
    dT = np.linspace(-5.0, 40.0, 7)
    lam = optics.free_grating_wavelength_nm(dT, 1552.0)
    np.testing.assert_allclose(optics.grating_temperature_change_K(lam, 1552.0), dT, atol=1e-9)
    # (alpha_f + xi) lambda = 11.2 pm/K at 1552 nm (paper eq. 3)
    assert 11.0e-3 < (lam[1] - lam[0]) / (dT[1] - dT[0]) < 11.4e-3


def test_the_reference_grating_compensates_its_sensor(tmp_path):
    def heat(t):
        return 0.2 * t  # 12 K over the minute

    c = read_campaign(make_folder(tmp_path, meta=REF_META, tables=_tables_with_reference(heat)))
    s3 = c.meta.sensor("S3")
    assert s3.temperature_probe == "S3_ref" and s3.reference_column == "S3_ref_nm"
    assert c.probe_names == ["T_bulk", "T_surf", "S3_ref"]
    a = c.aligned(zero_window_s=0.5)
    k = a.probe_names.index("S3_ref")
    np.testing.assert_allclose(a.temperature_C[:, k] - a.temperature_zero_C[k], heat(a.time_s), atol=1e-6)
    # the models' elongations: S3 compensated by its reference reads no elongation (none
    # happened); read uncompensated it would be ~12 K x 10.5 pm/K of false strain
    fmap = FeatureMap(c.meta.sensors, a.probe_names, uses_temperature_features=False)
    e = fmap.base(a.wavelength_nm, a.temperature_C, a.wavelength_zero_nm, a.temperature_zero_C)
    j = a.sensor_names.index("S3")
    assert np.abs(e[:, j]).max() < 0.05
    raw = optics.elongation_um(a.wavelength_nm[:, j], a.wavelength_zero_nm[j], 400.0)
    assert np.abs(raw).max() > 20.0
    # written and read back with its column
    again = read_campaign(write_campaign(c, tmp_path / "copy"))
    np.testing.assert_array_equal(again.fbg["S3_ref_nm"], c.fbg["S3_ref_nm"])
    assert again.meta.sensor("S3").reference_lambda0_nm == 1552.0


def test_a_reference_column_needs_its_declaration(tmp_path):
    tables = _tables_with_reference(lambda t: 0.0 * t)
    with pytest.raises(InputError) as info:
        read_campaign(make_folder(tmp_path, tables=tables))  # META_YAML: no reference
    assert info.value.column == "S3_ref_nm" and "reference_lambda0_nm" in str(info.value)
    del tables["fbg.csv"]["S3_ref_nm"]
    with pytest.raises(InputError) as info:
        read_campaign(make_folder(tmp_path, meta=REF_META, tables=tables, name="other"))
    assert info.value.column == "S3_ref_nm" and "missing column" in str(info.value)


def test_a_lost_reference_peak_is_reported_against_its_column(tmp_path):
    tables = _tables_with_reference(lambda t: 0.0 * t)
    tables["fbg.csv"]["S3_ref_nm"][30] = 1400.0
    with pytest.raises(InputError) as info:
        read_campaign(make_folder(tmp_path, meta=REF_META, tables=tables))
    assert info.value.column == "S3_ref_nm" and info.value.row == 31


def test_the_test_bench_simulates_reference_gratings():
    """bench.measure writes <sensor>_ref_nm from the grating's own temperature: compensated by
    it, the elongation is the true one within the interrogator's noise, where the paper's probe
    on another face leaves the gauge-to-probe temperature mismatch."""
    base = load_machine(None)
    sensors = [s.model_copy(update={"reference_lambda0_nm": s.lambda0_nm + 2.0}) for s in base.sensors]
    machine = base.model_copy(update={"sensors": type(base.sensors)(sensors)})
    t = np.arange(0.0, 3601.0, 1.0)
    S, P = len(sensors), len(machine.probes)
    gauge_T = 22.0 + np.outer(1 - np.exp(-t / 900.0), 2.0 + np.arange(S))  # each gauge its own
    probe_T = 22.0 + np.outer(1 - np.exp(-t / 900.0), np.full(P, 1.0))  # probes lag behind
    elong = np.outer(np.sin(t / 600.0), np.linspace(-3.0, 3.0, S))
    truth = {
        "time_s": t,
        "sensor_elongation_um": elong,
        "sensor_temperature_C": gauge_T,
        "probe_C": probe_T,
        "ttp_um": np.zeros((t.size, 3)),
        "force_N": np.zeros((t.size, 3)),
        "ambient_C": np.full(t.size, 22.0),
    }
    scenario = bench.load_scenario("thermal-36h")
    c = bench.measure(machine, scenario, truth, seed=3)
    assert all(f"{s.name}_ref_nm" in c.fbg.columns for s in sensors)
    a = c.aligned()
    true = np.column_stack([np.interp(a.time_s, t, elong[:, j]) for j in range(S)])
    for how in ("reference", "probe"):
        errs = []
        for j, s in enumerate(c.meta.sensors):
            probe = s.reference_probe if how == "reference" else sensors[j].temperature_probe
            k = a.probe_names.index(probe)
            e = optics.elongation_um(
                a.wavelength_nm[:, j],
                a.wavelength_zero_nm[j],
                s.gauge_length_mm,
                a.temperature_C[:, k] - a.temperature_zero_C[k],
            )
            errs.append(np.abs(e - (true[:, j] - true[0, j])).max())
        # 1 pm of noise on each grating is ~0.6 µm of elongation per sample
        if how == "reference":
            assert max(errs) < 2.5, errs
        else:
            assert max(errs) > 10.0, errs
