"""Runtime benchmark: core pipeline throughput and end-to-end latency.

1. Core throughput (frames/s) for 5 and 64 sensors: Hyperion stream bytes -> vectorised
   decode -> wavelength windows -> sensor checks -> model (``Predictor.predict``) -> correction,
   in batches of 1, 10, 100 and 1000 frames (a batch is "whatever has arrived").
2. End-to-end latency at 1 kHz: ``fbgcomp sim-interrogator`` and ``fbgcomp serve`` as real
   processes, an asyncua client (Basic256Sha256 Sign & Encrypt) subscribed to ``SampleTime``;
   latency = time the client sees the value change - time stamp of the frame, which the
   simulated instrument sets when it sends the frame (same host clock).

Both run beside ``--load`` (default 2) busy background processes the benchmark starts and stops
itself, with the runtime's real-time settings (``--cpu``: a pinned core; SCHED_FIFO where
permitted, ``--no-fifo`` to measure without). The core is timed after the zero window (every
timed frame reaches the model), interleaved with a fair baseline - plain numpy doing the same
per-frame arithmetic on the same bytes - and the ratio printed; the fixed cost per batch is the
batch-1 time less the per-frame cost (batch 100 -> 1000).

Targets (issue 16): fixed cost <= 100 us per batch (batch 1 >= 5 000 frames/s); core at batch 100
>= 200 000 frames/s with 5 sensors and within 3x of numpy; end-to-end p99 <= 5 ms at 1 kHz, under
the benchmark's own load. p50, p99 and p99.9 are printed.
Usage: python benchmarks/bench_runtime.py [--quick] [--load 2|0] [--e2e-seconds 10]
The last line printed is the JSON summary.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from datetime import UTC, datetime
from pathlib import Path

import numpy as np
import pandas as pd

from _loopback import busy_processes, free_port, git_commit, wait_port


def _five_sensor_model(tmp: Path):
    from fbgcomp.bench.synthetic import linear_truth_campaign
    from fbgcomp.io.campaign import write_campaign
    from fbgcomp.models.mra import MRAModel

    train, _ = linear_truth_campaign("train", seed=1, duration_s=2 * 3600)
    model = MRAModel(features="eq13", zero_window_s=0.5, fallbacks="loo").fit(train)
    serve, _ = linear_truth_campaign(
        "serve", seed=2, duration_s=600, fbg_dt_s=0.1, temperature_dt_s=0.1, reference_dt_s=0.1, settle_s=0.0
    )
    return model.save(tmp / "model5.json"), write_campaign(serve, tmp / "serve5")


def _many_sensor_model(tmp: Path, n_sensors=64, channels=4):
    """A 64-grating ram (16 per fibre on 4 channels), eq. 11 model (elongations only)."""
    from fbgcomp import optics
    from fbgcomp.io.campaign import Campaign
    from fbgcomp.models.mra import MRAModel

    rng = np.random.default_rng(3)
    per = n_sensors // channels
    sensors = [
        {
            "name": f"S{i + 1}",
            "lambda0_nm": 1515.0 + 5.0 * (i % per),
            "gauge_length_mm": 500.0,
            "channel": 1 + i // per,
        }
        for i in range(n_sensors)
    ]
    meta = {
        "name": "many",
        "kind": "thermal",
        "start": datetime(2026, 1, 1, tzinfo=UTC),
        "sensors": sensors,
        "temperature_probes": [{"name": "T_bulk"}],
    }
    t = np.arange(0.0, 3600.0, 1.0)
    dl = np.column_stack(
        [
            np.sin(t / rng.uniform(200, 900) + rng.uniform(0, 6)) * 20 + rng.normal(0, 2, t.size)
            for _ in range(n_sensors)
        ]
    )
    lam0 = np.array([s["lambda0_nm"] for s in sensors])
    wl = optics.wavelength_nm(dl, lam0, np.full(n_sensors, 500.0), np.zeros((t.size, n_sensors)))
    coef = rng.normal(0, 0.3, (n_sensors, 3))
    ref = dl @ coef + rng.normal(0, 0.05, (t.size, 3))
    fbg = pd.DataFrame(wl, columns=[f"S{i + 1}_nm" for i in range(n_sensors)])
    fbg.insert(0, "time_s", t)
    temps = pd.DataFrame({"time_s": t, "T_bulk_C": 20.0 + 0 * t})
    reference = pd.DataFrame({"time_s": t, "dx_um": ref[:, 0], "dy_um": ref[:, 1], "dz_um": ref[:, 2]})
    c = Campaign.from_arrays(meta, fbg=fbg, temperatures=temps, reference=reference)
    model = MRAModel(features="eq11", zero_window_s=0.5, fallbacks="none").fit(c)
    return model.save(tmp / "model64.json"), (
        t,
        wl,
        [s["name"] for s in sensors],
        [s["channel"] for s in sensors],
    )


class CoreRun:
    """The runtime core on a simulated stream: Hyperion bytes -> vectorised decode -> wavelength
    windows -> probe temperatures -> Pipeline.process (checks, model, output policy), in
    batches of ``batch`` frames. The zero window is run through first (untimed), so every timed
    frame reaches the model."""

    def __init__(self, model_path, table, n_frames: int, batch: int, rate_hz=5000.0):
        from fbgcomp.models.registry import load_model
        from fbgcomp.runtime.pipeline import Pipeline
        from fbgcomp.runtime.simulator import SimConfig, SimulatedHyperion
        from fbgcomp.runtime.sources import NoTemperatures, TableTemperatures
        from fbgcomp.runtime.windows import PeakMapper

        self.model = load_model(model_path)
        sim = SimulatedHyperion(table, SimConfig(rate_hz=rate_hz, noise_pm=0.3))
        sim._t0 = 1.7e9
        warm = int(self.model.zero_window_s * rate_hz) + 2 * batch
        self.n_frames, self.batch = n_frames, batch
        rel = np.arange(warm + n_frames) / rate_hz
        self.warm = [sim._frames(rel[i : i + batch]) for i in range(0, warm, batch)]
        self.chunks = [sim._frames(rel[i : i + batch]) for i in range(warm, warm + n_frames, batch)]
        self.mapper = PeakMapper.for_sensors(self.model.sensors, 2.5)
        probes = self.model.probe_names
        self.temps = (
            TableTemperatures(probes, np.array([0.0, 1e6]), np.full((2, len(probes)), 20.0))
            if probes
            else NoTemperatures([])
        )
        self.Pipeline = Pipeline

    def _feed(self, pipe, chunks, out=None):
        from fbgcomp.runtime import hyperion

        buf = bytearray()
        for chunk in chunks:
            buf += chunk
            blocks, used = hyperion.decode_peak_frames(buf)
            del buf[:used]
            b = self.mapper.map_blocks(blocks, 0.0)
            r = pipe.process(
                b.time_s, b.wavelength_nm, b.peak_count, b.near_count, self.temps.latest(b.time_s)
            )
            if out is not None:
                out.append(r)

    def rate(self, keep=None) -> float:
        """Frames per second after the zero window."""
        pipe = self.Pipeline(self.model)
        pipe.predictor(0)  # compiled once at start-up, not per frame
        self._feed(pipe, self.warm)
        assert pipe.zeroed
        t0 = time.perf_counter()
        self._feed(pipe, self.chunks, keep)
        return self.n_frames / (time.perf_counter() - t0)

    def numpy_rate(self, check_against=None) -> float:
        """Plain numpy doing the core's per-frame arithmetic on the same bytes, with nothing
        but arrays between batches: structured-dtype decode, window search, the finite / one
        peak / jump checks, the model's base features, design, deviation and interval, and the
        correction's bound and rate-limit test. The fair baseline of the core."""
        from fbgcomp.models.features import parse_term
        from fbgcomp.runtime.hyperion import HEADER_SIZE, _frame_dtype

        pipe = self.Pipeline(self.model)
        p = pipe.predictor(0)
        self._feed(pipe, self.warm)
        fm, w0, t0z = p.feature_map, pipe.wavelength_zero_nm, pipe.temperature_zero_C
        head = self.chunks[0]
        n_ch = int(np.frombuffer(head, "<u2", 1, HEADER_SIZE)[0] - 24) // 2
        frame_len = HEADER_SIZE + int(np.frombuffer(head, "<u4", 1, 4)[0])
        n_pk = (frame_len - HEADER_SIZE - 24 - 2 * n_ch) // 8
        dtype = _frame_dtype(n_ch, n_pk)
        lam = self.mapper.lambda0_nm
        order = np.argsort(lam)
        lo, hi = (lam - self.mapper.window_nm)[order], (lam + self.mapper.window_nm)[order]
        idx = {name: i for i, name in enumerate(fm.base_names)}
        width = len(fm.base_names)
        factors = [[idx[f] for f in parse_term(term)] for term in p.terms]
        k = max(len(f) for f in factors)
        fac = np.array([f + [width] * (k - len(f)) for f in factors])  # width: a column of ones
        coef = p.coef
        cov = np.concatenate(list(p._cov_sqrt), axis=1)  # (K, 3K)
        K = coef.shape[0]
        limit = pipe.max_correction_um
        step = pipe.max_slew_um_per_s / 5000.0
        temps = self.temps
        last = w0.copy()
        out = []
        start = time.perf_counter()
        for chunk in self.chunks:
            rec = np.frombuffer(chunk, dtype)
            peaks = rec["peaks"].reshape(rec.size, -1)
            ts = rec["t_int"] + rec["t_frac"] * 1e-9
            j = np.searchsorted(lo, peaks, side="right") - 1
            inside = (j >= 0) & (peaks <= hi[np.clip(j, 0, None)])
            wl = np.full((rec.size, lam.size), np.nan)
            rows = np.broadcast_to(np.arange(rec.size)[:, None], peaks.shape)
            wl[rows[inside], order[j[inside]]] = peaks[inside]
            prev = np.vstack([last, wl[:-1]])
            good = np.isfinite(wl) & (np.abs(wl - prev) <= 0.1)
            last = wl[-1]
            base = fm.base(wl, temps.latest(ts), w0, t0z)
            ext = np.hstack([base, np.ones((rec.size, 1))])
            d = np.ones((rec.size, K))
            cols = ext[:, fac]  # (n, K-1, k)
            d[:, 1:] = cols[:, :, 0]
            for c in range(1, k):
                d[:, 1:] *= cols[:, :, c]
            dev = d @ coef
            spread = d @ cov
            half = p._t * np.sqrt(p._resid_var + (spread * spread).reshape(rec.size, 3, K).sum(axis=2))
            corr = np.clip(-dev, -limit, limit)
            _ = np.abs(np.diff(corr, axis=0)) > step  # the slew check's work, timed with the rest
            out.append((dev, half, good.all()))
        rate = self.n_frames / (time.perf_counter() - start)
        if check_against is not None:
            dev = np.concatenate([o[0] for o in out])
            half = np.concatenate([o[1] for o in out])
            ref_dev = np.concatenate([r.deviation_um for r in check_against])
            ref_half = np.concatenate([r.half_width_um for r in check_against])
            self.baseline_max_diff_um = float(max(np.abs(dev - ref_dev).max(), np.abs(half - ref_half).max()))
        return rate


def core_throughput(model_path, table, n_frames: int, batch: int) -> float:
    """Frames per second through decode -> map -> checks -> model -> correction."""
    return CoreRun(model_path, table, n_frames, batch).rate()


# --------------------------------------------------------------------------- end to end
async def _latency(url, state: Path, seconds: float, warmup_s: float):
    from asyncua import Client, ua
    from asyncua.crypto.security_policies import SecurityPolicyBasic256Sha256

    seen = []
    t_start = time.time()

    class Handler:
        def datachange_notification(self, node, val, data):
            now = time.time()
            if now - t_start > warmup_s and isinstance(val, datetime):
                seen.append((val.replace(tzinfo=UTC).timestamp(), now))

    client = Client(url, timeout=10)
    client.application_uri = "urn:fbgcomp:bench:client"
    cert, key = await client.setup_self_signed_certificate(state / "k.pem", state / "c.der")
    await client.set_security(
        SecurityPolicyBasic256Sha256, str(cert), str(key), mode=ua.MessageSecurityMode.SignAndEncrypt
    )
    # serve trusts only known client certificates (its <state-dir>/opcua/trusted)
    from fbgcomp.runtime.trust import add_certificate

    add_certificate(cert, state / "state" / "opcua" / "trusted")
    client.set_user("bench")
    client.set_password("bench-password")
    async with client:
        sub = await client.create_subscription(0, Handler())
        # Heartbeat keeps the subscription alive before data flows (publishing interval 0)
        await sub.subscribe_data_change(
            [
                client.get_node(ua.NodeId("FbgComp.SampleTime", 2)),
                client.get_node(ua.NodeId("FbgComp.Heartbeat", 2)),
            ]
        )
        # this process holds fitted models and campaigns: keep them out of the cyclic
        # collector so its full passes do not show up as latency of the system under test
        import gc

        gc.collect()
        gc.freeze()
        await asyncio.sleep(seconds + warmup_s)
    return np.array(seen).reshape(-1, 2)


def end_to_end(model_path, campaign, seconds: float, rate_hz=1000.0, opcua_rate_hz=0.0, cpu=-1, fifo=0):
    """Latencies (s) from the instrument's send to the client, from the frame stamp to the
    client, and how the processes ran. serve applies its own real-time settings (``--cpu``,
    ``--realtime-priority``); the simulated instrument and the client, stand-ins for a device of
    their own and the CNC, get SCHED_FIFO too (no pinning), so the busy processes delay only
    what a deployment shares with them."""
    from fbgcomp.runtime.realtime import RealtimeConfig, apply

    env = dict(os.environ, FBGCOMP_OPCUA_USER="bench", FBGCOMP_OPCUA_PASSWORD="bench-password")
    with tempfile.TemporaryDirectory() as d:
        d = Path(d)
        sp, cp, op = free_port(), free_port(), free_port()
        url = f"opc.tcp://127.0.0.1:{op}/fbgcomp/"
        cmd = [sys.executable, "-m", "fbgcomp"]
        serve = subprocess.Popen(
            [
                *cmd,
                "serve",
                "--model",
                str(model_path),
                "--source",
                f"hyperion://127.0.0.1:{sp}?command_port={cp}",
                "--temperatures",
                str(campaign),
                "--opcua",
                url,
                "--state-dir",
                str(d / "state"),
                "--log",
                str(d / "log"),
                "--rate",
                str(opcua_rate_hz),
                "--cpu",
                str(cpu),
                "--realtime-priority",
                str(fifo),
            ],
            env=env,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
        )
        sim = None
        try:
            wait_port(op)
            sim = subprocess.Popen(
                [
                    *cmd,
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
                    "--send-log",
                    str(d / "sends.npy"),
                ],
                stdout=subprocess.DEVNULL,
                stderr=subprocess.DEVNULL,
            )
            peers = RealtimeConfig(fifo_priority=fifo, gc_threshold=0)
            how = (
                f"serve: --cpu {cpu} --realtime-priority {fifo}; sim-interrogator: "
                + ("; ".join(apply(peers, sim.pid)) or "normal scheduling")
                + "; client (this process): "
                + ("; ".join(apply(peers)) or "normal scheduling")
            )
            try:
                seen = asyncio.run(_latency(url, d, seconds, warmup_s=3.0))
            finally:
                if fifo:
                    os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
        finally:
            for p in (sim, serve):
                if p is not None and p.poll() is None:
                    p.send_signal(signal.SIGTERM)
            for p in (sim, serve):
                if p is not None:
                    try:
                        p.wait(15)
                    except subprocess.TimeoutExpired:
                        p.kill()
        sends = np.load(d / "sends.npy")
    # the block that carried each published frame, and the time it left the instrument
    stamp, recv = seen[:, 0], seen[:, 1]
    i = np.searchsorted(sends[:, 0], stamp + 0.5 / rate_hz, side="right") - 1
    k = np.round((stamp - sends[i, 0]) * rate_hz)
    ok = (i >= 0) & (k < sends[i, 1])
    return recv[ok] - sends[i[ok], 2], recv - stamp, how


def _pct(x, q):
    return round(float(np.percentile(x, q)), 3)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="fewer frames, shorter e2e run")
    ap.add_argument("--e2e-seconds", type=float, default=10.0)
    ap.add_argument("--skip-core", action="store_true", help="only the end-to-end latency")
    ap.add_argument("--skip-e2e", action="store_true", help="only the core throughput")
    ap.add_argument("--runs", type=int, default=5, help="interleaved core / numpy runs (median)")
    ap.add_argument(
        "--opcua-rates",
        default="0,250",
        help="OPC UA update rates to measure, Hz (0 = every processed batch)",
    )
    ap.add_argument(
        "--load", type=int, default=2, help="busy background processes started for the whole run (0: quiet)"
    )
    ap.add_argument(
        "--cpu", type=int, default=1, help="CPU the core measurement and serve are pinned to (-1: none)"
    )
    ap.add_argument(
        "--no-fifo",
        action="store_true",
        help="normal scheduling instead of SCHED_FIFO for the measured processes",
    )
    args = ap.parse_args(argv)
    from fbgcomp.runtime.realtime import RealtimeConfig, apply
    from fbgcomp.runtime.simulator import SignalTable

    started = datetime.now(UTC)
    commit = git_commit()
    print(f"{started:%Y-%m-%d %H:%M} UTC, code of {commit}, {os.cpu_count()} CPUs")
    n_frames = 20_000 if args.quick else 100_000
    fifo = 0 if args.no_fifo else 50
    summary = {
        "utc": f"{started:%Y-%m-%dT%H:%MZ}",
        "commit": commit,
        "background_processes": args.load,
        "core_frames_per_s": {},
        "numpy_frames_per_s": {},
        "core_vs_numpy": {},
        "fixed_cost_us": {},
        "e2e": {},
    }
    loads = []
    with tempfile.TemporaryDirectory() as d, busy_processes(args.load):
        d = Path(d)
        m5, c5 = _five_sensor_model(d)
        m64, (t64, wl64, names64, ch64) = _many_sensor_model(d)
        tables = {5: SignalTable.from_campaign(c5), 64: SignalTable(t64, wl64, names64, ch64)}
        print(f"background load: {args.load} busy processes (started by this benchmark)")
        if not args.skip_core:
            # the measuring process as serve runs: pinned core, SCHED_FIFO where permitted
            done = apply(RealtimeConfig(cpu=args.cpu, fifo_priority=fifo, gc_threshold=0))
            summary["core_process"] = "; ".join(done) or "normal scheduling, any CPU"
            print(f"core measured in this process: {summary['core_process']}")
            print(
                "core pipeline throughput after the zero window (decode -> windows -> checks "
                "-> model -> correction) vs. plain numpy doing the same per-frame arithmetic "
                f"on the same bytes; interleaved, median of {args.runs}"
            )
            for n_sensors, model_path in ((5, m5), (64, m64)):
                per_batch_s = {}
                for batch in (1, 10, 100, 1000):
                    frames = min(n_frames, 2_000 * batch) if batch < 100 else n_frames
                    run = CoreRun(model_path, tables[n_sensors], frames, batch)
                    kept = []
                    run.rate(kept)  # warm-up, and the results numpy is checked on
                    run.numpy_rate(kept)
                    core, base = [], []
                    for _ in range(args.runs):
                        core.append(run.rate())
                        base.append(run.numpy_rate())
                    fps, nps = float(np.median(core)), float(np.median(base))
                    key = f"{n_sensors}_sensors_batch_{batch}"
                    summary["core_frames_per_s"][key] = round(fps)
                    summary["numpy_frames_per_s"][key] = round(nps)
                    summary["core_vs_numpy"][key] = round(nps / fps, 2)
                    per_batch_s[batch] = batch / fps
                    print(
                        f"  {n_sensors:3d} sensors, batch {batch:5d}: core {fps:12,.0f} "
                        f"frames/s, numpy {nps:12,.0f} frames/s, numpy / core "
                        f"{nps / fps:5.2f} (same results to {run.baseline_max_diff_um:.1e} "
                        "um)"
                    )
                # per-batch time = fixed + frames x per-frame (per frame from 100 -> 1000)
                per_frame = (per_batch_s[1000] - per_batch_s[100]) / 900
                fixed = per_batch_s[1] - per_frame
                summary["fixed_cost_us"][f"{n_sensors}_sensors"] = round(fixed * 1e6, 1)
                print(
                    f"  {n_sensors:3d} sensors: fixed cost per batch {fixed * 1e6:6.1f} us, "
                    f"{per_frame * 1e6:5.2f} us per frame"
                )
                loads.append(os.getloadavg()[0])
            # back to normal for the rest (the client sets its own)
            if fifo:
                os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
            os.sched_setaffinity(0, range(os.cpu_count()))
        seconds = 4.0 if args.quick else args.e2e_seconds
        for opcua_rate in [] if args.skip_e2e else [float(r) for r in args.opcua_rates.split(",")]:
            label = "every batch" if opcua_rate == 0 else f"{opcua_rate:g} Hz"
            print(
                f"end-to-end latency at 1 kHz input, OPC UA updates {label} ({seconds:g} s after "
                "3 s warm-up): frame sent by sim-interrogator -> value change at a subscribed "
                "client"
            )
            lat, since_stamp, how = end_to_end(
                m5, c5, seconds, opcua_rate_hz=opcua_rate, cpu=args.cpu, fifo=fifo
            )
            print(f"  {how}")
            lat, since_stamp = lat * 1e3, since_stamp * 1e3
            if lat.size:
                e2e = {
                    "samples": int(lat.size),
                    "p50_ms": _pct(lat, 50),
                    "p99_ms": _pct(lat, 99),
                    "p99.9_ms": _pct(lat, 99.9),
                    "max_ms": round(float(lat.max()), 3),
                    "updates_per_s": round(lat.size / seconds, 1),
                    "from_frame_timestamp_p50_ms": _pct(since_stamp, 50),
                    "from_frame_timestamp_p99_ms": _pct(since_stamp, 99),
                }
            else:
                e2e = {"samples": 0}
            summary["e2e"][f"opcua_rate_{opcua_rate:g}"] = e2e
            summary["e2e_processes"] = how
            print("  " + ", ".join(f"{k} {v}" for k, v in e2e.items()))
            loads.append(os.getloadavg()[0])
    summary["load_average_1min"] = [round(x, 2) for x in loads]
    summary["cpus"] = os.cpu_count()
    print(f"1-min load average during the run {summary['load_average_1min']} on {summary['cpus']} CPUs")
    core = summary["core_frames_per_s"]
    best_p99 = min((v.get("p99_ms", float("inf")) for v in summary["e2e"].values()), default=float("inf"))
    summary["targets_met"] = {
        "fixed_cost_le_100us": summary["fixed_cost_us"].get("5_sensors", 1e9) <= 100,
        "batch_1_ge_5k_fps": core.get("5_sensors_batch_1", 0) >= 5_000,
        "core_5_sensors_ge_200k_fps_batch_100": core.get("5_sensors_batch_100", 0) >= 200_000,
        "core_within_3x_numpy_batch_100": summary["core_vs_numpy"].get("5_sensors_batch_100", 1e9) <= 3.0,
        "e2e_p99_le_5ms": best_p99 <= 5.0,
    }
    print(json.dumps(summary))


if __name__ == "__main__":
    main()
