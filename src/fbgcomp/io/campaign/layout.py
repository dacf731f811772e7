"""The campaign folder's layout: its file names and the column names the format fixes.

Kept apart from the modules that read and check the files so that every one of them (metadata,
tables, alignment, folder I/O) names the files the same way.
"""

from __future__ import annotations

from fbgcomp.units import REFERENCE_COLUMNS

__all__ = [
    "FBG_FILE",
    "LOADS_FILE",
    "LOAD_COLUMNS",
    "META_FILE",
    "REFERENCE_COLUMNS",
    "REFERENCE_FILE",
    "TEMPERATURES_FILE",
    "TIME_COLUMN",
]

META_FILE = "campaign.yaml"
FBG_FILE = "fbg.csv"
TEMPERATURES_FILE = "temperatures.csv"
REFERENCE_FILE = "reference.csv"
LOADS_FILE = "loads.csv"

TIME_COLUMN = "time_s"
LOAD_COLUMNS = ("fx_N", "fy_N", "fz_N")
