"""TUM RGB-D folders -> ROS 2 bags, the way users benchmark RGB-D SLAM (``tum2bag``).

A TUM RGB-D folder (Sturm et al. 2012, the benchmark's "file formats" page):

* ``rgb.txt`` and ``depth.txt``: ``stamp path`` per line (``#`` comments), stamps in seconds;
* ``groundtruth.txt``: ``stamp tx ty tz qx qy qz qw``, the pose of the colour camera's optical
  centre in the motion-capture frame (z up, floor at 0 in the fr1 / fr2 rooms), ~100 Hz;
* ``rgb/*.png`` (640x480 colour) and ``depth/*.png`` (16-bit, :data:`TUM_DEPTH_SCALE` units per
  metre, 0 = no depth, registered pixel for pixel to the colour image).

:func:`tum_to_bag` writes one frame per colour image that has a depth image within 20 ms (the
benchmark's ``associate.py``) and ground truth at its stamp (interpolated between the two samples
around it when they are at most :data:`GROUND_TRUTH_MAX_GAP_S` apart):

* ``/rgb/image`` (rgb8) and ``/depth/image`` (16UC1 millimetres, or 32FC1 metres), both with the
  colour image's stamp and frame ``camera_optical``;
* ``/rgb/camera_info``: the chosen calibration (:data:`CAMERAS`: fr1, fr2, fr3 from the benchmark,
  ``ros`` the ROS default), K = P and D its plumb_bob coefficients: the images are as recorded,
  not rectified (``rectify=True`` undistorts them and writes D = 0);
* ``/odom`` (base_link in odom): the ground truth, optionally with a drift (:func:`drifting_odometry`),
  first pose = the first ground truth pose (odom = the motion-capture frame);
* ``/tf_static``: base_link -> camera_optical, the standard optical rotation at the base origin
  (base_link is the camera body: x forward, y left, z up);
* ``ground_truth.txt`` in the bag folder: the base's true poses at the frames' stamps (TUM
  format, the frame ``export``'s poses.txt is in), as ``carmen2bag`` writes its reference.
"""

from __future__ import annotations

import itertools
import logging
import math
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator, Optional

import cv2
import numpy as np

from rtabmap_ros2.core import transforms
from rtabmap_ros2.core.sensor import CameraModel, SensorFrame
from rtabmap_ros2.errors import DatasetError
from rtabmap_ros2.io.bag import DEFAULT_T_BASE_CAMERA, TopicNames, write_bag
from rtabmap_ros2.io.carmen import GROUND_TRUTH_NAME, MIN_VARIANCE
from rtabmap_ros2.io.datasets import (TUM_DEPTH_SCALE, TUM_MAX_DIFFERENCE_S, associate, read_rgb, read_tum_list,
                                      read_tum_poses)
from rtabmap_ros2.io.trajectory import NS_PER_S, write_tum

logger = logging.getLogger(__name__)

# Ground truth is interpolated between the two samples around a frame when they are at most this
# far apart (the motion capture runs at 100 Hz; a longer gap is a tracking loss).
GROUND_TRUTH_MAX_GAP_S = 0.1
# The odometry message's covariance: the error the drift adds in this long (the default detection
# period, the length of a link between two nodes at 1 Hz).
ODOM_COVARIANCE_PERIOD_S = 1.0
# /depth/image encoding -> write_bag's depth_format.
DEPTH_FORMATS = {"16UC1": "raw", "32FC1": "float"}


@dataclass(frozen=True)
class TumCamera:
    """A calibration: intrinsics (px) of a 640x480 image and plumb_bob distortion (k1 k2 p1 p2 k3)."""

    fx: float
    fy: float
    cx: float
    cy: float
    distortion: tuple[float, float, float, float, float] = (0.0, 0.0, 0.0, 0.0, 0.0)
    width: int = 640
    height: int = 480

    def describe(self) -> str:
        d = " ".join(f"{v:g}" for v in self.distortion)
        return f"fx {self.fx:g} fy {self.fy:g} cx {self.cx:g} cy {self.cy:g}, distortion [{d}]"


# The benchmark's calibrations of its three Kinects (fr3's images are already undistorted) and the
# ROS default it recommends for the pre-registered depth.
CAMERAS = {
    "fr1": TumCamera(517.306408, 516.469215, 318.643040, 255.313989,
                     (0.262383, -0.953104, -0.005358, 0.002628, 1.163314)),
    "fr2": TumCamera(520.908620, 521.007327, 325.141442, 249.701764,
                     (0.231222, -0.784899, -0.003257, -0.000105, 0.917205)),
    "fr3": TumCamera(535.4, 539.2, 320.1, 247.6),
    "ros": TumCamera(525.0, 525.0, 319.5, 239.5),
}
_FOLDER_CAMERA = re.compile(r"(?:freiburg|fr)([123])(?!\d)", re.IGNORECASE)


def camera_from_text(text: str) -> TumCamera:
    """A calibration from ``--camera``: a name of :data:`CAMERAS`, or ``fx,fy,cx,cy`` optionally
    followed by the five distortion coefficients."""
    if text in CAMERAS:
        return CAMERAS[text]
    try:
        values = [float(v) for v in text.replace(",", " ").split()]
    except ValueError:
        values = []
    if len(values) not in (4, 9) or not all(math.isfinite(v) for v in values) or values[0] <= 0 or values[1] <= 0:
        raise DatasetError(f"--camera {text!r}: expected one of {', '.join(CAMERAS)} or fx,fy,cx,cy[,k1,k2,p1,p2,k3] "
                           "(positive focal lengths, px)")
    return TumCamera(*values[:4], tuple(values[4:]) if len(values) == 9 else (0.0,) * 5)


def camera_for_folder(folder: Path) -> tuple[str, TumCamera]:
    """The calibration named by the folder (``rgbd_dataset_freiburg1_xyz`` -> fr1), with its name."""
    match = _FOLDER_CAMERA.search(Path(folder).resolve().name)
    if match is None:
        raise DatasetError(f"{folder}: the folder name does not say which Kinect recorded it (freiburg1/2/3): "
                           f"give --camera {'|'.join(CAMERAS)} or --camera fx,fy,cx,cy[,k1,k2,p1,p2,k3]")
    name = f"fr{match.group(1)}"
    return name, CAMERAS[name]


@dataclass(frozen=True)
class TumFrame:
    """One colour image with its depth image and the base's true pose (4x4 ``T_world_base``)."""

    stamp_ns: int
    rgb_path: Path
    depth_path: Path
    T_world_base: np.ndarray


def tum_frames(folder: Path, max_difference_s: float = TUM_MAX_DIFFERENCE_S,
               T_base_camera: np.ndarray = DEFAULT_T_BASE_CAMERA) -> tuple[list[TumFrame], dict[str, int]]:
    """The folder's frames in time order, and how many colour images were left out and why.

    Raises:
        DatasetError: a missing list or image file, a bad line, no frame left.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise DatasetError(f"TUM RGB-D folder {folder} does not exist")
    rgb = sorted((t, n, r[1]) for n, t, r in read_tum_list(folder / "rgb.txt", 2, "stamp path"))
    depth = sorted((t, n, r[1]) for n, t, r in read_tum_list(folder / "depth.txt", 2, "stamp path"))
    gt_file = folder / "groundtruth.txt"
    if not gt_file.is_file():
        raise DatasetError(f"TUM RGB-D file {gt_file} is missing: tum2bag makes /odom and the reference poses from it")
    gt_stamps, gt_poses = read_tum_poses(gt_file)
    if not len(rgb) or not len(depth) or not len(gt_stamps):
        empty = next(name for name, rows in (("rgb.txt", rgb), ("depth.txt", depth), ("groundtruth.txt", gt_stamps))
                     if not len(rows))
        raise DatasetError(f"{folder / empty} lists nothing")
    order = np.argsort(gt_stamps, kind="stable")
    gt_stamps, gt_poses = gt_stamps[order], gt_poses[order]
    pairs = associate(np.array([t for t, _, _ in rgb], dtype=np.int64),
                      np.array([t for t, _, _ in depth], dtype=np.int64), int(round(max_difference_s * NS_PER_S)))
    T_camera_base = transforms.inverse(T_base_camera)
    frames, no_truth = [], 0
    for i, j in pairs:
        stamp, line, rgb_name = rgb[i]
        _, depth_line, depth_name = depth[j]
        rgb_path, depth_path = folder / rgb_name, folder / depth_name
        for path, list_name, number in ((rgb_path, "rgb.txt", line), (depth_path, "depth.txt", depth_line)):
            if not path.is_file():
                raise DatasetError(f"{folder / list_name}:{number}: image {path} is missing")
        T_world_camera = interpolate_pose(gt_stamps, gt_poses, stamp, GROUND_TRUTH_MAX_GAP_S)
        if T_world_camera is None:
            no_truth += 1
            continue
        frames.append(TumFrame(stamp, rgb_path, depth_path, T_world_camera @ T_camera_base))
    left_out = {"no depth within %g s" % max_difference_s: len(rgb) - len(pairs), "no ground truth": no_truth}
    if not frames:
        raise DatasetError(f"TUM RGB-D folder {folder}: none of the {len(rgb)} colour images has a depth image within "
                           f"{max_difference_s} s and ground truth within {GROUND_TRUTH_MAX_GAP_S} s")
    return frames, {k: v for k, v in left_out.items() if v}


def interpolate_pose(stamps_ns: np.ndarray, poses: np.ndarray, stamp_ns: int, max_gap_s: float) -> Optional[np.ndarray]:
    """Pose (4x4) at ``stamp_ns`` between the samples around it (linear position, spherical linear
    rotation), or None when it is outside them or they are more than ``max_gap_s`` apart.

    Args:
        stamps_ns: (N,) sorted int64 stamps (ns); poses: (N,4,4).
    """
    k = int(np.searchsorted(stamps_ns, stamp_ns))
    if k < len(stamps_ns) and stamps_ns[k] == stamp_ns:
        return poses[k].copy()
    if k == 0 or k == len(stamps_ns) or stamps_ns[k] - stamps_ns[k - 1] > max_gap_s * NS_PER_S:
        return None
    from scipy.spatial.transform import Rotation, Slerp

    t0, t1 = int(stamps_ns[k - 1]), int(stamps_ns[k])
    f = (stamp_ns - t0) / (t1 - t0)
    T = np.eye(4)
    T[:3, :3] = Slerp([0.0, 1.0], Rotation.from_matrix(poses[k - 1:k + 1, :3, :3]))([f]).as_matrix()[0]
    T[:3, 3] = (1 - f) * poses[k - 1, :3, 3] + f * poses[k, :3, 3]
    return T


def drifting_odometry(stamps_ns: list[int], poses: list[np.ndarray], drift_yaw_deg_s: float, drift_m_s: float,
                      rng: np.random.Generator) -> tuple[list[np.ndarray], Optional[list[np.ndarray]]]:
    """Odometry (4x4, the world frame) integrating the true motion with a drift, and its covariance.

    The heading error grows at ``drift_yaw_deg_s`` about the world's vertical (z) and the position
    error at ``drift_m_s`` along a horizontal direction; the heading error's sign and the direction
    are drawn from ``rng``. Each true step (world frame) is turned by the heading error at its end
    and the position drift is added: odometry that drifts as visual or wheel odometry does, with
    roll and pitch (gravity) kept. The first pose is the first true pose.

    Returns:
        ``(poses, covariances)``: per pose, the diagonal 6x6 (x y z roll pitch yaw) of the error the
        drift adds over :data:`ODOM_COVARIANCE_PERIOD_S`, in the body's axes as the mapper reads a
        link's covariance (RTAB-Map's convention): the heading drift about the world's vertical
        falls on the body's roll, pitch and yaw in proportion to the vertical's components in the
        body frame (a camera looking down at a desk turns the drift into roll; a level robot keeps
        it all in yaw), and the position drift's variance on every axis. None without drift (the
        mapper then uses its graph.odom_default_variance).
    """
    yaw_rate = math.radians(drift_yaw_deg_s) * (1.0 if rng.random() < 0.5 else -1.0)
    heading = rng.uniform(0.0, 2.0 * math.pi)
    velocity = drift_m_s * np.array([math.cos(heading), math.sin(heading), 0.0])
    odom = [np.array(poses[0], dtype=np.float64)]
    for k in range(1, len(poses)):
        elapsed = (stamps_ns[k] - stamps_ns[0]) / NS_PER_S
        dt = (stamps_ns[k] - stamps_ns[k - 1]) / NS_PER_S
        R_err = transforms.from_xy_yaw(0.0, 0.0, yaw_rate * elapsed)[:3, :3]
        T = np.eye(4)
        T[:3, :3] = R_err @ poses[k][:3, :3]
        T[:3, 3] = odom[-1][:3, 3] + R_err @ (poses[k][:3, 3] - poses[k - 1][:3, 3]) + velocity * dt
        odom.append(T)
    if drift_yaw_deg_s == 0 and drift_m_s == 0:
        return odom, None
    var_t = max((drift_m_s * ODOM_COVARIANCE_PERIOD_S) ** 2, MIN_VARIANCE)
    var_heading = (math.radians(drift_yaw_deg_s) * ODOM_COVARIANCE_PERIOD_S) ** 2
    covariances = []
    for T in odom:
        up_in_body = T[2, :3]   # the world's vertical in the body's axes (row 2 of R_world_body)
        variances = np.full(6, var_t)
        variances[3:] = np.maximum(var_heading * up_in_body ** 2, MIN_VARIANCE)
        covariances.append(np.diag(variances))
    return odom, covariances


def read_depth_m(path: Path, size: tuple[int, int], depth_scale: float = TUM_DEPTH_SCALE) -> np.ndarray:
    """HxW float32 depth (m, NaN = none) of a TUM depth PNG (16-bit, ``depth_scale`` per metre).

    Args:
        size: (width, height) the depth must have (its colour image's).

    Raises:
        DatasetError: unreadable, not 16-bit single channel, or another size than ``size``.
    """
    raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if raw is None:
        raise DatasetError(f"depth image {path} cannot be read (missing, empty or not an image)")
    if raw.dtype != np.uint16 or raw.ndim != 2:
        raise DatasetError(f"depth image {path} is {raw.dtype} with shape {raw.shape}: a TUM depth image is 16-bit "
                           f"single channel, {depth_scale:g} per metre")
    if (raw.shape[1], raw.shape[0]) != size:
        raise DatasetError(f"depth image {path} is {raw.shape[1]}x{raw.shape[0]}, its colour image "
                           f"{size[0]}x{size[1]}: TUM depth is registered pixel for pixel to the colour image")
    depth = raw.astype(np.float32) / np.float32(depth_scale)
    depth[raw == 0] = np.nan
    return depth


class _Undistorter:
    """Undistortion maps of one calibration (rgb bilinear, depth nearest: no depth invented)."""

    def __init__(self, camera: TumCamera) -> None:
        K = np.array([[camera.fx, 0, camera.cx], [0, camera.fy, camera.cy], [0, 0, 1]])
        self.maps = cv2.initUndistortRectifyMap(K, np.array(camera.distortion), None, K,
                                                (camera.width, camera.height), cv2.CV_32FC1)

    def __call__(self, image: np.ndarray, nearest: bool) -> np.ndarray:
        interpolation = cv2.INTER_NEAREST if nearest else cv2.INTER_LINEAR
        return cv2.remap(image, *self.maps, interpolation, borderMode=cv2.BORDER_CONSTANT,
                         borderValue=float("nan") if nearest else 0)


@dataclass(frozen=True)
class TumConversion:
    """What :func:`tum_to_bag` wrote."""

    bag_path: Path
    ground_truth_path: Path
    frames: int
    left_out: dict[str, int]
    camera: TumCamera
    odometry_final_error_m: float   # distance between the last odometry and true positions


def tum_to_bag(folder, out, camera: Optional[TumCamera] = None, depth_encoding: str = "16UC1",
               drift_yaw_deg_s: float = 0.0, drift_m_s: float = 0.0, seed: int = 0, rectify: bool = False,
               storage: str = "sqlite3", topics: TopicNames = TopicNames()) -> TumConversion:
    """Convert a TUM RGB-D folder to a ROS 2 bag folder ``out`` (module doc).

    Args:
        folder: the TUM folder.
        out: bag folder to create (must not exist).
        camera: calibration; default: the one the folder's name names (fr1 / fr2 / fr3).
        depth_encoding: ``16UC1`` (mm) or ``32FC1`` (m) for /depth/image.
        drift_yaw_deg_s, drift_m_s: odometry drift (>= 0; :func:`drifting_odometry`).
        seed: seed of the drift's sign and direction.
        rectify: undistort the images (bilinear colour, nearest depth) and write D = 0.

    Raises:
        DatasetError: a bad folder (missing file, bad line, unreadable image, depth of the wrong
            size), a bad option.
    """
    folder = Path(folder)
    if depth_encoding not in DEPTH_FORMATS:
        raise DatasetError(f"depth encoding {depth_encoding!r}: choose {' or '.join(DEPTH_FORMATS)}")
    if not (drift_yaw_deg_s >= 0 and drift_m_s >= 0 and math.isfinite(drift_yaw_deg_s) and math.isfinite(drift_m_s)):
        raise DatasetError(f"odometry drift must be finite and >= 0 (got {drift_yaw_deg_s} deg/s, {drift_m_s} m/s)")
    if camera is None:
        _, camera = camera_for_folder(folder)
    frames, left_out = tum_frames(folder)
    for reason, count in left_out.items():
        logger.warning("%s: %d colour images left out (%s)", folder, count, reason)
    truth = [f.T_world_base for f in frames]
    stamps = [f.stamp_ns for f in frames]
    odom, covariances = drifting_odometry(stamps, truth, drift_yaw_deg_s, drift_m_s, np.random.default_rng(seed))
    undistort = _Undistorter(camera) if rectify else None
    bag_path = write_bag(out, _sensor_frames(frames, odom, covariances, camera, undistort), topics=topics,
                         storage=storage, depth_format=DEPTH_FORMATS[depth_encoding],
                         camera_distortion=None if rectify else camera.distortion)
    gt_path = bag_path / GROUND_TRUTH_NAME
    write_tum(gt_path, stamps, truth, "timestamp tx ty tz qx qy qz qw (T_world_base: base_link, the camera body, "
              "in the motion-capture frame; /odom's first pose)")
    error = float(np.linalg.norm(odom[-1][:3, 3] - truth[-1][:3, 3]))
    return TumConversion(bag_path, gt_path, len(frames), left_out, camera, error)


def _sensor_frames(frames: list[TumFrame], odom: list[np.ndarray], covariances: Optional[list[np.ndarray]],
                   camera: TumCamera, undistort: Optional[_Undistorter]) -> Iterator[SensorFrame]:
    """The frames as SensorFrames (images read one at a time)."""
    model = CameraModel(camera.fx, camera.fy, camera.cx, camera.cy, camera.width, camera.height,
                        np.array(DEFAULT_T_BASE_CAMERA))
    for frame, T_odom_base, covariance in zip(frames, odom, covariances or itertools.repeat(None)):
        rgb = read_rgb(frame.rgb_path)
        if rgb is None:
            raise DatasetError(f"colour image {frame.rgb_path} cannot be read (empty or not an image)")
        if (rgb.shape[1], rgb.shape[0]) != (camera.width, camera.height):
            raise DatasetError(f"colour image {frame.rgb_path} is {rgb.shape[1]}x{rgb.shape[0]}, the calibration is "
                               f"for {camera.width}x{camera.height}: give --camera fx,fy,cx,cy for this size")
        depth = read_depth_m(frame.depth_path, (camera.width, camera.height))
        if undistort is not None:
            rgb, depth = undistort(rgb, nearest=False), undistort(depth, nearest=True)
        yield SensorFrame(stamp_ns=frame.stamp_ns, T_odom_base=T_odom_base, odom_covariance=covariance, rgb=rgb,
                          depth_m=depth, camera=model)


__all__ = ["CAMERAS", "GROUND_TRUTH_MAX_GAP_S", "TumCamera", "TumConversion", "TumFrame", "camera_for_folder",
           "camera_from_text", "drifting_odometry", "interpolate_pose", "read_depth_m", "tum_frames", "tum_to_bag"]
