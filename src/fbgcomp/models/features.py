"""Regressors of the TTP-deviation models (paper eq. 11-13), as pure array functions.

Base features, all relative to the zero state:

* ``dL_<sensor>``: the sensor path's elongation in µm (optics, eq. 2-4), temperature-compensated
  with the sensor's assigned probe when it has one;
* ``dT_bulk``: change of the bulk temperature since the zero state, K;
* ``dT_surf``: change of (bulk - surface) temperature, K;
* ``dT_flange``: change of (flange - bulk) temperature, K (paper sec. 3.2, eq. 13).

Feature sets (each TTP axis gets its own coefficients; a constant term always comes first):

* ``eq11``: constant + dL of every sensor (paper eq. 11);
* ``eq13``: eq11 + dT_bulk, dT_surf, dT_flange (paper eq. 13);
* ``eq12``: eq11 + the quadratic thermal form ``A1'·dT + dT'·A2·dT`` over the three temperature
  features: linear terms, squares and pairwise products (paper eq. 12). The paper adds the
  thermal form to the geometric (elongation) part, so eq12 keeps the elongations.

A term is a product of base features, named ``dL_S1``, ``dT_bulk^2`` or ``dT_bulk*dT_surf``.
The same functions build the design for a 36 h campaign and for one runtime frame.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from itertools import combinations_with_replacement

import numpy as np

from fbgcomp import optics

CONSTANT = "const"
TEMPERATURE_FEATURES = ("dT_bulk", "dT_surf", "dT_flange")
FEATURE_SETS = ("eq11", "eq12", "eq13")


@dataclass(frozen=True)
class TemperatureRoles:
    """Which probe plays which role in the eq. 13 temperature features."""

    bulk: str = "T_bulk"
    surf: str = "T_surf"
    flange: str = "T_flange"

    def as_dict(self) -> dict:
        """The roles as ``{"bulk": probe, "surf": probe, "flange": probe}``."""
        return {"bulk": self.bulk, "surf": self.surf, "flange": self.flange}


#: Name keys of each role, used when a campaign's probes do not carry the paper's names; probes
#: whose name holds an ``AMBIENT_KEYS`` key (or the description's ambient probes) play none.
ROLE_KEYS = {
    "flange": ("flange", "housing", "spindle", "bearing", "head"),
    "bulk": ("bulk", "wall", "core", "mid", "inner", "inside"),
    "surf": ("surf", "skin", "outer", "face"),
}
AMBIENT_KEYS = ("amb", "air", "room", "hall", "env")


def resolve_roles(probe_names, machine=None) -> TemperatureRoles:
    """The probes that play eq. 13's bulk, surface and flange roles for a campaign's probes.

    The paper's names (``T_bulk``, ``T_surf``, ``T_flange``) where the campaign has them. A role
    whose paper name is missing goes to a free probe that fits it: with a machine description,
    by position (a point probe in or on the housing, the one nearest its centre, for the flange;
    one inside the ram's wall for the bulk; one on its outer surface for the surface), else by
    name (:data:`ROLE_KEYS`).
    A role still open takes what is left in the campaign's order, a probe on the ram before
    one in the housing for the bulk and the surface, and the air (the description's ambient
    probe, else a name in :data:`AMBIENT_KEYS`) only as the last resort: a ram without a
    housing probe still gets eq. 13's three features. Raises ``ValueError`` when the campaign
    has fewer than three probes.
    """
    names = list(probe_names)
    default = TemperatureRoles().as_dict()
    if all(p in names for p in default.values()):
        return TemperatureRoles()
    desc = {p.name: p for p in machine.probes} if machine is not None else {}
    # the housing probes nearest the housing's centre first, as every model ranks them
    housing = machine.housing_probe_names() if machine is not None else []

    def ambient(n):
        d = desc.get(n)
        return d.kind == "ambient" if d is not None else any(k in n.lower() for k in AMBIENT_KEYS)

    def where(n):
        """'housing', 'inside' (the ram wall), 'surface' or None (not described)."""
        d = desc.get(n)
        if d is None or d.kind != "point":
            return None
        if n in housing:
            return "housing"
        half_w, half_d = machine.ram.outer_width_mm / 2, machine.ram.outer_depth_mm / 2
        on_face = min(half_w - abs(d.x_mm), half_d - abs(d.y_mm)) <= 1e-6
        return "surface" if on_face else "inside"

    place = {"flange": "housing", "bulk": "inside", "surf": "surface"}
    chosen = {r: p for r, p in default.items() if p in names}
    free = [n for n in names if n not in chosen.values()]
    solid = [n for n in free if not ambient(n)]
    # first by position in the description, then by name; then what is left: for the bulk and
    # the surface a probe on the ram before one in the housing, the air last for every role
    for role in ("flange", "bulk", "surf"):
        if role in chosen:
            continue
        fits = [n for n in solid if where(n) == place[role]]
        if role == "flange":
            fits.sort(key=housing.index)
        fits += [n for n in solid if any(k in n.lower() for k in ROLE_KEYS[role])]
        pick = next((n for n in fits if n not in chosen.values()), None)
        if pick is not None:
            chosen[role] = pick
    for role in ("bulk", "surf", "flange"):
        if role in chosen:
            continue
        left = [n for n in free if n not in chosen.values()]
        ranked = sorted(left, key=lambda n: (ambient(n), role != "flange" and where(n) == "housing"))
        if not ranked:
            raise ValueError(
                f"no temperature probe is left for the {role} role of eq. 13 among "
                f"{', '.join(names) or 'none'} (name them with --roles bulk=..,surf=..,flange=.., "
                "or use --features eq11)"
            )
        chosen[role] = ranked[0]
    return TemperatureRoles(**chosen)


def term_name(factors: tuple[str, ...]) -> str:
    """Name of a product term: ``('dT_bulk', 'dT_bulk') -> 'dT_bulk^2'``."""
    if len(factors) == 2 and factors[0] == factors[1]:
        return f"{factors[0]}^2"
    return "*".join(factors)


def parse_term(name: str) -> tuple[str, ...]:
    """Inverse of :func:`term_name`."""
    if name.endswith("^2"):
        base = name[:-2]
        return (base, base)
    return tuple(name.split("*"))


def candidate_terms(feature_set: str, sensor_names) -> list[str]:
    """Names of the candidate terms of a feature set, constant excluded, in model order."""
    if feature_set not in FEATURE_SETS:
        raise ValueError(f"unknown feature set {feature_set!r}; expected one of {', '.join(FEATURE_SETS)}")
    terms = [f"dL_{s}" for s in sensor_names]
    if feature_set in ("eq12", "eq13"):
        terms += list(TEMPERATURE_FEATURES)
    if feature_set == "eq12":
        terms += [term_name(p) for p in combinations_with_replacement(TEMPERATURE_FEATURES, 2)]
    return terms


def as_frames(a) -> np.ndarray:
    """(n, k) float64 of one frame (k,) or of frames (n, k); an array that already is one is
    returned as it is (the runtime passes such arrays once per frame)."""
    if isinstance(a, np.ndarray) and a.ndim == 2 and a.dtype == np.float64:
        return a
    return np.atleast_2d(np.asarray(a, dtype=float))


@dataclass
class FeatureMap:
    """Compiled map from raw instrument arrays to base features and model terms.

    Built once from sensor metadata (a model file or a campaign); then :meth:`base` and
    :meth:`design` are cheap, vectorised and free of pandas, so the runtime can call them per
    batch of frames.

    Parameters
    ----------
    sensors : list of SensorSpec-like
        Objects with ``name``, ``gauge_length_mm``, ``photoelastic``, ``thermo_optic_per_K``,
        ``fibre_cte_per_K`` and ``temperature_probe`` (None for uncompensated sensors).
    probe_names : list of str
        Column order of the temperature arrays passed in.
    uses_temperature_features : bool
        Whether dT_bulk, dT_surf, dT_flange are computed (eq12, eq13).
    roles : TemperatureRoles
    """

    sensors: list
    probe_names: list
    uses_temperature_features: bool
    roles: TemperatureRoles = field(default_factory=TemperatureRoles)

    def __post_init__(self):
        self.sensor_names = [s.name for s in self.sensors]
        self._gauge_mm = np.array([s.gauge_length_mm for s in self.sensors], dtype=float)
        self._pe = np.array([s.photoelastic for s in self.sensors], dtype=float)
        self._xi = np.array([s.thermo_optic_per_K for s in self.sensors], dtype=float)
        self._af = np.array([s.fibre_cte_per_K for s in self.sensors], dtype=float)
        index = {p: i for i, p in enumerate(self.probe_names)}
        missing = [
            s.temperature_probe
            for s in self.sensors
            if s.temperature_probe is not None and s.temperature_probe not in index
        ]
        if self.uses_temperature_features:
            missing += [p for p in self.roles.as_dict().values() if p not in index]
        if missing:
            raise KeyError(f"temperature probe(s) not available: {', '.join(dict.fromkeys(missing))}")
        # Sensors without a probe get dT = 0 (uncompensated): index a column of zeros.
        self._sensor_probe = np.array(
            [index.get(s.temperature_probe, -1) if s.temperature_probe else -1 for s in self.sensors]
        )
        self._compensated = self._sensor_probe >= 0
        # base(): the column of each sensor's probe in the temperature changes, the last
        # (always 0) for an uncompensated sensor; the fibre constants as eq. 2-3 combine them
        self._sensor_col = np.where(self._compensated, self._sensor_probe, len(self.probe_names))
        self._af_plus_xi = self._af + self._xi
        self._one_minus_pe = 1.0 - self._pe
        if self.uses_temperature_features:
            self._roles = (index[self.roles.bulk], index[self.roles.surf], index[self.roles.flange])
        self.base_names = [f"dL_{s}" for s in self.sensor_names]
        if self.uses_temperature_features:
            self.base_names += list(TEMPERATURE_FEATURES)
        self._width = len(self.base_names)  # of base(); a subclass may append its own after it

    @staticmethod
    def required_probes(sensors, uses_temperature_features: bool, roles: TemperatureRoles) -> list[str]:
        """Probes a model needs, in a stable order: sensor probes first, then roles."""
        names = [s.temperature_probe for s in sensors if s.temperature_probe]
        if uses_temperature_features:
            names += [roles.bulk, roles.surf, roles.flange]
        return list(dict.fromkeys(names))

    def base(self, wavelength_nm, temperature_C, wavelength_zero_nm, temperature_zero_C):
        """Base features (n, B) in ``base_names`` order: elongations in µm, temperatures in K.

        The elongations are :func:`fbgcomp.optics.elongation_um` (eq. 2-4) with each sensor's
        probe, operation for operation (the same bits, tested), written in place into one
        output with the fibre constants combined once: the runtime calls this per frame, where
        numpy's per-call cost, not the arithmetic, is the time. The temperature features are
        eq. 13's (dT_bulk, dT_bulk - dT_surf, dT_flange - dT_bulk)."""
        w = as_frames(wavelength_nm)
        n, S = w.shape[0], self._gauge_mm.size
        w0 = np.asarray(wavelength_zero_nm, dtype=float)
        out = np.empty((n, self._width))
        dl = out[:, :S]
        np.subtract(w, w0, out=dl)
        dl /= w0  # the relative shift
        P = len(self.probe_names)
        if P:
            t = as_frames(temperature_C)
            delta = np.empty((n, P + 1))  # the last column: dT = 0 of uncompensated sensors
            np.subtract(t, temperature_zero_C, out=delta[:, :P])
            delta[:, P] = 0.0
            dt = delta[:, self._sensor_col]
            dl -= self._af_plus_xi * dt
            dl /= self._one_minus_pe
            dl += self._af * dt
        else:  # no probe: every sensor uncompensated (dT = 0)
            dl /= self._one_minus_pe
        dl *= self._gauge_mm
        dl *= optics._UM_PER_MM
        if self.uses_temperature_features:
            b, s, f = self._roles
            out[:, S] = delta[:, b]
            np.subtract(delta[:, b], delta[:, s], out=out[:, S + 1])
            np.subtract(delta[:, f], delta[:, b], out=out[:, S + 2])
        return out


def design_matrix(base, base_names, terms) -> np.ndarray:
    """Design matrix (n, 1 + len(terms)): a constant column, then each product term.

    Parameters
    ----------
    base : ndarray, shape (n, B)
        Base features in ``base_names`` order.
    terms : list of str
        Term names (see :func:`term_name`), constant excluded.
    """
    base = np.atleast_2d(np.asarray(base, dtype=float))
    index = {name: i for i, name in enumerate(base_names)}
    out = np.empty((base.shape[0], 1 + len(terms)))
    out[:, 0] = 1.0
    for j, term in enumerate(terms, start=1):
        factors = parse_term(term)
        try:
            col = base[:, index[factors[0]]].copy()
            for f in factors[1:]:
                col *= base[:, index[f]]
        except KeyError as exc:
            raise KeyError(f"term {term!r} needs base feature {exc.args[0]!r}") from None
        out[:, j] = col
    return out
