"""The live inputs together (:class:`LiveInputs`), the LinuxCNC Z position, and serve's
temperature source over them (:class:`LiveTemperatures`)."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import time

import numpy as np

from fbgcomp.errors import InputError
from fbgcomp.runtime.live_inputs.config import (
    POSITION_SOURCES,
    Z_NAME,
    Latest,
    OpcUaInputConfig,
    PositionConfig,
    TemperaturesConfig,
)
from fbgcomp.runtime.live_inputs.modbus_reader import ModbusReader
from fbgcomp.runtime.live_inputs.opcua_reader import OpcUaReader

log = logging.getLogger("fbgcomp.runtime.inputs")


class LinuxCncPositionReader:
    """The Z position the HAL component sends back (:meth:`LinuxCncOutput.position`)."""

    kind = "linuxcnc"

    def __init__(self, output):
        self.output = output
        self.values = {Z_NAME: Latest()}
        self.status = "waiting"

    def refresh(self) -> None:
        """Take the newest position from the output (NaN while the machine is not homed)."""
        got = self.output.position()
        if got is None:
            return
        z_mm, received_s, homed = got
        lat = self.values[Z_NAME]
        lat.value = z_mm if homed else math.nan
        lat.received_s = received_s
        self.status = "homed" if homed else "not homed"

    async def run(self) -> None:
        """Nothing to run: the output's own thread receives the positions."""
        await asyncio.Event().wait()  # the output's thread receives; nothing to run here

    async def close(self) -> None:
        """Nothing to close (the output owns the socket)."""
        pass


LiveReader = OpcUaReader | ModbusReader | LinuxCncPositionReader


# ------------------------------------------------------------------------------ together
class LiveInputs:
    """The configured readers, the probes and Z they supply, and their freshness."""

    def __init__(
        self,
        temperatures: TemperaturesConfig,
        position: PositionConfig,
        model_probes: list[str],
        cnc_output=None,
    ):
        self.readers: list[LiveReader] = []
        self.probe_reader: dict[str, tuple[LiveReader, float]] = {}  # probe -> (reader, stale_s)
        self.z_reader: tuple[LiveReader, float] | None = None  # (reader, stale_s)
        self._tasks: list[asyncio.Task] = []
        self._stale: tuple = ()
        opc = temperatures.opcua
        mb = temperatures.modbus
        by_endpoint: dict[str, OpcUaReader] = {}
        if opc.endpoint or opc.nodes:
            if not opc.endpoint:
                raise InputError(
                    "nodes given without an endpoint", column="field temperatures.opcua.endpoint"
                )
            _positive(opc.stale_s, "temperatures.opcua.stale_s")
            opc_reader = OpcUaReader(opc.endpoint, {k: str(v) for k, v in opc.nodes.items()}, opc)
            by_endpoint[opc.endpoint] = opc_reader
            self.readers.append(opc_reader)
            self._add_probes(opc_reader, opc.nodes, opc.stale_s, model_probes, "temperatures.opcua.nodes")
        if mb.host or mb.registers:
            if not mb.host:
                raise InputError("registers given without a host", column="field temperatures.modbus.host")
            mb_reader = ModbusReader(mb)
            self.readers.append(mb_reader)
            self._add_probes(
                mb_reader, mb.registers, mb.stale_s, model_probes, "temperatures.modbus.registers"
            )
        if position.source not in POSITION_SOURCES:
            raise InputError(
                f"expected linuxcnc or opcua, got {position.source!r}", column="field position.source"
            )
        self.z_resolution_mm = float(position.resolution_mm)
        if position.source:
            _positive(position.stale_s, "position.stale_s")
        if position.source == "opcua":
            endpoint = position.endpoint or opc.endpoint
            if not endpoint or not position.node:
                raise InputError(
                    "position over OPC UA needs node (and endpoint, or the one of [temperatures.opcua])",
                    column="field position.node",
                )
            z_opc = by_endpoint.get(endpoint)
            if z_opc is None:
                z_opc = OpcUaReader(endpoint, {}, OpcUaInputConfig(endpoint=endpoint), where="position")
                by_endpoint[endpoint] = z_opc
                self.readers.append(z_opc)
            try:
                from asyncua import ua  # noqa: PLC0415 - optional extra: asyncua (imported only when used)

                ua.NodeId.from_string(position.node)
            except Exception as exc:
                raise InputError(
                    f"not an OPC UA node id: {position.node!r}", column="field position.node"
                ) from exc
            z_opc.add(Z_NAME, position.node, position.scale)
            self.z_reader = (z_opc, position.stale_s)
        elif position.source == "linuxcnc":
            if cnc_output is None:
                raise InputError(
                    "position from LinuxCNC needs the LinuxCNC output (--cnc linuxcnc)",
                    column="field position.source",
                )
            z_cnc = LinuxCncPositionReader(cnc_output)
            self.readers.append(z_cnc)
            self.z_reader = (z_cnc, position.stale_s)

    def _add_probes(self, reader, names, stale_s, model_probes, where) -> None:
        for p in names:
            if p not in model_probes:
                raise InputError(
                    f"{p} is not a probe the model reads from a thermometer "
                    f"(those: {', '.join(model_probes) or 'none'})",
                    column=f"field {where}.{p}",
                )
            if p in self.probe_reader:
                raise InputError(
                    f"probe {p} has two live sources ({self.probe_reader[p][0].kind} and {reader.kind})",
                    column=f"field {where}.{p}",
                )
            self.probe_reader[p] = (reader, float(stale_s))

    @property
    def probes(self) -> list[str]:
        """The probes a live input supplies."""
        return list(self.probe_reader)

    @property
    def has_position(self) -> bool:
        """Whether a live Z position is configured."""
        return self.z_reader is not None

    def __bool__(self) -> bool:
        return bool(self.readers)

    def start(self) -> None:
        """The readers as tasks on the running loop (they never end by themselves)."""
        for r in self.readers:
            self._tasks.append(asyncio.create_task(self._guard(r)))

    @staticmethod
    async def _guard(reader) -> None:
        try:
            await reader.run()
        except asyncio.CancelledError:
            raise
        except Exception:  # a reader's bug must not end serve: its inputs just go stale
            log.exception("%s input reader stopped", reader.kind)
            reader.status = "stopped (error)"

    async def close(self) -> None:
        """Cancel the readers' tasks and close their connections."""
        for t in self._tasks:
            t.cancel()
        for t in self._tasks:
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await t
        for r in self.readers:
            with contextlib.suppress(Exception):
                await r.close()

    # -- the frame loop's side (cheap: a handful of numbers)
    def _fresh(self, reader, name: str, stale_s: float, now: float) -> float:
        lat = reader.values[name]
        if lat.received_s is None or now - lat.received_s > stale_s:
            return math.nan
        return lat.value

    def temperatures_C(self, now: float | None = None) -> dict[str, float]:
        """Latest value per live probe, °C; NaN when stale, missing or bad."""
        now = time.monotonic() if now is None else now
        return {p: self._fresh(r, p, s, now) for p, (r, s) in self.probe_reader.items()}

    def z_mm(self, now: float | None = None) -> float | None:
        """Latest Z position, mm; NaN when stale or missing; None without a position source."""
        if self.z_reader is None:
            return None
        r, stale_s = self.z_reader
        if isinstance(r, LinuxCncPositionReader):
            r.refresh()
        z = self._fresh(r, Z_NAME, stale_s, time.monotonic() if now is None else now)
        res = self.z_resolution_mm
        return round(z / res) * res if res > 0 and math.isfinite(z) else z

    def check(self, temperatures: dict, z_mm) -> str:
        """The status line for these values (``inputs OK`` or ``stale: T_bulk (opcua), ...``);
        a change of the stale set is logged once."""
        names = [p for p, v in temperatures.items() if not math.isfinite(v)]
        if z_mm is not None and not math.isfinite(z_mm):
            names.append(Z_NAME)
        stale = tuple(names)
        if stale != self._stale:
            if stale:
                log.warning("live inputs missing or stale: %s", self._describe(stale))
            else:
                log.warning("live inputs fresh again")
            self._stale = stale
        return "inputs OK" if not stale else f"stale: {self._describe(stale)}"

    def _describe(self, names) -> str:
        now = time.monotonic()
        out = []
        for n in names:
            if n == Z_NAME:
                assert self.z_reader is not None, "Z is stale only with a position source"
                r = self.z_reader[0]
            else:
                r = self.probe_reader[n][0]
            lat = r.values[n]
            age = "never" if lat.received_s is None else f"{now - lat.received_s:.1f} s"
            out.append(f"{n} ({r.kind}, {age})")
        return ", ".join(out)


def _positive(value, where: str) -> None:
    if not (isinstance(value, (int, float)) and value > 0):
        raise InputError(f"expected a number > 0, got {value!r}", column=f"field {where}")


class LiveTemperatures:
    """The temperature source of serve with live inputs: the live probes' latest values (the
    same for every frame of a batch: they change over seconds, a batch lasts milliseconds),
    the others from ``fallback`` (``--temperatures``), in ``probe_names`` order."""

    def __init__(self, probe_names: list[str], live: LiveInputs, fallback=None):
        self.probe_names = list(probe_names)
        self.live = live
        self.fallback = fallback
        self._live_cols = [i for i, p in enumerate(self.probe_names) if p in live.probe_reader]
        self._live_names = [self.probe_names[i] for i in self._live_cols]
        self._other_cols = [i for i, p in enumerate(self.probe_names) if p not in live.probe_reader]
        self.last_live: dict = {}

    @property
    def all_live(self) -> bool:
        """Every probe comes from a live input (none from ``--temperatures``): the temperatures
        go on arriving when the interrogator's link is lost."""
        return bool(self._live_cols) and not self._other_cols

    def latest(self, time_s: np.ndarray) -> np.ndarray:
        """The temperatures (n, P) for frames at ``time_s``: live probes their newest value
        (kept in ``last_live``), the others from ``fallback``.
        """
        n = np.asarray(time_s).size
        out = np.empty((n, len(self.probe_names)))
        if self._other_cols:
            out[:, self._other_cols] = self.fallback.latest(time_s)
        vals = self.live.temperatures_C()
        self.last_live = vals
        if self._live_cols:
            out[:, self._live_cols] = [vals[p] for p in self._live_names]
        return out
