"""How many CPU cores a process may use: thread pools and worker processes are sized from it."""

from __future__ import annotations

import os
import time
from pathlib import Path

#: How long the machine's CPU use is sampled to see what other work is running, s.
SAMPLE_S = 0.2
#: The kernel's CPU counters (Linux).
PROC_STAT = Path("/proc/stat")
#: A sample is reused for this long, s (a run resolves ``${threads:}`` in many config nodes; each would sleep).
REUSE_S = 30.0
_last: tuple[float, float] | None = None  # (when, busy cores)


def _cpu_counters() -> tuple[int, int] | None:
    """(busy, total) jiffies of all CPUs from ``/proc/stat``, or None where the file cannot be read."""
    try:
        fields = [int(v) for v in PROC_STAT.read_text().splitlines()[0].split()[1:]]
    except (OSError, ValueError, IndexError):
        return None
    idle = fields[3] + (fields[4] if len(fields) > 4 else 0)  # idle + iowait
    return sum(fields[:8]) - idle, sum(fields[:8])


def busy_cores(sample_s: float = SAMPLE_S) -> float:
    """Cores other processes keep busy now: the machine's CPU use over ``sample_s`` seconds (Linux), else the 1-minute load.

    The load average lags by a minute: right after ``pip install`` it still counts the finished
    install as a busy core, and a run started then would use half of a quiet 2-core machine. The
    kernel's counters over a short sample see what runs now.
    """
    global _last
    if _last is not None and time.monotonic() - _last[0] < REUSE_S:
        return _last[1]
    _last = (time.monotonic(), _sampled_busy_cores(sample_s))
    return _last[1]


def _sampled_busy_cores(sample_s: float) -> float:
    first = _cpu_counters()
    if first is not None:
        time.sleep(sample_s)
        second = _cpu_counters()
        if second is not None and second[1] > first[1]:
            return (second[0] - first[0]) / (second[1] - first[1]) * (os.cpu_count() or 1)
    try:
        return float(os.getloadavg()[0])
    except OSError:  # not available on this platform
        return 0.0


def free_cores() -> int:
    """Cores this process may use that other work is not already using: the CPU affinity minus the busy cores, ≥ 1.

    Oversubscribed OpenMP threads spin-wait (a minute of work can take twenty), so model threads
    are sized from what is free, not from what the machine has: the config's ``${threads:}``.
    The answer never changes a result, only how fast it comes: every threaded plugin gives the same
    numbers on any number of threads.
    """
    available = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    return max(1, min(available, available - int(round(busy_cores()))))
