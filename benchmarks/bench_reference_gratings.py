"""What strain-free reference gratings buy, on the twin (twin-only figures).

The built-in machine's five gratings are compensated by probes on other points of the ram
(T_surf, T_bulk), as in the paper. Here each gets a strain-free reference grating beside it
(``reference_lambda0_nm`` in the machine description, the same gauge temperature, no strain),
and the same two thermal campaigns are simulated with the same seeds. Printed:

* per sensor, the error of the temperature-compensated elongation against the twin's true
  host elongation, max |error| µm, probe- vs reference-compensated (eq. 2-4);
* the paper's recipe (``--features eq13 --stepwise``) fitted on thermal-36h and judged on
  thermal-36h-b with each compensation: max |error| per axis against the uncompensated drift;
* the default model (``physical``, ``fit --machine``) fitted on thermal-36h and judged on
  thermal-36h-b, once on the campaigns as recorded with their reference gratings and a
  description that declares them, once on the same campaigns with the reference gratings taken
  out (columns and declarations) and the plain description: max |error| and 95 % interval
  coverage per axis.

Both on the built-in machine and on the twin of ``examples/machines/ram2.yaml`` (a ram
guided on one face, whose lateral drift is large). Last line: one JSON object with the same
figures. Run: ``python benchmarks/bench_reference_gratings.py``.
These are figures on our own simulator, not an accuracy a user can expect on a real machine.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

from fbgcomp import optics
from fbgcomp.bench import virtual as bench
from fbgcomp.bench.virtual import load_scenario
from fbgcomp.io.campaign import Campaign
from fbgcomp.models.metrics import validation_metrics
from fbgcomp.models.mra import MRAModel
from fbgcomp.models.physical import PhysicalModel
from fbgcomp.structure import Twin, load_machine

ROOT = Path(__file__).resolve().parents[1]
AXES = ("dx", "dy", "dz")
SCENARIOS = ("thermal-36h", "thermal-36h-b")


def with_reference_gratings(machine):
    """The machine with a strain-free grating 2 nm above each sensor's wavelength."""
    sensors = [s.model_copy(update={"reference_lambda0_nm": s.lambda0_nm + 2.0}) for s in machine.sensors]
    return machine.model_copy(update={"sensors": type(machine.sensors)(sensors)})


def compensated_by(campaign: Campaign, how: str) -> Campaign:
    """The same measurements with each sensor compensated by its probe or its reference grating."""
    sensors = [
        s.model_copy(
            update={"temperature_probe": s.reference_probe if how == "reference" else s.temperature_probe}
        )
        for s in campaign.meta.sensors
    ]
    return campaign.replaced(meta=campaign.meta.model_copy(update={"sensors": sensors}))


def without_reference_gratings(campaign: Campaign) -> Campaign:
    """The same campaign as an installation without strain-free gratings records it: their
    fbg.csv columns and their declarations gone, each sensor compensated by its probe."""
    sensors = [s.model_copy(update={"reference_lambda0_nm": None}) for s in campaign.meta.sensors]
    meta = campaign.meta.model_copy(update={"sensors": sensors})
    fbg = campaign.fbg[[c for c in campaign.fbg.columns if not c.endswith("_ref_nm")]]
    return campaign.replaced(meta=meta, fbg=fbg)


def elongation_errors(campaign: Campaign, truth: dict) -> dict:
    """Max |compensated elongation - true host elongation| per sensor, µm."""
    a = campaign.aligned()
    true = np.column_stack(
        [
            np.interp(a.time_s, truth["time_s"], truth["sensor_elongation_um"][:, j])
            for j in range(len(a.sensor_names))
        ]
    )
    out = {}
    for j, s in enumerate(campaign.meta.sensors):
        k = a.probe_names.index(s.temperature_probe)
        dT = a.temperature_C[:, k] - a.temperature_zero_C[k]
        e = optics.elongation_um(
            a.wavelength_nm[:, j],
            a.wavelength_zero_nm[j],
            s.gauge_length_mm,
            dT,
            photoelastic=s.photoelastic,
            thermo_optic_per_K=s.thermo_optic_per_K,
            fibre_cte_per_K=s.fibre_cte_per_K,
        )
        out[s.name] = float(np.abs(e - (true[:, j] - true[0, j])).max())
    return out


def on_machine(label: str, plain) -> dict:
    """Every figure of the module docstring on the twin of the machine ``plain`` (a Machine)."""
    machine = with_reference_gratings(plain)
    twin = Twin(machine)
    runs = {name: bench.simulate(machine, load_scenario(name), seed=0, twin=twin) for name in SCENARIOS}
    result: dict = {}
    print(f"== {label}: max |compensated elongation - true| µm on thermal-36h-b (twin)")
    print(f"{'sensor':<8}{'probe':>10}{'reference':>11}")
    camp_b, truth_b = runs["thermal-36h-b"]
    errs = {how: elongation_errors(compensated_by(camp_b, how), truth_b) for how in ("probe", "reference")}
    for s in errs["probe"]:
        print(f"{s:<8}{errs['probe'][s]:>10.2f}{errs['reference'][s]:>11.2f}")
    result["elongation_max_err_um"] = errs
    a_b = camp_b.aligned()
    uncomp = np.abs(a_b.reference_um).max(axis=0)
    result["uncompensated_um"] = uncomp.tolist()
    print(f"\n{label}: fitted on thermal-36h, judged on thermal-36h-b: max |error| µm (twin)")
    print(f"{'model':<24}" + "".join(f"{ax:>9}" for ax in ("dx", "dy", "dz")) + "   PI95 dx/dy/dz")
    print(f"{'none (drift)':<24}" + "".join(f"{v:>9.2f}" for v in uncomp))
    result["eq13_max_err_um"] = {}
    for how in ("probe", "reference"):
        train = compensated_by(runs["thermal-36h"][0], how)
        model = MRAModel(features="eq13", stepwise=True).fit([train])
        pred = model.predict(compensated_by(camp_b, how))
        err = np.abs(pred - a_b.reference_um).max(axis=0)
        print(f"{'eq13 stepwise, ' + how:<24}" + "".join(f"{v:>9.2f}" for v in err))
        result["eq13_max_err_um"][how] = err.tolist()
    # the default as each installation would run it: the description declares the reference
    # gratings where the campaigns carry them, and neither where they do not
    result["physical"] = {}
    for how, described, strip in (
        ("reference", machine, lambda c: c),
        ("probe", plain, without_reference_gratings),
    ):
        model = PhysicalModel(machine=described).fit([strip(runs["thermal-36h"][0])])
        held_out = strip(camp_b)
        pred, half = model.predict_interval(held_out)
        ref = held_out.aligned(zero_window_s=model.zero_window_s).reference_um
        m = validation_metrics(ref, pred, half)
        err = [m["axes"][ax]["max_abs_error_um"] for ax in AXES]
        cov = [m["axes"][ax]["pi95_coverage"] for ax in AXES]
        line = f"{'default, ' + how:<24}" + "".join(f"{v:>9.2f}" for v in err)
        print(line + "   " + "/".join(f"{v:.2f}" for v in cov))
        result["physical"][how] = {"max_err_um": err, "pi95_coverage": cov}
    print()
    return result


def main():
    t_start = time.perf_counter()
    result = {
        "built-in": on_machine("built-in machine", load_machine(None)),
        "ram2.yaml": on_machine("ram2.yaml", load_machine(ROOT / "examples" / "machines" / "ram2.yaml")),
    }
    result["seconds"] = round(time.perf_counter() - t_start, 1)
    print(json.dumps(result))


if __name__ == "__main__":
    main()
