#!/usr/bin/python3
"""LinuxCNC userspace HAL component ``fbgcomp``: fbgcomp's tool-tip correction -> external offsets.

Run by the *system* Python 3 (the ``hal`` module of Debian's ``linuxcnc-uspace``), normally from
the machine's HAL file::

    loadusr -Wn fbgcomp /usr/bin/python3 fbgcomp_hal.py --listen udp://127.0.0.1:47300

Only the standard library is used at import time (``hal`` is imported in :func:`main`), so the
venv side (:mod:`fbgcomp.runtime.outputs.linuxcnc`) imports the packet format and the limiter from this
very file.

Local channel: one datagram per correction, :data:`PACKET` (little endian, 52 bytes) =
``magic b"FBGC", version u16 (1), flags u16, seq u32, sent_s f64 (sender wall clock, s),
sample_time_s f64 (instrument time, s), correction_x_um, correction_y_um, correction_z_um f64``.
Flags: :data:`FLAG_ENABLED` (the compensator's Enabled switch), :data:`FLAG_ALARM` (health ALARM),
:data:`FLAG_ZEROING`, :data:`FLAG_STALE` (the compensator's loop has not published for a while).
The sender repeats the newest datagram every few tens of milliseconds with a new ``seq``: that is
the heartbeat.

Back over the same channel, every cycle while the link is alive, the component answers the
newest datagram's sender with the axis position: :data:`POSITION` (little endian, 28 bytes) =
``magic b"FBGZ", version u16 (1), flags u16, seq u32, sent_s f64, z_mm f64``, ``z_mm`` the input
pin ``z-pos-mm`` (net it to ``joint.2.pos-fb`` or ``axis.z.pos-cmd``), flags
:data:`POS_HOMED` (``homed``) and :data:`POS_MACHINE_ON` (``machine-on``): ``fbgcomp serve``'s
``[position] source = "linuxcnc"`` passes it to the model (a Z of an unhomed machine is no
position: missing). Transport: ``udp://127.0.0.1:PORT`` (default 47300) or ``unix:///path`` (a Unix
datagram socket; its file permissions decide who may send).

Each cycle (``--period``, default 5 ms) the component takes the newest datagram and drives, per
axis, the applied correction toward the target at most ``max-rate-um-s`` µm/s, clipped to
± ``max-correction-um``. The target is the received correction only while *all* of these hold:
``machine-on``, ``homed``, ``enable`` (HAL inputs), link alive (a datagram within ``timeout-s``),
the compensator enabled and not in ALARM / stale; otherwise it is 0, so a fault, a lost
heartbeat, a disable or an unhome returns the offset to zero *at the configured rate*. The applied
correction goes out as counts for ``axis.L.eoffset-counts`` with ``scale`` (mm per count) for
``axis.L.eoffset-scale``: one count = ``--um-per-count`` µm (default 0.1 µm). While the machine is
off the counts are held at 0, because LinuxCNC zeroes its external-offset register at machine-on
and accumulates count *changes* from there (docs/linuxcnc.md).

Sign: fbgcomp publishes correction = − predicted TTP deviation (µm); the external offset is
correction_um / 1000 mm, added to the commanded axis position.
"""

from __future__ import annotations

import argparse
import contextlib
import math
import os
import select
import signal
import socket
import struct
import sys
import time

PACKET = struct.Struct("<4sHHIddddd")
MAGIC = b"FBGC"
VERSION = 1
FLAG_ENABLED = 1
FLAG_ALARM = 2
FLAG_ZEROING = 4
FLAG_STALE = 8
DEFAULT_ADDRESS = "udp://127.0.0.1:47300"
POSITION = struct.Struct("<4sHHIdd")
POSITION_MAGIC = b"FBGZ"
POS_HOMED = 1
POS_MACHINE_ON = 2
AXES = ("x", "y", "z")


def encode_packet(
    seq: int, correction_um, flags: int, sample_time_s: float = 0.0, sent_s: float | None = None
) -> bytes:
    """One datagram of the local channel (see the module docstring)."""
    cx, cy, cz = (float(v) for v in correction_um)
    return PACKET.pack(
        MAGIC,
        VERSION,
        int(flags) & 0xFFFF,
        int(seq) & 0xFFFFFFFF,
        time.time() if sent_s is None else float(sent_s),
        float(sample_time_s),
        cx,
        cy,
        cz,
    )


def decode_packet(data: bytes):
    """``(seq, flags, sent_s, sample_time_s, (x, y, z) µm)`` or None for anything malformed."""
    if len(data) != PACKET.size:
        return None
    magic, version, flags, seq, sent_s, sample_s, cx, cy, cz = PACKET.unpack(data)
    if magic != MAGIC or version != VERSION:
        return None
    corr = (cx, cy, cz)
    # a non-finite correction is a compensator fault, never a value to apply
    if not all(math.isfinite(c) for c in corr):
        flags |= FLAG_ALARM
        corr = (0.0, 0.0, 0.0)
    return seq, flags, sent_s, sample_s, corr


def encode_position(seq: int, z_mm: float, flags: int, sent_s: float | None = None) -> bytes:
    """One position datagram, component -> compensator (see the module docstring)."""
    return POSITION.pack(
        POSITION_MAGIC,
        VERSION,
        int(flags) & 0xFFFF,
        int(seq) & 0xFFFFFFFF,
        time.time() if sent_s is None else float(sent_s),
        float(z_mm),
    )


def decode_position(data: bytes):
    """``(seq, flags, sent_s, z_mm)`` or None for anything malformed (a non-finite Z: None)."""
    if len(data) != POSITION.size:
        return None
    magic, version, flags, seq, sent_s, z_mm = POSITION.unpack(data)
    if magic != POSITION_MAGIC or version != VERSION or not math.isfinite(z_mm):
        return None
    return seq, flags, sent_s, z_mm


def parse_address(address: str):
    """``(family, sockaddr)`` for ``udp://HOST:PORT`` or ``unix:///path``."""
    if address.startswith("unix://"):
        path = address[len("unix://") :]
        if not path:
            raise ValueError(f"no socket path in {address!r}")
        return socket.AF_UNIX, path
    if address.startswith("udp://"):
        hostport = address[len("udp://") :]
        host, sep, port = hostport.rpartition(":")
        if not sep or not port.isdigit():
            raise ValueError(f"expected udp://HOST:PORT, got {address!r}")
        return socket.AF_INET, (host or "127.0.0.1", int(port))
    raise ValueError(f"expected udp://HOST:PORT or unix:///path, got {address!r}")


def limit_step(current_um, target_um, max_rate_um_s: float, max_abs_um: float, dt_s: float):
    """Move ``current_um`` toward ``target_um`` (clipped to ± max_abs_um) by at most
    max_rate_um_s * dt_s per axis. Pure; the same rule as fbgcomp's own tests check."""
    step = max(0.0, max_rate_um_s) * max(0.0, dt_s)
    lim = max(0.0, max_abs_um)
    out = []
    for c, t in zip(current_um, target_um):
        t = min(lim, max(-lim, t))
        out.append(c + min(step, max(-step, t - c)))
    return tuple(out)


def target_for(received_um, flags: int, link_ok: bool, machine_on: bool, homed: bool, enable: bool):
    """The correction to steer toward: the received one only when everything allows it."""
    ok = (
        machine_on
        and homed
        and enable
        and link_ok
        and bool(flags & FLAG_ENABLED)
        and not flags & (FLAG_ALARM | FLAG_STALE)
    )
    return (tuple(received_um) if ok else (0.0, 0.0, 0.0)), ok


class Receiver:
    """The component's end of the local channel: newest valid datagram, never blocking."""

    def __init__(self, address: str):
        family, addr = parse_address(address)
        self.sock = socket.socket(family, socket.SOCK_DGRAM)
        if family == socket.AF_UNIX:
            with contextlib.suppress(FileNotFoundError):
                os.unlink(addr)
        self.sock.bind(addr)
        self.sock.setblocking(False)
        self.path = addr if family == socket.AF_UNIX else None
        self.last: tuple | None = None  # (seq, flags, sent_s, sample_s, corr)
        self.last_rx: float | None = None  # monotonic time of the newest datagram
        self.peer = None  # its sender's address: where the position goes back to
        self.latency_ms = -1.0  # sender's send -> received, newest datagram
        self.rejected = 0

    def drain(self, max_datagrams: int = 10000) -> int:
        """Read the pending datagrams (at most ``max_datagrams``), keeping the newest valid one and its
        sender; the number of valid ones read (invalid ones count in ``rejected``)."""
        n = 0
        for _ in range(max_datagrams):  # bounded: a flood cannot hold the cycle
            try:
                data, peer = self.sock.recvfrom(256)
            except (BlockingIOError, InterruptedError):
                break
            p = decode_packet(data)
            if p is None:
                self.rejected += 1
                continue
            self.last, self.last_rx = p, time.monotonic()
            self.peer = peer or None  # an unbound Unix sender cannot be answered
            self.latency_ms = (time.time() - p[2]) * 1000.0
            n += 1
        return n

    def send_position(self, seq: int, z_mm: float, flags: int) -> bool:
        """The axis position back to the newest datagram's sender (never blocks)."""
        if self.peer is None:
            return False
        try:
            self.sock.sendto(encode_position(seq, z_mm, flags), self.peer)
            return True
        except OSError:  # the compensator went away: the next datagram names the new one
            return False

    def close(self):
        """Close the socket and remove its Unix socket file, if it has one."""
        self.sock.close()
        if self.path:
            with contextlib.suppress(OSError):
                os.unlink(self.path)


def _args(argv):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--name", default="fbgcomp", help="HAL component name (pin prefix)")
    ap.add_argument("--listen", default=DEFAULT_ADDRESS, help="udp://HOST:PORT or unix:///path")
    ap.add_argument(
        "--um-per-count", type=float, default=0.1, help="µm per eoffset count (scale pin = this / 1000 mm)"
    )
    ap.add_argument("--period", type=float, default=0.005, help="cycle time, s")
    ap.add_argument("--max-rate-um-s", type=float, default=50.0)
    ap.add_argument("--max-correction-um", type=float, default=200.0)
    ap.add_argument("--timeout-s", type=float, default=0.25, help="heartbeat timeout, s")
    return ap.parse_args(argv)


def main(argv=None) -> int:
    """Run the HAL component: every ``--period`` s, steer the X, Y, Z external offsets toward the newest
    received correction (rate and size limited) and send the Z position back; the exit status."""
    import hal  # noqa: PLC0415 - LinuxCNC's module, absent from fbgcomp's venv, which imports this file

    a = _args(argv)
    if a.um_per_count <= 0 or a.period <= 0:
        print("fbgcomp_hal: --um-per-count and --period must be positive", file=sys.stderr)
        return 2
    rx = Receiver(a.listen)
    c = hal.component(a.name)
    pin = {}

    def new(name, typ, direction, value=None):
        pin[name] = c.newpin(name, typ, direction)
        if value is not None:
            c[name] = value

    for ax in AXES:
        new(f"{ax}.counts", hal.HAL_S32, hal.HAL_OUT)  # -> axis.L.eoffset-counts
        new(f"{ax}.offset-um", hal.HAL_FLOAT, hal.HAL_OUT)  # applied (limited) correction
        new(f"{ax}.request-um", hal.HAL_FLOAT, hal.HAL_OUT)  # newest received correction
    new("scale", hal.HAL_FLOAT, hal.HAL_OUT, a.um_per_count / 1000.0)  # -> axis.L.eoffset-scale
    new("eoffset-enable", hal.HAL_BIT, hal.HAL_OUT)  # -> axis.L.eoffset-enable
    new("enable", hal.HAL_BIT, hal.HAL_IN)  # operator / machine permission
    new("homed", hal.HAL_BIT, hal.HAL_IN)  # <- motion.is-all-homed
    new("machine-on", hal.HAL_BIT, hal.HAL_IN)  # <- motion.motion-enabled
    new("max-rate-um-s", hal.HAL_FLOAT, hal.HAL_IN, a.max_rate_um_s)
    new("max-correction-um", hal.HAL_FLOAT, hal.HAL_IN, a.max_correction_um)
    new("timeout-s", hal.HAL_FLOAT, hal.HAL_IN, a.timeout_s)
    new("z-pos-mm", hal.HAL_FLOAT, hal.HAL_IN)  # <- joint.2.pos-fb (to serve)
    new("active", hal.HAL_BIT, hal.HAL_OUT)  # received correction is the target
    new("fault", hal.HAL_BIT, hal.HAL_OUT)  # compensator ALARM/stale or link lost
    new("link-ok", hal.HAL_BIT, hal.HAL_OUT)  # a datagram within timeout-s
    new("limited", hal.HAL_BIT, hal.HAL_OUT)  # request beyond max-correction-um
    new("heartbeat", hal.HAL_BIT, hal.HAL_OUT)  # toggles every cycle (watchdog)
    new("compensator-seq", hal.HAL_S32, hal.HAL_OUT)  # seq of the newest datagram
    new("latency-ms", hal.HAL_FLOAT, hal.HAL_OUT)  # sender send -> received, ms
    c.ready()

    stop = []
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: stop.append(1))

    current = (0.0, 0.0, 0.0)
    beat = False
    pos_seq = 0
    last_t = time.monotonic()
    try:
        while not stop:
            with contextlib.suppress(InterruptedError):
                select.select([rx.sock], [], [], a.period)
            rx.drain()
            now = time.monotonic()
            dt = min(now - last_t, 0.1)  # after a stall, never jump more than 0.1 s of rate
            last_t = now
            link_ok = rx.last_rx is not None and now - rx.last_rx <= c["timeout-s"]
            seq, flags, _, _, received = rx.last if rx.last else (0, 0, 0.0, 0.0, (0.0,) * 3)
            machine_on = bool(c["machine-on"])
            target, active = target_for(
                received, flags, link_ok, machine_on, bool(c["homed"]), bool(c["enable"])
            )
            if machine_on:
                current = limit_step(current, target, c["max-rate-um-s"], c["max-correction-um"], dt)
            else:
                current = (0.0, 0.0, 0.0)  # LinuxCNC restarts its offset register from zero
            for ax, cur, req in zip(AXES, current, received):
                c[f"{ax}.counts"] = round(cur / a.um_per_count)
                c[f"{ax}.offset-um"] = cur
                c[f"{ax}.request-um"] = req
            c["eoffset-enable"] = machine_on
            c["active"] = active
            c["link-ok"] = link_ok
            c["fault"] = (not link_ok) or bool(flags & (FLAG_ALARM | FLAG_STALE))
            c["limited"] = any(abs(r) > c["max-correction-um"] for r in received)
            c["compensator-seq"] = seq & 0x7FFFFFFF
            c["latency-ms"] = rx.latency_ms if link_ok else -1.0
            beat = not beat
            c["heartbeat"] = beat
            if link_ok:
                pos_seq += 1
                rx.send_position(
                    pos_seq,
                    c["z-pos-mm"],
                    (POS_HOMED if c["homed"] else 0) | (POS_MACHINE_ON if machine_on else 0),
                )
    finally:
        rx.close()
        c.exit()
    return 0


if __name__ == "__main__":
    sys.exit(main())
