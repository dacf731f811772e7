"""The correction in the form a production CNC's thermal compensation takes: offset + slope.

Siemens Sinumerik, Heidenhain TNC, Beckhoff TwinCAT CNC and others compensate thermal growth per
axis with a straight line, fed by the PLC: an offset at a reference position plus a slope times
the distance from it (docs/cnc-integration.md cites each). Per axis a (dx, dy, dz):

    correction_a(z) ≈ offset_a + slope_a · (z − z_ref)

* ``offset_um`` — the published correction at the reference position ``z_ref_mm``, µm (the
  pipeline's rate-limited, clamped correction = − predicted TTP deviation);
* ``slope_um_per_m`` — d correction_a / dz at ``z_ref_mm``, µm of correction per m of Z travel
  (Beckhoff's ``temp_comp_coefficient`` unit; Sinumerik's dimensionless tan β is this × 1e-6);
* ``z_ref_mm`` — the Z position the model was evaluated at: the live Z when the runtime passes
  one, else the Z the model assumes (its machine description's ``supports.z_axis_mm``).

The slope is a central finite difference of the model's own prediction through its
``z_axis_mm`` argument, on the newest frame: (d(z_ref − h) − d(z_ref + h)) / 2h. A model whose
``predict`` takes no ``z_axis_mm`` (the regression, the default physical model) has no Z
dependence: slope 0. The difference is evaluated without disturbing a predictor with memory
(dynamic filters, load tracking): its state is put back after the two extra calls.
"""

from __future__ import annotations

import inspect

import numpy as np

#: Half-step of the central difference, mm: large against the kinematic chain's 0.001 mm key
#: rounding, small against the carriage spacing the chain's lever arms change over.
DZ_MM = 10.0
_STATE_ATTRS = ("state", "last_flags", "last_base")


_TAKES_Z: dict[type, bool] = {}


def takes_z(predictor) -> bool:
    """Whether ``predictor.predict`` accepts the Z position (keyword ``z_axis_mm``)."""
    kind = type(predictor)
    if kind not in _TAKES_Z:
        try:
            takes = "z_axis_mm" in inspect.signature(predictor.predict).parameters
        except (TypeError, ValueError):
            takes = False
        _TAKES_Z[kind] = takes
    return _TAKES_Z[kind]


def reference_z_mm(predictor) -> float | None:
    """The Z position, mm, a predictor evaluates at when given none (its chain's default), or
    None for a predictor without a kinematic chain."""
    chain_owner = getattr(predictor, "kinematic", predictor)
    chain = getattr(chain_owner, "chain", None)
    if chain is None or not callable(chain):
        return None
    return float(chain(None).z_axis_mm)


def _saved_state(predictor) -> list:
    objs = [predictor] + [
        getattr(predictor, a) for a in ("kinematic", "residual") if getattr(predictor, a, None) is not None
    ]
    return [(o, a, getattr(o, a)) for o in objs for a in _STATE_ATTRS if hasattr(o, a)]


def z_slope_um_per_m(
    predictor,
    wavelength_nm,
    temperature_C,
    wavelength_zero_nm,
    temperature_zero_C,
    z_ref_mm: float | None,
    *,
    time_s=None,
    dz_mm: float = DZ_MM,
) -> np.ndarray:
    """Slope (3,) of the correction with the Z position, µm per m, at ``z_ref_mm``.

    Parameters
    ----------
    predictor
        A model's predictor (``model.predictor(exclude)``), as the pipeline uses it.
    wavelength_nm, temperature_C : ndarray, shape (S,) and (P,)
        The newest frame's Bragg wavelengths, nm, and probe temperatures, °C.
    wavelength_zero_nm, temperature_zero_C : ndarray
        The zero state (S,) nm and (P,) °C.
    z_ref_mm : float or None
        Z position the slope is taken at, mm; None: the predictor's own default
        (:func:`reference_z_mm`).
    time_s : float, optional
        The frame's time, s (passed to predictors with memory; their state is restored).
    dz_mm : float
        Half-step of the central difference, mm.

    Returns
    -------
    ndarray, shape (3,)
        d correction / dz per axis (dx, dy, dz), µm/m; 0 for a model without Z dependence,
        NaN when the prediction is not finite.
    """
    if not takes_z(predictor):
        return np.zeros(3)
    z0 = reference_z_mm(predictor) if z_ref_mm is None else float(z_ref_mm)
    if z0 is None:  # takes the keyword, has no chain: no Z dependence
        return np.zeros(3)
    w = np.atleast_2d(np.asarray(wavelength_nm, float))
    t = np.atleast_2d(np.asarray(temperature_C, float))
    clock = {} if time_s is None else {"time_s": np.atleast_1d(np.asarray(time_s, float))}
    saved = _saved_state(predictor)
    try:
        lo, _ = predictor.predict(w, t, wavelength_zero_nm, temperature_zero_C, z_axis_mm=z0 - dz_mm, **clock)
        hi, _ = predictor.predict(w, t, wavelength_zero_nm, temperature_zero_C, z_axis_mm=z0 + dz_mm, **clock)
    finally:
        for obj, attr, value in saved:
            setattr(obj, attr, value)
    # correction = - deviation; µm per mm x 1000 = µm per m
    slope = -(np.asarray(hi, float)[-1] - np.asarray(lo, float)[-1]) / (2.0 * dz_mm) * 1000.0
    return slope


def limit_toward(current, target, dt_s: float, rate_per_s, maximum):
    """One step of a per-axis rate and magnitude limit (the published offset or slope).

    ``target`` is clamped to ±``maximum``, then ``current`` moves toward it by at most
    ``rate_per_s · dt_s``. A non-finite target counts as 0 (nothing trustworthy to publish:
    ramp out). ``inf`` disables either limit.

    Returns
    -------
    (value, rate_limited, max_limited) : ndarray (3,), bool (3,), bool (3,)
    """
    current = np.asarray(current, float)
    target = np.asarray(target, float)
    target = np.where(np.isfinite(target), target, 0.0)
    maximum = np.asarray(maximum, float)
    clamped = np.clip(target, -maximum, maximum)
    max_limited = clamped != target
    rate, dt_s = np.asarray(rate_per_s, float), max(float(dt_s), 0.0)
    # inf (no rate limit) x 0 s would be NaN, and a NaN value never recovers
    step = rate * dt_s if dt_s > 0 else np.where(np.isinf(rate), np.inf, 0.0)
    value = current + np.clip(clamped - current, -step, step)
    rate_limited = value != clamped
    return value, rate_limited, max_limited


def newest_slope(pipeline, result, wavelength_nm, z_axis_mm: float | None = None):
    """Slope (3,) µm/m and reference Z (mm or None) of a pipeline batch's newest frame, with the
    model set the pipeline used on it; slope 0 on a frame without a model (ALARM, ZEROING).

    ``wavelength_nm`` (S,) is the frame as received (a jumped grating's offset is taken off
    here, as the pipeline does); ``z_axis_mm`` the Z position the pipeline evaluated at (None:
    the model's own)."""
    k = int(result.model_set[-1])
    if k < 0 or not pipeline.zeroed:
        return np.zeros(3), z_axis_mm
    p = pipeline.predictor(k)
    if not takes_z(p):
        return np.zeros(3), z_axis_mm
    z_ref = reference_z_mm(p) if z_axis_mm is None else float(z_axis_mm)
    wl = np.asarray(wavelength_nm, float) - pipeline.checks.offset_nm
    slope = z_slope_um_per_m(
        p,
        wl,
        result.temperature_C[-1],
        pipeline.wavelength_zero_nm,
        pipeline.temperature_zero_C,
        z_ref,
        time_s=result.time_s[-1],
    )
    return slope, z_ref
