"""What a real-time deployment of ``fbgcomp serve`` sets for its own process.

* a pinned core (``os.sched_setaffinity``): the process is not migrated between cores, and its
  caches stay warm;
* ``SCHED_FIFO`` (``os.sched_setscheduler``) where permitted (root, ``CAP_SYS_NICE`` or an
  ``rtprio`` limit): it runs as soon as a frame arrives instead of waiting for the time slice of
  a busy process. Where not permitted it says so once and runs on at normal priority;
* the cyclic garbage collector frozen after start-up (``gc.freeze``, done by the service) and
  its young-generation threshold raised, so a collection pass does not land on a frame;
* BLAS on one thread: a frame's algebra is too small for threads to pay; threaded BLAS beside
  other work on the cores made a served frame up to 1.3x slower (benchmarks/bench_observer_speed.py),
  and its threads would run off the pinned core.

The kernel's real-time throttling (``/proc/sys/kernel/sched_rt_runtime_us``, 95 % by default)
still leaves the other processes of the pinned core a share of it should the loop ever spin.
"""

from __future__ import annotations

import gc
import logging
import os
from dataclasses import dataclass

from fbgcomp.threads import limit_blas_threads

log = logging.getLogger("fbgcomp.runtime")


@dataclass
class RealtimeConfig:
    """``--cpu``, ``--realtime-priority``: what :func:`apply` sets for the process."""

    cpu: int = -1  # pin the service to this CPU; -1 = no pinning
    fifo_priority: int = 0  # SCHED_FIFO priority 1..99; 0 = normal scheduling
    gc_threshold: int = 50_000  # young-generation threshold of the cyclic collector (0: keep)
    blas_threads: int = 1  # BLAS threads of the service's process (0: keep the library's own)


def apply(config: RealtimeConfig, pid: int = 0) -> list[str]:
    """Apply ``config`` to process ``pid`` (0: this one); return one line per setting made or
    refused (the refusals are logged once as warnings, the run goes on)."""
    done = []
    if config.cpu >= 0:
        try:
            os.sched_setaffinity(pid, {config.cpu})
            done.append(f"pinned to CPU {config.cpu}")
        except (OSError, AttributeError, ValueError) as exc:
            msg = f"cannot pin to CPU {config.cpu} ({exc}): running on any CPU"
            log.warning(msg)
            done.append(msg)
    if config.fifo_priority > 0:
        try:
            os.sched_setscheduler(pid, os.SCHED_FIFO, os.sched_param(config.fifo_priority))
            done.append(f"SCHED_FIFO priority {config.fifo_priority}")
        except (OSError, AttributeError) as exc:
            reason = getattr(exc, "strerror", None) or str(exc)
            msg = (
                f"SCHED_FIFO not permitted ({reason}): running at normal priority (grant "
                "CAP_SYS_NICE or an rtprio limit to the service's user)"
            )
            log.warning(msg)
            done.append(msg)
    if config.gc_threshold > 0 and pid == 0:
        _, g1, g2 = gc.get_threshold()
        gc.set_threshold(config.gc_threshold, g1, g2)
        done.append(f"gc threshold {config.gc_threshold}")
    if config.blas_threads > 0 and pid == 0:
        done.append(limit_blas_threads(config.blas_threads))
    return done
