"""When a new map (session) starts: the 2014 paper's multi-session mapping (§III).

"When the robot is turned off and moved, or when odometry is reset, a new map is started": the
2014 paper's robot knows because it is told. A bag or a live odometry stream does not say it, so
:class:`Sessions` infers it frame by frame from the odometry (identity after a pose that was not,
rtabmap_ros' lost-covariance convention, a jump the elapsed time cannot explain, a move across a
long silence), and takes explicit requests (``Rtabmap.trigger_new_map``, the node's
``trigger_new_map`` service). It also turns the odometry covariance into a neighbour link's
information. What the new map does to memory (STM flushed, Bayes filter reset) is ``Rtabmap``'s.
"""

from __future__ import annotations

from collections import deque
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
