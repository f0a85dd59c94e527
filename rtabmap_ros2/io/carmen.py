"""CARMEN laser logs -> ROS 2 bag with /scan and drifting /odom, plus the reference poses.

The Radish "corrected" logs hold, per ``FLASER`` line, the ranges of a 180 degree planar scan
and the *corrected* pose of the robot (close to ground truth), no raw wheel odometry::

    FLASER n r_0 ... r_{n-1} x y theta odom_x odom_y odom_theta timestamp hostname logger_timestamp

To exercise drift correction, the odometry written to the bag integrates the relative motion
between consecutive corrected poses with seeded Gaussian noise (module constants give the model);
the corrected poses are written as the reference ``ground_truth.txt`` (TUM format, seconds)
inside the bag folder.
"""

from __future__ import annotations

import gzip
import logging
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator, Optional

import numpy as np

from rtabmap_ros2.core import transforms
from rtabmap_ros2.core.sensor import LaserScan, SensorFrame
from rtabmap_ros2.errors import DatasetError
from rtabmap_ros2.io.bag import TopicNames, write_bag

logger = logging.getLogger(__name__)

NS_PER_S = 1_000_000_000
# The CARMEN front laser spans 180 degrees starting at -90 degrees (right of the robot).
SCAN_FOV_RAD = math.pi
SCAN_ANGLE_MIN_RAD = -math.pi / 2
# SICK LMS readings: 81.83 m means "no return"; real returns are below 80 m.
CARMEN_RANGE_MIN_M = 0.0
CARMEN_RANGE_MAX_M = 80.0
# Odometry noise defaults: translation error 2 % of the distance travelled (std-dev, per axis of the
# step; the same fraction of the step's rotation is added to the heading noise), heading error
# 1 degree per metre travelled.
DEFAULT_NOISE_TRANS = 0.02
DEFAULT_NOISE_ROT_DEG_PER_M = 1.0
# Repair of log stamps that do not increase (intel has 4 out of order; csail's stamps were written
# with 6 significant digits, so all are equal): a stamp not after the previous one becomes the
# previous + STAMP_REPAIR_STEP_S; when most stamps need it, they are all replaced by the first
# stamp + i * NOMINAL_SCAN_PERIOD_S (these corrected logs hold roughly one scan per second).
STAMP_REPAIR_STEP_S = 0.001
NOMINAL_SCAN_PERIOD_S = 1.0
# Variance floor (m^2, rad^2) of the odometry covariance (z, roll, pitch, and still robots).
MIN_VARIANCE = 1e-6
GROUND_TRUTH_NAME = "ground_truth.txt"


@dataclass(frozen=True)
class CarmenScan:
    """One FLASER record: ranges (n,, m), corrected pose (m, m, rad) and stamp (ns)."""

    stamp_ns: int
    ranges: np.ndarray
    x: float
    y: float
    theta: float


@dataclass(frozen=True)
class CarmenLog:
    """The FLASER records of a log and the front laser's forward offset (m)."""

    scans: list[CarmenScan]
    laser_offset_m: float

    def laser_scans(self) -> list[LaserScan]:
        """The records as LaserScans (180 degrees from -90, SICK range limits, laser offset)."""
        T_base_laser = transforms.from_xy_yaw(self.laser_offset_m, 0.0, 0.0)
        return [LaserScan(s.ranges, SCAN_ANGLE_MIN_RAD, angle_increment(len(s.ranges)), CARMEN_RANGE_MIN_M,
                          CARMEN_RANGE_MAX_M, T_base_laser) for s in self.scans]

    def poses(self) -> list[np.ndarray]:
        """The corrected poses (4x4 ``T_map_base``) of the records."""
        return [transforms.from_xy_yaw(s.x, s.y, s.theta) for s in self.scans]


def _open_text(path: Path):
    return gzip.open(path, "rt") if path.suffix == ".gz" else open(path, "rt")


def read_carmen_log(path) -> CarmenLog:
    """Parse the FLASER lines (and ``PARAM robot_frontlaser_offset``) of a CARMEN log (.log or .log.gz)."""
    path = Path(path)
    if not path.is_file():
        raise DatasetError(f"CARMEN log {path} does not exist")
    scans: list[CarmenScan] = []
    offset = 0.0
    try:
        with _open_text(path) as f:
            for lineno, line in enumerate(f, start=1):
                tok = line.split()
                if not tok:
                    continue
                if tok[0] == "PARAM" and len(tok) >= 3 and tok[1] == "robot_frontlaser_offset":
                    offset = float(tok[2])
                if tok[0] != "FLASER":
                    continue
                try:
                    n = int(tok[1])
                    ranges = np.array(tok[2:2 + n], dtype=np.float32)
                    x, y, th = (float(v) for v in tok[2 + n:5 + n])
                    stamp_s = float(tok[8 + n])
                except (ValueError, IndexError) as exc:
                    raise DatasetError(f"{path}:{lineno}: malformed FLASER line ({exc})") from exc
                if len(ranges) != n:
                    raise DatasetError(f"{path}:{lineno}: FLASER announces {n} ranges, has {len(ranges)}")
                scans.append(CarmenScan(int(round(stamp_s * NS_PER_S)), ranges, x, y, th))
    except (OSError, EOFError, UnicodeDecodeError) as exc:
        raise DatasetError(f"cannot read CARMEN log {path}: {exc}") from exc
    if not scans:
        raise DatasetError(f"CARMEN log {path} has no FLASER line")
    return CarmenLog(_repair_stamps(scans, path), offset)


def _repair_stamps(scans: list[CarmenScan], path: Path) -> list[CarmenScan]:
    """Strictly increasing stamps (rule: STAMP_REPAIR_STEP_S / NOMINAL_SCAN_PERIOD_S)."""
    stamps = np.array([s.stamp_ns for s in scans], dtype=np.int64)
    bad = int(np.sum(np.diff(stamps) <= 0))
    if bad == 0:
        return scans
    if bad > len(scans) // 2:
        logger.warning("%s: %d of %d scan stamps do not increase: using %.1f s between scans instead",
                       path, bad, len(scans), NOMINAL_SCAN_PERIOD_S)
        fixed = stamps[0] + np.arange(len(scans), dtype=np.int64) * int(NOMINAL_SCAN_PERIOD_S * NS_PER_S)
    else:
        logger.warning("%s: %d scan stamps do not increase: each set %.3f s after the previous one",
                       path, bad, STAMP_REPAIR_STEP_S)
        fixed = stamps.copy()
        for i in range(1, len(fixed)):
            fixed[i] = max(fixed[i], fixed[i - 1] + int(STAMP_REPAIR_STEP_S * NS_PER_S))
    return [CarmenScan(int(t), s.ranges, s.x, s.y, s.theta) for t, s in zip(fixed, scans)]


def angle_increment(n_beams: int) -> float:
    """Beam spacing (rad) of an n-beam 180 degree scan (180 -> 1 deg, 181 -> 1 deg, 361 -> 0.5 deg)."""
    return SCAN_FOV_RAD / (n_beams - 1 if n_beams % 2 else n_beams)


def drifting_odometry(poses: list[np.ndarray], rng: np.random.Generator, noise_trans: float = DEFAULT_NOISE_TRANS,
                      noise_rot_deg_per_m: float = DEFAULT_NOISE_ROT_DEG_PER_M
                      ) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Odometry poses (4x4, odom frame) and per-step 6x6 covariances from reference poses.

    The first odometry pose equals the first reference pose. Each step's relative motion
    (dx, dy, dtheta in the previous robot frame) gets Gaussian noise: std-dev
    ``noise_trans * distance`` on dx and dy, ``radians(noise_rot_deg_per_m) * distance +
    noise_trans * |dtheta|`` on dtheta. The covariance is that of the step's noise
    (diagonal; floor :data:`MIN_VARIANCE`), i.e. the uncertainty of the motion since the previous
    message, as RTAB-Map's odometry links use it.
    """
    rot_per_m = math.radians(noise_rot_deg_per_m)
    odom = [poses[0].copy()]
    covs = [np.eye(6) * MIN_VARIANCE]
    for prev, cur in zip(poses[:-1], poses[1:]):
        dx, dy, dth = transforms.to_xy_yaw(transforms.relative(prev, cur))
        dist = math.hypot(dx, dy)
        s_xy = noise_trans * dist
        s_th = rot_per_m * dist + noise_trans * abs(dth)
        noisy = transforms.from_xy_yaw(dx + rng.normal(0, s_xy) if s_xy > 0 else dx,
                                       dy + rng.normal(0, s_xy) if s_xy > 0 else dy,
                                       dth + rng.normal(0, s_th) if s_th > 0 else dth)
        odom.append(odom[-1] @ noisy)
        var_xy, var_th = max(s_xy ** 2, MIN_VARIANCE), max(s_th ** 2, MIN_VARIANCE)
        covs.append(np.diag([var_xy, var_xy, MIN_VARIANCE, MIN_VARIANCE, MIN_VARIANCE, var_th]))
    return odom, covs


def write_tum(path, stamps_ns: list[int], poses: list[np.ndarray]) -> None:
    """TUM trajectory file: ``stamp tx ty tz qx qy qz qw`` per line, stamps in seconds (9 decimals)."""
    with open(path, "w") as f:
        f.write("# timestamp tx ty tz qx qy qz qw\n")
        for t, T in zip(stamps_ns, poses):
            q = transforms.quat_xyzw(T)
            s, ns = divmod(int(t), NS_PER_S)
            f.write(f"{s}.{ns:09d} {T[0, 3]:.9f} {T[1, 3]:.9f} {T[2, 3]:.9f} "
                    f"{q[0]:.9f} {q[1]:.9f} {q[2]:.9f} {q[3]:.9f}\n")


@dataclass(frozen=True)
class CarmenConversion:
    """What :func:`carmen_to_bag` wrote."""

    bag_path: Path
    ground_truth_path: Path
    scans: int
    odometry_final_error_m: float   # distance between the last odometry and reference positions


def carmen_frames(log: CarmenLog, odom: list[np.ndarray], covs: list[np.ndarray]) -> Iterator[SensorFrame]:
    """SensorFrames (scan + drifting odometry) of a parsed log."""
    for s, scan, T, cov in zip(log.scans, log.laser_scans(), odom, covs):
        yield SensorFrame(stamp_ns=s.stamp_ns, T_odom_base=T, odom_covariance=cov, scan=scan)


def carmen_to_bag(log_path, out, seed: int = 0, noise_trans: float = DEFAULT_NOISE_TRANS,
                  noise_rot_deg_per_m: float = DEFAULT_NOISE_ROT_DEG_PER_M, storage: str = "sqlite3",
                  topics: TopicNames = TopicNames(), ground_truth: Optional[Path] = None) -> CarmenConversion:
    """Convert a CARMEN log to a ROS 2 bag folder ``out`` (/scan, /odom, /tf_static).

    Args:
        log_path: ``.log`` or ``.log.gz`` CARMEN file.
        out: bag folder to create (must not exist).
        seed: seed of the odometry noise.
        noise_trans: translation noise, fraction of the distance travelled (std-dev).
        noise_rot_deg_per_m: heading noise (deg of std-dev per metre travelled).
        ground_truth: TUM file of the corrected poses; default ``out/ground_truth.txt``.
    """
    if noise_trans < 0 or noise_rot_deg_per_m < 0:
        raise DatasetError(f"odometry noise must be >= 0 (got trans {noise_trans}, rot {noise_rot_deg_per_m})")
    log = read_carmen_log(log_path)
    reference = log.poses()
    odom, covs = drifting_odometry(reference, np.random.default_rng(seed), noise_trans, noise_rot_deg_per_m)
    bag_path = write_bag(out, carmen_frames(log, odom, covs), topics=topics, storage=storage)
    gt_path = Path(ground_truth) if ground_truth is not None else bag_path / GROUND_TRUTH_NAME
    write_tum(gt_path, [s.stamp_ns for s in log.scans], reference)
    err = float(np.linalg.norm(odom[-1][:2, 3] - reference[-1][:2, 3]))
    logger.info("%s: %d scans -> %s (final odometry error %.2f m), reference poses -> %s",
                log_path, len(log.scans), bag_path, err, gt_path)
    return CarmenConversion(bag_path, gt_path, len(log.scans), err)
