"""The twin's elastic factor: the block-by-block Cholesky against the banded one, per machine.

Every twin factorises its elastic stiffness once (with the supports) and solves it for its
adjoint rows (each grating's elongation and the three TTP axes): `fbgcomp.structure.fe.Factorised`
with ``blocked=True``. The matrix, numbered layer by layer along the ram, is block tridiagonal
in blocks of one node layer; the library factorises those blocks with dense LAPACK when their
flop count is below ``fe._BLOCKED_WORK_RATIO`` times the band's (n bw^2), and otherwise takes
the banded Cholesky (LAPACK dpbtrf).

**Baseline**: the rule up to 8e22e0d, ratio 0.8, under which ram2, ram3 and ram4 took the banded
factor. Both are timed on the same matrix (factor + the adjoint solves), interleaved, median of
``--reps``; the adjoint solutions must agree to 1e-9 relative (round-off of two factorisations).

Machines: the built-in ram and the three independent rams' descriptions (examples/machines),
each at its own mesh and optionally at ``--resolution`` factors. Their twins are built once in
a temporary twin cache. BLAS on one thread (as the twin runs it). Last line: one JSON object.

    .venv/bin/python benchmarks/bench_factor.py [--reps 3] [--resolution 1.0 0.5] [--machines ...]
"""

from __future__ import annotations

import os

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import json  # noqa: E402
import statistics  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from datetime import UTC, datetime  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from _loopback import git_commit  # noqa: E402
from fbgcomp.structure import Twin, fe, load_machine  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
MACHINES = {
    "built-in": REPO / "src" / "fbgcomp" / "data" / "ram.yaml",
    "ram2": REPO / "examples" / "machines" / "ram2.yaml",
    "ram3": REPO / "examples" / "machines" / "ram3.yaml",
    "ram4": REPO / "examples" / "machines" / "ram4.yaml",
}
BASELINE_RATIO = 0.8  # fe._BLOCKED_WORK_RATIO up to 8e22e0d


def factor_and_solve(K, order, rhs, ratio: float):
    """Seconds, backend and solution of Factorised(K, order, blocked=True) + solve(rhs) under
    the rule ``ratio``."""
    kept = fe._BLOCKED_WORK_RATIO
    fe._BLOCKED_WORK_RATIO = ratio
    try:
        t0 = time.perf_counter()
        f = fe.Factorised(K, order=order, blocked=True)
        x = f.solve(rhs)
        return time.perf_counter() - t0, f.backend, x
    finally:
        fe._BLOCKED_WORK_RATIO = kept


def work_ratio(K, order) -> float:
    """The block factor's flop count over the band's (the quantity the rule compares)."""
    n = K.shape[0]
    inv = np.empty_like(order)
    inv[order] = np.arange(n)
    A = K.tocoo()
    row, col = inv[A.row], inv[A.col]
    up = col >= row
    bw = int(np.max(col[up] - row[up]))
    m = np.diff(fe.block_partition(col[up], row[up], n)).astype(float)
    work = (m**3 / 3).sum() + (m[1:] * m[:-1] ** 2 + m[1:] ** 2 * m[:-1]).sum()
    return float(work / (n * float(bw) ** 2))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--reps", type=int, default=3)
    ap.add_argument("--resolution", type=float, nargs="+", default=[1.0])
    ap.add_argument("--machines", nargs="+", default=list(MACHINES), choices=list(MACHINES))
    args = ap.parse_args()
    started = datetime.now(UTC)
    print(
        f"{started:%Y-%m-%d %H:%M} UTC, code of {git_commit()}, load average {os.getloadavg()[0]:.1f}; "
        f"library rule {fe._BLOCKED_WORK_RATIO} against the baseline's {BASELINE_RATIO}"
    )
    rows = []
    with tempfile.TemporaryDirectory() as cache:
        os.environ["FBGCOMP_CACHE_DIR"] = cache
        for name in args.machines:
            for res in args.resolution:
                twin = Twin(load_machine(MACHINES[name]), resolution=res)
                K = twin._K_elastic
                order = fe.layer_order(twin.mesh.mesh.p, twin._vbasis.nodal_dofs)
                rhs = np.asarray(twin._R.T)
                times: dict[str, list[float]] = {"baseline": [], "library": []}
                backends, sols = {}, {}
                for _ in range(args.reps):
                    for who, ratio in (("baseline", BASELINE_RATIO), ("library", fe._BLOCKED_WORK_RATIO)):
                        s, backends[who], sols[who] = factor_and_solve(K, order, rhs, ratio)
                        times[who].append(s)
                base, lib = statistics.median(times["baseline"]), statistics.median(times["library"])
                diff = float(
                    np.abs(sols["library"] - sols["baseline"]).max() / np.abs(sols["baseline"]).max()
                )
                row = {
                    "machine": name,
                    "resolution": res,
                    "n_dof": int(K.shape[0]),
                    "work_ratio": round(work_ratio(K, order), 3),
                    "baseline_s": round(base, 3),
                    "library_s": round(lib, 3),
                    "speedup": round(base / lib, 3),
                    "baseline_backend": backends["baseline"],
                    "library_backend": backends["library"],
                    "max_rel_diff": diff,
                }
                rows.append(row)
                print(
                    f"{name:9s} x{res:<4g} {row['n_dof']:7d} DOF  work ratio {row['work_ratio']:.2f}  "
                    f"baseline {base:6.2f} s ({row['baseline_backend']})  library {lib:6.2f} s "
                    f"({row['library_backend']})  x{row['speedup']:.2f}  max rel diff {diff:.1e}",
                    flush=True,
                )
                if diff > 1e-9:
                    raise SystemExit(f"{name}: the two factors' solutions differ by {diff:.1e} relative")
    print(f"load average after: {os.getloadavg()[0]:.1f}")
    print(json.dumps({"benchmark": "bench_factor", "started": f"{started:%Y-%m-%dT%H:%M}Z", "rows": rows}))


if __name__ == "__main__":
    main()
