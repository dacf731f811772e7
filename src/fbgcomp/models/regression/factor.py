"""What the accumulator, the results and stepwise selection all ask of a triangular factor.

Its rank (which columns are numerically linear combinations of the ones before them, and the
error naming them), its conditioning once the columns' units are taken out, and reading a
factor's arrays back from a saved state.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from fbgcomp.errors import InputError

__all__ = [
    "EPS",
    "KAPPA_EXTENDED",
    "RankDeficientError",
    "deficient_columns",
    "equilibrated_cond",
    "field_array",
]

EPS = np.finfo(float).eps
# Above this condition number of the scaled design, double-precision QR would lose more than
# ~10 of the 16 digits: the "auto" precision switches the data pass to double-double, and
# stepwise selection its sub-model statistics.
KAPPA_EXTENDED = 1e6


class RankDeficientError(InputError, ValueError):
    """The design has (numerically) linearly dependent columns.

    ``columns`` lists the names of the columns whose scaled-R diagonal is (near) zero, i.e. that
    are (nearly) linear combinations of the columns before them in the model.
    """

    def __init__(self, message: str, columns: Sequence[str] = ()):
        self.columns = list(columns)
        super().__init__(message)


def deficient_columns(diag_abs: np.ndarray, nobs: int) -> list[int]:
    """Positions whose |R_ii| is (near) zero: <= max(n, p) * eps * max|R_ii| (LAPACK-style)."""
    if diag_abs.size == 0:
        return []
    tol = max(nobs, diag_abs.size) * EPS * float(diag_abs.max())
    return [int(i) for i in np.flatnonzero(~(diag_abs > tol))]


def equilibrated_cond(r: np.ndarray) -> float:
    """2-norm condition number of the triangle ``r`` with its columns scaled to unit norm: the
    conditioning that governs a Cholesky/normal-equations solution (van der Sluis), whatever the
    columns' units. inf when a column is zero."""
    norms = np.linalg.norm(r, axis=0)
    if r.size == 0:
        return 1.0
    if not (norms > 0).all():
        return math.inf
    return float(np.linalg.cond(r / norms))


def field_array(state: dict, key: str, shape: tuple[int, ...]) -> np.ndarray:
    """The numeric array ``state[key]`` of a saved state, checked to have ``shape``.

    Raises
    ------
    KeyError
        The field is missing (the caller names what it was reading).
    InputError
        The field is not numeric or has another shape.
    """
    try:
        arr = np.asarray(state[key], dtype=float)
    except (TypeError, ValueError):
        raise InputError(f"field {key!r} is not numeric", column=f"field {key}") from None
    if arr.shape != shape:
        raise InputError(f"field {key!r} has shape {arr.shape}, expected {shape}", column=f"field {key}")
    return arr
