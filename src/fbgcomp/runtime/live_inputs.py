"""Live inputs of ``serve``: probe temperatures over OPC UA and Modbus TCP, the Z-axis position
from LinuxCNC or OPC UA (docs/runtime.md, "Live inputs").

A real machine's probes are read by its PLC or a logger; the axis position is the CNC's. Each
reader runs as an asyncio task beside the frame loop and never blocks it: it only keeps, per
input, the latest value and the monotonic time it was received. At every batch the service
asks for the latest temperatures and Z; a value older than its ``stale_s`` (or never received,
or received with a bad status) is *missing*: NaN, which the pipeline handles as it handles a
missing temperature - no usable model, health ALARM, the last correction held and ramped to
zero (the do-no-harm fallback). A missing Z matters only to a model whose prediction depends on
Z (kinematic, hybrid, calibrated); the others ignore it. :attr:`LiveInputs.status` names the
stale inputs (OPC UA ``SourceStatus``, the log).

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

from __future__ import annotations

import asyncio
import logging
import math
import os
import time
from dataclasses import dataclass, field

import numpy as np

from fbgcomp.errors import InputError

log = logging.getLogger("fbgcomp.runtime.inputs")

MODBUS_TYPES = {"int16": ("INT16", 1), "uint16": ("UINT16", 1), "int32": ("INT32", 2),
                "uint32": ("UINT32", 2), "float32": ("FLOAT32", 2)}
POSITION_SOURCES = ("", "linuxcnc", "opcua")
Z_NAME = "Z"


@dataclass
class OpcUaInputConfig:
    """``[temperatures.opcua]``: an OPC UA server the probe temperatures are read from."""

    endpoint: str = ""                # opc.tcp://HOST:PORT[/path]; "" = off
    security: str = "None"            # "None" or "Basic256Sha256"
    mode: str = "SignAndEncrypt"      # "SignAndEncrypt" or "Sign" (with Basic256Sha256)
    certificate: str = ""             # client certificate (DER/PEM), created if absent
    private_key: str = ""             # its private key (PEM), created if absent
    server_certificate: str = ""      # optional: the server's certificate to pin
    user: str = ""                    # optional user; password from env FBGCOMP_INPUT_PASSWORD
    nodes: dict = field(default_factory=dict)   # probe -> node id ("ns=2;s=Probes.T_bulk")
    stale_s: float = 30.0
    sampling_ms: float = 0.0          # server sampling of the monitored items (0: fastest)
    timeout_s: float = 4.0


@dataclass
class ModbusInputConfig:
    """``[temperatures.modbus]``: a Modbus TCP device the probe temperatures are polled from."""

    host: str = ""                    # "" = off
    port: int = 502
    unit: int = 1
    registers: dict = field(default_factory=dict)   # probe -> {address, type, scale, offset}
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

    source: str = ""                  # "" (none: the model's own Z), "linuxcnc" or "opcua"
    endpoint: str = ""                # opcua: default [temperatures.opcua] endpoint
    node: str = ""                    # opcua: node id of the Z position
    scale: float = 1.0                # opcua: mm per unit of the node's value
    stale_s: float = 1.0
    # Z is rounded to this before it reaches the model: a kinematic chain is compiled per Z
    # (~3.5 ms, kept), and its Z dependence is smooth (well below 0.01 µm per mm on the ram)
    resolution_mm: float = 1.0


class Latest:
    """The newest value of one input and the monotonic time it arrived (NaN: bad / none)."""

    __slots__ = ("value", "received_s")

    def __init__(self):
        self.value = math.nan
        self.received_s: float | None = None

    def set(self, value: float, now: float | None = None) -> None:
        """Store a new value (NaN when it is not a number), received at ``now`` (monotonic s)."""
        try:
            self.value = float(value)
        except (TypeError, ValueError):
            self.value = math.nan
        self.received_s = time.monotonic() if now is None else now


# ------------------------------------------------------------------------------ OPC UA client
class OpcUaReader:
    """One asyncua client, subscribed to ``nodes`` (name -> node id) of one endpoint."""

    kind = "opcua"

    def __init__(self, endpoint: str, nodes: dict, config: OpcUaInputConfig | None = None,
                 where: str = "temperatures.opcua"):
        self.endpoint = endpoint
        self.config = config or OpcUaInputConfig(endpoint=endpoint)
        self.where = where
        self.nodes = dict(nodes)
        self.values = {n: Latest() for n in self.nodes}
        self.scale = {n: 1.0 for n in self.nodes}
        self.status = "connecting"
        self._client = None
        if not endpoint.startswith("opc.tcp://"):
            raise InputError(f"expected opc.tcp://HOST:PORT, got {endpoint!r}",
                             column=f"field {where}.endpoint")
        if self.config.security not in ("None", "Basic256Sha256"):
            raise InputError(f"expected None or Basic256Sha256, got {self.config.security!r}",
                             column=f"field {where}.security")
        from asyncua import ua  # the runtime extra (asyncua): imported only when used
        for name, nid in self.nodes.items():
            try:
                ua.NodeId.from_string(str(nid))
            except Exception:
                raise InputError(f"not an OPC UA node id: {nid!r} (e.g. ns=2;s=Probes.T_bulk)",
                                 column=f"field {where}.nodes.{name}")

    def add(self, name: str, node: str, scale: float = 1.0) -> None:
        """Read input ``name`` from node id ``node``, multiplied by ``scale``."""
        self.nodes[name] = node
        self.values[name] = Latest()
        self.scale[name] = float(scale)

    async def _connect(self):
        from asyncua import Client, ua  # the runtime extra (asyncua): imported only when used

        cfg = self.config
        client = Client(self.endpoint, timeout=cfg.timeout_s, watchdog_intervall=1.0,
                        auto_reconnect=True, reconnect_max_delay=5.0)
        client.application_uri = "urn:fbgcomp:serve:inputs"
        client.session_timeout = 600_000     # ms: what asyncua servers grant at most
        if cfg.security == "Basic256Sha256":
            if not cfg.certificate or not cfg.private_key:
                raise InputError("Basic256Sha256 needs certificate and private_key paths",
                                 column=f"field {self.where}.certificate")
            if not (os.path.exists(cfg.certificate) and os.path.exists(cfg.private_key)):
                await client.setup_self_signed_certificate(cfg.private_key, cfg.certificate)
            parts = ["Basic256Sha256", cfg.mode, cfg.certificate, cfg.private_key]
            if cfg.server_certificate:
                parts.append(cfg.server_certificate)
            await client.set_security_string(",".join(parts))
        if cfg.user:
            client.set_user(cfg.user)
            client.set_password(os.environ.get("FBGCOMP_INPUT_PASSWORD", ""))
        reader = self

        async def lost(exc):
            reader.status = f"reconnecting ({type(exc).__name__})"

        client.connection_lost_callback = lost
        await client.connect()

        class Handler:
            def datachange_notification(self, node, val, data):
                name = names.get(node.nodeid)
                if name is None:
                    return
                reader.status = "connected"
                dv = data.monitored_item.Value
                good = dv is None or dv.StatusCode is None or dv.StatusCode.is_good()
                reader.values[name].set(val * reader.scale[name] if good and val is not None
                                        else math.nan)

            def status_change_notification(self, status):
                reader.status = f"subscription status {status}"

        names = {client.get_node(nid).nodeid: name for name, nid in self.nodes.items()}
        sub = await client.create_subscription(100, Handler())
        # StatusValueTimestamp: a rewritten steady value (new timestamp) is fresh, not stale
        flt = ua.DataChangeFilter(Trigger=ua.DataChangeTrigger.StatusValueTimestamp)
        handles = await sub._subscribe([client.get_node(nid) for nid in self.nodes.values()],
                                       mfilter=flt, queuesize=1,
                                       sampling_interval=float(cfg.sampling_ms))
        for (name, nid), h in zip(self.nodes.items(), handles):
            if isinstance(h, ua.StatusCode):
                log.warning("OPC UA input %s: cannot subscribe to %s (%s)", name, nid, h)
        return client

    async def run(self) -> None:
        """Connect (retrying with capped back-off) and keep the subscription until cancelled."""
        delay = 0.2
        while True:
            try:
                self._client = await self._connect()
                self.status = "connected"
                log.info("OPC UA inputs: %s on %s", ", ".join(self.nodes), self.endpoint)
                # asyncua's supervisor now watches the link, reconnects and re-creates the
                # subscription; until then the values simply stop arriving (and go stale)
                await asyncio.Event().wait()
            except asyncio.CancelledError:
                raise
            except InputError:
                raise
            except Exception as exc:   # refused, timed out, bad certificate: retry
                self.status = f"connecting ({type(exc).__name__})"
                log.warning("OPC UA inputs: %s: %s; retry in %.1f s", self.endpoint, exc, delay)
                await self._disconnect()
                await asyncio.sleep(delay)
                delay = min(delay * 2.0, 5.0)

    async def _disconnect(self) -> None:
        client, self._client = self._client, None
        if client is not None:
            try:
                await asyncio.wait_for(client.disconnect(), 2.0)
            except Exception:
                pass

    async def close(self) -> None:
        """Unsubscribe and disconnect."""
        await self._disconnect()


# ------------------------------------------------------------------------------ Modbus client
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
        raise InputError(f"unknown key(s) {', '.join(sorted(unknown))} (known: address, type, "
                         "scale, offset)", column=col)
    addr = spec.get("address")
    if not isinstance(addr, int) or isinstance(addr, bool) or not 0 <= addr <= 65535:
        raise InputError(f"address: expected 0..65535, got {addr!r}", column=col)
    typ = spec.get("type", "int16")
    if typ not in MODBUS_TYPES:
        raise InputError(f"type: expected one of {', '.join(MODBUS_TYPES)}, got {typ!r}",
                         column=col)
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
        self.specs = {name: register_spec(name, spec, where)
                      for name, spec in config.registers.items()}
        self.values = {n: Latest() for n in self.specs}
        self.status = "connecting"
        self._client = None

    @staticmethod
    def decode(registers, spec: RegisterSpec) -> float:
        """Raw registers (high word first) -> value * scale + offset."""
        # the runtime extra (pymodbus): imported only when used
        from pymodbus.client import AsyncModbusTcpClient

        dt = getattr(AsyncModbusTcpClient.DATATYPE, MODBUS_TYPES[spec.type][0])
        raw = AsyncModbusTcpClient.convert_from_registers(list(registers), dt, word_order="big")
        return float(raw) * spec.scale + spec.offset

    async def run(self) -> None:
        """Poll the registers every ``poll_s`` until cancelled, reconnecting as needed."""
        # the runtime extra (pymodbus): imported only when used
        from pymodbus.client import AsyncModbusTcpClient

        cfg = self.config
        client = AsyncModbusTcpClient(cfg.host, port=int(cfg.port), timeout=cfg.timeout_s,
                                      retries=0, reconnect_delay=0.2, reconnect_delay_max=5.0)
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
                except Exception as exc:   # lost link, timeout, exception response
                    self.status = f"error ({type(exc).__name__})"
                    log.debug("Modbus inputs %s:%s: %s", cfg.host, cfg.port, exc)
                await asyncio.sleep(max(0.0, t_next - time.monotonic()))
        finally:
            client.close()

    async def _poll(self, client) -> None:
        for name, spec in self.specs.items():
            rr = await client.read_holding_registers(spec.address, count=spec.words,
                                                     device_id=int(self.config.unit))
            if rr.isError():
                self.values[name].set(math.nan)   # an exception response: no value
                self.status = f"exception response for {name}"
                continue
            self.values[name].set(self.decode(rr.registers, spec))

    async def close(self) -> None:
        """Close the connection."""
        if self._client is not None:
            self._client.close()


# ------------------------------------------------------------------------------ LinuxCNC Z
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
        await asyncio.Event().wait()     # the output's thread receives; nothing to run here

    async def close(self) -> None:
        """Nothing to close (the output owns the socket)."""
        pass


# ------------------------------------------------------------------------------ together
class LiveInputs:
    """The configured readers, the probes and Z they supply, and their freshness."""

    def __init__(self, temperatures: TemperaturesConfig, position: PositionConfig,
                 model_probes: list[str], cnc_output=None):
        self.readers: list = []
        self.probe_reader: dict[str, tuple] = {}      # probe -> (reader, stale_s)
        self.z_reader: tuple | None = None
        self._tasks: list[asyncio.Task] = []
        self._stale: tuple = ()
        opc = temperatures.opcua
        mb = temperatures.modbus
        by_endpoint: dict[str, OpcUaReader] = {}
        if opc.endpoint or opc.nodes:
            if not opc.endpoint:
                raise InputError("nodes given without an endpoint",
                                 column="field temperatures.opcua.endpoint")
            _positive(opc.stale_s, "temperatures.opcua.stale_s")
            r = OpcUaReader(opc.endpoint, {k: str(v) for k, v in opc.nodes.items()}, opc)
            by_endpoint[opc.endpoint] = r
            self.readers.append(r)
            self._add_probes(r, opc.nodes, opc.stale_s, model_probes, "temperatures.opcua.nodes")
        if mb.host or mb.registers:
            if not mb.host:
                raise InputError("registers given without a host",
                                 column="field temperatures.modbus.host")
            r = ModbusReader(mb)
            self.readers.append(r)
            self._add_probes(r, mb.registers, mb.stale_s, model_probes,
                             "temperatures.modbus.registers")
        if position.source not in POSITION_SOURCES:
            raise InputError(f"expected linuxcnc or opcua, got {position.source!r}",
                             column="field position.source")
        self.z_resolution_mm = float(position.resolution_mm)
        if position.source:
            _positive(position.stale_s, "position.stale_s")
        if position.source == "opcua":
            endpoint = position.endpoint or opc.endpoint
            if not endpoint or not position.node:
                raise InputError("position over OPC UA needs node (and endpoint, or the one "
                                 "of [temperatures.opcua])", column="field position.node")
            r = by_endpoint.get(endpoint)
            if r is None:
                r = OpcUaReader(endpoint, {}, OpcUaInputConfig(endpoint=endpoint),
                                where="position")
                by_endpoint[endpoint] = r
                self.readers.append(r)
            try:
                from asyncua import ua  # the runtime extra (asyncua): imported only when used
                ua.NodeId.from_string(position.node)
            except Exception:
                raise InputError(f"not an OPC UA node id: {position.node!r}",
                                 column="field position.node")
            r.add(Z_NAME, position.node, position.scale)
            self.z_reader = (r, position.stale_s)
        elif position.source == "linuxcnc":
            if cnc_output is None:
                raise InputError("position from LinuxCNC needs the LinuxCNC output "
                                 "(--cnc linuxcnc)", column="field position.source")
            r = LinuxCncPositionReader(cnc_output)
            self.readers.append(r)
            self.z_reader = (r, position.stale_s)

    def _add_probes(self, reader, names, stale_s, model_probes, where) -> None:
        for p in names:
            if p not in model_probes:
                raise InputError(f"{p} is not a probe the model reads from a thermometer "
                                 f"(those: {', '.join(model_probes) or 'none'})",
                                 column=f"field {where}.{p}")
            if p in self.probe_reader:
                raise InputError(f"probe {p} has two live sources "
                                 f"({self.probe_reader[p][0].kind} and {reader.kind})",
                                 column=f"field {where}.{p}")
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
        except Exception:      # a reader's bug must not end serve: its inputs just go stale
            log.exception("%s input reader stopped", reader.kind)
            reader.status = "stopped (error)"

    async def close(self) -> None:
        """Cancel the readers' tasks and close their connections."""
        for t in self._tasks:
            t.cancel()
        for t in self._tasks:
            try:
                await t
            except (asyncio.CancelledError, Exception):
                pass
        for r in self.readers:
            try:
                await r.close()
            except Exception:
                pass

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
        stale = [p for p, v in temperatures.items() if not math.isfinite(v)]
        if z_mm is not None and not math.isfinite(z_mm):
            stale.append(Z_NAME)
        stale = tuple(stale)
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
            r = self.z_reader[0] if n == Z_NAME else self.probe_reader[n][0]
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
        self._other_cols = [i for i, p in enumerate(self.probe_names)
                            if p not in live.probe_reader]
        self.last_live: dict = {}

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
