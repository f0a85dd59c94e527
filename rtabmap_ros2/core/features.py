"""Location creation, first half (2013 §III-A, Alg. 2 lines 2-3): keypoints and descriptors.

The paper extracted SURF features; SURF is patented and absent from the OpenCV wheels, so the
detectors offered are those of RTAB-Map's later releases:

* ``gftt_orb``: Shi-Tomasi corners (``cv2.GFTTDetector``) described by ORB (RTAB-Map's
  ``Kp/DetectorStrategy=8``, its current default). Binary 256-bit descriptors.
* ``orb``: ORB's own oriented FAST keypoints over an 8-level pyramid. Binary.
* ``sift``: SIFT (float 128-d descriptors), the closest free relative of SURF.

``bench/bench_features.py`` compares them (time, keypoints kept, geometrically correct matches on
TUM pairs). Extraction is deterministic: the same image always gives the same features, in the
same order (strongest response first).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Optional

import cv2
import numpy as np

from rtabmap_ros2.core.params import FeatureParams
from rtabmap_ros2.core.sensor import depth_in_range
from rtabmap_ros2.errors import SensorDataError

logger = logging.getLogger(__name__)

# GFTT settings of RTAB-Map (GFTT/QualityLevel, GFTT/BlockSize; GFTT/MinDistance is
# features.gftt_min_distance_px). A quality level of 0.001 leaves ~1,900 corners on a 640x480 indoor
# frame, so the T_maxFeatures cap (GFTT returns corners strongest first) is what selects the features,
# as Alg. 2 line 2 asks.
GFTT_QUALITY_LEVEL = 0.001
GFTT_BLOCK_SIZE_PX = 3
# ORB settings: RTAB-Map's ORB/* defaults (Parameters.h: ORB/ScaleFactor 2, ORB/NLevels 3,
# ORB/EdgeThreshold 19, ORB/PatchSize 31, ORB/FastThreshold 20), not OpenCV's (1.2, 8, 31): on a
# 240x192 image OpenCV's 31 px band left 236 words per image against the reference's 277 (issue 32).
ORB_SCALE_FACTOR = 2.0
ORB_N_LEVELS = 3
ORB_EDGE_THRESHOLD_PX = 19
ORB_PATCH_SIZE_PX = 31
ORB_FAST_THRESHOLD = 20
# ORB needs a number of features; "all" (max_features = 0) is this many.
ORB_ALL_FEATURES = 100_000
ORB_DESCRIPTOR_BYTES = 32
SIFT_DESCRIPTOR_SIZE = 128


@dataclass(frozen=True)
class Features:
    """Features of one image, strongest response first.

    Attributes:
        keypoints: (N,2) float32 pixel coordinates (x = column, y = row) in the full image.
        descriptors: (N,32) uint8 (binary ORB, Hamming distance) or (N,128) float32 (SIFT, L2).
        responses: (N,) float32 detector responses, non-increasing (detector-specific scale).
    """

    keypoints: np.ndarray
    descriptors: np.ndarray
    responses: np.ndarray

    def __len__(self) -> int:
        return int(self.keypoints.shape[0])


def to_gray(image: np.ndarray) -> np.ndarray:
    """Validate an image and return it as HxW uint8 grey.

    Args:
        image: HxWx3 uint8 RGB or HxW uint8 grey.

    Raises:
        SensorDataError: not a numpy array, not uint8, wrong number of dimensions or channels, or empty.
    """
    if not isinstance(image, np.ndarray):
        raise SensorDataError(f"image must be a numpy array, got {type(image).__name__}")
    if image.dtype != np.uint8:
        raise SensorDataError(
            f"image dtype is {image.dtype}, expected uint8 (convert 16-bit or float images to 8-bit first)")
    if image.ndim == 3 and image.shape[2] == 3:
        gray = cv2.cvtColor(np.ascontiguousarray(image), cv2.COLOR_RGB2GRAY)
    elif image.ndim == 2:
        gray = np.ascontiguousarray(image)
    else:
        raise SensorDataError(f"image shape is {image.shape}, expected HxWx3 (RGB) or HxW (grey)")
    if gray.shape[0] == 0 or gray.shape[1] == 0:
        raise SensorDataError(f"image shape is {image.shape}: the image is empty")
    return gray


def roi_bounds(width: int, height: int, roi_ratios: tuple[float, float, float, float]) -> tuple[int, int, int, int]:
    """Pixel bounds ``(x0, x1, y0, y1)`` (half-open) left after cutting the ROI ratios.

    Args:
        width, height: image size (px).
        roi_ratios: ratios of the width cut at left and right, of the height cut at top and bottom.
    """
    left, right, top, bottom = roi_ratios
    x0 = int(round(left * width))
    x1 = width - int(round(right * width))
    y0 = int(round(top * height))
    y1 = height - int(round(bottom * height))
    return x0, max(x1, x0), y0, max(y1, y0)


class FeatureExtractor:
    """Detects at most ``T_maxFeatures`` features over ``T_response`` and describes them (Alg. 2)."""

    def __init__(self, params: FeatureParams):
        """Create the OpenCV detector/descriptor named by ``params.detector``."""
        self.params = params
        self.binary: bool = params.detector != "sift"
        self.descriptor_size: int = ORB_DESCRIPTOR_BYTES if self.binary else SIFT_DESCRIPTOR_SIZE
        if params.detector in ("gftt_orb", "orb"):
            # ORB itself keeps nfeatures = T_maxFeatures, the strongest of each pyramid level in
            # proportion to the level's area (as RTAB-Map's ORB does): Harris responses of different
            # levels are not comparable, and a global cut would keep the finest scale only.
            n_features = params.max_features if params.max_features > 0 else ORB_ALL_FEATURES
            self._orb = cv2.ORB_create(
                nfeatures=n_features, scaleFactor=ORB_SCALE_FACTOR, nlevels=ORB_N_LEVELS,
                edgeThreshold=ORB_EDGE_THRESHOLD_PX, patchSize=ORB_PATCH_SIZE_PX,
                fastThreshold=ORB_FAST_THRESHOLD)
        if params.detector == "gftt_orb":
            # maxCorners = 0 means "no limit" for OpenCV, as max_features = 0 does here.
            self._gftt = cv2.GFTTDetector_create(
                maxCorners=params.max_features, qualityLevel=GFTT_QUALITY_LEVEL,
                minDistance=params.gftt_min_distance_px, blockSize=GFTT_BLOCK_SIZE_PX)
        if params.detector == "sift":
            self._sift = cv2.SIFT_create(nfeatures=params.max_features)

    def extract(self, image: np.ndarray, depth_m: Optional[np.ndarray] = None) -> Features:
        """Features of an image (Alg. 2 lines 2-3).

        Args:
            image: HxWx3 uint8 RGB or HxW uint8 grey.
            depth_m: its depth image (m, NaN or 0 invalid; registered to it, any size of the same
                aspect ratio), or None. With ``depth_as_mask`` features are detected only where the
                depth is valid and within ``min_depth``..``max_depth`` (RTAB-Map's Mem/DepthAsMask,
                Kp/MinDepth, Kp/MaxDepth); without it (the default here), features outside those
                depths are dropped when either is set.

        Returns:
            :class:`Features`, strongest first, all inside the region of interest.

        Raises:
            SensorDataError: wrong dtype or shape (see :func:`to_gray`).
        """
        gray = to_gray(image)
        mask = self._detection_mask(gray.shape)
        params = self.params
        uses_depth = params.depth_as_mask or params.min_depth > 0 or params.max_depth > 0
        in_depth = self._depth_mask(depth_m, gray.shape) if depth_m is not None and uses_depth else None
        if in_depth is not None and params.depth_as_mask:
            mask &= in_depth
        features = self._extract(gray, mask)
        if in_depth is not None and not params.depth_as_mask:   # the limits, on the features found
            rows = np.clip(np.rint(features.keypoints[:, 1]).astype(np.int64), 0, gray.shape[0] - 1)
            cols = np.clip(np.rint(features.keypoints[:, 0]).astype(np.int64), 0, gray.shape[1] - 1)
            keep = in_depth[rows, cols] > 0
            features = Features(features.keypoints[keep], features.descriptors[keep], features.responses[keep])
        return features

    def _depth_mask(self, depth_m: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
        """uint8 mask (HxW of the image), 255 where the depth is valid and within min..max depth."""
        valid = depth_in_range(np.asarray(depth_m, dtype=np.float32), self.params.min_depth, self.params.max_depth)
        mask = valid.astype(np.uint8) * 255
        if mask.shape != shape:   # depth registered at another size (same aspect ratio): scaled
            mask = cv2.resize(mask, (shape[1], shape[0]), interpolation=cv2.INTER_NEAREST)
        return mask

    def _extract(self, gray: np.ndarray, mask: np.ndarray) -> Features:
        if self.params.detector == "gftt_orb":
            # GFTT corners (at most T_maxFeatures, strongest first), then ORB descriptors; ORB drops
            # the corners too close to the image border to describe (kept below: those described),
            # as RTAB-Map's GFTT_ORB does (a median 346 of 400 corners kept on 640x480 images).
            keypoints = self._gftt.detect(gray, mask)
            keypoints, descriptors = self._orb.compute(gray, keypoints)
        elif self.params.detector == "orb":
            keypoints, descriptors = self._orb.detectAndCompute(gray, mask)
        else:
            keypoints, descriptors = self._sift.detectAndCompute(gray, mask)
        return self._select(keypoints, descriptors)

    def _detection_mask(self, shape: tuple[int, int]) -> np.ndarray:
        """uint8 mask (HxW), 255 where keypoints may be detected: the region of interest."""
        height, width = shape
        x0, x1, y0, y1 = roi_bounds(width, height, self.params.roi_ratios)
        mask = np.zeros((height, width), np.uint8)
        if x1 > x0 and y1 > y0:
            mask[y0:y1, x0:x1] = 255
        return mask

    def _select(self, keypoints, descriptors) -> Features:
        """Apply T_response, sort strongest first (ties by position), keep T_maxFeatures."""
        n = len(keypoints)
        if n == 0 or descriptors is None:
            return self.empty()
        points = np.array([kp.pt for kp in keypoints], np.float32).reshape(n, 2)
        responses = np.array([kp.response for kp in keypoints], np.float32)
        keep = np.ones(n, bool)
        if self.params.response_threshold > 0.0:
            # T_response (Alg. 2 line 2): only features over the threshold; 0 disables the test.
            keep = responses > self.params.response_threshold
        # Deterministic order: response descending, then row, then column.
        order = np.lexsort((points[:, 0], points[:, 1], -responses))
        order = order[keep[order]]
        if self.params.max_features > 0:
            # T_maxFeatures (Alg. 2 line 2): the strongest ones.
            order = order[: self.params.max_features]
        dtype = np.uint8 if self.binary else np.float32
        return Features(
            keypoints=np.ascontiguousarray(points[order]),
            descriptors=np.ascontiguousarray(descriptors[order], dtype=dtype),
            responses=np.ascontiguousarray(responses[order]),
        )

    def empty(self) -> Features:
        """No features, with this extractor's descriptor type and size."""
        dtype = np.uint8 if self.binary else np.float32
        return Features(np.zeros((0, 2), np.float32), np.zeros((0, self.descriptor_size), dtype),
                        np.zeros(0, np.float32))
