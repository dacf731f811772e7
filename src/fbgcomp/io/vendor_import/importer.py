"""The import itself: every export of a mapping file into one campaign, on one clock from one
start, checked by the campaign's own rules and written atomically; an error the campaign checks
raise is pointed back at the export row and column (or the mapping field) it came from.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import numpy as np
import pandas as pd
import yaml

from fbgcomp.errors import InputError, read_bounded
from fbgcomp.io.campaign import META_FILE, TIME_COLUMN, Campaign, MetaLoader, write_campaign
from fbgcomp.io.vendor_import.mapping import (
    MAX_MAPPING_BYTES,
    ROLE_FILES,
    ROLE_SUFFIX,
    UNITS,
    ImportMapping,
    SourceSpec,
    read_mapping,
)
from fbgcomp.io.vendor_import.readers import RawExport, read_export, resolve_column
from fbgcomp.io.vendor_import.values import NS_PER_S, convert_units, origin_ns, parse_numbers, source_times

__all__ = ["describe", "import_campaign"]

_ROLE_OF_FILE = {v: k for k, v in ROLE_FILES.items()}


class _Table:
    """One campaign file built from one export, with what it takes to point back at it."""

    def __init__(
        self,
        source: SourceSpec,
        raw: RawExport,
        time_ns: np.ndarray,
        absolute: bool,
        values: dict[str, np.ndarray],
        column_of: dict[str, int],
        time_column: int,
    ):
        self.source, self.raw, self.time_ns, self.absolute = source, raw, time_ns, absolute
        self.values, self.column_of, self.time_column = values, column_of, time_column


def _build_table(source: SourceSpec, base: Path, zone_name: str | None) -> _Table:
    path = Path(source.file)
    path = path if path.is_absolute() else base / path
    time_refs = source.time.column if isinstance(source.time.column, list) else [source.time.column]
    wanted = [(ref, "time") for ref in time_refs] + [
        (spec.column, target) for target, spec in source.columns.items()
    ]
    raw = read_export(path, source.format, wanted)
    if raw.lines.size == 0:
        raise InputError("no data rows below the column header", file=raw.label)
    locate = lambda ref, what: resolve_column(ref, raw.names, raw.label, what, raw.label)  # noqa: E731
    time_columns = [locate(ref, "time") for ref in time_refs]
    column_of = {target: locate(spec.column, target) for target, spec in source.columns.items()}

    suffix = ROLE_SUFFIX[source.role]
    values, empties = {}, []
    for target, spec in source.columns.items():
        v, empty = parse_numbers(
            raw, column_of[target], source.format, f"a number ({spec.unit or suffix[1:]})"
        )
        values[target] = convert_units(v, spec.unit or _default_unit(suffix), suffix)
        empties.append(empty)
    empty_row = np.logical_or.reduce(empties)
    if empty_row.any():
        if source.format.on_empty == "error":
            row = int(np.flatnonzero(empty_row)[0])
            target = next(t for t, e in zip(source.columns, empties) if e[row])
            raise raw.error(
                "empty cell (a lost peak or a logger gap?); every mapped cell must "
                "hold a number, or set format.on_empty: drop_row",
                row,
                column_of[target],
            )
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
        raise raw.error(
            f"time {kind} the previous row's (data row {row}); times must increase "
            "strictly (a daylight-saving change in local time? export with a UTC "
            "offset, or give the zone in time.timezone)",
            row,
            time_columns[0],
        )
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
            data = yaml.load(raw.decode("utf-8-sig"), Loader=MetaLoader)
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
    tables: dict[str, _Table] = {
        s.role: _build_table(s, mapping_file.parent, mapping.timezone) for s in mapping.sources
    }

    relative = [t for t in tables.values() if not t.absolute]
    if relative and len(relative) != len(tables):
        t = relative[0]
        raise InputError(
            f"the {t.source.role} export's times are elapsed without an origin while "
            "other exports carry dates: give time.origin or "
            "time.origin_from_header",
            file=t.raw.label,
        )
    if mapping.start is not None:
        start_ns = origin_ns(mapping.start, None, mapping.timezone, mapping_file, "start")
    elif relative:
        raise InputError(
            "every export's time is elapsed without an origin: give 'start' (the "
            "date and time of elapsed 0, with a zone)",
            file=mapping_file,
            column="field start",
        )
    else:
        start_ns = min(int(t.time_ns[0]) for t in tables.values())
    offset_ns = start_ns if not relative else 0

    frames = {}
    for role, t in tables.items():
        columns = {TIME_COLUMN: (t.time_ns - offset_ns) / NS_PER_S}
        columns.update(t.values)
        frames[role] = pd.DataFrame(columns)
    meta = {**meta, "start": pd.Timestamp(start_ns, tz="UTC").isoformat()}
    try:
        campaign = Campaign.from_arrays(
            meta,
            fbg=frames["fbg"],
            temperatures=frames["temperatures"],
            reference=frames["reference"],
            loads=frames.get("loads"),
        )
    except InputError as exc:
        raise _point_back(exc, tables, meta_file, prefix) from None
    write_campaign(campaign, output)
    return campaign


def _point_back(exc: InputError, tables: dict[str, _Table], meta_file: Path, prefix: str) -> InputError:
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
    index = table.time_column if exc.column == TIME_COLUMN else table.column_of.get(exc.column or "")
    message = exc.message if exc.column is None else f"{exc.message} [campaign column {exc.column}]"
    if exc.row is None:
        return InputError(
            message, file=table.raw.label, column=None if index is None else table.raw.column_label(index)
        )
    return table.raw.error(message, exc.row - 1, index)


def describe(campaign: Campaign, mapping: str | Path, output: str | Path) -> str:
    """What an import wrote, for the console."""
    lines = [
        f"campaign {campaign.name!r} ({campaign.meta.kind}) written to {output}, "
        f"start {campaign.meta.start.isoformat()}"
    ]
    for role, frame in (
        ("fbg.csv", campaign.fbg),
        ("temperatures.csv", campaign.temperatures),
        ("reference.csv", campaign.reference),
        ("loads.csv", campaign.loads),
    ):
        if frame is None:
            continue
        t = frame[TIME_COLUMN].to_numpy()
        cols = ", ".join(c for c in frame.columns if c != TIME_COLUMN)
        lines.append(f"  {role:<17} {len(frame):>8} rows  {t[0]:>10.3f} to {t[-1]:>10.3f} s  {cols}")
    return "\n".join(lines)
