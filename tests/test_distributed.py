import json
import os
import shutil
import subprocess
import sys

import numpy as np
import pytest

from fbgcomp.bench.synthetic import linear_truth_campaign
from fbgcomp.cluster import map_over_cluster
from fbgcomp.errors import InputError
from fbgcomp.io.campaign import read_campaign, write_campaign
from fbgcomp.io.dataset import ingest
from fbgcomp.models.distributed import accumulate_paths, fit_paths
from fbgcomp.models.mra import MRAModel
from fbgcomp.units import AXES
from fbgcomp_testing import require

FBGCOMP = [sys.executable, "-m", "fbgcomp"]


@pytest.fixture(scope="module")
def client():
    """A real LocalCluster: two single-threaded worker processes."""
    distributed = require("distributed")
    require("pyarrow")
    from fbgcomp.cluster import local_cluster

    with local_cluster(2) as lc, distributed.Client(lc) as c:
        yield c


@pytest.fixture(scope="session")
def data(tmp_path_factory):
    require("pyarrow")
    root = tmp_path_factory.mktemp("fleet")
    folders = []
    for i, (duration, offset) in enumerate(((1500, 0.3), (1100, 0.0), (800, 0.5))):
        c, _ = linear_truth_campaign(
            f"c{i}", seed=40 + i, duration_s=duration, temperature_dt_s=5, reference_offset_s=offset
        )
        folders.append(write_campaign(c, root / f"c{i}"))
    ds = root / "dataset"
    ingest(folders[:2], ds, machine="ram1", rows_per_file=350)
    ingest(folders[2:], ds, machine="ram2", rows_per_file=350)
    return folders, ds


@pytest.fixture(scope="session")
def reference_fit(data):
    """The in-process fit of the campaign folders (eq13, stepwise, no fallbacks)."""
    folders, _ = data
    return MRAModel(features="eq13", stepwise=True, fallbacks="none").fit([read_campaign(f) for f in folders])


def _assert_same_fit(got, want, rtol=1e-10):
    sets = [(got.axes_, want.axes_)] + [(got.fallbacks_[k], want.fallbacks_[k]) for k in want.fallbacks_]
    assert set(got.fallbacks_) == set(want.fallbacks_)
    for g, w in sets:
        for a in AXES:
            assert g[a].terms == w[a].terms
            np.testing.assert_allclose(g[a].params, w[a].params, rtol=rtol, atol=0)
            np.testing.assert_allclose(g[a].bse, w[a].bse, rtol=rtol, atol=0)
            assert g[a].nobs == w[a].nobs
            assert abs(g[a].rsquared - w[a].rsquared) <= rtol


def test_dask_fit_equals_in_process_fit(client, data, reference_fit):
    folders, ds = data
    params = dict(features="eq13", stepwise=True, p_enter=1e-4, p_remove=1e-3, fallbacks="loo")
    on_cluster = fit_paths(MRAModel(**params), [ds], dask=client)
    in_process = fit_paths(MRAModel(**params), [ds])
    from_folders = MRAModel(**params).fit([read_campaign(f) for f in folders])
    _assert_same_fit(on_cluster, in_process)
    _assert_same_fit(on_cluster, from_folders)
    # The stepwise search found the true terms of the synthetic truth.
    assert on_cluster.axes_["dy"].terms == ["const", "dL_S3", "dL_S4", "dT_flange"]
    names = [c["name"] for c in on_cluster.training_["campaigns"]]
    assert names == ["c0", "c1", "c2"]
    assert on_cluster.training_["n_samples"] == from_folders.training_["n_samples"]
    assert [c["machine"] for c in on_cluster.training_["campaigns"]] == ["ram1", "ram1", "ram2"]
    # Campaign folders also fan out over the cluster (one task per folder).
    folders_on_cluster = fit_paths(
        MRAModel(features="eq13", stepwise=True, fallbacks="none"), folders, dask=client
    )
    _assert_same_fit(folders_on_cluster, reference_fit)


def test_stepwise_and_fallbacks_run_on_the_reduced_factor_alone(client, data, tmp_path):
    folders, ds = data
    copy = tmp_path / "copy"
    shutil.copytree(ds, copy)
    model = MRAModel(features="eq12", stepwise=True, fallbacks="none")
    acc, training = accumulate_paths(model, [copy], dask=client)
    shutil.rmtree(copy)  # nothing left to re-read
    model.fit_factor(acc, training=training)
    assert all(model.axes_[a].history for a in AXES)
    want = MRAModel(features="eq12", stepwise=True, fallbacks="none").fit([read_campaign(f) for f in folders])
    for a in AXES:
        assert model.axes_[a].terms == want.axes_[a].terms
        # eq12 is ill-conditioned (kappa ~1e5): equal normwise to 1e-10.
        diff = np.abs(model.axes_[a].params - want.axes_[a].params)
        assert diff.max() <= 1e-10 * np.abs(want.axes_[a].params).max()


def _worker_pid(x):
    return x * x, os.getpid()


def _malloc_trim(_):
    return os.environ.get("MALLOC_TRIM_THRESHOLD_"), os.getpid()


def test_map_over_cluster_keeps_order_in_process_and_on_workers(client):
    items = list(range(12))
    local = map_over_cluster(_worker_pid, items)
    remote = map_over_cluster(_worker_pid, items, dask=client)
    assert [v for v, _ in local] == [v for v, _ in remote] == [i * i for i in items]
    assert {p for _, p in local} == {os.getpid()}
    assert os.getpid() not in {p for _, p in remote}
    # "local:N" starts (and stops) its own cluster, whose workers keep glibc's malloc defaults.
    trims = map_over_cluster(_malloc_trim, [0, 1], dask="local:1")
    assert {t for t, _ in trims} == {os.environ.get("MALLOC_TRIM_THRESHOLD_")}
    assert os.getpid() not in {p for _, p in trims}


def test_two_local_clusters_at_once_take_no_fixed_port_and_warn_nothing(client):
    """dask's scheduler serves HTTP (health, metrics) even without a dashboard, on 8787 unless
    told otherwise: the second cluster on a machine (this module's ``client`` fixture is the
    first) warned on stderr that the port was taken. fbgcomp's clusters take a free loopback
    port each."""
    import warnings

    from fbgcomp.cluster import local_cluster

    with warnings.catch_warnings():
        warnings.simplefilter("error")  # dask's "Port 8787 is already in use" fails the test
        with local_cluster(1) as a, local_cluster(1) as b:
            ports = []
            for lc in (a, client.cluster, b):
                bound = [s.getsockname() for s in lc.scheduler.http_server._sockets.values()]
                assert bound and all(host == "127.0.0.1" for host, _ in bound), bound
                ports += [port for _, port in bound]
    assert 8787 not in ports and len(set(ports)) == len(ports), ports


def run(*args):
    return subprocess.run(
        [*FBGCOMP, *map(str, args)],
        capture_output=True,
        text=True,
        timeout=180,
        env={**os.environ, "PYTHONWARNINGS": "ignore"},
    )


def test_cli_fits_a_dataset_on_a_scheduler_address(client, data, reference_fit, tmp_path):
    _folders, ds = data
    address = client.scheduler.address
    assert address.startswith("tcp://")
    out = tmp_path / "model.json"
    r = run(
        "fit", ds, "--features", "eq13", "--stepwise", "--fallbacks", "none", "--dask", address, "-o", out
    )
    assert r.returncode == 0, r.stderr
    assert "== dx (µm) ==" in r.stdout and "stepwise history" in r.stdout
    got = json.loads(out.read_text())
    want = reference_fit
    for a in AXES:
        assert got["axes"][a]["terms"] == want.axes_[a].terms
        np.testing.assert_allclose(got["axes"][a]["params"], want.axes_[a].params, rtol=1e-10)
    assert got["training"]["n_samples"] == want.training_["n_samples"]

    r = run("fit", ds, "--dask", "cluster-please", "-o", tmp_path / "m2.json")
    assert r.returncode == 2
    assert r.stderr.strip() == (
        "error: <command line>, column option --dask: --dask expects "
        "tcp://HOST:PORT or local:N, got 'cluster-please'"
    )


def test_incompatible_partition_is_a_clear_error(data, tmp_path):
    _folders, ds = data
    other = tmp_path / "other"
    c, _ = linear_truth_campaign("short", seed=3, duration_s=300)
    c.meta.sensors[2].gauge_length_mm = 123.0
    ingest([write_campaign(c, tmp_path / "short")], other)
    with pytest.raises(InputError, match=r"sensor S3 has gauge_length_mm 123\.0"):
        fit_paths(MRAModel(features="eq13"), [ds, other])
