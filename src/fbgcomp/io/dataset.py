"""Campaigns as one partitioned Parquet dataset: storage for fleets and months of records.

Layout (Hive partitioning, so pandas, DuckDB, pyarrow and Dask all read it as one table with
``machine`` and ``campaign`` columns)::

    DATASET/_campaigns.json                           index: one entry per (machine, campaign)
    DATASET/machine=<m>/campaign=<c>/part-00000.parquet
    DATASET/machine=<m>/campaign=<c>/part-00001.parquet ...

Rows are the campaign's *aligned raw* samples, one per kept reference sample (the reference
instrument's clock, see :meth:`fbgcomp.io.campaign.Campaign.aligned`)::

    time_s      reference clock, s
    <S>_nm      Bragg wavelength of sensor S, nm          (same names as fbg.csv and the run log)
    <P>_C       temperature of probe P, degC              (same names as temperatures.csv and the run log)
    dx_um, dy_um, dz_um   TTP displacement as measured (NOT minus its zero), um
    fx_N, fy_N, fz_N      applied forces, N (only when the campaign has loads.csv; NaN outside it)

Nothing is derived at ingest time except the alignment, so any feature set can be fitted later.
The zero state of each signal (mean over its first ``zero_window_s`` seconds on its *own* clock,
which cannot be recomputed from the aligned rows) is stored per campaign in the metadata, with
the whole ``campaign.yaml`` content: in every Parquet file's key-value metadata (key
``fbgcomp.io.campaign``, so each partition describes itself) and in the ``_campaigns.json`` sidecar
(an index for quick listing, rebuilt from the files when stale). Files and folders starting
with ``_`` or ``.`` are ignored by pyarrow/pandas/Dask discovery; with DuckDB read
``DATASET/machine=*/campaign=*/*.parquet`` with ``hive_partitioning = true``.

Writes are atomic: a campaign's files are written into ``DATASET/.ingest.tmp-<token>/``, fsynced,
and the folder is renamed to ``machine=<m>/campaign=<c>`` (an existing one is swapped out by
rename and removed, :func:`fbgcomp.atomic.staged_dir`); the sidecar is written with
:func:`fbgcomp.atomic.write_json`. A crash leaves at worst an ignored ``.ingest.*`` folder, never
a half-written partition.

pyarrow (the ``scale`` extra) is imported only where Parquet is read or written, so detecting a
dataset path works in a minimal install.
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from urllib.parse import quote

import numpy as np
import pandas as pd

from fbgcomp.atomic import json_safe, staged_dir, write_json
from fbgcomp.errors import InputError
from fbgcomp.io.campaign import (
    LOAD_COLUMNS,
    REFERENCE_COLUMNS,
    CampaignMeta,
    check_sensors_match,
    read_campaign,
)

try:
    import fcntl
except ImportError:  # not POSIX: the files stay the source of truth (open_dataset)
    fcntl = None  # type: ignore[assignment]  # mypy cannot type an optional module's None fallback

__all__ = [
    "DATASET_FORMAT",
    "INDEX_FILE",
    "LOAD_COLUMNS",
    "METADATA_KEY",
    "REFERENCE_COLUMNS",
    "Dataset",
    "Partition",
    "accumulate_partition_file",
    "ingest",
    "ingest_campaign",
    "is_dataset",
    "is_run_log",
    "open_dataset",
    "partition_arrays",
    "partition_design",
]

DATASET_FORMAT = "fbgcomp-dataset"
DATASET_VERSION = 1
INDEX_FILE = "_campaigns.json"
METADATA_KEY = b"fbgcomp.campaign"
DEFAULT_MACHINE = "default"
#: Rows per Parquet file: one file is one task of a distributed fit, so it bounds a worker's
#: work unit; reading goes by row group, so it does not bound memory.
ROWS_PER_FILE = 1_000_000
#: Rows per row group = rows per batch when a partition is streamed.
ROW_GROUP_ROWS = 100_000


# --------------------------------------------------------------------------------------------
# Paths
# --------------------------------------------------------------------------------------------


def _segment(key: str, value: str) -> str:
    # Hive partitions are URI-encoded path segments (pyarrow decodes them by default).
    return f"{key}={quote(str(value), safe='')}"


def _partition_dir(root: Path, machine: str, campaign: str) -> Path:
    return root / _segment("machine", machine) / _segment("campaign", campaign)


def is_dataset(path) -> bool:
    """True when ``path`` is a folder made by :func:`ingest` (no Parquet needed to tell)."""
    p = Path(path)
    if not p.is_dir():
        return False
    if (p / INDEX_FILE).is_file():
        return True
    return any(child.is_dir() for child in p.glob("machine=*"))


def is_run_log(path) -> bool:
    """True when ``path`` is a runtime run-log folder (``meta.json`` + ``part-*.parquet``)."""
    p = Path(path)
    meta = p / "meta.json"
    if not meta.is_file():
        return False
    try:
        return json.loads(meta.read_text(encoding="utf-8")).get("format") == "fbgcomp-runlog"
    except (OSError, ValueError, AttributeError):
        return False


# --------------------------------------------------------------------------------------------
# Metadata
# --------------------------------------------------------------------------------------------


@dataclass
class Partition:
    """One (machine, campaign) partition: where its files are and what is needed to fit on it."""

    machine: str
    campaign: str
    path: Path  # the partition folder
    files: list  # file names inside it, in row order
    n_rows: int
    sensor_names: list
    probe_names: list
    wavelength_zero_nm: np.ndarray
    temperature_zero_C: np.ndarray
    reference_zero_um: np.ndarray
    zero_window_s: float
    meta: dict  # campaign.yaml content (JSON-safe)
    dropped: dict = field(default_factory=dict)
    columns: list = field(default_factory=list)
    source: str | None = None
    ingested_utc: str | None = None

    @property
    def kind(self) -> str:
        """The campaign's kind (thermal, static, combined) from its campaign.yaml."""
        return self.meta.get("kind", "")

    @property
    def file_paths(self) -> list[Path]:
        """The partition's Parquet files, in row order."""
        return [self.path / f for f in self.files]

    def sensors(self):
        """``SensorSpec`` objects from the stored campaign.yaml."""
        return list(CampaignMeta.model_validate(self.meta).sensors)

    def to_entry(self) -> dict:
        """The partition as its JSON-safe index entry (also stored in each Parquet file)."""
        return {
            "machine": self.machine,
            "campaign": self.campaign,
            "path": f"{_segment('machine', self.machine)}/{_segment('campaign', self.campaign)}",
            "files": list(self.files),
            "n_rows": int(self.n_rows),
            "sensor_names": list(self.sensor_names),
            "probe_names": list(self.probe_names),
            "wavelength_zero_nm": [float(v) for v in self.wavelength_zero_nm],
            "temperature_zero_C": [float(v) for v in self.temperature_zero_C],
            "reference_zero_um": [float(v) for v in self.reference_zero_um],
            "zero_window_s": float(self.zero_window_s),
            "meta": self.meta,
            "dropped": self.dropped,
            "columns": list(self.columns),
            "source": self.source,
            "ingested_utc": self.ingested_utc,
        }

    @classmethod
    def from_entry(cls, root: Path, e: dict, where=None) -> Partition:
        """The partition an index entry describes, in dataset ``root``; InputError naming
        ``where`` (default ``root``) when the entry is malformed."""
        try:
            return cls(
                machine=str(e["machine"]),
                campaign=str(e["campaign"]),
                path=_partition_dir(root, e["machine"], e["campaign"]),
                files=[str(f) for f in e["files"]],
                n_rows=int(e["n_rows"]),
                sensor_names=list(e["sensor_names"]),
                probe_names=list(e["probe_names"]),
                wavelength_zero_nm=np.asarray(e["wavelength_zero_nm"], dtype=float),
                temperature_zero_C=np.asarray(e["temperature_zero_C"], dtype=float),
                reference_zero_um=np.asarray(e["reference_zero_um"], dtype=float),
                zero_window_s=float(e["zero_window_s"]),
                meta=dict(e["meta"]),
                dropped=dict(e.get("dropped") or {}),
                columns=list(e.get("columns") or []),
                source=e.get("source"),
                ingested_utc=e.get("ingested_utc"),
            )
        except (KeyError, TypeError, ValueError) as exc:
            raise InputError(f"malformed partition metadata: {exc}", file=where or root) from None


@dataclass
class Dataset:
    """A dataset folder: its partitions in (machine, campaign) order."""

    path: Path
    partitions: list

    def partition(self, machine: str, campaign: str) -> Partition:
        """The partition of ``machine`` and ``campaign`` (KeyError if there is none)."""
        for p in self.partitions:
            if p.machine == machine and p.campaign == campaign:
                return p
        raise KeyError((machine, campaign))

    @property
    def n_rows(self) -> int:
        """Rows over all partitions."""
        return sum(p.n_rows for p in self.partitions)

    def to_pandas(self, machine=None, campaign=None, columns=None):
        """Rows of the whole dataset (or one machine / campaign) as a DataFrame with ``machine``
        and ``campaign`` columns. Materialises the rows: for big data, stream instead."""
        frames = []
        for p in self.partitions:
            if (machine is not None and p.machine != machine) or (
                campaign is not None and p.campaign != campaign
            ):
                continue
            for f in p.file_paths:
                frame = _read_table(f, columns).to_pandas()
                frame.insert(0, "campaign", p.campaign)
                frame.insert(0, "machine", p.machine)
                frames.append(frame)
        if not frames:
            raise InputError("no partition matches", file=self.path)
        return pd.concat(frames, ignore_index=True)


def _read_table(path, columns=None):
    import pyarrow.parquet as pq  # noqa: PLC0415 - pyarrow is the optional scale extra

    try:
        return pq.read_table(path, columns=columns)
    except (OSError, ValueError) as exc:
        raise InputError(f"cannot read Parquet file: {exc}", file=path) from None


def _file_entry(path: Path) -> dict:
    import pyarrow.parquet as pq  # noqa: PLC0415 - pyarrow is the optional scale extra

    try:
        metadata = pq.read_schema(path).metadata or {}
    except (OSError, ValueError) as exc:
        raise InputError(f"cannot read Parquet file: {exc}", file=path) from None
    if METADATA_KEY not in metadata:
        raise InputError(
            f"Parquet file lacks the {METADATA_KEY.decode()} metadata: not written by fbgcomp ingest",
            file=path,
        )
    return json.loads(metadata[METADATA_KEY])


def open_dataset(path) -> Dataset:
    """List a dataset's partitions (index first; partitions missing from it, e.g. after a
    crash between the folder rename and the index update, are described from their files)."""
    root = Path(path)
    if not root.is_dir():
        raise InputError("dataset folder not found", file=root)
    index = _read_index(root)
    by_path = {e.get("path"): e for e in index.get("campaigns", [])}
    partitions = []
    for mdir in sorted(root.glob("machine=*")):
        if not mdir.is_dir():
            continue
        for cdir in sorted(mdir.glob("campaign=*")):
            if not cdir.is_dir():
                continue
            rel = f"{mdir.name}/{cdir.name}"
            entry = by_path.get(rel)
            on_disk = sorted(f.name for f in cdir.glob("part-*.parquet"))
            if entry is None or sorted(entry.get("files", [])) != on_disk:
                if not on_disk:
                    continue
                entry = _file_entry(cdir / on_disk[0])
            partitions.append(Partition.from_entry(root, entry, where=cdir))
    if not partitions:
        raise InputError("no partition (machine=*/campaign=*/part-*.parquet) in the dataset", file=root)
    return Dataset(root, partitions)


def _read_index(root: Path) -> dict:
    file = root / INDEX_FILE
    if not file.is_file():
        return {}
    try:
        data = json.loads(file.read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        raise InputError(f"unreadable dataset index: {exc}", file=file) from None
    if not isinstance(data, dict) or data.get("format") != DATASET_FORMAT:
        raise InputError(
            f"not an fbgcomp dataset index (field 'format' must be {DATASET_FORMAT!r})",
            file=file,
            column="field format",
        )
    if int(data.get("version", 0)) > DATASET_VERSION:
        raise InputError(
            f"dataset version {data.get('version')} is newer than this fbgcomp "
            f"supports ({DATASET_VERSION}); upgrade fbgcomp",
            file=file,
            column="field version",
        )
    return data


def _update_index(root: Path, partition: Partition) -> None:
    # Read-modify-write under an exclusive lock so that concurrent ingests into one dataset
    # do not lose each other's entries (the hidden lock file is ignored by every reader).
    with open(root / ".index.lock", "a") as lock:
        if fcntl is not None:
            fcntl.flock(lock.fileno(), fcntl.LOCK_EX)
        index = _read_index(root) or {"format": DATASET_FORMAT, "version": DATASET_VERSION, "campaigns": []}
        entry = partition.to_entry()
        entries = [e for e in index.get("campaigns", []) if e.get("path") != entry["path"]]
        entries.append(entry)
        entries.sort(key=lambda e: (e["machine"], e["campaign"]))
        index.update({"format": DATASET_FORMAT, "version": DATASET_VERSION, "campaigns": entries})
        write_json(root / INDEX_FILE, index)


# --------------------------------------------------------------------------------------------
# Ingest
# --------------------------------------------------------------------------------------------


def ingest_campaign(
    campaign,
    dataset,
    *,
    machine: str | None = None,
    zero_window_s: float = 10.0,
    rows_per_file: int = ROWS_PER_FILE,
    row_group_rows: int = ROW_GROUP_ROWS,
    source: str | None = None,
) -> Partition:
    """Write one campaign (a :class:`~fbgcomp.io.campaign.Campaign`) as a partition, atomically.

    The machine is ``campaign.yaml``'s ``machine`` key when present, else ``machine``, else
    ``"default"``. An existing partition of the same machine and campaign is replaced whole.
    """
    import pyarrow as pa  # noqa: PLC0415 - pyarrow is the optional scale extra
    import pyarrow.parquet as pq  # noqa: PLC0415 - as above

    if rows_per_file < 1 or row_group_rows < 1:
        raise ValueError("rows_per_file and row_group_rows must be at least 1")
    root = Path(dataset)
    if root.exists() and not root.is_dir():
        raise InputError("cannot write a dataset: a file of that name exists", file=root)
    if root.is_dir() and any(root.iterdir()) and not is_dataset(root):
        raise InputError(
            "refusing to write a dataset into a folder that is not one "
            f"(no {INDEX_FILE}, no machine=* folders)",
            file=root,
        )
    meta_extra = campaign.meta.model_extra or {}
    machine_name = str(meta_extra.get("machine") or machine or DEFAULT_MACHINE)
    aligned = campaign.aligned(zero_window_s=zero_window_s)

    # The raw reference as measured (the aligned one is already minus its zero): bit-identical
    # to what the in-process fit subtracts the zero from.
    ref_t = campaign.reference["time_s"].to_numpy()
    first = int(np.searchsorted(ref_t, aligned.time_s[0], side="left"))
    raw_ref = campaign.reference[list(REFERENCE_COLUMNS)].to_numpy(dtype=np.float64)
    raw_ref = raw_ref[first : first + len(aligned)]

    columns = {"time_s": aligned.time_s}
    for j, s in enumerate(aligned.sensor_names):
        columns[f"{s}_nm"] = aligned.wavelength_nm[:, j]
    for j, p in enumerate(aligned.probe_names):
        columns[f"{p}_C"] = aligned.temperature_C[:, j]
    for j, c in enumerate(REFERENCE_COLUMNS):
        columns[c] = raw_ref[:, j]
    if aligned.loads_N is not None:
        for j, c in enumerate(LOAD_COLUMNS):
            columns[c] = aligned.loads_N[:, j]
    n = len(aligned)
    n_files = max(1, math.ceil(n / rows_per_file))
    files = [f"part-{i:05d}.parquet" for i in range(n_files)]
    partition = Partition(
        machine=machine_name,
        campaign=campaign.meta.name,
        path=_partition_dir(root, machine_name, campaign.meta.name),
        files=files,
        n_rows=n,
        sensor_names=list(aligned.sensor_names),
        probe_names=list(aligned.probe_names),
        wavelength_zero_nm=aligned.wavelength_zero_nm,
        temperature_zero_C=aligned.temperature_zero_C,
        reference_zero_um=aligned.reference_zero_um,
        zero_window_s=aligned.zero_window_s,
        meta=json_safe(campaign.meta.model_dump(mode="json")),
        dropped=json_safe({k: (list(v) if isinstance(v, tuple) else v) for k, v in aligned.dropped.items()}),
        columns=list(columns),
        source=source or (None if campaign.path is None else str(campaign.path)),
        ingested_utc=datetime.now(UTC).isoformat(timespec="seconds"),
    )
    kv = {METADATA_KEY: json.dumps(partition.to_entry(), allow_nan=False).encode()}
    schema = pa.schema([(name, pa.float64()) for name in columns], metadata=kv)

    root.mkdir(parents=True, exist_ok=True)
    with staged_dir(partition.path, staging_parent=root, staging_name=".ingest") as staging:
        for i, name in enumerate(files):
            lo, hi = i * rows_per_file, min(n, (i + 1) * rows_per_file)
            table = pa.table({k: v[lo:hi] for k, v in columns.items()}, schema=schema)
            pq.write_table(table, staging / name, row_group_size=row_group_rows, compression="zstd")
            with open(staging / name, "rb") as fh:
                os.fsync(fh.fileno())
    _update_index(root, partition)
    return partition


def ingest(
    sources,
    dataset,
    *,
    machine: str | None = None,
    zero_window_s: float = 10.0,
    rows_per_file: int = ROWS_PER_FILE,
    progress=None,
) -> list:
    """Ingest campaign folders into ``dataset``; returns their partitions.

    A runtime run log is not a campaign (it has no measurement of the true TTP deviation): it
    is refused here and ingested by :func:`fbgcomp.runtime.log.ingest_run_log`, which turns it
    into one first (``fbgcomp ingest`` takes both).
    """
    out = []
    for src in sources:
        src = Path(src)
        if is_run_log(src):
            raise InputError(
                "a runtime run log, not a campaign folder: ingest it with "
                "fbgcomp ingest or fbgcomp.runtime.log.ingest_run_log",
                file=src,
            )
        part = ingest_campaign(
            read_campaign(src),
            dataset,
            machine=machine,
            zero_window_s=zero_window_s,
            rows_per_file=rows_per_file,
        )
        out.append(part)
        if progress is not None:
            progress(part)
    return out


# --------------------------------------------------------------------------------------------
# Reading for a fit: stream one file of a partition in row groups
# --------------------------------------------------------------------------------------------


def partition_arrays(file, sensor_names, probe_names, batch_rows: int = ROW_GROUP_ROWS):
    """Yield ``(wavelength_nm (m, S), temperature_C (m, P), reference_um (m, 3))`` batches of
    one Parquet file, columns in the given sensor and probe order; reference as stored (raw)."""
    import pyarrow.parquet as pq  # noqa: PLC0415 - pyarrow is the optional scale extra

    wl_cols = [f"{s}_nm" for s in sensor_names]
    t_cols = [f"{p}_C" for p in probe_names]
    cols = wl_cols + t_cols + list(REFERENCE_COLUMNS)
    try:
        pf = pq.ParquetFile(file)
    except (OSError, ValueError) as exc:
        raise InputError(f"cannot read Parquet file: {exc}", file=file) from None
    have = set(pf.schema_arrow.names)
    missing = [c for c in cols if c not in have]
    if missing:
        raise InputError(f"missing column(s) {', '.join(missing)}", file=file, column=missing[0])
    for batch in pf.iter_batches(batch_size=batch_rows, columns=cols):
        arr = np.column_stack(
            [batch.column(i).to_numpy(zero_copy_only=False) for i in range(len(cols))]
        ).astype(np.float64, copy=False)
        s, p = len(wl_cols), len(t_cols)
        yield arr[:, :s], arr[:, s : s + p], arr[:, s + p :]


def check_partition(model, partition: Partition) -> None:
    """Raise InputError when a partition lacks what the model needs (as ``check_compatible``)."""
    where = partition.path
    check_sensors_match(model.sensors_, partition.sensors(), where, "partition")
    for p in model.probe_names_:
        if p not in partition.probe_names:
            raise InputError(
                f"model needs temperature probe {p} which the partition does not have",
                file=where,
                column="field temperature_probes",
            )
    if abs(float(partition.zero_window_s) - float(model.zero_window_s)) > 1e-12:
        raise InputError(
            f"the partition was ingested with a {partition.zero_window_s:g} s zero "
            f"window but the fit asks for {model.zero_window_s:g} s: fit with "
            f"--zero-window {partition.zero_window_s:g} or ingest again with "
            f"--zero-window {model.zero_window_s:g}",
            file=where,
            column="option --zero-window",
        )


def accumulate_partition_file(
    model, partition: Partition, file, acc=None, *, second_pass: bool = False, weight=None
):
    """Stream one file of a partition into ``acc`` (default: a fresh accumulator of ``model``,
    which must have had :meth:`~fbgcomp.models.base.MRAModel.new_accumulator` called); returns it.

    First pass (default): rows enter the factor. ``second_pass=True``: after
    ``acc.begin_hac()`` on the factor of *every* row, the same rows enter the
    autocorrelation statistics (:meth:`~fbgcomp.models.regression.QRAccumulator.update_hac`), with
    the row ``weight`` the first pass gave them (for pooled campaigns).
    """
    if acc is None:
        acc = model.new_accumulator(model.sensors_)
    for design, ref in partition_design(model, partition, file):
        if second_pass:
            acc.update_hac(design, ref, weights=weight)
        else:
            acc.update(design, ref, weights=weight)
    return acc


def partition_design(model, partition: Partition, file):
    """Yield ``(design (m, 1 + terms), reference_um (m, 3))`` batches of one partition file for
    ``model`` (after :meth:`~fbgcomp.models.base.MRAModel.new_accumulator`), both zeroed as the
    campaign was at ingest."""
    s_idx = [partition.sensor_names.index(s) for s in model.sensor_names]
    p_idx = [partition.probe_names.index(p) for p in model.probe_names_]
    w0 = partition.wavelength_zero_nm[s_idx]
    t0 = partition.temperature_zero_C[p_idx]
    r0 = partition.reference_zero_um
    for w, t, ref in partition_arrays(file, model.sensor_names, model.probe_names_):
        yield model.design_from_arrays(w, t, w0, t0), ref - r0
