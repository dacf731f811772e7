"""Run log and the runtime commands through the real CLI entry point (replay source)."""

import json

import numpy as np
import pytest

import fbgcomp_testing
from fbgcomp.cli.app import main
from fbgcomp.io.campaign import read_campaign


@pytest.fixture(scope="session")
def paths(runtime_model_and_campaign):
    fbgcomp_testing.require("pyarrow")
    return runtime_model_and_campaign


@pytest.fixture(scope="session")
def replayed(paths, tmp_path_factory):
    """``fbgcomp serve`` on a campaign replayed at 20x for 3 s, OPC UA off, logged."""
    model, campaign = paths
    out = tmp_path_factory.mktemp("replay")
    code = main(
        [
            "serve",
            "--model",
            str(model),
            "--source",
            f"replay://{campaign}?speed=20",
            "--opcua",
            "off",
            "--log",
            str(out / "log"),
            "--duration",
            "3",
        ]
    )
    assert code == 0
    return out / "log", campaign, model


def test_replayed_run_is_logged_in_closed_parquet_parts(replayed):
    import pyarrow.parquet as pq

    from fbgcomp.runtime.log import log_parts, read_log

    log_dir, campaign, _ = replayed
    parts = log_parts(log_dir)
    assert len(parts) >= 4  # one file per <= 0.5 s
    # data files in their own folder, by day; nothing half-written left, meta.json outside
    assert all(p.parent.parent == log_dir / "data" and p.parent.name.startswith("date=") for p in parts)
    assert not list(log_dir.rglob(".*.tmp"))
    assert sorted(f.name for f in log_dir.iterdir()) == ["data", "meta.json"]
    meta, df = read_log(log_dir)
    assert sum(pq.read_table(p).num_rows for p in parts) == len(df)
    assert json.loads((log_dir / "meta.json").read_text())["sensor_names"] == meta["sensor_names"]
    # the logged wavelengths and temperatures are the campaign's own samples, in order
    src = read_campaign(campaign)
    n = len(df)
    assert n > 500
    for s in meta["sensor_names"]:
        np.testing.assert_array_equal(df[f"{s}_nm"].to_numpy(), src.fbg[f"{s}_nm"].to_numpy()[:n])
    for p in meta["probe_names"]:
        np.testing.assert_array_equal(df[f"{p}_C"].to_numpy(), src.temperatures[f"{p}_C"].to_numpy()[:n])
    assert set(df["health"].unique()) == {0, 3}  # zeroing, then OK
    _, named = read_log(log_dir, labels=True)
    assert set(named["health"].unique()) == {"OK", "ZEROING"}
    assert list(named["health"].cat.categories) == ["OK", "DEGRADED", "ALARM", "ZEROING"]


def test_the_log_opens_in_pandas_and_duckdb_with_health_as_dictionary_strings(replayed):
    """The log a real ``fbgcomp serve`` wrote, read by the usual tools as they come."""
    duckdb = fbgcomp_testing.require("duckdb")
    import pandas as pd
    import pyarrow as pa
    import pyarrow.parquet as pq

    from fbgcomp.runtime.log import log_parts, read_log

    log_dir, _campaign, _ = replayed
    meta, ours = read_log(log_dir, labels=True)
    df = pd.read_parquet(log_dir / "data").sort_values("time_s", kind="stable")
    assert len(df) == len(ours) > 500
    np.testing.assert_array_equal(df["time_s"].to_numpy(), ours["time_s"].to_numpy())
    np.testing.assert_array_equal(df["S1_nm"].to_numpy(), ours["S1_nm"].to_numpy())
    # health and every sensor status are strings, stored dictionary-encoded
    assert isinstance(df["health"].dtype, pd.CategoricalDtype)
    assert list(df["health"].astype(str)) == list(ours["health"].astype(str))
    assert set(df["health"].astype(str)) == {"ZEROING", "OK"}
    schema = pq.read_schema(log_parts(log_dir)[-1])
    for name in ["health"] + [f"{s}_status" for s in meta["sensor_names"]]:
        assert pa.types.is_dictionary(schema.field(name).type), name
        assert pa.types.is_string(schema.field(name).type.value_type), name
    assert set(df["S1_status"].astype(str)) == {"OK"}
    # the hive partition: the UTC day each part was written
    assert df["date"].astype(str).str.match(r"^\d{4}-\d\d-\d\d$").all()

    glob = str(log_dir / "**" / "*.parquet")
    con = duckdb.connect()
    n, n_ok, first, last = con.execute(
        "SELECT count(*), count(*) FILTER (WHERE health = 'OK'), min(time_s), max(time_s) "
        "FROM read_parquet(?)",
        [glob],
    ).fetchone()
    assert n == len(ours) and n_ok == int((ours["health"] == "OK").sum()) > 0
    assert (first, last) == (ours["time_s"].min(), ours["time_s"].max())
    statuses = con.execute("SELECT DISTINCT S3_status FROM read_parquet(?)", [glob]).fetchall()
    assert statuses == [("OK",)]
    # duckdb.read_parquet, the relational API named in the issue, reads the same rows
    rel = duckdb.read_parquet(glob, connection=con)
    assert rel.aggregate("count(*)").fetchall() == [(len(ours),)]
    con.close()


def test_log_export_round_trips_to_a_campaign(replayed, tmp_path):
    from fbgcomp.runtime.log import read_log

    log_dir, campaign, _model = replayed
    out = tmp_path / "exported"
    assert main(["log", "export", str(log_dir), "-o", str(out)]) == 0
    c = read_campaign(out)
    meta, df = read_log(log_dir)
    src = read_campaign(campaign)
    assert c.meta.sensor_names == meta["sensor_names"]
    assert [s.lambda0_nm for s in c.meta.sensors] == [s.lambda0_nm for s in src.meta.sensors]
    n = len(c.fbg)
    assert n == len(df)
    np.testing.assert_array_equal(c.fbg["S1_nm"].to_numpy(), src.fbg["S1_nm"].to_numpy()[:n])
    # replayed at 20x: the campaign clock of the export runs 20x slower than the source's
    np.testing.assert_allclose(np.diff(c.fbg["time_s"].to_numpy()), 0.1 / 20, atol=1e-6)
    assert c.meta.reference.instrument.startswith("fbgcomp prediction")
    # the exported campaign can be fitted again
    from fbgcomp.models.mra import MRAModel

    refit = MRAModel(features="eq11", zero_window_s=0.5, fallbacks="none").fit(c)
    assert refit.sensor_names == c.meta.sensor_names


@pytest.mark.parametrize(
    "args, fragment",
    [
        (["serve", "--model", "nope.json", "--source", "replay://x", "--opcua", "off"], "nope.json"),
        (["serve", "--model", "{model}", "--source", "ftp://x", "--opcua", "off"], "--source"),
        (
            [
                "serve",
                "--model",
                "{model}",
                "--source",
                "replay://{campaign}",
                "--opcua",
                "off",
                "--config",
                "{bad_config}",
            ],
            "field source.speeed",
        ),
        (
            ["serve", "--model", "{model}", "--source", "hyperion://127.0.0.1:1", "--opcua", "off"],
            "--temperatures",
        ),
        (["sim-interrogator", "{campaign}", "--fault", "melt:S1@2"], "--fault"),
        (["sim-interrogator", "{campaign}", "--fault", "drop:S9@2"], "S9"),
        (["log", "export", "{campaign}", "-o", "{tmp}/x"], "meta.json"),
    ],
)
def test_bad_input_is_one_line_and_exit_2(paths, tmp_path, capsys, args, fragment):
    model, campaign = paths
    bad = tmp_path / "bad.toml"
    bad.write_text("[source]\nspeeed = 3\n")
    fill = dict(model=model, campaign=campaign, bad_config=bad, tmp=tmp_path)
    assert main([a.format(**fill) for a in args]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error:") and "\n" not in err and fragment in err, err


def test_configuration_example_in_the_docs_is_valid():
    import re
    from pathlib import Path

    from fbgcomp.runtime.service import RuntimeConfig

    doc = (Path(__file__).parents[1] / "docs" / "runtime.md").read_text()
    block = re.search(r"```toml\n(.*?)```", doc, re.S).group(1)
    import tempfile

    with tempfile.TemporaryDirectory() as d:
        f = Path(d) / "serve.toml"
        f.write_text(block)
        cfg = RuntimeConfig.from_toml(f)
    assert cfg.pipeline.health.stuck_s == 2.0 and cfg.opcua.rate_hz == 100.0
    assert cfg.source.url.startswith("hyperion://") and cfg.log.flush_s == 0.5
    assert cfg.pipeline.output_filter.short_s == 0.6 and cfg.pipeline.max_slew_um_per_s == (1000.0,) * 3


def test_in_process_simulated_source_keeps_temperatures_on_the_instrument_clock(paths, tmp_path):
    import asyncio

    from fbgcomp.runtime.log import read_log
    from fbgcomp.runtime.service import RuntimeConfig, Service

    model, campaign = paths
    cfg = RuntimeConfig(model=str(model), opcua_enabled=False)
    cfg.source.url = f"sim://{campaign}?rate=2000&speed=5"
    cfg.log.dir = str(tmp_path / "log")
    svc = Service(cfg)
    asyncio.run(svc.run(2.0))
    _meta, df = read_log(tmp_path / "log")
    src = read_campaign(campaign)
    camp_t = (df["time_s"].to_numpy() - svc.sim._t0) * 5.0  # campaign clock of each frame
    assert len(df) > 2000 and (df["health"].iloc[-100:] == 0).all()
    np.testing.assert_allclose(df["S2_nm"], np.interp(camp_t, src.fbg["time_s"], src.fbg["S2_nm"]), atol=1e-9)
    idx = np.searchsorted(src.temperatures["time_s"].to_numpy(), camp_t + 1e-6, "right") - 1
    np.testing.assert_array_equal(df["T_bulk_C"], src.temperatures["T_bulk_C"].to_numpy()[idx])


def test_model_reload_keeps_the_zero_state_and_refuses_other_sensors(paths, tmp_path):
    import asyncio

    from fbgcomp.errors import InputError
    from fbgcomp.models.mra import MRAModel
    from fbgcomp.runtime.service import RuntimeConfig, Service

    model, campaign = paths
    src = read_campaign(campaign)
    other = (
        MRAModel(features="eq11", zero_window_s=0.5, fallbacks="none").fit(src).save(tmp_path / "other.json")
    )
    cfg = RuntimeConfig(model=str(model), opcua_enabled=False)
    cfg.source.url = f"replay://{campaign}?speed=20"
    svc = Service(cfg)

    async def main():
        run = asyncio.create_task(svc.run(30.0))
        loop = asyncio.get_running_loop()
        end = loop.time() + 20.0
        while not (svc.pipeline.zeroed and svc.frames > 200) and loop.time() < end:
            await asyncio.sleep(0.05)
        zero = svc.pipeline.wavelength_zero_nm.copy()
        answer = await svc.reload(str(model))
        assert answer == f"loaded {svc.model_id}"
        np.testing.assert_array_equal(svc.pipeline.wavelength_zero_nm, zero)
        with pytest.raises(InputError):
            await svc.reload(str(other))  # eq11 needs no probes: other inputs
        frames = svc.frames
        while svc.frames < frames + 100 and loop.time() < end:
            await asyncio.sleep(0.05)  # the reloaded model keeps running
        svc.stop()
        await run
        return svc.last_result

    last = asyncio.run(main())
    assert last.health[-1] == 0


def test_a_slow_disk_drops_batches_instead_of_blocking(tmp_path):
    fbgcomp_testing.require("pyarrow")
    from fbgcomp.runtime.log import RunLog, read_log
    from fbgcomp.runtime.pipeline import BatchResult
    from fbgcomp.runtime.windows import SensorBatch

    meta = {"sensor_names": ["S1", "S2"], "probe_names": ["T_bulk"]}
    log = RunLog(tmp_path / "log", meta, flush_s=0.2, max_queue=2)
    n, total = 50, 0
    for k in range(400):  # far faster than parquet files can be written
        t = 1.7e9 + k * n * 1e-3 + np.arange(n) * 1e-3
        b = SensorBatch(
            t, np.full((n, 2), 1530.0), np.ones((n, 2), np.int8), np.zeros((n, 2), np.int8), float(t[-1])
        )
        nan3 = np.full((n, 3), np.nan)
        r = BatchResult(
            t,
            nan3,
            nan3,
            np.zeros((n, 3)),
            nan3,
            np.zeros(n, np.uint8),
            np.zeros((n, 2), np.uint8),
            np.zeros(n, np.int16),
            np.full((n, 1), 20.0),
        )
        log.submit(b, r, True)
        total += n
    log.close()
    _, df = read_log(tmp_path / "log")
    assert log.dropped_rows > 0
    assert len(df) == log.written_rows == total - log.dropped_rows
    assert (np.diff(df["time_s"].to_numpy()) > 0).all()


def test_busy_opcua_port_is_a_one_line_error(paths, tmp_path, capsys, monkeypatch):
    import socket

    fbgcomp_testing.require("asyncua")
    monkeypatch.setenv("FBGCOMP_OPCUA_USER", "operator")
    monkeypatch.setenv("FBGCOMP_OPCUA_PASSWORD", "pw-for-test")
    model, campaign = paths
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        code = main(
            [
                "serve",
                "--model",
                str(model),
                "--source",
                f"replay://{campaign}",
                "--opcua",
                f"opc.tcp://127.0.0.1:{port}/fbgcomp/",
                "--state-dir",
                str(tmp_path / "state"),
                "--duration",
                "1",
            ]
        )
    err = capsys.readouterr().err.strip()
    assert code == 2 and err.startswith("error:") and "\n" not in err
    assert "opcua.endpoint" in err and "address already in use" in err


def test_sigterm_stops_gracefully_and_flushes_every_processed_frame(paths, tmp_path):
    import re
    import signal
    import time

    from fbgcomp.runtime.log import read_log
    from test_runtime_support import fbgcomp_process

    model, campaign = paths
    serve = fbgcomp_process(
        "serve",
        "--model",
        model,
        "--source",
        f"replay://{campaign}?speed=10",
        "--opcua",
        "off",
        "--log",
        tmp_path / "log",
    )
    try:
        end = time.monotonic() + 30
        while time.monotonic() < end and len(list((tmp_path / "log").rglob("part-*"))) < 3:
            time.sleep(0.1)
        serve.send_signal(signal.SIGTERM)
        _, err = serve.communicate(timeout=20)
    finally:
        if serve.poll() is None:
            serve.kill()
            serve.communicate()
    assert serve.returncode == 0, err.decode()[-2000:]
    frames = int(re.search(rb"processed (\d+) frames", err).group(1))
    _, df = read_log(tmp_path / "log")
    assert frames > 100 and len(df) == frames  # nothing lost on a graceful stop


def test_a_log_folder_of_another_sensor_set_is_refused(tmp_path):
    fbgcomp_testing.require("pyarrow")
    from fbgcomp.errors import InputError
    from fbgcomp.runtime.log import RunLog

    RunLog(tmp_path, {"sensor_names": ["S1"], "probe_names": []}).close()
    RunLog(tmp_path, {"sensor_names": ["S1"], "probe_names": []}).close()  # same run: appends
    with pytest.raises(InputError):
        RunLog(tmp_path, {"sensor_names": ["S1", "S2"], "probe_names": []})


def _batch(t, wavelength_nm, status, health):
    from fbgcomp.runtime.pipeline import BatchResult
    from fbgcomp.runtime.windows import SensorBatch

    n, S = wavelength_nm.shape
    b = SensorBatch(t, wavelength_nm, np.ones((n, S), np.int8), np.zeros((n, S), np.int8), float(t[-1]))
    dev = np.stack([np.sin(t), np.cos(t), t * 0.0], axis=1)
    r = BatchResult(
        t,
        dev,
        np.full((n, 3), 0.5),
        dev * 0.5,
        np.ones((n, 3)),
        health,
        status,
        np.zeros(n, np.int16),
        np.full((n, 1), 20.0),
        output_flags=np.zeros((n, 3), np.uint8),
    )
    return b, r


def test_health_and_status_are_named_and_old_integer_logs_still_read(tmp_path):
    """A real RunLog writes names; a log in the earlier layout (parts beside meta.json, integer
    codes) reads to the same codes and names, and both export to the same campaign."""
    fbgcomp_testing.require("pyarrow")
    import pandas as pd
    import pyarrow as pa
    import pyarrow.parquet as pq

    from fbgcomp.runtime import health as H
    from fbgcomp.runtime.log import RunLog, export_campaign, log_parts, read_log
    from fbgcomp.runtime.pipeline import HEALTH_NAMES

    meta = {
        "format": "fbgcomp-runlog",
        "sensor_names": ["S1", "S2"],
        "probe_names": ["T_amb"],
        "sensors": [
            {"name": "S1", "lambda0_nm": 1530.0, "gauge_length_mm": 100.0},
            {"name": "S2", "lambda0_nm": 1540.0, "gauge_length_mm": 100.0},
        ],
        "health_names": list(HEALTH_NAMES),
        "status_names": list(H.STATUS_NAMES),
    }
    t = 1.7e9 + np.arange(40) * 0.1
    health = np.repeat(np.arange(4, dtype=np.uint8), 10)  # OK, DEGRADED, ALARM, ZEROING
    status = np.zeros((40, 2), np.uint8)
    status[10:20, 1] = H.MISSING
    status[20:30, 0] = H.INCONSISTENT
    wl = np.column_stack([1530.0 + 1e-4 * np.arange(40), 1540.0 + 1e-4 * np.arange(40)])
    log = RunLog(tmp_path / "new", meta, flush_s=0.1)
    log.submit(*_batch(t, wl, status, health), True)
    log.close()
    (part,) = log_parts(tmp_path / "new")
    raw = pq.read_table(part)
    assert pa.types.is_dictionary(raw.schema.field("health").type)
    assert raw.column("health").to_pylist() == [HEALTH_NAMES[h] for h in health]
    assert raw.column("S2_status").to_pylist()[10:20] == ["MISSING"] * 10
    assert raw.column("S1_status").to_pylist()[20:30] == ["INCONSISTENT"] * 10
    assert np.isnan(raw.column("z_mm").to_numpy()).all()  # no position given: none logged

    # the same frames as the earlier RunLog wrote them: integer codes, parts beside meta.json
    old = tmp_path / "old"
    old.mkdir()
    (old / "meta.json").write_text(json.dumps(meta))
    table = raw.to_pandas()
    table["health"], table["S1_status"], table["S2_status"] = health, status[:, 0], status[:, 1]
    pq.write_table(
        pa.Table.from_pandas(table, preserve_index=False), old / "part-0000000000001-000000.parquet"
    )
    for folder in (tmp_path / "new", old):
        _, codes = read_log(folder)
        np.testing.assert_array_equal(codes["health"], health)
        np.testing.assert_array_equal(codes[["S1_status", "S2_status"]].to_numpy(), status)
        _, names = read_log(folder, labels=True)
        assert list(names["health"]) == [HEALTH_NAMES[h] for h in health]
        assert list(names["S2_status"][10:20]) == ["MISSING"] * 10
    new_c = export_campaign(tmp_path / "new", tmp_path / "c_new")
    old_c = export_campaign(old, tmp_path / "c_old")
    # healthy frames only: S2 MISSING and S1 INCONSISTENT frames are left out in both
    assert len(new_c.fbg) == len(old_c.fbg) == 20
    pd.testing.assert_frame_equal(new_c.fbg, old_c.fbg)
