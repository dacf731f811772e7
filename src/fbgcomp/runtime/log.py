"""Durable run log: a Parquet dataset of raw wavelengths, temperatures, corrections and health.

Layout of a log folder::

    LOG/meta.json                       sensors, probes, model id, model sets (written atomically)
    LOG/data/date=<YYYY-MM-DD>/part-<epoch_ms>-<seq>.parquet
                                        one file per flush, at most ``flush_s`` (≤ 1 s) of frames

Only Parquet files live under ``LOG/data``, so the usual tools read it as one table:
``pd.read_parquet("LOG/data")``, ``duckdb.read_parquet("LOG/**/*.parquet")`` (both add the
hive partition column ``date``: the UTC day the part was written, by this host's clock, which
lets a reader of a long log open only the days it needs and lets old days be deleted whole).
Logs written before this layout (parts next to meta.json) are still read by :func:`read_log`
and :func:`log_parts`.

Each part is written to a temporary name (``.part-….tmp``, which Parquet readers skip) in its
own folder, fsynced and renamed, so a reader (or a ``kill -9``) never sees a half-written file;
at most the frames of the last ``flush_s`` are lost. Writing happens in a background thread
behind a bounded queue: when the disk is slower than the stream the oldest unwritten batches are
dropped and counted (``dropped_rows``) rather than ever blocking the compensation loop.

Columns: ``time_s`` (instrument epoch s), ``received_s``, ``<S>_nm`` (wavelength in the sensor
window, NaN if none), ``<S>_peaks`` (peaks in the window), ``<S>_status`` (sensor status, a
dictionary-encoded string: ``OK``, ``MISSING``, … as :data:`fbgcomp.runtime.health.STATUS_NAMES`),
``<P>_C`` (probe temperatures paired with the frame), ``dev_dx_um``… (predicted deviation),
``half_dx_um``… (95 % interval half-width), ``corr_dx_um``… (published correction),
``flags_dx``… (output flag word per axis, bits in meta.json ``flag_names``:
model policy 1 SHRUNK, 2 CLAMPED, 4 LOAD_REFUSED; limits 8 RATE_LIMITED, 16 MAX_LIMITED),
``health`` (dictionary-encoded string ``OK``, ``DEGRADED``, ``ALARM``, ``ZEROING``),
``model_set`` (index in meta.json ``model_sets``, -1 none), ``enabled``. Logs written before
stored health and status as their integer codes (the index in those name lists).
"""

from __future__ import annotations

import collections
import json
import logging
import os
import tempfile
import threading
import time
from datetime import UTC, datetime
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import pandas as pd

from fbgcomp.atomic import atomic_path, write_bytes
from fbgcomp.errors import InputError
from fbgcomp.io.campaign import Campaign, read_campaign, write_campaign
from fbgcomp.io.dataset import ROWS_PER_FILE, ingest_campaign
from fbgcomp.optics import free_grating_wavelength_nm
from fbgcomp.runtime.health import STATUS_NAMES
from fbgcomp.runtime.pipeline import HEALTH_NAMES
from fbgcomp.units import AXES

if TYPE_CHECKING:
    import pyarrow

log = logging.getLogger("fbgcomp.runtime")
DATA_DIR = "data"  # LOG/data/date=YYYY-MM-DD/part-*.parquet


def _labels(codes: np.ndarray, names) -> pyarrow.DictionaryArray:
    """Integer codes as a dictionary-encoded string column (names[code]); a code beyond the
    names is kept as ``CODE<n>`` rather than lost."""
    import pyarrow as pa  # noqa: PLC0415 - optional extra: pyarrow (the runtime extra), imported only when used

    names = list(names)
    codes = np.asarray(codes)
    top = int(codes.max()) if codes.size else -1
    names += [f"CODE{k}" for k in range(len(names), top + 1)]
    return pa.DictionaryArray.from_arrays(pa.array(codes.astype(np.int16)), pa.array(names))


def _codes(column, names) -> np.ndarray:
    """A logged health/status column as integer codes: names (this layout) are looked up in
    ``names``, integer codes (older logs) are kept; an unknown name is -1."""
    lookup = {n: k for k, n in enumerate(names)}
    if isinstance(column.dtype, pd.CategoricalDtype):
        table = np.array([lookup.get(c, -1) for c in column.cat.categories] + [-1], np.int16)
        return table[column.cat.codes.to_numpy()]  # code -1 (no value) -> the last: -1
    if pd.api.types.is_numeric_dtype(column.dtype):
        return column.to_numpy()
    return column.map(lookup).fillna(-1).to_numpy(np.int16)


class RunLog:
    """Background Parquet writer; ``submit`` never blocks."""

    def __init__(
        self, folder: str | Path, meta: dict, flush_s: float = 0.5, max_queue: int = 2000, fsync: bool = True
    ):
        import pyarrow  # noqa: F401, PLC0415 - optional extra: pyarrow; fail early if it is missing

        if not 0 < flush_s <= 1.0:
            raise InputError(f"log flush interval {flush_s} s must be in (0, 1]", column="log.flush_s")
        self.folder = Path(folder)
        self.folder.mkdir(parents=True, exist_ok=True)
        self.data_dir = self.folder / DATA_DIR
        self.data_dir.mkdir(exist_ok=True)
        self.meta = meta
        self.health_names = list(meta.get("health_names") or HEALTH_NAMES)
        self.status_names = list(meta.get("status_names") or STATUS_NAMES)
        self.sensor_names = list(meta["sensor_names"])
        self.probe_names = list(meta["probe_names"])
        heat = set(meta.get("heat_inputs") or [])
        # a probe's column <probe>_C, a measured heat input's its name (<source>_W)
        self._input_cols = [p if p in heat else f"{p}_C" for p in self.probe_names]
        self.flush_s = flush_s
        self.fsync = fsync
        self.dropped_rows = 0
        self.written_rows = 0
        self.files = 0
        # A plain deque: appending never wakes the writer thread (waking it on every batch
        # would hand the GIL over at the stream rate); the writer polls every flush_s.
        self._q: collections.deque = collections.deque()
        self.max_queue = max_queue
        self._stop = threading.Event()
        self._seq = 0
        old = self.folder / "meta.json"
        if old.is_file():
            # appending to an earlier run is fine only with the same columns
            try:
                previous = json.loads(old.read_text())
            except (OSError, json.JSONDecodeError):
                previous = {}
            if (previous.get("sensor_names"), previous.get("probe_names")) != (
                self.sensor_names,
                self.probe_names,
            ):
                raise InputError(
                    "the log folder holds a run with other sensors or probes; give a new folder",
                    file=self.folder,
                )
        write_bytes(self.folder / "meta.json", json.dumps(meta, indent=2, default=str).encode())
        self._thread = threading.Thread(target=self._run, name="fbgcomp-log", daemon=True)
        self._thread.start()

    def submit(self, batch, result, enabled: bool, z_mm: float | None = None) -> None:
        """Queue a processed batch for writing (never blocks: when the queue is full the batch
        is dropped and counted in ``dropped_rows``). ``z_mm``: the Z position the model was
        given for the batch (the live ``[position]``; None or NaN: none, or stale).
        """
        if len(self._q) >= self.max_queue:
            self.dropped_rows += len(batch)
            return
        self._q.append((batch, result, enabled, np.nan if z_mm is None else float(z_mm)))

    def _columns(self, items) -> dict:
        b = [i[0] for i in items]
        r = [i[1] for i in items]
        cat = np.concatenate
        cols = {
            "time_s": cat([x.time_s for x in b]),
            "received_s": cat([np.full(len(x), x.received_s) for x in b]),
        }
        wl = cat([x.wavelength_nm for x in b])
        pk = cat([x.peak_count for x in b])
        st = cat([x.sensor_status for x in r])
        for j, s in enumerate(self.sensor_names):
            cols[f"{s}_nm"] = wl[:, j]
            cols[f"{s}_peaks"] = pk[:, j]
            cols[f"{s}_status"] = _labels(st[:, j], self.status_names)
        temp = cat([x.temperature_C for x in r])
        for j, col in enumerate(self._input_cols):
            cols[col] = temp[:, j]
        for name, attr in (("dev", "deviation_um"), ("half", "half_width_um"), ("corr", "correction_um")):
            v = cat([getattr(x, attr) for x in r])
            for j, a in enumerate(AXES):
                cols[f"{name}_{a}_um"] = v[:, j]
        flags = cat([x.output_flags for x in r])
        for j, a in enumerate(AXES):
            cols[f"flags_{a}"] = flags[:, j]
        cols["health"] = _labels(cat([x.health for x in r]), self.health_names)
        cols["model_set"] = cat([x.model_set for x in r])
        cols["enabled"] = cat([np.full(len(x), e, bool) for x, _, e, _ in items])
        # the axis position the model was given (paper sec. 2.4: the errors depend on Z)
        cols["z_mm"] = cat([np.full(len(x), z, float) for x, _, _, z in items])
        return cols

    def _write(self, items) -> None:
        import pyarrow as pa  # noqa: PLC0415 - optional extra: pyarrow (the runtime extra)
        import pyarrow.parquet as pq  # noqa: PLC0415 - optional extra: pyarrow

        table = pa.table(self._columns(items))
        now = time.time()
        name = f"part-{int(now * 1000):013d}-{self._seq:06d}.parquet"
        self._seq += 1
        day = self.data_dir / time.strftime("date=%Y-%m-%d", time.gmtime(now))
        if not day.is_dir():
            day.mkdir(exist_ok=True)
            if self.fsync:
                _fsync_dir(self.data_dir)
        # ".part-….tmp", which Parquet readers skip, until complete, fsynced and renamed
        with atomic_path(day / name, fsync=self.fsync) as tmp:
            pq.write_table(table, tmp, compression="zstd")
        self.written_rows += table.num_rows
        self.files += 1

    def _drain(self) -> list:
        items = []
        while True:
            try:
                items.append(self._q.popleft())
            except IndexError:
                return items

    def _run(self) -> None:
        while True:
            stopping = self._stop.wait(self.flush_s)
            pending = self._drain()
            if pending:
                try:
                    self._write(pending)
                except Exception:  # a full disk must not kill the service
                    log.exception("run log: could not write %d batches", len(pending))
                    self.dropped_rows += sum(len(p[0]) for p in pending)
            if stopping:
                return

    def close(self, timeout_s: float = 5.0) -> None:
        """Write what is queued and stop the writer thread (waiting at most ``timeout_s``)."""
        self._stop.set()
        self._thread.join(timeout_s)


def _fsync_dir(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


# --------------------------------------------------------------------------- reading / export
def part_write_s(path: str | Path) -> float:
    """The time (epoch s, this host's clock) a part was written, from its name."""
    return int(Path(path).name.split("-")[1]) / 1000.0


def log_parts(folder: str | Path, since_s: float | None = None) -> list[Path]:
    """The closed Parquet parts of a run log in the order written: ``LOG/data/date=*/part-*``
    and, for logs written before that layout, ``LOG/part-*``. With ``since_s`` (epoch s), only
    parts written at or after it: whole days before it are not even listed."""
    folder = Path(folder)
    days = sorted((folder / DATA_DIR).glob("date=*"))
    if since_s is not None:
        first = time.strftime("date=%Y-%m-%d", time.gmtime(since_s))
        days = [d for d in days if d.name >= first]
    parts = [p for d in days for p in d.glob("part-*.parquet")]
    parts += folder.glob("part-*.parquet")
    if since_s is not None:
        parts = [p for p in parts if part_write_s(p) >= since_s]
    return sorted(parts, key=lambda p: p.name)


def read_meta(folder: str | Path) -> dict:
    """A run log's meta.json; a one-line InputError when the folder is not a run log."""
    meta_path = Path(folder) / "meta.json"
    if not meta_path.is_file():
        raise InputError("not a run log (no meta.json)", file=folder)
    try:
        return json.loads(meta_path.read_text())
    except json.JSONDecodeError as exc:
        raise InputError(f"meta.json is not valid JSON: {exc}", file=meta_path) from exc


def read_log(folder: str | Path, labels: bool = False):
    """(meta dict, DataFrame of every readable part in time order).

    ``health`` and ``<S>_status`` come as the runtime's integer codes (``HEALTH_OK``…,
    :mod:`fbgcomp.runtime.health` status codes) whichever way the log stored them, or with
    ``labels=True`` as their names (a pandas categorical, every name a category, in code order).
    """
    import pyarrow.parquet as pq  # noqa: PLC0415 - optional extra: pyarrow (the runtime extra)

    folder = Path(folder)
    meta = read_meta(folder)
    parts = log_parts(folder)
    if not parts:
        raise InputError("run log has no data files", file=folder)
    frames = [pq.read_table(p).to_pandas() for p in parts]
    df = pd.concat(frames, ignore_index=True).sort_values("time_s", kind="stable")
    df = df.reset_index(drop=True)
    health_names = list(meta.get("health_names") or HEALTH_NAMES)
    status_names = list(meta.get("status_names") or STATUS_NAMES)
    for col, names in [("health", health_names)] + [
        (f"{s}_status", status_names) for s in meta.get("sensor_names", [])
    ]:
        if col not in df:
            continue
        codes = _codes(df[col], names)
        if labels:
            known = (codes >= 0) & (codes < len(names))
            df[col] = pd.Categorical.from_codes(np.where(known, codes, -1), categories=pd.Index(names))
        else:
            df[col] = codes
    return meta, df


def export_campaign(
    log_folder: str | Path, out: str | Path, name: str | None = None, reference_csv: str | Path | None = None
):
    """Turn a run log into a campaign folder (``fbgcomp.io.campaign.write_campaign``).

    The campaign clock starts at the first logged frame. Only frames where every sensor was
    healthy (status OK, one peak in its window) go to ``fbg.csv`` and only frames with every
    probe known go to ``temperatures.csv``: a campaign holds finite numbers only. A production
    run has no measurement of the true TTP deviation; give one with ``reference_csv``
    (``time_s`` on the campaign clock, ``dx_um``, ``dy_um``, ``dz_um``). Without it the
    reference table holds the logged *model prediction*, labelled as such in campaign.yaml
    (``reference.instrument = "fbgcomp prediction, model <id>"``) so it is never mistaken for
    a measurement.
    """
    meta, df = read_log(log_folder)
    df = df.drop_duplicates("time_s", keep="first")
    t0 = float(df["time_s"].iloc[0])
    t = df["time_s"].to_numpy() - t0
    sensors, probes = meta["sensor_names"], meta["probe_names"]
    # a strain-free reference grating was logged as its sensor's gauge temperature <S>_ref_C
    # (relative to reference_lambda0_nm); it goes back to fbg.csv as the wavelength it read
    refs = {
        f"{d['name']}_ref": d
        for d in meta.get("sensors") or []
        if d.get("reference_lambda0_nm") is not None and f"{d['name']}_ref" in probes
    }
    heat = [p for p in meta.get("heat_inputs") or [] if p in probes]
    probes = [p for p in probes if p not in refs and p not in heat]
    ok = np.ones(len(df), bool)
    for s in sensors:
        ok &= (df[f"{s}_status"].to_numpy() == 0) & np.isfinite(df[f"{s}_nm"].to_numpy())
    for p in refs:
        ok &= np.isfinite(df[f"{p}_C"].to_numpy())
    if not ok.any():
        raise InputError("no frame in the log has every sensor healthy", file=log_folder)
    fbg = pd.DataFrame({"time_s": t[ok]})
    for s in sensors:
        fbg[f"{s}_nm"] = df[f"{s}_nm"].to_numpy()[ok]
    for p, d in refs.items():
        kw = {k: d[k] for k in ("thermo_optic_per_K", "fibre_cte_per_K") if d.get(k) is not None}
        fbg[f"{d['name']}_ref_nm"] = free_grating_wavelength_nm(
            df[f"{p}_C"].to_numpy()[ok], d["reference_lambda0_nm"], **kw
        )
    tok = np.ones(len(df), bool)
    for p in probes:
        tok &= np.isfinite(df[f"{p}_C"].to_numpy())
    temps = pd.DataFrame({"time_s": t[tok]})
    for p in probes:
        temps[f"{p}_C"] = df[f"{p}_C"].to_numpy()[tok]
    heat_table = None
    if heat:
        hok = np.all(np.isfinite(df[heat].to_numpy(float)), axis=1)
        heat_table = pd.DataFrame({"time_s": t[hok], **{h: df[h].to_numpy()[hok] for h in heat}})
    reference_spec = dict(meta.get("reference") or {"point": "TTP", "units": "um"})
    if reference_csv is not None:
        reference = pd.read_csv(reference_csv)
        missing = [c for c in ("time_s", "dx_um", "dy_um", "dz_um") if c not in reference.columns]
        if missing:
            raise InputError(f"reference lacks column(s) {', '.join(missing)}", file=reference_csv)
        reference_spec.setdefault("instrument", "laser interferometer")
    else:
        dev = df[[f"dev_{a}_um" for a in AXES]].to_numpy()
        rok = np.all(np.isfinite(dev), axis=1)
        if not rok.any():
            raise InputError(
                "the log holds no prediction to use as reference; give --reference", file=log_folder
            )
        reference = pd.DataFrame({"time_s": t[rok], **{f"{a}_um": dev[rok, j] for j, a in enumerate(AXES)}})
        reference_spec["instrument"] = f"fbgcomp prediction, model {meta.get('model_id')}"
    known = {p["name"]: p for p in (meta.get("temperature_probes") or [])}
    cmeta = {
        "name": name or Path(log_folder).name,
        "kind": meta.get("campaign_kind", "combined"),
        "description": f"exported from run log {Path(log_folder).name} (model {meta.get('model_id')})",
        "start": datetime.fromtimestamp(t0, tz=UTC),
        "sensors": meta["sensors"],
        "temperature_probes": [known.get(p, {"name": p, "location": "unknown"}) for p in probes],
        "reference": reference_spec,
    }
    campaign = Campaign.from_arrays(cmeta, fbg=fbg, temperatures=temps, reference=reference, heat=heat_table)
    write_campaign(campaign, out)
    return campaign


def ingest_run_log(
    log_folder: str | Path,
    dataset: str | Path,
    *,
    machine: str | None = None,
    zero_window_s: float = 10.0,
    rows_per_file: int = ROWS_PER_FILE,
    reference_csv: str | Path | None = None,
):
    """Ingest a run log into a Parquet dataset (:mod:`fbgcomp.io.dataset`) as one campaign.

    The log is first turned into a campaign by :func:`export_campaign` (healthy frames only;
    reference from ``reference_csv`` or, labelled as such, the logged prediction). Its machine
    is the log's ``meta.json`` ``machine`` key, else ``machine``. Returns the partition.
    """
    log_folder = Path(log_folder)
    log_meta = read_meta(log_folder)
    with tempfile.TemporaryDirectory(prefix=".fbgcomp-log-") as tmp:
        export_campaign(
            log_folder, Path(tmp) / log_folder.name, name=log_folder.name, reference_csv=reference_csv
        )
        campaign = read_campaign(Path(tmp) / log_folder.name)
        return ingest_campaign(
            campaign,
            dataset,
            machine=log_meta.get("machine") or machine,
            zero_window_s=zero_window_s,
            rows_per_file=rows_per_file,
            source=str(log_folder),
        )
