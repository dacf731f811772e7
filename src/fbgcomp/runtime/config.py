"""``fbgcomp serve``'s configuration: the TOML file's sections (``[source]``, ``[log]``, and the
sections of the parts they configure), overridden by the command line; a bad key or value is one
:class:`~fbgcomp.errors.InputError` naming the file and field. The service (:mod:`.service`)
reads it."""

from __future__ import annotations

import tomllib
from dataclasses import dataclass, field, fields, is_dataclass
from pathlib import Path

from fbgcomp.dashboard import DashboardConfig
from fbgcomp.errors import InputError
from fbgcomp.runtime.live_inputs import PositionConfig, TemperaturesConfig
from fbgcomp.runtime.outputs.linuxcnc import CncConfig
from fbgcomp.runtime.outputs.modbus import ModbusConfig
from fbgcomp.runtime.outputs.opcua import OpcUaConfig
from fbgcomp.runtime.pipeline import PipelineConfig
from fbgcomp.runtime.realtime import RealtimeConfig

__all__ = ["LogConfig", "RuntimeConfig", "SourceConfig"]


@dataclass
class SourceConfig:
    """``[source]``: where the wavelengths (and, for replays, the temperatures) come from."""

    url: str = ""
    window_nm: float = 2.5
    speed: float = 1.0  # replay:// and sim:// only
    loop: bool = False  # replay:// and sim:// only
    backoff_initial_s: float = 0.1
    backoff_max_s: float = 5.0
    stall_timeout_s: float = 2.0
    no_data_s: float = 0.1  # no frame for this long = link lost
    # link lost while every probe is a live input: the set without gratings goes on from the
    # probes (DEGRADED); false (or no such set): hold and ramp (ALARM)
    probes_on_link_loss: bool = True
    temperatures: str | None = None  # campaign folder, temperatures CSV or const:P=°C,...


@dataclass
class LogConfig:
    """``[log]``: the run log folder (none: no log), its flush period and whether parts are fsynced."""

    dir: str | None = None
    flush_s: float = 0.5
    fsync: bool = True


@dataclass
class RuntimeConfig:
    """serve's whole configuration: the TOML file's sections, overridden by the command line."""

    model: str = ""
    source: SourceConfig = field(default_factory=SourceConfig)
    pipeline: PipelineConfig = field(default_factory=PipelineConfig)
    opcua: OpcUaConfig = field(default_factory=OpcUaConfig)
    log: LogConfig = field(default_factory=LogConfig)
    opcua_enabled: bool = True
    dashboard: DashboardConfig = field(default_factory=DashboardConfig)
    cnc: CncConfig = field(default_factory=CncConfig)  # --cnc linuxcnc (docs/linuxcnc.md)
    modbus: ModbusConfig = field(default_factory=ModbusConfig)  # docs/cnc-integration.md
    realtime: RealtimeConfig = field(default_factory=RealtimeConfig)  # --cpu, --realtime-priority
    # live probe temperatures (OPC UA, Modbus TCP) and the Z position (LinuxCNC, OPC UA):
    # fbgcomp.runtime.live_inputs, docs/runtime.md "Live inputs"
    temperatures: TemperaturesConfig = field(default_factory=TemperaturesConfig)
    position: PositionConfig = field(default_factory=PositionConfig)

    @classmethod
    def from_toml(cls, path: str | Path) -> RuntimeConfig:
        """The configuration in a TOML file; InputError naming the file and field otherwise."""
        path = Path(path)
        try:
            data = tomllib.loads(path.read_text())
        except FileNotFoundError:
            raise InputError("configuration file not found", file=path) from None
        except tomllib.TOMLDecodeError as exc:
            raise InputError(f"not valid TOML: {exc}", file=path) from exc
        cfg = cls()
        _update(cfg, data, str(path), "")
        return cfg


def _update(obj, data: dict, file: str, prefix: str) -> None:
    known = {f.name: f for f in fields(obj)}
    for key, value in data.items():
        where = f"field {prefix}{key}"
        if key not in known:
            raise InputError(
                f"unknown configuration key (known: {', '.join(known)})", file=file, column=where
            )
        current = getattr(obj, key)
        if is_dataclass(current):
            if not isinstance(value, dict):
                raise InputError("expected a table", file=file, column=where)
            _update(current, value, file, f"{prefix}{key}.")
        elif isinstance(current, tuple):  # per-axis (dx, dy, dz) or one value for all
            items = value if isinstance(value, list) else [value]
            if len(items) not in (1, 3) or not all(
                isinstance(v, (int, float)) and not isinstance(v, bool) and v >= 0 for v in items
            ):
                raise InputError(
                    f"expected one number >= 0 or three (dx, dy, dz), got {value!r}", file=file, column=where
                )
            setattr(obj, key, tuple(float(v) for v in items) * (3 if len(items) == 1 else 1))
        else:
            if (
                current is not None
                and not isinstance(value, type(current))
                and not (isinstance(current, float) and isinstance(value, int))
            ):
                raise InputError(f"expected {type(current).__name__}, got {value!r}", file=file, column=where)
            setattr(obj, key, float(value) if isinstance(current, float) else value)
