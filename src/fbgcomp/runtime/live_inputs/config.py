"""The live inputs' configuration (``[temperatures.opcua]``, ``[temperatures.modbus]``,
``[position]``) and :class:`Latest`, the newest value of one input."""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

MODBUS_TYPES = {
    "int16": ("INT16", 1),
    "uint16": ("UINT16", 1),
    "int32": ("INT32", 2),
    "uint32": ("UINT32", 2),
    "float32": ("FLOAT32", 2),
}
POSITION_SOURCES = ("", "linuxcnc", "opcua")
Z_NAME = "Z"


@dataclass
class OpcUaInputConfig:
    """``[temperatures.opcua]``: an OPC UA server the probe temperatures are read from."""

    endpoint: str = ""  # opc.tcp://HOST:PORT[/path]; "" = off
    security: str = "None"  # "None" or "Basic256Sha256"
    mode: str = "SignAndEncrypt"  # "SignAndEncrypt" or "Sign" (with Basic256Sha256)
    certificate: str = ""  # client certificate (DER/PEM), created if absent
    private_key: str = ""  # its private key (PEM), created if absent
    server_certificate: str = ""  # optional: the server's certificate to pin
    user: str = ""  # optional user; password from env FBGCOMP_INPUT_PASSWORD
    nodes: dict = field(default_factory=dict)  # probe -> node id ("ns=2;s=Probes.T_bulk")
    stale_s: float = 30.0
    sampling_ms: float = 0.0  # server sampling of the monitored items (0: fastest)
    timeout_s: float = 4.0


@dataclass
class ModbusInputConfig:
    """``[temperatures.modbus]``: a Modbus TCP device the probe temperatures are polled from."""

    host: str = ""  # "" = off
    port: int = 502
    unit: int = 1
    registers: dict = field(default_factory=dict)  # probe -> {address, type, scale, offset}
    poll_s: float = 1.0
    stale_s: float = 30.0
    timeout_s: float = 1.0


@dataclass
class TemperaturesConfig:
    """``[temperatures]``: the live sources of probe temperatures (docs/runtime.md)."""

    opcua: OpcUaInputConfig = field(default_factory=OpcUaInputConfig)
    modbus: ModbusInputConfig = field(default_factory=ModbusInputConfig)


@dataclass
class PositionConfig:
    """``[position]``: where the live Z position comes from (docs/runtime.md)."""

    source: str = ""  # "" (none: the model's own Z), "linuxcnc" or "opcua"
    endpoint: str = ""  # opcua: default [temperatures.opcua] endpoint
    node: str = ""  # opcua: node id of the Z position
    scale: float = 1.0  # opcua: mm per unit of the node's value
    stale_s: float = 1.0
    # Z is rounded to this before it reaches the model: a kinematic chain is compiled per Z
    # (~3.5 ms, kept), and its Z dependence is smooth (well below 0.01 µm per mm on the ram)
    resolution_mm: float = 1.0


class Latest:
    """The newest value of one input and the monotonic time it arrived (NaN: bad / none)."""

    __slots__ = ("received_s", "value")

    def __init__(self) -> None:
        self.value = math.nan
        self.received_s: float | None = None

    def set(self, value: float, now: float | None = None) -> None:
        """Store a new value (NaN when it is not a number), received at ``now`` (monotonic s)."""
        try:
            self.value = float(value)
        except (TypeError, ValueError):
            self.value = math.nan
        self.received_s = time.monotonic() if now is None else now
