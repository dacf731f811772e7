"""The correction in the form a CNC's PLC takes (issue 15, item 5): offset + Z slope per axis,
rate- and magnitude-limited, as Modbus TCP holding registers read by a real pymodbus client on
loopback - from the output object alone and from a real ``fbgcomp serve`` fed by a real
simulated interrogator."""

from __future__ import annotations

import itertools
import time
import types

import numpy as np
import pytest

import fbgcomp_testing
from test_runtime_support import free_port, modbus_serve_config, serve_with_simulator

# one worker runs the module: its served scenario (a module fixture, ~20 s) is then served once
pytestmark = pytest.mark.xdist_group("runtime_modbus")

ENV = {"FBGCOMP_OPCUA_USER": "operator", "FBGCOMP_OPCUA_PASSWORD": "modbus-pass-123"}


def _regs(client, unit=1):
    r = client.read_holding_registers(0, count=29, device_id=unit)
    assert not r.isError(), r
    return list(r.registers)


def _decoded(regs):
    """The documented table (fbgcomp.runtime.outputs.modbus docstring), decoded the PLC's way."""
    from fbgcomp.runtime.outputs.modbus import decode_int32

    i32 = lambda a: decode_int32(regs[a], regs[a + 1])  # noqa: E731
    return dict(
        layout=regs[0],
        health=regs[1],
        enabled=regs[2],
        apply=regs[3],
        sequence=(regs[4] << 16) | regs[5],
        z_ref_mm=i32(6) * 0.001,
        offset_um=np.array([i32(8 + 2 * a) for a in range(3)]) * 0.1,
        slope_um_per_m=np.array([i32(14 + 2 * a) for a in range(3)]) * 0.01,
        flags=np.array(regs[20:23]),
        correction_um=np.array([i32(23 + 2 * a) for a in range(3)]) * 0.1,
    )


# ---------------------------------------------------------------- offset / slope, pure maths
def test_slope_of_a_z_dependent_model_is_its_finite_difference_and_predicts_other_z():
    from fbgcomp.models.kinematic import KinematicModel
    from fbgcomp.runtime.outputs.cnc_form import reference_z_mm, takes_z, z_slope_um_per_m

    model = KinematicModel().fit()
    p = model.predictor()
    w0 = np.array([s.lambda0_nm for s in model.sensors])
    t0 = np.full(len(model.probe_names), 20.0)
    rng = np.random.default_rng(3)
    w = w0 + rng.normal(scale=0.03, size=w0.size)  # bars stretched by tens of µm
    t = t0 + 1.5
    z0 = reference_z_mm(p)
    assert takes_z(p) and z0 == pytest.approx(model.machine_.supports.z_axis_mm)

    def correction(z):
        return -p.predict(w[None], t[None], w0, t0, z_axis_mm=z)[0][0]

    slope = z_slope_um_per_m(p, w, t, w0, t0, z0)
    # independently: least-squares line of the model's own correction over the same ±10 mm
    zs = z0 + np.linspace(-10, 10, 5)
    fit = np.polyfit(zs, np.array([correction(z) for z in zs]), 1)[0] * 1000.0  # µm/m
    assert np.abs(slope).max() > 100.0  # this model does depend on Z
    np.testing.assert_allclose(slope, fit, rtol=0.02, atol=0.05)
    # the offset + slope form gives the model 5 mm away far better than the offset alone
    for dz in (-5.0, 5.0):
        line = correction(z0) + slope * dz / 1000.0
        miss_line = np.abs(line - correction(z0 + dz))
        miss_offset = np.abs(correction(z0) - correction(z0 + dz))
        assert (miss_line <= 0.1 * miss_offset + 0.01).all(), (miss_line, miss_offset)
    # the default Z (None) is the reference position
    np.testing.assert_allclose(z_slope_um_per_m(p, w, t, w0, t0, None), slope)


def test_slope_is_zero_for_a_model_without_z(runtime_model_and_campaign):
    from fbgcomp.models.registry import load_model
    from fbgcomp.runtime.outputs.cnc_form import takes_z, z_slope_um_per_m

    model_path, _ = runtime_model_and_campaign
    model = load_model(model_path)
    p = model.predictor()
    w0 = np.array([s.lambda0_nm for s in model.sensors])
    t0 = np.full(len(model.probe_names), 20.0)
    assert not takes_z(p)
    np.testing.assert_array_equal(z_slope_um_per_m(p, w0 + 0.05, t0 + 1, w0, t0, 300.0), 0.0)


def test_slope_leaves_a_predictor_with_memory_as_it_was():
    """A predictor with state (its filters) gives the same next prediction whether or not the
    slope was taken in between."""
    from fbgcomp.runtime.outputs.cnc_form import z_slope_um_per_m

    class Stateful:
        def __init__(self):
            self.state = 0.0

        def chain(self, z):
            return types.SimpleNamespace(z_axis_mm=100.0)

        def predict(self, w, t, w0, t0, *, z_axis_mm=None, time_s=None):
            self.state = self.state + 1.0  # memory: every call counts
            d = np.full((1, 3), self.state) * np.array([1.0, 0.0, 2.0]) * (z_axis_mm or 0) / 1000
            return d, np.zeros((1, 3))

    p = Stateful()
    slope = z_slope_um_per_m(p, [1.0], [20.0], [1.0], [20.0], None, dz_mm=10.0)
    assert p.state == 0.0
    # state 1 at z-10, state 2 at z+10: the difference the stub makes, in µm/m
    expected = -(2 * 110 - 1 * 90) / 20.0 * np.array([1.0, 0.0, 2.0])
    np.testing.assert_allclose(slope, expected)


def test_limit_toward_rate_and_maximum():
    from fbgcomp.runtime.outputs.cnc_form import limit_toward

    v, rate, cap = limit_toward([0.0, 0.0, 5.0], [100.0, -3.0, np.nan], 0.5, [20.0] * 3, [50.0, 50.0, 50.0])
    np.testing.assert_allclose(v, [10.0, -3.0, 0.0])  # NaN target ramps out toward 0
    assert rate.tolist() == [True, False, False] and cap.tolist() == [True, False, False]
    v, _, cap = limit_toward(v, [100.0, -3.0, 0.0], 100.0, [20.0] * 3, [50.0] * 3)
    np.testing.assert_allclose(v, [50.0, -3.0, 0.0])  # held at the maximum
    assert cap[0]
    v, rate, _ = limit_toward(v, [0.0, 0.0, 0.0], -1.0, [20.0] * 3, [50.0] * 3)
    np.testing.assert_allclose(v, [50.0, -3.0, 0.0])  # time going back moves nothing
    assert rate[:2].all()


# ---------------------------------------------------------- the output object, real client
def test_registers_read_by_a_real_client_limits_and_refused_writes():
    fbgcomp_testing.require("pymodbus")
    from pymodbus.client import ModbusTcpClient

    from fbgcomp.runtime.outputs.modbus import ModbusConfig, ModbusOutput

    now = [0.0]
    port = free_port()
    out = ModbusOutput(
        ModbusConfig(
            listen=f"127.0.0.1:{port}",
            unit_id=3,
            offset_rate_um_per_s=10,
            max_offset_um=[30, 30, 500],
            slope_rate_um_per_m_per_s=4,
            max_slope_um_per_m=5,
        ),
        clock=lambda: now[0],
    )
    out.start()
    client = ModbusTcpClient("127.0.0.1", port=port, timeout=3)
    try:
        assert client.connect()
        first = _decoded(_regs(client, 3))
        assert first["layout"] == 1 and first["health"] == 3 and first["sequence"] == 0
        snap = types.SimpleNamespace(
            correction_um=(-123.44, 7.26, 420.0), health="OK", output_flags=(0, 8, 2)
        )
        out.publish(snap, True, [3.0, -12.5, 0.0], 812.5)  # t = 0: starts from zero
        for k in range(1, 11):  # then 0.5 s apart
            now[0] = 0.5 * k
            out.publish(snap, True, [3.0, -12.5, 0.0], 812.5)
        d = _decoded(_regs(client, 3))
        assert d["sequence"] == 11 and d["health"] == 0 and d["enabled"] == 1 and d["apply"] == 1
        assert d["z_ref_mm"] == pytest.approx(812.5)
        np.testing.assert_allclose(d["correction_um"], [-123.4, 7.3, 420.0], atol=0.05 + 1e-9)
        # 5 s at 10 µm/s: X held at -30 by its maximum, Y reached, Z still ramping
        np.testing.assert_allclose(d["offset_um"], [-30.0, 7.3, 50.0], atol=0.05 + 1e-9)
        np.testing.assert_allclose(d["slope_um_per_m"], [3.0, -5.0, 0.0], atol=0.005 + 1e-9)
        # X offset held by its maximum; Y: the pipeline's RATE_LIMITED + slope at its maximum;
        # Z: the model's CLAMPED + offset rate-limited here
        assert d["flags"].tolist() == [512, 8 | 2048, 2 | 256]
        # writes refused (ILLEGAL FUNCTION), the table unchanged
        for w in (client.write_register(8, 1, device_id=3), client.write_registers(8, [0, 0], device_id=3)):
            assert w.isError() and w.exception_code == 1
        assert _decoded(_regs(client, 3))["offset_um"].tolist() == d["offset_um"].tolist()
        # ALARM: nothing to apply, the slope ramps out, the offset follows the pipeline's ramp
        alarm = types.SimpleNamespace(correction_um=(0.0, 0.0, 0.0), health="ALARM", output_flags=(0, 0, 0))
        now[0] += 1.0
        out.publish(alarm, True, [3.0, -12.5, 0.0], 812.5)
        a = _decoded(_regs(client, 3))
        assert a["health"] == 2 and a["apply"] == 0 and a["sequence"] == 12
        np.testing.assert_allclose(a["offset_um"], [-20.0, 0.0, 40.0], atol=0.05 + 1e-9)
        np.testing.assert_allclose(a["slope_um_per_m"], [0.0, -1.0, 0.0], atol=0.005 + 1e-9)
    finally:
        client.close()
        out.stop()
    assert out.writes_refused == 2


def test_busy_port_is_a_one_line_error():
    fbgcomp_testing.require("pymodbus")
    import socket

    from fbgcomp.errors import InputError
    from fbgcomp.runtime.outputs.modbus import ModbusConfig, ModbusOutput

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        port = s.getsockname()[1]
        with pytest.raises(InputError, match=r"modbus\.listen"):
            ModbusOutput(ModbusConfig(listen=f"127.0.0.1:{port}")).start()
    with pytest.raises(InputError, match="HOST:PORT"):
        ModbusOutput(ModbusConfig(listen="5020"))


# ------------------------------------------------------------------ a real serve, end to end
# session scope: the module's tests share one worker (xdist_group), but the worker may run other
# modules' tests between them, and a module-scoped fixture was then built again (CI of
# 2026-11-29: twice: 30 and 29 s)
@pytest.fixture(scope="session")
def served(tmp_path_factory, runtime_model_and_campaign):
    fbgcomp_testing.require("asyncua")
    fbgcomp_testing.require("pyarrow")
    fbgcomp_testing.require("pymodbus")
    from pymodbus.client import ModbusTcpClient

    from fbgcomp.runtime.log import read_log

    model_path, campaign = runtime_model_and_campaign
    tmp = tmp_path_factory.mktemp("modbus")
    port = free_port()
    rate = 2.0
    config = modbus_serve_config(port, rate)
    reads, writes = [], []
    with serve_with_simulator(tmp, config, model_path, campaign, ENV, ("--rate", 1000, "--speed", 30)) as run:
        client = ModbusTcpClient("127.0.0.1", port=port, timeout=3)
        assert client.connect()
        end = time.monotonic() + 60
        alarm_since = None
        while time.monotonic() < end:
            t = time.time()
            d = _decoded(_regs(client))
            d["sim_done"] = run.sim.poll() is not None
            reads.append((t, d))
            if len(reads) == 100:
                writes.append(client.write_register(8, 7, device_id=1))
            if d["health"] == 2:
                alarm_since = alarm_since or time.monotonic()
                if np.abs(d["offset_um"]).max() == 0 or time.monotonic() - alarm_since > 15:
                    break
            else:
                # an ALARM the data's return ended (a host too loaded to stream for no_data_s)
                # is not the end of the data
                alarm_since = None
            time.sleep(0.05)
        client.close()
        alive = run.serve.poll() is None
    _meta, log = read_log(tmp / "log")
    return dict(reads=reads, writes=writes, log=log, rate=rate, alive=alive)


def _final_alarm(reads) -> int:
    """Index of the first read of the last ALARM episode (the data's end), the reads' timeline
    in the message where there is none or it began before the simulator had finished."""
    health = [d["health"] for _, d in reads]
    first = next((i for i in range(len(health) - 1, -1, -1) if health[i] != 2), -1) + 1
    t0 = reads[0][0]
    timeline = "; ".join(
        f"{t - t0:.2f}s h{d['health']} seq{d['sequence']} off{d['offset_um'].tolist()} sim_done {d['sim_done']}"
        for t, d in reads[max(first - 5, 0) : first + 5]
    )
    assert first < len(health), f"no ALARM at the end of the data: {timeline}"
    # the simulator exits a moment after its last frame; the ALARM follows no_data_s (0.2 s)
    # later, so a read or two may still see the simulator's process alive
    assert any(d["sim_done"] for _, d in reads[first:]), f"an ALARM while the data still came: {timeline}"
    return first


def test_serve_publishes_the_logged_correction_in_the_documented_scale(served):
    assert served["alive"]
    log, reads = served["log"], served["reads"]
    rx = log["received_s"].to_numpy()
    corr = log[["corr_dx_um", "corr_dy_um", "corr_dz_um"]].to_numpy()
    checked = 0
    for t, d in reads:
        if d["health"] != 0:
            continue
        near = (rx <= t + 0.5) & (rx > t - 1.0)  # t: just before the request was sent
        if not near.any() or np.abs(d["correction_um"]).max() < 1.0:
            continue
        # the published sample is one the run log holds, to the register's 0.1 µm
        err = np.abs(corr[near] - d["correction_um"]).max(axis=1).min()
        assert err <= 0.05 + 1e-6, (t, d["correction_um"], err)
        checked += 1
    assert checked >= 20
    assert all(
        d["layout"] == 1 and d["z_ref_mm"] == 0 and not d["slope_um_per_m"].any() for _, d in reads
    )  # the regression model has no Z term


def test_heartbeat_advances_and_writes_are_refused(served):
    seqs = [d["sequence"] for _, d in served["reads"]]
    assert all(b >= a for a, b in itertools.pairwise(seqs))
    assert len(set(seqs)) >= 10  # it advances while the PLC polls
    (w,) = served["writes"]
    assert w.isError() and w.exception_code == 1


def test_a_step_of_the_correction_reaches_the_registers_rate_limited(served):
    """When the data stop the pipeline ramps its correction to zero within ramp_s (0.5 s): a
    step of several µm for the PLC. The published offset follows at the configured rate."""
    reads, rate = served["reads"], served["rate"]
    # The limiter runs on publication times. A sample read at t1 was published before t1; one
    # first seen with sequence s was published after the last read that still saw an older
    # sequence. So between two samples the offset moves at most rate x (t1 - that read's time),
    # however late a loaded machine publishes (assuming it at most 0.1 s late failed under load).
    # (sequences never decrease: test_heartbeat_advances_and_writes_are_refused)
    since, boundary = [], None  # per read: the time of the last read of an older sequence
    for k, (_, d) in enumerate(reads):
        if k and d["sequence"] != reads[k - 1][1]["sequence"]:
            boundary = reads[k - 1][0]
        since.append(boundary)
    checked = 0
    for i, ((_, a), (t1, b)) in enumerate(itertools.pairwise(reads)):
        if since[i] is None:
            continue
        assert np.abs(b["offset_um"] - a["offset_um"]).max() <= rate * (t1 - since[i]) + 0.1 + 1e-6
        checked += 1
    assert checked >= 20
    first = _final_alarm(reads)
    t_step, before = reads[first - 1][0], reads[first - 1][1]["offset_um"]
    axis = int(np.argmax(np.abs(before)))
    assert abs(before[axis]) > 5.0, [(t - t_step, d["health"], d["offset_um"]) for t, d in reads[-40:]]
    ramp = [(t - t_step, d) for t, d in reads[first:] if d["offset_um"][axis] != 0]
    lags = [abs(d["offset_um"][axis] - d["correction_um"][axis]) for _, d in ramp]
    assert max(lags) > 4.0  # the correction went, the offset lags
    assert sum(bool(d["flags"][axis] & 256) for _, d in ramp) >= 0.9 * len(ramp) >= 10
    # it ramps at the configured rate: slope of |offset| over the ramp
    tt = np.array([t for t, _ in ramp])
    mag = np.array([abs(d["offset_um"][axis]) for _, d in ramp])
    assert -np.polyfit(tt, mag, 1)[0] == pytest.approx(rate, rel=0.15)


def test_alarm_when_the_data_stops_and_the_offset_ramps_out(served):
    reads = served["reads"]
    health = [d["health"] for _, d in reads]
    assert 0 in health and health[-1] == 2
    first = _final_alarm(reads)
    after = [(t, d) for t, d in reads[first:]]
    assert all(d["apply"] == 0 and d["health"] == 2 for _, d in after)
    # the pipeline's own correction is ramped to zero within its ramp_s (0.5 s) ...
    t_alarm = after[0][0]
    late = [(round(t - t_alarm, 2), d["correction_um"].tolist()) for t, d in after if t > t_alarm + 1.0]
    assert all(not any(c) for _, c in late), late[:10]
    # ... and the published offset follows at the configured rate, never growing
    mags = [np.abs(d["offset_um"]) for _, d in after]
    assert all((b <= a + 1e-9).all() for a, b in itertools.pairwise(mags))
    assert not after[-1][1]["offset_um"].any() or after[-1][0] - t_alarm > 14
