"""Live dashboard: the real ``fbgcomp serve --dashboard`` process fed by the simulated Hyperion
interrogator, watched by Debian's chromium and by plain SSE clients; the control is checked
against the OPC UA server's Enabled node with a real secure asyncua client; the connection limits,
the default bind, login for reads beyond loopback and TLS are checked on real sockets.
Rates are checked against the server's own sequence numbers and clock (``seq``, ``server_s`` in
every message), never against the test's wall clock, which a loaded machine stretches.
Screenshots go to test-artifacts/dashboard/."""

from __future__ import annotations

import asyncio
import concurrent.futures
import datetime as dt
import ipaddress
import json
import selectors
import shutil
import signal
import socket
import ssl
import subprocess
import threading
import time
import urllib.error
import urllib.request
from pathlib import Path

import pytest

import fbgcomp_testing
from test_runtime_support import fallback_peak_um, fbgcomp_process, free_port, secure_client, wait_port

ARTIFACTS = Path(__file__).resolve().parent.parent / "test-artifacts" / "dashboard"
CHROMIUM_ARGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--no-first-run",
]
ENV = {
    "FBGCOMP_DASHBOARD_USER": "engineer",
    "FBGCOMP_DASHBOARD_PASSWORD": "dash-pass-123",
    "FBGCOMP_OPCUA_USER": "operator",
    "FBGCOMP_OPCUA_PASSWORD": "opc-pass-123",
}
RATE_HZ = 200  # interrogator frames per second: far more than the page's 10 updates/s
MAX_RATE_HZ = 10.0  # the dashboard's default max_rate_hz
REQUEST_TIMEOUT_S = 5.0  # the dashboard's default request_timeout_s
MAX_CONNECTIONS = 64  # the dashboard's default max_connections

# every test here starts serve, chromium or both (10-35 s each under load)
pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def service(tmp_path_factory, runtime_model_and_campaign):
    fbgcomp_testing.require("asyncua")
    model, campaign = runtime_model_and_campaign
    tmp = tmp_path_factory.mktemp("dashboard")
    dp, op = free_port(), free_port()
    url = f"opc.tcp://127.0.0.1:{op}/fbgcomp/"
    proc = fbgcomp_process(
        "serve",
        "--model",
        model,
        "--source",
        f"sim://{campaign}?rate={RATE_HZ}&loop=1",
        "--opcua",
        url,
        "--state-dir",
        tmp / "state",
        "--dashboard",
        str(dp),  # host: default
        env=ENV,
    )

    def ready():
        if proc.poll() is not None:
            raise AssertionError(f"serve exited with {proc.returncode} during start-up")
        try:
            return _get(f"http://127.0.0.1:{dp}/api/state") is not None
        except OSError:  # refused or reset while the service is still starting
            return False

    try:
        wait_port(dp, 40)
        wait_port(op, 40)
        _wait_for(ready, 30)
    except BaseException as exc:  # whatever went wrong, show what the service said
        proc.kill()
        stderr = proc.communicate(timeout=5)[1].decode()[-3000:]
        raise AssertionError(f"{type(exc).__name__}: {exc}\nserve stderr:\n{stderr}") from exc
    yield {"base": f"http://127.0.0.1:{dp}", "port": dp, "opcua": url, "state": tmp / "state", "proc": proc}
    proc.send_signal(signal.SIGTERM)
    try:
        _, err = proc.communicate(timeout=20)
    except subprocess.TimeoutExpired:
        proc.kill()
        raise
    assert proc.returncode == 0, err.decode()[-3000:]


def _get(url):
    with urllib.request.urlopen(url, timeout=5) as r:
        return json.loads(r.read())


def _wait_for(predicate, timeout_s):
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        value = predicate()
        if value:
            return value
        time.sleep(0.1)
    raise AssertionError("condition not met in time")


class SseReader(threading.Thread):
    """A plain Server-Sent-Events client counting the messages and bytes it receives, until it
    has ``messages`` of them spanning ``t_span_s`` of sample time (the stream's pace, not the
    test's clock, decides how long)."""

    def __init__(self, port, messages, t_span_s=0.0, timeout_s=60.0):
        super().__init__(daemon=True)
        self.port, self.messages, self.t_span_s, self.timeout_s = port, messages, t_span_s, timeout_s
        self.events, self.bytes, self.frames = 0, 0, []

    def run(self):
        with socket.create_connection(("127.0.0.1", self.port), timeout=5) as s:
            s.sendall(b"GET /api/stream HTTP/1.1\r\nHost: x\r\nAccept: text/event-stream\r\n\r\n")
            f = s.makefile("rb")
            end = time.monotonic() + self.timeout_s  # a guard only
            while not self.done() and time.monotonic() < end:
                line = f.readline()
                if not line:
                    break
                self.bytes += len(line)
                if line.startswith(b"data: "):
                    self.events += 1
                    self.frames.append(json.loads(line[6:]))

    def done(self) -> bool:
        return self.events >= self.messages and self.frames[-1]["t"] - self.frames[0]["t"] >= self.t_span_s


def _assert_decimated(sent: int, server_span_s: float) -> None:
    """At most MAX_RATE_HZ messages per second of the server's own clock. No lower bound on the
    rate: a loaded machine sends fewer (that messages flow is checked by waiting for them)."""
    assert sent >= 1 and server_span_s > 0, (sent, server_span_s)
    assert sent <= server_span_s * MAX_RATE_HZ * 1.02 + 1, (sent, server_span_s)


def _assert_stream(reader: SseReader) -> None:
    """A plain SSE client got increasing, decimated messages of a few hundred bytes each."""
    seqs = [f["seq"] for f in reader.frames]
    assert reader.done(), (seqs, [f["t"] for f in reader.frames[:: max(1, len(seqs) // 10)]])
    assert seqs == sorted(set(seqs)), seqs  # none twice, none out of order
    sent = seqs[-1] - seqs[0]
    span = reader.frames[-1]["server_s"] - reader.frames[0]["server_s"]
    _assert_decimated(sent, span)
    assert 0.3 * sent <= len(seqs) - 1 <= sent, (len(seqs), sent)
    assert reader.bytes / span < 10_000, reader.bytes  # a few kB/s per client


def _enabled_on_opcua(service) -> bool:
    from asyncua import ua

    async def read():
        client = await secure_client(
            service["opcua"], service["state"], ENV["FBGCOMP_OPCUA_USER"], ENV["FBGCOMP_OPCUA_PASSWORD"]
        )
        # the server admits only clients in its trust list (as `fbgcomp trust add` fills it)
        trusted = service["state"] / "opcua" / "trusted"
        trusted.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(service["state"] / "client_cert.der", trusted / "dashboard-test-client.der")
        async with client:
            return await client.get_node(ua.NodeId("FbgComp.Enabled", 2)).read_value()

    # in a thread of its own: Playwright's sync API already runs an event loop in this one
    with concurrent.futures.ThreadPoolExecutor(1) as pool:
        return bool(pool.submit(lambda: asyncio.run(read())).result(60))


def _browser(p):
    chromium = fbgcomp_testing.require_program("chromium")
    return p.chromium.launch(executable_path=chromium, args=CHROMIUM_ARGS)


def _wait_for_badge(page, state):
    page.wait_for_function(
        "s => document.getElementById('enabled-badge').dataset.state === s || "
        "document.getElementById('control-error').textContent !== ''",
        arg=state,
        timeout=20000,
    )
    assert page.inner_text("#control-error") == ""
    assert page.get_attribute("#enabled-badge", "data-state") == state


def _chart_pixels(page, canvas_id):
    return page.evaluate(f"document.getElementById('{canvas_id}').toDataURL()")


def test_live_page_shows_values_that_move_with_the_interrogator_among_ten_clients(service):
    sync_api = fbgcomp_testing.require("playwright.sync_api")
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    others = [SseReader(service["port"], 30) for _ in range(9)]  # the page is the 10th client
    for r in others:
        r.start()
    with sync_api.sync_playwright() as p:
        browser = _browser(p)
        try:
            page = browser.new_page(viewport={"width": 1280, "height": 1000})
            requested = []
            page.on("request", lambda r: requested.append(r.url))
            page.goto(service["base"] + "/")
            page.wait_for_function("() => window.fbgcomp && window.fbgcomp.updates >= 3", timeout=15000)
            probe = (
                "({u: fbgcomp.updates, f: fbgcomp.last.frames, t: fbgcomp.last.t, "
                "seq: fbgcomp.last.seq, s: fbgcomp.last.server_s})"
            )
            before = page.evaluate(probe)
            texts0 = [page.inner_text(f"#corr-{a}") for a in ("dx", "dy", "dz")]
            dl0 = page.inner_text("#sensors tbody tr:first-child td.dl")
            charts0 = {
                c: _chart_pixels(page, c)
                for c in ("chart-elongation", "chart-temperature", "chart-deviation", "chart-correction")
            }
            # wait for the stream, not the clock: a few more updates and 2 s of sample time
            page.wait_for_function(
                "b => fbgcomp.updates >= b.u + 5 && fbgcomp.last.t >= b.t + 2.0 && "
                "fbgcomp.last.server_s > b.s",
                arg=before,
                timeout=60000,
            )
            after = page.evaluate(probe)
            # decimated to <= 10 messages per second of the server's own clock, and the page
            # (one of ten clients) got them all or nearly: it cannot get more than were sent
            received, sent = after["u"] - before["u"], after["seq"] - before["seq"]
            _assert_decimated(sent, after["s"] - before["s"])
            assert 0.3 * sent <= received <= sent, (received, sent)
            # every frame of the interval was processed: frames count with sample time
            assert after["f"] - before["f"] >= 0.9 * (after["t"] - before["t"]) * RATE_HZ
            assert after["t"] >= before["t"] + 2.0  # sample time stamps moved on
            texts1 = [page.inner_text(f"#corr-{a}") for a in ("dx", "dy", "dz")]
            assert texts1 != texts0 and all(t != "—" for t in texts1)
            assert page.inner_text("#sensors tbody tr:first-child td.dl") != dl0
            for c, pixels in charts0.items():
                assert _chart_pixels(page, c) != pixels, c  # every chart redrew new data
            assert page.inner_text("#health").startswith("OK")
            assert page.inner_text("#link") == "live"
            statuses = page.locator("#sensors tbody td.status").all_inner_texts()
            assert statuses == ["OK"] * 5
            assert float(page.inner_text("#latency")) < 1000.0
            assert page.inner_text("#fallback") == "none (full model)"
            # the page itself, its script and style: nothing from outside this server
            assert all(u.startswith(service["base"]) for u in requested), requested
            page.screenshot(path=str(ARTIFACTS / "live.png"), full_page=True)
        finally:
            browser.close()
    for r in others:
        r.join(60)
        assert not r.is_alive()
        _assert_stream(r)


def test_control_needs_login_and_switches_the_opcua_enabled_state(service):
    sync_api = fbgcomp_testing.require("playwright.sync_api")
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    # without a session the control is refused at the server, not only greyed out in the page
    req = urllib.request.Request(
        service["base"] + "/api/enabled",
        method="POST",
        data=b'{"enabled": false}',
        headers={"Content-Type": "application/json"},
    )
    with pytest.raises(urllib.error.HTTPError) as err:
        urllib.request.urlopen(req, timeout=5)
    assert err.value.code == 401
    assert _enabled_on_opcua(service) is True

    with sync_api.sync_playwright() as p:
        browser = _browser(p)
        try:
            context = browser.new_context(viewport={"width": 1280, "height": 1000})
            page = context.new_page()
            page.goto(service["base"] + "/")
            page.wait_for_function("() => window.fbgcomp && window.fbgcomp.updates >= 2", timeout=15000)
            assert page.is_disabled("#toggle")
            page.fill("#username", "engineer")
            page.fill("#password", "wrong-password")
            page.click("#login")
            page.wait_for_function("() => document.getElementById('control-error').textContent !== ''")
            assert "wrong user name or password" in page.inner_text("#control-error")
            assert page.is_disabled("#toggle")
            page.screenshot(path=str(ARTIFACTS / "login-refused.png"))

            page.fill("#password", ENV["FBGCOMP_DASHBOARD_PASSWORD"])
            page.click("#login")
            page.wait_for_selector("#user-line:not([hidden])")
            assert page.inner_text("#user") == "engineer"
            assert page.is_hidden("#login-form")
            assert page.is_enabled("#toggle")
            (cookie,) = [c for c in context.cookies() if c["name"] == "fbgcomp_session"]
            assert cookie["httpOnly"] and cookie["sameSite"] == "Strict"
            assert "fbgcomp_session" not in page.evaluate("document.cookie")
            # a cross-site form could only send text/plain: refused even with the session
            status = page.evaluate(
                "fetch('/api/enabled', {method: 'POST', body: "
                "'{\"enabled\": false}', headers: {'Content-Type': "
                "'text/plain'}}).then(r => r.status)"
            )
            assert status == 400

            # every state the badge shows from now on: a frame built before the switch but
            # delivered after its answer must not turn it back (a clean-clone run saw exactly
            # that: DISABLED, then ENABLED again with no error)
            page.evaluate("""() => { const b = document.getElementById('enabled-badge');
                window.badgeLog = [];
                new MutationObserver(() => window.badgeLog.push(b.dataset.state))
                    .observe(b, {attributes: true, attributeFilter: ['data-state']}); }""")
            page.click("#toggle")
            _wait_for_badge(page, "DISABLED")
            assert _enabled_on_opcua(service) is False
            # the published correction is zero while disabled (the prediction goes on)
            page.wait_for_function("() => fbgcomp.last && !fbgcomp.last.enabled", timeout=20000)
            n = page.evaluate("fbgcomp.updates")
            page.wait_for_function(f"() => fbgcomp.updates >= {n + 3}", timeout=20000)
            last = page.evaluate("fbgcomp.last")
            assert last["correction_um"] == [0.0, 0.0, 0.0]
            assert any(abs(v) > 0 for v in last["deviation_um"])
            assert page.inner_text("#corr-dx") in ("0.000", "-0.000")
            shown = page.evaluate("window.badgeLog")
            assert "ENABLED" not in shown[shown.index("DISABLED") :], shown
            page.screenshot(path=str(ARTIFACTS / "control-disabled.png"), full_page=True)

            page.click("#toggle")
            _wait_for_badge(page, "ENABLED")
            assert _enabled_on_opcua(service) is True
            page.click("#logout")
            page.wait_for_selector("#login-form:not([hidden])")
            assert page.is_disabled("#toggle")
        finally:
            browser.close()


def test_a_client_that_stops_reading_blocks_no_one(service):
    stalled = socket.socket()
    stalled.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1024)
    stalled.connect(("127.0.0.1", service["port"]))
    stalled.sendall(b"GET /api/stream HTTP/1.1\r\nHost: x\r\n\r\n")  # and never read again
    try:
        state0 = _get(service["base"] + "/api/state")
        readers = [SseReader(service["port"], 10, t_span_s=1.5) for _ in range(3)]
        for r in readers:
            r.start()
        for r in readers:
            r.join(60)
        for r in readers:
            _assert_stream(r)
            times = [f["t"] for f in r.frames]
            assert times == sorted(times) and times[-1] - times[0] > 1.0
        state1 = _get(service["base"] + "/api/state")
        # the compensation loop never waited: every frame since was processed
        assert state1["t"] > state0["t"] + 1.0
        assert state1["frames"] - state0["frames"] >= 0.9 * (state1["t"] - state0["t"]) * RATE_HZ
    finally:
        stalled.close()


def _state_or_none(base, context=None):
    try:
        with urllib.request.urlopen(base + "/api/state", timeout=5, context=context) as r:
            return json.loads(r.read())
    except OSError:  # not listening yet, or reset while starting
        return None


def _stop(*procs) -> list[str]:
    """SIGTERM, then the stderr of each process."""
    for proc in procs:
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
    errs = []
    for proc in procs:
        try:
            err = proc.communicate(timeout=20)[1]
        except subprocess.TimeoutExpired:
            proc.kill()
            err = proc.communicate()[1]
        errs.append(err.decode(errors="replace"))
    return errs


def test_a_lost_grating_shows_as_degraded_with_the_fallback_in_use(tmp_path, runtime_model_and_campaign):
    """A separate simulated instrument; once the service has taken its zero state with all five
    gratings, the instrument is restarted with S3 gone (MISSING: seen at the zero, lost after).

    The fault is not timed from the instrument's start: a service that connects after it (a
    loaded machine) would take its zero without S3, which is NO_ZERO, another state."""
    sync_api = fbgcomp_testing.require("playwright.sync_api")
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    model, campaign = runtime_model_and_campaign
    # a bound below the fallback's largest correction on each axis (its switch-over step
    # passes it at once) but never 3x beyond it: the output is held back (MAX_LIMITED,
    # DEGRADED), not refused (ALARM, which a correction beyond 3x the bound raises)
    bound = fallback_peak_um(model, campaign, "S3") / 2.2
    sp, cp, dp = free_port(), free_port(), free_port()
    sim_args = ("sim-interrogator", campaign, "--port", sp, "--command-port", cp, "--rate", RATE_HZ, "--loop")
    sim = fbgcomp_process(*sim_args)
    serve = fbgcomp_process(
        "serve",
        "--model",
        model,
        "--source",
        f"hyperion://127.0.0.1:{sp}?command_port={cp}",
        "--temperatures",
        campaign,
        "--opcua",
        "off",
        "--dashboard",
        f"127.0.0.1:{dp}",
        "--log",
        tmp_path / "runlog",
        "--max-correction-um",
        ",".join(f"{b:g}" for b in bound),
    )
    base = f"http://127.0.0.1:{dp}"
    try:
        wait_port(dp, 40)

        def zeroed_with_all_five():
            # health may already be DEGRADED: the bound also holds the full model back
            state = _state_or_none(base)
            return (
                bool(state) and state["health"] in ("OK", "DEGRADED") and state["sensor_status"] == ["OK"] * 5
            )

        _wait_for(zeroed_with_all_five, 60)
        _stop(sim)
        sim = fbgcomp_process(*sim_args, "--fault", "drop:S3@0")  # the service reconnects
        with sync_api.sync_playwright() as p:
            browser = _browser(p)
            try:
                page = browser.new_page(viewport={"width": 1280, "height": 1000})
                page.goto(base + "/")
                # DEGRADED alone may still be the first instrument's frames (the bound holds the
                # full model back) before the service sees its link go (ALARM): wait for the
                # fallback itself
                page.wait_for_function(
                    "() => window.fbgcomp && fbgcomp.last && fbgcomp.last.health === 'DEGRADED'"
                    " && fbgcomp.last.fallback === 'S3'",
                    timeout=60000,
                )
                n = page.evaluate("fbgcomp.updates")
                page.wait_for_function(f"() => fbgcomp.updates >= {n + 3}", timeout=10000)
                assert page.inner_text("#health").startswith("DEGRADED")
                assert page.get_attribute("#health", "data-state") == "DEGRADED"
                assert page.inner_text("#fallback") == "without S3"
                statuses = page.locator("#sensors tbody td.status").all_inner_texts()
                assert statuses == ["OK", "OK", "MISSING", "OK", "OK"], statuses
                assert page.inner_text("#sensors tbody tr:nth-child(3) td.wl") == "—"
                assert page.inner_text("#corr-dx") != "—"  # the fallback still corrects
                # a frame held back at the maximum, read with what the page shows of it in one
                # evaluation (the next frame may no longer be limited)
                shown = page.wait_for_function(
                    "() => fbgcomp.last.limited && ({limited: fbgcomp.last.limited,"
                    " flags: fbgcomp.last.output_flags, names: fbgcomp.last.output_flag_names,"
                    " banner: !document.getElementById('limited').hidden,"
                    " text: ['dx', 'dy', 'dz'].map(a => document.getElementById('flags-' + a).textContent)})",
                    timeout=10000,
                ).json_value()
                assert shown["limited"] and shown["banner"], shown
                j = next(k for k, v in enumerate(shown["flags"]) if v & 16)
                assert "MAX_LIMITED" in shown["names"][j]
                assert "MAX_LIMITED" in shown["text"][j]
                # no dashboard user configured: nothing to log in to, the control stays off
                assert page.is_hidden("#login-form") and page.is_disabled("#toggle")
                page.screenshot(path=str(ARTIFACTS / "degraded-fallback.png"), full_page=True)
            finally:
                browser.close()

        # serve hands its --log folder to the dashboard: the drift window counts the lost
        # grating's frames and the held-back ones from what the run log holds
        def history_shows_the_fault():
            d = _get(base + "/api/history?window_s=60&points=60")
            return d if sum(d["counts"].get("sensor:S3", [0])) > 0 else None

        d = _wait_for(history_shows_the_fault, 20)
        assert d["frames"] > 0 and sum(d["counts"]["health:DEGRADED"]) > 0
    finally:
        _stop(serve, sim)


def _listening_ips(pid: int, port: int) -> set[str]:
    import psutil

    proc = psutil.Process(pid)
    conns = proc.net_connections("tcp") if hasattr(proc, "net_connections") else proc.connections("tcp")
    return {c.laddr.ip for c in conns if c.status == psutil.CONN_LISTEN and c.laddr.port == port}


def test_the_dashboard_binds_loopback_unless_told_otherwise(service):
    fbgcomp_testing.require("psutil")
    # the fixture gave --dashboard PORT, no host
    assert _listening_ips(service["proc"].pid, service["port"]) == {"127.0.0.1"}


def _closed_by_server(socks, deadline_s):
    """Read every socket until the server closes it: {socket: (seconds, bytes received)}."""
    sel = selectors.DefaultSelector()
    for s in socks:
        s.setblocking(False)
        sel.register(s, selectors.EVENT_READ)
    t0, got, closed = time.monotonic(), dict.fromkeys(socks, b""), {}
    while len(closed) < len(socks) and time.monotonic() - t0 < deadline_s:
        for key, _ in sel.select(0.2):
            s = key.fileobj
            try:
                data = s.recv(65536)
            except BlockingIOError:  # nothing after all: wait again
                continue
            except ConnectionResetError:
                data = b""
            if data:
                got[s] += data
            else:
                closed[s] = (time.monotonic() - t0, got[s])
                sel.unregister(s)
    sel.close()
    return closed


def test_half_sent_requests_are_dropped_and_the_server_still_answers(service):
    """The finding: 200 clients sending half a request held 200 threads for over 10 s."""
    psutil = fbgcomp_testing.require("psutil")
    proc = psutil.Process(service["proc"].pid)
    threads0 = proc.num_threads()
    state0 = _get(service["base"] + "/api/state")
    socks = []
    try:
        for i in range(200):
            s = socket.create_connection(("127.0.0.1", service["port"]), timeout=5)
            if i < 20:  # a complete head, then a body that never comes
                s.sendall(
                    b"POST /api/login HTTP/1.1\r\nHost: x\r\nContent-Type: "
                    b'application/json\r\nContent-Length: 200\r\n\r\n{"user'
                )
            else:  # half a head
                s.sendall(b"GET /api/state HTTP/1.1\r\nHost: x\r\nAccept: ")
            socks.append(s)
        assert proc.num_threads() <= threads0 + 4  # no thread per connection
        t_opened = time.monotonic()
        closed = _closed_by_server(socks, 3 * REQUEST_TIMEOUT_S)
        waited = time.monotonic() - t_opened
        assert len(closed) == 200, f"{200 - len(closed)} still open after {waited:.1f} s"
        busy = [s for s, (_, data) in closed.items() if data.startswith(b"HTTP/1.1 503")]
        held = [t for s, (t, data) in closed.items() if s not in busy]
        # at most max_connections held, each dropped after the request timeout (a body: plus
        # <= 1 s to read the answer), the others refused at once
        assert len(held) <= MAX_CONNECTIONS and len(busy) >= 200 - MAX_CONNECTIONS
        assert max(held) <= REQUEST_TIMEOUT_S + 1.0 + 2.0, max(held)
        assert max(t for s, (t, _) in closed.items() if s in busy) < 2.0
        timed_out = [data for s, (_, data) in closed.items() if data.startswith(b"HTTP/1.1 408")]
        assert timed_out, "no half-sent body was answered 408"
    finally:
        for s in socks:
            s.close()
    # and it still answers, and the compensation loop never waited
    state1 = _get(service["base"] + "/api/state")
    assert state1["frames"] - state0["frames"] >= 0.9 * (state1["t"] - state0["t"]) * RATE_HZ
    assert state1["t"] > state0["t"]
    with urllib.request.urlopen(service["base"] + "/", timeout=5) as r:
        assert r.status == 200 and b"fbgcomp live" in r.read()


def test_beyond_loopback_without_a_user_serve_refuses_to_start(runtime_model_and_campaign):
    model, campaign = runtime_model_and_campaign
    dp = free_port()
    proc = fbgcomp_process(
        "serve",
        "--model",
        model,
        "--source",
        f"sim://{campaign}?rate=50",
        "--opcua",
        "off",
        "--dashboard",
        f"0.0.0.0:{dp}",
        env={"FBGCOMP_DASHBOARD_USER": "", "FBGCOMP_DASHBOARD_PASSWORD": ""},
    )
    try:
        _, err = proc.communicate(timeout=120)
    except subprocess.TimeoutExpired:
        proc.kill()
        raise
    lines = err.decode().strip().splitlines()
    assert proc.returncode == 2, err.decode()[-2000:]
    assert len(lines) == 1 and lines[0].startswith("error:"), lines
    assert "dashboard" in lines[0] and "127.0.0.1" in lines[0], lines[0]


def _self_signed(folder: Path) -> tuple[Path, Path]:
    """A certificate for 127.0.0.1 and its key, PEM files (cryptography: the runtime extra)."""
    fbgcomp_testing.require("cryptography")
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import NameOID

    key = ec.generate_private_key(ec.SECP256R1())
    name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "fbgcomp dashboard test")])
    now = dt.datetime.now(dt.UTC)
    cert = (
        x509.CertificateBuilder()
        .subject_name(name)
        .issuer_name(name)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - dt.timedelta(minutes=5))
        .not_valid_after(now + dt.timedelta(days=1))
        .add_extension(
            x509.SubjectAlternativeName([x509.IPAddress(ipaddress.ip_address("127.0.0.1"))]), critical=False
        )
        .sign(key, hashes.SHA256())
    )
    cert_path, key_path = folder / "dashboard.crt", folder / "dashboard.key"
    cert_path.write_bytes(cert.public_bytes(serialization.Encoding.PEM))
    key_path.write_bytes(
        key.private_bytes(
            serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption()
        )
    )
    return cert_path, key_path


def test_beyond_loopback_every_read_needs_a_login_over_tls(tmp_path, runtime_model_and_campaign):
    sync_api = fbgcomp_testing.require("playwright.sync_api")
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    model, campaign = runtime_model_and_campaign
    cert, key = _self_signed(tmp_path)
    dp = free_port()
    serve = fbgcomp_process(
        "serve",
        "--model",
        model,
        "--source",
        f"sim://{campaign}?rate={RATE_HZ}&loop=1",
        "--opcua",
        "off",
        "--dashboard",
        f"0.0.0.0:{dp}",
        "--dashboard-cert",
        cert,
        "--dashboard-key",
        key,
        env=ENV,
    )
    base = f"https://127.0.0.1:{dp}"
    tls = ssl.create_default_context(cafile=str(cert))

    def get(path, cookie=None):
        req = urllib.request.Request(base + path, headers={"Cookie": cookie} if cookie else {})
        with urllib.request.urlopen(req, timeout=5, context=tls) as r:
            return r.status, dict(r.headers), r.read()

    try:
        wait_port(dp, 40)
        # without a login: the page (to log in) and who may log in, nothing about the machine.
        # An open port is not yet a server that answers: on a loaded host serve's start-up held
        # the dashboard's thread past its 5 s TLS handshake timeout and the first handshake was
        # reset (CI of 2026-12-06). The first page is asked again until it comes, for 30 s.
        deadline = time.monotonic() + 30
        while True:
            try:
                status, _, body = get("/")
                break
            except (urllib.error.URLError, ConnectionError, ssl.SSLError, TimeoutError):
                if serve.poll() is not None:
                    pytest.fail(f"serve exited {serve.returncode}: {serve.stderr.read().decode()[-3000:]}")
                if time.monotonic() > deadline:
                    raise
                time.sleep(0.5)
        assert status == 200 and b"fbgcomp live" in body
        meta = json.loads(get("/api/meta")[2])
        assert meta == {"user": None, "login_possible": True, "read_login": True}, meta
        for path in ("/api/state", "/api/stream"):
            with pytest.raises(urllib.error.HTTPError) as err:
                get(path)
            assert err.value.code == 401, path
        # plain HTTP on the TLS port gets nothing
        with socket.create_connection(("127.0.0.1", dp), timeout=10) as s:
            s.sendall(b"GET /api/state HTTP/1.1\r\nHost: x\r\n\r\n")
            try:
                reply = s.recv(4096)
            except ConnectionResetError:
                reply = b""
            assert b"frames" not in reply and not reply.startswith(b"HTTP/1.1 200")
        # a login over TLS: the cookie is Secure too
        req = urllib.request.Request(
            base + "/api/login",
            method="POST",
            data=json.dumps({"username": "engineer", "password": ENV["FBGCOMP_DASHBOARD_PASSWORD"]}).encode(),
            headers={"Content-Type": "application/json"},
        )
        with urllib.request.urlopen(req, timeout=10, context=tls) as r:
            set_cookie = r.headers["Set-Cookie"]
        attributes = {a.strip().split("=")[0].lower() for a in set_cookie.split(";")}
        assert {"secure", "httponly", "samesite", "path"} <= attributes, set_cookie
        assert "samesite=strict" in set_cookie.lower()
        cookie = set_cookie.split(";")[0]
        _wait_for(lambda: json.loads(get("/api/state", cookie)[2]) is not None, 30)
        assert json.loads(get("/api/state", cookie)[2])["frames"] > 0
        # the page: a login form first, the live values after logging in
        with sync_api.sync_playwright() as p:
            browser = _browser(p)
            try:
                context = browser.new_context(
                    ignore_https_errors=True, viewport={"width": 1280, "height": 1000}
                )
                page = context.new_page()
                # until the service has said whether a login is possible (/api/meta, held
                # here), the page shows no login form: it came with the HTML, and on a loaded
                # host the form stood before the link said LOGIN (CI of 2026-12-06)
                held = []
                page.route("**/api/meta", lambda route: held.append(route))
                page.goto(base + "/")
                deadline = time.monotonic() + 20
                while not held and time.monotonic() < deadline:
                    page.wait_for_timeout(50)
                assert held, "the page never asked /api/meta"
                assert page.is_hidden("#login-form")
                assert page.get_attribute("#link", "data-state") == "CONNECTING"
                held[0].continue_()
                page.unroute("**/api/meta")  # (continues any request it still holds)
                page.wait_for_selector("#login-form:not([hidden])")
                assert page.get_attribute("#link", "data-state") == "LOGIN"
                assert page.evaluate("fbgcomp.updates") == 0
                assert page.inner_text("#access-note") == "Login needed to read"
                page.fill("#username", "engineer")
                page.fill("#password", ENV["FBGCOMP_DASHBOARD_PASSWORD"])
                page.click("#login")
                page.wait_for_function("() => fbgcomp.updates >= 3", timeout=20000)
                assert page.inner_text("#link") == "live"
                assert page.inner_text("#corr-dx") != "—"
                page.screenshot(path=str(ARTIFACTS / "tls-after-login.png"), full_page=True)
                page.click("#logout")  # reloads: nothing stays on screen
                page.wait_for_selector("#login-form:not([hidden])")
                page.wait_for_timeout(500)
                assert page.evaluate("fbgcomp.updates") == 0
            finally:
                browser.close()
    finally:
        (err,) = _stop(serve)
    assert "without TLS" not in err, err[-2000:]
