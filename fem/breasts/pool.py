"""Process pools whose workers never outlive the command that started them.

A killed ``fem.cohort`` (SIGKILL included) must not leave workers that go on writing breast
files while a resumed run writes the same ones: each worker asks the kernel to kill it when its
parent dies (Linux ``prctl(PR_SET_PDEATHSIG)``), or elsewhere watches its parent from a thread.
"""

from __future__ import annotations

import ctypes
import os
import signal
import sys
import threading
import time
from concurrent.futures import ProcessPoolExecutor

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


def worker_pool(workers: int) -> ProcessPoolExecutor:
    """A process pool of ``workers`` processes that die with the calling process."""
    if workers < 1:
        raise ValueError(f"workers must be at least 1, got {workers}")
    return ProcessPoolExecutor(workers, initializer=die_with_parent, initargs=(os.getpid(),))
