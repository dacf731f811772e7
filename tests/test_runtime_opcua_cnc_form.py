"""The offset + Z slope form a CNC's PLC takes (issue 15, item 5) over OPC UA: per axis
``OffsetX_um``, ``SlopeX_um_per_m`` and the reference ``ZRef_mm``, AnalogItemType variables
(units in tests/test_runtime_opcua.py), carrying the numbers the Modbus output publishes -
read with a real asyncua client beside a real pymodbus client on loopback."""

from __future__ import annotations

import asyncio
import time

import numpy as np
import pytest

import fbgcomp_testing
from test_runtime_modbus import ENV, _decoded, _regs
from test_runtime_opcua import TRUSTED, server_factory, trusted_client  # noqa: F401 (fixture)
from test_runtime_support import free_port, modbus_serve_config, serve_with_simulator

NAMES = [f"Offset{a}_um" for a in "XYZ"] + [f"Slope{a}_um_per_m" for a in "XYZ"] + ["ZRef_mm"]


def _snapshot(correction_um, health="OK", flags=(0, 0, 0)):
    from fbgcomp.runtime.outputs.opcua import Snapshot

    return Snapshot(
        sample_time_s=time.time(),
        correction_um=tuple(correction_um),
        deviation_um=tuple(-c for c in correction_um),
        half_width_um=(1.0,) * 3,
        expected_rms_um=(0.5,) * 3,
        health=health,
        fallback="",
        alarm=health == "ALARM",
        sensor_status=["OK", "OK"],
        sensor_wavelength_nm=[1530.0, 1540.0],
        output_flags=tuple(flags),
    )


async def _read_when(client, expect_z_ref, timeout_s=5.0):
    """The seven variables once ZRef_mm shows ``expect_z_ref`` (the last one written)."""
    from asyncua import ua

    end = time.monotonic() + timeout_s
    nodes = [client.get_node(ua.NodeId(f"FbgComp.{n}", 2)) for n in NAMES]
    # ZRef_mm is written after the offsets and slopes: read it first
    while await nodes[-1].read_value() != pytest.approx(expect_z_ref):
        assert time.monotonic() < end, f"ZRef_mm never became {expect_z_ref}"
        await asyncio.sleep(0.05)
    return dict(zip(NAMES, [await n.read_value() for n in nodes]))


def _kinematic_slope():
    """Slope (3,) µm/m and reference Z (mm) of a Z-dependent model (the kinematic type on the
    built-in ram) for a stretched frame: what cnc_form computes in serve."""
    from fbgcomp.models.kinematic import KinematicModel
    from fbgcomp.runtime.outputs.cnc_form import reference_z_mm, z_slope_um_per_m

    model = KinematicModel().fit()
    p = model.predictor()
    w0 = np.array([s.lambda0_nm for s in model.sensors])
    t0 = np.full(len(model.probe_names), 20.0)
    w = w0 + np.random.default_rng(3).normal(scale=0.03, size=w0.size)
    z_ref = reference_z_mm(p)
    return z_slope_um_per_m(p, w, t0 + 1.5, w0, t0, z_ref), z_ref


def test_a_limit_that_is_off_passes_the_first_sample():
    """rate 0 (off) is an infinite rate: the first sample (0 s since none) goes through, and
    is not NaN (which no later sample would repair)."""
    from fbgcomp.runtime.outputs.cnc_form import limit_toward
    from fbgcomp.runtime.pipeline import per_axis

    v, rate, cap = limit_toward(np.zeros(3), [1.0, -2.0, 300.0], 0.0, per_axis(0), [1e3, 1e3, 100])
    np.testing.assert_array_equal(v, [1.0, -2.0, 100.0])
    assert not rate.any() and cap.tolist() == [False, False, True]


def test_opcua_carries_the_modbus_outputs_limited_offset_and_slope(server_factory, tmp_path):  # noqa: F811 - the fixture
    """Fed the same samples, the OPC UA variables hold what the Modbus registers hold (to the
    registers' 0.1 µm, 0.01 µm/m and 0.001 mm), limits and all, for a Z-dependent model."""
    fbgcomp_testing.require("pymodbus")
    from pymodbus.client import ModbusTcpClient

    from fbgcomp.runtime.outputs.modbus import ModbusConfig, ModbusOutput

    slope, z_ref = _kinematic_slope()
    assert np.abs(slope).max() > 100.0  # a real Z dependence
    srv, url = server_factory()
    now = [0.0]
    port = free_port()
    modbus = ModbusOutput(
        ModbusConfig(
            listen=f"127.0.0.1:{port}",
            offset_rate_um_per_s=10,
            max_offset_um=[30, 30, 500],
            slope_rate_um_per_m_per_s=40,
            max_slope_um_per_m=150,
        ),
        clock=lambda: now[0],
    )
    modbus.start()
    plc = ModbusTcpClient("127.0.0.1", port=port, timeout=3)
    snap = _snapshot((-123.44, 7.26, 42.0))

    async def main():
        client = await trusted_client(url, tmp_path / "c", TRUSTED(tmp_path), "operator", "s3cret-for-test")
        seen = []
        async with client:
            for k in range(6):  # 0.5 s apart: offsets still ramping
                now[0] = 0.5 * k
                z = z_ref + k  # a new ZRef each step: sample marker
                modbus.publish(snap, True, slope, z)
                srv.publish(snap, True, slope, z, modbus)
                seen.append((await _read_when(client, z), _decoded(_regs(plc))))
        return seen

    try:
        assert plc.connect()
        seen = asyncio.run(main())
    finally:
        plc.close()
        modbus.stop()
    for k, (opc, regs) in enumerate(seen):
        assert opc["ZRef_mm"] == pytest.approx(regs["z_ref_mm"], abs=0.0005 + 1e-9)
        offset = np.array([opc[f"Offset{a}_um"] for a in "XYZ"])
        slope_opc = np.array([opc[f"Slope{a}_um_per_m"] for a in "XYZ"])
        np.testing.assert_allclose(offset, regs["offset_um"], atol=0.05 + 1e-9)
        np.testing.assert_allclose(slope_opc, regs["slope_um_per_m"], atol=0.005 + 1e-9)
        # and they are the limited values, not the raw ones
        np.testing.assert_allclose(
            offset,
            np.clip(np.clip(snap.correction_um, -5 * k, 5 * k), [-30, -30, -500], [30, 30, 500]),
            atol=1e-9,
        )
        np.testing.assert_allclose(slope_opc, np.clip(slope, -min(20 * k, 150), min(20 * k, 150)), atol=1e-9)
    assert np.abs(seen[-1][0]["SlopeX_um_per_m"]) + np.abs(seen[-1][0]["SlopeZ_um_per_m"]) > 0


def test_without_modbus_the_same_limits_apply(server_factory, tmp_path):  # noqa: F811 - the fixture
    """No [modbus] listener: the OPC UA output applies the [modbus] table's maxima itself
    (rates off here, so the result is exact), and publishes no slope when the output is off."""
    from fbgcomp.runtime.outputs.modbus import ModbusConfig

    srv, url = server_factory()
    limits = ModbusConfig(
        offset_rate_um_per_s=0, max_offset_um=[30, 30, 500], slope_rate_um_per_m_per_s=0, max_slope_um_per_m=5
    )

    async def main():
        client = await trusted_client(url, tmp_path / "c", TRUSTED(tmp_path), "operator", "s3cret-for-test")
        async with client:
            srv.publish(_snapshot((-123.44, 7.26, 420.0)), True, [3.0, -12.5, 0.0], 812.5, limits)
            on = await _read_when(client, 812.5)
            srv.publish(_snapshot((0.0, 0.0, 0.0), "ALARM"), True, [3.0, -12.5, 0.0], 700.0, limits)
            alarm = await _read_when(client, 700.0)
        return on, alarm

    on, alarm = asyncio.run(main())
    assert [on[f"Offset{a}_um"] for a in "XYZ"] == [-30.0, 7.26, 420.0]
    assert [on[f"Slope{a}_um_per_m"] for a in "XYZ"] == [3.0, -5.0, 0.0]
    assert [alarm[n] for n in NAMES] == [0.0] * 6 + [700.0]


@pytest.fixture(scope="session")
def served_both(tmp_path_factory, runtime_model_and_campaign):
    """A real serve with OPC UA and [modbus], fed by the real simulated interrogator; an OPC UA
    subscription to the offset variables while a PLC-side pymodbus client polls the registers."""
    fbgcomp_testing.require("asyncua")
    fbgcomp_testing.require("pymodbus")
    from pymodbus.client import ModbusTcpClient

    model_path, campaign = runtime_model_and_campaign
    tmp = tmp_path_factory.mktemp("opcua_modbus")
    port = free_port()
    rate = 2.0
    config = modbus_serve_config(port, rate)
    polls = []
    with serve_with_simulator(tmp, config, model_path, campaign, ENV, ("--rate", 1000, "--speed", 30)) as run:
        plc = ModbusTcpClient("127.0.0.1", port=port, timeout=3)
        assert plc.connect()

        def poll(seen):
            # until the data have stopped (ALARM) and the offset has ramped out, or 10 s after
            polls.append((time.time(), _decoded(_regs(plc))))
            alarm = [t for t, d in polls if d["health"] == 2]
            return bool(alarm) and (
                not np.abs(polls[-1][1]["offset_um"]).any() or time.time() - alarm[0] > 10
            )

        seen = run.watch([*NAMES, "CorrectionX_um", "CorrectionY_um", "CorrectionZ_um"], 60, poll)
        plc.close()
        alive = run.serve.poll() is None
    return dict(seen=seen, polls=polls, rate=rate, alive=alive)


def test_serve_publishes_the_modbus_offsets_over_opcua(served_both):
    seen, polls, rate = served_both["seen"], served_both["polls"], served_both["rate"]
    assert served_both["alive"]
    latest, compared, lagging = {}, 0, 0
    events = sorted(
        [(t_rx, "opc", (name, value)) for name, value, _, t_rx in seen] + [(t, "plc", d) for t, d in polls],
        key=lambda e: e[0],
    )
    changed_at = {}
    for t, kind, item in events:
        if kind == "opc":
            latest[item[0]] = item[1]
            changed_at[item[0]] = t
            continue
        if not all(f"Offset{a}_um" in latest for a in "XYZ"):
            continue
        opc = np.array([latest[f"Offset{a}_um"] for a in "XYZ"])
        # both come from one limiter; between the two reads the offset moves at most at the
        # configured rate (plus a batch and the register's 0.05 µm rounding)
        gap = max(t - min(changed_at[f"Offset{a}_um"] for a in "XYZ"), 0.0)
        tol = rate * min(gap + 0.2, 1.0) + 0.05 + 1e-6
        assert np.abs(opc - item["offset_um"]).max() <= tol, (t, opc, item["offset_um"])
        assert latest.get("ZRef_mm", 0.0) == item["z_ref_mm"] == 0.0  # no Z term: slope 0
        assert all(latest.get(f"Slope{a}_um_per_m", 0.0) == 0.0 for a in "XYZ")
        compared += 1
        corr = np.array([latest.get(f"Correction{a}_um", 0.0) for a in "XYZ"])
        lagging += np.abs(corr - opc).max() > 1.0  # the limited offset, not the correction
    assert compared >= 20
    assert lagging >= 3
    assert max(abs(v) for n, v, _, _ in seen if n.startswith("Offset")) > 1.0
