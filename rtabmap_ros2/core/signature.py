"""A location (2013 §III-A) / node (2014 §II): its signature of visual words and its data.

Held in RAM while the location is in STM or WM; in LTM it lives in the database only. Images are
not kept in RAM (they are written to the database at creation); the laser scan is, because loop
closure refinement and the local occupancy grid need it, and so are the depth image's points the
local occupancy grid is drawn from when it uses the depth (``grid.sensor``; grid.DepthPoints).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional

import numpy as np

from rtabmap_ros2.core.grid import DepthPoints
from rtabmap_ros2.core.sensor import CameraModel, LaserScan


@dataclass
class Signature:
    """One location.

    Attributes:
        id: location id (> 0), unique over the database.
        map_id: session (map) the location belongs to.
        stamp_ns: acquisition time.
        weight: number of times the place was seen (rehearsal) plus weights transferred by loop
            closures (2013 §III-B, D).
        word_ids: (N,) int64 visual word of every kept feature (same order as the arrays below).
        keypoints: (N,2) float32 pixel coordinates of the features.
        points3d: (N,3) float32 positions of the words in the base frame (m); NaN without depth.
        T_odom_base: odometry pose (4x4) or None (appearance-only mode).
        scan: laser scan of the node, or None.
        depth_points: the depth image's points for the local occupancy grid (base frame), or None
            (no depth image, or ``grid.sensor`` does not use it for this node).
        camera: camera model of the node's images, or None.
        bad: a bad signature (too few words, 2013 §III-A): kept as a graph node only.
    """

    id: int
    map_id: int
    stamp_ns: int
    word_ids: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    keypoints: np.ndarray = field(default_factory=lambda: np.zeros((0, 2), np.float32))
    points3d: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), np.float32))
    weight: int = 0
    T_odom_base: Optional[np.ndarray] = None
    scan: Optional[LaserScan] = None
    depth_points: Optional[DepthPoints] = None
    camera: Optional[CameraModel] = None
    bad: bool = False

    def word_counts(self) -> dict[int, int]:
        """Occurrences of each word in the signature."""
        ids, counts = np.unique(self.word_ids, return_counts=True)
        return dict(zip(ids.tolist(), counts.tolist()))

    def unique_words(self) -> dict[int, int]:
        """Word -> feature index, for words that occur exactly once (for RANSAC correspondences)."""
        ids, index = self.words_found_once()
        return dict(zip(ids.tolist(), index.tolist()))

    def words_found_once(self) -> tuple[np.ndarray, np.ndarray]:
        """The words that occur exactly once (sorted) and their feature indices."""
        ids, first, counts = np.unique(self.word_ids, return_index=True, return_counts=True)
        once = counts == 1
        return ids[once], first[once]


def similarity(a: dict[int, int], b: dict[int, int]) -> float:
    """Eq. 1: matched word pairs over the size of the larger signature (word -> count maps)."""
    if not a or not b:
        return 0.0
    if len(a) > len(b):
        a, b = b, a
    pairs = sum(min(count, b[word]) for word, count in a.items() if word in b)
    return pairs / max(sum(a.values()), sum(b.values()))
