"""Core real-time pipeline: sensor wavelengths (+ temperatures) -> TTP deviation -> correction.

The maths is the offline model's own (``model.predictor(...).predict``); this module only adds
what a running machine needs, vectorised over every frame of a batch:

* zero state: mean of the first ``model.zero_window_s`` seconds of each signal;
* sensor checks (:mod:`fbgcomp.runtime.health`) and, from the first bad sample on, the
  fallback model fitted without the faulted sensor(s) and lost probes (a probe without a
  reading or a zero: smallest stored excluded set covering them) - the switch happens on the
  very sample the fault appears;
* when no usable model remains: hold the last correction and ramp it linearly to zero over
  ``ramp_s`` (alarm);
* the output policy, in this order: the adaptive output filter (:mod:`fbgcomp.runtime.output_filter`,
  on by default: still at rest, fast on a real change), the hold / ramp above, optional
  exponential smoothing (``smoothing_tau_s``), the output switch, a per-axis maximum
  |correction| (``max_correction_um``, at most the model's own ``max_correction_um``) and a
  per-axis rate limit (``max_slew_um_per_s``), so that a model switch, a re-admitted sensor or
  switching the output off never steps the axes and no absurd value reaches the CNC.

The per-axis maximum is also the envelope the correction is trusted in. A prediction beyond it
is clamped to it and never published with health OK (OK becomes DEGRADED, flag
``MAX_LIMITED``); beyond ``ABSURD_FACTOR`` times it on any axis (or not finite) it is not
published at all - the frame is handled as one without a usable model (ALARM, hold the last
correction and ramp it to zero). The rate limit counts at most ``2 x`` the nominal frame interval
per frame, so a gap in the frames (a reconnect) does not bank a step. A grating that jumped is
re-zeroed by the step (:mod:`fbgcomp.runtime.health`) before it is re-admitted, and no grating is
re-admitted unless the model with it agrees with the fallback without it on that frame, within
``readmit_k_sigma`` combined expected errors per axis (else it stays out, INCONSISTENT, for
another ``recover_s``): a grating back from a gap with a shifted reading is not taken as truth.

Health codes per frame: OK, DEGRADED (fallback in use), ALARM (hold / ramp), ZEROING. Beside
them, a flag word per frame and axis (``BatchResult.output_flags``, bits in
:mod:`fbgcomp.runtime.health`) says when the published correction was held back - by the
model's own policy (its predictor's ``last_flags``) or by the limits.

One module over 600 lines, on purpose: it is the hot path. Every stage above works on the same
per-batch arrays and on state carried from batch to batch (zero state, sensor history, the last
correction, filter and rate-limit state) that :meth:`Pipeline.continue_from` hands to a reloaded
model in one piece; split into modules, that state would be shared across them, and the order
of the stages - which is the safety argument - would no longer be read in one place. The
stages that stand alone already live beside it (:mod:`.health`, :mod:`.output_filter`,
:mod:`.outputs.cnc_form`).
"""

from __future__ import annotations

import copy
import inspect
import itertools
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from fbgcomp.runtime import health as H
from fbgcomp.runtime.output_filter import AdaptiveLevelFilter, OutputFilterConfig
from fbgcomp.runtime.outputs.cnc_form import reference_z_mm, takes_z

HEALTH_OK, HEALTH_DEGRADED, HEALTH_ALARM, HEALTH_ZEROING = range(4)
HEALTH_NAMES = ("OK", "DEGRADED", "ALARM", "ZEROING")

_TAKES_TIME: dict[type, bool] = {}
# A prediction beyond this many times the per-axis maximum is no machine state (the maximum
# already holds the largest validated load with margin) but a broken model or sensor.
ABSURD_FACTOR = 3.0


def _takes_time(predictor) -> bool:
    """Whether ``predictor.predict`` accepts the frame clock ``time_s`` (every built-in model
    does; a predictor of one's own may not need it)."""
    kind = type(predictor)
    if kind not in _TAKES_TIME:
        params: Mapping[str, inspect.Parameter]
        try:
            params = inspect.signature(predictor.predict).parameters
        except (TypeError, ValueError):
            params = {}
        _TAKES_TIME[kind] = "time_s" in params or any(
            p.kind is inspect.Parameter.VAR_KEYWORD for p in params.values()
        )
    return _TAKES_TIME[kind]


@dataclass
class PipelineConfig:
    """Output policy and checks of the pipeline (``[pipeline]``, docs/runtime.md)."""

    ramp_s: float = 2.0  # hold-then-ramp-to-zero time when no model is usable
    smoothing_tau_s: float = 0.0  # exponential smoothing of the correction; 0 = off
    # Per axis (dx, dy, dz) or one value for all; 0 = off on that axis (docs/runtime.md: why
    # these defaults). A real load step of a few hundred µm is still followed within 1 s.
    max_slew_um_per_s: tuple = (1000.0, 1000.0, 1000.0)  # largest rate of change, µm/s
    max_correction_um: tuple = (1000.0, 1000.0, 1000.0)  # largest |correction|, µm
    health: H.HealthConfig = field(default_factory=H.HealthConfig)
    output_filter: OutputFilterConfig = field(default_factory=OutputFilterConfig)


def per_axis(value, name: str = "value") -> np.ndarray:
    """One number or three (dx, dy, dz) -> a (3,) array; 0 (off) becomes +inf."""
    v = np.asarray(value, dtype=float).reshape(-1)
    if v.size == 1:
        v = np.repeat(v, 3)
    if v.size != 3 or not np.all(v >= 0):
        raise ValueError(f"{name}: expected one value or three (dx, dy, dz), each >= 0")
    return np.where(v > 0, v, np.inf)


@dataclass
class BatchResult:
    """Per-frame outputs of one batch (n frames)."""

    time_s: np.ndarray  # (n,)
    deviation_um: np.ndarray  # (n,3) predicted TTP deviation, NaN without a model
    half_width_um: np.ndarray  # (n,3) 95 % prediction interval half-width
    correction_um: np.ndarray  # (n,3) published correction (-deviation, held, smoothed)
    expected_rms_um: np.ndarray  # (n,3) residual SD of the model in use
    health: np.ndarray  # (n,) uint8 HEALTH_*
    sensor_status: np.ndarray  # (n,S) uint8 health.* codes
    model_set: np.ndarray  # (n,) int16 index into Pipeline.model_sets, -1 none
    temperature_C: np.ndarray  # (n,P) temperatures paired with the frames
    # (n,3) uint8 health.FLAG_* (model policy | limits); not given: no flag on any frame
    output_flags: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), np.uint8))

    def __post_init__(self):
        if self.output_flags.shape[0] == 0 and self.time_s.size:
            self.output_flags = np.zeros((self.time_s.size, 3), np.uint8)

    def __len__(self) -> int:
        return self.time_s.size


class Pipeline:
    """Stateful batch processor around a loaded model (see ``fbgcomp.models.base.load_model``)."""

    def __init__(self, model, config: PipelineConfig | None = None):
        self.model = model
        self.config = config or PipelineConfig()
        self.sensor_names = list(model.sensor_names)
        self.probe_names = list(model.probe_names)
        S, P = len(self.sensor_names), len(self.probe_names)
        self.checks = H.SensorChecks(S, self.config.health)
        self.zero_window_s = float(model.zero_window_s)
        self._zero_sum = np.zeros(S)
        self._zero_n = np.zeros(S)
        self._tzero_sum = np.zeros(P)
        self._tzero_n = np.zeros(P)
        self._t_first: float | None = None
        self.wavelength_zero_nm: np.ndarray | None = None
        self.temperature_zero_C: np.ndarray | None = None
        self._probe_unzeroed = np.zeros(P, bool)  # probes without a zero-state value: lost
        # model_sets[0] is the full model; the rest the stored fallbacks
        self.model_sets: list[frozenset[str]] = [
            frozenset(),
            *sorted((frozenset(s) for s in model.fallback_sets), key=lambda s: (len(s), sorted(s))),
        ]
        # duck-typed: any object with predict(...) and expected_rms_error_um (a model's own
        # predictor classes share no base, and a predictor of one's own may be used)
        self._predictors: dict[int, Any] = {}
        self._choice_cache: dict[bytes, int] = {}
        self._last_correction = np.zeros(3)
        self._hold_start_s: float | None = None
        self._hold_frac = 1.0  # the ramp's fraction reached by the hold _hold_start_s begins
        self._hold_from = np.zeros(3)
        self._smoothed: np.ndarray | None = None
        self._last_t: float | None = None
        self._slew_y: np.ndarray | None = None
        self._slew_t: float | None = None
        self.max_slew_um_per_s = per_axis(self.config.max_slew_um_per_s, "max_slew_um_per_s")
        cap = per_axis(self.config.max_correction_um, "max_correction_um")
        own = getattr(model, "max_correction_um", None)
        if own is not None:  # the model file's own bound wins where it is tighter
            cap = np.minimum(cap, per_axis(own, "model max_correction_um"))
        self.max_correction_um = cap
        self.output_filter: AdaptiveLevelFilter | None = None
        self._filter_set: int | None = None  # model set of the last filtered frame
        self._zero_frames = 0
        self._t_zero_last: float | None = None
        self.frame_dt_s: float | None = None  # nominal frame interval (the rate limit's cap)
        self._prev_mask = np.zeros(S, bool)  # faulted sensors on the last predicted frame
        self._prev_choice = 0  # model set of the last predicted frame
        self._ran = -1  # model set whose predictor ran the last predicted frame
        self._inconsistent_until = np.full(S, -np.inf)  # kept out by the re-admission check
        self.readmissions_refused = 0
        self._no_fault = np.zeros(S, bool)  # read only: _prev_mask, no fault
        self._no_fault.flags.writeable = False
        rate = self.max_slew_um_per_s
        self._slew_axes = ~np.isinf(rate)  # axes with a rate limit
        self._slew_rate = np.where(self._slew_axes, rate, 0.0)
        self._slew_off = not self._slew_axes.any()  # no axis limited
        self._slew_lists = (self._slew_rate.tolist(), self._slew_axes.tolist())  # the one-frame test
        self._max_list = self.max_correction_um.tolist()
        self._z: np.ndarray | None = None  # this batch's Z position per frame, mm
        self._uses_z: bool | None = None

    def continue_from(self, old: Pipeline) -> None:
        """Take over the running state of ``old`` (a model reload: the machine has not been
        re-zeroed, the gratings have not been re-checked). Zero state, sensor checks, hold,
        smoothing, rate limit and output filter carry over, and so does the re-admission check:
        gratings held out as INCONSISTENT stay so until their time is up, and a grating coming
        back on the first frame after the reload is checked against the faulted set before it.
        Model-set indices are translated by the sets they name (the new model's stored
        fallbacks may differ)."""
        self.checks = old.checks
        self._t_first = old._t_first
        self._zero_sum, self._zero_n = old._zero_sum, old._zero_n
        self._tzero_sum, self._tzero_n = old._tzero_sum, old._tzero_n
        self.wavelength_zero_nm = old.wavelength_zero_nm
        self.temperature_zero_C = old.temperature_zero_C
        self._probe_unzeroed = old._probe_unzeroed
        self._last_correction, self._hold_start_s = old._last_correction, old._hold_start_s
        self._hold_frac = old._hold_frac
        self._hold_from = old._hold_from
        self._smoothed, self._last_t = old._smoothed, old._last_t
        self._slew_y, self._slew_t = old._slew_y, old._slew_t
        self._zero_frames, self.output_filter = old._zero_frames, old.output_filter
        self._t_zero_last, self.frame_dt_s = old._t_zero_last, old.frame_dt_s
        self._prev_mask = old._prev_mask.copy()
        self._inconsistent_until = old._inconsistent_until.copy()
        self.readmissions_refused = old.readmissions_refused
        # the set in use on the last predicted frame, as this model would have chosen it for
        # the same faulted gratings (-1 stays -1: nothing was predicted, nothing to compare)
        self._prev_choice = self._choose(self._prev_mask) if old._prev_choice >= 0 else -1
        if old._filter_set is None:
            self._filter_set = None
        elif old._filter_set >= 0 and old.model_sets[old._filter_set] in self.model_sets:
            self._filter_set = self.model_sets.index(old.model_sets[old._filter_set])
        else:  # a set this model does not have: its first frame is a switch (filter re-seated)
            self._filter_set = -2

    # -- model selection
    def predictor(self, k: int) -> Any:
        """The predictor of model set ``k`` (``model_sets[k]`` excluded), made once and kept.

        A predictor with state (filters, a load tracker: it has ``reset``) is this pipeline's
        own copy, from a fresh state: the model keeps one predictor per sensor set, so a
        second pipeline on the same model (a replay beside a live run, a test) went on from
        the first one's state, and the load the first had read was applied again."""
        if k not in self._predictors:
            p = self.model.predictor(exclude=self.model_sets[k])
            if callable(getattr(p, "reset", None)):
                p = copy.copy(p)
                p.reset()
            self._predictors[k] = p
        return self._predictors[k]

    def set_without(self, excluded_mask: np.ndarray) -> int:
        """Index into ``model_sets`` of the smallest set that leaves out every instrument of
        ``excluded_mask`` (the gratings, then the probes), -1 for none: whether the model can
        go on without them."""
        return self._choose(np.asarray(excluded_mask, bool))

    def _choose(self, excluded_mask: np.ndarray) -> int:
        """The smallest model set that leaves out every instrument of ``excluded_mask``: the
        gratings (S,), or the gratings then the probes (S + P,); -1 for none."""
        key = excluded_mask.tobytes()
        if key not in self._choice_cache:
            names = self.sensor_names + self.probe_names
            excluded = frozenset(n for n, m in zip(names, excluded_mask) if m)
            choice = -1
            for k, s in enumerate(self.model_sets):  # sorted smallest first
                if excluded <= s:
                    choice = k
                    break
            self._choice_cache[key] = choice
        return self._choice_cache[key]

    @property
    def zeroed(self) -> bool:
        """Whether the zero state (the wavelengths of the zero window) is known."""
        return self.wavelength_zero_nm is not None

    # -- zero state
    def _accumulate_zero(self, t, wl, status, temp) -> int:
        """Use the leading rows that fall in the zero window; return how many were used."""
        first_call = self._t_first is None
        if self._t_first is None:
            self._t_first = float(t[0])
        t_first = self._t_first
        # same convention as the offline path: samples with t <= t_first + window
        end = t_first + self.zero_window_s
        m = int(np.searchsorted(t, end, side="right"))
        if first_call:
            m = max(m, 1)
        self._zero_frames += m
        if m:
            self._t_zero_last = float(t[m - 1])
        good = (status[:m] == H.OK) & np.isfinite(wl[:m])
        self._zero_sum += np.where(good, wl[:m], 0.0).sum(axis=0)
        self._zero_n += good.sum(axis=0)
        if temp.shape[1]:
            tg = np.isfinite(temp[:m])
            self._tzero_sum += np.where(tg, temp[:m], 0.0).sum(axis=0)
            self._tzero_n += tg.sum(axis=0)
        if m < t.size or self.zero_window_s <= 0:
            with np.errstate(invalid="ignore", divide="ignore"):
                self.wavelength_zero_nm = np.where(self._zero_n > 0, self._zero_sum / self._zero_n, np.nan)
                self.temperature_zero_C = np.where(self._tzero_n > 0, self._tzero_sum / self._tzero_n, np.nan)
            self._probe_unzeroed = ~np.isfinite(self.temperature_zero_C)
            self.checks.never_zeroed = ~np.isfinite(self.wavelength_zero_nm)
            t_last = self._t_zero_last  # set once a frame was used (_zero_frames > 0)
            if self._zero_frames > 1 and t_last is not None and t_last > t_first:
                self.frame_dt_s = (t_last - t_first) / (self._zero_frames - 1)
        return m

    # -- main entry
    def process(
        self,
        time_s: np.ndarray,
        wavelength_nm: np.ndarray,
        peak_count: np.ndarray,
        near_count: np.ndarray,
        temperature_C: np.ndarray,
        enabled: bool = True,
        z_axis_mm=None,
    ) -> BatchResult:
        """One batch of frames -> :class:`BatchResult`.

        ``z_axis_mm`` is the Z-axis position, mm (scalar or (n,)), passed to the model's
        ``predict`` on every frame; None (no position source) leaves the model at the Z it
        assumes. For a model whose prediction depends on Z (a kinematic chain), a non-finite Z
        is a missing input: no model usable, ALARM, hold / ramp (a missing temperature is a lost
        probe, for which the model may store a set without it).
        The default (physical) model holds dx and dy back at a Z more than its
        ``z_tolerance_mm`` from the positions it was trained at, or a non-finite one; a
        regression ignores it."""
        self._z = (
            None
            if z_axis_mm is None
            else np.broadcast_to(np.asarray(z_axis_mm, dtype=np.float64), time_s.shape)
        )
        if self.wavelength_zero_nm is not None and time_s.size:
            res = self._process_steady(time_s, wavelength_nm, peak_count, temperature_C, enabled)
            if res is not None:
                return res
        return self._process(time_s, wavelength_nm, peak_count, near_count, temperature_C, enabled)

    def _process_steady(
        self, time_s, wavelength_nm, peak_count, temperature_C, enabled
    ) -> BatchResult | None:
        """The usual batch of a running machine, in few numpy calls (its fixed cost is what
        limits the frame rate at small batches): zeroed, every grating good and none
        recovering, every probe finite, the full model in use and no re-admission pending.
        The same steps as :meth:`_process` - only the branches such a batch cannot take are
        left out - so the results are the same to the bit (tests/test_runtime_fastpath.py).
        None (nothing changed) for any other batch."""
        if self._prev_choice != 0 and self._prev_mask.any() and self.config.health.readmit_k_sigma > 0:
            return None  # the previous frame was on a fallback: a re-admission
        if self._ran > 0:
            return None  # a fallback ran last: the full model takes over from its state
        if temperature_C.shape[1] and (self._probe_unzeroed.any() or not np.isfinite(temperature_C).all()):
            return None  # a probe lost: the set without it, if the model has one
        if self._z is not None and self.uses_z and not np.isfinite(self._z).all():
            return None
        if not self.checks.all_good(time_s, wavelength_nm, peak_count):
            return None
        n, S = wavelength_nm.shape
        offset = self.checks.offset_nm
        if offset.any():  # a grating that jumped reads from its offset after the step
            wavelength_nm = wavelength_nm - offset
        self._prev_mask = self._no_fault
        self._prev_choice = 0
        p = self._predictors.get(0)
        if p is None:
            p = self.predictor(0)
        self._ran = 0
        d, h = p.predict(
            wavelength_nm,
            temperature_C,
            self.wavelength_zero_nm,
            self.temperature_zero_C,
            **self._inputs(p, time_s, slice(None)),
        )
        dev = np.empty((n, 3))
        dev[:] = d
        half = np.empty((n, 3))
        half[:] = h
        rms = np.empty((n, 3))
        rms[:] = p.expected_rms_error_um
        health = np.zeros(n, np.uint8)  # HEALTH_OK
        model_set = np.zeros(n, np.int16)
        flags = np.zeros((n, 3), np.uint8)
        own = getattr(p, "last_flags", None)  # the model's own output policy
        if own is not None:
            flags |= np.asarray(own, np.uint8).reshape(n, 3) & H.MODEL_FLAGS
        target = -dev
        in_bounds = bool((np.abs(target) <= self.max_correction_um).all())  # NaN is not
        if not in_bounds:
            target = self._envelope(target, health, flags)
        if (
            self.config.output_filter.enabled
            and self.output_filter is not None
            and self._filter_set == 0
            and (in_bounds or np.isfinite(target).all())
        ):
            correction = self.output_filter.process(target, getattr(p, "last_follow", None))  # one segment
        else:
            correction = self._filter(time_s, target, rms, model_set, getattr(p, "last_follow", None))
        if np.isfinite(correction).all():  # nothing to hold
            self._hold_start_s = None
            self._last_correction = correction[-1].copy()
        else:
            correction = self._hold_and_ramp(time_s, correction, health)
        correction = self._shape(time_s, correction, enabled, flags, self._gap_cap(time_s))
        status = np.zeros((n, S), np.uint8)  # health.OK
        return BatchResult(
            time_s, dev, half, correction, rms, health, status, model_set, temperature_C, flags
        )

    def _process(
        self,
        time_s: np.ndarray,
        wavelength_nm: np.ndarray,
        peak_count: np.ndarray,
        near_count: np.ndarray,
        temperature_C: np.ndarray,
        enabled: bool = True,
    ) -> BatchResult:
        n, _ = wavelength_nm.shape
        status, faulted = self.checks.check(time_s, wavelength_nm, peak_count, near_count)
        if n and (self._inconsistent_until > time_s[0]).any():
            held = (status == H.RECOVERING) & (time_s[:, None] < self._inconsistent_until)
            status[held] = H.INCONSISTENT
        # a grating that jumped (mode hop) reads from its offset after the step
        if self.checks.row_offset_nm.any():
            wavelength_nm = wavelength_nm - self.checks.row_offset_nm
        dev = np.full((n, 3), np.nan)
        half = np.full((n, 3), np.nan)
        rms = np.full((n, 3), np.nan)
        health = np.full(n, HEALTH_ZEROING, np.uint8)
        model_set = np.full(n, -1, np.int16)
        flags = np.zeros((n, 3), np.uint8)
        follow = None  # (n, 3) frames a model publishes as they are (its confirmed motion)
        start = 0
        if not self.zeroed:
            start = self._accumulate_zero(time_s, wavelength_nm, status, temperature_C)
            if not self.zeroed:
                start = n
            elif self.checks.never_zeroed.any():
                # sensors without a zero value are faulted from now on
                status[start:, self.checks.never_zeroed] = H.NO_ZERO
                faulted[start:, self.checks.never_zeroed] = True
        if start < n:
            rows = slice(start, n)
            f = faulted[rows]
            # a probe without a reading (or without a zero) is lost: a model set without it
            # (the model's stored ones) or none
            lost_p = ~np.isfinite(temperature_C[rows]) | self._probe_unzeroed
            z_ok = np.ones(n - start, bool)
            if self._z is not None and self.uses_z:  # a Z-dependent model without its Z
                z_ok &= np.isfinite(self._z[rows])
            choice = self._choices(f, z_ok, lost_p)
            if self.config.health.readmit_k_sigma > 0:
                choice = self._check_readmissions(
                    time_s, wavelength_nm, temperature_C, start, status, faulted, z_ok, choice, lost_p
                )
            self._prev_mask = faulted[-1].copy()
            self._prev_choice = int(choice[-1])
            model_set[rows] = choice
            # runs of frames on one model set, in time order: a model with memory that takes
            # over from another goes on from its state (take_state), not from its own of the
            # last time it ran, nor from a fresh one mid-run
            cuts = np.flatnonzero(np.diff(choice)) + 1
            for lo, hi in zip(np.concatenate([[0], cuts]), np.concatenate([cuts, [choice.size]])):
                k = int(choice[lo])
                if k < 0:
                    continue
                sel = np.arange(lo, hi) + start
                p = self.predictor(k)
                self._take_over(p, k)
                self._ran = k
                d, h = p.predict(
                    wavelength_nm[sel],
                    temperature_C[sel],
                    self.wavelength_zero_nm,
                    self.temperature_zero_C,
                    **self._inputs(p, time_s, sel),
                )
                dev[sel], half[sel] = d, h
                rms[sel] = np.asarray(p.expected_rms_error_um, float)
                own = getattr(p, "last_flags", None)  # the model's own output policy
                if own is not None:
                    flags[sel] |= np.asarray(own, np.uint8).reshape(sel.size, 3) & H.MODEL_FLAGS
                moving = getattr(p, "last_follow", None)
                if moving is not None and moving.any():
                    if follow is None:
                        follow = np.zeros((n, 3), bool)
                    follow[sel] = moving
            health[rows] = np.where(
                choice == 0, HEALTH_OK, np.where(choice > 0, HEALTH_DEGRADED, HEALTH_ALARM)
            )
        target = self._envelope(-dev, health, flags)
        correction = self._filter(time_s, target, rms, model_set, follow)
        correction = self._hold_and_ramp(time_s, correction, health)
        correction = self._shape(time_s, correction, enabled, flags, self._gap_cap(time_s))
        return BatchResult(
            time_s, dev, half, correction, rms, health, status, model_set, temperature_C, flags
        )

    def _inputs(self, p, time_s, sel) -> dict:
        """Keywords of ``p.predict`` for the rows ``sel``: the frame clock (models with memory
        - load tracking, low-passes, leads - run on it, not on the training campaign's
        interval) and the batch's Z position when one is given and the model takes it."""
        kw = {"time_s": time_s[sel]} if _takes_time(p) else {}
        if self._z is not None and takes_z(p):
            kw["z_axis_mm"] = self._z[sel]
        return kw

    @property
    def uses_z(self) -> bool:
        """Whether the model's prediction follows the Z position (it has a kinematic chain:
        kinematic, hybrid, calibrated); the regression does not, and the default model only
        checks it (dx and dy held back at a Z its training never saw, or an unknown one)."""
        if self._uses_z is None:
            self._uses_z = reference_z_mm(self.predictor(0)) is not None
        return self._uses_z

    @property
    def z_note(self) -> str:
        """What the Z position does to a model that does not follow it (serve's start-up note)."""
        trained = getattr(self.model, "trained_z_axis_mm_", None)
        if not trained:
            return "this model's prediction does not depend on Z; the position is read but changes nothing"
        return (
            f"this model was trained at Z = {', '.join(f'{z:g}' for z in trained)} mm; at a Z more than "
            f"{self.model.z_tolerance_mm:g} mm from it, or an unknown one, dx and dy "
            "are held back (SHRUNK)"
        )

    def _choices(self, f: np.ndarray, z_ok: np.ndarray, lost_p: np.ndarray | None = None) -> np.ndarray:
        """Model set per row for the faulted gratings ``f`` (n, S) and lost probes ``lost_p``
        (n, P) (-1: none usable, or ``z_ok`` False: a Z-dependent model without its Z)."""
        if lost_p is not None and lost_p.any():
            f = np.hstack([f, lost_p])
        if f.any():
            patterns, inverse = np.unique(f, axis=0, return_inverse=True)
            choice = np.array([self._choose(p) for p in patterns])[inverse.reshape(-1)]
        else:
            choice = np.zeros(f.shape[0], int)
        return np.where(z_ok, choice, -1)

    def _take_over(self, p, k: int) -> None:
        """Predictor ``p`` of model set ``k`` goes on from the state of the set that ran last,
        if another one did and ``p`` has memory to hand over (``take_state``)."""
        if k != self._ran and self._ran >= 0 and callable(getattr(p, "take_state", None)):
            p.take_state(self.predictor(self._ran))

    def _predict_one(self, k: int, time_s, wavelength_nm, temperature_C, row: int):
        """One frame on model set ``k`` by a copy of its predictor (the check must not move a
        model's state: the frames before ``row`` in this batch are still to come), taking
        over from the set that ran last as the batch would."""
        p = copy.copy(self.predictor(int(k)))
        if hasattr(p, "state"):
            p.state = copy.deepcopy(p.state)
            self._take_over(p, int(k))
        sel = slice(row, row + 1)
        d, _ = p.predict(
            wavelength_nm[sel],
            temperature_C[sel],
            self.wavelength_zero_nm,
            self.temperature_zero_C,
            **self._inputs(p, time_s, sel),
        )
        return np.asarray(d, float).reshape(3), np.asarray(p.expected_rms_error_um, float)

    def _check_readmissions(
        self, time_s, wavelength_nm, temperature_C, start, status, faulted, z_ok, choice, lost_p=None
    ) -> np.ndarray:
        """Keep out a grating whose re-admission the other gratings contradict.

        On a frame where gratings come back (the faulted set shrinks from one predicted frame
        to the next), the model set they come back to and the one in use until then predict
        that same frame; if they differ by more than ``readmit_k_sigma`` x sqrt(rms_new^2 +
        rms_old^2) on any axis, the returning gratings stay faulted (INCONSISTENT) for another
        ``recover_s`` and the rows are re-chosen. Rare (a re-admission a second at most per
        grating): two one-frame predictions per re-admission. Gratings that come back to a set
        that read none are admitted unchecked: no other grating speaks against them."""
        cfg = self.config.health
        f = faulted[start:]
        t = time_s[start:]
        i = 0
        while i < f.shape[0]:
            prev_mask = np.vstack([self._prev_mask[None, :], f[:-1]])
            prev_k = np.concatenate([[self._prev_choice], choice[:-1]])
            back = (prev_mask & ~f).any(axis=1) & (prev_k >= 0) & (choice >= 0) & (prev_k != choice)
            # no grating in use until then (a lost link, every fibre cut): none to contradict
            # the returning ones, and a set that reads no force would refuse them for good
            # under a held load (ram2's thermal_c: 350 µm of Fx read by them, none by it)
            back &= ~prev_mask.all(axis=1)
            back[:i] = False
            if not back.any():
                break
            r = int(np.argmax(back))
            row = start + r
            d_new, rms_new = self._predict_one(choice[r], time_s, wavelength_nm, temperature_C, row)
            d_old, rms_old = self._predict_one(prev_k[r], time_s, wavelength_nm, temperature_C, row)
            tol = cfg.readmit_k_sigma * np.hypot(rms_new, rms_old)
            with np.errstate(invalid="ignore"):
                agree = np.abs(d_new - d_old) <= tol
            # a model without an error estimate cannot be checked (NaN tolerance): admitted
            if (agree | ~np.isfinite(tol)).all() and np.isfinite(d_new).all():
                i = r + 1
                continue
            js = prev_mask[r] & ~f[r]
            until = float(t[r]) + cfg.recover_s
            span = t[r:] < until
            f[r:, js] |= span[:, None]
            st = status[row:, :]
            st[:, js] = np.where(span[:, None] & (st[:, js] == H.OK), H.INCONSISTENT, st[:, js])
            self.checks.last_bad_s[js] = np.maximum(self.checks.last_bad_s[js], float(t[r]))
            self._inconsistent_until[js] = until
            self.readmissions_refused += 1
            choice[r:] = self._choices(f[r:], z_ok[r:], None if lost_p is None else lost_p[r:])
            i = r + 1
        return choice

    def _envelope(self, corr: np.ndarray, health: np.ndarray, flags: np.ndarray) -> np.ndarray:
        """Rows whose prediction is beyond the per-axis maximum are not OK (DEGRADED; the
        clamp in ``_shape`` bounds them); beyond ``ABSURD_FACTOR`` times it on any axis, or not
        finite, they are not trusted at all: NaN (so held and ramped like a frame without a
        model), ALARM. ``FLAG_MAX_LIMITED`` on the offending axes."""
        predicted = (health == HEALTH_OK) | (health == HEALTH_DEGRADED)
        with np.errstate(invalid="ignore"):
            over_axis = predicted[:, None] & ~(np.abs(corr) <= self.max_correction_um)
            bad_axis = over_axis & ~(np.abs(corr) <= ABSURD_FACTOR * self.max_correction_um)
        if not over_axis.any():
            return corr
        flags[over_axis] |= H.FLAG_MAX_LIMITED
        health[over_axis.any(axis=1) & (health == HEALTH_OK)] = HEALTH_DEGRADED
        bad = bad_axis.any(axis=1)
        if not bad.any():
            return corr
        health[bad] = HEALTH_ALARM
        out = corr.copy()
        out[bad] = np.nan
        return out

    def _gap_cap(self, t: np.ndarray) -> float:
        """Longest interval the rate limit credits to one frame: twice the nominal frame
        interval (from the zero window, else this batch), so a gap cannot bank a step."""
        if self.frame_dt_s is None and t.size > 1:
            d = np.diff(t)
            d = d[d > 0]
            if d.size:
                self.frame_dt_s = float(np.median(d))
        return np.inf if self.frame_dt_s is None else 2.0 * self.frame_dt_s

    def _filter(
        self,
        t: np.ndarray,
        corr: np.ndarray,
        rms: np.ndarray,
        model_set: np.ndarray | None = None,
        follow: np.ndarray | None = None,
    ) -> np.ndarray:
        """Adaptive output filter over the rows with a prediction (the others stay NaN).

        It is re-seated (:meth:`AdaptiveLevelFilter.reseated`) on the first frame of another
        model set than the last filtered one: a fallback taken on a fault, or the full model
        again on re-admission, is published at its own level at once (the rate limit still
        bounds the change), not after the filter confirmed the models' difference as a step -
        which kept the fallback's level published with Health OK for ~0.3 s after a mode hop's
        re-admission (tests/test_runtime_modehop.py). ``follow`` (n, 3): the frames a model
        publishes as they are (:meth:`AdaptiveLevelFilter.process`)."""
        if not self.config.output_filter.enabled:
            return corr
        good = np.isfinite(corr).all(axis=1)
        if not good.any():
            return corr
        if self.output_filter is None:
            assert self._t_first is not None  # a prediction comes after the zero window
            first = int(np.argmax(good))
            # nominal frame interval: the zero window's frames up to the first prediction, the
            # same numbers however the frames were batched
            dt = (float(t[first]) - self._t_first) / max(self._zero_frames, 1)
            self.output_filter = AdaptiveLevelFilter(self.config.output_filter, dt, rms[first])
        out = corr.copy()
        rows = np.flatnonzero(good)
        sets = np.zeros(rows.size, np.int64) if model_set is None else model_set[rows].astype(np.int64)
        prev = self._filter_set if self._filter_set is not None else int(sets[0])
        switch = set(np.flatnonzero(np.concatenate([[prev], sets[:-1]]) != sets).tolist())
        edges = sorted({0, rows.size, *switch})
        for a, b in itertools.pairwise(edges):
            if a in switch:
                self.output_filter = self.output_filter.reseated()
            f = None if follow is None else follow[rows[a:b]]
            out[rows[a:b]] = self.output_filter.process(corr[rows[a:b]], f)
        self._filter_set = int(sets[-1])
        return out

    def _shape(self, t, corr, enabled, flags, dt_cap=np.inf) -> np.ndarray:
        """Smoothing, the output switch, the per-axis maximum and rate limit (flags set)."""
        corr = self._smooth(t, corr)
        if not enabled:
            corr = np.zeros_like(corr)
        if corr.shape[0] == 1:  # one frame: the same test on Python floats
            over_any = any(abs(v) > m for v, m in zip(corr[0].tolist(), self._max_list))
        else:
            over_any = bool((np.abs(corr) > self.max_correction_um).any())
        if over_any:
            over = np.abs(corr) > self.max_correction_um
            corr = np.clip(corr, -self.max_correction_um, self.max_correction_um)
            flags[over] |= H.FLAG_MAX_LIMITED
        limited = self._slew_limit(t, corr, dt_cap)
        if limited is not corr:
            flags[np.abs(limited - corr) > 1e-9] |= H.FLAG_RATE_LIMITED
        return limited

    def no_data(self, t_s: float, enabled: bool = True) -> BatchResult:
        """No frame arrives (link lost): hold the last correction and ramp it to zero (alarm),
        shaped like any other output (smoothing, slew limit)."""
        t = np.array([t_s], dtype=np.float64)
        S, P = len(self.sensor_names), len(self.probe_names)
        nan3 = np.full((1, 3), np.nan)
        health = np.array([HEALTH_ALARM], np.uint8)
        corr = self._hold_and_ramp(t, nan3, health)
        flags = np.zeros((1, 3), np.uint8)
        corr = self._shape(t, corr, enabled, flags)
        return BatchResult(
            t,
            nan3,
            nan3,
            corr,
            nan3,
            health,
            np.full((1, S), H.MISSING, np.uint8),
            np.array([-1], np.int16),
            np.full((1, P), np.nan),
            flags,
        )

    def _hold_and_ramp(self, t: np.ndarray, corr: np.ndarray, health: np.ndarray) -> np.ndarray:
        """Rows without a model hold the last good correction, ramped to zero over ramp_s."""
        n = t.size
        good = np.isfinite(corr).all(axis=1)
        zeroing = health == HEALTH_ZEROING
        out = np.where(zeroing[:, None], 0.0, corr)
        hold = ~good & ~zeroing
        if hold.any():
            idx = np.arange(n)
            last_good = np.maximum.accumulate(np.where(good, idx, -1))
            from_batch = last_good >= 0
            held_value = np.where(from_batch[:, None], corr[np.maximum(last_good, 0)], self._last_correction)
            # a hold starts at the first frame after the last good one
            first_hold_t = np.where(
                from_batch,
                t[np.minimum(last_good + 1, n - 1)],
                self._hold_start_s if self._hold_start_s is not None else t[np.argmax(hold)],
            )
            ramp = self.config.ramp_s
            frac = np.clip(1.0 - (t - first_hold_t) / ramp, 0.0, 1.0) if ramp > 0 else np.zeros(n)
            # a hold carried over from earlier calls never ramps back up: a no-data tick is
            # timed by the wall clock (less the last offset seen), and the frames that arrive
            # after a stall carry older instrument times than it; without this they published
            # a larger correction than the tick before them
            carried = self._hold_frac if self._hold_start_s is not None else 1.0
            frac = np.where(from_batch, frac, np.minimum(frac, carried))
            out = np.where(hold[:, None], held_value * frac[:, None], out)
            if hold[-1]:
                self._hold_start_s = float(first_hold_t[-1])
                self._last_correction = held_value[-1]
                self._hold_frac = float(frac[-1])
        if good.any():
            last = np.flatnonzero(good)[-1]
            if last == n - 1:
                self._hold_start_s = None
            self._last_correction = corr[last].copy()
        return out

    def _smooth(self, t: np.ndarray, corr: np.ndarray) -> np.ndarray:
        tau = self.config.smoothing_tau_s
        if tau <= 0 or t.size == 0:
            return corr
        prev_t = self._last_t if self._last_t is not None else t[0]
        dt = np.diff(np.concatenate([[prev_t], t]))
        dt_typ = float(np.median(dt)) if dt.size else 0.0
        a = float(np.exp(-max(dt_typ, 1e-9) / tau))
        y0 = self._smoothed if self._smoothed is not None else corr[0]
        # the recursion scipy.signal.lfilter ran here, whose import (seconds, with scipy.stats)
        # came on the first batch served with smoothing on; the models are loaded by now, and
        # the OPC UA server process and the log readers, which load this module, need none
        from fbgcomp.models.filters import decay_scan  # noqa: PLC0415 - keep this module light

        y = decay_scan(a, (1.0 - a) * corr, y0)
        self._smoothed = y[-1].copy()
        self._last_t = float(t[-1])
        return y

    def _slew_limit(self, t: np.ndarray, corr: np.ndarray, dt_cap: float = np.inf) -> np.ndarray:
        """Limit |d correction / dt| to ``max_slew_um_per_s`` (per axis).

        Where the correction already respects the limit (nearly always) it passes unchanged,
        checked for the whole batch at once; only while the limiter is engaged - a transient
        of a few hundred samples at most - is it followed sample by sample, since each limited
        sample depends on the previous output. Each frame is credited at most ``dt_cap`` s
        (frames: twice the nominal interval; the no-data ticks of a lost link: their own).
        """
        rate = self.max_slew_um_per_s
        n = t.size
        if self._slew_off or n == 0:
            return corr
        prev = self._slew_y if self._slew_y is not None else corr[0]
        t_prev = self._slew_t if self._slew_t is not None else float(t[0])
        if n == 1:  # one frame (the usual batch at a high rate): the same test on scalars
            dt1 = min(max(float(t[0]) - t_prev, 0.0), dt_cap)
            c, p = corr[0].tolist(), prev.tolist()
            if not any(ax and abs(a - b) > r * dt1 + 1e-12 for a, b, r, ax in zip(c, p, *self._slew_lists)):
                self._slew_y = corr[0].copy()
                self._slew_t = float(t[0])
                return corr
        dt = np.clip(np.diff(np.concatenate([[t_prev], t])), 0.0, dt_cap)[:, None]
        step = (
            np.where(np.isinf(rate)[None, :], np.inf, np.where(np.isinf(rate), 0.0, rate)[None, :] * dt)
            + 1e-12
        )
        out = corr.copy()
        i = 0
        while i < n:
            jump = np.abs(np.diff(np.vstack([prev[None, :], corr[i:]]), axis=0)) > step[i:]
            rows = np.flatnonzero(jump.any(axis=1))
            if rows.size == 0:
                break
            k = i + int(rows[0])
            if k > i:
                prev = corr[k - 1]
            j = k
            while j < n:  # engaged: follow the target at the limited rate
                prev = prev + np.clip(corr[j] - prev, -step[j], step[j])
                out[j] = prev
                j += 1
                if np.array_equal(prev, corr[j - 1]):
                    break  # caught up: back to the batch-wide check
            i = j
        self._slew_y = out[-1].copy()
        self._slew_t = float(t[-1])
        return out
