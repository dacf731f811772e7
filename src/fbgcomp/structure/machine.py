"""Machine description: the CFRP ram, its housing, materials, supports, FBG paths and probes.

Over 600 lines as one unit: the pydantic schema of a machine description, whose validators check the
parts against each other.

Read from YAML (``load_machine``) and validated with pydantic v2; every problem is raised as
:class:`fbgcomp.errors.InputError` naming the file and the field (``field sensors[2].lambda0_nm``).
Geometry follows the paper's prototype (sections 2.3-2.4): ram axis along Z, z = 0 at the spindle
end, the housing below (z < 0), the TTP on the axis below the housing.
"""

from __future__ import annotations

import importlib.resources
from pathlib import Path
from typing import Annotated, Literal

import numpy as np
import yaml
from pydantic import (
    AliasChoices,
    BaseModel,
    BeforeValidator,
    ConfigDict,
    Field,
    ValidationError,
    field_validator,
    model_validator,
)

from fbgcomp.errors import InputError

Face = Literal["+X", "-X", "+Y", "-Y"]


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


#: The ram's four outer faces, in the order every per-face table of the package uses.
FACES: tuple[Face, ...] = ("+X", "-X", "+Y", "-Y")


def walls_per_face(wall_mm) -> dict[str, float]:
    """Each face's wall thickness (mm) from one thickness or a mapping of the four faces."""
    if isinstance(wall_mm, dict):
        return {f: float(wall_mm[f]) for f in FACES}
    return dict.fromkeys(FACES, float(wall_mm))


def cavity_bounds_mm(
    half_width_mm: float, half_depth_mm: float, walls_mm
) -> tuple[float, float, float, float]:
    """The box cavity's bounds (x_lo, x_hi, y_lo, y_hi), mm, of an outer section centred on the
    axis whose walls (:func:`walls_per_face`) each run in from their outer face."""
    w = walls_per_face(walls_mm)
    return (
        float(-half_width_mm + w["-X"]),
        float(half_width_mm - w["+X"]),
        float(-half_depth_mm + w["-Y"]),
        float(half_depth_mm - w["+Y"]),
    )


class Ram(_Strict):
    """The ram: a hollow CFRP box, its outer section, wall thickness and length (mm).

    ``wall_mm`` is one thickness for every wall, or one per face (``{"+X": 22, "-X": 22, "+Y": 14,
    "-Y": 14}``: a data sheet's thicker rail faces), each measured in from its outer face; the
    outer section stays centred on the ram axis and the cavity moves with the walls.
    """

    outer_width_mm: float = Field(gt=0)
    outer_depth_mm: float = Field(gt=0)
    wall_mm: float | dict[Face, float]
    length_mm: float = Field(gt=0)

    @field_validator("wall_mm", mode="before")
    @classmethod
    def _thickness(cls, v):
        def one(value, where: str) -> float:
            if isinstance(value, bool) or not isinstance(value, int | float) or not value > 0:
                raise ValueError(f"{where} must be a thickness in mm greater than 0, got {value!r}")
            return float(value)

        if isinstance(v, dict):
            unknown = [k for k in v if k not in FACES]
            if unknown:
                raise ValueError(f"unknown face {unknown[0]!r}; a wall per face names +X, -X, +Y and -Y")
            missing = [f for f in FACES if f not in v]
            if missing:
                raise ValueError(f"a wall per face names all four faces +X, -X, +Y, -Y; missing {missing}")
            return {f: one(v[f], f"the {f} wall") for f in FACES}
        return one(v, "the wall")

    @model_validator(mode="after")
    def _wall_fits(self):
        w = self.walls_mm
        if w["+X"] + w["-X"] >= self.outer_width_mm or w["+Y"] + w["-Y"] >= self.outer_depth_mm:
            raise _FieldError(
                "ram.wall_mm",
                "the walls of opposite faces must leave a cavity: each pair thinner than the outer "
                "width (+-X) or depth (+-Y) (hollow box)",
            )
        return self

    @property
    def walls_mm(self) -> dict[str, float]:
        """Thickness (mm) of each face's wall."""
        return walls_per_face(self.wall_mm)

    @property
    def cavity_mm(self) -> tuple[float, float, float, float]:
        """The cavity's bounds (x_lo, x_hi, y_lo, y_hi), mm, in the ram's section frame."""
        return cavity_bounds_mm(self.outer_width_mm / 2, self.outer_depth_mm / 2, self.wall_mm)


class Housing(_Strict):
    """The solid steel spindle housing below the ram: its block size (mm)."""

    width_mm: float = Field(gt=0)
    depth_mm: float = Field(gt=0)
    height_mm: float = Field(gt=0)


class Tool(_Strict):
    """The rigid tool: how far the TTP sits below the housing and the nose patch that carries it (mm)."""

    ttp_below_housing_mm: float = Field(ge=0)
    # Size (x, y) of the central spindle-nose patch of the housing bottom face that carries the
    # rigid tool; None: the whole bottom face.
    nose_patch_mm: tuple[float, float] | None = None

    @model_validator(mode="after")
    def _positive_patch(self):
        if self.nose_patch_mm is not None and min(self.nose_patch_mm) <= 0:
            raise ValueError("nose_patch_mm must be two positive sizes (x, y)")
        return self


class CFRP(_Strict):
    """The ram's CFRP, transversely isotropic with the fibres along Z: moduli (GPa), Poisson ratios,
    expansion (per K), conductivity, density and specific heat."""

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
    """The housing's steel, isotropic: modulus (GPa), Poisson ratio, expansion (per K), conductivity,
    density and specific heat."""

    E_GPa: float = Field(gt=0)
    nu: float = Field(gt=-1, lt=0.5)
    cte_per_K: float
    k_W_per_mK: float = Field(gt=0)
    density_kg_per_m3: float = Field(gt=0)
    specific_heat_J_per_kgK: float = Field(gt=0)


class Materials(_Strict):
    """The two materials: the ram's CFRP and the housing's metal, whatever it is (steel, cast
    iron, aluminium). The YAML names the housing's ``housing`` or, as descriptions written before
    that name did, ``steel``; in code it is ``steel`` either way."""

    cfrp: CFRP
    steel: Steel = Field(validation_alias=AliasChoices("housing", "steel"))

    @model_validator(mode="before")
    @classmethod
    def _one_housing(cls, data):
        if isinstance(data, dict) and "housing" in data and "steel" in data:
            raise ValueError("give the housing's material once, as `housing` (`steel` is its older name)")
        return data


def _stiffness(v):
    if v == "rigid":
        return v
    try:
        k = float(v)  # YAML reads 1.0e6 (no sign in the exponent) as a string
    except (TypeError, ValueError):
        k = float("nan")
    if isinstance(v, bool) or not k > 0:
        raise ValueError("must be a stiffness > 0 (N/um) or 'rigid'")
    return k


Stiffness = Annotated[float | Literal["rigid"], BeforeValidator(_stiffness)]


def _ordered_range(v, what: str):
    if v is not None and not v[1] > v[0]:
        raise ValueError(f"{what} must be [low, high] with high > low")
    return v


class Carriage(_Strict):
    """A carriage (guide-shoe) station: its centre ``z_mm`` or its extent ``z_range_mm``."""

    name: str
    z_mm: float | None = None
    z_range_mm: tuple[float, float] | None = None

    @model_validator(mode="before")
    @classmethod
    def _centre_from_range(cls, data):
        if isinstance(data, dict) and data.get("z_mm") is None and data.get("z_range_mm"):
            lo, hi = data["z_range_mm"]
            if isinstance(lo, (int, float)) and isinstance(hi, (int, float)):
                data = {**data, "z_mm": 0.5 * (lo + hi)}
        return data

    @field_validator("z_range_mm")
    @classmethod
    def _range(cls, v):
        return _ordered_range(v, "z_range_mm")

    @model_validator(mode="after")
    def _located(self):
        if self.z_mm is None:
            raise ValueError("a carriage needs z_mm or z_range_mm")
        if self.z_range_mm is not None and abs(self.z_mm - 0.5 * sum(self.z_range_mm)) > 1e-6:
            raise ValueError("z_mm must be the centre of z_range_mm (give one of them)")
        return self


class Rail(_Strict):
    """A guide rail along Z on one outer face; ``across_mm`` is its strip across the face
    (y on the +-X faces, x on the +-Y faces).

    A locating rail holds both directions of the cross-section at its carriages: the face normal
    and the in-plane lateral one (across the face). A floating rail releases one of them,
    ``floats``: ``across`` (the default) holds the face normal only, as the second rail on the
    same face does (ram2's); ``normal`` holds across the face only, as the second of two rails
    on opposite faces whose carriages let the box grow towards them (a floating bearing)."""

    face: Face
    across_mm: tuple[float, float]
    locating: bool = False
    floats: Literal["across", "normal"] | None = None

    @field_validator("across_mm")
    @classmethod
    def _strip(cls, v):
        return _ordered_range(v, "across_mm")

    @model_validator(mode="after")
    def _one_meaning(self):
        if self.locating and self.floats is not None:
            raise ValueError("a locating rail floats in no direction: drop floats or set locating: false")
        return self

    @property
    def held_axes(self) -> tuple[int, ...]:
        """The directions its carriages hold: 0 = X, 1 = Y (the face normal first)."""
        normal = 0 if self.face[1] == "X" else 1
        if self.locating:
            return (normal, 1 - normal)
        return (1 - normal,) if self.floats == "normal" else (normal,)


class Nut(_Strict):
    """The ball-screw nut: its z (mm), axial stiffness (N/µm or ``rigid``) and how it holds the
    cross-section."""

    z_mm: float
    stiffness_N_per_um: Stiffness
    # mean: one spring on the mean u_z of the cross-section at z_mm; nodes: u_z held at every
    # node of that cross-section (e.g. a bracket bonded to the whole top ring face).
    constraint: Literal["mean", "nodes"] = "mean"


class Supports(_Strict):
    """How the ram is held: guide shoes or rails, the carriage stations and their stiffness (N/µm),
    the nut."""

    z_axis_mm: float = 0.0
    shoe_faces: tuple[Face, Face] = ("+X", "-X")
    rails: tuple[Rail, ...] | None = None
    carriages: tuple[Carriage, ...] = Field(min_length=2)
    shoe_length_mm: float | None = Field(default=None, gt=0)
    shoe_width_mm: float | None = Field(default=None, gt=0)
    carriage_stiffness_N_per_um: Stiffness
    nut: Nut

    @model_validator(mode="after")
    def _consistent_supports(self):
        for i, c in enumerate(self.carriages):
            if c.z_range_mm is None and self.shoe_length_mm is None:
                raise _FieldError(
                    f"supports.carriages[{i}].z_range_mm",
                    "give the station's z_range_mm or supports.shoe_length_mm",
                )
        if self.rails is None:
            a, b = self.shoe_faces
            if a[1] != b[1] or a == b:
                raise _FieldError(
                    "supports.shoe_faces", "shoe_faces must be two opposite faces, e.g. ['+X', '-X']"
                )
            if len(self.carriages) != 2:
                raise _FieldError(
                    "supports.carriages",
                    "shoe_faces supports take exactly two carriage stations; give rails for more",
                )
            if self.shoe_width_mm is None:
                raise _FieldError(
                    "supports.shoe_width_mm", "required field is missing (or describe the guides with rails)"
                )
            return self
        if not self.rails:
            raise _FieldError("supports.rails", "give at least one rail")
        holds = {"X": False, "Y": False}
        for r in self.rails:
            for axis in r.held_axes:
                holds["XY"[axis]] = True
        for axis, held in holds.items():
            if not held:
                raise _FieldError(
                    "supports.rails",
                    f"no rail holds the ram along {axis}: add a "
                    f"rail on a +-{axis} face or make a rail on the other faces locating",
                )
        return self

    @property
    def carriage_stiffness_value_N_per_um(self) -> float:
        """Carriage stiffness (N/µm) as a number: ``inf`` for rigid carriages."""
        k = self.carriage_stiffness_N_per_um
        return float("inf") if k == "rigid" else float(k)

    def station_ranges_mm(self, z_axis_mm: float | None = None) -> list[tuple[float, float]]:
        """Carriage patch z ranges in the ram frame at Z-axis position ``z_axis_mm``, by station."""
        z_axis = self.z_axis_mm if z_axis_mm is None else z_axis_mm
        out = []
        for c in self.carriages:
            if c.z_range_mm is not None:
                lo, hi = c.z_range_mm
            else:
                # Carriage._located requires z_mm; Supports._consistent_supports requires
                # shoe_length_mm for a carriage without z_range_mm
                assert c.z_mm is not None and self.shoe_length_mm is not None
                lo, hi = c.z_mm - self.shoe_length_mm / 2, c.z_mm + self.shoe_length_mm / 2
            out.append((lo - z_axis, hi - z_axis))
        return out


class Sensor(_Strict):
    """One FBG path in a ram wall, along z: its face, position across the face, depth into the
    wall and end points along z (mm), nominal wavelength (nm), optical and fibre coefficients, its
    temperature probe."""

    name: str = Field(min_length=1)
    face: Face
    offset_mm: float = 0.0
    #: distance from the face's outer surface into the wall, mm: 0 bonded on the outer surface,
    #: the wall thickness on the inner (cavity) surface, in between embedded in the laminate
    depth_mm: float = Field(default=0.0, ge=0)
    z_start_mm: float
    z_end_mm: float
    lambda0_nm: float = Field(gt=0)
    photoelastic: float = Field(ge=0, lt=1)
    thermo_optic_per_K: float
    fibre_cte_per_K: float
    temperature_probe: str | None = None
    gauge_length_mm: float | None = Field(default=None, gt=0)
    #: nominal wavelength of a strain-free reference grating beside the sensor (same gauge
    #: temperature, no strain), as real installations carry for temperature compensation
    reference_lambda0_nm: float | None = Field(default=None, gt=0)

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
    """One temperature probe: a point in the ram wall or the housing (mm), or the ambient air."""

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


FilmSurface = Literal["+X", "-X", "+Y", "-Y", "cavity", "top", "housing_sides", "housing_bottom"]
FILM_SURFACES: tuple[str, ...] = ("+X", "-X", "+Y", "-Y", "cavity", "top", "housing_sides", "housing_bottom")


class HeatSource(_Strict):
    """A heat input of the thermal model, one input channel of the twin.

    volume: power (W) spread uniformly over the box zone x_mm, y_mm, z_mm (each [low, high]; an
    omitted range spans the housing). radiant: flux (W/m^2) on ``face`` for z in ``z_mm``
    (omitted: the whole ram face), times ``absorptivity``.
    """

    name: str = Field(min_length=1, pattern=r"^[A-Za-z_][A-Za-z0-9_]*$")
    kind: Literal["volume", "radiant"]
    x_mm: tuple[float, float] | None = None
    y_mm: tuple[float, float] | None = None
    z_mm: tuple[float, float] | None = None
    face: Face | None = None
    absorptivity: float = Field(default=1.0, ge=0, le=1)
    nominal_W: float | None = Field(default=None, ge=0)
    nominal_W_per_m2: float | None = Field(default=None, ge=0)

    @field_validator("x_mm", "y_mm", "z_mm")
    @classmethod
    def _ranges(cls, v, info):
        return _ordered_range(v, info.field_name)

    @model_validator(mode="after")
    def _kind_fields(self):
        if self.kind == "volume":
            if self.face is not None or self.nominal_W_per_m2 is not None:
                raise ValueError(
                    "a volume source takes x_mm, y_mm, z_mm and nominal_W (no face, no nominal_W_per_m2)"
                )
        else:
            if self.face is None:
                raise ValueError("a radiant source needs its face")
            if self.x_mm is not None or self.y_mm is not None or self.nominal_W is not None:
                raise ValueError(
                    "a radiant source takes face, z_mm, absorptivity and "
                    "nominal_W_per_m2 (no x_mm, y_mm, nominal_W)"
                )
        return self

    @property
    def in_housing(self) -> bool:
        """A volume source whose zone lies in the steel housing: its z range at or below the
        flange face (z <= 0), or omitted (it then spans the housing)."""
        return self.kind == "volume" and (self.z_mm is None or self.z_mm[1] <= 0.0)

    @property
    def input_name(self) -> str:
        """Name of the twin's input channel: ``<name>_W`` or ``<name>_W_per_m2``."""
        return f"{self.name}_W" if self.kind == "volume" else f"{self.name}_W_per_m2"

    @property
    def nominal(self) -> float:
        """The source's typical input (W for a volume source, W/m² for a radiant one; 0 when not given)."""
        v = self.nominal_W if self.kind == "volume" else self.nominal_W_per_m2
        return 0.0 if v is None else float(v)


class Thermal(_Strict):
    """The thermal model's boundary conditions: film coefficients (W/(m² K)) by surface and the heat
    sources."""

    film_outer_W_per_m2K: float | None = Field(default=None, gt=0)
    film_inner_W_per_m2K: float | None = Field(default=None, ge=0)
    films_W_per_m2K: dict[FilmSurface, float] = {}
    heat_sources: tuple[HeatSource, ...] | None = None
    spindle_heat: Literal["housing"] = "housing"
    radiant_face: Face = "+X"
    radiant_absorptivity: float = Field(default=0.9, ge=0, le=1)
    nominal_spindle_heat_W: float = Field(default=150.0, ge=0)
    nominal_radiant_W_per_m2: float = Field(default=40.0, ge=0)

    @model_validator(mode="after")
    def _films_complete(self):
        for surface, h in self.films_W_per_m2K.items():
            if not h >= 0:
                raise _FieldError(f"thermal.films_W_per_m2K.{surface}", "must be >= 0")
        for surface in FILM_SURFACES:
            if self.film_W_per_m2K(surface) is None:
                fallback = "film_inner_W_per_m2K" if surface == "cavity" else "film_outer_W_per_m2K"
                raise _FieldError(
                    f"thermal.films_W_per_m2K.{surface}",
                    f"no film coefficient for {surface!r}: give it or {fallback}",
                )
        if self.heat_sources is not None:
            names = [h.name for h in self.heat_sources]
            for i, n in enumerate(names):
                if n in names[:i]:
                    raise _FieldError(f"thermal.heat_sources[{i}].name", f"duplicate heat source name {n!r}")
        return self

    def film_W_per_m2K(self, surface: str) -> float | None:
        """Film coefficient of one surface (see FILM_SURFACES), falling back to outer/inner."""
        if surface in self.films_W_per_m2K:
            return float(self.films_W_per_m2K[surface])
        return self.film_inner_W_per_m2K if surface == "cavity" else self.film_outer_W_per_m2K

    @property
    def sources(self) -> tuple[HeatSource, ...]:
        """The declared heat sources; by default spindle heat in the whole housing and a radiant
        flux on ``radiant_face`` (inputs ``spindle_heat_W``, ``radiant_W_per_m2``)."""
        if self.heat_sources is not None:
            return self.heat_sources
        return (
            HeatSource(name="spindle_heat", kind="volume", nominal_W=self.nominal_spindle_heat_W),
            HeatSource(
                name="radiant",
                kind="radiant",
                face=self.radiant_face,
                absorptivity=self.radiant_absorptivity,
                nominal_W_per_m2=self.nominal_radiant_W_per_m2,
            ),
        )


class MeshSettings(_Strict):
    """The FE mesh: element counts and length along Z (mm) at resolution 1, the element type, and the
    reduced thermal model's number of expansion points."""

    resolution: float = Field(default=1.0, gt=0, le=8)
    wall_elements: int = Field(default=3, ge=1)
    span_elements: int = Field(default=10, ge=2)
    dz_mm: float = Field(default=20.0, gt=0)
    thermal_shifts: int = Field(default=12, ge=0, le=60)
    # hex8: trilinear hexahedra; hex8i: with condensed incompatible modes (like C3D8I), which do
    # not lock in bending and need no mesh refinement for thin plate-bending walls. hex8i is the
    # default: a description written from a data sheet has no mesh section, and with hex8 the
    # twin of ram2 came out 9.6 % too stiff in X (docs/twin.md). The built-in ram names hex8.
    element: Literal["hex8", "hex8i"] = "hex8i"


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
                raise _FieldError(
                    f"probes[{i}]",
                    f"probe {p.name!r} at ({p.x_mm:g}, {p.y_mm:g}, "
                    f"{p.z_mm:g}) mm is not inside the ram wall or the housing",
                )
        for group in ("sensors", "candidate_sensors"):
            for i, s in enumerate(getattr(self, group)):
                across = half_d if s.face[1] == "X" else half_w
                if abs(s.offset_mm) > across:
                    raise _FieldError(
                        f"{group}[{i}].offset_mm", f"offset {s.offset_mm:g} mm lies off the {s.face} face"
                    )
                wall = self.ram.walls_mm[s.face]
                if s.depth_mm > wall:
                    raise _FieldError(
                        f"{group}[{i}].depth_mm",
                        f"depth {s.depth_mm:g} mm lies beyond the {wall:g} mm wall of the {s.face} face",
                    )
                if s.z_start_mm < 0 or s.z_end_mm > self.ram.length_mm:
                    raise _FieldError(
                        f"{group}[{i}].z_end_mm"
                        if s.z_end_mm > self.ram.length_mm
                        else f"{group}[{i}].z_start_mm",
                        f"path must lie on the ram, 0..{self.ram.length_mm:g} mm",
                    )
                if s.temperature_probe is not None and s.temperature_probe not in probe_names:
                    raise _FieldError(
                        f"{group}[{i}].temperature_probe",
                        f"unknown probe {s.temperature_probe!r}; known: {probe_names}",
                    )
        sup = self.supports
        for i, (lo, hi) in enumerate(sup.station_ranges_mm()):
            if not (lo >= -1e-6 and hi <= self.ram.length_mm + 1e-6):
                raise _FieldError(
                    f"supports.carriages[{i}].z_mm",
                    f"carriage station at z = {lo:g}..{hi:g} mm in the ram frame lies off the ram",
                )
        zc = [c.z_mm for c in sup.carriages]
        for i in range(1, len(zc)):
            if zc[i] in zc[:i]:
                raise _FieldError(f"supports.carriages[{i}].z_mm", "the carriage stations must differ")
        for i, r in enumerate(sup.rails or ()):
            across = half_d if r.face[1] == "X" else half_w
            if r.across_mm[0] < -across - 1e-6 or r.across_mm[1] > across + 1e-6:
                raise _FieldError(
                    f"supports.rails[{i}].across_mm",
                    f"strip {r.across_mm[0]:g}..{r.across_mm[1]:g} mm lies off the "
                    f"{r.face} face (+-{across:g} mm)",
                )
        patch = self.tool.nose_patch_mm
        if patch is not None and (
            patch[0] > self.housing.width_mm + 1e-6 or patch[1] > self.housing.depth_mm + 1e-6
        ):
            raise _FieldError("tool.nose_patch_mm", "the nose patch must fit on the housing bottom")
        for i, h in enumerate(self.thermal.sources):
            self._check_source(i, h)
        if not (0 < self.supports.nut.z_mm <= self.ram.length_mm):
            raise _FieldError("supports.nut.z_mm", "the nut must be on the ram")
        return self

    def _check_source(self, i: int, h) -> None:
        where = f"thermal.heat_sources[{i}]"
        if h.kind == "radiant":
            if h.z_mm is not None and (
                h.z_mm[0] < -self.housing.height_mm - 1e-6 or h.z_mm[1] > self.ram.length_mm + 1e-6
            ):
                raise _FieldError(
                    f"{where}.z_mm",
                    "the radiant zone must lie on the structure, "
                    f"{-self.housing.height_mm:g}..{self.ram.length_mm:g} mm",
                )
            return
        lo, hi = self.volume_source_box_mm(h)
        if hi[2] <= lo[2] or hi[0] <= lo[0] or hi[1] <= lo[1]:
            raise _FieldError(where, f"heat zone of {h.name!r} has no volume in the housing")
        if not self.zone_holds_material(lo, hi):
            raise _FieldError(
                where, f"heat zone {h.name!r} holds no material of the housing or the ram walls"
            )

    def volume_source_box_mm(self, h):
        """(low, high) corners (mm) of a volume heat zone; omitted ranges span the housing."""
        hw, hd, H = self.housing.width_mm / 2, self.housing.depth_mm / 2, self.housing.height_mm
        x = h.x_mm or (-hw, hw)
        y = h.y_mm or (-hd, hd)
        z = h.z_mm or (-H, 0.0)
        return np.array([x[0], y[0], z[0]], float), np.array([x[1], y[1], z[1]], float)

    def zone_holds_material(self, lo_mm, hi_mm) -> bool:
        """True when the box ``lo_mm``..``hi_mm`` (x, y, z corners, mm) overlaps the housing or the
        ram's walls with a volume: a heat zone may span the walls around the cavity (a ring at
        the nut, a motor flange), its centre in the air."""
        lo, hi = np.asarray(lo_mm, float), np.asarray(hi_mm, float)
        r, h = self.ram, self.housing

        def overlap(a_lo, a_hi) -> bool:
            return bool(np.all(np.minimum(hi, a_hi) > np.maximum(lo, a_lo)))

        hw, hd = h.width_mm / 2, h.depth_mm / 2
        if overlap((-hw, -hd, -h.height_mm), (hw, hd, 0.0)):
            return True
        ow, od = r.outer_width_mm / 2, r.outer_depth_mm / 2
        x_lo, x_hi, y_lo, y_hi = r.cavity_mm
        if not overlap((-ow, -od, 0.0), (ow, od, r.length_mm)):
            return False
        # inside the outer box: material unless the zone lies wholly in the cavity
        return not (lo[0] >= x_lo and hi[0] <= x_hi and lo[1] >= y_lo and hi[1] <= y_hi)

    def contains_point(self, x_mm: float, y_mm: float, z_mm: float, tol_mm: float = 1e-6) -> bool:
        """True when the point lies in the ram wall or the housing (boundary included)."""
        r, h = self.ram, self.housing
        ax, ay = abs(x_mm), abs(y_mm)
        if (
            -h.height_mm - tol_mm <= z_mm <= 0
            and ax <= h.width_mm / 2 + tol_mm
            and ay <= h.depth_mm / 2 + tol_mm
        ):
            return True
        if 0 <= z_mm <= r.length_mm + tol_mm:
            inside_outer = ax <= r.outer_width_mm / 2 + tol_mm and ay <= r.outer_depth_mm / 2 + tol_mm
            x_lo, x_hi, y_lo, y_hi = r.cavity_mm
            in_cavity = x_lo + tol_mm < x_mm < x_hi - tol_mm and y_lo + tol_mm < y_mm < y_hi - tol_mm
            return inside_outer and not in_cavity
        return False

    @property
    def point_probe_names(self) -> list[str]:
        """The probes at a point of the structure (not the air), in description order."""
        return [p.name for p in self.probes if p.kind == "point"]

    def housing_probe_names(self, tol_mm: float = 1e-6) -> list[str]:
        """The point probes in or on the steel housing (z <= 0: the flange face at z = 0 counts),
        nearest to the housing's centre first. The one rule every model uses for "the housing
        probe" (eq. 13's flange role, the kinematic chain's steel expansion, the physical model's
        housing transient)."""
        h = self.housing
        found = []
        for p in self.probes:
            if p.kind != "point" or p.x_mm is None or p.y_mm is None or p.z_mm is None:
                continue  # the air (a point probe always has its three coordinates)
            x, y, z = p.x_mm, p.y_mm, p.z_mm
            if z > tol_mm or z < -h.height_mm - tol_mm:
                continue
            if abs(x) > h.width_mm / 2 + tol_mm or abs(y) > h.depth_mm / 2 + tol_mm:
                continue
            found.append((float(np.hypot(np.hypot(x, y), z + h.height_mm / 2)), p.name))
        return [name for _, name in sorted(found, key=lambda f: f[0])]

    @property
    def ttp_z_mm(self) -> float:
        """Z of the tool tip point in the ram frame (mm)."""
        return -self.housing.height_mm - self.tool.ttp_below_housing_mm

    def with_z_axis(self, z_axis_mm: float) -> Machine:
        """The same machine with the Z axis at ``z_axis_mm`` (carriages move along the ram)."""
        return self.model_copy(
            update={"supports": self.supports.model_copy(update={"z_axis_mm": float(z_axis_mm)})}
        )


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
