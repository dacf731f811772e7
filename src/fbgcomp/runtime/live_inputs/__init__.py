"""Live inputs of ``serve``: probe temperatures over OPC UA and Modbus TCP, the Z-axis position
from LinuxCNC or OPC UA (docs/runtime.md, "Live inputs").

A real machine's probes are read by its PLC or a logger; the axis position is the CNC's. Each
reader runs as an asyncio task beside the frame loop and never blocks it: it only keeps, per
input, the latest value and the monotonic time it was received. At every batch the service
asks for the latest temperatures and Z; a value older than its ``stale_s`` (or never received,
or received with a bad status) is *missing*: NaN, which the pipeline handles as a lost probe -
the model's stored set without it (DEGRADED), or without one, no usable model: health ALARM,
the last correction held and ramped to zero (the do-no-harm fallback). A missing Z matters
only to a model whose prediction depends on Z (kinematic, hybrid, calibrated); the others
ignore it. :attr:`LiveInputs.status` names the stale inputs (OPC UA ``SourceStatus``, the log).

Configuration (serve TOML; any subset)::

    [temperatures.opcua]
    endpoint = "opc.tcp://127.0.0.1:4841"
    security = "None"            # or "Basic256Sha256" (with certificate, private_key,
                                 # optional server_certificate, mode "SignAndEncrypt" | "Sign")
    nodes = { T_bulk = "ns=2;s=Probes.T_bulk", T_surf = "ns=2;s=Probes.T_surf" }
    stale_s = 30

    [temperatures.modbus]
    host = "127.0.0.1"
    port = 502
    unit = 1
    registers = { T_flange = { address = 0, type = "int16", scale = 0.1 } }
    poll_s = 1
    stale_s = 30

    [position]
    source = "linuxcnc"          # or "opcua" (node = "ns=2;s=Axes.Z", endpoint = ...)
    stale_s = 1

OPC UA values come by subscription (data-change trigger *StatusValueTimestamp*, so a server
that rewrites a steady temperature with a new timestamp keeps it fresh; a server that stops
writing lets it go stale). The client reconnects by itself (asyncua's supervisor, with its
subscriptions re-created). Modbus registers are holding registers (function 3), one read per
probe per ``poll_s``, decoded big-endian (high word first for 32-bit types, as
:mod:`fbgcomp.runtime.outputs.modbus` writes its own): ``value = raw * scale + offset``, °C. Types:
``int16``, ``uint16``, ``int32``, ``uint32``, ``float32``. The LinuxCNC position is the HAL
component's ``fbgcomp.z-pos-mm`` pin, sent back over the local channel
(:mod:`fbgcomp.cnc.fbgcomp_hal`); it counts as missing until the machine is homed.

Each model probe comes from exactly one source: the live ones named here, the rest from
``--temperatures`` (a campaign folder, CSV or constants); a probe no source names, or that two
name, stops the start with a one-line error.
"""

from fbgcomp.runtime.live_inputs.config import (
    MODBUS_TYPES,
    POSITION_SOURCES,
    Z_NAME,
    Latest,
    ModbusInputConfig,
    OpcUaInputConfig,
    PositionConfig,
    TemperaturesConfig,
)
from fbgcomp.runtime.live_inputs.inputs import LinuxCncPositionReader, LiveInputs, LiveTemperatures
from fbgcomp.runtime.live_inputs.modbus_reader import ModbusReader, RegisterSpec, register_spec
from fbgcomp.runtime.live_inputs.opcua_reader import OpcUaReader

__all__ = [
    "MODBUS_TYPES",
    "POSITION_SOURCES",
    "Z_NAME",
    "Latest",
    "LinuxCncPositionReader",
    "LiveInputs",
    "LiveTemperatures",
    "ModbusInputConfig",
    "ModbusReader",
    "OpcUaInputConfig",
    "OpcUaReader",
    "PositionConfig",
    "RegisterSpec",
    "TemperaturesConfig",
    "register_spec",
]
