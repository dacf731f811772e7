import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml

from fbgcomp.bench.synthetic import linear_truth_campaign
from fbgcomp.errors import InputError
from fbgcomp.io.campaign import read_campaign, write_campaign
from fbgcomp.io.dataset import (
    INDEX_FILE,
    METADATA_KEY,
    accumulate_partition_file,
    ingest,
    is_dataset,
    open_dataset,
)
from fbgcomp.models.mra import MRAModel
from fbgcomp_testing import require

SCALE_CLI = [sys.executable, "-m", "fbgcomp"]


def run(*args):
    return subprocess.run(
        [*SCALE_CLI, *map(str, args)],
        capture_output=True,
        text=True,
        timeout=120,
        env={**os.environ, "PYTHONWARNINGS": "ignore"},
    )


@pytest.fixture(scope="session")
def campaigns(tmp_path_factory):
    require("pyarrow")
    root = tmp_path_factory.mktemp("campaigns")
    a, _ = linear_truth_campaign(
        "run_a", seed=11, duration_s=1500, temperature_dt_s=10, reference_offset_s=0.3
    )
    b, _ = linear_truth_campaign("run_b", seed=12, duration_s=900)
    pa_ = write_campaign(a, root / "run_a")
    pb = write_campaign(b, root / "run_b")
    # run_b names its machine in campaign.yaml; run_a takes --machine.
    meta = yaml.safe_load((pb / "campaign.yaml").read_text())
    meta["machine"] = "ram 2/B"
    (pb / "campaign.yaml").write_text(yaml.safe_dump(meta, sort_keys=False))
    return pa_, pb


def test_ingest_stores_aligned_raw_samples_readable_by_pandas_duckdb_and_dask(campaigns, tmp_path):
    duckdb = require("duckdb")
    dd = require("dask.dataframe")
    pa_, pb = campaigns
    ds = tmp_path / "fleet"
    parts = ingest([pa_, pb], ds, machine="ram1", rows_per_file=400)
    assert [(p.machine, p.campaign) for p in parts] == [("ram1", "run_a"), ("ram 2/B", "run_b")]
    assert is_dataset(ds) and (ds / INDEX_FILE).is_file()
    # Hive layout, values URI-encoded in the folder names.
    assert (ds / "machine=ram1" / "campaign=run_a" / "part-00000.parquet").is_file()
    assert (ds / "machine=ram%202%2FB" / "campaign=run_b").is_dir()
    assert len(parts[0].files) == -(-parts[0].n_rows // 400) > 1

    for path, part in zip((pa_, pb), parts):
        c = read_campaign(path)
        al = c.aligned()
        frame = open_dataset(ds).to_pandas(machine=part.machine, campaign=part.campaign)
        assert len(frame) == len(al)
        assert np.array_equal(frame["time_s"], al.time_s)
        assert np.array_equal(frame[[f"{s}_nm" for s in al.sensor_names]], al.wavelength_nm)
        assert np.array_equal(frame[[f"{p}_C" for p in al.probe_names]], al.temperature_C)
        # Raw reference stored; minus the stored zero it is exactly what the fit regresses on.
        raw = frame[["dx_um", "dy_um", "dz_um"]].to_numpy()
        assert np.array_equal(raw - part.reference_zero_um, al.reference_um)
        assert np.array_equal(part.wavelength_zero_nm, al.wavelength_zero_nm)
        assert np.array_equal(part.temperature_zero_C, al.temperature_zero_C)
        # The campaign.yaml content travels in every file's key-value metadata.
        import pyarrow.parquet as pq

        kv = json.loads(pq.read_schema(part.file_paths[-1]).metadata[METADATA_KEY])
        assert kv["meta"]["name"] == part.campaign and kv["meta"]["sensors"][0]["lambda0_nm"] == 1530.0
        assert kv["zero_window_s"] == 10.0

    # Three engines, one table, with the partition columns.
    whole = pd.read_parquet(ds)
    assert len(whole) == sum(p.n_rows for p in parts)
    assert set(whole["machine"].astype(str)) == {"ram1", "ram 2/B"}
    with duckdb.connect() as con:  # not the module's default connection, alive until exit
        counts = con.sql(
            f"select machine, campaign, count(*) from read_parquet("
            f"'{ds}/machine=*/campaign=*/*.parquet', hive_partitioning=true) "
            f"group by all order by all"
        ).fetchall()
    assert counts == sorted([(p.machine, p.campaign, p.n_rows) for p in parts])
    mean_dd = dd.read_parquet(str(ds)).groupby("campaign")["S1_nm"].mean().compute()
    mean_pd = whole.groupby("campaign", observed=True)["S1_nm"].mean()
    by_dd = {str(k): v for k, v in mean_dd.items()}
    by_pd = {str(k): v for k, v in mean_pd.items()}
    assert by_dd.keys() == by_pd.keys() == {"run_a", "run_b"}
    assert all(np.isclose(by_dd[k], by_pd[k], rtol=1e-14) for k in by_pd)


def test_ingest_through_the_console_and_bad_input(campaigns, tmp_path):
    pa_, _ = campaigns
    ds = tmp_path / "ds"
    r = run("ingest", pa_, "--to", ds)
    assert r.returncode == 0, r.stderr
    n = len(read_campaign(pa_).aligned())
    assert f"machine=default campaign=run_a: {n} rows" in r.stdout
    assert open_dataset(ds).partitions[0].machine == "default"

    r = run("ingest", tmp_path / "nowhere", "--to", ds)
    assert r.returncode == 2 and r.stderr.startswith("error: ") and "campaign folder not found" in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1

    stray = tmp_path / "notes"
    stray.mkdir()
    (stray / "readme.txt").write_text("mine")
    r = run("ingest", pa_, "--to", stray)
    assert r.returncode == 2 and "not one" in r.stderr
    assert sorted(p.name for p in stray.iterdir()) == ["readme.txt"]


def test_failed_or_crashed_ingest_never_shows_a_half_written_partition(campaigns, tmp_path, monkeypatch):
    import pyarrow.parquet as pq

    pa_, _ = campaigns
    ds = tmp_path / "ds"
    ingest([pa_], ds, rows_per_file=400)
    before = pd.read_parquet(ds)

    # A failure while writing the third file of a re-ingest: the old partition stays whole.
    real_write = pq.write_table
    calls = []

    def failing_write(table, where, **kw):
        calls.append(where)
        if len(calls) == 3:
            real_write(table.slice(0, 10), where, **kw)  # a partial file on disk ...
            raise OSError("disk full")  # ... then the failure
        return real_write(table, where, **kw)

    monkeypatch.setattr(pq, "write_table", failing_write)
    with pytest.raises(OSError, match="disk full"):
        ingest([pa_], ds, rows_per_file=400)
    monkeypatch.setattr(pq, "write_table", real_write)
    assert not [p for p in ds.iterdir() if p.name.startswith(".ingest")]
    pd.testing.assert_frame_equal(pd.read_parquet(ds), before)

    # A kill -9 leaves its staging folder behind: every reader ignores it.
    staging = ds / ".ingest.tmp-deadbeef" / "machine=default" / "campaign=run_a"
    staging.mkdir(parents=True)
    real_write(
        pq.read_table(ds / "machine=default" / "campaign=run_a" / "part-00000.parquet"),
        staging / "part-00009.parquet",
    )
    pd.testing.assert_frame_equal(pd.read_parquet(ds), before)
    assert open_dataset(ds).n_rows == len(before)


def test_partition_describes_itself_when_the_index_is_stale(campaigns, tmp_path):
    pa_, pb = campaigns
    ds = tmp_path / "ds"
    ingest([pa_, pb], ds, rows_per_file=500)
    want = open_dataset(ds)
    (ds / INDEX_FILE).unlink()  # e.g. a crash between the folder rename and the index
    got = open_dataset(ds)
    assert [(p.machine, p.campaign, p.n_rows, p.files) for p in got.partitions] == [
        (p.machine, p.campaign, p.n_rows, p.files) for p in want.partitions
    ]
    assert np.array_equal(got.partitions[1].wavelength_zero_nm, want.partitions[1].wavelength_zero_nm)


def test_partition_stream_accumulates_the_same_factor_as_the_campaign_fit(campaigns, tmp_path):
    pa_, _ = campaigns
    ds = tmp_path / "ds"
    (part,) = ingest([pa_], ds, rows_per_file=300)
    model = MRAModel(features="eq12", fallbacks="none")
    acc = model.new_accumulator(part.sensors(), part.probe_names)
    for f in part.file_paths:
        accumulate_partition_file(model, part, f, acc)
    with pytest.raises(ValueError, match="cover 0 of the 1500 rows"):
        model.fit_factor(acc.copy())  # Newey-West needs the second pass
    acc.begin_hac()
    for f in part.file_paths:
        accumulate_partition_file(model, part, f, acc, second_pass=True)
    model.fit_factor(acc)
    ref = MRAModel(features="eq12", fallbacks="none").fit(read_campaign(pa_))
    # Same rows cut into other chunks: equal up to the QR's rounding, kappa * u normwise (eq12's
    # raw quadratic temperature terms make kappa ~1e5, so a small coefficient alone may differ
    # by more than 1e-10 of itself). The Newey-West standard errors come from a sum of squares
    # (the meat) whose weakest direction holds eps kappa^2 ~ 1.6e-5 of it: equal to that.
    for axis in ("dx", "dy", "dz"):
        got, want = model.axes_[axis], ref.axes_[axis]
        assert got.terms == want.terms
        assert np.max(np.abs(got.params - want.params)) <= 1e-10 * np.max(np.abs(want.params))
        assert got.cov_type == want.cov_type == "HAC"
        assert np.all(want.bse > 0)
        np.testing.assert_allclose(got.bse, want.bse, rtol=2e-5)


def test_zero_window_must_match_the_ingested_one(campaigns, tmp_path):
    from fbgcomp.models.distributed import fit_paths

    pa_, _ = campaigns
    ds = tmp_path / "ds"
    ingest([pa_], ds, zero_window_s=20.0)
    with pytest.raises(InputError, match="--zero-window 20"):
        fit_paths(MRAModel(features="eq13", zero_window_s=10.0), [ds])
    model = fit_paths(MRAModel(features="eq13", zero_window_s=20.0, fallbacks="none"), [ds])
    ref = MRAModel(features="eq13", zero_window_s=20.0, fallbacks="none").fit(read_campaign(pa_))
    np.testing.assert_allclose(model.axes_["dx"].params, ref.axes_["dx"].params, rtol=1e-10)


def _write_run_log(folder: Path, campaign, machine: str) -> Path:
    """A run log in the runtime's documented format (meta.json + part-*.parquet)."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    folder.mkdir()
    sensors = campaign.meta.sensors
    probes = campaign.meta.probe_names
    meta = {
        "format": "fbgcomp-runlog",
        "version": 1,
        "model_id": "abc123",
        "machine": machine,
        "sensor_names": [s.name for s in sensors],
        "probe_names": probes,
        "sensors": [s.model_dump(mode="json") for s in sensors],
        "temperature_probes": [p.model_dump(mode="json") for p in campaign.meta.temperature_probes],
    }
    (folder / "meta.json").write_text(json.dumps(meta))
    al = campaign.aligned()
    t = 1.7e9 + al.time_s
    for k, sl in enumerate((slice(0, 600), slice(600, None))):
        cols = {"time_s": t[sl], "received_s": t[sl] + 0.01}
        for j, s in enumerate(sensors):
            cols[f"{s.name}_nm"] = al.wavelength_nm[sl, j]
            cols[f"{s.name}_peaks"] = np.ones(len(t[sl]), np.int16)
            cols[f"{s.name}_status"] = np.zeros(len(t[sl]), np.int8)
        for j, p in enumerate(probes):
            cols[f"{p}_C"] = al.temperature_C[sl, j]
        for a in ("dx", "dy", "dz"):
            for kind in ("dev", "half", "corr"):
                cols[f"{kind}_{a}_um"] = np.zeros(len(t[sl]))
        cols["health"] = np.zeros(len(t[sl]), np.int8)
        cols["model_set"] = np.zeros(len(t[sl]), np.int16)
        cols["enabled"] = np.ones(len(t[sl]), bool)
        pq.write_table(pa.table(cols), folder / f"part-{k:013d}-{k:06d}.parquet")
    return folder


def test_a_run_log_is_ingested_with_a_measured_reference(campaigns, tmp_path):
    pa_, _ = campaigns
    c = read_campaign(pa_)
    log = _write_run_log(tmp_path / "log_2026_01_12", c, machine="ram7")
    al = c.aligned()
    ref = pd.DataFrame(
        {
            "time_s": al.time_s - al.time_s[0],
            **{f"{a}_um": al.reference_um[:, j] for j, a in enumerate(("dx", "dy", "dz"))},
        }
    )
    ref.to_csv(tmp_path / "interferometer.csv", index=False)
    ds = tmp_path / "ds"
    r = run("ingest", log, "--to", ds, "--reference", tmp_path / "interferometer.csv")
    assert r.returncode == 0, r.stderr
    (part,) = open_dataset(ds).partitions
    assert (part.machine, part.campaign, part.n_rows) == ("ram7", "log_2026_01_12", len(al))
    assert part.source == str(log)
    frame = open_dataset(ds).to_pandas()
    np.testing.assert_array_equal(frame["S3_nm"], al.wavelength_nm[:, 2])
