"""The node's outputs, published beside the worker from the newest local map (issue 50).

The worker hands each processed frame to :class:`MapPublisher` (:meth:`MapPublisher.submit`: its
statistics and a snapshot of the local map) and goes on with the next frame. Two threads publish:

* the **publisher** thread, in rounds: every frame handed over since the last round gets its
  ``info`` (per-frame statistics, in order, none skipped) and its ``localization_pose``; the newest
  local map of the round is published on ``mapPath`` and ``mapGraph`` and given to the map -> odom
  broadcaster. When frames come faster than it publishes (a bag replayed at 4x), the local maps in
  between are skipped, not queued: RViz shows the newest map, and a 700-node ``mapPath`` (6-40 ms
  to build) is not built four times a second. The latency of a frame (``latencies_s``, ``info``'s
  ``node_latency_ms``) runs from its last message to the publication of a map that holds it.
* the **grid** thread: at most once per ``grid_period_s`` (and busy at most GRID_MAX_SHARE of the
  time: a loaded machine's slow updates are spaced out, not left to take the worker's CPU), the newest local map's occupancy grid
  (:class:`~rtabmap_ros2.core.local_grid.LocalGrid`, its own: the nodes' laser scans and / or depth
  points as ``grid.sensor`` says, incremental, at most ``grid_max_casts`` nodes cast per update, the
  nodes nearest the robot first) on ``map``; it goes on updating while nodes are left to cast (after
  a loop closure moved a large map) even when no new frame comes.

Neither blocks the worker: :meth:`MapPublisher.submit` appends to a list. A publish that fails
(e.g. the context shut down under it) is logged once per kind and the thread goes on.
:meth:`MapPublisher.reset` forgets what is waiting and starts a new grid (the core was reset).
"""

from __future__ import annotations

import threading
import time
import traceback
from collections import deque
from dataclasses import dataclass, field
from typing import Any, Callable, Optional

import numpy as np
from geometry_msgs.msg import PoseStamped

from rtabmap_ros2.core.local_grid import LocalGrid
from rtabmap_ros2.core.local_map import LocalMap
from rtabmap_ros2.core.params import GridParams
from rtabmap_ros2.ros import conversions as conv
from rtabmap_ros2.ros.frame_times import FrameTimer, FrameTimes

PUBLISHER_THREAD = "publisher"
GRID_THREAD = "grid"
# Wake-up period of the threads when idle, so a stop is noticed (s).
POLL_S = 0.1
# The grid thread waits at least its last update's time / this before the next: on 2 cores at load
# 10-18 (issue 50's recording at 1x) its updates took 180-450 ms and it used more CPU than the worker.
GRID_MAX_SHARE = 0.25


@dataclass
class Published:
    """What the worker hands over for one processed frame."""

    stamp_ns: int
    arrival: float                      # time.monotonic() of the frame's last message
    statistics: dict[str, Any]          # Statistics.to_dict()
    local: LocalMap
    localization_pose: Optional[np.ndarray] = None
    worker_times: dict[str, float] = field(default_factory=dict)   # info's node_time_ms of the worker
    generation: int = 0


@dataclass
class Outputs:
    """The node's publishers and what the publisher thread reads from it when it publishes ``info``."""

    path: Any
    graph: Any
    grid: Any
    info: Any
    localization: Any
    tf_broadcaster: Any                 # MapOdomBroadcaster or None (no tf2)
    map_frame: str
    info_extra: Callable[[], dict]      # the node's counters at publish time
    log_error: Callable[[str], None]


class MapPublisher:
    """Publisher and grid threads fed by the worker (module doc)."""

    def __init__(self, outputs: Outputs, grid_params: GridParams, times: FrameTimes, latencies: deque,
                 grid_period_s: float, grid_max_casts: int) -> None:
        self._out = outputs
        self._grid_params = grid_params
        self._times = times
        self.latencies_s = latencies
        self._grid_period_s = grid_period_s
        self._grid_max_casts = grid_max_casts
        self._lock = threading.Lock()
        self._waiting: list[Published] = []
        self._newest: Optional[Published] = None       # the newest local map, for the grid thread
        self._generation = 0
        self._errors: dict[str, int] = {}
        self._stop = threading.Event()
        self._publish_wake = threading.Event()
        self._grid_wake = threading.Event()
        # Held for a whole publishing round: reset() publishes its empty map after the round.
        self.round_lock = threading.Lock()
        self.published_rounds = 0
        self.grids_published = 0
        self._threads = [threading.Thread(target=self._publish_loop, name="rtabmap_publisher", daemon=True),
                         threading.Thread(target=self._grid_loop, name="rtabmap_grid", daemon=True)]
        for thread in self._threads:
            thread.start()

    @property
    def generation(self) -> int:
        return self._generation

    def submit(self, item: Published) -> None:
        """Hand one processed frame over (never blocks on publishing)."""
        with self._lock:
            self._waiting.append(item)
            if item.generation == self._generation:
                self._newest = item
        self._publish_wake.set()
        self._grid_wake.set()

    def reset(self) -> None:
        """The core was reset (called by the worker, between frames): the maps handed over before are
        not published any more (their frames' ``info`` still is) and the grid starts anew."""
        with self._lock:
            self._generation += 1
            self._newest = None

    def stop(self) -> None:
        """End both threads (after the round under way); what waits is not published."""
        self._stop.set()
        self._publish_wake.set()
        self._grid_wake.set()
        for thread in self._threads:
            thread.join()

    # -- publisher thread ----------------------------------------------------------------------
    def _publish_loop(self) -> None:
        while not self._stop.is_set():
            self._publish_wake.wait(POLL_S)
            with self._lock:
                items, self._waiting = self._waiting, []
                self._publish_wake.clear()
            if items:
                self._guarded(lambda: self._publish_round(items))

    def _publish_round(self, items: list[Published]) -> None:
        out, newest = self._out, items[-1]
        timer = FrameTimer()
        with self.round_lock:
            # Frames processed before a reset get their info, not their (forgotten) map.
            current = newest.generation == self._generation
            with timer.part("path"):
                if current:
                    out.path.publish(conv.path_to_msg(newest.local.poses, newest.stamp_ns, out.map_frame))
            now = time.monotonic()
            latencies = [now - item.arrival for item in items]
            if current:
                self.latencies_s.extend(latencies)
            with timer.part("markers"):
                if current:
                    out.graph.publish(conv.graph_to_markers(newest.local.poses, newest.local.links, newest.stamp_ns,
                                                            out.map_frame))
            with timer.part("tf"):
                if out.tf_broadcaster is not None and current:
                    out.tf_broadcaster.update(newest.local.T_map_odom)
                for item in items:
                    if item.localization_pose is not None:
                        out.localization.publish(PoseStamped(header=conv.header(item.stamp_ns, out.map_frame),
                                                             pose=conv.pose_to_msg(item.localization_pose)))
            with timer.part("info"):
                for item, latency in zip(items, latencies):
                    extra = {"node_latency_ms": round(latency * 1e3, 3), **out.info_extra(), **self._times.info(),
                             **item.worker_times}
                    out.info.publish(conv.statistics_to_msg({**item.statistics, **extra}, item.stamp_ns,
                                                            out.map_frame))
            self.published_rounds += 1
        self._times.add(timer, PUBLISHER_THREAD)

    # -- grid thread ---------------------------------------------------------------------------
    def _grid_loop(self) -> None:
        grid, generation, last_map, last_time = LocalGrid(self._grid_params), self._generation, None, -float("inf")
        last_duration = 0.0
        while not self._stop.is_set():
            pending = grid.pending > 0
            period = max(self._grid_period_s, last_duration / GRID_MAX_SHARE)
            wait = last_time + period - time.monotonic()
            if wait > 0:
                if self._stop.wait(wait):
                    return
            elif not pending:
                self._grid_wake.wait(POLL_S)
            with self._lock:
                newest = self._newest
                self._grid_wake.clear()
            if newest is None or (newest is last_map and not grid.pending):
                continue
            if newest.generation != generation:
                grid, generation = LocalGrid(self._grid_params), newest.generation
            last_map, last_time = newest, time.monotonic()
            self._guarded(lambda: self._publish_grid(grid, newest))
            last_duration = time.monotonic() - last_time

    def _publish_grid(self, grid: LocalGrid, newest: Published) -> None:
        timer = FrameTimer()
        with timer.part("local_grid"):
            occupancy = grid.update(newest.local.poses, newest.local.scans, self._grid_max_casts,
                                    newest.local.depth)
        if occupancy is None:
            return
        with timer.part("map"):
            with self._lock:
                current = newest.generation == self._generation
            if current:
                self._out.grid.publish(conv.grid_to_msg(occupancy, newest.stamp_ns, self._out.map_frame))
                self.grids_published += 1
        self._times.add(timer, GRID_THREAD)

    def _guarded(self, publish: Callable[[], None]) -> None:
        """Run ``publish``; an error is logged once per kind (the thread goes on), none after stop."""
        try:
            publish()
        except Exception as exc:  # noqa: BLE001 - a publishing thread must survive (context shut down...)
            if self._stop.is_set():
                return
            frames = traceback.extract_tb(exc.__traceback__)
            kind = f"{type(exc).__name__}" + (f" at {frames[-1].name}:{frames[-1].lineno}" if frames else "")
            self._errors[kind] = self._errors.get(kind, 0) + 1
            if self._errors[kind] == 1:
                self._out.log_error(f"publishing failed: {kind}: {exc} (logged once per kind; the node goes on)\n"
                                    + "".join(traceback.format_exception(exc)).rstrip())


__all__ = ["GRID_THREAD", "MapPublisher", "Outputs", "PUBLISHER_THREAD", "Published"]
