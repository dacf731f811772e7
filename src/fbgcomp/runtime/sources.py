"""Wavelength and temperature sources behind one interface.

A wavelength source is an async iterator of :class:`SensorBatch` (every frame that has arrived,
already mapped to the model's sensors); sources that lose their link reconnect by themselves
with capped exponential back-off (peaks go to sensors in :mod:`fbgcomp.runtime.windows`). A
temperature source answers the latest value per probe.

Strain-free reference gratings (``reference_lambda0_nm`` of a sensor) own a window of their own
(``reference_lambda0_nm ± window_nm``) and travel beside the sensors in
``SensorBatch.reference_nm``; :class:`ReferenceThermometers` turns them into the model's
``<sensor>_ref`` temperatures, so the temperature source only answers the real probes.
"""

from __future__ import annotations

import asyncio
import bisect
import contextlib
import logging
import time
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Protocol
from urllib.parse import parse_qs, urlparse

import numpy as np
import pandas as pd

from fbgcomp import optics
from fbgcomp.errors import InputError
from fbgcomp.io.campaign import read_campaign
from fbgcomp.io.campaign.layout import input_column
from fbgcomp.runtime import hyperion
from fbgcomp.runtime.windows import PeakMapper, SensorBatch

log = logging.getLogger("fbgcomp.runtime")


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
        self._tol_for: float | None = None  # the origin the clock tolerance below was computed for
        self._tol = 0.0
        self._times: list[float] = self.time_s.tolist()  # for the one-frame look-up

    @classmethod
    def from_campaign(
        cls, folder: str | Path, probe_names: list[str], speed: float = 1.0, loop: bool = False
    ) -> TableTemperatures:
        """The temperatures of a campaign folder."""
        c = read_campaign(folder)
        return cls.from_frame(c.slow_inputs(), probe_names, speed, str(folder), loop=loop)

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
        # a probe's <probe>_C first: a probe may be named like a heat input (T_W)
        cols = [f"{p}_C" if f"{p}_C" in df.columns else input_column(p) for p in probe_names]
        missing = [c for c in [*cols, "time_s"] if c not in df.columns]
        if missing:
            raise InputError(f"temperature table lacks column(s) {', '.join(missing)}", file=where)
        return cls(probe_names, df["time_s"].to_numpy(float), df[cols].to_numpy(float), speed, loop=loop)

    def latest(self, time_s: np.ndarray) -> np.ndarray:
        """The newest recorded temperatures at or before each frame's time on the campaign clock."""
        if self.origin is None:
            self.origin = float(time_s[0]) - self.time_s[0] / self.speed
        if self._tol_for != self.origin:
            # tolerance of the epoch <-> campaign clock arithmetic (an epoch in float64 is
            # only good to ~0.2 µs), so the sample stamped exactly t is not missed
            self._tol = 8.0 * float(np.spacing(abs(self.origin) + 1.0)) * self.speed + 1e-9
            self._tol_for = self.origin
        if np.ndim(time_s) == 1 and len(time_s) == 1 and not self.loop:
            # one frame (a high frame rate): the same arithmetic on a Python float
            i = (
                bisect.bisect_right(self._times, (float(time_s[0]) - self.origin) * self.speed + self._tol)
                - 1
            )
            return self.values[i : i + 1].copy() if i >= 0 else np.full((1, self.values.shape[1]), np.nan)
        camp_t = (np.asarray(time_s) - self.origin) * self.speed
        if self.loop and (span := self.time_s[-1] - self.time_s[0]) > 0:
            camp_t = self.time_s[0] + np.mod(camp_t - self.time_s[0], span)
        camp_t += self._tol
        idx = np.searchsorted(self.time_s, camp_t, side="right") - 1
        if idx.size and idx.min() < 0:  # before the first sample: unknown
            out = self.values[np.maximum(idx, 0)]
            out[idx < 0] = np.nan
            return out
        return self.values[idx]


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
            TableTemperatures.from_frame(c.slow_inputs(), probe_names, speed, str(folder), loop=loop)
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
