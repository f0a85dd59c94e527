"""Giving freed heap memory back to the operating system after WM shrinks a lot at once.

glibc's malloc returns memory to the system only from the top of its heap; the pages of blocks
freed below a block still in use stay in the process's RSS, free for reuse. A WM cap drop
(``WorkingMemoryBudget``: hundreds of locations transferred to LTM in one frame) frees their
signatures, words and graph objects all over the heap: measured on the 30 simulated sessions,
glibc then held ~100-120 MB free (bench_slam's ``memory.samples``, ``malloc_free``), and RSS
kept the high-water mark of WM rather than following WM down. ``malloc_trim(0)`` releases the
free pages anywhere in the heap (glibc >= 2.8, madvise MADV_DONTNEED); the blocks stay where
they are, nothing is moved or copied. On another C library (musl, macOS) it does nothing.
"""

from __future__ import annotations

import ctypes
import ctypes.util
from typing import Callable, Optional


def _glibc_malloc_trim() -> Optional[Callable[[int], int]]:
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        fn = libc.malloc_trim
    except (OSError, AttributeError):
        return None
    fn.argtypes = [ctypes.c_size_t]
    fn.restype = ctypes.c_int
    return fn


_MALLOC_TRIM = _glibc_malloc_trim()


def release_free_heap() -> bool:
    """Return the C heap's free pages to the operating system (glibc's ``malloc_trim(0)``).

    Returns True when memory was released, False when there was none to release or the C
    library has no ``malloc_trim``."""
    if _MALLOC_TRIM is None:
        return False
    return bool(_MALLOC_TRIM(0))


__all__ = ["release_free_heap"]
