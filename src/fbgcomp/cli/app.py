"""Command-line interface: a thin layer that parses, calls the library and prints.

Bad input raises :class:`fbgcomp.errors.InputError`; :func:`main` prints its one line on stderr
(``error: <file>, row R (line L), column C: ...``) and exits with code 2, without a traceback.
"""

from __future__ import annotations

import json
import sys
from contextlib import contextmanager
from pathlib import Path
from typing import List, Optional

import typer
from fbgcomp import progress
from fbgcomp.errors import InputError

app = typer.Typer(add_completion=False, no_args_is_help=True, pretty_exceptions_enable=False,
                  help="fbgcomp: compensate machine-tool deformations from FBG sensors.")


@app.callback()
def _options(quiet: bool = typer.Option(False, "--quiet", "-q", help="No progress on stderr (also FBGCOMP_PROGRESS=0; FBGCOMP_PROGRESS=1 shows it even when stderr is not a terminal).")):
    """fbgcomp: compensate machine-tool deformations from FBG sensors."""
    progress.QUIET = quiet


def _read_campaigns(paths, desc="reading campaigns"):
    from fbgcomp.io.campaign import read_campaign

    return [read_campaign(p) for p in progress.track(paths, desc, unit="campaign")]


@app.command()
def inspect(campaign: Path = typer.Argument(..., help="Campaign folder."),
            as_json: bool = typer.Option(False, "--json", help="Print the summary as JSON.")):
    """Summarise a campaign: duration, rates, ranges, alignment overlap, problems found."""
    from fbgcomp.io.campaign import read_campaign

    c = read_campaign(campaign)
    if as_json:
        typer.echo(json.dumps(c.summary(), indent=1, default=str))
    else:
        typer.echo(c.summary_text())


def _any_dataset(paths) -> bool:
    from fbgcomp.cli.scale import any_dataset

    return any_dataset(paths)


def _parse_roles(roles: Optional[str]):
    if not roles:
        return None
    out = {}
    for item in roles.split(","):
        key, sep, value = item.partition("=")
        if not sep or key.strip() not in ("bulk", "surf", "flange"):
            raise InputError(f"--roles expects bulk=PROBE,surf=PROBE,flange=PROBE, got {item!r}",
                             file="<command line>", column="option --roles")
        out[key.strip()] = value.strip()
    return out


@contextmanager
def _numeric_failures(campaigns):
    """A fit that fails on its numbers (an overflow, a singular system) ends in one line naming
    the campaigns instead of a traceback; the model file is then not written."""
    import numpy as np

    try:
        yield
    except (OverflowError, FloatingPointError, ZeroDivisionError, np.linalg.LinAlgError) as exc:
        raise InputError(f"the fit failed on its numbers ({type(exc).__name__}: {exc}); check "
                         "the campaigns' values (fbgcomp inspect); no model was written",
                         file=", ".join(str(c) for c in campaigns)) from None


@app.command()
def fit(campaigns: List[Path] = typer.Argument(..., help="Training campaign folders or Parquet datasets (fbgcomp ingest)."),
        output: Path = typer.Option(..., "-o", "--output", help="Model file to write (JSON)."),
        features: Optional[str] = typer.Option(None, help="Feature set of the paper's regression: eq11, eq13 or eq12 (selects --model mra)."),
        stepwise: bool = typer.Option(False, "--stepwise", help="Stepwise selection (F-tests; selects --model mra)."),
        direction: str = typer.Option("both", help="Stepwise direction: both, forward, backward."),
        p_enter: float = typer.Option(0.05, help="Stepwise p-value to enter."),
        p_remove: float = typer.Option(0.10, help="Stepwise p-value to remove."),
        max_terms: Optional[int] = typer.Option(None, help="Upper bound on selected terms."),
        cov_type: str = typer.Option("HAC", "--cov-type", help="Inference of the paper's regression (mra): HAC (Newey-West, autocorrelation-robust; the default) or nonrobust (the paper's i.i.d. F tests and Table 1)."),
        hac_maxlags: str = typer.Option("auto", "--hac-maxlags", help="Newey-West bandwidth in lags: auto (Andrews' AR(1) rule) or a positive integer."),
        roles: Optional[str] = typer.Option(None, help="Probe roles, e.g. bulk=T_bulk,surf=T_surf,flange=T_flange."),
        zero_window: float = typer.Option(10.0, "--zero-window", help="Zero state: mean of the first N seconds."),
        fallbacks: str = typer.Option("loo", help="Fallback models for sensor faults: loo, lto or none."),
        dask: Optional[str] = typer.Option(None, "--dask", help="Reduce on a Dask cluster: tcp://HOST:8786 or local:N (default: in-process)."),
        model_type: Optional[str] = typer.Option(None, "--model", help="Model type: physical (the default: load signature + housing thermal with the do-no-harm policy), mra (the paper's regression), kinematic, hybrid, calibrated or dynamic (docs/models.md)."),
        machine: Optional[Path] = typer.Option(None, "--machine", help="Machine description YAML for kinematic/hybrid/calibrated (default: the built-in ram).")):
    """Fit the TTP-deviation model and print its coefficient tables.

    Without --model, --features or --stepwise: the physical model with the do-no-harm policy
    (docs/accuracy.md). --features/--stepwise give the paper's regression (Table 1)."""
    if model_type is None:
        model_type = "mra" if (features is not None or stepwise or dask is not None
                               or _any_dataset(campaigns)) else "physical"
    features = features or "eq13"
    with progress.stages("fit", 3) as stage:
        _fit(stage, campaigns, output, model_type, features, stepwise, direction, p_enter,
             p_remove, max_terms, cov_type, hac_maxlags, roles, zero_window, fallbacks, dask,
             machine)


def _fit(stage, campaigns, output, model_type, features, stepwise, direction, p_enter, p_remove,
         max_terms, cov_type, hac_maxlags, roles, zero_window, fallbacks, dask, machine):
    from fbgcomp.models.base import MRAModel

    if model_type == "physical":
        from fbgcomp.models.physical import PhysicalModel

        stage("reading campaigns")
        data = _read_campaigns(campaigns)
        stage("fitting the physical model (twin scenarios, housing thermal, policy)")
        with _numeric_failures(campaigns):
            model = PhysicalModel(machine=machine, zero_window_s=zero_window).fit(data)
        stage(f"writing {output}")
        model.save(output)   # only a model that loads back replaces an existing file
        typer.echo(model.summary())
        typer.echo(f"\nmodel {model.model_id} (physical) written to {output}")
        return
    if model_type != "mra":
        from fbgcomp.models.model_types import fit_from_cli

        stage("reading campaigns")
        data = _read_campaigns(campaigns)
        stage(f"fitting the {model_type} model")
        with _numeric_failures(campaigns):
            model = fit_from_cli(model_type, data, machine=machine, features=features,
                                 stepwise=stepwise, direction=direction, p_enter=p_enter,
                                 p_remove=p_remove, max_terms=max_terms, roles=_parse_roles(roles),
                                 zero_window_s=zero_window, fallbacks=fallbacks)
        stage(f"writing {output}")
        model.save(output)
        typer.echo(model.summary())
        typer.echo(f"\nmodel {model.model_id} ({model_type}) written to {output}")
        return

    if features not in ("eq11", "eq12", "eq13"):
        raise InputError(f"unknown feature set {features!r}; expected eq11, eq12 or eq13",
                         file="<command line>", column="option --features")
    if direction not in ("both", "forward", "backward"):
        raise InputError(f"unknown direction {direction!r}", file="<command line>", column="option --direction")
    if fallbacks not in ("loo", "lto", "none"):
        raise InputError(f"unknown fallbacks {fallbacks!r}", file="<command line>", column="option --fallbacks")
    if cov_type not in ("HAC", "nonrobust"):
        raise InputError(f"unknown --cov-type {cov_type!r}; expected HAC or nonrobust",
                         file="<command line>", column="option --cov-type")
    if hac_maxlags != "auto":
        try:
            lags = int(hac_maxlags)
        except ValueError:
            lags = 0
        if lags < 1:
            raise InputError(f"--hac-maxlags must be auto or a positive integer, not {hac_maxlags!r}",
                             file="<command line>", column="option --hac-maxlags")
        hac_maxlags = lags
    from fbgcomp.cli.scale import any_dataset

    scaled = dask is not None or any_dataset(campaigns)
    stage("reading campaigns" if not scaled else "opening the datasets")
    data = None if scaled else _read_campaigns(campaigns)
    model = MRAModel(features=features, stepwise=stepwise, direction=direction, p_enter=p_enter,
                     p_remove=p_remove, max_terms=max_terms, roles=_parse_roles(roles),
                     zero_window_s=zero_window, fallbacks=fallbacks, cov_type=cov_type,
                     hac_maxlags=hac_maxlags)
    stage(f"fitting the regression ({features}{', stepwise' if stepwise else ''}, per axis)")
    with _numeric_failures(campaigns):
        if scaled:
            from fbgcomp.io.distributed import fit_paths

            fit_paths(model, campaigns, dask=dask)
        else:
            model.fit(data)
    stage(f"writing {output}")
    model.save(output)
    typer.echo(model.summary())
    typer.echo(f"\nmodel {model.model_id} written to {output}")


@app.command()
def validate(model_file: Path = typer.Argument(..., help="Model file (JSON)."),
             campaigns: List[Path] = typer.Argument(..., help="Campaign folders to judge the model on."),
             json_out: Optional[Path] = typer.Option(None, "--json", help="Write the metrics as JSON.")):
    """Judge a model on campaigns: per axis peak, max |error|, RMS, % of peak, compensation ratio.

    The model is loaded through the checks every consumer uses (fbgcomp.models.base.load_model): a
    model with non-finite or absurd numbers, or parts that disagree, exits 2 with one line."""
    import numpy as np

    from fbgcomp.models.metrics import (format_metrics, format_static_metrics, static_level_metrics,
                          validation_metrics)
    from fbgcomp.atomic import write_json
    from fbgcomp.models.base import load_model

    model = load_model(model_file)
    refs, preds, halves, per_campaign = [], [], [], {}
    for c in progress.track(_read_campaigns(campaigns), "validating", unit="campaign"):
        pred, half = model.predict_interval(c)
        ref = c.aligned(zero_window_s=model.zero_window_s).reference_um
        m = validation_metrics(ref, pred, half)
        per_campaign[c.meta.name] = m
        typer.echo(format_metrics(m, title=f"campaign {c.meta.name}"))
        loads = c.aligned(zero_window_s=model.zero_window_s).loads_N
        if loads is not None:
            m["static_levels"] = static_level_metrics(loads, ref, pred)
            typer.echo(format_static_metrics(m["static_levels"]))
        typer.echo("")
        refs.append(ref), preds.append(pred), halves.append(half)
    pooled = validation_metrics(np.vstack(refs), np.vstack(preds), np.vstack(halves))
    if len(per_campaign) > 1:
        typer.echo(format_metrics(pooled, title="all campaigns"))
    pooled["campaigns"] = per_campaign
    pooled["model_id"] = model.model_id
    if json_out is not None:
        write_json(json_out, pooled)
        typer.echo(f"metrics written to {json_out}")


@app.command()
def simulate(machine: Optional[Path] = typer.Option(None, help="Machine description YAML (default: the built-in ram)."),
             scenario: str = typer.Option(..., help="Scenario: a built-in name (static-y, static-xyz, "
                                          "thermal-36h, thermal-36h-b, combined) or a scenario YAML."),
             seed: int = typer.Option(0, help="Random seed of the measurement noise and random inputs."),
             output: Path = typer.Option(..., "-o", "--output", help="Campaign folder to write.")):
    """Run a scenario on the FE twin and write the measured campaign (virtual test bench)."""
    from fbgcomp.bench.virtual import load_scenario, simulate as run
    from fbgcomp.io.campaign import write_campaign
    from fbgcomp.structure import load_machine

    with progress.stages("simulate", 3) as stage:
        stage("reading the machine and scenario")
        sc = load_scenario(scenario)
        m = load_machine(machine)
        stage("running the scenario on the FE twin (built or loaded from its cache)")
        campaign, _ = run(m, sc, seed=seed)
        stage(f"writing {output}")
        write_campaign(campaign, output)
    typer.echo(f"campaign {sc.name} ({sc.duration_s() / 3600:.2f} h) written to {output}")


@app.command("fe-calibrate")
def fe_calibrate_cmd(machine: Optional[Path] = typer.Option(None, help="Machine description YAML (default: the built-in ram)."),
                     output: Path = typer.Option(..., "-o", "--output", help="Model file to write (JSON)."),
                     features: str = typer.Option("eq11", help="eq11 (elongations only, as the paper) or eq13/eq12 (with probe temperatures)."),
                     samples: int = typer.Option(2000, help="Random combinations of the FE load cases."),
                     seed: int = typer.Option(0, help="Random seed.")):
    """Fit the eq. 11 model on a design of FE load cases (paper sec. 2.3) and write a model file."""
    from fbgcomp.models.fe_calibrated import fe_calibrate
    from fbgcomp.structure import load_machine

    if features not in ("eq11", "eq12", "eq13"):
        raise InputError(f"unknown feature set {features!r}", file="<command line>", column="option --features")
    with progress.stages("fe-calibrate", 2) as stage:
        stage("FE twin, load cases and fit")
        model, _ = fe_calibrate(load_machine(machine), features=features, n_samples=samples,
                                seed=seed)
        stage(f"writing {output}")
        model.save(output)
    typer.echo(model.summary())
    typer.echo(f"\nmodel {model.model_id} written to {output}")


@app.command()
def resolution(machine: Optional[Path] = typer.Option(None, help="Machine description YAML (default: the built-in ram)."),
               noise_pm: float = typer.Option(1.0, help="Interrogator wavelength noise, pm."),
               as_json: bool = typer.Option(False, "--json", help="Print JSON.")):
    """Smallest TTP deviation the sensor set resolves, and the condition of the sensor-to-TTP map."""
    from fbgcomp.models.fe_calibrated import format_resolution, resolution_report
    from fbgcomp.structure import load_machine

    with progress.stages("resolution", 1) as stage:
        stage("FE twin and the sensor-to-TTP map")
        rep = resolution_report(load_machine(machine), wavelength_noise_nm=noise_pm * 1e-3)
    typer.echo(json.dumps(rep, indent=1) if as_json else format_resolution(rep))


@app.command()
def demo(output: Path = typer.Option(Path("demo-out"), "-o", "--output", help="Folder for the results."),
         machine: Optional[Path] = typer.Option(None, help="Machine description YAML (default: the built-in ram)."),
         seed: int = typer.Option(0, help="Random seed of the simulated campaigns."),
         quick: bool = typer.Option(False, "--quick", help="6 h thermal campaigns instead of 36 h (for tests)."),
         mesh_resolution: Optional[float] = typer.Option(None, "--mesh-resolution",
                                                         help="FE mesh refinement (default: the machine's)."),
         ram2: Optional[Path] = typer.Option(None, "--ram2", help="The independent ram2 data set (default: "
                                             "$FBGCOMP_RAM2, else ../shared/reference/ram2 beside the repository).")):
    """The main job: simulate, FE-calibrate, fit and validate on the built-in default machine, then
    the default model on the independent ram2 data set beside it (skipped in one line without it)."""
    from fbgcomp.cli.demo import run_demo

    run_demo(output, machine_path=machine, seed=seed, quick=quick, resolution=mesh_resolution, ram2=ram2)


@app.command()
def compare(train: List[Path] = typer.Option(..., "--train", help="Training campaign folder (repeat the option)."),
            test: List[Path] = typer.Option(..., "--test", help="Held-out campaign folder (repeat the option)."),
            machine: Optional[Path] = typer.Option(None, "--machine", help="Machine description YAML (default: the built-in ram; the physical model then runs without one, as fbgcomp fit)."),
            csv_out: Path = typer.Option(Path("comparison.csv"), "--csv", help="Pooled table, ranked per axis (CSV)."),
            campaign_csv: Optional[Path] = typer.Option(None, "--campaign-csv", help="Per held-out campaign table with the uncompensated row and harm marks (CSV; default: <csv stem>_by_campaign.csv beside --csv)."),
            json_out: Path = typer.Option(Path("comparison.json"), "--json", help="Everything (JSON)."),
            markdown: Optional[Path] = typer.Option(None, "--markdown", help="Also write the per-campaign tables as Markdown.")):
    """Every model type fitted on --train and judged on each --test campaign beside no compensation
    (rows marked WORSE where an axis ends worse than uncompensated), then pooled and ranked per axis."""
    from fbgcomp.models.compare import (ENTRIES, compare as run, default_campaign_csv, format_comparison,
                          write_comparison)

    with progress.stages("compare", 2 + len(ENTRIES)) as stage:
        stage("reading campaigns")
        train_c = _read_campaigns(train, "reading training campaigns")
        test_c = _read_campaigns(test, "reading held-out campaigns")
        result = run(train_c, test_c, machine=machine,
                     progress=lambda name: stage(f"fitting and judging {name}"))
        stage("writing the tables")
        campaign_csv = campaign_csv or default_campaign_csv(csv_out)
        write_comparison(result, csv_out, json_out, campaign_csv, markdown)
    typer.echo(format_comparison(result))
    typer.echo(f"\ntables written to {csv_out}, {campaign_csv} and {json_out}"
               + (f" (Markdown: {markdown})" if markdown else ""))


#: Grid searched by ``place`` when neither --grid nor the machine names candidate paths: one
#: centred path of 500 mm every 250 mm on each face.
DEFAULT_PLACEMENT_GRID = "faces=+X,-X,+Y,-Y;offsets=0;length=500;step=250"


@app.command()
def place(k: int = typer.Option(..., "--k", help="Number of sensor paths to choose."),
          machine: Optional[Path] = typer.Option(None, "--machine", help="Machine description YAML (default: the built-in ram)."),
          grid: Optional[str] = typer.Option(None, "--grid", help="Candidate grid on the faces, e.g. "
                                             "'faces=+X,-X,+Y,-Y;offsets=-80,0,80;length=400;step=200' "
                                             "(default: the machine's candidate paths, else "
                                             f"'{DEFAULT_PLACEMENT_GRID}')."),
          resolution: Optional[float] = typer.Option(None, "--resolution", help="FE mesh resolution (default: the machine's)."),
          z_axis: Optional[float] = typer.Option(None, "--z-axis", help="Z-axis position, mm."),
          noise_pm: float = typer.Option(1.0, "--noise-pm", help="Interrogator wavelength noise, pm."),
          dask: Optional[str] = typer.Option(None, "--dask", help="Evaluate candidates on a Dask cluster: tcp://HOST:8786 or local:N."),
          json_out: Optional[Path] = typer.Option(None, "--json", help="Write the result as JSON.")):
    """Choose K sensor paths minimising the predicted worst-case TTP error (FE load design + noise)."""
    from fbgcomp.atomic import write_json
    from fbgcomp.structure.placement import parse_grid, place as run
    from fbgcomp.structure import load_machine

    m = load_machine(machine)
    if k < 1:
        raise InputError("--k must be at least 1", file="<command line>", column="option --k")
    if grid is None and not m.candidate_sensors:
        # Choosing K of the machine's own K paths would only re-order them: search a grid.
        grid = DEFAULT_PLACEMENT_GRID
        typer.echo(f"no --grid and no candidate paths in the machine description: searching the "
                   f"default grid '{grid}' beside the machine's own paths")
    with progress.stages("place", 1) as stage:
        stage("FE twin, candidate paths and the search")
        result = run(m, k, grid=parse_grid(grid) if grid else None, resolution=resolution,
                     z_axis_mm=z_axis, dask=dask, wavelength_noise_nm=noise_pm * 1e-3)
    typer.echo(result.format())
    if json_out is not None:
        write_json(json_out, result.to_dict())
        typer.echo(f"result written to {json_out}")


@app.command()
def plan(target_um: float = typer.Option(..., "--target-um", help="Target TTP accuracy per axis, µm (worst case)."),
         machine: Optional[Path] = typer.Option(None, "--machine", help="Machine description YAML (default: the built-in ram)."),
         noise_pm: float = typer.Option(1.0, "--noise-pm", help="Interrogator wavelength noise, pm (SD)."),
         axes: str = typer.Option("dx,dy,dz", "--axes", help="Axes to judge, e.g. dx,dz."),
         extra: int = typer.Option(2, "--extra-sensors", help="Also place layouts of up to this many more "
                                   "paths (machine candidates, else the place default grid); 0: none."),
         as_json: bool = typer.Option(False, "--json", help="Print JSON.")):
    """Before buying hardware: the predicted TTP accuracy of the machine's layout with this noise
    against a target, per axis, and what would close a gap (docs/campaign-guide.md)."""
    import math

    from fbgcomp.structure.placement import parse_grid
    from fbgcomp.structure.plan import parse_axes, plan as run
    from fbgcomp.structure import load_machine

    if not math.isfinite(target_um) or target_um <= 0:
        raise InputError(f"--target-um must be a positive number of µm, not {target_um:g}",
                         file="<command line>", column="option --target-um")
    if not math.isfinite(noise_pm) or noise_pm <= 0:
        raise InputError(f"--noise-pm must be a positive number of pm, not {noise_pm:g}",
                         file="<command line>", column="option --noise-pm")
    if extra < 0:
        raise InputError(f"--extra-sensors must be 0 or more, not {extra}", file="<command line>",
                         column="option --extra-sensors")
    chosen_axes = parse_axes(axes)
    m = load_machine(machine)
    grid = None if m.candidate_sensors else parse_grid(DEFAULT_PLACEMENT_GRID)
    typer.echo(f"plan: FE twin and load design of {machine or 'the built-in ram'} (cached after the "
               "first run) ...", err=True)
    with progress.stages("plan", 1) as stage:
        stage("FE twin, load design and the layouts")
        result = run(m, target_um, axes=chosen_axes, wavelength_noise_nm=noise_pm * 1e-3,
                     grid=grid, extra_sensors=extra,
                     machine_name=str(machine) if machine else "the built-in ram")
    typer.echo(json.dumps(result.to_dict(), indent=1) if as_json else result.format())


@app.command("import")
def import_cmd(mapping: Path = typer.Argument(..., help="Mapping file (YAML): campaign metadata, exports, columns, units, times (docs/import.md)."),
               output: Path = typer.Option(..., "-o", "--output", help="Campaign folder to write (an existing one is replaced atomically).")):
    """Turn vendor and logger exports (CSV, TSV, Excel) into a campaign folder."""
    from fbgcomp.io.vendor_import import describe, import_campaign

    typer.echo(describe(import_campaign(mapping, output), mapping, output))


def _mount_optional_commands() -> None:
    """Commands of packages that may be absent in a minimal install (runtime needs asyncua)."""
    from fbgcomp.cli.cnc_demo import register as register_cnc_demo
    from fbgcomp.report.html import register as register_report
    from fbgcomp.cli.scale import register as register_scale

    register_report(app)
    register_cnc_demo(app)
    register_scale(app)
    __import__("fbgcomp.structure.twin_check", fromlist=["register"]).register(app)
    try:
        from fbgcomp.cli.runtime import register
    except ImportError:
        return
    register(app)


_mount_optional_commands()


def main(argv=None) -> int:
    try:
        app(args=argv, prog_name="fbgcomp")
    except InputError as exc:
        print(f"error: {exc.one_line()}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("error: interrupted", file=sys.stderr)
        return 130
    except SystemExit as exc:
        return exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
