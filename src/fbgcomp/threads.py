"""BLAS threads around small or banded dense algebra."""

from __future__ import annotations

import contextlib


def one_blas_thread():
    """A context in which BLAS runs single-threaded, when threadpoolctl is there to say so.

    Threaded OpenBLAS spends its time synchronising on small or banded problems: the FE twin's
    banded factorisation ran 4-30x slower threaded on a shared 2-core machine; the thermal
    observer's 100-state Kalman step gains nothing from threads either
    (benchmarks/bench_observer_speed.py). Entering it costs about 0.1 ms."""
    try:
        from threadpoolctl import threadpool_limits  # noqa: PLC0415 - optional: threadpoolctl

        return threadpool_limits(1)
    except ImportError:
        return contextlib.nullcontext()


def limit_blas_threads(threads: int) -> str:
    """Limit BLAS to ``threads`` threads for the rest of the process; say what was done.

    For a process that serves frames (``fbgcomp serve``): a model's per-frame algebra is too
    small for threads to pay, and threaded OpenBLAS beside other work on the cores made the
    default model's served frame up to 1.3x slower (benchmarks/bench_observer_speed.py); its
    threads would also leave the core ``serve`` is pinned to."""
    try:
        from threadpoolctl import threadpool_info, threadpool_limits  # noqa: PLC0415 - optional

        before = sorted({p["num_threads"] for p in threadpool_info() if p.get("user_api") == "blas"})
        threadpool_limits(threads, user_api="blas")  # applied on creation; kept for the process
    except ImportError:
        return f"BLAS threads not limited (threadpoolctl not installed): set OPENBLAS_NUM_THREADS={threads}"
    was = ", ".join(str(n) for n in before) or "none loaded"
    return f"BLAS on {threads} thread{'s' if threads != 1 else ''} (was {was})"
