"""Mesh convergence of the FE twin: TTP response to a unit tip force and to 1 K uniform heating
at three resolutions.

    .venv/bin/python benchmarks/fe_convergence.py [--resolutions 0.5 1 1.5]
"""

from __future__ import annotations

import argparse
import time

from fbgcomp.structure import Twin, load_machine


def main():
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--resolutions", type=float, nargs="+", default=[0.5, 1.0, 1.5])
    args = ap.parse_args()
    machine = load_machine()
    cf, st = machine.materials.cfrp, machine.materials.steel
    free_dz = -1e3 * (cf.cte_L_per_K * machine.supports.nut.z_mm + st.cte_per_K * machine.housing.height_mm)
    print(
        f"{'res':>5} {'DOF':>8} {'build s':>8} | TTP per 1 kN [um]: {'Fx->dx':>8} {'Fy->dy':>8} "
        f"{'Fz->dz':>8} | 1 K uniform: {'dz um':>8} (free expansion {free_dz:.4f}) | S1 per kN Fx"
    )
    for r in args.resolutions:
        t0 = time.perf_counter()
        twin = Twin(machine, resolution=r)
        build = time.perf_counter() - t0
        C = 1e3 * twin.influence.ttp_per_force_um_per_N
        heat = twin.static_temperature_response("uniform", 1.0)
        s1 = 1e3 * twin.influence.sensor_per_force_um_per_N[0, 0]
        print(
            f"{r:5.2f} {twin.n_dof:8d} {build:8.1f} | {'':19}{C[0, 0]:8.3f} {C[1, 1]:8.3f} "
            f"{C[2, 2]:8.4f} | {'':12} {heat.ttp_um[2]:8.4f} {'':26} | {s1:8.4f}"
        )
        del twin


if __name__ == "__main__":
    main()
