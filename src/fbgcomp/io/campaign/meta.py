"""``campaign.yaml``: the metadata schema (sensors, probes, reference instrument), its YAML
dialect, and reading, validating and writing it.

Errors are :class:`fbgcomp.errors.InputError` naming campaign.yaml and the field path
(``field sensors[1].lambda0_nm``).
"""

from __future__ import annotations

import re
from collections.abc import Mapping
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
import yaml
from pydantic import (
    AwareDatetime,
    BaseModel,
    ConfigDict,
    Field,
    StrictStr,
    ValidationError,
    field_validator,
    model_validator,
)
from pydantic_core import PydanticCustomError

from fbgcomp.errors import InputError, read_bounded
from fbgcomp.io.campaign.layout import META_FILE

__all__ = [
    "MAX_META_BYTES",
    "CampaignMeta",
    "MetaLoader",
    "ProbeSpec",
    "ReferenceSpec",
    "SensorSpec",
    "check_sensors_match",
    "meta_error",
    "meta_yaml",
    "read_meta",
    "short_repr",
    "to_builtins",
    "validate_meta",
]

#: Largest campaign.yaml read, bytes (a real one is a few kB).
MAX_META_BYTES = 1 << 20

# Silica fibre defaults (paper eq. 2); the same values as fbgcomp.optics, repeated here so that
# the file format does not depend on the physics module.
_DEFAULT_PHOTOELASTIC = 0.22
_DEFAULT_THERMO_OPTIC_PER_K = 6.67e-6
_DEFAULT_FIBRE_CTE_PER_K = 0.55e-6

_NAME_RE = r"^[A-Za-z_][A-Za-z0-9_.\-]*$"
_FiniteFloat = Annotated[float, Field(strict=True, allow_inf_nan=False)]
_PositiveFloat = Annotated[float, Field(strict=True, allow_inf_nan=False, gt=0)]
_Name = Annotated[StrictStr, Field(pattern=_NAME_RE)]


class SensorSpec(BaseModel):
    """One long-gauge FBG sensor: its grating, its fibre and where it is bonded.

    Unknown keys are kept (and round-tripped) so that instrument-specific metadata survives;
    ``Campaign.summary()`` lists them in case one is a typo of a known key.
    """

    model_config = ConfigDict(extra="allow")

    name: _Name
    lambda0_nm: _PositiveFloat = Field(description="nominal Bragg wavelength of the grating, nm")
    gauge_length_mm: _PositiveFloat = Field(description="bonded length of the sensor path, mm")
    photoelastic: _FiniteFloat = Field(
        default=_DEFAULT_PHOTOELASTIC, ge=0, lt=1, description="effective photo-elastic coefficient p_e"
    )
    thermo_optic_per_K: _FiniteFloat = Field(
        default=_DEFAULT_THERMO_OPTIC_PER_K, description="thermo-optic coefficient xi, 1/K"
    )
    fibre_cte_per_K: _FiniteFloat = Field(
        default=_DEFAULT_FIBRE_CTE_PER_K, description="fibre thermal expansion alpha_f, 1/K"
    )
    face: Literal["+X", "-X", "+Y", "-Y", "+Z", "-Z"] | None = None
    z_start_mm: _FiniteFloat | None = None
    z_end_mm: _FiniteFloat | None = None
    depth_mm: _FiniteFloat | None = Field(
        default=None,
        ge=0,
        description="distance from the face's outer surface into the wall, mm (0: bonded on the "
        "outer surface; the wall thickness: on the inner surface)",
    )
    temperature_probe: _Name | None = Field(
        default=None, description="probe used for temperature compensation; none: uncompensated"
    )
    reference_lambda0_nm: _PositiveFloat | None = Field(
        default=None,
        description="nominal wavelength of a strain-free reference grating beside the "
        "sensor (fbg.csv column <name>_ref_nm); it compensates the sensor "
        "unless temperature_probe names another probe",
    )

    @model_validator(mode="after")
    def _reference_compensates(self):
        if self.reference_lambda0_nm is not None and self.temperature_probe is None:
            self.temperature_probe = self.reference_probe
        return self

    @property
    def column(self) -> str:
        """Its column in fbg.csv."""
        return f"{self.name}_nm"

    @property
    def reference_column(self) -> str | None:
        """The fbg.csv column of its strain-free reference grating, None without one."""
        return None if self.reference_lambda0_nm is None else f"{self.name}_ref_nm"

    @property
    def reference_probe(self) -> str | None:
        """The temperature the reference grating reads, as a probe name (``<name>_ref``)."""
        return None if self.reference_lambda0_nm is None else f"{self.name}_ref"


def check_sensors_match(expected, have, where, source: str = "campaign") -> None:
    """Raise InputError unless every sensor in ``expected`` is among ``have`` with the same gauge
    length (to 1e-6 relative) and a lambda0_nm within 5 nm: what a fitted model needs of the
    data it is applied to. ``source`` names that data in the message ("campaign", "partition").
    """
    by_name = {s.name: s for s in have}
    for s in expected:
        if s.name not in by_name:
            raise InputError(
                f"model expects sensor {s.name} but the {source} has {', '.join(by_name) or 'none'}",
                file=where,
                column="field sensors",
            )
        c = by_name[s.name]
        if abs(c.gauge_length_mm - s.gauge_length_mm) > 1e-6 * max(1.0, s.gauge_length_mm):
            raise InputError(
                f"sensor {s.name} has gauge_length_mm {c.gauge_length_mm} but the model "
                f"was fitted with {s.gauge_length_mm}",
                file=where,
                column="field sensors",
            )
        if abs(c.lambda0_nm - s.lambda0_nm) > 5.0:
            raise InputError(
                f"sensor {s.name} has lambda0_nm {c.lambda0_nm} but the model expects {s.lambda0_nm} ± 5 nm",
                file=where,
                column="field sensors",
            )


class ProbeSpec(BaseModel):
    """One temperature probe (thermocouple, LM35...)."""

    model_config = ConfigDict(extra="allow")

    name: _Name
    location: StrictStr | None = None

    @property
    def column(self) -> str:
        """Its column in temperatures.csv."""
        return f"{self.name}_C"


class ReferenceSpec(BaseModel):
    """The instrument measuring the true TTP displacement (reference.csv)."""

    model_config = ConfigDict(extra="allow")

    instrument: StrictStr = "laser interferometer"
    point: StrictStr = "TTP"
    units: Literal["um"] = "um"


class CampaignMeta(BaseModel):
    """Contents of ``campaign.yaml``. Keys not modelled here (``machine``, ``seed``...) are kept."""

    model_config = ConfigDict(extra="allow")

    name: Annotated[StrictStr, Field(min_length=1)]
    kind: Literal["thermal", "static", "combined"]
    description: StrictStr = ""
    start: AwareDatetime
    sensors: Annotated[list[SensorSpec], Field(min_length=1)]
    temperature_probes: list[ProbeSpec] = Field(default_factory=list)
    reference: ReferenceSpec = Field(default_factory=ReferenceSpec)

    @field_validator("description", mode="before")
    @classmethod
    def _blank_description(cls, value):
        # "description:" with nothing after it is YAML null; treat it as no description.
        return "" if value is None else value

    @model_validator(mode="after")
    def _names_consistent(self):
        for kind, items in (("sensor", self.sensors), ("probe", self.temperature_probes)):
            key = "sensors" if kind == "sensor" else "temperature_probes"
            first: dict[str, int] = {}
            for i, item in enumerate(items):
                if item.name in first:
                    raise PydanticCustomError(
                        "duplicate_name",
                        "duplicate {kind} name '{name}' (first declared as {key}[{first}])",
                        {
                            "kind": kind,
                            "name": item.name,
                            "key": key,
                            "first": first[item.name],
                            "field": f"{key}[{i}].name",
                        },
                    )
                first[item.name] = i
        refs = set(self.reference_probe_names)
        for i, probe in enumerate(self.temperature_probes):
            if probe.name in refs:
                raise PydanticCustomError(
                    "duplicate_name",
                    "probe name '{name}' is taken by the reference grating of sensor '{sensor}'",
                    {"name": probe.name, "sensor": probe.name[:-4], "field": f"temperature_probes[{i}].name"},
                )
        probes = self.probe_names
        for i, sensor in enumerate(self.sensors):
            if sensor.temperature_probe is not None and sensor.temperature_probe not in probes:
                raise PydanticCustomError(
                    "unknown_probe",
                    "sensor '{sensor}' names temperature probe '{probe}', which is not declared "
                    "in temperature_probes (declared: {declared})",
                    {
                        "sensor": sensor.name,
                        "probe": sensor.temperature_probe,
                        "declared": ", ".join(probes) or "none",
                        "field": f"sensors[{i}].temperature_probe",
                    },
                )
        return self

    @property
    def sensor_names(self) -> list[str]:
        """Sensor names in campaign.yaml order."""
        return [s.name for s in self.sensors]

    @property
    def probe_names(self) -> list[str]:
        """Declared probes, then the strain-free reference gratings read as thermometers
        (``<sensor>_ref``); see :attr:`Campaign.probe_names` for undeclared CSV columns."""
        return [p.name for p in self.temperature_probes] + self.reference_probe_names

    @property
    def reference_probe_names(self) -> list[str]:
        """``<sensor>_ref`` for every sensor with a strain-free reference grating."""
        return [s.reference_probe for s in self.sensors if s.reference_probe is not None]

    def sensor(self, name: str) -> SensorSpec:
        """The sensor called ``name`` (KeyError if there is none)."""
        for s in self.sensors:
            if s.name == name:
                return s
        raise KeyError(name)

    def probe(self, name: str) -> ProbeSpec:
        """The declared probe called ``name`` (KeyError if there is none)."""
        for p in self.temperature_probes:
            if p.name == name:
                return p
        raise KeyError(name)


_YAML_FLOAT_RE = re.compile(
    r"""^(?:[-+]?(?:[0-9][0-9_]*)\.[0-9_]*(?:[eE][-+]?[0-9]+)?
    |[-+]?(?:[0-9][0-9_]*)(?:[eE][-+]?[0-9]+)
    |[-+]?\.[0-9_]+(?:[eE][-+]?[0-9]+)?
    |[-+]?\.(?:inf|Inf|INF)
    |\.(?:nan|NaN|NAN))$""",
    re.X,
)


class MetaLoader(yaml.SafeLoader):
    """Safe loader that reads ``1e-6`` as a number (YAML 1.1 would make it a string, and a
    coefficient typed that way would then be rejected) and refuses duplicate keys, which plain
    PyYAML silently resolves by keeping the last one."""

    def construct_mapping(self, node, deep=False):
        """The mapping of ``node``; ConstructorError naming the line of a repeated key."""
        seen = {}
        for key_node, _ in node.value:
            key = self.construct_object(key_node, deep=True)
            try:
                duplicate = key in seen
            except TypeError:  # unhashable key: let the base class report it
                break
            if duplicate:
                raise yaml.constructor.ConstructorError(
                    None, None, f"duplicate key {key!r} (first at line {seen[key] + 1})", key_node.start_mark
                )
            seen[key] = key_node.start_mark.line
        return super().construct_mapping(node, deep=deep)


class _MetaDumper(yaml.SafeDumper):
    """Quotes strings such as ``'1e5'`` that :class:`MetaLoader` would read back as numbers."""


def _represent_str(dumper, value: str):
    # PyYAML writes NEL / LINE SEPARATOR / PARAGRAPH SEPARATOR / BOM raw in plain and single-quoted
    # scalars, where a reader folds them into spaces; double quotes escape them (\N, \L, \P).
    style = '"' if any(ch in value for ch in "\x85\u2028\u2029\ufeff") else None
    return dumper.represent_scalar("tag:yaml.org,2002:str", value, style=style)


MetaLoader.add_implicit_resolver("tag:yaml.org,2002:float", _YAML_FLOAT_RE, list("-+0123456789."))
_MetaDumper.add_implicit_resolver("tag:yaml.org,2002:float", _YAML_FLOAT_RE, list("-+0123456789."))
_MetaDumper.add_representer(str, _represent_str)


def _field_path(loc) -> str:
    path = ""
    for part in loc:
        path += f"[{part}]" if isinstance(part, int) else (f".{part}" if path else str(part))
    return path


def short_repr(value, limit: int = 60) -> str:
    """``repr(value)`` cut to ``limit`` characters (ending in ``...``), for error messages."""
    text = repr(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."


def meta_error(exc: ValidationError, file) -> InputError:
    """A pydantic ValidationError as one InputError naming ``file`` and the first problem's field
    path (``field sensors[1].lambda0_nm``), with the count of further problems."""
    err = exc.errors()[0]
    ctx = err.get("ctx") or {}
    path = ctx.get("field") or _field_path(err["loc"]) or "campaign.yaml"
    if err["type"] == "missing":
        message = "required field is missing"
    elif err["type"] in ("duplicate_name", "unknown_probe"):
        message = err["msg"]
    else:
        message = f"{err['msg']} (got {short_repr(err.get('input'))})"
    more = exc.error_count() - 1
    if more:
        message += f" [and {more} more problem{'s' if more > 1 else ''}]"
    return InputError(message, file=file, column=f"field {path}")


def validate_meta(data: Any, file) -> CampaignMeta:
    """Metadata (a mapping or a CampaignMeta) checked against the schema; InputError naming
    ``file`` and the field otherwise."""
    if isinstance(data, CampaignMeta):
        data = data.model_dump()
    if not isinstance(data, Mapping):
        raise InputError(
            "expected a mapping of fields (name: ..., kind: ..., sensors: ...) at the "
            f"top level, found {type(data).__name__}",
            file=file,
        )
    try:
        return CampaignMeta.model_validate(dict(data))
    except ValidationError as exc:
        raise meta_error(exc, file) from None


def read_meta(folder: Path) -> CampaignMeta:
    """Read and validate ``folder/campaign.yaml`` (bounded to :data:`MAX_META_BYTES`); InputError
    naming the file and the line or field path."""
    file = folder / META_FILE
    if not file.is_file():
        raise InputError(
            "missing file: a campaign folder needs campaign.yaml "
            "(name, kind, start, sensors, temperature_probes, reference)",
            file=file,
        )
    raw = read_bounded(file, MAX_META_BYTES, what="campaign metadata")
    if not raw.strip():
        raise InputError(
            "empty file: expected the campaign metadata (name, kind, start, sensors, ...)", file=file
        )
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        line = raw[: exc.start].count(b"\n") + 1
        raise InputError(f"not UTF-8 text: byte 0x{raw[exc.start]:02x} at line {line}", file=file) from None
    try:
        data = yaml.load(text, Loader=MetaLoader)
    except yaml.MarkedYAMLError as exc:
        mark = exc.problem_mark or exc.context_mark
        where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark else ""
        problem = exc.problem or exc.context or "invalid YAML"
        raise InputError(f"YAML syntax error{where}: {problem}", file=file) from None
    except yaml.YAMLError as exc:
        raise InputError(f"YAML syntax error: {exc}", file=file) from None
    return validate_meta(data, file)


def to_builtins(value):
    """Metadata as YAML-safe builtins (numpy scalars from a generator, tuples...)."""
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, Mapping):
        return {k: to_builtins(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [to_builtins(v) for v in value]
    if isinstance(value, Path):
        return str(value)
    return value


_OPTIONAL_SENSOR_KEYS = ("face", "z_start_mm", "z_end_mm", "depth_mm", "temperature_probe")


def meta_yaml(meta: CampaignMeta, file) -> str:
    """``meta`` as the text of a campaign.yaml that :func:`read_meta` reads back equal (unset
    optional sensor and probe keys left out); InputError naming ``file`` if it cannot be written."""
    data = to_builtins(meta.model_dump(mode="python"))
    for sensor in data["sensors"]:
        for key in _OPTIONAL_SENSOR_KEYS:
            if sensor.get(key, "") is None:
                del sensor[key]
    for probe in data["temperature_probes"]:
        if probe.get("location", "") is None:
            del probe["location"]
    try:
        return yaml.dump(
            data, Dumper=_MetaDumper, sort_keys=False, allow_unicode=True, default_flow_style=None, width=160
        )
    except yaml.YAMLError as exc:
        raise InputError(f"metadata cannot be written as YAML: {exc}", file=file) from None
