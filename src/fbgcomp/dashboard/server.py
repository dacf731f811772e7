"""Live dashboard: an aiohttp server with Server-Sent Events for browsers on the shop-floor network.

Over 600 lines as one unit: every endpoint reads the same published state under one lock; the HTTP
plumbing is in :mod:`fbgcomp.dashboard.transport`.

Its own thread and event loop, never the compensation loop:

* :meth:`Dashboard.publish` is called by the service for every processed batch. It only stores
  references to the newest values under a lock (no copy of history, no JSON, no I/O), so the
  compensation loop is never slowed by the dashboard, however many browsers watch it.
* The server runs an asyncio loop in one thread of its own (``fbgcomp-dashboard``). A
  broadcaster task there wakes at most ``max_rate_hz`` times a second (default 10), turns the
  newest values into one small JSON message (sensor elongations, temperatures, predicted
  deviation, correction, health, fallback, latency; ~0.6 kB) and bumps a sequence number.
* Each browser's stream is a coroutine that sends the newest message whenever the sequence
  number moves: a slow client simply skips messages (latest wins), one that stops reading is
  dropped; nobody else waits for it.

Connections: HTTP parsing, keep-alive, TLS and cookies are aiohttp's and asyncio's. Every wait
for a client is bounded by ``request_timeout_s`` (default 5 s): a connection that has not sent a
complete request head by then - idle, or half a request - is closed (aiohttp's keep-alive timer,
which also runs from the moment a connection opens; hence aiohttp >= 3.14.4), a request body not
complete in time gets 408 and the connection is closed, and so is a TLS handshake. A stream whose
write does not complete within ``send_timeout_s``, or with more than 64 kB unsent, is dropped. At
most ``max_connections`` connections are open at a time (the one thing aiohttp has no setting
for: :class:`~fbgcomp.dashboard.transport.ConnectionCap`); one more is answered 503 and closed
at once. That plumbing (listen address, TLS, connection cap, JSON errors, security headers) is
:mod:`fbgcomp.dashboard.transport`'s; this module holds what is served.

Access (docs/security.md, "Dashboard"): the server binds 127.0.0.1 unless told otherwise
(``--dashboard [HOST:]PORT``). Bound beyond loopback, or with ``read_login = "always"``, every
read needs a login too, and the service refuses to start without a dashboard user. The
enable/disable control always needs a login. Users come from ``users_file`` (lines
``name:pbkdf2_sha256$...`` as made by ``fbgcomp.runtime.auth.hash_password``) or
``FBGCOMP_DASHBOARD_USER`` / ``FBGCOMP_DASHBOARD_PASSWORD``; nothing is built in. A login sets a
random session cookie (HttpOnly, SameSite=Strict, Secure under TLS) naming a session held in
this process; state-changing requests must also be JSON, which a cross-site form cannot send.
``tls_cert`` / ``tls_key`` serve HTTPS directly. The control calls back into the service, which
toggles the very ``Enabled`` state the OPC UA server exposes.

Drift (``GET /api/history?window_s=…&points=…``): windows of 1 min to 36 h of the run log,
downsampled server-side (:mod:`fbgcomp.dashboard.history`) in a worker thread, one computation
at a time, an answer reused for a second by every browser asking for the same window. It needs
the run log's folder: ``log_dir`` (given by the service, or ``[dashboard] log_dir``).

Static assets (HTML, JS, CSS) are files of this package, hand-written, no CDN: the page works
on a network without internet access.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import math
import os
import secrets
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from aiohttp import web

from fbgcomp.dashboard.history import MAX_POINTS, MAX_WINDOW_S, MIN_WINDOW_S, WINDOWS_S, LogHistory
from fbgcomp.dashboard.transport import (
    ConnectionCap,
    Refused,
    errors_as_json,
    is_loopback,
    json_response,
    parse_listen,
    security_headers,
    tls_context,
)
from fbgcomp.errors import InputError
from fbgcomp.models.features import FeatureMap
from fbgcomp.runtime.auth import load_users as _load_users
from fbgcomp.runtime.auth import verify_password
from fbgcomp.runtime.health import flag_names
from fbgcomp.units import AXES

log = logging.getLogger("fbgcomp.dashboard")

STATIC_DIR = Path(__file__).resolve().parent / "static"
_STATIC = {"index.html": "text/html", "dashboard.js": "text/javascript", "dashboard.css": "text/css"}
COOKIE = "fbgcomp_session"
MAX_BODY_BYTES = 4096  # the largest request body (a login or a switch is < 200 bytes)
MAX_UNSENT_BYTES = 64 * 1024  # a stream with more queued for the browser is dropped
MAX_SESSIONS = 256  # the oldest login is forgotten beyond this
FAILED_LOGIN_S = 0.5  # every failed login costs this, one at a time
KEEPALIVE_COMMENT_S = 15.0  # an SSE comment when nothing new: proxies and dead peers


@dataclass
class DashboardConfig:
    """The ``[dashboard]`` section of serve's configuration (docs/dashboard.md)."""

    listen: str = ""  # [HOST:]PORT, HOST 127.0.0.1 if omitted; empty = no dashboard
    users_file: str | None = None  # lines name:pbkdf2_sha256$... (see module docstring)
    read_login: str = "auto"  # auto: reads need a login when bound beyond loopback; always
    tls_cert: str | None = None  # PEM certificate (chain): serve HTTPS, with tls_key
    tls_key: str | None = None  # PEM private key of tls_cert
    max_rate_hz: float = 10.0  # updates per second per client, at most
    max_clients: int = 32  # concurrent live streams; more get 503
    max_connections: int = 64  # concurrent connections of any kind; more get 503, closed
    request_timeout_s: float = 5.0  # to send a request (head, body) or finish a TLS handshake
    session_s: float = 8 * 3600.0  # a login lasts one shift
    send_timeout_s: float = 5.0  # a client not reading for this long is dropped
    log_dir: str | None = None  # run log folder for the drift windows (default: serve's --log)


def load_users(users_file: str | Path | None, environ=os.environ) -> dict[str, str]:
    """User -> password hash, from ``users_file`` and ``FBGCOMP_DASHBOARD_USER/PASSWORD``."""
    return _load_users(
        users_file,
        environ,
        service="dashboard",
        env_prefix="FBGCOMP_DASHBOARD",
        doc="docs/dashboard.md",
        iterations=20_000,
    )


def _clean(values, digits: int) -> list:
    """Floats rounded for the wire; NaN/inf (no value) become null."""
    out = []
    for v in np.asarray(values, dtype=float).ravel():
        out.append(round(float(v), digits) if math.isfinite(v) else None)
    return out


class Dashboard:
    """The dashboard server. ``start``/``stop`` from any thread; ``publish`` from the service."""

    def __init__(
        self,
        config: DashboardConfig,
        sensor_names,
        probe_names,
        model_id: str = "",
        control: Callable[[bool], bool] | None = None,
        enabled: Callable[[], bool] | None = None,
        log_dir: str | Path | None = None,
    ):
        self.config = config
        log_dir = log_dir or config.log_dir
        # the drift windows read the run log (it may not exist yet: serve creates it later)
        self.history = LogHistory(log_dir) if log_dir else None
        self._history_answers: dict = {}  # (window_s, points) -> (monotonic, bytes)
        self._history_lock: asyncio.Lock | None = None
        self.host, self.port = parse_listen(config.listen)
        self.sensor_names = list(sensor_names)
        self.probe_names = list(probe_names)
        self.model_id = model_id
        self.control = control
        self.enabled = enabled or (lambda: True)
        self.users = load_users(config.users_file)
        if config.read_login not in ("auto", "always"):
            raise InputError(
                f"expected auto or always, got {config.read_login!r}", column="field dashboard.read_login"
            )
        self.read_login = config.read_login == "always" or not is_loopback(self.host)
        if self.read_login and not self.users:
            why = (
                f"the dashboard on {self.host} would show the machine's state to anyone on the network"
                if not is_loopback(self.host)
                else 'read_login = "always" needs a login to read'
            )
            raise InputError(
                f"{why}: configure a dashboard user (--dashboard-users FILE or "
                "FBGCOMP_DASHBOARD_USER/PASSWORD), who must then log in to read"
                + (", or bind to 127.0.0.1" if not is_loopback(self.host) else "")
                + " (docs/security.md)",
                column="--dashboard",
            )
        self.ssl_context = tls_context(config.tls_cert, config.tls_key)
        self._assets = {name: (STATIC_DIR / name).read_bytes() for name in _STATIC}
        self.sessions: dict[str, tuple[str, float]] = {}  # token -> (user, expiry monotonic)
        self.clients = 0
        self.messages = 0
        # service thread -> broadcaster: the newest sample, and whether the broadcaster sleeps
        self._lock = threading.Lock()
        # (snapshot, temperature_C, model, wavelength_zero_nm, temperature_zero_C, publish time)
        self._latest: tuple[Any, Any, Any, Any, Any, float] | None = None
        self._idle = False
        self._feature_maps: dict = {}
        # (value, version) of Enabled as last seen here: the version grows on every change, so
        # the page can tell a frame built before a switch from one built after it
        self._enabled_seen: tuple[bool | None, int] = (None, 0)
        self._enabled_lock = threading.Lock()
        # owned by the dashboard's loop (created in it)
        self._loop: asyncio.AbstractEventLoop | None = None
        self._thread: threading.Thread | None = None
        self._seq = 0
        self._message = b""
        self._stopping = False
        self._wake: asyncio.Event | None = None
        self._next: asyncio.Future | None = None  # resolved when a new message is out
        self._failed_login: asyncio.Lock | None = None
        self._runner: web.AppRunner | None = None
        self._server: asyncio.Server | None = None
        self._cap: ConnectionCap | None = None
        self._broadcaster: asyncio.Task | None = None

    @property
    def url(self) -> str:
        """The address browsers open, ``http(s)://HOST:PORT/`` (the bound port once started)."""
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"{'https' if self.ssl_context else 'http'}://{host}:{self.port}/"

    # -- service side -------------------------------------------------------------------
    def publish(self, snapshot, temperature_C, pipeline) -> None:
        """Newest sample (non-blocking: references only; the broadcaster does the work)."""
        item = (
            snapshot,
            temperature_C,
            pipeline.model,
            pipeline.wavelength_zero_nm,
            pipeline.temperature_zero_C,
            time.time(),
        )
        with self._lock:
            self._latest = item
            wake, self._idle = self._idle, False
        loop, event = self._loop, self._wake
        # only when the broadcaster waits (it made the event first): once per idle spell
        if wake and loop is not None and event is not None:
            with contextlib.suppress(RuntimeError):  # the loop closed meanwhile (stopping)
                loop.call_soon_threadsafe(event.set)

    def start(self) -> None:
        """Listen and serve from a thread of its own; InputError if the address is unusable."""
        loop = asyncio.new_event_loop()
        self._loop = loop
        self._thread = threading.Thread(target=loop.run_forever, name="fbgcomp-dashboard", daemon=True)
        self._thread.start()
        try:
            asyncio.run_coroutine_threadsafe(self._serve(), loop).result(30)
        except BaseException:
            self._end_loop()
            raise
        log.info(
            "dashboard on %s (%d user(s); reads %s)",
            self.url,
            len(self.users),
            "need a login" if self.read_login else "open",
        )
        if not is_loopback(self.host) and self.ssl_context is None:
            log.warning(
                "dashboard on %s without TLS: passwords and values cross the network in "
                "clear text (docs/security.md)",
                self.url,
            )

    def stop(self) -> None:
        """Close every stream and connection and end the dashboard's thread (any thread)."""
        loop = self._loop
        if loop is None:
            return
        try:
            asyncio.run_coroutine_threadsafe(self._shutdown(), loop).result(15)
        except Exception:  # stopping anyway: the loop ends below
            log.exception("dashboard: unclean shutdown")
        self._end_loop()

    def _end_loop(self) -> None:
        loop, self._loop = self._loop, None
        thread = self._thread
        assert loop is not None and thread is not None, "start() made both"
        loop.call_soon_threadsafe(loop.stop)
        thread.join(5.0)
        if not thread.is_alive():
            loop.close()

    # -- server (the dashboard's loop) --------------------------------------------------------
    async def _serve(self) -> None:
        loop = asyncio.get_running_loop()
        self._wake = asyncio.Event()
        self._next = loop.create_future()
        self._failed_login = asyncio.Lock()
        self._history_lock = asyncio.Lock()
        app = web.Application(client_max_size=MAX_BODY_BYTES, middlewares=[errors_as_json])
        app.on_response_prepare.append(security_headers)
        app.router.add_get("/", self._index)
        app.router.add_get("/index.html", self._index)
        app.router.add_get("/static/{name}", self._static)
        app.router.add_get("/api/meta", self._meta)
        app.router.add_get("/api/state", self._state)
        app.router.add_get("/api/stream", self._stream)
        app.router.add_get("/api/history", self._history)
        app.router.add_post("/api/login", self._login)
        app.router.add_post("/api/logout", self._logout)
        app.router.add_post("/api/enabled", self._set_enabled)
        timeout = self.config.request_timeout_s
        # keepalive_timeout: no complete request head within it (idle or half-sent) = closed;
        # lingering_time: how long an unread body is drained after the answer (<= 1 s)
        runner = self._runner = web.AppRunner(
            app,
            access_log=None,
            keepalive_timeout=timeout,
            lingering_time=min(1.0, timeout),
            shutdown_timeout=2.0,
        )
        await runner.setup()
        assert runner.server is not None, "made by setup()"
        self._cap = ConnectionCap(runner.server, self.config.max_connections)
        try:
            self._server = server = await loop.create_server(
                self._cap,
                self.host,
                self.port,
                backlog=128,
                reuse_address=True,
                ssl=self.ssl_context,
                # asyncio takes a handshake timeout only with TLS
                ssl_handshake_timeout=None if self.ssl_context is None else timeout,
            )
        except OSError as exc:
            await runner.cleanup()
            raise InputError(
                f"cannot listen on {self.host}:{self.port}: {exc.strerror or exc}", column="--dashboard"
            ) from None
        self.port = server.sockets[0].getsockname()[1]
        self._broadcaster = asyncio.create_task(self._broadcast_loop())

    async def _shutdown(self) -> None:
        self._stopping = True
        if self._server is not None:
            self._server.close()
        if self._next is not None and not self._next.done():
            self._next.set_result(None)  # every stream wakes up and ends
        if self._broadcaster is not None:
            self._broadcaster.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._broadcaster
        if self._runner is not None:
            await self._runner.cleanup()

    async def _broadcast_loop(self) -> None:
        loop = asyncio.get_running_loop()
        period = 1.0 / self.config.max_rate_hz if self.config.max_rate_hz > 0 else 0.0
        wake = self._wake
        assert wake is not None, "made by _serve() before this task"
        last = -math.inf
        while not self._stopping:
            wait = last + period - loop.time()
            if wait > 0:
                await asyncio.sleep(wait)  # decimation: whatever arrives meanwhile, newest wins
            with self._lock:
                item, self._latest = self._latest, None
                if item is None:
                    wake.clear()  # before _idle: a publish after this lock wakes us
                    self._idle = True
            if item is None:
                await wake.wait()
                continue
            last = loop.time()
            try:
                message = self._message_for(*item, seq=self._seq + 1)
            except Exception:  # never let one odd sample stop the live view
                log.exception("dashboard: cannot encode a sample")
                continue
            self._message = message
            self._seq += 1
            self.messages += 1
            done, self._next = self._next, loop.create_future()
            assert done is not None, "made by _serve() before this task"
            done.set_result(None)

    def _elongations(self, model, wavelength_nm, temperature_C, w0, t0):
        if w0 is None:
            return np.full(len(self.sensor_names), np.nan)
        key = id(model)
        fmap = self._feature_maps.get(key)
        if fmap is None:
            # ΔS as the runtime sees it: every model type exposes its sensors and probes
            try:
                fmap = FeatureMap(list(model.sensors), list(model.probe_names), False)
            except (AttributeError, KeyError, TypeError):
                fmap = False  # a model without sensor metadata: no elongations to show
            self._feature_maps = {key: fmap}  # one model at a time (reload replaces it)
        if fmap is False:
            return np.full(len(self.sensor_names), np.nan)
        with np.errstate(invalid="ignore"):
            base = fmap.base(
                np.asarray(wavelength_nm, float)[None, :], np.asarray(temperature_C, float)[None, :], w0, t0
            )
        return base[0, : len(self.sensor_names)]

    def _message_for(self, snap, temperature_C, model, w0, t0, published_s, seq=0) -> bytes:
        elong = self._elongations(model, snap.sensor_wavelength_nm, temperature_C, w0, t0)
        enabled, enabled_version = self.enabled_state()
        frame = {
            "t": snap.sample_time_s,
            # this server's own count and clock (time.time(), s) of the messages it sends: at
            # most max_rate_hz of them per second of this clock, whatever the client sees
            "seq": seq,
            "server_s": round(time.time(), 4),
            "elongation_um": _clean(elong, 3),
            "wavelength_nm": _clean(snap.sensor_wavelength_nm, 5),
            "temperature_C": _clean(temperature_C, 3),
            "deviation_um": _clean(snap.deviation_um, 3),
            "half_width_um": _clean(snap.half_width_um, 3),
            "correction_um": _clean(snap.correction_um, 3),
            "expected_rms_um": _clean(snap.expected_rms_um, 3),
            "health": snap.health,
            "alarm": bool(snap.alarm),
            "fallback": snap.fallback,
            # per axis: the flag word (fbgcomp.runtime.health.FLAG_*) and its names
            "output_flags": [int(v) for v in getattr(snap, "output_flags", (0, 0, 0))],
            "output_flag_names": [flag_names(v) for v in getattr(snap, "output_flags", (0, 0, 0))],
            "limited": any(int(v) for v in getattr(snap, "output_flags", (0, 0, 0))),
            "sensor_status": list(snap.sensor_status),
            "source_status": snap.source_status,
            "frames": int(snap.frames),
            "model_id": snap.model_id or self.model_id,
            # a frame may reach the page after the answer to a switch it predates: the page
            # keeps the state of the newest version it has seen
            "enabled": enabled,
            "enabled_version": enabled_version,
            # sample time stamp -> correction computed (interrogator clock vs. this host)
            "latency_ms": round((published_s - snap.sample_time_s) * 1e3, 2),
            # batch received -> correction computed (this host only)
            "processing_ms": round((published_s - snap.received_s) * 1e3, 2) if snap.received_s else None,
        }
        return json.dumps(frame, separators=(",", ":"), allow_nan=False).encode()

    def enabled_state(self) -> tuple[bool, int]:
        """Enabled now and its version (+1 on every change seen), read under one lock so that
        versions and values stay in step across the broadcaster and the requests."""
        with self._enabled_lock:
            value = bool(self.enabled())
            last, version = self._enabled_seen
            if value != last:
                version += 1
                self._enabled_seen = (value, version)
            return value, version

    # -- sessions -------------------------------------------------------------------------
    def login(self, user: str, password: str) -> str | None:
        """A new session token if the password is right (slow on purpose: PBKDF2)."""
        stored = self.users.get(user)
        if stored is None or not verify_password(password, stored):
            return None
        token = secrets.token_urlsafe(32)
        now = time.monotonic()
        with self._lock:
            live = sorted(((k, v) for k, v in self.sessions.items() if v[1] > now), key=lambda kv: kv[1][1])
            self.sessions = dict(live[-(MAX_SESSIONS - 1) :])
            self.sessions[token] = (user, now + self.config.session_s)
        return token

    def session_user(self, token: str | None) -> str | None:
        """The user of a live session token, None for none, an unknown or an expired one."""
        if not token:
            return None
        with self._lock:
            entry = self.sessions.get(token)
        if entry is None or entry[1] < time.monotonic():
            return None
        return entry[0]

    def logout(self, token: str | None) -> None:
        """Forget the session ``token`` (nothing if unknown)."""
        with self._lock:
            self.sessions.pop(token or "", None)

    def meta(self, user: str | None) -> dict:
        """``GET /api/meta``: who is logged in and what may be done; with read access, the
        sensors, probes, model, drift windows and the Enabled state too."""
        access = {"user": user, "login_possible": bool(self.users), "read_login": self.read_login}
        if self.read_login and user is None:
            return access  # nothing about the machine before a login
        return {
            "sensors": self.sensor_names,
            "probes": self.probe_names,
            "axes": list(AXES),
            "model_id": self.model_id,
            "max_rate_hz": self.config.max_rate_hz,
            "control_available": self.control is not None,
            **access,
            "history": self.history is not None,
            "windows_s": list(WINDOWS_S) if self.history is not None else [60],
            **dict(zip(("enabled", "enabled_version"), self.enabled_state())),
        }

    # -- request handlers ---------------------------------------------------------------------
    def _user(self, request: web.Request) -> str | None:
        return self.session_user(request.cookies.get(COOKIE))

    def _check_read(self, request: web.Request) -> None:
        if self.read_login and self._user(request) is None:
            raise Refused(401, "log in to see the live values")

    async def _read_json(self, request: web.Request) -> dict | None:
        """The JSON object of a small ``application/json`` body, None if it is something else."""
        length = request.content_length
        if (length is None and request.body_exists) or (length or 0) > MAX_BODY_BYTES:
            raise Refused(400, f"expected a JSON body of at most {MAX_BODY_BYTES} bytes", close=True)
        try:
            async with asyncio.timeout(self.config.request_timeout_s):
                body = await request.read()
        except TimeoutError:
            raise Refused(408, "request body not received in time", close=True) from None
        if request.content_type != "application/json" or not body:
            return None
        try:
            data = json.loads(body)
        except (ValueError, UnicodeDecodeError):
            return None
        return data if isinstance(data, dict) else None

    async def _index(self, request: web.Request) -> web.Response:
        return self._asset("index.html")

    async def _static(self, request: web.Request) -> web.Response:
        return self._asset(request.match_info["name"])

    def _asset(self, name: str) -> web.Response:
        ctype = _STATIC.get(name)
        if ctype is None:
            raise Refused(404, "not found")
        return web.Response(body=self._assets[name], content_type=ctype, charset="utf-8")

    async def _meta(self, request: web.Request) -> web.Response:
        return json_response(self.meta(self._user(request)))

    async def _state(self, request: web.Request) -> web.Response:
        self._check_read(request)
        return web.Response(body=self._message or b"null", content_type="application/json")

    async def _history(self, request: web.Request) -> web.Response:
        self._check_read(request)
        if self.history is None:
            raise Refused(
                404, "no run log: start serve with --log DIR to see the drift beyond the live minute"
            )
        try:
            window_s = float(request.query.get("window_s", "3600"))
            points = int(request.query.get("points", "600"))
        except ValueError:
            raise Refused(400, "expected window_s (s) and points as numbers") from None
        if not (MIN_WINDOW_S <= window_s <= MAX_WINDOW_S) or not 10 <= points <= MAX_POINTS:
            raise Refused(
                400,
                f"window_s must be in [{MIN_WINDOW_S:g}, {MAX_WINDOW_S:g}] s "
                f"and points in [10, {MAX_POINTS}]",
            )
        key = (window_s, points)
        lock = self._history_lock
        assert lock is not None, "made by _serve() before the routes"
        async with lock:  # one computation at a time, however many browsers
            now = time.monotonic()
            done = self._history_answers.get(key)
            if done is None or now - done[0] > 1.0:
                try:
                    answer = await asyncio.get_running_loop().run_in_executor(
                        None, self.history.window, window_s, points
                    )
                except InputError as exc:  # no meta.json yet: serve has not started logging
                    raise Refused(404, str(exc)) from None
                body = json.dumps(answer, separators=(",", ":"), allow_nan=False).encode()
                self._history_answers = {k: v for k, v in self._history_answers.items() if now - v[0] <= 1.0}
                done = self._history_answers[key] = (time.monotonic(), body)
        return web.Response(body=done[1], content_type="application/json")

    async def _stream(self, request: web.Request) -> web.StreamResponse:
        self._check_read(request)
        if self.clients >= self.config.max_clients:
            return json_response({"error": "too many live clients"}, 503, headers={"Retry-After": "5"})
        self.clients += 1
        loop = asyncio.get_running_loop()
        period = 1.0 / self.config.max_rate_hz if self.config.max_rate_hz > 0 else 0.0
        resp = web.StreamResponse(headers={"Content-Type": "text/event-stream"})
        resp.force_close()  # one stream per connection
        try:
            await resp.prepare(request)
            await self._send(request, resp, b"retry: 2000\n\n")
            seq, last = -1, -math.inf
            while not self._stopping:
                wait = last + period - loop.time()
                if wait > 0:
                    await asyncio.sleep(wait)
                if self._seq == seq:
                    nxt = self._next
                    assert nxt is not None, "made by _serve() before the routes"
                    with contextlib.suppress(TimeoutError):
                        await asyncio.wait_for(asyncio.shield(nxt), KEEPALIVE_COMMENT_S)
                if self._stopping:
                    break
                if self._seq == seq or not self._message:
                    chunk = b": keep-alive\n\n"
                else:
                    seq, last = self._seq, loop.time()
                    chunk = b"data: " + self._message + b"\n\n"
                await self._send(request, resp, chunk)
        except (ConnectionError, TimeoutError):
            # the browser went away or stopped reading: drop it, unsent data and all
            if request.transport is not None:
                request.transport.abort()
        finally:
            self.clients -= 1
        return resp

    async def _send(self, request: web.Request, resp: web.StreamResponse, chunk: bytes) -> None:
        transport = request.transport
        if transport is None or transport.get_write_buffer_size() > MAX_UNSENT_BYTES:
            raise ConnectionResetError("the client does not read")
        async with asyncio.timeout(self.config.send_timeout_s):
            await resp.write(chunk)

    async def _login(self, request: web.Request) -> web.Response:
        data = await self._read_json(request)
        if data is None:
            raise Refused(400, "expected a JSON body")
        user, password = data.get("username"), data.get("password")
        token = None
        if isinstance(user, str) and isinstance(password, str):
            # PBKDF2 takes a while: in a worker thread, so other requests go on meanwhile
            token = await asyncio.get_running_loop().run_in_executor(None, self.login, user, password)
        if token is None:
            lock = self._failed_login
            assert lock is not None, "made by _serve() before the routes"
            async with lock:  # failures one at a time: slows password guessing
                await asyncio.sleep(FAILED_LOGIN_S)
            raise Refused(401, "wrong user name or password")
        resp = json_response({"user": user})
        resp.set_cookie(
            COOKIE,
            token,
            path="/",
            httponly=True,
            samesite="Strict",
            secure=self.ssl_context is not None,
            max_age=int(self.config.session_s),
        )
        return resp

    async def _logout(self, request: web.Request) -> web.Response:
        self.logout(request.cookies.get(COOKIE))
        resp = json_response({"user": None})
        resp.del_cookie(
            COOKIE, path="/", httponly=True, samesite="Strict", secure=self.ssl_context is not None
        )
        return resp

    async def _set_enabled(self, request: web.Request) -> web.Response:
        user = self._user(request)
        if user is None:
            raise Refused(401, "log in to change the compensation")
        data = await self._read_json(request)
        if data is None or not isinstance(data.get("enabled"), bool):
            raise Refused(400, 'expected {"enabled": true|false}')
        if self.control is None:
            raise Refused(409, "no control in this service")
        try:
            # the service may wait on the OPC UA process: not in this loop
            state = await asyncio.get_running_loop().run_in_executor(None, self.control, data["enabled"])
        except Exception as exc:
            log.warning("dashboard: enable/disable by %s failed: %s", user, exc)
            raise Refused(500, f"could not change the state: {exc}") from None
        log.warning(
            "compensation %s by %s from the dashboard (%s)",
            "enabled" if state else "disabled",
            user,
            request.remote,
        )
        state, version = self.enabled_state()
        return json_response({"enabled": state, "enabled_version": version})
