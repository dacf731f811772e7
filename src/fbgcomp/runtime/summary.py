"""serve's one-line start-up summary: what the service reads, publishes, applies, and who may
change it (issue 15: a shop-floor user sees at once what is running)."""

from __future__ import annotations


def startup_summary(service) -> str:
    """One line on what the running ``service`` (:class:`fbgcomp.runtime.service.Service`, all
    its outputs started) reads, publishes, applies and lets others change: inputs, outputs,
    model, policy, and who may write (the OPC UA users that may switch the compensation and
    reload the model, the dashboard users that may switch it)."""
    cfg = service.config
    inputs = [f"gratings {cfg.source.url}"]
    if cfg.source.temperatures:
        inputs.append(f"temperatures {cfg.source.temperatures}")
    if cfg.temperatures.opcua.endpoint:
        inputs.append(f"temperatures live from OPC UA {cfg.temperatures.opcua.endpoint}")
    if cfg.temperatures.modbus.host:
        m = cfg.temperatures.modbus
        inputs.append(f"temperatures live from Modbus {m.host}:{m.port}")
    if cfg.position.source:
        inputs.append(f"Z from {cfg.position.source}")
    outputs = []
    if service.opc is not None:
        outputs.append(f"OPC UA {cfg.opcua.endpoint}")
    if service.modbus is not None:
        outputs.append(f"Modbus {cfg.modbus.listen}")
    if service.cnc is not None:
        outputs.append(f"LinuxCNC {cfg.cnc.address}")
    if service.dashboard is not None:
        outputs.append(f"dashboard {service.dashboard.url}")
    if service.runlog is not None:
        outputs.append(f"run log {cfg.log.dir}")
    pc = cfg.pipeline
    policy = [
        f"output filter {'on' if pc.output_filter.enabled else 'off'}",
        "max correction " + "/".join(f"{v:g}" for v in service.pipeline.max_correction_um) + " µm",
        "max slew " + "/".join(f"{v:g}" for v in service.pipeline.max_slew_um_per_s) + " µm/s",
    ]
    if pc.smoothing_tau_s:
        policy.append(f"smoothing {pc.smoothing_tau_s:g} s")
    writers = []
    if service.opc is not None:
        users = sorted(service.opc.users)
        writers.append(
            "OPC UA: "
            + (", ".join(users) if users else "nobody")
            + (" (anonymous sessions read only)" if cfg.opcua.allow_anonymous else "")
        )
    if service.dashboard is not None:
        users = sorted(service.dashboard.users)
        writers.append("dashboard: " + (", ".join(users) if users else "nobody"))
    return (
        f"serving model {service.model_id} ({service.model.model_type}, {cfg.model or 'in memory'})"
        f" | inputs: {'; '.join(inputs)}"
        f" | outputs: {'; '.join(outputs) if outputs else 'none'}"
        f" | policy: {', '.join(policy)}"
        f" | may write: {'; '.join(writers) if writers else 'nobody (no OPC UA, no dashboard)'}"
    )
