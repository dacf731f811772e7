"""BLAS threads around small or banded dense algebra."""

from __future__ import annotations

import contextlib


def one_blas_thread():
    """A context in which BLAS runs single-threaded, when threadpoolctl is there to say so.

    Threaded OpenBLAS spends its time synchronising on small or banded problems: the FE twin's
    banded factorisation ran 4-30x slower threaded on a shared 2-core machine, and the thermal
    observer's 100-state Kalman step 11.6x slower per served frame with another job on the
    cores (benchmarks/bench_observer_speed.py). Entering it costs about 0.1 ms."""
    try:
        from threadpoolctl import threadpool_limits  # noqa: PLC0415 - optional: threadpoolctl

        return threadpool_limits(1)
    except ImportError:
        return contextlib.nullcontext()
