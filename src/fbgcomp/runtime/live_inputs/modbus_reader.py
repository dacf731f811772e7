"""Live inputs polled from a Modbus TCP device's holding registers (:class:`ModbusReader`)."""

from __future__ import annotations

import asyncio
import logging
import math
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING

from fbgcomp.errors import InputError
from fbgcomp.runtime.live_inputs.config import MODBUS_TYPES, Latest, ModbusInputConfig

if TYPE_CHECKING:
    from pymodbus.client import AsyncModbusTcpClient

log = logging.getLogger("fbgcomp.runtime.inputs")


@dataclass
class RegisterSpec:
    """Where one input is in the device's registers and how it becomes a value."""

    address: int
    type: str = "int16"
    scale: float = 1.0
    offset: float = 0.0

    @property
    def words(self) -> int:
        """How many 16-bit registers the value takes."""
        return MODBUS_TYPES[self.type][1]


def register_spec(name: str, spec, where: str) -> RegisterSpec:
    """The :class:`RegisterSpec` of input ``name`` from its configuration (an address, or a
    table ``{address, type, scale, offset}``); InputError naming ``where`` otherwise.
    """
    col = f"field {where}.registers.{name}"
    if isinstance(spec, int) and not isinstance(spec, bool):
        spec = {"address": spec}
    if not isinstance(spec, dict):
        raise InputError("expected a table {address = N, type = ..., scale = ...}", column=col)
    unknown = set(spec) - {"address", "type", "scale", "offset"}
    if unknown:
        raise InputError(
            f"unknown key(s) {', '.join(sorted(unknown))} (known: address, type, scale, offset)", column=col
        )
    addr = spec.get("address")
    if not isinstance(addr, int) or isinstance(addr, bool) or not 0 <= addr <= 65535:
        raise InputError(f"address: expected 0..65535, got {addr!r}", column=col)
    typ = spec.get("type", "int16")
    if typ not in MODBUS_TYPES:
        raise InputError(f"type: expected one of {', '.join(MODBUS_TYPES)}, got {typ!r}", column=col)
    nums = {}
    for k, default in (("scale", 1.0), ("offset", 0.0)):
        v = spec.get(k, default)
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            raise InputError(f"{k}: expected a number, got {v!r}", column=col)
        nums[k] = float(v)
    return RegisterSpec(addr, typ, nums["scale"], nums["offset"])


class ModbusReader:
    """Polls holding registers of one Modbus TCP server (pymodbus asyncio client)."""

    kind = "modbus"

    def __init__(self, config: ModbusInputConfig, where: str = "temperatures.modbus"):
        self.config = config
        if not 0 <= int(config.unit) <= 247:
            raise InputError(f"expected 0..247, got {config.unit}", column=f"field {where}.unit")
        if not 0 < int(config.port) < 65536:
            raise InputError(f"expected 1..65535, got {config.port}", column=f"field {where}.port")
        if not config.poll_s > 0 or not config.stale_s > 0:
            raise InputError("poll_s and stale_s must be positive", column=f"field {where}.poll_s")
        self.specs = {name: register_spec(name, spec, where) for name, spec in config.registers.items()}
        self.values = {n: Latest() for n in self.specs}
        self.status = "connecting"
        self._client: AsyncModbusTcpClient | None = None

    @staticmethod
    def decode(registers, spec: RegisterSpec) -> float:
        """Raw registers (high word first) -> value * scale + offset."""
        from pymodbus.client import AsyncModbusTcpClient  # noqa: PLC0415 - optional extra: pymodbus

        dt = getattr(AsyncModbusTcpClient.DATATYPE, MODBUS_TYPES[spec.type][0])
        raw = AsyncModbusTcpClient.convert_from_registers(list(registers), dt, word_order="big")
        assert isinstance(raw, (int, float)), "MODBUS_TYPES are single numbers"
        return float(raw) * spec.scale + spec.offset

    async def run(self) -> None:
        """Poll the registers every ``poll_s`` until cancelled, reconnecting as needed."""
        from pymodbus.client import AsyncModbusTcpClient  # noqa: PLC0415 - optional extra: pymodbus

        cfg = self.config
        client = AsyncModbusTcpClient(
            cfg.host,
            port=int(cfg.port),
            timeout=cfg.timeout_s,
            retries=0,
            reconnect_delay=0.2,
            reconnect_delay_max=5.0,
        )
        self._client = client
        try:
            while True:
                t_next = time.monotonic() + cfg.poll_s
                try:
                    if not client.connected:
                        await client.connect()
                    if client.connected:
                        await self._poll(client)
                        self.status = "connected"
                    else:
                        self.status = "connecting"
                except asyncio.CancelledError:
                    raise
                except Exception as exc:  # lost link, timeout, exception response
                    self.status = f"error ({type(exc).__name__})"
                    log.debug("Modbus inputs %s:%s: %s", cfg.host, cfg.port, exc)
                await asyncio.sleep(max(0.0, t_next - time.monotonic()))
        finally:
            client.close()

    async def _poll(self, client) -> None:
        for name, spec in self.specs.items():
            rr = await client.read_holding_registers(
                spec.address, count=spec.words, device_id=int(self.config.unit)
            )
            if rr.isError():
                self.values[name].set(math.nan)  # an exception response: no value
                self.status = f"exception response for {name}"
                continue
            self.values[name].set(self.decode(rr.registers, spec))

    async def close(self) -> None:
        """Close the connection."""
        if self._client is not None:
            self._client.close()
