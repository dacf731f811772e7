"""Loads superposed on a measured campaign, through a linear structure's unit responses.

A linear structure's response to TTP forces adds to whatever else it does (the thermal drift a
campaign recorded): the TTP moves by ``F @ ttp_um_per_N`` and each sensor path elongates by
``F @ elongation_um_per_N``, which the gratings read through eq. 2 at constant temperature
(:func:`fbgcomp.optics.strain_sensitivity_nm`). So a thermal campaign of an independent model
(ram2, whose README states it is linear and publishes its unit responses in ``results.json``)
becomes a combined one with any load history, exactly, without simulating anything again: the
load tracker is then judged on independent thermal drift.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from fbgcomp import optics
from fbgcomp.io.campaign import Campaign
from fbgcomp.units import AXES

#: Duration of each load change, s: ram2's static campaigns ramp in 5 s.
RAMP_S = 5.0


def force_history_N(time_s, steps, ramp_s=RAMP_S):
    """TTP force (n, 3) N at ``time_s`` (n,) s: ``steps`` is a sequence of (start h, end h,
    (Fx, Fy, Fz) N), each applied and removed by a linear ramp of ``ramp_s`` s; they add."""
    t = np.asarray(time_s, float)
    F = np.zeros((t.size, 3))
    for start_h, end_h, f in steps:
        on = np.clip((t - 3600.0 * start_h) / ramp_s, 0.0, 1.0) - np.clip(
            (t - 3600.0 * end_h) / ramp_s, 0.0, 1.0
        )
        F += on[:, None] * np.asarray(f, float)[None, :]
    return F


def ram2_unit_responses(results: dict) -> tuple[np.ndarray, np.ndarray]:
    """(ttp_um_per_N (3 forces, 3 axes), elongation_um_per_N (3 forces, sensors)) from ram2's
    ``results.json`` (``unit_response_um_per_N``: per force x, y, z the list [dx, dy, dz, S1..])."""
    unit = results["unit_response_um_per_N"]
    R = np.array([unit[a] for a in ("x", "y", "z")], float)
    return R[:, :3], R[:, 3:]


def superpose_loads(
    campaign: Campaign,
    ttp_um_per_N,
    elongation_um_per_N,
    steps,
    *,
    ramp_s=RAMP_S,
    load_noise_N=0.5,
    seed=0,
    name=None,
) -> Campaign:
    """``campaign`` with the load history ``steps`` (:func:`force_history_N`) superposed.

    ``ttp_um_per_N`` (3 forces, 3 axes) and ``elongation_um_per_N`` (3 forces, sensors in the
    campaign's order) are the structure's unit responses. The gratings get the load's strain at
    each frame (their wavelength shift at constant temperature), the reference the TTP's
    deflection at each of its samples, and a loads.csv at the interrogator's frames reads the
    forces with ``load_noise_N`` of white noise. The result is a ``combined`` campaign named
    ``name`` (default: the campaign's name + ``-loaded``)."""
    C = np.asarray(ttp_um_per_N, float)
    G = np.asarray(elongation_um_per_N, float)
    meta = campaign.meta.model_dump()
    if G.shape != (3, len(meta["sensors"])) or C.shape != (3, 3):
        raise ValueError(
            f"unit responses must be (3, 3) and (3, {len(meta['sensors'])}), got {C.shape} and {G.shape}"
        )
    meta.update(name=name or f"{meta['name']}-loaded", kind="combined")
    fbg, ref = campaign.fbg.copy(), campaign.reference.copy()
    t_fbg = fbg["time_s"].to_numpy(float)
    F = force_history_N(t_fbg, steps, ramp_s)
    strain = (F @ G) / (1e3 * np.array([s["gauge_length_mm"] for s in meta["sensors"]]))  # µm / µm
    for j, s in enumerate(meta["sensors"]):
        sens = optics.strain_sensitivity_nm(s["lambda0_nm"], photoelastic=s["photoelastic"])
        fbg[f"{s['name']}_nm"] = fbg[f"{s['name']}_nm"].to_numpy(float) + sens * strain[:, j]
    noise = np.random.default_rng(seed).normal(0.0, load_noise_N, F.shape)
    loads = pd.DataFrame({"time_s": t_fbg, **{f"f{a}_N": F[:, k] + noise[:, k] for k, a in enumerate("xyz")}})
    deflection = force_history_N(ref["time_s"].to_numpy(float), steps, ramp_s) @ C
    for k, axis in enumerate(AXES):
        ref[f"{axis}_um"] = ref[f"{axis}_um"].to_numpy(float) + deflection[:, k]
    return Campaign.from_arrays(meta, fbg=fbg, temperatures=campaign.temperatures, reference=ref, loads=loads)
