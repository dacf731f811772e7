"""Vendor and logger exports into a campaign folder (``fbgcomp import``).

An interrogator writes its peaks in its own layout, a temperature logger in another, the laser
interferometer in a third; each with its own clock, time zone, units, delimiter and decimal mark.
A *mapping file* (YAML) says, for each export, which column is which sensor, probe or axis, in
which unit, and how its time is written; :func:`import_campaign` reads the exports, converts them
to the campaign's units (nm, degC, um, N) and to seconds from one common start, and writes a
campaign folder that :func:`fbgcomp.io.campaign.read_campaign` accepts (atomically, through
:func:`fbgcomp.io.campaign.write_campaign`: nothing half-written on error).

Mapping file (see ``docs/import.md`` for every key)::

    campaign:                 # campaign.yaml without ``start`` (or the path of such a YAML file)
      name: thermal_a
      kind: thermal
      sensors: [{name: S1, lambda0_nm: 1530.0, gauge_length_mm: 600, temperature_probe: T1}]
      temperature_probes: [{name: T1}]
    timezone: Europe/Berlin   # zone of timestamps written without a UTC offset
    sources:
      - file: peaks.csv
        role: fbg             # fbg | temperatures | reference | loads
        format: {delimiter: ";", decimal: ","}
        time: {column: Timestamp, format: "%d.%m.%Y %H:%M:%S,%f"}
        columns: {S1_nm: {column: "CH1 Peak1", unit: nm}}

Presets (:data:`PRESETS`) fill ``format`` and ``time`` for layouts that a vendor's published
manual documents; each cites its document. Only those are shipped: see ``docs/import.md`` for
the formats searched for and not found.

Errors are :class:`fbgcomp.errors.InputError` (one line, exit 2 from the CLI) naming the export
file, its data row and file line, and the export's column; a mapping error names the mapping
file and the field.

Modules: :mod:`~fbgcomp.io.vendor_import.mapping` (the mapping file's schema),
:mod:`~fbgcomp.io.vendor_import.presets`, :mod:`~fbgcomp.io.vendor_import.readers` (CSV / TSV /
.xlsx exports), :mod:`~fbgcomp.io.vendor_import.values` (numbers, times, units) and
:mod:`~fbgcomp.io.vendor_import.importer` (the import). Every public name is importable from
``fbgcomp.io.vendor_import`` itself.
"""

from fbgcomp.io.vendor_import.importer import describe, import_campaign
from fbgcomp.io.vendor_import.mapping import (
    MAX_MAPPING_BYTES,
    ROLE_FILES,
    ROLE_SUFFIX,
    UNITS,
    ColumnSpec,
    FormatSpec,
    HeaderField,
    ImportMapping,
    SourceSpec,
    TimeSpec,
    parse_zone,
    read_mapping,
)
from fbgcomp.io.vendor_import.presets import NOT_SHIPPED, PRESETS
from fbgcomp.io.vendor_import.readers import (
    MAX_EXPORT_BYTES,
    MAX_PREAMBLE_LINES,
    ExportError,
    RawExport,
    read_export,
)
from fbgcomp.io.vendor_import.values import convert_units, source_times

__all__ = [
    "MAX_EXPORT_BYTES",
    "MAX_MAPPING_BYTES",
    "MAX_PREAMBLE_LINES",
    "NOT_SHIPPED",
    "PRESETS",
    "ROLE_FILES",
    "ROLE_SUFFIX",
    "UNITS",
    "ColumnSpec",
    "ExportError",
    "FormatSpec",
    "HeaderField",
    "ImportMapping",
    "RawExport",
    "SourceSpec",
    "TimeSpec",
    "convert_units",
    "describe",
    "import_campaign",
    "parse_zone",
    "read_export",
    "read_mapping",
    "source_times",
]
