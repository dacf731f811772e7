"""Console tables of the CLI: aligned columns, units in the headers, rounding-level numbers as 0.

Every table ``fbgcomp`` prints goes through :func:`format_table`, so that columns never run
together (each is as wide as its widest cell, two spaces apart), every numeric header names its
unit (``max |err| (µm)``) and a number that rounds to zero at the column's precision is printed
``0`` - not ``-0.000``, not ``1.169e-31`` - while a missing value (NaN, None) is ``—``.
Only the text changes: the figures stay those of the computation (and of the JSON/CSV outputs).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

#: How a missing number (NaN, None) is shown.
MISSING = "\u2014"


def format_number(value, decimals: int = 3) -> str:
    """A number for a console table, fixed-point with ``decimals`` decimals.

    ``|value| < 0.5 · 10**-decimals`` (it rounds to zero at this precision) is ``"0"``, without
    a sign; NaN and None are :data:`MISSING`; ±inf is ``"inf"``/``"-inf"``. Integers (``int``,
    ``bool`` excluded) are printed as they are.

    Examples
    --------
    >>> format_number(25.7104, 2), format_number(-0.0004), format_number(1.169e-31)
    ('25.71', '0', '0')
    """
    if value is None:
        return MISSING
    if isinstance(value, int) and not isinstance(value, bool):
        return str(value)
    x = float(value)
    if math.isnan(x):
        return MISSING
    if math.isinf(x):
        return "inf" if x > 0 else "-inf"
    if abs(x) < 0.5 * 10.0**-decimals:
        return "0"
    text = f"{x:.{decimals}f}"
    # a value just above the threshold that still rounds to zero (binary representation)
    return "0" if float(text) == 0.0 else text


@dataclass(frozen=True)
class Column:
    """One column: its name, unit (shown in the header as ``name (unit)``), the decimals of its
    numbers, and its alignment (``">"`` right, the default for numbers; ``"<"`` left)."""

    name: str
    unit: str = ""
    decimals: int = 3
    align: str = ">"

    @property
    def header(self) -> str:
        """The header: ``name (unit)``, or the name alone without a unit."""
        return f"{self.name} ({self.unit})" if self.unit else self.name

    def cell(self, value) -> str:
        """A cell: a string as it is, a number through :func:`format_number`."""
        if isinstance(value, str):
            return value
        return format_number(value, self.decimals)


def text(name: str) -> Column:
    """A left-aligned text column."""
    return Column(name, align="<")


def format_table(columns, rows, *, indent: str = "", gap: int = 2) -> str:
    """Rows (sequences of cells, one per column; numbers or ready strings) as aligned lines.

    A row may carry one more cell than there are columns: a note printed after the last column
    (e.g. ``WORSE than uncompensated``), which does not widen the table.
    """
    columns = list(columns)
    cells = []
    notes = []
    for row in rows:
        row = list(row)
        if len(row) not in (len(columns), len(columns) + 1):
            raise ValueError(f"a row of {len(row)} cells in a table of {len(columns)} columns")
        cells.append([c.cell(v) for c, v in zip(columns, row)])
        notes.append(row[len(columns)] if len(row) > len(columns) else "")
    widths = [max([len(c.header)] + [len(r[j]) for r in cells]) for j, c in enumerate(columns)]
    sep = " " * gap

    def line(parts, note=""):
        out = sep.join(f"{p:{c.align}{w}}" for p, c, w in zip(parts, columns, widths))
        out = out.rstrip() if not note else f"{out}{sep}{note}"
        return indent + out

    return "\n".join([line([c.header for c in columns])] + [line(r, n) for r, n in zip(cells, notes)])
