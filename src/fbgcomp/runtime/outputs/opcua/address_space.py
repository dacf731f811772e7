"""The OPC UA address space, as data: namespace, node names, descriptions, units and EU ranges.

What a PLC programmer or an integrator browsing the server reads (docs/runtime.md, and
docs/opcua-cnc.md for its mapping onto OPC 40501-1). Plain data, without asyncua, so the service
side can import it; :mod:`.nodes` builds the nodes from it in the server process.
"""

from __future__ import annotations

NAMESPACE = "urn:fbgcomp:runtime"
APPLICATION_URI = "urn:fbgcomp:runtime:server"
AXES = ("X", "Y", "Z")  # axis letters of node names (fbgcomp.units.AXES: dx, dy, dz)


# --------------------------------------------------------------------------- units
UNECE_NAMESPACE_URI = "http://www.opcfoundation.org/UA/units/un/cefact"
# unit in our names (``_um``...) -> UNECE Rec. 20 common code, display name, description
UNITS = {
    "um": ("4H", "\u00b5m", "micrometre (micron)"),
    "nm": ("C45", "nm", "nanometre"),
    "ms": ("C26", "ms", "millisecond"),
    "mm": ("MMT", "mm", "millimetre"),
    # Rec. 20 has no micrometre per metre; "59" (part per million, 10^-6) is the same ratio
    # (1 µm of correction per m of travel), shown as µm/m (docs/opcua-cnc.md)
    "um_per_m": ("59", "\u00b5m/m", "micrometre per metre (part per million, 1e-6)"),
}


def unece_unit_id(common_code: str) -> int:
    """OPC UA ``EUInformation.UnitId`` of a UNECE Rec. 20 common code (OPC 10000-8, 5.6.3).

    The code's (at most three) ASCII characters, most significant first:
    ``"4H"`` (micrometre) -> ``0x3448`` = 13384, ``"C45"`` (nanometre) -> ``0x433435``.
    """
    if not 1 <= len(common_code) <= 3 or not common_code.isascii():
        raise ValueError(f"not a UNECE common code: {common_code!r}")
    unit_id = 0
    for c in common_code:
        unit_id = (unit_id << 8) | ord(c)
    return unit_id


# EURange (OPC 10000-8: the range "likely to be obtained in normal operation", e.g. to scale a
# bar graph) of the analog variables; OpcUaServer(eu_ranges=...) overrides any of them
DEFAULT_EU_RANGES = {
    "Correction": (-1000.0, 1000.0),  # µm: serve's default --max-correction-um
    "PredictedDeviation": (-1000.0, 1000.0),  # µm
    "IntervalHalfWidth": (0.0, 1000.0),  # µm
    "ExpectedError": (0.0, 1000.0),  # µm
    "Latency_ms": (0.0, 1000.0),  # ms
    "Wavelength_nm": (1460.0, 1640.0),  # nm: S, C and L bands of FBG interrogators
    "Offset": (-1000.0, 1000.0),  # µm: the offset + Z slope form (cnc_form)
    "Slope": (-1000.0, 1000.0),  # µm/m
    "ZRef_mm": (-10000.0, 10000.0),  # mm
}

# Description attribute of every node (what a PLC programmer or an integrator browsing the
# server reads); the per-axis ones take the axis letter
DESCRIPTIONS = {
    "FbgComp": "Thermal compensation of the machine tool from fibre-Bragg-grating strain sensors "
    "(fbgcomp). OPC 40501-1: a <MonitoredElement> of MachineTool/Monitoring "
    "(ElementMonitoringType concept); vendor-specific, see docs/opcua-cnc.md.",
    "ThermalCompensationType": "fbgcomp's thermal compensation of a machine tool. Corresponds to "
    "OPC 40501-1 ElementMonitoringType (a <MonitoredElement> of the "
    "machine tool's Monitoring); not derived from it, since the server "
    "does not load the Machine Tools nodeset.",
    "Name": "Name of the monitored element (as ElementMonitoringType.Name in OPC 40501-1).",
    "Correction": "Correction to apply on axis {a}: minus the predicted tool-tip deviation, "
    "after the do-no-harm limits; 0 while ZEROING or not Enabled, held and ramped "
    "to 0 in ALARM.",
    "PredictedDeviation": "Model prediction of the tool-tip (TTP) thermal deviation on axis {a} "
    "(NaN without a model).",
    "IntervalHalfWidth": "Half-width of the 95 % prediction interval of the deviation on axis {a}.",
    "ExpectedError": "Residual standard deviation of the model in use (full or fallback) on axis {a}.",
    "OutputFlags": "Why the published correction on axis {a} is held back, one bit each: "
    "{flags}; 0 = not held back.",
    "SampleTime": "Instrument time stamp of the published sample; written last, so a client "
    "watching it sees a complete sample.",
    "Latency_ms": "Frame time stamp to publication (updated at most 10 times a second).",
    "ModelId": "model_id of the model file in use.",
    "Health": "ZEROING, OK, DEGRADED or ALARM; apply the correction only in OK or DEGRADED.",
    "Alarm": "True: compensator fault (health ALARM); ramp the applied correction to zero.",
    "FallbackInUse": "Sensors (and lost probes) excluded by the fallback model in use, e.g. S3 or "
    "T_flange; empty for the full model.",
    "Limited": "True: the published correction is held back on some axis (a flag is set).",
    "OutputFlagsText": "The output flags as text, e.g. Y:RATE_LIMITED Z:SHRUNK; empty when "
    "nothing is held back.",
    "SourceStatus": "Wavelength source: connected, reconnecting (...), replaying or finished.",
    "FramesProcessed": "Frames processed since start (updated at most 10 times a second).",
    "Heartbeat": "Incremented at least every 0.2 s, data or not: the CNC's watchdog.",
    "Enabled": "Switch of the correction output (false: the published correction is 0). "
    "Writable by an authenticated user.",
    "Sensors": "The fibre-Bragg-grating strain sensors (vendor-specific).",
    "Sensor": "Strain sensor {s}: a grating bonded to the machine structure.",
    "Sensors.Status": "Sensor status, one of {statuses} (docs/runtime.md).",
    "Sensors.Wavelength_nm": "Last Bragg wavelength of the sensor in its window (updated at "
    "most 10 times a second).",
    "Offset": "Offset of the correction on axis {a} at the reference position ZRef_mm, the "
    "form a CNC's thermal compensation takes from the PLC (offset + slope x (Z - "
    "ZRef_mm), docs/cnc-integration.md): the correction rate- and magnitude-limited "
    "as the Modbus output's offset; ramps to 0 when the output is off or in ALARM.",
    "Slope": "Slope of the correction on axis {a} with the Z position at ZRef_mm, micrometres "
    "of correction per metre of Z travel (rate- and magnitude-limited as the Modbus "
    "output's); 0 for a model without a Z term or when not applied.",
    "ZRef_mm": "Reference Z position of OffsetX/Y/Z_um and SlopeX/Y/Z_um_per_m: the live Z "
    "the model was evaluated at, else the model's own; 0 for a model without a Z "
    "term (its slope is 0).",
    "ReloadModel": "Load a model file of the models folder (opcua.models_dir), or reload the "
    "current one. Needs an authenticated user; the new model must expect the "
    "same sensors and probes.",
    "ReloadModel.ModelFile": "Model file name relative to the models folder (no absolute path, "
    "no '..'); empty: reload the model serve was started with.",
    "ReloadModel.Result": "What was loaded: 'loaded <model_id>'.",
}


def eu_range(eu_ranges: dict, kind: str, sensor: str | None = None) -> tuple[float, float]:
    """EURange of a kind of analog variable: ``eu_ranges`` given to the server (by kind, or
    ``<kind>.<sensor>`` for one sensor or axis: ``Wavelength_nm.S2``, ``Correction.Z``), else
    :data:`DEFAULT_EU_RANGES`."""
    if sensor is not None and f"{kind}.{sensor}" in eu_ranges:
        return tuple(eu_ranges[f"{kind}.{sensor}"])
    return tuple(eu_ranges.get(kind, DEFAULT_EU_RANGES[kind]))
