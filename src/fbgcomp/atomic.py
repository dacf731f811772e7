"""Atomic writes: a reader sees the old file or folder, or the complete new one, never a half.

Files are written to a temporary name in the same folder (:func:`atomic_path`), flushed to
disk, then renamed over the target. Folders are built in a staging folder beside the target
(:func:`staged_dir`) and swapped in with :func:`replace_dir`, which puts the old folder back if
the swap fails.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import secrets
import shutil
from collections.abc import Iterator
from pathlib import Path

import numpy as np


def json_safe(obj):
    """Undefined numbers (NaN, ±inf: e.g. "% of peak" of an axis that never moved) become null."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {str(k): json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_safe(v) for v in obj]
    if isinstance(obj, np.generic):
        return json_safe(obj.item())
    if isinstance(obj, np.ndarray):
        return json_safe(obj.tolist())
    return obj


@contextlib.contextmanager
def atomic_path(
    target, *, mode: int = 0o600, prefix: str | None = None, suffix: str = ".tmp", fsync: bool = True
) -> Iterator[Path]:
    """Yield a new, empty temporary file beside ``target`` to write by name; on success it
    replaces ``target``.

    The temporary file is created exclusively with permissions ``mode`` (less the umask) in
    ``target``'s folder (which must exist), named ``<prefix><hex><suffix>``; ``prefix`` defaults
    to ``.<target name>.``, so the name starts with a dot and ends with ``.tmp``: tools that read
    a folder (Parquet readers, asyncua's trust store with ``prefix=".incoming-"``: hex digits
    never spell "der" or "pem") skip it. When the ``with`` block ends normally the file is
    fsynced (unless ``fsync`` is False) and renamed over ``target`` with :func:`os.replace`; when
    it raises, the file is removed, ``target`` is left as it was and the exception propagates.
    """
    target = Path(target)
    if prefix is None:
        prefix = f".{target.name}."
    while True:
        tmp = target.with_name(f"{prefix}{secrets.token_hex(4)}{suffix}")
        try:
            os.close(os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, mode))
            break
        except FileExistsError:
            continue
    try:
        yield tmp
        if fsync:
            fd = os.open(tmp, os.O_RDWR)
            try:
                os.fsync(fd)
            finally:
                os.close(fd)
        os.replace(tmp, target)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def write_bytes(path, data: bytes, check=None, *, mode: int = 0o600, prefix: str | None = None) -> Path:
    """Write ``data`` to ``path`` atomically (temporary file, fsync, rename), creating its folder.

    ``check``, if given, is called with the temporary file's path once it is completely
    written; if it raises, the temporary file is removed, ``path`` is left as it was and the
    exception propagates (write, validate by reading back, then replace). ``mode`` and
    ``prefix``: as for :func:`atomic_path`.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path, mode=mode, prefix=prefix) as tmp:
        with open(tmp, "wb") as fh:
            fh.write(data)
        if check is not None:
            check(tmp)
    return path


def write_json(path, data, check=None) -> Path:
    """Write JSON atomically; non-finite numbers are written as null (JSON has no NaN).
    ``check``: as for :func:`write_bytes`."""
    text = json.dumps(json_safe(data), indent=1, allow_nan=False) + "\n"
    return write_bytes(path, text.encode("utf-8"), check=check)


def replace_dir(staging, target, retired) -> None:
    """Move the complete folder ``staging`` to ``target``.

    An existing ``target`` is first renamed to ``retired`` (same file system) and restored if the
    second rename fails, then deleted; so ``target`` is always either the old or the new folder.
    """
    staging, target, retired = Path(staging), Path(target), Path(retired)
    if not target.exists():
        os.rename(staging, target)
        return
    os.rename(target, retired)
    try:
        os.rename(staging, target)
    except BaseException:
        os.rename(retired, target)
        raise
    shutil.rmtree(retired, ignore_errors=True)


@contextlib.contextmanager
def staged_dir(target, staging_parent=None, staging_name=None) -> Iterator[Path]:
    """Build the folder ``target`` atomically: yields an empty staging folder (in
    ``staging_parent``, default beside ``target``, so on the same file system); when the block
    ends without an exception the staging folder replaces ``target`` (:func:`replace_dir`),
    else it is removed and ``target`` is left as it was."""
    target = Path(target)
    parent = Path(staging_parent) if staging_parent is not None else target.parent
    parent.mkdir(parents=True, exist_ok=True)
    token = secrets.token_hex(6)
    name = staging_name or f".{target.name}"
    staging = parent / f"{name}.tmp-{token}"
    staging.mkdir()
    try:
        yield staging
        target.parent.mkdir(parents=True, exist_ok=True)
        replace_dir(staging, target, parent / f"{name}.old-{token}")
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
