"""Wavelength and temperature sources behind one interface.

A wavelength source is an async iterator of :class:`SensorBatch` (every frame that has arrived,
already mapped to the model's sensors); sources that lose their link reconnect by themselves
with capped exponential back-off. A temperature source answers the latest value per probe.

Peaks are mapped to sensors by wavelength windows ``lambda0_nm ± window_nm``: exactly one peak
in the window gives the sensor's wavelength; none (grating lost or moved out of its window) or
more than one (doubled peak) gives NaN and a peak count the health checks turn into a fault.

Strain-free reference gratings (``reference_lambda0_nm`` of a sensor) own a window of their own
(``reference_lambda0_nm ± window_nm``) and travel beside the sensors in
``SensorBatch.reference_nm``; :class:`ReferenceThermometers` turns them into the model's
``<sensor>_ref`` temperatures, so the temperature source only answers the real probes.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections.abc import AsyncIterator
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol
from urllib.parse import parse_qs, urlparse

import numpy as np
import numpy.typing as npt
import pandas as pd

from fbgcomp import optics
from fbgcomp.errors import InputError
from fbgcomp.io.campaign import read_campaign
from fbgcomp.runtime import hyperion

log = logging.getLogger("fbgcomp.runtime")


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
        count = np.zeros(n * S, np.int64)
        value = np.zeros(n * S)
        near = np.zeros(n * S, np.int64)
        groups = np.unique(peak_channel) if peak_channel is not None and self.channel.all() else [None]
        for ch in groups:
            cols = np.flatnonzero(peak_channel == ch) if ch is not None else slice(None)
            sens = np.flatnonzero(self.channel == ch) if ch is not None else self._all
            if sens.size:
                self._map_group(peaks_nm[:, cols], sens, count, value, near)
        count = count.reshape(n, S)
        wl = np.where(count == 1, value.reshape(n, S), np.nan)
        count = np.minimum(count, 127).astype(np.int8)
        near = np.minimum(near.reshape(n, S), 127).astype(np.int8)
        k = self.n_sensors
        if k == S:
            return SensorBatch(time_s, wl, count, near, received_s)
        return SensorBatch(time_s, wl[:, :k], count[:, :k], near[:, :k], received_s, reference_nm=wl[:, k:])

    def _map_group(self, peaks, sens, count, value, near) -> None:
        """Windows of the sensors ``sens`` (one fibre) against its (n, k) peaks, O(n k log s).

        Windows on one fibre do not overlap (checked at first use), so each peak falls in at
        most one window: a binary search over the sorted window edges finds it.
        """
        S = self.lambda0_nm.size
        key = sens.tobytes()
        cache = self.__dict__.setdefault("_groups", {})
        if key not in cache:
            order = sens[np.argsort(self.lambda0_nm[sens])]
            lo, hi = self.lo[order], self.hi[order]
            cache[key] = (order, lo, hi, self.lambda0_nm[order], bool(np.any(lo[1:] < hi[:-1])))
        order, lo, hi, lam, overlapping = cache[key]
        n = peaks.shape[0]
        if overlapping:
            self._map_group_overlapping(peaks, sens, count, value, near)
            return
        row = np.broadcast_to(np.arange(n)[:, None] * S, peaks.shape)
        finite = np.isfinite(peaks)
        p = np.where(finite, peaks, -np.inf)
        j = np.searchsorted(lo, p, side="right") - 1  # window starting at or below
        jc = np.clip(j, 0, order.size - 1)
        inside = finite & (j >= 0) & (p <= hi[jc])
        flat = row[inside] + order[jc[inside]]
        size = count.size
        count += np.bincount(flat, minlength=size)
        value += np.bincount(flat, weights=p[inside], minlength=size)
        # peaks owned by no window but within the guard band of one: that grating moved
        stray = finite & ~inside
        if not stray.any():
            return
        for cand in (j, j + 1):  # the windows just below and just above
            valid = (cand >= 0) & (cand < order.size)
            k = np.clip(cand, 0, order.size - 1)
            d = np.abs(p - lam[k])
            hit = stray & valid & (d > self.window_nm) & (d <= self.window_nm + self.guard_nm)
            if hit.any():
                near += np.bincount(row[hit] + order[k[hit]], minlength=size)

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


class WavelengthSource(Protocol):
    """What the service reads wavelengths from."""

    def batches(self) -> AsyncIterator[SensorBatch]:
        """Batches of frames as they arrive, until the source ends or is closed."""
        ...

    async def close(self) -> None:
        """Stop the source and release its connections."""
        ...

    status: str


class TemperatureSource(Protocol):
    """The latest temperature per probe (°C), in ``probe_names`` order; NaN when unknown."""

    probe_names: list[str]

    def latest(self, time_s: np.ndarray) -> np.ndarray:
        """(n, P) temperatures to pair with wavelength samples stamped ``time_s``."""
        ...


# --------------------------------------------------------------------------- temperatures
class ReferenceThermometers:
    """The model's temperatures from the temperature source (real probes) and the strain-free
    reference gratings (``<sensor>_ref``: the temperature change of the sensor's gauge, eq. 3
    inverted, :func:`fbgcomp.optics.grating_temperature_change_K`).

    A reference grating reads relative to its nominal ``reference_lambda0_nm``; the constant
    offset from its actual zero-state wavelength cancels in the model's zero state (up to the
    ratio of the two wavelengths, ~1e-4 of the temperature change). A grating without exactly
    one peak in its window gives NaN: a missing temperature, as for a probe.
    """

    def __init__(self, probe_names: list[str], sensors, mapped_references: list[str]):
        self.probe_names = list(probe_names)
        by_probe = {
            f"{s.name}_ref": s for s in sensors if getattr(s, "reference_lambda0_nm", None) is not None
        }
        self.reference_probes = [p for p in self.probe_names if p in by_probe]
        self.real_probes = [p for p in self.probe_names if p not in by_probe]
        self._real = [self.probe_names.index(p) for p in self.real_probes]
        self._ref = [self.probe_names.index(p) for p in self.reference_probes]
        self._col = [mapped_references.index(p) for p in self.reference_probes]
        specs = [by_probe[p] for p in self.reference_probes]
        self._lambda0 = np.array([s.reference_lambda0_nm for s in specs], float)
        self._xi = np.array([s.thermo_optic_per_K for s in specs], float)
        self._af = np.array([s.fibre_cte_per_K for s in specs], float)

    def temperature_C(self, probes_C: np.ndarray, reference_nm: np.ndarray | None) -> np.ndarray:
        """(n, P) in the model's probe order from the real probes (n, len(real_probes)) and
        the batch's reference gratings (n, R) (None: none arrived, NaN)."""
        if not self._ref:
            return probes_C
        n = probes_C.shape[0]
        out = np.empty((n, len(self.probe_names)))
        out[:, self._real] = probes_C
        lam = np.full((n, len(self._ref)), np.nan) if reference_nm is None else reference_nm[:, self._col]
        out[:, self._ref] = optics.grating_temperature_change_K(
            lam, self._lambda0, thermo_optic_per_K=self._xi, fibre_cte_per_K=self._af
        )
        return out


class NoTemperatures:
    """For models that need no probe (eq. 11 style)."""

    def __init__(self, probe_names: list[str]):
        self.probe_names = list(probe_names)

    def latest(self, time_s: np.ndarray) -> np.ndarray:
        """NaN for every probe."""
        return np.full((time_s.size, len(self.probe_names)), np.nan)


class ConstantTemperatures:
    """Fixed probe temperatures, e.g. ``const:T_bulk=20.5,T_surf=21``."""

    def __init__(self, probe_names: list[str], values_C: dict[str, float]):
        missing = [p for p in probe_names if p not in values_C]
        if missing:
            raise InputError(
                f"no constant temperature for probe(s) {', '.join(missing)}", column="--temperatures"
            )
        self.probe_names = list(probe_names)
        self._row = np.array([values_C[p] for p in probe_names], dtype=np.float64)

    def latest(self, time_s: np.ndarray) -> np.ndarray:
        """The fixed temperatures, one row per frame."""
        return np.broadcast_to(self._row, (time_s.size, self._row.size)).copy()


class TableTemperatures:
    """Temperatures recorded in a campaign, replayed against the wavelength time stamps.

    ``clock_origin_s`` is the epoch time that campaign time 0 corresponds to; it is fixed on
    the first call (the first wavelength sample) unless given, so a campaign replayed by an
    instrument simulator and its temperatures stay in step. Only samples at or before the
    requested time are used (latest value per probe, no look-ahead).
    """

    def __init__(
        self,
        probe_names: list[str],
        time_s: np.ndarray,
        temperature_C: np.ndarray,
        speed: float = 1.0,
        clock_origin_s: float | None = None,
        loop: bool = False,
    ):
        self.probe_names = list(probe_names)
        self.time_s = np.asarray(time_s, dtype=np.float64)
        self.values = np.asarray(temperature_C, dtype=np.float64).reshape(self.time_s.size, -1)
        self.speed = float(speed)
        self.origin = clock_origin_s
        self.loop = loop

    @classmethod
    def from_campaign(
        cls, folder: str | Path, probe_names: list[str], speed: float = 1.0, loop: bool = False
    ) -> TableTemperatures:
        """The temperatures of a campaign folder."""
        c = read_campaign(folder)
        return cls.from_frame(c.temperatures, probe_names, speed, str(folder), loop=loop)

    @classmethod
    def from_csv(
        cls, path: str | Path, probe_names: list[str], speed: float = 1.0, loop: bool = False
    ) -> TableTemperatures:
        """The temperatures of a CSV with ``time_s`` and ``<probe>_C`` columns."""
        return cls.from_frame(pd.read_csv(path), probe_names, speed, str(path), loop=loop)

    @classmethod
    def from_frame(cls, df, probe_names, speed, where, loop=False) -> TableTemperatures:
        """The temperatures of a table with ``time_s`` and ``<probe>_C`` columns; InputError
        naming ``where`` when a column is missing.
        """
        cols = [f"{p}_C" for p in probe_names]
        missing = [c for c in [*cols, "time_s"] if c not in df.columns]
        if missing:
            raise InputError(f"temperature table lacks column(s) {', '.join(missing)}", file=where)
        return cls(probe_names, df["time_s"].to_numpy(float), df[cols].to_numpy(float), speed, loop=loop)

    def latest(self, time_s: np.ndarray) -> np.ndarray:
        """The newest recorded temperatures at or before each frame's time on the campaign clock."""
        if self.origin is None:
            self.origin = float(time_s[0]) - self.time_s[0] / self.speed
        camp_t = (np.asarray(time_s) - self.origin) * self.speed
        span = self.time_s[-1] - self.time_s[0]
        if self.loop and span > 0:
            camp_t = self.time_s[0] + np.mod(camp_t - self.time_s[0], span)
        # tolerance of the epoch <-> campaign clock arithmetic (an epoch in float64 is only
        # good to ~0.2 µs), so the sample stamped exactly t is not missed
        tol = 8.0 * float(np.spacing(abs(self.origin) + 1.0)) * self.speed + 1e-9
        idx = np.searchsorted(self.time_s, camp_t + tol, side="right") - 1
        out = self.values[np.clip(idx, 0, None)]
        out[idx < 0] = np.nan
        return out


def open_temperatures(
    spec: str | None, probe_names: list[str], speed: float = 1.0, loop: bool = False
) -> TemperatureSource:
    """Temperature source from ``--temperatures``: a campaign folder, a CSV file or ``const:...``."""
    if not probe_names:
        return NoTemperatures([])
    if spec is None:
        raise InputError(
            f"the model needs probe temperatures ({', '.join(probe_names)}); give "
            "--temperatures DIR|FILE.csv|const:P=°C,...",
            column="--temperatures",
        )
    if spec.startswith("const:"):
        try:
            values = {
                k.strip(): float(v)
                for k, v in (item.split("=") for item in spec[6:].split(",") if item.strip())
            }
        except ValueError as exc:
            raise InputError(f"bad constant temperatures {spec!r}", column="--temperatures") from exc
        return ConstantTemperatures(probe_names, values)
    path = Path(spec)
    if path.is_dir():
        return TableTemperatures.from_campaign(path, probe_names, speed, loop)
    if path.is_file():
        return TableTemperatures.from_csv(path, probe_names, speed, loop)
    raise InputError("temperature source not found", file=spec)


# --------------------------------------------------------------------------- wavelength sources
class HyperionSource:
    """Peaks from a Hyperion instrument; reconnects with capped exponential back-off."""

    def __init__(
        self,
        host: str,
        stream_port: int,
        command_port: int,
        mapper: PeakMapper,
        backoff_initial_s: float = 0.1,
        backoff_max_s: float = 5.0,
        stall_timeout_s: float = 2.0,
    ):
        self.host, self.stream_port, self.command_port = host, stream_port, command_port
        self.mapper = mapper
        self.backoff_initial_s = backoff_initial_s
        self.backoff_max_s = backoff_max_s
        self.stall_timeout_s = stall_timeout_s
        self.status = "connecting"
        self.reconnects = 0
        self.serial_number = ""
        self._client: hyperion.HyperionClient | None = None
        self._closed = False

    async def _connect(self) -> hyperion.HyperionClient:
        client = hyperion.HyperionClient(
            self.host, self.command_port, self.stream_port, timeout_s=self.stall_timeout_s
        )
        # The command port is optional for streaming; use it when present.
        with contextlib.suppress(TimeoutError, OSError, hyperion.HyperionError, asyncio.IncompleteReadError):
            self.serial_number = await client.serial_number()
        await client.open_stream()
        return client

    async def batches(self) -> AsyncIterator[SensorBatch]:
        """Batches from the instrument, reconnecting with capped exponential back-off."""
        delay = self.backoff_initial_s
        while not self._closed:
            try:
                self._client = await self._connect()
                self.status = "connected"
                while True:
                    blocks = await self._client.read_blocks(self.stall_timeout_s)
                    # back-off restarts only once data flows (an instrument that accepts and
                    # drops connections must not be hammered)
                    delay = self.backoff_initial_s
                    yield self.mapper.map_blocks(blocks, time.time())
            except (
                TimeoutError,
                OSError,
                ConnectionError,
                asyncio.IncompleteReadError,
                hyperion.HyperionError,
            ) as exc:
                self.status = f"reconnecting ({type(exc).__name__})"
                log.warning(
                    "hyperion link %s:%s lost (%s); retry in %.2f s", self.host, self.stream_port, exc, delay
                )
            if self._client is not None:
                await self._client.close()
                self._client = None
            if self._closed:
                break
            self.reconnects += 1
            await asyncio.sleep(delay)
            delay = min(delay * 2.0, self.backoff_max_s)

    async def close(self) -> None:
        """Stop reading and close the connection."""
        self._closed = True
        if self._client is not None:
            await self._client.close()


class ReplaySource:
    """A campaign's wavelengths replayed at ``speed`` × real time (already one value per sensor).

    Time stamps are ``start epoch + campaign time``; the matching :class:`TableTemperatures`
    (same origin) is exposed as ``temperatures``.
    """

    def __init__(
        self,
        folder: str | Path,
        sensor_names: list[str],
        probe_names: list[str],
        speed: float = 1.0,
        chunk_s: float = 0.002,
        loop: bool = False,
        reference_probes: list[str] | None = None,
    ):
        c = read_campaign(folder)
        missing = [s for s in sensor_names if f"{s}_nm" not in c.fbg.columns]
        if missing:
            raise InputError(f"campaign lacks sensor(s) {', '.join(missing)} the model needs", file=folder)
        self.time_s = c.fbg["time_s"].to_numpy(float)
        self.wavelength_nm = c.fbg[[f"{s}_nm" for s in sensor_names]].to_numpy(float)
        # strain-free reference gratings (<sensor>_ref -> column <sensor>_ref_nm); a campaign
        # without one replays it as lost (NaN), as an instrument without its peak would
        self.reference_nm = None
        if reference_probes:
            self.reference_nm = np.column_stack(
                [
                    c.fbg[f"{p}_nm"].to_numpy(float)
                    if f"{p}_nm" in c.fbg.columns
                    else np.full(self.time_s.size, np.nan)
                    for p in reference_probes
                ]
            )
        self.speed = float(speed)
        self.chunk_s = chunk_s
        self.loop = loop
        self.origin_s = time.time() - self.time_s[0] / self.speed
        self.temperatures = (
            TableTemperatures.from_frame(c.temperatures, probe_names, speed, str(folder), loop=loop)
            if probe_names
            else NoTemperatures([])
        )
        if isinstance(self.temperatures, TableTemperatures):  # there are probes
            self.temperatures.origin = self.origin_s
        self.status = "replaying"
        self._closed = False

    async def batches(self) -> AsyncIterator[SensorBatch]:
        """The campaign's frames at ``speed`` times real time (looping if asked)."""
        i = 0
        n = self.time_s.size
        span = self.time_s[-1] - self.time_s[0]
        lap = 0
        while not self._closed:
            now_camp = (time.time() - self.origin_s) * self.speed - lap * span
            j = int(np.searchsorted(self.time_s, now_camp, side="right"))
            if j > i:
                wl = self.wavelength_nm[i:j]
                ok = np.isfinite(wl)
                stamp = self.origin_s + (self.time_s[i:j] + lap * span) / self.speed
                yield SensorBatch(
                    stamp,
                    wl,
                    ok.astype(np.int8),
                    np.zeros(wl.shape, np.int8),
                    time.time(),
                    None if self.reference_nm is None else self.reference_nm[i:j],
                )
                i = j
            if i >= n:
                if not self.loop:
                    self.status = "finished"
                    return
                i, lap = 0, lap + 1
            await asyncio.sleep(self.chunk_s)

    async def close(self) -> None:
        """Stop the replay."""
        self._closed = True


def parse_source_url(url: str) -> tuple[str, dict]:
    """``hyperion://HOST[:PORT]``, ``replay://DIR?speed=10``, ``sim://DIR?rate=1000``."""
    u = urlparse(url)
    if u.scheme not in ("hyperion", "replay", "sim"):
        raise InputError(
            f"unknown source {url!r}: use hyperion://HOST:PORT, replay://DIR or sim://DIR", column="--source"
        )
    opts = {k: v[-1] for k, v in parse_qs(u.query).items()}
    if u.scheme == "hyperion":
        if not u.hostname:
            raise InputError(f"no host in {url!r}", column="--source")
        opts["host"] = u.hostname
        opts["stream_port"] = str(u.port or hyperion.STREAM_PORT)
        opts.setdefault("command_port", str(hyperion.COMMAND_PORT if u.port is None else u.port - 1))
    else:
        opts["path"] = (u.netloc + u.path) if u.netloc else u.path
    return u.scheme, opts
