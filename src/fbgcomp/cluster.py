"""Scale-out on an existing engine (Dask distributed); in-process by default.

``dask`` arguments everywhere accept ``None`` (in-process, no Dask import), a scheduler address
``tcp://HOST:8786``, ``local:N`` (a LocalCluster of N single-threaded worker processes, started
and stopped around the call) or an existing ``distributed.Client``. :func:`map_over_cluster`
maps a function over items (the placement search, one task per candidate; the fits, one task
per data file) and :func:`tree_reduce` merges results pairwise on the workers
(:mod:`fbgcomp.models.distributed` merges QR factors with it).

Workers must be able to import fbgcomp and see the same paths as the client (a shared file
system or the same machine).
"""

from __future__ import annotations

import contextlib
import os
import re

from fbgcomp.errors import InputError

__all__ = ["cluster", "local_cluster", "map_over_cluster", "pairwise", "parse_dask", "tree_reduce"]

_LOCAL_RE = re.compile(r"^local(?::(\d+))?$")


def parse_dask(spec) -> tuple[str, object]:
    """``("none", None)``, ``("client", client)``, ``("local", n_workers)`` or
    ``("address", "tcp://...")``; InputError naming the option for anything else."""
    if spec is None or spec == "" or spec == "none":
        return "none", None
    if not isinstance(spec, str):
        return "client", spec
    m = _LOCAL_RE.match(spec.strip())
    if m:
        n = int(m.group(1) or (os.cpu_count() or 1))
        if n < 1:
            raise InputError("local:N needs N >= 1 workers", file="<command line>", column="option --dask")
        return "local", n
    if re.match(r"^(tcp|tls|inproc|ws|wss|ucx)://\S+$", spec.strip()):
        return "address", spec.strip()
    raise InputError(
        f"--dask expects tcp://HOST:PORT or local:N, got {spec!r}",
        file="<command line>",
        column="option --dask",
    )


def local_cluster(n_workers: int, **kwargs):
    """A ``distributed.LocalCluster`` of ``n_workers`` single-threaded worker processes.

    Dask's nanny starts workers with ``MALLOC_TRIM_THRESHOLD_=65536``, which switches off
    glibc's dynamic mmap threshold: every multi-MB temporary of a 10^5-row chunk is then a
    fresh mmap, and the page faults doubled the CPU of a fit (0.52 -> 1.19 CPU-s per 10^6
    rows, measured). fbgcomp's tasks hold one chunk at a time, so their workers keep glibc's
    defaults. The scheduler's HTTP server (its health and metrics routes: dask starts one even
    without a dashboard) listens on a free loopback port: dask's default, 8787, was taken by
    the first cluster on the machine, and every other one warned on stderr. Extra keyword
    arguments go to ``LocalCluster``.
    """
    import dask  # noqa: PLC0415 - the scale extra (Dask) is optional: imported when a cluster is used
    from distributed import LocalCluster  # noqa: PLC0415 - as above

    options = {
        "threads_per_worker": 1,
        "processes": True,
        "dashboard_address": None,
        "scheduler_kwargs": {"dashboard_address": "127.0.0.1:0"},
        "silence_logs": 40,
    }
    options.update(kwargs)
    with dask.config.set({"distributed.nanny.pre-spawn-environ.MALLOC_TRIM_THRESHOLD_": None}):
        return LocalCluster(n_workers=n_workers, **options)


@contextlib.contextmanager
def cluster(spec):
    """Context manager yielding a ``distributed.Client`` for ``spec`` (None: yields None).

    A ``local:N`` cluster is created for the duration (worker processes, one thread each, no
    dashboard) and shut down after; a given client is left open.
    """
    kind, value = parse_dask(spec)
    if kind == "none":
        yield None
        return
    if kind == "client":
        yield value
        return
    try:
        from distributed import Client  # noqa: PLC0415 - the scale extra is optional
    except ImportError:
        raise InputError(
            "--dask needs the scale extra: pip install 'fbgcomp[scale]'",
            file="<command line>",
            column="option --dask",
        ) from None
    if kind == "local":
        with local_cluster(value) as lc, Client(lc) as client:
            yield client
        return
    try:
        client = Client(value, timeout="10s")
    except (OSError, TimeoutError) as exc:
        raise InputError(
            f"cannot reach the Dask scheduler at {value}: {exc}",
            file="<command line>",
            column="option --dask",
        ) from None
    try:
        yield client
    finally:
        client.close()


def map_over_cluster(func, items, dask=None) -> list:
    """``[func(item) for item in items]``, on a Dask cluster when ``dask`` is given.

    For the FE design sweeps (sensor placement over thousands of layouts, load designs): the
    results come back in the order of ``items``. ``func`` must be importable (or picklable by
    cloudpickle) on the workers; each item is one task.
    """
    items = list(items)
    with cluster(dask) as client:
        if client is None:
            return [func(item) for item in items]
        futures = client.map(func, items, pure=False)
        return client.gather(futures)


def pairwise(merge, items: list) -> object:
    """Merge ``items`` pairwise, level by level, into one (a binary tree of ``merge`` calls)."""
    while len(items) > 1:
        nxt = [merge(items[i], items[i + 1]) for i in range(0, len(items) - 1, 2)]
        if len(items) % 2:
            nxt.append(items[-1])
        items = nxt
    return items[0]


def tree_reduce(func, items, merge, dask=None):
    """``merge``-reduce ``func(item)`` over ``items`` as a balanced binary tree.

    On a cluster both the map and every merge run on the workers, so the client only ever
    receives the final value; the tree has the same shape in-process, so results are identical
    up to the merge's rounding.
    """
    items = list(items)
    if not items:
        raise ValueError("nothing to reduce")
    with cluster(dask) as client:
        if client is None:
            return pairwise(merge, [func(item) for item in items])
        futures = client.map(func, items, pure=False)
        final = pairwise(lambda a, b: client.submit(merge, a, b, pure=False), futures)
        return final.result()
