"""Vendor and logger exports into a campaign folder (``fbgcomp import``).

An interrogator writes its peaks in its own layout, a temperature logger in another, the laser
interferometer in a third; each with its own clock, time zone, units, delimiter and decimal mark.
A *mapping file* (YAML) says, for each export, which column is which sensor, probe or axis, in
which unit, and how its time is written; :func:`import_campaign` reads the exports, converts them
to the campaign's units (nm, degC, um, N) and to seconds from one common start, and writes a
campaign folder that :func:`fbgcomp.io.campaign.read_campaign` accepts (atomically, through
:func:`fbgcomp.io.campaign.write_campaign`: nothing half-written on error).

Mapping file (see ``docs/import.md`` for every key)::

    campaign:                 # campaign.yaml without ``start`` (or the path of such a YAML file)
      name: thermal_a
      kind: thermal
      sensors: [{name: S1, lambda0_nm: 1530.0, gauge_length_mm: 600, temperature_probe: T1}]
      temperature_probes: [{name: T1}]
    timezone: Europe/Berlin   # zone of timestamps written without a UTC offset
    sources:
      - file: peaks.csv
        role: fbg             # fbg | temperatures | reference | loads
        format: {delimiter: ";", decimal: ","}
        time: {column: Timestamp, format: "%d.%m.%Y %H:%M:%S,%f"}
        columns: {S1_nm: {column: "CH1 Peak1", unit: nm}}

Presets (:data:`PRESETS`) fill ``format`` and ``time`` for layouts that a vendor's published
manual documents; each cites its document. Only those are shipped: see ``docs/import.md`` for
the formats searched for and not found.

Errors are :class:`fbgcomp.errors.InputError` (one line, exit 2 from the CLI) naming the export
file, its data row and file line, and the export's column; a mapping error names the mapping
file and the field.
"""

from __future__ import annotations

import codecs
import csv
import datetime as dt
import re
from pathlib import Path
from typing import Annotated, Any, Literal, Mapping
from zoneinfo import ZoneInfo, ZoneInfoNotFoundError

import numpy as np
import pandas as pd
import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from fbgcomp.io.campaign import (FBG_FILE, LOADS_FILE, META_FILE, REFERENCE_FILE, TEMPERATURES_FILE,
                                 TIME_COLUMN, Campaign, MetaLoader, meta_error, write_campaign)
from fbgcomp.errors import InputError, read_bounded

__all__ = ["ImportMapping", "SourceSpec", "FormatSpec", "TimeSpec", "ColumnSpec", "PRESETS",
           "ExportError", "read_mapping", "read_export", "import_campaign", "convert_units",
           "parse_zone", "MAX_EXPORT_BYTES"]

#: Largest export read, bytes. A 36 h campaign at 10 Hz with 16 gratings is ~60 MB of text.
MAX_EXPORT_BYTES = 2 << 30
#: Largest mapping file, bytes.
MAX_MAPPING_BYTES = 1 << 20
#: Lines searched for ``header_marker`` before giving up.
MAX_PREAMBLE_LINES = 10_000

ROLE_FILES = {"fbg": FBG_FILE, "temperatures": TEMPERATURES_FILE, "reference": REFERENCE_FILE,
              "loads": LOADS_FILE}
_ROLE_OF_FILE = {v: k for k, v in ROLE_FILES.items()}
#: The campaign unit of each role (suffix of its columns).
ROLE_SUFFIX = {"fbg": "_nm", "temperatures": "_C", "reference": "_um", "loads": "_N"}

#: Source unit -> (scale, offset) onto the campaign unit: ``value * scale + offset``.
UNITS = {
    "_nm": {"nm": (1.0, 0.0), "pm": (1e-3, 0.0), "um": (1e3, 0.0), "µm": (1e3, 0.0)},
    "_C": {"degC": (1.0, 0.0), "C": (1.0, 0.0), "°C": (1.0, 0.0), "K": (1.0, -273.15),
           "degF": (5.0 / 9.0, -32.0 * 5.0 / 9.0), "°F": (5.0 / 9.0, -32.0 * 5.0 / 9.0)},
    "_um": {"um": (1.0, 0.0), "µm": (1.0, 0.0), "nm": (1e-3, 0.0), "mm": (1e3, 0.0),
            "m": (1e6, 0.0), "in": (25400.0, 0.0), "mil": (25.4, 0.0)},
    "_N": {"N": (1.0, 0.0), "kN": (1e3, 0.0), "daN": (10.0, 0.0), "lbf": (4.4482216152605, 0.0)},
}
_TIME_UNITS_S = {"s": 1.0, "ms": 1e-3, "us": 1e-6, "min": 60.0, "h": 3600.0, "d": 86400.0}

_NUMBER_RE = r"[+-]?(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][+-]?[0-9]+)?"
_AWARE_RE = r"(?:Z|[+-][0-9]{2}:?[0-9]{2})\s*$"
_OFFSET_RE = re.compile(r"^(?:UTC|GMT)?\s*([+-])([0-9]{1,2})(?::?([0-9]{2}))?$")
_NS = 1_000_000_000


# --------------------------------------------------------------------------------------------
# Errors
# --------------------------------------------------------------------------------------------

class ExportError(InputError):
    """An :class:`InputError` in an export whose data rows do not start on line 2: names the
    data row and the file line (or spreadsheet row) it is on, ``row 3 (line 12)``."""

    def __init__(self, message: str, file=None, row: int | None = None, line: int | None = None,
                 column: str | None = None, line_label: str = "line"):
        self.line = line
        self.line_label = line_label
        super().__init__(message, file=file, row=row, column=column)

    def one_line(self) -> str:
        if self.row is None or self.line is None:
            return super().one_line()
        where = [] if self.file is None else [self.file]
        where.append(f"row {self.row} ({self.line_label} {self.line})")
        if self.column is not None:
            where.append(f"column {self.column}")
        return " ".join(f"{', '.join(where)}: {self.message}".split())


# --------------------------------------------------------------------------------------------
# Mapping schema
# --------------------------------------------------------------------------------------------

def parse_zone(text: str) -> dt.tzinfo:
    """A time zone from an IANA name (``Europe/Berlin``), ``UTC`` / ``Z`` or a fixed offset
    (``+01:00``, ``UTC-05``). Raises ValueError naming what it expected."""
    text = str(text).strip()
    if text.upper() in ("UTC", "Z", "GMT"):
        return dt.timezone.utc
    match = _OFFSET_RE.match(text)
    if match:
        sign, hours, minutes = match.groups()
        offset = dt.timedelta(hours=int(hours), minutes=int(minutes or 0))
        if offset > dt.timedelta(hours=14):
            raise ValueError(f"UTC offset {text!r} is beyond ±14:00")
        return dt.timezone(-offset if sign == "-" else offset)
    try:
        return ZoneInfo(text)
    except (ZoneInfoNotFoundError, ValueError):
        raise ValueError(f"unknown time zone {text!r}; give an IANA name such as 'Europe/Berlin', "
                         "'UTC' or an offset such as '+01:00'") from None


def _check_zone(value):
    if value is not None:
        parse_zone(value)
    return value


_ColumnRef = Annotated[str, Field(min_length=1)] | Annotated[int, Field(ge=1)]


class FormatSpec(BaseModel):
    """How an export file is laid out."""

    model_config = ConfigDict(extra="forbid")

    kind: Literal["csv", "excel"] | None = Field(
        None, description="csv (any delimited text) or excel (.xlsx); default from the extension")
    delimiter: str | None = Field(
        None, description="one character, or 'tab' / 'space'; default ',' (tab for .tsv / .tab)")
    decimal: Literal[".", ","] = "."
    thousands: Literal["", " ", ".", ",", "'", "\u202f"] = Field(
        "", description="digit-group separator dropped before parsing numbers")
    encoding: str = "utf-8-sig"
    header_row: Annotated[int, Field(ge=1)] | None = Field(
        None, description="1-based line (spreadsheet row) holding the column names")
    header_marker: str | None = Field(
        None, description="the column names are on the first line whose first cell is this")
    skip_after_header: Annotated[int, Field(ge=0)] = Field(
        0, description="lines between the column names and the first data row (e.g. units)")
    sheet: str | Annotated[int, Field(ge=1)] | None = Field(
        None, description="spreadsheet: sheet name or 1-based index; default the first")
    on_empty: Literal["error", "drop_row"] = Field(
        "error", description="an empty cell in a mapped column: refuse, or drop its row")

    @field_validator("delimiter")
    @classmethod
    def _one_character(cls, value):
        if value is None:
            return value
        named = {"tab": "\t", "\\t": "\t", "space": " "}
        value = named.get(value, value)
        if len(value) != 1 or value in "\r\n\"":
            raise ValueError("delimiter must be one character (or 'tab' / 'space')")
        return value

    @field_validator("encoding")
    @classmethod
    def _known_encoding(cls, value):
        try:
            codecs.lookup(value)
        except LookupError:
            raise ValueError(f"unknown text encoding {value!r}") from None
        return value

    @model_validator(mode="after")
    def _one_header_rule(self):
        if self.header_row is not None and self.header_marker is not None:
            raise ValueError("give header_row or header_marker, not both")
        if self.decimal == self.thousands or (self.delimiter is not None
                                              and self.delimiter in (self.decimal, self.thousands)):
            raise ValueError("delimiter, decimal mark and digit-group separator must differ")
        return self


class HeaderField(BaseModel):
    """A value in the lines above the column names: the cell after the one labelled ``label``."""

    model_config = ConfigDict(extra="forbid")

    label: Annotated[str, Field(min_length=1)]
    format: str | None = Field(None, description="strptime format; default ISO 8601")


class TimeSpec(BaseModel):
    """How an export writes its sample times."""

    model_config = ConfigDict(extra="forbid")

    column: _ColumnRef | Annotated[list[_ColumnRef], Field(min_length=1)] = Field(
        description="time column (name or 1-based position); a list is joined with spaces "
                    "(a date column and a time column)")
    kind: Literal["datetime", "elapsed"] = "datetime"
    format: str | None = Field(None, description="datetime: strptime format; default ISO 8601")
    timezone: str | None = Field(
        None, description="zone of timestamps without a UTC offset (default: the mapping's)")
    unit: Literal["s", "ms", "us", "min", "h", "d"] = Field("s", description="elapsed: unit")
    origin: str | None = Field(None, description="elapsed: the date and time of elapsed 0")
    origin_from_header: HeaderField | None = Field(
        None, description="elapsed: read the date and time of elapsed 0 from the file's header")

    @field_validator("timezone")
    @classmethod
    def _zone(cls, value):
        return _check_zone(value)

    @model_validator(mode="after")
    def _consistent(self):
        if self.kind == "datetime" and (self.origin or self.origin_from_header):
            raise ValueError("origin / origin_from_header apply to elapsed times only")
        if self.origin and self.origin_from_header:
            raise ValueError("give origin or origin_from_header, not both")
        return self


class ColumnSpec(BaseModel):
    """One campaign column taken from an export column."""

    model_config = ConfigDict(extra="forbid")

    column: _ColumnRef = Field(description="export column name or 1-based position")
    unit: str | None = Field(None, description="its unit; default the campaign's")


class SourceSpec(BaseModel):
    """One export file and what it holds."""

    model_config = ConfigDict(extra="forbid")

    file: Annotated[str, Field(min_length=1)]
    role: Literal["fbg", "temperatures", "reference", "loads"]
    preset: str | None = None
    format: FormatSpec = Field(default_factory=FormatSpec)
    time: TimeSpec
    columns: Annotated[dict[str, ColumnSpec], Field(min_length=1)]

    @field_validator("columns", mode="before")
    @classmethod
    def _shorthand(cls, value):
        # ``S1_nm: "Peak 1"`` is ``S1_nm: {column: "Peak 1"}`` (already in the campaign unit).
        if isinstance(value, Mapping):
            return {k: ({"column": v} if isinstance(v, (str, int)) and not isinstance(v, bool)
                        else v) for k, v in value.items()}
        return value

    @model_validator(mode="after")
    def _units_fit_the_role(self):
        suffix = ROLE_SUFFIX[self.role]
        for target, spec in self.columns.items():
            if not target.endswith(suffix) or target == suffix:
                raise ValueError(f"column {target!r} cannot go into {ROLE_FILES[self.role]}: its "
                                 f"columns are named <name>{suffix}")
            if spec.unit is not None and spec.unit not in UNITS[suffix]:
                raise ValueError(f"unit {spec.unit!r} of column {target!r} is not one of "
                                 f"{', '.join(UNITS[suffix])}")
        return self


class ImportMapping(BaseModel):
    """The whole mapping file."""

    model_config = ConfigDict(extra="forbid")

    campaign: dict[str, Any] | Annotated[str, Field(min_length=1)] = Field(
        description="campaign.yaml content without start, or the path of such a YAML file")
    start: str | None = Field(None, description="campaign start; default the first sample")
    timezone: str | None = Field(None, description="default zone of timestamps without offset")
    sources: Annotated[list[SourceSpec], Field(min_length=1)]

    @field_validator("timezone")
    @classmethod
    def _zone(cls, value):
        return _check_zone(value)

    @model_validator(mode="after")
    def _roles(self):
        seen: dict[str, int] = {}
        for i, source in enumerate(self.sources):
            if source.role in seen:
                raise ValueError(f"sources[{i}] and sources[{seen[source.role]}] both give "
                                 f"role {source.role!r}; one export per campaign file")
            seen[source.role] = i
        missing = [r for r in ("fbg", "temperatures", "reference") if r not in seen]
        if missing:
            raise ValueError(f"no source for role(s) {', '.join(missing)}: a campaign needs "
                             "fbg, temperatures and reference (loads is optional)")
        return self


# --------------------------------------------------------------------------------------------
# Presets: layouts documented in a vendor's published manual, as data
# --------------------------------------------------------------------------------------------

#: Each preset fills ``format`` and ``time`` (the mapping's own keys win) and cites the document
#: its layout is written from. The columns (which channel is which probe) are always the user's.
PRESETS: dict[str, dict[str, Any]] = {
    "hioki-lr8431-csv": {
        "instrument": "Hioki MEMORY HiLOGGER LR8431-20 (thermocouple / voltage logger)",
        "citation": "Hioki LR8431-20 Instruction Manual, Appendix 3 'Text File (CSV) Internal "
                    "Format', p. A8: https://manualshive.com/en/manual/hioki/lr8431/2137135?page=166 "
                    "(also https://www.easymanua.ls/hioki/lr8431-20/manual?p=166)",
        "layout": "header lines 'File name', 'Title comment', 'Trigger Time' "
                  "(\"'yy-mm-dd hh:mm:ss\"), a channel-settings table (Ch, Mode, Range, Comment, "
                  "Scaling, Ratio, Offset), then the data header 'Time', 'CH-n[unit]', ..., "
                  "'Event' and comma-separated rows whose Time is seconds from the trigger time "
                  "(rows and header end with a comma)",
        "format": {"kind": "csv", "delimiter": ",", "decimal": ".", "header_marker": "Time"},
        "time": {"column": "Time", "kind": "elapsed", "unit": "s",
                 "origin_from_header": {"label": "Trigger Time", "format": "'%y-%m-%d %H:%M:%S"}},
    },
}

#: Formats searched for and not shipped (docs/import.md says what was searched).
NOT_SHIPPED = {
    "Luna / Micron Optics ENLIGHT peak files": "only the user guide's table of contents "
    "(ENLIGHT User Guide rev. 1.138) was reachable; no page describing the saved peak file",
    "HBM catman ASCII export": "no published description of the export layout found",
    "FBGS ILLumiSense export": "no published description found",
    "Renishaw laser (LaserXL / CARTO) exports": "no published description found",
}


def _apply_preset(raw: Mapping, index: int, file) -> dict:
    source = dict(raw)
    name = source.get("preset")
    if name is None:
        return source
    if not isinstance(name, str) or name not in PRESETS:
        raise InputError(f"unknown preset {name!r}; shipped presets: {', '.join(PRESETS)} "
                         "(docs/import.md)", file=file, column=f"field sources[{index}].preset")
    preset = PRESETS[name]
    for key in ("format", "time"):
        own = source.get(key) or {}
        if not isinstance(own, Mapping):
            continue  # the schema names the field
        source[key] = {**preset[key], **own}
    return source


def read_mapping(path: str | Path) -> ImportMapping:
    """Read and validate a mapping file (InputError naming the file and the field)."""
    file = Path(path)
    if not file.is_file():
        raise InputError("mapping file not found", file=file)
    raw = read_bounded(file, MAX_MAPPING_BYTES, what="a mapping file")
    try:
        data = yaml.load(raw.decode("utf-8-sig"), Loader=MetaLoader)  # noqa: S506 - SafeLoader
    except UnicodeDecodeError as exc:
        raise InputError(f"not UTF-8 text: byte 0x{raw[exc.start]:02x}", file=file) from None
    except yaml.MarkedYAMLError as exc:
        mark = exc.problem_mark or exc.context_mark
        where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark else ""
        raise InputError(f"YAML syntax error{where}: {exc.problem or exc.context}",
                         file=file) from None
    if not isinstance(data, Mapping):
        raise InputError("expected a mapping (campaign: ..., sources: [...]) at the top level",
                         file=file)
    data = dict(data)
    if isinstance(data.get("sources"), list):
        data["sources"] = [_apply_preset(s, i, file) if isinstance(s, Mapping) else s
                           for i, s in enumerate(data["sources"])]
    try:
        return ImportMapping.model_validate(data)
    except ValidationError as exc:
        raise meta_error(exc, file) from None


# --------------------------------------------------------------------------------------------
# Reading an export
# --------------------------------------------------------------------------------------------

class RawExport:
    """The cells of one export: column names, the mapped columns' cells, file lines per row."""

    def __init__(self, label: str, names: list[str], preamble: list[list[str]],
                 cells: dict[int, np.ndarray], lines: np.ndarray, line_label: str,
                 text: bool = False):
        self.label = label              # file name for messages
        self.text = text                # every cell is a str (delimited text): vectorised paths
        self.names = names              # every column name of the header
        self.preamble = preamble        # cells of the lines above the header
        self.cells = cells              # 0-based column index -> object array of cells
        self.lines = lines              # file line (spreadsheet row) of each data row
        self.line_label = line_label

    def error(self, message: str, row_index: int | None = None, column: int | None = None):
        return ExportError(message, file=self.label,
                           row=None if row_index is None else int(row_index) + 1,
                           line=None if row_index is None else int(self.lines[row_index]),
                           column=None if column is None else self.column_label(column),
                           line_label=self.line_label)

    def column_label(self, index: int) -> str:
        name = self.names[index] if index < len(self.names) else ""
        return repr(name) if name and name.isprintable() and len(name) <= 64 else f"#{index + 1}"

    def keep(self, mask: np.ndarray) -> None:
        self.cells = {k: v[mask] for k, v in self.cells.items()}
        self.lines = self.lines[mask]


def _export_kind(path: Path, fmt: FormatSpec) -> str:
    if fmt.kind is not None:
        return fmt.kind
    return "excel" if path.suffix.lower() in (".xlsx", ".xlsm") else "csv"


def _resolve_column(ref, names: list[str], label: str, what: str, raw_label: str) -> int:
    if isinstance(ref, int):
        if ref > len(names):
            raise InputError(f"{what} is column {ref}, but the header has {len(names)} columns",
                             file=raw_label)
        return ref - 1
    stripped = [n.strip() for n in names]
    if ref.strip() in stripped:
        return stripped.index(ref.strip())
    import difflib

    close = difflib.get_close_matches(ref, [n for n in stripped if n.isprintable()], n=1, cutoff=0.6)
    hint = f"; did you mean {close[0]!r}?" if close else ""
    raise InputError(f"no column {ref!r} ({what}) in the header ({len(names)} columns){hint}",
                     file=raw_label, column=repr(ref) if len(ref) <= 64 else None)


def _split_line(line: str, delimiter: str) -> list[str]:
    return [c.strip() for c in next(csv.reader([line], delimiter=delimiter), [])]


def _read_csv(path: Path, fmt: FormatSpec, wanted) -> RawExport:
    delimiter = fmt.delimiter or ("\t" if path.suffix.lower() in (".tsv", ".tab") else ",")
    label = str(path)
    preamble: list[list[str]] = []
    header: list[str] | None = None
    header_line = 0
    try:
        with open(path, encoding=fmt.encoding, newline="") as handle:
            for number in range(1, MAX_PREAMBLE_LINES + 1):
                line = handle.readline(1 << 20)
                if not line:
                    break
                cells = _split_line(line.rstrip("\r\n"), delimiter)
                is_header = (number == fmt.header_row if fmt.header_row is not None else
                             bool(cells) and cells[0] == fmt.header_marker
                             if fmt.header_marker is not None else number == 1)
                if is_header:
                    header, header_line = cells, number
                    break
                preamble.append(cells)
    except UnicodeDecodeError as exc:
        raise InputError(f"not {fmt.encoding} text ({exc.reason}); set format.encoding "
                         "(e.g. cp1252, shift_jis)", file=label) from None
    except OSError as exc:
        raise InputError(f"cannot read the file: {exc.strerror or type(exc).__name__}",
                         file=label) from None
    if header is None:
        rule = (f"line {fmt.header_row}" if fmt.header_row is not None else
                f"a line starting with {fmt.header_marker!r}" if fmt.header_marker else "line 1")
        raise InputError(f"no column header: expected it on {rule} (format.header_row / "
                         "format.header_marker)", file=label)
    if len(header) == 1 and delimiter not in (";", "\t") and any(d in header[0] for d in ";\t"):
        found = "';'" if ";" in header[0] else "tab"
        raise InputError(f"the header has one column but holds {found}: set format.delimiter",
                         file=label)
    columns = sorted({_resolve_column(ref, header, label, what, label) for ref, what in wanted})
    first_data_line = header_line + 1 + fmt.skip_after_header
    try:
        frame = pd.read_csv(path, sep=delimiter, header=None, skiprows=first_data_line - 1,
                            usecols=columns, dtype=str, na_filter=False, skip_blank_lines=False,
                            encoding=fmt.encoding, engine="c", quotechar='"')
    except pd.errors.EmptyDataError:
        frame = pd.DataFrame({c: pd.Series([], dtype=object) for c in columns})
    except UnicodeDecodeError as exc:
        raise InputError(f"not {fmt.encoding} text ({exc.reason}); set format.encoding",
                         file=label) from None
    except (pd.errors.ParserError, ValueError) as exc:
        text = " ".join(str(exc).split())
        match = re.search(r"line (\d+)", text)
        where = f" near line {int(match.group(1)) + first_data_line - 1}" if match else ""
        raise InputError(f"cannot split the rows{where}: {text[:120]}", file=label) from None
    cells = {c: np.asarray(frame[c].to_numpy(dtype=object)) for c in columns}
    lines = np.arange(first_data_line, first_data_line + len(frame))
    raw = RawExport(label, header, preamble, cells, lines, "line", text=True)
    _drop_trailing_blank(raw)
    return raw


def _read_excel(path: Path, fmt: FormatSpec, wanted) -> RawExport:
    try:
        import openpyxl
    except ImportError:  # pragma: no cover - a declared dependency
        raise InputError("reading Excel files needs openpyxl (pip install openpyxl)",
                         file=path) from None
    try:
        book = openpyxl.load_workbook(path, read_only=True, data_only=True)
    except Exception as exc:  # noqa: BLE001 - zip / XML errors of a damaged or foreign file
        raise InputError(f"not a readable .xlsx workbook: {type(exc).__name__}", file=path) from None
    try:
        names = book.sheetnames
        if fmt.sheet is None:
            sheet = names[0]
        elif isinstance(fmt.sheet, int):
            if fmt.sheet > len(names):
                raise InputError(f"sheet {fmt.sheet} requested, the workbook has {len(names)}",
                                 file=path)
            sheet = names[fmt.sheet - 1]
        elif fmt.sheet in names:
            sheet = fmt.sheet
        else:
            raise InputError(f"no sheet {fmt.sheet!r} (sheets: {', '.join(names)})", file=path)
        label = f"{path}[{sheet}]"
        preamble: list[list[str]] = []
        header, header_row, body, body_rows = None, 0, [], []
        first_data = None
        for number, values in enumerate(book[sheet].iter_rows(values_only=True), start=1):
            if header is None:
                cells = ["" if v is None else str(v).strip() for v in values]
                is_header = (number == fmt.header_row if fmt.header_row is not None else
                             bool(cells) and cells[0] == fmt.header_marker
                             if fmt.header_marker is not None else number == 1)
                if is_header:
                    header, header_row = cells, number
                    first_data = number + 1 + fmt.skip_after_header
                else:
                    preamble.append(cells)
                    if number >= MAX_PREAMBLE_LINES:
                        break
                continue
            if number >= first_data:
                body.append(values)
                body_rows.append(number)
    finally:
        book.close()
    if header is None:
        raise InputError("no column header found (format.header_row / format.header_marker)",
                         file=label)
    columns = sorted({_resolve_column(ref, header, label, what, label) for ref, what in wanted})
    cells = {c: np.array([row[c] if c < len(row) else None for row in body], dtype=object)
             for c in columns}
    raw = RawExport(label, header, preamble, cells, np.asarray(body_rows, dtype=np.int64),
                    "sheet row")
    _drop_trailing_blank(raw)
    return raw


def _is_empty(cells: np.ndarray, text: bool = False) -> np.ndarray:
    if text:
        return (_text(cells) == "").to_numpy(dtype=bool)
    return np.array([c is None or (isinstance(c, str) and not c.strip())
                     or (isinstance(c, float) and c != c) for c in cells], dtype=bool)


def _text(cells: np.ndarray) -> pd.Series:
    """Cells that are all str as a stripped string Series (Arrow-backed where pyarrow is
    installed: the string operations below then run in C++, ~20x faster than in Python)."""
    return pd.Series(cells, dtype="str").fillna("").str.strip()


def _drop_trailing_blank(raw: RawExport) -> None:
    """Rows empty in every mapped column at the end of the file are an editor's habit."""
    if not raw.cells or raw.lines.size == 0:
        return
    empty = np.logical_and.reduce([_is_empty(c, raw.text) for c in raw.cells.values()])
    last = np.flatnonzero(~empty)
    raw.keep(np.arange(raw.lines.size) <= (last[-1] if last.size else -1))


def read_export(path: str | Path, fmt: FormatSpec, wanted) -> RawExport:
    """The cells of the columns ``wanted`` (``[(name or 1-based position, description)]``)."""
    file = Path(path)
    if not file.exists():
        raise InputError("export file not found", file=file)
    if not file.is_file():
        raise InputError("expected a file, found a folder or device", file=file)
    if file.stat().st_size > MAX_EXPORT_BYTES:
        raise InputError(f"larger than {MAX_EXPORT_BYTES} bytes: split the export", file=file)
    reader = _read_excel if _export_kind(file, fmt) == "excel" else _read_csv
    return reader(file, fmt, wanted)


# --------------------------------------------------------------------------------------------
# Cells -> numbers and times
# --------------------------------------------------------------------------------------------

def _numbers(raw: RawExport, column: int, fmt: FormatSpec, what: str) -> tuple[np.ndarray, np.ndarray]:
    """Floats of a column and its empty-cell mask; InputError at the first bad cell."""
    cells = raw.cells[column]
    values = np.full(cells.size, np.nan)
    if raw.text:
        s = _text(cells)
        empty = (s == "").to_numpy(dtype=bool)
        numeric = np.zeros(cells.size, dtype=bool)
    else:
        s = None
        empty = _is_empty(cells)
        numeric = np.array([isinstance(c, (int, float, np.integer, np.floating))
                            and not isinstance(c, (bool, np.bool_)) for c in cells], dtype=bool)
        numeric &= ~empty
    if numeric.any():
        values[numeric] = np.asarray(cells[numeric], dtype=np.float64)
    text = ~numeric & ~empty
    if text.any():
        s = (s[text].reset_index(drop=True) if s is not None
             else pd.Series([str(c) for c in cells[text]], dtype=object).str.strip())
        if fmt.thousands:
            s = s.str.replace(fmt.thousands, "", regex=False)
        if fmt.decimal == ",":
            if s.str.contains(".", regex=False).any():
                bad = np.flatnonzero(np.asarray(s.str.contains(".", regex=False)))[0]
                row = np.flatnonzero(text)[bad]
                raise raw.error(f"{_quote(cells[row])} holds '.' where the decimal mark is ',' "
                                "(format.decimal / format.thousands)", row, column)
            s = s.str.replace(",", ".", regex=False)
        ok = np.asarray(s.str.fullmatch(_NUMBER_RE), dtype=bool)
        if not ok.all():
            row = np.flatnonzero(text)[np.flatnonzero(~ok)[0]]
            hint = (" (decimal comma? set format.decimal: ',')" if fmt.decimal == "."
                    and re.fullmatch(r"\s*[+-]?[0-9]+,[0-9]+\s*", str(cells[row])) else "")
            raise raw.error(f"not a number: {_quote(cells[row])}; expected {what}{hint}",
                            row, column)
        values[text] = s.astype("float64").to_numpy(dtype=np.float64)
    bad = ~np.isfinite(values) & ~empty
    if bad.any():
        row = int(np.flatnonzero(bad)[0])
        raise raw.error(f"non-finite value {_quote(cells[row])}", row, column)
    return values, empty


def _quote(cell) -> str:
    text = repr(cell if isinstance(cell, str) else str(cell))
    return text if len(text) <= 40 else text[:37] + "..."


def _localize(raw: RawExport, column: int, parsed: pd.Series, zone: dt.tzinfo, zone_name: str):
    """Naive local times -> UTC; a time the clocks skipped, or a repeated hour the order cannot
    place, is an error at its row."""
    try:
        return parsed.dt.tz_localize(zone, ambiguous="infer", nonexistent="raise")
    except Exception:  # noqa: BLE001 - pandas raises several types; locate the row below
        pass
    for row, stamp in enumerate(parsed):
        if pd.isna(stamp):
            continue
        try:
            pd.Timestamp(stamp).tz_localize(zone, ambiguous="raise", nonexistent="raise")
        except Exception as exc:  # noqa: BLE001
            if "nonexistent" in f"{type(exc).__name__} {exc}".lower():
                problem = "does not exist (the clocks skipped it: daylight-saving change)"
            else:
                problem = ("is ambiguous (the clocks went back: it occurs twice) and the order of "
                           "the rows cannot tell which; export with a UTC offset")
            raise raw.error(f"local time {stamp} in {zone_name} {problem}", row, column) from None
    raise raw.error(f"cannot place the local times in {zone_name}", None, column)


def _parse_datetimes(raw: RawExport, column: int, cells: np.ndarray, spec: TimeSpec,
                     zone_name: str | None) -> np.ndarray:
    """Timestamps -> int64 ns since 1970 UTC."""
    if raw.text:
        is_stamp = np.zeros(cells.size, dtype=bool)
        text = _text(cells)
    else:
        is_stamp = np.array([isinstance(c, (dt.datetime, pd.Timestamp)) for c in cells],
                            dtype=bool)
        text = pd.Series(["" if c is None else (c.isoformat(sep=" ") if isinstance(c, dt.datetime)
                                                else str(c)).strip() for c in cells], dtype=object)
    aware = np.asarray(text.str.contains(_AWARE_RE, regex=True), dtype=bool) & ~is_stamp
    if aware.any() and not aware.all():
        row = int(np.flatnonzero(aware != aware[0])[0])
        raise raw.error(f"timestamp {_quote(cells[row])} {'has' if aware[row] else 'lacks'} a UTC "
                        "offset where the first row's does not; mixed zones", row, column)
    fmt = spec.format or "ISO8601"
    parsed = pd.to_datetime(text, format=fmt, errors="coerce", utc=bool(aware.all()))
    if parsed.isna().any():
        row = int(np.flatnonzero(parsed.isna().to_numpy())[0])
        expected = f"the format {spec.format!r}" if spec.format else "ISO 8601 (2026-03-02 08:00:00)"
        raise raw.error(f"not a date and time: {_quote(cells[row])}; expected {expected} "
                        "(time.format)", row, column)
    if not aware.all():
        if zone_name is None:
            raise raw.error("timestamps have no UTC offset and no time zone is given: set "
                            "'timezone' in the mapping (or time.timezone)", None, column)
        parsed = _localize(raw, column, parsed, parse_zone(zone_name), zone_name)
    return parsed.dt.tz_convert("UTC").dt.as_unit("ns").astype("int64").to_numpy()


def _header_origin(raw: RawExport, spec: TimeSpec, zone_name: str | None) -> int:
    field = spec.origin_from_header
    for cells in raw.preamble:
        if cells and cells[0].strip().strip('"') == field.label:
            if len(cells) < 2 or not cells[1].strip():
                raise InputError(f"header line {field.label!r} holds no date and time",
                                 file=raw.label)
            return _origin_ns(cells[1].strip(), field.format, zone_name, raw.label,
                              f"header {field.label!r}")
    raise InputError(f"no header line {field.label!r} above the column names "
                     "(time.origin_from_header)", file=raw.label)


def _origin_ns(text: str, fmt: str | None, zone_name: str | None, file, where: str) -> int:
    try:
        stamp = (pd.Timestamp(dt.datetime.strptime(text, fmt)) if fmt else pd.Timestamp(text))
    except (ValueError, TypeError):
        expected = f"the format {fmt!r}" if fmt else "ISO 8601"
        raise InputError(f"{where}: not a date and time: {text!r}; expected {expected}",
                         file=file) from None
    if stamp.tzinfo is None:
        if zone_name is None:
            raise InputError(f"{where}: {text!r} has no UTC offset and no time zone is given "
                             "(set 'timezone' in the mapping)", file=file)
        try:
            stamp = stamp.tz_localize(parse_zone(zone_name), ambiguous="raise",
                                      nonexistent="raise")
        except Exception:  # noqa: BLE001 - nonexistent / ambiguous local time
            raise InputError(f"{where}: local time {text!r} does not exist or is ambiguous in "
                             f"{zone_name} (daylight-saving change); give a UTC offset",
                             file=file) from None
    return int(stamp.tz_convert("UTC").as_unit("ns").value)


def source_times(raw: RawExport, spec: TimeSpec, fmt: FormatSpec, zone_name: str | None,
                 time_columns: list[int]) -> tuple[np.ndarray, bool]:
    """Sample times as int64 ns: since 1970 UTC (absolute) or since the export's own zero
    (``elapsed`` without an origin; then the second value is False)."""
    column = time_columns[0]
    if spec.kind == "elapsed":
        values, empty = _numbers(raw, column, fmt, f"a time in {spec.unit}")
        if empty.any():
            raise raw.error("empty time cell", int(np.flatnonzero(empty)[0]), column)
        ns = np.rint(values * (_TIME_UNITS_S[spec.unit] * _NS)).astype(np.int64)
        if spec.origin is not None:
            return ns + _origin_ns(spec.origin, None, zone_name, raw.label, "time.origin"), True
        if spec.origin_from_header is not None:
            return ns + _header_origin(raw, spec, zone_name), True
        return ns, False
    parts = [raw.cells[c] for c in time_columns]
    if len(parts) == 1:
        cells = parts[0]
    elif raw.text:
        joined = _text(parts[0])
        for part in parts[1:]:
            joined = joined.str.cat(_text(part), sep=" ")
        cells = joined.to_numpy(dtype=object)
    else:
        cells = np.array([" ".join("" if p is None else (p.strftime("%Y-%m-%d") if isinstance(
            p, dt.datetime) and i == 0 else p.strftime("%H:%M:%S.%f") if isinstance(p, dt.datetime)
            else p.isoformat() if isinstance(p, dt.time) else str(p)).strip()
            for i, p in enumerate(row)) for row in zip(*parts)], dtype=object)
    empty = _is_empty(cells, raw.text)
    if empty.any():
        raise raw.error("empty time cell", int(np.flatnonzero(empty)[0]), column)
    return _parse_datetimes(raw, column, cells, spec, zone_name), True


def convert_units(values: np.ndarray, unit: str, suffix: str) -> np.ndarray:
    """``values`` in ``unit`` onto the campaign unit of columns ending in ``suffix``
    (``_nm``, ``_C``, ``_um``, ``_N``)."""
    scale, offset = UNITS[suffix][unit]
    return values * scale + offset


# --------------------------------------------------------------------------------------------
# The import
# --------------------------------------------------------------------------------------------

class _Table:
    """One campaign file built from one export, with what it takes to point back at it."""

    def __init__(self, source: SourceSpec, raw: RawExport, time_ns: np.ndarray,
                 absolute: bool, values: dict[str, np.ndarray], column_of: dict[str, int],
                 time_column: int):
        self.source, self.raw, self.time_ns, self.absolute = source, raw, time_ns, absolute
        self.values, self.column_of, self.time_column = values, column_of, time_column


def _build_table(source: SourceSpec, base: Path, zone_name: str | None) -> _Table:
    path = Path(source.file)
    path = path if path.is_absolute() else base / path
    time_refs = source.time.column if isinstance(source.time.column, list) else [source.time.column]
    wanted = [(ref, "time") for ref in time_refs] + \
             [(spec.column, target) for target, spec in source.columns.items()]
    raw = read_export(path, source.format, wanted)
    if raw.lines.size == 0:
        raise InputError("no data rows below the column header", file=raw.label)
    locate = lambda ref, what: _resolve_column(ref, raw.names, raw.label, what, raw.label)  # noqa: E731
    time_columns = [locate(ref, "time") for ref in time_refs]
    column_of = {target: locate(spec.column, target) for target, spec in source.columns.items()}

    suffix = ROLE_SUFFIX[source.role]
    values, empties = {}, []
    for target, spec in source.columns.items():
        v, empty = _numbers(raw, column_of[target], source.format,
                            f"a number ({spec.unit or suffix[1:]})")
        values[target] = convert_units(v, spec.unit or _default_unit(suffix), suffix)
        empties.append(empty)
    empty_row = np.logical_or.reduce(empties)
    if empty_row.any():
        if source.format.on_empty == "error":
            row = int(np.flatnonzero(empty_row)[0])
            target = next(t for t, e in zip(source.columns, empties) if e[row])
            raise raw.error("empty cell (a lost peak or a logger gap?); every mapped cell must "
                            "hold a number, or set format.on_empty: drop_row", row,
                            column_of[target])
        keep = ~empty_row
        raw.keep(keep)
        values = {k: v[keep] for k, v in values.items()}
        if raw.lines.size == 0:
            raise InputError("every data row has an empty mapped cell", file=raw.label)
    time_tz = source.time.timezone or zone_name
    time_ns, absolute = source_times(raw, source.time, source.format, time_tz, time_columns)
    step = np.diff(time_ns)
    wrong = np.flatnonzero(step <= 0)
    if wrong.size:
        row = int(wrong[0]) + 1
        kind = "repeats" if step[row - 1] == 0 else "goes backwards from"
        raise raw.error(f"time {kind} the previous row's (data row {row}); times must increase "
                        "strictly (a daylight-saving change in local time? export with a UTC "
                        "offset, or give the zone in time.timezone)", row, time_columns[0])
    return _Table(source, raw, time_ns, absolute, values, column_of, time_columns[0])


def _default_unit(suffix: str) -> str:
    return next(iter(UNITS[suffix]))


def _campaign_meta(mapping: ImportMapping, mapping_file: Path) -> tuple[dict, Path, str]:
    """The campaign metadata block, the file it came from and the field prefix for errors."""
    if isinstance(mapping.campaign, str):
        path = Path(mapping.campaign)
        path = path if path.is_absolute() else mapping_file.parent / path
        if not path.is_file():
            raise InputError("campaign metadata file not found", file=path)
        raw = read_bounded(path, MAX_MAPPING_BYTES, what="campaign metadata")
        try:
            data = yaml.load(raw.decode("utf-8-sig"), Loader=MetaLoader)  # noqa: S506
        except (UnicodeDecodeError, yaml.YAMLError) as exc:
            raise InputError(f"not a readable YAML file: {type(exc).__name__}", file=path) from None
        if not isinstance(data, Mapping):
            raise InputError("expected a mapping (name, kind, sensors, ...)", file=path)
        return dict(data), path, ""
    return dict(mapping.campaign), mapping_file, "campaign."


def import_campaign(mapping_file: str | Path, output: str | Path) -> Campaign:
    """Read the exports a mapping file names and write the campaign folder ``output``.

    Times become seconds from the campaign start: ``start`` of the mapping, else the earliest
    first sample of all exports (timestamps with a zone or UTC offset on one common epoch).
    Values become nm, degC, um and N. Returns the campaign written.

    Raises
    ------
    InputError
        Naming the export file, its row (and file line) and column, or the mapping's field.
    """
    mapping_file = Path(mapping_file)
    mapping = read_mapping(mapping_file)
    meta, meta_file, prefix = _campaign_meta(mapping, mapping_file)
    if "start" in meta and mapping.start is None:
        mapping.start = str(meta["start"])
    tables = {s.role: _build_table(s, mapping_file.parent, mapping.timezone)
              for s in mapping.sources}

    relative = [t for t in tables.values() if not t.absolute]
    if relative and len(relative) != len(tables):
        t = relative[0]
        raise InputError(f"the {t.source.role} export's times are elapsed without an origin while "
                         "other exports carry dates: give time.origin or "
                         "time.origin_from_header", file=t.raw.label)
    if mapping.start is not None:
        start_ns = _origin_ns(mapping.start, None, mapping.timezone, mapping_file, "start")
    elif relative:
        raise InputError("every export's time is elapsed without an origin: give 'start' (the "
                         "date and time of elapsed 0, with a zone)", file=mapping_file,
                         column="field start")
    else:
        start_ns = min(int(t.time_ns[0]) for t in tables.values())
    offset_ns = start_ns if not relative else 0

    frames = {}
    for role, t in tables.items():
        columns = {TIME_COLUMN: (t.time_ns - offset_ns) / _NS}
        columns.update(t.values)
        frames[role] = pd.DataFrame(columns)
    meta = {**meta, "start": pd.Timestamp(start_ns, tz="UTC").isoformat()}
    try:
        campaign = Campaign.from_arrays(meta, fbg=frames["fbg"], temperatures=frames["temperatures"],
                                        reference=frames["reference"], loads=frames.get("loads"))
    except InputError as exc:
        raise _point_back(exc, tables, meta_file, prefix) from None
    write_campaign(campaign, output)
    return campaign


def _point_back(exc: InputError, tables: dict[str, _Table], meta_file: Path,
                prefix: str) -> InputError:
    """Turn an error the campaign checks raised about a campaign file into one naming the
    export row and column (or the mapping's field) it came from."""
    if exc.file == META_FILE:
        column = exc.column
        if column and column.startswith("field "):
            column = f"field {prefix}{column[6:]}"
        return InputError(exc.message, file=meta_file, column=column)
    role = _ROLE_OF_FILE.get(exc.file or "")
    table = tables.get(role) if role else None
    if table is None:
        return exc
    column = (table.time_column if exc.column == TIME_COLUMN
              else table.column_of.get(exc.column or ""))
    message = exc.message if exc.column is None else f"{exc.message} [campaign column {exc.column}]"
    if exc.row is None:
        return InputError(message, file=table.raw.label,
                          column=None if column is None else table.raw.column_label(column))
    return table.raw.error(message, exc.row - 1, column)


def describe(campaign: Campaign, mapping: str | Path, output: str | Path) -> str:
    """What an import wrote, for the console."""
    lines = [f"campaign {campaign.name!r} ({campaign.meta.kind}) written to {output}, "
             f"start {campaign.meta.start.isoformat()}"]
    for role, frame in (("fbg.csv", campaign.fbg), ("temperatures.csv", campaign.temperatures),
                        ("reference.csv", campaign.reference), ("loads.csv", campaign.loads)):
        if frame is None:
            continue
        t = frame[TIME_COLUMN].to_numpy()
        cols = ", ".join(c for c in frame.columns if c != TIME_COLUMN)
        lines.append(f"  {role:<17} {len(frame):>8} rows  {t[0]:>10.3f} to {t[-1]:>10.3f} s  {cols}")
    return "\n".join(lines)
