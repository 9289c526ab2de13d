"""The cohort's executors: local workers die with the process that started them (SIGKILL
included), Dask runs the tasks on a cluster's workers, and the settings are checked."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time
from concurrent.futures import as_completed

import pytest
from threadpoolctl import threadpool_info

from fem.breasts.pool import (
    check_executor,
    cohort_executor,
    dask_client,
    one_blas_thread,
    worker_pool,
)

PARENT = textwrap.dedent(
    """
    import os, sys, time
    from fem.breasts.pool import cohort_executor

    if __name__ == "__main__":
        with cohort_executor(sys.argv[1], 1) as pool:
            print(pool.submit(os.getpid).result(), flush=True)
            pool.submit(time.sleep, 60)
            time.sleep(60)
    """
)


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    # a zombie (dead, not yet reaped by init) counts as gone
    with open(f"/proc/{pid}/stat") as f:
        return f.read().split()[2] != "Z"


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
@pytest.mark.parametrize("executor", ["local", "dask"])
def test_workers_die_with_a_killed_parent(executor):
    parent = subprocess.Popen(
        [sys.executable, "-c", PARENT, executor], stdout=subprocess.PIPE, text=True
    )
    worker = int(parent.stdout.readline())
    assert _alive(worker)
    parent.send_signal(signal.SIGKILL)
    parent.wait()
    deadline = time.monotonic() + 10
    while _alive(worker) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert not _alive(worker), f"worker {worker} outlived its killed parent"


def test_a_pool_needs_a_worker():
    with pytest.raises(ValueError, match="workers must be an integer >= 1, got 0"):
        worker_pool(0)


@pytest.mark.parametrize(
    ("executor", "scheduler", "message"),
    [
        ("bogus", None, r"executor must be one of \('local', 'dask'\), got 'bogus'"),
        ("local", "tcp://host:8786", r"scheduler=tcp://host:8786 .* needs executor=dask"),
        ("dask", 8786, r"scheduler must be a Dask scheduler's address .*, got 8786"),
    ],
)
def test_executor_settings_are_checked(executor, scheduler, message):
    with pytest.raises(ValueError, match=message):
        check_executor(executor, scheduler)


def test_a_task_runs_with_one_blas_thread():
    def blas_threads() -> set[int]:
        return {lib["num_threads"] for lib in threadpool_info() if lib["user_api"] == "blas"}

    assert one_blas_thread(blas_threads)() == {1}


def test_dask_runs_tasks_on_the_scheduler_s_workers_and_leaves_its_cluster_running():
    with dask_client(2) as client:
        worker_pids = set(client.run(os.getpid).values())
        with cohort_executor("dask", 1, client.scheduler.address) as pool:
            futures = [pool.submit(os.getpid) for _ in range(4)]
            pids = {f.result() for f in as_completed(futures)}
        assert len(worker_pids) == 2 and pids <= worker_pids
        assert len(client.scheduler_info()["workers"]) == 2  # the cluster is still there
    assert client.status == "closed"
