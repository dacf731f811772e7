"""Live dashboard: an HTTP server with Server-Sent Events for a browser on the shop-floor network.

Threads, never the compensation loop:

* :meth:`Dashboard.publish` is called by the service for every processed batch. It only stores
  references to the newest values under a lock (no copy of history, no JSON, no I/O), so the
  compensation loop is never slowed by the dashboard, however many browsers watch it.
* A broadcaster thread wakes at most ``max_rate_hz`` times a second (default 10), turns the
  newest values into one small JSON message (sensor elongations, temperatures, predicted
  deviation, correction, health, fallback, latency; ~0.6 kB) and bumps a sequence number.
* Each browser has its own handler thread (``ThreadingHTTPServer``) that sends the newest
  message whenever the sequence number moves: a slow client simply skips messages (latest
  wins) and a client that stops reading times out on its own socket; nobody else waits for it.

Access: everything is readable without login. The enable/disable control needs a user name and
password (``users_file`` with lines ``name:pbkdf2_sha256$...`` as made by
``fbgcomp.runtime.opcua.hash_password``, or ``FBGCOMP_DASHBOARD_USER`` /
``FBGCOMP_DASHBOARD_PASSWORD`` in the environment; nothing is built in). A login sets a random
session cookie (HttpOnly, SameSite=Strict); state-changing requests must also be JSON, which a
cross-site form cannot send. The control calls back into the service, which toggles the very
``Enabled`` state the OPC UA server exposes.

Static assets (HTML, JS, CSS) are files of this package, hand-written, no CDN: the page works
on a network without internet access.
"""

from __future__ import annotations

import json
import logging
import math
import os
import secrets
import threading
import time
from dataclasses import dataclass
from http import HTTPStatus
from http.cookies import SimpleCookie
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from typing import Callable

import numpy as np

from fbgcomp.errors import InputError
from fbgcomp.runtime.health import flag_names

log = logging.getLogger("fbgcomp.dashboard")

STATIC_DIR = Path(__file__).resolve().parent / "static"
_STATIC = {"index.html": "text/html; charset=utf-8",
           "dashboard.js": "text/javascript; charset=utf-8",
           "dashboard.css": "text/css; charset=utf-8"}
COOKIE = "fbgcomp_session"
AXES = ("dx", "dy", "dz")


@dataclass
class DashboardConfig:
    listen: str = ""                 # HOST:PORT; empty = no dashboard
    users_file: str | None = None    # lines name:pbkdf2_sha256$... (see module docstring)
    max_rate_hz: float = 10.0        # updates per second per client, at most
    max_clients: int = 32            # concurrent live streams; more get 503
    session_s: float = 8 * 3600.0    # a login lasts one shift
    send_timeout_s: float = 5.0      # a client not reading for this long is dropped


def parse_listen(listen: str) -> tuple[str, int]:
    """``HOST:PORT`` (``[::1]:8080`` for IPv6) -> (host, port); InputError otherwise."""
    host, sep, port = listen.rpartition(":")
    host = host.strip("[]")
    if not sep or not host or not port.isdigit() or not 0 <= int(port) <= 65535:
        raise InputError(f"expected HOST:PORT, e.g. 0.0.0.0:8080, got {listen!r}",
                         column="--dashboard")
    return host, int(port)


def load_users(users_file: str | Path | None, environ=os.environ) -> dict[str, str]:
    """User -> password hash, from ``users_file`` and ``FBGCOMP_DASHBOARD_USER/PASSWORD``."""
    from fbgcomp.runtime.opcua import load_users as load

    return load(users_file, environ, service="dashboard", env_prefix="FBGCOMP_DASHBOARD",
                doc="docs/dashboard.md", iterations=20_000)


def _clean(values, digits: int) -> list:
    """Floats rounded for the wire; NaN/inf (no value) become null."""
    out = []
    for v in np.asarray(values, dtype=float).ravel():
        out.append(round(float(v), digits) if math.isfinite(v) else None)
    return out


class Dashboard:
    """The dashboard server. ``start``/``stop`` from any thread; ``publish`` from the service."""

    def __init__(self, config: DashboardConfig, sensor_names, probe_names, model_id: str = "",
                 control: Callable[[bool], bool] | None = None,
                 enabled: Callable[[], bool] | None = None):
        self.config = config
        self.host, self.port = parse_listen(config.listen)
        self.sensor_names = list(sensor_names)
        self.probe_names = list(probe_names)
        self.model_id = model_id
        self.control = control
        self.enabled = enabled or (lambda: True)
        self.users = load_users(config.users_file)
        self.sessions: dict[str, tuple[str, float]] = {}   # token -> (user, expiry monotonic)
        self.clients = 0
        self.messages = 0
        self._latest = None
        self._lock = threading.Lock()
        self._new = threading.Event()
        self._cond = threading.Condition()
        self._seq = 0
        self._message = b""
        self._stopping = threading.Event()
        self._feature_maps: dict = {}
        # (value, version) of Enabled as last seen here: the version grows on every change, so
        # the page can tell a frame built before a switch from one built after it
        self._enabled_seen: tuple[bool | None, int] = (None, 0)
        self._enabled_lock = threading.Lock()
        self._httpd: ThreadingHTTPServer | None = None
        self._threads: list[threading.Thread] = []

    # -- service side -------------------------------------------------------------------
    def publish(self, snapshot, temperature_C, pipeline) -> None:
        """Newest sample (non-blocking: references only; the broadcaster does the work)."""
        item = (snapshot, temperature_C, pipeline.model, pipeline.wavelength_zero_nm,
                pipeline.temperature_zero_C, time.time())
        with self._lock:
            self._latest = item
        self._new.set()

    def start(self) -> None:
        handler = _make_handler(self)
        try:
            self._httpd = _Server((self.host, self.port), handler)
        except OSError as exc:
            raise InputError(f"cannot listen on {self.host}:{self.port}: {exc.strerror}",
                             column="--dashboard") from None
        self.port = self._httpd.server_address[1]
        for target, name in ((self._httpd.serve_forever, "fbgcomp-dashboard-http"),
                             (self._broadcast_loop, "fbgcomp-dashboard-push")):
            t = threading.Thread(target=target, name=name, daemon=True)
            t.start()
            self._threads.append(t)
        log.info("dashboard on http://%s:%d/ (%d user(s) may control)", self.host, self.port,
                 len(self.users))

    def stop(self) -> None:
        self._stopping.set()
        self._new.set()
        with self._cond:
            self._cond.notify_all()
        if self._httpd is not None:
            self._httpd.shutdown()
            self._httpd.server_close()
        for t in self._threads:
            t.join(2.0)

    # -- broadcaster -----------------------------------------------------------------------
    def _broadcast_loop(self) -> None:
        period = 1.0 / self.config.max_rate_hz if self.config.max_rate_hz > 0 else 0.0
        last = 0.0
        while not self._stopping.is_set():
            self._new.wait(1.0)
            if self._stopping.is_set():
                return
            wait = last + period - time.monotonic()
            if wait > 0:
                time.sleep(wait)   # decimation: whatever arrives meanwhile, the newest wins
            self._new.clear()
            with self._lock:
                item, self._latest = self._latest, None
            if item is None:
                continue
            last = time.monotonic()
            try:
                message = self._message_for(*item)
            except Exception:  # never let one odd sample stop the live view
                log.exception("dashboard: cannot encode a sample")
                continue
            with self._cond:
                self._message = message
                self._seq += 1
                self.messages += 1
                self._cond.notify_all()

    def _elongations(self, model, wavelength_nm, temperature_C, w0, t0):
        if w0 is None:
            return np.full(len(self.sensor_names), np.nan)
        key = id(model)
        fmap = self._feature_maps.get(key)
        if fmap is None:
            # ΔS as the runtime sees it: every model type exposes its sensors and probes
            from fbgcomp.features import FeatureMap
            try:
                fmap = FeatureMap(list(model.sensors), list(model.probe_names), False)
            except (AttributeError, KeyError, TypeError):
                fmap = False   # a model without sensor metadata: no elongations to show
            self._feature_maps = {key: fmap}   # one model at a time (reload replaces it)
        if fmap is False:
            return np.full(len(self.sensor_names), np.nan)
        with np.errstate(invalid="ignore"):
            base = fmap.base(np.asarray(wavelength_nm, float)[None, :],
                             np.asarray(temperature_C, float)[None, :], w0, t0)
        return base[0, :len(self.sensor_names)]

    def _message_for(self, snap, temperature_C, model, w0, t0, published_s) -> bytes:
        elong = self._elongations(model, snap.sensor_wavelength_nm, temperature_C, w0, t0)
        enabled, enabled_version = self.enabled_state()
        frame = {
            "t": snap.sample_time_s,
            "elongation_um": _clean(elong, 3),
            "wavelength_nm": _clean(snap.sensor_wavelength_nm, 5),
            "temperature_C": _clean(temperature_C, 3),
            "deviation_um": _clean(snap.deviation_um, 3),
            "half_width_um": _clean(snap.half_width_um, 3),
            "correction_um": _clean(snap.correction_um, 3),
            "expected_rms_um": _clean(snap.expected_rms_um, 3),
            "health": snap.health, "alarm": bool(snap.alarm), "fallback": snap.fallback,
            # per axis: the flag word (fbgcomp.runtime.health.FLAG_*) and its names
            "output_flags": [int(v) for v in getattr(snap, "output_flags", (0, 0, 0))],
            "output_flag_names": [flag_names(v) for v in getattr(snap, "output_flags", (0, 0, 0))],
            "limited": any(int(v) for v in getattr(snap, "output_flags", (0, 0, 0))),
            "sensor_status": list(snap.sensor_status), "source_status": snap.source_status,
            "frames": int(snap.frames), "model_id": snap.model_id or self.model_id,
            # a frame may reach the page after the answer to a switch it predates: the page
            # keeps the state of the newest version it has seen
            "enabled": enabled, "enabled_version": enabled_version,
            # sample time stamp -> correction computed (interrogator clock vs. this host)
            "latency_ms": round((published_s - snap.sample_time_s) * 1e3, 2),
            # batch received -> correction computed (this host only)
            "processing_ms": round((published_s - snap.received_s) * 1e3, 2)
            if snap.received_s else None,
        }
        return json.dumps(frame, separators=(",", ":"), allow_nan=False).encode()

    def enabled_state(self) -> tuple[bool, int]:
        """Enabled now and its version (+1 on every change seen), read under one lock so that
        versions and values stay in step across the broadcaster and the request threads."""
        with self._enabled_lock:
            value = bool(self.enabled())
            last, version = self._enabled_seen
            if value != last:
                version += 1
                self._enabled_seen = (value, version)
            return value, version

    def wait_message(self, after_seq: int, timeout_s: float) -> tuple[int, bytes]:
        with self._cond:
            self._cond.wait_for(lambda: self._seq != after_seq or self._stopping.is_set(),
                                timeout_s)
            return self._seq, self._message

    # -- sessions -------------------------------------------------------------------------
    def login(self, user: str, password: str) -> str | None:
        from fbgcomp.runtime.opcua import verify_password

        stored = self.users.get(user)
        if stored is None or not verify_password(password, stored):
            return None
        token = secrets.token_urlsafe(32)
        now = time.monotonic()
        with self._lock:
            self.sessions = {k: v for k, v in self.sessions.items() if v[1] > now}
            self.sessions[token] = (user, now + self.config.session_s)
        return token

    def session_user(self, token: str | None) -> str | None:
        if not token:
            return None
        with self._lock:
            entry = self.sessions.get(token)
        if entry is None or entry[1] < time.monotonic():
            return None
        return entry[0]

    def logout(self, token: str | None) -> None:
        with self._lock:
            self.sessions.pop(token or "", None)

    def meta(self, user: str | None) -> dict:
        return {"sensors": self.sensor_names, "probes": self.probe_names, "axes": list(AXES),
                "model_id": self.model_id, "max_rate_hz": self.config.max_rate_hz,
                "user": user, "login_possible": bool(self.users),
                "control_available": self.control is not None,
                **dict(zip(("enabled", "enabled_version"), self.enabled_state()))}


class _Server(ThreadingHTTPServer):
    daemon_threads = True
    allow_reuse_address = True
    request_queue_size = 64


def _make_handler(dash: Dashboard):
    class Handler(BaseHTTPRequestHandler):
        server_version = "fbgcomp-dashboard"
        sys_version = ""
        protocol_version = "HTTP/1.1"

        def log_message(self, fmt, *args):  # quiet: the service log is for the machine
            log.debug("%s " + fmt, self.client_address[0], *args)

        # -- helpers
        def _token(self) -> str | None:
            cookie = SimpleCookie()
            try:
                cookie.load(self.headers.get("Cookie", ""))
            except Exception:
                return None
            morsel = cookie.get(COOKIE)
            return morsel.value if morsel else None

        def _send(self, status, body: bytes, ctype="application/json", headers=()):
            self.send_response(status)
            self.send_header("Content-Type", ctype)
            self.send_header("Content-Length", str(len(body)))
            self.send_header("Cache-Control", "no-store")
            self.send_header("X-Content-Type-Options", "nosniff")
            self.send_header("X-Frame-Options", "DENY")
            self.send_header("Referrer-Policy", "no-referrer")
            self.send_header("Content-Security-Policy",
                             "default-src 'self'; img-src 'self' data:; object-src 'none'; "
                             "frame-ancestors 'none'; base-uri 'none'; form-action 'self'")
            for k, v in headers:
                self.send_header(k, v)
            self.end_headers()
            if self.command != "HEAD":
                self.wfile.write(body)

        def _json(self, status, data, headers=()):
            self._send(status, json.dumps(data).encode(), headers=headers)

        def _read_json(self):
            try:
                length = int(self.headers.get("Content-Length", "0"))
            except ValueError:
                length = -1
            if not 0 <= length <= 4096:
                self.close_connection = True   # cannot skip an unknown body: start afresh
                return None
            # read the body whatever it is: left unread it would be parsed as the next request
            body = self.rfile.read(length) if length else b""
            if self.headers.get_content_type() != "application/json" or not body:
                return None
            try:
                data = json.loads(body)
            except (ValueError, UnicodeDecodeError):
                return None
            return data if isinstance(data, dict) else None

        # -- GET
        def do_GET(self):  # noqa: N802 - http.server naming
            path = self.path.split("?", 1)[0]
            if path in ("/", "/index.html"):
                return self._static("index.html")
            if path.startswith("/static/"):
                return self._static(path[len("/static/"):])
            if path == "/api/meta":
                return self._json(200, dash.meta(dash.session_user(self._token())))
            if path == "/api/state":
                with dash._cond:
                    message = dash._message
                return self._send(200, message or b"null")
            if path == "/api/stream":
                return self._stream()
            self._json(404, {"error": "not found"})

        do_HEAD = do_GET

        def _static(self, name):
            ctype = _STATIC.get(name)
            if ctype is None:
                return self._json(404, {"error": "not found"})
            self._send(200, (STATIC_DIR / name).read_bytes(), ctype)

        def _stream(self):
            with dash._lock:
                if dash.clients >= dash.config.max_clients:
                    full = True
                else:
                    full = False
                    dash.clients += 1
            if full:
                return self._json(503, {"error": "too many live clients"},
                                  headers=[("Retry-After", "5")])
            try:
                self.connection.settimeout(dash.config.send_timeout_s)
                self.send_response(200)
                self.send_header("Content-Type", "text/event-stream")
                self.send_header("Cache-Control", "no-store")
                self.send_header("X-Content-Type-Options", "nosniff")
                self.send_header("Connection", "close")
                self.end_headers()
                self.close_connection = True
                self.wfile.write(b"retry: 2000\n\n")
                self.wfile.flush()
                seq = -1
                period = 1.0 / dash.config.max_rate_hz if dash.config.max_rate_hz > 0 else 0.0
                last = 0.0
                while not dash._stopping.is_set():
                    wait = last + period - time.monotonic()
                    if wait > 0:
                        time.sleep(wait)
                    new_seq, message = dash.wait_message(seq, 15.0)
                    if dash._stopping.is_set():
                        break
                    if new_seq == seq or not message:
                        self.wfile.write(b": keep-alive\n\n")   # proxies and dead peers
                    else:
                        seq = new_seq
                        last = time.monotonic()
                        self.wfile.write(b"data: " + message + b"\n\n")
                    self.wfile.flush()
            except (OSError, ValueError):
                pass   # the browser went away or stopped reading: drop it
            finally:
                with dash._lock:
                    dash.clients -= 1

        # -- POST
        def do_POST(self):  # noqa: N802
            path = self.path.split("?", 1)[0]
            if path == "/api/login":
                data = self._read_json()
                if data is None:
                    return self._json(400, {"error": "expected a JSON body"})
                user, password = data.get("username"), data.get("password")
                token = None
                if isinstance(user, str) and isinstance(password, str):
                    token = dash.login(user, password)
                if token is None:
                    time.sleep(0.5)   # this thread only: slows password guessing
                    return self._json(401, {"error": "wrong user name or password"})
                cookie = (f"{COOKIE}={token}; Path=/; HttpOnly; SameSite=Strict; "
                          f"Max-Age={int(dash.config.session_s)}")
                return self._json(200, {"user": user}, headers=[("Set-Cookie", cookie)])
            if path == "/api/logout":
                dash.logout(self._token())
                return self._json(200, {"user": None}, headers=[
                    ("Set-Cookie", f"{COOKIE}=; Path=/; HttpOnly; SameSite=Strict; Max-Age=0")])
            if path == "/api/enabled":
                user = dash.session_user(self._token())
                if user is None:
                    return self._json(401, {"error": "log in to change the compensation"})
                data = self._read_json()
                if data is None or not isinstance(data.get("enabled"), bool):
                    return self._json(400, {"error": 'expected {"enabled": true|false}'})
                if dash.control is None:
                    return self._json(409, {"error": "no control in this service"})
                try:
                    state = dash.control(data["enabled"])
                except Exception as exc:
                    log.warning("dashboard: enable/disable by %s failed: %s", user, exc)
                    return self._json(500, {"error": f"could not change the state: {exc}"})
                log.warning("compensation %s by %s from the dashboard (%s)",
                            "enabled" if state else "disabled", user, self.client_address[0])
                state, version = dash.enabled_state()
                return self._json(200, {"enabled": state, "enabled_version": version})
            self._json(404, {"error": "not found"})

    return Handler
