"""The process's memory around a frame: freed heap given back to the operating system after WM
shrinks a lot at once (:func:`release_free_heap`), and the garbage collector kept out of a frame's
processing time (:func:`collection_deferred`).

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

import contextlib
import ctypes
import ctypes.util
import gc
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


@contextlib.contextmanager
def collection_deferred():
    """CPython's automatic garbage collection paused, then resumed: the collections this block's
    allocations make due run at the next allocation after it, out of the frame's pTime.

    A full (generation 2) collection traverses every tracked object, a WM of 1,000-2,000 locations
    with their words: 40-140 ms (bench_slam's full_gc_ms) in whatever step allocated at that
    moment. A frame that took one could go over T_time and teach the WM budget a cap for work the
    frame did not do (likely in a rerun of seed 0 at T_time 0.1 s: its one frame over T_time, at
    session 1's start, capped WM at ~110, no loop closure within session 1, ATE 0.058 m).
    Reference counting still frees everything that is not in a cycle meanwhile, and the
    interpreter's own schedule (thresholds, the full collection's 25 % rule) decides what runs
    once collection is back on. Left alone when the caller has turned collection off.
    """
    if not gc.isenabled():
        yield
        return
    gc.disable()
    try:
        yield
    finally:
        gc.enable()


__all__ = ["collection_deferred", "release_free_heap"]
