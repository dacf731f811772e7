"""Distributed fit: time and peak memory per worker, local Dask cluster vs. in-process.

For each row count (default 10^7 and 10^8) the rows are cut into partitions of
``--partition-rows`` (default 10^6). Every partition is *generated inside the task that
consumes it*, chunk by chunk (``--chunk-rows``): raw interrogator wavelengths (nm, from known
elongations through the bonded-FBG forward model, paper eq. 2-4), probe temperatures (°C) and a
TTP deviation (µm) that is a known eq. 13 combination plus noise. The task runs the production
feature chain (:meth:`fbgcomp.models.mra.MRAModel.design_from_arrays`) into a QR factor; factors are
merged as a binary tree by :func:`fbgcomp.cluster.tree_reduce` (on the workers with Dask),
and the eq. 13 stepwise model is selected from the final factor. No process ever holds more
than one chunk of rows, so the memory of a worker must stay flat as rows grow.

Runs, per row count:
  * in-process: the same tasks one after the other in a fresh child process (its peak RSS);
  * Dask: a fresh ``LocalCluster`` of ``--workers`` single-threaded worker processes (peak RSS
    of each worker process, ``ru_maxrss``, and its RSS when idle before the run).
Prints times, peak memories, rows/s, the speed-up and that both fits agree (1e-10 relative),
then one JSON line.

    python benchmarks/bench_scale.py [--rows 10000000,100000000] [--workers 2]
                                     [--partition-rows 1000000] [--chunk-rows 100000]
"""

from __future__ import annotations

import os

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import concurrent.futures  # noqa: E402
import json  # noqa: E402
import multiprocessing  # noqa: E402
import platform  # noqa: E402
import resource  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402

SEED = 2026
NOISE_UM = 0.3


def _sensors():
    from fbgcomp.bench.synthetic import default_meta
    from fbgcomp.io.campaign import CampaignMeta

    return list(CampaignMeta(**default_meta()).sensors)


def _model():
    from fbgcomp.models.mra import MRAModel

    model = MRAModel(features="eq13", stepwise=True, fallbacks="loo")
    model.new_accumulator(_sensors())
    return model


def synthetic_partition(task: dict) -> dict:
    """One task: generate partition ``task['index']`` chunk by chunk and accumulate it."""
    from fbgcomp import optics
    from fbgcomp.bench.synthetic import default_coefficients

    model = _model()
    acc = model.new_accumulator(model.sensors_)
    sensors = model.sensors_
    lam0 = np.array([s.lambda0_nm for s in sensors])
    gauge = np.array([s.gauge_length_mm for s in sensors])
    truth = default_coefficients()
    names = ["const", *model.candidates_]
    beta = np.array([[truth[a].get(n, 0.0) for a in ("dx", "dy", "dz")] for n in names])
    probes = model.probe_names_  # T_surf, T_bulk, T_flange (model order)
    t_zero = np.array([30.0, 30.0, 30.0])[: len(probes)]
    rng = np.random.default_rng([SEED, task["index"]])
    period_s = 36 * 3600.0
    rows, chunk = task["rows"], task["chunk_rows"]
    for lo in range(0, rows, chunk):
        m = min(chunk, rows - lo)
        t = (task["start"] + lo + np.arange(m)) * (period_s / task["total"])
        ph = 2 * np.pi * t / period_s
        temps = t_zero + np.column_stack([4.0 * (1 - np.cos(ph + k)) for k in range(len(probes))])
        temps += rng.normal(scale=0.02, size=temps.shape)
        elong = np.column_stack([15.0 * np.sin(ph * (j + 1) + j) for j in range(len(sensors))])
        elong += rng.normal(scale=1.0, size=elong.shape)
        dt_sensor = (temps[:, [probes.index("T_surf")]] - t_zero[probes.index("T_surf")]) * np.ones(
            len(sensors)
        )
        wl = optics.wavelength_nm(elong, lam0, gauge, dt_sensor)
        design = model.design_from_arrays(wl, temps, lam0, t_zero)
        dev = design @ beta + rng.normal(scale=NOISE_UM, size=(m, 3))
        acc.update(design, dev)
    return acc.to_dict()


def merge_states(a: dict, b: dict) -> dict:
    from fbgcomp.models.regression import QRAccumulator

    return QRAccumulator.from_dict(a).merge(QRAccumulator.from_dict(b)).to_dict()


def tasks_for(rows: int, partition_rows: int, chunk_rows: int) -> list[dict]:
    out = []
    for i, start in enumerate(range(0, rows, partition_rows)):
        out.append(
            {
                "index": i,
                "start": start,
                "rows": min(partition_rows, rows - start),
                "total": rows,
                "chunk_rows": chunk_rows,
            }
        )
    return out


def peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def cpu_s() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def current_rss_mb() -> float:
    import psutil

    return psutil.Process().memory_info().rss / 2**20


def fit_from_state(state: dict):
    from fbgcomp.models.regression import QRAccumulator

    model = _model()
    t0 = time.perf_counter()
    model.fit_factor(QRAccumulator.from_dict(state))
    return model, time.perf_counter() - t0


def in_process_run(rows: int, partition_rows: int, chunk_rows: int) -> dict:
    """Runs in a fresh child process so that its peak RSS is this run's alone."""
    from fbgcomp.cluster import tree_reduce

    idle = current_rss_mb()
    t0, c0 = time.perf_counter(), cpu_s()
    state = tree_reduce(synthetic_partition, tasks_for(rows, partition_rows, chunk_rows), merge_states)
    reduce_s = time.perf_counter() - t0
    return {
        "state": state,
        "reduce_s": reduce_s,
        "idle_rss_mb": idle,
        "peak_rss_mb": peak_rss_mb(),
        "cpu_s": [cpu_s() - c0],
    }


def dask_run(rows: int, partition_rows: int, chunk_rows: int, workers: int) -> dict:
    from distributed import Client

    from fbgcomp.cluster import local_cluster, tree_reduce

    with local_cluster(workers, memory_limit=0) as lc, Client(lc) as client:
        idle = client.run(current_rss_mb)
        cpu0 = client.run(cpu_s)
        t0 = time.perf_counter()
        state = tree_reduce(
            synthetic_partition, tasks_for(rows, partition_rows, chunk_rows), merge_states, dask=client
        )
        reduce_s = time.perf_counter() - t0
        peaks = client.run(peak_rss_mb)
        cpu1 = client.run(cpu_s)
    return {
        "state": state,
        "reduce_s": reduce_s,
        "idle_rss_mb": sorted(idle.values()),
        "peak_rss_mb": sorted(peaks.values()),
        "cpu_s": sorted(cpu1[w] - cpu0[w] for w in cpu1),
    }


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument(
        "--rows", default="10000000,100000000", help="comma-separated row counts (e.g. 1000000,10000000)"
    )
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--partition-rows", type=int, default=1_000_000)
    ap.add_argument("--chunk-rows", type=int, default=100_000)
    ap.add_argument(
        "--skip-in-process",
        action="store_true",
        help="only the Dask run (the in-process one takes ~workers x longer)",
    )
    args = ap.parse_args(argv)
    sizes = [int(float(s)) for s in args.rows.split(",") if s]

    print(
        f"load average (1/5/15 min) at start: {', '.join(f'{v:.1f}' for v in os.getloadavg())} "
        "(a shared machine: wall times depend on the neighbours, CPU times and RSS do not)"
    )
    print(
        f"bench_scale: eq13 stepwise + loo fallbacks, partitions of {args.partition_rows} rows "
        f"generated in-task in chunks of {args.chunk_rows}; LocalCluster of {args.workers} "
        f"worker processes x 1 thread; Python {platform.python_version()}, "
        f"{os.cpu_count()} cores"
    )
    results = []
    ctx = multiprocessing.get_context("spawn")
    for rows in sizes:
        line = {"rows": rows, "partitions": len(tasks_for(rows, args.partition_rows, args.chunk_rows))}
        local = None
        if not args.skip_in_process:
            with concurrent.futures.ProcessPoolExecutor(1, mp_context=ctx) as ex:
                local = ex.submit(in_process_run, rows, args.partition_rows, args.chunk_rows).result()
            model_local, select_s = fit_from_state(local["state"])
            line.update(
                {
                    "in_process_s": round(local["reduce_s"] + select_s, 2),
                    "in_process_cpu_s": round(local["cpu_s"][0], 1),
                    "load_avg_1min": round(os.getloadavg()[0], 1),
                    "in_process_peak_rss_mb": round(local["peak_rss_mb"], 1),
                    "in_process_idle_rss_mb": round(local["idle_rss_mb"], 1),
                }
            )
            print(
                f"{rows:>12,d} rows  in-process: {line['in_process_s']:8.1f} s "
                f"({rows / line['in_process_s']:,.0f} rows/s; CPU {local['cpu_s'][0]:.0f} s), peak RSS "
                f"{local['peak_rss_mb']:.0f} MB (idle {local['idle_rss_mb']:.0f} MB)"
            )
            sys.stdout.flush()
        dask = dask_run(rows, args.partition_rows, args.chunk_rows, args.workers)
        model_dask, select_s = fit_from_state(dask["state"])
        line.update(
            {
                "dask_s": round(dask["reduce_s"] + select_s, 2),
                "select_s": round(select_s, 3),
                "dask_peak_rss_mb_per_worker": [round(v, 1) for v in dask["peak_rss_mb"]],
                "dask_idle_rss_mb_per_worker": [round(v, 1) for v in dask["idle_rss_mb"]],
                "dask_cpu_s_per_worker": [round(v, 1) for v in dask["cpu_s"]],
                "load_avg_1min_after": round(os.getloadavg()[0], 1),
            }
        )
        print(
            f"{rows:>12,d} rows  dask x{args.workers}:   {line['dask_s']:8.1f} s "
            f"({rows / line['dask_s']:,.0f} rows/s; CPU per worker "
            f"{', '.join(f'{v:.0f}' for v in dask['cpu_s'])} s), peak RSS per worker "
            f"{', '.join(f'{v:.0f}' for v in dask['peak_rss_mb'])} MB (idle "
            f"{', '.join(f'{v:.0f}' for v in dask['idle_rss_mb'])} MB); selection from the "
            f"factor {select_s:.2f} s"
        )
        if local is not None:
            worst = 0.0
            for a in ("dx", "dy", "dz"):
                assert model_local.axes_[a].terms == model_dask.axes_[a].terms
                p, q = model_local.axes_[a].params, model_dask.axes_[a].params
                worst = max(worst, float(np.max(np.abs(p - q) / np.abs(p))))
            line["speedup"] = round(line["in_process_s"] / line["dask_s"], 2)
            line["max_rel_coef_diff"] = worst
            print(
                f"{'':>12}       speed-up {line['speedup']:.2f}x; dask vs in-process "
                f"coefficients: max relative difference {worst:.1e}"
            )
        line["dx_terms"] = model_dask.axes_["dx"].terms
        results.append(line)
        sys.stdout.flush()
    if len(results) > 1:
        a, b = results[0], results[-1]
        growth = max(b["dask_peak_rss_mb_per_worker"]) / max(a["dask_peak_rss_mb_per_worker"])
        print(
            f"peak RSS per worker, {b['rows']:,d} vs {a['rows']:,d} rows: x{growth:.2f} "
            f"for x{b['rows'] / a['rows']:.0f} rows"
        )
    print(
        json.dumps(
            {
                "bench": "scale",
                "workers": args.workers,
                "partition_rows": args.partition_rows,
                "results": results,
            }
        )
    )


if __name__ == "__main__":
    main()
