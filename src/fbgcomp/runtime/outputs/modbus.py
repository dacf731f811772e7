"""``[modbus]`` in serve: the correction as Modbus TCP holding registers, for a CNC's PLC.

A Modbus TCP server (pymodbus, its own thread and asyncio loop: a slow or stuck client never
holds up the compensation loop) publishes per axis the offset + Z slope form of
:mod:`fbgcomp.runtime.outputs.cnc_form` - the form Sinumerik, Heidenhain and Fanuc thermal compensation
take from the PLC (docs/cnc-integration.md) - beside the plain dx/dy/dz, with its own rate limit
and maximum, the health code, the output switch, a sequence counter (a PLC that sees it stop
knows the value is stale) and per axis the flags saying why the value was held back.

The registers are read-only: any write (function codes 5, 6, 15, 16, 22, 23) is refused with
exception 01 ILLEGAL FUNCTION - nothing on the network may change what the CNC applies. Every
read of one request comes from one published sample (the block is filled under a lock), so a
PLC reading the table in one request never mixes two samples.

Register table (0-based protocol addresses; a PLC's "4x" numbering adds 40001). 32-bit values
take two registers, high word first (big-endian word and byte order, "ABCD"), two's complement.

====  =====  ==========================  =======================================================
addr  words  name                        meaning, scale
====  =====  ==========================  =======================================================
0     1      layout                      1 (this table)
1     1      health                      0 OK, 1 DEGRADED, 2 ALARM, 3 ZEROING
2     1      enabled                     1 when the output switch is on
3     1      apply                       1 when the offset/slope may be applied (health OK or
                                         DEGRADED, output on); 0: hold the CNC's own value and
                                         let these registers ramp it to 0
4     2      sequence                    uint32, +1 per published sample (wraps)
6     2      z_ref                       int32, 0.001 mm: reference position of the slope
8     2×3    offset X, Y, Z              int32, 0.1 µm: correction at z_ref (rate/max limited)
14    2×3    slope X, Y, Z               int32, 0.01 µm/m: d correction / dZ at z_ref (limited)
20    1×3    flags X, Y, Z               bits 0-4 the pipeline's (SHRUNK 1, CLAMPED 2,
                                         LOAD_REFUSED 4, RATE_LIMITED 8, MAX_LIMITED 16);
                                         256 offset rate-limited here, 512 offset max-limited
                                         here, 1024 slope rate-limited, 2048 slope max-limited
23    2×3    correction X, Y, Z          int32, 0.1 µm: the pipeline's published dx, dy, dz
====  =====  ==========================  =======================================================
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import threading
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from fbgcomp.errors import InputError
from fbgcomp.runtime.outputs.cnc_form import limit_toward
from fbgcomp.runtime.pipeline import HEALTH_NAMES, per_axis

if TYPE_CHECKING:
    from pymodbus.server import ModbusTcpServer

log = logging.getLogger("fbgcomp.runtime.outputs.modbus")

LAYOUT_VERSION = 1
REG_LAYOUT, REG_HEALTH, REG_ENABLED, REG_APPLY, REG_SEQUENCE, REG_Z_REF = 0, 1, 2, 3, 4, 6
REG_OFFSET, REG_SLOPE, REG_FLAGS, REG_CORRECTION = 8, 14, 20, 23
N_REGISTERS = 29
OFFSET_UM_PER_COUNT = 0.1
SLOPE_UM_PER_M_PER_COUNT = 0.01
Z_MM_PER_COUNT = 0.001
CORRECTION_UM_PER_COUNT = 0.1
FLAG_OFFSET_RATE, FLAG_OFFSET_MAX, FLAG_SLOPE_RATE, FLAG_SLOPE_MAX = 256, 512, 1024, 2048
_INT32 = (-(2**31), 2**31 - 1)


@dataclass
class ModbusConfig:
    """``[modbus]``: the Modbus TCP server a PLC reads the offset + Z slope form from."""

    listen: str = ""  # "HOST:PORT", e.g. "127.0.0.1:5020"; "" = off
    unit_id: int = 1  # Modbus unit (device) id answered; 0 = any
    # Limits of the published offset and slope, per axis (dx, dy, dz) or one for all; 0 = off.
    # Thermal drift is µm per minute; these still follow it, and keep a load step or a model
    # switch from reaching the CNC as a jump (docs/cnc-integration.md: the defaults).
    offset_rate_um_per_s: tuple = (20.0, 20.0, 20.0)
    max_offset_um: tuple = (200.0, 200.0, 200.0)
    slope_rate_um_per_m_per_s: tuple = (20.0, 20.0, 20.0)
    max_slope_um_per_m: tuple = (200.0, 200.0, 200.0)


def parse_listen(listen: str) -> tuple[str, int]:
    """``HOST:PORT`` (``[::1]:5020`` for IPv6) -> (host, port); both are required."""
    host, sep, port = listen.rpartition(":")
    if not sep or not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise InputError(f"expected HOST:PORT, got {listen!r}", column="field modbus.listen")
    return host.strip("[]"), int(port)


def int32_words(value: float, per_count: float) -> list[int]:
    """A value as a saturated int32 count of ``per_count``, in two 16-bit words, high first."""
    count = int(np.clip(np.rint(value / per_count), *_INT32)) if np.isfinite(value) else 0
    u = count & 0xFFFFFFFF
    return [u >> 16, u & 0xFFFF]


def decode_int32(high: int, low: int) -> int:
    """Two registers (high word first) -> the signed 32-bit count (the PLC's side)."""
    u = (high << 16) | low
    return u - (1 << 32) if u & 0x80000000 else u


class ModbusOutput:
    """The Modbus TCP server of one serve. ``publish`` from the service loop (never blocks)."""

    def __init__(self, config: ModbusConfig, clock=time.monotonic):
        self.config = config
        self.host, self.port = parse_listen(config.listen)
        if not 0 <= int(config.unit_id) <= 247:
            raise InputError(f"expected 0..247, got {config.unit_id}", column="field modbus.unit_id")
        try:
            self.offset_rate = per_axis(config.offset_rate_um_per_s)
            self.max_offset = per_axis(config.max_offset_um)
            self.slope_rate = per_axis(config.slope_rate_um_per_m_per_s)
            self.max_slope = per_axis(config.max_slope_um_per_m)
        except ValueError as exc:
            raise InputError(str(exc), column="table modbus") from exc
        self._clock = clock
        self._lock = threading.Lock()
        self.sequence = 0
        self.offset_um = np.zeros(3)
        self.slope_um_per_m = np.zeros(3)
        self._t_last: float | None = None
        self._registers = [0] * N_REGISTERS
        self._registers[REG_LAYOUT] = LAYOUT_VERSION
        self._registers[REG_HEALTH] = HEALTH_NAMES.index("ZEROING")
        self.reads = 0
        self.writes_refused = 0
        self._thread: threading.Thread | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._server: ModbusTcpServer | None = None

    # -- the PLC's side: pymodbus server in its own thread
    def start(self, timeout_s: float = 10.0) -> None:
        """Serve from a thread of its own; InputError if the address cannot be bound within
        ``timeout_s``.
        """
        started = threading.Event()
        failure: list[BaseException] = []

        def run():
            loop = asyncio.new_event_loop()
            self._loop = loop
            try:
                loop.run_until_complete(self._serve(started, failure))
            finally:
                loop.close()

        self._thread = threading.Thread(target=run, name="fbgcomp-modbus", daemon=True)
        self._thread.start()
        if not started.wait(timeout_s):
            raise InputError("Modbus server did not start", column="field modbus.listen")
        if failure:
            raise InputError(
                f"cannot listen on {self.host}:{self.port}: {failure[0]}", column="field modbus.listen"
            )
        log.info(
            "Modbus TCP on %s:%d (unit %d, %d holding registers, read-only)",
            self.host,
            self.port,
            self.config.unit_id,
            N_REGISTERS,
        )

    async def _serve(self, started: threading.Event, failure: list) -> None:
        from pymodbus.server import ModbusTcpServer  # noqa: PLC0415 - optional extra: pymodbus
        from pymodbus.simulator import DataType, SimData, SimDevice  # noqa: PLC0415 - optional extra: pymodbus

        device = SimDevice(
            id=int(self.config.unit_id),
            action=self._action,
            simdata=[SimData(0, count=N_REGISTERS, values=0, datatype=DataType.REGISTERS)],
        )
        try:
            server = self._server = ModbusTcpServer(
                device, address=(self.host, self.port), ignore_missing_devices=True
            )
            await server.serve_forever(background=True)
        except BaseException as exc:  # a busy port: reported by start()
            failure.append(exc)
            started.set()
            return
        started.set()
        await server.serving

    async def _action(self, function_code, start_address, address, count, registers, set_values):
        """Pymodbus calls this on every access: writes refused, reads get the newest sample."""
        from pymodbus.constants import ExcCodes  # noqa: PLC0415 - optional extra: pymodbus

        if set_values is not None:
            self.writes_refused += 1
            return ExcCodes.ILLEGAL_FUNCTION
        with self._lock:
            registers[:N_REGISTERS] = self._registers
        self.reads += 1
        return None

    def stop(self) -> None:
        """Publish the switch-off (apply 0, ALARM) for a last reader, then close the server."""
        with self._lock:
            self._registers[REG_APPLY] = 0
            self._registers[REG_HEALTH] = HEALTH_NAMES.index("ALARM")
        loop, server = self._loop, self._server
        if loop is not None and server is not None and loop.is_running():
            fut = asyncio.run_coroutine_threadsafe(server.shutdown(), loop)
            with contextlib.suppress(Exception):  # already closing
                fut.result(5)
        if self._thread is not None:
            self._thread.join(5)

    # -- the compensator's side
    def publish(self, snapshot, enabled: bool, slope_um_per_m, z_ref_mm: float | None) -> None:
        """The newest sample: limit the offset and slope, encode, store (never blocks)."""
        now = self._clock()
        dt = 0.0 if self._t_last is None else now - self._t_last
        self._t_last = now
        apply = bool(enabled) and snapshot.health in ("OK", "DEGRADED")
        correction = np.asarray(snapshot.correction_um, float)
        slope_target = np.asarray(slope_um_per_m, float) if apply else np.zeros(3)
        self.offset_um, o_rate, o_max = limit_toward(
            self.offset_um, correction, dt, self.offset_rate, self.max_offset
        )
        self.slope_um_per_m, s_rate, s_max = limit_toward(
            self.slope_um_per_m, slope_target, dt, self.slope_rate, self.max_slope
        )
        flags = (
            (np.asarray(snapshot.output_flags, int) & 0xFF)
            | np.where(o_rate, FLAG_OFFSET_RATE, 0)
            | np.where(o_max, FLAG_OFFSET_MAX, 0)
            | np.where(s_rate, FLAG_SLOPE_RATE, 0)
            | np.where(s_max, FLAG_SLOPE_MAX, 0)
        )
        regs = [0] * N_REGISTERS
        regs[REG_LAYOUT] = LAYOUT_VERSION
        regs[REG_HEALTH] = HEALTH_NAMES.index(snapshot.health)
        regs[REG_ENABLED] = int(bool(enabled))
        regs[REG_APPLY] = int(apply)
        regs[REG_Z_REF : REG_Z_REF + 2] = int32_words(0.0 if z_ref_mm is None else z_ref_mm, Z_MM_PER_COUNT)
        for a in range(3):
            regs[REG_OFFSET + 2 * a : REG_OFFSET + 2 * a + 2] = int32_words(
                self.offset_um[a], OFFSET_UM_PER_COUNT
            )
            regs[REG_SLOPE + 2 * a : REG_SLOPE + 2 * a + 2] = int32_words(
                self.slope_um_per_m[a], SLOPE_UM_PER_M_PER_COUNT
            )
            regs[REG_FLAGS + a] = int(flags[a]) & 0xFFFF
            regs[REG_CORRECTION + 2 * a : REG_CORRECTION + 2 * a + 2] = int32_words(
                correction[a], CORRECTION_UM_PER_COUNT
            )
        with self._lock:
            self.sequence = (self.sequence + 1) & 0xFFFFFFFF
            regs[REG_SEQUENCE : REG_SEQUENCE + 2] = [self.sequence >> 16, self.sequence & 0xFFFF]
            self._registers = regs


def open_modbus_output(config: ModbusConfig) -> ModbusOutput | None:
    """The Modbus output when ``config.listen`` is set (None otherwise), not yet started."""
    if not config.listen:
        return None
    return ModbusOutput(config)
