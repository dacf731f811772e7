"""The offline commands: ``inspect``, ``fit``, ``validate``, ``simulate``, ``fe-calibrate``,
``compare``, ``import`` and ``report`` (mounted by :mod:`fbgcomp.cli.app`).

Each command parses its options, calls the library of its stage and prints. The libraries
(numpy, the models, the campaign reader, matplotlib) are imported inside the commands so that
``fbgcomp --help`` and the commands that do not need them start fast.
"""

from __future__ import annotations

import json
from contextlib import contextmanager
from pathlib import Path

import typer

from fbgcomp import progress
from fbgcomp.cli.scale import any_dataset
from fbgcomp.errors import InputError


def read_campaigns(paths, desc="reading campaigns"):
    """Read campaign folders with a progress bar (one step per campaign)."""
    from fbgcomp.io.campaign import read_campaign

    return [read_campaign(p) for p in progress.track(paths, desc, unit="campaign")]


def inspect(
    campaign: Path = typer.Argument(..., help="Campaign folder."),
    as_json: bool = typer.Option(False, "--json", help="Print the summary as JSON."),
):
    """Summarise a campaign: duration, rates, ranges, alignment overlap, problems found."""
    from fbgcomp.io.campaign import read_campaign

    c = read_campaign(campaign)
    if as_json:
        typer.echo(json.dumps(c.summary(), indent=1, default=str))
    else:
        typer.echo(c.summary_text())


def _parse_roles(roles: str | None):
    if not roles:
        return None
    out = {}
    for item in roles.split(","):
        key, sep, value = item.partition("=")
        if not sep or key.strip() not in ("bulk", "surf", "flange"):
            raise InputError(
                f"--roles expects bulk=PROBE,surf=PROBE,flange=PROBE, got {item!r}",
                file="<command line>",
                column="option --roles",
            )
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
        raise InputError(
            f"the fit failed on its numbers ({type(exc).__name__}: {exc}); check "
            "the campaigns' values (fbgcomp inspect); no model was written",
            file=", ".join(str(c) for c in campaigns),
        ) from None


def fit(
    campaigns: list[Path] = typer.Argument(
        ..., help="Training campaign folders or Parquet datasets (fbgcomp ingest)."
    ),
    output: Path = typer.Option(..., "-o", "--output", help="Model file to write (JSON)."),
    features: str | None = typer.Option(
        None, help="Feature set of the paper's regression: eq11, eq13 or eq12 (selects --model mra)."
    ),
    stepwise: bool = typer.Option(
        False, "--stepwise", help="Stepwise selection (F-tests; selects --model mra)."
    ),
    direction: str = typer.Option("both", help="Stepwise direction: both, forward, backward."),
    p_enter: float = typer.Option(0.05, help="Stepwise p-value to enter."),
    p_remove: float = typer.Option(0.10, help="Stepwise p-value to remove."),
    max_terms: int | None = typer.Option(None, help="Upper bound on selected terms."),
    cov_type: str = typer.Option(
        "HAC",
        "--cov-type",
        help=(
            "Inference of the paper's regression (mra): HAC (Newey-West, autocorrelation-robust; the "
            "default) or nonrobust (the paper's i.i.d. F tests and Table 1)."
        ),
    ),
    hac_maxlags: str = typer.Option(
        "auto",
        "--hac-maxlags",
        help="Newey-West bandwidth in lags: auto (Andrews' AR(1) rule) or a positive integer.",
    ),
    roles: str | None = typer.Option(None, help="Probe roles, e.g. bulk=T_bulk,surf=T_surf,flange=T_flange."),
    zero_window: float = typer.Option(10.0, "--zero-window", help="Zero state: mean of the first N seconds."),
    fallbacks: str = typer.Option("loo", help="Fallback models for sensor faults: loo, lto or none."),
    dask: str | None = typer.Option(
        None, "--dask", help="Reduce on a Dask cluster: tcp://HOST:8786 or local:N (default: in-process)."
    ),
    model_type: str | None = typer.Option(
        None,
        "--model",
        help=(
            "Model type: physical (the default: load signature + housing thermal with the do-no-harm "
            "policy), mra (the paper's regression), kinematic, hybrid, calibrated or dynamic "
            "(docs/models.md)."
        ),
    ),
    machine: Path | None = typer.Option(
        None,
        "--machine",
        help="Machine description YAML for kinematic/hybrid/calibrated (default: the built-in ram).",
    ),
    observer: bool = typer.Option(
        False,
        "--observer",
        help=(
            "physical with --machine: average the thermal map with a thermal state observer on the "
            "twin while its heat estimates stay plausible (docs/accuracy.md; off by default)."
        ),
    ),
    heat_inputs: bool = typer.Option(
        True,
        "--heat-inputs/--no-heat-inputs",
        help=(
            "physical: take the campaigns' measured spindle power (heat.csv) into the housing "
            "calibration when every thermal training campaign carries it (docs/campaign-guide.md)."
        ),
    ),
):
    """Fit the TTP-deviation model and print its coefficient tables.

    Without --model, --features or --stepwise: the physical model with the do-no-harm policy
    (docs/accuracy.md). --features/--stepwise give the paper's regression (Table 1)."""
    if model_type is None:
        model_type = (
            "mra"
            if (features is not None or stepwise or dask is not None or any_dataset(campaigns))
            else "physical"
        )
    features = features or "eq13"
    with progress.stages("fit", 3) as stage:
        _fit(
            stage,
            campaigns,
            output,
            model_type,
            features,
            stepwise,
            direction,
            p_enter,
            p_remove,
            max_terms,
            cov_type,
            hac_maxlags,
            roles,
            zero_window,
            fallbacks,
            dask,
            machine,
            observer,
            heat_inputs,
        )


def _fit(
    stage,
    campaigns,
    output,
    model_type,
    features,
    stepwise,
    direction,
    p_enter,
    p_remove,
    max_terms,
    cov_type,
    hac_maxlags,
    roles,
    zero_window,
    fallbacks,
    dask,
    machine,
    observer=False,
    heat_inputs=True,
):
    from fbgcomp.models.mra import MRAModel

    if observer and (model_type != "physical" or machine is None):
        raise InputError(
            "--observer needs the physical model and a --machine (it filters the twin's thermal state)",
            file="<command line>",
            column="option --observer",
        )
    if model_type == "physical":
        from fbgcomp.models.physical import PhysicalModel

        stage("reading campaigns")
        data = read_campaigns(campaigns)
        stage("fitting the physical model (twin scenarios, housing thermal, policy)")
        with _numeric_failures(campaigns):
            model = PhysicalModel(
                machine=machine, zero_window_s=zero_window, observer=observer, heat_inputs=heat_inputs
            ).fit(data)
        stage(f"writing {output}")
        model.save(output)  # only a model that loads back replaces an existing file
        typer.echo(model.summary())
        typer.echo(f"\nmodel {model.model_id} (physical) written to {output}")
        return
    if model_type != "mra":
        from fbgcomp.models.registry import fit_from_cli

        stage("reading campaigns")
        data = read_campaigns(campaigns)
        stage(f"fitting the {model_type} model")
        with _numeric_failures(campaigns):
            model = fit_from_cli(
                model_type,
                data,
                machine=machine,
                features=features,
                stepwise=stepwise,
                direction=direction,
                p_enter=p_enter,
                p_remove=p_remove,
                max_terms=max_terms,
                roles=_parse_roles(roles),
                zero_window_s=zero_window,
                fallbacks=fallbacks,
            )
        stage(f"writing {output}")
        model.save(output)
        typer.echo(model.summary())
        typer.echo(f"\nmodel {model.model_id} ({model_type}) written to {output}")
        return

    if features not in ("eq11", "eq12", "eq13"):
        raise InputError(
            f"unknown feature set {features!r}; expected eq11, eq12 or eq13",
            file="<command line>",
            column="option --features",
        )
    if direction not in ("both", "forward", "backward"):
        raise InputError(
            f"unknown direction {direction!r}", file="<command line>", column="option --direction"
        )
    if fallbacks not in ("loo", "lto", "none"):
        raise InputError(
            f"unknown fallbacks {fallbacks!r}", file="<command line>", column="option --fallbacks"
        )
    if cov_type not in ("HAC", "nonrobust"):
        raise InputError(
            f"unknown --cov-type {cov_type!r}; expected HAC or nonrobust",
            file="<command line>",
            column="option --cov-type",
        )
    if hac_maxlags != "auto":
        try:
            lags = int(hac_maxlags)
        except ValueError:
            lags = 0
        if lags < 1:
            raise InputError(
                f"--hac-maxlags must be auto or a positive integer, not {hac_maxlags!r}",
                file="<command line>",
                column="option --hac-maxlags",
            )
        hac_maxlags = lags
    scaled = dask is not None or any_dataset(campaigns)
    stage("reading campaigns" if not scaled else "opening the datasets")
    data = None if scaled else read_campaigns(campaigns)
    model = MRAModel(
        features=features,
        stepwise=stepwise,
        direction=direction,
        p_enter=p_enter,
        p_remove=p_remove,
        max_terms=max_terms,
        roles=_parse_roles(roles),
        zero_window_s=zero_window,
        fallbacks=fallbacks,
        cov_type=cov_type,
        hac_maxlags=hac_maxlags,
    )
    stage(f"fitting the regression ({features}{', stepwise' if stepwise else ''}, per axis)")
    with _numeric_failures(campaigns):
        if scaled:
            from fbgcomp.models.distributed import fit_paths

            fit_paths(model, campaigns, dask=dask)
        else:
            model.fit(data)
    stage(f"writing {output}")
    model.save(output)
    typer.echo(model.summary())
    typer.echo(f"\nmodel {model.model_id} written to {output}")


def validate(
    model_file: Path = typer.Argument(..., help="Model file (JSON)."),
    campaigns: list[Path] = typer.Argument(..., help="Campaign folders to judge the model on."),
    json_out: Path | None = typer.Option(None, "--json", help="Write the metrics as JSON."),
    served: bool = typer.Option(
        False,
        "--served",
        help="Judge the correction the runtime publishes (`fbgcomp serve`'s default pipeline: "
        "output filter, per-axis limit and rate), fed the campaign's own interrogator frames.",
    ),
):
    """Judge a model on campaigns: per axis peak, max |error|, RMS, % of peak, compensation ratio.

    The model is loaded through the checks every consumer uses (fbgcomp.models.base.load_model): a
    model with non-finite or absurd numbers, or parts that disagree, exits 2 with one line.
    ``--served`` judges what a CNC would receive instead of the model's own prediction: the two
    differ where the runtime's output filter holds the correction still (docs/runtime.md)."""
    import numpy as np

    from fbgcomp.atomic import write_json
    from fbgcomp.cli.demo import prediction
    from fbgcomp.models.compare import unique_name
    from fbgcomp.models.metrics import (
        format_metrics,
        format_static_metrics,
        static_level_metrics,
        validation_metrics,
    )
    from fbgcomp.models.registry import load_model

    model = load_model(model_file)
    refs, preds, halves, per_campaign = [], [], [], {}
    seen: dict[str, int] = {}
    for c in progress.track(read_campaigns(campaigns), "validating", unit="campaign"):
        pred, half = prediction(model, c, served)
        aligned = c.aligned(zero_window_s=model.zero_window_s)
        ref, loads = aligned.reference_um, aligned.loads_N
        m = validation_metrics(ref, pred, half)
        name = unique_name(c.meta.name, seen)  # as compare names them
        per_campaign[name] = m
        how = " (served through the runtime)" if served else ""
        typer.echo(format_metrics(m, title=f"campaign {name}{how}"))
        inside = _inside_gaps(c, aligned.time_s, ref, pred, served)
        if inside is not None:
            m["inside_gaps"] = inside
            typer.echo(inside["note"])
        if loads is not None:
            m["static_levels"] = static_level_metrics(loads, ref, pred)
            typer.echo(format_static_metrics(m["static_levels"]))
            unread = _unread_forces(model, loads)
            if unread:
                m["unread_forces"] = unread
        typer.echo("")
        refs.append(ref)
        preds.append(pred)
        halves.append(half)
    pooled = validation_metrics(np.vstack(refs), np.vstack(preds), np.vstack(halves))
    if len(per_campaign) > 1:
        typer.echo(format_metrics(pooled, title="all campaigns"))
    pooled["campaigns"] = per_campaign
    pooled["model_id"] = model.model_id
    pooled["served"] = served
    if json_out is not None:
        write_json(json_out, pooled)
        typer.echo(f"metrics written to {json_out}")


def _inside_gaps(campaign, time_s, ref, pred, served=False) -> dict | None:
    """The reference samples inside a gap of an input file (:meth:`Campaign.gaps`: fbg.csv,
    temperatures.csv, heat.csv), where the model had no reading of that file (the default model
    goes on from the last frame before it, the others from readings interpolated across it; or,
    ``served``, the runtime's link was lost: :func:`fbgcomp.bench.served.link_loss_frames`), with
    their max |error| per axis and a note that says so; None without such a sample.

    An hour of ram2's thermal_b without the interrogator took the default model's dx
    from 2.30 to 10.53 µm (2026-12-07, docs/accuracy.md): those errors are the gap's, not the
    model's, and the judged figures carry them."""
    import numpy as np

    from fbgcomp.io.campaign.folder import FBG_FILE, HEAT_FILE, TEMPERATURES_FILE

    gaps = {f: g for f, g in campaign.gaps().items() if f in (FBG_FILE, TEMPERATURES_FILE, HEAT_FILE)}
    inside = np.zeros(len(time_s), bool)
    for spans in gaps.values():
        for a, b in spans:
            inside |= (time_s > a) & (time_s < b)
    if not inside.any():
        return None
    err = np.abs(np.asarray(pred)[inside] - np.asarray(ref)[inside]).max(axis=0)
    files = ", ".join(f"{f} ({len(g)}, longest {max(b - a for a, b in g):g} s)" for f, g in gaps.items())
    note = (
        f"note: {int(inside.sum())} of {len(time_s)} reference samples lie in a gap of {files}; "
        + (
            "the runtime's link is lost there: it runs its set without gratings on the probes "
            "(or holds and ramps its correction to zero without one)"
            if served
            else "no reading of it was taken there (the model goes on from the last, or from "
            "readings interpolated across it)"
        )
        + ", and the figures above include them "
        f"(max |error| inside: dx {err[0]:.3f}, dy {err[1]:.3f}, dz {err[2]:.3f} µm)"
    )
    return {
        "samples": int(inside.sum()),
        "files": {f: [list(g) for g in spans] for f, spans in gaps.items()},
        "max_abs_error_um": dict(zip(("dx", "dy", "dz"), err.tolist())),
        "note": note,
    }


def _unread_forces(model, loads_N) -> dict:
    """The force components the campaign applies that the model cannot read from the gratings
    (:meth:`PhysicalModel.unread_forces`), each said in one line (what it moves, and that neither
    the correction nor its interval holds it); {} for a model that reads every one it is given."""
    if not hasattr(model, "unread_forces"):
        return {}
    out = model.unread_forces(loads_N)
    for f, u in out.items():
        moves = ", ".join(f"{a} {v:.3g}" for a, v in u["ttp_um"].items())
        typer.echo(
            f"note: {f} (up to {u['max_abs_N']:.4g} N here) is not read from the gratings: its "
            f"signature is their warming pattern. It moves the TTP {moves} µm through the load "
            "signature, which neither the correction nor its interval holds."
        )
    return out


def simulate(
    machine: Path | None = typer.Option(None, help="Machine description YAML (default: the built-in ram)."),
    scenario: str = typer.Option(
        ...,
        help="Scenario: a built-in name (static-y, static-xyz, "
        "thermal-36h, thermal-36h-b, combined) or a scenario YAML.",
    ),
    seed: int = typer.Option(0, help="Random seed of the measurement noise and random inputs."),
    output: Path = typer.Option(..., "-o", "--output", help="Campaign folder to write."),
):
    """Run a scenario on the FE twin and write the measured campaign (virtual test bench)."""
    from fbgcomp.bench.virtual import load_scenario
    from fbgcomp.bench.virtual import simulate as run
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


def fe_calibrate(
    machine: Path | None = typer.Option(None, help="Machine description YAML (default: the built-in ram)."),
    output: Path = typer.Option(..., "-o", "--output", help="Model file to write (JSON)."),
    features: str = typer.Option(
        "eq11", help="eq11 (elongations only, as the paper) or eq13/eq12 (with probe temperatures)."
    ),
    samples: int = typer.Option(2000, help="Random combinations of the FE load cases."),
    seed: int = typer.Option(0, help="Random seed."),
):
    """Fit the eq. 11 model on a design of FE load cases (paper sec. 2.3) and write a model file."""
    from fbgcomp.models.fe_calibrated import fe_calibrate as run
    from fbgcomp.structure import load_machine

    if features not in ("eq11", "eq12", "eq13"):
        raise InputError(
            f"unknown feature set {features!r}", file="<command line>", column="option --features"
        )
    with progress.stages("fe-calibrate", 2) as stage:
        stage("FE twin, load cases and fit")
        model, _ = run(load_machine(machine), features=features, n_samples=samples, seed=seed)
        stage(f"writing {output}")
        model.save(output)
    typer.echo(model.summary())
    typer.echo(f"\nmodel {model.model_id} written to {output}")


def compare(
    train: list[Path] = typer.Option(..., "--train", help="Training campaign folder (repeat the option)."),
    test: list[Path] = typer.Option(..., "--test", help="Held-out campaign folder (repeat the option)."),
    machine: Path | None = typer.Option(
        None,
        "--machine",
        help=(
            "Machine description YAML (default: the built-in ram; the physical model then runs without one, "
            "as fbgcomp fit)."
        ),
    ),
    csv_out: Path = typer.Option(
        Path("comparison.csv"), "--csv", help="Pooled table, ranked per axis (CSV)."
    ),
    campaign_csv: Path | None = typer.Option(
        None,
        "--campaign-csv",
        help=(
            "Per held-out campaign table with the uncompensated row and harm marks (CSV; default: <csv "
            "stem>_by_campaign.csv beside --csv)."
        ),
    ),
    json_out: Path = typer.Option(Path("comparison.json"), "--json", help="Everything (JSON)."),
    markdown: Path | None = typer.Option(
        None, "--markdown", help="Also write the per-campaign tables as Markdown."
    ),
):
    """Every model type fitted on --train and judged on each --test campaign beside no compensation
    (rows marked WORSE where an axis ends worse than uncompensated), then pooled and ranked per axis."""
    from fbgcomp.models.compare import (
        ENTRIES,
        default_campaign_csv,
        format_comparison,
        write_comparison,
    )
    from fbgcomp.models.compare import (
        compare as run,
    )

    with progress.stages("compare", 2 + len(ENTRIES)) as stage:
        stage("reading campaigns")
        train_c = read_campaigns(train, "reading training campaigns")
        test_c = read_campaigns(test, "reading held-out campaigns")
        result = run(
            train_c, test_c, machine=machine, progress=lambda name: stage(f"fitting and judging {name}")
        )
        stage("writing the tables")
        campaign_csv = campaign_csv or default_campaign_csv(csv_out)
        write_comparison(result, csv_out, json_out, campaign_csv, markdown)
    typer.echo(format_comparison(result))
    typer.echo(
        f"\ntables written to {csv_out}, {campaign_csv} and {json_out}"
        + (f" (Markdown: {markdown})" if markdown else "")
    )


def import_campaign(
    mapping: Path = typer.Argument(
        ..., help="Mapping file (YAML): campaign metadata, exports, columns, units, times (docs/import.md)."
    ),
    output: Path = typer.Option(
        ..., "-o", "--output", help="Campaign folder to write (an existing one is replaced atomically)."
    ),
):
    """Turn vendor and logger exports (CSV, TSV, Excel) into a campaign folder."""
    from fbgcomp.io.vendor_import import describe
    from fbgcomp.io.vendor_import import import_campaign as run

    typer.echo(describe(run(mapping, output), mapping, output))


def report(
    campaigns: list[Path] = typer.Argument(..., help="Campaign folders to report on."),
    model: Path = typer.Option(..., "--model", help="Model file (JSON) from fbgcomp fit."),
    output: Path = typer.Option(..., "-o", "--output", help="Report folder to write (report.html + PNGs)."),
):
    """Write a self-contained HTML report: campaign summaries, paper figs. 6-9, Table 1 per
    axis with the stepwise history, validation metrics and sensor health."""
    import matplotlib  # noqa: F401 - a clear ImportError before any work

    from fbgcomp.io.campaign import read_campaign
    from fbgcomp.models.registry import load_model
    from fbgcomp.report.html import write_report

    with progress.stages("report", 2 + len(campaigns)) as stage:
        stage("reading the model and campaigns")
        fitted = load_model(model)
        data = [read_campaign(p) for p in campaigns]
        path = write_report(
            data,
            fitted,
            output,
            model_path=str(model),
            progress=lambda name: stage(f"analysing {name}"),
        )
        stage(f"written to {output}")
    n_fig = sum(1 for _ in output.glob("*.png"))
    typer.echo(f"report written to {path} ({len(data)} campaign(s), {n_fig} figure(s))")
