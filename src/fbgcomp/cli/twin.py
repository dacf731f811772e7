"""Commands on the machine description and its FE twin: ``resolution``, ``place``, ``plan`` and
``twin-check`` (mounted by :mod:`fbgcomp.cli.app`).

The twin, the placement search and the plan are imported inside the commands (they pull in
numpy, scikit-fem and pandas) so that ``fbgcomp --help`` starts fast.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import typer

from fbgcomp import progress
from fbgcomp.errors import InputError
from fbgcomp.tables import Column, format_number, format_table, text
from fbgcomp.units import AXES

#: Grid searched by ``place`` when neither --grid nor the machine names candidate paths: one
#: centred path of 500 mm every 250 mm on each face.
DEFAULT_PLACEMENT_GRID = "faces=+X,-X,+Y,-Y;offsets=0;length=500;step=250"


def format_resolution(rep: dict) -> str:
    """The report of :func:`fbgcomp.models.fe_calibrated.resolution_report` as console tables:
    the elongations and TTP displacements of each load case, then per axis the smallest TTP
    deviation resolved, the largest load case's and what the sensors leave unexplained (µm)."""
    lines = [
        "FBG resolution check (2σ, interrogator noise on the elongations)",
        "sensor noise (µm): "
        + ", ".join(f"{s} {format_number(n, 3)}" for s, n in zip(rep["sensors"], rep["elongation_noise_um"])),
    ]
    cases = (
        [text("load case"), Column("magnitude")]
        + [Column(s, "µm") for s in rep["sensors"]]
        + [Column(a, "µm") for a in AXES]
    )
    lines.append(
        format_table(
            cases,
            [
                [c["name"], f"{c['magnitude']:g} {c['unit']}", *c["sensor_elongation_um"], *c["ttp_um"]]
                for c in rep["load_cases"]
            ],
        )
    )
    lines.append(
        format_table(
            [text("axis"), Column("resolves", "µm"), Column("max case", "µm"), Column("unexplained", "µm")],
            [
                [a, m["resolution_um"], m["max_load_case_ttp_um"], m["max_unexplained_um"]]
                for a, m in rep["axes"].items()
            ],
        )
    )
    lines.append(
        f"sensor-to-TTP map (noise units): singular values "
        f"{', '.join(f'{v:.3g}' for v in rep['singular_values'])}; rank {rep['rank']} of "
        f"{len(rep['sensors'])}, condition number {rep['condition_number']:.3g}"
    )
    for combo in rep["unobservable_combinations"]:
        lines.append(
            "unobservable (no load case excites it above the noise): "
            + " ".join(f"{v:+.2f}·{k}" for k, v in combo.items() if abs(v) > 1e-3)
        )
    return "\n".join(lines)


def resolution(
    machine: Path | None = typer.Option(None, help="Machine description YAML (default: the built-in ram)."),
    noise_pm: float = typer.Option(1.0, help="Interrogator wavelength noise, pm."),
    as_json: bool = typer.Option(False, "--json", help="Print JSON."),
):
    """Smallest TTP deviation the sensor set resolves, and the condition of the sensor-to-TTP map."""
    from fbgcomp.models.fe_calibrated import resolution_report
    from fbgcomp.structure import load_machine

    with progress.stages("resolution", 1) as stage:
        stage("FE twin and the sensor-to-TTP map")
        rep = resolution_report(load_machine(machine), wavelength_noise_nm=noise_pm * 1e-3)
    typer.echo(json.dumps(rep, indent=1) if as_json else format_resolution(rep))


def place(
    k: int = typer.Option(..., "--k", help="Number of sensor paths to choose."),
    machine: Path | None = typer.Option(
        None, "--machine", help="Machine description YAML (default: the built-in ram)."
    ),
    grid: str | None = typer.Option(
        None,
        "--grid",
        help="Candidate grid on the faces, e.g. "
        "'faces=+X,-X,+Y,-Y;offsets=-80,0,80;length=400;step=200' "
        "(default: the machine's candidate paths, else "
        f"'{DEFAULT_PLACEMENT_GRID}').",
    ),
    resolution: float | None = typer.Option(
        None, "--resolution", help="FE mesh resolution (default: the machine's)."
    ),
    z_axis: float | None = typer.Option(None, "--z-axis", help="Z-axis position, mm."),
    noise_pm: float = typer.Option(1.0, "--noise-pm", help="Interrogator wavelength noise, pm."),
    dask: str | None = typer.Option(
        None, "--dask", help="Evaluate candidates on a Dask cluster: tcp://HOST:8786 or local:N."
    ),
    json_out: Path | None = typer.Option(None, "--json", help="Write the result as JSON."),
):
    """Choose K sensor paths minimising the predicted worst-case TTP error (FE load design + noise)."""
    from fbgcomp.atomic import write_json
    from fbgcomp.structure import load_machine
    from fbgcomp.structure.placement import parse_grid
    from fbgcomp.structure.placement import place as run

    m = load_machine(machine)
    if k < 1:
        raise InputError("--k must be at least 1", file="<command line>", column="option --k")
    if grid is None and not m.candidate_sensors:
        # Choosing K of the machine's own K paths would only re-order them: search a grid.
        grid = DEFAULT_PLACEMENT_GRID
        typer.echo(
            f"no --grid and no candidate paths in the machine description: searching the "
            f"default grid '{grid}' beside the machine's own paths"
        )
    with progress.stages("place", 1) as stage:
        stage("FE twin, candidate paths and the search")
        result = run(
            m,
            k,
            grid=parse_grid(grid) if grid else None,
            resolution=resolution,
            z_axis_mm=z_axis,
            dask=dask,
            wavelength_noise_nm=noise_pm * 1e-3,
        )
    typer.echo(result.format())
    if json_out is not None:
        write_json(json_out, result.to_dict())
        typer.echo(f"result written to {json_out}")


def plan(
    target_um: float = typer.Option(
        ..., "--target-um", help="Target TTP accuracy per axis, µm (worst case)."
    ),
    machine: Path | None = typer.Option(
        None, "--machine", help="Machine description YAML (default: the built-in ram)."
    ),
    noise_pm: float = typer.Option(1.0, "--noise-pm", help="Interrogator wavelength noise, pm (SD)."),
    axes: str = typer.Option("dx,dy,dz", "--axes", help="Axes to judge, e.g. dx,dz."),
    extra: int = typer.Option(
        2,
        "--extra-sensors",
        help="Also place layouts of up to this many more "
        "paths (machine candidates, else the place default grid); 0: none.",
    ),
    as_json: bool = typer.Option(False, "--json", help="Print JSON."),
):
    """Before buying hardware: the predicted TTP accuracy of the machine's layout with this noise
    against a target, per axis, and what would close a gap (docs/campaign-guide.md)."""
    from fbgcomp.structure import load_machine
    from fbgcomp.structure.placement import parse_grid
    from fbgcomp.structure.plan import parse_axes
    from fbgcomp.structure.plan import plan as run

    if not math.isfinite(target_um) or target_um <= 0:
        raise InputError(
            f"--target-um must be a positive number of µm, not {target_um:g}",
            file="<command line>",
            column="option --target-um",
        )
    if not math.isfinite(noise_pm) or noise_pm <= 0:
        raise InputError(
            f"--noise-pm must be a positive number of pm, not {noise_pm:g}",
            file="<command line>",
            column="option --noise-pm",
        )
    if extra < 0:
        raise InputError(
            f"--extra-sensors must be 0 or more, not {extra}",
            file="<command line>",
            column="option --extra-sensors",
        )
    chosen_axes = parse_axes(axes)
    m = load_machine(machine)
    grid = None if m.candidate_sensors else parse_grid(DEFAULT_PLACEMENT_GRID)
    typer.echo(
        f"plan: FE twin and load design of {machine or 'the built-in ram'} (cached after the first run) ...",
        err=True,
    )
    with progress.stages("plan", 1) as stage:
        stage("FE twin, load design and the layouts")
        result = run(
            m,
            target_um,
            axes=chosen_axes,
            wavelength_noise_nm=noise_pm * 1e-3,
            grid=grid,
            extra_sensors=extra,
            machine_name=str(machine) if machine else "the built-in ram",
        )
    typer.echo(json.dumps(result.to_dict(), indent=1) if as_json else result.format())


def twin_check(
    machine: Path = typer.Argument(..., help="Machine description (YAML)."),
    against: Path = typer.Option(
        ..., "--against", help="Independent model's results.json (unit responses, checks)."
    ),
    json_out: Path | None = typer.Option(None, "--json", help="Write the figures to this JSON file."),
    resolution: float | None = typer.Option(
        None, "--resolution", help="Mesh refinement factor (default: the machine's mesh.resolution)."
    ),
):
    """Compare the FE twin with an independent model: TTP compliance, sensor responses, +10 K,
    and (reported) the 36 h unit thermal steps where the results carry them."""
    from fbgcomp.atomic import write_json
    from fbgcomp.structure.twin_check import Row, run
    from fbgcomp.structure.twin_check import format_table as format_rows

    if resolution is not None and not (math.isfinite(resolution) and resolution > 0):
        raise InputError(
            "--resolution must be a positive number", file="<command line>", column="option --resolution"
        )
    with progress.stages("twin-check", 1) as stage:
        stage("building the twin (or loading it from its cache) and computing its responses")
        out = run(machine, against, resolution)
    typer.echo(
        f"twin of {machine} ({out['element']}, resolution {out['resolution']:g}, "
        f"{out['n_nodes']} nodes) against {against}"
    )
    typer.echo(format_rows([Row(**r) for r in out["rows"]]))
    if json_out is not None:
        write_json(json_out, out)
        typer.echo(f"figures written to {json_out}")
