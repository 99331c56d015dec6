"""Keep freed memory for reuse in long batch loops (glibc's malloc settings), instead of page-faulting it back each batch.

A localizing loop allocates the same few arrays of tens of megabytes for every batch (padded audio,
spectra, correlations). By default glibc's malloc serves blocks above its mmap threshold with a
fresh ``mmap`` and returns them with ``munmap``, so every batch faults those pages in again and the
kernel zeroes them, which shows as system time. Raising the mmap threshold to its largest
value (32 MiB on 64-bit systems) and the trim threshold keeps freed blocks in the heap, where the
next batch finds them. The peak resident memory is unchanged (it is set by one batch's arrays);
what changes is that memory freed after the peak stays with the process, up to
``KEEP_FREED_BYTES``.

No library does this: numpy's allocator caches only small blocks, and the glibc settings are a
C call (``mallopt``), reached here through ``ctypes``. Elsewhere (macOS, musl) nothing changes.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import logging

log = logging.getLogger(__name__)

#: ``mallopt`` parameters (glibc's malloc.h).
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3
#: Blocks up to this size come from the heap, not from their own mmap (glibc's largest allowed value on 64-bit).
MMAP_THRESHOLD_BYTES = 32 * 1024**2
#: Freed memory at the top of the heap up to this size stays with the process for the next batch.
KEEP_FREED_BYTES = 1024**3

_done: bool | None = None


def keep_freed_memory() -> bool:
    """Set glibc's malloc to reuse freed batch-sized blocks (module docstring); True where it took effect, False elsewhere.

    Safe to call more than once (the settings are made once per process).
    """
    global _done
    if _done is not None:
        return _done
    _done = False
    name = ctypes.util.find_library("c")
    try:
        libc = ctypes.CDLL(name)
        mallopt = libc.mallopt
    except (OSError, AttributeError, TypeError):  # no C library by that name, or one without mallopt (not glibc)
        log.debug("keep_freed_memory: no glibc mallopt here; malloc left as it is")
        return False
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    _done = bool(mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES)) and bool(mallopt(_M_TRIM_THRESHOLD, KEEP_FREED_BYTES))
    log.debug("keep_freed_memory: glibc mallopt %s", "set" if _done else "refused")
    return _done
