"""The default model on ram2's own independent data, logged, oriented, instrumented and described otherwise.

A hidden ram differs from ram2 in its physics and in much that is not: how its files are logged,
how it stands in its machine frame, which instruments it carries. This benchmark keeps ram2's
physics (the independent CalculiX data, not our twin) and rewrites the rest, as another site's
files and data sheet would have it. For each variant, as a user runs it:

    fbgcomp fit thermal_a static_xyz --machine V.yaml -o m.json
    fbgcomp validate m.json thermal_b thermal_c static_x

* files: a Unix-epoch clock; every column and campaign.yaml list in reverse order; 2 % of the
  interrogator and probe rows missing; a 0.2 Hz thermal interrogator with probes every 60 s; 1 Hz
  static interrogators; static_xyz without its loads.csv; an interrogator with 1 pm more white
  noise on every wavelength (ram2's own is ~0.24 pm; 1 pm is a common instrument's figure);
* orientation: the whole ram turned 90° about Z (x' = -y, y' = x: rails on +X, spindle heat
  towards +Y, the radiant load on +Y, thermal_c's force along Y) and mirrored (x' = -x); the
  physics is the same, so every figure must be ram2's with the axes exchanged;
* instruments: ram2 without S5 and S6 (four gratings), without S2 and S4 (gratings on +X and +Y
  only), without S1, and without each probe but T_surf (whose gratings then name T_bulk);
* the description a less careful data sheet gives, ram2's files as published: no radiant source
  declared, the radiant source on another face and zone, the bearing heat centred in the housing
  (80 W), one film coefficient everywhere, handbook materials, and the last three together; the
  housing probe at the housing's centre, a longer tool, another nominal bearing power, both rails
  locating, the carriage stations lower, every film doubled, no mesh section or nose patch.

Then, with ram2 as published: load histories superposed on its thermal campaigns through its
unit responses (exact: ram2 is linear, README section 6; :mod:`fbgcomp.bench.superpose`), so that
the load tracker is judged on independent thermal drift: small and large steps along each axis
under thermal_b's radiant load, a held Fy, an Fz (which the gratings cannot tell from a warming),
mixed forces, thermal_c with an Fy as well as its Fx, 72 short cutting loads, a load held 20 h
and loads applied as the spindle starts and stops.

Figures are given in ram2's own axes (a turned variant's dy is ram2's dx). Per variant: thermal_b
max |error| per axis, thermal_c's loaded axis in % of its peak and its dz, static_x's load
plateau error on its loaded axis, the range of the 95 % interval coverage over the three held-out
campaigns, and the axes (if any) worse than uncompensated (+0.5 µm).

    nice -n 10 .venv/bin/python benchmarks/bench_ram2_variants.py [--ram2 PATH] [--work DIR] [--only NAME ...]

Prints one line per variant, one per loaded campaign and, last, one JSON line with every figure.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
import zlib
from datetime import UTC, datetime
from pathlib import Path

import numpy as np
import pandas as pd
import yaml

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

REPO = Path(__file__).resolve().parents[1]
MACHINE = REPO / "examples" / "machines" / "ram2.yaml"
AXES = ("dx", "dy", "dz")
TRAIN = ("thermal_a", "static_xyz")
HELD = ("thermal_b", "thermal_c", "static_x")
THERMAL = ("thermal_a", "thermal_b", "thermal_c")
STATIC = ("static_x", "static_xyz")
LOADED_UM = 5.0
EPOCH_S = 1.773e9
NOISY_INTERROGATOR_NM = 1e-3  # a common interrogator's per-frame wavelength noise (1 pm)

# --- what a variant rewrites: f(campaign name, file name, table) and g(machine description) ----


def _epoch(name, fname, df):
    df["time_s"] = df["time_s"].astype(float) + EPOCH_S
    return df


def _reverse(name, fname, df):
    return df[["time_s", *reversed([c for c in df.columns if c != "time_s"])]]


def _reverse_lists(meta):
    for key in ("sensors", "temperature_probes"):
        meta[key] = list(reversed(meta[key]))


def _drop(name, fname, df):
    if fname not in ("fbg.csv", "temperatures.csv"):
        return df
    keep = np.random.default_rng(zlib.crc32(f"{name}/{fname}".encode())).random(len(df)) >= 0.02
    keep[0] = True  # the zero window stays
    return df[keep]


def _slow_thermal(name, fname, df):
    if name in THERMAL and fname == "fbg.csv":
        return df.iloc[::5]  # 1 s -> 5 s
    if name in THERMAL and fname == "temperatures.csv":
        return df.iloc[::6]  # 10 s -> 60 s
    return df


def _noisy_interrogator(name, fname, df):
    if fname != "fbg.csv":
        return df
    rng = np.random.default_rng(zlib.crc32(f"{name}/{fname}/noise".encode()))
    for col in [c for c in df.columns if c.endswith("_nm")]:
        df[col] = (df[col] + rng.normal(0.0, NOISY_INTERROGATOR_NM, len(df))).round(6)
    return df


def _slow_static(name, fname, df):
    return df.iloc[::10] if name in STATIC and fname == "fbg.csv" else df  # 10 Hz -> 1 Hz


def _negate(col):
    return -col.astype(float)


def _turn_table(name, fname, df):
    """x' = -y, y' = x for the interferometer and the load cell."""
    for x, y in (("dx_um", "dy_um"), ("fx_N", "fy_N")):
        if x in df.columns:
            old_x, old_y = df[x].astype(float), df[y].astype(float)
            df[x], df[y] = -old_y, old_x
    return df


def _mirror_table(name, fname, df):
    for x in ("dx_um", "fx_N"):
        if x in df.columns:
            df[x] = _negate(df[x])
    return df


TURN = {"+X": "+Y", "-X": "-Y", "+Y": "-X", "-Y": "+X"}
MIRROR = {"+X": "-X", "-X": "+X", "+Y": "+Y", "-Y": "-Y"}


def _faces(meta, faces):
    for s in meta["sensors"]:
        s["face"] = faces[s["face"]]


def _turn_machine(d):
    _faces(d, TURN)
    for p in d["probes"]:
        if p["kind"] == "point":
            p["x_mm"], p["y_mm"] = -p["y_mm"], p["x_mm"]
    for r in d["supports"]["rails"]:
        r["face"] = TURN[r["face"]]  # across: x on a Y face becomes y on an X face, same numbers
    d["thermal"]["films_W_per_m2K"] = {TURN.get(k, k): v for k, v in d["thermal"]["films_W_per_m2K"].items()}
    for h in d["thermal"]["heat_sources"]:
        if h["kind"] == "volume":
            x, y = h["x_mm"], h["y_mm"]
            h["x_mm"], h["y_mm"] = [-y[1], -y[0]], x
        else:
            h["face"] = TURN[h["face"]]


def _mirror_machine(d):
    _faces(d, MIRROR)
    for p in d["probes"]:
        if p["kind"] == "point":
            p["x_mm"] = -p["x_mm"]
    for r in d["supports"]["rails"]:
        r["face"] = MIRROR[r["face"]]
        if r["face"] in ("+Y", "-Y"):  # across is x on a Y face
            r["across_mm"] = [-r["across_mm"][1], -r["across_mm"][0]]
    d["thermal"]["films_W_per_m2K"] = {
        MIRROR.get(k, k): v for k, v in d["thermal"]["films_W_per_m2K"].items()
    }
    for h in d["thermal"]["heat_sources"]:
        if h["kind"] == "volume":
            h["x_mm"] = [-h["x_mm"][1], -h["x_mm"][0]]
        else:
            h["face"] = MIRROR[h["face"]]


def _without(*names, fallback=None):
    """Drop instruments from the files, campaign.yaml and the description; a grating whose
    nearest probe is dropped names ``fallback``."""
    gone = set(names)

    def table(name, fname, df):
        return df[[c for c in df.columns if c.rsplit("_", 1)[0] not in gone]]

    def lists(meta, probes_key):
        meta["sensors"] = [s for s in meta["sensors"] if s["name"] not in gone]
        for s in meta["sensors"]:
            if s.get("temperature_probe") in gone:
                s["temperature_probe"] = fallback
        meta[probes_key] = [p for p in meta[probes_key] if p["name"] not in gone]

    return table, (lambda meta: lists(meta, "temperature_probes")), (lambda d: lists(d, "probes"))


def _variant(what, table=None, meta=None, machine=None, drop=(), axes=None):
    return {"what": what, "table": table, "meta": meta, "machine": machine, "drop": drop, "axes": axes or {}}


#: name -> how it differs; ``axes`` maps a variant's axis to ram2's (a turned ram's dy is ram2's dx)
VARIANTS = {
    "as-published": _variant("ram2 as published"),
    "epoch-clock": _variant("every time_s + 1.773e9 s (Unix epoch)", table=_epoch),
    "reversed": _variant(
        "columns and campaign.yaml lists in reverse order", table=_reverse, meta=_reverse_lists
    ),
    "rows-dropped": _variant("2 % of interrogator and probe rows missing", table=_drop),
    "slow-thermal": _variant("thermal interrogator 0.2 Hz, probes every 60 s", table=_slow_thermal),
    "slow-static": _variant("static interrogators 1 Hz (10 Hz published)", table=_slow_static),
    "noisy-interrogator": _variant(
        "1 pm more white noise on every wavelength (ram2's own is ~0.24 pm)", table=_noisy_interrogator
    ),
    "no-loads-file": _variant("static_xyz without loads.csv", drop=(("static_xyz", "loads.csv"),)),
    "turned-90": _variant(
        "the ram turned 90° about Z: rails on +X, heat towards +Y, thermal_c's force along Y",
        table=_turn_table,
        meta=lambda m: _faces(m, TURN),
        machine=_turn_machine,
        axes={"dx": "dy", "dy": "dx"},
    ),
    "mirrored": _variant(
        "the ram mirrored (x' = -x)",
        table=_mirror_table,
        meta=lambda m: _faces(m, MIRROR),
        machine=_mirror_machine,
    ),
}
for _name, _what, _gone, _fb in (
    ("four-gratings", "without S5 and S6", ("S5", "S6"), None),
    ("two-faces", "without S2 and S4 (gratings on +X and +Y only)", ("S2", "S4"), None),
    ("no-S1", "without S1", ("S1",), None),
    ("no-T_bulk", "without T_bulk (S5, S6 name T_surf)", ("T_bulk",), "T_surf"),
    ("no-T_flange", "without T_flange (no housing probe)", ("T_flange",), None),
    ("no-T_amb", "without T_amb (no ambient probe)", ("T_amb",), None),
):
    _t, _m, _d = _without(*_gone, fallback=_fb)
    VARIANTS[_name] = _variant(_what, table=_t, meta=_m, machine=_d)


# --- the description a less careful data sheet gives (ram2's files as published) ----------------


def _no_radiant(d):
    d["thermal"]["heat_sources"] = [h for h in d["thermal"]["heat_sources"] if h["kind"] != "radiant"]


def _radiant_elsewhere(d):
    for h in d["thermal"]["heat_sources"]:
        if h["kind"] == "radiant":
            h["face"], h["z_mm"] = "-X", [0.0, 700.0]


def _spindle_centred(d):
    for h in d["thermal"]["heat_sources"]:
        if h["kind"] == "volume":
            h["x_mm"], h["y_mm"], h["z_mm"], h["nominal_W"] = (
                [-75.0, 75.0],
                [-75.0, 75.0],
                [-180.0, 0.0],
                80.0,
            )


def _films_uniform(d):
    d["thermal"]["films_W_per_m2K"] = dict.fromkeys(d["thermal"]["films_W_per_m2K"], 8.0)


def _handbook_materials(d):
    d["materials"]["cfrp"].update(
        {
            "E_L_GPa": 125.0,
            "E_T_GPa": 8.0,
            "cte_L_per_K": 0.0,
            "cte_T_per_K": 30.0e-6,
            "k_L_W_per_mK": 5.0,
            "k_T_W_per_mK": 0.5,
        }
    )
    housing = d["materials"]["housing"]
    if housing["cte_per_K"] > 18e-6:  # an aluminium alloy's handbook values (ram7)
        housing.update({"cte_per_K": 23.1e-6, "k_W_per_mK": 160.0})
    else:  # a steel's or cast iron's
        housing.update({"cte_per_K": 12.0e-6, "k_W_per_mK": 50.0})


def _rough(d):
    for f in (_spindle_centred, _films_uniform, _handbook_materials):
        f(d)


def _flange_probe_centred(d):
    for q in d["probes"]:
        if q["name"] == "T_flange":
            q["x_mm"], q["y_mm"] = 0.0, 0.0  # "in the spindle housing"


def _longer_tool(d):
    d["tool"]["ttp_below_housing_mm"] = 150.0


def _spindle_200w(d):
    for h in d["thermal"]["heat_sources"]:
        if h["kind"] == "volume":
            h["nominal_W"] = 200.0


def _spindle_60w(d):
    for h in d["thermal"]["heat_sources"]:
        if h["kind"] == "volume":
            h["nominal_W"] = 60.0


def _both_rails_locating(d):
    for r in d["supports"]["rails"]:
        r["locating"] = True
        # a locating rail floats in no direction (ram5's -Y rail floats along its normal)
        r.pop("floats", None)


def _stations_off(d):
    d["supports"]["carriages"] = [
        {"name": "lower", "z_range_mm": [900.0, 1000.0]},
        {"name": "upper", "z_range_mm": [1250.0, 1350.0]},
    ]


def _films_doubled(d):
    d["thermal"]["films_W_per_m2K"] = {k: 2.0 * v for k, v in d["thermal"]["films_W_per_m2K"].items()}


def _defaults_only(d):
    d.pop("mesh", None)
    d["tool"].pop("nose_patch_mm", None)


for _name, _what, _f in (
    (
        "flange-probe-centred",
        "description: T_flange at the housing's centre (the sheet: in the housing)",
        _flange_probe_centred,
    ),
    ("tool-150", "description: the TTP 150 mm below the housing (120 in ram2)", _longer_tool),
    ("spindle-200W", "description: the bearing heat's nominal power 200 W (120)", _spindle_200w),
    ("spindle-60W", "description: the bearing heat's nominal power 60 W (120)", _spindle_60w),
    ("rails-both-locating", "description: both rails locating (one floats in ram2)", _both_rails_locating),
    ("stations-off", "description: carriage stations 50 mm lower than ram2's", _stations_off),
    ("films-doubled", "description: every film coefficient doubled", _films_doubled),
    ("defaults", "description: no mesh section and no nose patch (the defaults)", _defaults_only),
    (
        "no-radiant-declared",
        "description: no radiant source (the data sheet lists the spindle only)",
        _no_radiant,
    ),
    (
        "radiant-elsewhere",
        "description: the radiant source on -X, z 0-700 (thermal_b heats +X, 300-1400)",
        _radiant_elsewhere,
    ),
    (
        "spindle-centred",
        "description: the bearing heat over the whole housing's middle, 80 W (not offset to +X)",
        _spindle_centred,
    ),
    ("films-uniform", "description: one film coefficient, 8 W/m2K, on every surface", _films_uniform),
    (
        "handbook-materials",
        "description: handbook CFRP (E 125/8 GPa, CTE 0/30e-6, k 5/0.5) and steel (12e-6, 50 W/mK)",
        _handbook_materials,
    ),
    (
        "rough-description",
        "description: spindle centred, uniform films and handbook materials together",
        _rough,
    ),
):
    VARIANTS[_name] = _variant(_what, machine=_f)


def _write_csv(df: pd.DataFrame, path: Path) -> None:
    """A table as a CSV file, every number in its shortest exact form (pyarrow's writer; pandas'
    ``to_csv`` took 21 of this benchmark's 263 s on eight variants, one profiled run)."""
    import pyarrow as pa  # the runtime extra, which the benchmarks have
    import pyarrow.csv as pacsv

    with open(path, "wb") as fh:
        fh.write((",".join(map(str, df.columns)) + "\n").encode())
        pacsv.write_csv(
            pa.Table.from_pandas(df, preserve_index=False), fh, pacsv.WriteOptions(include_header=False)
        )


def write_variant(name, data: Path, folder: Path) -> Path:
    """ram2's campaigns (the folder ``data``) and description rewritten as variant ``name``;
    returns the description's path."""
    v = VARIANTS[name]
    shutil.rmtree(folder, ignore_errors=True)
    for campaign in sorted(data.iterdir()):
        if not campaign.is_dir():
            continue
        dst = folder / campaign.name
        dst.mkdir(parents=True)
        for f in sorted(campaign.iterdir()):
            if (campaign.name, f.name) in v["drop"]:
                continue
            if f.suffix == ".csv" and v["table"] is not None:
                _write_csv(v["table"](campaign.name, f.name, pd.read_csv(f)), dst / f.name)
            elif f.name == "campaign.yaml" and v["meta"] is not None:
                meta = yaml.safe_load(f.read_text())
                v["meta"](meta)
                (dst / f.name).write_text(yaml.safe_dump(meta, sort_keys=False))
            else:
                shutil.copy(f, dst / f.name)
    desc = yaml.safe_load(MACHINE.read_text())
    if v["machine"] is not None:
        v["machine"](desc)
    path = folder / "machine.yaml"
    path.write_text(yaml.safe_dump(desc, sort_keys=False))
    return path


def _fbgcomp(*args):
    r = subprocess.run(
        [sys.executable, "-m", "fbgcomp", "-q", *map(str, args)], capture_output=True, text=True
    )
    if r.returncode != 0:
        raise SystemExit(f"fbgcomp {' '.join(map(str, args))} failed:\n{r.stderr}")


def run_variant(name, data: Path, work: Path) -> dict:
    """Rewrite, fit by default and judge one variant; figures in ram2's axes."""
    from fbgcomp.cli.demo import judge
    from fbgcomp.io.campaign import read_campaign
    from fbgcomp.models.registry import load_model

    folder = work / name
    machine = write_variant(name, data, folder)
    model = folder / "model.json"
    _fbgcomp("fit", *(folder / t for t in TRAIN), "--machine", machine, "-o", model)
    m = load_model(model)
    back = VARIANTS[name]["axes"]  # variant axis -> ram2 axis
    out = {}
    for held in HELD:
        j = judge(m, read_campaign(folder / held))
        axes = {
            back.get(a, a): {
                k: j["axes"][a].get(k)
                for k in (
                    "peak_um",
                    "max_abs_error_um",
                    "rms_error_um",
                    "pi95_coverage",
                    "pi95_mean_halfwidth_um",
                    "harm",
                )
            }
            for a in AXES
        }
        entry = {"axes": {a: axes[a] for a in AXES}}
        if "static_levels" in j:
            entry["plateaus"] = {back.get(a, a): j["static_levels"]["axes"][a] for a in AXES}
        out[held] = entry
    return out


#: name -> (ram2 campaign, load steps (start h, end h, (Fx, Fy, Fz) N))
LOADED = {
    "b+300N-radiant": ("thermal_b", [(10.0, 10.5, (300.0, 0.0, 0.0))]),
    "b+steps": (
        "thermal_b",
        [
            (2.0, 2.5, (150.0, 0.0, 0.0)),
            (3.0, 3.5, (300.0, 0.0, 0.0)),
            (4.0, 4.5, (600.0, 0.0, 0.0)),
            (5.0, 5.5, (1000.0, 0.0, 0.0)),
            (6.0, 6.5, (2000.0, 0.0, 0.0)),
            (11.0, 11.5, (300.0, 0.0, 0.0)),
            (12.0, 12.5, (0.0, 300.0, 0.0)),
            (13.0, 13.5, (0.0, 600.0, 0.0)),
            (20.0, 20.5, (-300.0, 0.0, 0.0)),
            (22.0, 22.5, (0.0, -300.0, 0.0)),
        ],
    ),
    "b+Fy-held": ("thermal_b", [(9.0, 12.0, (0.0, 2500.0, 0.0))]),
    "b+Fz": ("thermal_b", [(20.0, 24.0, (0.0, 0.0, -4000.0))]),
    "b+mixed": (
        "thermal_b",
        [
            (6.0, 8.0, (1500.0, 0.0, 0.0)),
            (14.0, 16.0, (0.0, -2000.0, 0.0)),
            (25.0, 27.0, (1000.0, 1000.0, 0.0)),
            (30.0, 31.0, (0.0, 0.0, 3000.0)),
        ],
    ),
    "c+Fy": ("thermal_c", [(1.0, 2.0, (0.0, -1500.0, 0.0)), (8.0, 10.0, (0.0, 2000.0, 0.0))]),
    # cutting: 200 N for 2 min every 5 min through the radiant load (8-14 h)
    "b+cutting": (
        "thermal_b",
        [(8.0 + k / 12.0, 8.0 + k / 12.0 + 2.0 / 60.0, (200.0, 0.0, 0.0)) for k in range(72)],
    ),
    "b+held-20h": ("thermal_b", [(2.0, 22.0, (0.0, 1500.0, 0.0))]),
    # applied as the spindle starts (0.42 h) and as it stops (4.92 h)
    "b+spindle": ("thermal_b", [(0.4, 1.0, (1000.0, 0.0, 0.0)), (4.9, 5.3, (0.0, 800.0, 0.0))]),
}


def run_loaded(data: Path, work: Path, model: Path | None = None) -> dict:
    """The default fit of ram2 as published (``model``: the as-published variant's, when it ran:
    the same campaigns and description), judged on its thermal campaigns with loads superposed."""
    from fbgcomp.bench.superpose import ram2_unit_responses, superpose_loads
    from fbgcomp.cli.demo import judge
    from fbgcomp.io.campaign import read_campaign
    from fbgcomp.models.registry import load_model

    if model is None:
        folder = work / "loaded"
        folder.mkdir(parents=True, exist_ok=True)
        model = folder / "model.json"
        _fbgcomp("fit", *(data / t for t in TRAIN), "--machine", MACHINE, "-o", model)
    m = load_model(model)
    C, G = ram2_unit_responses(json.loads((data.parent / "results.json").read_text()))
    out = {}
    for name, (base, steps) in LOADED.items():
        j = judge(m, superpose_loads(read_campaign(data / base), C, G, steps, name=name))
        plateaus = j["static_levels"]["axes"]
        out[name] = {
            "axes": {
                a: {k: j["axes"][a].get(k) for k in ("peak_um", "max_abs_error_um", "rms_error_um", "harm")}
                for a in AXES
            },
            "plateau_error_um": {a: plateaus[a]["max_plateau_error_um"] for a in AXES},
            "plateau_deflection_um": {a: plateaus[a]["max_plateau_deflection_um"] for a in AXES},
        }
    return out


def summary(fig: dict) -> dict:
    """The row of one variant: thermal_b per axis, thermal_c's loaded axis and dz, static_x's plateau,
    coverage range and harm."""
    b, c, s = fig["thermal_b"]["axes"], fig["thermal_c"]["axes"], fig["static_x"]
    loaded = max(("dx", "dy"), key=lambda a: c[a]["peak_um"])
    plateau = max(
        (
            p["error_pct_of_deflection"]
            for p in s["plateaus"].values()
            if p["max_plateau_deflection_um"] >= LOADED_UM
        ),
        default=float("nan"),
    )
    cov = [fig[h]["axes"][a]["pi95_coverage"] for h in HELD for a in AXES]
    return {
        "thermal_b_max_um": [b[a]["max_abs_error_um"] for a in AXES],
        "thermal_b_peak_um": [b[a]["peak_um"] for a in AXES],
        "thermal_c_loaded_axis": loaded,
        "thermal_c_loaded_pct": 100.0 * c[loaded]["max_abs_error_um"] / c[loaded]["peak_um"],
        "thermal_c_dz_um": c["dz"]["max_abs_error_um"],
        "static_x_plateau_pct": plateau,
        "pi95_range": [min(cov), max(cov)],
        "harm": [f"{h} {a}" for h in HELD for a in AXES if fig[h]["axes"][a]["harm"]],
    }


def main(argv=None) -> int:
    from fbgcomp.cli.demo import find_ram2

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--ram2", type=Path, help="the ram2 data set (default: as fbgcomp demo finds it)")
    ap.add_argument("--work", type=Path, help="keep the rewritten campaigns and models here")
    ap.add_argument("--only", nargs="+", choices=sorted(VARIANTS), help="run only these variants")
    args = ap.parse_args(argv)
    data, looked = find_ram2(args.ram2)
    if data is None:
        raise SystemExit(f"ram2 not found at {looked} (give --ram2)")
    tmp = None if args.work else tempfile.TemporaryDirectory(prefix="bench-ram2-variants-")
    work = Path(args.work or tmp.name)
    t0 = time.perf_counter()
    results, rows, harms = {}, {}, []
    print("ram2 (independent data), rewritten; default fit on thermal_a + static_xyz; figures in ram2's axes")
    print(
        f"{'variant':14} {'thermal_b dx / dy / dz max (µm)':>32} {'thermal_c loaded, dz':>22} "
        f"{'static_x':>9} {'PI95':>13}  harm"
    )
    for name in args.only or VARIANTS:
        results[name] = run_variant(name, data, work)
        r = rows[name] = summary(results[name])
        harms += [f"{name}: {h}" for h in r["harm"]]
        tb = " / ".join(f"{x:.2f}" for x in r["thermal_b_max_um"])
        loaded = f"{r['thermal_c_loaded_axis']} {r['thermal_c_loaded_pct']:.2f} %"
        print(
            f"{name:14} {tb:>32} {loaded:>12}"
            f"{r['thermal_c_dz_um']:>8.2f} µm {r['static_x_plateau_pct']:>7.2f} % "
            f"{r['pi95_range'][0]:.3f}-{r['pi95_range'][1]:.3f}  {', '.join(r['harm']) or 'none'}"
        )
    published = work / "as-published" / "model.json"
    loaded = run_loaded(data, work, published if "as-published" in results else None)
    print(
        "\nram2 as published, judged on its thermal campaigns with loads superposed (exact, ram2 is linear)"
    )
    print(
        f"{'campaign':15} "
        + "  ".join(f"{a + ' max / peak (µm)':>20}" for a in AXES)
        + "   worst plateau error (µm)"
    )
    for name, r in loaded.items():
        cells = [
            f"{r['axes'][a]['max_abs_error_um']:8.2f} / {r['axes'][a]['peak_um']:7.2f}"
            + (" WORSE" if r["axes"][a]["harm"] else "      ")
            for a in AXES
        ]
        harms += [f"{name}: {a}" for a in AXES if r["axes"][a]["harm"]]
        worst = " ".join(f"{a} {r['plateau_error_um'][a]:.2f}" for a in AXES)
        print(f"{name:15} " + "  ".join(cells) + f"   {worst}")
    print(
        f"do-no-harm: {'every axis of every variant and campaign' if not harms else 'BROKEN on ' + '; '.join(harms)}"
    )
    print(
        json.dumps(
            {
                "benchmark": "bench_ram2_variants",
                "date_utc": datetime.now(UTC).isoformat(timespec="seconds"),
                "seconds": round(time.perf_counter() - t0, 1),
                "ram2": str(data),
                "variants": {k: VARIANTS[k]["what"] for k in results},
                "rows": rows,
                "results": results,
                "loaded": {k: {"base": LOADED[k][0], "steps": LOADED[k][1], **loaded[k]} for k in loaded},
                "harm": harms,
            },
            default=float,
        )
    )
    if tmp is not None:
        tmp.cleanup()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
