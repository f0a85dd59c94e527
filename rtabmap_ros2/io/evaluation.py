"""Precision / recall of loop closure detection against RTAB-Map ground-truth matrices.

RTAB-Map's ground truth for an image sequence is an N x N image: pixel (i, j) is white (255)
when image i+1 closes a loop with image j+1 (1-based image numbers = location ids of ``detect``).

Matching policy. Rehearsal (2013 §III-B) merges the previous location into the new one and keeps
the *older* location's words under the *newer* id, so location ``t`` may show the place of an
earlier image. :func:`origins` follows the ``merged_id`` chains (``origin(t) = origin(c)`` when
``c`` was merged into ``t``); with the *origin* policy a loop closure ``i -> L`` is correct when
``GT[i, L]`` or ``GT[i, origin(L)]``. The *strict* policy checks ``GT[i, L]`` only.

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


def origins(merged_ids: Mapping[int, int]) -> dict[int, int]:
    """Oldest location whose words each location holds, following ``merged_id`` chains.

    Args:
        merged_ids: location id -> id of the location rehearsal merged into it (0 or absent: none).
            Must be given in processing order (older locations first), as ``detect`` rows are.
    """
    out: dict[int, int] = {}
    for location, merged in merged_ids.items():
        out[location] = out.get(merged, merged) if merged else location
    return out


def is_correct(gt: np.ndarray, image: int, location: int, origin: Mapping[int, int] | None = None) -> bool:
    """Is ``image -> location`` (1-based ids) a true loop closure? ``origin`` None = strict policy."""
    if location <= 0 or image <= 0 or image > gt.shape[0] or location > gt.shape[1]:
        return False
    if gt[image - 1, location - 1]:
        return True
    if origin is None:
        return False
    root = origin.get(location, location)
    return 0 < root <= gt.shape[1] and bool(gt[image - 1, root - 1])


def precision_recall(gt: np.ndarray, detections: Iterable[tuple[int, int]],
                     origin: Mapping[int, int] | None = None) -> PrecisionRecall:
    """Precision and recall of accepted loop closures ``(image, location)`` (1-based, location > 0)."""
    accepted = tp = 0
    for image, location in detections:
        if location <= 0:
            continue
        accepted += 1
        tp += is_correct(gt, image, location, origin)
    positives = int(gt.any(axis=1).sum())
    return PrecisionRecall(accepted, tp, positives, tp / accepted if accepted else 1.0,
                           tp / positives if positives else 0.0)


def pr_curve(gt: np.ndarray, hypothesis_ids: Sequence[int], values: Sequence[float],
             origin: Mapping[int, int] | None = None) -> list[CurvePoint]:
    """Precision-recall curve when accepting every hypothesis whose value reaches a threshold.

    Args:
        gt: (N, N) bool ground truth.
        hypothesis_ids: (N,) highest hypothesis id of every image (0 = none), image order.
        values: (N,) highest hypothesis value of every image (RTAB-Map: 1 - p(new location)).
        origin: see :func:`origins`; None = strict policy.

    Returns:
        One point per distinct value (decreasing threshold), each accepting values >= threshold.
    """
    ids = np.asarray(hypothesis_ids, dtype=np.int64)
    vals = np.asarray(values, dtype=float)
    if len(ids) != gt.shape[0] or len(vals) != gt.shape[0]:
        raise DatasetError(f"{len(ids)} detection rows for a {gt.shape[0]}x{gt.shape[0]} ground truth")
    valid = ids > 0
    correct = np.array([is_correct(gt, i + 1, int(h), origin) for i, h in enumerate(ids)], dtype=bool)
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
    merged = {int(r["location_id"]): int(r["merged_id"]) for r in rows if int(r["location_id"]) > 0}
    origin = origins(merged)
    loops = [(k, int(r["loop_closure_id"])) for k, r in enumerate(rows, start=1)]
    hyp_ids = [int(r["highest_hypothesis_id"]) for r in rows]
    values = [float(r["highest_hypothesis_value"]) for r in rows]
    out: dict = {}
    for policy, org in (("origin", origin), ("strict", None)):
        pr = precision_recall(gt, loops, org)
        best, threshold = recall_at_full_precision(pr_curve(gt, hyp_ids, values, org))
        out[policy] = {**pr.to_dict(), "recall_at_100_precision": best, "threshold_at_100_precision": threshold}
    return out


__all__ = ["CurvePoint", "PrecisionRecall", "evaluate_rows", "is_correct", "load_ground_truth", "origins",
           "pr_curve", "precision_recall", "recall_at_full_precision"]
