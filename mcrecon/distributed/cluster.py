"""Dask clusters: a local one sized to the machine, or a scheduler's.
"""

from __future__ import annotations

import contextlib
import os
import socket
import warnings


from ..errors import InputError, McreconWarning



__all__ = ['local_client']

def _dask():
    try:
        import distributed
    except ImportError:
        raise InputError("mcrecon.distributed", "dask", "dask.distributed is not installed; "
                         "pip install 'mcrecon[dask]' (or pip install 'dask[distributed]')") from None
    return distributed


# ----------------------------------------------------------------------------
# Clusters
# ----------------------------------------------------------------------------

def _cores() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return os.cpu_count() or 1


#: Dask housekeeping switched off or slowed down for the clusters :func:`local_client` starts.
#: On a machine whose cores all run frames, every CPU-second the scheduler, the nannies and the
#: workers' event loops spend is taken from a frame.  Measured on the 16-frame gem batch with 2
#: workers on 2 cores (CPU time of the client process, which hosts the scheduler and the nannies,
#: plus the workers' event-loop threads, during the batch; docs/distributed.md): 1.45-2.6 CPU-s
#: with Dask's defaults, 0.9-1.0 without the profiler, 0.5-0.6 with the tick at 1 s too, against
#: ~15 CPU-s of frames.  The statistical profiler samples the running task's stack 100 times a
#: second on the worker's event loop (and a second thread watches each event loop); the tick
#: wakes every event loop 50 times a second to check that it is not blocked (it warns after 3 s,
#: which a 1 s tick still sees).  Only Dask's dashboard profile page loses anything.  A cluster
#: the user starts (``--scheduler``) keeps its own configuration (docs/distributed.md).
_QUIET = {
    "distributed.worker.profile.enabled": False,
    "distributed.admin.tick.interval": "1s",
}


@contextlib.contextmanager
def local_client(workers: int | None = None, *, threads: int | None = None):
    """A :class:`distributed.Client` on a fresh LocalCluster of ``workers`` processes (default: the cores).

    Each worker runs one task at a time; ``threads`` (default: cores //
    workers, at least 1) is its ``MCRECON_THREADS``, the threads of
    mcrecon's own filters, so the workers together do not oversubscribe
    the machine.  Results do not depend on it.
    """
    distributed = _dask()
    n = int(workers) if workers is not None else _cores()
    if n < 1:
        raise InputError("mcrecon.distributed", "workers", f"{workers!r}, expected a positive integer")
    t = int(threads) if threads is not None else max(1, _cores() // n)
    import logging

    import dask

    # Dask's nanny starts workers with MALLOC_TRIM_THRESHOLD_=65536 (to hand freed memory back
    # to the OS).  Setting it also switches off glibc's adaptive mmap threshold, so every
    # image-sized temporary becomes a fresh mmap whose pages fault in on first touch: a 512^2,
    # 32-spp gem frame took 1.00-1.03 s instead of 0.79-0.88 s in the same process
    # (docs/distributed.md, "Measured scaling").  Our workers allocate as `mcrecon reconstruct`
    # does; an explicit MALLOC_TRIM_THRESHOLD_ in the environment is still inherited.
    with dask.config.set({"distributed.nanny.pre-spawn-environ.MALLOC_TRIM_THRESHOLD_": None, **_QUIET}):
        cluster = distributed.LocalCluster(n_workers=n, threads_per_worker=1, processes=True,
                                           dashboard_address=":0", silence_logs=logging.CRITICAL,
                                           env={"MCRECON_THREADS": str(t), "OMP_NUM_THREADS": "1"})
    try:
        # gathers and scatters go straight to the workers (on this machine, reachable): a result
        # crosses one TCP connection instead of two, through the scheduler, and big pickled
        # objects keep pickle protocol 5 (out-of-band arrays) instead of the scheduler's 4
        client = distributed.Client(cluster, direct_to_workers=True)
        try:
            yield client
        finally:
            client.close()
    finally:
        cluster.close()


def _local_workers(workers: int | None, frames: int) -> int:
    """Workers of a local cluster for ``frames`` frames: never more than the frames or the cores
    (each extra worker is an idle process of a few hundred MB; a million of them never start)."""
    cores = _cores()
    if workers is not None and (isinstance(workers, bool) or int(workers) != workers or workers < 1):
        raise InputError("batch", "workers", f"{workers!r}, expected a positive integer")
    n = min(cores if workers is None else int(workers), max(frames, 1), cores)
    if workers is not None and n < workers:
        warnings.warn(f"batch: {workers} workers capped at {n} ({frames} frame(s) to reconstruct, "
                      f"{cores} core(s))", McreconWarning, stacklevel=3)
    return n


@contextlib.contextmanager
def _client_for(client=None, scheduler: str | None = None, workers: int | None = None):
    if client is not None:
        yield client
    elif scheduler is not None:
        distributed = _dask()
        try:
            c = distributed.Client(scheduler, timeout="20s")
        except (OSError, TimeoutError) as exc:
            raise InputError(str(scheduler), "scheduler", f"cannot connect: {exc}") from None
        try:
            yield c
        finally:
            c.close()
    else:
        with local_client(workers) as c:
            yield c


def _worker_name() -> str:
    try:
        from distributed import get_worker

        return get_worker().address
    except (ImportError, ValueError):
        return f"{socket.gethostname()}:{os.getpid()}"


def _one_line(exc: BaseException) -> str:
    text = str(exc) if isinstance(exc, InputError) else f"{type(exc).__name__}: {exc}"
    if isinstance(exc, OSError) and exc.filename:
        text = f"{exc.filename}: {exc.strerror or exc}"
    return " ".join(text.split())
