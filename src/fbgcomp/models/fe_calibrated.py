"""FE-calibrated model and sensor resolution check (paper sec. 2.3-2.4).

Before any hardware exists, the paper uses FE simulations of the ram under static tool-tip
forces and thermal loads (i) to check that the FBG resolution sees the distortions and (ii) to
get the first regression coefficients of eq. 11. Here the twin's influence operators give each
sensor path's elongation and the TTP displacement for a design of elementary load cases; random
combinations of them, with the interrogator's noise on the elongations, are fitted by the same
:class:`~fbgcomp.models.mra.MRAModel` the campaigns use, so the result is an ordinary model file.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from fbgcomp import optics
from fbgcomp.models.base import CHUNK_ROWS
from fbgcomp.models.features import TEMPERATURE_FEATURES, design_matrix, resolve_roles
from fbgcomp.models.machines import campaign_sensor_specs
from fbgcomp.models.mra import MRAModel
from fbgcomp.models.regression import accumulate_series
from fbgcomp.optics import elongation_noise_um
from fbgcomp.structure.loadcases import LOAD_CASES, load_case_responses
from fbgcomp.units import AXES

__all__ = [
    "LOAD_CASES",
    "elongation_noise_um",
    "fe_calibrate",
    "fe_design",
    "format_resolution",
    "load_case_responses",
    "resolution_report",
]


def fe_design(machine, twin, *, n_samples=2000, wavelength_noise_nm=0.001, seed=0):
    """Random combinations of the FE load cases, as an interrogator and probes would see them.

    Each sample is a combination of the elementary cases with standard-normal weights (times
    each case's typical magnitude). The elongation is what the FBG reports after compensation
    with its assigned probe (paper eq. 2-4): the grating's own temperature rise changes the
    wavelength, the probe's rise is what the optics subtract; plus the interrogator's noise.

    Returns
    -------
    (pandas.DataFrame, ndarray, dict)
        Base features (``dL_<sensor>`` µm and the eq. 13 temperature features ``dT_bulk``,
        ``dT_surf``, ``dT_flange`` K), TTP deviations (n, 3) µm, and the case responses.
    """
    cases = load_case_responses(twin)
    rng = np.random.default_rng(seed)
    w = rng.standard_normal((n_samples, len(cases["names"])))
    host = w @ cases["sensor_elongation_um"]
    sensor_rise = w @ cases["sensor_temperature_C"]
    probe_rise = w @ cases["probe_C"]
    probe_index = {p: i for i, p in enumerate(twin.probe_names)}
    sensors = machine.sensors
    consts = dict(
        photoelastic=np.array([s.photoelastic for s in sensors]),
        thermo_optic_per_K=np.array([s.thermo_optic_per_K for s in sensors]),
        fibre_cte_per_K=np.array([s.fibre_cte_per_K for s in sensors]),
    )
    lam0 = np.array([s.lambda0_nm for s in sensors])
    gauge = np.array([s.gauge_length for s in sensors])
    compensating = np.column_stack(
        [
            probe_rise[:, probe_index[s.temperature_probe]] if s.temperature_probe else np.zeros(n_samples)
            for s in sensors
        ]
    )
    lam = optics.wavelength_nm(host, lam0, gauge, sensor_rise, **consts)
    lam = lam + wavelength_noise_nm * rng.standard_normal(lam.shape)
    read = optics.elongation_um(lam, lam0, gauge, compensating, **consts)
    roles = resolve_roles([p.name for p in machine.probes], machine)
    rise = {
        r: (probe_rise[:, probe_index[p]] if p in probe_index else np.zeros(n_samples))
        for r, p in roles.as_dict().items()
    }
    temps = np.column_stack([rise["bulk"], rise["bulk"] - rise["surf"], rise["flange"] - rise["bulk"]])
    X = pd.DataFrame(
        np.hstack([read, temps]), columns=[f"dL_{s.name}" for s in sensors] + list(TEMPERATURE_FEATURES)
    )
    return X, w @ cases["ttp_um"], cases


def _design_record(seed, n_samples, wavelength_noise_nm):
    rec = {
        "load_cases": [{"name": n, "magnitude": m, "unit": u} for n, m, u in LOAD_CASES],
        "n_samples": int(n_samples),
        "wavelength_noise_nm": wavelength_noise_nm,
        "seed": seed,
    }
    return rec


def fe_calibrate(
    machine, twin=None, *, features="eq11", n_samples=2000, wavelength_noise_nm=0.001, seed=0, stepwise=False
):
    """Fit a model on a random design of FE load cases (paper sec. 2.3): an ordinary model file.

    ``features`` "eq11" (the paper's FE step: elongations only) or "eq13"/"eq12" (with the
    probes' temperature features).

    Returns
    -------
    (MRAModel, dict)
        The fitted model (sensors from the machine, ready for campaigns and the runtime) and the
        case responses.
    """
    from fbgcomp.structure import Twin  # noqa: PLC0415 - optional extra: scikit-fem (the FE twin)

    twin = twin or Twin(machine, reduce_thermal=False)  # load cases only: static operators
    X, y, cases = fe_design(
        machine, twin, n_samples=n_samples, wavelength_noise_nm=wavelength_noise_nm, seed=seed
    )
    model = MRAModel(features=features, stepwise=stepwise, fallbacks="loo")
    sensors = campaign_sensor_specs(machine)
    acc = model.new_accumulator(sensors, [p.name for p in machine.probes], machine=machine)
    fmap = model._feature_map()
    keep = [c for c in X.columns if c in fmap.base_names]
    accumulate_series(
        acc,
        [(design_matrix(X[keep].to_numpy(), keep, model.candidates_), np.asarray(y, dtype=float), None)],
        chunk_rows=CHUNK_ROWS,
    )
    model.fit_factor(
        acc,
        training={
            "campaigns": [],
            "n_samples": int(n_samples),
            "fe_design": _design_record(seed, n_samples, wavelength_noise_nm),
        },
    )
    return model, cases


def resolution_report(machine, twin=None, wavelength_noise_nm=0.001):
    """Does the FBG resolution see the distortions? (paper sec. 2.3)

    The sensor responses to the load cases are whitened by each sensor's noise (so a singular
    value of 1 is one noise SD); combinations of sensors that no load case excites above the
    noise are unobservable and are left out of the sensor-to-TTP map (a truncated
    pseudo-inverse) instead of being amplified. Returns, per axis, the smallest TTP deviation the
    sensor set resolves (2 σ of the prediction's noise), the largest TTP displacement of a load
    case and the part the sensors cannot explain; and the map's singular values, numerical rank,
    condition number over the observable part and the unobservable sensor combinations.
    """
    from fbgcomp.structure import Twin  # noqa: PLC0415 - optional extra: scikit-fem (the FE twin)

    twin = twin or Twin(machine, reduce_thermal=False)  # load cases only: static operators
    cases = load_case_responses(twin)
    elong, ttp = cases["sensor_elongation_um"], cases["ttp_um"]
    noise = elongation_noise_um(machine.sensors, wavelength_noise_nm)
    scaled = elong / noise  # (C, S) in noise units
    u, sv, vt = np.linalg.svd(scaled, full_matrices=True)
    rank = int(np.sum(sv > 1.0))  # excited above one noise SD
    # TTP = scaled @ G: G from the observable subspace only.
    inv = np.zeros((len(sv), len(sv)))
    inv[:rank, :rank] = np.diag(1.0 / sv[:rank])
    G = vt[: len(sv)].T @ inv @ u[:, : len(sv)].T @ ttp  # (S, 3) µm per noise unit
    unexplained = ttp - scaled @ G
    sigma_ttp = np.sqrt((G**2).sum(axis=0))  # white unit noise per sensor
    unobservable = [dict(zip([s.name for s in machine.sensors], np.round(v, 3).tolist())) for v in vt[rank:]]
    axes = {}
    for j, a in enumerate(AXES):
        axes[a] = {
            "resolution_um": float(2 * sigma_ttp[j]),
            "noise_sd_um": float(sigma_ttp[j]),
            "max_load_case_ttp_um": float(np.max(np.abs(ttp[:, j]))),
            "max_unexplained_um": float(np.max(np.abs(unexplained[:, j]))),
            "um_per_sensor_um": (G[:, j] / noise).tolist(),
        }
    return {
        "sensors": [s.name for s in machine.sensors],
        "wavelength_noise_nm": wavelength_noise_nm,
        "elongation_noise_um": noise.tolist(),
        "load_cases": [
            {
                "name": n,
                "magnitude": m,
                "unit": unit,
                "sensor_elongation_um": elong[i].tolist(),
                "ttp_um": ttp[i].tolist(),
                "snr": (np.abs(elong[i]) / noise).tolist(),
            }
            for i, (n, m, unit) in enumerate(LOAD_CASES)
        ],
        "singular_values": sv.tolist(),
        "rank": rank,
        "condition_number": float(sv[0] / sv[rank - 1]) if rank else float("inf"),
        "unobservable_combinations": unobservable,
        "axes": axes,
    }


def format_resolution(rep: dict) -> str:
    """The resolution report (:func:`resolution_report`) as text tables."""
    lines = [
        "FBG resolution check (2σ, interrogator noise on the elongations)",
        "sensor noise (µm): "
        + ", ".join(f"{s} {n:.3f}" for s, n in zip(rep["sensors"], rep["elongation_noise_um"])),
    ]
    lines.append(
        f"{'load case':<12}{'magnitude':>11}  "
        + "".join(f"{s + ' µm':>10}" for s in rep["sensors"])
        + f"{'dx µm':>9}{'dy µm':>9}{'dz µm':>9}"
    )
    for c in rep["load_cases"]:
        lines.append(
            f"{c['name']:<12}{c['magnitude']:>8g} {c['unit']:<2} "
            + "".join(f"{v:>10.3f}" for v in c["sensor_elongation_um"])
            + "".join(f"{v:>9.3f}" for v in c["ttp_um"])
        )
    lines.append(f"{'axis':<5}{'resolves µm':>13}{'max case µm':>13}{'unexplained µm':>16}")
    for a, m in rep["axes"].items():
        lines.append(
            f"{a:<5}{m['resolution_um']:>13.3f}{m['max_load_case_ttp_um']:>13.3f}"
            f"{m['max_unexplained_um']:>16.3f}"
        )
    lines.append(
        f"sensor-to-TTP map (noise units): singular values "
        f"{', '.join(f'{v:.3g}' for v in rep['singular_values'])}; rank {rep['rank']} of "
        f"{len(rep['sensors'])}, condition number {rep['condition_number']:.3g}"
    )
    for combo in rep["unobservable_combinations"]:
        lines.append(
            "unobservable (no load case excites it above the noise): "
            + " ".join(f"{v:+.2f}·{k}" for k, v in combo.items() if abs(v) > 1e-3)
        )
    return "\n".join(lines)
