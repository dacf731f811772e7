"""Campaigns with a known linear truth, for tests, examples and checks of the fitting chain.

Not a physical simulation (that is :mod:`fbgcomp.structure` and the virtual test bench): smooth
random elongation and temperature histories, a TTP deviation that is an exact linear function of
the model's regressors plus Gaussian noise, and the bonded-FBG forward model of
:mod:`fbgcomp.optics` to produce the wavelengths an interrogator would log. Because the truth is
known, a fit can be checked coefficient by coefficient.
"""

from __future__ import annotations

from datetime import UTC, datetime

import numpy as np
import pandas as pd

from fbgcomp import optics
from fbgcomp.io.campaign import Campaign, CampaignMeta
from fbgcomp.models.features import TEMPERATURE_FEATURES, design_matrix
from fbgcomp.units import AXES

SENSORS = ("S1", "S2", "S3", "S4", "S5")
PROBES = ("T_bulk", "T_surf", "T_flange", "T_amb")


def default_meta(
    name="synthetic", kind="thermal", sensors=SENSORS, probes=PROBES, sensor_probe="T_surf"
) -> dict:
    """Campaign metadata (as a dict for ``CampaignMeta``) for the default 5-sensor ram layout."""
    faces = ["+X", "-X", "+Y", "-Y", "+X"]
    spans = [(100, 600)] * 4 + [(650, 1050)]
    sensor_list = []
    for i, s in enumerate(sensors):
        z0, z1 = spans[i % len(spans)]
        sensor_list.append(
            {
                "name": s,
                "lambda0_nm": 1530.0 + 5.0 * i,
                "gauge_length_mm": float(z1 - z0),
                "photoelastic": optics.PHOTOELASTIC,
                "thermo_optic_per_K": optics.THERMO_OPTIC_PER_K,
                "fibre_cte_per_K": optics.FIBRE_CTE_PER_K,
                "face": faces[i % len(faces)],
                "z_start_mm": float(z0),
                "z_end_mm": float(z1),
                "temperature_probe": sensor_probe,
            }
        )
    return {
        "name": name,
        "kind": kind,
        "description": "synthetic campaign with a known linear truth",
        "start": datetime(2026, 1, 12, 8, 0, tzinfo=UTC),
        "sensors": sensor_list,
        "temperature_probes": [{"name": p, "location": "synthetic"} for p in probes],
        "reference": {"instrument": "synthetic", "point": "TTP", "units": "um"},
    }


def _smooth_signal(rng, t, amplitude, periods_s=(900.0, 3000.0), n_terms=4):
    out = np.zeros_like(t)
    for _ in range(n_terms):
        period = rng.uniform(*periods_s)
        out += rng.uniform(0.3, 1.0) * amplitude * np.sin(2 * np.pi * t / period + rng.uniform(0, 2 * np.pi))
    return out


def linear_truth_campaign(
    name="synthetic",
    *,
    seed=0,
    duration_s=3600.0,
    fbg_dt_s=1.0,
    temperature_dt_s=1.0,
    reference_dt_s=1.0,
    reference_offset_s=0.0,
    coefficients=None,
    noise_um=0.05,
    wavelength_noise_nm=0.0,
    kind="thermal",
    settle_s=60.0,
):
    """A campaign whose TTP deviation is an exact linear function of eq. 13 regressors.

    Parameters
    ----------
    seed : int
        Random seed: the same seed gives the same campaign.
    duration_s : float
        Length of the record, s.
    fbg_dt_s, temperature_dt_s, reference_dt_s : float
        Sampling intervals of the interrogator, the probes and the interferometer, s.
    reference_offset_s : float
        Start of the interferometer's clock relative to the others, s.
    coefficients : dict, optional
        ``{"dx": {"const": .., "dL_S1": .., "dT_bulk": ..}, ...}`` in µm per µm / per K; terms
        not named are zero. Default: a fixed, plausible set using every eq. 13 term.
    noise_um : float
        Standard deviation of the Gaussian noise added to the reference, µm.
    wavelength_noise_nm : float
        Standard deviation of the interrogator's wavelength noise, nm.
    settle_s : float
        The machine rests for this long before anything changes, as in a real campaign: the zero
        state (mean of each signal's first seconds, on each instrument's own clock) is only
        consistent across instruments when nothing moves during it.

    Returns
    -------
    (Campaign, dict)
        The campaign, and the truth: ``coefficients`` and the noise-free deviation on the
        reference clock.
    """
    rng = np.random.default_rng(seed)
    coefficients = coefficients or default_coefficients()
    meta = CampaignMeta(**default_meta(name=name, kind=kind))
    t_fine = np.arange(0.0, duration_s + 1e-9, min(fbg_dt_s, temperature_dt_s, reference_dt_s) / 2)
    dl = np.column_stack([_smooth_signal(rng, t_fine, 20.0) for _ in SENSORS])
    t_bulk = 30.0 + _smooth_signal(rng, t_fine, 1.5)
    t_surf = t_bulk - 0.6 * _smooth_signal(rng, t_fine, 1.0)
    t_flange = t_bulk + 0.8 * _smooth_signal(rng, t_fine, 1.0)
    t_amb = t_bulk + _smooth_signal(rng, t_fine, 0.5)
    temps = np.column_stack([t_bulk, t_surf, t_flange, t_amb])

    def sample(t, values):
        t_moving = np.maximum(np.asarray(t, dtype=float) - settle_s, 0.0)
        return np.column_stack([np.interp(t_moving, t_fine, values[:, j]) for j in range(values.shape[1])])

    t_fbg = np.arange(0.0, duration_s + 1e-9, fbg_dt_s)
    t_tmp = np.arange(0.0, duration_s + 1e-9, temperature_dt_s)
    t_ref = np.arange(reference_offset_s, duration_s + 1e-9, reference_dt_s)

    gauge = np.array([s.gauge_length_mm for s in meta.sensors])
    lam0 = np.array([s.lambda0_nm for s in meta.sensors])
    surf_fbg = sample(t_fbg, temps[:, [1]])[:, 0]
    dt_sensor = (surf_fbg - surf_fbg[0])[:, None] * np.ones(len(SENSORS))
    lam = optics.wavelength_nm(sample(t_fbg, dl), lam0, gauge, dt_sensor)
    lam = lam + wavelength_noise_nm * rng.standard_normal(lam.shape)

    # The truth in the regressors the fit sees: elongations and eq. 13 temperature features.
    base_ref = np.hstack([sample(t_ref, dl), _temperature_features(sample(t_ref, temps))])
    base_names = [f"dL_{s}" for s in SENSORS] + list(TEMPERATURE_FEATURES)
    terms = base_names
    design = design_matrix(base_ref, base_names, terms)
    beta = np.array([[coefficients[a].get(name, 0.0) for a in AXES] for name in ["const", *terms]])
    clean = design @ beta
    reference = clean + noise_um * rng.standard_normal(clean.shape)

    fbg = pd.DataFrame(lam, columns=[f"{s}_nm" for s in SENSORS])
    fbg.insert(0, "time_s", t_fbg)
    temperatures = pd.DataFrame(sample(t_tmp, temps), columns=[f"{p}_C" for p in PROBES])
    temperatures.insert(0, "time_s", t_tmp)
    ref = pd.DataFrame(reference, columns=[f"{a}_um" for a in AXES])
    ref.insert(0, "time_s", t_ref)
    campaign = Campaign.from_arrays(meta, fbg=fbg, temperatures=temperatures, reference=ref)
    return campaign, {"coefficients": coefficients, "clean_um": clean, "time_s": t_ref}


def _temperature_features(temps):
    """Eq. 13 features relative to t = 0 (columns T_bulk, T_surf, T_flange, ...)."""
    d = temps - temps[0]
    return np.column_stack([d[:, 0], d[:, 0] - d[:, 1], d[:, 2] - d[:, 0]])


def default_coefficients() -> dict:
    """A plausible truth: every eq. 13 term matters on at least one axis."""
    return {
        "dx": {"const": 0.1, "dL_S1": 0.40, "dL_S2": -0.35, "dL_S5": 0.20, "dT_bulk": 1.5, "dT_surf": -2.0},
        "dy": {"const": -0.2, "dL_S3": 0.45, "dL_S4": -0.40, "dT_flange": 1.2},
        "dz": {"const": 0.0, "dL_S1": -0.25, "dL_S2": -0.25, "dL_S3": -0.25, "dL_S4": -0.25, "dT_bulk": 3.0},
    }
