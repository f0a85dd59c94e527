"""The node worker's time per frame, split into its parts (issue 33).

Each processed frame is timed part by part: ``process`` (the core's ``Rtabmap.process``),
``local_map`` (reading the optimised local map), ``local_grid`` (the local occupancy grid),
``path`` (``mapPath``: conversion and publish), ``map`` (the grid message), ``markers``
(``mapGraph``), ``tf`` (map -> odom and ``localization_pose``) and ``info`` (statistics message).
The parts of the previous frame are published on ``info`` as ``node_time_ms/<part>`` and
``node_time_ms/total`` (this frame's ``info`` is not finished when its message is built), and
every frame's are kept for benchmarks (``FrameTimes.history``).
"""

from __future__ import annotations

import time
from collections import deque
from contextlib import contextmanager
from typing import Iterator

# Key prefix of the per-part times in the info DiagnosticArray.
INFO_KEY_PREFIX = "node_time_ms"
MS_PER_S = 1e3


class FrameTimer:
    """Wall time (s) of the named parts of one frame, in the order they ran."""

    def __init__(self) -> None:
        self.parts: dict[str, float] = {}

    @contextmanager
    def part(self, name: str) -> Iterator[None]:
        """Time the ``with`` block as part ``name`` (added to it if it ran before in this frame)."""
        start = time.perf_counter()
        try:
            yield
        finally:
            self.parts[name] = self.parts.get(name, 0.0) + time.perf_counter() - start

    @property
    def total(self) -> float:
        return sum(self.parts.values())


class FrameTimes:
    """The per-part times of the last ``history`` frames (ms)."""

    def __init__(self, history: int) -> None:
        self.history: deque[dict[str, float]] = deque(maxlen=history)

    def add(self, timer: FrameTimer) -> None:
        row = {name: seconds * MS_PER_S for name, seconds in timer.parts.items()}
        row["total"] = timer.total * MS_PER_S
        self.history.append(row)

    def info(self) -> dict[str, float]:
        """``{"node_time_ms/<part>": ms, ..., "node_time_ms/total": ms}`` of the last frame added."""
        if not self.history:
            return {}
        return {f"{INFO_KEY_PREFIX}/{name}": round(ms, 3) for name, ms in self.history[-1].items()}


__all__ = ["FrameTimer", "FrameTimes", "INFO_KEY_PREFIX"]
