"""Runtime benchmark: core pipeline throughput and end-to-end latency.

1. Core throughput (frames/s) for 5 and 64 sensors: Hyperion stream bytes -> vectorised
   decode -> wavelength windows -> sensor checks -> model (``Predictor.predict``) -> correction,
   in batches of 1, 10, 100 and 1000 frames (a batch is "whatever has arrived").
2. End-to-end latency at 1 kHz: ``fbgcomp sim-interrogator`` and ``fbgcomp serve`` as real
   processes, an asyncua client (Basic256Sha256 Sign & Encrypt) subscribed to ``SampleTime``;
   latency = time the client sees the value change - time stamp of the frame, which the
   simulated instrument sets when it sends the frame (same host clock).

Targets: core >= 50,000 frames/s with 5 sensors; end-to-end p99 <= 5 ms at 1 kHz.
Usage: python benchmarks/bench_runtime.py [--quick] [--e2e-seconds 10]
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
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
import pandas as pd

from _loopback import free_port, wait_port


def _five_sensor_model(tmp: Path):
    from fbgcomp.campaign import write_campaign
    from fbgcomp.models import MRAModel
    from fbgcomp.synthetic import linear_truth_campaign

    train, _ = linear_truth_campaign("train", seed=1, duration_s=2 * 3600)
    model = MRAModel(features="eq13", zero_window_s=0.5, fallbacks="loo").fit(train)
    serve, _ = linear_truth_campaign("serve", seed=2, duration_s=600, fbg_dt_s=0.1,
                                     temperature_dt_s=0.1, reference_dt_s=0.1, settle_s=0.0)
    return model.save(tmp / "model5.json"), write_campaign(serve, tmp / "serve5")


def _many_sensor_model(tmp: Path, n_sensors=64, channels=4):
    """A 64-grating ram (16 per fibre on 4 channels), eq. 11 model (elongations only)."""
    from fbgcomp import optics
    from fbgcomp.campaign import Campaign
    from fbgcomp.models import MRAModel

    rng = np.random.default_rng(3)
    per = n_sensors // channels
    sensors = [{"name": f"S{i + 1}", "lambda0_nm": 1515.0 + 5.0 * (i % per),
                "gauge_length_mm": 500.0, "channel": 1 + i // per} for i in range(n_sensors)]
    meta = {"name": "many", "kind": "thermal", "start": datetime(2026, 1, 1, tzinfo=timezone.utc),
            "sensors": sensors, "temperature_probes": [{"name": "T_bulk"}]}
    t = np.arange(0.0, 3600.0, 1.0)
    dl = np.column_stack([np.sin(t / rng.uniform(200, 900) + rng.uniform(0, 6)) * 20
                          + rng.normal(0, 2, t.size) for _ in range(n_sensors)])
    lam0 = np.array([s["lambda0_nm"] for s in sensors])
    wl = optics.wavelength_nm(dl, lam0, np.full(n_sensors, 500.0), np.zeros((t.size, n_sensors)))
    coef = rng.normal(0, 0.3, (n_sensors, 3))
    ref = dl @ coef + rng.normal(0, 0.05, (t.size, 3))
    fbg = pd.DataFrame(wl, columns=[f"S{i + 1}_nm" for i in range(n_sensors)])
    fbg.insert(0, "time_s", t)
    temps = pd.DataFrame({"time_s": t, "T_bulk_C": 20.0 + 0 * t})
    reference = pd.DataFrame({"time_s": t, "dx_um": ref[:, 0], "dy_um": ref[:, 1],
                              "dz_um": ref[:, 2]})
    c = Campaign.from_arrays(meta, fbg=fbg, temperatures=temps, reference=reference)
    model = MRAModel(features="eq11", zero_window_s=0.5, fallbacks="none").fit(c)
    return model.save(tmp / "model64.json"), (t, wl, [s["name"] for s in sensors],
                                              [s["channel"] for s in sensors])


def core_throughput(model_path, table, n_frames: int, batch: int) -> float:
    """Frames per second through decode -> map -> checks -> model -> correction."""
    from fbgcomp.models import load_model
    from fbgcomp.runtime import hyperion
    from fbgcomp.runtime.pipeline import Pipeline
    from fbgcomp.runtime.simulator import SignalTable, SimConfig, SimulatedHyperion
    from fbgcomp.runtime.sources import NoTemperatures, PeakMapper, TableTemperatures

    model = load_model(model_path)
    sim = SimulatedHyperion(table, SimConfig(rate_hz=5000, noise_pm=0.3))
    sim._t0 = 1.7e9
    rel = np.arange(n_frames) / 5000.0
    chunks = [sim._frames(rel[i:i + batch]) for i in range(0, n_frames, batch)]
    mapper = PeakMapper.for_sensors(model.sensors, 2.5)
    probes = model.probe_names
    temps = (TableTemperatures(probes, np.array([0.0, 1e6]), np.full((2, len(probes)), 20.0))
             if probes else NoTemperatures([]))
    pipe = Pipeline(model)
    pipe.predictor(0)              # compiled once at start-up, not per frame
    buf = bytearray()
    t0 = time.perf_counter()
    for chunk in chunks:
        buf += chunk
        blocks, used = hyperion.decode_peak_frames(buf)
        del buf[:used]
        b = mapper.map_blocks(blocks, 0.0)
        pipe.process(b.time_s, b.wavelength_nm, b.peak_count, b.near_count,
                     temps.latest(b.time_s))
    elapsed = time.perf_counter() - t0
    return n_frames / elapsed


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
                seen.append((val.replace(tzinfo=timezone.utc).timestamp(), now))

    client = Client(url, timeout=10)
    client.application_uri = "urn:fbgcomp:bench:client"
    cert, key = await client.setup_self_signed_certificate(state / "k.pem", state / "c.der")
    await client.set_security(SecurityPolicyBasic256Sha256, str(cert), str(key),
                              mode=ua.MessageSecurityMode.SignAndEncrypt)
    # serve trusts only known client certificates (its <state-dir>/opcua/trusted)
    from fbgcomp.runtime.trust import add_certificate
    add_certificate(cert, state / "state" / "opcua" / "trusted")
    client.set_user("bench")
    client.set_password("bench-password")
    async with client:
        sub = await client.create_subscription(0, Handler())
        # Heartbeat keeps the subscription alive before data flows (publishing interval 0)
        await sub.subscribe_data_change([client.get_node(ua.NodeId("FbgComp.SampleTime", 2)),
                                         client.get_node(ua.NodeId("FbgComp.Heartbeat", 2))])
        # this process holds fitted models and campaigns: keep them out of the cyclic
        # collector so its full passes do not show up as latency of the system under test
        import gc
        gc.collect()
        gc.freeze()
        await asyncio.sleep(seconds + warmup_s)
    return np.array(seen).reshape(-1, 2)


def end_to_end(model_path, campaign, seconds: float, rate_hz=1000.0, opcua_rate_hz=0.0):
    env = dict(os.environ, FBGCOMP_OPCUA_USER="bench", FBGCOMP_OPCUA_PASSWORD="bench-password")
    with tempfile.TemporaryDirectory() as d:
        d = Path(d)
        sp, cp, op = free_port(), free_port(), free_port()
        url = f"opc.tcp://127.0.0.1:{op}/fbgcomp/"
        cmd = [sys.executable, "-m", "fbgcomp"]
        serve = subprocess.Popen(cmd + ["serve", "--model", str(model_path), "--source",
                                        f"hyperion://127.0.0.1:{sp}?command_port={cp}",
                                        "--temperatures", str(campaign), "--opcua", url,
                                        "--state-dir", str(d / "state"), "--log", str(d / "log"),
                                        "--rate", str(opcua_rate_hz)],
                                 env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
        sim = None
        try:
            wait_port(op)
            sim = subprocess.Popen(cmd + ["sim-interrogator", str(campaign), "--port", str(sp),
                                          "--command-port", str(cp), "--rate", str(rate_hz),
                                          "--noise-pm", "0.3", "--send-log",
                                          str(d / "sends.npy")],
                                   stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
            seen = asyncio.run(_latency(url, d, seconds, warmup_s=3.0))
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
    return recv[ok] - sends[i[ok], 2], recv - stamp


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="fewer frames, shorter e2e run")
    ap.add_argument("--e2e-seconds", type=float, default=10.0)
    ap.add_argument("--skip-core", action="store_true", help="only the end-to-end latency")
    ap.add_argument("--opcua-rates", default="0,250",
                    help="OPC UA update rates to measure, Hz (0 = every processed batch)")
    args = ap.parse_args(argv)
    from fbgcomp.runtime.simulator import SignalTable

    n_frames = 20_000 if args.quick else 100_000
    summary = {"core_frames_per_s": {}, "e2e": {}}
    with tempfile.TemporaryDirectory() as d:
        d = Path(d)
        m5, c5 = _five_sensor_model(d)
        m64, (t64, wl64, names64, ch64) = _many_sensor_model(d)
        tables = {5: SignalTable.from_campaign(c5),
                  64: SignalTable(t64, wl64, names64, ch64)}
        print("core pipeline throughput (decode -> windows -> checks -> model -> correction)")
        for n_sensors, model_path in (() if args.skip_core else ((5, m5), (64, m64))):
            for batch in (1, 10, 100, 1000):
                frames = min(n_frames, 5_000 * batch) if batch < 100 else n_frames
                fps = core_throughput(model_path, tables[n_sensors], frames, batch)
                summary["core_frames_per_s"][f"{n_sensors}_sensors_batch_{batch}"] = round(fps)
                print(f"  {n_sensors:3d} sensors, batch {batch:5d} frames: {fps:12,.0f} frames/s")
        seconds = 4.0 if args.quick else args.e2e_seconds
        for opcua_rate in [float(r) for r in args.opcua_rates.split(",")]:
            label = "every batch" if opcua_rate == 0 else f"{opcua_rate:g} Hz"
            print(f"end-to-end latency at 1 kHz input, OPC UA updates {label} ({seconds:g} s after "
                  "3 s warm-up): frame sent by sim-interrogator -> value change at a subscribed "
                  "client")
            lat, since_stamp = end_to_end(m5, c5, seconds, opcua_rate_hz=opcua_rate)
            lat, since_stamp = lat * 1e3, since_stamp * 1e3
            if lat.size:
                e2e = {"samples": int(lat.size),
                       "p50_ms": round(float(np.percentile(lat, 50)), 3),
                       "p99_ms": round(float(np.percentile(lat, 99)), 3),
                       "max_ms": round(float(lat.max()), 3),
                       "updates_per_s": round(lat.size / seconds, 1),
                       "from_frame_timestamp_p50_ms":
                           round(float(np.percentile(since_stamp, 50)), 3),
                       "from_frame_timestamp_p99_ms":
                           round(float(np.percentile(since_stamp, 99)), 3)}
            else:
                e2e = {"samples": 0}
            summary["e2e"][f"opcua_rate_{opcua_rate:g}"] = e2e
            print("  " + ", ".join(f"{k} {v}" for k, v in e2e.items()))
        summary["load_average"] = [round(x, 2) for x in os.getloadavg()]
        summary["cpus"] = os.cpu_count()
        print(f"load average {summary['load_average']} on {summary['cpus']} CPUs")
    target_core = summary["core_frames_per_s"].get("5_sensors_batch_100", 0) >= 50_000
    best_p99 = min((v.get("p99_ms", float("inf")) for v in summary["e2e"].values()),
                   default=float("inf"))
    summary["targets_met"] = {"core_5_sensors_ge_50k_fps_batch_100": target_core,
                              "e2e_p99_le_5ms": best_p99 <= 5.0}
    print(json.dumps(summary))


if __name__ == "__main__":
    main()
