"""Campaign folders: read, validate, align the instruments' clocks, zero state, write.

A campaign is one experiment on the machine (paper section 3: static loads at the TTP, or a 36 h
thermal run) stored as a folder::

    <campaign>/campaign.yaml       metadata: sensors, probes, reference instrument, free extras
    <campaign>/fbg.csv             time_s, <sensor>_nm ...     Bragg peak wavelengths, nm
    <campaign>/temperatures.csv    time_s, <probe>_C ...       probe temperatures, degC
    <campaign>/reference.csv       time_s, dx_um, dy_um, dz_um TTP displacement (interferometer), um
    <campaign>/loads.csv           time_s, fx_N, fy_N, fz_N    optional: forces at the TTP, N

Each CSV has its own clock and rate. :func:`read_campaign` validates everything at this boundary
and raises :class:`fbgcomp.errors.InputError` naming file, row and column, so the physics modules
downstream can assume clean, finite, strictly time-ordered arrays. :meth:`Campaign.aligned` puts
every instrument on the reference instrument's clock (linear interpolation, never extrapolation)
and takes the zero state the paper's deltas (``Delta S_i``, ``Delta T``, eq. 13) are measured from.

Decisions the rest of the package relies on
-------------------------------------------
* Column order is canonical after reading: ``time_s`` first, then sensors in ``campaign.yaml``
  order (fbg), declared probes then undeclared ``<probe>_C`` columns in file order (temperatures),
  dx/dy/dz (reference), fx/fy/fz (loads).
* Temperature columns not declared in ``campaign.yaml`` are kept as probes
  (:attr:`Campaign.probe_names` lists them after the declared ones) and reported by
  :meth:`Campaign.summary`; ``meta`` itself stays exactly what the YAML says, so it round-trips.
* Loads do not restrict the alignment overlap. Inside the loads' own time range they are linearly
  interpolated; outside it they are NaN (never extrapolated, never held).
  ``dropped["loads_outside"]`` counts those samples.
* The zero state of every signal is the mean over the first ``zero_window_s`` seconds of that
  signal on its own clock (samples with ``t <= t_first + zero_window_s``, at least one), taken from
  the whole file, including samples before the alignment overlap.

Limits (the reader is bounded whatever a file holds)
----------------------------------------------------
* A CSV holds at most :data:`MAX_COLUMNS` (4096) columns; its header line is read with a bounded
  readline (:data:`MAX_HEADER_BYTES`, 1 MiB) and checked in linear time. A data row may be at
  most :data:`MAX_CELL_BYTES` (256) bytes per column long (64 KiB at least).
* Files are streamed: the body is parsed in blocks of whole rows, never read whole.
  ``campaign.yaml`` may be at most :data:`MAX_META_BYTES` (1 MiB).
* Every number must lie within its column's physical bounds (:data:`VALUE_BOUNDS`): wavelengths
  in (0, 10000) nm, temperatures in [-273.15, 1000] degC, displacements in (-1e6, 1e6) um, forces
  in (-1e7, 1e7) N, times in (-1e10, 1e10) s. Anything else is refused as a bad cell of the file
  it is in, so no overflow can reach the physics and surface against a derived quantity.
* Errors quote at most the offending cell or column name, cut short, and only names that are
  printable text: never a header line (``fbg.csv`` may be a link to some other file).
"""

from __future__ import annotations

import codecs
import csv
import difflib
import io
import math
import os
import re
import shutil
import uuid
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any, Literal, Mapping

import numpy as np
import pandas as pd
import yaml
from pydantic import (AwareDatetime, BaseModel, ConfigDict, Field, StrictStr, ValidationError,
                      field_validator, model_validator)
from pydantic_core import PydanticCustomError

from fbgcomp import optics
from fbgcomp.atomic import replace_dir
from fbgcomp.errors import InputError, read_bounded

__all__ = [
    "SensorSpec", "ProbeSpec", "ReferenceSpec", "CampaignMeta", "Campaign", "AlignedCampaign",
    "read_campaign", "write_campaign",
    "META_FILE", "FBG_FILE", "TEMPERATURES_FILE", "REFERENCE_FILE", "LOADS_FILE",
    "REFERENCE_COLUMNS", "LOAD_COLUMNS", "WAVELENGTH_BAND_NM", "GAP_FACTOR",
    "MAX_COLUMNS", "MAX_HEADER_BYTES", "MAX_CELL_BYTES", "MAX_META_BYTES", "VALUE_BOUNDS",
]

META_FILE = "campaign.yaml"
FBG_FILE = "fbg.csv"
TEMPERATURES_FILE = "temperatures.csv"
REFERENCE_FILE = "reference.csv"
LOADS_FILE = "loads.csv"

TIME_COLUMN = "time_s"
REFERENCE_COLUMNS = ("dx_um", "dy_um", "dz_um")
LOAD_COLUMNS = ("fx_N", "fy_N", "fz_N")
#: A peak further than this from the grating's nominal lambda0_nm is a lost peak, a peak picked
#: from the neighbouring grating or a wrong channel mapping: no structure strains an FBG by ~0.4 %.
WAVELENGTH_BAND_NM = 5.0
#: Sampling gaps longer than this many median intervals are reported by ``summary()``.
GAP_FACTOR = 5.0
#: Largest campaign.yaml read, bytes (a real one is a few kB).
MAX_META_BYTES = 1 << 20

# Silica fibre defaults (paper eq. 2); the same values as fbgcomp.optics, repeated here so that
# the file format does not depend on the physics module.
_DEFAULT_PHOTOELASTIC = 0.22
_DEFAULT_THERMO_OPTIC_PER_K = 6.67e-6
_DEFAULT_FIBRE_CTE_PER_K = 0.55e-6

_NAME_RE = r"^[A-Za-z_][A-Za-z0-9_.\-]*$"
_FiniteFloat = Annotated[float, Field(strict=True, allow_inf_nan=False)]
_PositiveFloat = Annotated[float, Field(strict=True, allow_inf_nan=False, gt=0)]
_Name = Annotated[StrictStr, Field(pattern=_NAME_RE)]


# --------------------------------------------------------------------------------------------
# Metadata (campaign.yaml)
# --------------------------------------------------------------------------------------------

class SensorSpec(BaseModel):
    """One long-gauge FBG sensor: its grating, its fibre and where it is bonded.

    Unknown keys are kept (and round-tripped) so that instrument-specific metadata survives;
    ``Campaign.summary()`` lists them in case one is a typo of a known key.
    """

    model_config = ConfigDict(extra="allow")

    name: _Name
    lambda0_nm: _PositiveFloat = Field(description="nominal Bragg wavelength of the grating, nm")
    gauge_length_mm: _PositiveFloat = Field(description="bonded length of the sensor path, mm")
    photoelastic: _FiniteFloat = Field(_DEFAULT_PHOTOELASTIC, ge=0, lt=1,
                                       description="effective photo-elastic coefficient p_e")
    thermo_optic_per_K: _FiniteFloat = Field(_DEFAULT_THERMO_OPTIC_PER_K,
                                             description="thermo-optic coefficient xi, 1/K")
    fibre_cte_per_K: _FiniteFloat = Field(_DEFAULT_FIBRE_CTE_PER_K,
                                          description="fibre thermal expansion alpha_f, 1/K")
    face: Literal["+X", "-X", "+Y", "-Y", "+Z", "-Z"] | None = None
    z_start_mm: _FiniteFloat | None = None
    z_end_mm: _FiniteFloat | None = None
    temperature_probe: _Name | None = Field(
        None, description="probe used for temperature compensation; none: uncompensated")
    reference_lambda0_nm: _PositiveFloat | None = Field(
        None, description="nominal wavelength of a strain-free reference grating beside the "
                          "sensor (fbg.csv column <name>_ref_nm); it compensates the sensor "
                          "unless temperature_probe names another probe")

    @model_validator(mode="after")
    def _reference_compensates(self):
        if self.reference_lambda0_nm is not None and self.temperature_probe is None:
            self.temperature_probe = self.reference_probe
        return self

    @property
    def column(self) -> str:
        """Its column in fbg.csv."""
        return f"{self.name}_nm"

    @property
    def reference_column(self) -> str | None:
        """The fbg.csv column of its strain-free reference grating, None without one."""
        return None if self.reference_lambda0_nm is None else f"{self.name}_ref_nm"

    @property
    def reference_probe(self) -> str | None:
        """The temperature the reference grating reads, as a probe name (``<name>_ref``)."""
        return None if self.reference_lambda0_nm is None else f"{self.name}_ref"


class ProbeSpec(BaseModel):
    """One temperature probe (thermocouple, LM35...)."""

    model_config = ConfigDict(extra="allow")

    name: _Name
    location: StrictStr | None = None

    @property
    def column(self) -> str:
        """Its column in temperatures.csv."""
        return f"{self.name}_C"


class ReferenceSpec(BaseModel):
    """The instrument measuring the true TTP displacement (reference.csv)."""

    model_config = ConfigDict(extra="allow")

    instrument: StrictStr = "laser interferometer"
    point: StrictStr = "TTP"
    units: Literal["um"] = "um"


class CampaignMeta(BaseModel):
    """Contents of ``campaign.yaml``. Keys not modelled here (``machine``, ``seed``...) are kept."""

    model_config = ConfigDict(extra="allow")

    name: Annotated[StrictStr, Field(min_length=1)]
    kind: Literal["thermal", "static", "combined"]
    description: StrictStr = ""
    start: AwareDatetime
    sensors: Annotated[list[SensorSpec], Field(min_length=1)]
    temperature_probes: list[ProbeSpec] = Field(default_factory=list)
    reference: ReferenceSpec = Field(default_factory=ReferenceSpec)

    @field_validator("description", mode="before")
    @classmethod
    def _blank_description(cls, value):
        # "description:" with nothing after it is YAML null; treat it as no description.
        return "" if value is None else value

    @model_validator(mode="after")
    def _names_consistent(self):
        for kind, items in (("sensor", self.sensors), ("probe", self.temperature_probes)):
            key = "sensors" if kind == "sensor" else "temperature_probes"
            first: dict[str, int] = {}
            for i, item in enumerate(items):
                if item.name in first:
                    raise PydanticCustomError(
                        "duplicate_name",
                        "duplicate {kind} name '{name}' (first declared as {key}[{first}])",
                        {"kind": kind, "name": item.name, "key": key, "first": first[item.name],
                         "field": f"{key}[{i}].name"})
                first[item.name] = i
        refs = set(self.reference_probe_names)
        for i, probe in enumerate(self.temperature_probes):
            if probe.name in refs:
                raise PydanticCustomError(
                    "duplicate_name",
                    "probe name '{name}' is taken by the reference grating of sensor '{sensor}'",
                    {"name": probe.name, "sensor": probe.name[:-4],
                     "field": f"temperature_probes[{i}].name"})
        probes = self.probe_names
        for i, sensor in enumerate(self.sensors):
            if sensor.temperature_probe is not None and sensor.temperature_probe not in probes:
                raise PydanticCustomError(
                    "unknown_probe",
                    "sensor '{sensor}' names temperature probe '{probe}', which is not declared "
                    "in temperature_probes (declared: {declared})",
                    {"sensor": sensor.name, "probe": sensor.temperature_probe,
                     "declared": ", ".join(probes) or "none",
                     "field": f"sensors[{i}].temperature_probe"})
        return self

    @property
    def sensor_names(self) -> list[str]:
        return [s.name for s in self.sensors]

    @property
    def probe_names(self) -> list[str]:
        """Declared probes, then the strain-free reference gratings read as thermometers
        (``<sensor>_ref``); see :attr:`Campaign.probe_names` for undeclared CSV columns."""
        return [p.name for p in self.temperature_probes] + self.reference_probe_names

    @property
    def reference_probe_names(self) -> list[str]:
        """``<sensor>_ref`` for every sensor with a strain-free reference grating."""
        return [s.reference_probe for s in self.sensors if s.reference_probe is not None]

    def sensor(self, name: str) -> SensorSpec:
        for s in self.sensors:
            if s.name == name:
                return s
        raise KeyError(name)

    def probe(self, name: str) -> ProbeSpec:
        for p in self.temperature_probes:
            if p.name == name:
                return p
        raise KeyError(name)


_YAML_FLOAT_RE = re.compile(r"""^(?:[-+]?(?:[0-9][0-9_]*)\.[0-9_]*(?:[eE][-+]?[0-9]+)?
    |[-+]?(?:[0-9][0-9_]*)(?:[eE][-+]?[0-9]+)
    |[-+]?\.[0-9_]+(?:[eE][-+]?[0-9]+)?
    |[-+]?\.(?:inf|Inf|INF)
    |\.(?:nan|NaN|NAN))$""", re.X)


class _MetaLoader(yaml.SafeLoader):
    """Safe loader that reads ``1e-6`` as a number (YAML 1.1 would make it a string, and a
    coefficient typed that way would then be rejected) and refuses duplicate keys, which plain
    PyYAML silently resolves by keeping the last one."""

    def construct_mapping(self, node, deep=False):
        seen = {}
        for key_node, _ in node.value:
            key = self.construct_object(key_node, deep=True)
            try:
                duplicate = key in seen
            except TypeError:  # unhashable key: let the base class report it
                break
            if duplicate:
                raise yaml.constructor.ConstructorError(
                    None, None, f"duplicate key {key!r} (first at line {seen[key] + 1})",
                    key_node.start_mark)
            seen[key] = key_node.start_mark.line
        return super().construct_mapping(node, deep=deep)


class _MetaDumper(yaml.SafeDumper):
    """Quotes strings such as ``'1e5'`` that :class:`_MetaLoader` would read back as numbers."""


def _represent_str(dumper, value: str):
    # PyYAML writes NEL / LINE SEPARATOR / PARAGRAPH SEPARATOR / BOM raw in plain and single-quoted
    # scalars, where a reader folds them into spaces; double quotes escape them (\N, \L, \P).
    style = '"' if any(ch in value for ch in "\x85\u2028\u2029\ufeff") else None
    return dumper.represent_scalar("tag:yaml.org,2002:str", value, style=style)


_MetaLoader.add_implicit_resolver("tag:yaml.org,2002:float", _YAML_FLOAT_RE, list("-+0123456789."))
_MetaDumper.add_implicit_resolver("tag:yaml.org,2002:float", _YAML_FLOAT_RE, list("-+0123456789."))
_MetaDumper.add_representer(str, _represent_str)


def _field_path(loc) -> str:
    path = ""
    for part in loc:
        path += f"[{part}]" if isinstance(part, int) else (f".{part}" if path else str(part))
    return path


def _short(value, limit: int = 60) -> str:
    text = repr(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _meta_error(exc: ValidationError, file) -> InputError:
    err = exc.errors()[0]
    ctx = err.get("ctx") or {}
    path = ctx.get("field") or _field_path(err["loc"]) or "campaign.yaml"
    if err["type"] == "missing":
        message = "required field is missing"
    elif err["type"] in ("duplicate_name", "unknown_probe"):
        message = err["msg"]
    else:
        message = f"{err['msg']} (got {_short(err.get('input'))})"
    more = exc.error_count() - 1
    if more:
        message += f" [and {more} more problem{'s' if more > 1 else ''}]"
    return InputError(message, file=file, column=f"field {path}")


def _validate_meta(data: Any, file) -> CampaignMeta:
    if isinstance(data, CampaignMeta):
        data = data.model_dump()
    if not isinstance(data, Mapping):
        raise InputError("expected a mapping of fields (name: ..., kind: ..., sensors: ...) at the "
                         f"top level, found {type(data).__name__}", file=file)
    try:
        return CampaignMeta.model_validate(dict(data))
    except ValidationError as exc:
        raise _meta_error(exc, file) from None


def _read_meta(folder: Path) -> CampaignMeta:
    file = folder / META_FILE
    if not file.is_file():
        raise InputError("missing file: a campaign folder needs campaign.yaml "
                         "(name, kind, start, sensors, temperature_probes, reference)", file=file)
    raw = read_bounded(file, MAX_META_BYTES, what="campaign metadata")
    if not raw.strip():
        raise InputError("empty file: expected the campaign metadata "
                         "(name, kind, start, sensors, ...)", file=file)
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        line = raw[: exc.start].count(b"\n") + 1
        raise InputError(f"not UTF-8 text: byte 0x{raw[exc.start]:02x} at line {line}",
                         file=file) from None
    try:
        data = yaml.load(text, Loader=_MetaLoader)  # noqa: S506 - a SafeLoader subclass
    except yaml.MarkedYAMLError as exc:
        mark = exc.problem_mark or exc.context_mark
        where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark else ""
        problem = exc.problem or exc.context or "invalid YAML"
        raise InputError(f"YAML syntax error{where}: {problem}", file=file) from None
    except yaml.YAMLError as exc:
        raise InputError(f"YAML syntax error: {exc}", file=file) from None
    return _validate_meta(data, file)


def _plain(value):
    """Metadata as YAML-safe builtins (numpy scalars from a generator, tuples...)."""
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, Mapping):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, Path):
        return str(value)
    return value


_OPTIONAL_SENSOR_KEYS = ("face", "z_start_mm", "z_end_mm", "temperature_probe")


def _meta_yaml(meta: CampaignMeta, file) -> str:
    data = _plain(meta.model_dump(mode="python"))
    for sensor in data["sensors"]:
        for key in _OPTIONAL_SENSOR_KEYS:
            if sensor.get(key, "") is None:
                del sensor[key]
    for probe in data["temperature_probes"]:
        if probe.get("location", "") is None:
            del probe["location"]
    try:
        return yaml.dump(data, Dumper=_MetaDumper, sort_keys=False, allow_unicode=True,
                         default_flow_style=None, width=160)
    except yaml.YAMLError as exc:
        raise InputError(f"metadata cannot be written as YAML: {exc}", file=file) from None


# --------------------------------------------------------------------------------------------
# CSV tables
# --------------------------------------------------------------------------------------------

_NUMBER_RE = re.compile(r"[+-]?(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][+-]?[0-9]+)?", re.ASCII)
_NON_FINITE_RE = re.compile(r"[+-]?(?:nan|inf|infinity)", re.ASCII | re.IGNORECASE)
_DELIMITERS = ((";", "';'"), ("\t", "tab ('\\t')"), ("|", "'|'"))
_LINE_END_RE = re.compile(rb"[\r\n]")

#: Most columns a campaign CSV may hold. A machine carries tens of gratings and probes; a wider
#: header is a wrong file (or an attack on the reader), refused before any row is read.
MAX_COLUMNS = 4096
#: Longest header line (line 1), bytes: MAX_COLUMNS names of up to 255 bytes. It is read with
#: a bounded readline, so a file with no line end cannot make the reader take it whole.
MAX_HEADER_BYTES = 1 << 20
#: Longest data row, bytes per column (a number printed in full is ~25 bytes): a row longer than
#: this many bytes times the columns (at least 64 KiB) is refused instead of being buffered.
MAX_CELL_BYTES = 256
_MIN_ROW_BYTES = 1 << 16
#: The body is parsed in blocks of about this many bytes (whole rows), so reading a file holds
#: one block of text at a time beside the parsed numbers.
_CHUNK_BYTES = 4 << 20
#: Physical bounds per column role: a number outside them is a bad cell (a unit mix-up, a
#: logger's overflow, a corrupted file), not a measurement. ``(low, high, ends included,
#: quantity, unit)``; a wavelength must be inside (0, 10000) nm, a temperature inside
#: [-273.15, 1000] degC, a displacement inside (-1e6, 1e6) um (1 m), a force inside
#: (-1e7, 1e7) N and a time inside (-1e10, 1e10) s (about 317 years).
VALUE_BOUNDS = {
    TIME_COLUMN: (-1e10, 1e10, False, "time", "s"),
    "_nm": (0.0, 1e4, False, "wavelength", "nm"),
    "_C": (-273.15, 1000.0, True, "temperature", "degC"),
    "_um": (-1e6, 1e6, False, "displacement", "um"),
    "_N": (-1e7, 1e7, False, "force", "N"),
}


def _role_columns(role: str, meta: CampaignMeta) -> tuple[list[str], str]:
    """Required columns of a file and a description of what it holds (for messages)."""
    if role == FBG_FILE:
        refs = [s.reference_column for s in meta.sensors if s.reference_column is not None]
        return ([TIME_COLUMN] + [s.column for s in meta.sensors] + refs,
                "time_s, <sensor>_nm and, for sensors with reference_lambda0_nm, <sensor>_ref_nm columns")
    if role == TEMPERATURES_FILE:
        return ([TIME_COLUMN] + [p.column for p in meta.temperature_probes],
                "time_s and <probe>_C columns")
    if role == REFERENCE_FILE:
        return [TIME_COLUMN, *REFERENCE_COLUMNS], "time_s, dx_um, dy_um, dz_um"
    return [TIME_COLUMN, *LOAD_COLUMNS], "time_s, fx_N, fy_N, fz_N"


def _column_label(name: str, position: int) -> str:
    """A header name as errors may show it: the name when it is short printable text, else its
    position (``#3``), so that an error never prints a binary or foreign file's first line."""
    if name.isprintable() and len(name) <= 64:
        return name
    return f"#{position}"


def _check_columns(role: str, names: list[str], meta: CampaignMeta, file) -> list[str]:
    """Check a header against the metadata; return the canonical column order."""
    required, holds = _role_columns(role, meta)
    present = set(names)
    for column in required:
        if column not in present:
            shown = [n for n in names if n.isprintable() and len(n) <= 64]
            close = difflib.get_close_matches(column, shown[:MAX_COLUMNS], n=1, cutoff=0.75)
            hint = f"; did you mean {close[0]!r}?" if close else ""
            # Never list the header itself: fbg.csv may be a link to some other file.
            raise InputError(f"missing column {column!r}; {role} must hold {holds} (the header "
                             f"has {len(names)} column{'s' if len(names) != 1 else ''}{hint})",
                             file=file, column=column)
    wanted = set(required)
    extra = [(position, n) for position, n in enumerate(names, start=1) if n not in wanted]
    for position, column in extra:
        if role == FBG_FILE and column.endswith("_ref_nm") and column[:-7] in meta.sensor_names:
            raise InputError(
                f"column {column} holds a reference grating for sensor {column[:-7]}, which "
                f"declares none: give it reference_lambda0_nm in campaign.yaml",
                file=file, column=column)
        if role == FBG_FILE and column.endswith("_nm"):
            label = _column_label(column, position)
            sensor = f"{column[:-3]!r}" if label == column else "of that name"
            raise InputError(
                f"unknown sensor {sensor}: column {label} has no entry in campaign.yaml "
                f"sensors (declared: {', '.join(meta.sensor_names)})", file=file, column=label)
    # Any other extra column (a status flag, a second interferometer axis, ...) is read, checked
    # like the rest, and left out of the campaign; summary() reports it. The format names the
    # columns a file must hold, not the only ones it may hold. Undeclared <probe>_C columns are
    # kept as probes (and reported by summary()).
    return required + [n for _, n in extra
                       if role == TEMPERATURES_FILE and n.endswith("_C") and len(n) > 2]


def _cell_problem(text: str) -> str | None:
    """Why a CSV cell is not a finite number, or None when it is one (quotes the cell cut to
    32 characters)."""
    cell = text.strip()
    if cell == "":
        return "empty cell; every cell must hold a number"
    if _NUMBER_RE.fullmatch(cell):
        if math.isfinite(float(cell)):
            return None
        return f"value {_short(cell, 32)} overflows to infinity"
    if _NON_FINITE_RE.fullmatch(cell):
        return f"non-finite value {_short(cell, 32)}; every cell must be a finite number"
    return f"not a number: {_short(cell, 32)}; expected a decimal number such as 1530.125"


def _locate_bad_cell(file, names: list[str], body: bytes, first_row: int = 1) -> None:
    """Slow path, run only after the fast parser failed on one block of rows: raise the first
    bad cell's InputError (``first_row``: the data row number of the block's first line).

    A text read of the block and pandas' vectorised number conversion nominate suspect cells;
    each is confirmed by :func:`_cell_problem` in file order. Only when that finds nothing (or
    the text read itself fails) is every line scanned in Python.
    """
    try:
        text = pd.read_csv(io.BytesIO(body + b"\n"), header=None, names=names, index_col=False,
                           dtype=str, sep=",", engine="c", quoting=csv.QUOTE_NONE,
                           na_filter=False, skip_blank_lines=False, encoding="utf-8")
    except Exception:  # noqa: BLE001 - e.g. bytes that are not UTF-8: the line scan names them
        text = None
    if text is not None and text.shape[1] == len(names):
        suspects = []
        for col, name in enumerate(names):
            numbers = pd.to_numeric(text[name], errors="coerce").to_numpy(dtype=np.float64)
            suspects.extend((int(row), col) for row in np.flatnonzero(~np.isfinite(numbers)))
        for row, col in sorted(suspects):
            problem = _cell_problem(text.iat[row, col])
            if problem:
                raise InputError(problem, file=file, row=first_row + row, column=names[col])
    for index, line in enumerate(body.split(b"\n")):
        row = first_row + index
        try:
            decoded = line.decode("utf-8")
        except UnicodeDecodeError as exc:
            col = line[: exc.start].count(b",")
            raise InputError(f"not UTF-8 text: byte 0x{line[exc.start]:02x}", file=file, row=row,
                             column=names[col] if col < len(names) else None) from None
        for col, cell in enumerate(decoded.split(",")[: len(names)]):
            problem = _cell_problem(cell)
            if problem:
                raise InputError(problem, file=file, row=row, column=names[col])


def _open_table(file: Path):
    """The CSV opened for reading in binary, or the InputError saying why it cannot be."""
    if not file.exists():
        raise InputError("missing file", file=file)
    if not file.is_file():
        raise InputError("expected a file, found a folder or device", file=file)
    try:
        return open(file, "rb")
    except OSError as exc:
        raise InputError(f"cannot open the file: {exc.strerror or type(exc).__name__}",
                         file=file) from None


def _read_header(handle, file) -> tuple[list[str], bytes]:
    """Column names, and the bytes read beyond them (the header's line end and what follows).

    Reads at most :data:`MAX_HEADER_BYTES` + 1 bytes, counts the columns before decoding them and
    checks for duplicates with a set: linear in the header's length whatever it holds.
    """
    head = handle.readline(MAX_HEADER_BYTES + 1)
    if not head:
        raise InputError("empty file (0 bytes); expected a header row such as 'time_s,...' "
                         "followed by data rows", file=file)
    cut = _LINE_END_RE.search(head)
    if cut is None and len(head) > MAX_HEADER_BYTES:
        raise InputError(f"the header (line 1) is longer than {MAX_HEADER_BYTES} bytes; a "
                         f"campaign CSV holds at most {MAX_COLUMNS} columns", file=file)
    line, rest = (head, b"") if cut is None else (head[: cut.start()], head[cut.start():])
    if line.startswith(codecs.BOM_UTF8):
        line = line[len(codecs.BOM_UTF8):]
    n_columns = line.count(b",") + 1
    if n_columns > MAX_COLUMNS:
        raise InputError(f"the header has {n_columns} columns; a campaign CSV holds at most "
                         f"{MAX_COLUMNS}", file=file)
    try:
        header = line.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise InputError(f"header (line 1) is not UTF-8 text: byte 0x{line[exc.start]:02x}",
                         file=file) from None
    if not header.strip():
        raise InputError("line 1 is blank; expected the header row, e.g. 'time_s,...'", file=file)
    if "," not in header:
        for delimiter, label in _DELIMITERS:
            if delimiter in header:
                raise InputError(f"expected comma-separated columns, found {label}", file=file)
    names: list[str] = []
    first: dict[str, int] = {}
    for position, name in enumerate(header.split(","), start=1):
        name = name.strip()
        if len(name) >= 2 and name[0] == name[-1] == '"':
            name = name[1:-1].strip()
        if not name:
            raise InputError(f"header column {position} has no name", file=file)
        if name in first:
            raise InputError(f"column name appears twice in the header (columns "
                             f"{first[name]} and {position})", file=file,
                             column=_column_label(name, position))
        first[name] = position
        names.append(name)
    return names, rest


def _body_blocks(handle, rest: bytes):
    """The data rows' bytes, in blocks of about :data:`_CHUNK_BYTES`, with CR LF and lone CR
    line ends turned into LF. ``rest`` is what the header read took beyond the header line:
    empty (the file ends there) or starting with the header's own line end, which is dropped."""
    pending_cr = False   # the previous block ended with CR: an LF opening this one belongs to it
    first = True
    block = rest
    while block:
        if pending_cr and block[:1] == b"\n":
            block = block[1:]
        pending_cr = block[-1:] == b"\r"
        if b"\r" in block:
            block = block.replace(b"\r\n", b"\n").replace(b"\r", b"\n")
        if first and block:
            block, first = block[1:], False
        if block:
            yield block
        block = handle.read(_CHUNK_BYTES)


def _parse_rows(file, names: list[str], blocks) -> np.ndarray:
    """All data rows as floats (n_rows, n_columns), parsed block by block of whole lines, or
    the InputError of the first bad row or cell. Blank lines at the very end are an editor's
    habit and ignored; a blank line before a data row is an empty row."""
    n_cols = len(names)
    longest = max(_MIN_ROW_BYTES, n_cols * MAX_CELL_BYTES)
    parts: list[np.ndarray] = []
    rows = 0      # data rows parsed so far
    blank = 0     # blank lines after them, not yet known to be the file's trailing ones
    carry = b""   # a line whose end has not been read yet

    def take(lines: bytes) -> None:
        nonlocal rows, blank
        end = len(lines.rstrip(b" \t\n"))
        if end == 0:
            blank += lines.count(b"\n") + 1
            return
        if blank:
            raise InputError(f"empty row (blank line); expected {n_cols} comma-separated values",
                             file=file, row=rows + 1)
        tail = lines.find(b"\n", end)
        if tail >= 0:
            blank = lines.count(b"\n", tail)
            lines = lines[:tail]
        values = _parse_body(file, names, lines, first_row=rows + 1)
        parts.append(values)
        rows += values.shape[0]

    for block in blocks:
        buffer = carry + block if carry else block
        last = buffer.rfind(b"\n")
        if last >= 0:
            carry = buffer[last + 1:]
            take(buffer[:last])
        else:
            carry = buffer
        if len(carry) > longest:
            raise InputError(f"row is longer than {longest} bytes; expected {n_cols} "
                             "comma-separated numbers", file=file, row=rows + blank + 1)
    if carry.strip(b" \t"):
        take(carry.rstrip(b" \t"))
    if not parts:
        raise InputError("no data rows: the file holds only a header", file=file)
    return parts[0] if len(parts) == 1 else np.vstack(parts)


def _columns_text(names: list[str], limit: int = 12) -> str:
    shown = [_column_label(n, i) for i, n in enumerate(names[:limit], start=1)]
    return ", ".join(shown) + (f", ... ({len(names)} in all)" if len(names) > limit else "")


def _parse_body(file, names: list[str], body: bytes, first_row: int = 1) -> np.ndarray:
    """Whole data rows (no trailing line end) as floats (n_rows, n_columns), or the InputError
    of the first bad cell; ``first_row`` numbers the first line in messages."""
    if not body:
        raise InputError("no data rows: the file holds only a header", file=file)
    n_cols = len(names)
    buffer = np.frombuffer(body, dtype=np.uint8)
    line_ends = np.flatnonzero(buffer == ord("\n"))
    n_rows = line_ends.size + 1
    separators = np.bincount(np.searchsorted(line_ends, np.flatnonzero(buffer == ord(","))),
                             minlength=n_rows)
    wrong = np.flatnonzero(separators != n_cols - 1)
    if wrong.size:
        index = int(wrong[0])
        start = 0 if index == 0 else int(line_ends[index - 1]) + 1
        stop = int(line_ends[index]) if index < line_ends.size else len(body)
        line = body[start:stop].decode("utf-8", errors="replace")
        found = int(separators[index]) + 1
        if not line.strip():
            raise InputError(f"empty row (blank line); expected {n_cols} comma-separated values",
                             file=file, row=first_row + index)
        if found == 1:
            for delimiter, label in _DELIMITERS:
                if delimiter in line:
                    raise InputError(f"expected comma-separated columns, found {label}",
                                     file=file, row=first_row + index)
        raise InputError(f"row has {found} values, expected {n_cols} ({_columns_text(names)})",
                         file=file, row=first_row + index,
                         column=names[found] if found < n_cols else None)
    try:
        frame = pd.read_csv(io.BytesIO(body + b"\n"), header=None, names=names, index_col=False,
                            dtype=np.float64, sep=",", engine="c", quoting=csv.QUOTE_NONE,
                            na_filter=False, skip_blank_lines=False, encoding="utf-8")
        values = frame.to_numpy(dtype=np.float64)
        if values.shape != (n_rows, n_cols):
            raise ValueError(f"parsed {values.shape}, expected {(n_rows, n_cols)}")
    except Exception as exc:  # noqa: BLE001 - any parser failure is located cell by cell below
        _locate_bad_cell(file, names, body, first_row)
        raise InputError(f"cannot read the numbers: {type(exc).__name__}", file=file) from None
    bad = ~np.isfinite(values)
    if bad.any():
        index = int(np.argmax(bad.any(axis=1)))
        col = int(np.argmax(bad[index]))
        start = 0 if index == 0 else int(line_ends[index - 1]) + 1
        stop = int(line_ends[index]) if index < line_ends.size else len(body)
        cell = body[start:stop].decode("utf-8", errors="replace").split(",")[col]
        raise InputError(_cell_problem(cell) or f"non-finite value {_short(cell, 32)}",
                         file=file, row=first_row + index, column=names[col])
    return values


def _bounds_of(column: str):
    if column == TIME_COLUMN:
        return VALUE_BOUNDS[TIME_COLUMN]
    for suffix in ("_nm", "_C", "_um", "_N"):
        if column.endswith(suffix):
            return VALUE_BOUNDS[suffix]
    return None


def _check_bounds(names: list[str], kept, values: np.ndarray, file) -> None:
    """Refuse the first number (in file order) outside its column's :data:`VALUE_BOUNDS`."""
    first = None
    for col, name in enumerate(names):
        bounds = _bounds_of(name) if name in kept else None
        if bounds is None:
            continue
        low, high, closed, _, _ = bounds
        column = values[:, col]
        outside = ((column < low) | (column > high)) if closed else ((column <= low) | (column >= high))
        if outside.any():
            row = int(np.argmax(outside))
            if first is None or (row, col) < first:
                first = (row, col)
    if first is None:
        return
    row, col = first
    low, high, closed, quantity, unit = _bounds_of(names[col])
    short = lambda v: f"{v:g}".replace("e+", "e").replace("e0", "e")  # noqa: E731 - 1e6, not 1e+06
    ends = f"[{short(low)}, {short(high)}]" if closed else f"({short(low)}, {short(high)})"
    raise InputError(f"{quantity} {float(values[row, col])!r} {unit} is outside the physical "
                     f"range {ends} {unit}; a unit mix-up or a corrupted record?",
                     file=file, row=row + 1, column=names[col])


def _check_values(role: str, names: list[str], values: np.ndarray, meta: CampaignMeta, file):
    """Checks on parsed numbers shared by the reader and :meth:`Campaign.from_arrays`."""
    if values.shape[0] == 0:
        raise InputError("no data rows", file=file)
    bad = ~np.isfinite(values)
    if bad.any():
        index = int(np.argmax(bad.any(axis=1)))
        col = int(np.argmax(bad[index]))
        raise InputError(f"non-finite value {float(values[index, col])!r}; every cell must be "
                         "a finite number", file=file, row=index + 1, column=names[col])
    kept = set(_check_columns(role, names, meta, file))
    _check_bounds(names, kept, values, file)
    time_s = values[:, names.index(TIME_COLUMN)]
    step = np.diff(time_s)
    wrong = np.flatnonzero(step <= 0)
    if wrong.size:
        index = int(wrong[0]) + 1
        if step[index - 1] == 0:
            message = (f"duplicated time {float(time_s[index])!r} s (same as row {index}); "
                       "time_s must increase strictly")
        else:
            message = (f"time goes backwards: {float(time_s[index])!r} s after "
                       f"{float(time_s[index - 1])!r} s in row {index}; time_s must increase "
                       "strictly")
        raise InputError(message, file=file, row=index + 1, column=TIME_COLUMN)
    if role == FBG_FILE:
        gratings = [(s.name, s.column, s.lambda0_nm) for s in meta.sensors] + \
            [(f"{s.name} (reference grating, reference_lambda0_nm)", s.reference_column,
              s.reference_lambda0_nm) for s in meta.sensors if s.reference_column is not None]
        cols = [names.index(column) for _, column, _ in gratings]
        lambda0_nm = np.array([lam for _, _, lam in gratings])
        outside = np.abs(values[:, cols] - lambda0_nm) > WAVELENGTH_BAND_NM
        if outside.any():
            index = int(np.argmax(outside.any(axis=1)))
            j = int(np.argmax(outside[index]))
            value = float(values[index, cols[j]])
            raise InputError(
                f"wavelength {value!r} nm is outside the grating's plausible band "
                f"{lambda0_nm[j]:g} ± {WAVELENGTH_BAND_NM:g} nm (lambda0_nm of sensor "
                f"{gratings[j][0]}): a lost peak or a wrong channel mapping?",
                file=file, row=index + 1, column=gratings[j][1])


def _read_table(folder: Path, role: str, meta: CampaignMeta) -> pd.DataFrame:
    file = folder / role
    with _open_table(file) as handle:
        try:
            names, rest = _read_header(handle, file)
            order = _check_columns(role, names, meta, file)
            values = _parse_rows(file, names, _body_blocks(handle, rest))
        except OSError as exc:  # e.g. EIO, or a file that vanished while being read
            raise InputError(f"cannot read the file: {exc.strerror or type(exc).__name__}",
                             file=file) from None
    _check_values(role, names, values, meta, file)
    frame = pd.DataFrame(values, columns=names)
    ignored = [n for n in names if n not in order]
    frame = frame[order] if order != names else frame
    frame.attrs["ignored_columns"] = ignored
    return frame


def _table_from_input(role: str, table, meta: CampaignMeta, file) -> pd.DataFrame:
    """Validate an in-memory table (DataFrame or mapping of columns) like a file of ``role``."""
    try:
        frame = table if isinstance(table, pd.DataFrame) else pd.DataFrame(dict(table))
    except (TypeError, ValueError) as exc:
        raise InputError(f"cannot make a table of it: {exc}", file=file) from None
    names = [str(c) for c in frame.columns]
    seen: set[str] = set()
    for name in names:
        if name in seen:
            raise InputError("column name appears twice", file=file, column=name)
        seen.add(name)
    if len(names) > MAX_COLUMNS:
        raise InputError(f"the table has {len(names)} columns; a campaign table holds at most "
                         f"{MAX_COLUMNS}", file=file)
    order = _check_columns(role, names, meta, file)
    columns = []
    for name, column in zip(names, frame.columns):
        try:
            columns.append(np.asarray(frame[column].to_numpy(), dtype=np.float64))
        except (TypeError, ValueError) as exc:
            raise InputError(f"column is not numeric: {exc}", file=file, column=name) from None
    values = np.column_stack(columns) if columns else np.empty((len(frame), 0))
    _check_values(role, names, values, meta, file)
    return pd.DataFrame(values, columns=names)[order]


def _write_csv(frame: pd.DataFrame, file: Path) -> None:
    # Python's shortest round-trip repr for every float: wavelengths keep all their digits
    # (1530.1234567 stays 1530.1234567 and reads back bit-identical), times and forces stay short.
    with open(file, "w", encoding="utf-8", newline="") as handle:
        frame.to_csv(handle, index=False, lineterminator="\n")
        handle.flush()
        os.fsync(handle.fileno())


# --------------------------------------------------------------------------------------------
# Campaign
# --------------------------------------------------------------------------------------------

def _interp_columns(time_s: np.ndarray, source_time_s: np.ndarray, values: np.ndarray,
                    outside: float | None = None) -> np.ndarray:
    """Linear interpolation of every column of ``values`` onto ``time_s``."""
    out = np.empty((time_s.size, values.shape[1]))
    for j in range(values.shape[1]):
        out[:, j] = np.interp(time_s, source_time_s, values[:, j], left=outside, right=outside)
    return out


#: An instrument with at least this many samples per reference interval is averaged onto the
#: reference clock instead of being interpolated.
AVERAGE_MIN_SAMPLES = 3


def _local_linear_columns(time_s: np.ndarray, source_time_s: np.ndarray, values: np.ndarray,
                          half_width_s: float, chunk: int = 20_000) -> np.ndarray:
    """Value at each ``time_s`` of the least-squares line through the source samples within
    ``± half_width_s`` (an anti-aliasing filter: exact for linear signals, noise / sqrt(n)).

    Targets whose window holds fewer than two samples are interpolated linearly instead.
    """
    lo = np.searchsorted(source_time_s, time_s - half_width_s, side="left")
    hi = np.searchsorted(source_time_s, time_s + half_width_s, side="right")
    width = int(np.max(hi - lo)) if time_s.size else 0
    out = _interp_columns(time_s, source_time_s, values)
    if width < 2:
        return out
    offsets = np.arange(width)
    for a in range(0, time_s.size, chunk):
        b = min(a + chunk, time_s.size)
        idx = lo[a:b, None] + offsets[None, :]
        valid = idx < hi[a:b, None]
        idx = np.minimum(idx, source_time_s.size - 1)
        n = valid.sum(axis=1)
        ok = n >= 2
        dt = np.where(valid, source_time_s[idx] - time_s[a:b, None], 0.0)     # centred: exact
        mean_dt = dt.sum(axis=1) / np.maximum(n, 1)
        ddt = np.where(valid, dt - mean_dt[:, None], 0.0)
        sxx = (ddt ** 2).sum(axis=1)
        for j in range(values.shape[1]):
            v = np.where(valid, values[idx, j], 0.0)
            mean_v = v.sum(axis=1) / np.maximum(n, 1)
            slope = np.where(sxx > 0, (ddt * np.where(valid, v - mean_v[:, None], 0.0)).sum(axis=1)
                             / np.where(sxx > 0, sxx, 1.0), 0.0)
            out[a:b, j] = np.where(ok, mean_v - slope * mean_dt, out[a:b, j])
    return out


def _onto_reference(time_s, source_time_s, values, reference_dt_s, average: bool):
    """Bring one instrument onto the reference times: averaged when it samples much faster."""
    if average and source_time_s.size > 1 and time_s.size:
        source_dt = float(np.median(np.diff(source_time_s)))
        if reference_dt_s >= AVERAGE_MIN_SAMPLES * source_dt:
            return _local_linear_columns(time_s, source_time_s, values, reference_dt_s / 2)
    return _interp_columns(time_s, source_time_s, values)


def _zero_state(time_s: np.ndarray, values: np.ndarray, window_s: float) -> np.ndarray:
    """Mean of the samples with ``t <= t_first + window_s`` (at least the first one)."""
    n = max(1, int(np.searchsorted(time_s, time_s[0] + window_s, side="right")))
    return values[:n].mean(axis=0)


def _check_window(zero_window_s) -> float:
    try:
        window = float(zero_window_s)
    except (TypeError, ValueError):
        window = math.nan
    if not math.isfinite(window) or window < 0:
        raise InputError(f"zero window must be a finite number of seconds >= 0, got "
                         f"{zero_window_s!r}", column="zero_window_s")
    return window


@dataclass(eq=False)
class AlignedCampaign:
    """Every instrument on the reference instrument's clock, inside the common time range.

    Arrays have one row per kept reference sample. Wavelengths and temperatures are the measured
    values (their zero state is given separately); the reference displacement is already relative
    to its zero state, which is what a compensation model predicts.

    Attributes
    ----------
    time_s : (n,) reference times inside the overlap, s
    wavelength_nm : (n, n_sensors) Bragg wavelengths, columns in ``sensor_names`` order, nm
    wavelength_zero_nm : (n_sensors,) zero state, nm
    temperature_C : (n, n_probes) columns in ``probe_names`` order, degC
    temperature_zero_C : (n_probes,) zero state, degC
    reference_um : (n, 3) dx, dy, dz minus ``reference_zero_um``, um
    reference_zero_um : (3,) zero state of dx, dy, dz, um
    loads_N : (n, 3) fx, fy, fz or None; NaN where the sample lies outside loads.csv's time range
    dropped : dict with ``before`` and ``after`` (reference samples outside the overlap),
        ``overlap_s`` (t0, t1) and ``loads_outside`` (samples with NaN loads, None without loads)
    """

    name: str
    meta: CampaignMeta
    time_s: np.ndarray
    wavelength_nm: np.ndarray
    wavelength_zero_nm: np.ndarray
    temperature_C: np.ndarray
    temperature_zero_C: np.ndarray
    reference_um: np.ndarray
    reference_zero_um: np.ndarray
    loads_N: np.ndarray | None
    dropped: dict
    sensor_names: list[str]
    probe_names: list[str]
    zero_window_s: float = 10.0

    def __len__(self) -> int:
        return int(self.time_s.size)

    @property
    def delta_wavelength_nm(self) -> np.ndarray:
        """Wavelength shift from the zero state, (n, n_sensors), nm (Delta S before eq. 2-4)."""
        return self.wavelength_nm - self.wavelength_zero_nm

    @property
    def delta_temperature_C(self) -> np.ndarray:
        """Temperature change from the zero state, (n, n_probes), K."""
        return self.temperature_C - self.temperature_zero_C

    def __repr__(self) -> str:
        t0, t1 = self.dropped["overlap_s"]
        return (f"AlignedCampaign(name={self.name!r}, n={len(self)}, overlap_s=({t0:g}, {t1:g}), "
                f"sensors={self.sensor_names}, probes={self.probe_names})")


@dataclass(eq=False)
class Campaign:
    """A campaign folder in memory: metadata and one DataFrame per instrument, each on its own
    clock, validated and with canonical column order (see the module docstring)."""

    path: Path | None
    meta: CampaignMeta
    fbg: pd.DataFrame
    temperatures: pd.DataFrame
    reference: pd.DataFrame
    loads: pd.DataFrame | None = None

    # -- names -------------------------------------------------------------------------------
    @property
    def name(self) -> str:
        return self.meta.name

    @property
    def sensor_names(self) -> list[str]:
        return self.meta.sensor_names

    @property
    def probe_names(self) -> list[str]:
        """Declared probes, then temperature columns found in the data but not declared."""
        return self.meta.probe_names + self.undeclared_probes

    @property
    def undeclared_probes(self) -> list[str]:
        declared = {p.column for p in self.meta.temperature_probes}
        return [c[:-2] for c in self.temperatures.columns
                if c != TIME_COLUMN and c not in declared]

    def __repr__(self) -> str:
        loads = "none" if self.loads is None else f"{len(self.loads)} rows"
        return (f"Campaign(name={self.name!r}, kind={self.meta.kind!r}, path={self.path}, "
                f"fbg={len(self.fbg)} rows x {len(self.sensor_names)} sensors, "
                f"temperatures={len(self.temperatures)} rows x {len(self.probe_names)} probes, "
                f"reference={len(self.reference)} rows, loads={loads})")

    # -- construction ------------------------------------------------------------------------
    @classmethod
    def from_arrays(cls, meta: CampaignMeta | Mapping, *, fbg, temperatures, reference,
                    loads=None, path: str | Path | None = None) -> "Campaign":
        """Build a validated campaign from DataFrames or mappings ``{column: 1-D array}``.

        The same checks as :func:`read_campaign` apply (columns, finite numbers, strictly
        increasing ``time_s``, wavelengths within the grating band); errors name the file the
        table would be written to.
        """
        meta = _validate_meta(meta, META_FILE)
        return cls(
            path=None if path is None else Path(path),
            meta=meta,
            fbg=_table_from_input(FBG_FILE, fbg, meta, FBG_FILE),
            temperatures=_table_from_input(TEMPERATURES_FILE, temperatures, meta,
                                           TEMPERATURES_FILE),
            reference=_table_from_input(REFERENCE_FILE, reference, meta, REFERENCE_FILE),
            loads=None if loads is None else _table_from_input(LOADS_FILE, loads, meta, LOADS_FILE),
        )

    def validate(self) -> "Campaign":
        """Re-run every check on the in-memory tables (after editing them); returns a campaign
        with canonical column order."""
        return Campaign.from_arrays(self.meta, fbg=self.fbg, temperatures=self.temperatures,
                                    reference=self.reference, loads=self.loads, path=self.path)

    # -- alignment ---------------------------------------------------------------------------
    def _spans(self) -> dict[str, tuple[float, float]]:
        spans = {}
        for role, frame in ((FBG_FILE, self.fbg), (TEMPERATURES_FILE, self.temperatures),
                            (REFERENCE_FILE, self.reference)):
            t = frame[TIME_COLUMN].to_numpy()
            spans[role] = (float(t[0]), float(t[-1]))
        return spans

    def _where(self):
        return self.path if self.path is not None else self.name

    def aligned(self, zero_window_s: float = 10.0, average: bool = True) -> AlignedCampaign:
        """All instruments on the reference clock inside their common time range.

        The overlap is [latest first sample, earliest last sample] over fbg, temperatures and
        reference; reference samples outside it are dropped (and counted), the other signals are
        interpolated linearly, never extrapolated. With ``average`` (default), an instrument
        that samples at least three times per reference interval (e.g. a 10 Hz interrogator
        against a 1 Hz interferometer) is first averaged over that interval — a local
        least-squares line centred on each reference time, exact for linear signals — so its
        noise drops by the square root of the samples averaged instead of aliasing. Loads do not restrict the overlap: they are
        interpolated inside their own time range and NaN outside it. Zero states are the mean of
        the first ``zero_window_s`` seconds of each signal on its own clock.
        """
        window = _check_window(zero_window_s)
        spans = self._spans()
        t0 = max(span[0] for span in spans.values())
        t1 = min(span[1] for span in spans.values())
        if t0 > t1:
            ranges = "; ".join(f"{role} {a:g} to {b:g} s" for role, (a, b) in spans.items())
            raise InputError(f"the instruments' records do not overlap in time: {ranges}",
                             file=self._where())
        ref_t = self.reference[TIME_COLUMN].to_numpy()
        first = int(np.searchsorted(ref_t, t0, side="left"))
        stop = int(np.searchsorted(ref_t, t1, side="right"))
        if stop <= first:
            raise InputError(f"no reference sample falls inside the overlap {t0:g} to {t1:g} s "
                             "of fbg.csv, temperatures.csv and reference.csv",
                             file=self._where())
        time_s = ref_t[first:stop].copy()
        ref_dt = float(np.median(np.diff(ref_t))) if ref_t.size > 1 else 0.0

        fbg_t = self.fbg[TIME_COLUMN].to_numpy()
        fbg_v = self.fbg[[s.column for s in self.meta.sensors]].to_numpy(dtype=np.float64)
        # each thermometer on its own clock: probes on temperatures.csv's, reference gratings
        # on the interrogator's
        temperature_C = np.empty((time_s.size, len(self.probe_names)))
        temperature_zero_C = np.empty(len(self.probe_names))
        for names, (src_t, src_v) in self.thermometers().items():
            idx = [self.probe_names.index(p) for p in names]
            temperature_C[:, idx] = _onto_reference(time_s, src_t, src_v, ref_dt, average)
            temperature_zero_C[idx] = _zero_state(src_t, src_v, window)
        ref_v = self.reference[list(REFERENCE_COLUMNS)].to_numpy(dtype=np.float64)
        reference_zero_um = _zero_state(ref_t, ref_v, window)

        loads_N = None
        loads_outside = None
        if self.loads is not None:
            loads_t = self.loads[TIME_COLUMN].to_numpy()
            loads_v = self.loads[list(LOAD_COLUMNS)].to_numpy(dtype=np.float64)
            loads_N = _interp_columns(time_s, loads_t, loads_v, outside=np.nan)
            loads_outside = int(np.isnan(loads_N[:, 0]).sum())

        return AlignedCampaign(
            name=self.name,
            meta=self.meta,
            time_s=time_s,
            wavelength_nm=_onto_reference(time_s, fbg_t, fbg_v, ref_dt, average),
            wavelength_zero_nm=_zero_state(fbg_t, fbg_v, window),
            temperature_C=temperature_C,
            temperature_zero_C=temperature_zero_C,
            reference_um=ref_v[first:stop] - reference_zero_um,
            reference_zero_um=reference_zero_um,
            loads_N=loads_N,
            dropped={"before": first, "after": int(ref_t.size - stop), "overlap_s": (t0, t1),
                     "loads_outside": loads_outside},
            sensor_names=list(self.sensor_names),
            probe_names=list(self.probe_names),
            zero_window_s=window,
        )

    def thermometers(self) -> dict[tuple, tuple[np.ndarray, np.ndarray]]:
        """Every temperature reading on its own clock: ``{probe names: (time_s (n,), values
        (n, k) degC)}``. Probes come from temperatures.csv; a strain-free reference grating
        (``<sensor>_ref``) is read from fbg.csv as the temperature change of the sensor's gauge
        since the first sample (eq. 3 inverted, :func:`fbgcomp.optics.grating_temperature_change_K`)."""
        refs = set(self.meta.reference_probe_names)
        probes = tuple(p for p in self.probe_names if p not in refs)
        out = {probes: (self.temperatures[TIME_COLUMN].to_numpy(),
                        self.temperatures[[f"{p}_C" for p in probes]].to_numpy(dtype=np.float64))}
        with_ref = [s for s in self.meta.sensors if s.reference_column is not None]
        if with_ref:
            lam = self.fbg[[s.reference_column for s in with_ref]].to_numpy(dtype=np.float64)
            dT = optics.grating_temperature_change_K(
                lam, lam[0], thermo_optic_per_K=np.array([s.thermo_optic_per_K for s in with_ref]),
                fibre_cte_per_K=np.array([s.fibre_cte_per_K for s in with_ref]))
            out[tuple(s.reference_probe for s in with_ref)] = (self.fbg[TIME_COLUMN].to_numpy(), dT)
        return out

    # -- inspection --------------------------------------------------------------------------
    def _tables(self) -> dict[str, pd.DataFrame]:
        tables = {FBG_FILE: self.fbg, TEMPERATURES_FILE: self.temperatures,
                  REFERENCE_FILE: self.reference}
        if self.loads is not None:
            tables[LOADS_FILE] = self.loads
        return tables

    def summary(self) -> dict:
        """What ``fbgcomp inspect`` shows: per-file statistics, the alignment overlap and
        non-fatal problems. Only builtins (JSON-serialisable)."""
        problems: list[str] = []
        files = {}
        for role, frame in self._tables().items():
            t = frame[TIME_COLUMN].to_numpy()
            step = np.diff(t)
            median = float(np.median(step)) if step.size else None
            info = {
                "rows": int(t.size),
                "start_s": float(t[0]),
                "end_s": float(t[-1]),
                "duration_s": float(t[-1] - t[0]),
                "median_interval_s": median,
                "rate_hz": (1.0 / median) if median else None,
                "columns": {c: {"min": float(frame[c].min()), "max": float(frame[c].max())}
                            for c in frame.columns if c != TIME_COLUMN},
            }
            if median:
                gaps = np.flatnonzero(step > GAP_FACTOR * median)
                info["gaps"] = int(gaps.size)
                if gaps.size:
                    longest = int(gaps[np.argmax(step[gaps])])
                    problems.append(
                        f"{role}: {gaps.size} gap(s) longer than {GAP_FACTOR:g} x the median "
                        f"interval ({median:g} s); longest {step[longest]:g} s before row "
                        f"{longest + 2} (t = {t[longest + 1]:g} s)")
            else:
                info["gaps"] = 0
            files[role] = info

        spans = self._spans()
        t0 = max(span[0] for span in spans.values())
        t1 = min(span[1] for span in spans.values())
        ref_t = self.reference[TIME_COLUMN].to_numpy()
        if t0 <= t1:
            overlap = [t0, t1]
            before = int(np.searchsorted(ref_t, t0, side="left"))
            after = int(ref_t.size - np.searchsorted(ref_t, t1, side="right"))
            if before + after:
                problems.append(f"{before + after} reference sample(s) outside the overlap "
                                f"{t0:g} to {t1:g} s will be dropped ({before} before, "
                                f"{after} after)")
            if self.loads is not None:
                lt = self.loads[TIME_COLUMN].to_numpy()
                inside = ref_t[(ref_t >= t0) & (ref_t <= t1)]
                uncovered = int(((inside < lt[0]) | (inside > lt[-1])).sum())
                if uncovered:
                    problems.append(f"{LOADS_FILE} covers {lt[0]:g} to {lt[-1]:g} s only: "
                                    f"{uncovered} aligned sample(s) will have NaN loads")
        else:
            overlap, before, after = None, int(ref_t.size), 0
            problems.append("fbg.csv, temperatures.csv and reference.csv do not overlap in time")

        for probe in self.undeclared_probes:
            problems.append(f"{TEMPERATURES_FILE}: column {probe}_C is not declared in "
                            f"campaign.yaml temperature_probes (used as probe {probe!r})")
        for role, frame in self._tables().items():
            for column in frame.attrs.get("ignored_columns", []):
                problems.append(f"{role}: column {column!r} is not part of the format and was ignored")
        for i, sensor in enumerate(self.meta.sensors):
            for key in sensor.model_extra or {}:
                problems.append(f"{META_FILE}: sensors[{i}] has unrecognised key {key!r} "
                                "(kept; a typo?)")

        return {
            "name": self.name,
            "kind": self.meta.kind,
            "description": self.meta.description,
            "start": self.meta.start.isoformat(),
            "path": None if self.path is None else str(self.path),
            "files": files,
            "overlap_s": overlap,
            "reference_outside_overlap": {"before": before, "after": after},
            "sensors": [{"name": s.name, "lambda0_nm": s.lambda0_nm,
                         "temperature_probe": s.temperature_probe} for s in self.meta.sensors],
            "probes": self.probe_names,
            "undeclared_probes": self.undeclared_probes,
            "problems": problems,
        }

    def summary_text(self) -> str:
        """:meth:`summary` as a human-readable report."""
        s = self.summary()
        lines = [f"campaign {s['name']!r} ({s['kind']}), start {s['start']}"]
        if s["path"]:
            lines.append(f"  folder: {s['path']}")
        if s["description"]:
            lines.append(f"  {s['description']}")
        for role, info in s["files"].items():
            rate = (f"every {info['median_interval_s']:g} s ({info['rate_hz']:.4g} Hz)"
                    if info["median_interval_s"] else "single sample")
            lines.append(f"{role}: {info['rows']} rows, {info['start_s']:g} to {info['end_s']:g} s "
                         f"({info['duration_s']:g} s), {rate}")
            for column, mm in info["columns"].items():
                lines.append(f"    {column:<16} min {mm['min']:.12g}  max {mm['max']:.12g}")
        if s["overlap_s"] is None:
            lines.append("overlap: none")
        else:
            out = s["reference_outside_overlap"]
            lines.append(f"overlap: {s['overlap_s'][0]:g} to {s['overlap_s'][1]:g} s; reference "
                         f"samples outside: {out['before']} before, {out['after']} after")
        probes = {sensor["name"]: sensor["temperature_probe"] for sensor in s["sensors"]}
        lines.append("sensors: " + ", ".join(
            f"{name} (probe {probe})" if probe else f"{name} (uncompensated)"
            for name, probe in probes.items()))
        lines.append("probes: " + (", ".join(s["probes"]) or "none"))
        if s["problems"]:
            lines.append("problems:")
            lines.extend(f"  - {p}" for p in s["problems"])
        else:
            lines.append("problems: none")
        return "\n".join(lines)


# --------------------------------------------------------------------------------------------
# Folder I/O
# --------------------------------------------------------------------------------------------

def read_campaign(path: str | Path) -> Campaign:
    """Read and validate a campaign folder.

    Raises
    ------
    InputError
        For anything wrong with the folder, naming the file and, where it applies, the 1-based
        data row and the column (or the YAML field path).
    """
    folder = Path(path)
    if not folder.exists():
        raise InputError("campaign folder not found", file=folder)
    if not folder.is_dir():
        raise InputError("expected a campaign folder, found a file", file=folder)
    meta = _read_meta(folder)
    fbg = _read_table(folder, FBG_FILE, meta)
    temperatures = _read_table(folder, TEMPERATURES_FILE, meta)
    reference = _read_table(folder, REFERENCE_FILE, meta)
    loads = _read_table(folder, LOADS_FILE, meta) if (folder / LOADS_FILE).exists() else None
    return Campaign(path=folder, meta=meta, fbg=fbg, temperatures=temperatures,
                    reference=reference, loads=loads)


def write_campaign(campaign: Campaign, path: str | Path) -> Path:
    """Write a campaign folder atomically and return its path.

    Everything is written into a temporary sibling folder first; an existing campaign folder at
    ``path`` is replaced only once the new one is complete, and nothing temporary is left behind
    on failure. A folder that is not a campaign folder (no campaign.yaml) is never replaced.
    """
    target = Path(path)
    if target.exists() and not target.is_dir():
        raise InputError("cannot write a campaign folder: a file of that name exists", file=target)
    if target.is_dir() and any(target.iterdir()) and not (target / META_FILE).is_file():
        raise InputError("refusing to replace a folder that is not a campaign folder "
                         "(it has no campaign.yaml)", file=target)
    checked = campaign.validate()
    target.parent.mkdir(parents=True, exist_ok=True)
    token = uuid.uuid4().hex[:12]
    staging = target.parent / f".{target.name}.tmp-{token}"
    staging.mkdir()
    try:
        _write_csv(checked.fbg, staging / FBG_FILE)
        _write_csv(checked.temperatures, staging / TEMPERATURES_FILE)
        _write_csv(checked.reference, staging / REFERENCE_FILE)
        if checked.loads is not None:
            _write_csv(checked.loads, staging / LOADS_FILE)
        # Metadata last: a folder with campaign.yaml is a complete one.
        text = _meta_yaml(checked.meta, target / META_FILE)
        with open(staging / META_FILE, "w", encoding="utf-8", newline="\n") as handle:
            handle.write(text)
            handle.flush()
            os.fsync(handle.fileno())
        replace_dir(staging, target, target.parent / f".{target.name}.old-{token}")
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    return target
