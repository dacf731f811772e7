"""Per-sensor fault checks, vectorised over the frames of a batch.

A sample of a sensor is *bad* when its peak is missing, doubled, just outside its window, NaN,
jumps by more than a physical bound from the previous sample, or has been exactly constant
for too long (a stuck interrogator channel). A sensor is *faulted* from its first bad sample
until it has been good for ``recover_s`` (re-admission after a stable period). The state
carried between batches is a handful of per-sensor vectors, so checks cost O(n·S) numpy work.

A jump between two consecutive samples (an interrogator mode hop: the peak moves by a
fraction of a nm or more in one frame and stays there) is not re-admitted against the old zero:
the step itself is taken as the sensor's new offset (``offset_nm``; per frame in
``row_offset_nm``), so that once re-admitted the sensor reads what it read just before the
jump plus what it has changed since. The pipeline subtracts that offset from the wavelength.

Re-admission is also checked against the other gratings (:class:`fbgcomp.runtime.pipeline.
Pipeline`): on the frame a grating would come back, the model with it and the fallback without
it must agree within ``readmit_k_sigma`` times their combined expected error on every axis;
otherwise it stays out (INCONSISTENT) for another ``recover_s`` and is checked again. This
catches what the re-zero rule cannot see: a grating that comes back shifted after a gap.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

OK, MISSING, DOUBLED, OUT_OF_WINDOW, JUMP, STUCK, NAN, RECOVERING, NO_ZERO, INCONSISTENT = range(10)
STATUS_NAMES = (
    "OK",
    "MISSING",
    "DOUBLED",
    "OUT_OF_WINDOW",
    "JUMP",
    "STUCK",
    "NAN",
    "RECOVERING",
    "NO_ZERO",
    "INCONSISTENT",
)


@dataclass
class HealthConfig:
    """Thresholds of the sensor checks (``[pipeline.health]``, docs/runtime.md)."""

    max_jump_nm: float = 0.1  # ~80 µε or ~10 K in one sample: not physical for the ram
    stuck_s: float = 2.0  # exactly constant wavelength this long = stuck channel (0: off)
    # ... and for at least this many repeats of the value in a row: at 1 frame/s, 2 s is two
    # repeats, which a live grating recorded to 1 fm makes by chance (ram2's thermal_b: once in
    # 36 h, and the full model then stood out of service for 70 s); five is ~1e-15 a frame
    stuck_repeats: int = 5
    recover_s: float = 1.0  # a recovered sensor must stay good this long
    # re-admission: the models with and without the grating agree within this many combined
    # expected errors (sqrt(rms_with^2 + rms_without^2)) per axis; 0 = no check
    readmit_k_sigma: float = 4.0


class SensorChecks:
    """Stateful per-sensor checks; ``check`` returns (status (n,S) uint8, faulted (n,S) bool)."""

    def __init__(self, n_sensors: int, config: HealthConfig | None = None):
        self.config = config or HealthConfig()
        self.last_value = np.full(n_sensors, np.nan)  # last finite wavelength, nm
        self.last_raw = np.full(n_sensors, np.nan)  # last sample as received
        self.last_change_s = np.full(n_sensors, -np.inf)  # time the value last changed
        self.repeats = np.zeros(n_sensors, np.int64)  # repeats of the last value in a row
        self.last_bad_s = np.full(n_sensors, -np.inf)  # time of the last bad sample
        self.never_zeroed = np.zeros(n_sensors, bool)  # (a property: its any() is kept)
        self.offset_nm = np.zeros(n_sensors)  # summed mode-hop steps, nm
        self.row_offset_nm = np.zeros((0, n_sensors))  # offset_nm per frame, last batch
        self._zeros_cache: dict[int, np.ndarray] = {}

    def all_good(self, time_s: np.ndarray, wavelength_nm: np.ndarray, peak_count: np.ndarray) -> bool:
        """The usual batch in a handful of numpy calls: True when :meth:`check` would find every
        sample OK and no sensor faulted (one peak each, finite, every value changed from the
        previous one by at most ``max_jump_nm``, no sensor recovering or without a zero), and
        then carries the state exactly as :meth:`check` would. False (state untouched)
        otherwise: the caller runs :meth:`check`.

        A sample equal to the previous one is left to :meth:`check` (it may start a stuck
        run), so noise-free replays with ``stuck_s = 0`` take the full check."""
        n = time_s.size
        if n == 0 or self._any_never_zeroed:
            return False
        cfg = self.config
        t_first = float(time_s[0]) if n == 1 else float(time_s.min())
        # every sensor good for recover_s before the first frame: nothing is recovering
        if t_first - float(self.last_bad_s.max()) < cfg.recover_s:
            return False
        # NaN (missing value or no previous one) fails both comparisons
        if n == 1:  # one frame (a high frame rate): the same tests on Python floats
            jump = cfg.max_jump_nm
            for a, b in zip(wavelength_nm[0].tolist(), self.last_value.tolist()):
                if not 0.0 < abs(a - b) <= jump:
                    return False
            if peak_count[0].tolist().count(1) != peak_count.shape[1]:
                return False
        else:
            step = np.abs(np.diff(wavelength_nm, axis=0, prepend=self.last_value[None, :]))
            if not ((step <= cfg.max_jump_nm) & (step > 0.0)).all() or not (peak_count == 1).all():
                return False
        if not self.offset_nm.any():
            self.row_offset_nm = self._zero_offsets(n)
        else:
            self.row_offset_nm = np.broadcast_to(self.offset_nm, wavelength_nm.shape)
        last = wavelength_nm[-1].copy()
        self.last_raw = last
        self.last_value = last
        self.repeats.fill(0)
        # every sample changed: check's running maximum of the change times
        self.last_change_s = np.maximum(
            self.last_change_s, float(time_s[0]) if n == 1 else float(time_s.max())
        )
        return True

    def _zero_offsets(self, n: int) -> np.ndarray:
        """A read-only (n, S) zero offset, shared between batches of one size."""
        z = self._zeros_cache.get(n)
        if z is None:
            z = np.zeros((n, self.offset_nm.size))
            z.flags.writeable = False
            if len(self._zeros_cache) < 64:
                self._zeros_cache[n] = z
        return z

    @property
    def never_zeroed(self) -> np.ndarray:
        """(S,) bool: sensors without a zero wavelength (read-only; assign a new array)."""
        return self._never_zeroed

    @never_zeroed.setter
    def never_zeroed(self, value) -> None:
        value = np.array(value, dtype=bool)
        value.flags.writeable = False
        self._never_zeroed = value
        self._any_never_zeroed = bool(value.any())  # asked per batch by all_good

    def check(
        self, time_s: np.ndarray, wavelength_nm: np.ndarray, peak_count: np.ndarray, near_count: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """Check a batch: (status (n, S) codes of :data:`STATUS_NAMES`, faulted (n, S) bool).

        A sensor is faulted from its first bad sample until it has been good for ``recover_s``;
        the last values are carried to the next batch.
        """
        cfg = self.config
        n, S = wavelength_nm.shape
        t = time_s[:, None]
        finite = np.isfinite(wavelength_nm)
        status = np.zeros((n, S), np.uint8)

        # Jump: against the previous finite value (carried over from the previous batch).
        all_finite = bool(finite.all())
        if all_finite:  # the usual case: the previous value is simply the previous row
            last_fin = None
            prev_val = np.concatenate([self.last_value[None, :], wavelength_nm[:-1]])
        else:
            idx = np.arange(n)[:, None]
            last_fin = np.maximum.accumulate(np.where(finite, idx, -1), axis=0)
            prev_fin = np.vstack([np.full((1, S), -1), last_fin[:-1]])
            prev_val = np.where(
                prev_fin >= 0,
                np.take_along_axis(wavelength_nm, np.maximum(prev_fin, 0), axis=0),
                self.last_value,
            )
        with np.errstate(invalid="ignore"):
            jump = finite & (np.abs(wavelength_nm - prev_val) > cfg.max_jump_nm)

        # Stuck: exactly the same value as the previous sample for at least stuck_s and
        # stuck_repeats samples.
        prev_raw = np.vstack([self.last_raw[None, :], wavelength_nm[:-1]])
        changed = ~(finite & (wavelength_nm == prev_raw))
        t_change = np.maximum.accumulate(np.where(changed, t, -np.inf), axis=0)
        t_change = np.maximum(t_change, self.last_change_s)
        row = np.arange(n)[:, None]
        last_row = np.maximum.accumulate(np.where(changed, row, -1), axis=0)
        repeats = np.where(last_row >= 0, row - last_row, row + 1 + self.repeats)
        # a live grating always shows some noise; noise-free replays must set stuck_s = 0
        stuck = (
            finite & ((t - t_change) >= cfg.stuck_s) & (repeats >= cfg.stuck_repeats)
            if cfg.stuck_s > 0
            else np.zeros((n, S), bool)
        )

        # Re-zero rule: a jump between consecutive finite samples (no gap) is a step of the
        # reading, not of the machine; from that frame on it is subtracted (offset_nm). A jump
        # after missing samples is only flagged: the machine may have moved in the gap.
        with np.errstate(invalid="ignore"):
            hop = jump & np.isfinite(prev_raw)
        step = np.where(hop, wavelength_nm - prev_val, 0.0)
        self.row_offset_nm = self.offset_nm + np.cumsum(step, axis=0)

        status[stuck] = STUCK
        status[jump] = JUMP
        status[(peak_count == 1) & ~finite] = NAN
        status[(peak_count == 0) & (near_count > 0)] = OUT_OF_WINDOW
        status[(peak_count == 0) & (near_count == 0)] = MISSING
        status[peak_count > 1] = DOUBLED
        status[:, self.never_zeroed] = NO_ZERO
        bad = status != OK

        if bad.any():
            last_bad = np.maximum.accumulate(np.where(bad, t, -np.inf), axis=0)
            last_bad = np.maximum(last_bad, self.last_bad_s)
        else:
            last_bad = np.broadcast_to(self.last_bad_s, (n, S))
        faulted = bad | ((t - last_bad) < cfg.recover_s)
        status[faulted & ~bad] = RECOVERING

        # carry state
        if n:
            self.offset_nm = self.row_offset_nm[-1].copy()
            self.last_raw = wavelength_nm[-1].copy()
            self.last_change_s = t_change[-1].copy()
            self.repeats = repeats[-1].copy()
            self.last_bad_s = last_bad[-1].copy()
            if last_fin is None:  # all finite
                self.last_value = wavelength_nm[-1].copy()
            else:
                has = last_fin[-1] >= 0
                self.last_value = np.where(
                    has, wavelength_nm[np.maximum(last_fin[-1], 0), np.arange(S)], self.last_value
                )
        return status, faulted


# --------------------------------------------------------------------------- output flags
# One flag word per frame and TTP axis (uint8), OR-ed from the model's own policy flags
# (its predictor's ``last_flags``) and the runtime's output limits. Published in the batch
# result, the run log (``flags_dx``...), OPC UA (``OutputFlagsX``...) and the dashboard.
FLAG_SHRUNK = 1  # model: inputs outside the training envelope, correction shrunk
FLAG_CLAMPED = 2  # model: bounded to the model's own maximum
FLAG_LOAD_REFUSED = 4  # model: the gratings contradict each other, the load part dropped
FLAG_RATE_LIMITED = 8  # runtime: the rate limit held the published correction back
FLAG_MAX_LIMITED = 16  # runtime: the per-axis maximum |correction| held it back
MODEL_FLAGS = FLAG_SHRUNK | FLAG_CLAMPED | FLAG_LOAD_REFUSED
LIMIT_FLAGS = FLAG_RATE_LIMITED | FLAG_MAX_LIMITED
FLAG_NAMES = {
    FLAG_SHRUNK: "SHRUNK",
    FLAG_CLAMPED: "CLAMPED",
    FLAG_LOAD_REFUSED: "LOAD_REFUSED",
    FLAG_RATE_LIMITED: "RATE_LIMITED",
    FLAG_MAX_LIMITED: "MAX_LIMITED",
}


def flag_names(word: int) -> list[str]:
    """Names of the bits set in one flag word, lowest bit first."""
    return [name for bit, name in FLAG_NAMES.items() if int(word) & bit]


def describe_flags(words, axes=("X", "Y", "Z")) -> str:
    """``"Y:RATE_LIMITED|MAX_LIMITED Z:SHRUNK"``; empty when nothing is held back."""
    return " ".join(f"{a}:{'|'.join(flag_names(w))}" for a, w in zip(axes, words) if int(w))
