"""The physical model's load tracker (``PhysicalPredictor._track_load``): this checkout against a
baseline commit, on the same model file and the same frames.

A load transition (a force stepping on or off, a ramp) is tracked frame by frame; the stretches
between transitions run vectorised. ram2's default fit (``fbgcomp fit thermal_a static_xyz
--machine examples/machines/ram2.yaml``, fitted once by this checkout) tracks, from rest:

* **static_x at 10 Hz** and **static_xyz at 100 Hz** (its first 200 s): ram2's static campaigns
  resampled with fresh noise of their own level (as ``tests/test_physical.py`` serves them):
  mostly transition frames;
* **static_x at 10 Hz, one frame per call**: the runtime's batches of one;
* **thermal_b listening** (``listen=True``: how far heat and noise move the low-passed force
  reading, which calibrates the drift allowance in every fit): no step is taken.

Each case runs in a fresh process with the tree's ``src`` first on ``PYTHONPATH``, for this
checkout and for ``--baseline`` (default b84c834, the per-frame recursion on numpy arrays) in a
temporary git worktree, interleaved, median of ``--reps``. The forces of both must agree to
1e-6 N (exit 1 otherwise). Last line: one JSON object.

    .venv/bin/python benchmarks/bench_load_tracker.py [--ram2 PATH] [--reps 3] [--baseline REV]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from datetime import UTC, datetime
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
CASES = ("static_x@10", "static_xyz@100", "static_x@10/1", "thermal_b/listen")


def _frames(model, campaign, rate_hz, seed=0):
    """The campaign's frames resampled to ``rate_hz`` with fresh white noise of their own level."""
    import numpy as np

    fbg, temps = campaign.fbg, campaign.temperatures
    t_in = fbg["time_s"].to_numpy()
    w_in = fbg[[f"{s}_nm" for s in model.sensor_names]].to_numpy()
    t = np.arange(0.0, t_in[-1], 1.0 / rate_hz)
    w = np.column_stack([np.interp(t, t_in, w_in[:, j]) for j in range(w_in.shape[1])])
    sd = np.std(np.diff(w_in[:100], axis=0), axis=0) / np.sqrt(2)
    w += np.random.default_rng(seed).normal(0.0, sd, w.shape)
    T = np.column_stack([np.interp(t, temps["time_s"], temps[f"{p}_C"]) for p in model.probe_names_])
    zero = t < model.zero_window_s
    return t, w, T, w[zero].mean(axis=0), T[zero].mean(axis=0)


def worker(model_path: Path, data: Path, case: str, out: Path) -> None:
    """One case in this process (the tree on PYTHONPATH): prints seconds and transition frames
    as JSON, writes the forces to ``out`` (.npy)."""
    import numpy as np

    from fbgcomp.io.campaign import read_campaign
    from fbgcomp.models.physical.predictor import PhysicalPredictor
    from fbgcomp.models.registry import load_model

    model = load_model(model_path)
    name, _, how = case.partition("/")
    name, _, rate = name.partition("@")
    campaign = read_campaign(data / name)
    if rate:
        t, w, T, w0, T0 = _frames(model, campaign, float(rate))
        keep = t < 200.0 if float(rate) >= 100.0 else slice(None)
        t, w, T = t[keep], w[keep], T[keep]
    else:
        aligned = campaign.aligned(zero_window_s=model.zero_window_s)
        w, T, w0, T0 = model.instrument_arrays(aligned)
        t = aligned.time_s
    p = PhysicalPredictor(model)
    P = len(p.probe_names)
    e = p._fmap.base(np.atleast_2d(w), T[:, :P], w0, T0[:P])[:, p._keep]
    step = 1 if how == "1" else len(e)
    forces, moving, state = [], 0, None
    t0 = time.perf_counter()
    for lo in range(0, len(e), step):
        new = {}
        f, _, _ = p._track_load(e[lo : lo + step], t[lo : lo + step], state, new, listen=how == "listen")
        state = new["load"]
        forces.append(f)
        moving += int(p.last_transition.any(axis=1).sum())
    seconds = time.perf_counter() - t0
    np.save(out, np.vstack(forces))
    print(json.dumps({"seconds": seconds, "frames": len(e), "transition_frames": moving}))


def _run(src: Path, model: Path, data: Path, case: str, out: Path) -> dict:
    env = {**os.environ, "PYTHONPATH": str(src), "OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1"}
    cmd = [sys.executable, __file__, "--worker", str(model), str(data), case, str(out)]
    r = subprocess.run(cmd, env=env, capture_output=True, text=True, cwd=src.parent)
    if r.returncode != 0:
        raise SystemExit(f"{case} failed ({src}):\n{r.stderr[-3000:]}")
    return json.loads(r.stdout.strip().splitlines()[-1])


def main(argv=None) -> int:
    if argv is None and len(sys.argv) > 1 and sys.argv[1] == "--worker":
        worker(Path(sys.argv[2]), Path(sys.argv[3]), sys.argv[4], Path(sys.argv[5]))
        return 0
    import numpy as np

    from _loopback import baseline_worktree, git_commit
    from fbgcomp.cli.demo import RAM2_MACHINE, find_ram2

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--ram2", type=Path, help="the ram2 data set (default: as fbgcomp demo finds it)")
    ap.add_argument("--reps", type=int, default=3)
    ap.add_argument("--baseline", default="b84c834", help="the commit to compare with (default b84c834)")
    args = ap.parse_args(argv)
    data, looked = find_ram2(args.ram2)
    if data is None:
        raise SystemExit(f"ram2 not found at {looked} (give --ram2)")
    with (
        tempfile.TemporaryDirectory(prefix="bench-load-tracker-") as folder,
        baseline_worktree(args.baseline, Path(folder) / "baseline") as base,
    ):
        tmp = Path(folder)
        model = tmp / "model.json"
        fit = [sys.executable, "-m", "fbgcomp", "-q", "fit", data / "thermal_a", data / "static_xyz"]
        subprocess.run(
            [*map(str, fit), "--machine", str(RAM2_MACHINE), "-o", str(model)],
            check=True,
            capture_output=True,
        )
        runs: dict[tuple[str, str], list[dict]] = {}
        for rep in range(args.reps):
            for case in CASES:
                for who, src in (("baseline", base / "src"), ("now", REPO / "src")):
                    out = tmp / f"{who}-{case.replace('/', '_')}-{rep}.npy"
                    runs.setdefault((who, case), []).append(_run(src, model, data, case, out))
        worst = {
            case: float(
                np.max(
                    np.abs(
                        np.load(tmp / f"now-{case.replace('/', '_')}-0.npy")
                        - np.load(tmp / f"baseline-{case.replace('/', '_')}-0.npy")
                    )
                )
            )
            for case in CASES
        }
    load = os.getloadavg()[0]
    print(f"load tracker, median of {args.reps} (load average {load:.1f}); baseline {args.baseline}")
    head = ("case", "frames", "moving", "baseline", "now", "ratio", "us/frame", "max |dF| N")
    print(" ".join(f"{h:{w}}" for h, w in zip(head, ("18", ">7", ">7", ">9", ">8", ">6", ">9", ">11"))))
    figures = {}
    for case in CASES:
        b = statistics.median(r["seconds"] for r in runs["baseline", case])
        n = statistics.median(r["seconds"] for r in runs["now", case])
        first = runs["now", case][0]
        per = 1e6 * n / max(first["frames"], 1)
        print(
            f"{case:18} {first['frames']:>7} {first['transition_frames']:>7} {b:>8.3f}s {n:>7.3f}s "
            f"{b / n:>5.2f}x {per:>9.1f} {worst[case]:>11.2e}"
        )
        figures[case] = {
            "frames": first["frames"],
            "transition_frames": first["transition_frames"],
            "baseline_s": round(b, 4),
            "now_s": round(n, 4),
            "ratio": round(b / n, 3),
            "max_abs_force_difference_N": worst[case],
        }
    agree = all(v <= 1e-6 for v in worst.values())
    print("forces agree to 1e-6 N" if agree else "forces DIFFER beyond 1e-6 N")
    print(
        json.dumps(
            {
                "benchmark": "load_tracker",
                "utc": datetime.now(UTC).isoformat(timespec="seconds"),
                "commit": git_commit(),
                "baseline": args.baseline,
                "load_average": round(load, 2),
                "cases": figures,
                "agree": agree,
            }
        )
    )
    return 0 if agree else 1


if __name__ == "__main__":
    sys.exit(main())
