"""Resident set size of the running benchmark, for the benches that report memory over a run,
and where it lives (:func:`memory_breakdown_mb`): a creeping RSS is attributed by these figures
before anyone guesses at its owner."""

from __future__ import annotations

import ctypes
import ctypes.util
import os
import sys


def rss_mb() -> float:
    """Resident set size of this process (MB), from /proc/self/statm."""
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 1e6


class _MallInfo2(ctypes.Structure):
    """glibc's ``struct mallinfo2`` (glibc >= 2.33): all fields ``size_t``."""
    _fields_ = [(name, ctypes.c_size_t) for name in
                ("arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks", "fsmblks", "uordblks",
                 "fordblks", "keepcost")]


def _glibc_mallinfo2():
    """glibc's ``mallinfo2`` function, or None (another C library, or an older glibc)."""
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        fn = libc.mallinfo2
    except (OSError, AttributeError):
        return None
    fn.restype = _MallInfo2
    return fn


_MALLINFO2 = _glibc_mallinfo2()


def memory_breakdown_mb() -> dict:
    """Where the resident memory is (MB):

    * ``anon`` / ``file`` / ``shmem``: the RSS split of /proc/self/status (heap and anonymous
      mappings; mapped files such as libraries; shared memory such as SQLite's WAL index);
    * ``malloc_used`` / ``malloc_free``: glibc's heap (main arena, other arenas and mmapped
      chunks) in use by the program, and free but still held (holes the allocator cannot return);
    * ``python_blocks_k``: objects allocated by CPython's small-object allocator (thousands).
    """
    out: dict = {}
    with open("/proc/self/status") as f:
        for line in f:
            key, _, value = line.partition(":")
            if key in ("RssAnon", "RssFile", "RssShmem"):
                out[key[3:].lower()] = round(int(value.split()[0]) / 1024.0, 1)
    if _MALLINFO2 is not None:
        m = _MALLINFO2()
        out["malloc_used"] = round((m.uordblks + m.hblkhd) / 2**20, 1)
        out["malloc_free"] = round(m.fordblks / 2**20, 1)
    out["python_blocks_k"] = round(sys.getallocatedblocks() / 1000.0, 1)
    return out
