"""Gratings embedded in the wall or bonded inside the cavity: what describing their depth buys
(twin-only figures).

The paper's gratings are embedded in the CFRP; other installations bond them on the cavity side
of a wall. A grating at depth d in from a face's outer surface sits nearer the section's neutral
axis and reads the laminate's temperature at that depth, not at the surface. Here the twin of
``examples/machines/ram2.yaml`` is given its six gratings at one depth (``depth_mm`` in the
machine description: 7.5 mm, mid-wall, and 15 mm, the inner surface), the demo's campaigns are
simulated on it (seed 0), and the default model (``physical``, ``fit --machine``) is fitted on
thermal-36h + static-xyz and judged on thermal-36h-b, combined and static-y:

* **described**: the description gives the gratings' depth, as the installation has them;
* **on the surface**: the same campaigns, described as if every grating were on the outer
  surface (the campaign files then say nothing of the depth either) - what a user could write
  before the description had a depth.

Printed per case: max |error| per axis against the uncompensated peak, 95 % interval coverage,
and whether any axis ends worse than uncompensated (+0.5 µm). Last line: one JSON object.
Run: ``python benchmarks/bench_sensor_depth.py``. Figures on our own simulator, not an accuracy
a user can expect on a real machine: here the model's twin and the data's twin differ only by
the depth.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

from fbgcomp.bench import virtual as bench
from fbgcomp.bench.virtual import load_scenario
from fbgcomp.io.campaign import Campaign
from fbgcomp.models.metrics import validation_metrics
from fbgcomp.models.physical import PhysicalModel
from fbgcomp.structure import Twin, load_machine

ROOT = Path(__file__).resolve().parents[1]
AXES = ("dx", "dy", "dz")
TRAIN = ("thermal-36h", "static-xyz")
HELD_OUT = ("thermal-36h-b", "combined", "static-y")
HARM_ALLOWANCE_UM = 0.5  # the interferometer's own noise on an axis that hardly moves


def at_depth(machine, depth_mm: float):
    """The machine with every grating ``depth_mm`` in from its face's outer surface."""
    sensors = [s.model_copy(update={"depth_mm": depth_mm}) for s in machine.sensors]
    return machine.model_copy(update={"sensors": type(machine.sensors)(sensors)})


def without_depth(campaign: Campaign) -> Campaign:
    """The same measurements with campaign.yaml silent on the gratings' depth."""
    sensors = [s.model_copy(update={"depth_mm": None}) for s in campaign.meta.sensors]
    return campaign.replaced(meta=campaign.meta.model_copy(update={"sensors": sensors}))


def judged(model, campaign: Campaign) -> dict:
    """Max |error|, uncompensated peak and PI95 coverage per axis on one held-out campaign."""
    pred, half = model.predict_interval(campaign)
    ref = campaign.aligned(zero_window_s=model.zero_window_s).reference_um
    m = validation_metrics(ref, pred, half)
    out = {}
    for j, ax in enumerate(AXES):
        err = m["axes"][ax]["max_abs_error_um"]
        peak = float(np.abs(ref[:, j]).max())
        out[ax] = {
            "max_err_um": err,
            "peak_um": peak,
            "pi95_coverage": m["axes"][ax]["pi95_coverage"],
            "harm": bool(err > peak + HARM_ALLOWANCE_UM),
        }
    return out


def at(depth_mm: float, plain) -> dict:
    """Both cases of the module docstring with the gratings ``depth_mm`` deep."""
    machine = at_depth(plain, depth_mm)
    twin = Twin(machine)
    runs = {
        name: bench.simulate(machine, load_scenario(name), seed=0, twin=twin)[0] for name in TRAIN + HELD_OUT
    }
    result: dict = {}
    print(f"== gratings {depth_mm:g} mm deep (twin of ram2.yaml): max |error| / peak µm, PI95 dx/dy/dz")
    for case, described, strip in (
        ("described", machine, lambda c: c),
        ("on the surface", plain, without_depth),
    ):
        model = PhysicalModel(machine=described).fit([strip(runs[n]) for n in TRAIN])
        result[case] = {}
        for name in HELD_OUT:
            r = judged(model, strip(runs[name]))
            result[case][name] = r
            cells = "  ".join(f"{r[ax]['max_err_um']:7.2f} /{r[ax]['peak_um']:7.2f}" for ax in AXES)
            cov = "/".join(f"{r[ax]['pi95_coverage']:.2f}" for ax in AXES)
            harm = [ax for ax in AXES if r[ax]["harm"]]
            print(f"  {case:<16}{name:<15}{cells}   {cov}   harm: {', '.join(harm) or 'none'}")
    print()
    return result


def main():
    t_start = time.perf_counter()
    plain = load_machine(ROOT / "examples" / "machines" / "ram2.yaml")
    result = {f"{d:g} mm": at(d, plain) for d in (7.5, 15.0)}
    result["seconds"] = round(time.perf_counter() - t_start, 1)
    print(json.dumps({"benchmark": "bench_sensor_depth", **result}))


if __name__ == "__main__":
    main()
