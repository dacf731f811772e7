"""The service's handle on the OPC UA server process (:class:`OpcUaServer`).

It starts the server process (``python -m fbgcomp.runtime.outputs.opcua --worker-fd N``,
:mod:`.worker`), hands it the newest sample without ever blocking the compensation loop, and
passes the server's ``Enabled`` changes and ``ReloadModel`` calls back to the service.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import logging
import pickle
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Coroutine
from typing import Any

import numpy as np

from fbgcomp.errors import InputError
from fbgcomp.runtime.auth import load_users
from fbgcomp.runtime.outputs.cnc_form import limit_toward
from fbgcomp.runtime.outputs.opcua.channel import MESSAGE_BYTES, OpcUaConfig, Snapshot, send_control
from fbgcomp.runtime.outputs.opcua.security import ensure_certificate, writer_warning
from fbgcomp.runtime.pipeline import per_axis

log = logging.getLogger("fbgcomp.runtime")
WORKER_MODULE = "fbgcomp.runtime.outputs.opcua"  # run with -m: the server process


class OpcUaServer:
    """The OPC UA server, run in a child process; this is the service-side handle.

    Running asyncua in its own process (not a thread) keeps its work - encryption of every
    notification, secure-channel handshakes, clients coming and going - off the compensation
    loop's interpreter: no GIL hand-over on every update. The two sides talk over a Unix
    ``SOCK_SEQPACKET`` socket pair: ``publish`` sends the newest snapshot without ever blocking
    (when the server process lags, snapshots are dropped: the newest wins anyway); the server
    sends back changes of ``Enabled`` and ``ReloadModel`` calls, which a small reader thread
    hands to ``on_reload`` on ``main_loop``. The server process exits when the service dies
    (the socket closes).
    """

    def __init__(
        self,
        config: OpcUaConfig,
        sensor_names: list[str],
        model_id: str,
        on_reload: Callable[[str], Coroutine[Any, Any, str]] | None = None,
        main_loop: asyncio.AbstractEventLoop | None = None,
        eu_ranges: dict[str, tuple[float, float]] | None = None,
    ):
        self.config = config
        # EURange overrides, by kind (keys of DEFAULT_EU_RANGES) or Wavelength_nm.<sensor>
        self.eu_ranges = dict(eu_ranges or {})
        self.sensor_names = list(sensor_names)
        self._model_id = model_id
        self.on_reload = on_reload
        self.main_loop = main_loop
        self.enabled = True
        self.users = load_users(config.users_file)
        self.dropped = 0
        self.cert_path, self.key_path = ensure_certificate(config.state_dir)
        self._sock: socket.socket | None = None
        self._proc: subprocess.Popen[bytes] | None = None
        self._reader: threading.Thread | None = None
        # (monotonic s, offset µm, slope µm/m) of _cnc_form
        self._cnc_state: tuple[float, np.ndarray, np.ndarray] | None = None

    @property
    def model_id(self) -> str:
        """The model id the server shows (``ModelId``); setting it tells the server process."""
        return self._model_id

    @model_id.setter
    def model_id(self, value: str) -> None:
        """Show ``value`` as the model id and tell the server process."""
        self._model_id = value
        send_control(self._sock, ("model_id", value))

    def start(self, timeout_s: float = 60.0) -> None:
        """Start the server process and wait (up to ``timeout_s``) until it serves.

        InputError naming ``opcua.endpoint`` when it cannot (busy port...). Warns, loudly,
        when no user may write (:func:`~.security.writer_warning`).
        """
        parent, child = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
        proc = self._proc = subprocess.Popen(
            [sys.executable, "-m", WORKER_MODULE, "--worker-fd", str(child.fileno())],
            pass_fds=[child.fileno()],
        )
        child.close()
        init = {
            "config": self.config.__dict__,
            "sensor_names": self.sensor_names,
            "model_id": self._model_id,
            "users": self.users,
            "cert": str(self.cert_path),
            "key": str(self.key_path),
            "enabled": self.enabled,
            "eu_ranges": self.eu_ranges,
            "log_level": logging.getLogger("fbgcomp").getEffectiveLevel(),
        }
        parent.sendall(pickle.dumps(("init", init)))
        parent.settimeout(timeout_s)
        try:
            kind, payload = pickle.loads(parent.recv(MESSAGE_BYTES))
        except (TimeoutError, EOFError, OSError, pickle.UnpicklingError) as exc:
            proc.kill()
            raise InputError(
                f"OPC UA server at {self.config.endpoint} did not start", column="opcua.endpoint"
            ) from exc
        if kind != "ready":
            proc.wait(5)
            raise InputError(
                f"cannot start OPC UA server at {self.config.endpoint}: {payload}", column="opcua.endpoint"
            )
        parent.settimeout(None)
        self._sock = parent
        self._reader = threading.Thread(target=self._read_messages, name="fbgcomp-opcua-rx", daemon=True)
        self._reader.start()
        warning = writer_warning(self.users, self.config.allow_anonymous)
        if warning:
            # loud: the README's serve command has no users, and nothing else would say why
            # the PLC's or the operator's switch is refused
            log.warning(warning)
            print(f"WARNING: {warning}", flush=True)

    def _send(self, message) -> bool:
        sock = self._sock
        if sock is None:
            return False
        try:
            sock.send(pickle.dumps(message), socket.MSG_DONTWAIT)
            return True
        except (BlockingIOError, InterruptedError):
            self.dropped += 1  # the server process lags: never wait for it
        except OSError:
            pass
        return False

    def publish(
        self,
        snapshot: Snapshot,
        enabled: bool | None = None,
        slope_um_per_m=None,
        z_ref_mm: float | None = None,
        cnc_limits=None,
    ) -> None:
        """Send the newest sample; with ``slope_um_per_m`` (runtime.cnc_form.newest_slope) also
        its offset + Z slope form, limited by ``cnc_limits``: a ModbusOutput that has just
        published this sample (its limited values are taken as they are, so a PLC reads the
        same numbers over OPC UA and Modbus) or a ModbusConfig (its limits, applied here)."""
        if slope_um_per_m is not None:
            offset, slope = self._cnc_form(snapshot, bool(enabled), slope_um_per_m, cnc_limits)
            snapshot = dataclasses.replace(
                snapshot,
                cnc_offset_um=tuple(float(v) for v in offset),
                cnc_slope_um_per_m=tuple(float(v) for v in slope),
                cnc_z_ref_mm=0.0 if z_ref_mm is None else float(z_ref_mm),
            )
        self._send(("snap", snapshot))

    def _cnc_form(self, snapshot: Snapshot, enabled: bool, slope_um_per_m, limits):
        """Limited (offset µm, slope µm/m) per axis: the Modbus output's when it published this
        sample, else the same limiter (cnc_form.limit_toward, the Modbus output's apply rule)
        with ``limits``' rates and maxima (none: no limit)."""
        if hasattr(limits, "offset_um") and hasattr(limits, "slope_um_per_m"):
            return np.asarray(limits.offset_um, float), np.asarray(limits.slope_um_per_m, float)
        now = time.monotonic()
        state = self._cnc_state
        dt = 0.0 if state is None else now - state[0]
        offset, slope = (np.zeros(3), np.zeros(3)) if state is None else state[1:]

        def lim(name):
            return per_axis(getattr(limits, name, float("inf")))

        apply = enabled and snapshot.health in ("OK", "DEGRADED")
        target = np.asarray(slope_um_per_m, float) if apply else np.zeros(3)
        offset = limit_toward(
            offset,
            np.asarray(snapshot.correction_um, float),
            dt,
            lim("offset_rate_um_per_s"),
            lim("max_offset_um"),
        )[0]
        slope = limit_toward(slope, target, dt, lim("slope_rate_um_per_m_per_s"), lim("max_slope_um_per_m"))[
            0
        ]
        self._cnc_state = (now, offset, slope)
        return offset, slope

    def set_enabled(self, value: bool) -> None:
        """Write ``Enabled`` from the service side (e.g. the dashboard): one shared state."""
        self.enabled = bool(value)
        send_control(self._sock, ("set_enabled", self.enabled))

    def _read_messages(self) -> None:
        sock = self._sock
        assert sock is not None, "start() opens the socket before this thread"
        while True:
            try:
                data = sock.recv(MESSAGE_BYTES)
            except OSError:
                return
            if not data:
                return
            kind, payload = pickle.loads(data)
            if kind == "enabled":
                self.enabled = bool(payload)
            elif kind == "reload":
                request_id, path = payload
                self._reload(request_id, path)

    def _reload(self, request_id: int, path: str) -> None:
        if self.on_reload is None or self.main_loop is None:
            send_control(self._sock, ("reload_result", (request_id, False, "reload not supported")))
            return
        fut = asyncio.run_coroutine_threadsafe(self.on_reload(path), self.main_loop)

        def done(f):
            try:
                send_control(self._sock, ("reload_result", (request_id, True, f.result())))
            except Exception as exc:
                log.warning("model reload refused: %s", exc)
                send_control(self._sock, ("reload_result", (request_id, False, str(exc))))

        fut.add_done_callback(done)

    def stop(self, timeout_s: float = 5.0) -> None:
        """Ask the server process to stop, wait for it (kill it after ``timeout_s``), close."""
        if self._sock is not None:
            with contextlib.suppress(OSError):
                self._sock.send(pickle.dumps(("stop", None)))
        if self._proc is not None:
            try:
                self._proc.wait(timeout_s)
            except Exception:
                self._proc.kill()
                self._proc.wait(5)
        if self._sock is not None:
            self._sock.close()
            self._sock = None
