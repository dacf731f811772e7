"""Putting the instruments on the reference instrument's clock, and the zero state.

Linear interpolation, never extrapolation; an instrument sampling much faster than the reference
is averaged over each reference interval (a local least-squares line) instead of being aliased.
:meth:`fbgcomp.io.campaign.Campaign.aligned` uses these to build an :class:`AlignedCampaign`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from fbgcomp.errors import InputError
from fbgcomp.io.campaign.meta import CampaignMeta

__all__ = [
    "AVERAGE_MIN_SAMPLES",
    "AlignedCampaign",
    "check_window",
    "interp_columns",
    "onto_reference",
    "zero_state",
]


def interp_columns(
    time_s: np.ndarray, source_time_s: np.ndarray, values: np.ndarray, outside: float | None = None
) -> np.ndarray:
    """Linear interpolation of every column of ``values`` onto ``time_s``."""
    out = np.empty((time_s.size, values.shape[1]))
    for j in range(values.shape[1]):
        out[:, j] = np.interp(time_s, source_time_s, values[:, j], left=outside, right=outside)
    return out


#: An instrument with at least this many samples per reference interval is averaged onto the
#: reference clock instead of being interpolated.
AVERAGE_MIN_SAMPLES = 3


def _local_linear_columns(
    time_s: np.ndarray,
    source_time_s: np.ndarray,
    values: np.ndarray,
    half_width_s: float,
    chunk: int = 20_000,
) -> np.ndarray:
    """Value at each ``time_s`` of the least-squares line through the source samples within
    ``± half_width_s`` (an anti-aliasing filter: exact for linear signals, noise / sqrt(n)).

    Targets whose window holds fewer than two samples are interpolated linearly instead.
    """
    lo = np.searchsorted(source_time_s, time_s - half_width_s, side="left")
    hi = np.searchsorted(source_time_s, time_s + half_width_s, side="right")
    width = int(np.max(hi - lo)) if time_s.size else 0
    out = interp_columns(time_s, source_time_s, values)
    if width < 2:
        return out
    offsets = np.arange(width)
    for a in range(0, time_s.size, chunk):
        b = min(a + chunk, time_s.size)
        idx = lo[a:b, None] + offsets[None, :]
        valid = idx < hi[a:b, None]
        idx = np.minimum(idx, source_time_s.size - 1)
        n = valid.sum(axis=1)
        ok = n >= 2
        dt = np.where(valid, source_time_s[idx] - time_s[a:b, None], 0.0)  # centred: exact
        mean_dt = dt.sum(axis=1) / np.maximum(n, 1)
        ddt = np.where(valid, dt - mean_dt[:, None], 0.0)
        sxx = (ddt**2).sum(axis=1)
        for j in range(values.shape[1]):
            v = np.where(valid, values[idx, j], 0.0)
            mean_v = v.sum(axis=1) / np.maximum(n, 1)
            slope = np.where(
                sxx > 0,
                (ddt * np.where(valid, v - mean_v[:, None], 0.0)).sum(axis=1) / np.where(sxx > 0, sxx, 1.0),
                0.0,
            )
            out[a:b, j] = np.where(ok, mean_v - slope * mean_dt, out[a:b, j])
    return out


def onto_reference(time_s, source_time_s, values, reference_dt_s, average: bool):
    """Bring one instrument onto the reference times: averaged when it samples much faster."""
    if average and source_time_s.size > 1 and time_s.size:
        source_dt = float(np.median(np.diff(source_time_s)))
        if reference_dt_s >= AVERAGE_MIN_SAMPLES * source_dt:
            return _local_linear_columns(time_s, source_time_s, values, reference_dt_s / 2)
    return interp_columns(time_s, source_time_s, values)


def zero_state(time_s: np.ndarray, values: np.ndarray, window_s: float) -> np.ndarray:
    """Mean of the samples with ``t <= t_first + window_s`` (at least the first one)."""
    n = max(1, int(np.searchsorted(time_s, time_s[0] + window_s, side="right")))
    return values[:n].mean(axis=0)


def diff_noise_sd(values, axis=0):
    """White-noise SD of each series along ``axis`` from its successive differences, robustly:
    MAD(diff) x 1.4826 / sqrt 2 (steps and slow drift hardly move the median difference; white
    noise of SD sigma gives sigma)."""
    d = np.diff(np.asarray(values, float), axis=axis)
    mad = np.median(np.abs(d - np.median(d, axis=axis, keepdims=True)), axis=axis)
    return 1.4826 * mad / math.sqrt(2.0)


#: A load the load cell sees change by more than this within the zero window, N, beyond six
#: times its own noise, means the zero state was not taken at rest.
REST_LOAD_CHANGE_N = 20.0


def moving_in_window(time_s, values, window_s, floor=REST_LOAD_CHANGE_N):
    """Where a column of ``values`` (n, k) moves inside the zero window (the first ``window_s``
    seconds): the first row (0-based) and column whose value stands more than ``floor`` and six
    times the column's own noise (robust SD of successive differences over the whole record,
    over sqrt 2) away from the window's first sample, and that change; None when every column
    holds still. A load applied while the zero state is taken (logging started mid-ramp) makes
    every instrument's zero a different mix of loaded and unloaded samples on its own clock:
    on ram2's thermal_b, a 2000 N step in the first 5 s left the gratings zeroed at 1450 N and
    the interferometer at 120 N, and the correction 185 µm off for as long as the load held."""
    t = np.asarray(time_s, float)
    v = np.asarray(values, float)
    n = int(np.searchsorted(t, t[0] + window_s, side="right")) if t.size else 0
    if n < 2:
        return None
    limit = np.maximum(floor, 6.0 * diff_noise_sd(v))
    away = np.abs(v[:n] - v[0]) > limit
    if not away.any():
        return None
    row, col = np.argwhere(away)[0]
    return int(row), int(col), float(v[row, col] - v[0, col])


def check_window(zero_window_s) -> float:
    """``zero_window_s`` as a float; InputError unless it is a finite number of seconds >= 0."""
    try:
        window = float(zero_window_s)
    except (TypeError, ValueError):
        window = math.nan
    if not math.isfinite(window) or window < 0:
        raise InputError(
            f"zero window must be a finite number of seconds >= 0, got {zero_window_s!r}",
            column="zero_window_s",
        )
    return window


@dataclass(eq=False)
class AlignedCampaign:
    """Every instrument on the reference instrument's clock, inside the common time range.

    Arrays have one row per kept reference sample. Wavelengths and temperatures are the measured
    values (their zero state is given separately); the reference displacement is already relative
    to its zero state, which is what a compensation model predicts.

    Attributes
    ----------
    time_s : (n,) reference times inside the overlap, s
    wavelength_nm : (n, n_sensors) Bragg wavelengths, columns in ``sensor_names`` order, nm
    wavelength_zero_nm : (n_sensors,) zero state, nm
    temperature_C : (n, n_probes) columns in ``probe_names`` order, degC
    temperature_zero_C : (n_probes,) zero state, degC
    reference_um : (n, 3) dx, dy, dz minus ``reference_zero_um``, um
    reference_zero_um : (3,) zero state of dx, dy, dz, um
    loads_N : (n, 3) fx, fy, fz or None; NaN where the sample lies outside loads.csv's time range
    dropped : dict with ``before`` and ``after`` (reference samples outside the overlap),
        ``overlap_s`` (t0, t1) and ``loads_outside`` (samples with NaN loads, None without loads)
    """

    name: str
    meta: CampaignMeta
    time_s: np.ndarray
    wavelength_nm: np.ndarray
    wavelength_zero_nm: np.ndarray
    temperature_C: np.ndarray
    temperature_zero_C: np.ndarray
    reference_um: np.ndarray
    reference_zero_um: np.ndarray
    loads_N: np.ndarray | None
    dropped: dict
    sensor_names: list[str]
    probe_names: list[str]
    zero_window_s: float = 10.0

    def __len__(self) -> int:
        """Number of aligned samples."""
        return int(self.time_s.size)

    @property
    def delta_wavelength_nm(self) -> np.ndarray:
        """Wavelength shift from the zero state, (n, n_sensors), nm (Delta S before eq. 2-4)."""
        return self.wavelength_nm - self.wavelength_zero_nm

    @property
    def delta_temperature_C(self) -> np.ndarray:
        """Temperature change from the zero state, (n, n_probes), K."""
        return self.temperature_C - self.temperature_zero_C

    def __repr__(self) -> str:
        t0, t1 = self.dropped["overlap_s"]
        return (
            f"AlignedCampaign(name={self.name!r}, n={len(self)}, overlap_s=({t0:g}, {t1:g}), "
            f"sensors={self.sensor_names}, probes={self.probe_names})"
        )
