"""How many CPU cores a process may use: thread pools and worker processes are sized from it."""

from __future__ import annotations

import os


def free_cores() -> int:
    """Cores this process may use that other work is not already using: the CPU affinity minus the 1-minute load, ≥ 1.

    Oversubscribed OpenMP threads spin-wait (a minute of work can take twenty), so model threads
    are sized from what is free, not from what the machine has: the config's ``${threads:}``.
    """
    available = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    try:
        busy = int(round(os.getloadavg()[0]))
    except OSError:  # not available on this platform
        busy = 0
    return max(1, min(available, available - busy))
