"""A location (2013 §III-A) / node (2014 §II): its signature of visual words and its data.

Held in RAM while the location is in STM or WM; in LTM it lives in the database only. Images are
not kept in RAM (they are written to the database at creation); the laser scan is, because loop
closure refinement and the local occupancy grid need it.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional, Sequence

import numpy as np

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


def aligned_words(query: Signature, others: Sequence[Signature], radius_px: float) -> list[float]:
    """For each of ``others``: how much of ``query``'s view it shows in place. The words found once
    in both vote for the shift between the two images (their keypoints' offsets; the median is the
    shift); those within ``radius_px`` of it agree, and their count is weighted by the fraction of
    the frame the two views share at that shift (1 - |shift| / image size, per axis, the image size
    taken from ``query``'s keypoints). Two overlapping views of a place share many words, but the
    one shifted by half a frame shows only half of this image: the view closest to ``query``'s
    scores highest."""
    extent = np.ptp(query.keypoints, axis=0) if len(query.keypoints) else np.zeros(2)
    if not np.all(extent > 0):
        return [0.0] * len(others)
    mine, mine_index = query.words_found_once()
    mine_xy = query.keypoints[mine_index]
    scores = []
    for other in others:
        theirs, their_index = other.words_found_once()
        _, i, j = np.intersect1d(mine, theirs, assume_unique=True, return_indices=True)
        if not len(i):
            scores.append(0.0)
            continue
        offsets = mine_xy[i] - other.keypoints[their_index[j]]
        shift = np.median(offsets, axis=0)
        agreeing = np.count_nonzero(np.hypot(*(offsets - shift).T) <= radius_px)
        shared_frame = np.prod(np.clip(1.0 - np.abs(shift) / extent, 0.0, 1.0))
        scores.append(float(agreeing * shared_frame))
    return scores


def similarity(a: dict[int, int], b: dict[int, int]) -> float:
    """Eq. 1: matched word pairs over the size of the larger signature (word -> count maps)."""
    if not a or not b:
        return 0.0
    if len(a) > len(b):
        a, b = b, a
    pairs = sum(min(count, b[word]) for word, count in a.items() if word in b)
    return pairs / max(sum(a.values()), sum(b.values()))
