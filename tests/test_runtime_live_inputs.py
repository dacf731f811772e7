"""Live inputs of ``fbgcomp serve`` (issue 15 item 4): probe temperatures from a real asyncua
server and a real pymodbus server on loopback, the Z position over OPC UA and from the real
LinuxCNC sim, the simulator's own OPC UA temperatures; stale inputs -> ALARM, hold and ramp.

Every serve here is the real ``python -m fbgcomp serve`` process fed by the real
``sim-interrogator`` (Hyperion protocol); what it did is read back from its Parquet run log and,
where named, from its own OPC UA server."""

from __future__ import annotations

import asyncio
import contextlib
import subprocess
import threading
import time
from contextlib import contextmanager
from datetime import UTC
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

import fbgcomp_testing
from fbgcomp.runtime.pipeline import Pipeline
from test_runtime_support import fbgcomp_process, free_port, serve_with_simulator

ENV = {"FBGCOMP_OPCUA_USER": "operator", "FBGCOMP_OPCUA_PASSWORD": "live-pass-123"}


# ------------------------------------------------------------------ servers of the test
class OpcUaTestServer:
    """A real asyncua server in its own thread: ``ns=2;s=<name>`` Double variables, each
    rewritten (fresh source timestamp) every ``period_s`` unless frozen - as a PLC publishes."""

    def __init__(self, values: dict, period_s: float = 0.2):
        self.port = free_port()
        self.endpoint = f"opc.tcp://127.0.0.1:{self.port}"
        self.values = dict(values)
        self.frozen: set = set()
        self.period_s = period_s
        self._loop = asyncio.new_event_loop()
        self._ready = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _run(self):
        asyncio.set_event_loop(self._loop)
        self._loop.run_until_complete(self._main())

    async def _main(self):
        from datetime import datetime

        from asyncua import Server, ua

        server = Server()
        await server.init()
        server.set_endpoint(self.endpoint)
        await self.secure(server)
        idx = await server.register_namespace("urn:fbgcomp:test:plc")
        assert idx == 2
        obj = await server.nodes.objects.add_object(ua.NodeId("PLC", idx), "PLC")
        nodes = {n: await obj.add_variable(ua.NodeId(n, idx), n, float(v)) for n, v in self.values.items()}
        self._stop = asyncio.Event()
        async with server:
            self._ready.set()
            while not self._stop.is_set():
                now = datetime.now(UTC)
                for n, node in nodes.items():
                    if n not in self.frozen:
                        await node.write_value(
                            ua.DataValue(
                                ua.Variant(float(self.values[n]), ua.VariantType.Double), SourceTimestamp=now
                            )
                        )
                with contextlib.suppress(TimeoutError):
                    await asyncio.wait_for(self._stop.wait(), self.period_s)

    async def secure(self, server):
        """The server's endpoints: security None only (a subclass loads a certificate)."""
        from asyncua import ua

        server.set_security_policy([ua.SecurityPolicyType.NoSecurity])

    def __enter__(self):
        self._thread.start()
        assert self._ready.wait(30), "asyncua test server did not start"
        return self

    def __exit__(self, *exc):
        self._loop.call_soon_threadsafe(self._stop.set)
        self._thread.join(15)


class ModbusTestServer:
    """A real pymodbus TCP server (unit 1) in its own thread whose holding registers are
    ``regs`` (a list the test changes)."""

    def __init__(self, n: int = 8):
        self.port = free_port()
        self.regs = [0] * n
        self._ready = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._loop = None

    def _run(self):
        from pymodbus.server import ModbusTcpServer
        from pymodbus.simulator import DataType, SimData, SimDevice

        async def action(function_code, start_address, address, count, registers, set_values):
            registers[: len(self.regs)] = self.regs
            return None

        async def main():
            dev = SimDevice(
                id=1,
                action=action,
                simdata=[SimData(0, count=len(self.regs), values=0, datatype=DataType.REGISTERS)],
            )
            self._server = ModbusTcpServer(dev, address=("127.0.0.1", self.port))
            await self._server.serve_forever(background=True)
            self._ready.set()
            await self._server.serving

        self._loop = asyncio.new_event_loop()
        self._loop.run_until_complete(main())

    def __enter__(self):
        self._thread.start()
        assert self._ready.wait(30), "pymodbus test server did not start"
        return self

    def __exit__(self, *exc):
        fut = asyncio.run_coroutine_threadsafe(self._server.shutdown(), self._loop)
        fut.result(10)
        self._thread.join(10)


def int16(value: int) -> int:
    return value & 0xFFFF


def _log(folder: Path) -> pd.DataFrame:
    df = pd.read_parquet(folder / "data").sort_values("time_s").reset_index(drop=True)
    df["health"] = df["health"].astype(str)
    return df


def _replay_offline(model, df: pd.DataFrame, z_axis_mm=None):
    """The offline pipeline on the logged frames and temperatures (batches of 50)."""
    from fbgcomp.runtime.pipeline import Pipeline

    w = df[[f"{s}_nm" for s in model.sensor_names]].to_numpy(float)
    t = df[[f"{p}_C" for p in model.probe_names]].to_numpy(float)
    counts = df[[f"{s}_peaks" for s in model.sensor_names]].to_numpy(np.int8)
    pipe = Pipeline(model)
    time_s = df["time_s"].to_numpy(float)
    out = [
        pipe.process(
            time_s[i : i + 50],
            w[i : i + 50],
            counts[i : i + 50],
            np.zeros_like(counts[i : i + 50]),
            t[i : i + 50],
            z_axis_mm=z_axis_mm,
        )
        for i in range(0, time_s.size, 50)
    ]
    return {
        n: np.concatenate([getattr(r, n) for r in out]) for n in ("deviation_um", "correction_um", "health")
    }


@contextmanager
def serve_and_sim(tmp: Path, toml: str, model, campaign, serve_args=(), sim_args=()):
    """``fbgcomp serve`` (OPC UA off, run log ``tmp/log``) then ``sim-interrogator``."""
    (tmp / "serve.toml").write_text(toml)
    sp, cp = free_port(), free_port()
    serve = fbgcomp_process(
        "serve",
        "--config",
        tmp / "serve.toml",
        "--model",
        model,
        "--source",
        f"hyperion://127.0.0.1:{sp}?command_port={cp}",
        "--opcua",
        "off",
        "--log",
        tmp / "log",
        *serve_args,
    )
    sim = fbgcomp_process("sim-interrogator", campaign, "--port", sp, "--command-port", cp, *sim_args)
    try:
        yield serve, sim
    finally:
        for p in (sim, serve):
            if p.poll() is None:
                p.terminate()
                try:
                    p.wait(15)
                except subprocess.TimeoutExpired:
                    p.kill()
        tmp.joinpath("serve.err").write_bytes(serve.communicate(timeout=10)[1])
        sim.communicate(timeout=10)


# ------------------------------------------------------------------ tests
def test_serve_reads_opcua_and_modbus_temperatures_and_holds_when_one_goes_stale(
    tmp_path_factory, runtime_model_and_campaign
):
    fbgcomp_testing.require("asyncua")
    fbgcomp_testing.require("pymodbus")
    from fbgcomp.models.registry import load_model

    model_path, campaign = runtime_model_and_campaign
    model = load_model(model_path)
    assert set(model.probe_names) == {"T_bulk", "T_surf", "T_flange"}
    tmp = tmp_path_factory.mktemp("live")
    camp_t = pd.read_csv(campaign / "temperatures.csv").iloc[0]
    with (
        OpcUaTestServer({"T_bulk": camp_t["T_bulk_C"], "T_surf": camp_t["T_surf_C"]}) as opc,
        ModbusTestServer() as mb,
    ):
        flange_count = round(camp_t["T_flange_C"] * 100)  # int16, 0.01 °C
        mb.regs[3] = int16(flange_count)
        toml = f"""
[temperatures.opcua]
endpoint = "{opc.endpoint}"
nodes = {{ T_bulk = "ns=2;s=T_bulk", T_surf = "ns=2;s=T_surf" }}
stale_s = 1.5

[temperatures.modbus]
host = "127.0.0.1"
port = {mb.port}
unit = 1
registers = {{ T_flange = {{ address = 3, type = "int16", scale = 0.01 }} }}
poll_s = 0.2
stale_s = 1.5
"""
        with serve_with_simulator(
            tmp, toml, model_path, campaign, ENV, sim_args=("--rate", "200", "--speed", "5")
        ) as run:
            seen = run.watch(
                ["Health", "SourceStatus", "CorrectionX_um"],
                25,
                lambda s: sum(1 for n, v, *_ in s if n == "Health" and v == "OK") >= 1,
            )
            assert any(n == "Health" and v == "OK" for n, v, *_ in seen), seen
            time.sleep(2.0)
            # the PLC's values change: a step on both servers
            opc.values["T_bulk"] += 0.4
            mb.regs[3] = int16(flange_count - 30)  # -0.30 °C
            time.sleep(3.0)
            opc.frozen.add("T_surf")  # the PLC stops updating it
            t_frozen = time.time()
            seen = run.watch(
                ["Health", "SourceStatus", "CorrectionX_um"],
                20,
                lambda s: (
                    any(n == "Health" and v == "ALARM" for n, v, *_ in s) and time.time() - t_frozen > 4.0
                ),
            )
            opc.frozen.discard("T_surf")  # and resumes
            # Health and SourceStatus come from one snapshot but may reach the client in two
            # publish responses: wait for both
            seen_back = run.watch(
                ["Health", "SourceStatus"],
                20,
                lambda s: (
                    any(n == "Health" and v == "OK" for n, v, *_ in s)
                    and any(n == "SourceStatus" and "inputs OK" in v for n, v, *_ in s)
                ),
            )
            run.serve.terminate()
            run.serve.wait(20)
    alarms = [r for r in seen if r[0] == "Health" and r[1] == "ALARM"]
    assert alarms, seen
    status = [v for n, v, *_ in seen if n == "SourceStatus"]
    assert any("stale: T_surf (opcua" in v for v in status), status
    # stale stale_s (1.5 s) after the last update, which the server wrote up to one period
    # (0.2 s) before it was frozen: not before that, and not much later (plus the sampling)
    assert 1.5 - 0.2 - 0.05 < alarms[0][3] - t_frozen < 3.5
    assert any(n == "Health" and v == "OK" for n, v, *_ in seen_back)
    assert any("inputs OK" in v for n, v, *_ in seen_back if n == "SourceStatus")

    df = _log(tmp / "log")
    ok = df[df.health == "OK"]
    # the logged temperatures are the servers' values: OPC UA doubles exactly, Modbus counts
    assert set(np.round(ok["T_bulk_C"], 9)) == {
        round(camp_t["T_bulk_C"], 9),
        round(camp_t["T_bulk_C"] + 0.4, 9),
    }
    assert set(np.round(ok["T_flange_C"], 9)) == {
        round(flange_count * 0.01, 9),
        round((flange_count - 30) * 0.01, 9),
    }
    # the correction is the offline model's on the same frames and temperatures
    off = _replay_offline(model, df)
    rows = (df.health == "OK").to_numpy()
    np.testing.assert_allclose(
        df.loc[rows, ["dev_dx_um", "dev_dy_um", "dev_dz_um"]], off["deviation_um"][rows], atol=1e-9
    )
    assert np.abs(off["deviation_um"][rows]).max() > 0.5  # a correction worth checking
    # the temperature step moved it: the model sees live values, not a replay
    after = df.index[df.T_bulk_C > camp_t["T_bulk_C"] + 0.2]
    assert len(after) > 50
    # while T_surf was stale: no temperature, ALARM, the correction held then ramped to zero
    stale = df[df.T_surf_C.isna() & (df.health == "ALARM")]
    assert len(stale) > 100
    corr = np.abs(stale["corr_dx_um"].to_numpy())
    assert corr[-1] <= 1e-9 < corr[0] or corr[0] == 0
    assert np.all(np.diff(corr) <= 1e-9)  # never grows while held


def test_simulator_serves_the_campaigns_temperatures_over_opcua(tmp_path_factory, runtime_model_and_campaign):
    fbgcomp_testing.require("asyncua")
    from fbgcomp.models.registry import load_model

    model_path, campaign = runtime_model_and_campaign
    model = load_model(model_path)
    tmp = tmp_path_factory.mktemp("simtemps")
    port = free_port()
    nodes = ", ".join(f'{p} = "ns=2;s=Probes.{p}"' for p in model.probe_names)
    toml = f"""
[temperatures.opcua]
endpoint = "opc.tcp://127.0.0.1:{port}"
nodes = {{ {nodes} }}
stale_s = 2
"""
    # the campaign lasts 300 s, 60 s of the simulator's clock at this speed, which starts with
    # the simulator: a serve slow to start on a loaded machine (a CI run's other worker) met it
    # at 10x near its end, where the last sample stands (slope 0.07, 2026-12-07)
    speed = 5.0
    with serve_and_sim(
        tmp,
        toml,
        model_path,
        campaign,
        ("--duration", "12"),
        ("--rate", "200", "--speed", str(speed), "--temperatures-opcua", f"opc.tcp://127.0.0.1:{port}"),
    ) as (serve, _sim):
        serve.wait(60)
    assert serve.returncode == 0, tmp.joinpath("serve.err").read_text()[-3000:]
    df = _log(tmp / "log")
    temps = pd.read_csv(campaign / "temperatures.csv")
    ok = df[df.health == "OK"]
    assert len(ok) > 1000
    for p in model.probe_names:
        # every logged value is one of the campaign's samples, sent as a double
        assert np.isin(ok[f"{p}_C"].to_numpy(), temps[f"{p}_C"].to_numpy()).all(), p
    # ... taken on the simulator's clock: the campaign time of the served sample advances at
    # the simulator's speed against the frames' clock
    camp_time = np.array(
        [
            temps["time_s"].to_numpy()[np.flatnonzero(temps["T_bulk_C"].to_numpy() == v)[0]]
            for v in ok["T_bulk_C"].to_numpy()[::50]
        ]
    )
    running = camp_time < temps["time_s"].to_numpy()[-1] - 10.0  # not the held last sample
    assert running.sum() >= 10, (running.sum(), camp_time)
    slope = np.polyfit(ok["time_s"].to_numpy()[::50][running], camp_time[running], 1)[0]
    assert slope == pytest.approx(speed, rel=0.15)
    off = _replay_offline(model, df)
    rows = (df.health == "OK").to_numpy()
    np.testing.assert_allclose(
        df.loc[rows, ["dev_dx_um", "dev_dy_um", "dev_dz_um"]], off["deviation_um"][rows], atol=1e-9
    )


def test_a_lost_interrogator_link_leaves_the_live_probes_correcting(
    tmp_path_factory, runtime_model_and_campaign
):
    """The interrogator's link cut for 3 s (``cut@12:3``) while every probe arrives live over OPC
    UA (a PLC's server, a path of its own) and stands 2 K above its zero: the default (physical)
    model's set without gratings goes on from the probes, health DEGRADED, where the correction
    was held and ramped to zero in ``ramp_s`` (ALARM), a machine's thermal drift then left
    uncompensated for as long as the link stays down. The frames it runs are logged like any
    other: the offline pipeline on the logged frames gives the published deviation and
    correction, through the cut and after it. (``probes_on_link_loss = false``:
    test_runtime_pipeline.py.)"""
    fbgcomp_testing.require("asyncua")
    fbgcomp_testing.require("pyarrow")
    from fbgcomp.bench.synthetic import linear_truth_campaign
    from fbgcomp.models.physical import PhysicalModel
    from fbgcomp.models.registry import load_model

    _, campaign = runtime_model_and_campaign
    tmp = tmp_path_factory.mktemp("linkloss")
    train, _ = linear_truth_campaign("train", seed=1, duration_s=2 * 3600, noise_um=0.05)
    model_path = PhysicalModel(zero_window_s=0.5).fit([train]).save(tmp / "physical.json")
    model = load_model(model_path)
    all_gratings = Pipeline(model).model_sets.index(frozenset(model.sensor_names))
    first = pd.read_csv(campaign / "temperatures.csv").iloc[0]
    run = tmp / "run"
    run.mkdir()
    with OpcUaTestServer({p: first[f"{p}_C"] for p in model.probe_names}) as opc:
        nodes = ", ".join(f'{p} = "ns=2;s={p}"' for p in model.probe_names)
        # the output policy off: the published correction is the model's own, frame by frame
        toml = f"""
[source]
backoff_initial_s = 0.05
backoff_max_s = 0.2
no_data_s = 0.3

[pipeline]
ramp_s = 0.5
max_slew_um_per_s = 0
max_correction_um = [0, 0, 0]

[pipeline.output_filter]
enabled = false

[temperatures.opcua]
endpoint = "{opc.endpoint}"
nodes = {{ {nodes} }}
stale_s = 5
"""
        with serve_and_sim(
            run,
            toml,
            model_path,
            campaign,
            ("--duration", "20"),
            # the cut on the simulator's clock, late enough for serve to have zeroed first under
            # a loaded CI (at 6 s, serve once had not logged a frame when the link came back)
            ("--rate", "200", "--speed", "5", "--fault", "cut@12:3"),
        ) as (serve, _sim):
            wait_log(run / "log", "OK")  # zeroed: every probe 2 K warmer from here on
            for p in model.probe_names:
                opc.values[p] += 2.0
            serve.wait(60)
    assert serve.returncode == 0, run.joinpath("serve.err").read_text()[-3000:]
    df = _log(run / "log")
    cut = (df[[f"{s}_peaks" for s in model.sensor_names]].to_numpy() == 0).all(axis=1)
    # the cut's frames: 50 a second while the link is down, every one on the set without
    # gratings, DEGRADED, the probes read
    assert cut.sum() > 50, cut.sum()
    assert (df.health[cut] == "DEGRADED").all() and (df.model_set[cut] == all_gratings).all()
    assert np.isfinite(df.loc[cut, [f"{p}_C" for p in model.probe_names]].to_numpy()).all()
    # back on the full model once the gratings have been good for recover_s (1 s) again
    t = df.time_s.to_numpy()
    back = t > t[np.flatnonzero(cut)[-1]] + 1.5
    assert back.sum() > 200 and (df.health[back] == "OK").all()
    off = _replay_offline(model, df)
    axes = ["dx", "dy", "dz"]
    dev = df[[f"dev_{a}_um" for a in axes]].to_numpy()
    np.testing.assert_allclose(dev, off["deviation_um"], atol=1e-9)
    corr = df[[f"corr_{a}_um" for a in axes]].to_numpy()
    zeroed = (df.health != "ZEROING").to_numpy()
    np.testing.assert_allclose(corr[zeroed], -dev[zeroed], atol=1e-9)  # the policy off
    # the correction goes on through the cut: the 2 K's, never ramped to zero (ramp_s, 0.5 s,
    # would have it at 0 within the cut's first sixth). How far the model's leads have grown
    # when the cut comes depends on how soon serve zeroed (0.49-0.87 µm under a loaded CI):
    # it keeps growing through the cut, from at least 0.2 µm
    size = np.abs(corr[cut]).max(axis=1)
    assert size.min() > 0.2 and size[-1] >= size[0], (size.min(), size[0], size[-1])


def _kinematic_model(base: Path) -> Path:
    from fbgcomp.models.kinematic import KinematicModel

    path = base / "kinematic.json"
    if not path.exists():
        KinematicModel(zero_window_s=1.0).fit().save(path)
    return path


def wait_log(folder: Path, health: str, timeout_s: float = 30.0) -> pd.DataFrame:
    """Read the run log until a frame with ``health`` has been written (parts every 0.5 s)."""
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        try:
            df = _log(folder)
            if (df.health == health).any():
                return df
        except (OSError, ValueError, KeyError):
            pass
        time.sleep(0.3)
    raise AssertionError(f"no {health} frame in the run log within {timeout_s} s")


def test_z_over_opcua_moves_a_kinematic_models_correction_and_stale_z_holds(
    tmp_path_factory, runtime_model_and_campaign
):
    fbgcomp_testing.require("asyncua")
    from fbgcomp.models.registry import load_model

    shared_model, campaign = runtime_model_and_campaign
    model_path = _kinematic_model(shared_model.parent)
    model = load_model(model_path)
    tmp = tmp_path_factory.mktemp("zopc")
    camp_t = pd.read_csv(campaign / "temperatures.csv").iloc[0]
    z0, z1 = 0.0, 300.0
    values = {p: camp_t[f"{p}_C"] for p in model.probe_names}
    with OpcUaTestServer({**values, "AxisZ": z0}) as opc:
        nodes = ", ".join(f'{p} = "ns=2;s={p}"' for p in model.probe_names)
        toml = f"""
[temperatures.opcua]
endpoint = "{opc.endpoint}"
nodes = {{ {nodes} }}
stale_s = 5

[position]
source = "opcua"
node = "ns=2;s=AxisZ"
stale_s = 1
"""
        with serve_and_sim(
            tmp, toml, model_path, campaign, ("--duration", "60"), ("--rate", "200", "--speed", "5")
        ) as (serve, _sim):
            wait_log(tmp / "log", "OK")
            time.sleep(2)
            opc.values["AxisZ"] = z1
            t_moved = time.time()
            time.sleep(4)
            opc.frozen.add("AxisZ")  # the position stops arriving
            t_frozen = time.time()
            time.sleep(4)
            serve.terminate()
            serve.wait(20)
    err = tmp.joinpath("serve.err").read_text()
    stale_lines = [ln for ln in err.splitlines() if "live inputs missing or stale:" in ln]
    assert stale_lines and stale_lines[-1].split("stale: ")[1].startswith("Z (opcua, "), err[-3000:]
    df = _log(tmp / "log")
    dev = df[["dev_dx_um", "dev_dy_um", "dev_dz_um"]].to_numpy()
    at0 = _replay_offline(model, df, z0)["deviation_um"]
    at1 = _replay_offline(model, df, z1)["deviation_um"]
    ok = (df.health == "OK").to_numpy()
    rt = df["received_s"].to_numpy()
    before = ok & (rt < t_moved - 0.5)
    after = ok & (rt > t_moved + 1.0) & (rt < t_frozen)
    assert before.sum() > 200 and after.sum() > 200
    np.testing.assert_allclose(dev[before], at0[before], atol=1e-9)
    np.testing.assert_allclose(dev[after], at1[after], atol=1e-9)
    # Z matters to this model: the two positions give different corrections
    assert np.abs(at1[after] - at0[after]).max() > 0.3
    # the run log records the position the model was given, frame by frame
    z_logged = df["z_mm"].to_numpy()
    assert (z_logged[before] == z0).all() and (z_logged[after] == z1).all()
    # no Z for longer than stale_s: a missing input -> ALARM (hold / ramp), not the old Z
    late = rt > t_frozen + 2.0
    assert late.sum() > 100 and (df.health.to_numpy()[late] == "ALARM").all()
    assert np.isnan(dev[late]).all()


@pytest.fixture
def machine():
    fbgcomp_testing.require_program("linuxcnc")
    from fbgcomp.cli.cnc_demo import LinuxCncMachine

    m = LinuxCncMachine(fbgcomp={"MAX_RATE_UM_S": 1e6})
    m.start()
    try:
        yield m
    finally:
        m.stop()


def test_linuxcnc_hal_pin_z_reaches_the_model(machine, tmp_path_factory, runtime_model_and_campaign):
    fbgcomp_testing.require("asyncua")
    from fbgcomp.models.registry import load_model

    shared_model, campaign = runtime_model_and_campaign
    model_path = _kinematic_model(shared_model.parent)
    model = load_model(model_path)
    tmp = tmp_path_factory.mktemp("zcnc")
    camp_t = pd.read_csv(campaign / "temperatures.csv").iloc[0]
    const = ",".join(f"{p}={camp_t[f'{p}_C']}" for p in model.probe_names)
    toml = '[position]\nsource = "linuxcnc"\nstale_s = 1\n'
    machine.call("machine_on")
    with serve_and_sim(
        tmp,
        toml,
        model_path,
        campaign,
        (
            "--cnc",
            "linuxcnc",
            "--cnc-address",
            machine.address,
            "--temperatures",
            f"const:{const}",
            "--duration",
            "90",
        ),
        ("--rate", "200", "--speed", "5"),
    ) as (serve, _sim):
        time.sleep(4)  # not homed yet: Z is no position (missing)
        t_homing = time.time()
        machine.call("home")
        machine.call("wait_pin", pin="fbgcomp.active", value=1, tol=0, timeout_s=30)
        time.sleep(3)
        prog = machine.run_dir / "z.ngc"
        prog.write_text("G21 G90\nG0 Z-40\nM2\n")
        prog.chmod(0o644)
        machine.call("program", path=str(prog), wait=True, timeout_s=60)
        t_moved = time.time()
        pin_z = machine.getp("joint.2.pos-fb", "fbgcomp.z-pos-mm")
        time.sleep(3)
        serve.terminate()
        serve.wait(20)
    assert pin_z["fbgcomp.z-pos-mm"] == pytest.approx(pin_z["joint.2.pos-fb"], abs=1e-3)
    assert pin_z["fbgcomp.z-pos-mm"] == pytest.approx(-40.0, abs=0.01)
    df = _log(tmp / "log")
    rt = df["received_s"].to_numpy()
    health = df.health.to_numpy()
    # before homing the Z-dependent model had no position: zeroing waited, nothing applied
    assert not (health[rt < t_homing] == "OK").any()
    dev = df[["dev_dx_um", "dev_dy_um", "dev_dz_um"]].to_numpy()
    # every logged frame came after homing (zeroing waited for the position)
    at_home = _replay_offline(model, df, 0.0)["deviation_um"]
    at_z = _replay_offline(model, df, -40.0)["deviation_um"]
    moved = (health == "OK") & (rt > t_moved + 0.5)
    assert moved.sum() > 100
    np.testing.assert_allclose(dev[moved], at_z[moved], atol=1e-9)
    assert np.abs(at_z[moved] - at_home[moved]).max() > 0.05


def assert_serve_refuses(config, model_path, message) -> list[str]:
    """``fbgcomp serve --config CONFIG`` stops at start with exit code 2 and one ``error:`` line
    holding ``message``; returns stderr's lines."""
    p = fbgcomp_process(
        "serve",
        "--config",
        config,
        "--model",
        model_path,
        "--source",
        "hyperion://127.0.0.1:9",
        "--opcua",
        "off",
        "--duration",
        "1",
    )
    _, err = p.communicate(timeout=60)
    lines = err.decode().strip().splitlines()
    assert p.returncode == 2 and lines[-1].startswith("error:") and message in lines[-1], lines
    return lines


@pytest.mark.parametrize(
    "toml,message",
    [
        (
            '[temperatures.opcua]\nendpoint = "opc.tcp://127.0.0.1:9"\nnodes = { T_bulk = "ns=2;s=T" }\n',
            "probe T_surf has no source",
        ),
        (
            '[temperatures.opcua]\nendpoint = "opc.tcp://127.0.0.1:9"\nnodes = { T_bulk = "ns=2;s=T" }\n'
            '[temperatures.modbus]\nhost = "127.0.0.1"\nregisters = { T_bulk = { address = 1 } }\n',
            "probe T_bulk has two live sources",
        ),
        (
            '[temperatures.modbus]\nhost = "127.0.0.1"\nregisters = { T_nope = { address = 1 } }\n',
            "T_nope is not a probe",
        ),
        (
            '[temperatures.modbus]\nhost = "127.0.0.1"\n'
            'registers = { T_bulk = { address = 1, type = "int8" } }\n',
            "type: expected one of",
        ),
        ('[position]\nsource = "linuxcnc"\n', "needs the LinuxCNC output"),
    ],
)
def test_bad_live_input_configuration_is_one_line(
    tmp_path_factory, runtime_model_and_campaign, toml, message
):
    fbgcomp_testing.require("asyncua")
    model_path, _campaign = runtime_model_and_campaign
    tmp = tmp_path_factory.mktemp("badcfg")
    (tmp / "serve.toml").write_text(toml)
    assert_serve_refuses(tmp / "serve.toml", model_path, message)
