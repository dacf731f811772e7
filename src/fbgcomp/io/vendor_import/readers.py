"""Reading an export of ``fbgcomp import``: delimited text (CSV, TSV, any delimiter) or an .xlsx
sheet, down to the cells of the mapped columns and the file line of every data row.

Errors are :class:`ExportError` naming the export file, the data row and its file line (or
spreadsheet row), and the export's column.
"""

from __future__ import annotations

import csv
import difflib
import re
from pathlib import Path

import numpy as np
import pandas as pd

from fbgcomp.errors import InputError
from fbgcomp.io.vendor_import.mapping import FormatSpec

__all__ = [
    "MAX_EXPORT_BYTES",
    "MAX_PREAMBLE_LINES",
    "ExportError",
    "RawExport",
    "is_empty",
    "read_export",
    "resolve_column",
    "text_cells",
]

#: Largest export read, bytes. A 36 h campaign at 10 Hz with 16 gratings is ~60 MB of text.
MAX_EXPORT_BYTES = 2 << 30
#: Lines searched for ``header_marker`` before giving up.
MAX_PREAMBLE_LINES = 10_000


class ExportError(InputError):
    """An :class:`InputError` in an export whose data rows do not start on line 2: names the
    data row and the file line (or spreadsheet row) it is on, ``row 3 (line 12)``."""

    def __init__(
        self,
        message: str,
        file=None,
        row: int | None = None,
        line: int | None = None,
        column: str | None = None,
        line_label: str = "line",
    ):
        self.line = line
        self.line_label = line_label
        super().__init__(message, file=file, row=row, column=column)

    def one_line(self) -> str:
        """The message with file, ``row N (line M)`` and column, on one line."""
        if self.row is None or self.line is None:
            return super().one_line()
        where = [] if self.file is None else [self.file]
        where.append(f"row {self.row} ({self.line_label} {self.line})")
        if self.column is not None:
            where.append(f"column {self.column}")
        return " ".join(f"{', '.join(where)}: {self.message}".split())


class RawExport:
    """The cells of one export: column names, the mapped columns' cells, file lines per row."""

    def __init__(
        self,
        label: str,
        names: list[str],
        preamble: list[list[str]],
        cells: dict[int, np.ndarray],
        lines: np.ndarray,
        line_label: str,
        text: bool = False,
    ):
        self.label = label  # file name for messages
        self.text = text  # every cell is a str (delimited text): vectorised paths
        self.names = names  # every column name of the header
        self.preamble = preamble  # cells of the lines above the header
        self.cells = cells  # 0-based column index -> object array of cells
        self.lines = lines  # file line (spreadsheet row) of each data row
        self.line_label = line_label

    def error(self, message: str, row_index: int | None = None, column: int | None = None):
        """An :class:`ExportError` at the 0-based data row ``row_index`` and column index."""
        return ExportError(
            message,
            file=self.label,
            row=None if row_index is None else int(row_index) + 1,
            line=None if row_index is None else int(self.lines[row_index]),
            column=None if column is None else self.column_label(column),
            line_label=self.line_label,
        )

    def column_label(self, index: int) -> str:
        """Column ``index`` (0-based) as messages show it: its quoted name, or ``#n``."""
        name = self.names[index] if index < len(self.names) else ""
        return repr(name) if name and name.isprintable() and len(name) <= 64 else f"#{index + 1}"

    def keep(self, mask: np.ndarray) -> None:
        """Keep only the data rows where ``mask`` is true."""
        self.cells = {k: v[mask] for k, v in self.cells.items()}
        self.lines = self.lines[mask]


def _export_kind(path: Path, fmt: FormatSpec) -> str:
    if fmt.kind is not None:
        return fmt.kind
    return "excel" if path.suffix.lower() in (".xlsx", ".xlsm") else "csv"


def resolve_column(ref, names: list[str], label: str, what: str, raw_label: str) -> int:
    """0-based index of the column ``ref`` (a header name or a 1-based position) holding
    ``what``; InputError naming the export, with the closest header name as a hint."""
    if isinstance(ref, int):
        if ref > len(names):
            raise InputError(
                f"{what} is column {ref}, but the header has {len(names)} columns", file=raw_label
            )
        return ref - 1
    stripped = [n.strip() for n in names]
    if ref.strip() in stripped:
        return stripped.index(ref.strip())
    close = difflib.get_close_matches(ref, [n for n in stripped if n.isprintable()], n=1, cutoff=0.6)
    hint = f"; did you mean {close[0]!r}?" if close else ""
    raise InputError(
        f"no column {ref!r} ({what}) in the header ({len(names)} columns){hint}",
        file=raw_label,
        column=repr(ref) if len(ref) <= 64 else None,
    )


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
                line_cells = _split_line(line.rstrip("\r\n"), delimiter)
                is_header = (
                    number == fmt.header_row
                    if fmt.header_row is not None
                    else bool(line_cells) and line_cells[0] == fmt.header_marker
                    if fmt.header_marker is not None
                    else number == 1
                )
                if is_header:
                    header, header_line = line_cells, number
                    break
                preamble.append(line_cells)
    except UnicodeDecodeError as exc:
        raise InputError(
            f"not {fmt.encoding} text ({exc.reason}); set format.encoding (e.g. cp1252, shift_jis)",
            file=label,
        ) from None
    except OSError as exc:
        raise InputError(f"cannot read the file: {exc.strerror or type(exc).__name__}", file=label) from None
    if header is None:
        rule = (
            f"line {fmt.header_row}"
            if fmt.header_row is not None
            else f"a line starting with {fmt.header_marker!r}"
            if fmt.header_marker
            else "line 1"
        )
        raise InputError(
            f"no column header: expected it on {rule} (format.header_row / format.header_marker)", file=label
        )
    if len(header) == 1 and delimiter not in (";", "\t") and any(d in header[0] for d in ";\t"):
        found = "';'" if ";" in header[0] else "tab"
        raise InputError(f"the header has one column but holds {found}: set format.delimiter", file=label)
    columns = sorted({resolve_column(ref, header, label, what, label) for ref, what in wanted})
    first_data_line = header_line + 1 + fmt.skip_after_header
    try:
        frame = pd.read_csv(
            path,
            sep=delimiter,
            header=None,
            skiprows=first_data_line - 1,
            usecols=columns,
            dtype=str,
            na_filter=False,
            skip_blank_lines=False,
            encoding=fmt.encoding,
            engine="c",
            quotechar='"',
        )
    except pd.errors.EmptyDataError:
        frame = pd.DataFrame({c: pd.Series([], dtype=object) for c in columns})
    except UnicodeDecodeError as exc:
        raise InputError(f"not {fmt.encoding} text ({exc.reason}); set format.encoding", file=label) from None
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
        import openpyxl  # noqa: PLC0415 - only .xlsx exports need openpyxl, and it is slow to import
    except ImportError:  # pragma: no cover - a declared dependency
        raise InputError("reading Excel files needs openpyxl (pip install openpyxl)", file=path) from None
    try:
        book = openpyxl.load_workbook(path, read_only=True, data_only=True)
    except Exception as exc:
        raise InputError(f"not a readable .xlsx workbook: {type(exc).__name__}", file=path) from None
    try:
        names = book.sheetnames
        if fmt.sheet is None:
            sheet = names[0]
        elif isinstance(fmt.sheet, int):
            if fmt.sheet > len(names):
                raise InputError(f"sheet {fmt.sheet} requested, the workbook has {len(names)}", file=path)
            sheet = names[fmt.sheet - 1]
        elif fmt.sheet in names:
            sheet = fmt.sheet
        else:
            raise InputError(f"no sheet {fmt.sheet!r} (sheets: {', '.join(names)})", file=path)
        label = f"{path}[{sheet}]"
        preamble: list[list[str]] = []
        header: list[str] | None = None
        body: list[tuple] = []
        body_rows: list[int] = []
        first_data = 0  # set with the header; no data row is read before it
        for number, values in enumerate(book[sheet].iter_rows(values_only=True), start=1):
            if header is None:
                line_cells = ["" if v is None else str(v).strip() for v in values]
                is_header = (
                    number == fmt.header_row
                    if fmt.header_row is not None
                    else bool(line_cells) and line_cells[0] == fmt.header_marker
                    if fmt.header_marker is not None
                    else number == 1
                )
                if is_header:
                    header = line_cells
                    first_data = number + 1 + fmt.skip_after_header
                else:
                    preamble.append(line_cells)
                    if number >= MAX_PREAMBLE_LINES:
                        break
                continue
            if number >= first_data:
                body.append(values)
                body_rows.append(number)
    finally:
        book.close()
    if header is None:
        raise InputError("no column header found (format.header_row / format.header_marker)", file=label)
    columns = sorted({resolve_column(ref, header, label, what, label) for ref, what in wanted})
    cells = {c: np.array([row[c] if c < len(row) else None for row in body], dtype=object) for c in columns}
    raw = RawExport(label, header, preamble, cells, np.asarray(body_rows, dtype=np.int64), "sheet row")
    _drop_trailing_blank(raw)
    return raw


def is_empty(cells: np.ndarray, text: bool = False) -> np.ndarray:
    """Mask of the empty cells (None, blank text, NaN); ``text``: every cell is a str."""
    if text:
        return (text_cells(cells) == "").to_numpy(dtype=bool)
    return np.array(
        [
            c is None or (isinstance(c, str) and not c.strip()) or (isinstance(c, float) and c != c)
            for c in cells
        ],
        dtype=bool,
    )


def text_cells(cells: np.ndarray) -> pd.Series:
    """Cells that are all str as a stripped string Series (Arrow-backed where pyarrow is
    installed: the string operations below then run in C++, ~20x faster than in Python)."""
    return pd.Series(cells, dtype="str").fillna("").str.strip()


def _drop_trailing_blank(raw: RawExport) -> None:
    """Rows empty in every mapped column at the end of the file are an editor's habit."""
    if not raw.cells or raw.lines.size == 0:
        return
    empty = np.logical_and.reduce([is_empty(c, raw.text) for c in raw.cells.values()])
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
