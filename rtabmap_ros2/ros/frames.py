"""Where the sensors are on the robot, and the map -> odom transform: tf2 when it is importable.

Sensor mounts (``T_base_sensor``, base = the node's ``frame_id``):

* with ``tf2_ros`` importable (a ROS 2 install), each message's ``header.frame_id`` is looked up in
  tf2 from ``frame_id`` at the message's stamp, waiting up to ``wait_for_transform`` (s); a missing
  transform drops the message (the node logs it once per topic);
* without it (rclpy from pip has no tf2_ros), or for a mount whose parameter is set to something else
  than its default: the parameters ``base_to_laser`` and ``base_to_camera`` (``[x, y, z, roll, pitch,
  yaw]``, the camera one for the optical frame of the RGB image).

map -> odom: with tf2 and ``publish_tf``, a :class:`MapOdomBroadcaster` sends the newest correction from
a timer at ``tf_publish_rate``, stamped now + ``tf_delay`` (so listeners interpolating up to "now" find
it), also while the node is paused. Without tf2 nothing is broadcast; the map is on ``mapPath``/``map``.

The node logs once which source is used (:meth:`SensorMounts.describe`).
"""

from __future__ import annotations

import threading
from typing import Optional

import numpy as np

from rtabmap_ros2.core import transforms
from rtabmap_ros2.core.params import NodeParams
from rtabmap_ros2.errors import SensorDataError
from rtabmap_ros2.ros import conversions as conv

LASER = "laser"
CAMERA = "camera"


def import_tf2():
    """The ``tf2_ros`` module, or None when it is not importable (pip install without ROS 2)."""
    try:
        import tf2_ros
    except ImportError:
        return None
    return tf2_ros


class SensorMounts:
    """``T_base_sensor`` of each message: tf2 look-ups, or the ``base_to_*`` parameters."""

    def __init__(self, node, params: NodeParams, tf2=None) -> None:
        self.base_frame = params.frame_id
        self.wait_s = params.wait_for_transform
        defaults = NodeParams()
        self.parameters = {LASER: transforms.from_xyz_rpy(params.base_to_laser),
                           CAMERA: transforms.from_xyz_rpy(params.base_to_camera)}
        # A parameter set to something else than its default wins over tf2 (the user said so).
        self.explicit = {LASER: tuple(params.base_to_laser) != tuple(defaults.base_to_laser),
                         CAMERA: tuple(params.base_to_camera) != tuple(defaults.base_to_camera)}
        self._params = params
        self._tf2 = tf2
        self.buffer = None
        if tf2 is not None:
            # The listener's subscriptions sit in a reentrant group of this node, served by the node's
            # executor while a sensor callback waits in lookup_transform (main() runs 3 threads).
            self.buffer = tf2.Buffer()
            self._listener = tf2.TransformListener(self.buffer, node)

    @property
    def source(self) -> str:
        return "tf2" if self.buffer is not None else "parameters"

    def describe(self) -> str:
        """One log line: where the mounts come from."""
        p = self._params
        params_text = f"base_to_laser {list(p.base_to_laser)}, base_to_camera {[round(v, 4) for v in p.base_to_camera]}"
        if self.buffer is None:
            return (f"sensor mounts: tf2_ros is not available (no ROS 2 install), using the parameters "
                    f"{params_text} [x, y, z, roll, pitch, yaw]; map -> odom is not broadcast on TF")
        explicit = [f"base_to_{s}" for s, on in self.explicit.items() if on]
        return (f"sensor mounts: tf2 ({self.base_frame} -> each message's header.frame_id, waiting up to "
                f"{self.wait_s:g} s)" + (f"; parameters for {', '.join(explicit)} ({params_text})" if explicit else ""))

    def T_base(self, sensor: str, frame_id: str, stamp_ns: int) -> np.ndarray:
        """``T_base_sensor`` (4x4) for a message of ``sensor`` (LASER or CAMERA).

        Raises:
            SensorDataError: tf2 has no transform ``frame_id`` -> ``frame_id`` of the message in time.
        """
        if self.buffer is None or self.explicit[sensor] or not frame_id:
            return self.parameters[sensor].copy()
        frame_id = frame_id.lstrip("/")
        if frame_id == self.base_frame:
            return np.eye(4)
        from rclpy.duration import Duration
        from rclpy.time import Time

        try:
            tf = self.buffer.lookup_transform(self.base_frame, frame_id, Time(nanoseconds=int(stamp_ns)),
                                              timeout=Duration(nanoseconds=int(self.wait_s * 1e9)))
        except Exception as exc:  # noqa: BLE001 - tf2's LookupException, ExtrapolationException...
            raise SensorDataError(
                f"no transform {self.base_frame} -> {frame_id} within {self.wait_s:g} s "
                f"({type(exc).__name__}: {exc}): publish it (robot_state_publisher, static_transform_publisher) "
                f"or set base_to_{sensor}", "no_transform") from exc
        return conv.transform_from_msg(tf)


class MapOdomBroadcaster:
    """The newest map -> odom correction, broadcast on TF from a timer (tf2 only)."""

    def __init__(self, node, params: NodeParams, tf2, callback_group=None) -> None:
        self._node = node
        self._params = params
        self._lock = threading.Lock()
        self._T_map_odom: Optional[np.ndarray] = None
        self._broadcaster = tf2.TransformBroadcaster(node)
        self.sent = 0
        self._timer = node.create_timer(1.0 / params.tf_publish_rate, self.broadcast, callback_group=callback_group)

    def update(self, T_map_odom: np.ndarray) -> None:
        with self._lock:
            self._T_map_odom = np.array(T_map_odom, dtype=np.float64)

    def broadcast(self) -> None:
        """Send the newest correction stamped now + tf_delay (nothing before the first frame)."""
        with self._lock:
            T = self._T_map_odom
        if T is None:
            return
        stamp = self._node.get_clock().now().nanoseconds + int(self._params.tf_delay * 1e9)
        self._broadcaster.sendTransform(conv.transform_to_msg(T, max(stamp, 0), self._params.map_frame_id,
                                                              self._params.odom_frame_id))
        self.sent += 1
