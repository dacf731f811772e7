"""Elementary load cases of the ram on its twin: forces at the TTP and steady temperature fields.

The design the FE calibration (paper sec. 2.3), the resolution check, the placement search and
the accuracy plan are built from: each case's sensor elongations, temperatures and TTP
displacement, from the twin's influence operators.
"""

from __future__ import annotations

import numpy as np

__all__ = ["LOAD_CASES", "load_case_responses"]


#: Typical magnitudes of each elementary load case in a working machine (the design's scale).
LOAD_CASES = (
    ("force_x", 4000.0, "N"),
    ("force_y", 4000.0, "N"),
    ("force_z", 4000.0, "N"),
    ("uniform", 5.0, "K"),
    ("gradient_x", 1.0, "K"),
    ("gradient_y", 1.0, "K"),
    ("gradient_z", 1.0, "K"),
    ("housing", 5.0, "K"),
)


def load_case_responses(twin, cases=LOAD_CASES):
    """Responses of each elementary load case (forces at the TTP, steady temperature fields).

    Returns a dict of arrays over the C cases: ``names``, ``sensor_elongation_um`` (C, S) host
    elongations, ``sensor_temperature_C`` (C, S) and ``probe_C`` (C, P) temperature rises (K),
    ``ttp_um`` (C, 3). Temperature fields come from the twin's ``static_temperature_response``
    (uniform change, linear gradients across X, Y and along Z, housing heating).
    """
    S, P = len(twin.sensor_names), len(twin.probe_names)
    out = {k: [] for k in ("names", "sensor_elongation_um", "sensor_temperature_C", "probe_C", "ttp_um")}
    for name, magnitude, _unit in cases:
        if name.startswith("force_"):
            f = np.zeros((1, 3))
            f[0, "xyz".index(name[-1])] = magnitude
            r = twin.static(f)
            e, t = np.asarray(r.sensor_elongation_um)[0], np.asarray(r.ttp_um)[0]
            st, pt = np.zeros(S), np.zeros(P)
        else:
            r = twin.static_temperature_response(name, magnitude)
            e, t = np.asarray(r.sensor_elongation_um).ravel(), np.asarray(r.ttp_um).ravel()
            st, pt = np.asarray(r.sensor_temperature_C).ravel(), np.asarray(r.probe_C).ravel()
        for key, value in zip(out, (name, e, st, pt, t)):
            out[key].append(value)
    return {k: (v if k == "names" else np.array(v, dtype=float)) for k, v in out.items()}
