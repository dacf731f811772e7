"""The campaign CSV tables (fbg, temperatures, reference, loads, heat): streamed, bounded reading, and
the checks every table passes, read from a file or given in memory.

Errors are :class:`fbgcomp.errors.InputError` naming the file, the 1-based data row and the column.
"""

from __future__ import annotations

import codecs
import csv
import difflib
import io
import math
import os
import re
from pathlib import Path

import numpy as np
import pandas as pd

from fbgcomp.errors import InputError
from fbgcomp.io.campaign.layout import (
    FBG_FILE,
    HEAT_FILE,
    HEAT_SUFFIX,
    LOAD_COLUMNS,
    REFERENCE_COLUMNS,
    REFERENCE_FILE,
    TEMPERATURES_FILE,
    TIME_COLUMN,
)
from fbgcomp.io.campaign.meta import CampaignMeta, short_repr

__all__ = [
    "MAX_CELL_BYTES",
    "MAX_COLUMNS",
    "MAX_HEADER_BYTES",
    "VALUE_BOUNDS",
    "WAVELENGTH_BAND_NM",
    "read_table",
    "table_from_input",
    "write_csv",
]

#: A peak further than this from the grating's nominal lambda0_nm is a lost peak, a peak picked
#: from the neighbouring grating or a wrong channel mapping: no structure strains an FBG by ~0.4 %.
WAVELENGTH_BAND_NM = 5.0

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
#: (-1e7, 1e7) N, a power inside (-1e7, 1e7) W and a time inside (-1e10, 1e10) s (about 317 years).
VALUE_BOUNDS = {
    TIME_COLUMN: (-1e10, 1e10, False, "time", "s"),
    "_nm": (0.0, 1e4, False, "wavelength", "nm"),
    "_C": (-273.15, 1000.0, True, "temperature", "degC"),
    "_um": (-1e6, 1e6, False, "displacement", "um"),
    "_N": (-1e7, 1e7, False, "force", "N"),
    HEAT_SUFFIX: (-1e7, 1e7, False, "power", "W"),
}


def _role_columns(role: str, meta: CampaignMeta) -> tuple[list[str], str]:
    """Required columns of a file and a description of what it holds (for messages)."""
    if role == FBG_FILE:
        refs = [s.reference_column for s in meta.sensors if s.reference_column is not None]
        return (
            [TIME_COLUMN] + [s.column for s in meta.sensors] + refs,
            "time_s, <sensor>_nm and, for sensors with reference_lambda0_nm, <sensor>_ref_nm columns",
        )
    if role == TEMPERATURES_FILE:
        return ([TIME_COLUMN] + [p.column for p in meta.temperature_probes], "time_s and <probe>_C columns")
    if role == REFERENCE_FILE:
        return [TIME_COLUMN, *REFERENCE_COLUMNS], "time_s, dx_um, dy_um, dz_um"
    if role == HEAT_FILE:
        return [TIME_COLUMN], "time_s and one <heat source>_W column per measured heat input"
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
            raise InputError(
                f"missing column {column!r}; {role} must hold {holds} (the header "
                f"has {len(names)} column{'s' if len(names) != 1 else ''}{hint})",
                file=file,
                column=column,
            )
    wanted = set(required)
    extra = [(position, n) for position, n in enumerate(names, start=1) if n not in wanted]
    for position, column in extra:
        if role == FBG_FILE and column.endswith("_ref_nm") and column[:-7] in meta.sensor_names:
            raise InputError(
                f"column {column} holds a reference grating for sensor {column[:-7]}, which "
                f"declares none: give it reference_lambda0_nm in campaign.yaml",
                file=file,
                column=column,
            )
        if role == FBG_FILE and column.endswith("_nm"):
            label = _column_label(column, position)
            sensor = f"{column[:-3]!r}" if label == column else "of that name"
            raise InputError(
                f"unknown sensor {sensor}: column {label} has no entry in campaign.yaml "
                f"sensors (declared: {', '.join(meta.sensor_names)})",
                file=file,
                column=label,
            )
    if role == HEAT_FILE and not any(_is_heat_column(n) for _, n in extra):
        raise InputError(
            f"no heat input column; {role} must hold {holds} (e.g. spindle_heat_W)",
            file=file,
        )
    # Any other extra column (a status flag, a second interferometer axis, ...) is read, checked
    # like the rest, and left out of the campaign; summary() reports it. The format names the
    # columns a file must hold, not the only ones it may hold. Undeclared <probe>_C columns are
    # kept as probes (and reported by summary()).
    if role == HEAT_FILE:
        return required + [n for _, n in extra if _is_heat_column(n)]
    return required + [n for _, n in extra if role == TEMPERATURES_FILE and n.endswith("_C") and len(n) > 2]


def _is_heat_column(name: str) -> bool:
    return name.endswith(HEAT_SUFFIX) and len(name) > len(HEAT_SUFFIX) and name.isprintable()


def _cell_problem(text: str) -> str | None:
    """Why a CSV cell is not a finite number, or None when it is one (quotes the cell cut to
    32 characters)."""
    cell = text.strip()
    if cell == "":
        return "empty cell; every cell must hold a number"
    if _NUMBER_RE.fullmatch(cell):
        if math.isfinite(float(cell)):
            return None
        return f"value {short_repr(cell, 32)} overflows to infinity"
    if _NON_FINITE_RE.fullmatch(cell):
        return f"non-finite value {short_repr(cell, 32)}; every cell must be a finite number"
    return f"not a number: {short_repr(cell, 32)}; expected a decimal number such as 1530.125"


def _locate_bad_cell(file, names: list[str], body: bytes, first_row: int = 1) -> None:
    """Slow path, run only after the fast parser failed on one block of rows: raise the first
    bad cell's InputError (``first_row``: the data row number of the block's first line).

    A text read of the block and pandas' vectorised number conversion nominate suspect cells;
    each is confirmed by :func:`_cell_problem` in file order. Only when that finds nothing (or
    the text read itself fails) is every line scanned in Python.
    """
    try:
        text = pd.read_csv(
            io.BytesIO(body + b"\n"),
            header=None,
            names=names,
            index_col=False,
            dtype=str,
            sep=",",
            engine="c",
            quoting=csv.QUOTE_NONE,
            na_filter=False,
            skip_blank_lines=False,
            encoding="utf-8",
        )
    except Exception:
        text = None
    if text is not None and text.shape[1] == len(names):
        suspects: list[tuple[int, int]] = []
        for col, name in enumerate(names):
            numbers = pd.to_numeric(text[name], errors="coerce").to_numpy(dtype=np.float64)
            suspects.extend((int(row), col) for row in np.flatnonzero(~np.isfinite(numbers)))
        for row, col in sorted(suspects):
            problem = _cell_problem(str(text.iat[row, col]))  # read as text (dtype=str)
            if problem:
                raise InputError(problem, file=file, row=first_row + row, column=names[col])
    for index, line in enumerate(body.split(b"\n")):
        row = first_row + index
        try:
            decoded = line.decode("utf-8")
        except UnicodeDecodeError as exc:
            col = line[: exc.start].count(b",")
            raise InputError(
                f"not UTF-8 text: byte 0x{line[exc.start]:02x}",
                file=file,
                row=row,
                column=names[col] if col < len(names) else None,
            ) from None
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
        raise InputError(f"cannot open the file: {exc.strerror or type(exc).__name__}", file=file) from None


def _read_header(handle, file) -> tuple[list[str], bytes]:
    """Column names, and the bytes read beyond them (the header's line end and what follows).

    Reads at most :data:`MAX_HEADER_BYTES` + 1 bytes, counts the columns before decoding them and
    checks for duplicates with a set: linear in the header's length whatever it holds.
    """
    head = handle.readline(MAX_HEADER_BYTES + 1)
    if not head:
        raise InputError(
            "empty file (0 bytes); expected a header row such as 'time_s,...' followed by data rows",
            file=file,
        )
    cut = _LINE_END_RE.search(head)
    if cut is None and len(head) > MAX_HEADER_BYTES:
        raise InputError(
            f"the header (line 1) is longer than {MAX_HEADER_BYTES} bytes; a "
            f"campaign CSV holds at most {MAX_COLUMNS} columns",
            file=file,
        )
    line, rest = (head, b"") if cut is None else (head[: cut.start()], head[cut.start() :])
    if line.startswith(codecs.BOM_UTF8):
        line = line[len(codecs.BOM_UTF8) :]
    n_columns = line.count(b",") + 1
    if n_columns > MAX_COLUMNS:
        raise InputError(
            f"the header has {n_columns} columns; a campaign CSV holds at most {MAX_COLUMNS}", file=file
        )
    try:
        header = line.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise InputError(
            f"header (line 1) is not UTF-8 text: byte 0x{line[exc.start]:02x}", file=file
        ) from None
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
            raise InputError(
                f"column name appears twice in the header (columns {first[name]} and {position})",
                file=file,
                column=_column_label(name, position),
            )
        first[name] = position
        names.append(name)
    return names, rest


def _body_blocks(handle, rest: bytes):
    """The data rows' bytes, in blocks of about :data:`_CHUNK_BYTES`, with CR LF and lone CR
    line ends turned into LF. ``rest`` is what the header read took beyond the header line:
    empty (the file ends there) or starting with the header's own line end, which is dropped."""
    pending_cr = False  # the previous block ended with CR: an LF opening this one belongs to it
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
    rows = 0  # data rows parsed so far
    blank = 0  # blank lines after them, not yet known to be the file's trailing ones
    carry = b""  # a line whose end has not been read yet

    def take(lines: bytes) -> None:
        nonlocal rows, blank
        end = len(lines.rstrip(b" \t\n"))
        if end == 0:
            blank += lines.count(b"\n") + 1
            return
        if blank:
            raise InputError(
                f"empty row (blank line); expected {n_cols} comma-separated values", file=file, row=rows + 1
            )
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
            carry = buffer[last + 1 :]
            take(buffer[:last])
        else:
            carry = buffer
        if len(carry) > longest:
            raise InputError(
                f"row is longer than {longest} bytes; expected {n_cols} comma-separated numbers",
                file=file,
                row=rows + blank + 1,
            )
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
    separators = np.bincount(np.searchsorted(line_ends, np.flatnonzero(buffer == ord(","))), minlength=n_rows)
    wrong = np.flatnonzero(separators != n_cols - 1)
    if wrong.size:
        index = int(wrong[0])
        start = 0 if index == 0 else int(line_ends[index - 1]) + 1
        stop = int(line_ends[index]) if index < line_ends.size else len(body)
        line = body[start:stop].decode("utf-8", errors="replace")
        found = int(separators[index]) + 1
        if not line.strip():
            raise InputError(
                f"empty row (blank line); expected {n_cols} comma-separated values",
                file=file,
                row=first_row + index,
            )
        if found == 1:
            for delimiter, label in _DELIMITERS:
                if delimiter in line:
                    raise InputError(
                        f"expected comma-separated columns, found {label}", file=file, row=first_row + index
                    )
        raise InputError(
            f"row has {found} values, expected {n_cols} ({_columns_text(names)})",
            file=file,
            row=first_row + index,
            column=names[found] if found < n_cols else None,
        )
    try:
        frame = pd.read_csv(
            io.BytesIO(body + b"\n"),
            header=None,
            names=names,
            index_col=False,
            dtype=np.float64,
            sep=",",
            engine="c",
            quoting=csv.QUOTE_NONE,
            na_filter=False,
            skip_blank_lines=False,
            encoding="utf-8",
        )
        values = frame.to_numpy(dtype=np.float64)
        if values.shape != (n_rows, n_cols):
            raise ValueError(f"parsed {values.shape}, expected {(n_rows, n_cols)}")
    except Exception as exc:
        _locate_bad_cell(file, names, body, first_row)
        raise InputError(f"cannot read the numbers: {type(exc).__name__}", file=file) from None
    bad = ~np.isfinite(values)
    if bad.any():
        index = int(np.argmax(bad.any(axis=1)))
        col = int(np.argmax(bad[index]))
        start = 0 if index == 0 else int(line_ends[index - 1]) + 1
        stop = int(line_ends[index]) if index < line_ends.size else len(body)
        cell = body[start:stop].decode("utf-8", errors="replace").split(",")[col]
        raise InputError(
            _cell_problem(cell) or f"non-finite value {short_repr(cell, 32)}",
            file=file,
            row=first_row + index,
            column=names[col],
        )
    return values


def _bounds_of(column: str):
    if column == TIME_COLUMN:
        return VALUE_BOUNDS[TIME_COLUMN]
    for suffix in ("_nm", "_C", "_um", "_N", HEAT_SUFFIX):
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
    raise InputError(
        f"{quantity} {float(values[row, col])!r} {unit} is outside the physical "
        f"range {ends} {unit}; a unit mix-up or a corrupted record?",
        file=file,
        row=row + 1,
        column=names[col],
    )


def _check_values(role: str, names: list[str], values: np.ndarray, meta: CampaignMeta, file):
    """Checks on parsed numbers shared by the reader and :meth:`Campaign.from_arrays`."""
    if values.shape[0] == 0:
        raise InputError("no data rows", file=file)
    bad = ~np.isfinite(values)
    if bad.any():
        index = int(np.argmax(bad.any(axis=1)))
        col = int(np.argmax(bad[index]))
        raise InputError(
            f"non-finite value {float(values[index, col])!r}; every cell must be a finite number",
            file=file,
            row=index + 1,
            column=names[col],
        )
    kept = set(_check_columns(role, names, meta, file))
    _check_bounds(names, kept, values, file)
    time_s = values[:, names.index(TIME_COLUMN)]
    step = np.diff(time_s)
    wrong = np.flatnonzero(step <= 0)
    if wrong.size:
        index = int(wrong[0]) + 1
        if step[index - 1] == 0:
            message = (
                f"duplicated time {float(time_s[index])!r} s (same as row {index}); "
                "time_s must increase strictly"
            )
        else:
            message = (
                f"time goes backwards: {float(time_s[index])!r} s after "
                f"{float(time_s[index - 1])!r} s in row {index}; time_s must increase "
                "strictly"
            )
        raise InputError(message, file=file, row=index + 1, column=TIME_COLUMN)
    if role == FBG_FILE:
        gratings = [(s.name, s.column, s.lambda0_nm) for s in meta.sensors] + [
            (
                f"{s.name} (reference grating, reference_lambda0_nm)",
                s.reference_column,
                s.reference_lambda0_nm,
            )
            for s in meta.sensors
            if s.reference_column is not None
        ]
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
                file=file,
                row=index + 1,
                column=gratings[j][1],
            )


def read_table(folder: Path, role: str, meta: CampaignMeta) -> pd.DataFrame:
    """Read and check the table ``folder/role`` (one of the campaign CSV files) against ``meta``:
    columns in canonical order, extra columns listed in ``frame.attrs["ignored_columns"]``."""
    file = folder / role
    with _open_table(file) as handle:
        try:
            names, rest = _read_header(handle, file)
            order = _check_columns(role, names, meta, file)
            values = _parse_rows(file, names, _body_blocks(handle, rest))
        except OSError as exc:  # e.g. EIO, or a file that vanished while being read
            raise InputError(
                f"cannot read the file: {exc.strerror or type(exc).__name__}", file=file
            ) from None
    _check_values(role, names, values, meta, file)
    frame = pd.DataFrame(values, columns=names)
    ignored = [n for n in names if n not in order]
    frame = frame[order] if order != names else frame
    frame.attrs["ignored_columns"] = ignored
    return frame


def table_from_input(role: str, table, meta: CampaignMeta, file) -> pd.DataFrame:
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
        raise InputError(
            f"the table has {len(names)} columns; a campaign table holds at most {MAX_COLUMNS}", file=file
        )
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


def write_csv(frame: pd.DataFrame, file: Path) -> None:
    """Write ``frame`` as a campaign CSV and fsync it (into a staging folder: not atomic itself).

    Python's shortest round-trip repr for every float: wavelengths keep all their digits
    (1530.1234567 stays 1530.1234567 and reads back bit-identical), times and forces stay short.
    """
    with open(file, "w", encoding="utf-8", newline="") as handle:
        frame.to_csv(handle, index=False, lineterminator="\n")
        handle.flush()
        os.fsync(handle.fileno())
