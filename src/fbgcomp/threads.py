"""BLAS threads around small or banded dense algebra."""

from __future__ import annotations

import contextlib
import functools


@functools.lru_cache(maxsize=1)
def _controller():
    """The loaded thread pools as threadpoolctl sees them, listed once (None without threadpoolctl).

    Forming it reads /proc/self/maps and opens every pool's library: ~5 ms in a process with
    scipy, pandas and the rest loaded, which ``threadpool_limits`` paid on every entry (6 of
    37 s of ram2's thermal_b served with the observer, 1296 batches). SciPy's linear algebra,
    which brings its own OpenBLAS, is imported first so that its pool is in the view."""
    try:
        from threadpoolctl import ThreadpoolController  # noqa: PLC0415 - optional: threadpoolctl
    except ImportError:
        return None
    import scipy.linalg  # noqa: F401, PLC0415 - load SciPy's BLAS before the pools are listed

    return ThreadpoolController()


def one_blas_thread():
    """A context in which BLAS runs single-threaded, when threadpoolctl is there to say so.

    Threaded OpenBLAS spends its time synchronising on small or banded problems: the FE twin's
    banded factorisation ran 4-30x slower threaded on a shared 2-core machine; the thermal
    observer's 100-state Kalman step gains nothing from threads either
    (benchmarks/bench_observer_speed.py). Entering it costs a few µs: the pools are listed
    once per process (:func:`_controller`)."""
    controller = _controller()
    return contextlib.nullcontext() if controller is None else controller.limit(limits=1)


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
