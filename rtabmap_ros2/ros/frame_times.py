"""Where the node's time per frame goes, part by part and thread by thread (issues 33 and 50).

The node's threads (:mod:`rtabmap_ros2.ros.node`) each time their parts:

* ``worker`` (the critical path: one frame at a time, in order): ``wait`` (the frame's features were
  not ready when the worker took it: waiting for the feature thread, or extracting them itself),
  ``process`` (the core's ``Rtabmap.process``), ``local_map`` (the snapshot of the optimised local
  map handed to the publisher); ``total`` is their sum, the worker's time per frame;
* ``features`` (the frame's features, extracted ahead while the worker processes earlier frames):
  ``features``;
* ``publisher`` (one round per published local map; it publishes every frame's ``info`` and the
  newest local map): ``path`` (``mapPath``), ``markers`` (``mapGraph``), ``tf`` (map -> odom and
  ``localization_pose``), ``info`` (statistics messages);
* ``grid`` (at most once per ``GRID_PERIOD_S``, from the newest local map): ``local_grid`` (the
  incremental occupancy grid), ``map`` (its message);
* ``callbacks`` (one row per sensor message, the executor's threads): the message's stream (``odom``,
  ``scan``, ``rgb``, ``depth``, ``camera_info``): its conversion, the synchroniser and, for the message
  completing a set, the frame's checks and queueing.

``info`` carries, as ``node_time_ms/<part>``, the newest row of every thread: the worker's of the
frame itself (``node_time_ms/total`` its total), the others' of their last round. Every row is kept
for benchmarks (:meth:`FrameTimes.spread`).
"""

from __future__ import annotations

import time
from collections import deque
from contextlib import contextmanager
from typing import Iterator

import numpy as np

# Key prefix of the per-part times in the info DiagnosticArray.
INFO_KEY_PREFIX = "node_time_ms"
MS_PER_S = 1e3
# The thread whose rows have a ``total`` (the critical path).
WORKER = "worker"
# The rows of the sensor callbacks (one per message).
CALLBACKS = "callbacks"


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
    """The per-part times (ms) of the last ``history`` rows of each thread."""

    def __init__(self, history: int) -> None:
        self._size = history
        self.threads: dict[str, deque[dict[str, float]]] = {WORKER: deque(maxlen=history)}

    @property
    def history(self) -> deque[dict[str, float]]:
        """The worker's rows (one per processed frame, with ``total``)."""
        return self.threads[WORKER]

    def add(self, timer: FrameTimer, thread: str = WORKER) -> dict[str, float]:
        """Keep ``timer``'s parts as a row of ``thread`` (the worker's with ``total``); returns the row."""
        row = {name: seconds * MS_PER_S for name, seconds in timer.parts.items()}
        if thread == WORKER:
            row["total"] = timer.total * MS_PER_S
        self.threads.setdefault(thread, deque(maxlen=self._size)).append(row)
        return row

    @staticmethod
    def info_of(row: dict[str, float]) -> dict[str, float]:
        """``{"node_time_ms/<part>": ms}`` of one row (what :meth:`add` returned)."""
        return {f"{INFO_KEY_PREFIX}/{name}": round(ms, 3) for name, ms in row.items()}

    def info(self) -> dict[str, float]:
        """``{"node_time_ms/<part>": ms, ...}``: the newest row of every thread (module doc)."""
        out: dict[str, float] = {}
        for thread, rows in list(self.threads.items()):
            if rows and thread != CALLBACKS:   # one row per message, not per frame: benchmarks only
                out.update(self.info_of(rows[-1]))
        return out

    def spread(self) -> dict[str, dict[str, dict[str, float]]]:
        """``{thread: {part: {"median", "p95", "max"}}}`` over the kept rows (ms)."""
        out: dict[str, dict[str, dict[str, float]]] = {}
        for thread, rows in list(self.threads.items()):
            rows = list(rows)
            parts = sorted({name for row in rows for name in row}, key=lambda n: (n == "total", n))
            out[thread] = {}
            for name in parts:
                values = np.array([row[name] for row in rows if name in row])
                out[thread][name] = {"median": float(np.median(values)), "p95": float(np.percentile(values, 95)),
                                     "max": float(values.max())}
        return out


__all__ = ["CALLBACKS", "FrameTimer", "FrameTimes", "INFO_KEY_PREFIX", "WORKER"]
