"""The thermal state observer (issue 12's suggested route) beside the default model, on ram2.

ram2's independent data, fitted as the default is (`fbgcomp fit thermal_a static_xyz --machine
M`), judged on thermal_b, thermal_c and static_x. Two thermal parts are compared on the same load
part (the default's load tracker, as served frame by frame):

* ``default``: the default model as it is (twin-learned map, housing calibration, policy);
* ``gated``: the observer while every heat input it estimates stays within 3 times its
  source's nominal value (:func:`~fbgcomp.models.physical.observer.plausible`), the default's
  correction from the first step it does not (latched);
* ``observer``: :class:`fbgcomp.models.physical.observer.ThermalObserver`, a Kalman filter over
  the twin's reduced thermal model (the description's heat sources plus a whole-face source per
  face as random walks, probes and gratings as measurements), with no calibration on the
  measured campaigns and no policy. Its parameters are the module's defaults, set from the
  instruments' data-sheet noise and the size of a spindle's power steps, not fitted to ram2;
* ``--observer``: the model ``fbgcomp fit --observer`` writes, served as the runtime serves it
  (the observer streamed on the frames with its probes' zero errors as states, averaged with the
  default's map while the gate holds), with its own 95 % interval coverage.

Each description variant is ram2.yaml changed as a less careful data sheet would give it (the
same changes as ``bench_ram2_variants.py``): the observer trusts the twin's dynamics, so these
show what it costs when the description is wrong. Figures are max |error| per axis, µm; WORSE
where an axis ends above uncompensated + 0.5 µm (issue 12's do-no-harm rule).

    nice -n 10 .venv/bin/python benchmarks/bench_observer.py [--ram2 PATH] [--only NAME ...]

Prints the table and, last, one JSON line.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from datetime import UTC, datetime
from pathlib import Path

import numpy as np
import yaml

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_ram2_variants import MACHINE, VARIANTS, _fbgcomp

ROOT = Path(__file__).resolve().parents[1]
TRAIN = ("thermal_a", "static_xyz")
HELD = ("thermal_b", "thermal_c", "static_x")
DESCRIPTIONS = (
    "as-published",
    "no-radiant-declared",
    "radiant-elsewhere",
    "films-doubled",
    "handbook-materials",
    "rails-both-locating",
)
AXES = ("dx", "dy", "dz")
HARM_ALLOWANCE_UM = 0.5
#: The applicability gate: the observer is trusted while every heat estimate stays within this
#: many times its source's nominal value, else the default's correction (latched).
GATE_K = 3.0


def observer_prediction(model, campaign, twin, machine):
    """The default's served prediction and the observer's (the default's load part plus the
    observer's thermal part), at the reference samples (n, 3) each, and the reference (n, 3)."""
    from fbgcomp.models.physical.observer import ThermalObserver, campaign_inputs, plausible

    pred, _, p, at = model._served(campaign)  # at the reference samples
    aligned = campaign.aligned(zero_window_s=model.zero_window_s)
    frames = model.frame_arrays(campaign, aligned)[0]
    load = (p.last_force_N @ p.C.T)[at] if p.has_load else np.zeros_like(pred)
    sensors = campaign.meta.sensors
    point = {q.name for q in machine.probes if q.kind == "point"}
    air = {q.name for q in machine.probes if q.kind == "ambient"}
    probes = [q for q in campaign.probe_names if q in point]
    ambient = [q for q in campaign.probe_names if q in air]
    obs = ThermalObserver(twin, sensors, probes)
    force = p.last_force_N if p.has_load else None
    ends, amb, pr, gr = campaign_inputs(
        campaign,
        sensors,
        probes,
        ambient,
        obs.step_s,
        force_N=force,
        force_time_s=frames,
        sensor_per_force_um_per_N=p.G if p.has_load else None,
    )
    r = obs.run(amb, pr, gr)
    t_ref = aligned.time_s
    k = np.searchsorted(ends, t_ref, side="right") - 1
    thermal = np.where(k[:, None] >= 0, r.ttp_um[np.clip(k, 0, None)], 0.0)
    nominal = [h.nominal for h in twin.machine.thermal.sources]
    trusted = plausible(r.heat, nominal, GATE_K)[np.clip(k, 0, None)]
    gated = np.where(trusted[:, None], load + thermal, pred)
    return pred, load + thermal, gated, aligned.reference_um, r


def run(name, ram2: Path, work: Path) -> dict:
    from fbgcomp.io.campaign import read_campaign
    from fbgcomp.models.registry import load_model
    from fbgcomp.structure import load_machine
    from fbgcomp.structure.scenarios import generic_heat_machine
    from fbgcomp.structure.twin import Twin

    desc = yaml.safe_load(MACHINE.read_text())
    if VARIANTS[name]["machine"] is not None:
        VARIANTS[name]["machine"](desc)
    folder = work / name
    folder.mkdir(parents=True, exist_ok=True)
    mpath = folder / "machine.yaml"
    mpath.write_text(yaml.safe_dump(desc, sort_keys=False))
    model_path = folder / "model.json"
    _fbgcomp("fit", *(ram2 / t for t in TRAIN), "--machine", mpath, "-o", model_path)
    model = load_model(model_path)
    obs_path = folder / "model-observer.json"
    _fbgcomp("fit", *(ram2 / t for t in TRAIN), "--machine", mpath, "--observer", "-o", obs_path)
    in_model = load_model(obs_path)
    machine = load_machine(mpath)
    twin = Twin(generic_heat_machine(machine))
    out = {}
    for held in HELD:
        campaign = read_campaign(ram2 / held)
        d, o, g, ref, r = observer_prediction(model, campaign, twin, machine)
        m, half = in_model.predict_interval(campaign)
        peak = np.abs(ref).max(axis=0)
        e_d, e_o, e_g, e_m = (np.abs(x - ref).max(axis=0) for x in (d, o, g, m))
        cover = (np.abs(m - ref) <= half).mean(axis=0)
        out[held] = {
            a: {
                "uncompensated_um": float(peak[j]),
                "default_um": float(e_d[j]),
                "observer_um": float(e_o[j]),
                "default_harm": bool(e_d[j] > peak[j] + HARM_ALLOWANCE_UM),
                "observer_harm": bool(e_o[j] > peak[j] + HARM_ALLOWANCE_UM),
                "gated_um": float(e_g[j]),
                "gated_harm": bool(e_g[j] > peak[j] + HARM_ALLOWANCE_UM),
                "in_model_um": float(e_m[j]),
                "in_model_harm": bool(e_m[j] > peak[j] + HARM_ALLOWANCE_UM),
                "in_model_pi95": float(cover[j]),
            }
            for j, a in enumerate(AXES)
        }
        out[held]["observer_heat_max"] = dict(
            zip(r.input_names, np.abs(r.heat).max(axis=0).round(1).tolist())
        )
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--ram2", type=Path, default=ROOT.parent / "shared" / "reference" / "ram2")
    ap.add_argument("--only", nargs="+", choices=DESCRIPTIONS)
    args = ap.parse_args(argv)
    data = args.ram2 / "data"
    if not data.is_dir():
        print(f"ram2 not found at {args.ram2}", file=sys.stderr)
        return 2
    start = time.perf_counter()
    results = {}
    print(
        "max |error| (µm) on ram2: uncompensated / default / observer / gated observer "
        "(!: above uncompensated + 0.5, per observer, gated, default)"
    )
    print(f"{'description':<22}{'campaign':<11}" + "".join(f"{a:>36}" for a in AXES))
    with tempfile.TemporaryDirectory(prefix="bench-observer-") as tmp:
        for name in args.only or DESCRIPTIONS:
            res = run(name, data, Path(tmp))
            results[name] = res
            for held in HELD:
                cells = []
                for a in AXES:
                    c = res[held][a]
                    flag = "".join(
                        "!" if c[k] else " " for k in ("observer_harm", "gated_harm", "default_harm")
                    )
                    cells.append(
                        f"{c['uncompensated_um']:8.2f} /{c['default_um']:7.2f} /{c['observer_um']:7.2f}"
                        f" /{c['gated_um']:7.2f}{flag}"
                    )
                print(f"{name:<22}{held:<11}" + "".join(f"{x:>36}" for x in cells), flush=True)
    print("\nfbgcomp fit --observer, served: max |error| µm (PI95 coverage); !: above uncompensated + 0.5")
    for name, res in results.items():
        for held in HELD:
            cells = [
                f"{res[held][a]['in_model_um']:7.2f} ({res[held][a]['in_model_pi95']:.3f})"
                + ("!" if res[held][a]["in_model_harm"] else " ")
                for a in AXES
            ]
            print(f"{name:<22}{held:<11}" + "".join(f"{x:>20}" for x in cells), flush=True)
    for who in ("observer", "gated", "default", "in_model"):
        harm = {
            k: sorted({f"{h}:{a}" for h in HELD for a in AXES if results[k][h][a][f"{who}_harm"]})
            for k in results
        }
        print(
            f"{who} WORSE than uncompensated: "
            + ("; ".join(f"{k} {', '.join(v)}" for k, v in harm.items() if v) or "none")
        )
    print(
        json.dumps(
            {
                "benchmark": "bench_observer",
                "date_utc": datetime.now(UTC).isoformat(timespec="seconds"),
                "seconds": round(time.perf_counter() - start, 1),
                "results": results,
            }
        )
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
