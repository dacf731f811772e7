#!/usr/bin/python3
"""Headless "display" for the simulated LinuxCNC machine (examples/linuxcnc), system Python 3.

LinuxCNC starts the program named by ``[DISPLAY] DISPLAY`` and shuts the whole machine down
(its own clean-up path: motion, task, io, rtapi_app and the HAL components) when that program
exits. This one opens no window: it serves a tiny JSON-lines protocol on a Unix stream socket
(``[DISPLAY] FBGCOMP_SOCKET``, relative to the INI's folder) through which ``fbgcomp cnc-demo``
and the tests drive the machine with the ``linuxcnc`` (stat / command) and ``hal`` modules.

One request per line, one JSON answer per line (``{"ok": true, ...}`` or
``{"ok": false, "error": "..."}``). Commands: ``status``, ``machine_on`` (estop reset + machine
on), ``machine_off``, ``home`` (all joints), ``unhome``, ``mdi`` (``text``), ``program``
(``path``, runs it; ``wait`` for the end), ``wait_idle``, ``getp`` (``pins``), ``setp``
(``pin``, ``value``), ``wait_pin`` (``pin``, ``value``, ``tol``: time.time() when
|pin - value| <= tol, polled every millisecond), ``wait_position`` (``values``, ``tol``: the same
for the actual X, Y, Z position), ``trace`` (``pins``, ``duration_s``,
``interval_s``: samples of time, commanded and actual position and the pins), ``quit``.
Every wait is bounded by its ``timeout_s``.
"""

from __future__ import annotations

import configparser
import contextlib
import json
import os
import socket
import sys
import time

AXES = "xyz"
DEFAULT_PINS = (
    [f"axis.{a}.eoffset" for a in AXES]
    + [f"axis.{a}.eoffset-request" for a in AXES]
    + [f"fbgcomp.{a}.request-um" for a in AXES]
    + [f"fbgcomp.{a}.offset-um" for a in AXES]
    + [f"fbgcomp.{a}.counts" for a in AXES]
    + [
        "fbgcomp.active",
        "fbgcomp.fault",
        "fbgcomp.link-ok",
        "fbgcomp.enable",
        "fbgcomp.homed",
        "fbgcomp.latency-ms",
        "motion.eoffset-active",
        "motion.is-all-homed",
    ]
)


class Machine:
    """The simulated LinuxCNC machine, driven through ``linuxcnc`` (stat, command, error channel)
    and ``hal``."""

    def __init__(self) -> None:
        # LinuxCNC's modules: present only on a LinuxCNC machine, where this display runs
        import hal  # noqa: PLC0415 - LinuxCNC's module, absent from fbgcomp's venv
        import linuxcnc  # noqa: PLC0415 - LinuxCNC's module, absent from fbgcomp's venv

        self.lc, self.hal = linuxcnc, hal
        self.s = linuxcnc.stat()
        self.c = linuxcnc.command()
        self.e = linuxcnc.error_channel()
        self.errors: list[str] = []
        # hal.get_value / set_p need a component of this process (it has no pins)
        self.comp = hal.component("fbgcomp-display")
        self.comp.ready()

    def poll(self):
        """The refreshed ``linuxcnc.stat``, after moving up to 100 pending error-channel messages
        into ``errors``."""
        self.s.poll()
        for _ in range(100):
            err = self.e.poll()
            if not err:
                break
            self.errors.append(str(err[1]))
        return self.s

    def _until(self, cond, timeout_s, what):
        end = time.monotonic() + float(timeout_s)
        while time.monotonic() < end:
            self.poll()
            if cond():
                return True
            time.sleep(0.002)
        raise TimeoutError(f"{what} not reached in {timeout_s} s (errors: {self.errors[-3:]})")

    def getp(self, pins):
        """Current values of the HAL pins ``pins``, by pin name."""
        return {p: self.hal.get_value(p) for p in pins}

    def status(self, pins=None):
        """Answer to ``status``: time, estop, enabled, homing, commanded and actual X, Y, Z position (mm),
        interpreter idle, task mode, the last errors and the values of ``pins`` (default DEFAULT_PINS)."""
        s = self.poll()
        n = len(AXES)
        return {
            "time": time.time(),
            "estop": bool(s.estop),
            "enabled": bool(s.enabled),
            "homed": [bool(h) for h in s.homed[:n]],
            "all_homed": all(s.homed[:n]),
            "position": list(s.position[:n]),
            "actual": list(s.actual_position[:n]),
            "interp_idle": s.interp_state == self.lc.INTERP_IDLE,
            "task_mode": s.task_mode,
            "errors": self.errors[-5:],
            "pins": self.getp(pins or DEFAULT_PINS),
        }

    def mode(self, m, timeout_s=5.0):
        """Switch the task mode to ``m`` (``linuxcnc.MODE_*``) unless already in it (``timeout_s`` s)."""
        if self.poll().task_mode != m:
            self.c.mode(m)
            self.c.wait_complete(timeout_s)
            self._until(lambda: self.s.task_mode == m, timeout_s, "task mode")

    def machine_on(self, timeout_s=10.0):
        """Reset the estop and switch the machine on; waits (up to ``timeout_s`` s) until it is enabled."""
        self.c.state(self.lc.STATE_ESTOP_RESET)
        self.c.wait_complete(timeout_s)
        self.c.state(self.lc.STATE_ON)
        self.c.wait_complete(timeout_s)
        self._until(lambda: self.s.enabled, timeout_s, "machine on")

    def machine_off(self, timeout_s=10.0):
        """Switch the machine off; waits (up to ``timeout_s`` s) until it is disabled."""
        self.c.state(self.lc.STATE_OFF)
        self.c.wait_complete(timeout_s)
        self._until(lambda: not self.s.enabled, timeout_s, "machine off")

    def home(self, timeout_s=20.0):
        """Home all joints (manual, joint mode), then go back to world (teleop) mode; ``timeout_s`` in s."""
        self.mode(self.lc.MODE_MANUAL)
        self.c.teleop_enable(0)
        self.c.wait_complete(timeout_s)
        self.c.home(-1)
        self.c.wait_complete(timeout_s)
        self._until(lambda: all(self.s.homed[: len(AXES)]), timeout_s, "all joints homed")
        # world (teleop) mode after homing, as the stock displays do
        self.c.teleop_enable(1)
        self.c.wait_complete(timeout_s)

    def unhome(self, timeout_s=10.0):
        """Unhome all joints (manual, joint mode); waits (up to ``timeout_s`` s) until none is homed."""
        self.mode(self.lc.MODE_MANUAL)
        self.c.teleop_enable(0)
        self.c.wait_complete(timeout_s)
        self.c.unhome(-1)
        self.c.wait_complete(timeout_s)
        self._until(lambda: not any(self.s.homed[: len(AXES)]), timeout_s, "joints unhomed")

    def wait_idle(self, timeout_s=60.0):
        """Wait (up to ``timeout_s`` s) for an idle interpreter, an empty motion queue and the axes
        in position."""
        self._until(
            lambda: self.s.interp_state == self.lc.INTERP_IDLE and self.s.queue == 0 and self.s.inpos,
            timeout_s,
            "interpreter idle",
        )

    def mdi(self, text, timeout_s=60.0):
        """Run the MDI line ``text`` and wait (up to ``timeout_s`` s) until the machine is idle again."""
        self.mode(self.lc.MODE_MDI)
        self.c.mdi(text)
        self.c.wait_complete(timeout_s)
        self.wait_idle(timeout_s)

    def program(self, path, wait=True, timeout_s=120.0):
        """Open and run the G-code file ``path`` in auto mode; with ``wait``, until it has ended
        (up to ``timeout_s`` s)."""
        self.mode(self.lc.MODE_AUTO)
        self.c.program_open(path)
        self.c.wait_complete(timeout_s)
        self.c.auto(self.lc.AUTO_RUN, 0)
        # no wait_complete here: for AUTO_RUN it returns only at the end of the program.
        # Running first, then idle: do not mistake "not started yet" for "finished".
        with contextlib.suppress(TimeoutError):
            self._until(lambda: self.s.interp_state != self.lc.INTERP_IDLE, 2.0, "start")
        if wait:
            self.wait_idle(timeout_s)

    def wait_pin(self, pin, value, tol, timeout_s=5.0):
        """time.time() when HAL pin ``pin`` is within ``tol`` of ``value`` (1 ms poll), and its value then."""
        end = time.monotonic() + float(timeout_s)
        while time.monotonic() < end:
            v = self.hal.get_value(pin)
            if abs(float(v) - float(value)) <= float(tol):
                return {"reached": time.time(), "value": v}
            time.sleep(0.001)
        raise TimeoutError(f"{pin} = {self.hal.get_value(pin)}, not {value} ± {tol}")

    def wait_position(self, values, tol, timeout_s=5.0):
        """time.time() when every actual axis position is within tol of values (1 ms poll)."""
        end = time.monotonic() + float(timeout_s)
        while time.monotonic() < end:
            s = self.poll()
            act = list(s.actual_position[: len(values)])
            if all(abs(a - float(v)) <= float(tol) for a, v in zip(act, values)):
                return {"reached": time.time(), "actual": act}
            time.sleep(0.001)
        raise TimeoutError(f"actual position {list(self.s.actual_position[:3])}, not {values} ± {tol}")

    def trace(self, pins, duration_s, interval_s=0.01):
        """Samples every ``interval_s`` s for ``duration_s`` s (at most 120 s): time, commanded and actual
        X, Y, Z position (mm) and the values of ``pins`` (default DEFAULT_PINS)."""
        pins = pins or DEFAULT_PINS
        rows = []
        end = time.monotonic() + min(float(duration_s), 120.0)
        while time.monotonic() < end:
            s = self.poll()
            rows.append(
                [
                    time.time(),
                    list(s.position[:3]),
                    list(s.actual_position[:3]),
                    [self.hal.get_value(p) for p in pins],
                ]
            )
            time.sleep(max(0.0005, float(interval_s)))
        return {"pins": pins, "rows": rows}


def _handle(m: Machine, req: dict):
    cmd = req.get("cmd")
    t = float(req.get("timeout_s", 30.0))
    if cmd == "status":
        return m.status(req.get("pins"))
    if cmd == "machine_on":
        m.machine_on(t)
    elif cmd == "machine_off":
        m.machine_off(t)
    elif cmd == "home":
        m.home(t)
    elif cmd == "unhome":
        m.unhome(t)
    elif cmd == "mdi":
        m.mdi(req["text"], t)
    elif cmd == "program":
        m.program(req["path"], bool(req.get("wait", True)), t)
    elif cmd == "wait_idle":
        m.wait_idle(t)
    elif cmd == "getp":
        return {"values": m.getp(req["pins"])}
    elif cmd == "setp":
        m.hal.set_p(req["pin"], str(req["value"]))
    elif cmd == "wait_pin":
        return m.wait_pin(req["pin"], req["value"], req.get("tol", 0.0), t)
    elif cmd == "wait_position":
        return m.wait_position(req["values"], req.get("tol", 0.0), t)
    elif cmd == "trace":
        return m.trace(req.get("pins"), req.get("duration_s", 1.0), req.get("interval_s", 0.01))
    else:
        raise ValueError(f"unknown command {cmd!r}")
    return m.status()


def main(argv=None) -> int:
    """Serve the JSON-lines protocol on the INI's ``[DISPLAY] FBGCOMP_SOCKET`` until ``quit``; the
    exit status (2 when started without ``-ini INIFILE``)."""
    argv = list(sys.argv[1:] if argv is None else argv)
    ini = argv[argv.index("-ini") + 1] if "-ini" in argv else None
    if ini is None:
        print("fbgcomp_display: started without -ini INIFILE", file=sys.stderr)
        return 2
    cp = configparser.ConfigParser(strict=False, interpolation=None, inline_comment_prefixes=("#",))
    cp.read(ini)
    path = cp.get("DISPLAY", "FBGCOMP_SOCKET", fallback="display.sock").strip()
    path = os.path.join(os.path.dirname(os.path.abspath(ini)), path)
    m = Machine()
    with contextlib.suppress(FileNotFoundError):
        os.unlink(path)
    srv = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    srv.bind(path)
    os.chmod(path, 0o600)  # the machine is driven by its own user only (and root)
    srv.listen(4)
    print(f"fbgcomp_display: listening on {path}", file=sys.stderr, flush=True)
    quit_ = False
    try:
        while not quit_:
            conn, _ = srv.accept()
            with conn, conn.makefile("rwb") as f:
                for line in f:
                    try:
                        req = json.loads(line)
                        ans: dict[str, object]
                        if req.get("cmd") == "quit":
                            quit_ = True
                            ans = {"ok": True}
                        else:
                            ans = {"ok": True, **(_handle(m, req) or {})}
                    except Exception as exc:  # an answer for every request, the display lives on
                        ans = {"ok": False, "error": f"{type(exc).__name__}: {exc}"}
                    f.write((json.dumps(ans) + "\n").encode())
                    f.flush()
                    if quit_:
                        break
    finally:
        srv.close()
        with contextlib.suppress(OSError):
            os.unlink(path)
    return 0


if __name__ == "__main__":
    sys.exit(main())
