"""Sensor data of one synchronised frame, ROS-free.

A :class:`SensorFrame` is what the synchroniser (bags and the live node alike) hands to
:meth:`rtabmap_ros2.core.rtabmap.Rtabmap.process`. Every part is optional: an image-only frame
(the 2013 paper's experiments) has just ``rgb``; the 2014 robot has all of them.

Frames: ``base`` is the robot base (``frame_id``), ``odom`` the odometry frame; the camera model
holds ``T_base_camera`` to the *optical* frame (z forward, x right, y down), the scan
``T_base_laser``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Iterator, Optional, Protocol, runtime_checkable

import cv2
import numpy as np

from rtabmap_ros2.core import transforms
from rtabmap_ros2.core.params import SyncParams
from rtabmap_ros2.errors import SensorDataError

MM_PER_M = 1000.0  # 16-bit depth images (16UC1, the database's PNGs) hold millimetres
MAX_DEPTH_MM = 65535  # their largest value: depth is clipped to 65.535 m


def depth_to_mm(depth_m: np.ndarray) -> np.ndarray:
    """HxW uint16 millimetres of an HxW depth (m): NaN, inf and values <= 0 become 0 (invalid),
    depths beyond 65.535 m are clipped to it. Four passes over the image (the database writer
    converts every node's depth: the seven of numpy's nan_to_num / clip took 6.5 ms of a 640x480
    image, these 1.0 ms, to the same millimetres)."""
    d = np.asarray(depth_m)
    with np.errstate(invalid="ignore"):
        invalid = ~(np.isfinite(d) & (d > 0))
        mm = np.multiply(d, MM_PER_M, dtype=np.float64)
        np.minimum(mm, MAX_DEPTH_MM, out=mm)
        np.rint(mm, out=mm)
    mm[invalid] = 0
    return mm.astype(np.uint16)


def depth_from_mm(mm: np.ndarray) -> np.ndarray:
    """HxW float32 metres (0 -> NaN, invalid) of HxW uint16 millimetres."""
    d = mm.astype(np.float32) / np.float32(MM_PER_M)
    d[mm == 0] = np.nan
    return d


@dataclass(frozen=True)
class CameraModel:
    """Pinhole camera: intrinsics (px), the base -> optical frame transform (4x4) and, for images that
    are not rectified, their lens distortion (OpenCV's k1 k2 p1 p2 [k3 ...], a CameraInfo's plumb_bob
    or rational_polynomial D; empty: the images are rectified)."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    T_base_camera: np.ndarray = field(default_factory=transforms.identity)
    distortion: tuple[float, ...] = ()

    def __post_init__(self) -> None:
        if not (self.fx > 0 and self.fy > 0 and np.isfinite([self.fx, self.fy, self.cx, self.cy]).all()):
            raise SensorDataError(
                f"camera model has invalid intrinsics fx={self.fx} fy={self.fy} cx={self.cx} cy={self.cy}: "
                "check the camera_info (K must be filled)", "invalid_intrinsics", "camera_info")
        if self.width <= 0 or self.height <= 0:
            raise SensorDataError(f"camera model has invalid size {self.width}x{self.height}", "invalid_size",
                                  "camera_info")
        if not transforms.is_rigid(self.T_base_camera):
            raise SensorDataError("camera model's T_base_camera is not a rigid 4x4 transform", "invalid_mount",
                                  "camera_info")

    def undistort(self, uv: np.ndarray) -> np.ndarray:
        """Pixels (N,2, float32) of this pinhole model (no distortion) where pixels ``uv`` (N,2) of the
        image as taken are: ``uv`` itself when the images are rectified."""
        uv = np.asarray(uv, dtype=np.float32).reshape(-1, 2)
        if not self.distortion or len(uv) == 0:
            return uv
        K = np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])
        return cv2.undistortPoints(uv.reshape(-1, 1, 2).astype(np.float64), K, np.asarray(self.distortion),
                                   P=K).reshape(-1, 2).astype(np.float32)

    def back_project(self, uv: np.ndarray, depth_m: np.ndarray) -> np.ndarray:
        """Points in the optical frame (N,3, m) of pixels ``uv`` (N,2, px) of the image as taken at
        depths (N,, m): with a lens distortion each point lies on its pixel's undistorted ray."""
        uv = self.undistort(uv).astype(np.float64) if self.distortion else np.asarray(uv, dtype=np.float64)
        z = np.asarray(depth_m, dtype=np.float64)
        x = (uv[:, 0] - self.cx) * z / self.fx
        y = (uv[:, 1] - self.cy) * z / self.fy
        return np.stack([x, y, z], axis=1)

    def project(self, points_camera: np.ndarray) -> np.ndarray:
        """Pixels (N,2) of points in the optical frame (N,3); points behind the camera give NaN."""
        p = np.asarray(points_camera, dtype=np.float64)
        with np.errstate(divide="ignore", invalid="ignore"):
            z = np.where(p[:, 2] > 0, p[:, 2], np.nan)
            return np.stack([p[:, 0] * self.fx / z + self.cx, p[:, 1] * self.fy / z + self.cy], axis=1)

    def scaled(self, width: int, height: int) -> "CameraModel":
        """The same camera at another resolution (e.g. depth registered at half size)."""
        sx, sy = width / self.width, height / self.height
        return CameraModel(self.fx * sx, self.fy * sy, self.cx * sx, self.cy * sy, width, height,
                           self.T_base_camera, self.distortion)


def depth_in_range(depth: np.ndarray, min_depth: float, max_depth: float) -> np.ndarray:
    """Bool array of the depths (m; NaN invalid) that are finite, above ``min_depth`` and at most
    ``max_depth`` (0 = no limit): RTAB-Map's Kp/ and Vis/ MinDepth, MaxDepth."""
    with np.errstate(invalid="ignore"):
        within = np.isfinite(depth) & (depth > min_depth)
        if max_depth > 0:
            within &= depth <= max_depth
    return within


@dataclass(frozen=True)
class LaserScan:
    """A planar laser scan: ranges (N,, m, NaN/inf = no return) and its geometry."""

    ranges: np.ndarray
    angle_min: float
    angle_increment: float
    range_min: float
    range_max: float
    T_base_laser: np.ndarray = field(default_factory=transforms.identity)

    def __post_init__(self) -> None:
        r = np.asarray(self.ranges)
        if r.ndim != 1 or r.size == 0:
            raise SensorDataError(f"laser scan has no ranges (shape {r.shape})", "empty_scan", "scan")
        if not (np.isfinite(self.angle_min) and np.isfinite(self.angle_increment) and self.angle_increment != 0):
            raise SensorDataError(
                f"laser scan has invalid angles: angle_min={self.angle_min} increment={self.angle_increment}",
                "invalid_angles", "scan")
        if not (0 <= self.range_min < self.range_max and np.isfinite(self.range_max)):
            raise SensorDataError(f"laser scan has invalid range limits [{self.range_min}, {self.range_max}]",
                                  "invalid_range_limits", "scan")

    @property
    def angles(self) -> np.ndarray:
        """Beam angles (N,, rad) in the laser frame."""
        return self.angle_min + self.angle_increment * np.arange(len(self.ranges))

    def valid_mask(self) -> np.ndarray:
        """Beams with a return inside [range_min, range_max)."""
        r = np.asarray(self.ranges, dtype=np.float64)
        with np.errstate(invalid="ignore"):
            return np.isfinite(r) & (r >= self.range_min) & (r < self.range_max)

    def points_laser(self) -> np.ndarray:
        """Valid returns as (M,2) points (m) in the laser frame."""
        m = self.valid_mask()
        r = np.asarray(self.ranges, dtype=np.float64)[m]
        a = self.angles[m]
        return np.stack([r * np.cos(a), r * np.sin(a)], axis=1)

    def points_base(self) -> np.ndarray:
        """Valid returns as (M,2) points (m) in the base frame (planar projection)."""
        p = self.points_laser()
        T = self.T_base_laser
        return p @ T[:2, :2].T + T[:2, 3]


@dataclass
class SensorFrame:
    """One synchronised set of sensor data; every part but the stamp is optional.

    Attributes:
        stamp_ns: acquisition time (ns since the epoch, or since the bag's start).
        T_odom_base: odometry pose (4x4, odom frame), or None without odometry.
        odom_covariance: 6x6 covariance of the odometry pose (x y z roll pitch yaw), or None.
        rgb: HxWx3 uint8 image in RGB order, or None.
        depth_m: HxW float32 depth (m) registered to ``rgb``; NaN or 0 = invalid.
        camera: pinhole model of ``rgb`` / ``depth_m``.
        scan: planar laser scan.
        rgb_jpeg, depth_png16_mm: the images as the database stores them (a JPEG; a 16-bit PNG of
            millimetres), when the input came so (a JPEG CompressedImage, a 16UC1 compressedDepth,
            a stored node): stored as they came, not encoded again (the depth PNG took ~11 ms of
            a 640x480 frame). None: encoded from ``rgb`` / ``depth_m``. Whoever changes ``rgb`` or
            ``depth_m`` sets its bytes to None.
    """

    stamp_ns: int
    T_odom_base: Optional[np.ndarray] = None
    odom_covariance: Optional[np.ndarray] = None
    rgb: Optional[np.ndarray] = None
    depth_m: Optional[np.ndarray] = None
    camera: Optional[CameraModel] = None
    scan: Optional[LaserScan] = None
    rgb_jpeg: Optional[bytes] = field(default=None, repr=False)
    depth_png16_mm: Optional[bytes] = field(default=None, repr=False)

    def validate(self, params: Optional[SyncParams] = None) -> None:
        """Raise :class:`SensorDataError` naming the problem when the frame cannot be used.

        Called where frames are made (the node, the bag reader) and again by ``Rtabmap.process``.
        The error's ``reason`` names the fault and its ``source`` the part of the frame at fault.

        Args:
            params: thresholds on valid depth pixels and scan returns (default: SyncParams()).
        """
        params = params if params is not None else SyncParams()
        if self.T_odom_base is not None and not transforms.is_rigid(np.asarray(self.T_odom_base), tol=1e-3):
            raise SensorDataError("odometry pose is not a finite rigid transform (NaN or invalid quaternion?)",
                                  "invalid_pose", "odom")
        if self.odom_covariance is not None:
            c = np.asarray(self.odom_covariance)
            if c.shape != (6, 6) or not np.all(np.isfinite(c)):
                raise SensorDataError(f"odometry covariance must be a finite 6x6 matrix, got shape {c.shape}",
                                      "invalid_covariance", "odom")
        if self.rgb is not None:
            if self.rgb.dtype != np.uint8 or self.rgb.ndim != 3 or self.rgb.shape[2] != 3:
                raise SensorDataError(
                    f"rgb image must be HxWx3 uint8, got shape {self.rgb.shape} dtype {self.rgb.dtype}",
                    "invalid_image", "rgb")
        if self.depth_m is not None:
            self._validate_depth(params.min_valid_depth_ratio)
        if self.camera is not None and self.rgb is not None:
            if (self.camera.width, self.camera.height) != (self.rgb.shape[1], self.rgb.shape[0]):
                raise SensorDataError(
                    f"camera_info size {self.camera.width}x{self.camera.height} differs from the image "
                    f"{self.rgb.shape[1]}x{self.rgb.shape[0]}", "size_mismatch", "camera_info")
        if self.scan is not None:
            self._validate_scan(params.min_valid_scan_ratio)

    def _validate_depth(self, min_valid_ratio: float) -> None:
        d = self.depth_m
        if d.ndim != 2 or d.dtype != np.float32:
            raise SensorDataError(f"depth must be HxW float32 metres, got shape {d.shape} dtype {d.dtype}",
                                  "invalid_image", "depth")
        if np.isinf(d).any():
            raise SensorDataError("depth image contains inf values (use NaN or 0 for invalid depth)",
                                  "inf_depth", "depth")
        if self.rgb is not None and self.rgb.shape[:2] != d.shape:
            raise SensorDataError(
                f"rgb {self.rgb.shape[1]}x{self.rgb.shape[0]} and depth {d.shape[1]}x{d.shape[0]} sizes differ",
                "size_mismatch", "depth")
        if self.camera is None:
            raise SensorDataError("depth image without a camera model (camera_info missing)",
                                  "no_camera_info", "camera_info")
        with np.errstate(invalid="ignore"):
            valid = int(np.count_nonzero(d > 0))   # NaN compares False
        if valid == 0 or valid < min_valid_ratio * d.size:
            raise SensorDataError(
                f"depth image has {valid} valid pixels of {d.size} ({100.0 * valid / d.size:.2f} %, fewer than "
                f"sync.min_valid_depth_ratio = {min_valid_ratio:g}): all NaN or zero?", "no_valid_depth", "depth")

    def _validate_scan(self, min_valid_ratio: float) -> None:
        valid = int(np.count_nonzero(self.scan.valid_mask()))
        beams = len(self.scan.ranges)
        if valid == 0 or valid < min_valid_ratio * beams:
            raise SensorDataError(
                f"laser scan has {valid} valid returns of {beams} beams (fewer than sync.min_valid_scan_ratio = "
                f"{min_valid_ratio:g}; empty, NaN/inf or out of [{self.scan.range_min}, {self.scan.range_max}) m)",
                "no_valid_scan", "scan")


@runtime_checkable
class Dataset(Protocol):
    """A sequence of frames: bags, TUM RGB-D folders, image folders, simulated sessions."""

    def __iter__(self) -> Iterator[SensorFrame]: ...

    def __len__(self) -> int: ...
