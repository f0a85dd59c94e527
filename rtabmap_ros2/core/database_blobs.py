"""A node's raw sensor data as the map database stores it: RGB as JPEG, depth as a 16-bit PNG (mm).

Images are encoded once, when a node is created (or later, on the background writer's thread,
:meth:`SensorBlobs.deferred`), and kept in the ``sensor_data`` table apart from the graph
(:mod:`rtabmap_ros2.core.database_schema`), so graph-only queries never page through images.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional

import cv2
import numpy as np

from rtabmap_ros2.core.sensor import depth_from_mm, depth_to_mm
from rtabmap_ros2.errors import DatabaseError, SensorDataError

JPEG_QUALITY = 90  # RGB images are stored as JPEG at this quality (0-100)


def encode_rgb(rgb: np.ndarray, quality: int = JPEG_QUALITY) -> bytes:
    """JPEG bytes (``quality``, 0-100) of an HxWx3 uint8 image in RGB order: a node's stored RGB, and a
    CompressedImage's payload (``io.bag``)."""
    if rgb.dtype != np.uint8 or rgb.ndim != 3 or rgb.shape[2] != 3:
        raise SensorDataError(f"encode_rgb needs an HxWx3 uint8 RGB image, got shape {rgb.shape} dtype {rgb.dtype}")
    ok, buf = cv2.imencode(".jpg", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:
        raise SensorDataError(f"OpenCV could not JPEG-encode an image of shape {rgb.shape}")
    return buf.tobytes()


def decode_rgb(data: bytes) -> np.ndarray:
    """HxWx3 uint8 RGB image of JPEG bytes written by :func:`encode_rgb`."""
    bgr = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
    if bgr is None:
        raise DatabaseError(f"stored RGB image ({len(data)} bytes) is not a readable JPEG: the database is damaged")
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)


def encode_depth(depth_m: np.ndarray) -> bytes:
    """16-bit PNG bytes of an HxW depth image (m) stored in millimetres (a node's stored depth, and the
    PNG of a 16UC1 compressedDepth payload, ``io.bag``).

    NaN, inf and values <= 0 become 0 (invalid); depths beyond 65.535 m are clipped to it.
    """
    if depth_m.ndim != 2:
        raise SensorDataError(f"encode_depth needs an HxW depth image (m), got shape {depth_m.shape}")
    mm = depth_to_mm(depth_m)
    ok, buf = cv2.imencode(".png", mm)
    if not ok:
        raise SensorDataError(f"OpenCV could not PNG-encode a depth image of shape {depth_m.shape}")
    return buf.tobytes()


def decode_depth(data: bytes) -> np.ndarray:
    """HxW float32 depth (m) of a PNG written by :func:`encode_depth`; 0 (invalid) becomes NaN."""
    mm = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    if mm is None or mm.dtype != np.uint16 or mm.ndim != 2:
        raise DatabaseError(f"stored depth image ({len(data)} bytes) is not a 16-bit PNG: the database is damaged")
    return depth_from_mm(mm)


@dataclass
class SensorBlobs:
    """A node's raw sensor data, encoded once at node creation.

    Attributes:
        rgb_jpeg: the RGB image as JPEG (:func:`encode_rgb`), or None.
        depth_png16_mm: the depth image as a 16-bit PNG in mm (:func:`encode_depth`), or None.
        odom_covariance: 6x6 float64 covariance of the odometry pose (x y z roll pitch yaw), or None.

    The laser scan and camera model are stored from the :class:`Signature`.
    """

    rgb_jpeg: Optional[bytes] = None
    depth_png16_mm: Optional[bytes] = None
    odom_covariance: Optional[np.ndarray] = None
    # Images still to encode (:meth:`deferred`): (rgb, depth_m), encoded by :meth:`encoded`.
    pending: Optional[tuple[Optional[np.ndarray], Optional[np.ndarray]]] = field(default=None, repr=False,
                                                                                  compare=False)

    @classmethod
    def encode(cls, rgb: Optional[np.ndarray] = None, depth_m: Optional[np.ndarray] = None,
               odom_covariance: Optional[np.ndarray] = None) -> "SensorBlobs":
        """Encode an HxWx3 uint8 RGB image and an HxW float32 depth (m), either may be None."""
        return cls.deferred(rgb, depth_m, odom_covariance).encoded()

    @classmethod
    def deferred(cls, rgb: Optional[np.ndarray] = None, depth_m: Optional[np.ndarray] = None,
                 odom_covariance: Optional[np.ndarray] = None, rgb_jpeg: Optional[bytes] = None,
                 depth_png16_mm: Optional[bytes] = None) -> "SensorBlobs":
        """The images kept (copied) as they are, encoded later by :meth:`encoded`: the background
        writer does it, off the frame's critical path (JPEG + 16-bit PNG took ~8 ms a frame).
        An image already encoded as stored (``rgb_jpeg``, ``depth_png16_mm``: the input's own bytes,
        :class:`~rtabmap_ros2.core.sensor.SensorFrame`) is kept as it is instead."""
        return cls(rgb_jpeg, depth_png16_mm,
                   None if odom_covariance is None else np.asarray(odom_covariance, dtype=np.float64),
                   pending=(None if rgb is None or rgb_jpeg is not None else np.array(rgb),
                            None if depth_m is None or depth_png16_mm is not None else np.array(depth_m)))

    def encoded(self) -> "SensorBlobs":
        """These blobs with the pending images encoded (self when none is pending)."""
        if self.pending is None:
            return self
        rgb, depth_m = self.pending
        return SensorBlobs(self.rgb_jpeg if rgb is None else encode_rgb(rgb),
                           self.depth_png16_mm if depth_m is None else encode_depth(depth_m), self.odom_covariance)

    def rgb(self) -> Optional[np.ndarray]:
        """Decoded HxWx3 uint8 RGB image, or None."""
        return None if self.rgb_jpeg is None else decode_rgb(self.rgb_jpeg)

    def depth_m(self) -> Optional[np.ndarray]:
        """Decoded HxW float32 depth (m, NaN invalid), or None."""
        return None if self.depth_png16_mm is None else decode_depth(self.depth_png16_mm)

