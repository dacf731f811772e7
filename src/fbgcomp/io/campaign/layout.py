"""The campaign folder's layout: its file names and the column names the format fixes.

Kept apart from the modules that read and check the files so that every one of them (metadata,
tables, alignment, folder I/O) names the files the same way.
"""

from __future__ import annotations

from fbgcomp.units import REFERENCE_COLUMNS

__all__ = [
    "FBG_FILE",
    "HEAT_FILE",
    "HEAT_SUFFIX",
    "LOADS_FILE",
    "LOAD_COLUMNS",
    "META_FILE",
    "REFERENCE_COLUMNS",
    "REFERENCE_FILE",
    "TEMPERATURES_FILE",
    "TIME_COLUMN",
    "input_column",
]

META_FILE = "campaign.yaml"
FBG_FILE = "fbg.csv"
TEMPERATURES_FILE = "temperatures.csv"
REFERENCE_FILE = "reference.csv"
LOADS_FILE = "loads.csv"
#: Optional: measured heat inputs (a spindle's power as the CNC reads it), one ``<source>_W``
#: column per heat source of the machine description.
HEAT_FILE = "heat.csv"
HEAT_SUFFIX = "_W"

TIME_COLUMN = "time_s"
LOAD_COLUMNS = ("fx_N", "fy_N", "fz_N")


def input_column(name: str) -> str:
    """The column of a model's slow input (``model.probe_names``) in a table: ``<probe>_C`` for
    a temperature probe; a measured heat input is named with its unit already (``<source>_W``)."""
    return name if name.endswith(HEAT_SUFFIX) else f"{name}_C"
