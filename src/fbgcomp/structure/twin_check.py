"""``fbgcomp twin-check``: the FE twin of a machine against an independent model's figures.

The independent model (e.g. ``../shared/reference/ram2/results.json``, CalculiX C3D8I) reports
the TTP compliance and the sensor elongations per newton of TTP force along X, Y and Z
(``unit_response_um_per_N``: dx, dy, dz, then the sensors, µm/N) and the response to a uniform
+10 K (``checks.uniform10``: ``fe_dx_um``, ``fe_dy_um``, ``fe_dz_um``, ``fe_elong_um``). The twin
is built from the machine description and the same quantities are compared.

Judging: a main component (the TTP displacement along the load, a sensor reading at least a
tenth of the load case's largest sensor reading, the uniform dz) is compared in per cent; a
cross component that small is compared absolutely, against the target times the load case's main
TTP component (TTP rows) or largest sensor reading (sensor rows): a 0.001 µm/kN cross compliance
has no meaningful percentage. Targets: unit-load TTP compliances and sensor responses 3 %,
uniform +10 K dz 2 %; the uniform dx, dy and elongations are reported without a target.

Where the results also carry the response 36 h after a unit step of each heat input
(``unit_thermal_step_responses_at_36h_um``: per input, dx, dy, dz and the sensors in µm; the
optional ``unit_thermal_step_definition`` says what each step is, e.g. "100 W step"), the twin
runs the same steps from rest through its reduced thermal model and each figure is reported
without a target: a transient thermal check of the description's heat sources, films and
materials that the uniform case cannot give. An input is the description's heat source of the
same name (or the one source whose name contains it, or is contained in it: "spindle" for
"spindle_heat"), or the ambient ("ambient"); an input the description has no source for is left
out. The step's size is read from its definition (W, W/m², K), else 100 W for a volume source,
100 W/m² for a radiant one and +1 K for the ambient.
"""

from __future__ import annotations

import json
import re
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from fbgcomp import tables
from fbgcomp.errors import InputError
from fbgcomp.structure import load_machine

UNIT_LOAD_TARGET = 0.03  # relative, unit-load TTP compliances and sensor responses
UNIFORM_DZ_TARGET = 0.02  # relative, uniform +10 K dz
MAIN_SENSOR_FRACTION = 0.1  # a sensor reading below this share of the largest is a cross term
UNIFORM_DT_K = 10.0
PER_KN = 1000.0  # the table shows µm per 1000 N
STEP_HOURS = 36.0  # the unit thermal steps are read 36 h after the step
STEPS_FIELD = "unit_thermal_step_responses_at_36h_um"


@dataclass(frozen=True)
class Reference:
    """The independent model's figures: µm/N per load axis, and the uniform +10 K response (µm)."""

    sensor_names: tuple[str, ...]
    unit_um_per_N: dict  # axis -> (3 + S,) dx, dy, dz, sensors
    uniform_ttp_um: np.ndarray  # (3,)
    uniform_elongation_um: np.ndarray  # (S,)
    # input -> {dx, dy, dz, sensor: µm} 36 h after a unit step, and what each step is
    thermal_steps_um: dict = field(default_factory=dict)
    thermal_step_definitions: dict = field(default_factory=dict)


@dataclass(frozen=True)
class Row:
    """One compared quantity: both figures, their difference in % (None when the independent
    figure is 0), the target as shown, how it was judged and whether it passed (None: reported)."""

    quantity: str
    independent: float
    twin: float
    difference_pct: float | None
    target: str
    judged: str  # "relative", "absolute" or "report"
    passed: bool | None


def _field(data, path: str, file: str):
    node = data
    for part in path.split("."):
        if not isinstance(node, dict) or part not in node:
            raise InputError("required field is missing", file=file, column=f"field {path}")
        node = node[part]
    return node


def _numbers(value, path: str, file: str, n: int | None = None) -> np.ndarray:
    try:
        a = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        a = np.array([np.nan])
    if a.ndim > 1 or not np.all(np.isfinite(a)) or (n is not None and a.size != n):
        want = f"{n} numbers" if n is not None else "finite numbers"
        raise InputError(f"expected {want}", file=file, column=f"field {path}")
    return np.atleast_1d(a)


def load_reference(path: str | Path) -> Reference:
    """Read an independent model's ``results.json`` (errors name the file and the field)."""
    file = str(path)
    try:
        text = Path(path).read_text(encoding="utf-8")
    except OSError as exc:
        raise InputError(f"cannot read the independent model's results: {exc.strerror}", file=file) from None
    try:
        data = json.loads(text)
    except json.JSONDecodeError as exc:
        raise InputError(
            f"invalid JSON at line {exc.lineno}, column {exc.colno}: {exc.msg}", file=file
        ) from None
    if not isinstance(data, dict):
        raise InputError("the results must be a JSON object", file=file)
    elong = _field(data, "checks.uniform10.fe_elong_um", file)
    if not isinstance(elong, dict) or not elong:
        raise InputError(
            "expected an object of sensor elongations (um)",
            file=file,
            column="field checks.uniform10.fe_elong_um",
        )
    names = tuple(str(k) for k in elong)
    uniform_elong = _numbers(list(elong.values()), "checks.uniform10.fe_elong_um", file)
    uniform_ttp = np.array(
        [
            float(
                _numbers(
                    _field(data, f"checks.uniform10.fe_{a}_um", file), f"checks.uniform10.fe_{a}_um", file, 1
                )[0]
            )
            for a in ("dx", "dy", "dz")
        ]
    )
    unit = {
        a: _numbers(
            _field(data, f"unit_response_um_per_N.{a}", file),
            f"unit_response_um_per_N.{a}",
            file,
            3 + len(names),
        )
        for a in "xyz"
    }
    steps: dict = {}
    raw = data.get(STEPS_FIELD)
    if raw is not None:
        if not isinstance(raw, dict):
            raise InputError("expected an object of inputs", file=file, column=f"field {STEPS_FIELD}")
        for case, figures in raw.items():
            path = f"{STEPS_FIELD}.{case}"
            if not isinstance(figures, dict) or not figures:
                raise InputError("expected an object of figures (um)", file=file, column=f"field {path}")
            values = _numbers(list(figures.values()), path, file)
            steps[str(case)] = dict(zip((str(k) for k in figures), values.tolist(), strict=True))
    defs = data.get("unit_thermal_step_definition")
    definitions = {str(k): str(v) for k, v in defs.items()} if isinstance(defs, dict) else {}
    return Reference(names, unit, uniform_ttp, uniform_elong, steps, definitions)


#: an independent figure below this share of its case's largest is round-off of a zero (a
#: symmetric ram's lateral response, 1e-13 µm): its difference in % is noise, not shown
NEGLIGIBLE_SHARE = 1e-9


def _row(quantity, independent, twin, target_rel, scale=None, report_only=False, largest=None) -> Row:
    """Relative judgement, or absolute against ``target_rel * scale`` when ``scale`` is given.
    ``largest``: the case's largest independent figure (default ``scale``), below
    :data:`NEGLIGIBLE_SHARE` of which the difference in % is None."""
    size = abs(largest if largest is not None else (scale if scale is not None else 0.0))
    negligible = abs(independent) <= NEGLIGIBLE_SHARE * size
    diff_pct = 100.0 * (twin / independent - 1.0) if independent != 0 and not negligible else None
    if report_only:
        return Row(quantity, independent, twin, diff_pct, "-", "report", None)
    if scale is None:
        ok = abs(twin - independent) <= target_rel * abs(independent)
        return Row(quantity, independent, twin, diff_pct, f"{100 * target_rel:g} %", "relative", ok)
    tol = target_rel * abs(scale)
    return Row(
        quantity, independent, twin, diff_pct, f"+-{tol:.3g}", "absolute", abs(twin - independent) <= tol
    )


def step_source(case: str, sources) -> str | None:
    """The description's heat source a results' step input names (None: none does)."""
    names = [h.name for h in sources]
    if case in names:
        return case
    near = [n for n in names if case in n or n in case]
    return near[0] if len(near) == 1 else None


def step_size(definition: str | None, kind: str) -> float:
    """A unit step's size: the first number with its unit (W, W/m², K) in ``definition``, else
    100 W (volume), 100 W/m² (radiant) or 1 K (ambient)."""
    unit = {"ambient": "K", "radiant": "W/m"}.get(kind, "W")
    for number, found in re.findall(r"([+-]?\d+(?:\.\d+)?)\s*(W/m|W|K)", definition or ""):
        if found == unit:
            return float(number)
    return 1.0 if kind == "ambient" else 100.0


def thermal_step_responses(twin, ref: Reference) -> dict:
    """{input: {dx, dy, dz, sensor: µm}} of the twin 36 h after each of the results' unit steps,
    from rest (the inputs no source of the description answers are left out)."""
    machine = twin.machine
    sources = machine.thermal.sources
    t0 = machine.reference_temperature_C
    t = np.concatenate([[0.0], np.geomspace(1.0, STEP_HOURS * 3600.0, 400)])
    out = {}
    for case in ref.thermal_steps_um:
        heat = {h.name: np.zeros_like(t) for h in sources}
        ambient = np.full_like(t, t0)
        if case == "ambient":
            ambient[1:] += step_size(ref.thermal_step_definitions.get(case), "ambient")
        else:
            name = step_source(case, sources)
            if name is None:
                continue
            kind = next(h.kind for h in sources if h.name == name)
            heat[name][1:] = step_size(ref.thermal_step_definitions.get(case), kind)
        r = twin.thermal(t, ambient, heat=heat, initial_C=t0)
        ttp = r.ttp_um[-1] - r.ttp_um[0]
        el = r.sensor_elongation_um[-1] - r.sensor_elongation_um[0]
        out[case] = dict(zip(("dx", "dy", "dz"), ttp.tolist(), strict=True)) | dict(
            zip(twin.sensor_names, el.tolist(), strict=True)
        )
    return out


def compare(twin, ref: Reference, machine_file: str | None = None) -> list[Row]:
    """Rows comparing the twin with the independent model (values µm per 1000 N, or µm)."""
    names = list(twin.sensor_names)
    missing = [n for n in ref.sensor_names if n not in names]
    if missing:
        raise InputError(
            f"the independent model's sensors {missing} are not in the machine description (it has {names})",
            file=machine_file,
            column="field sensors",
        )
    idx = [names.index(n) for n in ref.sensor_names]
    inf = twin.influence
    rows: list[Row] = []
    for j, axis in enumerate("xyz"):
        ind = PER_KN * ref.unit_um_per_N[axis]
        ttp = PER_KN * inf.ttp_per_force_um_per_N[:, j]
        sens = PER_KN * inf.sensor_per_force_um_per_N[idx, j]
        main = ind[j]
        for k, comp in enumerate(("dx", "dy", "dz")):
            rows.append(
                _row(f"F{axis} {comp} (um/kN)", ind[k], ttp[k], UNIT_LOAD_TARGET, None if k == j else main)
            )
        largest = np.abs(ind[3:]).max()
        for name, a, b in zip(ref.sensor_names, ind[3:], sens):
            cross = abs(a) < MAIN_SENSOR_FRACTION * largest
            rows.append(_row(f"F{axis} {name} (um/kN)", a, b, UNIT_LOAD_TARGET, largest if cross else None))
    u = twin.static_temperature_response("uniform", UNIFORM_DT_K)
    for k, comp in enumerate(("dx", "dy", "dz")):
        rows.append(
            _row(
                f"+10 K {comp} (um)",
                ref.uniform_ttp_um[k],
                u.ttp_um[k],
                UNIFORM_DZ_TARGET,
                report_only=comp != "dz",
                largest=np.abs(ref.uniform_ttp_um).max(),
            )
        )
    for name, a, i in zip(ref.sensor_names, ref.uniform_elongation_um, idx):
        rows.append(_row(f"+10 K {name} (um)", a, u.sensor_elongation_um[i], 0.0, report_only=True))
    for case, figures in thermal_step_responses(twin, ref).items():
        step = ref.thermal_steps_um[case]
        for k, v in step.items():
            if k in figures:
                rows.append(
                    _row(
                        f"{STEP_HOURS:g} h {case} step {k} (um)",
                        v,
                        figures[k],
                        0.0,
                        report_only=True,
                        largest=max(abs(x) for x in step.values()),
                    )
                )
    return rows


def format_table(rows: list[Row]) -> str:
    """The rows as a console table, then how many of the judged quantities are within target."""
    verdicts = {True: "pass", False: "FAIL", None: "report"}
    lines = [
        tables.format_table(
            [
                tables.text("quantity"),
                tables.Column("independent", decimals=4),
                tables.Column("twin", decimals=4),
                tables.Column("diff", "%", 2),
                tables.Column("target"),
                tables.text("result"),
            ],
            [
                [r.quantity, r.independent, r.twin, r.difference_pct, r.target, verdicts[r.passed]]
                for r in rows
            ],
        )
    ]
    judged = [r for r in rows if r.passed is not None]
    lines.append(f"{sum(1 for r in judged if r.passed)} of {len(judged)} judged quantities within target")
    return "\n".join(lines)


def run(machine_path: str | Path, against: str | Path, resolution: float | None = None) -> dict:
    """Build the twin of ``machine_path`` and compare it with ``against``; returns the figures."""
    from fbgcomp.structure import Twin  # noqa: PLC0415 - optional heavy extra: skfem (the fe extra)

    ref = load_reference(against)
    machine = load_machine(machine_path)
    # the unit loads and the uniform case read static operators only: the reduced thermal model
    # (a third of a build) only for results with thermal steps
    twin = Twin(machine, resolution=resolution, reduce_thermal=bool(ref.thermal_steps_um))
    rows = compare(twin, ref, str(machine_path))
    return {
        "machine": str(machine_path),
        "against": str(against),
        "resolution": machine.mesh.resolution if resolution is None else resolution,
        "element": machine.mesh.element,
        "n_nodes": int(twin.n_nodes),
        "rows": [asdict(r) for r in rows],
        "passed": all(r.passed for r in rows if r.passed is not None),
    }
