"""``fbgcomp serve --cnc linuxcnc``: send the correction to LinuxCNC's ``fbgcomp`` HAL component.

The component (:mod:`fbgcomp.cnc.fbgcomp_hal`, run by LinuxCNC under the system Python) turns
the correction into external axis offsets, rate- and magnitude-limited, and clears them on a
fault, a lost heartbeat, a disable or an unhome. This side only sends: one datagram per
published sample over the local channel (``udp://127.0.0.1:47300`` by default, or
``unix:///path``), and from a small thread the newest one again every ``heartbeat_s`` with a new
sequence number - the heartbeat, so the component also notices a compensator whose loop has
stopped. When the service has not published for ``stale_s`` (a stalled loop: before zeroing there
is nothing to apply anyway), the repeated datagram carries ``FLAG_STALE`` and the component
ramps to zero. Sending never blocks the compensation loop: a full or absent receiver only
drops datagrams (counted in ``send_errors``).

The same socket receives what the component sends back: the Z-axis position (its
``z-pos-mm`` pin, with the homed flag), kept by :meth:`LinuxCncOutput.position` for
``[position] source = "linuxcnc"`` (:mod:`fbgcomp.runtime.live_inputs`). A Unix-socket sender is
bound to an abstract address of its own so the component can answer it.

Sign: the datagram carries the published correction = − predicted TTP deviation, µm, which the
component applies as an external offset of correction_um / 1000 mm. See docs/linuxcnc.md.
"""

from __future__ import annotations

import select
import socket
import threading
import time
from dataclasses import dataclass

from fbgcomp.cnc.fbgcomp_hal import (
    DEFAULT_ADDRESS,
    FLAG_ALARM,
    FLAG_ENABLED,
    FLAG_STALE,
    FLAG_ZEROING,
    POS_HOMED,
    decode_position,
    encode_packet,
    parse_address,
)
from fbgcomp.errors import InputError

CNC_KINDS = ("off", "linuxcnc")


@dataclass
class CncConfig:
    """``--cnc linuxcnc`` / ``[cnc]``: the HAL component the correction is sent to (docs/linuxcnc.md)."""

    kind: str = "off"  # "off" or "linuxcnc"
    address: str = DEFAULT_ADDRESS  # udp://HOST:PORT or unix:///path of the HAL component
    heartbeat_s: float = 0.02  # the newest datagram is repeated at least this often
    stale_s: float = 0.5  # no publication for this long = compensator fault


class LinuxCncOutput:
    """The compensator's end of the local channel. ``publish`` from the service loop."""

    def __init__(self, config: CncConfig):
        try:
            self.family, self.sockaddr = parse_address(config.address)
        except ValueError as exc:
            raise InputError(str(exc), column="field cnc.address") from exc
        if config.heartbeat_s <= 0 or config.stale_s <= 0:
            raise InputError(
                "cnc.heartbeat_s and cnc.stale_s must be positive", column="field cnc.heartbeat_s"
            )
        self.config = config
        self.sock: socket.socket | None = None
        self.seq = 0
        self.sent = 0
        self.send_errors = 0
        self._lock = threading.Lock()
        # correction µm per axis, flags, sample time
        self._latest: tuple[tuple[float, ...], int, float] = ((0.0, 0.0, 0.0), FLAG_ZEROING, 0.0)
        self._published_at: float | None = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        # (z_mm, monotonic receive time, homed) from the component
        self._position: tuple[float, float, bool] | None = None
        self.positions = 0

    def start(self) -> None:
        """Open the datagram socket and start the heartbeat thread that repeats the newest values."""
        self.sock = socket.socket(self.family, socket.SOCK_DGRAM)
        if self.family == socket.AF_UNIX:
            self.sock.bind("")  # Linux autobind: an abstract address the component answers
        self.sock.setblocking(False)
        self._thread = threading.Thread(target=self._heartbeat, name="fbgcomp-linuxcnc", daemon=True)
        self._thread.start()

    @staticmethod
    def flags_for(snapshot, enabled: bool) -> int:
        """The datagram's flag word for a snapshot: enabled, alarm, zeroing."""
        flags = FLAG_ENABLED if enabled else 0
        if snapshot.alarm:
            flags |= FLAG_ALARM
        if snapshot.health == "ZEROING":
            flags |= FLAG_ZEROING
        return flags

    def publish(self, snapshot, enabled: bool = True) -> None:
        """Send the newest sample now (never blocks)."""
        self.publish_values(snapshot.correction_um, self.flags_for(snapshot, enabled), snapshot.sample_time_s)

    def publish_values(self, correction_um, flags: int, sample_time_s: float = 0.0) -> None:
        """Send a correction (µm per axis) with its flags now, and repeat it until the next."""
        with self._lock:
            self._latest = (tuple(float(v) for v in correction_um), int(flags), float(sample_time_s))
            self._published_at = time.monotonic()
            self._send_locked()

    def _send_locked(self) -> None:
        sock = self.sock
        assert sock is not None, "start() opens the socket before anything is sent"
        corr, flags, sample_s = self._latest
        if self._published_at is not None and time.monotonic() - self._published_at > self.config.stale_s:
            flags |= FLAG_STALE
        self.seq = (self.seq + 1) & 0xFFFFFFFF
        try:
            sock.sendto(encode_packet(self.seq, corr, flags, sample_s), self.sockaddr)
            self.sent += 1
        except OSError:  # receiver not there yet, buffer full: the next datagram will do
            self.send_errors += 1

    def position(self) -> tuple[float, float, bool] | None:
        """``(z_mm, received monotonic s, homed)`` of the newest position datagram, or None."""
        return self._position

    def _receive(self, sock: socket.socket) -> None:
        for _ in range(1000):  # bounded: a flood cannot hold the heartbeat
            try:
                data = sock.recv(64)
            except (BlockingIOError, InterruptedError):
                return
            except OSError:  # e.g. ICMP refused from an absent receiver
                return
            p = decode_position(data)
            if p is not None:
                self._position = (p[3], time.monotonic(), bool(p[1] & POS_HOMED))
                self.positions += 1

    def _heartbeat(self) -> None:
        sock = self.sock
        if sock is None:  # started by start(), after the socket is open
            return
        period = self.config.heartbeat_s
        next_beat = time.monotonic() + period
        while not self._stop.is_set():
            wait = max(0.0, next_beat - time.monotonic())
            try:
                ready, _, _ = select.select([sock], [], [], wait)
            except (OSError, ValueError):
                return
            if ready:
                self._receive(sock)
            now = time.monotonic()
            if now >= next_beat:
                with self._lock:
                    if self.sock is not None:
                        self._send_locked()
                next_beat = max(next_beat + period, now)

    def stop(self) -> None:
        """Tell the component the compensator is going away (it ramps to zero), then close."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(2.0)
        with self._lock:
            if self.sock is not None:
                self._latest = ((0.0, 0.0, 0.0), 0, self._latest[2])
                self._published_at = time.monotonic()
                self._send_locked()
                self.sock.close()
                self.sock = None


def open_cnc_output(config: CncConfig) -> LinuxCncOutput | None:
    """The output named by ``config.kind`` (None for "off")."""
    if config.kind not in CNC_KINDS:
        raise InputError(
            f"unknown CNC output {config.kind!r} (known: {', '.join(CNC_KINDS)})", column="--cnc"
        )
    if config.kind == "off":
        return None
    return LinuxCncOutput(config)
