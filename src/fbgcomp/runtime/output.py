"""Adaptive output filter: the published correction holds still at rest and follows real steps.

A model's prediction carries the noise of its inputs (on the twin served live, ±60 µm second to
second on dy for a true drift below 1 µm); a CNC must not be moved by it. A linear low-pass
filter cannot do both jobs - hours of averaging at rest, a load step followed within a second -
so this filter switches, per axis, between two regimes:

* **rest**: the level is the running mean of the raw correction since the last restart
  (expanding window), which becomes an exponential mean of time constant ``rest_tau_s`` once
  that many seconds have been averaged. Its wander is the input noise / sqrt(samples averaged);
* **snap**: a *fast* copy of the input (exponential mean, ``fast_tau_s``) is compared with the
  level. When it stays more than ``threshold_sd`` noise SDs away for ``confirm_s`` (a change the
  noise cannot explain), the level jumps to the fast value and the averaging restarts from
  there. A ramp re-triggers it as often as needed, so the level follows within
  ~``confirm_s`` + threshold / ramp rate.

The noise SD is that of the fast value within blocks of ``block_s`` (its variance about the
block's own mean: a slow thermal drift does not count as noise, so a drift the level lags behind
by more than the threshold restarts it, and the lag stays below ~threshold), winsorised (a step
cannot blow the estimate up) and blended with time constant ``noise_tau_s``, starting from the
predictor's ``expected_rms_error_um``. Because it is the spread actually seen over seconds, it
holds for correlated noise too (probe temperatures held for seconds, an interrogator stream
interpolated from slower samples).

Per-sample gains come from the nominal frame interval (fixed once, at the zero state), so every
stage is either a cumulative sum or a constant-coefficient ``lfilter`` with its state carried:
the output is the same, to the bit, whether frames come one by one or in batches. Work is
vectorised over a batch; Python only loops over restarts and noise blocks (≥ 1 s of data each).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass
class OutputFilterConfig:
    enabled: bool = True
    rest_tau_s: float = 600.0    # averaging time at rest: ±18 µm of 1 Hz noise -> < 0.1 µm wander
    fast_tau_s: float = 0.05     # fast copy used to detect and follow a change
    threshold_sd: float = 6.0    # a change beyond this many noise SDs of the fast copy ...
    confirm_s: float = 0.1       # ... held this long (at least 2 samples) is real
    noise_tau_s: float = 60.0    # memory of the online noise estimate
    block_s: float = 10.0        # noise = spread of the fast copy within blocks this long
    min_noise_um: float = 0.001  # floor of the noise SD (a noise-free replay)


class AdaptiveLevelFilter:
    """Per-axis rest / snap filter of the correction (3 axes), state carried between batches."""

    def __init__(self, config: OutputFilterConfig, frame_interval_s: float, noise_um):
        cfg = self.config = config
        dt = float(min(max(frame_interval_s, 1e-5), 10.0))
        self.frame_interval_s = dt
        self.fast_gain = 1.0 - math.exp(-dt / cfg.fast_tau_s) if cfg.fast_tau_s > 0 else 1.0
        self.rest_n = max(1.0, cfg.rest_tau_s / dt)          # samples averaged at most
        self.snap_weight = max(1.0, cfg.fast_tau_s / dt)    # samples the fast copy stands for
        self.confirm_n = max(2, math.ceil(cfg.confirm_s / dt - 1e-9))
        self.block_n = max(10, int(round(cfg.block_s / dt)))
        self.noise_gain = min(1.0, cfg.block_s / cfg.noise_tau_s) if cfg.noise_tau_s > 0 else 1.0
        noise = np.nan_to_num(np.asarray(noise_um, float) * np.ones(3), nan=1.0)
        self.var = np.maximum(noise, cfg.min_noise_um) ** 2
        self.fast: np.ndarray | None = None
        self.sum = np.zeros(3)       # expanding regime: sum of the inputs averaged (incl. snap)
        self.count = np.zeros(3)     # samples averaged since the last restart (capped: rest_n)
        self.level = np.zeros(3)
        self.run = np.zeros(3, np.int64)     # consecutive significant samples so far
        self.block_sum = np.zeros(3)      # of (fast - block_ref) and its square
        self.block_sum2 = np.zeros(3)
        self.block_ref: np.ndarray | None = None
        self.block_count = 0
        self.restarts = np.zeros(3, np.int64)

    @property
    def noise_sd_um(self) -> np.ndarray:
        return np.sqrt(self.var)

    def process(self, x: np.ndarray) -> np.ndarray:
        """Filtered correction (m, 3) for raw corrections ``x`` (m, 3), all finite."""
        from scipy.signal import lfilter
        m = x.shape[0]
        if m == 0:
            return x.copy()
        g = self.fast_gain
        if self.fast is None:
            self.fast = x[0].copy()
        fast, zf = lfilter([g], [1.0, -(1.0 - g)], x, axis=0,
                           zi=((1.0 - g) * self.fast)[None, :])
        self.fast = fast[-1].copy()
        out = np.empty_like(x)
        i = 0
        while i < m:
            end = min(m, i + self.block_n - self.block_count)
            # the expanding mean turns into the exponential one: a segment boundary
            crossing = self.rest_n - self.count
            expanding = crossing > 0
            if expanding.any():
                end = min(end, i + max(1, int(math.ceil(crossing[expanding].min()))))
            level, cs = self._levels(x[i:end], expanding)
            thr = self.config.threshold_sd * np.sqrt(self.var)
            if self.block_ref is None:
                self.block_ref = fast[i].copy()
            e = fast[i:end] - level
            exceed = np.abs(e) > thr
            idx = np.arange(end - i)[:, None]
            last_quiet = np.maximum.accumulate(np.where(exceed, -1, idx), axis=0)
            run = np.where(exceed, np.where(last_quiet < 0, idx + 1 + self.run, idx - last_quiet),
                           0)
            hit = run >= self.confirm_n
            if hit.any():
                k = int(np.flatnonzero(hit.any(axis=1))[0])     # first restart of any axis
                snap = hit[k]
                self._commit(level, cs, fast[i:i + k + 1], run, k + 1, expanding)
                out[i:i + k + 1] = level[:k + 1]
                f = fast[i + k]
                out[i + k, snap] = f[snap]
                self.level[snap] = f[snap]
                self.sum[snap] = self.snap_weight * f[snap]
                self.count[snap] = self.snap_weight
                self.run[snap] = 0
                self.restarts[snap] += 1
                i += k + 1
            else:
                self._commit(level, cs, fast[i:end], run, end - i, expanding)
                out[i:end] = level
                i = end
            if self.block_count >= self.block_n:
                # winsorised: a step adds at most threshold² to one block's variance
                mean = self.block_sum / self.block_count
                ms = np.maximum(self.block_sum2 / self.block_count - mean * mean, 0.0)
                ms = np.minimum(ms, self.config.threshold_sd ** 2 * self.var)
                self.var = np.maximum(self.var + self.noise_gain * (ms - self.var),
                                      self.config.min_noise_um ** 2)
                self.block_sum = np.zeros(3)
                self.block_sum2 = np.zeros(3)
                self.block_ref = None
                self.block_count = 0
        return out

    def _levels(self, x: np.ndarray, expanding: np.ndarray):
        """Level per sample of a segment without restart, and the running sums."""
        from scipy.signal import lfilter
        n = x.shape[0]
        level = np.empty_like(x)
        cs = np.cumsum(np.vstack([self.sum[None, :], x]), axis=0)[1:]
        if expanding.any():
            counts = self.count[None, :] + np.arange(1, n + 1)[:, None]
            level[:, expanding] = (cs / counts)[:, expanding]
        rest = ~expanding
        if rest.any():
            a = 1.0 - 1.0 / self.rest_n
            y, _ = lfilter([1.0 / self.rest_n], [1.0, -a], x[:, rest], axis=0,
                           zi=(a * self.level[rest])[None, :])
            level[:, rest] = y
        return level, cs

    def _commit(self, level, cs, fast, run, k: int, expanding) -> None:
        """Take the state after the first ``k`` samples of the segment."""
        self.level = level[k - 1].copy()
        self.sum = np.where(expanding, cs[k - 1], self.sum)
        self.count = np.where(expanding, np.minimum(self.count + k, self.rest_n), self.count)
        self.run = run[k - 1].astype(np.int64)
        d = fast[:k] - self.block_ref
        self.block_sum = np.cumsum(np.vstack([self.block_sum[None, :], d]), axis=0)[-1]
        self.block_sum2 = np.cumsum(np.vstack([self.block_sum2[None, :], d * d]), axis=0)[-1]
        self.block_count += k
