"""Loopback helpers shared by the benchmarks that start real processes (bench_runtime,
bench_soak): a free TCP port and waiting for a listener; and what the runtime benchmarks
share: busy background processes, the code commit, the runtime's real-time settings; and a
baseline commit's code checked out beside this one (bench_startup, bench_load_tracker)."""

from __future__ import annotations

import contextlib
import socket
import subprocess
import sys
import time
from pathlib import Path


def free_port() -> int:
    """A TCP port free on 127.0.0.1 at the time of the call."""
    with socket.socket() as sk:
        sk.bind(("127.0.0.1", 0))
        return sk.getsockname()[1]


def wait_port(port: int, timeout_s: float = 60.0) -> None:
    """Return once something listens on 127.0.0.1:``port``; TimeoutError after ``timeout_s``."""
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        try:
            with socket.create_connection(("127.0.0.1", port), timeout=0.2):
                return
        except OSError:
            time.sleep(0.05)
    raise TimeoutError(f"nothing listening on 127.0.0.1:{port}")


@contextlib.contextmanager
def busy_processes(count: int):
    """``count`` busy background processes (a pure-Python spin each, normal priority) for the
    duration of the block: the benchmark loads both cores itself, whatever else runs."""
    procs = [
        subprocess.Popen(
            [sys.executable, "-c", "while True: pass"], stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL
        )
        for _ in range(count)
    ]
    try:
        time.sleep(0.5 if count else 0.0)
        yield procs
    finally:
        for p in procs:
            p.terminate()
        for p in procs:
            try:
                p.wait(5)
            except subprocess.TimeoutExpired:
                p.kill()


def git_commit() -> str:
    """Short hash of the checked-out commit (``+dirty`` with uncommitted changes)."""
    root = Path(__file__).resolve().parent.parent
    try:
        head = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], cwd=root, text=True, capture_output=True, check=True
        ).stdout.strip()
        dirty = subprocess.run(
            ["git", "status", "--porcelain", "--untracked-files=no", "--", "src", "benchmarks"],
            cwd=root,
            text=True,
            capture_output=True,
        ).stdout.strip()
        return head + ("+dirty" if dirty else "")
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


@contextlib.contextmanager
def baseline_worktree(rev: str, folder: Path):
    """A detached git worktree of ``rev`` at ``folder``, removed on exit: a baseline commit's code
    beside this checkout's, run with its ``src`` first on ``PYTHONPATH``."""
    root = Path(__file__).resolve().parent.parent
    subprocess.run(["git", "worktree", "add", "--detach", "-q", str(folder), rev], cwd=root, check=True)
    try:
        yield folder
    finally:
        subprocess.run(["git", "worktree", "remove", "--force", str(folder)], cwd=root, check=False)


def realtime_settings(cpu: int | None, fifo: bool) -> str:
    """The runtime's own real-time settings (fbgcomp.runtime.realtime) on this process."""
    from fbgcomp.runtime.realtime import RealtimeConfig, apply

    done = apply(
        RealtimeConfig(cpu=-1 if cpu is None else cpu, fifo_priority=50 if fifo else 0, gc_threshold=0)
    )
    return "; ".join(done) or "normal scheduling, any CPU"
