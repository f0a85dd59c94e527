"""Datasets that are not bags: a folder of images, a TUM RGB-D sequence.

Both implement the :class:`~rtabmap_ros2.core.sensor.Dataset` protocol (iterate
:class:`SensorFrame` s, ``len``).
"""

from __future__ import annotations

import logging
import re
from decimal import Decimal, InvalidOperation
from pathlib import Path
from typing import Iterator, Optional

import cv2
import numpy as np

from rtabmap_ros2.core import transforms
from rtabmap_ros2.core.sensor import CameraModel, SensorFrame
from rtabmap_ros2.errors import DatasetError
from rtabmap_ros2.io.bag import DEFAULT_T_BASE_CAMERA

logger = logging.getLogger(__name__)

NS_PER_S = 1_000_000_000
IMAGE_EXTENSIONS = (".jpg", ".jpeg", ".png", ".bmp", ".pgm", ".ppm", ".tif", ".tiff")
# Image folders have no clock: image i (1-based) is stamped i seconds.
IMAGE_FOLDER_PERIOD_NS = NS_PER_S

# TUM RGB-D (Sturm et al. 2012): depth PNG value / 5000 = metres; Kinect (fr1) intrinsics of the
# benchmark's default calibration; associate.py's default maximum stamp difference.
TUM_DEPTH_SCALE = 5000.0
TUM_FX, TUM_FY, TUM_CX, TUM_CY = 525.0, 525.0, 319.5, 239.5
TUM_MAX_DIFFERENCE_S = 0.02


def natural_key(name: str) -> list:
    """Sort key putting ``img2`` before ``img10`` (numbers compared as numbers)."""
    return [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", name)]


def read_rgb(path: Path) -> Optional[np.ndarray]:
    """HxWx3 uint8 RGB of an image file (grey images are replicated), or None when unreadable."""
    bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
    return None if bgr is None else cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)


class ImageFolderDataset:
    """Images of a folder in natural order (1, 2, ..., 10), one rgb-only frame each.

    Image ``i`` (1-based, in that order) is stamped ``i`` seconds. An unreadable image is skipped
    with a warning naming it; :meth:`items` still lists it (frame None) so callers can keep the
    1-based image numbering. ``len`` is the number of image files (an unreadable file, found only
    when decoding, makes the iteration one shorter).
    """

    def __init__(self, path) -> None:
        self.path = Path(path)
        if not self.path.is_dir():
            raise DatasetError(f"image folder {self.path} does not exist or is not a folder")
        files = [p for p in self.path.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_EXTENSIONS]
        if not files:
            raise DatasetError(f"image folder {self.path} holds no image ({', '.join(IMAGE_EXTENSIONS)})")
        self.paths: list[tuple[int, Path]] = [
            (i, p) for i, p in enumerate(sorted(files, key=lambda p: natural_key(p.name)), start=1)]

    def __len__(self) -> int:
        return len(self.paths)

    def check_readable(self) -> None:
        """Raise DatasetError when no image of the folder can be decoded (decodes up to the first
        readable one)."""
        if not any(read_rgb(path) is not None for _, path in self.paths):
            raise DatasetError(
                f"none of the {len(self.paths)} image files of {self.path} can be read "
                f"(e.g. {self.paths[0][1].name}): corrupt, empty or not images; nothing to detect")

    def items(self) -> Iterator[tuple[int, Path, Optional[SensorFrame]]]:
        """(1-based image index, path, frame or None when the image cannot be read)."""
        for index, path in self.paths:
            rgb = read_rgb(path)
            if rgb is None:
                logger.warning("image %d (%s) cannot be read: skipped", index, path)
                yield index, path, None
                continue
            yield index, path, SensorFrame(stamp_ns=index * IMAGE_FOLDER_PERIOD_NS, rgb=rgb)

    def __iter__(self) -> Iterator[SensorFrame]:
        for _, _, frame in self.items():
            if frame is not None:
                yield frame


def read_tum_list(path: Path, fields: int, layout: str) -> list[tuple[int, int, list[str]]]:
    """(line number, stamp in ns, fields) of the rows of a TUM text file; comments ('#') and blank
    lines skipped. The stamp (first field) is read exactly (:func:`_to_ns`).

    Args:
        path: the file (``rgb.txt``, ``depth.txt``, ``groundtruth.txt``).
        fields: how many whitespace-separated fields a row has.
        layout: the row's layout for the error message (``"stamp path"``).

    Raises:
        DatasetError: the file is missing or unreadable, or a row has another number of fields or
            a first field that is not a number of seconds (naming the file, line and text).
    """
    if not path.is_file():
        raise DatasetError(f"TUM RGB-D file {path} is missing (a TUM RGB-D folder holds rgb.txt, depth.txt and, "
                           "for ground truth, groundtruth.txt)")
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as exc:
        raise DatasetError(f"cannot read TUM RGB-D file {path}: {exc}") from exc
    rows = []
    for number, line in enumerate(text.splitlines(), start=1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        parts = line.split()
        if len(parts) != fields:
            raise DatasetError(f"{path}:{number}: expected '{layout}' ({fields} fields), got {line[:80]!r}")
        rows.append((number, _to_ns(parts[0], f"{path}:{number}"), parts))
    return rows


def _to_ns(stamp: str, where: str = "TUM") -> int:
    """int ns of a decimal seconds string, exactly (a float64 loses the microseconds of epoch stamps)."""
    try:
        value = Decimal(stamp)
    except InvalidOperation as exc:
        raise DatasetError(f"{where}: stamp {stamp!r} is not a number of seconds") from exc
    if not value.is_finite():
        raise DatasetError(f"{where}: stamp {stamp!r} is not a number of seconds")
    return int((value * NS_PER_S).to_integral_value())


def associate(stamps_a: np.ndarray, stamps_b: np.ndarray, max_difference_ns: int) -> list[tuple[int, int]]:
    """Pairs (i, j) of nearest stamps within ``max_difference_ns``, each index used once.

    Greedy on increasing difference, as the TUM benchmark's ``associate.py``; sorted by ``i``.
    Stamps are int ns arrays (N,) and (M,), b sorted.
    """
    pairs = []
    if len(stamps_b) == 0:
        return pairs
    for i, t in enumerate(stamps_a):
        k = np.searchsorted(stamps_b, t)
        for j in (k - 1, k, k + 1):
            if 0 <= j < len(stamps_b) and abs(int(stamps_b[j]) - int(t)) <= max_difference_ns:
                pairs.append((abs(int(stamps_b[j]) - int(t)), i, j))
    pairs.sort()
    used_a, used_b, out = set(), set(), []
    for _, i, j in pairs:
        if i not in used_a and j not in used_b:
            used_a.add(i)
            used_b.add(j)
            out.append((i, j))
    return sorted(out)


def read_tum_poses(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Stamps (N,) int64 ns and poses (N,4,4) of a TUM trajectory file (``stamp tx ty tz qx qy qz
    qw`` rows), in file order; DatasetError naming the line of a bad row (text, NaN, a zero
    quaternion)."""
    stamps, poses = [], []
    for number, stamp, row in read_tum_list(path, 8, "stamp tx ty tz qx qy qz qw"):
        try:
            values = np.array([float(v) for v in row[1:]])
        except ValueError as exc:
            raise DatasetError(f"{path}:{number}: {exc} in {' '.join(row)!r}") from exc
        if not np.isfinite(values).all() or np.linalg.norm(values[3:]) < 1e-6:
            raise DatasetError(f"{path}:{number}: not a pose (NaN, inf or a zero quaternion): {' '.join(row)!r}")
        stamps.append(stamp)
        poses.append(transforms.from_xyz_quat_xyzw(values[:3], values[3:]))
    return np.array(stamps, dtype=np.int64), np.array(poses).reshape(-1, 4, 4)


class TumRgbdDataset:
    """A TUM RGB-D sequence folder (``rgb.txt``, ``depth.txt``, optional ``groundtruth.txt``).

    rgb and depth images are associated by nearest stamps within ``max_difference_s``; depth PNGs
    hold ``depth_scale`` units per metre (0 = invalid -> NaN). Frames carry no odometry.
    Ground truth (motion capture pose of the colour camera's optical frame) is exposed as base
    poses ``T_world_base = T_world_camera @ inv(T_base_camera)`` by :meth:`ground_truth`.
    """

    def __init__(self, path, fx: float = TUM_FX, fy: float = TUM_FY, cx: float = TUM_CX, cy: float = TUM_CY,
                 depth_scale: float = TUM_DEPTH_SCALE, max_difference_s: float = TUM_MAX_DIFFERENCE_S,
                 T_base_camera: Optional[np.ndarray] = None) -> None:
        self.path = Path(path)
        if not self.path.is_dir():
            raise DatasetError(f"TUM RGB-D folder {self.path} does not exist")
        self.intrinsics = (fx, fy, cx, cy)
        self.depth_scale = float(depth_scale)
        self.T_base_camera = np.array(DEFAULT_T_BASE_CAMERA if T_base_camera is None else T_base_camera,
                                      dtype=np.float64)
        max_diff_ns = int(round(max_difference_s * NS_PER_S))
        rgb = [(t, r[1]) for _, t, r in read_tum_list(self.path / "rgb.txt", 2, "stamp path")]
        depth = sorted((t, r[1]) for _, t, r in read_tum_list(self.path / "depth.txt", 2, "stamp path"))
        pairs = associate(np.array([t for t, _ in rgb], dtype=np.int64),
                          np.array([t for t, _ in depth], dtype=np.int64), max_diff_ns)
        if not pairs:
            raise DatasetError(f"TUM RGB-D folder {self.path}: no rgb/depth pair within {max_difference_s} s")
        # (stamp_ns of rgb, rgb path, depth path)
        self.pairs: list[tuple[int, Path, Path]] = [
            (rgb[i][0], self.path / rgb[i][1], self.path / depth[j][1]) for i, j in pairs]
        self._gt_stamps = np.zeros(0, dtype=np.int64)
        self._gt_poses: list[np.ndarray] = []
        gt_file = self.path / "groundtruth.txt"
        if gt_file.is_file():
            stamps, poses = read_tum_poses(gt_file)
            self._gt_stamps, self._gt_poses = stamps, list(poses)
        self._max_diff_ns = max_diff_ns

    def __len__(self) -> int:
        return len(self.pairs)

    @property
    def stamps_ns(self) -> list[int]:
        """Stamps (ns) of the frames, in order."""
        return [t for t, _, _ in self.pairs]

    def ground_truth(self) -> list[Optional[np.ndarray]]:
        """Per frame, T_world_base (4x4) from the nearest ground truth within the tolerance, else None."""
        out: list[Optional[np.ndarray]] = []
        T_camera_base = transforms.inverse(self.T_base_camera)
        for t, _, _ in self.pairs:
            j = associate(np.array([t]), self._gt_stamps, self._max_diff_ns)
            out.append(self._gt_poses[j[0][1]] @ T_camera_base if j else None)
        return out

    def __iter__(self) -> Iterator[SensorFrame]:
        fx, fy, cx, cy = self.intrinsics
        for stamp_ns, rgb_path, depth_path in self.pairs:
            rgb = read_rgb(rgb_path)
            raw = cv2.imread(str(depth_path), cv2.IMREAD_UNCHANGED)
            if rgb is None or raw is None or raw.ndim != 2:
                logger.warning("TUM frame at %.6f s skipped: cannot read %s", stamp_ns / NS_PER_S,
                               rgb_path if rgb is None else depth_path)
                continue
            depth = raw.astype(np.float32) / np.float32(self.depth_scale)
            depth[raw == 0] = np.nan
            camera = CameraModel(fx, fy, cx, cy, rgb.shape[1], rgb.shape[0], self.T_base_camera)
            yield SensorFrame(stamp_ns=stamp_ns, rgb=rgb, depth_m=depth, camera=camera)
