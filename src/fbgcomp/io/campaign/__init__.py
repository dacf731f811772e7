"""Campaign folders: read, validate, align the instruments' clocks, zero state, write.

A campaign is one experiment on the machine (paper section 3: static loads at the TTP, or a 36 h
thermal run) stored as a folder::

    <campaign>/campaign.yaml       metadata: sensors, probes, reference instrument, free extras
    <campaign>/fbg.csv             time_s, <sensor>_nm ...     Bragg peak wavelengths, nm
    <campaign>/temperatures.csv    time_s, <probe>_C ...       probe temperatures, degC
    <campaign>/reference.csv       time_s, dx_um, dy_um, dz_um TTP displacement (interferometer), um
    <campaign>/loads.csv           time_s, fx_N, fy_N, fz_N    optional: forces at the TTP, N
    <campaign>/heat.csv            time_s, <source>_W ...      optional: measured heat inputs, W
                                                               (a spindle's power, as the CNC reads it)

Each CSV has its own clock and rate. :func:`read_campaign` validates everything at this boundary
and raises :class:`fbgcomp.errors.InputError` naming file, row and column, so the physics modules
downstream can assume clean, finite, strictly time-ordered arrays. :meth:`Campaign.aligned` puts
every instrument on the reference instrument's clock (linear interpolation, never extrapolation)
and takes the zero state the paper's deltas (``Delta S_i``, ``Delta T``, eq. 13) are measured from.

Decisions the rest of the package relies on
-------------------------------------------
* Column order is canonical after reading: ``time_s`` first, then sensors in ``campaign.yaml``
  order (fbg), declared probes then undeclared ``<probe>_C`` columns in file order (temperatures),
  dx/dy/dz (reference), fx/fy/fz (loads), ``<source>_W`` columns in file order (heat; other
  columns there are read, checked and left out).
* Temperature columns not declared in ``campaign.yaml`` are kept as probes
  (:attr:`Campaign.probe_names` lists them after the declared ones) and reported by
  :meth:`Campaign.summary`; ``meta`` itself stays exactly what the YAML says, so it round-trips.
* Loads do not restrict the alignment overlap. Inside the loads' own time range they are linearly
  interpolated; outside it they are NaN (never extrapolated, never held).
  ``dropped["loads_outside"]`` counts those samples.
* The zero state of every signal is the mean over the first ``zero_window_s`` seconds of that
  signal on its own clock (samples with ``t <= t_first + zero_window_s``, at least one), taken from
  the whole file, including samples before the alignment overlap.

Limits (the reader is bounded whatever a file holds)
----------------------------------------------------
* A CSV holds at most :data:`MAX_COLUMNS` (4096) columns; its header line is read with a bounded
  readline (:data:`MAX_HEADER_BYTES`, 1 MiB) and checked in linear time. A data row may be at
  most :data:`MAX_CELL_BYTES` (256) bytes per column long (64 KiB at least).
* Files are streamed: the body is parsed in blocks of whole rows, never read whole.
  ``campaign.yaml`` may be at most :data:`MAX_META_BYTES` (1 MiB).
* Every number must lie within its column's physical bounds (:data:`VALUE_BOUNDS`): wavelengths
  in (0, 10000) nm, temperatures in [-273.15, 1000] degC, displacements in (-1e6, 1e6) um, forces
  in (-1e7, 1e7) N, powers in (-1e7, 1e7) W, times in (-1e10, 1e10) s. Anything else is refused
  as a bad cell of the file it is in, so no overflow can reach the physics and surface against a derived quantity.
* Errors quote at most the offending cell or column name, cut short, and only names that are
  printable text: never a header line (``fbg.csv`` may be a link to some other file).

Modules
-------
:mod:`~fbgcomp.io.campaign.layout` file and column names; :mod:`~fbgcomp.io.campaign.meta`
campaign.yaml; :mod:`~fbgcomp.io.campaign.tables` the CSV tables; :mod:`~fbgcomp.io.campaign.align`
clocks and zero state; :mod:`~fbgcomp.io.campaign.folder` the :class:`Campaign` and the folder
I/O. Every public name is importable from ``fbgcomp.io.campaign`` itself.
"""

from fbgcomp.io.campaign.align import AVERAGE_MIN_SAMPLES, AlignedCampaign
from fbgcomp.io.campaign.folder import GAP_FACTOR, Campaign, read_campaign, write_campaign
from fbgcomp.io.campaign.layout import (
    FBG_FILE,
    HEAT_FILE,
    HEAT_SUFFIX,
    LOAD_COLUMNS,
    LOADS_FILE,
    META_FILE,
    REFERENCE_COLUMNS,
    REFERENCE_FILE,
    TEMPERATURES_FILE,
    TIME_COLUMN,
)
from fbgcomp.io.campaign.meta import (
    MAX_META_BYTES,
    CampaignMeta,
    MetaLoader,
    ProbeSpec,
    ReferenceSpec,
    SensorSpec,
    check_sensors_match,
    meta_error,
    read_meta,
)
from fbgcomp.io.campaign.tables import (
    MAX_CELL_BYTES,
    MAX_COLUMNS,
    MAX_HEADER_BYTES,
    VALUE_BOUNDS,
    WAVELENGTH_BAND_NM,
)

__all__ = [
    "AVERAGE_MIN_SAMPLES",
    "FBG_FILE",
    "GAP_FACTOR",
    "HEAT_FILE",
    "HEAT_SUFFIX",
    "LOADS_FILE",
    "LOAD_COLUMNS",
    "MAX_CELL_BYTES",
    "MAX_COLUMNS",
    "MAX_HEADER_BYTES",
    "MAX_META_BYTES",
    "META_FILE",
    "REFERENCE_COLUMNS",
    "REFERENCE_FILE",
    "TEMPERATURES_FILE",
    "TIME_COLUMN",
    "VALUE_BOUNDS",
    "WAVELENGTH_BAND_NM",
    "AlignedCampaign",
    "Campaign",
    "CampaignMeta",
    "MetaLoader",
    "ProbeSpec",
    "ReferenceSpec",
    "SensorSpec",
    "check_sensors_match",
    "meta_error",
    "read_campaign",
    "read_meta",
    "write_campaign",
]
