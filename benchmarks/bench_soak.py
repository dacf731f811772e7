"""Soak benchmark (issue 13): ``fbgcomp serve`` for minutes against a simulated interrogator
injecting random faults, then ``kill -9``.

``fbgcomp sim-interrogator`` (a real process, 1 kHz, 0.3 pm noise, the campaign looped) is given
a random schedule of faults that come and go: grating drops, doubled peaks, mode hops inside
the window (a 0.3-2 nm shift there and back), shifts out of the window, stuck channels, link
cuts and bursts of random bytes on the stream. ``fbgcomp serve`` runs with its default output
policy and a run log. Printed:

* the largest |published correction| per axis against the model's bound (the per-axis maximum
  |correction|, the envelope the correction is trusted in), and the frames published with
  Health OK whose correction or raw prediction lies beyond it (must be 0);
* how far the corrections published with Health OK are from the fault-free one (the full model
  on the campaign's noise-free wavelengths at the same instants): what a bound alone misses;
* serve's resident memory (RSS) after the warm-up and at the end, MiB and %;
* reconnects (serve's "link lost" warnings, one per failed attempt) and gaps in the logged
  frames, against the cuts and garbage bursts injected;
* after ``kill -9`` of serve: run-log files unreadable, and frames the instrument sent before
  the kill that are missing from the log's tail.

Usage: python benchmarks/bench_soak.py [--seconds 300] [--quick] [--seed 13]
The last line printed is the JSON summary.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from _loopback import free_port, wait_port

SENSORS = ["S1", "S2", "S3", "S4", "S5"]
WARMUP_S = 15.0  # zero state and first faults-free seconds; RSS is taken after it


def _model_and_campaign(tmp: Path):
    from fbgcomp.bench.synthetic import linear_truth_campaign
    from fbgcomp.io.campaign import write_campaign
    from fbgcomp.models.mra import MRAModel

    train, _ = linear_truth_campaign("train", seed=1, duration_s=2 * 3600, noise_um=0.05)
    model = MRAModel(features="eq13", zero_window_s=0.5, fallbacks="loo").fit(train)
    serve, _ = linear_truth_campaign(
        "serve", seed=2, duration_s=600, fbg_dt_s=0.1, temperature_dt_s=0.1, reference_dt_s=0.1, settle_s=0.0
    )
    return model.save(tmp / "model.json"), write_campaign(serve, tmp / "serve")


def fault_schedule(seconds: float, rng: np.random.Generator, mean_gap_s: float = 6.0):
    """Random faults from WARMUP_S to ``seconds`` - 5: (spec, kind) pairs; the first seven
    are one of each kind in random order, the rest drawn at random."""
    kinds = ["drop", "double", "hop", "out", "stuck", "cut", "garbage"]
    first = list(rng.permutation(kinds))
    out, t = [], WARMUP_S
    while True:
        t += rng.exponential(mean_gap_s)
        if t > seconds - 5.0:
            return out
        kind = first.pop(0) if first else rng.choice(kinds, p=[0.18, 0.12, 0.22, 0.1, 0.1, 0.14, 0.14])
        s = rng.choice(SENSORS)
        if kind == "drop":
            spec = f"drop:{s}@{t:.2f}/{rng.uniform(0.5, 5):.2f}"
        elif kind == "double":
            spec = f"double:{s}@{t:.2f}/{rng.uniform(0.5, 3):.2f}"
        elif kind == "hop":  # inside the window (2.5 nm), there and back
            nm = rng.choice([-1, 1]) * rng.uniform(0.3, 2.0)
            spec = f"shift:{s}@{t:.2f}:{nm:+.3f}/{rng.uniform(2, 20):.2f}"
        elif kind == "out":
            spec = f"shift:{s}@{t:.2f}:{rng.choice([-6, 6]):+d}/{rng.uniform(1, 5):.2f}"
        elif kind == "stuck":
            spec = f"stuck:{s}@{t:.2f}/{rng.uniform(3, 8):.2f}"
        elif kind == "cut":
            spec = f"cut@{t:.2f}:{rng.uniform(0.5, 2):.2f}"
        else:
            spec = f"garbage@{t:.2f}:{int(rng.integers(512, 8192))}"
        out.append((spec, str(kind)))


def _rss_mib(pid: int) -> float:
    with open(f"/proc/{pid}/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    return float("nan")


def soak(seconds: float, seed: int, rate_hz: float, tmp: Path) -> dict:
    import pyarrow.parquet as pq

    from fbgcomp.models.registry import load_model
    from fbgcomp.runtime.log import log_parts, read_log
    from fbgcomp.runtime.pipeline import HEALTH_OK, Pipeline

    model_path, campaign = _model_and_campaign(tmp)
    bound = Pipeline(load_model(model_path)).max_correction_um
    faults = fault_schedule(seconds, np.random.default_rng(seed))
    sp, cp, op = free_port(), free_port(), free_port()
    env = dict(
        os.environ,
        FBGCOMP_OPCUA_USER="soak",
        FBGCOMP_OPCUA_PASSWORD="soak-password",
        OPENBLAS_NUM_THREADS="1",
    )
    py = [sys.executable, "-m", "fbgcomp"]
    (tmp / "serve.toml").write_text("[source]\nbackoff_initial_s = 0.05\nbackoff_max_s = 0.4\n")
    serve_err = open(tmp / "serve.err", "w")  # noqa: SIM115 - closed in the finally below, after serve
    serve = subprocess.Popen(
        [
            *py,
            "serve",
            "--config",
            str(tmp / "serve.toml"),
            "--model",
            str(model_path),
            "--source",
            f"hyperion://127.0.0.1:{sp}?command_port={cp}",
            "--temperatures",
            str(campaign),
            "--opcua",
            f"opc.tcp://127.0.0.1:{op}/fbgcomp/",
            "--state-dir",
            str(tmp / "state"),
            "--log",
            str(tmp / "log"),
        ],
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=serve_err,
    )
    sim = None
    rss = []
    try:
        wait_port(op, 60)
        sim_cmd = [
            *py,
            "sim-interrogator",
            str(campaign),
            "--port",
            str(sp),
            "--command-port",
            str(cp),
            "--rate",
            str(rate_hz),
            "--noise-pm",
            "0.3",
            "--loop",
            "--send-log",
            str(tmp / "sent.npy"),
        ]
        for spec, _ in faults:
            sim_cmd += ["--fault", spec]
        sim = subprocess.Popen(sim_cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        t0 = time.monotonic()
        while time.monotonic() - t0 < seconds:
            time.sleep(1.0)
            if serve.poll() is not None or sim.poll() is not None:
                raise RuntimeError(
                    "serve or the simulator stopped during the soak: "
                    + (tmp / "serve.err").read_text()[-2000:]
                )
            rss.append((time.monotonic() - t0, _rss_mib(serve.pid)))
        os.kill(serve.pid, signal.SIGKILL)
        t_kill = time.time()
        serve.wait(10)
        sim.send_signal(signal.SIGTERM)  # it saves its send log on the way out
        sim.wait(20)
    finally:
        for p in (sim, serve):
            if p is not None and p.poll() is None:
                p.kill()
                p.wait(10)
        serve_err.close()

    # run log after kill -9: every file must read
    parts = log_parts(tmp / "log")
    unreadable = 0
    for p in parts:
        try:
            pq.read_table(p)
        except Exception:
            unreadable += 1
    meta, log = read_log(tmp / "log")
    t_log = log["time_s"].to_numpy()
    sent = np.load(tmp / "sent.npy")  # first frame stamp s, frames, send time s
    stamps = (
        np.concatenate([s0 + np.arange(int(n)) / rate_hz for s0, n, _ in sent]) if sent.size else np.zeros(0)
    )
    sent_before_kill = (
        np.concatenate([np.full(int(n), ts) for _, n, ts in sent]) < t_kill
        if sent.size
        else np.zeros(0, bool)
    )
    tail = stamps[sent_before_kill & (stamps > t_log.max() + 0.5 / rate_hz)]
    corr = log[["corr_dx_um", "corr_dy_um", "corr_dz_um"]].to_numpy()
    dev = log[["dev_dx_um", "dev_dy_um", "dev_dz_um"]].to_numpy()
    health = log["health"].to_numpy()
    ok = health == HEALTH_OK
    with np.errstate(invalid="ignore"):
        ok_beyond = int((ok & ((np.abs(corr) > bound).any(axis=1) | (np.abs(dev) > bound).any(axis=1))).sum())
        beyond = int((np.abs(corr) > bound).any(axis=1).sum())
    # the fault-free correction: the full model on the campaign's noise-free wavelengths at
    # the logged frames' instrument times (the simulator's clock starts at its first stamp),
    # zero state as serve takes it (the logged frames of the first zero window)
    from fbgcomp.runtime.simulator import SignalTable

    model = load_model(model_path)
    table = SignalTable.from_campaign(campaign)
    span = table.time_s[-1] - table.time_s[0]
    cols = [table.sensor_names.index(n) for n in model.sensor_names]
    wl_clean = table.at(table.time_s[0] + np.mod(t_log - sent[0, 0], span))[:, cols]
    temp = log[[f"{p}_C" for p in model.probe_names]].to_numpy()
    zero = t_log <= t_log[0] + model.zero_window_s
    wl_log = log[[f"{n}_nm" for n in model.sensor_names]].to_numpy()
    clean_dev, _ = model.predictor().predict(
        wl_clean, temp, np.nanmean(wl_log[zero], axis=0), np.nanmean(temp[zero], axis=0)
    )
    flags = log[["flags_dx", "flags_dy", "flags_dz"]].to_numpy()
    settled = ok & ((flags & 8) == 0).all(axis=1)  # not held back by the rate limit
    off_ok = np.abs(corr + clean_dev)
    err = (tmp / "serve.err").read_text()
    reconnects = err.count("hyperion link")
    kinds = [k for _, k in faults]
    warm = [m for t, m in rss if t >= WARMUP_S]
    rss_start, rss_end = (warm[0], warm[-1]) if warm else (float("nan"), float("nan"))
    return {
        "seconds": seconds,
        "seed": seed,
        "rate_hz": rate_hz,
        "faults": {k: kinds.count(k) for k in sorted(set(kinds))},
        "bound_um": bound.tolist(),
        "max_abs_correction_um": np.nanmax(np.abs(corr), axis=0).tolist(),
        "max_abs_prediction_ok_um": (np.nanmax(np.abs(dev[ok]), axis=0).tolist() if ok.any() else None),
        "frames_beyond_bound": beyond,
        "frames_ok_beyond_bound": ok_beyond,
        "max_ok_off_fault_free_um": (off_ok[ok].max(axis=0).tolist() if ok.any() else None),
        "max_ok_settled_off_fault_free_um": (off_ok[settled].max(axis=0).tolist() if settled.any() else None),
        "p999_ok_off_fault_free_um": (np.percentile(off_ok[ok], 99.9, axis=0).tolist() if ok.any() else None),
        "frames_ok_rate_limited": int((ok & ~settled).sum()),
        "health_share": {
            n: float((health == i).mean()) for i, n in enumerate(("OK", "DEGRADED", "ALARM", "ZEROING"))
        },
        "rss_start_mib": rss_start,
        "rss_end_mib": rss_end,
        "rss_growth_mib": rss_end - rss_start,
        "rss_growth_pct": 100.0 * (rss_end - rss_start) / rss_start,
        "rss_max_mib": max(m for _, m in rss) if rss else float("nan"),
        "reconnects": reconnects,
        "outages": int((np.diff(t_log) > 0.1).sum()),
        "links_broken_injected": kinds.count("cut") + kinds.count("garbage"),
        "log_rows": len(log),
        "log_files": len(parts),
        "log_files_unreadable": unreadable,
        "rows_lost_at_kill": int(tail.size),
        "seconds_lost_at_kill": float(t_kill - log["received_s"].max()),
        "log_dropped_rows": int(meta.get("dropped_rows", 0) or 0),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=300.0, help="soak duration (default 300)")
    ap.add_argument("--quick", action="store_true", help="60 s")
    ap.add_argument("--seed", type=int, default=13)
    ap.add_argument("--rate", type=float, default=1000.0, help="frames/s of the instrument")
    args = ap.parse_args()
    seconds = 60.0 if args.quick else args.seconds
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    with tempfile.TemporaryDirectory(prefix="bench_soak_") as d:
        r = soak(seconds, args.seed, args.rate, Path(d))
    ax = ("dx", "dy", "dz")
    print(
        f"soak {r['seconds']:.0f} s at {r['rate_hz']:g} Hz, seed {r['seed']}; faults injected: "
        + ", ".join(f"{k} {n}" for k, n in r["faults"].items())
    )
    print(
        "max |correction| vs bound: "
        + ", ".join(
            f"{a} {m:.2f} / {b:.0f} um" for a, m, b in zip(ax, r["max_abs_correction_um"], r["bound_um"])
        )
    )
    if r["max_abs_prediction_ok_um"] is not None:
        print(
            "max |prediction| with Health OK: "
            + ", ".join(f"{a} {m:.2f} um" for a, m in zip(ax, r["max_abs_prediction_ok_um"]))
        )
    print(
        f"frames beyond the bound: {r['frames_beyond_bound']} published, "
        f"{r['frames_ok_beyond_bound']} with Health OK (correction or prediction)"
    )
    if r["max_ok_off_fault_free_um"] is not None:
        print(
            "Health OK frames vs the fault-free model: max "
            + ", ".join(f"{a} {m:.2f}" for a, m in zip(ax, r["max_ok_off_fault_free_um"]))
            + " um; without the rate limit's transit frames "
            f"({r['frames_ok_rate_limited']}): "
            + ", ".join(f"{a} {m:.2f}" for a, m in zip(ax, r["max_ok_settled_off_fault_free_um"]))
            + " um; 99.9th percentile "
            + ", ".join(f"{a} {m:.2f}" for a, m in zip(ax, r["p999_ok_off_fault_free_um"]))
            + " um"
        )
    print("health: " + ", ".join(f"{k} {100 * v:.1f} %" for k, v in r["health_share"].items()))
    print(
        f"serve RSS: {r['rss_start_mib']:.1f} MiB after {WARMUP_S:.0f} s -> "
        f"{r['rss_end_mib']:.1f} MiB at the end ({r['rss_growth_mib']:+.1f} MiB, "
        f"{r['rss_growth_pct']:+.1f} %), max {r['rss_max_mib']:.1f} MiB"
    )
    print(
        f"reconnects: {r['reconnects']} link-lost warnings (every refused retry during a cut "
        f"counts), {r['outages']} gaps > 0.1 s in the logged frames; cuts + garbage bursts "
        f"injected: {r['links_broken_injected']}"
    )
    print(
        f"after kill -9: {r['log_files']} log files, {r['log_files_unreadable']} unreadable; "
        f"{r['log_rows']} rows; {r['rows_lost_at_kill']} frames sent before the kill not "
        f"logged ({r['seconds_lost_at_kill']:.2f} s of reception); "
        f"{r['log_dropped_rows']} rows dropped by the writer"
    )
    print(json.dumps(r))


if __name__ == "__main__":
    main()
