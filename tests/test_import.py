"""fbgcomp import: vendor and logger exports into campaign folders, through the real CLI.

The sample exports live in tests/data/import (README there names what each is written from);
Excel workbooks and the daylight-saving cases are written by the tests themselves.
"""

import csv
import datetime as dt
import shutil
from pathlib import Path
from zoneinfo import ZoneInfo

import numpy as np
import openpyxl
import pytest
import yaml

from fbgcomp.io.campaign import read_campaign
from fbgcomp.io.vendor_import import PRESETS
from fbgcomp_testing import cli

DATA = Path(__file__).parent / "data" / "import"
BERLIN = ZoneInfo("Europe/Berlin")

#: Every shipped preset and the sample export written from its cited document.
PRESET_SAMPLES = {"hioki-lr8431-csv": "hioki_lr8431_written_from_manual_appendix3.csv"}


def run(*args):
    return cli(*args)


def mapping_dict():
    return yaml.safe_load((DATA / "mapping_thermal.yaml").read_text())


def write_mapping(folder: Path, mapping: dict) -> Path:
    path = folder / "mapping.yaml"
    path.write_text(yaml.safe_dump(mapping, sort_keys=False, allow_unicode=True))
    return path


def copy_samples(folder: Path) -> None:
    for name in (
        "peaks_semicolon_decimal_comma.csv",
        "interferometer_utc_mm.tsv",
        PRESET_SAMPLES["hioki-lr8431-csv"],
    ):
        shutil.copy(DATA / name, folder / name)


# --- independent readings of the sample files (csv module + zoneinfo, not the importer) ---


def peaks_expected():
    with open(DATA / "peaks_semicolon_decimal_comma.csv", newline="") as handle:
        rows = list(csv.reader(handle, delimiter=";"))[4:]
    times = [dt.datetime.strptime(r[0], "%d.%m.%Y %H:%M:%S,%f").replace(tzinfo=BERLIN) for r in rows]
    values = np.array([[float(c.replace(",", ".")) for c in r[1:3]] for r in rows])
    return times, values


def hioki_expected():
    with open(DATA / PRESET_SAMPLES["hioki-lr8431-csv"], newline="") as handle:
        rows = list(csv.reader(handle))
    trigger = dt.datetime.strptime(rows[2][1], "'%y-%m-%d %H:%M:%S").replace(tzinfo=BERLIN)
    header = next(i for i, r in enumerate(rows) if r[0] == "Time")
    data = [r for r in rows[header + 1 :] if r]
    times = [trigger + dt.timedelta(seconds=float(r[0])) for r in data]
    return times, np.array([[float(r[1]), float(r[2])] for r in data])


def interferometer_expected():
    with open(DATA / "interferometer_utc_mm.tsv", newline="") as handle:
        rows = list(csv.reader(handle, delimiter="\t"))[1:]
    times = [dt.datetime.fromisoformat(r[0].replace("Z", "+00:00")) for r in rows]
    return times, np.array([[float(c) * 1000.0 for c in r[1:4]] for r in rows])


def seconds_from(start, times):
    return np.array([(t - start).total_seconds() for t in times])


def test_mapped_exports_and_the_preset_sample_become_a_campaign(tmp_path):
    """Semicolons + decimal comma + local time (peaks), the Hioki preset (elapsed seconds from
    the header's local trigger time) and a TSV in UTC millimetres (interferometer) land on one
    epoch, in nm, degC and um."""
    out = tmp_path / "imported"
    r = run("import", DATA / "mapping_thermal.yaml", "-o", out)
    assert r.returncode == 0, r.stderr
    assert "fbg.csv" in r.stdout and "31 rows" in r.stdout

    c = read_campaign(out)
    peak_t, peak_v = peaks_expected()
    temp_t, temp_v = hioki_expected()
    ref_t, ref_v = interferometer_expected()
    start = min(peak_t[0], temp_t[0], ref_t[0])
    assert c.meta.start == start == dt.datetime(2026, 3, 2, 7, 0, tzinfo=dt.UTC)

    np.testing.assert_allclose(c.fbg["time_s"], seconds_from(start, peak_t), atol=1e-9)
    np.testing.assert_allclose(c.fbg[["S1_nm", "S2_nm"]].to_numpy(), peak_v, rtol=0, atol=1e-9)
    np.testing.assert_allclose(c.temperatures["time_s"], seconds_from(start, temp_t), atol=1e-9)
    np.testing.assert_allclose(c.temperatures[["T1_C", "T2_C"]].to_numpy(), temp_v, atol=1e-12)
    np.testing.assert_allclose(c.reference["time_s"], seconds_from(start, ref_t), atol=1e-9)
    np.testing.assert_allclose(c.reference[["dx_um", "dy_um", "dz_um"]].to_numpy(), ref_v, atol=1e-9)
    assert c.meta.sensor("S1").temperature_probe == "T1"
    assert c.meta.sensor("S2").face == "-X"
    assert c.summary()["problems"] == []
    assert len(c.aligned()) == 12


def test_every_shipped_preset_has_a_cited_sample_that_imports(tmp_path):
    assert set(PRESETS) == set(PRESET_SAMPLES)
    readme = (DATA / "README.md").read_text()
    docs = (Path(__file__).parents[1] / "docs" / "import.md").read_text()
    for name, sample in PRESET_SAMPLES.items():
        assert (DATA / sample).is_file()
        assert "written from" in sample.replace("_", " ") or "written_from" in sample
        assert sample in readme and name in readme and name in docs
        assert "http" in PRESETS[name]["citation"]
        assert PRESETS[name]["citation"].split(",")[0] in docs  # the document is named
        assert PRESETS[name]["citation"].split(",")[0] in readme
    # the thermal mapping reads the sample through the preset (see the test above); here the
    # preset alone, with a user override of its time column kept as the preset gives it
    copy_samples(tmp_path)
    mapping = mapping_dict()
    mapping["sources"][1]["time"] = {"unit": "s"}  # user keys merge over the preset's
    (tmp_path / "sensors.yaml").write_text(yaml.safe_dump(mapping["campaign"]))
    mapping["campaign"] = "sensors.yaml"  # metadata from a file of its own
    r = run("import", write_mapping(tmp_path, mapping), "-o", tmp_path / "out")
    assert r.returncode == 0, r.stderr
    assert read_campaign(tmp_path / "out").temperatures["time_s"].tolist() == [
        0.0,
        10.0,
        20.0,
        30.0,
        40.0,
        50.0,
        60.0,
    ]


def write_utc_csv(path: Path, start: dt.datetime, step_s: float, rows: int, columns, value):
    with open(path, "w", newline="") as handle:
        w = csv.writer(handle)
        w.writerow(["t", *columns])
        for k in range(rows):
            t = start + dt.timedelta(seconds=k * step_s)
            w.writerow([t.isoformat(), *[value(j, k) for j in range(len(columns))]])


def dst_mapping(folder: Path, temperature_source: dict) -> Path:
    """A mapping around the spring-forward night: peaks and interferometer in UTC (CSV) plus the
    temperature source under test."""
    start = dt.datetime(2026, 3, 29, 0, 58, tzinfo=dt.UTC)
    write_utc_csv(folder / "peaks.csv", start, 10, 25, ["p1"], lambda j, k: 1530.0 + 1e-4 * k)
    write_utc_csv(folder / "ref.csv", start, 20, 12, ["x", "y", "z"], lambda j, k: 0.01 * k * j)
    return write_mapping(
        folder,
        {
            "campaign": {
                "name": "dst",
                "kind": "thermal",
                "sensors": [{"name": "S1", "lambda0_nm": 1530.0, "gauge_length_mm": 500}],
                "temperature_probes": [{"name": "T_air"}],
            },
            "timezone": "Europe/Berlin",
            "sources": [
                {"file": "peaks.csv", "role": "fbg", "time": {"column": "t"}, "columns": {"S1_nm": "p1"}},
                temperature_source,
                {
                    "file": "ref.csv",
                    "role": "reference",
                    "time": {"column": "t"},
                    "columns": {"dx_um": {"column": "x", "unit": "um"}, "dy_um": "y", "dz_um": "z"},
                },
            ],
        },
    )


def test_excel_export_with_date_and_time_columns_across_the_spring_forward(tmp_path):
    """A logger's .xlsx: title rows above the header, separate date and time cells in local time
    without an offset, degF. 01:59:30 then 03:00:00 in Berlin is 30 s, not an hour and 30 s."""
    book = openpyxl.Workbook()
    sheet = book.active
    sheet.title = "Log"
    sheet.append(["Temperature log, unit 7"])
    sheet.append([])
    sheet.append(["Datum", "Uhrzeit", "Fühler 1"])
    local = [
        dt.datetime(2026, 3, 29, 1, 58, 30),
        dt.datetime(2026, 3, 29, 1, 59),
        dt.datetime(2026, 3, 29, 1, 59, 30),
        dt.datetime(2026, 3, 29, 3, 0),
        dt.datetime(2026, 3, 29, 3, 0, 30),
        dt.datetime(2026, 3, 29, 3, 1),
    ]
    fahrenheit = [68.0, 68.9, 69.8, 70.7, 71.6, 72.5]
    for stamp, value in zip(local, fahrenheit):
        sheet.append([stamp.date(), stamp.time(), value])
    book.save(tmp_path / "log.xlsx")

    mapping = dst_mapping(
        tmp_path,
        {
            "file": "log.xlsx",
            "role": "temperatures",
            "format": {"sheet": "Log", "header_row": 3},
            "time": {"column": ["Datum", "Uhrzeit"]},
            "columns": {"T_air_C": {"column": "Fühler 1", "unit": "degF"}},
        },
    )
    r = run("import", mapping, "-o", tmp_path / "out")
    assert r.returncode == 0, r.stderr
    c = read_campaign(tmp_path / "out")
    start = dt.datetime(2026, 3, 29, 0, 58, tzinfo=dt.UTC)
    assert c.meta.start == start
    expected_t = [(s.replace(tzinfo=BERLIN) - start).total_seconds() for s in local]
    assert c.temperatures["time_s"].tolist() == expected_t == [30, 60, 90, 120, 150, 180]
    np.testing.assert_allclose(c.temperatures["T_air_C"], [(f - 32) * 5 / 9 for f in fahrenheit], atol=1e-12)


def test_repeated_autumn_hour_in_local_time_is_placed_by_its_order(tmp_path):
    """25 Oct 2026 in Berlin: 02:00-02:59 happens twice. Rows in order keep 30-min steps."""
    (tmp_path / "t.tsv").write_text(
        "Zeit\tT\n"
        + "".join(
            f"2026-10-25 {hm}\t{20 + k}\n"
            for k, hm in enumerate(["01:30", "02:00", "02:30", "02:00", "02:30", "03:00"])
        )
    )
    mapping = dst_mapping(
        tmp_path,
        {"file": "t.tsv", "role": "temperatures", "time": {"column": "Zeit"}, "columns": {"T_air_C": "T"}},
    )
    doc = yaml.safe_load(mapping.read_text())
    doc["start"] = "2026-10-24T23:00:00Z"
    write_utc_csv(
        tmp_path / "peaks.csv",
        dt.datetime(2026, 10, 24, 23, 0, tzinfo=dt.UTC),
        600,
        20,
        ["p1"],
        lambda j, k: 1530.0,
    )
    write_utc_csv(
        tmp_path / "ref.csv",
        dt.datetime(2026, 10, 24, 23, 0, tzinfo=dt.UTC),
        600,
        20,
        ["x", "y", "z"],
        lambda j, k: 0.0,
    )
    r = run("import", write_mapping(tmp_path, doc), "-o", tmp_path / "out")
    assert r.returncode == 0, r.stderr
    t = read_campaign(tmp_path / "out").temperatures["time_s"].to_numpy()
    np.testing.assert_array_equal(t, 1800.0 * np.arange(1, 7))


# --- bad exports: one line on stderr naming file, row (line) and column; exit 2 ----------------


def edit_line(path: Path, number: int, old: str, new: str) -> None:
    lines = path.read_text().splitlines(keepends=True)
    assert old in lines[number - 1]
    lines[number - 1] = lines[number - 1].replace(old, new, 1)
    path.write_text("".join(lines))


def bad_cell(folder):
    edit_line(folder / "peaks_semicolon_decimal_comma.csv", 7, "1530,0014", "1530,00x4")
    return mapping_dict(), [
        "peaks_semicolon_decimal_comma.csv, row 3 (line 7), column 'CH1 Peak 1': not a number: '1530,00x4'"
    ]


def point_in_a_decimal_comma_file(folder):
    edit_line(folder / "peaks_semicolon_decimal_comma.csv", 9, "1540,0017", "1540.0017")
    return mapping_dict(), ["row 5 (line 9), column 'CH1 Peak 2'", "decimal mark is ','"]


def missing_column(folder):
    m = mapping_dict()
    m["sources"][0]["columns"]["S2_nm"]["column"] = "CH1 Peak 3"
    return m, ["peaks_semicolon_decimal_comma.csv", "no column 'CH1 Peak 3'", "did you mean 'CH1 Peak 2'"]


def time_backwards(folder):
    edit_line(folder / "interferometer_utc_mm.tsv", 5, "07:00:15.5", "07:00:04.5")
    return mapping_dict(), ["interferometer_utc_mm.tsv, row 4 (line 5), column 'time'", "goes backwards"]


def wavelength_off_band(folder):
    edit_line(folder / "peaks_semicolon_decimal_comma.csv", 12, "1530,0019", "1536,0019")
    return mapping_dict(), [
        "peaks_semicolon_decimal_comma.csv, row 8 (line 12), column 'CH1 Peak 1'",
        "outside the grating's plausible band",
        "[campaign column S1_nm]",
    ]


def skipped_local_time(folder):
    edit_line(folder / "peaks_semicolon_decimal_comma.csv", 5, "02.03.2026 08:00:00", "29.03.2026 02:30:00")
    return mapping_dict(), ["row 1 (line 5), column 'Timestamp'", "does not exist"]


def unplaceable_repeated_hour(folder):
    edit_line(folder / "peaks_semicolon_decimal_comma.csv", 5, "02.03.2026 08:00:00", "25.10.2026 02:30:00")
    return mapping_dict(), ["row 1 (line 5), column 'Timestamp'", "is ambiguous"]


def wrong_delimiter(folder):
    m = mapping_dict()
    del m["sources"][0]["format"]["delimiter"]
    m["sources"][0]["format"]["header_row"] = 3
    return m, ["peaks_semicolon_decimal_comma.csv: the header has one column but holds ';'"]


def unknown_unit(folder):
    m = mapping_dict()
    m["sources"][2]["columns"]["dz_um"]["unit"] = "furlong"
    return m, ["mapping.yaml, field sources[2]", "unit 'furlong'"]


def bad_sensor_metadata(folder):
    m = mapping_dict()
    m["campaign"]["sensors"][1]["lambda0_nm"] = -5
    return m, ["mapping.yaml, field campaign.sensors[1].lambda0_nm"]


def empty_cell_without_drop(folder):
    edit_line(folder / "peaks_semicolon_decimal_comma.csv", 6, "1540,0020", "")
    return mapping_dict(), ["row 2 (line 6), column 'CH1 Peak 2': empty cell"]


def excel_bad_cell(folder):
    book = openpyxl.Workbook()
    sheet = book.active
    sheet.title = "T"
    sheet.append(["logger"])
    sheet.append(["t", "a", "b"])
    for k in range(5):
        sheet.append([k * 10.0, 22.0 + k, "n/a" if k == 3 else 21.0])
    book.save(folder / "temps.xlsx")
    m = mapping_dict()
    m["sources"][1] = {
        "file": "temps.xlsx",
        "role": "temperatures",
        "format": {"header_row": 2},
        "time": {"column": "t", "kind": "elapsed", "origin": "2026-03-02T08:00:00+01:00"},
        "columns": {"T1_C": "a", "T2_C": "b"},
    }
    return m, ["temps.xlsx[T], row 4 (sheet row 6), column 'b': not a number: 'n/a'"]


@pytest.mark.parametrize(
    "case",
    [
        bad_cell,
        point_in_a_decimal_comma_file,
        missing_column,
        time_backwards,
        wavelength_off_band,
        skipped_local_time,
        unplaceable_repeated_hour,
        wrong_delimiter,
        unknown_unit,
        bad_sensor_metadata,
        empty_cell_without_drop,
        excel_bad_cell,
    ],
    ids=lambda f: f.__name__,
)
def test_bad_exports_give_one_line_errors(tmp_path, case):
    copy_samples(tmp_path)
    mapping, expected = case(tmp_path)
    out = tmp_path / "out"
    r = run("import", write_mapping(tmp_path, mapping), "-o", out)
    assert r.returncode == 2, (r.stdout, r.stderr)
    assert "Traceback" not in r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), r.stderr
    for piece in expected:
        assert piece in lines[0], lines[0]
    assert not out.exists() and not list(tmp_path.glob(".out.*"))  # nothing half-written


def test_empty_cells_can_drop_their_rows(tmp_path):
    copy_samples(tmp_path)
    edit_line(tmp_path / "peaks_semicolon_decimal_comma.csv", 6, "1540,0020", "")
    m = mapping_dict()
    m["sources"][0]["format"]["on_empty"] = "drop_row"
    r = run("import", write_mapping(tmp_path, m), "-o", tmp_path / "out")
    assert r.returncode == 0, r.stderr
    t = read_campaign(tmp_path / "out").fbg["time_s"].tolist()
    assert len(t) == 30 and 2.0 not in t and t[:2] == [0.0, 4.0]


def test_a_failed_import_leaves_an_existing_campaign_as_it_was(tmp_path):
    copy_samples(tmp_path)
    out = tmp_path / "out"
    assert run("import", write_mapping(tmp_path, mapping_dict()), "-o", out).returncode == 0
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    bad_cell(tmp_path)
    r = run("import", tmp_path / "mapping.yaml", "-o", out)
    assert r.returncode == 2
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before
