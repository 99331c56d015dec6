"""Local worker processes that end with the run that started them.

A run killed with ``kill -9`` cannot tell its workers to stop. On Linux each worker asks the kernel
to kill it when its parent dies (``prctl(PR_SET_PDEATHSIG, SIGKILL)``); elsewhere the work loop
checks its parent between chunks (``acoustlab.season.stream.localize_chunks``). Every part a
worker writes is written atomically, so a worker killed mid-chunk leaves nothing half written.
The pool is the standard library's (spawned processes, no reuse across runs), so no idle pool or
resource tracker of a third-party executor outlives the run either.
"""

from __future__ import annotations

import ctypes
import multiprocessing
import os
import signal
import sys
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor
from typing import Any

#: prctl's option to set the signal a process receives when its parent dies (linux/prctl.h).
PR_SET_PDEATHSIG = 1


def die_with_parent(parent_pid: int) -> None:
    """Worker initializer: be killed when the process ``parent_pid`` dies (Linux), and exit now if it is already gone."""
    if sys.platform.startswith("linux"):
        try:
            ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGKILL)
        except (OSError, AttributeError):  # no libc prctl (another libc): the work loop's own check remains
            pass
    if os.getppid() != parent_pid:  # the parent died before the request was made
        os._exit(1)


def run_in_workers(function: Callable[..., Any], arguments: Sequence[tuple[Any, ...]], n_workers: int) -> list[Any]:
    """``function(*args)`` for each of ``arguments`` in ``n_workers`` spawned processes that die with this one; results in order."""
    context = multiprocessing.get_context("spawn")
    with ProcessPoolExecutor(n_workers, mp_context=context, initializer=die_with_parent, initargs=(os.getpid(),)) as pool:
        return [future.result() for future in [pool.submit(function, *args) for args in arguments]]
