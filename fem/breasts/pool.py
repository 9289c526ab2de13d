"""The executors of ``fem.cohort``'s per-breast tasks: a local process pool, or Dask distributed.

`cohort_executor` is the one place both stages of the cohort get their executor from, chosen
by the ``executor`` setting: ``local`` (the default), a process pool on this machine whose
workers never outlive the command; ``dask``, the workers of a Dask distributed cluster, a
``LocalCluster`` started for the command or a running scheduler's (``scheduler``). Either
executor returns `concurrent.futures` futures, so the callers' ``as_completed`` loops are the
same. Each task writes its breast's files itself and runs with one BLAS thread
(`one_blas_thread`), so a breast's arrays do not depend on the executor, nor on the machine's
core count.

A killed ``fem.cohort`` (SIGKILL included) must not leave workers that go on writing breast
files while a resumed run writes the same ones: each local worker asks the kernel to kill it
when its parent dies (Linux ``prctl(PR_SET_PDEATHSIG)``), or elsewhere watches its parent from a
thread; a ``LocalCluster``'s workers end when the pipe from their parent closes (Dask's own).
"""

from __future__ import annotations

import ctypes
import os
import signal
import sys
import threading
import time
from collections.abc import Callable, Iterator
from concurrent.futures import Executor, ProcessPoolExecutor
from contextlib import contextmanager
from functools import wraps
from typing import TYPE_CHECKING, ParamSpec, TypeVar

from threadpoolctl import threadpool_limits

if TYPE_CHECKING:  # Dask is imported only where executor=dask asks for it
    from distributed import Client

#: The values of the ``executor`` setting.
EXECUTORS = ("local", "dask")

P = ParamSpec("P")
R = TypeVar("R")

#: ``prctl`` option: the signal this process gets when its parent dies (linux/prctl.h).
PR_SET_PDEATHSIG = 1


def die_with_parent(parent: int) -> None:
    """Pool-worker initializer: end this process as soon as process ``parent`` is gone."""
    if sys.platform.startswith("linux"):
        ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGKILL)
    else:
        threading.Thread(target=_watch, args=(parent,), daemon=True).start()
    if os.getppid() != parent:  # the parent died before the request took effect
        os._exit(1)


def _watch(parent: int, interval: float = 0.5) -> None:
    while os.getppid() == parent:
        time.sleep(interval)
    os._exit(1)


def one_blas_thread(task: Callable[P, R]) -> Callable[P, R]:
    """``task`` run with one BLAS thread (a decorator of the cohort's per-breast tasks).

    OpenBLAS splits a product over the threads it has, and another split rounds differently:
    a compression step on 2 threads differs from one on 1 thread by about 1e-13 mm. A Dask
    worker has one thread (Dask sets ``OMP_NUM_THREADS=1``), a local worker as many as the
    machine's cores; with one thread everywhere a breast's arrays are the same bytes whatever
    the executor and the machine.
    """

    @wraps(task)
    def one_thread(*args: P.args, **kwargs: P.kwargs) -> R:
        with threadpool_limits(limits=1, user_api="blas"):
            return task(*args, **kwargs)

    return one_thread


def check_workers(workers: int) -> None:
    """Refuse a ``workers`` setting that is not a whole number of processes."""
    if not (isinstance(workers, int) and workers >= 1):
        raise ValueError(f"workers must be an integer >= 1, got {workers!r}")


def worker_pool(workers: int) -> ProcessPoolExecutor:
    """A process pool of ``workers`` processes that die with the calling process."""
    check_workers(workers)
    return ProcessPoolExecutor(workers, initializer=die_with_parent, initargs=(os.getpid(),))


def check_executor(executor: str, scheduler: str | None) -> None:
    """Refuse an unknown ``executor``, or a ``scheduler`` address that no Dask executor uses.

    Raises
    ------
    ValueError
        The message names the setting and what it may be.
    """
    if executor not in EXECUTORS:
        raise ValueError(f"executor must be one of {EXECUTORS}, got {executor!r}")
    if scheduler is None:
        return
    if not (isinstance(scheduler, str) and scheduler):
        raise ValueError(
            f"scheduler must be a Dask scheduler's address (tcp://host:8786), got {scheduler!r}"
        )
    if executor != "dask":
        raise ValueError(
            f"scheduler={scheduler} is a Dask scheduler's address: it needs executor=dask, "
            f"got executor={executor}"
        )


@contextmanager
def dask_client(workers: int, scheduler: str | None = None) -> Iterator[Client]:
    """A Dask client of the scheduler at ``scheduler``, or of a new ``LocalCluster``.

    Without ``scheduler`` the cluster has ``workers`` single-threaded worker processes and is
    closed on exit; a running scheduler's cluster is left running.
    """
    from distributed import Client, LocalCluster

    if scheduler is not None:
        with Client(scheduler) as client:
            yield client
        return
    check_workers(workers)
    with (
        LocalCluster(n_workers=workers, threads_per_worker=1, processes=True) as cluster,
        Client(cluster) as client,
    ):
        yield client


@contextmanager
def cohort_executor(
    executor: str = "local", workers: int = 1, scheduler: str | None = None
) -> Iterator[Executor]:
    """The executor of the cohort's per-breast tasks, shut down (its tasks waited for) on exit.

    Parameters
    ----------
    executor
        ``local``: `worker_pool` of ``workers`` processes; ``dask``: Dask distributed.
    workers
        Processes of the local pool or of the ``LocalCluster``; a running scheduler's cluster
        has its own.
    scheduler
        With ``executor="dask"``, a running scheduler's address (``tcp://host:8786``), whose
        workers must see the same output folder; ``None`` starts a ``LocalCluster``.

    Raises
    ------
    ValueError
        See `check_executor`; ``workers`` below 1.
    """
    check_executor(executor, scheduler)
    if executor == "local":
        with worker_pool(workers) as pool:
            yield pool
        return
    with dask_client(workers, scheduler) as client, client.get_executor(pure=False) as pool:
        yield pool
