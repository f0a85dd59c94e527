"""What the process keeps in RAM about *every* node, WM and LTM, in a few bytes a node.

Everything else about an LTM node (signature, links, sensor data) is in the database only, as in
RTAB-Map (2013 §III: LTM is the database). These two tables are what remains, so that RSS stays
flat once WM stops growing (issue 14: with a dict entry and a 4x4 array per node, plus the
links of every node, RAM grew ~2 KB per frame at a constant WM):

* :class:`SessionIds`: node id -> map (session) id, as ranges: ids only grow and a session's
  nodes are created one after the other, so a session is a range of ids (O(sessions) RAM);
* :class:`PoseTable`: the kept pose of a node (its last optimised pose in the world frame), a
  3x4 float64 row indexed by node id (96 bytes a node, no Python object per node).
"""

from __future__ import annotations

import bisect
from typing import Iterable, Iterator, Optional

import numpy as np

_INITIAL_CAPACITY = 1024


class SessionIds:
    """Map id of every node: ``starts[k]`` is the first node id of map ``maps[k]`` (both increasing).

    Dict-like where the code needs it (``[]``, ``get``, ``in``); a node id between two sessions'
    first ids that was never created (or was merged away by rehearsal) still answers the session
    its id falls in: callers ask about nodes they know.
    """

    def __init__(self, firsts: Optional[dict[int, int]] = None, last_id: int = -1) -> None:
        """``firsts``: map id -> first node id of that map, ``last_id`` the largest node id (e.g.
        from the database)."""
        pairs = sorted(((first, m) for m, first in (firsts or {}).items()))
        self._starts = [first for first, _ in pairs]
        self._maps = [m for _, m in pairs]
        self._last_id = max(max(self._starts, default=-1), last_id)

    def add(self, node_id: int, map_id: int) -> None:
        """Record a new node (ids increase; a new map id starts a new range)."""
        if node_id < self._last_id:
            raise ValueError(f"node id {node_id} is smaller than the last one ({self._last_id})")
        self._last_id = node_id
        if not self._maps or self._maps[-1] != map_id:
            self._starts.append(node_id)
            self._maps.append(map_id)

    def get(self, node_id: int, default: Optional[int] = None) -> Optional[int]:
        k = bisect.bisect_right(self._starts, node_id) - 1
        return self._maps[k] if k >= 0 and node_id <= self._last_id else default

    def __getitem__(self, node_id: int) -> int:
        m = self.get(node_id)
        if m is None:
            raise KeyError(node_id)
        return m

    def __contains__(self, node_id: int) -> bool:
        return self.get(node_id) is not None

    def of(self, node_ids: np.ndarray) -> np.ndarray:
        """Map id of each of ``node_ids`` (an int array of any shape), as ``[]`` answers it."""
        k = np.searchsorted(self._starts, node_ids, side="right") - 1
        unknown = (k < 0) | (node_ids > self._last_id)
        if unknown.any():
            raise KeyError(int(np.asarray(node_ids)[unknown].flat[0]))
        return np.asarray(self._maps, dtype=np.int64)[k]

    def id_range(self, map_id: int) -> range:
        """Node ids that fall in map ``map_id`` (empty if it has no node)."""
        for k, m in enumerate(self._maps):
            if m == map_id:
                end = self._starts[k + 1] if k + 1 < len(self._starts) else self._last_id + 1
                return range(self._starts[k], end)
        return range(0)


class PoseTable:
    """Node id -> 4x4 rigid pose, stored as a 3x4 float64 row per id (ids are small and dense)."""

    def __init__(self) -> None:
        self._rows = np.zeros((_INITIAL_CAPACITY, 3, 4))
        self._present = np.zeros(_INITIAL_CAPACITY, dtype=bool)
        self._count = 0

    def _grow(self, node_id: int) -> None:
        capacity = len(self._present)
        if node_id < capacity:
            return
        while capacity <= node_id:
            capacity *= 2
        rows = np.zeros((capacity, 3, 4))
        rows[: len(self._rows)] = self._rows
        present = np.zeros(capacity, dtype=bool)
        present[: len(self._present)] = self._present
        self._rows, self._present = rows, present

    def __setitem__(self, node_id: int, pose: np.ndarray) -> None:
        if node_id < 0:
            raise KeyError(node_id)
        self._grow(node_id)
        self._count += not self._present[node_id]
        self._rows[node_id] = pose[:3]
        self._present[node_id] = True

    def __contains__(self, node_id: int) -> bool:
        return 0 <= node_id < len(self._present) and bool(self._present[node_id])

    def get(self, node_id: int, default: Optional[np.ndarray] = None) -> Optional[np.ndarray]:
        if node_id not in self:
            return default
        pose = np.eye(4)
        pose[:3] = self._rows[node_id]
        return pose

    def __getitem__(self, node_id: int) -> np.ndarray:
        pose = self.get(node_id)
        if pose is None:
            raise KeyError(node_id)
        return pose

    def pop(self, node_id: int, default: Optional[np.ndarray] = None) -> Optional[np.ndarray]:
        pose = self.get(node_id, default)
        if node_id in self:
            self._present[node_id] = False
            self._count -= 1
        return pose

    def update(self, poses: dict[int, np.ndarray]) -> None:
        for node_id, pose in poses.items():
            self[node_id] = pose

    def items_in(self, ids: Iterable[int]) -> dict[int, np.ndarray]:
        """id -> pose of the ids in ``ids`` that have one (all at once)."""
        wanted = np.fromiter(ids, dtype=np.int64)
        wanted = wanted[(wanted >= 0) & (wanted < len(self._present))]
        found = wanted[self._present[wanted]]
        poses = np.tile(np.eye(4), (len(found), 1, 1))
        poses[:, :3] = self._rows[found]
        return dict(zip(found.tolist(), poses))

    def __len__(self) -> int:
        return self._count

    def __iter__(self) -> Iterator[int]:
        return iter(np.flatnonzero(self._present).tolist())
