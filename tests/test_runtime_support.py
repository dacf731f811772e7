"""Shared set-up for the runtime tests (no tests here): a real model file fitted by
fbgcomp.models.base on a synthetic campaign, and a short campaign to serve."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import time
from contextlib import contextmanager
from pathlib import Path
from types import SimpleNamespace


def model_and_campaign(base: Path) -> tuple[Path, Path]:
    """(model.json, campaign folder) built under ``base``, anew at every call: the runtime
    tests share the one the session fixture ``runtime_model_and_campaign`` (conftest) builds."""
    from fbgcomp.bench.synthetic import linear_truth_campaign
    from fbgcomp.io.campaign import write_campaign
    from fbgcomp.models.mra import MRAModel

    base.mkdir(parents=True, exist_ok=True)
    train, _ = linear_truth_campaign("train", seed=1, duration_s=2 * 3600, noise_um=0.05)
    model = MRAModel(features="eq13", zero_window_s=0.5, fallbacks="loo").fit(train)
    model_path = model.save(base / "model.json")
    # settle_s=0: the signals move from the first sample (a resting machine would look like
    # a stuck channel to a noise-free replay)
    serve, _ = linear_truth_campaign(
        "serve", seed=2, duration_s=300, fbg_dt_s=0.1, temperature_dt_s=0.1, reference_dt_s=0.1, settle_s=0.0
    )
    campaign = write_campaign(serve, base / "serve")
    return Path(model_path), Path(campaign)


def model_and_arrays(model_path: Path, campaign_path: Path):
    """The model of ``model_path`` (loaded from its file) and the campaign's aligned time (s),
    wavelengths (nm) and temperatures (°C) in the model's order: the session fixture
    ``runtime_model_and_arrays`` (conftest) of :func:`model_and_campaign`'s files."""
    from fbgcomp.io.campaign import read_campaign
    from fbgcomp.models.registry import load_model

    model = load_model(model_path)
    aligned = read_campaign(campaign_path).aligned(zero_window_s=model.zero_window_s)
    w, t, _, _ = model.instrument_arrays(aligned)
    return model, aligned.time_s, w, t


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def fbgcomp_process(*args, env=None, **kw) -> subprocess.Popen:
    """Start ``python -m fbgcomp ARGS`` (the real console entry point) in a new process."""
    full_env = dict(os.environ)
    full_env.update(env or {})
    return subprocess.Popen(
        [sys.executable, "-m", "fbgcomp", *map(str, args)],
        env=full_env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        **kw,
    )


def wait_port(port: int, timeout_s: float = 20.0) -> None:
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        try:
            with socket.create_connection(("127.0.0.1", port), timeout=0.2):
                return
        except OSError:
            time.sleep(0.05)
    raise TimeoutError(f"nothing listening on 127.0.0.1:{port}")


async def secure_client(url: str, state: Path, user: str | None = None, password: str | None = None):
    """An asyncua client with its own certificate, Basic256Sha256 SignAndEncrypt."""
    from asyncua import Client, ua
    from asyncua.crypto.security_policies import SecurityPolicyBasic256Sha256

    client = Client(url, timeout=10)
    client.application_uri = "urn:fbgcomp:test:client"
    cert, key = await client.setup_self_signed_certificate(
        state / "client_key.pem", state / "client_cert.der"
    )
    await client.set_security(
        SecurityPolicyBasic256Sha256, str(cert), str(key), mode=ua.MessageSecurityMode.SignAndEncrypt
    )
    if user is not None:
        client.set_user(user)
        client.set_password(password)
    return client


def run_in_batches(pipe, time_s, wl, temp, sizes, counts=None) -> dict:
    """Feed frames to ``pipe.process`` in batches cycling through ``sizes`` (one peak per
    grating unless ``counts``); the batch results' fields, concatenated
    (:func:`fbgcomp.bench.served.process_in_batches`)."""
    from fbgcomp.bench.served import process_in_batches

    return process_in_batches(pipe, time_s, wl, temp, sizes, counts)


def fallback_peak_um(model_path, campaign_path, lost: str):
    """Largest |correction| per axis (3,) µm the runtime pipeline publishes from the campaign
    with grating ``lost`` missing throughout (no output filter, rate or size limit): what a
    test's size bound must be measured against when the runtime serves that fallback."""
    import numpy as np

    from fbgcomp.io.campaign import read_campaign
    from fbgcomp.models.registry import load_model
    from fbgcomp.runtime.output_filter import OutputFilterConfig
    from fbgcomp.runtime.pipeline import Pipeline, PipelineConfig

    model = load_model(model_path)
    aligned = read_campaign(campaign_path).aligned(zero_window_s=model.zero_window_s)
    w, t, _, _ = model.instrument_arrays(aligned)
    counts = np.ones(w.shape, np.int8)
    j = model.sensor_names.index(lost)
    after = aligned.time_s > aligned.time_s[0] + model.zero_window_s
    w, counts[after, j] = w.copy(), 0
    w[after, j] = np.nan
    free = PipelineConfig(
        output_filter=OutputFilterConfig(enabled=False), max_slew_um_per_s=0, max_correction_um=0
    )
    r = run_in_batches(Pipeline(model, free), aligned.time_s, w, t, [1000], counts)
    return np.abs(r["correction_um"][after]).max(axis=0)


async def watch_outputs(
    url: str, state: Path, trust_dir: Path, env: dict, names, timeout_s: float, stop_when
):
    """A real asyncua client (signed and encrypted, user from ``env``) whose certificate is put
    in serve's trust list ``trust_dir``, subscribed to ``FbgComp.<name>`` for each of ``names``
    until ``stop_when(seen)`` or ``timeout_s``; returns ``seen`` = [(name, value, source time s,
    receive time s)]."""
    import asyncio

    from asyncua import ua

    from fbgcomp.runtime.trust import add_certificate

    seen = []

    class Handler:
        def datachange_notification(self, node, val, data):
            ts = data.monitored_item.Value.SourceTimestamp
            seen.append(
                (
                    node.nodeid.Identifier[len("FbgComp.") :],
                    val,
                    ts.timestamp() if ts else float("nan"),
                    time.time(),
                )
            )

    client = await secure_client(url, state, env["FBGCOMP_OPCUA_USER"], env["FBGCOMP_OPCUA_PASSWORD"])
    add_certificate(state / "client_cert.der", trust_dir)  # serve trusts known clients only
    async with client:
        sub = await client.create_subscription(0, Handler())
        await sub.subscribe_data_change([client.get_node(ua.NodeId(f"FbgComp.{n}", 2)) for n in names])
        end = time.monotonic() + timeout_s
        while time.monotonic() < end and not stop_when(seen):
            await asyncio.sleep(0.05)
    return seen


def modbus_serve_config(port: int, offset_rate_um_per_s: float) -> str:
    """serve TOML for the Modbus output tests: fast reconnects, the pipeline's own policy off
    (the model's correction as is), the [modbus] output on 127.0.0.1:``port`` with its offset
    rate limit."""
    return (
        "[source]\nbackoff_initial_s = 0.05\nbackoff_max_s = 0.4\nno_data_s = 0.2\n\n"
        "[pipeline]\nramp_s = 0.5\nmax_slew_um_per_s = 0\nmax_correction_um = [0, 0, 0]\n"
        "[pipeline.output_filter]\nenabled = false\n\n"
        f'[modbus]\nlisten = "127.0.0.1:{port}"\nunit_id = 1\n'
        f"offset_rate_um_per_s = {offset_rate_um_per_s}\nmax_offset_um = 1000\n"
    )


@contextmanager
def serve_with_simulator(tmp: Path, config_toml: str, model_path, campaign, env: dict, sim_args=()):
    """``fbgcomp serve`` (config ``config_toml``, OPC UA on a free loopback port, state in
    ``tmp/state``, run log in ``tmp/log``, temperatures from ``campaign``) and then
    ``fbgcomp sim-interrogator`` replaying ``campaign`` to it with ``sim_args``, both real
    processes. Yields ``url``, the ``serve`` and ``sim`` processes and ``watch(names, timeout_s,
    stop_when)`` (:func:`watch_outputs` with a client state in ``tmp/client``, trusted by serve).
    On exit whatever still runs is terminated (killed after 10 s) and its pipes drained."""
    import asyncio

    config = tmp / "serve.toml"
    config.write_text(config_toml)
    sp, cp, op = free_port(), free_port(), free_port()
    url = f"opc.tcp://127.0.0.1:{op}/fbgcomp/"
    serve = fbgcomp_process(
        "serve",
        "--config",
        config,
        "--model",
        model_path,
        "--source",
        f"hyperion://127.0.0.1:{sp}?command_port={cp}",
        "--temperatures",
        campaign,
        "--opcua",
        url,
        "--state-dir",
        tmp / "state",
        "--log",
        tmp / "log",
        "--rate",
        0,
        env=env,
    )
    sim = None
    try:
        try:
            wait_port(op, 40)
        except TimeoutError:
            serve.kill()
            raise AssertionError(serve.communicate(timeout=5)[1].decode()[-3000:]) from None
        # the instrument comes up after the service: the source's back-off finds it
        sim = fbgcomp_process("sim-interrogator", campaign, "--port", sp, "--command-port", cp, *sim_args)

        def watch(names, timeout_s, stop_when):
            return asyncio.run(
                watch_outputs(
                    url, tmp / "client", tmp / "state" / "opcua" / "trusted", env, names, timeout_s, stop_when
                )
            )

        yield SimpleNamespace(url=url, serve=serve, sim=sim, watch=watch)
    finally:
        for p in (sim, serve):
            if p is not None and p.poll() is None:
                p.terminate()
                try:
                    p.wait(10)
                except subprocess.TimeoutExpired:
                    p.kill()
            if p is not None:
                p.communicate(timeout=10)
