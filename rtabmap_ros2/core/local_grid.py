"""The local map's occupancy grid, kept up to date incrementally (issue 33; off the worker: issue 50).

:class:`LocalGrid` holds a :class:`~rtabmap_ros2.core.grid.GridAccumulator` and what each node
added to it at which pose. :meth:`LocalGrid.update` takes the local map as plain inputs (optimised
poses, laser scans and depth points by node), so its owner can be the core (``LocalMapper.grid``)
or another thread working on a snapshot of the local map (the live node builds its grid beside the
worker).

A node adds its laser scan, or the points of its depth image (``grid.sensor``: a camera-only
robot's grid is its depth images', as ``export``'s; ``core/grid.py`` ``depth_points``), or both.
The depth points are kept with the signature in the base frame, made once when the node is
created, as RTAB-Map keeps a node's local grid: working memory does not hold the images.
"""

from __future__ import annotations

from typing import Mapping, Optional

import numpy as np

from rtabmap_ros2.core.grid import DepthCells, DepthPoints, GridAccumulator, OccupancyGrid, points_cells
from rtabmap_ros2.core.params import GridParams
from rtabmap_ros2.core.sensor import LaserScan

# A node's scan is cast again when its optimised pose moved by more than this fraction of a cell
# (translation, or rotation moving the end of a range_max beam that much): below it the grid drawn
# differs from one cast at the new pose by less than a quarter cell. Issue 33: with 1 mm / 0.001 rad
# every re-optimisation after a loop closure (poses shifting by a few mm) rebuilt the whole grid,
# 80-110 ms median a frame in the node on 50-frame sessions.
GRID_RECAST_CELLS = 0.25
# Longest beam assumed when grid.range_max is 0 (the scans' own range_max) (m).
GRID_DEFAULT_RANGE_M = 5.0


class LocalGrid:
    """Occupancy grid of a local map, updated with the nodes that changed since the last update."""

    def __init__(self, params: GridParams) -> None:
        self.params = params
        self._grid: Optional[GridAccumulator] = None
        # node -> (pose, scan, depth cells) cast into the grid
        self._cast: dict[int, tuple[np.ndarray, Optional[LaserScan], Optional[DepthCells]]] = {}
        # Nodes not cast at their current pose after the last update (a budget left them).
        self.pending = 0

    def reset(self) -> None:
        """Forget every cast node (the next update starts a new grid)."""
        self._grid = None
        self._cast.clear()
        self.pending = 0

    def update(self, poses: Mapping[int, np.ndarray], scans: Mapping[int, LaserScan],
               max_casts: Optional[int] = None, depth: Optional[Mapping[int, DepthPoints]] = None
               ) -> Optional[OccupancyGrid]:
        """The grid of the nodes of ``poses`` that have a scan in ``scans`` or points in ``depth``,
        or None without either.

        Incremental: new nodes are cast into the previous grid; a node that left the local map or
        whose pose moved (more than :data:`GRID_RECAST_CELLS` of a cell) is taken back out at the
        pose it was cast at and cast again at its new pose, so an update costs the nodes that
        changed, not the whole map's. Without ``max_casts``, when most of them moved (a loop
        closure) the grid is cast again from scratch, which is then cheaper.

        With ``max_casts`` (the live node: a loop closure on a map of 700 nodes moved them all and
        recasting them took 1-4 s), at most that many nodes are cast (taken back or added) per
        call: the nodes that left first, then the moved and new ones nearest the newest node (the
        largest id), so the grid around the robot is right first and the rest follows over the
        next calls (``pending`` says how many nodes are not cast at their current pose yet).

        Args:
            poses: node -> 4x4 optimised pose (map frame) of the local map's nodes.
            scans: node -> laser scan.
            max_casts: nodes cast per call at most (None: all).
            depth: node -> its depth image's points (grid.depth_points).
        """
        depth = depth or {}
        views = {n: (scans.get(n), depth.get(n)) for n in poses
                 if scans.get(n) is not None or depth.get(n) is not None}
        if not views:
            self.pending = 0
            return None
        cast = self._cast
        tolerance_m = GRID_RECAST_CELLS * self.params.resolution
        tolerance_rad = tolerance_m / (self.params.range_max or GRID_DEFAULT_RANGE_M)
        left = [n for n in cast if n not in views]
        kept = [n for n in views if n in cast]
        moved = set(np.asarray(kept)[_moved([cast[n][0] for n in kept], [poses[n] for n in kept],
                                             tolerance_m, tolerance_rad)].tolist()) if kept else set()
        if self._grid is None or (max_casts is None and 2 * (len(left) + len(moved)) > len(cast)):
            self._grid = GridAccumulator(self.params)
            cast.clear()
            left, moved = [], set()
        todo = [n for n in views if n not in cast or n in moved]
        budget = len(left) + len(todo) + len(moved) if max_casts is None else max(1, max_casts)
        taken_back = 0
        for node in left[:budget]:   # left the local map: taken back first
            self._take_back(node)
            taken_back += 1
        budget -= taken_back
        if max_casts is not None and len(todo) > budget:
            robot = poses[max(poses)][:2, 3]
            todo.sort(key=lambda n: float(np.linalg.norm(poses[n][:2, 3] - robot)))
        done = 0
        for node in todo:
            cost = 2 if node in moved else 1
            if cost > budget:
                break
            if node in moved:
                self._take_back(node)
            self._cast_node(node, poses[node], *views[node])
            budget -= cost
            done += 1
        self.pending = len(left) - taken_back + len(todo) - done
        return self._grid.grid()

    def _cast_node(self, node: int, pose: np.ndarray, scan: Optional[LaserScan], points: Optional[DepthPoints]
                   ) -> None:
        """Add a node's scan and / or depth cells at ``pose``, remembering what was added."""
        cells = points_cells(pose, points, self.params) if points is not None else None
        if scan is not None:
            self._grid.add(pose, scan)
        if cells is not None:
            self._grid.add_depth(cells)
        self._cast[node] = (pose, scan, cells)

    def _take_back(self, node: int) -> None:
        """Remove exactly what :meth:`_cast_node` added for ``node``."""
        pose, scan, cells = self._cast.pop(node)
        if scan is not None:
            self._grid.add(pose, scan, weight=-1)
        if cells is not None:
            self._grid.add_depth(cells, weight=-1)


def _moved(before: list[np.ndarray], after: list[np.ndarray], tolerance_m: float, tolerance_rad: float) -> np.ndarray:
    """(N,) bool: pose i of ``after`` is ``tolerance_m`` (on an axis) or ``tolerance_rad`` (rotation
    angle of before_i^-1 after_i) or more from pose i of ``before`` (4x4 each), all at once (one
    pose at a time was 40 % of an update's time on a 300-node local map, issue 50)."""
    a, b = np.stack(before), np.stack(after)
    far = np.abs(a[:, :3, 3] - b[:, :3, 3]).max(axis=1) >= tolerance_m
    # trace(Ra^T Rb) = sum of Ra * Rb element by element; angle = arccos((trace - 1) / 2).
    cos = (np.einsum("nij,nij->n", a[:, :3, :3], b[:, :3, :3]) - 1.0) / 2.0
    return far | (np.arccos(np.clip(cos, -1.0, 1.0)) >= tolerance_rad)
