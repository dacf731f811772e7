"""Adaptive output filter: the published correction holds still at rest and follows real steps.

A model's prediction carries the noise of its inputs and of its own policy: served live on the
twin, the physical model as it was before 02c50bc popped on dy by 10-100 µm for 0.3-2.3 s some 16
times a minute (its load part crossing the firm-shrinkage threshold) while nothing moved; on ram2
the 0.1 °C steps of the probes moved its thermal part by ~1 µm for tens of seconds, and its load
refusals dropped the correction by ~370 µm for a few frames. A CNC must not be moved by that, yet
a load step must reach it within a second. No linear filter does both, so this one decides, per
axis, on robust statistics of the raw correction:

* frames are reduced to the median of **blocks** of ``block_s`` (the decision rate, 20 Hz by
  default): a model output that flickers for a frame or two moves no block;
* **rest**: the level is a straight line fitted, with exponential weights of time constant
  ``rest_tau_s``, to the *median* of the block medians over the last ``rest_median_s`` (at most
  since the last restart) and read at the newest block. The median drops pops shorter than half
  its window, the long fit averages what is left, and the line follows a steady thermal drift
  without staircase. The fit lags a drift whose rate changes (a housing cooling after the
  spindle stops) by a part of its time constant, so that is short; on an axis whose robust noise
  SD exceeds ``rest_noise_um`` it grows as the SD squared (the level's jitter goes as SD /
  sqrt(tau)), up to ``rest_tau_max_s``. Its slope counts only as far as the data show it: it is shrunk by
  t² / (t² + ``trend_t2``), t its ratio to its standard error (one independent point per median
  window), and is zero with fewer than three windows since the last restart;
* **step**: the *short* median ``m`` (block medians over ``short_s``) is compared with the level.
  A change is real when ``m`` stays on one side beyond a large threshold for ``fast_confirm_s``,
  or when the median over the last ``slow_confirm_s`` is beyond a small one. Each threshold is
  the larger of ``threshold_sd`` robust noise SDs (median absolute deviation of ``m`` from the
  level, per ``noise_block_s``, blended over ``noise_tau_s``), ``margin`` times the largest
  excursion the noise itself produced that way at rest (an envelope that decays over
  ``envelope_tau_s``) and ``min_threshold_um``. The level then follows the short median of the
  blocks since the change began for ``hold_s`` and the rest fit restarts from the newest blocks;
  a ramp re-triggers as often as it needs;
* **spikes**: at the end of ``hold_s`` (counted from the last restart), if ``m`` is back within
  the slow threshold of the level before the episode, or was for a quarter of it, the episode
  was noise: the rest state from before it is restored and its excursions are learnt into the
  envelopes, so pops of that size are not followed again. Excursions seen at rest are learnt
  ``hold_s`` late, and only if no step followed, so a real step being confirmed never raises its
  own threshold. The price: a real step smaller than the largest pop the model has produced
  waits for the slow path (~``slow_confirm_s`` / 2); a change below ``min_threshold_um`` waits
  for the rest fit, and a fast drift is followed in stairs of that size until its trend shows.

Everything depends on the frame count only (blocks of ``block_n`` frames of the nominal frame
interval, fixed at the zero state): the output is the same, to the bit, whether frames come one
by one or in batches. A frame's output is the level after the last completed block, so the
decision delay is at most one block. Work per frame is a vectorised block median; Python runs once
per block (≤ 20 times a second at the defaults) and axis.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TypedDict

import numpy as np

SD_FLOOR_UM = 1e-3  # the robust noise SD never drops below this (a noise-free replay)


def _block_medians(blocks, axis=1) -> np.ndarray:
    """Medians of ``blocks`` along ``axis`` ((nb, n, 3) blocks over their frames: (nb, 3)), the
    same values as ``np.median`` (NaN-free input) without its generic-reduction overhead (about
    20 µs a call, nine calls a block: a third of the runtime core's time at batches of 100)."""
    a = np.sort(blocks, axis=axis)
    n = a.shape[axis]
    mid = a.take(n // 2, axis=axis)
    return mid if n % 2 else 0.5 * (a.take(n // 2 - 1, axis=axis) + mid)


def _median(v) -> float:
    """Median of a short window (a list of floats, or 1-D), the same value as ``np.median``
    (NaN-free input), on Python floats: the filter's per-block windows hold a few values."""
    s = sorted(v)
    n = len(s)
    mid = s[n // 2]
    return float(mid if n % 2 else 0.5 * (s[n // 2 - 1] + mid))


def _pair_max(a, b) -> list[float]:
    """Element-wise maximum of two (fast, slow) pairs."""
    return [max(a[0], b[0]), max(a[1], b[1])]


@dataclass
class OutputFilterConfig:
    """Settings of the adaptive output filter (``[pipeline.output_filter]``, docs/runtime.md)."""

    enabled: bool = True
    block_s: float = 0.05  # frames averaged per decision block
    short_s: float = 0.6  # fast robust statistic: median of the block medians over this
    rest_median_s: float = 8.0  # slow robust statistic feeding the rest fit
    rest_tau_s: float = 30.0  # rest fit: exponential weights of this time constant ...
    # ... while the robust noise SD is at most this; beyond, ∝ SD² (30 s at 2.24 µm is the jitter
    # of 150 s at 5 µm, the fit until 2026-12-06: noisy axes keep it, quiet ones follow faster) ...
    rest_noise_um: float = 2.24
    rest_tau_max_s: float = 600.0  # ... up to this
    trend_t2: float = 25.0  # a trend of t = 5 standard errors counts half
    fast_confirm_s: float = 0.15  # beyond the large threshold this long: a step
    slow_confirm_s: float = 1.6  # the median over this long beyond the small threshold: a step
    threshold_sd: float = 6.0  # thresholds: at least this many robust noise SDs ...
    margin: float = 1.5  # ... and this times the noise's own excursion envelope ...
    min_threshold_um: float = 1.0  # ... and at least this: smaller changes wait for the rest fit
    envelope_tau_s: float = 1800.0  # memory of the excursion envelopes
    noise_block_s: float = 10.0  # robust noise SD measured per block this long ...
    noise_tau_s: float = 60.0  # ... and blended with this time constant
    hold_s: float = 2.5  # after a restart: back to the old level within this = noise


class _Episode(TypedDict):
    """The rest state kept while an axis follows a change, restored if it was noise."""

    level: float  # the rest level when the change was seen
    fit: list[float]  # the rest fit's weighted sums then
    origin: float  # ... and the block index they count from
    since: int  # blocks the rest median could use then
    start: int  # block index of the trigger
    first: int  # block index the change began at
    thr: float  # the slow threshold then: back within it = noise
    within: int  # blocks of the episode back within it


class AdaptiveLevelFilter:
    """Per-axis rest / step filter of the correction (3 axes), state carried between batches.

    The per-block state is kept in Python lists and floats, one list per axis: a block's
    decisions read windows of a few to a few hundred values, where numpy's per-call overhead
    was the cost: 212 µs a block in numpy, 88 % of the runtime core's time serving ram2's
    thermal_b at 1 frame/s (a block a frame); 43 µs on Python floats
    (benchmarks/bench_output_filter.py). The arithmetic is the same, operation for operation,
    so the output is too, to the bit."""

    def __init__(self, config: OutputFilterConfig, frame_interval_s: float, noise_um):
        cfg = self.config = config
        dt = float(min(max(frame_interval_s, 1e-5), 10.0))
        self.frame_interval_s = dt
        self.block_n = max(1, round(cfg.block_s / dt))
        blk = self.block_n * dt  # block duration, s
        self.block_duration_s = blk
        self.short_n = max(1, round(cfg.short_s / blk))
        self.rest_n = max(self.short_n, round(cfg.rest_median_s / blk))
        self.fast_n = max(2, math.ceil(cfg.fast_confirm_s / blk - 1e-9))
        self.slow_n = max(self.fast_n + 1, math.ceil(cfg.slow_confirm_s / blk - 1e-9))
        self.hold_n = max(1, math.ceil(cfg.hold_s / blk - 1e-9))
        self._blk = blk
        self.env_decay = math.exp(-blk / cfg.envelope_tau_s) if cfg.envelope_tau_s > 0 else 0.0
        self.noise_n = max(1, round(cfg.noise_block_s / blk))
        self.noise_gain = min(1.0, cfg.noise_block_s / cfg.noise_tau_s) if cfg.noise_tau_s > 0 else 1.0
        noise = np.nan_to_num(np.asarray(noise_um, float) * np.ones(3), nan=1.0)
        self.sd: list[float] = np.maximum(np.abs(noise), SD_FLOOR_UM).tolist()
        self.noise_blocks = [0, 0, 0]
        self._decay = [self._fit_decay(j) for j in range(3)]  # the rest fit's, per block
        self.ring_n = max(self.rest_n, self.slow_n, self.short_n) + 1
        r = self.ring_n
        self.b = [[0.0] * r for _ in range(3)]  # block medians (a ring per axis)
        self.e = [[0.0] * r for _ in range(3)]  # m - level (ring)
        self.eb = [[0.0] * r for _ in range(3)]  # m - level before the episode (ring)
        self.k = 0  # completed blocks
        self._part = np.empty((self.block_n, 3))  # frames of the block not yet complete ...
        self._pf = np.zeros((self.block_n, 3), bool)  # ... their follow flags (process)
        self._part_follow_any = False
        self._held = 0  # ... this many of them
        self.level: list[float] | None = None  # per axis, after the first block
        self.since = [0, 0, 0]  # blocks the rest median may use
        self.fresh = [0, 0, 0]  # blocks compared with the level since a restart
        self.fit = [[0.0] * 6 for _ in range(3)]  # weighted sums: w, w u, w u², w y, w u y, w y²
        self.fit_origin = [0.0, 0.0, 0.0]  # block index u is counted from
        self.env = [[0.0, 0.0] for _ in range(3)]  # excursion envelopes (fast, slow), µm
        self.pending = [[(0.0, 0.0)] * self.hold_n for _ in range(3)]  # excursions to be learnt
        self.abs_dev: list[list[float]] = [[], [], []]
        self.episode_end = [-1, -1, -1]  # block index; -1: not in an episode
        self.saved: list[_Episode | None] = [None, None, None]
        self.ep_max = [[0.0, 0.0] for _ in range(3)]
        self.restarts = np.zeros(3, np.int64)
        self.undone = np.zeros(3, np.int64)

    def reseated(self) -> AdaptiveLevelFilter:
        """A filter that starts afresh from the next frame (its level the running mean of
        the new frames until its first block closes), keeping what this one learnt of the
        noise: its robust SD and excursion envelopes. For a switch of model (a fallback taken
        or left): the two models' corrections differ by their own fits, not by any motion of
        the machine, so the new model's level is not a step to confirm - confirming it would
        keep the old model's level published for up to ``slow_confirm_s``, and the episode
        would then be learnt as a pop, raising the thresholds for ``envelope_tau_s``."""
        new = AdaptiveLevelFilter(self.config, self.frame_interval_s, self.sd)
        new.noise_blocks = list(self.noise_blocks)
        new.env = [list(e) for e in self.env]
        return new

    @property
    def partial(self) -> np.ndarray:
        """The frames (k, 3) of the block not yet complete (k < ``block_n``)."""
        return self._part[: self._held]

    @property
    def noise_sd_um(self) -> np.ndarray:
        """The per-axis noise standard deviation the thresholds are built on, µm (a copy)."""
        return np.array(self.sd)

    def thresholds(self) -> np.ndarray:
        """(3, 2): the fast (large) and slow (small) step thresholds per axis, µm."""
        return np.array(self._thresholds())

    def _thresholds(self) -> list[list[float]]:
        cfg = self.config
        out = []
        for sd, env in zip(self.sd, self.env):
            base = max(cfg.threshold_sd * sd, cfg.min_threshold_um)
            out.append([max(cfg.margin * env[0], base), max(cfg.margin * env[1], base)])
        return out

    # -- per frame -----------------------------------------------------------------------
    def process(self, x: np.ndarray, follow: np.ndarray | None = None) -> np.ndarray:
        """Filtered correction (m, 3) for raw corrections ``x`` (m, 3), all finite.

        ``follow`` (m, 3) bool, optional: frames and axes on which the model itself follows a
        motion it has confirmed (a load transition its step test took). They are published as
        they are, and the rest fit restarts from the block that holds the last of them: a
        second confirmation here lagged a 200 N/s ramp by the short median's half-width (at
        10 Hz, ram2's static_x dx 8.4 -> 19.2 µm) and, at 1 frame/s, by two frames (thermal_c
        dx 10.5 -> 17.6 µm at the force's release)."""
        m = x.shape[0]
        out = np.empty_like(x)
        if m == 0:
            return out
        held = self._held
        any_follow = follow is not None and bool(follow.any())
        if self.level is not None and held + m < self.block_n:
            # no block closes (the usual small batch): every frame sees the current level
            out[:] = self.level
            self._part[held : held + m] = x
            if any_follow or self._part_follow_any:
                f = np.zeros((m, 3), bool) if follow is None else follow
                if not self._part_follow_any:
                    self._pf[:held] = False  # (not kept while no frame of the block followed)
                self._pf[held : held + m] = f
                self._part_follow_any = True
                out = np.where(f, x, out)
            self._held = held + m
            return out
        allx = np.vstack([self.partial, x]) if held else x
        if any_follow or self._part_follow_any:
            f = np.zeros((m, 3), bool) if follow is None else follow
            pf = self._pf[:held] if self._part_follow_any else np.zeros((held, 3), bool)
            allf = np.vstack([pf, f]) if held else f
        else:
            allf = None
        nb = allx.shape[0] // self.block_n
        # block medians, not means: a model that flickers for a few frames (ram2's load
        # refusals: 4-12 frames, 370 µm each) moves no block
        med = (
            _block_medians(allx[: nb * self.block_n].reshape(nb, self.block_n, 3)) if nb else np.empty((0, 3))
        )
        med_rows = med.tolist()
        for q in range(nb + 1):
            lo, hi = q * self.block_n - held, min((q + 1) * self.block_n - held, m)
            lo = max(lo, 0)
            if hi <= lo:
                continue
            if self.level is None:
                # before the first block closes: the running mean of the frames so far
                start = q * self.block_n
                cs = np.cumsum(allx[start : hi + held], axis=0)[lo + held - start :]
                out[lo:hi] = cs / (np.arange(lo + held - start, hi + held - start) + 1)[:, None]
            else:
                out[lo:hi] = self.level
            if q < nb:
                fb = (
                    None
                    if allf is None
                    else np.asarray(allf[q * self.block_n : (q + 1) * self.block_n].any(axis=0))
                )
                self._block(med_rows[q], fb)
                out[hi - 1] = self.level  # the frame that closes a block sees it
        rest = allx[nb * self.block_n :]
        self._part[: rest.shape[0]] = rest
        self._held = rest.shape[0]
        if allf is not None:
            left = allf[nb * self.block_n :]
            self._pf[: left.shape[0]] = left
            self._part_follow_any = bool(left.any())
            if any_follow:
                out = np.where(allf[held:], x, out)
        else:
            self._part_follow_any = False
        return out

    # -- per block -----------------------------------------------------------------------
    def _newest(self, ring: list[float], n: int) -> list[float]:
        """The newest ``n`` values of one axis's ring (in ring order: the windows are read by
        medians, minima and maxima only)."""
        hi = self.k % self.ring_n + 1  # the current block's slot, inclusive
        if n <= hi:
            return ring[hi - n : hi]
        if n <= self.ring_n:
            return ring[:hi] + ring[self.ring_n - (n - hi) :]
        return [ring[(self.k - i) % self.ring_n] for i in range(n)]  # a window longer than the ring

    def rest_tau(self, j: int) -> float:
        """The rest fit's time constant on axis ``j``, s: ``rest_tau_s`` while the axis's robust
        noise SD is at most ``rest_noise_um``, longer as the SD squared beyond it (the level's
        jitter goes as SD / sqrt(tau)), at most ``rest_tau_max_s``."""
        cfg = self.config
        grow = (self.sd[j] / cfg.rest_noise_um) ** 2 if cfg.rest_noise_um > 0 else 1.0
        return min(cfg.rest_tau_s * max(grow, 1.0), max(cfg.rest_tau_max_s, cfg.rest_tau_s))

    def _fit_decay(self, j: int) -> float:
        """The rest fit's weight decay per block on axis ``j`` (it changes with the noise SD)."""
        tau = self.rest_tau(j)
        return math.exp(-self._blk / tau) if tau > 0 else 0.0

    def _fit_point(self, j: int, y: float, u: float) -> None:
        d = self._decay[j]
        w, su, suu, sy, suy, syy = self.fit[j]
        self.fit[j] = [w * d + 1.0, su * d + u, suu * d + u * u, sy * d + y, suy * d + u * y, syy * d + y * y]

    def _fit_level(self, j: int) -> float:
        """The rest fit read at the newest block: weighted mean plus the fitted trend, the
        trend shrunk by its significance (t² / (t² + trend_t2)) so noise does not tilt it."""
        w, su, suu, sy, suy, syy = self.fit[j]
        ubar, ybar = su / w, sy / w
        var_u = suu / w - ubar * ubar
        if var_u <= 1e-9:
            return ybar
        cov = suy / w - ubar * ybar
        slope = cov / var_u
        resid = max(syy / w - ybar * ybar - slope * cov, 0.0)
        # the fitted points are medians over rest_n blocks: about one independent per window
        n_eff = w / self.rest_n
        if n_eff < 3.0:  # too few independent points to tell a trend
            return ybar
        var_slope = resid / ((n_eff - 2.0) * var_u)
        t2 = slope * slope / var_slope if var_slope > 0 else math.inf
        if math.isfinite(t2) and t2 + self.config.trend_t2 > 0:
            slope *= t2 / (t2 + self.config.trend_t2)
        return ybar + slope * ((self.k - self.fit_origin[j]) - ubar)

    def _restart(self, j: int, n: int) -> None:
        """The rest fit starts again from the median of the newest ``n`` blocks only."""
        self.since[j] = n
        self.fresh[j] = 0
        self.fit[j] = [0.0] * 6
        self.fit_origin[j] = float(self.k)
        self._fit_point(j, _median(self._newest(self.b[j], n)), -(n - 1) / 2.0)

    def _excursion(self, j: int, e_ring: list[float], ref: float, n_avail: int) -> tuple[float, float]:
        """(fast, slow) on axis ``j``: how far ``m`` stayed on one side of the level through the
        last ``fast_n`` blocks (``e_ring``: m minus the level), and how far the median of the
        block medians over the last ``slow_n`` blocks is from ``ref``; 0 where fewer blocks than
        that are available (``n_avail``)."""
        fast = slow = 0.0
        if n_avail >= self.fast_n:
            w = self._newest(e_ring, self.fast_n)
            fast = max(max(min(w), -max(w)), 0.0)
        if n_avail >= self.slow_n:
            slow = abs(_median(self._newest(self.b[j], self.slow_n)) - ref)
        return fast, slow

    def _block(self, bm: list[float], followed=None) -> None:
        slot = self.k % self.ring_n
        for j in range(3):
            self.b[j][slot] = bm[j]
        first = self.level is None
        if self.level is None:
            self.level = list(bm)
        level = self.level
        thr = self._thresholds()
        n_short = min(self.short_n, self.k + 1)
        resting = []  # axes at rest, with their short medians
        for j in range(3):
            self.since[j] += 1
            self.fresh[j] += 1
            mj = _median(self._newest(self.b[j], n_short))
            if followed is not None and followed[j]:
                # the model follows a motion it confirmed: its value is the level, and the
                # rest fit starts from this block (nothing of it is noise to learn)
                self.episode_end[j] = -1
                self.saved[j] = None
                self.pending[j] = [(0.0, 0.0)] * self.hold_n
                self._restart(j, 1)
                level[j] = bm[j]
                self.e[j][slot] = 0.0
                continue
            if self.episode_end[j] >= 0:
                level[j] = self._track(j, mj)
                continue
            n_rest = min(self.rest_n, self.since[j])
            rest = _median(self._newest(self.b[j], n_rest))
            self._fit_point(j, rest, (self.k - self.fit_origin[j]) - (n_rest - 1) / 2.0)
            level[j] = self._fit_level(j)
            self.e[j][slot] = mj - level[j]
            resting.append((j, mj))
        for j, mj in resting:
            lv = level[j]
            p = self._excursion(j, self.e[j], lv, self.fresh[j])
            trigger = (
                0 if first else (self.fast_n if p[0] > thr[j][0] else self.slow_n if p[1] > thr[j][1] else 0)
            )
            if trigger:
                # a change the noise does not explain: follow it (track) for hold_s, keeping
                # the rest state in case it was noise after all
                self.saved[j] = {
                    "level": lv,
                    "fit": list(self.fit[j]),
                    "origin": self.fit_origin[j],
                    "since": self.since[j],
                    "start": self.k,
                    "first": self.k - trigger + 1,
                    "thr": thr[j][1],
                    "within": 0,
                }
                self.ep_max[j] = list(p)
                self.eb[j] = list(self.e[j])
                self.pending[j] = [(0.0, 0.0)] * self.hold_n  # a step follows: nothing recent was noise
                self.episode_end[j] = self.k + self.hold_n
                self.restarts[j] += 1
                level[j] = _median(self._newest(self.b[j], trigger))
            elif not first:
                # learn from rest: the excursion of hold_n blocks ago (no step since), and the
                # robust spread of m about the level
                ps = self.k % self.hold_n
                env = self.env[j]
                self.env[j] = _pair_max(
                    (env[0] * self.env_decay, env[1] * self.env_decay), self.pending[j][ps]
                )
                self.pending[j][ps] = p
                dev = self.abs_dev[j]
                dev.append(abs(mj - lv))
                if len(dev) >= self.noise_n:
                    sd = 1.4826 * _median(dev)
                    self.noise_blocks[j] += 1
                    g = max(self.noise_gain, 1.0 / self.noise_blocks[j])
                    self.sd[j] = max(self.sd[j] + g * (sd - self.sd[j]), SD_FLOOR_UM)
                    self._decay[j] = self._fit_decay(j)
                    dev.clear()
        self.k += 1

    def _track(self, j: int, mj: float) -> float:
        """One block of an episode: the level follows the short median of the blocks since the
        change began; at its end either the old rest state returns (noise) or the rest fit
        restarts from the newest blocks."""
        s = self.saved[j]
        assert s is not None  # an axis in an episode has its rest state saved
        n = min(self.short_n, self.k - s["first"] + 1)
        level = _median(self._newest(self.b[j], n))
        self.eb[j][self.k % self.ring_n] = mj - s["level"]
        p = self._excursion(j, self.eb[j], s["level"], self.k - s["start"] + s["since"])
        self.ep_max[j] = _pair_max(self.ep_max[j], p)
        if abs(mj - s["level"]) <= s["thr"]:
            s["within"] += 1
        if self.k < self.episode_end[j]:
            return level
        self.episode_end[j] = -1
        self.saved[j] = None
        if abs(mj - s["level"]) <= s["thr"] or s["within"] >= 0.25 * (self.k - s["start"]):
            # back where it was (or kept coming back): noise. Restore the rest state, learn it
            self.fit[j], self.fit_origin[j] = s["fit"], s["origin"]
            self.since[j] = s["since"] + (self.k - s["start"])
            self.fresh[j] = 0  # the episode's comparisons were with other levels
            self.env[j] = _pair_max(self.env[j], self.ep_max[j])
            self.undone[j] += 1
            return self._fit_level(j)
        self._restart(j, min(2 * self.short_n, self.k - s["first"] + 1))
        return self._fit_level(j)
