"""Machine description: the CFRP ram, its housing, materials, supports, FBG paths and probes.

Read from YAML (``load_machine``) and validated with pydantic v2; every problem is raised as
:class:`fbgcomp.errors.InputError` naming the file and the field (``field sensors[2].lambda0_nm``).
Geometry follows the paper's prototype (sections 2.3-2.4): ram axis along Z, z = 0 at the spindle
end, the housing below (z < 0), the TTP on the axis below the housing.
"""

from __future__ import annotations

import importlib.resources
from pathlib import Path
from typing import Literal

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from fbgcomp.errors import InputError

Face = Literal["+X", "-X", "+Y", "-Y"]


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class Ram(_Strict):
    outer_width_mm: float = Field(gt=0)
    outer_depth_mm: float = Field(gt=0)
    wall_mm: float = Field(gt=0)
    length_mm: float = Field(gt=0)

    @model_validator(mode="after")
    def _wall_fits(self):
        if 2 * self.wall_mm >= min(self.outer_width_mm, self.outer_depth_mm):
            raise ValueError("wall_mm must be less than half the outer width and depth (hollow box)")
        return self


class Housing(_Strict):
    width_mm: float = Field(gt=0)
    depth_mm: float = Field(gt=0)
    height_mm: float = Field(gt=0)


class Tool(_Strict):
    ttp_below_housing_mm: float = Field(ge=0)


class CFRP(_Strict):
    E_L_GPa: float = Field(gt=0)
    E_T_GPa: float = Field(gt=0)
    G_LT_GPa: float = Field(gt=0)
    nu_LT: float = Field(gt=-1, lt=0.5)
    nu_TT: float = Field(gt=-1, lt=1)
    cte_L_per_K: float
    cte_T_per_K: float
    k_L_W_per_mK: float = Field(gt=0)
    k_T_W_per_mK: float = Field(gt=0)
    density_kg_per_m3: float = Field(gt=0)
    specific_heat_J_per_kgK: float = Field(gt=0)


class Steel(_Strict):
    E_GPa: float = Field(gt=0)
    nu: float = Field(gt=-1, lt=0.5)
    cte_per_K: float
    k_W_per_mK: float = Field(gt=0)
    density_kg_per_m3: float = Field(gt=0)
    specific_heat_J_per_kgK: float = Field(gt=0)


class Materials(_Strict):
    cfrp: CFRP
    steel: Steel


class Carriage(_Strict):
    name: str
    z_mm: float


class Nut(_Strict):
    z_mm: float
    stiffness_N_per_um: float = Field(gt=0)


class Supports(_Strict):
    z_axis_mm: float = 0.0
    shoe_faces: tuple[Face, Face] = ("+X", "-X")
    carriages: tuple[Carriage, Carriage]
    shoe_length_mm: float = Field(gt=0)
    shoe_width_mm: float = Field(gt=0)
    carriage_stiffness_N_per_um: float = Field(gt=0)
    nut: Nut

    @model_validator(mode="after")
    def _opposite_faces(self):
        a, b = self.shoe_faces
        if a[1] != b[1] or a == b:
            raise ValueError("shoe_faces must be two opposite faces, e.g. ['+X', '-X']")
        return self


class Sensor(_Strict):
    name: str = Field(min_length=1)
    face: Face
    offset_mm: float = 0.0
    z_start_mm: float
    z_end_mm: float
    lambda0_nm: float = Field(gt=0)
    photoelastic: float = Field(ge=0, lt=1)
    thermo_optic_per_K: float
    fibre_cte_per_K: float
    temperature_probe: str | None = None
    gauge_length_mm: float | None = Field(default=None, gt=0)

    @model_validator(mode="after")
    def _ordered(self):
        if self.z_end_mm <= self.z_start_mm:
            raise ValueError("z_end_mm must be greater than z_start_mm")
        length = self.z_end_mm - self.z_start_mm
        if self.gauge_length_mm is not None and abs(self.gauge_length_mm - length) > 1e-6:
            raise ValueError(f"gauge_length_mm must equal z_end_mm - z_start_mm = {length:g}")
        return self

    @property
    def gauge_length(self) -> float:
        """Gauge length in mm: the path length between the grating's end points."""
        return self.z_end_mm - self.z_start_mm


class Probe(_Strict):
    name: str = Field(min_length=1)
    kind: Literal["point", "ambient"] = "point"
    x_mm: float | None = None
    y_mm: float | None = None
    z_mm: float | None = None

    @model_validator(mode="after")
    def _located(self):
        coords = (self.x_mm, self.y_mm, self.z_mm)
        if self.kind == "point" and any(c is None for c in coords):
            raise ValueError("a point probe needs x_mm, y_mm and z_mm")
        if self.kind == "ambient" and any(c is not None for c in coords):
            raise ValueError("the ambient probe is the ambient input, it takes no coordinates")
        return self


class Thermal(_Strict):
    film_outer_W_per_m2K: float = Field(gt=0)
    film_inner_W_per_m2K: float = Field(ge=0)
    spindle_heat: Literal["housing"] = "housing"
    radiant_face: Face = "+X"
    radiant_absorptivity: float = Field(default=0.9, ge=0, le=1)
    nominal_spindle_heat_W: float = Field(default=150.0, ge=0)
    nominal_radiant_W_per_m2: float = Field(default=40.0, ge=0)


class MeshSettings(_Strict):
    resolution: float = Field(default=1.0, gt=0, le=8)
    wall_elements: int = Field(default=3, ge=1)
    span_elements: int = Field(default=10, ge=2)
    dz_mm: float = Field(default=20.0, gt=0)
    thermal_shifts: int = Field(default=12, ge=0, le=60)


class Machine(_Strict):
    """The whole machine description (see ``data/ram.yaml`` for every field, with its unit)."""

    reference_temperature_C: float = 20.0
    ram: Ram
    housing: Housing
    tool: Tool
    materials: Materials
    supports: Supports
    sensors: tuple[Sensor, ...] = Field(min_length=1)
    candidate_sensors: tuple[Sensor, ...] = ()
    probes: tuple[Probe, ...] = ()
    thermal: Thermal
    mesh: MeshSettings = MeshSettings()

    @model_validator(mode="after")
    def _consistent(self):
        # Raised as (field path, message) so the loader can name the offending field.
        half_w, half_d = self.ram.outer_width_mm / 2, self.ram.outer_depth_mm / 2
        names = [s.name for s in self.sensors]
        for i, s in enumerate(self.sensors):
            if names.count(s.name) > 1:
                raise _FieldError(f"sensors[{i}].name", f"duplicate sensor name {s.name!r}")
        probe_names = [p.name for p in self.probes]
        for i, p in enumerate(self.probes):
            if probe_names.count(p.name) > 1:
                raise _FieldError(f"probes[{i}].name", f"duplicate probe name {p.name!r}")
            if p.kind == "point" and not self.contains_point(p.x_mm, p.y_mm, p.z_mm):
                raise _FieldError(f"probes[{i}]", f"probe {p.name!r} at ({p.x_mm:g}, {p.y_mm:g}, "
                                  f"{p.z_mm:g}) mm is not inside the ram wall or the housing")
        for group in ("sensors", "candidate_sensors"):
            for i, s in enumerate(getattr(self, group)):
                across = half_d if s.face[1] == "X" else half_w
                if abs(s.offset_mm) > across:
                    raise _FieldError(f"{group}[{i}].offset_mm",
                                      f"offset {s.offset_mm:g} mm lies off the {s.face} face")
                if s.z_start_mm < 0 or s.z_end_mm > self.ram.length_mm:
                    raise _FieldError(f"{group}[{i}].z_end_mm" if s.z_end_mm > self.ram.length_mm
                                      else f"{group}[{i}].z_start_mm",
                                      f"path must lie on the ram, 0..{self.ram.length_mm:g} mm")
                if s.temperature_probe is not None and s.temperature_probe not in probe_names:
                    raise _FieldError(f"{group}[{i}].temperature_probe",
                                      f"unknown probe {s.temperature_probe!r}; known: {probe_names}")
        for i, c in enumerate(self.supports.carriages):
            z = c.z_mm - self.supports.z_axis_mm
            if not (self.supports.shoe_length_mm / 2 <= z
                    <= self.ram.length_mm - self.supports.shoe_length_mm / 2):
                raise _FieldError(f"supports.carriages[{i}].z_mm",
                                  f"carriage station at z = {z:g} mm in the ram frame lies off the ram")
        if self.supports.carriages[0].z_mm == self.supports.carriages[1].z_mm:
            raise _FieldError("supports.carriages[1].z_mm", "the two carriage stations must differ")
        if not (0 < self.supports.nut.z_mm <= self.ram.length_mm):
            raise _FieldError("supports.nut.z_mm", "the nut must be on the ram")
        return self

    def contains_point(self, x_mm: float, y_mm: float, z_mm: float, tol_mm: float = 1e-6) -> bool:
        """True when the point lies in the ram wall or the housing (boundary included)."""
        r, h = self.ram, self.housing
        ax, ay = abs(x_mm), abs(y_mm)
        if -h.height_mm - tol_mm <= z_mm <= 0:
            if ax <= h.width_mm / 2 + tol_mm and ay <= h.depth_mm / 2 + tol_mm:
                return True
        if 0 <= z_mm <= r.length_mm + tol_mm:
            inside_outer = ax <= r.outer_width_mm / 2 + tol_mm and ay <= r.outer_depth_mm / 2 + tol_mm
            in_cavity = (ax < r.outer_width_mm / 2 - r.wall_mm - tol_mm
                         and ay < r.outer_depth_mm / 2 - r.wall_mm - tol_mm)
            return inside_outer and not in_cavity
        return False

    @property
    def ttp_z_mm(self) -> float:
        """z of the tool tip point in the ram frame (mm)."""
        return -self.housing.height_mm - self.tool.ttp_below_housing_mm

    def with_z_axis(self, z_axis_mm: float) -> "Machine":
        """The same machine with the Z axis at ``z_axis_mm`` (carriages move along the ram)."""
        return self.model_copy(update={"supports": self.supports.model_copy(
            update={"z_axis_mm": float(z_axis_mm)})})


class _FieldError(ValueError):
    def __init__(self, field: str, message: str):
        super().__init__(message)
        self.field = field
        self.message = message


def _field_path(loc) -> str:
    out = ""
    for part in loc:
        if isinstance(part, int):
            out += f"[{part}]"
        else:
            out += ("." if out else "") + str(part)
    return out


def _default_path():
    return importlib.resources.files("fbgcomp") / "data" / "ram.yaml"


def parse_machine(data, file: str | Path | None = None) -> Machine:
    """Validate an already-parsed mapping as a :class:`Machine` (errors name file and field)."""
    if not isinstance(data, dict):
        raise InputError("the machine description must be a YAML mapping", file=file)
    try:
        return Machine.model_validate(data)
    except ValidationError as exc:
        err = exc.errors()[0]
        ctx_error = (err.get("ctx") or {}).get("error")
        if isinstance(ctx_error, _FieldError):
            raise InputError(ctx_error.message, file=file, column=f"field {ctx_error.field}") from None
        path = _field_path(err["loc"])
        msg = err["msg"].removeprefix("Value error, ")
        if err["type"] == "missing":
            msg = "required field is missing"
        elif err["type"] == "extra_forbidden":
            msg = "unknown field (check the spelling against data/ram.yaml)"
        raise InputError(msg, file=file, column=f"field {path}" if path else None) from None


def load_machine(path: str | Path | None = None) -> Machine:
    """Load and validate a machine description; ``None`` loads the embedded default ram."""
    if path is None:
        resource = _default_path()
        text = resource.read_text(encoding="utf-8")
        file = str(resource)
    else:
        file = str(path)
        try:
            text = Path(path).read_text(encoding="utf-8")
        except OSError as exc:
            raise InputError(f"cannot read machine description: {exc.strerror}", file=file) from None
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark else ""
        raise InputError(f"invalid YAML{where}: {getattr(exc, 'problem', exc)}", file=file) from None
    return parse_machine(data, file=file)
