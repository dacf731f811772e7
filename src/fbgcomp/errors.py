"""Errors the user can act on.

Every problem with user input is raised as :class:`InputError`; the CLI turns it into one
line on stderr that starts with ``error:`` and names the file (and row / column or field
when known), and exits with code 2, without a traceback.
"""

from __future__ import annotations

from pathlib import Path


class InputError(Exception):
    """Bad user input: names the file and, when known, the row and the column or field.

    Parameters
    ----------
    message : str
        What is wrong and what was expected.
    file : str or Path, optional
        The offending file.
    row : int, optional
        1-based data row of a CSV: data row 1 is line 2 of the file (the header is line 1).
        The message names both, ``row 4 (line 5)``.
    column : str, optional
        Column name (CSV) or field path (YAML / JSON), e.g. ``sensors[2].lambda0_nm``.
    """

    def __init__(
        self, message: str, file: str | Path | None = None, row: int | None = None, column: str | None = None
    ):
        self.message = message
        self.file = None if file is None else str(file)
        self.row = row
        self.column = column
        super().__init__(self.one_line())

    def one_line(self) -> str:
        """The message on one line, after where it applies: file, row (and line), column."""
        where = []
        if self.file is not None:
            where.append(self.file)
        if self.row is not None:
            where.append(f"row {self.row} (line {self.row + 1})")
        if self.column is not None:
            where.append(f"column {self.column}" if not self.column.startswith("field ") else self.column)
        prefix = ", ".join(where)
        text = f"{prefix}: {self.message}" if prefix else self.message
        return " ".join(text.split())  # exactly one line


def read_bounded(
    path: str | Path, max_bytes: int, *, what: str, unreadable: str = "cannot read the file"
) -> bytes:
    """The bytes of ``path``, read without ever holding more than ``max_bytes + 1`` of them.

    InputError naming the file: ``"<unreadable>: <reason>"`` when it cannot be opened or read,
    ``"larger than <max_bytes> bytes: not <what>"`` when it is bigger than ``max_bytes``."""
    try:
        with open(path, "rb") as handle:
            raw = handle.read(max_bytes + 1)
    except OSError as exc:
        raise InputError(f"{unreadable}: {exc.strerror or type(exc).__name__}", file=path) from None
    if len(raw) > max_bytes:
        raise InputError(f"larger than {max_bytes} bytes: not {what}", file=path)
    return raw
