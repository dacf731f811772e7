"""Simulated Hyperion instrument: serves the Hyperion protocol on loopback from recorded signals.

Over 600 lines as one unit: the protocol server, the signal interpolation and the fault injection
share the streaming loop's state.

The signal table (a campaign's ``fbg.csv``, later the digital twin) is interpolated in time at
the configured frame rate; sensors are laid out over channels in order. Faults can be injected
at given times (seconds since the simulator started streaming)::

    drop:S3@5          grating S3 disappears from t = 5 s
    double:S2@3        S2 shows two peaks (the second 0.3 nm higher) from t = 3 s
    shift:S4@2:+6      S4 moves by +6 nm (out of its window) from t = 2 s
    cut@4:1.5          every connection is closed at t = 4 s and refused for 1.5 s
    stuck:S1@2         S1 repeats its last value from t = 2 s
    garbage@6:4096     4096 random bytes on every stream connection at t = 6 s (the client's
                       decoder must refuse them and reconnect)

Strain-free reference gratings of the campaign (``<sensor>_ref_nm``) are served as peaks too
and named ``<sensor>_ref`` in faults (``drop:S3_ref@5``).

A grating fault lasts to the end unless ``/duration`` follows it: ``drop:S3@5/2`` brings S3
back at t = 7 s, ``shift:S2@3:+2/10`` moves S2 by 2 nm for 10 s (a mode hop there and back).

With ``temperatures_opcua`` (``sim-interrogator --temperatures-opcua opc.tcp://HOST:PORT``) the
campaign's probe temperatures are served too, on a small OPC UA server of the simulator's own
(:class:`OpcUaTemperatureServer`: security None, anonymous, read-only variables
``ns=2;s=Probes.<probe>``, °C), on the same clock and at the same speed as the gratings: what a
PLC or a temperature logger would publish beside the interrogator, for ``serve``'s
``[temperatures.opcua]`` live input.

Frames are produced in vectorised blocks (all frames due since the last tick) and written to
every connected stream client; a client that does not keep up (more than ``max_buffer_bytes``
queued) is disconnected rather than slowing the instrument down.
"""

from __future__ import annotations

import asyncio
import contextlib
import gc
import re
import signal
import struct
import time
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from fbgcomp.atomic import atomic_path
from fbgcomp.errors import InputError
from fbgcomp.io.campaign import read_campaign
from fbgcomp.runtime import hyperion

if TYPE_CHECKING:
    from asyncua import Node, Server

_FAULT_RE = re.compile(
    r"^(drop|double|shift|stuck):([^@]+)@([0-9.eE+-]+)(?::([0-9.eE+-]+))?"
    r"(?:/([0-9.eE+-]+))?$"
)
_CUT_RE = re.compile(r"^(cut|garbage)@([0-9.eE+-]+)(?::([0-9.eE+-]+))?$")
GARBAGE_BYTES = 4096
MAX_GARBAGE_BYTES = 1 << 20


@dataclass
class Fault:
    """One injected fault: ``kind`` on ``sensor`` from ``at_s`` to ``until_s`` (``value``:
    shift nm / cut s / garbage bytes)."""

    kind: str
    sensor: str | None
    at_s: float
    value: float = 0.0
    until_s: float = float("inf")

    def active(self, t_rel_s: float) -> bool:
        """Whether the fault is on at ``t_rel_s`` seconds after the start."""
        return self.at_s <= t_rel_s < self.until_s


def parse_fault(text: str) -> Fault:
    """Parse one fault specification (see the module docstring)."""
    text = text.strip()
    m = _FAULT_RE.match(text)
    try:
        if m:
            kind, sensor, at, value, duration = m.groups()
            default = 6.0 if kind == "shift" else 0.0
            f = Fault(kind, sensor, float(at), float(value) if value else default)
            if duration is not None:
                f.until_s = f.at_s + float(duration)
            if f.at_s >= 0 and f.until_s > f.at_s and np.isfinite(f.value):
                return f
        m = _CUT_RE.match(text)
        if m:
            kind, at, value = m.groups()
            default = 1.0 if kind == "cut" else GARBAGE_BYTES
            f = Fault(kind, None, float(at), float(value) if value else default)
            if (
                f.at_s >= 0
                and np.isfinite(f.value)
                and f.value >= 0
                and (kind == "cut" or f.value <= MAX_GARBAGE_BYTES)
            ):
                return f
    except ValueError:
        pass
    raise InputError(
        f"bad fault {text!r}: expected drop:S@t, double:S@t, shift:S@t:nm, "
        "stuck:S@t (each optionally /duration), cut@t:duration or "
        f"garbage@t:bytes (at most {MAX_GARBAGE_BYTES})",
        column="--fault",
    )


@dataclass
class SignalTable:
    """Wavelength signals to serve: ``time_s`` (m,), ``wavelengths_nm`` (m, S), sensor names."""

    time_s: np.ndarray
    wavelengths_nm: np.ndarray
    sensor_names: list[str]
    channel: list[int] | None = None  # 1-based instrument channel per sensor (campaign meta)

    @classmethod
    def from_campaign(cls, folder: str | Path) -> SignalTable:
        """The campaign's gratings: its sensors, then the strain-free reference gratings of
        those that carry one (signal ``<sensor>_ref`` from column ``<sensor>_ref_nm``, on the
        sensor's channel; faults name them so: ``drop:S3_ref@5``)."""
        c = read_campaign(folder)
        refs = [s for s in c.meta.sensors if s.reference_column is not None]
        names = [s.name for s in c.meta.sensors] + c.meta.reference_probe_names  # refs' probes
        columns = [s.column for s in c.meta.sensors] + [s.reference_column for s in refs]
        wl = c.fbg[columns].to_numpy(dtype=np.float64)
        channel = [int(getattr(s, "channel", None) or 0) for s in c.meta.sensors + refs]
        return cls(c.fbg["time_s"].to_numpy(dtype=np.float64), wl, names, channel if all(channel) else None)

    def at(self, campaign_time_s: np.ndarray) -> np.ndarray:
        """Linear interpolation of every sensor at the given campaign times, (n, S)."""
        out = np.empty((campaign_time_s.size, len(self.sensor_names)))
        for j in range(out.shape[1]):  # loop over sensors only, each column vectorised in time
            out[:, j] = np.interp(campaign_time_s, self.time_s, self.wavelengths_nm[:, j])
        return out


@dataclass
class SimConfig:
    """Settings of the simulated instrument: frame rate, channels, padding peaks, speed, faults."""

    rate_hz: float = 1000.0
    channels: int = 1
    extra_peaks_per_channel: int = 0
    peaks_per_channel: int | None = None  # pad every channel with far peaks up to this count
    speed: float = 1.0
    loop: bool = False
    noise_pm: float = 0.0
    serial_number: str = "SIM-HYPERION-0001"
    faults: list[Fault] = field(default_factory=list)
    max_buffer_bytes: int = 16 << 20
    seed: int = 0


class SimulatedHyperion:
    """Asyncio Hyperion instrument serving ``table`` on ``host`` (command and stream ports)."""

    def __init__(
        self,
        table: SignalTable,
        config: SimConfig | None = None,
        host: str = "127.0.0.1",
        command_port: int = 0,
        stream_port: int = 0,
    ):
        self.table = table
        self.config = config or SimConfig()
        if not 0 < self.config.rate_hz <= 20_000:
            raise InputError(f"rate {self.config.rate_hz} Hz outside (0, 20000]", column="--rate")
        if self.config.channels < 1:
            raise InputError("at least one channel is needed", column="--channels")
        for f in self.config.faults:
            if f.sensor is not None and f.sensor not in table.sensor_names:
                raise InputError(
                    f"fault names unknown sensor {f.sensor!r}; sensors are {', '.join(table.sensor_names)}",
                    column="--fault",
                )
        self.host = host
        self._ports = (command_port, stream_port)
        self._servers: list[asyncio.Server] = []
        self._stream_writers: set[asyncio.StreamWriter] = set()
        self._all_writers: set[asyncio.StreamWriter] = set()
        self._t0: float | None = None
        self._sent = 0
        self._cut_until = -1.0
        self._rng = np.random.default_rng(self.config.seed)
        self.finished = asyncio.Event()
        self._task: asyncio.Task | None = None
        S = len(table.sensor_names)
        if table.channel is not None:
            self._sensor_channel = np.asarray(table.channel) - 1
            if self._sensor_channel.max() >= self.config.channels:
                self.config.channels = int(self._sensor_channel.max()) + 1
        else:
            per = -(-S // self.config.channels)
            self._sensor_channel = np.arange(S) // per
        self._stuck_value: dict[int, float] = {}
        self.send_log: list[tuple[float, int, float]] | None = None
        self._fired_cuts: set[int] = set()
        self.garbage_sent = 0  # bursts of random bytes sent (garbage faults)

    @property
    def command_port(self) -> int:
        """The bound command port."""
        return self._servers[0].sockets[0].getsockname()[1]

    @property
    def stream_port(self) -> int:
        """The bound peak-stream port."""
        return self._servers[1].sockets[0].getsockname()[1]

    @property
    def frames_sent(self) -> int:
        """Frames sent so far."""
        return self._sent

    async def start(self) -> None:
        """Listen on the command and stream ports and start streaming."""
        self._servers = [
            await asyncio.start_server(self._serve_commands, self.host, self._ports[0]),
            await asyncio.start_server(self._serve_stream, self.host, self._ports[1]),
        ]
        self._t0 = time.time()
        self._task = asyncio.create_task(self._stream_loop())

    async def stop(self) -> None:
        """Stop streaming, disconnect the clients and close the ports."""
        await _cancel(self._task)
        self._close_clients()
        for s in self._servers:
            s.close()
        for s in self._servers:
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(s.wait_closed(), 1.0)

    def _close_clients(self) -> None:
        for w in list(self._all_writers):
            w.close()
        self._all_writers.clear()
        self._stream_writers.clear()

    def _elapsed(self) -> float:
        return time.time() - (self._t0 or time.time())

    def _link_cut(self) -> bool:
        return self._elapsed() < self._cut_until

    # -- command port
    async def _serve_commands(self, reader, writer) -> None:
        if self._link_cut():
            writer.close()
            return
        self._all_writers.add(writer)
        try:
            while True:
                _, cmd, _arg = await hyperion.read_request(reader)
                writer.write(self._answer(cmd))
                await writer.drain()
        except (asyncio.IncompleteReadError, ConnectionError):
            pass
        finally:
            self._all_writers.discard(writer)
            writer.close()

    def _answer(self, cmd: str) -> bytes:
        c = cmd.strip().lower()
        if c == "#getserialnumber":
            return hyperion.encode_response("", self.config.serial_number.encode("ascii"))
        if c == "#getdutchannelcount":
            return hyperion.encode_response("", struct.pack("<I", self.config.channels))
        if c == "#isready":
            return hyperion.encode_response("", b"\x01")
        if c == "#getlaserscanspeed":
            return hyperion.encode_response("", struct.pack("<I", int(self.config.rate_hz)))
        return hyperion.encode_response(f"unknown command {cmd}", b"", status=1)

    # -- stream port
    async def _serve_stream(self, reader, writer) -> None:
        if self._link_cut():
            writer.close()
            return
        self._all_writers.add(writer)
        self._stream_writers.add(writer)
        try:
            await reader.read()  # clients never send on the stream port; wait for EOF
        except ConnectionError:
            pass
        finally:
            self._stream_writers.discard(writer)
            self._all_writers.discard(writer)
            writer.close()

    async def _stream_loop(self) -> None:
        cfg = self.config
        period = 1.0 / cfg.rate_hz
        tick = max(period, 0.0005)
        duration = (self.table.time_s[-1] - self.table.time_s[0]) / cfg.speed
        while True:
            elapsed = self._elapsed()
            for i, f in enumerate(cfg.faults):
                if f.kind == "cut" and i not in self._fired_cuts and elapsed >= f.at_s:
                    self._fired_cuts.add(i)
                    self._cut_until = f.at_s + f.value
                    self._close_clients()
                elif f.kind == "garbage" and i not in self._fired_cuts and elapsed >= f.at_s:
                    self._fired_cuts.add(i)
                    if self._stream_writers and not self._link_cut():
                        junk = self._rng.integers(0, 256, int(f.value), dtype=np.uint8)
                        for w in list(self._stream_writers):
                            w.write(junk.tobytes())
                        self.garbage_sent += 1
            due = int(elapsed * cfg.rate_hz) + 1
            if due > self._sent:
                k = np.arange(self._sent, due)
                t_rel = k * period
                if not cfg.loop and t_rel[0] > duration:
                    self._close_clients()
                    self.finished.set()
                    return
                if not cfg.loop:
                    k = k[t_rel <= duration]
                    t_rel = t_rel[: k.size]
                self._sent = due
                if not self._link_cut() and self._stream_writers and k.size:
                    self._broadcast(self._frames(t_rel), self._t0 + t_rel[0], k.size)
            next_t = self._sent * period
            await asyncio.sleep(max(0.0, min(tick, next_t - self._elapsed())))

    def _broadcast(self, data: bytes, first_stamp_s: float = 0.0, n: int = 0) -> None:
        if self.send_log is not None:
            # wall-clock time each block of frames left, for latency measurements
            self.send_log.append((first_stamp_s, n, time.time()))
        for w in list(self._stream_writers):
            if w.transport.get_write_buffer_size() > self.config.max_buffer_bytes:
                self._stream_writers.discard(w)
                w.close()  # a slow reader is dropped, as a real instrument would
                continue
            w.write(data)

    def _frames(self, t_rel_s: np.ndarray) -> bytes:
        """Encode the frames at stream-relative times ``t_rel_s`` (faults applied)."""
        cfg = self.config
        span = self.table.time_s[-1] - self.table.time_s[0]
        camp_t = t_rel_s * cfg.speed
        if cfg.loop and span > 0:
            camp_t = np.mod(camp_t, span)
        wl = self.table.at(self.table.time_s[0] + camp_t)
        if cfg.noise_pm:
            wl += self._rng.normal(0.0, cfg.noise_pm * 1e-3, wl.shape)
        # Fault boundaries split the block into runs with one peak layout each.
        edges = sorted(
            {e for f in cfg.faults if f.sensor is not None for e in (f.at_s, f.until_s) if np.isfinite(e)}
        )
        seg = (
            np.searchsorted(np.asarray(edges), t_rel_s, side="right")
            if edges
            else np.zeros(t_rel_s.size, int)
        )
        out = []
        for s in np.unique(seg):
            rows = seg == s
            t_now = t_rel_s[rows][0]
            out.append(self._encode_segment(self._t0 + t_rel_s[rows], wl[rows], t_now))
        return b"".join(out)

    def _encode_segment(self, stamp_s: np.ndarray, wl: np.ndarray, t_rel: float) -> bytes:
        cfg = self.config
        names = self.table.sensor_names
        dropped, doubled = set(), set()
        for i, f in enumerate(cfg.faults):
            if f.sensor is None or not f.active(t_rel):
                if f.kind == "stuck" and t_rel >= f.until_s:
                    self._stuck_value.pop(i, None)
                continue
            j = names.index(f.sensor)
            if f.kind == "drop":
                dropped.add(j)
            elif f.kind == "double":
                doubled.add(j)
            elif f.kind == "shift":
                wl[:, j] += f.value
            elif f.kind == "stuck":
                self._stuck_value.setdefault(i, float(wl[0, j]))
                wl[:, j] = self._stuck_value[i]
        cols, counts = [], np.zeros(cfg.channels, np.int16)
        for ch in range(cfg.channels):
            members = [j for j in np.flatnonzero(self._sensor_channel == ch).tolist() if j not in dropped]
            ch_cols = []
            for j in members:
                ch_cols.append(wl[:, j])
                if j in doubled:
                    ch_cols.append(wl[:, j] + 0.3)
            n_extra = (
                cfg.extra_peaks_per_channel
                if cfg.peaks_per_channel is None
                else max(0, cfg.peaks_per_channel - len(ch_cols))
            )
            for e in range(n_extra):
                # Other gratings on the fibre, far from every sensor window.
                ch_cols.append(np.full(wl.shape[0], 1600.0 + 2.0 * e + 0.1 * ch))
            if ch_cols:
                order = np.argsort([c[0] for c in ch_cols], kind="stable")
                ch_cols = [ch_cols[i] for i in order]
            counts[ch] = len(ch_cols)
            cols.extend(ch_cols)
        peaks = np.column_stack(cols) if cols else np.zeros((wl.shape[0], 0))
        serial = int.from_bytes(self.config.serial_number.encode()[-8:].rjust(8, b"\0"), "little")
        return hyperion.encode_peak_frames(serial, stamp_s, counts, peaks)


def save_send_log(sim: SimulatedHyperion, path: str | Path) -> None:
    """Atomically save (first frame stamp s, frames, send wall time s) rows as ``.npy``."""
    # the temporary name ends in .npy, else np.save would append it
    with atomic_path(path, suffix=".npy") as tmp:
        np.save(tmp, np.array(sim.send_log or [], dtype=np.float64).reshape(-1, 3))


class OpcUaTemperatureServer:
    """A campaign's probe temperatures on OPC UA, on a simulator's clock (see the module
    docstring): every ``period_s`` each ``Probes.<probe>`` variable takes the campaign's newest
    sample at or before campaign time ``t0 + elapsed x speed`` (looping with the gratings when
    they loop), written with a fresh source timestamp.

    Parameters
    ----------
    endpoint : str
        ``opc.tcp://HOST:PORT[/path]`` to listen on.
    time_s : ndarray (m,)
        Campaign times of the temperature samples, s.
    temperature_C : ndarray (m, P)
        The samples, °C.
    probe_names : list of str
    speed : float
        Campaign seconds per real second (the simulator's ``--speed``).
    loop : bool
        Restart at the end of the span ``span_s`` (the gratings' span when looping together).
    """

    NAMESPACE = "urn:fbgcomp:sim-interrogator"

    def __init__(
        self,
        endpoint: str,
        time_s,
        temperature_C,
        probe_names,
        speed: float = 1.0,
        loop: bool = False,
        span_s: float | None = None,
        t_start_s: float | None = None,
        period_s: float = 0.1,
    ):
        if not endpoint.startswith("opc.tcp://"):
            raise InputError(f"expected opc.tcp://HOST:PORT, got {endpoint!r}", column="--temperatures-opcua")
        self.endpoint = endpoint
        self.time_s = np.asarray(time_s, float)
        self.values = np.asarray(temperature_C, float).reshape(self.time_s.size, -1)
        self.probe_names = list(probe_names)
        self.speed = float(speed)
        self.loop = loop
        self.t_start_s = float(self.time_s[0] if t_start_s is None else t_start_s)
        self.span_s = float(span_s if span_s is not None else self.time_s[-1] - self.time_s[0])
        self.period_s = period_s
        self.server: Server | None = None
        self._vars: list[Node] = []
        self._task: asyncio.Task | None = None
        self._t0: float | None = None
        self.updates = 0

    @classmethod
    def from_campaign(
        cls, endpoint: str, folder, config: SimConfig, table: SignalTable
    ) -> OpcUaTemperatureServer:
        """A server of the campaign's probe temperatures (InputError if it has none)."""
        c = read_campaign(folder)
        probes = [p.name for p in c.meta.temperature_probes if f"{p.name}_C" in c.temperatures.columns]
        if not probes:
            raise InputError("the campaign has no probe temperatures to serve", file=folder)
        return cls(
            endpoint,
            c.temperatures["time_s"].to_numpy(float),
            c.temperatures[[f"{p}_C" for p in probes]].to_numpy(float),
            probes,
            config.speed,
            config.loop,
            table.time_s[-1] - table.time_s[0],
            table.time_s[0],
        )

    def at(self, elapsed_s: float) -> np.ndarray:
        """(P,) the newest sample at or before the campaign time reached after ``elapsed_s``."""
        camp = elapsed_s * self.speed
        if self.loop and self.span_s > 0:
            camp = np.mod(camp, self.span_s)
        i = int(np.searchsorted(self.time_s, self.t_start_s + camp + 1e-9, side="right")) - 1
        return self.values[max(i, 0)]

    async def start(self, t0: float | None = None) -> None:
        """Start the OPC UA server and its update loop (campaign time 0 at ``t0``, default now)."""
        from asyncua import Server, ua  # noqa: PLC0415 - optional extra: asyncua (the runtime extra)

        server = Server()
        await server.init()
        server.set_endpoint(self.endpoint)
        server.set_server_name("fbgcomp sim-interrogator temperatures")
        server.set_security_policy([ua.SecurityPolicyType.NoSecurity])
        idx = await server.register_namespace(self.NAMESPACE)
        # asyncua annotates NodeId with its own str / int subclasses; plain ones are what it takes
        probes = await server.nodes.objects.add_object(ua.NodeId("Probes", idx), "Probes")  # type: ignore[arg-type]
        first = self.at(0.0)
        for name, v in zip(self.probe_names, first):
            var = await probes.add_variable(
                ua.NodeId(f"Probes.{name}", idx),  # type: ignore[arg-type]  # str / int, as above
                name,
                float(v),
                varianttype=ua.VariantType.Double,
            )
            self._vars.append(var)
        await server.start()
        self.server = server
        self._t0 = time.time() if t0 is None else t0
        self._task = asyncio.create_task(self._update_loop())

    async def _update_loop(self) -> None:
        from asyncua import ua  # noqa: PLC0415 - optional extra: asyncua (the runtime extra)

        t0 = self._t0
        assert t0 is not None  # start() sets it before it starts this loop
        while True:
            row = self.at(time.time() - t0)
            now = datetime.now(UTC)  # a fresh timestamp: the value is live
            for var, v in zip(self._vars, row):
                # asyncua annotates the timestamps as its datetime subclass; a datetime is what it takes
                dv = ua.DataValue(
                    ua.Variant(float(v), ua.VariantType.Double),
                    SourceTimestamp=now,  # type: ignore[arg-type]
                    ServerTimestamp=now,  # type: ignore[arg-type]
                )
                await var.write_value(dv)
            self.updates += 1
            await asyncio.sleep(self.period_s)

    async def stop(self) -> None:
        """Stop the update loop and the server."""
        await _cancel(self._task)
        if self.server is not None:
            await self.server.stop()
            self.server = None


async def _cancel(task) -> None:
    """Cancel a background task (None: nothing) and wait until it has ended, whatever it raises."""
    if task is None:
        return
    task.cancel()
    with contextlib.suppress(asyncio.CancelledError, Exception):
        await task


async def run_simulator(
    table: SignalTable,
    config: SimConfig,
    host: str,
    command_port: int,
    stream_port: int,
    ready=None,
    duration_s: float | None = None,
    send_log: str | Path | None = None,
    temperatures: OpcUaTemperatureServer | None = None,
) -> None:
    """Serve until the signals end (unless looping), ``duration_s`` passes, or cancellation;
    with ``temperatures``, the campaign's probe temperatures over OPC UA on the same clock."""
    sim = SimulatedHyperion(table, config, host, command_port, stream_port)
    if send_log is not None:
        sim.send_log = []
    await sim.start()
    if temperatures is not None:
        try:
            await temperatures.start(sim._t0)
        except BaseException:
            await sim.stop()
            raise
    gc.collect()
    gc.freeze()  # the campaign tables stay: no full collector passes over them mid-stream
    if ready is not None:
        ready(sim)
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        with contextlib.suppress(NotImplementedError, RuntimeError):  # not on this platform / thread
            loop.add_signal_handler(sig, stop.set)
    try:
        waiters = {asyncio.create_task(sim.finished.wait()), asyncio.create_task(stop.wait())}
        await asyncio.wait(waiters, timeout=duration_s, return_when=asyncio.FIRST_COMPLETED)
        for w in waiters:
            w.cancel()
    finally:
        await sim.stop()
        if temperatures is not None:
            await temperatures.stop()
        if send_log is not None:
            save_send_log(sim, send_log)
