"""Test helper: two unconnected sessions driving one corridor, and loop closures between them
(used by test_loop_validation.py and test_local_map.py)."""

from __future__ import annotations

import numpy as np

from rtabmap_ros2.core import transforms
from rtabmap_ros2.core.graph import Link, LinkType
from rtabmap_ros2.core.sensor import LaserScan

ODOM_INFO = np.diag(1.0 / np.array([1e-4, 1e-4, 1e-6, 1e-6, 1e-6, 1e-5]))


def two_corridor_sessions(tmp_path):
    """Rtabmap whose memory holds two unconnected sessions driving one corridor (0.5 m steps).

    Session 0 = nodes 1..30 from odometry origin x = 0; session 1 = nodes 31..60, 0.5 m to the
    side, its odometry frame starting at world (0, 0.5): world = odom for session 0, and
    world = T_world_odom1 @ odom for session 1.
    """
    from rtabmap_ros2.core.params import Params
    from rtabmap_ros2.core.rtabmap import Rtabmap
    from rtabmap_ros2.core.signature import Signature

    rtabmap = Rtabmap(Params(), tmp_path / "merge.db")
    memory = rtabmap.memory
    for map_id, first in ((0, 1), (1, 31)):
        memory.map_id = map_id
        for k in range(30):
            sig = Signature(id=first + k, map_id=map_id, stamp_ns=first + k,
                            T_odom_base=transforms.from_xy_yaw(0.5 * k, 0.0, 0.0))
            neighbor = None
            if k:
                neighbor = Link(first + k - 1, first + k, LinkType.NEIGHBOR,
                                transforms.from_xy_yaw(0.5, 0.0, 0.0), ODOM_INFO)
            memory.add_location(sig, None, neighbor)
    return rtabmap


def inter_link(new_id: int, old_id: int, error_xy=(0.0, 0.0)) -> Link:
    """Session-1 node ``new_id`` -> session-0 node ``old_id`` (true relative pose, plus an error)."""
    T_world_new = transforms.from_xy_yaw(0.5 * (new_id - 31), 0.5, 0.0)
    T_world_old = transforms.from_xy_yaw(0.5 * (old_id - 1), 0.0, 0.0)
    T = transforms.inverse(T_world_new) @ T_world_old @ transforms.from_xy_yaw(*error_xy, 0.0)
    return Link(new_id, old_id, LinkType.LOOP_INTER, T, ODOM_INFO)


def corridor_scan(x: float, y: float, n: int = 481) -> LaserScan:
    """A 360-degree scan from (x, y), yaw 0, in the corridor both sessions drive (x -2..16, y -1..1.5,
    door frames at x = 3, 8 and 14.5)."""
    walls = [(-2, -1, 16, -1), (-2, 1.5, 16, 1.5), (-2, -1, -2, 1.5), (16, -1, 16, 1.5)]
    for door in (3.0, 8.0, 14.5):
        walls += [(door, -1, door, -0.4), (door, 0.9, door, 1.5)]
    walls = np.array(walls, float)
    angles = -np.pi + 2 * np.pi * np.arange(n) / n
    d = np.stack([np.cos(angles), np.sin(angles)], axis=1)[:, None, :]
    p, e = walls[None, :, :2] - np.array([x, y]), (walls[:, 2:] - walls[:, :2])[None]
    cross = d[..., 0] * e[..., 1] - d[..., 1] * e[..., 0]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (p[..., 0] * e[..., 1] - p[..., 1] * e[..., 0]) / cross
        u = (p[..., 0] * d[..., 1] - p[..., 1] * d[..., 0]) / cross
    t = np.where((t > 0) & (u >= 0) & (u <= 1), t, np.inf).min(axis=1)
    return LaserScan(np.where(t < 30, t, np.inf), -np.pi, 2 * np.pi / n, 0.1, 30.0)
