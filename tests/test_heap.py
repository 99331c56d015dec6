"""glibc malloc settings for batch loops (acoustlab.core.heap)."""

import ctypes.util
import platform

from acoustlab.core import heap


def test_keep_freed_memory_takes_effect_on_glibc_once_and_is_harmless_elsewhere():
    first = heap.keep_freed_memory()
    assert isinstance(first, bool)
    assert heap.keep_freed_memory() is first  # set once per process
    if platform.system() == "Linux" and platform.libc_ver()[0] == "glibc" and ctypes.util.find_library("c"):
        assert first
