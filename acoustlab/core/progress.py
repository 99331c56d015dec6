"""Progress that is seen both in a terminal (a tqdm bar) and in a batch job's log (a line at most every 30 s)."""

from __future__ import annotations

import logging
import sys
import time
from collections.abc import Iterable, Iterator
from typing import TypeVar

from tqdm.auto import tqdm

T = TypeVar("T")
log = logging.getLogger("acoustlab.progress")

#: Seconds between progress log lines when stderr is not a terminal.
LOG_INTERVAL_S = 30.0


def progress(
    items: Iterable[T], total: int | None = None, desc: str = "", unit: str = "it", interval_s: float = LOG_INTERVAL_S, leave: bool = True
) -> Iterator[T]:
    """Yield ``items``, showing a tqdm bar on a terminal or logging ``desc: k/total unit (elapsed, left)`` every ``interval_s``.

    tqdm hides its bar when output is not a terminal (a batch job, a log file); then a log line
    at most every ``interval_s`` seconds and one at the end say how far the stage has got, so a
    long stage is never silent.
    """
    if sys.stderr.isatty():
        yield from tqdm(items, total=total, desc=desc, unit=unit, leave=leave)
        return
    total = total if total is not None else (len(items) if hasattr(items, "__len__") else None)
    start = last = time.monotonic()
    done = 0
    for item in items:
        yield item
        done += 1
        now = time.monotonic()
        if now - last >= interval_s:
            last = now
            log.info("%s: %s %s (%s)", desc, f"{done}/{total}" if total else done, unit + "s", _eta(now - start, done, total))
    if done and time.monotonic() - start >= interval_s:
        log.info("%s: %s %s done in %.0f s", desc, done, unit + "s", time.monotonic() - start)


def _eta(elapsed: float, done: int, total: int | None) -> str:
    if not total:
        return f"{elapsed:.0f} s"
    left = elapsed / done * (total - done)
    return f"{elapsed:.0f} s elapsed, about {left:.0f} s left"
