"""The OPC UA server process: an asyncua server fed by the service over a socket pair.

Started by :class:`~.bridge.OpcUaServer` as ``python -m fbgcomp.runtime.outputs.opcua
--worker-fd N`` (:func:`main`). It builds the address space (:mod:`.nodes`), writes the newest
snapshot into it at most ``rate_hz`` times a second (latest value wins), bumps ``Heartbeat``,
and sends back ``Enabled`` written by a client and ``ReloadModel`` calls. Every write and
method call, refused or not, and every client certificate accepted or refused is logged with
its user on the ``fbgcomp.audit`` logger and in ``<state_dir>/opcua/audit.log``.
"""

from __future__ import annotations

import asyncio
import datetime as dt
import gc
import logging
import pickle
import signal
import socket
import sys
import time
from logging.handlers import RotatingFileHandler
from pathlib import Path

from asyncua import Server, ua
from asyncua.common.callback import CallbackType

from fbgcomp.runtime import trust
from fbgcomp.runtime.health import describe_flags
from fbgcomp.runtime.outputs.opcua.access import make_ruleset, make_user_manager, request_user, user_label
from fbgcomp.runtime.outputs.opcua.address_space import APPLICATION_URI, AXES, NAMESPACE
from fbgcomp.runtime.outputs.opcua.channel import MESSAGE_BYTES, OpcUaConfig, Snapshot, send_control
from fbgcomp.runtime.outputs.opcua.nodes import build_address_space
from fbgcomp.runtime.outputs.opcua.security import ModelPathRefused, model_in_folder

log = logging.getLogger("fbgcomp.runtime")
audit = logging.getLogger("fbgcomp.audit")
AUDIT_LOG_BYTES = 1 << 20  # audit.log rotates at 1 MiB, 5 old files kept


class ServerCore:
    """The asyncua server itself, in the server process; ``sock`` is its end of the socket
    pair, ``init`` the payload of the service's ``init`` message (:mod:`.channel`)."""

    def __init__(self, sock: socket.socket, init: dict):
        self.sock = sock
        self.config = OpcUaConfig(**init["config"])
        self.sensor_names = init["sensor_names"]
        self.model_id = init["model_id"]
        self.users = init["users"]
        self.cert_path, self.key_path = init["cert"], init["key"]
        self.enabled = bool(init["enabled"])
        self.eu_ranges = init.get("eu_ranges", {})
        self.published = 0
        self._latest: Snapshot | None = None
        self._reloads: dict[int, asyncio.Future] = {}
        self._next_reload = 0
        self._last_text: dict[str, object] = {}  # values written, to skip unchanged ones
        self._beat_at = 0.0  # monotonic s of the last Heartbeat
        self._beats = 0
        self._diag_at = 0.0  # monotonic s of the last diagnostics
        self._tasks: set[asyncio.Future] = set()  # fire-and-forget tasks, held until they end

    def send(self, message) -> None:
        """Control messages to the service (Enabled written by a client, reload requests)."""
        send_control(self.sock, message, timeout_s=1.0)

    def _on_readable(self) -> None:
        while True:
            try:
                data = self.sock.recv(MESSAGE_BYTES, socket.MSG_DONTWAIT)
            except (BlockingIOError, InterruptedError):
                break
            except OSError:
                data = b""
            if not data:  # the service is gone: stop serving
                self._stop.set()
                break
            kind, payload = pickle.loads(data)
            if kind == "snap":
                self._latest = payload
                self._wake.set()
            elif kind == "model_id":
                self.model_id = payload
            elif kind == "set_enabled":
                task = asyncio.ensure_future(self._set_enabled(bool(payload)))
                self._tasks.add(task)
                task.add_done_callback(self._tasks.discard)
            elif kind == "reload_result":
                request_id, ok, message = payload
                fut = self._reloads.pop(request_id, None)
                if fut is not None and not fut.done():
                    fut.set_result((ok, message))
            elif kind == "stop":
                self._stop.set()

    async def main(self) -> None:
        """Serve until the service says stop or goes away (its end of the socket closes)."""
        loop = asyncio.get_running_loop()
        self._wake, self._stop = asyncio.Event(), asyncio.Event()
        cfg = self.config
        server = Server(user_manager=make_user_manager(self.users, cfg.allow_anonymous))
        await server.init()
        server.set_endpoint(cfg.endpoint)
        server.set_server_name("fbgcomp runtime")
        await server.set_application_uri(APPLICATION_URI)
        await server.load_certificate(str(self.cert_path))
        await server.load_private_key(str(self.key_path))
        server.set_security_policy(
            [ua.SecurityPolicyType.Basic256Sha256_SignAndEncrypt], permission_ruleset=make_ruleset()
        )
        tokens: list[type] = [ua.UserNameIdentityToken]
        if cfg.allow_anonymous:
            tokens.append(ua.AnonymousIdentityToken)
        server.set_identity_tokens(tokens)
        # unknown client certificates are refused, always (an empty trust list trusts nobody)
        server.set_certificate_validator(
            trust.TrustListValidator(
                trust.trusted_dir(cfg.state_dir, cfg.trusted_clients_dir), trust.rejected_dir(cfg.state_dir)
            )
        )
        server.subscribe_server_callback(CallbackType.PostWrite, self._audit_write)
        idx = await server.register_namespace(NAMESPACE)
        self._nodes = await build_address_space(
            server, idx, self.sensor_names, self.model_id, self.enabled, self.eu_ranges, self._reload
        )
        self._server = server
        async with server:
            logging.getLogger("asyncua").setLevel(logging.WARNING)
            # the standard address space is tens of thousands of long-lived objects: keep them
            # out of the cyclic collector, whose full passes would stall updates for ~10 ms
            gc.collect()
            gc.freeze()
            self.send(("ready", cfg.endpoint))
            loop.add_reader(self.sock.fileno(), self._on_readable)
            try:
                await self._publish_loop()
            finally:
                loop.remove_reader(self.sock.fileno())

    def _audit_write(self, event, _dispatcher) -> None:
        """PostWrite: every client write, with its user, value and result."""
        if not event.is_external:
            return
        results = event.response_params or []
        for i, item in enumerate(event.request_params.NodesToWrite):
            status = results[i].name if i < len(results) else "?"
            value = item.Value.Value.Value if item.Value and item.Value.Value else None
            audit.info(
                "OPC UA write %s = %r by %s: %s",
                item.NodeId.to_string(),
                value,
                user_label(event.user),
                status,
            )

    async def _reload(self, parent, path_variant):
        """ReloadModel: ask the service to load a model file of the models folder."""
        name = path_variant.Value if hasattr(path_variant, "Value") else str(path_variant)
        user = request_user.get()
        try:
            path = model_in_folder(str(name), self.config.models_dir)
        except ModelPathRefused as exc:
            audit.warning("OPC UA call ReloadModel(%r) by %s refused: %s", name, user, exc)
            return ua.StatusCode(getattr(ua.StatusCodes, exc.status))
        self._next_reload += 1
        fut = asyncio.get_running_loop().create_future()
        self._reloads[self._next_reload] = fut
        self.send(("reload", (self._next_reload, path)))
        try:
            ok, message = await asyncio.wait_for(fut, 30.0)
        except TimeoutError:
            audit.warning("OPC UA call ReloadModel(%r) by %s: no answer", name, user)
            return ua.StatusCode(ua.StatusCodes.BadTimeout)
        audit.log(
            logging.INFO if ok else logging.WARNING,
            "OPC UA call ReloadModel(%r) by %s: %s",
            name,
            user,
            message if ok else f"failed: {message}",
        )
        if not ok:
            return ua.StatusCode(ua.StatusCodes.BadInvalidArgument)
        return [ua.Variant(message, ua.VariantType.String)]

    async def _publish_loop(self) -> None:
        period = 1.0 / self.config.rate_hz if self.config.rate_hz > 0 else 0.0
        last = 0.0
        stop_task = asyncio.ensure_future(self._stop.wait())
        try:
            while not self._stop.is_set():
                if not self._wake.is_set():
                    wake_task = asyncio.ensure_future(self._wake.wait())
                    await asyncio.wait(
                        {wake_task, stop_task}, timeout=0.2, return_when=asyncio.FIRST_COMPLETED
                    )
                    wake_task.cancel()
                self._wake.clear()
                await self._read_enabled()
                await self._heartbeat()
                wait = last + period - time.monotonic()
                if wait > 0:
                    await asyncio.sleep(wait)  # rate limit: the newest snapshot wins
                snap, self._latest = self._latest, None
                if snap is not None:
                    last = time.monotonic()
                    await self._write(snap)
        finally:
            stop_task.cancel()

    async def _heartbeat(self) -> None:
        """Counter bumped at least every 0.2 s, data or not: a watchdog for the CNC side."""
        now = time.monotonic()
        if now - self._beat_at < 0.2:
            return
        self._beat_at = now
        self._beats = (self._beats + 1) % (1 << 32)
        await self._server.write_attribute_value(
            self._nodes["Heartbeat"].nodeid, ua.DataValue(ua.Variant(self._beats, ua.VariantType.UInt32))
        )

    async def _set_enabled(self, value: bool) -> None:
        self.enabled = value
        await self._server.write_attribute_value(
            self._nodes["Enabled"].nodeid, ua.DataValue(ua.Variant(value, ua.VariantType.Boolean))
        )

    async def _read_enabled(self) -> None:
        # straight from the address space: no request round trip on every update
        dv = self._server.iserver.aspace.read_attribute_value(
            self._nodes["Enabled"].nodeid, ua.AttributeIds.Value
        )
        if dv.Value is not None and bool(dv.Value.Value) != self.enabled:
            self.enabled = bool(dv.Value.Value)
            self.send(("enabled", self.enabled))

    async def _write(self, s: Snapshot) -> None:
        server = self._server
        now = dt.datetime.now(dt.UTC)
        src = dt.datetime.fromtimestamp(s.sample_time_s, dt.UTC)

        async def put(path, value, vtype, always=True):
            if not always and self._last_text.get(path) == value:
                return
            self._last_text[path] = value
            await server.write_attribute_value(
                self._nodes[path].nodeid,
                ua.DataValue(ua.Variant(value, vtype), SourceTimestamp=src, ServerTimestamp=now),
            )

        D = ua.VariantType.Double
        for prefix, values in (
            ("Correction", s.correction_um),
            ("PredictedDeviation", s.deviation_um),
            ("IntervalHalfWidth", s.half_width_um),
            ("ExpectedError", s.expected_rms_um),
        ):
            for a, v in zip(AXES, values):
                await put(f"{prefix}{a}_um", float(v), D, always=prefix == "Correction")
        offset, slope, z_ref = s.cnc_offset_um, s.cnc_slope_um_per_m, s.cnc_z_ref_mm
        if offset is not None:
            assert slope is not None and z_ref is not None, "the bridge sets the CNC form's three together"
            for a, o, k in zip(AXES, offset, slope):
                await put(f"Offset{a}_um", float(o), D)
                await put(f"Slope{a}_um_per_m", float(k), D)
            await put("ZRef_mm", float(z_ref), D, False)
        S = ua.VariantType.String
        await put("Health", s.health, S, False)
        await put("Alarm", bool(s.alarm), ua.VariantType.Boolean, False)
        await put("FallbackInUse", s.fallback, S, False)
        flags = tuple(int(v) for v in s.output_flags)
        for a, v in zip(AXES, flags):
            await put(f"OutputFlags{a}", v, ua.VariantType.Byte, False)
        await put("Limited", any(flags), ua.VariantType.Boolean, False)
        await put("OutputFlags", describe_flags(flags), S, False)
        await put("SourceStatus", s.source_status, S, False)
        await put("ModelId", self.model_id, S, False)
        for name, st in zip(self.sensor_names, s.sensor_status):
            await put(f"Sensors.{name}.Status", st, S, False)
        mono = time.monotonic()
        if mono - self._diag_at >= 0.1:
            # diagnostics at <= 10 Hz: they must not slow down the correction updates
            self._diag_at = mono
            await put("FramesProcessed", int(s.frames), ua.VariantType.UInt64)
            for name, wl in zip(self.sensor_names, s.sensor_wavelength_nm):
                await put(f"Sensors.{name}.Wavelength_nm", float(wl), D)
            await put("Latency_ms", (time.time() - s.sample_time_s) * 1e3, D)
        # SampleTime last: a client watching it sees a complete, consistent sample
        await put("SampleTime", src, ua.VariantType.DateTime)
        self.published += 1


def _setup_logging(init: dict) -> None:
    """The server process logs to stderr at serve's level, and its audit records (always) to
    ``<state_dir>/opcua/audit.log``, rotated at :data:`AUDIT_LOG_BYTES`."""
    fmt = logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s")
    stderr = logging.StreamHandler()
    stderr.setFormatter(fmt)
    stderr.setLevel(int(init.get("log_level", logging.WARNING)))
    root = logging.getLogger()
    root.handlers[:] = [stderr]
    root.setLevel(stderr.level)
    audit.setLevel(logging.INFO)
    folder = Path(init["config"]["state_dir"]) / "opcua"
    try:
        folder.mkdir(parents=True, exist_ok=True)
        handler = RotatingFileHandler(
            folder / "audit.log", maxBytes=AUDIT_LOG_BYTES, backupCount=5, encoding="utf-8"
        )
    except OSError as exc:
        log.error("no OPC UA audit file in %s (%s): audit records go to stderr only", folder, exc.strerror)
        return
    handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(message)s"))
    audit.addHandler(handler)


def _worker(fd: int) -> None:
    """Run the server process on the socket-pair end ``fd`` (inherited from the service)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the service decides when to stop
    sock = socket.socket(fileno=fd)
    _kind, init = pickle.loads(sock.recv(MESSAGE_BYTES))
    _setup_logging(init)
    # start-up failures (busy port...) reach the user as serve's one-line error, not as
    # asyncua tracebacks
    logging.getLogger("asyncua").setLevel(logging.CRITICAL)
    core = ServerCore(sock, init)
    try:
        asyncio.run(core.main())
    except Exception as exc:
        core.send(("error", f"{type(exc).__name__}: {exc}"))
        raise SystemExit(1) from exc


def main(argv: list[str] | None = None) -> None:
    """``python -m fbgcomp.runtime.outputs.opcua --worker-fd FD``: started by serve only."""
    argv = sys.argv[1:] if argv is None else argv
    logging.basicConfig(level=logging.WARNING)
    if len(argv) == 2 and argv[0] == "--worker-fd":
        _worker(int(argv[1]))
    else:
        raise SystemExit("usage: python -m fbgcomp.runtime.outputs.opcua --worker-fd FD (started by serve)")
