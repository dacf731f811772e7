"""Cells of an export into numbers and times: decimal marks and digit groups, timestamps in
any zone or elapsed from an origin (onto int64 ns since 1970 UTC), and units onto the campaign's
(nm, degC, um, N).
"""

from __future__ import annotations

import datetime as dt
import re

import numpy as np
import pandas as pd

from fbgcomp.errors import InputError
from fbgcomp.io.vendor_import.mapping import UNITS, FormatSpec, HeaderField, TimeSpec, parse_zone
from fbgcomp.io.vendor_import.readers import RawExport, is_empty, text_cells

__all__ = ["NS_PER_S", "convert_units", "origin_ns", "parse_numbers", "quote_cell", "source_times"]

_TIME_UNITS_S = {"s": 1.0, "ms": 1e-3, "us": 1e-6, "min": 60.0, "h": 3600.0, "d": 86400.0}

_NUMBER_RE = r"[+-]?(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][+-]?[0-9]+)?"
_AWARE_RE = r"(?:Z|[+-][0-9]{2}:?[0-9]{2})\s*$"
#: Nanoseconds per second: times are carried as int64 ns.
NS_PER_S = 1_000_000_000


def parse_numbers(raw: RawExport, column: int, fmt: FormatSpec, what: str) -> tuple[np.ndarray, np.ndarray]:
    """Floats of a column and its empty-cell mask; InputError at the first bad cell."""
    cells = raw.cells[column]
    values = np.full(cells.size, np.nan)
    if raw.text:
        s = text_cells(cells)
        empty = (s == "").to_numpy(dtype=bool)
        numeric = np.zeros(cells.size, dtype=bool)
    else:
        s = None
        empty = is_empty(cells)
        numeric = np.array(
            [
                isinstance(c, (int, float, np.integer, np.floating)) and not isinstance(c, (bool, np.bool_))
                for c in cells
            ],
            dtype=bool,
        )
        numeric &= ~empty
    if numeric.any():
        values[numeric] = np.asarray(cells[numeric], dtype=np.float64)
    text = ~numeric & ~empty
    if text.any():
        s = (
            s[text].reset_index(drop=True)
            if s is not None
            else pd.Series([str(c) for c in cells[text]], dtype=object).str.strip()
        )
        if fmt.thousands:
            s = s.str.replace(fmt.thousands, "", regex=False)
        if fmt.decimal == ",":
            if s.str.contains(".", regex=False).any():
                bad = np.flatnonzero(np.asarray(s.str.contains(".", regex=False)))[0]
                row = np.flatnonzero(text)[bad]
                raise raw.error(
                    f"{quote_cell(cells[row])} holds '.' where the decimal mark is ',' "
                    "(format.decimal / format.thousands)",
                    row,
                    column,
                )
            s = s.str.replace(",", ".", regex=False)
        ok = np.asarray(s.str.fullmatch(_NUMBER_RE), dtype=bool)
        if not ok.all():
            row = np.flatnonzero(text)[np.flatnonzero(~ok)[0]]
            hint = (
                " (decimal comma? set format.decimal: ',')"
                if fmt.decimal == "." and re.fullmatch(r"\s*[+-]?[0-9]+,[0-9]+\s*", str(cells[row]))
                else ""
            )
            raise raw.error(f"not a number: {quote_cell(cells[row])}; expected {what}{hint}", row, column)
        values[text] = s.astype("float64").to_numpy(dtype=np.float64)
    bad = ~np.isfinite(values) & ~empty
    if bad.any():
        row = int(np.flatnonzero(bad)[0])
        raise raw.error(f"non-finite value {quote_cell(cells[row])}", row, column)
    return values, empty


def quote_cell(cell) -> str:
    """A cell quoted for an error message, cut to 40 characters."""
    text = repr(cell if isinstance(cell, str) else str(cell))
    return text if len(text) <= 40 else text[:37] + "..."


def _localize(raw: RawExport, column: int, parsed: pd.Series, zone: dt.tzinfo, zone_name: str):
    """Naive local times -> UTC; a time the clocks skipped, or a repeated hour the order cannot
    place, is an error at its row."""
    try:
        return parsed.dt.tz_localize(zone, ambiguous="infer", nonexistent="raise")
    except Exception:
        pass
    for row, stamp in enumerate(parsed):
        if pd.isna(stamp):
            continue
        try:
            pd.Timestamp(stamp).tz_localize(zone, ambiguous="raise", nonexistent="raise")
        except Exception as exc:
            if "nonexistent" in f"{type(exc).__name__} {exc}".lower():
                problem = "does not exist (the clocks skipped it: daylight-saving change)"
            else:
                problem = (
                    "is ambiguous (the clocks went back: it occurs twice) and the order of "
                    "the rows cannot tell which; export with a UTC offset"
                )
            raise raw.error(f"local time {stamp} in {zone_name} {problem}", row, column) from None
    raise raw.error(f"cannot place the local times in {zone_name}", None, column)


def _parse_datetimes(
    raw: RawExport, column: int, cells: np.ndarray, spec: TimeSpec, zone_name: str | None
) -> np.ndarray:
    """Timestamps -> int64 ns since 1970 UTC."""
    if raw.text:
        is_stamp = np.zeros(cells.size, dtype=bool)
        text = text_cells(cells)
    else:
        is_stamp = np.array([isinstance(c, (dt.datetime, pd.Timestamp)) for c in cells], dtype=bool)
        text = pd.Series(
            [
                "" if c is None else (c.isoformat(sep=" ") if isinstance(c, dt.datetime) else str(c)).strip()
                for c in cells
            ],
            dtype=object,
        )
    aware = np.asarray(text.str.contains(_AWARE_RE, regex=True), dtype=bool) & ~is_stamp
    if aware.any() and not aware.all():
        row = int(np.flatnonzero(aware != aware[0])[0])
        raise raw.error(
            f"timestamp {quote_cell(cells[row])} {'has' if aware[row] else 'lacks'} a UTC "
            "offset where the first row's does not; mixed zones",
            row,
            column,
        )
    fmt = spec.format or "ISO8601"
    parsed = pd.to_datetime(text, format=fmt, errors="coerce", utc=bool(aware.all()))
    if parsed.isna().any():
        row = int(np.flatnonzero(parsed.isna().to_numpy())[0])
        expected = f"the format {spec.format!r}" if spec.format else "ISO 8601 (2026-03-02 08:00:00)"
        raise raw.error(
            f"not a date and time: {quote_cell(cells[row])}; expected {expected} (time.format)", row, column
        )
    if not aware.all():
        if zone_name is None:
            raise raw.error(
                "timestamps have no UTC offset and no time zone is given: set "
                "'timezone' in the mapping (or time.timezone)",
                None,
                column,
            )
        parsed = _localize(raw, column, parsed, parse_zone(zone_name), zone_name)
    return parsed.dt.tz_convert("UTC").dt.as_unit("ns").astype("int64").to_numpy()


def _header_origin(raw: RawExport, field: HeaderField, zone_name: str | None) -> int:
    for cells in raw.preamble:
        if cells and cells[0].strip().strip('"') == field.label:
            if len(cells) < 2 or not cells[1].strip():
                raise InputError(f"header line {field.label!r} holds no date and time", file=raw.label)
            return origin_ns(cells[1].strip(), field.format, zone_name, raw.label, f"header {field.label!r}")
    raise InputError(
        f"no header line {field.label!r} above the column names (time.origin_from_header)", file=raw.label
    )


def origin_ns(text: str, fmt: str | None, zone_name: str | None, file, where: str) -> int:
    """One date and time (``fmt``: strptime format, default ISO 8601; naive times in
    ``zone_name``) as int64 ns since 1970 UTC; InputError naming ``file`` and ``where``."""
    try:
        stamp = pd.Timestamp(dt.datetime.strptime(text, fmt)) if fmt else pd.Timestamp(text)
    except (ValueError, TypeError):
        expected = f"the format {fmt!r}" if fmt else "ISO 8601"
        raise InputError(f"{where}: not a date and time: {text!r}; expected {expected}", file=file) from None
    if stamp.tzinfo is None:
        if zone_name is None:
            raise InputError(
                f"{where}: {text!r} has no UTC offset and no time zone is given "
                "(set 'timezone' in the mapping)",
                file=file,
            )
        try:
            stamp = stamp.tz_localize(parse_zone(zone_name), ambiguous="raise", nonexistent="raise")
        except Exception:
            raise InputError(
                f"{where}: local time {text!r} does not exist or is ambiguous in "
                f"{zone_name} (daylight-saving change); give a UTC offset",
                file=file,
            ) from None
    return int(stamp.tz_convert("UTC").as_unit("ns").value)


def source_times(
    raw: RawExport, spec: TimeSpec, fmt: FormatSpec, zone_name: str | None, time_columns: list[int]
) -> tuple[np.ndarray, bool]:
    """Sample times as int64 ns: since 1970 UTC (absolute) or since the export's own zero
    (``elapsed`` without an origin; then the second value is False)."""
    column = time_columns[0]
    if spec.kind == "elapsed":
        values, empty = parse_numbers(raw, column, fmt, f"a time in {spec.unit}")
        if empty.any():
            raise raw.error("empty time cell", int(np.flatnonzero(empty)[0]), column)
        ns = np.rint(values * (_TIME_UNITS_S[spec.unit] * NS_PER_S)).astype(np.int64)
        if spec.origin is not None:
            return ns + origin_ns(spec.origin, None, zone_name, raw.label, "time.origin"), True
        if spec.origin_from_header is not None:
            return ns + _header_origin(raw, spec.origin_from_header, zone_name), True
        return ns, False
    parts = [raw.cells[c] for c in time_columns]
    if len(parts) == 1:
        cells = parts[0]
    elif raw.text:
        joined = text_cells(parts[0])
        for part in parts[1:]:
            joined = joined.str.cat(text_cells(part), sep=" ")
        cells = joined.to_numpy(dtype=object)
    else:
        cells = np.array(
            [
                " ".join(
                    ""
                    if p is None
                    else (
                        p.strftime("%Y-%m-%d")
                        if isinstance(p, dt.datetime) and i == 0
                        else p.strftime("%H:%M:%S.%f")
                        if isinstance(p, dt.datetime)
                        else p.isoformat()
                        if isinstance(p, dt.time)
                        else str(p)
                    ).strip()
                    for i, p in enumerate(row)
                )
                for row in zip(*parts)
            ],
            dtype=object,
        )
    empty = is_empty(cells, raw.text)
    if empty.any():
        raise raw.error("empty time cell", int(np.flatnonzero(empty)[0]), column)
    return _parse_datetimes(raw, column, cells, spec, zone_name), True


def convert_units(values: np.ndarray, unit: str, suffix: str) -> np.ndarray:
    """``values`` in ``unit`` onto the campaign unit of columns ending in ``suffix``
    (``_nm``, ``_C``, ``_um``, ``_N``)."""
    scale, offset = UNITS[suffix][unit]
    return values * scale + offset
