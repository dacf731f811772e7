"""Progress of long CLI commands on stderr (tqdm): named stages and per-item bars.

Shown only when stderr is a terminal, or when forced with ``FBGCOMP_PROGRESS=1``; never with
``FBGCOMP_PROGRESS=0`` or ``fbgcomp --quiet``. Progress never goes to stdout, so tables and
JSON printed there are the same with and without it.
"""

from __future__ import annotations

import os
import sys
from contextlib import contextmanager

from tqdm import tqdm

#: Set by ``fbgcomp --quiet``.
QUIET = False
_ON = ("1", "on", "yes", "true", "force")
_OFF = ("0", "off", "no", "false", "quiet")


def enabled() -> bool:
    """Whether progress is shown: ``FBGCOMP_PROGRESS`` (1/0) decides, else ``--quiet``, else
    whether stderr is a terminal."""
    env = os.environ.get("FBGCOMP_PROGRESS", "").strip().lower()
    if env in _OFF or QUIET:
        return False
    if env in _ON:
        return True
    return _terminal()


def _terminal() -> bool:
    try:
        return sys.stderr.isatty()
    except (AttributeError, ValueError):
        return False


def track(iterable, desc: str, unit: str = "item", total: int | None = None):
    """``iterable`` with a bar ``desc`` on stderr (when :func:`enabled`); forced into a file
    or a pipe, one line ``desc: N/total`` per item instead of redrawn bars."""
    if enabled() and not _terminal():
        return _lines(iterable, desc, unit, total)
    return tqdm(
        iterable,
        desc=desc,
        unit=unit,
        total=total,
        disable=not enabled(),
        leave=False,
        file=sys.stderr,
        dynamic_ncols=True,
    )


def _lines(iterable, desc, unit, total):
    total = total if total is not None else (len(iterable) if hasattr(iterable, "__len__") else "?")
    for i, item in enumerate(iterable, 1):
        print(f"  {desc}: {unit} {i}/{total}", file=sys.stderr, flush=True)
        yield item


@contextmanager
def stages(command: str, total: int):
    """A bar over a command's ``total`` named stages; yields ``stage(name)``, called at the
    start of each stage (it completes the previous one). The last stage is completed on exit
    without an exception; the bar is then left on the terminal as a record of the run."""
    plain = enabled() and not _terminal()  # forced into a file or pipe: plain lines
    bar = tqdm(
        total=total,
        desc=command,
        unit="stage",
        disable=plain or not enabled(),
        leave=True,
        file=sys.stderr,
        dynamic_ncols=True,
        bar_format="{desc}: {n_fmt}/{total_fmt} stages [{elapsed}]",
    )
    started = [False]

    def stage(name: str) -> None:
        if started[0]:
            bar.update(1)
        started[0] = True
        bar.set_description_str(f"{command}: {name}")
        if plain:
            print(f"{command}: {name}", file=sys.stderr, flush=True)

    ok = False
    try:
        yield stage
        ok = True
    finally:
        if ok and started[0]:
            bar.update(1)
            bar.set_description_str(f"{command}: done")
        bar.close()
