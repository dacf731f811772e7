"""On-disk cache of built twins: the mesh-independent arrays of :class:`~fbgcomp.structure.Twin`,
and of results derived from a twin that a fit needs again (:func:`cached_json`, in ``derived``
beside ``twin``: the physical model's thermal-map population and its heat prior's observer run).

Building the default twin (58 660 DOF) takes seconds (assembly, a banded Cholesky of the elastic
matrix, the rational-Krylov thermal reduction); every ``demo``, ``simulate``, ``fe-calibrate``
and ``compare --machine`` run needs the same twins again. A built twin's arrays are stored once
and reloaded in a fraction of the time.

Where
    ``platformdirs.user_cache_dir("fbgcomp")/twin`` (``~/.cache/fbgcomp/twin`` on Linux).
    The environment variable ``FBGCOMP_CACHE_DIR`` moves it (twins go to ``$FBGCOMP_CACHE_DIR/twin``);
    ``FBGCOMP_CACHE_DIR=off`` (or ``0``, ``no``, ``false``, ``none``, ``disabled``) turns the cache
    off: nothing is read or written. ``Twin(..., cache=False)`` does the same for one twin.

Key
    SHA-256 of the machine description's canonical content (its validated model dumped as JSON
    with sorted keys: the same machine read from another path, or from a YAML written
    differently, hits the same entry), the resolution, the number of thermal shifts, a format
    version and the code version: fbgcomp's version, a hash of every source file of the
    ``fbgcomp.structure`` package (an edit there invalidates every entry) and the versions of
    numpy, scipy and scikit-fem.

Format and safety
    One file per twin, ``<key>.twin``: a magic line, the SHA-256 of the payload, then the payload,
    an uncompressed numpy ``.npz`` of plain numeric arrays (sparse matrices as their CSR/CSC
    parts). It is read with ``allow_pickle=False``: no pickle is used, so loading an entry cannot
    run code. An entry whose magic, digest, format version, key or array set do not match (a
    truncated or corrupt file, an entry of an older format) is ignored and rebuilt; a cache that
    cannot be read or written never stops a build (the twin is built as without a cache).
    Entries are written to a temporary file in the same folder, flushed to disk and renamed over
    the target (:func:`fbgcomp.atomic.write_bytes`), so a reader sees a whole entry or none.
    Concurrent builders of the same twin (a test suite's workers, a fleet's processes) take an
    exclusive lock on ``locks/<key>.lock`` (:func:`build_lock`, POSIX ``flock``) for the look-up
    and the build: the first builds and stores, the others wait and load its entry. Where no
    lock can be taken each builds, writes a complete file, and the last rename wins. The
    folder keeps the most recently used entries, at most :data:`MAX_ENTRIES` (8) of them and
    :data:`MAX_BYTES` (1 GiB) in all, or the counts the environment variables
    ``FBGCOMP_CACHE_MAX_ENTRIES`` and ``FBGCOMP_CACHE_MAX_BYTES`` give (a machine builder with
    many machines, a test suite with dozens); delete the folder at any time to empty the cache.

Static halves
    ``static/<static key>`` (a few bytes, written atomically) names an entry that holds the static
    half of its twin (:func:`static_entry`, :func:`record_static`; the key: the description
    without its thermal section, the mesh and the code), so that a twin that differs from it in
    its thermal section only loads that half instead of assembling and factorising it. A record
    whose entry is gone is removed when pruning; one that names a missing or bad entry is a miss.
"""

from __future__ import annotations

import contextlib
import functools
import hashlib
import io
import json
import logging
import os
import time
from importlib import metadata
from pathlib import Path

import numpy as np
import platformdirs
import scipy.sparse as sp

import fbgcomp
from fbgcomp.atomic import write_bytes

log = logging.getLogger(__name__)

ENV = "FBGCOMP_CACHE_DIR"
OFF_VALUES = frozenset({"off", "0", "no", "false", "none", "disabled"})
FORMAT_VERSION = 1
MAGIC = b"FBGCOMP-TWIN-CACHE\n"
SUFFIX = ".twin"
# The folder keeps the most recently used entries, at most this many and this many bytes (the
# newest entry always stays): the default twin's entry is 64 MiB, a finer mesh's more.
MAX_ENTRIES = 8
MAX_BYTES = 1 << 30
ENV_MAX_ENTRIES = "FBGCOMP_CACHE_MAX_ENTRIES"
ENV_MAX_BYTES = "FBGCOMP_CACHE_MAX_BYTES"
LOCKS = "locks"
# Sub-folder of one small file per static half (the elasticity, its adjoint responses and the
# instruments' rows; fbgcomp.structure.twin._static_key): ``static/<static key>`` holds the key
# of an entry that contains it, so that a twin that differs from a cached one in its thermal
# description only (another film, heat source or ambient) takes that half from its entry.
STATIC = "static"
# A temporary file this old was left by a writer that died; it is removed when pruning.
_STALE_TMP_S = 3600.0


def cache_dir() -> Path | None:
    """Folder of the twin cache, or None when the cache is off (``FBGCOMP_CACHE_DIR=off``)."""
    value = os.environ.get(ENV)
    if value is not None and value.strip().lower() in OFF_VALUES:
        return None
    root = (
        Path(value.strip()).expanduser()
        if value and value.strip()
        else Path(platformdirs.user_cache_dir("fbgcomp"))
    )
    return root / "twin"


def _limit(env: str, default: int) -> int:
    """The positive integer of environment variable ``env``, else ``default`` (a value that is
    not one is logged and ignored: a cache setting never stops a build)."""
    value = os.environ.get(env, "").strip()
    if not value:
        return default
    try:
        n = int(value)
    except ValueError:
        n = 0
    if n < 1:
        log.warning("twin cache: %s=%r is not a positive integer; using %d", env, value[:40], default)
        return default
    return n


@contextlib.contextmanager
def build_lock(key: str, folder: Path):
    """Hold an exclusive lock on ``key``'s entry in ``folder`` (``locks/<key>.lock``, POSIX
    ``flock``) while it is looked up and built, so that concurrent builders of one twin build it
    once: the others wait, then find the entry. Where the lock cannot be taken (no ``fcntl``, a
    folder that cannot be written, a file system without locks) it yields without one: each
    builder builds, as before the lock (logged at debug level)."""
    try:
        import fcntl  # noqa: PLC0415 - POSIX only
    except ImportError:  # pragma: no cover - not POSIX
        yield
        return
    path = folder / LOCKS / f"{key}.lock"
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fh = open(path, "a+b")  # noqa: SIM115 - held open for the lock's lifetime
    except OSError as err:
        log.debug("twin cache: no build lock %s (%s)", path, err)
        yield
        return
    with fh:
        try:
            fcntl.flock(fh, fcntl.LOCK_EX)
        except OSError as err:
            log.debug("twin cache: no build lock %s (%s)", path, err)
            yield
            return
        try:
            yield
        finally:
            fcntl.flock(fh, fcntl.LOCK_UN)


@functools.lru_cache(maxsize=1)
def code_version() -> str:
    """Fbgcomp's version, a hash of the structure package's sources, and the numeric libraries'
    versions: anything that could change a twin's numbers for the same machine."""
    h = hashlib.sha256()
    here = Path(__file__).resolve().parent
    for path in sorted(here.glob("*.py")):
        h.update(path.name.encode() + b"\0" + path.read_bytes() + b"\0")
    libs = []
    for dist in ("numpy", "scipy", "scikit-fem"):
        try:
            libs.append(f"{dist}={metadata.version(dist)}")
        except metadata.PackageNotFoundError:
            libs.append(f"{dist}=?")
    return f"fbgcomp={fbgcomp.__version__};structure={h.hexdigest()};" + ";".join(libs)


def machine_content(machine) -> str:
    """Canonical JSON of a validated machine description (independent of its file and layout)."""
    # allow_nan: an infinite value (if a field allows one) is written Infinity, not refused,
    # and stays distinct from null.
    return json.dumps(machine.model_dump(mode="json"), sort_keys=True, separators=(",", ":"), allow_nan=True)


@functools.lru_cache(maxsize=1)
def package_version() -> str:
    """:func:`code_version` with a hash of every fbgcomp source file: anything that could change
    a result derived from a twin (:func:`cached_json`) for the same inputs."""
    h = hashlib.sha256(code_version().encode())
    root = Path(fbgcomp.__file__).resolve().parent
    for path in sorted(root.rglob("*.py")):
        h.update(str(path.relative_to(root)).encode() + b"\0" + path.read_bytes() + b"\0")
    return h.hexdigest()


def twin_key(machine, resolution: float, n_shifts: int) -> str:
    """Cache key (64 hex digits) of the twin of ``machine`` at this resolution and shift count."""
    ident = {
        "format": FORMAT_VERSION,
        "code": code_version(),
        "machine": machine_content(machine),
        "resolution": repr(float(resolution)),
        "n_shifts": int(n_shifts),
    }
    return hashlib.sha256(json.dumps(ident, sort_keys=True).encode()).hexdigest()


# ------------------------------------------------------------------------------ encoding
def _encode(arrays: dict) -> dict[str, np.ndarray]:
    """Flatten {name: ndarray | sparse matrix} into plain arrays (sparse: format, parts, shape)."""
    out = {}
    for name, value in arrays.items():
        if "." in name:
            raise ValueError(f"array name {name!r} may not contain '.'")
        if sp.issparse(value):
            fmt = "csc" if value.format == "csc" else "csr"
            m = value.asformat(fmt)
            out[f"{name}.{fmt}.data"] = m.data
            out[f"{name}.{fmt}.indices"] = m.indices
            out[f"{name}.{fmt}.indptr"] = m.indptr
            out[f"{name}.{fmt}.shape"] = np.asarray(m.shape, dtype=np.int64)
        else:
            a = np.asarray(value)
            if a.dtype == object:
                raise TypeError(f"{name}: object arrays are not cached")
            out[name] = a
    return out


def _decode(files: dict[str, np.ndarray]) -> dict:
    out: dict = {}
    parts: dict[tuple[str, str], dict[str, np.ndarray]] = {}
    for key, a in files.items():
        name, _, rest = key.partition(".")
        if not rest:
            out[name] = a
            continue
        fmt, _, part = rest.partition(".")
        if fmt not in ("csr", "csc") or part not in ("data", "indices", "indptr", "shape"):
            raise ValueError(f"unknown entry {key!r}")
        parts.setdefault((name, fmt), {})[part] = a
    for (name, fmt), p in parts.items():
        cls = sp.csc_matrix if fmt == "csc" else sp.csr_matrix
        shape = tuple(int(v) for v in p["shape"])
        out[name] = cls((p["data"], p["indices"], p["indptr"]), shape=shape)
    return out


def _entry_path(folder: Path, key: str) -> Path:
    return folder / f"{key}{SUFFIX}"


def dumps(key: str, arrays: dict) -> bytes:
    """The file content of an entry: magic, payload digest, payload (npz, no pickle)."""
    buf = io.BytesIO()
    files = _encode(arrays)
    files["__key__"] = np.frombuffer(key.encode("ascii"), dtype=np.uint8)
    files["__format__"] = np.asarray(FORMAT_VERSION, dtype=np.int64)
    np.savez(buf, allow_pickle=False, **files)
    payload = buf.getvalue()
    return MAGIC + hashlib.sha256(payload).digest() + payload


def loads(key: str, data: bytes, required=()) -> dict:
    """Arrays of an entry's content; ValueError if it is not a complete entry of this key."""
    head = len(MAGIC) + 32
    if len(data) < head or data[: len(MAGIC)] != MAGIC:
        raise ValueError("not a twin cache entry")
    payload = memoryview(data)[head:]
    if hashlib.sha256(payload).digest() != data[len(MAGIC) : head]:
        raise ValueError("digest mismatch (truncated or corrupt)")
    with np.load(io.BytesIO(payload), allow_pickle=False) as npz:
        files = {name: npz[name] for name in npz.files}
    if int(files.pop("__format__", -1)) != FORMAT_VERSION:
        raise ValueError("older cache format")
    if bytes(files.pop("__key__", np.zeros(0, np.uint8))).decode("ascii", "replace") != key:
        raise ValueError("entry of another key")
    arrays = _decode(files)
    missing = [name for name in required if name not in arrays]
    if missing:
        raise ValueError(f"entry lacks {missing}")
    return arrays


# ------------------------------------------------------------------------------ static halves
def static_entry(static_key: str, folder: Path | None = None) -> str | None:
    """The key of a cached entry that holds the static half ``static_key``, or None (cache off,
    none recorded, or its entry since pruned)."""
    folder = cache_dir() if folder is None else folder
    if folder is None:
        return None
    try:
        key = (folder / STATIC / static_key).read_text(encoding="ascii").strip()
    except (OSError, UnicodeDecodeError):
        return None
    return key if key and _entry_path(folder, key).is_file() else None


def record_static(static_key: str, key: str, folder: Path | None = None) -> None:
    """Record that entry ``key`` holds the static half ``static_key`` (atomic; a failed write is
    logged and the cache goes on without it)."""
    folder = cache_dir() if folder is None else folder
    if folder is None:
        return
    try:
        write_bytes(folder / STATIC / static_key, key.encode("ascii"))
    except OSError as err:
        log.debug("twin cache: cannot record the static half %s (%s)", static_key, err)


# ------------------------------------------------------------------------------ load / store
def load(key: str, required=(), folder: Path | None = None) -> dict | None:
    """The cached arrays of ``key``, or None (cache off, no entry, or a bad entry: logged)."""
    folder = cache_dir() if folder is None else folder
    if folder is None:
        return None
    path = _entry_path(folder, key)
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        return None
    except OSError as err:
        log.warning("twin cache: cannot read %s (%s); building", path, err)
        return None
    try:
        arrays = loads(key, data, required)
    except Exception as err:  # anything wrong with the file means: rebuild it
        log.warning("twin cache: ignoring %s (%s); rebuilding", path, err)
        return None
    with contextlib.suppress(OSError):
        os.utime(path)  # most recently used: the last to be pruned
    return arrays


def store(key: str, arrays: dict, folder: Path | None = None) -> Path | None:
    """Write the entry of ``key`` atomically; returns its path, or None (cache off or the write
    failed: logged, the caller goes on without the cache)."""
    folder = cache_dir() if folder is None else folder
    if folder is None:
        return None
    path = _entry_path(folder, key)
    try:
        write_bytes(path, dumps(key, arrays))
    except OSError as err:
        log.warning("twin cache: cannot write %s (%s); continuing without it", path, err)
        return None
    prune(folder)
    return path


def prune(folder: Path, keep: int | None = None, max_bytes: int | None = None) -> None:
    """Keep the most recently used entries, at most ``keep`` (default :data:`MAX_ENTRIES`) and
    ``max_bytes`` (default :data:`MAX_BYTES`; the newest entry always stays); remove temporary
    files of dead writers."""
    keep = _limit(ENV_MAX_ENTRIES, MAX_ENTRIES) if keep is None else keep
    max_bytes = _limit(ENV_MAX_BYTES, MAX_BYTES) if max_bytes is None else max_bytes
    try:
        entries = []
        now = time.time()
        for p in folder.iterdir():
            try:
                st = p.stat()
            except OSError:
                continue
            if p.name.endswith(SUFFIX) and not p.name.startswith("."):
                entries.append((st.st_mtime, st.st_size, p))
            elif p.name.startswith(".") and p.name.endswith(".tmp") and now - st.st_mtime > _STALE_TMP_S:
                p.unlink(missing_ok=True)
        entries.sort(key=lambda e: e[0], reverse=True)
        total = 0
        for i, (_, size, p) in enumerate(entries):
            total += size
            if i >= keep or (i > 0 and total > max_bytes):
                p.unlink(missing_ok=True)
        # the record of a static half whose entry is gone
        static = folder / STATIC
        if static.is_dir():
            for p in static.iterdir():
                if p.name.startswith("."):  # a dead writer's temporary file
                    if p.name.endswith(".tmp") and now - p.stat().st_mtime > _STALE_TMP_S:
                        p.unlink(missing_ok=True)
                    continue
                if static_entry(p.name, folder) is None:
                    p.unlink(missing_ok=True)
        # a lock of an entry that is gone, made long ago: no builder holds it any more
        locks = folder / LOCKS
        if locks.is_dir():
            for p in locks.iterdir():
                key = p.name.removesuffix(".lock")
                if not _entry_path(folder, key).exists() and now - p.stat().st_mtime > _STALE_TMP_S:
                    p.unlink(missing_ok=True)
    except OSError as err:
        log.debug("twin cache: pruning %s failed (%s)", folder, err)


# ------------------------------------------------------------------------------ derived results
#: Sub-folder (beside ``twin``) of the results derived from a twin (:func:`cached_json`).
DERIVED = "derived"


def _to_json(value):
    """``value`` with every ndarray as ``{"__ndarray__": nested list, "dtype": str, "shape": list}``
    (the shape for arrays with an empty axis, which a nested list does not keep)."""
    if isinstance(value, np.ndarray):
        if value.dtype == object:
            raise TypeError("object arrays are not cached")
        return {"__ndarray__": value.tolist(), "dtype": value.dtype.str, "shape": list(value.shape)}
    if isinstance(value, dict):
        return {str(k): _to_json(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_to_json(v) for v in value]
    if isinstance(value, np.generic):  # a numpy scalar: its Python number (json refuses np.int64)
        return value.item()
    return value


def _from_json(value):
    if isinstance(value, dict):
        if "__ndarray__" in value:
            a = np.asarray(value["__ndarray__"], dtype=np.dtype(value["dtype"]))
            return a.reshape(value["shape"])
        return {k: _from_json(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_from_json(v) for v in value]
    return value


def array_digest(*arrays) -> str:
    """SHA-256 of arrays' dtypes, shapes and values: data in a :func:`cached_json` identity."""
    h = hashlib.sha256()
    for a in arrays:
        a = np.ascontiguousarray(a)
        h.update(f"{a.dtype.str}{a.shape}".encode() + b"\0" + a.tobytes())
    return h.hexdigest()


def cached_json(kind: str, ident, compute):
    """``compute()``'s result, kept on disk per ``kind`` and ``ident`` beside the twins (a
    twin-derived result a fit needs again for the same machine and sensors: the thermal map's
    scenario population). ``ident`` is JSON-able and names every input the result depends on
    (a twin's by its cache key); the key adds :func:`package_version`, so any edit of fbgcomp
    invalidates every entry. The result is a dict or list of JSON values and ndarrays, written
    as JSON (floats exactly, ndarrays with their dtype; tuples come back as lists, numpy
    scalars as Python numbers, keys as strings) in an entry of the twins' format (digest, no
    pickle, atomic, locked while computed, pruned like them); a cache that is off, unreadable
    or unwritable, or a result JSON cannot hold, only means the result is computed."""
    folder = cache_dir()
    ident_json = json.dumps(ident, sort_keys=True, allow_nan=True)
    if folder is None:
        return compute()
    folder = folder.parent / DERIVED
    key = hashlib.sha256(
        json.dumps(
            {"format": FORMAT_VERSION, "kind": kind, "code": package_version(), "ident": ident_json},
            sort_keys=True,
        ).encode()
    ).hexdigest()
    with build_lock(key, folder):
        arrays = load(key, ("json",), folder)
        if arrays is not None:
            try:
                return _from_json(json.loads(arrays["json"].tobytes().decode()))
            except ValueError as err:
                log.warning("twin cache: ignoring %s entry %s (%s); computing", kind, key[:12], err)
        value = compute()
        try:
            text = json.dumps(_to_json(value), allow_nan=True)
        except (TypeError, ValueError) as err:  # not a value JSON holds: computed each time
            log.warning("twin cache: %s result not kept (%s)", kind, err)
            return value
        store(key, {"json": np.frombuffer(text.encode(), dtype=np.uint8)}, folder)
        return value
