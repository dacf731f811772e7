"""The model file on disk: its format, size and number limits, schema migrations and reading.

A model file is JSON (never pickle) with ``format`` :data:`MODEL_FORMAT`, a ``schema_version``
and a ``model_type``. Every model file is read through :func:`read_model_dict`, which checks it at
this boundary: at most :data:`MAX_MODEL_BYTES` and :data:`MAX_MODEL_DEPTH` levels of nesting; no
NaN or infinity anywhere; outside the descriptive statistics (:data:`STATISTICS`) no null inside
an array and no number beyond :data:`MAX_MODEL_VALUE`; a schema version this fbgcomp knows, older
ones upgraded by :data:`MIGRATIONS`. :func:`build_model` then turns the dict into a model of a
given class, any failure becoming one InputError naming the file. Which class a ``model_type``
names is the registry's business (:mod:`fbgcomp.models.registry`); this module knows no model
type, so every model type can use it.
"""

from __future__ import annotations

import hashlib
import json
import math
from pathlib import Path
from typing import Any

from fbgcomp.errors import InputError, read_bounded

#: Largest model file read, bytes (one with every fallback of a dozen gratings is ~1 MB).
MAX_MODEL_BYTES = 64 << 20
#: Deepest nesting of JSON objects and arrays in a model file (the deepest real one is ~10).
MAX_MODEL_DEPTH = 64
#: Largest magnitude of a number a model predicts with (coefficients in µm per µm or per K,
#: covariances, bounds, machine dimensions): a larger one is a corrupted or hostile file.
MAX_MODEL_VALUE = 1e12
#: Fields holding descriptive statistics, reported and never used to predict: inside them a
#: null (an undefined F, an infinite t of an exact fit) or a large number (a sum of squares) is
#: allowed. NaN and infinity are refused everywhere.
STATISTICS = frozenset(
    {
        "fvalue",
        "f_pvalue",
        "tvalues",
        "pvalues",
        "bse",
        "rsquared",
        "rsquared_adj",
        "stepwise_history",
        "hac",
        "training",
    }
)

#: The ``format`` field of every model file.
MODEL_FORMAT = "fbgcomp-model"
#: The schema version this fbgcomp writes.
SCHEMA_VERSION = 2


def migrate_v1_to_v2(d: dict) -> dict:
    """v2 (model types kinematic, hybrid, dynamic) adds to every file the prediction-interval
    description ``uncertainty`` and the Z-axis position ``z_axis_mm`` the model assumes when the
    caller gives none (v1 files are regressions: their interval is the regression's, no Z)."""
    d = dict(d)
    d.setdefault("model_type", "mra")
    d.setdefault("uncertainty", {"level": 0.95, "method": "regression: covariance + residual variance"})
    d.setdefault("z_axis_mm", None)
    d["schema_version"] = 2
    return d


#: Upgrades of older model files, ``{from_version: function(dict) -> dict of from_version + 1}``.
MIGRATIONS: dict = {1: migrate_v1_to_v2}


def short_text(text, limit: int = 80) -> str:
    """``text`` on one line, cut to ``limit`` characters (with "...") for an error message."""
    text = " ".join(str(text).split())
    return text if len(text) <= limit else text[: limit - 3] + "..."


def model_id(d: dict) -> str:
    """Short stable hash of a model's content (ignores its id and creation time)."""
    content = {k: v for k, v in d.items() if k not in ("model_id", "created_utc")}
    blob = json.dumps(content, sort_keys=True, separators=(",", ":")).encode()
    return hashlib.sha256(blob).hexdigest()[:12]


class _NonFinite:
    """A NaN, infinity or overflowing literal met while parsing (reported with its field)."""

    __slots__ = ("text",)

    def __init__(self, text):
        self.text = text


def _parse_float(text):
    value = float(text)
    return value if math.isfinite(value) else _NonFinite(text)


def read_model_json(path: Path):
    """The parsed JSON of a model file (non-finite numbers kept as markers for
    :func:`check_model_numbers`); InputError naming the file when it cannot be read or parsed."""
    if not path.exists():
        raise InputError("model file not found", file=path)
    if not path.is_file():
        raise InputError("not a regular file", file=path)
    raw = read_bounded(path, MAX_MODEL_BYTES, what="a model file", unreadable="cannot read model file")
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise InputError(
            f"not UTF-8 text: byte 0x{raw[exc.start]:02x} at offset {exc.start}", file=path
        ) from None
    try:
        return json.loads(text, parse_float=_parse_float, parse_constant=_NonFinite)
    except json.JSONDecodeError as exc:
        raise InputError(
            f"not a JSON model file: {exc.msg} at line {exc.lineno}, column {exc.colno}", file=path
        ) from None
    except RecursionError:
        raise InputError(
            f"JSON nested deeper than {MAX_MODEL_DEPTH} levels: not a model file", file=path
        ) from None
    except ValueError as exc:  # e.g. an integer literal of thousands of digits
        raise InputError(f"not a JSON model file: {short_text(exc)}", file=path) from None


def _field_text(parts) -> str:
    out = ""
    for part in parts:
        if isinstance(part, int):
            out += f"[{part}]"
        else:
            name = part if part.isprintable() and len(part) <= 40 else "<key>"
            out += f".{name}" if out else name
    return out or "<top level>"


def check_model_numbers(d, source="<dict>") -> None:
    """The checks :func:`read_model_dict` applies to every model type before building it: nesting
    at most :data:`MAX_MODEL_DEPTH`, no NaN or infinity anywhere, and outside :data:`STATISTICS` no
    null inside an array and no number beyond :data:`MAX_MODEL_VALUE`. InputError names the
    first offending field (in file order)."""
    stack: list[tuple[Any, tuple[Any, ...], bool]] = [(d, (), False)]
    while stack:
        node, parts, statistic = stack.pop()
        if len(parts) > MAX_MODEL_DEPTH:
            raise InputError(
                f"nested deeper than {MAX_MODEL_DEPTH} levels: not a model file",
                file=source,
                column=f"field {_field_text(parts[:8])}...",
            )
        if isinstance(node, dict):
            stack.extend(
                (v, (*parts, k), statistic or k in STATISTICS) for k, v in reversed(list(node.items()))
            )
        elif isinstance(node, list):
            if not statistic and any(v is None for v in node):
                i = next(i for i, v in enumerate(node) if v is None)
                raise InputError(
                    "null where a number is expected (a NaN written out?)",
                    file=source,
                    column=f"field {_field_text((*parts, i))}",
                )
            stack.extend((v, (*parts, i), statistic) for i, v in reversed(list(enumerate(node))))
        elif isinstance(node, _NonFinite):
            raise InputError(
                f"non-finite number {short_text(node.text, 24)}; a model holds finite numbers only",
                file=source,
                column=f"field {_field_text(parts)}",
            )
        elif (
            isinstance(node, (int, float))
            and not isinstance(node, bool)
            and not statistic
            and abs(node) > MAX_MODEL_VALUE
        ):
            shown = (
                f"{node:.3g}"
                if isinstance(node, float) or abs(node) < 10**300
                else "an integer of over 300 digits"
            )
            raise InputError(
                f"{shown} is beyond the {MAX_MODEL_VALUE:g} a model may hold (a corrupted or hostile file?)",
                file=source,
                column=f"field {_field_text(parts)}",
            )


def read_model_dict(path) -> dict:
    """A model file's dict, checked and migrated to :data:`SCHEMA_VERSION`; InputError naming
    the file and field on anything wrong (size, nesting, numbers, format, schema version, a
    ``model_type`` that is not a name). Which class builds it is left to the caller."""
    path = Path(path)
    d = read_model_json(path)
    if not isinstance(d, dict) or d.get("format") != MODEL_FORMAT:
        raise InputError(
            f"not an fbgcomp model file (field 'format' must be {MODEL_FORMAT!r})",
            file=path,
            column="field format",
        )
    check_model_numbers(d, path)
    version = d.get("schema_version")
    if not isinstance(version, int) or isinstance(version, bool) or version < 1:
        raise InputError("schema_version must be an integer >= 1", file=path, column="field schema_version")
    if version > SCHEMA_VERSION:
        raise InputError(
            f"model schema version {version} is newer than this fbgcomp supports "
            f"({SCHEMA_VERSION}); upgrade fbgcomp",
            file=path,
            column="field schema_version",
        )
    while version < SCHEMA_VERSION:
        d = MIGRATIONS[version](d)
        version = d["schema_version"]
    if not isinstance(d.get("model_type"), str):
        raise InputError("model_type must be a name", file=path, column="field model_type")
    return d


def build_model(cls, d: dict, path):
    """``cls.from_dict(d, source=path)``, with whatever a malformed file makes fail (a missing
    field, a wrong type) turned into one InputError naming the file."""
    try:
        return cls.from_dict(d, source=path)
    except InputError:
        raise
    except KeyError as exc:
        raise InputError(f"missing field {short_text(repr(exc.args[0]), 40)}", file=path) from None
    except Exception as exc:
        raise InputError(
            f"malformed model file: {type(exc).__name__}: {short_text(exc)}", file=path
        ) from None
