"""The Dask client of ``ttl reprocess`` and ``ttl scenarios``: a local cluster or any scheduler.

::

    from ttlcore.app.cluster import dask_client
    with dask_client(workers=2) as client:          # LocalCluster on 127.0.0.1
        ...
    with dask_client("tcp://host:8786") as client:  # a running scheduler (or its --scheduler-file)
        ...

Dask's own loggers (``distributed.*``) are held at ``log_level`` in this process and in the
local cluster's worker processes: Dask logs some thirty INFO lines per run (scheduler, nanny
and worker start and stop) and warnings about its own state (an event loop held up by a
busy machine, a task cancelled at shutdown) that say nothing to the user of a command; the
commands show them with ``-v`` (:func:`dask_log_level`).  After an interrupt (Ctrl-C) the
shutdown of the cluster is silent: the tasks it cancels and the busy worker it kills after
its grace period are the interrupt's doing, not news.
"""

from __future__ import annotations

import contextlib
import logging
import signal
import threading
from pathlib import Path

from ..errors import TTLError

#: Dask configuration key of the environment a nanny gives its worker processes.
SPAWN_ENV = "distributed.nanny.pre-spawn-environ"
#: Default memory limit of a local worker: a full day's `ttl analyze` peaks near 5 GB (its diagnosis near 3 GB).
DEFAULT_MEMORY_LIMIT = "6GiB"
#: The root of Dask distributed's loggers.
DASK_LOGGER = "distributed"


def dask_log_level(verbose: int = 0) -> int:
    """The level of Dask's loggers for a command: errors only (by default and with
    ``--quiet``), Dask's warnings with ``-v``, its INFO lines with ``-vv``."""
    return [logging.ERROR, logging.WARNING, logging.INFO][min(max(int(verbose), 0), 2)]


@contextlib.contextmanager
def dask_log_level_set(level: int):
    """Hold Dask's loggers (``distributed`` and below) at ``level`` in this process."""
    logger = logging.getLogger(DASK_LOGGER)
    previous = logger.level
    logger.setLevel(level)
    interrupted = False
    try:
        yield
    except KeyboardInterrupt:  # left silent: the process is on its way out
        interrupted = True
        _silence_dask()
        raise
    finally:
        if not interrupted:
            logger.setLevel(previous)


@contextlib.contextmanager
def dask_client(
    scheduler: str | None = None,
    *,
    workers: int = 2,
    threads_per_worker: int = 1,
    memory_limit: str | float = DEFAULT_MEMORY_LIMIT,
    dashboard: bool = False,
    log_level: int = logging.ERROR,
):
    """A :class:`distributed.Client`: to ``scheduler`` (``tcp://host:port`` of a
    ``dask scheduler``, or the path of its ``--scheduler-file``) or to a new
    :class:`distributed.LocalCluster` of ``workers`` processes bound to 127.0.0.1
    (dashboard off, or on 127.0.0.1 with ``dashboard=True``).  Closed on exit.

    ``log_level``: the level of Dask's loggers in this process and in the local workers
    (:func:`dask_log_level`); the workers of a remote cluster log where they run."""
    if int(workers) < 1 and not scheduler:
        raise TTLError(f"--workers: at least one worker, got {workers}")
    # imported first: importing distributed sets its loggers' levels (INFO)
    import dask
    from distributed import Client, LocalCluster

    with dask_log_level_set(log_level):
        if scheduler:
            if Path(scheduler).is_file():
                client = Client(scheduler_file=str(scheduler), timeout="30s")
            else:
                client = Client(scheduler, timeout="30s")
            with _serving(client):
                yield client
            return
        # Dask's nanny sets MALLOC_TRIM_THRESHOLD_=65536 in its workers, which fixes glibc's mmap
        # threshold at 128 kB: every array of a day is then a fresh mmap, zeroed page by page, and
        # a day's analysis takes twice the CPU time (measured: 0.82 s against 0.43 s for 1 h).
        # The worker memory is bounded by memory_limit anyway.
        with dask.config.set({f"{SPAWN_ENV}.MALLOC_TRIM_THRESHOLD_": None}), _sigint_ignored():
            cluster = LocalCluster(
                n_workers=int(workers),
                threads_per_worker=int(threads_per_worker),
                processes=True,
                host="127.0.0.1",
                # the scheduler serves HTTP (health, metrics) even without the dashboard, on Dask's
                # fixed 8787 unless told otherwise: an ephemeral loopback port instead, so that two
                # runs never meet on one port; the dashboard's pages only when asked for
                dashboard_address="127.0.0.1:0",
                scheduler_kwargs={"dashboard": bool(dashboard)},
                memory_limit=memory_limit,
                # the level of the workers' (and nannies') handlers of Dask's loggers: by default
                # not even their errors, which after an interrupt are a worker's failed heartbeat
                # to the scheduler just closed (a traceback on the terminal); a task's failure
                # reaches this process as its exception anyway
                silence_logs=logging.CRITICAL if log_level >= logging.ERROR else log_level,
            )
        try:
            client = Client(cluster)
            with _serving(client):
                yield client
        finally:
            cluster.close()


@contextlib.contextmanager
def _serving(client):
    """``client`` closed on exit; after an interrupt, silently (module docstring)."""
    try:
        yield client
    except KeyboardInterrupt:
        _silence_dask()
        raise
    finally:
        client.close()


@contextlib.contextmanager
def _sigint_ignored():
    """SIGINT ignored while the local cluster's processes start (main thread only): they
    inherit the ignored disposition, so a Ctrl-C at the terminal, which reaches the whole
    process group, stops the command alone (its ``KeyboardInterrupt`` closes the cluster)
    instead of printing a traceback from each nanny and worker.  A Ctrl-C during those
    seconds of start-up is lost; the next one stops the command."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    before = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, before)


def _silence_dask() -> None:
    """No Dask log line in this process from now on."""
    logging.getLogger(DASK_LOGGER).setLevel(logging.CRITICAL + 1)


__all__ = ["DEFAULT_MEMORY_LIMIT", "SPAWN_ENV", "dask_client", "dask_log_level"]
