"""The default model on rams we did not tune for: variants of ram2's description, on the twin.

TWIN-ONLY figures (our own simulator): they show whether the default fit runs and does no harm
on machine descriptions that differ from ram2's in the ways issue 12 lists (rails on adjacent or
opposite faces, fewer or more gratings, no housing or ambient probe, other heat sources) and in
the ram itself (size, materials, layup, a cast-iron box), not the accuracy a user can expect.
Each variant is ``examples/machines/ram2.yaml`` changed as a user with that data sheet would
write it; for each, as a user runs it:

    fbgcomp simulate --machine V.yaml --scenario thermal-36h   --seed 0   (training)
    fbgcomp simulate --machine V.yaml --scenario static-xyz    --seed 0   (training)
    fbgcomp simulate --machine V.yaml --scenario thermal-36h-b --seed 1   (held out)
    fbgcomp simulate --machine V.yaml --scenario combined      --seed 2   (held out)
    fbgcomp fit thermal-36h static-xyz --machine V.yaml -o m.json
    fbgcomp validate m.json thermal-36h-b combined

and once more fitted on thermal-36h alone (a user without a loaded campaign).

    nice -n 10 .venv/bin/python benchmarks/bench_variants.py [--work DIR] [--only NAME ...]

Prints per variant and held-out campaign the max |error| against the uncompensated peak per axis
(WORSE where an axis ends above uncompensated + 0.5 µm) and, last, one JSON line.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from datetime import UTC, datetime
from pathlib import Path

import yaml

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

REPO = Path(__file__).resolve().parents[1]
BASE = REPO / "examples" / "machines" / "ram2.yaml"
AXES = ("dx", "dy", "dz")
SCENARIOS = (("thermal-36h", 0), ("static-xyz", 0), ("thermal-36h-b", 1), ("combined", 2))
HELD = ("thermal-36h-b", "combined")


def _adjacent(d):
    d["supports"]["rails"] = [
        {"face": "-Y", "across_mm": [-150.0, -105.0], "locating": True},
        {"face": "-X", "across_mm": [-150.0, -105.0], "locating": False},
    ]


def _opposite(d):
    d["supports"]["rails"] = [
        {"face": "-Y", "across_mm": [-150.0, -105.0], "locating": True},
        {"face": "+Y", "across_mm": [-150.0, -105.0], "locating": False},
    ]


def _opposite_floating(d):
    # the usual opposite-face guide: the floating side lets the box grow towards it
    d["supports"]["rails"] = [
        {"face": "+Y", "across_mm": [-40.0, 40.0], "locating": True},
        {"face": "-Y", "across_mm": [-40.0, 40.0], "floats": "normal"},
    ]


def _four(d):
    d["sensors"] = d["sensors"][:4]
    d["probes"] = [p for p in d["probes"] if p["name"] != "T_bulk"]


def _eight(d):
    d["sensors"] += [
        dict(s, name=s["name"] + "b", offset_mm=80.0, lambda0_nm=s["lambda0_nm"] + 30.0)
        for s in d["sensors"][:4]
    ]


def _no_housing_probe(d):
    d["probes"] = [p for p in d["probes"] if p["name"] != "T_flange"]


def _no_ambient_probe(d):
    d["probes"] = [p for p in d["probes"] if p["kind"] != "ambient"]


def _other_sources(d):
    d["thermal"]["heat_sources"] = [
        d["thermal"]["heat_sources"][0],
        {
            "name": "motor",
            "kind": "volume",
            "x_mm": [-60.0, 60.0],
            "y_mm": [-60.0, 60.0],
            "z_mm": [-60.0, 0.0],
            "nominal_W": 40.0,
        },
        {
            "name": "radiant",
            "kind": "radiant",
            "face": "-X",
            "z_mm": [0.0, 700.0],
            "absorptivity": 0.8,
            "nominal_W_per_m2": 120.0,
        },
    ]


def _bigger(d):
    """A longer, wider, rectangular ram: 400 x 250 mm, 20 mm walls, 2000 mm long, a 250 mm
    housing, its heat sources and probes moved to match, the radiant on +Y."""
    d["ram"].update(outer_width_mm=400.0, outer_depth_mm=250.0, wall_mm=20.0, length_mm=2000.0)
    d["housing"].update(width_mm=400.0, depth_mm=250.0, height_mm=250.0)
    d["tool"].update(ttp_below_housing_mm=150.0, nose_patch_mm=[150.0, 150.0])
    where = {"T_bulk": (190.0, 0.0, 1000.0), "T_surf": (0.0, 125.0, 400.0), "T_flange": (-200.0, 0.0, -125.0)}
    for p in d["probes"]:
        if p["name"] in where:
            p["x_mm"], p["y_mm"], p["z_mm"] = where[p["name"]]
    for s in d["sensors"][4:]:
        s.update(z_start_mm=1000.0, z_end_mm=1500.0)
    sup = d["supports"]
    sup["rails"] = [
        {"face": "-Y", "across_mm": [-200.0, -150.0], "locating": True},
        {"face": "-Y", "across_mm": [150.0, 200.0], "locating": False},
    ]
    sup["carriages"] = [
        {"name": "lower", "z_range_mm": [1200.0, 1320.0]},
        {"name": "upper", "z_range_mm": [1850.0, 2000.0]},
    ]
    sup["nut"]["z_mm"] = 2000.0
    spindle, radiant = d["thermal"]["heat_sources"]
    spindle.update(x_mm=[-40.0, 40.0], y_mm=[-40.0, 40.0], z_mm=[-250.0, -150.0], nominal_W=200.0)
    radiant.update(face="+Y", z_mm=[800.0, 2000.0], absorptivity=0.9, nominal_W_per_m2=80.0)


def _other_materials(d):
    """A stiffer, negative-CTE carbon fibre (E_L 135 GPa, alpha_L -0.3e-6 /K) and a cast-iron
    housing (120 GPa, 10.5e-6 /K)."""
    d["materials"]["cfrp"].update(
        E_L_GPa=135.0,
        E_T_GPa=8.5,
        G_LT_GPa=5.0,
        cte_L_per_K=-0.3e-6,
        cte_T_per_K=32e-6,
        k_L_W_per_mK=4.5,
        k_T_W_per_mK=0.5,
        density_kg_per_m3=1550.0,
        specific_heat_J_per_kgK=1000.0,
    )
    d["materials"]["housing"].update(
        E_GPa=120.0,
        cte_per_K=10.5e-6,
        k_W_per_mK=50.0,
        density_kg_per_m3=7200.0,
        specific_heat_J_per_kgK=500.0,
    )


def _layup(d):
    """A layup with off-axis plies: alpha_L 2e-6 /K, so the gratings see real thermal
    elongation; softer along Z, stiffer across."""
    d["materials"]["cfrp"].update(
        E_L_GPa=60.0, E_T_GPa=25.0, cte_L_per_K=2.0e-6, cte_T_per_K=8e-6, k_L_W_per_mK=3.0, k_T_W_per_mK=0.8
    )


def _cast_iron(d):
    """Not CFRP: an isotropic cast-iron box (120 GPa, 10.5e-6 /K, 50 W/(m K)), 20 mm walls, so the
    gratings read its real thermal elongation."""
    d["ram"]["wall_mm"] = 20.0
    d["materials"]["cfrp"].update(
        E_L_GPa=120.0,
        E_T_GPa=120.0,
        G_LT_GPa=46.0,
        nu_LT=0.3,
        nu_TT=0.3,
        cte_L_per_K=10.5e-6,
        cte_T_per_K=10.5e-6,
        k_L_W_per_mK=50.0,
        k_T_W_per_mK=50.0,
        density_kg_per_m3=7200.0,
        specific_heat_J_per_kgK=500.0,
    )


#: name -> (what it changes, edit of the description)
VARIANTS = {
    "adjacent-rails": ("locating rail on -Y, floating rail on -X", _adjacent),
    "opposite-rails": ("locating rail on -Y, floating rail on +Y", _opposite),
    "opposite-rails-floating": (
        "locating rail on +Y, the -Y rail floating along its normal (central strips)",
        _opposite_floating,
    ),
    "four-gratings": ("S1-S4 only, no T_bulk", _four),
    "eight-gratings": ("S1-S6 and four more, 80 mm off the face centre", _eight),
    "no-housing-probe": ("no T_flange", _no_housing_probe),
    "no-ambient-probe": ("no T_amb", _no_ambient_probe),
    "other-sources": ("spindle, a 40 W motor zone, radiant on the lower half of -X", _other_sources),
    "bigger-ram": ("400 x 250 x 2000 mm ram, 250 mm housing, 200 W spindle, radiant on +Y", _bigger),
    "other-materials": ("CFRP with alpha_L -0.3e-6 /K, cast-iron housing", _other_materials),
    "off-axis-layup": ("CFRP with alpha_L 2e-6 /K (off-axis plies)", _layup),
    "cast-iron-ram": ("an isotropic cast-iron box instead of CFRP, 20 mm walls", _cast_iron),
}


def _run(*args):
    r = subprocess.run(
        [sys.executable, "-m", "fbgcomp", "-q", *map(str, args)], capture_output=True, text=True
    )
    if r.returncode != 0:
        raise SystemExit(f"fbgcomp {' '.join(map(str, args))} failed:\n{r.stderr}")
    return r


def variant(name, work: Path) -> dict:
    """Simulate, fit (with and without the loaded campaign) and judge one variant."""
    from fbgcomp.cli.demo import judge
    from fbgcomp.io.campaign import read_campaign
    from fbgcomp.models.registry import load_model

    d = yaml.safe_load(BASE.read_text())
    VARIANTS[name][1](d)
    folder = work / name
    folder.mkdir(parents=True, exist_ok=True)
    machine = folder / "machine.yaml"
    machine.write_text(yaml.safe_dump(d, sort_keys=False))
    for scenario, seed in SCENARIOS:
        if not (folder / scenario).is_dir():
            _run(
                "simulate",
                "--machine",
                machine,
                "--scenario",
                scenario,
                "--seed",
                seed,
                "-o",
                folder / scenario,
            )
    out = {}
    for fit, train in (
        ("thermal+static", ("thermal-36h", "static-xyz")),
        ("thermal alone", ("thermal-36h",)),
    ):
        model = folder / f"{fit.replace(' ', '_').replace('+', '_')}.json"
        _run("fit", *[folder / t for t in train], "--machine", machine, "-o", model)
        m = load_model(model)
        out[fit] = {}
        for held in HELD:
            j = judge(m, read_campaign(folder / held))
            out[fit][held] = {
                a: {k: j["axes"][a][k] for k in ("peak_um", "max_abs_error_um", "pi95_coverage", "harm")}
                for a in AXES
            }
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument(
        "--work", type=Path, help="keep the campaigns and models here (default: a temporary folder)"
    )
    ap.add_argument("--only", nargs="+", choices=sorted(VARIANTS), help="run only these variants")
    args = ap.parse_args(argv)
    tmp = None if args.work else tempfile.TemporaryDirectory(prefix="bench-variants-")
    work = Path(args.work or tmp.name)
    results, harms = {}, []
    t0 = time.perf_counter()
    print("TWIN-ONLY: the default model on variants of ram2's description (our own simulator)")
    print(
        f"{'variant':18} {'fit':15} {'held out':14} "
        + "  ".join(f"{a + ' max/peak (µm)':>22}" for a in AXES)
        + "  PI95 dx/dy/dz"
    )
    for name in args.only or VARIANTS:
        results[name] = variant(name, work)
        for fit, per in results[name].items():
            for held, axes in per.items():
                cells = []
                for a in AXES:
                    x = axes[a]
                    cells.append(
                        f"{x['max_abs_error_um']:9.2f} / {x['peak_um']:7.2f}"
                        + (" WORSE" if x["harm"] else "      ")
                    )
                    if x["harm"]:
                        harms.append(f"{name} ({fit}) {held} {a}")
                cover = "/".join(f"{axes[a]['pi95_coverage']:.2f}" for a in AXES)
                print(f"{name:18} {fit:15} {held:14} " + "  ".join(cells) + f"  {cover}")
    print(f"do-no-harm: {'every axis of every variant' if not harms else 'BROKEN on ' + ', '.join(harms)}")
    print(
        json.dumps(
            {
                "benchmark": "bench_variants",
                "date_utc": datetime.now(UTC).isoformat(timespec="seconds"),
                "seconds": round(time.perf_counter() - t0, 1),
                "variants": {k: VARIANTS[k][0] for k in results},
                "results": results,
                "harm": harms,
            }
        )
    )
    if tmp is not None:
        tmp.cleanup()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
