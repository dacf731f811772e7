"""Drift history for the dashboard: the run log, downsampled server-side for windows of 1 min to 36 h.

A 36 h log at 1 kHz holds ~1.3e8 frames in ~2.6e5 parts (one per ``flush_s``): far too much to
send, or to read at each request. The page asks for a window (``GET /api/history?window_s=…``)
and gets at most ``points`` buckets, each with the count of frames, the min, max and mean of every
plotted value (applied correction ``corr_*``, predicted deviation ``dev_*``, probe temperatures)
and how many of its frames were in each health state, carried each output flag, had the output
disabled or had a sensor not OK: what the operator needs to see whether compensation acts and
why it is held back. Min and max keep a short event visible in a bucket of hours; a count keeps
a single flagged frame visible.

Reading: parts are immutable once renamed, and their names carry the time they were written
(:func:`fbgcomp.runtime.log.part_write_s`), so a window only lists the days and parts written
within it (plus ``SLACK_S``) and reads only the columns it plots. Windows up to ``RAW_MAX_S`` are
bucketed from the frames; longer ones from per-second buckets (``BASE_S``) that each part is
reduced to once and kept (memory: one row per second of the longest window, ~36 h x ~40 numbers,
whatever the frame rate). A cold cache (a dashboard started on a long log) is filled newest part
first within ``budget_s`` per request; the answer says how far back it got (``complete``,
``covered_from_s``) and the page asks again.

The window ends at the newest logged frame (``time_s``, the instrument clock); the parts are
chosen by this host's clock, which suffices as long as the instrument's clock runs no slower
than the host's (a live interrogator, or a replay at speed >= 1).
"""

from __future__ import annotations

import math
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from fbgcomp.runtime.health import FLAG_NAMES, STATUS_NAMES
from fbgcomp.runtime.log import log_parts, part_write_s, read_meta
from fbgcomp.runtime.pipeline import HEALTH_NAMES
from fbgcomp.units import AXES

MIN_WINDOW_S = 60.0
MAX_WINDOW_S = 36 * 3600.0
WINDOWS_S = (60, 600, 3600, 6 * 3600, 12 * 3600, 36 * 3600)  # the page's choices
BASE_S = 1.0  # cached bucket width for long windows, s
RAW_MAX_S = 900.0  # windows up to 15 min are bucketed from the frames themselves
SLACK_S = 120.0  # parts written this long before the window may still hold its frames
MAX_POINTS = 2000


@dataclass
class Buckets:
    """Frames reduced to time buckets (rows sorted by ``ids``, one row per non-empty bucket).

    ``ids``: bucket index (floor(time_s / width)); ``n``: frames; per value column ``vmin``,
    ``vmax`` (NaN-ignoring), ``vsum`` and ``vcnt`` (sum and count of finite values); per
    indicator column ``icnt`` (frames where it holds)."""

    ids: np.ndarray
    n: np.ndarray
    vmin: np.ndarray
    vmax: np.ndarray
    vsum: np.ndarray
    vcnt: np.ndarray
    icnt: np.ndarray

    def __len__(self) -> int:
        return self.ids.size


def bucketise(time_s, values, indicators, width_s: float) -> Buckets:
    """Reduce frames to buckets of ``width_s`` seconds (bucket k holds k*w <= t < (k+1)*w).

    Parameters
    ----------
    time_s : (n,) frame times, s
    values : (n, V) float, NaN where there is no value
    indicators : (n, I) bool
    width_s : bucket width, s
    """
    ids = np.floor(np.asarray(time_s, float) / width_s).astype(np.int64)
    values = np.asarray(values, float).reshape(ids.size, -1)
    indicators = np.asarray(indicators, bool).reshape(ids.size, -1)
    finite = np.isfinite(values)
    return _reduce(
        ids,
        np.ones(ids.size, np.int64),
        values,
        values,
        np.where(finite, values, 0.0),
        finite.astype(np.int64),
        indicators.astype(np.int64),
    )


def merge(parts: list[Buckets], factor: int = 1) -> Buckets:
    """Buckets of several reductions (any order, overlapping buckets allowed) on one axis,
    ``factor`` of them per new bucket."""
    cat = np.concatenate
    return _reduce(
        cat([p.ids for p in parts]) // factor,
        cat([p.n for p in parts]),
        cat([p.vmin for p in parts]),
        cat([p.vmax for p in parts]),
        cat([p.vsum for p in parts]),
        cat([p.vcnt for p in parts]),
        cat([p.icnt for p in parts]),
    )


def _reduce(ids, n, vmin, vmax, vsum, vcnt, icnt) -> Buckets:
    order = np.argsort(ids, kind="stable")
    ids = ids[order]
    if ids.size == 0:
        return Buckets(ids, n[:0], vmin[:0], vmax[:0], vsum[:0], vcnt[:0], icnt[:0])
    start = np.flatnonzero(np.r_[True, ids[1:] != ids[:-1]])
    with np.errstate(invalid="ignore"):
        return Buckets(
            ids[start],
            np.add.reduceat(n[order], start),
            np.fmin.reduceat(vmin[order], start, axis=0),
            np.fmax.reduceat(vmax[order], start, axis=0),
            np.add.reduceat(vsum[order], start, axis=0),
            np.add.reduceat(vcnt[order], start, axis=0),
            np.add.reduceat(icnt[order], start, axis=0),
        )


def _codes(column, names) -> np.ndarray:
    """A pyarrow health/status column as integer codes: names (dictionary-encoded strings) are
    looked up in ``names`` (unknown: -1); integer codes of older logs are kept."""
    import pyarrow as pa  # noqa: PLC0415 - optional extra: pyarrow (the runtime extra)
    import pyarrow.compute as pc  # noqa: PLC0415 - optional extra: pyarrow

    column = column.combine_chunks() if isinstance(column, pa.ChunkedArray) else column
    if pa.types.is_dictionary(column.type):
        lookup = {v: k for k, v in enumerate(names)}
        table = np.array([lookup.get(v, -1) for v in column.dictionary.to_pylist()] + [-1], np.int64)
        idx = column.indices.fill_null(-1).to_numpy(zero_copy_only=False).astype(np.int64)
        return table[idx]
    if pa.types.is_string(column.type) or pa.types.is_large_string(column.type):
        return (
            pc.index_in(column, pa.array(list(names)))
            .fill_null(-1)
            .to_numpy(zero_copy_only=False)
            .astype(np.int64)
        )
    return column.to_numpy(zero_copy_only=False).astype(np.int64)


class LogHistory:
    """Downsampled windows of one run-log folder; ``window`` is thread-safe (one at a time)."""

    def __init__(self, folder: str | Path):
        self.folder = Path(folder)
        self._lock = threading.Lock()
        self._meta: dict | None = None
        self._done: dict[str, float] = {}  # part name -> newest time_s in it
        self._pending: list[Buckets] = []
        self._base: Buckets | None = None  # consolidated BASE_S buckets
        self._t_last = -math.inf  # newest frame time seen, s
        self.parts_read = 0  # parts reduced since start (for the tests)

    # -- columns -------------------------------------------------------------------------------
    def _columns(self) -> dict:
        if self._meta is None:
            meta = read_meta(self.folder)
            probes = list(meta.get("probe_names") or [])
            sensors = list(meta.get("sensor_names") or [])
            # the temperature chart's probes: not the measured heat inputs (W), logged as <source>_W
            heat = set(meta.get("heat_inputs") or [])
            probes = [p for p in probes if p not in heat]
            values = (
                [f"corr_{a}_um" for a in AXES] + [f"dev_{a}_um" for a in AXES] + [f"{p}_C" for p in probes]
            )
            health = list(meta.get("health_names") or HEALTH_NAMES)
            flags = {int(k): v for k, v in (meta.get("flag_names") or {}).items()} or dict(FLAG_NAMES)
            indicators = (
                [f"health:{h}" for h in health]
                + [f"flag:{name}" for name in flags.values()]
                + ["disabled"]
                + [f"sensor:{s}" for s in sensors]
            )
            self._meta = {
                "meta": meta,
                "probes": probes,
                "sensors": sensors,
                "values": values,
                "health": health,
                "flags": flags,
                "indicators": indicators,
                "status": list(meta.get("status_names") or STATUS_NAMES),
                "ambient": ambient_probes(meta),
            }
        return self._meta

    def _frames(self, path: Path):
        """(time_s, values (n,V), indicators (n,I)) of one part, only the plotted columns."""
        import pyarrow.parquet as pq  # noqa: PLC0415 - optional extra: pyarrow (the runtime extra)

        c = self._columns()
        flag_cols = [f"flags_{a}" for a in AXES]
        status_cols = [f"{s}_status" for s in c["sensors"]]
        table = pq.read_table(
            path, columns=["time_s"] + c["values"] + ["health", "enabled"] + flag_cols + status_cols
        )
        t = table.column("time_s").to_numpy()
        values = np.column_stack(
            [table.column(v).to_numpy(zero_copy_only=False).astype(float) for v in c["values"]]
        )
        health = _codes(table.column("health"), c["health"])
        words = np.bitwise_or.reduce(
            np.column_stack(
                [table.column(f).to_numpy(zero_copy_only=False).astype(np.int64) for f in flag_cols]
            ),
            axis=1,
        )
        ind = [health == k for k in range(len(c["health"]))]
        ind += [(words & bit) != 0 for bit in c["flags"]]
        ind.append(~table.column("enabled").to_numpy(zero_copy_only=False).astype(bool))
        ind += [_codes(table.column(s), c["status"]) != 0 for s in status_cols]
        return t, values, np.column_stack(ind)

    # -- the cache of BASE_S buckets ----------------------------------------------------------------
    def _fill(self, parts: list[Path], deadline: float) -> bool:
        """Reduce the parts not yet cached, newest first, until the deadline (at least one per
        call, so that asking again always gets further); True if all are."""
        read = 0
        for path in reversed(parts):
            if path.name in self._done:
                continue
            if read and time.monotonic() > deadline:
                return False
            read += 1
            t, values, ind = self._frames(path)
            self.parts_read += 1
            self._done[path.name] = float(t.max()) if t.size else -math.inf
            if t.size:
                self._t_last = max(self._t_last, float(t.max()))
                self._pending.append(bucketise(t, values, ind, BASE_S))
            if len(self._pending) >= 256:
                self._consolidate()
        return True

    def _consolidate(self) -> None:
        parts = self._pending + ([self._base] if self._base is not None else [])
        self._pending = []
        if not parts:
            return
        base = merge(parts)
        # bounded: nothing older than the longest window (plus slack) before the newest frame
        keep = base.ids >= math.floor((self._t_last - MAX_WINDOW_S - SLACK_S) / BASE_S)
        self._base = Buckets(*(getattr(base, f)[keep] for f in Buckets.__dataclass_fields__))

    def _forget(self, listed: set[str]) -> None:
        """Drop the names of parts too old to be listed again (or deleted)."""
        cut = time.time() - MAX_WINDOW_S - 2 * SLACK_S
        self._done = {k: v for k, v in self._done.items() if k in listed or part_write_s(k) >= cut}

    # -- a window ---------------------------------------------------------------------------------
    def window(self, window_s: float, points: int = 600, budget_s: float = 1.5) -> dict:
        """The last ``window_s`` seconds of the log in at most ``points`` buckets (JSON-ready)."""
        window_s = float(min(max(window_s, MIN_WINDOW_S), MAX_WINDOW_S))
        points = int(min(max(points, 10), MAX_POINTS))
        with self._lock:
            c = self._columns()
            deadline = time.monotonic() + budget_s
            parts = log_parts(self.folder, since_s=time.time() - window_s - SLACK_S)
            if window_s <= RAW_MAX_S:
                width = window_s / points
                got, complete = [], True
                t_end = -math.inf
                for path in reversed(parts):
                    t, values, ind = self._frames(path)
                    if t.size:
                        t_end = max(t_end, float(t.max()))
                        got.append((t, values, ind))
                        if float(t.min()) < t_end - window_s:
                            break  # parts are in writing order: older ones are older
                    if time.monotonic() > deadline:
                        complete = False
                        break
                if not got:
                    return self._answer(c, window_s, width, -math.inf, None, True)
                t = np.concatenate([g[0] for g in got])
                keep = t >= t_end - window_s
                buckets = bucketise(
                    t[keep],
                    np.concatenate([g[1] for g in got])[keep],
                    np.concatenate([g[2] for g in got])[keep],
                    width,
                )
                return self._answer(c, window_s, width, t_end, buckets, complete)
            complete = self._fill(parts, deadline)
            self._forget({p.name for p in parts})
            self._consolidate()
            factor = max(1, math.ceil(window_s / points / BASE_S))
            width = factor * BASE_S
            if self._base is None or not len(self._base):
                return self._answer(c, window_s, width, -math.inf, None, complete)
            t_end = self._t_last
            base = self._base
            keep = base.ids >= math.floor((t_end - window_s) / BASE_S)
            buckets = merge(
                [Buckets(*(getattr(base, f)[keep] for f in Buckets.__dataclass_fields__))], factor
            )
            return self._answer(c, window_s, width, t_end, buckets, complete)

    def _answer(self, c, window_s, width, t_end, b: Buckets | None, complete) -> dict:
        out = {
            "window_s": window_s,
            "bucket_s": width,
            "complete": bool(complete),
            "probes": c["probes"],
            "ambient": c["ambient"],
            "sensors": c["sensors"],
            "health_names": c["health"],
            "flag_names": list(c["flags"].values()),
        }
        if b is None or not len(b):
            return {
                **out,
                "t_end": None,
                "t": [],
                "n": [],
                "frames": 0,
                "series": {},
                "counts": {},
                "covered_from_s": None,
            }
        # a bucket that starts before the window holds only part of its time: left out, so
        # that every bucket shown is whole and there are at most `points` of them
        whole = b.ids * width >= t_end - window_s - 1e-6 * width
        b = Buckets(*(getattr(b, f)[whole] for f in Buckets.__dataclass_fields__))
        if not len(b):
            return self._answer(c, window_s, width, t_end, None, complete)
        with np.errstate(invalid="ignore", divide="ignore"):
            mean = b.vsum / b.vcnt
        out.update(
            {
                "t_end": t_end,
                "covered_from_s": float(b.ids[0] * width),
                # bucket start times, s on the instrument clock
                "t": _wire(b.ids * width, 3),
                "n": b.n.tolist(),
                "frames": int(b.n.sum()),
                "series": {
                    name: {
                        "min": _wire(b.vmin[:, j], 4),
                        "max": _wire(b.vmax[:, j], 4),
                        "mean": _wire(mean[:, j], 4),
                    }
                    for j, name in enumerate(c["values"])
                },
                "counts": {name: b.icnt[:, j].tolist() for j, name in enumerate(c["indicators"])},
            }
        )
        return out


def _wire(values, digits: int) -> list:
    """Rounded floats for JSON; NaN (no value in the bucket) as null."""
    v = np.round(np.asarray(values, float), digits)
    return [x if math.isfinite(x) else None for x in v.tolist()]


def ambient_probes(meta: dict) -> list[str]:
    """The probes that read the ambient: those the log's probe list marks ``kind: ambient`` (as
    the machine description does) or whose location or name says so (``T_amb``); empty if none
    does (the page then plots every probe)."""
    names = list(meta.get("probe_names") or [])
    specs = {p.get("name"): p for p in (meta.get("temperature_probes") or []) if isinstance(p, dict)}
    out = []
    for name in names:
        spec = specs.get(name, {})
        text = " ".join(str(spec.get(k) or "") for k in ("kind", "location")).lower()
        if "ambient" in text or name.lower() in ("t_amb", "t_ambient", "ambient", "t_air"):
            out.append(name)
    return out
