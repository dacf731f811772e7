"""Peaks to sensors: the wavelength windows of the gratings (:class:`PeakMapper`) and the
batch of mapped frames every wavelength source yields (:class:`SensorBatch`).

Peaks are mapped to sensors by wavelength windows ``lambda0_nm ± window_nm``: exactly one peak
in the window gives the sensor's wavelength; none (grating lost or moved out of its window) or
more than one (doubled peak) gives NaN and a peak count the health checks turn into a fault.

Strain-free reference gratings (``reference_lambda0_nm`` of a sensor) own a window of their own
(``reference_lambda0_nm ± window_nm``) and travel beside the sensors in
``SensorBatch.reference_nm``.

At a high frame rate a batch is one frame, so the mapping's cost is numpy's per-call cost: the
window tables are built once per fibre and layout, and the usual frame (every peak in a window)
takes one search, one comparison and two counts.
"""

from __future__ import annotations

import bisect
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from fbgcomp.runtime import hyperion


@dataclass
class SensorBatch:
    """Frames mapped to sensors.

    time_s : (n,) instrument time stamps, s since the epoch (replay: start + campaign time)
    wavelength_nm : (n, S) the single peak found in each sensor's window, NaN otherwise
    peak_count : (n, S) int8 peaks in the window (0 missing, 1 good, >1 doubled)
    near_count : (n, S) int8 peaks in the guard band just outside the window
    received_s : wall-clock time the batch was received (for latency figures)
    reference_nm : (n, R) the strain-free reference gratings (``PeakMapper.reference_probes``
        order), NaN unless exactly one peak in the window; None when there are none
    """

    time_s: np.ndarray
    wavelength_nm: np.ndarray
    peak_count: np.ndarray
    near_count: np.ndarray
    received_s: float
    reference_nm: np.ndarray | None = None

    def __len__(self) -> int:
        return self.time_s.size

    def take(self, keep: np.ndarray) -> SensorBatch:
        """The frames where ``keep`` (n,) is True."""
        return SensorBatch(
            self.time_s[keep],
            self.wavelength_nm[keep],
            self.peak_count[keep],
            self.near_count[keep],
            self.received_s,
            None if self.reference_nm is None else self.reference_nm[keep],
        )

    @staticmethod
    def concat(batches: list[SensorBatch]) -> SensorBatch:
        """One batch of several, in order."""
        if len(batches) == 1:
            return batches[0]
        return SensorBatch(
            np.concatenate([b.time_s for b in batches]),
            np.concatenate([b.wavelength_nm for b in batches]),
            np.concatenate([b.peak_count for b in batches]),
            np.concatenate([b.near_count for b in batches]),
            max(b.received_s for b in batches),
            None if batches[0].reference_nm is None else np.concatenate([b.reference_nm for b in batches]),
        )


class PeakMapper:
    """Assign peaks to sensors by wavelength windows (vectorised over frames and peaks)."""

    def __init__(
        self,
        lambda0_nm: npt.ArrayLike,
        window_nm: float = 2.5,
        guard_nm: float | None = None,
        channel: npt.ArrayLike | None = None,
        n_sensors: int | None = None,
        reference_probes: list[str] | None = None,
    ):
        self.lambda0_nm = np.asarray(lambda0_nm, dtype=np.float64)
        # windows beyond the first n_sensors are strain-free reference gratings, named by the
        # probe they read (<sensor>_ref); they go to SensorBatch.reference_nm
        self.n_sensors = self.lambda0_nm.size if n_sensors is None else int(n_sensors)
        self.reference_probes = list(reference_probes or [])
        if len(self.reference_probes) != self.lambda0_nm.size - self.n_sensors:
            raise ValueError("one name per reference grating window")
        # instrument channel (1-based, as the Hyperion numbers them) of each sensor, 0 = any:
        # several fibres may carry gratings of the same nominal wavelength
        self.channel = (
            np.zeros(self.lambda0_nm.size, int) if channel is None else np.asarray(channel, dtype=int)
        )
        self.window_nm = float(window_nm)
        self.guard_nm = float(window_nm if guard_nm is None else guard_nm)
        self.lo = self.lambda0_nm - self.window_nm
        self.hi = self.lambda0_nm + self.window_nm
        self._all = np.arange(self.lambda0_nm.size)

    @classmethod
    def for_sensors(cls, sensors, window_nm: float = 2.5) -> PeakMapper:
        """Windows from sensor specs (``lambda0_nm`` and optional extra key ``channel``), then
        one per strain-free reference grating (``reference_lambda0_nm``, the sensor's channel)."""
        channel = [int(getattr(s, "channel", None) or 0) for s in sensors]
        refs = [
            (s, c) for s, c in zip(sensors, channel) if getattr(s, "reference_lambda0_nm", None) is not None
        ]
        return cls(
            [s.lambda0_nm for s in sensors] + [s.reference_lambda0_nm for s, _ in refs],
            window_nm,
            channel=channel + [c for _, c in refs],
            n_sensors=len(sensors),
            reference_probes=[f"{s.name}_ref" for s, _ in refs],
        )

    def map(
        self,
        peaks_nm: np.ndarray,
        received_s: float,
        time_s: np.ndarray,
        peak_channel: np.ndarray | None = None,
    ) -> SensorBatch:
        """Map (n, K) peaks (NaN = no peak) to (n, S) sensor wavelengths.

        ``peak_channel`` (K,) gives the 1-based instrument channel of each peak column; sensors
        with a channel only look at their channel's peaks.
        """
        n, S = peaks_nm.shape[0], self.lambda0_nm.size
        if n == 1 and (one := self._map_one(peaks_nm[0].tolist(), peak_channel)) is not None:
            wl, count, near8 = one
        else:
            wl, count, near8 = self._map_many(peaks_nm, peak_channel)
        k = self.n_sensors
        if k == S:
            return SensorBatch(time_s, wl, count, near8, received_s)
        return SensorBatch(time_s, wl[:, :k], count[:, :k], near8[:, :k], received_s, reference_nm=wl[:, k:])

    def _map_one(self, peaks: list, peak_channel):
        """One frame (the batch of a high frame rate) on Python floats: per peak one bisection
        of the sorted window edges and one comparison, where numpy's per-call cost would be
        most of the time; the same results as :meth:`_map_many` (tested against the exhaustive
        comparison). None when a fibre's windows overlap (the array path handles those)."""
        S = self.lambda0_nm.size
        count = [0] * S
        value = [np.nan] * S
        near = [0] * S
        w, wg = self.window_nm, self.window_nm + self.guard_nm
        for cols, sens in self._groups_of(peak_channel):
            order, lo, hi_ext, order_ext, lam, overlapping = self._tables(sens)[6]
            if overlapping:
                return None
            m = len(order)
            for p in peaks if isinstance(cols, slice) else [peaks[c] for c in cols.tolist()]:
                j = bisect.bisect_right(lo, p)  # 1 + the window starting at or below
                if p <= hi_ext[j]:  # NaN fails, and so does the sentinel's NaN edge
                    k = order_ext[j]
                    count[k] += 1
                    value[k] = p
                elif p == p:  # a finite (or infinite) stray: in a guard band?
                    for cand in (j - 1, j):  # the windows just below and just above
                        if 0 <= cand < m and w < abs(p - lam[cand]) <= wg:
                            near[order[cand]] += 1
        wl = np.array([[v if c == 1 else np.nan for v, c in zip(value, count)]])
        return (
            wl,
            np.array([[min(c, 127) for c in count]], np.int8),
            np.array([[min(c, 127) for c in near]], np.int8),
        )

    def _tables(self, sens) -> tuple:
        """The window tables of a fibre's sensors ``sens``: sorted order, lower edges, upper
        edges behind a NaN sentinel, the order behind a sentinel, centres, overlapping; then
        the same as Python lists (index 6). Built once per fibre."""
        key = sens.tobytes()
        cache = self.__dict__.setdefault("_groups", {})
        tables = cache.get(key)
        if tables is None:
            order = sens[np.argsort(self.lambda0_nm[sens])]
            lo, hi = self.lo[order], self.hi[order]
            arrays = (
                order,
                lo,
                np.concatenate([[np.nan], hi]),
                np.concatenate([order[:1], order]),
                self.lambda0_nm[order],
            )
            overlapping = bool(np.any(lo[1:] < hi[:-1]))
            lists = tuple(a.tolist() for a in arrays)
            tables = cache[key] = (*arrays, overlapping, (*lists, overlapping))
        return tables

    def _map_many(self, peaks_nm, peak_channel):
        n, S = peaks_nm.shape[0], self.lambda0_nm.size
        count = np.zeros(n * S, np.int64)
        value = np.zeros(n * S)
        near: np.ndarray | None = None  # allocated by the first stray peak (rare)
        for cols, sens in self._groups_of(peak_channel):
            near = self._map_group(peaks_nm[:, cols], sens, count, value, near)
        count = count.reshape(n, S)
        wl = np.where(count == 1, value.reshape(n, S), np.nan)
        count = np.minimum(count, 127).astype(np.int8)
        near8 = (
            np.zeros((n, S), np.int8) if near is None else np.minimum(near.reshape(n, S), 127).astype(np.int8)
        )
        return wl, count, near8

    def _groups_of(self, peak_channel) -> list:
        """(peak columns, sensors) per fibre, for a layout's channel of every peak column;
        one group of everything when channels are not used. Cached per layout."""
        if peak_channel is None or not self.channel.all():
            return [(slice(None), self._all)]
        cache = self.__dict__.setdefault("_layouts", {})
        key = np.asarray(peak_channel).tobytes()
        groups = cache.get(key)
        if groups is None:
            groups = [
                (np.flatnonzero(peak_channel == ch), np.flatnonzero(self.channel == ch))
                for ch in np.unique(peak_channel)
            ]
            groups = [(c, s) for c, s in groups if s.size]
            if len(cache) < 64:
                cache[key] = groups
        return groups

    def _map_group(self, peaks, sens, count, value, near):
        """Windows of the sensors ``sens`` (one fibre) against its (n, k) peaks, O(n k log s);
        returns ``near`` (allocated when a peak first falls in a guard band).

        Windows on one fibre do not overlap (checked at first use), so each peak falls in at
        most one window: a binary search over the sorted window edges finds it. The edges'
        tables carry a sentinel in front (window 0 = "below every window", upper edge NaN), so
        a NaN or infinite peak fails the one comparison and needs no test of its own.
        """
        S = self.lambda0_nm.size
        order, lo, hi_ext, order_ext, lam, overlapping, _ = self._tables(sens)
        if overlapping:
            if near is None:
                near = np.zeros(count.size, np.int64)
            self._map_group_overlapping(peaks, sens, count, value, near)
            return near
        n = peaks.shape[0]
        j = np.searchsorted(lo, peaks, side="right")  # 1 + the window starting at or below
        inside = peaks <= hi_ext[j]
        slot = order_ext[j]
        if n > 1:
            slot += np.arange(0, n * S, S)[:, None]
        flat = slot[inside]
        size = count.size
        count += np.bincount(flat, minlength=size)
        value += np.bincount(flat, weights=peaks[inside], minlength=size)
        if flat.size == np.count_nonzero(peaks == peaks):
            return near  # every finite peak in a window: no stray (the usual frame)
        # peaks owned by no window but within the guard band of one: that grating moved
        finite = np.isfinite(peaks)
        stray = finite & ~inside
        if not stray.any():
            return near
        p = np.where(finite, peaks, -np.inf)
        row = np.broadcast_to(np.arange(n)[:, None] * S, peaks.shape)
        for cand in (j - 1, j):  # the windows just below and just above
            valid = (cand >= 0) & (cand < order.size)
            k = np.clip(cand, 0, order.size - 1)
            d = np.abs(p - lam[k])
            hit = stray & valid & (d > self.window_nm) & (d <= self.window_nm + self.guard_nm)
            if hit.any():
                if near is None:
                    near = np.zeros(size, np.int64)
                near += np.bincount(row[hit] + order[k[hit]], minlength=size)
        return near

    def _map_group_overlapping(self, peaks, sens, count, value, near) -> None:
        """Overlapping windows: a peak may count for two sensors (both then see a fault)."""
        S = self.lambda0_nm.size
        n = peaks.shape[0]
        p = peaks[:, :, None]
        inside = (p >= self.lo[sens]) & (p <= self.hi[sens])  # (n, k, s)
        dist = np.abs(p - self.lambda0_nm[sens])
        owned = inside.any(axis=2, keepdims=True)
        stray = (dist > self.window_nm) & (dist <= self.window_nm + self.guard_nm) & ~owned
        idx = (np.arange(n)[:, None] * S + sens[None, :]).ravel()
        count[idx] += inside.sum(axis=1).ravel()
        value[idx] += np.where(inside, p, 0.0).sum(axis=1).ravel()
        near[idx] += stray.sum(axis=1).ravel()

    def map_blocks(self, blocks: list[hyperion.PeakBlock], received_s: float) -> SensorBatch:
        """A batch of the decoded peak blocks of one read (received at ``received_s``)."""
        by_channel = bool(self.channel.all())
        return SensorBatch.concat(
            [
                self.map(
                    b.wavelengths_nm, received_s, b.timestamp_s, b.peak_channel + 1 if by_channel else None
                )
                for b in blocks
            ]
        )
