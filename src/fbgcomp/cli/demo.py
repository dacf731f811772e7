"""``fbgcomp demo``: the whole workflow on the built-in default machine.

1. build the FE twin of the default ram (``data/ram.yaml``);
2. simulate the four campaigns of the paper's programme on the virtual test bench: static-y
   and thermal-36h for fitting, static-xyz and thermal-36h-b (a different history, with a
   radiant load) held out for validation;
3. FE-calibrate the eq. 11 model and check the FBG resolution (paper sec. 2.3-2.4);
4. fit the regression on thermal-36h + static-y, validate it on the held-out campaigns;
5. write metrics (JSON), coefficient tables, figures in the spirit of the paper's figures 6-9,
   and the HTML report;
6. beside the twin, the independent check: the default model (``fbgcomp fit`` with no flags,
   the physical model) fitted on the ram2 data set's thermal_a + static_xyz with its machine
   description and judged on thermal_b, thermal_c and static_x, which it never saw. ram2 is
   found at ``--ram2``, else ``$FBGCOMP_RAM2``, else ``../shared/reference/ram2`` beside the
   repository; without it the demo says so in one line and carries on.

Both summaries use one table: per held-out campaign and axis, the max |error| (RMS) of each
model under the uncompensated drift (the error of a machine without compensation); static
campaigns on load-plateau means in % of the plateau deflection; WORSE where a model leaves an
axis worse than uncompensated (+ the 0.5 µm harm tolerance).

The FE twin, the bench, the models and the campaign reader are imported inside the functions
that use them so that ``fbgcomp --help``, which imports this module to mount ``demo``, starts
fast.
"""

from __future__ import annotations

import os
import sys
import time
from pathlib import Path

import typer

from fbgcomp.cli.twin import format_resolution
from fbgcomp.errors import InputError
from fbgcomp.tables import Column, format_number, format_table, text
from fbgcomp.units import AXES

TRAIN = ("thermal-36h", "static-y")
ZERO_WINDOW_S = 30.0
HELD_OUT = ("thermal-36h-b", "static-xyz")

#: The independent data set: where to look, what to fit on and what to judge on (its README).
RAM2_ENV = "FBGCOMP_RAM2"
RAM2_TRAIN = ("thermal_a", "static_xyz")
RAM2_HELD_OUT = ("thermal_b", "thermal_c", "static_x")
#: Repository root (src/fbgcomp/cli/demo.py → ../..), for the default ram2 place and its machine file.
REPO = Path(__file__).resolve().parents[3]
RAM2_MACHINE = REPO / "examples" / "machines" / "ram2.yaml"
#: Below this largest plateau deflection an axis is not loaded; its plateau error is shown in µm.
LOADED_UM = 5.0


def find_ram2(path=None):
    """The ram2 ``data`` folder: ``path``, else ``$FBGCOMP_RAM2``, else ../shared/reference/ram2
    beside the repository (the data set's root or its ``data`` folder). Returns (folder or None,
    where it was looked for)."""
    where = path or os.environ.get(RAM2_ENV) or REPO.parent / "shared" / "reference" / "ram2"
    root = Path(where)
    for folder in (root / "data", root):
        if all((folder / n).is_dir() for n in RAM2_TRAIN + RAM2_HELD_OUT):
            return folder, root
    return None, root


def fit_default(campaigns, machine=None, zero_window_s=10.0):
    """What ``fbgcomp fit CAMPAIGNS [--machine M] -o FILE`` fits with no other flag: the physical
    model (src/fbgcomp/models/physical.py)."""
    from fbgcomp.models.physical import PhysicalModel

    return PhysicalModel(machine=machine, zero_window_s=zero_window_s).fit(list(campaigns))


def prediction(model, campaign, served=False):
    """Deviation and 95 % half-width (m, 3) µm of ``model`` on ``campaign`` at its reference
    samples, as validation judges them: the model's own, or (``served``) those of the correction
    the runtime publishes (:func:`fbgcomp.bench.served.published`)."""
    if not served:
        return model.predict_interval(campaign)
    from fbgcomp.bench.served import published  # the runtime stack: only when served

    pred, half, _ = published(model, campaign)
    return pred, half


def judge(model, campaign, zero_window_s=None, served=False) -> dict:
    """validation_metrics of ``model`` on ``campaign``, with load-plateau errors when it has loads
    (``served``: of the correction the runtime publishes, :func:`prediction`)."""
    from fbgcomp.models.metrics import static_level_metrics, validation_metrics

    zero = model.zero_window_s if zero_window_s is None else zero_window_s
    aligned = campaign.aligned(zero_window_s=zero)
    pred, half = prediction(model, campaign, served)
    m = validation_metrics(aligned.reference_um, pred, half)
    if aligned.loads_N is not None:
        m["static_levels"] = static_level_metrics(aligned.loads_N, aligned.reference_um, pred)
    m["kind"] = campaign.meta.kind
    return m


def run_ram2(ram2=None, out=None) -> dict:
    """The independent check on ram2 (see the module docstring).

    Returns ``{"skipped": one-line reason}`` when the data set or its machine description is
    missing or unreadable, else the data set's place, the model id and per held-out campaign
    the metrics of :func:`judge`. The model is saved to ``out/ram2_model.json`` when ``out``.
    """
    from fbgcomp.io.campaign import read_campaign

    data, looked = find_ram2(ram2)
    if data is None:
        return {
            "skipped": f"ram2 not found at {looked} (give --ram2 or set {RAM2_ENV}): "
            "independent check skipped, twin figures only"
        }
    if not RAM2_MACHINE.is_file():
        return {"skipped": f"ram2 machine description not found at {RAM2_MACHINE}: independent check skipped"}
    try:
        train = [read_campaign(data / n) for n in RAM2_TRAIN]
        held = [read_campaign(data / n) for n in RAM2_HELD_OUT]
        model = fit_default(train, RAM2_MACHINE)
        validation = {c.meta.name: judge(model, c) for c in held}
    except InputError as exc:
        return {"skipped": f"ram2 unreadable ({exc.one_line()}): independent check skipped"}
    except Exception as exc:  # the twin's results stand; say what broke, in one line
        return {"skipped": f"ram2 check FAILED ({type(exc).__name__}: {exc})".replace("\n", " ")}
    if out is not None:
        model.save(Path(out) / "ram2_model.json")
    return {
        "data": str(data),
        "machine": str(RAM2_MACHINE),
        "model_type": model.model_type,
        "model_id": model.model_id,
        "trained_on": list(RAM2_TRAIN),
        "validation": validation,
    }


class _Steps:
    """Numbered progress lines on stderr, with the time each step took."""

    def __init__(self, total, quiet=False):
        self.total, self.n, self.quiet, self.t0 = total, 0, quiet, time.perf_counter()

    def __call__(self, text):
        self.n += 1
        if not self.quiet:
            print(
                f"[{self.n}/{self.total}] {text}  ({time.perf_counter() - self.t0:.0f} s)",
                file=sys.stderr,
                flush=True,
            )


def run_demo(
    out_dir="demo-out",
    *,
    machine_path=None,
    seed=0,
    quick=False,
    features="eq13",
    stepwise=True,
    quiet=False,
    report=True,
    resolution=None,
    ram2=None,
    independent=True,
) -> dict:
    """Run the demo and return its summary (also written to ``out_dir/metrics.json``)."""
    from fbgcomp.atomic import write_json
    from fbgcomp.bench.virtual import load_scenario, simulate
    from fbgcomp.io.campaign import read_campaign, write_campaign
    from fbgcomp.models.calibrated import CalibratedModel
    from fbgcomp.models.fe_calibrated import fe_calibrate, resolution_report
    from fbgcomp.models.metrics import (
        format_metrics,
        format_static_metrics,
        static_level_metrics,
        validation_metrics,
    )
    from fbgcomp.models.mra import MRAModel
    from fbgcomp.structure import Twin, load_machine

    out = Path(out_dir)
    (out / "campaigns").mkdir(parents=True, exist_ok=True)
    step = _Steps(5 + len(TRAIN) + len(HELD_OUT) + bool(independent), quiet)
    machine = load_machine(machine_path)
    twin = Twin(machine, resolution=resolution)
    step(f"built the FE twin of the default ram: {twin.n_dof} degrees of freedom")

    paths = {}
    for name in TRAIN + HELD_OUT:
        scenario = load_scenario(name)
        if quick:
            scenario = scenario.compressed(6.0)
        campaign, _truth = simulate(machine, scenario, seed=seed, twin=twin)
        paths[name] = write_campaign(campaign, out / "campaigns" / name)
        step(f"simulated {name} ({scenario.duration_s() / 3600:.2f} h)")

    fe_model, _design = fe_calibrate(machine, twin, seed=seed)
    fe_model.save(out / "fe_model.json")
    res = resolution_report(machine, twin)
    write_json(out / "resolution.json", res)
    (out / "resolution.txt").write_text(format_resolution(res) + "\n")
    step("FE-calibrated the eq. 11 model and checked the FBG resolution")

    train = [read_campaign(paths[n]) for n in TRAIN]
    # The lateral TTP estimate carries ~10 µm of sensor noise per 1 Hz sample, so the zero state's
    # own error falls as 1/sqrt(window): ~3 µm at 10 s, ~1.8 µm at 30 s, little gain beyond. The
    # bench rests >= 60 s before anything moves; half of that leaves margin for clock offsets.
    zero = ZERO_WINDOW_S
    regression = MRAModel(features=features, stepwise=stepwise, zero_window_s=zero).fit(train)
    regression.save(out / "regression_model.json")
    (out / "coefficients.txt").write_text(regression.summary() + "\n")
    calibrated = CalibratedModel(machine, features=features, stepwise=stepwise, zero_window_s=zero).fit(train)
    calibrated.save(out / "calibrated_model.json")
    (out / "calibrated_model.txt").write_text(calibrated.summary() + "\n")
    # the model a user gets from `fbgcomp fit` with the machine's description: its twin figures
    # beside the paper's model types (they are what bench_accuracy's twin rows measure)
    default = fit_default(train, machine)
    default.save(out / "default_model.json")
    step(
        f"fitted the default ({default.model_type}) model, the {features}"
        f"{' stepwise' if stepwise else ''} regression and the calibrated kinematic model on "
        f"{', '.join(TRAIN)}"
    )

    models = {"default": default, "regression": regression, "calibrated": calibrated, "fe_model": fe_model}
    summary = {
        "machine": "built-in default ram" if machine_path is None else str(machine_path),
        "n_dof": twin.n_dof,
        "features": features,
        "stepwise": stepwise,
        "trained_on": list(TRAIN),
        "zero_window_s": zero,
        "models": {
            k: {
                "type": m.model_type,
                "model_id": m.model_id,
                "zero_window_s": m.zero_window_s,
                "validation": {},
            }
            for k, m in models.items()
        },
    }
    texts = []
    for name in HELD_OUT:
        c = read_campaign(paths[name])
        aligned = c.aligned(zero_window_s=zero)
        for key, model in models.items():
            pred, half = model.predict_interval(c)
            m = validation_metrics(aligned.reference_um, pred, half)
            if aligned.loads_N is not None:
                m["static_levels"] = static_level_metrics(aligned.loads_N, aligned.reference_um, pred)
            m["kind"] = c.meta.kind
            summary["models"][key]["validation"][name] = m
            if key != "fe_model":
                texts.append(format_metrics(m, title=f"held-out {name} — {key} model"))
                if "static_levels" in m:
                    texts.append(format_static_metrics(m["static_levels"]))
    step(f"validated on the held-out {', '.join(HELD_OUT)}")

    if report:
        try:
            from fbgcomp.report.html import write_report
        except ImportError:  # the report module is optional in a minimal install
            pass
        else:
            write_report([read_campaign(paths[n]) for n in TRAIN + HELD_OUT], regression, out / "report")
    step("wrote figures and the report")

    if independent:
        summary["ram2"] = run_ram2(ram2, out)
        if "skipped" in summary["ram2"]:
            step(summary["ram2"]["skipped"])
        else:
            step(
                f"fitted the default model on ram2 {' + '.join(RAM2_TRAIN)}, judged on "
                f"{', '.join(RAM2_HELD_OUT)}"
            )
            for name, m in summary["ram2"]["validation"].items():
                texts.append(format_metrics(m, title=f"ram2 held-out {name} — default (physical) model"))
                if "static_levels" in m:
                    texts.append(format_static_metrics(m["static_levels"]))

    write_json(out / "metrics.json", summary)
    (out / "validation.txt").write_text("\n\n".join(texts) + "\n")
    if not quiet:
        print(_summary_text(summary, res, out))
    return summary


def _cell(m, axis, static):
    """One table cell: max |error| (RMS) in µm; on a static campaign, the load-plateau error in %
    of the plateau deflection on a loaded axis (µm on an axis that hardly moves)."""
    if static:
        v = m["static_levels"]["axes"][axis]
        if v["max_plateau_deflection_um"] >= LOADED_UM:
            return f"{format_number(v['error_pct_of_deflection'], 2)} %"
        return f"{format_number(v['max_plateau_error_um'], 2)} µm"
    a = m["axes"][axis]
    return f"{format_number(a['max_abs_error_um'], 2)} ({format_number(a['rms_error_um'], 2)})" + (
        " WORSE" if a["harm"] else ""
    )


def _uncompensated_cell(m, axis, static):
    if static:
        v = m["static_levels"]["axes"][axis]
        if v["max_plateau_deflection_um"] >= LOADED_UM:
            return f"100 % of {format_number(v['max_plateau_deflection_um'], 1)}"
        return f"{format_number(v['max_plateau_deflection_um'], 2)} µm"
    a = m["axes"][axis]
    return f"{format_number(a['uncompensated_max_um'], 2)} ({format_number(a['uncompensated_rms_um'], 2)})"


def summary_table(validation: dict, labels: dict) -> list:
    """The demo's summary table, one block per held-out campaign, with aligned columns.

    ``validation``: ``{campaign: {model key: metrics of judge()}}``; ``labels``: model key → name.
    Rows: the uncompensated drift (max |deviation| and its RMS), then each model. A block's
    header names the campaign and the unit (µm; a static campaign's cells carry their own: % of
    the plateau deflection on a loaded axis, µm on one that hardly moves).
    """
    from fbgcomp.models.metrics import HARM_TOLERANCE_UM

    lines = [
        f"  held-out max |error| µm (RMS) per axis under the uncompensated drift; static campaigns: "
        f"load-plateau means, % of the plateau deflection; WORSE = worse than uncompensated "
        f"+ {HARM_TOLERANCE_UM:g} µm"
    ]
    rows = []
    for camp, models in validation.items():
        first = next(iter(models.values()))
        static = first.get("kind") == "static" and "static_levels" in first
        unit = "" if static else " (µm)"
        rows.append(["model", f"{camp} {AXES[0]}{unit}"] + [f"{a}{unit}" for a in AXES[1:]])
        rows.append(["uncompensated"] + [_uncompensated_cell(first, a, static) for a in AXES])
        for key, m in models.items():
            rows.append([labels.get(key, key)] + [_cell(m, a, static) for a in AXES])
    if rows:
        # one table, the blocks' headers as rows, so that every block has the same columns
        table = format_table([text(rows[0][0])] + [Column(h) for h in rows[0][1:]], rows[1:], indent="  ")
        lines += table.splitlines()
    harmed: dict[str, list[str]] = {}
    for camp, models in validation.items():
        for key, m in models.items():
            axes = [a for a, v in m["axes"].items() if v["harm"]]
            if axes:
                harmed.setdefault(labels.get(key, key), []).append(f"{camp} {'/'.join(axes)}")
    lines.append(
        "  worse than uncompensated per sample: "
        + ("; ".join(f"{k}: {', '.join(v)}" for k, v in harmed.items()) if harmed else "none")
    )
    return lines


def _summary_text(summary, res, out) -> str:
    default = summary["models"].get("default")  # (a summary written before it was shown: none)
    names = {
        "default": f"default ({default['type']})" if default else "default",
        "regression": "regression (paper eq. 13)",
        "calibrated": "calibrated kinematic",
        "fe_model": "FE-calibrated eq. 11",
    }
    validation: dict[str, dict] = {}
    for key, info in summary["models"].items():
        for camp, m in info["validation"].items():
            validation.setdefault(camp, {})[key] = m
    lines = [
        "",
        f"fbgcomp demo — {summary['machine']}, FE twin with {summary['n_dof']} DOF (twin-only figures: "
        f"our own simulator); trained on {', '.join(summary['trained_on'])}, zero state "
        f"{summary['zero_window_s']:g} s"
        + (f" (the default model: {default['zero_window_s']:g} s, as fbgcomp fit)" if default else ""),
    ]
    lines += summary_table(validation, names)
    lines.append("  Lateral axes are noise- and heat-source-bound with this layout (docs/models.md).")
    lines.append(
        "FBG resolution (2σ): "
        + ", ".join(f"{a} {v['resolution_um']:.3f} µm" for a, v in res["axes"].items())
        + f"; rank {res['rank']} of {len(res['sensors'])} sensor combinations observable"
    )
    ram2 = summary.get("ram2")
    if ram2 is not None and "skipped" in ram2:
        lines.append("")
        lines.append(ram2["skipped"])
    elif ram2 is not None:
        lines.append("")
        lines.append(
            f"independent check — ram2 ({ram2['data']}), a ram we did not simulate: the default model "
            f"({ram2['model_type']}, fbgcomp fit --machine examples/machines/ram2.yaml) fitted on "
            f"{' + '.join(ram2['trained_on'])}, judged on campaigns it never saw"
        )
        lines += summary_table(
            {c: {"default": m} for c, m in ram2["validation"].items()},
            {"default": f"default ({ram2['model_type']})"},
        )
        lines.append("  figures of every model type and the targets: docs/accuracy.md")
    lines.append(
        f"results in {out}/ (default_model.json, regression_model.json, calibrated_model.json, fe_model.json, "
        + ("ram2_model.json, " if ram2 is not None and "skipped" not in ram2 else "")
        + "metrics.json, coefficients.txt, validation.txt, resolution.txt, report/)"
    )
    return "\n".join(lines)


def demo(
    output: Path = typer.Option(Path("demo-out"), "-o", "--output", help="Folder for the results."),
    machine: Path | None = typer.Option(None, help="Machine description YAML (default: the built-in ram)."),
    seed: int = typer.Option(0, help="Random seed of the simulated campaigns."),
    quick: bool = typer.Option(False, "--quick", help="6 h thermal campaigns instead of 36 h (for tests)."),
    mesh_resolution: float | None = typer.Option(
        None, "--mesh-resolution", help="FE mesh refinement (default: the machine's)."
    ),
    ram2: Path | None = typer.Option(
        None,
        "--ram2",
        help="The independent ram2 data set (default: "
        "$FBGCOMP_RAM2, else ../shared/reference/ram2 beside the repository).",
    ),
):
    """The main job: simulate, FE-calibrate, fit and validate on the built-in default machine, then
    the default model on the independent ram2 data set beside it (skipped in one line without it)."""
    run_demo(output, machine_path=machine, seed=seed, quick=quick, resolution=mesh_resolution, ram2=ram2)
