"""The campaign folder: reading and validation, alignment and zero state, atomic writing.

Reader tests build folders from plain text written here (not by ``write_campaign``), so the reader
is checked against the documented format rather than against our own writer.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
from datetime import UTC, timedelta, timezone
from pathlib import Path
from unittest import mock

import numpy as np
import pandas as pd
import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

import fbgcomp.io.campaign as campaign_module
import fbgcomp.io.campaign.tables as campaign_tables  # the reader's block size is patched there
from fbgcomp.errors import InputError
from fbgcomp.io.campaign import (
    AlignedCampaign,
    Campaign,
    CampaignMeta,
    SensorSpec,
    read_campaign,
    write_campaign,
)

META_YAML = """\
name: thermal_a
kind: thermal
description: 36 h thermal run, ambient cycling
start: 2026-01-12T08:00:00Z
machine: ram prototype
seed: 7
sensors:
  - {name: S1, lambda0_nm: 1530.0, gauge_length_mm: 500, photoelastic: 0.22, thermo_optic_per_K: 6.67e-6,
     fibre_cte_per_K: 0.55e-6, face: +X, z_start_mm: 100, z_end_mm: 600, temperature_probe: T_surf}
  - {name: S2, lambda0_nm: 1540.0, gauge_length_mm: 500, face: -X, temperature_probe: T_bulk}
  - {name: S3, lambda0_nm: 1550.0, gauge_length_mm: 400}
temperature_probes:
  - {name: T_bulk, location: "inside the +Y wall at mid-height"}
  - {name: T_surf, location: "+X face"}
reference: {instrument: laser interferometer, point: TTP, units: um}
"""


def csv_text(columns: dict) -> str:
    names = list(columns)
    n = len(columns[names[0]])
    rows = [",".join(names)]
    rows += [",".join(repr(float(columns[c][i])) for c in names) for i in range(n)]
    return "\n".join(rows) + "\n"


def default_tables() -> dict:
    t = np.arange(61.0)  # FBG every 1 s
    tt = np.arange(0.0, 61.0, 10)  # probes every 10 s
    tr = np.arange(0.0, 61.0, 2)  # interferometer every 2 s
    return {
        "fbg.csv": {
            "time_s": t,
            "S1_nm": 1530 + 1e-3 * t,
            "S2_nm": 1540 - 5e-4 * t,
            "S3_nm": 1550 + 2e-4 * t,
        },
        "temperatures.csv": {"time_s": tt, "T_bulk_C": 20 + 0.1 * tt, "T_surf_C": 21 + 0.05 * tt},
        "reference.csv": {"time_s": tr, "dx_um": 0.5 * tr, "dy_um": -0.25 * tr, "dz_um": np.ones_like(tr)},
    }


def make_folder(
    root: Path,
    *,
    meta: str = META_YAML,
    tables: dict | None = None,
    loads: dict | None = None,
    name: str = "camp",
) -> Path:
    folder = Path(root) / name
    folder.mkdir(parents=True)
    (folder / "campaign.yaml").write_text(meta, encoding="utf-8")
    for file, columns in (tables or default_tables()).items():
        (folder / file).write_text(csv_text(columns), encoding="utf-8")
    if loads is not None:
        (folder / "loads.csv").write_text(csv_text(loads), encoding="utf-8")
    return folder


def set_cell(folder: Path, file: str, row: int, column: str, text: str) -> None:
    """Replace the text of one cell (1-based data row) of a CSV."""
    path = folder / file
    lines = path.read_text(encoding="utf-8").split("\n")
    col = lines[0].split(",").index(column)
    cells = lines[row].split(",")
    cells[col] = text
    lines[row] = ",".join(cells)
    path.write_text("\n".join(lines), encoding="utf-8")


def expect_error(
    folder, file: str, row: int | None = None, column: str | None = None, match: str | None = None
) -> InputError:
    with pytest.raises(InputError) as info:
        read_campaign(folder)
    err = info.value
    line = str(err)
    assert "\n" not in line
    assert Path(err.file).name == file, line
    assert err.row == row, line
    assert err.column == column, line
    assert file in line
    if row is not None:
        assert f"row {row} (line {row + 1})" in line
    if column is not None:
        assert column in line
    if match is not None:
        assert re.search(match, err.message), line
    return err


@pytest.fixture
def folder(tmp_path) -> Path:
    return make_folder(tmp_path)


# --------------------------------------------------------------------------------------------
# Reading a valid folder
# --------------------------------------------------------------------------------------------


def test_reads_valid_folder(folder):
    c = read_campaign(folder)
    assert c.path == folder
    assert c.name == "thermal_a"
    assert c.meta.kind == "thermal"
    assert c.meta.start.utcoffset() == timedelta(0)
    assert c.sensor_names == ["S1", "S2", "S3"]
    assert c.probe_names == ["T_bulk", "T_surf"]
    s1 = c.meta.sensor("S1")
    assert (s1.lambda0_nm, s1.gauge_length_mm, s1.face, s1.temperature_probe) == (
        1530.0,
        500.0,
        "+X",
        "T_surf",
    )
    assert s1.thermo_optic_per_K == 6.67e-6 and s1.fibre_cte_per_K == 0.55e-6
    s3 = c.meta.sensor("S3")
    assert s3.temperature_probe is None and s3.face is None and s3.photoelastic == 0.22
    assert c.meta.model_extra == {"machine": "ram prototype", "seed": 7}
    assert list(c.fbg.columns) == ["time_s", "S1_nm", "S2_nm", "S3_nm"]
    assert len(c.fbg) == 61 and len(c.temperatures) == 7 and len(c.reference) == 31
    assert c.fbg["S2_nm"].iloc[10] == 1540 - 5e-3
    assert c.loads is None
    assert all(dtype == np.float64 for dtype in c.fbg.dtypes)


def test_reads_columns_in_any_order_and_returns_canonical_order(tmp_path):
    tables = default_tables()
    tables["fbg.csv"] = {k: tables["fbg.csv"][k] for k in ("S3_nm", "time_s", "S1_nm", "S2_nm")}
    tables["reference.csv"] = {k: tables["reference.csv"][k] for k in ("dz_um", "dx_um", "time_s", "dy_um")}
    c = read_campaign(make_folder(tmp_path, tables=tables))
    assert list(c.fbg.columns) == ["time_s", "S1_nm", "S2_nm", "S3_nm"]
    assert list(c.reference.columns) == ["time_s", "dx_um", "dy_um", "dz_um"]
    assert c.reference["dx_um"].iloc[3] == 3.0


def test_accepts_crlf_bom_quoted_header_and_trailing_blank_lines(folder):
    path = folder / "reference.csv"
    text = path.read_text()
    header, rest = text.split("\n", 1)
    header = ",".join(f'"{name}"' for name in header.split(","))
    path.write_bytes(b"\xef\xbb\xbf" + (header + "\n" + rest + "\n\n  \n").replace("\n", "\r\n").encode())
    c = read_campaign(folder)
    assert len(c.reference) == 31
    assert c.reference["dy_um"].iloc[-1] == -15.0


def test_loads_are_optional_and_read_when_present(tmp_path):
    loads = {
        "time_s": np.array([0.0, 30.0, 60.0]),
        "fx_N": np.array([0.0, 1000.0, 2000.0]),
        "fy_N": np.zeros(3),
        "fz_N": np.zeros(3),
    }
    c = read_campaign(make_folder(tmp_path, loads=loads))
    assert list(c.loads.columns) == ["time_s", "fx_N", "fy_N", "fz_N"]
    assert c.loads["fx_N"].tolist() == [0.0, 1000.0, 2000.0]


def test_undeclared_temperature_column_is_a_probe(tmp_path):
    tables = default_tables()
    tables["temperatures.csv"]["T_amb_C"] = np.full(7, 25.0)
    c = read_campaign(make_folder(tmp_path, tables=tables))
    assert c.meta.probe_names == ["T_bulk", "T_surf"]
    assert c.probe_names == ["T_bulk", "T_surf", "T_amb"]
    assert c.undeclared_probes == ["T_amb"]
    assert any("T_amb_C" in p and "not declared" in p for p in c.summary()["problems"])


def test_yaml_exponent_without_dot_is_a_number(tmp_path):
    meta = META_YAML.replace("thermo_optic_per_K: 6.67e-6", "thermo_optic_per_K: 7e-6")
    c = read_campaign(make_folder(tmp_path, meta=meta))
    assert c.meta.sensor("S1").thermo_optic_per_K == 7e-6


# --------------------------------------------------------------------------------------------
# Folder and file level errors
# --------------------------------------------------------------------------------------------


def test_missing_folder(tmp_path):
    with pytest.raises(InputError, match="campaign folder not found") as info:
        read_campaign(tmp_path / "nowhere")
    assert info.value.file == str(tmp_path / "nowhere")


@pytest.mark.parametrize("file", ["campaign.yaml", "fbg.csv", "temperatures.csv", "reference.csv"])
def test_missing_file(folder, file):
    (folder / file).unlink()
    expect_error(folder, file, match="missing file")


@pytest.mark.parametrize("file", ["fbg.csv", "temperatures.csv", "reference.csv"])
def test_empty_file(folder, file):
    (folder / file).write_bytes(b"")
    expect_error(folder, file, match=r"empty file \(0 bytes\)")


def test_empty_yaml(folder):
    (folder / "campaign.yaml").write_bytes(b"")
    expect_error(folder, "campaign.yaml", match="empty file")


def test_header_only_file(folder):
    (folder / "reference.csv").write_text("time_s,dx_um,dy_um,dz_um\n")
    expect_error(folder, "reference.csv", match="no data rows")


@pytest.mark.parametrize("delimiter, shown", [(";", "';'"), ("\t", "tab")])
def test_wrong_delimiter(folder, delimiter, shown):
    path = folder / "fbg.csv"
    path.write_text(path.read_text().replace(",", delimiter))
    err = expect_error(folder, "fbg.csv", match="expected comma-separated columns")
    assert f"found {shown}" in err.message


def test_wrong_delimiter_in_a_data_row(folder):
    path = folder / "fbg.csv"
    lines = path.read_text().split("\n")
    lines[5] = lines[5].replace(",", ";")
    path.write_text("\n".join(lines))
    expect_error(folder, "fbg.csv", row=5, match="expected comma-separated columns, found ';'")


def test_row_with_too_few_values(folder):
    path = folder / "temperatures.csv"
    lines = path.read_text().split("\n")
    lines[3] = lines[3].rsplit(",", 1)[0]
    path.write_text("\n".join(lines))
    expect_error(folder, "temperatures.csv", row=3, column="T_surf_C", match="row has 2 values, expected 3")


def test_row_with_too_many_values(folder):
    path = folder / "temperatures.csv"
    lines = path.read_text().split("\n")
    lines[2] += ",4.0"
    path.write_text("\n".join(lines))
    expect_error(folder, "temperatures.csv", row=2, match="row has 4 values, expected 3")


def test_blank_line_inside_data(folder):
    path = folder / "reference.csv"
    lines = path.read_text().split("\n")
    lines.insert(4, "")
    path.write_text("\n".join(lines))
    expect_error(folder, "reference.csv", row=4, match="empty row")


def test_non_utf8_bytes(folder):
    path = folder / "fbg.csv"
    lines = path.read_bytes().split(b"\n")
    cells = lines[7].split(b",")
    cells[2] = cells[2][:2] + b"\xff" + cells[2][2:]
    lines[7] = b",".join(cells)
    path.write_bytes(b"\n".join(lines))
    expect_error(folder, "fbg.csv", row=7, column="S2_nm", match="not UTF-8")


def test_duplicate_header_column(folder):
    path = folder / "reference.csv"
    text = path.read_text().replace("dz_um", "dx_um", 1)
    path.write_text(text)
    expect_error(folder, "reference.csv", column="dx_um", match="appears twice")


# --------------------------------------------------------------------------------------------
# campaign.yaml errors
# --------------------------------------------------------------------------------------------


def test_yaml_syntax_error_names_its_line(tmp_path):
    meta = META_YAML.replace(
        "  - {name: S3, lambda0_nm: 1550.0, gauge_length_mm: 400}",
        "  - {name: S3, lambda0_nm: 1550.0, gauge_length_mm: 400",
    )
    err = expect_error(make_folder(tmp_path, meta=meta), "campaign.yaml", match="YAML syntax error at line")
    line = int(re.search(r"line (\d+)", err.message).group(1))
    assert line in (11, 12)  # the unclosed flow mapping on line 11 is detected on line 12


def test_yaml_duplicate_key(tmp_path):
    meta = META_YAML.replace("seed: 7\n", "seed: 7\nname: other\n")
    expect_error(make_folder(tmp_path, meta=meta), "campaign.yaml", match=r"line 7.*duplicate key 'name'")


def test_yaml_top_level_not_a_mapping(folder):
    (folder / "campaign.yaml").write_text("- just\n- a list\n")
    expect_error(folder, "campaign.yaml", match="expected a mapping")


@pytest.mark.parametrize(
    "edit, field, match",
    [
        (("lambda0_nm: 1540.0, ", ""), "field sensors[1].lambda0_nm", "required field is missing"),
        (("lambda0_nm: 1540.0", "lambda0_nm: abc"), "field sensors[1].lambda0_nm", "valid number.*'abc'"),
        (("lambda0_nm: 1540.0", "lambda0_nm: '1540'"), "field sensors[1].lambda0_nm", "valid number"),
        (("kind: thermal", "kind: dynamic"), "field kind", "'thermal', 'static' or 'combined'"),
        (("start: 2026-01-12T08:00:00Z", "start: 2026-01-12T08:00:00"), "field start", "timezone"),
        (("start: 2026-01-12T08:00:00Z\n", ""), "field start", "required field is missing"),
        (("{name: S3,", "{name: S1,"), "field sensors[2].name", "duplicate sensor name 'S1'.*sensors\\[0\\]"),
        (
            ("temperature_probe: T_bulk", "temperature_probe: T_flange"),
            "field sensors[1].temperature_probe",
            "'T_flange'.*not declared.*T_bulk, T_surf",
        ),
        (("{name: T_surf,", "{name: T_bulk,"), "field temperature_probes[1].name", "duplicate probe"),
        (("face: -X", "face: left"), "field sensors[1].face", "'left'"),
        (
            ("gauge_length_mm: 400", "gauge_length_mm: -400"),
            "field sensors[2].gauge_length_mm",
            "greater than 0",
        ),
        (("units: um", "units: mm"), "field reference.units", "'um'"),
    ],
)
def test_yaml_schema_errors(tmp_path, edit, field, match):
    old, new = edit
    assert old in META_YAML
    folder = make_folder(tmp_path, meta=META_YAML.replace(old, new, 1))
    expect_error(folder, "campaign.yaml", column=field, match=match)


def test_yaml_no_sensors(tmp_path):
    meta = re.sub(r"sensors:\n(  - .*\n(     .*\n)?)+", "sensors: []\n", META_YAML)
    assert "sensors: []" in meta
    expect_error(
        make_folder(tmp_path, meta=meta), "campaign.yaml", column="field sensors", match="at least 1"
    )


# --------------------------------------------------------------------------------------------
# Column errors
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "file, column",
    [
        ("fbg.csv", "S2_nm"),
        ("fbg.csv", "time_s"),
        ("temperatures.csv", "T_surf_C"),
        ("reference.csv", "dy_um"),
        ("loads.csv", "fz_N"),
    ],
)
def test_missing_column(tmp_path, file, column):
    tables = default_tables()
    loads = {"time_s": np.arange(3.0), "fx_N": np.zeros(3), "fy_N": np.zeros(3), "fz_N": np.zeros(3)}
    target = loads if file == "loads.csv" else tables[file]
    del target[column]
    folder = make_folder(tmp_path, tables=tables, loads=loads)
    expect_error(folder, file, column=column, match=f"missing column '{column}'")


def test_unknown_sensor_column(tmp_path):
    tables = default_tables()
    tables["fbg.csv"]["S6_nm"] = np.full(61, 1560.0)
    expect_error(
        make_folder(tmp_path, tables=tables),
        "fbg.csv",
        column="S6_nm",
        match="unknown sensor 'S6'.*declared: S1, S2, S3",
    )


def test_extra_columns_outside_the_format_are_ignored_and_reported(tmp_path):
    # The format names the columns a file must hold, not the only ones it may hold (another
    # tool's campaign may carry a status flag); an extra *_nm column is still an unknown sensor.
    tables = default_tables()
    tables["reference.csv"]["status"] = np.zeros(31)
    tables["fbg.csv"]["channel"] = np.ones(61)
    c = read_campaign(make_folder(tmp_path, tables=tables))
    assert "status" not in c.reference.columns and "channel" not in c.fbg.columns
    problems = c.summary()["problems"]
    assert any("reference.csv: column 'status'" in p for p in problems)
    assert any("fbg.csv: column 'channel'" in p for p in problems)
    assert c.aligned().reference_um.shape[1] == 3
    # still checked like every other column
    again = make_folder(tmp_path / "again", tables=tables)
    set_cell(again, "reference.csv", 3, "status", "ok")
    with pytest.raises(InputError, match="status"):
        read_campaign(again)


# --------------------------------------------------------------------------------------------
# Cell errors
# --------------------------------------------------------------------------------------------


def test_non_numeric_cell(folder):
    set_cell(folder, "fbg.csv", 12, "S2_nm", "1540.0x1")
    expect_error(folder, "fbg.csv", row=12, column="S2_nm", match="not a number: '1540.0x1'")


def test_non_numeric_time(folder):
    set_cell(folder, "temperatures.csv", 4, "time_s", "12:00")
    expect_error(folder, "temperatures.csv", row=4, column="time_s", match="'12:00'")


def test_empty_cell(folder):
    set_cell(folder, "reference.csv", 9, "dz_um", "")
    expect_error(folder, "reference.csv", row=9, column="dz_um", match="empty cell")


@pytest.mark.parametrize("text", ["nan", "NaN", "inf", "-Infinity", "1e999"])
def test_non_finite_cell(folder, text):
    set_cell(folder, "temperatures.csv", 6, "T_bulk_C", text)
    err = expect_error(folder, "temperatures.csv", row=6, column="T_bulk_C")
    assert repr(text) in err.message and ("finite" in err.message or "infinity" in err.message)


def test_decreasing_time(folder):
    set_cell(folder, "reference.csv", 8, "time_s", "11.0")
    # row 7 is t = 12 s, row 8 now 11 s
    expect_error(
        folder, "reference.csv", row=8, column="time_s", match="time goes backwards: 11.0 s after 12.0 s"
    )


def test_duplicated_time(folder):
    set_cell(folder, "fbg.csv", 21, "time_s", "19.0")
    expect_error(
        folder, "fbg.csv", row=21, column="time_s", match=r"duplicated time 19.0 s \(same as row 20\)"
    )


def test_wavelength_outside_band(folder):
    set_cell(folder, "fbg.csv", 33, "S3_nm", "1555.25")
    expect_error(
        folder, "fbg.csv", row=33, column="S3_nm", match=r"wavelength 1555.25 nm is outside .*1550 ± 5 nm"
    )


def test_wavelength_just_inside_band_is_accepted(folder):
    set_cell(folder, "fbg.csv", 33, "S3_nm", "1545.0")
    assert read_campaign(folder).fbg["S3_nm"].iloc[32] == 1545.0


# --------------------------------------------------------------------------------------------
# Alignment and zero state
# --------------------------------------------------------------------------------------------


def staggered_campaign(loads: dict | None = None) -> Campaign:
    """Different clocks: FBG 10 Hz from 3 s, probes 10 s to 95 s, interferometer 1 s to 120 s."""
    tf = np.round(np.arange(3.0, 100.0001, 0.1), 10)
    tt = np.arange(0.0, 95.0001, 10.0)
    tt = np.append(tt[tt < 95], 95.0)
    tr = np.arange(0.0, 120.0001, 1.0)
    meta = yaml.load(META_YAML, Loader=yaml.SafeLoader)
    return Campaign.from_arrays(
        meta,
        fbg={
            "time_s": tf,
            "S1_nm": 1530 + 1e-3 * tf,
            "S2_nm": 1540 - 2e-3 * tf,
            "S3_nm": np.full_like(tf, 1550.5),
        },
        temperatures={"time_s": tt, "T_bulk_C": 20 + 0.1 * tt, "T_surf_C": 30 - 0.05 * tt},
        reference={"time_s": tr, "dx_um": 2.0 * tr, "dy_um": 100 - tr, "dz_um": np.zeros_like(tr)},
        loads=loads,
    )


def test_alignment_on_reference_clock_with_exact_linear_interpolation():
    a = staggered_campaign().aligned()
    assert isinstance(a, AlignedCampaign)
    assert a.dropped["overlap_s"] == (3.0, 95.0)
    assert a.dropped["before"] == 3 and a.dropped["after"] == 25  # 0,1,2 s and 96..120 s
    np.testing.assert_array_equal(a.time_s, np.arange(3.0, 95.0001))
    assert a.sensor_names == ["S1", "S2", "S3"] and a.probe_names == ["T_bulk", "T_surf"]
    assert a.wavelength_nm.shape == (93, 3) and a.temperature_C.shape == (93, 2)
    np.testing.assert_allclose(a.wavelength_nm[:, 0], 1530 + 1e-3 * a.time_s, rtol=0, atol=1e-9)
    np.testing.assert_allclose(a.wavelength_nm[:, 1], 1540 - 2e-3 * a.time_s, rtol=0, atol=1e-9)
    assert np.all(a.wavelength_nm[:, 2] == 1550.5)
    np.testing.assert_allclose(a.temperature_C[:, 0], 20 + 0.1 * a.time_s, rtol=0, atol=1e-12)
    np.testing.assert_allclose(a.temperature_C[:, 1], 30 - 0.05 * a.time_s, rtol=0, atol=1e-12)
    assert a.loads_N is None and a.dropped["loads_outside"] is None
    assert len(a) == 93


def test_alignment_never_extrapolates():
    c = staggered_campaign()
    a = c.aligned()
    for frame in (c.fbg, c.temperatures, c.reference):
        assert a.time_s[0] >= frame["time_s"].iloc[0]
        assert a.time_s[-1] <= frame["time_s"].iloc[-1]
    # linear interpolation stays within the samples it interpolates; extrapolation would not
    assert a.temperature_C[:, 0].max() <= c.temperatures["T_bulk_C"].max()
    assert a.wavelength_nm[:, 0].min() >= c.fbg["S1_nm"].min()


def test_zero_state_is_mean_of_first_10_s_of_each_signal():
    a = staggered_campaign().aligned()
    # FBG: samples 3.0 .. 13.0 s (101 samples), mean time 8 s
    np.testing.assert_allclose(a.wavelength_zero_nm, [1530 + 8e-3, 1540 - 16e-3, 1550.5], rtol=0, atol=1e-9)
    # probes: samples at 0 and 10 s, mean time 5 s
    np.testing.assert_allclose(a.temperature_zero_C, [20.5, 29.75], rtol=0, atol=1e-12)
    # interferometer: 0 .. 10 s on its own clock (before the overlap), mean time 5 s
    np.testing.assert_allclose(a.reference_zero_um, [10.0, 95.0, 0.0], rtol=0, atol=1e-12)
    np.testing.assert_allclose(a.reference_um[:, 0], 2.0 * a.time_s - 10.0, atol=1e-12)
    np.testing.assert_allclose(a.reference_um[:, 1], 5.0 - a.time_s, atol=1e-12)
    np.testing.assert_allclose(a.delta_temperature_C[0], [0.3 - 0.5, -0.15 + 0.25], atol=1e-12)


@pytest.mark.parametrize(
    "window, t_mean_fbg, t_mean_probe, t_mean_ref",
    [
        (0.0, 3.0, 0.0, 0.0),  # first sample only
        (25.0, 15.5, 10.0, 12.5),  # probes 0, 10, 20 s; reference 0..25 s; FBG 3..28 s
    ],
)
def test_zero_window_is_configurable(window, t_mean_fbg, t_mean_probe, t_mean_ref):
    a = staggered_campaign().aligned(zero_window_s=window)
    assert a.zero_window_s == window
    np.testing.assert_allclose(a.wavelength_zero_nm[0], 1530 + 1e-3 * t_mean_fbg, atol=1e-9)
    np.testing.assert_allclose(a.temperature_zero_C[0], 20 + 0.1 * t_mean_probe, atol=1e-12)
    np.testing.assert_allclose(a.reference_zero_um[0], 2.0 * t_mean_ref, atol=1e-12)


@pytest.mark.parametrize("window", [-1.0, float("nan"), "ten"])
def test_bad_zero_window(window):
    with pytest.raises(InputError, match="zero window"):
        staggered_campaign().aligned(zero_window_s=window)


def test_loads_interpolated_inside_their_range_and_nan_outside():
    tl = np.array([10.0, 50.0, 60.0])
    loads = {
        "time_s": tl,
        "fx_N": np.array([0.0, 4000.0, 4000.0]),
        "fy_N": np.zeros(3),
        "fz_N": np.array([-1.0, -1.0, -1.0]),
    }
    a = staggered_campaign(loads).aligned()
    # loads never narrow the overlap
    assert a.dropped["overlap_s"] == (3.0, 95.0)
    inside = (a.time_s >= 10) & (a.time_s <= 60)
    np.testing.assert_allclose(
        a.loads_N[inside, 0], np.interp(a.time_s[inside], tl, [0, 4000, 4000]), atol=1e-9
    )
    assert a.loads_N[a.time_s == 30.0, 0][0] == 2000.0
    assert np.isnan(a.loads_N[~inside]).all()
    assert a.dropped["loads_outside"] == int((~inside).sum()) == 7 + 35


def test_no_overlap_is_an_input_error():
    c = staggered_campaign()
    c.reference["time_s"] = c.reference["time_s"] + 1000.0
    with pytest.raises(InputError, match="do not overlap"):
        c.aligned()


def test_no_reference_sample_inside_overlap():
    c = staggered_campaign()
    c.reference = pd.DataFrame(
        {"time_s": [0.5, 99.5], "dx_um": [0.0, 1.0], "dy_um": [0.0, 1.0], "dz_um": [0.0, 1.0]}
    )
    c.fbg = c.fbg[(c.fbg["time_s"] >= 40) & (c.fbg["time_s"] <= 41)]
    with pytest.raises(InputError, match="no reference sample"):
        c.aligned()


# --------------------------------------------------------------------------------------------
# summary()
# --------------------------------------------------------------------------------------------


def test_summary_reports_files_overlap_and_problems(tmp_path):
    tables = default_tables()
    t = np.concatenate([np.arange(0.0, 20.0), np.arange(120.0, 161.0)])
    tables["fbg.csv"] = {
        "time_s": t,
        "S1_nm": 1530 + 1e-4 * t,
        "S2_nm": np.full_like(t, 1540.0),
        "S3_nm": np.full_like(t, 1550.0),
    }
    tables["temperatures.csv"]["T_amb_C"] = np.full(7, 24.5)
    meta = META_YAML.replace("gauge_length_mm: 400}", "gauge_length_mm: 400, colour: blue}")
    c = read_campaign(make_folder(tmp_path, tables=tables, meta=meta))
    s = c.summary()
    json.dumps(s)  # inspect --json must be able to print it
    fbg = s["files"]["fbg.csv"]
    assert fbg["rows"] == 61 and fbg["start_s"] == 0.0 and fbg["end_s"] == 160.0
    assert fbg["duration_s"] == 160.0 and fbg["median_interval_s"] == 1.0 and fbg["rate_hz"] == 1.0
    assert fbg["gaps"] == 1
    assert fbg["columns"]["S1_nm"] == {"min": 1530.0, "max": 1530 + 1e-4 * 160}
    temps = s["files"]["temperatures.csv"]
    assert temps["median_interval_s"] == 10.0 and temps["rate_hz"] == pytest.approx(0.1)
    assert s["overlap_s"] == [0.0, 60.0]
    assert s["reference_outside_overlap"] == {"before": 0, "after": 0}
    assert s["probes"] == ["T_bulk", "T_surf", "T_amb"] and s["undeclared_probes"] == ["T_amb"]
    assert [x["name"] for x in s["sensors"]] == ["S1", "S2", "S3"]
    problems = "\n".join(s["problems"])
    assert "fbg.csv: 1 gap(s)" in problems and "longest 101 s" in problems
    assert "before row 21 (t = 120 s)" in problems
    assert c.gaps() == {"fbg.csv": [(19.0, 120.0)]}
    assert "T_amb_C" in problems
    assert "'colour'" in problems
    text = c.summary_text()
    assert "fbg.csv: 61 rows" in text and "T_amb_C" in text and "S3 (uncompensated)" in text


def test_summary_counts_reference_outside_overlap_and_uncovered_loads():
    loads = {"time_s": np.array([50.0, 60.0]), "fx_N": np.zeros(2), "fy_N": np.zeros(2), "fz_N": np.zeros(2)}
    s = staggered_campaign(loads).summary()
    assert s["overlap_s"] == [3.0, 95.0]
    assert s["reference_outside_overlap"] == {"before": 3, "after": 25}
    assert s["files"]["loads.csv"]["rows"] == 2
    assert any("loads.csv covers 50 to 60 s" in p for p in s["problems"])


# --------------------------------------------------------------------------------------------
# from_arrays and writing
# --------------------------------------------------------------------------------------------


def test_from_arrays_validates_like_the_reader():
    meta = yaml.load(META_YAML, Loader=yaml.SafeLoader)
    tables = default_tables()
    good = dict(
        fbg=tables["fbg.csv"], temperatures=tables["temperatures.csv"], reference=tables["reference.csv"]
    )
    Campaign.from_arrays(meta, **good)

    bad = dict(good, fbg={k: v for k, v in tables["fbg.csv"].items() if k != "S1_nm"})
    with pytest.raises(InputError) as info:
        Campaign.from_arrays(meta, **bad)
    assert (info.value.file, info.value.column) == ("fbg.csv", "S1_nm")

    reference = dict(tables["reference.csv"], dx_um=tables["reference.csv"]["dx_um"].copy())
    reference["dx_um"][4] = np.nan
    with pytest.raises(InputError) as info:
        Campaign.from_arrays(meta, **dict(good, reference=reference))
    assert (info.value.file, info.value.row, info.value.column) == ("reference.csv", 5, "dx_um")

    with pytest.raises(InputError, match="not numeric"):
        Campaign.from_arrays(
            meta, **dict(good, temperatures=dict(tables["temperatures.csv"], T_bulk_C=["warm"] * 7))
        )
    with pytest.raises(InputError, match="cannot make a table"):
        Campaign.from_arrays(
            meta, **dict(good, temperatures=dict(tables["temperatures.csv"], T_bulk_C=np.zeros(3)))
        )
    with pytest.raises(InputError) as info:
        Campaign.from_arrays(dict(meta, kind="dynamic"), **good)
    assert info.value.column == "field kind"


def test_write_keeps_every_digit_of_a_wavelength(tmp_path):
    c = read_campaign(make_folder(tmp_path))
    c.fbg.loc[5, "S1_nm"] = 1530.1234567
    c.fbg.loc[6, "S1_nm"] = 1530.123456789012
    out = write_campaign(c, tmp_path / "copy")
    assert ",1530.1234567," in (out / "fbg.csv").read_text()
    back = read_campaign(out)
    assert back.fbg.loc[5, "S1_nm"] == 1530.1234567
    assert back.fbg.loc[6, "S1_nm"] == 1530.123456789012


def test_unicode_metadata_and_extra_keys_round_trip(tmp_path):
    c = read_campaign(make_folder(tmp_path, name="src"))
    meta = c.meta.model_dump()
    # NEL and LINE SEPARATOR are YAML line breaks: written raw they would come back as spaces
    meta.update(description="Prüfstand – 36 h Ωµ°C\x85next\u2028line", scenario={"ü": [1, "1e5"]}, notes=None)
    edited = Campaign.from_arrays(meta, fbg=c.fbg, temperatures=c.temperatures, reference=c.reference)
    back = read_campaign(write_campaign(edited, tmp_path / "copy"))
    assert back.meta.description == meta["description"]
    assert back.meta.model_extra == {
        "machine": "ram prototype",
        "seed": 7,
        "scenario": {"ü": [1, "1e5"]},
        "notes": None,
    }


def assert_same_campaign(a: Campaign, b: Campaign) -> None:
    assert a.meta.model_dump() == b.meta.model_dump()
    assert a.meta.start.utcoffset() == b.meta.start.utcoffset()
    for name in ("fbg", "temperatures", "reference"):
        pd.testing.assert_frame_equal(getattr(a, name), getattr(b, name), check_exact=True)
    assert (a.loads is None) == (b.loads is None)
    if a.loads is not None:
        pd.testing.assert_frame_equal(a.loads, b.loads, check_exact=True)


def test_write_replaces_existing_campaign_and_leaves_no_temporary(tmp_path):
    original = read_campaign(make_folder(tmp_path, name="src"))
    target = tmp_path / "out" / "camp"
    write_campaign(original, target)
    edited = original.validate()
    edited.reference["dz_um"] = 7.0
    write_campaign(edited, target)
    assert read_campaign(target).reference["dz_um"].eq(7.0).all()
    assert sorted(p.name for p in target.parent.iterdir()) == ["camp"]
    assert sorted(p.name for p in target.iterdir()) == [
        "campaign.yaml",
        "fbg.csv",
        "reference.csv",
        "temperatures.csv",
    ]


def test_failed_write_leaves_existing_folder_intact(tmp_path):
    c = read_campaign(make_folder(tmp_path, name="src"))
    target = tmp_path / "out"
    write_campaign(c, target)
    before = {p.name: p.read_bytes() for p in target.iterdir()}
    # metadata PyYAML cannot represent: the CSVs are already written when the YAML fails
    broken = Campaign(
        path=None,
        meta=c.meta.model_copy(update={"notes": object()}),
        fbg=c.fbg,
        temperatures=c.temperatures,
        reference=c.reference,
    )
    with pytest.raises(InputError, match="cannot be written as YAML"):
        write_campaign(broken, target)
    assert {p.name: p.read_bytes() for p in target.iterdir()} == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out", "src"]

    invalid = c.validate()
    invalid.fbg.loc[3, "S2_nm"] = np.inf
    with pytest.raises(InputError) as info:
        write_campaign(invalid, target)
    assert (info.value.file, info.value.row, info.value.column) == ("fbg.csv", 4, "S2_nm")
    assert {p.name: p.read_bytes() for p in target.iterdir()} == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out", "src"]


def test_write_refuses_to_replace_a_folder_that_is_not_a_campaign(tmp_path):
    c = read_campaign(make_folder(tmp_path, name="src"))
    precious = tmp_path / "results"
    precious.mkdir()
    (precious / "thesis.tex").write_text("years of work")
    with pytest.raises(InputError, match="not a campaign folder"):
        write_campaign(c, precious)
    assert (precious / "thesis.tex").read_text() == "years of work"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["results", "src"]


# --------------------------------------------------------------------------------------------
# Property tests
# --------------------------------------------------------------------------------------------

_FIELDS = set(CampaignMeta.model_fields)
_names = st.from_regex(r"[A-Za-z][A-Za-z0-9_]{0,5}", fullmatch=True)
_yaml_values = st.recursive(
    st.none()
    | st.booleans()
    | st.integers(-(10**12), 10**12)
    | st.floats(allow_nan=False, allow_infinity=False)
    | st.text(max_size=12),
    lambda inner: st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=6), inner, max_size=3),
    max_leaves=6,
)
_finite = st.floats(allow_nan=False, allow_infinity=False)
# Inside the reader's physical bounds (campaign.VALUE_BOUNDS): anything else is a bad cell.
_temperature = st.floats(-273.15, 1000.0)
_displacement = st.floats(-1e6, 1e6, exclude_min=True, exclude_max=True)
_force = st.floats(-1e7, 1e7, exclude_min=True, exclude_max=True)


def _times(n):
    return st.lists(st.floats(-1e7, 1e7, allow_nan=False), min_size=n, max_size=n, unique=True).map(
        lambda v: np.array(sorted(v), dtype=float)
    )


@st.composite
def campaigns(draw) -> Campaign:
    sensors = draw(st.lists(_names, min_size=1, max_size=4, unique=True))
    probes = draw(st.lists(_names, max_size=3, unique=True))
    sensor_specs = []
    for name in sensors:
        spec = {
            "name": name,
            "lambda0_nm": draw(st.floats(1000, 2000)),
            "gauge_length_mm": draw(st.floats(1, 2000)),
        }
        if draw(st.booleans()):
            spec.update(
                photoelastic=draw(st.floats(0, 0.5)),
                face=draw(st.sampled_from(["+X", "-X", "+Y", "-Y", "+Z", "-Z"])),
                z_start_mm=draw(_finite),
                z_end_mm=draw(_finite),
            )
        if probes and draw(st.booleans()):
            spec["temperature_probe"] = draw(st.sampled_from(probes))
        sensor_specs.append(spec)
    meta = {
        "name": draw(st.text(min_size=1, max_size=20)),
        "kind": draw(st.sampled_from(["thermal", "static", "combined"])),
        "description": draw(st.text(max_size=40)),
        "start": draw(
            st.datetimes(
                timezones=st.sampled_from(
                    [UTC, timezone(timedelta(hours=5, minutes=30)), timezone(timedelta(hours=-8))]
                )
            )
        ),
        "sensors": sensor_specs,
        "temperature_probes": [
            {"name": p, **({"location": draw(st.text(max_size=20))} if draw(st.booleans()) else {})}
            for p in probes
        ],
        **draw(st.dictionaries(_names.filter(lambda k: k not in _FIELDS), _yaml_values, max_size=3)),
    }
    n_fbg, n_temp, n_ref = (draw(st.integers(1, 12)) for _ in range(3))
    fbg = {"time_s": draw(_times(n_fbg))}
    for spec in sensor_specs:
        offsets = draw(hnp.arrays(np.float64, n_fbg, elements=st.floats(-4.9, 4.9)))
        fbg[f"{spec['name']}_nm"] = spec["lambda0_nm"] + offsets
    undeclared = draw(st.lists(_names.filter(lambda p: p not in probes), max_size=2, unique=True))
    temperatures = {"time_s": draw(_times(n_temp))}
    for p in probes + undeclared:
        temperatures[f"{p}_C"] = draw(hnp.arrays(np.float64, n_temp, elements=_temperature))
    reference = {"time_s": draw(_times(n_ref))}
    for column in ("dx_um", "dy_um", "dz_um"):
        reference[column] = draw(hnp.arrays(np.float64, n_ref, elements=_displacement))
    loads = None
    if draw(st.booleans()):
        n_loads = draw(st.integers(1, 6))
        loads = {"time_s": draw(_times(n_loads))}
        for column in ("fx_N", "fy_N", "fz_N"):
            loads[column] = draw(hnp.arrays(np.float64, n_loads, elements=_force))
    return Campaign.from_arrays(meta, fbg=fbg, temperatures=temperatures, reference=reference, loads=loads)


@settings(max_examples=30, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(campaign=campaigns())
def test_write_read_round_trip(campaign):
    with tempfile.TemporaryDirectory() as tmp:
        out = write_campaign(campaign, Path(tmp) / "c")
        back = read_campaign(out)
        assert_same_campaign(campaign, back)
        assert back.probe_names == campaign.probe_names
        # writing again over the existing folder gives the same bytes
        first = {p.name: p.read_bytes() for p in out.iterdir()}
        write_campaign(back, out)
        assert {p.name: p.read_bytes() for p in out.iterdir()} == first
        assert os.listdir(tmp) == ["c"]


@pytest.fixture(scope="session")
def template_folder(tmp_path_factory) -> Path:
    """The default campaign folder (:func:`make_folder`), made once per session for the property
    tests to copy (a session fixture: hypothesis refuses function-scoped ones)."""
    return make_folder(tmp_path_factory.mktemp("template"))


def _read_or_input_error(folder: Path) -> None:
    try:
        read_campaign(folder)
    except InputError as err:
        assert "\n" not in str(err)


@settings(max_examples=120, deadline=None)
@given(
    file=st.sampled_from(["fbg.csv", "temperatures.csv", "reference.csv"]),
    where=st.integers(0, 6),
    column=st.integers(0, 3),
    garbage=st.text(max_size=30),
)
def test_parser_survives_garbage_in_a_cell_or_header(template_folder, file, where, column, garbage):
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp) / "c"
        shutil.copytree(template_folder, folder)
        path = folder / file
        lines = path.read_text().split("\n")
        cells = lines[where].split(",")
        cells[column % len(cells)] = garbage
        lines[where] = ",".join(cells)
        path.write_text("\n".join(lines), encoding="utf-8", newline="")
        _read_or_input_error(folder)


@settings(max_examples=80, deadline=None)
@given(
    file=st.sampled_from(["fbg.csv", "reference.csv", "campaign.yaml"]),
    content=st.binary(max_size=200) | st.text(max_size=200).map(str.encode),
)
def test_reader_survives_arbitrary_file_contents(template_folder, file, content):
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp) / "c"
        shutil.copytree(template_folder, folder)
        (folder / file).write_bytes(content)
        _read_or_input_error(folder)


def test_sensor_spec_defaults():
    s = SensorSpec(name="S9", lambda0_nm=1560.0, gauge_length_mm=300)
    assert (s.photoelastic, s.thermo_optic_per_K, s.fibre_cte_per_K) == (0.22, 6.67e-6, 0.55e-6)
    assert s.column == "S9_nm" and s.temperature_probe is None


def test_fast_instrument_is_averaged_onto_the_reference_clock_exactly_for_linear_signals():
    from fbgcomp.bench.synthetic import linear_truth_campaign

    # 10 Hz interrogator, 1 Hz interferometer: linear-in-time wavelengths come through exactly,
    # white noise drops by ~sqrt(10) compared with point interpolation.
    c, _ = linear_truth_campaign(
        "avg", seed=4, duration_s=600, fbg_dt_s=0.1, reference_dt_s=1.0, reference_offset_s=0.37, settle_s=0.0
    )
    t = c.fbg["time_s"].to_numpy()
    ramp = 1530.0 + 1e-4 * t
    rng = np.random.default_rng(0)
    noisy = c.fbg.copy()
    noisy["S1_nm"] = ramp + 1e-3 * rng.standard_normal(t.size)
    noisy["S2_nm"] = ramp[:,] + 5.0  # S2 lambda0 is 1535
    c2 = type(c).from_arrays(c.meta, fbg=noisy, temperatures=c.temperatures, reference=c.reference)
    a = c2.aligned()
    exact = 1530.0 + 1e-4 * a.time_s
    np.testing.assert_allclose(a.wavelength_nm[:, 1], exact + 5.0, atol=1e-9)
    averaged = np.std(a.wavelength_nm[:, 0] - exact)
    pointwise = np.std(c2.aligned(average=False).wavelength_nm[:, 0] - exact)
    assert 2.3 < pointwise / averaged < 4.5


# --------------------------------------------------------------------------------------------
# A bounded reader (issue 13): wide headers, streamed bodies, physical bounds, nothing echoed
# --------------------------------------------------------------------------------------------


def _fbgcomp(*args, timeout=30):
    return subprocess.run(
        [sys.executable, "-m", "fbgcomp", *map(str, args)],
        capture_output=True,
        text=True,
        timeout=timeout,
        env={**os.environ, "PYTHONWARNINGS": "ignore"},
    )


def test_a_million_column_header_is_refused_in_seconds_by_inspect_and_fit(folder):
    # Finding 4: an 8.5 MB header of 10^6 columns hung inspect and fit for over 90 s (a
    # quadratic duplicate check over a file read whole). subprocess's timeout (30 s, a third of
    # the old hang, generous on a loaded machine) is the guard; no wall-clock rate is asserted.
    header = "time_s," + ",".join(f"c{i}" for i in range(10**6))
    (folder / "fbg.csv").write_text(header + "\n" + ",".join(["0"] * (10**6 + 1)) + "\n")
    model = folder.parent / "model.json"
    for command in (("inspect", folder), ("fit", folder, "-o", model)):
        r = _fbgcomp(*command)
        assert r.returncode == 2, r.stderr
        assert "fbg.csv" in r.stderr and "at most 4096 columns" in r.stderr, r.stderr
        assert "Traceback" not in r.stderr and len(r.stderr.splitlines()) == 1
    assert not model.exists()


def test_the_column_cap_is_documented_and_exact(folder):
    tables = default_tables()
    extra = campaign_module.MAX_COLUMNS - len(tables["fbg.csv"])
    for i in range(extra):
        tables["fbg.csv"][f"c{i}"] = np.zeros(61)
    wide = make_folder(folder.parent / "wide", tables=tables)
    assert len(read_campaign(wide).fbg.attrs["ignored_columns"]) == extra
    tables["fbg.csv"]["one_more"] = np.zeros(61)
    too_wide = make_folder(folder.parent / "too_wide", tables=tables)
    expect_error(
        too_wide,
        "fbg.csv",
        match=f"the header has {campaign_module.MAX_COLUMNS + 1} "
        f"columns; a campaign CSV holds at most {campaign_module.MAX_COLUMNS}",
    )
    assert "4096" in campaign_module.__doc__ and "4096" in Path("README.md").read_text()


def test_a_duplicate_at_the_end_of_a_wide_header_names_both_positions(folder):
    names = ["time_s", "S1_nm", "S2_nm", "S3_nm"] + [f"c{i}" for i in range(4000)] + ["c17"]
    (folder / "fbg.csv").write_text(",".join(names) + "\n" + ",".join(["1"] * len(names)) + "\n")
    expect_error(folder, "fbg.csv", column="c17", match=r"appears twice .*columns 22 and 4005")


def test_a_row_without_a_line_end_is_refused_without_being_buffered_whole(folder):
    with open(folder / "reference.csv", "ab") as handle:
        handle.write(b"1" * (8 << 20))
    expect_error(folder, "reference.csv", row=32, match="row is longer than 65536 bytes")


def test_oversized_campaign_yaml_is_refused(folder):
    (folder / "campaign.yaml").write_text(META_YAML + "# padding\n" * 200_000)
    expect_error(folder, "campaign.yaml", match="larger than 1048576 bytes")


def _rewrite(path: Path, line_end: bytes, trailing: bytes = b"") -> None:
    lines = path.read_bytes().rstrip(b"\n").split(b"\n")
    path.write_bytes(line_end.join(lines) + line_end + trailing)


@settings(max_examples=60, deadline=None)
@given(
    chunk=st.integers(1, 300),
    line_end=st.sampled_from([b"\n", b"\r\n", b"\r"]),
    trailing=st.sampled_from([b"", b"\n", b"\n\n  \n", b"\r\n\t"]),
    bad=st.none()
    | st.tuples(
        st.integers(1, 30),
        st.sampled_from(["dx_um", "dz_um"]),
        st.sampled_from(["x", "", "nan", "1e999", "3e6"]),
    ),
)
def test_streamed_blocks_read_exactly_what_a_whole_read_does(template_folder, chunk, line_end, trailing, bad):
    # The body is parsed in blocks of whole rows: any block size, line end or trailing blank
    # lines give the same numbers, and a bad cell the same row, column and message.
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp) / "c"
        shutil.copytree(template_folder, folder)
        if bad is not None:
            set_cell(folder, "reference.csv", *bad)
        for name in ("fbg.csv", "temperatures.csv", "reference.csv"):
            _rewrite(folder / name, line_end, trailing)

        def outcome():
            try:
                c = read_campaign(folder)
            except InputError as err:
                return str(err)
            return [frame.to_numpy().tolist() for frame in (c.fbg, c.temperatures, c.reference)]

        whole = outcome()
        with mock.patch.object(campaign_tables, "_CHUNK_BYTES", chunk):
            assert outcome() == whole
        if bad is None:
            assert isinstance(whole, list)
            np.testing.assert_array_equal(whole[2], read_campaign(template_folder).reference)
        else:
            assert f"row {bad[0]} (line {bad[0] + 1}), column {bad[1]}" in whole


def test_a_blank_line_between_blocks_is_an_empty_row(folder):
    path = folder / "reference.csv"
    lines = path.read_text().split("\n")
    lines.insert(11, "")  # after data row 10
    path.write_text("\n".join(lines))
    for chunk in (7, 64, 1 << 20):
        with mock.patch.object(campaign_tables, "_CHUNK_BYTES", chunk):
            expect_error(folder, "reference.csv", row=11, match="empty row")


@pytest.mark.parametrize(
    "file, row, column, text, match",
    [
        # finding 8: a 1e308 in temperatures.csv was reported against the derived column dL_S1
        (
            "temperatures.csv",
            3,
            "T_bulk_C",
            "1e308",
            r"temperature 1e\+308 degC is outside the "
            r"physical range \[-273.15, 1000\] degC",
        ),
        ("temperatures.csv", 5, "T_surf_C", "-300", "temperature -300.0 degC"),
        ("reference.csv", 4, "dy_um", "1e308", r"displacement 1e\+308 um .* \(-1e6, 1e6\) um"),
        ("reference.csv", 9, "dx_um", "-2000000", "displacement -2000000.0 um"),
        ("fbg.csv", 2, "S1_nm", "-1530", r"wavelength -1530.0 nm .* \(0, 10000\) nm"),
        ("fbg.csv", 61, "time_s", "1e11", r"time 100000000000.0 s .* \(-1e10, 1e10\) s"),
    ],
)
def test_absurd_magnitudes_are_bad_cells_of_their_file(folder, file, row, column, text, match):
    set_cell(folder, file, row, column, text)
    expect_error(folder, file, row=row, column=column, match=match)


def test_absurd_forces_are_bad_cells_of_loads_csv(tmp_path):
    t = np.arange(0.0, 61.0, 5)
    folder = make_folder(
        tmp_path,
        loads={"time_s": t, "fx_N": np.zeros_like(t), "fy_N": np.zeros_like(t), "fz_N": np.zeros_like(t)},
    )
    set_cell(folder, "loads.csv", 6, "fz_N", "-1e8")
    expect_error(folder, "loads.csv", row=6, column="fz_N", match=r"force -100000000.0 N")


def test_from_arrays_applies_the_same_bounds():
    meta = yaml.safe_load(META_YAML.replace("start: 2026-01-12T08:00:00Z", "start: '2026-01-12T08:00:00Z'"))
    tables = default_tables()
    tables["temperatures.csv"]["T_bulk_C"] = tables["temperatures.csv"]["T_bulk_C"] * 1e306
    with pytest.raises(InputError, match=r"temperatures\.csv, row 1 .*T_bulk_C: temperature 2e\+307"):
        Campaign.from_arrays(
            meta,
            fbg=tables["fbg.csv"],
            temperatures=tables["temperatures.csv"],
            reference=tables["reference.csv"],
        )


SECRET = "root:x:0:0:root:/root:/bin/bash"


@pytest.mark.parametrize(
    "content",
    [
        f"{SECRET}\ndaemon:x:1:1:daemon:/usr/sbin:/usr/sbin/nologin\n",
        "api_key=hunter2,password=swordfish,time\n1,2,3\n",
        "\x00\x01\x02 secret \x7f,\x1b[2J\n",
    ],
)
def test_a_link_to_another_file_never_has_its_content_echoed(folder, tmp_path, content):
    # Finding 8: a fbg.csv linked to a system file printed that file's first line.
    other = tmp_path / "elsewhere" / "passwd"
    other.parent.mkdir()
    other.write_text(content)
    (folder / "fbg.csv").unlink()
    (folder / "fbg.csv").symlink_to(other)
    err = expect_error(folder, "fbg.csv", column="time_s", match="missing column 'time_s'")
    for secret in ("root", "bash", "hunter2", "swordfish", "api_key", "secret", "\x1b", "x1b"):
        assert secret not in err.message
    r = _fbgcomp("inspect", folder)
    assert r.returncode == 2 and "missing column 'time_s'" in r.stderr
    shown = r.stderr.replace(str(folder), "<folder>")
    assert "root" not in shown and "hunter2" not in shown and "secret" not in shown


def test_a_near_miss_column_name_is_suggested(folder):
    path = folder / "reference.csv"
    path.write_text(path.read_text().replace("time_s", "time_sec", 1))
    expect_error(folder, "reference.csv", column="time_s", match="did you mean 'time_sec'")


def test_unprintable_header_names_are_named_by_position(folder):
    path = folder / "fbg.csv"
    lines = path.read_text().split("\n")
    lines[0] += ",\x01\x02,\x01\x02"
    lines[1:] = [line + ",0,0" if line else line for line in lines[1:]]
    path.write_text("\n".join(lines))
    err = expect_error(folder, "fbg.csv", column="#6", match=r"appears twice .*columns 5 and 6")
    assert "\x01" not in str(err) and "x01" not in str(err)


def test_a_cell_is_quoted_cut_short(folder):
    set_cell(folder, "reference.csv", 3, "dx_um", "z" * 500)
    err = expect_error(folder, "reference.csv", row=3, column="dx_um", match="not a number")
    assert "z" * 25 in err.message and "z" * 33 not in err.message


@settings(max_examples=150, deadline=None)
@given(
    chunk=st.sampled_from([3, 17, 256, 1 << 22]),
    head=st.sampled_from(
        [
            b"",
            b"time_s,S1_nm,S2_nm,S3_nm\n",
            b"time_s,S1_nm,S2_nm,S3_nm\r",
            b"\xef\xbb\xbftime_s,S1_nm,S2_nm,S3_nm\r\n",
        ]
    ),
    content=st.binary(max_size=400)
    | st.lists(
        st.sampled_from(
            [
                "1530",
                "1540.5",
                "1550",
                "0",
                "1",
                ",",
                "\n",
                "\r",
                " ",
                "nan",
                "1e308",
                "-",
                "\x00",
                "é",
                "\xff",
            ]
        ),
        max_size=120,
    ).map(lambda parts: "".join(parts).encode("utf-8", "surrogatepass")),
)
def test_arbitrary_bytes_in_fbg_csv_give_a_campaign_or_an_input_error(template_folder, chunk, head, content):
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp) / "c"
        shutil.copytree(template_folder, folder)
        (folder / "fbg.csv").write_bytes(head + content)
        with mock.patch.object(campaign_tables, "_CHUNK_BYTES", chunk):
            try:
                c = read_campaign(folder)
            except InputError as err:
                assert "\n" not in str(err) and len(str(err)) < 600
            else:
                assert np.isfinite(c.fbg.to_numpy()).all() and len(c.fbg) >= 1
