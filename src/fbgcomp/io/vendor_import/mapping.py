"""The mapping file of ``fbgcomp import``: its schema (sources, formats, times, columns, units)
and reading it.

A mapping error is an :class:`fbgcomp.errors.InputError` naming the mapping file and the field
(``field sources[0].time.format``).
"""

from __future__ import annotations

import codecs
import datetime as dt
import re
from collections.abc import Mapping
from pathlib import Path
from typing import Annotated, Any, Literal
from zoneinfo import ZoneInfo, ZoneInfoNotFoundError

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from fbgcomp.errors import InputError, read_bounded
from fbgcomp.io.campaign import (
    FBG_FILE,
    LOADS_FILE,
    REFERENCE_FILE,
    TEMPERATURES_FILE,
    MetaLoader,
    meta_error,
)
from fbgcomp.io.vendor_import.presets import apply_preset

__all__ = [
    "MAX_MAPPING_BYTES",
    "ROLE_FILES",
    "ROLE_SUFFIX",
    "UNITS",
    "ColumnSpec",
    "FormatSpec",
    "HeaderField",
    "ImportMapping",
    "SourceSpec",
    "TimeSpec",
    "parse_zone",
    "read_mapping",
]

#: Largest mapping file, bytes.
MAX_MAPPING_BYTES = 1 << 20

ROLE_FILES = {
    "fbg": FBG_FILE,
    "temperatures": TEMPERATURES_FILE,
    "reference": REFERENCE_FILE,
    "loads": LOADS_FILE,
}
#: The campaign unit of each role (suffix of its columns).
ROLE_SUFFIX = {"fbg": "_nm", "temperatures": "_C", "reference": "_um", "loads": "_N"}

#: Source unit -> (scale, offset) onto the campaign unit: ``value * scale + offset``.
UNITS = {
    "_nm": {"nm": (1.0, 0.0), "pm": (1e-3, 0.0), "um": (1e3, 0.0), "µm": (1e3, 0.0)},
    "_C": {
        "degC": (1.0, 0.0),
        "C": (1.0, 0.0),
        "°C": (1.0, 0.0),
        "K": (1.0, -273.15),
        "degF": (5.0 / 9.0, -32.0 * 5.0 / 9.0),
        "°F": (5.0 / 9.0, -32.0 * 5.0 / 9.0),
    },
    "_um": {
        "um": (1.0, 0.0),
        "µm": (1.0, 0.0),
        "nm": (1e-3, 0.0),
        "mm": (1e3, 0.0),
        "m": (1e6, 0.0),
        "in": (25400.0, 0.0),
        "mil": (25.4, 0.0),
    },
    "_N": {"N": (1.0, 0.0), "kN": (1e3, 0.0), "daN": (10.0, 0.0), "lbf": (4.4482216152605, 0.0)},
}

_OFFSET_RE = re.compile(r"^(?:UTC|GMT)?\s*([+-])([0-9]{1,2})(?::?([0-9]{2}))?$")


def parse_zone(text: str) -> dt.tzinfo:
    """A time zone from an IANA name (``Europe/Berlin``), ``UTC`` / ``Z`` or a fixed offset
    (``+01:00``, ``UTC-05``). Raises ValueError naming what it expected."""
    text = str(text).strip()
    if text.upper() in ("UTC", "Z", "GMT"):
        return dt.UTC
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
        raise ValueError(
            f"unknown time zone {text!r}; give an IANA name such as 'Europe/Berlin', "
            "'UTC' or an offset such as '+01:00'"
        ) from None


def _check_zone(value):
    if value is not None:
        parse_zone(value)
    return value


_ColumnRef = Annotated[str, Field(min_length=1)] | Annotated[int, Field(ge=1)]


class FormatSpec(BaseModel):
    """How an export file is laid out."""

    model_config = ConfigDict(extra="forbid")

    kind: Literal["csv", "excel"] | None = Field(
        default=None, description="csv (any delimited text) or excel (.xlsx); default from the extension"
    )
    delimiter: str | None = Field(
        default=None, description="one character, or 'tab' / 'space'; default ',' (tab for .tsv / .tab)"
    )
    decimal: Literal[".", ","] = "."
    thousands: Literal["", " ", ".", ",", "'", "\u202f"] = Field(
        default="", description="digit-group separator dropped before parsing numbers"
    )
    encoding: str = "utf-8-sig"
    header_row: Annotated[int, Field(ge=1)] | None = Field(
        default=None, description="1-based line (spreadsheet row) holding the column names"
    )
    header_marker: str | None = Field(
        default=None, description="the column names are on the first line whose first cell is this"
    )
    skip_after_header: Annotated[int, Field(ge=0)] = Field(
        default=0, description="lines between the column names and the first data row (e.g. units)"
    )
    sheet: str | Annotated[int, Field(ge=1)] | None = Field(
        default=None, description="spreadsheet: sheet name or 1-based index; default the first"
    )
    on_empty: Literal["error", "drop_row"] = Field(
        default="error", description="an empty cell in a mapped column: refuse, or drop its row"
    )

    @field_validator("delimiter")
    @classmethod
    def _one_character(cls, value):
        if value is None:
            return value
        named = {"tab": "\t", "\\t": "\t", "space": " "}
        value = named.get(value, value)
        if len(value) != 1 or value in '\r\n"':
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
        if self.decimal == self.thousands or (
            self.delimiter is not None and self.delimiter in (self.decimal, self.thousands)
        ):
            raise ValueError("delimiter, decimal mark and digit-group separator must differ")
        return self


class HeaderField(BaseModel):
    """A value in the lines above the column names: the cell after the one labelled ``label``."""

    model_config = ConfigDict(extra="forbid")

    label: Annotated[str, Field(min_length=1)]
    format: str | None = Field(default=None, description="strptime format; default ISO 8601")


class TimeSpec(BaseModel):
    """How an export writes its sample times."""

    model_config = ConfigDict(extra="forbid")

    column: _ColumnRef | Annotated[list[_ColumnRef], Field(min_length=1)] = Field(
        description="time column (name or 1-based position); a list is joined with spaces "
        "(a date column and a time column)"
    )
    kind: Literal["datetime", "elapsed"] = "datetime"
    format: str | None = Field(default=None, description="datetime: strptime format; default ISO 8601")
    timezone: str | None = Field(
        default=None, description="zone of timestamps without a UTC offset (default: the mapping's)"
    )
    unit: Literal["s", "ms", "us", "min", "h", "d"] = Field(default="s", description="elapsed: unit")
    origin: str | None = Field(default=None, description="elapsed: the date and time of elapsed 0")
    origin_from_header: HeaderField | None = Field(
        default=None, description="elapsed: read the date and time of elapsed 0 from the file's header"
    )

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
    unit: str | None = Field(default=None, description="its unit; default the campaign's")


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
            return {
                k: ({"column": v} if isinstance(v, (str, int)) and not isinstance(v, bool) else v)
                for k, v in value.items()
            }
        return value

    @model_validator(mode="after")
    def _units_fit_the_role(self):
        suffix = ROLE_SUFFIX[self.role]
        for target, spec in self.columns.items():
            if not target.endswith(suffix) or target == suffix:
                raise ValueError(
                    f"column {target!r} cannot go into {ROLE_FILES[self.role]}: its "
                    f"columns are named <name>{suffix}"
                )
            if spec.unit is not None and spec.unit not in UNITS[suffix]:
                raise ValueError(
                    f"unit {spec.unit!r} of column {target!r} is not one of {', '.join(UNITS[suffix])}"
                )
        return self


class ImportMapping(BaseModel):
    """The whole mapping file."""

    model_config = ConfigDict(extra="forbid")

    campaign: dict[str, Any] | Annotated[str, Field(min_length=1)] = Field(
        description="campaign.yaml content without start, or the path of such a YAML file"
    )
    start: str | None = Field(default=None, description="campaign start; default the first sample")
    timezone: str | None = Field(default=None, description="default zone of timestamps without offset")
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
                raise ValueError(
                    f"sources[{i}] and sources[{seen[source.role]}] both give "
                    f"role {source.role!r}; one export per campaign file"
                )
            seen[source.role] = i
        missing = [r for r in ("fbg", "temperatures", "reference") if r not in seen]
        if missing:
            raise ValueError(
                f"no source for role(s) {', '.join(missing)}: a campaign needs "
                "fbg, temperatures and reference (loads is optional)"
            )
        return self


def read_mapping(path: str | Path) -> ImportMapping:
    """Read and validate a mapping file (InputError naming the file and the field)."""
    file = Path(path)
    if not file.is_file():
        raise InputError("mapping file not found", file=file)
    raw = read_bounded(file, MAX_MAPPING_BYTES, what="a mapping file")
    try:
        data = yaml.load(raw.decode("utf-8-sig"), Loader=MetaLoader)
    except UnicodeDecodeError as exc:
        raise InputError(f"not UTF-8 text: byte 0x{raw[exc.start]:02x}", file=file) from None
    except yaml.MarkedYAMLError as exc:
        mark = exc.problem_mark or exc.context_mark
        where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark else ""
        raise InputError(f"YAML syntax error{where}: {exc.problem or exc.context}", file=file) from None
    if not isinstance(data, Mapping):
        raise InputError("expected a mapping (campaign: ..., sources: [...]) at the top level", file=file)
    data = dict(data)
    if isinstance(data.get("sources"), list):
        data["sources"] = [
            apply_preset(s, i, file) if isinstance(s, Mapping) else s for i, s in enumerate(data["sources"])
        ]
    try:
        return ImportMapping.model_validate(data)
    except ValidationError as exc:
        raise meta_error(exc, file) from None
