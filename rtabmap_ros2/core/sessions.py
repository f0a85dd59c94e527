"""When a new map (session) starts: the 2014 paper's multi-session mapping (§III).

"When the robot is turned off and moved, or when odometry is reset, a new map is started": the
2014 paper's robot knows because it is told. A bag or a live odometry stream does not say it, so
:class:`Sessions` infers it frame by frame from the odometry (identity after a pose that was not,
rtabmap_ros' lost-covariance convention, a jump the elapsed time cannot explain, a move across a
long silence), and takes explicit requests (``Rtabmap.trigger_new_map``, the node's
``trigger_new_map`` service). It also turns the odometry covariance into a neighbour link's
information, and checks that a session's odometry stays on the plane that planar mode
(``registration.planar``, RTAB-Map's Reg/Force3DoF) assumes (:class:`PlanarOdometryCheck`). What the
new map does to memory (STM flushed, Bayes filter reset) is ``Rtabmap``'s.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass
from typing import Optional

import numpy as np

from rtabmap_ros2.core import transforms
from rtabmap_ros2.core.graph import default_information
from rtabmap_ros2.core.params import GraphParams
from rtabmap_ros2.core.sensor import SensorFrame
from rtabmap_ros2.core.sync import NS_PER_S

# rtabmap_ros convention: an odometry covariance this large means odometry was lost / reset.
ODOM_RESET_VARIANCE = 9999.0
# A reset odometry restarts at identity exactly (RTAB-Map's Transform::isIdentity); this only
# absorbs round-off of message conversions (m, rad). Integrated odometry never lands this close.
IDENTITY_TOLERANCE = 1e-6
# Odometry reset detection: the plausible speed across a gap is at least this many times the
# fastest speed seen between consecutive frames over the last ODOM_SPEED_WINDOW frames.
ODOM_SPEED_MARGIN = 2.0
ODOM_SPEED_WINDOW = 20
# The reason new_map_reason gives for a map started on request.
REQUESTED = "requested"
# Planar mode keeps x, y and yaw. Odometry that moves farther than this along the session's first
# pose's z axis, or tilts more than this from it (roll and pitch together), is not a robot on a
# floor: a wheeled robot's odometry stays at 0 (the simulator's and CARMEN's exactly), a hand-held
# camera moves tens of centimetres and degrees (TUM fr1_rpy: 0.17 m, 40 deg).
PLANAR_TOLERANCE_M = 0.1
PLANAR_TOLERANCE_RAD = math.radians(5.0)


class Sessions:
    """Odometry continuity between frames, and requests for a new map."""

    def __init__(self, params: GraphParams) -> None:
        self.params = params
        # Nodes added to the current map: a map without any is never replaced by a new one.
        self.nodes_in_map = 0
        self._requested = False
        # Odometry pose, stamp (ns) and "lost" flag of the previous frame with odometry.
        self._last_odom: Optional[np.ndarray] = None
        self._last_odom_stamp_ns = 0
        self._last_odom_lost = False
        self._speeds: deque[float] = deque(maxlen=ODOM_SPEED_WINDOW)  # m/s, between frames

    def request_new_map(self) -> bool:
        """Ask for a new map at the next frame; False when the current one has no node yet (it is
        the new map)."""
        if self.nodes_in_map:
            self._requested = True
        return bool(self.nodes_in_map)

    def new_map_reason(self, frame: SensorFrame) -> str:
        """Why ``frame`` starts a new map (REQUESTED or an odometry reset), '' when it continues
        the current one. Called once per frame, before its node is added."""
        reset = self.reset_reason(frame)
        self._remember(frame, reset)
        requested, self._requested = self._requested, False
        if not (reset or requested) or not self.nodes_in_map:
            return ""
        self.nodes_in_map = 0
        return REQUESTED if requested else reset

    def reset_reason(self, frame: SensorFrame) -> str:
        """Why ``frame``'s odometry cannot continue the previous frame's ('' when it can).

        Odometry reset detection (2014 §III: a new map starts when odometry is reset), against the
        previous frame with odometry, so that a neighbour link never joins two odometry frames:

        1. identity after a pose that was not: a reset odometry restarts at identity (RTAB-Map's
           Rtabmap::process and rtabmap_ros' CoreWrapper, "Odometry is reset (identity pose
           detected)"), however close to its origin the previous session ended (a robot docking
           where it started; a robot merely driving back to its start never lands on identity);
        2. covariance >= 9999 after one that was not (rtabmap_ros' signal for lost / reset);
        3. a jump that the time between the frames cannot explain: farther than
           ``graph.odom_reset_jump`` + plausible speed x dt (RTAB-Map's
           RGBD/NewMapOdomChangeDistance plus a speed term, so frames lost in between are not a
           reset). This catches a reset whose first frames were lost, the first one received
           already away from the origin. Plausible speed: ``graph.odom_reset_speed``, or
           ODOM_SPEED_MARGIN times the fastest seen over the last frames if that is more; judged
           once the current map has two nodes;
        4. across a silence longer than ``graph.odom_reset_max_gap`` (or a stamp going back: a
           bag replayed), a move farther than ``graph.odom_reset_jump``: odometry is not trusted
           to bridge it.
        """
        pose, last = frame.T_odom_base, self._last_odom
        if pose is None or last is None:
            return ""
        if is_identity(pose) and not is_identity(last):
            return "odometry reset: identity pose"
        if odometry_lost(frame) and not self._last_odom_lost:
            return f"odometry reset: covariance >= {ODOM_RESET_VARIANCE:g}"
        graph = self.params
        if graph.odom_reset_jump <= 0:
            return ""
        jump = float(np.linalg.norm(transforms.relative(last, pose)[:3, 3]))
        dt = (frame.stamp_ns - self._last_odom_stamp_ns) / NS_PER_S
        if not 0 <= dt <= graph.odom_reset_max_gap:
            if jump > graph.odom_reset_jump:
                return f"odometry reset: it moved {jump:.2f} m across {dt:.4g} s between frames"
            return ""
        if self.nodes_in_map < 2:
            # A new map's first step is not judged: it is measured. (A robot faster than
            # odom_reset_speed would otherwise start a new map at every frame.)
            return ""
        speed = max(graph.odom_reset_speed, ODOM_SPEED_MARGIN * max(self._speeds, default=0.0))
        if jump > graph.odom_reset_jump + speed * dt:
            return f"odometry reset: it jumped {jump:.2f} m in {dt:.4g} s (plausible speed {speed:.2f} m/s)"
        return ""

    def _remember(self, frame: SensorFrame, reset: str) -> None:
        """Keep the frame's odometry for the next reset check, and its speed since the last frame."""
        pose = frame.T_odom_base
        if pose is None:
            return
        dt = (frame.stamp_ns - self._last_odom_stamp_ns) / NS_PER_S
        if self._last_odom is not None and not reset and 0 < dt <= self.params.odom_reset_max_gap:
            self._speeds.append(float(np.linalg.norm(transforms.relative(self._last_odom, pose)[:3, 3])) / dt)
        self._last_odom = pose
        self._last_odom_stamp_ns = frame.stamp_ns
        self._last_odom_lost = odometry_lost(frame)


def odometry_information(frame: SensorFrame, default_variance: float) -> np.ndarray:
    """Information of a neighbour link: the odometry covariance where it is usable (positive,
    not the lost / reset convention), ``default_variance`` elsewhere."""
    cov = frame.odom_covariance
    if cov is None:
        return default_information(default_variance)
    variances = np.diag(cov).astype(float).copy()
    variances[~(variances > 0) | (variances >= ODOM_RESET_VARIANCE)] = default_variance
    return np.diag(1.0 / variances)


def is_identity(T: np.ndarray) -> bool:
    """True when the 4x4 ``T`` is identity within IDENTITY_TOLERANCE."""
    return bool(np.abs(T - np.eye(4)).max() <= IDENTITY_TOLERANCE)


def odometry_lost(frame: SensorFrame) -> bool:
    """rtabmap_ros' convention: an x variance of 9999 or more means odometry was lost or reset."""
    cov = frame.odom_covariance
    return cov is not None and cov[0, 0] >= ODOM_RESET_VARIANCE


@dataclass
class OutOfPlane:
    """How far one session's odometry left the plane of its first pose: the largest height (m)
    along the first pose's z axis and the largest tilt (rad, roll and pitch together) from it."""

    map_id: int
    height_m: float = 0.0
    tilt_rad: float = 0.0

    @property
    def planar(self) -> bool:
        """Within :data:`PLANAR_TOLERANCE_M` and :data:`PLANAR_TOLERANCE_RAD`."""
        return self.height_m <= PLANAR_TOLERANCE_M and self.tilt_rad <= PLANAR_TOLERANCE_RAD


class PlanarOdometryCheck:
    """Planar mode meeting odometry that is not planar: measured per session, said once.

    Planar mode flattens every pose and link to x, y and yaw; on a hand-held camera or a robot
    moving in 3D that throws away real motion without a word (a 60-frame hand-held sequence: ATE
    0.078 m planar against 0.003 m in 6 DoF). Each session's odometry is compared with its first
    pose (``T_first^-1 T``: height along the first pose's z axis, tilt of its z axis).
    """

    def __init__(self) -> None:
        self.sessions: dict[int, OutOfPlane] = {}
        self._first: dict[int, np.ndarray] = {}

    def update(self, map_id: int, T_odom_base: np.ndarray) -> Optional[str]:
        """Measure one odometry pose (4x4) of session ``map_id``; the warning to give the first
        time that session leaves the plane, else None."""
        first = self._first.setdefault(map_id, np.asarray(T_odom_base, dtype=np.float64))
        record = self.sessions.setdefault(map_id, OutOfPlane(map_id))
        was_planar = record.planar
        T = transforms.inverse(first) @ T_odom_base
        record.height_m = max(record.height_m, abs(float(T[2, 3])))
        record.tilt_rad = max(record.tilt_rad, float(np.arccos(np.clip(T[2, 2], -1.0, 1.0))))
        if was_planar and not record.planar:
            return (f"map {map_id}: the odometry leaves the plane ({record.height_m:.2f} m up or down, tilted "
                    f"{math.degrees(record.tilt_rad):.0f} deg from the session's first pose; tolerance "
                    f"{PLANAR_TOLERANCE_M} m / {math.degrees(PLANAR_TOLERANCE_RAD):.0f} deg) while planar mode "
                    "(registration.planar, Reg/Force3DoF) keeps x, y and yaw only: for a hand-held camera or a "
                    "robot moving in 3D, set Reg/Force3DoF=false (--set on the command line, -p on the node)")
        return None
