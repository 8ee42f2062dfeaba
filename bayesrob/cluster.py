"""The Dask cluster that bayesrob's parallel work runs on: the design search's candidates, the
validation suite's studies, the diagnosis benchmark's rigs.

A ``LocalCluster`` of single-threaded worker processes, one per core, by default; a running
scheduler's address for a real cluster. Work that is already running as a Dask task (a
validation study that runs a design search) runs its tasks in its own process.
"""

from __future__ import annotations

import contextlib
import os
import signal
import threading
from collections.abc import Iterator, Sequence
from typing import Any

from distributed import WorkerPlugin

__all__ = ["ClusterError", "WORKER_ENV", "OneCorePerWorker", "dask_client", "share"]

# One XLA thread per worker process: two workers on two cores share nothing, and one worker
# does not secretly use both cores (the speed-up benchmark would lie).
WORKER_ENV = {"XLA_FLAGS": "--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1",
              "OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}


class ClusterError(ValueError):
    """A scheduler address that cannot be reached."""


class OneCorePerWorker(WorkerPlugin):
    """Pins each local worker process, every thread of it, to a core its name picks: XLA
    sizes its pool to the cores it may use, and two unpinned workers on two cores ran at half
    speed (0.20 s per candidate instead of 0.115)."""

    def __init__(self, cores: Sequence[int]):
        self.cores = tuple(cores)

    def setup(self, worker: Any) -> None:
        try:
            core = self.cores[int(worker.name) % len(self.cores)]
        except (TypeError, ValueError):
            return  # a worker not named by a LocalCluster: leave it as it is
        for tid in os.listdir("/proc/self/task"):
            with contextlib.suppress(OSError):  # a thread that ended meanwhile
                os.sched_setaffinity(int(tid), {core})


def _inside_a_task() -> bool:
    from distributed import get_worker

    try:
        get_worker()
    except ValueError:
        return False
    return True


def share(client: Any, value: Any) -> Any:
    """``value`` on every worker of ``client``'s cluster, once (``scatter(broadcast=True)``),
    for tasks to take as an argument. Inside a Dask task it is passed as it is: there
    ``scatter`` stores it on the task's own worker, which a cluster started in the task
    (:func:`dask_client`) does not know (the scheduler failed with a KeyError naming it)."""
    return value if _inside_a_task() else client.scatter(value, broadcast=True)


# How long an unreachable scheduler is retried before the one-line error: a cluster's scheduler
# may be starting as the command does.
CONNECT_TIMEOUT = "10s"


@contextlib.contextmanager
def dask_client(scheduler: str | None = None, workers: int = 2) -> Iterator[Any]:
    """A ``dask.distributed`` client: on an existing scheduler, or on a ``LocalCluster`` of
    ``workers`` worker processes, each pinned to a core with one XLA thread (``WORKER_ENV``),
    closed on exit. Called from a Dask task (a validation study that runs a
    design search), a cluster of one worker thread in that task's process: a worker's
    processes are daemons and may start none of their own, and the cluster's other workers
    are busy with tasks of their own (sent there, the search's tasks waited minutes behind
    them), so the task keeps to its own core."""
    from distributed import Client, LocalCluster

    if scheduler:
        try:
            client = Client(scheduler, timeout=CONNECT_TIMEOUT)
        except (OSError, TimeoutError) as e:
            raise ClusterError(f"--scheduler {scheduler}: cannot reach the Dask scheduler "
                               f"({type(e).__name__}: {e})") from None
        except ValueError as e:  # not an address at all: no port, an unknown protocol
            raise ClusterError(f"--scheduler {scheduler}: not a scheduler address "
                               f"(tcp://HOST:PORT): {e}") from None
        try:
            yield client
        finally:
            client.close()
        return
    if _inside_a_task():
        with LocalCluster(n_workers=1, threads_per_worker=1, processes=False,
                          dashboard_address=":0", silence_logs=40) as cluster, \
                Client(cluster) as client:
            yield client
        return
    saved = {k: os.environ.get(k) for k in WORKER_ENV}
    os.environ.update(WORKER_ENV)  # the nanny's worker processes inherit them at start
    # Ctrl-C reaches every process of the terminal's group: workers that took it would each
    # print a traceback. Started with SIGINT ignored (kept across exec, and Python leaves an
    # ignored SIGINT alone), they leave it to this process, which closes the cluster.
    main_thread = threading.current_thread() is threading.main_thread()
    sigint = signal.signal(signal.SIGINT, signal.SIG_IGN) if main_thread else None
    try:
        cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                               dashboard_address=":0", silence_logs=40)
    finally:
        if main_thread:
            signal.signal(signal.SIGINT, sigint)
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v
    client = Client(cluster)
    if hasattr(os, "sched_setaffinity"):  # Linux; elsewhere the workers stay unpinned
        client.register_plugin(OneCorePerWorker(sorted(os.sched_getaffinity(0))))
    try:
        yield client
    finally:
        client.close()
        cluster.close()
