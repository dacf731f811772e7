"""Runtime commands: ``serve``, ``sim-interrogator``, ``log export`` and ``trust add|list``
(mounted by :mod:`fbgcomp.cli.app`).

The runtime (asyncua, pyarrow, the simulator) is imported inside the commands so that
``fbgcomp --help`` and the offline commands start fast.
"""

from __future__ import annotations

import asyncio
import logging
import sys
from pathlib import Path

import typer

from fbgcomp.errors import InputError


def _per_axis_option(text: str, option: str) -> tuple:
    """``off`` | ``V`` | ``DX,DY,DZ`` -> three floats (0 = no limit on that axis)."""
    if text.strip().lower() == "off":
        return (0.0, 0.0, 0.0)
    try:
        values = [float(v) for v in text.split(",")]
    except ValueError:
        values = []
    if len(values) not in (1, 3) or any(not v >= 0 for v in values):
        raise InputError(f"expected off, one number >= 0 or three (dx,dy,dz), got {text!r}", column=option)
    return tuple(values * 3 if len(values) == 1 else values)


def serve(
    model: Path | None = typer.Option(None, "--model", help="Model file (JSON) from fbgcomp fit."),
    source: str | None = typer.Option(
        None,
        "--source",
        help="hyperion://HOST:PORT (stream port; command port = PORT-1 or "
        "?command_port=N), replay://DIR?speed=S or sim://DIR?rate=HZ&speed=S.",
    ),
    config: Path | None = typer.Option(None, "--config", help="TOML configuration (docs/runtime.md)."),
    temperatures: str | None = typer.Option(
        None,
        "--temperatures",
        help="Probe temperatures: campaign folder, temperatures CSV or const:PROBE=°C,...",
    ),
    opcua: str | None = typer.Option(
        None, "--opcua", help="OPC UA endpoint, e.g. opc.tcp://127.0.0.1:4840/fbgcomp/; 'off' disables."
    ),
    state_dir: Path | None = typer.Option(None, "--state-dir", help="Certificates and state."),
    log_dir: Path | None = typer.Option(None, "--log", help="Run-log folder (Parquet)."),
    rate: float | None = typer.Option(None, "--rate", help="OPC UA update rate, Hz (0 = every batch)."),
    smoothing: float | None = typer.Option(
        None, "--smoothing-tau", help="Correction smoothing time constant, s."
    ),
    max_slew: str | None = typer.Option(
        None,
        "--max-slew",
        help=(
            "Largest rate of change of the correction, µm/s: one value or dx,dy,dz (default 1000; 0 or off "
            "= no limit)."
        ),
    ),
    max_correction: str | None = typer.Option(
        None,
        "--max-correction-um",
        help=(
            "Largest |correction| per axis, µm: one value or dx,dy,dz (default 1000; 0 or off = none; a "
            "tighter bound in the model file still applies)."
        ),
    ),
    output_filter: str | None = typer.Option(
        None, "--output-filter", help="Adaptive output filter: on (default) or off."
    ),
    allow_anonymous: bool = typer.Option(
        False, "--allow-anonymous", help="Allow anonymous read-only OPC UA sessions."
    ),
    users_file: Path | None = typer.Option(
        None, "--users", help="OPC UA users file (name:pbkdf2_sha256$...)."
    ),
    trusted_clients: Path | None = typer.Option(
        None,
        "--trusted-clients",
        help="Folder of the client certificates OPC UA trusts "
        "(default <state-dir>/opcua/trusted; fill it with fbgcomp trust add).",
    ),
    models_dir: Path | None = typer.Option(
        None,
        "--models-dir",
        help="Folder OPC UA ReloadModel may load models from (default: none, "
        "ReloadModel only reloads the current model).",
    ),
    dashboard: str | None = typer.Option(
        None,
        "--dashboard",
        help=(
            "Serve the live dashboard on [HOST:]PORT, host 127.0.0.1 if omitted; beyond loopback reads need "
            "a login (docs/dashboard.md, docs/security.md)."
        ),
    ),
    dashboard_users: Path | None = typer.Option(
        None, "--dashboard-users", help="Dashboard users file (name:pbkdf2_sha256$...)."
    ),
    dashboard_cert: Path | None = typer.Option(
        None, "--dashboard-cert", help="Serve the dashboard over HTTPS with this PEM certificate (chain)."
    ),
    dashboard_key: Path | None = typer.Option(
        None, "--dashboard-key", help="PEM private key of --dashboard-cert."
    ),
    cnc: str | None = typer.Option(
        None, "--cnc", help="CNC output: linuxcnc (HAL component fbgcomp, docs/linuxcnc.md) or off."
    ),
    cnc_address: str | None = typer.Option(
        None, "--cnc-address", help="Local channel of the CNC output: udp://127.0.0.1:47300 or unix:///path."
    ),
    duration: float | None = typer.Option(None, "--duration", help="Stop after this many seconds."),
    cpu: int | None = typer.Option(
        None, "--cpu", help="Pin serve (and its OPC UA process) to this CPU; -1 = any (default)."
    ),
    realtime_priority: int | None = typer.Option(
        None,
        "--realtime-priority",
        help=(
            "Run under SCHED_FIFO at this priority (1-99) where permitted; where not, one warning and "
            "normal priority. 0 = normal scheduling (default)."
        ),
    ),
    verbose: bool = typer.Option(False, "--verbose", "-v", help="Log progress to stderr."),
):
    """Run the real-time compensator: wavelengths -> model -> correction on OPC UA, logged to Parquet."""
    from fbgcomp.runtime.service import RuntimeConfig, run_service

    logging.basicConfig(
        level=logging.INFO if verbose else logging.WARNING,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
    )
    cfg = RuntimeConfig.from_toml(config) if config else RuntimeConfig()
    if model is not None:
        cfg.model = str(model)
    if source is not None:
        cfg.source.url = source
    if not cfg.source.url:
        raise InputError("no source given", column="--source")
    if temperatures is not None:
        cfg.source.temperatures = temperatures
    if opcua is not None:
        if opcua == "off":
            cfg.opcua_enabled = False
        else:
            cfg.opcua.endpoint = opcua
    if state_dir is not None:
        cfg.opcua.state_dir = str(state_dir)
    if log_dir is not None:
        cfg.log.dir = str(log_dir)
    if rate is not None:
        cfg.opcua.rate_hz = rate
    if smoothing is not None:
        cfg.pipeline.smoothing_tau_s = smoothing
    if max_slew is not None:
        cfg.pipeline.max_slew_um_per_s = _per_axis_option(max_slew, "--max-slew")
    if max_correction is not None:
        cfg.pipeline.max_correction_um = _per_axis_option(max_correction, "--max-correction-um")
    if output_filter is not None:
        if output_filter not in ("on", "off"):
            raise InputError(f"expected on or off, got {output_filter!r}", column="--output-filter")
        cfg.pipeline.output_filter.enabled = output_filter == "on"
    if allow_anonymous:
        cfg.opcua.allow_anonymous = True
    if users_file is not None:
        cfg.opcua.users_file = str(users_file)
    if trusted_clients is not None:
        cfg.opcua.trusted_clients_dir = str(trusted_clients)
    if models_dir is not None:
        cfg.opcua.models_dir = str(models_dir)
    if cfg.opcua.models_dir and not Path(cfg.opcua.models_dir).is_dir():
        raise InputError("models folder not found", file=cfg.opcua.models_dir, column="opcua.models_dir")
    if dashboard is not None:
        cfg.dashboard.listen = dashboard
    if dashboard_users is not None:
        cfg.dashboard.users_file = str(dashboard_users)
    if dashboard_cert is not None:
        cfg.dashboard.tls_cert = str(dashboard_cert)
    if dashboard_key is not None:
        cfg.dashboard.tls_key = str(dashboard_key)
    if cnc is not None:
        cfg.cnc.kind = cnc
    if cnc_address is not None:
        cfg.cnc.address = cnc_address
    if cpu is not None:
        cfg.realtime.cpu = cpu
    if realtime_priority is not None:
        if not 0 <= realtime_priority <= 99:
            raise InputError(f"expected 0..99, got {realtime_priority}", column="--realtime-priority")
        cfg.realtime.fifo_priority = realtime_priority
    svc = run_service(cfg, duration, announce=lambda line: typer.echo(line, err=True))
    typer.echo(f"processed {svc.frames} frames in {svc.batches} batches", err=True)


def sim_interrogator(
    campaign: Path = typer.Argument(..., help="Campaign folder whose fbg.csv is served."),
    host: str = typer.Option("127.0.0.1", "--host", help="Address to listen on."),
    port: int = typer.Option(51972, "--port", help="Peak stream port (command port = --command-port)."),
    command_port: int = typer.Option(51971, "--command-port", help="Command port."),
    rate: float = typer.Option(1000.0, "--rate", help="Frames per second (up to 5000 and more)."),
    channels: int = typer.Option(1, "--channels", help="Instrument channels the sensors are spread over."),
    extra_peaks: int = typer.Option(0, "--extra-peaks", help="Additional non-sensor peaks per channel."),
    peaks_per_channel: int | None = typer.Option(
        None, "--peaks-per-channel", help="Pad every channel with non-sensor peaks up to this many peaks."
    ),
    speed: float = typer.Option(1.0, "--speed", help="Campaign seconds per real second."),
    loop: bool = typer.Option(False, "--loop", help="Restart the campaign at its end."),
    noise_pm: float = typer.Option(0.0, "--noise-pm", help="Gaussian wavelength noise, pm."),
    fault: list[str] = typer.Option(
        [],
        "--fault",
        help=(
            "drop:S@t, double:S@t, shift:S@t:nm, stuck:S@t, each optionally /duration (drop:S3@5/2 brings "
            "S3 back at 7 s, shift:S2@3:+2/10 moves S2 by 2 nm for 10 s; default: to the end), cut@t:s, "
            "garbage@t:bytes (random bytes on the stream, at most 1 MiB); t = s since start; S may name a "
            "reference grating, S3_ref. Repeatable."
        ),
    ),
    duration: float | None = typer.Option(None, "--duration", help="Stop after this many seconds."),
    send_log: Path | None = typer.Option(
        None,
        "--send-log",
        help=(
            "Save the wall-clock send time of every block of frames (.npy: first stamp s, frames, send time "
            "s) at exit, for latency measurements."
        ),
    ),
    temperatures_opcua: str | None = typer.Option(
        None,
        "--temperatures-opcua",
        help=(
            "Also serve the campaign's probe temperatures on this OPC UA endpoint (opc.tcp://HOST:PORT; "
            "nodes ns=2;s=Probes.<probe>, °C), on the simulator's clock and speed."
        ),
    ),
):
    """Serve a campaign's wavelengths over the Hyperion TCP protocol (a simulated instrument)."""
    from fbgcomp.runtime.simulator import (
        OpcUaTemperatureServer,
        SignalTable,
        SimConfig,
        parse_fault,
        run_simulator,
    )

    if not campaign.is_dir():
        raise InputError("campaign folder not found", file=campaign)
    table = SignalTable.from_campaign(campaign)
    cfg = SimConfig(
        rate_hz=rate,
        channels=channels,
        extra_peaks_per_channel=extra_peaks,
        peaks_per_channel=peaks_per_channel,
        speed=speed,
        loop=loop,
        noise_pm=noise_pm,
        faults=[parse_fault(f) for f in fault],
    )

    temps = None
    if temperatures_opcua:
        temps = OpcUaTemperatureServer.from_campaign(temperatures_opcua, campaign, cfg, table)

    def ready(sim):
        print(
            f"serving {len(table.sensor_names)} sensors at {rate:g} Hz on {host}: "
            f"command {sim.command_port}, stream {sim.stream_port}"
            + (
                f"; temperatures {', '.join(temps.probe_names)} on {temps.endpoint}"
                if temps is not None
                else ""
            ),
            file=sys.stderr,
            flush=True,
        )

    try:
        asyncio.run(
            run_simulator(table, cfg, host, command_port, port, ready, duration, send_log, temperatures=temps)
        )
    except OSError as exc:
        raise InputError(
            f"cannot listen on {host}:{port}/{command_port}: {exc.strerror}", column="--port"
        ) from exc
    except KeyboardInterrupt:
        pass


#: ``fbgcomp log ...``
log_app = typer.Typer(help="Run logs written by serve.", no_args_is_help=True)


@log_app.command("export")
def export(
    log: Path = typer.Argument(..., help="Run-log folder written by serve --log."),
    output: Path = typer.Option(..., "-o", "--output", help="Campaign folder to write."),
    name: str | None = typer.Option(None, "--name", help="Campaign name."),
    reference: Path | None = typer.Option(
        None, "--reference", help="TTP reference CSV (time_s from the log start, dx_um, dy_um, dz_um)."
    ),
):
    """Turn a run log back into a campaign folder (to re-fit a model on a production run)."""
    from fbgcomp.runtime.log import export_campaign

    c = export_campaign(log, output, name=name, reference_csv=reference)
    typer.echo(f"campaign written to {output} ({len(c.fbg)} samples)")


#: ``fbgcomp trust ...``
trust_app = typer.Typer(
    help="Client certificates the OPC UA server trusts (docs/security.md).", no_args_is_help=True
)
_DIR_HELP = "Trust-list folder (default <state-dir>/opcua/trusted, as serve uses without --trusted-clients)."


def _trust_dir(directory: Path | None, state_dir: Path | None) -> Path:
    from fbgcomp.runtime.trust import trusted_dir

    return trusted_dir(state_dir, directory)


@trust_app.command("add")
def trust_add(
    cert: Path = typer.Argument(..., help="Client certificate, DER or PEM."),
    directory: Path | None = typer.Option(None, "--dir", help=_DIR_HELP),
    state_dir: Path | None = typer.Option(None, "--state-dir", help="serve's --state-dir."),
):
    """Trust a client certificate: check it and copy it into the trust list (atomically)."""
    from fbgcomp.runtime.trust import add_certificate

    folder = _trust_dir(directory, state_dir)
    try:
        info, new = add_certificate(cert, folder)
    except OSError as exc:
        raise InputError(f"cannot write the trust list: {exc.strerror}", file=folder) from exc
    typer.echo(f"{'trusted' if new else 'already trusted'}: {info.describe()}")
    typer.echo(f"trust list: {folder}")


@trust_app.command("list")
def trust_list(
    directory: Path | None = typer.Option(None, "--dir", help=_DIR_HELP),
    state_dir: Path | None = typer.Option(None, "--state-dir", help="serve's --state-dir."),
):
    """Show the certificates in the trust list (unreadable files are flagged)."""
    from fbgcomp.runtime.trust import list_certificates

    folder = _trust_dir(directory, state_dir)
    if folder.exists() and not folder.is_dir():
        raise InputError("trust list is not a folder", file=folder)
    certs = list_certificates(folder)
    typer.echo(f"trust list: {folder} ({len(certs)} certificate(s))")
    for info in certs:
        typer.echo(f"  {info.describe()}")
    if any(c.error for c in certs):
        raise InputError(
            "unreadable file(s) in the trust list: the server trusts nobody until they are removed",
            file=folder,
        )
