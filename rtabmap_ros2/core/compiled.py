"""numba compilation shared by the core's compiled loops (kdtree.py, nearest.py, icp.py, registration.py,
graph_compiled.py)."""

from __future__ import annotations

import numba

# Functions compiled without numba's on-disk cache (no writable cache directory: see jit).
UNCACHED: list[str] = []


def jit(**options):
    """``numba.njit(nogil=True)`` with numba's on-disk cache (``cache=True``): compiled once per
    install and source version, then loaded (``__pycache__`` beside the module if writable, else
    ``NUMBA_CACHE_DIR``, else the user's cache directory). Where none is writable numba refuses
    ``cache=True`` at import (RuntimeError): then the function is compiled in every process."""
    def decorate(fn):
        try:
            return numba.njit(cache=True, nogil=True, **options)(fn)
        except RuntimeError:
            UNCACHED.append(fn.__name__)
            return numba.njit(nogil=True, **options)(fn)
    return decorate
