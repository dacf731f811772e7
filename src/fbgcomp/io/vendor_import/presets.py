"""Presets of ``fbgcomp import``: export layouts that a vendor's published manual documents, as
data, each citing its document (``docs/import.md`` lists the formats searched for and not found).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from fbgcomp.errors import InputError

__all__ = ["NOT_SHIPPED", "PRESETS", "apply_preset"]

#: Each preset fills ``format`` and ``time`` (the mapping's own keys win) and cites the document
#: its layout is written from. The columns (which channel is which probe) are always the user's.
PRESETS: dict[str, dict[str, Any]] = {
    "hioki-lr8431-csv": {
        "instrument": "Hioki MEMORY HiLOGGER LR8431-20 (thermocouple / voltage logger)",
        "citation": "Hioki LR8431-20 Instruction Manual, Appendix 3 'Text File (CSV) Internal "
        "Format', p. A8: https://manualshive.com/en/manual/hioki/lr8431/2137135?page=166 "
        "(also https://www.easymanua.ls/hioki/lr8431-20/manual?p=166)",
        "layout": "header lines 'File name', 'Title comment', 'Trigger Time' "
        '("\'yy-mm-dd hh:mm:ss"), a channel-settings table (Ch, Mode, Range, Comment, '
        "Scaling, Ratio, Offset), then the data header 'Time', 'CH-n[unit]', ..., "
        "'Event' and comma-separated rows whose Time is seconds from the trigger time "
        "(rows and header end with a comma)",
        "format": {"kind": "csv", "delimiter": ",", "decimal": ".", "header_marker": "Time"},
        "time": {
            "column": "Time",
            "kind": "elapsed",
            "unit": "s",
            "origin_from_header": {"label": "Trigger Time", "format": "'%y-%m-%d %H:%M:%S"},
        },
    },
}

#: Formats searched for and not shipped (docs/import.md says what was searched).
NOT_SHIPPED = {
    "Luna / Micron Optics ENLIGHT peak files": "only the user guide's table of contents "
    "(ENLIGHT User Guide rev. 1.138) was reachable; no page describing the saved peak file",
    "HBM catman ASCII export": "no published description of the export layout found",
    "FBGS ILLumiSense export": "no published description found",
    "Renishaw laser (LaserXL / CARTO) exports": "no published description found",
}


def apply_preset(raw: Mapping, index: int, file) -> dict:
    """Source ``index`` of a mapping file with its preset's ``format`` and ``time`` filled in
    (its own keys win); InputError naming the field for an unknown preset."""
    source = dict(raw)
    name = source.get("preset")
    if name is None:
        return source
    if not isinstance(name, str) or name not in PRESETS:
        raise InputError(
            f"unknown preset {name!r}; shipped presets: {', '.join(PRESETS)} (docs/import.md)",
            file=file,
            column=f"field sources[{index}].preset",
        )
    preset = PRESETS[name]
    for key in ("format", "time"):
        own = source.get(key) or {}
        if not isinstance(own, Mapping):
            continue  # the schema names the field
        source[key] = {**preset[key], **own}
    return source
