"""Resident set size of the running benchmark, for the benches that report memory over a run."""

from __future__ import annotations

import os


def rss_mb() -> float:
    """Resident set size of this process (MB), from /proc/self/statm."""
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 1e6
