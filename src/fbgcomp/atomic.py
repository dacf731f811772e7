"""Atomic writes: a reader sees the old file or folder, or the complete new one, never a half.

Files are written to a temporary name in the same folder, flushed to disk, then renamed over the
target. Folders are built in a staging folder beside the target and swapped in with
:func:`replace_dir`, which puts the old folder back if the swap fails.
"""

from __future__ import annotations

import json
import math
import os
import shutil
import tempfile
from pathlib import Path


def json_safe(obj):
    """Undefined numbers (NaN, ±inf: e.g. "% of peak" of an axis that never moved) become null."""
    import numpy as np

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


def write_bytes(path, data: bytes, check=None) -> Path:
    """Write ``data`` to ``path`` atomically (temporary file, fsync, rename).

    ``check``, if given, is called with the temporary file's path once it is complete on disk;
    if it raises, the temporary file is removed, ``path`` is left as it was and the exception
    propagates (write, validate by reading back, then replace).
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        if check is not None:
            check(Path(tmp))
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
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
