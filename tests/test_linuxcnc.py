"""fbgcomp -> LinuxCNC external axis offsets, with a real (simulated, headless) LinuxCNC.

The machine is examples/linuxcnc (3-axis mill, trivkins, POSIX non-realtime) started by
``fbgcomp.cli.cnc_demo.LinuxCncMachine`` as an unprivileged user; the fbgcomp side is the real
``LinuxCncOutput`` or a real ``fbgcomp serve --cnc linuxcnc`` process. Positions are LinuxCNC's
own (``linuxcnc.stat().actual_position``), read by the machine's headless display.
"""

import os
import signal
import time

import numpy as np
import pytest

import fbgcomp_testing
from fbgcomp.cnc.fbgcomp_hal import (
    FLAG_ALARM,
    FLAG_ENABLED,
    FLAG_STALE,
    PACKET,
    Receiver,
    decode_packet,
    encode_packet,
    limit_step,
    target_for,
)
from fbgcomp.runtime.outputs.linuxcnc import CncConfig, LinuxCncOutput
from test_runtime_support import fbgcomp_process

# LinuxCNC runs one instance per machine (its shared memory): every test that starts it runs on
# one worker when the suite runs in parallel (pytest-xdist, --dist loadgroup)
pytestmark = pytest.mark.xdist_group("linuxcnc")

COUNT_MM = 0.0001  # one eoffset count of the example machine (0.1 µm)


# -- the channel and the limiter, no LinuxCNC needed --------------------------------------


def test_packet_roundtrip_rejects_malformed_and_non_finite():
    data = encode_packet(7, (1.5, -2.25, 3.0), FLAG_ENABLED, sample_time_s=12.5, sent_s=100.0)
    assert len(data) == PACKET.size == 52
    assert decode_packet(data) == (7, FLAG_ENABLED, 100.0, 12.5, (1.5, -2.25, 3.0))
    assert decode_packet(data[:-1]) is None
    assert decode_packet(b"XXXX" + data[4:]) is None
    _seq, flags, *_, corr = decode_packet(encode_packet(8, (float("nan"), 1.0, 2.0), FLAG_ENABLED))
    assert flags & FLAG_ALARM and corr == (0.0, 0.0, 0.0)


def test_limiter_rate_and_magnitude():
    cur = (0.0, 0.0, 0.0)
    path = []
    for _ in range(30):  # 30 steps of 10 ms at 40 µm/s toward (+20, -500, 0.1)
        cur = limit_step(cur, (20.0, -500.0, 0.1), 40.0, 100.0, 0.01)
        path.append(cur)
    path = np.array(path)
    assert np.allclose(np.diff(path[:, 0])[:4], 0.4)  # 40 µm/s * 10 ms
    assert path[-1, 0] == pytest.approx(12.0)  # still ramping after 0.3 s
    assert path[-1, 1] == pytest.approx(-12.0)  # clipped target -100, rate-bound
    assert path[-1, 2] == pytest.approx(0.1)  # small steps land exactly
    for _ in range(1000):
        cur = limit_step(cur, (20.0, -500.0, 0.1), 40.0, 100.0, 0.01)
    assert cur == pytest.approx((20.0, -100.0, 0.1))  # magnitude limit


@pytest.mark.parametrize(
    "flags,link,on,homed,enable,applied",
    [
        (FLAG_ENABLED, True, True, True, True, True),
        (FLAG_ENABLED, True, True, False, True, False),  # not homed
        (FLAG_ENABLED, True, True, True, False, False),  # HAL enable off
        (FLAG_ENABLED, False, True, True, True, False),  # heartbeat lost
        (FLAG_ENABLED | FLAG_ALARM, True, True, True, True, False),
        (FLAG_ENABLED | FLAG_STALE, True, True, True, True, False),
        (0, True, True, True, True, False),  # compensator disabled
        (FLAG_ENABLED, True, False, True, True, False),  # machine off
    ],
)
def test_target_only_when_everything_allows_it(flags, link, on, homed, enable, applied):
    target, active = target_for((5.0, -6.0, 7.0), flags, link, on, homed, enable)
    assert active is applied
    assert target == ((5.0, -6.0, 7.0) if applied else (0.0, 0.0, 0.0))


def test_output_heartbeat_stale_flag_and_goodbye_over_udp():
    rx = Receiver("udp://127.0.0.1:0")
    port = rx.sock.getsockname()[1]
    out = LinuxCncOutput(
        CncConfig(kind="linuxcnc", address=f"udp://127.0.0.1:{port}", heartbeat_s=0.02, stale_s=1.0)
    )
    out.start()
    try:

        class Snap:
            correction_um, sample_time_s, alarm, health = (3.0, -4.0, 5.0), 1.0, False, "OK"

        published_s = time.time()
        out.publish(Snap(), enabled=True)
        # until the sender calls its newest value stale (an event, not a test-side clock);
        # Receiver.drain keeps the newest datagram only, so this sees some of them
        got, end = [], time.monotonic() + 30.0  # a guard only
        while time.monotonic() < end and not (got and got[-1][1] & FLAG_STALE):
            if rx.drain() and (not got or rx.last[0] != got[-1][0]):
                got.append(rx.last)
            time.sleep(0.002)
        seqs = [p[0] for p in got]
        assert len(got) >= 2 and seqs == sorted(set(seqs)), seqs
        # one publication, then heartbeats: the same value again with a new sequence number
        assert all(p[4] == (3.0, -4.0, 5.0) and p[1] & FLAG_ENABLED for p in got)
        assert not got[0][1] & FLAG_STALE and got[-1][1] & FLAG_STALE
        # stale only once stale_s of the sender's own clock has passed since the publication
        assert got[-1][2] - published_s >= 1.0, (got[-1][2], published_s)
    finally:
        out.stop()  # sends its goodbye before it returns
    end = time.monotonic() + 10.0
    while rx.last[1] != 0 and time.monotonic() < end:
        rx.drain()
        time.sleep(0.002)
    assert rx.last[1] == 0 and rx.last[4] == (0.0, 0.0, 0.0)  # goodbye: disabled, zero
    rx.close()


def test_output_over_unix_datagram_socket(tmp_path):
    path = tmp_path / "fbgcomp-cnc.sock"
    rx = Receiver(f"unix://{path}")
    out = LinuxCncOutput(CncConfig(kind="linuxcnc", address=f"unix://{path}"))
    out.start()
    try:
        out.publish_values((1.0, 2.0, -3.0), FLAG_ENABLED | FLAG_ALARM, 5.0)
        end = time.monotonic() + 10.0  # a guard only
        while time.monotonic() < end and rx.last is None:
            rx.drain()
            time.sleep(0.002)
        assert rx.last[1] == FLAG_ENABLED | FLAG_ALARM and rx.last[3:] == (5.0, (1.0, 2.0, -3.0))
    finally:
        out.stop()
        rx.close()
    assert not path.exists()


@pytest.mark.slow
def test_serve_rejects_unknown_cnc_output(runtime_model_and_campaign):
    fbgcomp_testing.require("asyncua")
    model, campaign = runtime_model_and_campaign
    p = fbgcomp_process(
        "serve",
        "--model",
        model,
        "--source",
        f"replay://{campaign}",
        "--opcua",
        "off",
        "--cnc",
        "fanuc",
        "--duration",
        "1",
    )
    _out, err = p.communicate(timeout=60)
    assert p.returncode == 2
    assert err.decode().strip().splitlines()[-1].startswith("error:") and b"fanuc" in err


# -- with LinuxCNC -------------------------------------------------------------------------


@pytest.fixture
def machine(request):
    fbgcomp_testing.require_program("linuxcnc")
    from fbgcomp.cli.cnc_demo import LinuxCncMachine

    settings = getattr(request, "param", {}) or {}
    m = LinuxCncMachine(fbgcomp=settings)
    m.start()
    try:
        yield m
    finally:
        session = m.proc.pid if m.proc else None
        m.stop()
        # LinuxCNC's own shutdown left nothing behind (rtapi_app, milltask, io, components)
        left = []
        for d in os.listdir("/proc"):
            if d.isdigit():
                try:
                    if os.getsid(int(d)) == session:
                        left.append(int(d))
                except (ProcessLookupError, PermissionError):
                    pass
        assert not left, f"processes left behind: {left}"


@pytest.fixture
def output(machine):
    # serve publishes every batch; these tests publish only when the value changes, so the
    # "no publication = stalled compensator" guard (tested above) is set out of the way
    out = LinuxCncOutput(CncConfig(kind="linuxcnc", address=machine.address, stale_s=3600.0))
    out.start()
    yield out
    out.stop()


def _offsets_mm(status):
    return np.array([status["pins"][f"axis.{a}.eoffset"] for a in "xyz"])


def _counts(status):
    return [status["pins"][f"fbgcomp.{a}.counts"] for a in "xyz"]


def _home(machine):
    machine.call("machine_on")
    return machine.call("home")


@pytest.mark.slow
@pytest.mark.parametrize("machine", [{"MAX_RATE_UM_S": 1e6}], indirect=True)
def test_correction_reaches_position_within_one_count_and_bounded_delay(machine, output):
    _home(machine)
    output.publish_values((0.0, 0.0, 0.0), FLAG_ENABLED)
    machine.call("wait_pin", pin="fbgcomp.active", value=1, tol=0, timeout_s=5)
    delays = []
    for corr in [(10.0, -7.3, 4.2), (-25.55, 12.0, -30.0), (3.05, 0.0, -0.15)]:
        t0 = time.time()
        output.publish_values(corr, FLAG_ENABLED)
        want = np.array(corr) / 1000.0  # the machine stands at X0 Y0 Z0
        r = machine.call("wait_position", values=list(want), tol=COUNT_MM, timeout_s=5)
        delays.append(r["reached"] - t0)
        time.sleep(0.1)  # settled: the offset holds the value
        st = machine.status()
        assert np.all(np.abs(np.array(st["actual"]) - want) <= COUNT_MM), st
        # the counts are what the docs say: correction / 0.1 µm, rounded
        assert [st["pins"][f"fbgcomp.{a}.counts"] for a in "xyz"] == [round(c / 0.1) for c in corr]
    # planning a 30 µm offset move at OFFSET_AV_RATIO * MAX_ACCELERATION takes ~50 ms;
    # the channel and the component's 5 ms cycle add a few ms
    print(f"correction -> LinuxCNC position delays: {[round(d * 1000, 1) for d in delays]} ms")
    assert max(delays) < 0.5


def _ramp_rate_um_s(rows, axis_pin, pins):
    """Slope of a ramp in the trace (µm/s), from where it leaves its start to where it hits 0."""
    t = np.array([r[0] for r in rows])
    v = np.array([r[3][pins.index(axis_pin)] for r in rows]) * 1000.0
    moving = np.flatnonzero((np.abs(v) < 0.95 * abs(v[0])) & (np.abs(v) > 0.05 * abs(v[0])))
    assert moving.size >= 5, v
    slope = np.polyfit(t[moving], v[moving], 1)[0]
    return slope, t, v


@pytest.mark.slow
@pytest.mark.parametrize("machine", [{"MAX_RATE_UM_S": 40}], indirect=True)
def test_disable_and_compensator_fault_ramp_to_zero_at_configured_rate(machine, output):
    _home(machine)
    corr = (20.0, -12.0, 8.0)
    output.publish_values(corr, FLAG_ENABLED)
    machine.call("wait_pin", pin="axis.x.eoffset", value=0.02, tol=COUNT_MM / 2, timeout_s=5)
    pins = [f"axis.{a}.eoffset" for a in "xyz"] + ["fbgcomp.fault", "fbgcomp.active"]

    # 1. the machine's enable input (HAL) off: ramp to zero at 40 µm/s
    machine.setp("fbgcomp.enable", 0)
    rows = machine.call("trace", pins=pins, duration_s=0.8, interval_s=0.005)["rows"]
    slope, _t, _v = _ramp_rate_um_s(rows, "axis.x.eoffset", pins)
    assert slope == pytest.approx(-40.0, rel=0.15)
    st = machine.status()
    assert _counts(st) == [0, 0, 0] and not st["pins"]["fbgcomp.active"]
    assert np.all(np.abs(_offsets_mm(st)) < 1e-6)  # zero but for float residue of the sum

    # 2. back on, then the compensator reports ALARM: fault out, ramp to zero at 40 µm/s
    machine.setp("fbgcomp.enable", 1)
    machine.call("wait_pin", pin="axis.x.eoffset", value=0.02, tol=COUNT_MM / 2, timeout_s=5)
    output.publish_values(corr, FLAG_ENABLED | FLAG_ALARM)
    rows = machine.call("trace", pins=pins, duration_s=0.8, interval_s=0.005)["rows"]
    slope, _t, _v = _ramp_rate_um_s(rows, "axis.x.eoffset", pins)
    assert slope == pytest.approx(-40.0, rel=0.15)
    assert rows[-1][3][pins.index("fbgcomp.fault")]
    st = machine.status()
    assert _counts(st) == [0, 0, 0] and np.all(np.abs(_offsets_mm(st)) < 1e-6)
    assert np.all(np.abs(np.array(st["actual"])) <= COUNT_MM / 2)


@pytest.mark.slow
def test_no_offset_before_homing(machine, output):
    machine.call("machine_on")
    output.publish_values((15.0, -15.0, 15.0), FLAG_ENABLED)
    machine.call("wait_pin", pin="fbgcomp.link-ok", value=1, tol=0, timeout_s=10)
    time.sleep(0.5)  # it had time to apply it: it did not
    st = machine.status()
    assert not st["all_homed"] and st["pins"]["fbgcomp.link-ok"]
    assert not st["pins"]["fbgcomp.active"]
    assert _counts(st) == [0, 0, 0]
    assert np.all(_offsets_mm(st) == 0.0) and np.all(np.array(st["actual"]) == 0.0)
    machine.call("home")
    r = machine.call("wait_position", values=[0.015, -0.015, 0.015], tol=COUNT_MM, timeout_s=5)
    assert r["actual"][0] == pytest.approx(0.015, abs=COUNT_MM)


@pytest.mark.slow
def test_gcode_move_ends_at_nominal_plus_correction(machine, output):
    _home(machine)
    corr = np.array([14.7, -9.2, 21.3])  # µm
    output.publish_values(tuple(corr), FLAG_ENABLED)
    machine.call("wait_position", values=list(corr / 1000), tol=COUNT_MM, timeout_s=10)
    prog = machine.run_dir / "move.ngc"
    prog.write_text("G21 G90\nG0 X12 Y7\nG1 X40.5 Y22.25 Z-3 F3000\nG1 X35 F3000\nM2\n")
    os.chmod(prog, 0o644)
    st = machine.call("program", path=str(prog), wait=True, timeout_s=60)
    nominal = np.array([35.0, 22.25, -3.0])
    time.sleep(0.05)
    st = machine.status()
    assert np.all(np.abs(np.array(st["actual"]) - (nominal + corr / 1000)) <= COUNT_MM), st
    # LinuxCNC's commanded position includes the external offset; without it, the program's
    assert np.all(np.abs(np.array(st["position"]) - _offsets_mm(st) - nominal) <= 1e-6)


@pytest.mark.slow
@pytest.mark.parametrize("machine", [{"MAX_RATE_UM_S": 100, "TIMEOUT_S": 0.2}], indirect=True)
def test_serve_drives_linuxcnc_and_heartbeat_loss_ramps_to_zero(machine, runtime_model_and_campaign):
    """A real ``fbgcomp serve --cnc linuxcnc`` on the simulated interrogator; then SIGKILL."""
    fbgcomp_testing.require("asyncua")
    model, campaign = runtime_model_and_campaign
    _home(machine)
    serve = fbgcomp_process(
        "serve",
        "--model",
        model,
        "--source",
        f"sim://{campaign}?rate=200&speed=5",
        "--opcua",
        "off",
        "--cnc",
        "linuxcnc",
        "--cnc-address",
        machine.address,
        "--duration",
        "60",
    )
    try:
        machine.call("wait_pin", pin="fbgcomp.active", value=1, tol=0, timeout_s=30)
        pins = (
            [f"fbgcomp.{a}.request-um" for a in "xyz"]
            + [f"axis.{a}.eoffset" for a in "xyz"]
            + ["fbgcomp.latency-ms"]
        )
        # the output filter averages while it learns the noise, so the correction of this
        # drifting campaign (0.2 µm/s at speed 5) needs a few seconds to be worth seeing
        end = time.monotonic() + 20
        while time.monotonic() < end:
            r = machine.call("trace", pins=pins[:3], duration_s=0.2, interval_s=0.05)["rows"]
            if np.abs([row[3][:3] for row in r]).max() > 10 * COUNT_MM * 1000:
                break
        rows = machine.call("trace", pins=pins, duration_s=1.5, interval_s=0.01)["rows"]
        transit_ms = np.array([r[3][-1] for r in rows])
        print(
            f"serve -> HAL component transit: median {np.median(transit_ms):.2f} ms, "
            f"max {transit_ms.max():.2f} ms"
        )
        assert np.all((transit_ms >= 0) & (transit_ms < 100))
        t = np.array([r[0] for r in rows])
        req_mm = np.array([r[3][:3] for r in rows]) / 1000.0
        actual = np.array([r[2] for r in rows])
        assert np.abs(req_mm).max() > 5 * COUNT_MM  # a correction worth seeing
        # actual = nominal (0) + correction, within one count plus what the correction moves
        # in 0.1 s (channel + component cycle + offset planning + status update)
        drift = np.abs(np.diff(req_mm, axis=0)).max(axis=0) / np.diff(t).min()
        err = np.abs(actual - req_mm)[10:]
        assert np.all(err <= COUNT_MM + drift * 0.1 + 1e-9), (err.max(axis=0), drift)

        # the compensator dies: heartbeat lost -> fault -> ramp to zero at 100 µm/s
        held = machine.status()
        serve.send_signal(signal.SIGKILL)
        serve.wait(10)
        killed = time.time()
        r = machine.call("wait_pin", pin="fbgcomp.fault", value=1, tol=0, timeout_s=2)
        assert r["reached"] - killed < 0.2 + 0.1  # TIMEOUT_S + a cycle and margin
        end = machine.call("wait_position", values=[0, 0, 0], tol=COUNT_MM / 2, timeout_s=5)
        biggest_um = np.abs(_offsets_mm(held)).max() * 1000
        assert end["reached"] - killed < 0.2 + biggest_um / 100.0 + 0.3
    finally:
        if serve.poll() is None:
            serve.kill()
        serve.communicate(timeout=10)


@pytest.mark.slow
def test_cnc_demo_compensates_a_program_and_stops_everything(tmp_path, runtime_model_and_campaign):
    fbgcomp_testing.require_program("linuxcnc")
    fbgcomp_testing.require("asyncua")
    from fbgcomp.cli.cnc_demo import CNC_USER, run_demo

    model, campaign = runtime_model_and_campaign
    prog = tmp_path / "short.ngc"
    # a dwell first: the output filter averages the first seconds while it learns the noise
    # (and leaves changes below 1 µm to its rest fit), so the correction of this drifting
    # campaign is worth seeing only after a few seconds of replay
    prog.write_text("G21 G90\nG4 P6\nG0 X5 Y5\nG1 X25 Y8 F1500\nM2\n")
    lines = []
    res = run_demo(model, campaign, speed=20, program=prog, echo=lines.append)
    text = "\n".join(lines)
    assert "compensated (actual) X Y Z, mm" in text and "ramped back to zero" in text
    final = res["final"]
    offsets = _offsets_mm(final)
    assert np.abs(offsets).max() > 5 * COUNT_MM  # compensation was on at the end
    # end of the program: actual = program end + external offset (two counts: the offset is
    # still following the replayed correction between the status and the pin reads)
    assert np.all(
        np.abs(np.array(final["actual"]) - (np.array([25.0, 8.0, 0.0]) + offsets)) <= 2 * COUNT_MM
    ), final
    rows = res["rows"]
    assert len(rows) > 10
    # nothing of the machine is left: no process of its user (root runs it as CNC_USER)
    if os.geteuid() == 0:
        import pwd

        uid = pwd.getpwnam(CNC_USER).pw_uid
        left = [d for d in os.listdir("/proc") if d.isdigit() and _owner(d) == uid]
        assert not left, left


def _owner(pid):
    try:
        return os.stat(f"/proc/{pid}").st_uid
    except FileNotFoundError:
        return None
