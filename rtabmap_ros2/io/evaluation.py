"""Precision / recall of loop closure detection against RTAB-Map ground-truth matrices.

RTAB-Map's ground truth for an image sequence is an N x N image: pixel (i, j) is white (255)
when image i+1 closes a loop with image j+1 (1-based image numbers = location ids of ``detect``).

Matching policy. Rehearsal (2013 §III-B) merges a new image's location into the previous one when
they look alike (RTAB-Map's rehearsal merge: the older location stays, with its id and words), so
location ``L`` stands for image ``L`` and for the images merged into it (``merged_id`` of the rows
whose ``location_id`` is ``L``: :func:`merged_images`). The *merged* policy counts a loop closure
``i -> L`` correct when ``GT[i, L]`` or ``GT[i, m]`` for an image ``m`` merged into ``L``; the
*strict* policy (``../shared/tools/score_lcd.py``'s) checks ``GT[i, L]`` only.

Recall is over the images that have at least one ground-truth loop closure (RTAB-Map's
definition); precision over the accepted loop closures.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Iterable, Mapping, Sequence

import numpy as np

from rtabmap_ros2.errors import DatasetError

# A ground-truth pixel is a loop closure when brighter than this (RTAB-Map writes 255 / 0).
GT_PIXEL_THRESHOLD = 127


@dataclass(frozen=True)
class PrecisionRecall:
    """Counts and ratios of one set of accepted loop closures."""

    accepted: int  # loop closures accepted
    true_positives: int
    positives: int  # images with at least one ground-truth loop closure
    precision: float  # 1.0 when nothing was accepted
    recall: float

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass(frozen=True)
class CurvePoint:
    """One threshold of a precision-recall curve over the highest hypothesis value."""

    threshold: float
    precision: float
    recall: float
    accepted: int
    true_positives: int


def load_ground_truth(path: str | Path, n_images: int | None = None) -> np.ndarray:
    """RTAB-Map ground-truth image -> (N, N) bool, ``gt[i, j]``: image i+1 closes a loop with j+1.

    Raises:
        DatasetError: the file is missing/unreadable, not square, or not ``n_images`` wide.
    """
    import cv2

    path = Path(path)
    image = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE) if path.is_file() else None
    if image is None:
        raise DatasetError(f"ground truth {path} is missing or is not an image (expected an N x N PNG)")
    if image.shape[0] != image.shape[1]:
        raise DatasetError(f"ground truth {path} is {image.shape[1]}x{image.shape[0]}: it must be square (N x N)")
    if n_images is not None and image.shape[0] != n_images:
        raise DatasetError(f"ground truth {path} is {image.shape[0]}x{image.shape[0]} but the folder has "
                           f"{n_images} images: give the matrix of this sequence")
    return image > GT_PIXEL_THRESHOLD


def merged_images(rows: Iterable[tuple[int, int]]) -> dict[int, tuple[int, ...]]:
    """Images each location stands for besides its own: ``(location_id, merged_id)`` of every row
    (``merged_id`` 0: nothing merged) -> location id -> the images merged into it."""
    out: dict[int, list[int]] = {}
    for location, merged in rows:
        if location > 0 and merged > 0:
            out.setdefault(location, []).append(merged)
    return {location: tuple(images) for location, images in out.items()}


def is_correct(gt: np.ndarray, image: int, location: int,
               merged: Mapping[int, tuple[int, ...]] | None = None) -> bool:
    """Is ``image -> location`` (1-based ids) a true loop closure? ``merged`` None = strict policy."""
    if location <= 0 or image <= 0 or image > gt.shape[0] or location > gt.shape[1]:
        return False
    if gt[image - 1, location - 1]:
        return True
    if merged is None:
        return False
    return any(0 < m <= gt.shape[1] and gt[image - 1, m - 1] for m in merged.get(location, ()))


def precision_recall(gt: np.ndarray, detections: Iterable[tuple[int, int]],
                     merged: Mapping[int, tuple[int, ...]] | None = None) -> PrecisionRecall:
    """Precision and recall of accepted loop closures ``(image, location)`` (1-based, location > 0)."""
    accepted = tp = 0
    for image, location in detections:
        if location <= 0:
            continue
        accepted += 1
        tp += is_correct(gt, image, location, merged)
    positives = int(gt.any(axis=1).sum())
    return PrecisionRecall(accepted, tp, positives, tp / accepted if accepted else 1.0,
                           tp / positives if positives else 0.0)


def pr_curve(gt: np.ndarray, hypothesis_ids: Sequence[int], values: Sequence[float],
             merged: Mapping[int, tuple[int, ...]] | None = None) -> list[CurvePoint]:
    """Precision-recall curve when accepting every hypothesis whose value reaches a threshold.

    Args:
        gt: (N, N) bool ground truth.
        hypothesis_ids: (N,) highest hypothesis id of every image (0 = none), image order.
        values: (N,) highest hypothesis value of every image (RTAB-Map: 1 - p(new location)).
        merged: see :func:`merged_images`; None = strict policy.

    Returns:
        One point per distinct value (decreasing threshold), each accepting values >= threshold.
    """
    ids = np.asarray(hypothesis_ids, dtype=np.int64)
    vals = np.asarray(values, dtype=float)
    if len(ids) != gt.shape[0] or len(vals) != gt.shape[0]:
        raise DatasetError(f"{len(ids)} detection rows for a {gt.shape[0]}x{gt.shape[0]} ground truth")
    valid = ids > 0
    correct = np.array([is_correct(gt, i + 1, int(h), merged) for i, h in enumerate(ids)], dtype=bool)
    positives = int(gt.any(axis=1).sum())
    order = np.argsort(-vals[valid], kind="stable")
    v, c = vals[valid][order], correct[valid][order]
    tp_cum, n_cum = np.cumsum(c), np.arange(1, len(v) + 1)
    points = []
    for k in range(len(v)):
        if k + 1 < len(v) and v[k + 1] == v[k]:
            continue  # ties are accepted together
        points.append(CurvePoint(float(v[k]), float(tp_cum[k] / n_cum[k]),
                                 float(tp_cum[k] / positives) if positives else 0.0, int(n_cum[k]), int(tp_cum[k])))
    return points


def recall_at_full_precision(curve: Sequence[CurvePoint]) -> tuple[float, float | None]:
    """(best recall with 100 % precision, the lowest threshold giving it); (0, None) if none."""
    best, threshold = 0.0, None
    for point in curve:
        if point.precision >= 1.0 and point.recall >= best and point.true_positives > 0:
            best, threshold = point.recall, point.threshold
    return best, threshold


def evaluate_rows(gt: np.ndarray, rows: Sequence[Mapping[str, object]]) -> dict:
    """Everything ``detect --ground-truth`` prints, from its rows (one per image, image order).

    Each row needs ``location_id``, ``loop_closure_id``, ``highest_hypothesis_id``,
    ``highest_hypothesis_value`` and ``merged_id``.
    """
    if len(rows) != gt.shape[0]:
        raise DatasetError(f"{len(rows)} images for a {gt.shape[0]}x{gt.shape[0]} ground truth")
    merged = merged_images((int(r["location_id"]), int(r["merged_id"])) for r in rows)
    loops = [(k, int(r["loop_closure_id"])) for k, r in enumerate(rows, start=1)]
    hyp_ids = [int(r["highest_hypothesis_id"]) for r in rows]
    values = [float(r["highest_hypothesis_value"]) for r in rows]
    out: dict = {}
    for policy, images in (("merged", merged), ("strict", None)):
        pr = precision_recall(gt, loops, images)
        best, threshold = recall_at_full_precision(pr_curve(gt, hyp_ids, values, images))
        out[policy] = {**pr.to_dict(), "recall_at_100_precision": best, "threshold_at_100_precision": threshold}
    return out


__all__ = ["CurvePoint", "PrecisionRecall", "evaluate_rows", "is_correct", "load_ground_truth", "merged_images",
           "pr_curve", "precision_recall", "recall_at_full_precision"]
