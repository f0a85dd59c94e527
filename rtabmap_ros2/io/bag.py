"""Bags: read ROS 1 / ROS 2 bags into :class:`SensorFrame` s, write ROS 2 (and ROS 1) bags.

Everything goes through ``rosbags`` (no ROS install needed): :class:`rosbags.highlevel.AnyReader`
reads ROS 1 ``.bag`` files and ROS 2 bag folders (``metadata.yaml`` + ``.db3`` or ``.mcap``);
:func:`write_bag` writes ROS 2 bags with the Jazzy typestore, :func:`write_ros1_bag` ROS 1 bags
with the Noetic one.

The message <-> numpy conversions live here as matched pairs working on ``rosbags`` message
objects (not rclpy): :func:`stamp_to_msg` / :func:`stamp_from_msg`, :func:`odometry_to_msg` /
:func:`odometry_from_msg`, :func:`scan_to_msg` / :func:`scan_from_msg`, :func:`image_to_msg` /
:func:`image_from_msg`, :func:`depth_to_msg` / :func:`depth_from_msg`,
:func:`compressed_image_to_msg` / :func:`compressed_image_from_msg`,
:func:`compressed_depth_to_msg` / :func:`compressed_depth_from_msg`,
:func:`camera_info_to_msg` / :func:`camera_info_from_msg`, :func:`transform_to_msg` /
:func:`transform_from_msg`.

Frames of a bag. Bags of this kind rarely carry ``/tf_static``, so the base -> sensor transforms
are, in order of precedence: the ``T_base_camera`` / ``T_base_laser`` arguments of
:class:`BagDataset`; the bag's ``/tf_static`` when it links the odometry's ``child_frame_id``
(else ``base_link``) to the image's / scan's ``frame_id``; the module defaults
:data:`DEFAULT_T_BASE_CAMERA` (optical frame at the base origin, standard optical rotation) and
:data:`DEFAULT_T_BASE_LASER` (identity).

Synchronisation: the streams go through the one :class:`FrameSynchronizer` (pivot rgb, else scan);
odometry is a synchronised stream like the others, i.e. the odometry message *nearest* to the
frame's stamp within ``tolerance_s`` (not interpolated). ``camera_info`` is not synchronised: the
newest camera_info received is attached to the frame (drivers publish it with every image, some
only once), and image frames before the first camera_info are skipped with a warning.
"""

from __future__ import annotations

import logging
import struct
from dataclasses import dataclass, fields
from functools import lru_cache
from pathlib import Path
from typing import Iterable, Iterator, Optional

import cv2
import numpy as np

from rtabmap_ros2.core import transforms
from rtabmap_ros2.core.database_blobs import JPEG_QUALITY, encode_depth, encode_rgb
from rtabmap_ros2.core.params import SyncParams
from rtabmap_ros2.core.sensor import CameraModel, LaserScan, SensorFrame, depth_from_mm, depth_to_mm
from rtabmap_ros2.core.sync import FrameSynchronizer, SyncedSet
from rtabmap_ros2.errors import BagError, SensorDataError

logger = logging.getLogger(__name__)

NS_PER_S = 1_000_000_000

# Stream names (the keys of FrameSynchronizer sets), in TopicNames' order.
STREAMS = ("odom", "scan", "rgb", "depth", "camera_info")

# Base -> camera optical frame used when neither the caller nor /tf_static gives one: the optical
# frame at the base origin (x = y = z = 0 m) with the standard optical rotation: optical z (forward)
# = base x, optical x (right) = -base y, optical y (down) = -base z. Columns = optical axes in base.
DEFAULT_T_BASE_CAMERA = np.array([
    [0.0, 0.0, 1.0, 0.0],
    [-1.0, 0.0, 0.0, 0.0],
    [0.0, -1.0, 0.0, 0.0],
    [0.0, 0.0, 0.0, 1.0],
])
DEFAULT_T_BASE_CAMERA.setflags(write=False)
# write_bag's depth_format -> Image encoding of the raw depth topic.
DEPTH_ENCODINGS = {"raw": "16UC1", "float": "32FC1"}
# Base -> laser used when neither the caller nor /tf_static gives one: the laser at the base origin.
DEFAULT_T_BASE_LASER = np.eye(4)
DEFAULT_T_BASE_LASER.setflags(write=False)

DEFAULT_BASE_FRAME = "base_link"
TF_STATIC_TOPIC = "/tf_static"
COMPRESSED_SUFFIX = "/compressed"
COMPRESSED_DEPTH_SUFFIX = "/compressedDepth"
JPEG_FORMAT = "rgb8; jpeg compressed bgr8"
COMPRESSED_DEPTH_FORMAT = "16UC1; compressedDepth png"

# image_transport's compressedDepth payload: a ConfigHeader (int32 format, float32 depthQuantA,
# float32 depthQuantB) before the PNG.
COMPRESSED_DEPTH_HEADER = struct.Struct("<iff")
PNG_MAGIC = b"\x89PNG"
JPEG_MAGIC = b"\xff\xd8\xff"

# Colour encodings (sensor_msgs/image_encodings names, lower case): (channels, dtype, cv2 conversion to
# RGB). 16-bit ones are scaled to 8 bits first (>> 8). Bayer patterns follow cv_bridge's mapping to
# OpenCV's names (OpenCV names the pattern by the 2x2 block starting at the second row and column).
_COLOR_ENCODINGS = {
    "rgb8": (3, np.uint8, None),
    "bgr8": (3, np.uint8, cv2.COLOR_BGR2RGB),
    "rgba8": (4, np.uint8, cv2.COLOR_RGBA2RGB),
    "bgra8": (4, np.uint8, cv2.COLOR_BGRA2RGB),
    "mono8": (1, np.uint8, cv2.COLOR_GRAY2RGB),
    "8uc1": (1, np.uint8, cv2.COLOR_GRAY2RGB),
    "8uc3": (3, np.uint8, cv2.COLOR_BGR2RGB),
    "mono16": (1, np.uint16, cv2.COLOR_GRAY2RGB),
    "rgb16": (3, np.uint16, None),
    "bgr16": (3, np.uint16, cv2.COLOR_BGR2RGB),
    "bayer_rggb8": (1, np.uint8, cv2.COLOR_BayerBG2RGB),
    "bayer_bggr8": (1, np.uint8, cv2.COLOR_BayerRG2RGB),
    "bayer_gbrg8": (1, np.uint8, cv2.COLOR_BayerGR2RGB),
    "bayer_grbg8": (1, np.uint8, cv2.COLOR_BayerGB2RGB),
    "bayer_rggb16": (1, np.uint16, cv2.COLOR_BayerBG2RGB),
    "bayer_bggr16": (1, np.uint16, cv2.COLOR_BayerRG2RGB),
    "bayer_gbrg16": (1, np.uint16, cv2.COLOR_BayerGR2RGB),
    "bayer_grbg16": (1, np.uint16, cv2.COLOR_BayerGB2RGB),
    # 4:2:2 YUV, 2 bytes per pixel: "yuv422" is UYVY (cv_bridge), "yuv422_yuy2" / "yuyv" are YUYV.
    "yuv422": (2, np.uint8, cv2.COLOR_YUV2RGB_UYVY),
    "uyvy": (2, np.uint8, cv2.COLOR_YUV2RGB_UYVY),
    "yuv422_yuy2": (2, np.uint8, cv2.COLOR_YUV2RGB_YUYV),
    "yuyv": (2, np.uint8, cv2.COLOR_YUV2RGB_YUYV),
}
# Bayer mosaics: the RGB channel seen at (row % 2, column % 2).
_BAYER_CHANNELS = {"rggb": ((0, 1), (1, 2)), "bggr": ((2, 1), (1, 0)), "gbrg": ((1, 2), (0, 1)),
                   "grbg": ((1, 0), (2, 1))}
_RGB_TO_YUV601 = np.array([[0.257, 0.504, 0.098], [-0.148, -0.291, 0.439], [0.439, -0.368, -0.071]])
_DEPTH_MM_ENCODINGS = ("16uc1", "mono16")
_DEPTH_M_ENCODINGS = ("32fc1",)

ODOM_TYPE = "nav_msgs/msg/Odometry"
SCAN_TYPE = "sensor_msgs/msg/LaserScan"
IMAGE_TYPE = "sensor_msgs/msg/Image"
COMPRESSED_TYPE = "sensor_msgs/msg/CompressedImage"
CAMERA_INFO_TYPE = "sensor_msgs/msg/CameraInfo"
TF_TYPE = "tf2_msgs/msg/TFMessage"
# The message types each stream is read from (rosbags names ROS 1 types the same way).
STREAM_TYPES = {"odom": (ODOM_TYPE,), "scan": (SCAN_TYPE,), "rgb": (IMAGE_TYPE, COMPRESSED_TYPE),
                "depth": (IMAGE_TYPE, COMPRESSED_TYPE), "camera_info": (CAMERA_INFO_TYPE,)}
TF_MSG_DEFINITION = "geometry_msgs/TransformStamped[] transforms"


@dataclass(frozen=True)
class TopicNames:
    """Topic of each stream. Compressed images are found at ``<rgb>/compressed`` and
    ``<depth>/compressedDepth`` when the raw topic is absent."""

    odom: str = "/odom"
    scan: str = "/scan"
    rgb: str = "/rgb/image"
    depth: str = "/depth/image"
    camera_info: str = "/rgb/camera_info"

    def of(self, stream: str) -> str:
        """Topic of ``stream`` (one of :data:`STREAMS`)."""
        return getattr(self, stream)


@dataclass(frozen=True)
class FrameIds:
    """Frame ids written into the headers by :func:`write_bag`."""

    base: str = DEFAULT_BASE_FRAME
    odom: str = "odom"
    camera: str = "camera_optical"
    laser: str = "laser"


# --------------------------------------------------------------------------------------------
# Typestores and message construction
# --------------------------------------------------------------------------------------------

@lru_cache(maxsize=None)
def typestore(ros1: bool = False):
    """The Jazzy (ROS 2) or Noetic (ROS 1) typestore of rosbags."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore
    ts = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_JAZZY)
    if TF_TYPE not in ts.types:
        # Noetic's store lacks tf2_msgs; its definition is one line.
        ts.register(get_types_from_msg(TF_MSG_DEFINITION, TF_TYPE))
    return ts


def _make(ts, msgtype: str, **values):
    """Build a message of ``msgtype`` in typestore ``ts``; fills ROS 1's ``seq`` and ``K``/``D``..."""
    cls = ts.types[msgtype]
    names = {f.name for f in fields(cls)}
    kwargs = {}
    for k, v in values.items():
        kwargs[k if k in names else k.upper()] = v
    if "seq" in names and "seq" not in kwargs:
        kwargs["seq"] = 0
    return cls(**kwargs)


def _field(msg, name: str):
    """Field ``name`` of a ROS 2 message, or its upper-case ROS 1 spelling (CameraInfo's K...)."""
    try:
        return getattr(msg, name)
    except AttributeError:
        return getattr(msg, name.upper())


def stamp_to_msg(stamp_ns: int, ts=None):
    """builtin_interfaces/Time of an int ns stamp."""
    ts = ts or typestore()
    sec, nanosec = divmod(int(stamp_ns), NS_PER_S)
    return _make(ts, "builtin_interfaces/msg/Time", sec=sec, nanosec=nanosec)


def stamp_from_msg(stamp) -> int:
    """int ns of a builtin_interfaces/Time (ROS 1 time deserialises to the same fields)."""
    return int(stamp.sec) * NS_PER_S + int(stamp.nanosec)


def _header(stamp_ns: int, frame_id: str, ts):
    return _make(ts, "std_msgs/msg/Header", stamp=stamp_to_msg(stamp_ns, ts), frame_id=frame_id)


def _pose_msg(T: np.ndarray, ts):
    q = transforms.quat_xyzw(T)
    return _make(ts, "geometry_msgs/msg/Pose",
                 position=_make(ts, "geometry_msgs/msg/Point", x=float(T[0, 3]), y=float(T[1, 3]), z=float(T[2, 3])),
                 orientation=_make(ts, "geometry_msgs/msg/Quaternion", x=q[0], y=q[1], z=q[2], w=q[3]))


def _pose_from(pose) -> np.ndarray:
    p, o = pose.position, pose.orientation
    return transforms.from_xyz_quat_xyzw((p.x, p.y, p.z), (o.x, o.y, o.z, o.w))


# --------------------------------------------------------------------------------------------
# Conversions (matched pairs)
# --------------------------------------------------------------------------------------------

def odometry_to_msg(T_odom_base: np.ndarray, covariance: Optional[np.ndarray], stamp_ns: int,
                    frame_id: str = "odom", child_frame_id: str = DEFAULT_BASE_FRAME, ts=None):
    """nav_msgs/Odometry of a pose (4x4, odom frame) and its 6x6 covariance (x y z roll pitch yaw)."""
    ts = ts or typestore()
    cov = np.zeros(36) if covariance is None else np.asarray(covariance, dtype=np.float64).reshape(36)
    vec = _make(ts, "geometry_msgs/msg/Vector3", x=0.0, y=0.0, z=0.0)
    twist = _make(ts, "geometry_msgs/msg/TwistWithCovariance",
                  twist=_make(ts, "geometry_msgs/msg/Twist", linear=vec, angular=vec), covariance=np.zeros(36))
    return _make(ts, ODOM_TYPE, header=_header(stamp_ns, frame_id, ts), child_frame_id=child_frame_id,
                 pose=_make(ts, "geometry_msgs/msg/PoseWithCovariance", pose=_pose_msg(T_odom_base, ts),
                            covariance=cov.copy()),
                 twist=twist)


def odometry_from_msg(msg) -> tuple[np.ndarray, np.ndarray]:
    """(T_odom_base 4x4, covariance 6x6) of a nav_msgs/Odometry."""
    cov = np.array(msg.pose.covariance, dtype=np.float64).reshape(6, 6)
    return _pose_from(msg.pose.pose), cov


def scan_to_msg(scan: LaserScan, stamp_ns: int, frame_id: str = "laser", ts=None):
    """sensor_msgs/LaserScan of a :class:`LaserScan` (ranges m; NaN kept)."""
    ts = ts or typestore()
    ranges = np.asarray(scan.ranges, dtype=np.float32)
    return _make(ts, SCAN_TYPE, header=_header(stamp_ns, frame_id, ts), angle_min=float(scan.angle_min),
                 angle_max=float(scan.angle_min + scan.angle_increment * (len(ranges) - 1)),
                 angle_increment=float(scan.angle_increment), time_increment=0.0, scan_time=0.0,
                 range_min=float(scan.range_min), range_max=float(scan.range_max), ranges=ranges.copy(),
                 intensities=np.zeros(0, dtype=np.float32))


def scan_from_msg(msg, T_base_laser: np.ndarray = DEFAULT_T_BASE_LASER) -> LaserScan:
    """:class:`LaserScan` of a sensor_msgs/LaserScan (T_base_laser: 4x4 base -> laser)."""
    return LaserScan(np.array(msg.ranges, dtype=np.float32), float(msg.angle_min), float(msg.angle_increment),
                     float(msg.range_min), float(msg.range_max), np.array(T_base_laser, dtype=np.float64))


def image_to_msg(rgb: np.ndarray, stamp_ns: int, frame_id: str = "camera_optical", ts=None):
    """sensor_msgs/Image rgb8 of an HxWx3 uint8 RGB image."""
    ts = ts or typestore()
    h, w = rgb.shape[:2]
    data = np.ascontiguousarray(rgb, dtype=np.uint8).reshape(-1)
    return _make(ts, IMAGE_TYPE, header=_header(stamp_ns, frame_id, ts), height=h, width=w, encoding="rgb8",
                 is_bigendian=0, step=w * 3, data=data)


def _buffer(data) -> np.ndarray:
    """uint8 view of a message's ``data`` (numpy array from rosbags, array.array or bytes from rclpy)."""
    return np.frombuffer(data, dtype=np.uint8)


def _pixels(msg, dtype: np.dtype, channels: int) -> np.ndarray:
    """HxWxC (or HxW) view of an Image's data honouring ``step`` and ``is_bigendian``."""
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    if h <= 0 or w <= 0:
        raise SensorDataError(f"image {msg.encoding} is empty ({w}x{h})", "empty_image")
    dt = np.dtype(dtype).newbyteorder(">" if msg.is_bigendian else "<")
    row_bytes = w * channels * dt.itemsize
    data = _buffer(msg.data)
    if step < row_bytes:
        raise SensorDataError(f"image {w}x{h} {msg.encoding} has step {step}, smaller than width x pixel size "
                              f"= {row_bytes} bytes", "bad_step")
    if data.size < step * h:
        raise SensorDataError(f"image {w}x{h} {msg.encoding} holds {data.size} bytes, expected step x height = "
                              f"{step * h} bytes", "short_data")
    raw = data[:step * h].reshape(h, step)
    px = raw[:, :row_bytes].copy().view(dt)
    shape = (h, w) if channels == 1 else (h, w, channels)
    return px.reshape(shape).astype(np.dtype(dtype).newbyteorder("="), copy=False)


def image_from_msg(msg) -> np.ndarray:
    """HxWx3 uint8 RGB of a sensor_msgs/Image in any encoding of ``_COLOR_ENCODINGS``: rgb8, bgr8,
    rgba8, bgra8, mono8, mono16, rgb16, bgr16, bayer_* (8 and 16 bits), yuv422 (UYVY), yuv422_yuy2 /
    yuyv (YUYV). Works on rosbags and rclpy messages alike (the node and the bag reader share it)."""
    enc = msg.encoding.lower()
    if enc not in _COLOR_ENCODINGS:
        raise SensorDataError(
            f"unsupported colour image encoding {msg.encoding!r} (supported: {', '.join(_COLOR_ENCODINGS)})",
            "encoding")
    channels, dtype, code = _COLOR_ENCODINGS[enc]
    if channels == 2:   # 4:2:2 YUV: 2 bytes per pixel, decoded by cv2 as a 2-channel image
        if int(msg.width) % 2:
            raise SensorDataError(f"{msg.encoding} image width {msg.width} is odd (4:2:2 needs pairs of pixels)",
                                  "invalid_image")
        return cv2.cvtColor(_pixels(msg, np.uint8, 2), code)
    px = _pixels(msg, dtype, channels)
    if px.dtype == np.uint16:
        px = (px >> 8).astype(np.uint8)
    return np.ascontiguousarray(px) if code is None else cv2.cvtColor(px, code)


def pixels_of_rgb(rgb: np.ndarray, encoding: str) -> np.ndarray:
    """The pixel array an Image of ``encoding`` carries for an HxWx3 uint8 RGB image (the inverse of
    :func:`image_from_msg`, exact for rgb8/bgr8/rgba8/bgra8; grey, Bayer and YUV lose colour detail).

    Returns HxW, HxWxC uint8 or uint16 (native byte order); ``tobytes()`` gives the message's data.
    """
    enc = encoding.lower()
    rgb = np.ascontiguousarray(rgb, dtype=np.uint8)
    if enc not in _COLOR_ENCODINGS:
        raise SensorDataError(f"cannot write colour encoding {encoding!r} (supported: {', '.join(_COLOR_ENCODINGS)})")
    channels, dtype, _ = _COLOR_ENCODINGS[enc]
    wide = np.dtype(dtype) == np.uint16
    if enc.startswith("bayer_"):
        h, w = rgb.shape[:2]
        pattern = _BAYER_CHANNELS[enc[6:10]]
        rows, cols = np.indices((h, w))
        channel = np.asarray(pattern)[rows % 2, cols % 2]
        out = np.take_along_axis(rgb, channel[..., None], axis=2)[..., 0]
    elif channels == 2:
        # BT.601 studio range (Y 16-235), the convention of cv2's YUV 4:2:2 -> RGB conversions.
        yuv = np.rint(rgb.astype(np.float64) @ _RGB_TO_YUV601.T + (16.0, 128.0, 128.0)).astype(np.int32)
        y, u, v = yuv[..., 0], yuv[..., 1], yuv[..., 2]
        u2 = ((u[:, 0::2] + u[:, 1::2] + 1) // 2).repeat(2, axis=1)
        v2 = ((v[:, 0::2] + v[:, 1::2] + 1) // 2).repeat(2, axis=1)
        chroma = np.where(np.arange(rgb.shape[1]) % 2 == 0, u2, v2)   # U on even pixels, V on odd
        pair = (chroma, y) if enc in ("yuv422", "uyvy") else (y, chroma)
        out = np.stack(pair, axis=2).astype(np.uint8)
    elif channels == 1:
        out = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
    elif enc in ("rgb8", "rgb16"):
        out = rgb
    elif enc in ("bgr8", "8uc3", "bgr16"):
        out = rgb[..., ::-1]
    elif enc == "rgba8":
        out = cv2.cvtColor(rgb, cv2.COLOR_RGB2RGBA)
    else:
        out = cv2.cvtColor(rgb, cv2.COLOR_RGB2BGRA)
    out = np.ascontiguousarray(out)
    return out.astype(np.uint16) * 257 if wide else out


def depth_to_msg(depth_m: np.ndarray, stamp_ns: int, frame_id: str = "camera_optical", ts=None,
                 encoding: str = "16UC1"):
    """sensor_msgs/Image of an HxW float32 depth (m): 16UC1 millimetres (NaN/0 -> 0, clipped at
    65.535 m) or 32FC1 metres (invalid -> NaN, as drivers publish it)."""
    ts = ts or typestore()
    if encoding == "32FC1":
        d = np.asarray(depth_m, dtype=np.float32).copy()
        d[~(d > 0)] = np.nan
        h, w = d.shape
        return _make(ts, IMAGE_TYPE, header=_header(stamp_ns, frame_id, ts), height=h, width=w, encoding="32FC1",
                     is_bigendian=0, step=w * 4, data=d.astype("<f4").reshape(-1).view(np.uint8))
    if encoding != "16UC1":
        raise BagError(f"depth encoding {encoding!r} cannot be written: 16UC1 (mm) or 32FC1 (m)")
    mm = depth_to_mm(depth_m)
    h, w = mm.shape
    return _make(ts, IMAGE_TYPE, header=_header(stamp_ns, frame_id, ts), height=h, width=w, encoding="16UC1",
                 is_bigendian=0, step=w * 2, data=mm.astype("<u2").reshape(-1).view(np.uint8))


def depth_from_msg(msg) -> np.ndarray:
    """HxW float32 depth (m, NaN invalid) of a sensor_msgs/Image 16UC1/mono16 (mm) or 32FC1 (m).

    0 and NaN are invalid (NaN); inf raises SensorDataError (drivers publish NaN or 0 for no depth).
    """
    enc = msg.encoding.lower()
    if enc in _DEPTH_MM_ENCODINGS:
        return depth_from_mm(_pixels(msg, np.uint16, 1))
    if enc in _DEPTH_M_ENCODINGS:
        d = _pixels(msg, np.float32, 1).copy()
        if np.isinf(d).any():
            raise SensorDataError("depth image contains inf values: the driver should publish NaN or 0 "
                                  "for invalid pixels", "inf_depth")
        d[~(d > 0)] = np.nan
        return d
    raise SensorDataError(f"unsupported depth image encoding {msg.encoding!r} (supported: 16UC1, mono16, 32FC1)",
                          "encoding")


def compressed_image_to_msg(rgb: np.ndarray, stamp_ns: int, frame_id: str = "camera_optical",
                            quality: int = JPEG_QUALITY, ts=None):
    """sensor_msgs/CompressedImage (jpeg, image_transport's format string) of an HxWx3 RGB image."""
    ts = ts or typestore()
    return _make(ts, COMPRESSED_TYPE, header=_header(stamp_ns, frame_id, ts), format=JPEG_FORMAT,
                 data=np.frombuffer(encode_rgb(rgb, quality), dtype=np.uint8).copy())


def compressed_image_from_msg(msg) -> np.ndarray:
    """HxWx3 uint8 RGB of a sensor_msgs/CompressedImage (jpeg or png)."""
    return compressed_image_and_jpeg(msg)[0]


def compressed_image_and_jpeg(msg) -> tuple[np.ndarray, Optional[bytes]]:
    """:func:`compressed_image_from_msg`'s image, and the message's bytes when they are a JPEG (as the
    database stores a node's RGB: kept as they came, :class:`~rtabmap_ros2.core.sensor.SensorFrame`),
    else None (a PNG one is stored as a JPEG of its pixels)."""
    data = _buffer(msg.data)
    bgr = cv2.imdecode(data, cv2.IMREAD_COLOR)
    if bgr is None:
        raise SensorDataError(f"cv2 could not decode the compressed image (format {msg.format!r}, {len(msg.data)} bytes)",
                              "decode")
    jpeg = data.tobytes() if data[:3].tobytes() == JPEG_MAGIC else None
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB), jpeg


def compressed_depth_of_depth(depth_m: np.ndarray) -> bytes:
    """image_transport's compressedDepth payload (ConfigHeader + 16-bit PNG of millimetres) of a depth (m)."""
    return COMPRESSED_DEPTH_HEADER.pack(0, 0.0, 0.0) + encode_depth(depth_m)


def compressed_depth_to_msg(depth_m: np.ndarray, stamp_ns: int, frame_id: str = "camera_optical", ts=None):
    """sensor_msgs/CompressedImage in image_transport's compressedDepth format (16UC1 mm, PNG)."""
    ts = ts or typestore()
    return _make(ts, COMPRESSED_TYPE, header=_header(stamp_ns, frame_id, ts), format=COMPRESSED_DEPTH_FORMAT,
                 data=np.frombuffer(compressed_depth_of_depth(depth_m), dtype=np.uint8).copy())


def compressed_depth_from_msg(msg) -> np.ndarray:
    """HxW float32 depth (m, NaN invalid) of a compressedDepth CompressedImage.

    ``16UC1`` payloads hold millimetres; ``32FC1`` payloads hold quantised inverse depth
    ``q`` with ``depth = depthQuantA / (q - depthQuantB)`` (image_transport's encoding).
    """
    return compressed_depth_and_png(msg)[0]


def compressed_depth_and_png(msg) -> tuple[np.ndarray, Optional[bytes]]:
    """:func:`compressed_depth_from_msg`'s depth, and the payload's PNG when it is what the database
    stores (millimetres: a 16UC1 payload; kept as it came), else None."""
    raw = _buffer(msg.data).tobytes()
    enc = msg.format.split(";")[0].strip().lower()
    quant_a = quant_b = 0.0
    if raw[:4] == PNG_MAGIC:
        png = raw   # old image_transport versions had no ConfigHeader
    elif len(raw) > COMPRESSED_DEPTH_HEADER.size and raw[COMPRESSED_DEPTH_HEADER.size:][:4] == PNG_MAGIC:
        _, quant_a, quant_b = COMPRESSED_DEPTH_HEADER.unpack_from(raw)
        png = raw[COMPRESSED_DEPTH_HEADER.size:]
    else:
        raise SensorDataError(f"compressedDepth message (format {msg.format!r}) holds no PNG", "decode")
    img = cv2.imdecode(np.frombuffer(png, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
    if img is None or img.dtype != np.uint16 or img.ndim != 2:
        raise SensorDataError(f"compressedDepth message (format {msg.format!r}) has an unreadable 16-bit PNG",
                              "decode")
    if enc in _DEPTH_MM_ENCODINGS:
        return depth_from_mm(img), png
    if enc in _DEPTH_M_ENCODINGS:
        with np.errstate(divide="ignore", invalid="ignore"):
            d = (quant_a / (img.astype(np.float32) - quant_b)).astype(np.float32)
        d[(img == 0) | ~np.isfinite(d) | (d <= 0)] = np.nan
        return d, None
    raise SensorDataError(f"unsupported compressedDepth encoding {enc!r} in format {msg.format!r}", "encoding")


def camera_info_to_msg(camera: CameraModel, stamp_ns: int, frame_id: str = "camera_optical", ts=None,
                       distortion: Optional[Iterable[float]] = None):
    """sensor_msgs/CameraInfo (K, P = K, R = I, plumb_bob) of a :class:`CameraModel`; ``D`` the
    plumb_bob coefficients (k1 k2 p1 p2 k3) of images as recorded (not rectified), zeros by default."""
    ts = ts or typestore()
    d = np.zeros(5) if distortion is None else np.asarray(list(distortion), dtype=np.float64)
    K = np.array([camera.fx, 0.0, camera.cx, 0.0, camera.fy, camera.cy, 0.0, 0.0, 1.0])
    P = np.array([camera.fx, 0.0, camera.cx, 0.0, 0.0, camera.fy, camera.cy, 0.0, 0.0, 0.0, 1.0, 0.0])
    roi = _make(ts, "sensor_msgs/msg/RegionOfInterest", x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
    return _make(ts, CAMERA_INFO_TYPE, header=_header(stamp_ns, frame_id, ts), height=camera.height,
                 width=camera.width, distortion_model="plumb_bob", d=d, k=K, r=np.eye(3).reshape(9),
                 p=P, binning_x=0, binning_y=0, roi=roi)


def camera_info_from_msg(msg, T_base_camera: np.ndarray = DEFAULT_T_BASE_CAMERA) -> CameraModel:
    """:class:`CameraModel` of a sensor_msgs/CameraInfo (T_base_camera 4x4 base -> optical frame).

    Intrinsics from ``K``; when the projection ``P`` is set and differs from ``K`` (a calibrated,
    distorted camera: ``P`` is the rectified image's), from ``P``: the images a SLAM node uses are the
    rectified ones (``image_rect``), whose intrinsics are ``P``'s. When ``P`` = ``K`` and ``D`` is not
    zero (plumb_bob or rational_polynomial), the images are the raw ones: the model keeps ``D`` and
    the keypoints are undistorted with it (:meth:`CameraModel.undistort`).
    """
    K = np.asarray(_field(msg, "k"), dtype=np.float64)
    P = np.asarray(_field(msg, "p"), dtype=np.float64)
    fx, fy, cx, cy = float(K[0]), float(K[4]), float(K[2]), float(K[5])
    calibrated = fx > 0 and fy > 0   # a zero K is an uncalibrated camera: rejected by CameraModel
    if (calibrated and P.size == 12 and P[0] > 0 and P[5] > 0
            and not np.allclose((P[0], P[5], P[2], P[6]), (fx, fy, cx, cy))):
        fx, fy, cx, cy = float(P[0]), float(P[5]), float(P[2]), float(P[6])
    return CameraModel(fx, fy, cx, cy, int(msg.width), int(msg.height), np.array(T_base_camera, dtype=np.float64),
                       raw_image_distortion(msg))


# CameraInfo distortion models whose D OpenCV's undistortPoints takes as it is.
_OPENCV_DISTORTION_MODELS = ("plumb_bob", "rational_polynomial")


def _raw_image_d(msg) -> np.ndarray:
    """A CameraInfo's ``D`` when it says its images are raw (``D`` not zero and no rectified
    projection: ``P`` = ``K``); empty otherwise."""
    d = np.asarray(_field(msg, "d"), dtype=np.float64)
    K = np.asarray(_field(msg, "k"), dtype=np.float64)
    P = np.asarray(_field(msg, "p"), dtype=np.float64)
    rectified_p = P.size == 12 and P[0] > 0 and not np.allclose((P[0], P[5], P[2], P[6]), (K[0], K[4], K[2], K[5]))
    return d if d.size and np.any(d != 0) and not rectified_p else np.zeros(0)


def raw_image_distortion(msg) -> tuple[float, ...]:
    """A CameraInfo's ``D`` when its images are not rectified (``D`` not zero, ``P`` = ``K``) and
    OpenCV models it; () otherwise (rectified images, or a model such as equidistant, said by
    :func:`_warn_if_not_rectified`)."""
    d = _raw_image_d(msg)
    model = str(getattr(msg, "distortion_model", "") or "plumb_bob")
    if model not in _OPENCV_DISTORTION_MODELS or d.size not in (4, 5, 8, 12, 14) or not np.isfinite(d).all():
        return ()
    return tuple(float(v) for v in d)


def register_to_rgb(frame: SensorFrame) -> SensorFrame:
    """The frame with depth and camera model at the RGB image's resolution.

    A depth image registered to the RGB camera but at another resolution, one an integer multiple of
    the other (e.g. 320x240 with a 640x480 colour image, as RTAB-Map requires), is resized to the RGB
    size (nearest neighbour: no depth is interpolated across edges), and a camera_info at such a
    resolution has its intrinsics scaled. Other sizes raise SensorDataError (reason
    ``size_mismatch``) naming them: an unregistered depth cannot be fixed by scaling.
    """
    if frame.rgb is None:
        return frame
    h, w = frame.rgb.shape[:2]

    def check(what: str, source: str, width: int, height: int) -> None:
        big, small = ((w, h), (width, height)) if w >= width else ((width, height), (w, h))
        factor = big[0] // small[0] if small[0] else 0
        if not factor or big != (small[0] * factor, small[1] * factor):
            raise SensorDataError(
                f"{what} {width}x{height} and rgb {w}x{h}: sizes differ and neither is an integer multiple of "
                "the other, so the depth cannot be registered by scaling (publish a depth registered to the RGB "
                "camera, e.g. depth_registered/image_rect)", "size_mismatch", source)

    if frame.depth_m is not None and frame.depth_m.ndim == 2 and frame.depth_m.shape != (h, w):
        dh, dw = frame.depth_m.shape
        check("depth", "depth", dw, dh)
        frame.depth_m = cv2.resize(frame.depth_m, (w, h), interpolation=cv2.INTER_NEAREST)
        frame.depth_png16_mm = None   # the input's PNG is of the other size
    if frame.camera is not None and (frame.camera.width, frame.camera.height) != (w, h):
        check("camera_info", "camera_info", frame.camera.width, frame.camera.height)
        frame.camera = frame.camera.scaled(w, h)
    return frame


def transform_to_msg(T_parent_child: np.ndarray, parent: str, child: str, stamp_ns: int, ts=None):
    """geometry_msgs/TransformStamped of a 4x4 transform (parent <- child)."""
    ts = ts or typestore()
    q = transforms.quat_xyzw(T_parent_child)
    t = T_parent_child[:3, 3]
    tf = _make(ts, "geometry_msgs/msg/Transform",
               translation=_make(ts, "geometry_msgs/msg/Vector3", x=float(t[0]), y=float(t[1]), z=float(t[2])),
               rotation=_make(ts, "geometry_msgs/msg/Quaternion", x=q[0], y=q[1], z=q[2], w=q[3]))
    return _make(ts, "geometry_msgs/msg/TransformStamped", header=_header(stamp_ns, parent, ts),
                 child_frame_id=child, transform=tf)


def transform_from_msg(msg) -> tuple[str, str, np.ndarray]:
    """(parent, child, T_parent_child 4x4) of a geometry_msgs/TransformStamped."""
    t, r = msg.transform.translation, msg.transform.rotation
    return (msg.header.frame_id.lstrip("/"), msg.child_frame_id.lstrip("/"),
            transforms.from_xyz_quat_xyzw((t.x, t.y, t.z), (r.x, r.y, r.z, r.w)))


# --------------------------------------------------------------------------------------------
# Reading
# --------------------------------------------------------------------------------------------

def _bag_paths(path: Path) -> list[Path]:
    """The path(s) AnyReader expects: a ROS 1 ``.bag`` file or a ROS 2 bag folder."""
    if not path.exists():
        raise BagError(f"bag {path} does not exist")
    if path.is_file() and path.suffix in (".db3", ".mcap"):
        if (path.parent / "metadata.yaml").exists():
            return [path.parent]
        raise BagError(f"{path} is a ROS 2 storage file without metadata.yaml next to it: "
                       "pass the bag folder (it holds metadata.yaml)")
    if path.is_dir() and not (path / "metadata.yaml").exists():
        raise BagError(f"{path} is a folder without metadata.yaml: not a ROS 2 bag")
    if path.is_file() and path.suffix != ".bag":
        raise BagError(f"{path} is not a bag: expected a ROS 1 .bag file or a ROS 2 bag folder")
    return [path]


def _open_reader(path: Path):
    """An opened AnyReader; rosbags' errors become :class:`BagError` naming the file."""
    from rosbags.highlevel import AnyReader
    try:
        reader = AnyReader(_bag_paths(path), default_typestore=typestore())
        reader.open()
    except BagError:
        raise
    except Exception as exc:   # rosbags raises several unrelated types for damaged files
        raise BagError(f"cannot read bag {path}: {type(exc).__name__}: {exc} "
                       "(truncated or not a bag? re-record or reindex it)") from exc
    return reader


class _TfTree:
    """Static transforms (child -> (parent, T_parent_child)) read from /tf_static."""

    def __init__(self) -> None:
        self.parent: dict[str, tuple[str, np.ndarray]] = {}

    def add(self, parent: str, child: str, T: np.ndarray) -> None:
        self.parent[child] = (parent, T)

    def lookup(self, target: str, source: str) -> Optional[np.ndarray]:
        """T_target_source, or None when the tree does not link them."""
        target, source = target.lstrip("/"), source.lstrip("/")

        def chain(frame: str) -> dict[str, np.ndarray]:
            out, T, seen = {frame: np.eye(4)}, np.eye(4), {frame}
            while frame in self.parent:
                frame, T_p_c = self.parent[frame][0], self.parent[frame][1]
                if frame in seen:
                    break
                seen.add(frame)
                T = T_p_c @ T
                out[frame] = T
            return out

        up_source, up_target = chain(source), chain(target)
        common = next((f for f in up_source if f in up_target), None)
        if common is None:
            return None
        return transforms.inverse(up_target[common]) @ up_source[common]


@dataclass(frozen=True)
class Mount:
    """Where a sensor's mount (``base_frame`` -> ``sensor_frame``) came from: ``kind`` is
    ``tf_static`` (the bag's /tf_static links the frames), ``same_frame`` (the sensor's frame is the
    base: identity), ``argument`` (given to BagDataset) or ``fallback`` (none of these: the fallback
    transform, e.g. ``map``'s ``base_to_camera``)."""

    kind: str
    base_frame: str
    sensor_frame: str


@dataclass(frozen=True)
class BagRead:
    """What the last full iteration of a bag did.

    Attributes:
        synchronised: complete synchronised sets, before the detection rate's limit.
        rate_limited: sets dropped by the detection rate (``sync.rate_hz``).
        frames: sets turned into frames (after the rate limit, bad messages skipped).
        bad: sets skipped for a bad message (each logged as a warning).
        dropped: the synchroniser's other drops (``queue_full``, ``late``, ``unmatched``).
    """

    synchronised: int
    rate_limited: int
    frames: int
    bad: int
    dropped: dict[str, int]


@dataclass
class _Raw:
    """A deserialised message waiting in the synchroniser (converted only if its set is emitted)."""

    topic: str
    msgtype: str
    stamp_ns: int
    msg: object


class BagDataset:
    """Frames of a ROS 1 or ROS 2 bag, synchronised and rate-limited (Dataset protocol).

    ``len()`` is exact: the first call reads the bag once (cached; iterating to the end also
    fills the cache), since a frame whose message cannot be decoded is skipped.
    """

    def __init__(self, path, topics: TopicNames = TopicNames(), sync: SyncParams = SyncParams(),
                 use: Optional[Iterable[str]] = None, T_base_camera: Optional[np.ndarray] = None,
                 T_base_laser: Optional[np.ndarray] = None, base_frame: Optional[str] = None,
                 fallback_T_base_camera: Optional[np.ndarray] = None,
                 fallback_T_base_laser: Optional[np.ndarray] = None) -> None:
        """Open ``path`` and check its topics.

        Args:
            path: ROS 1 ``.bag`` file, ROS 2 bag folder (or its ``.db3`` / ``.mcap`` file).
            topics: topic of each stream.
            sync: synchroniser parameters (``rate_hz`` = frames per second of bag time; 0 = all).
            use: streams to read among :data:`STREAMS`; default: those whose topic is present.
                A requested stream whose topic is missing raises :class:`BagError`.
            T_base_camera, T_base_laser: 4x4 base -> camera optical / laser; default: /tf_static
                if it links the frames, else :data:`DEFAULT_T_BASE_CAMERA` / :data:`DEFAULT_T_BASE_LASER`.
            base_frame: robot base frame for /tf_static look-ups; default: the odometry's
                child_frame_id, else ``base_link``.
            fallback_T_base_camera, fallback_T_base_laser: used instead of the module defaults when
                /tf_static does not give the mount (``map --set base_to_camera=[...]``).
        """
        self.path = Path(path)
        self.topics = topics
        self.sync = sync
        self._T_base_camera = None if T_base_camera is None else np.asarray(T_base_camera, dtype=np.float64)
        self._T_base_laser = None if T_base_laser is None else np.asarray(T_base_laser, dtype=np.float64)
        self._base_frame = base_frame
        self._fallback_camera = DEFAULT_T_BASE_CAMERA if fallback_T_base_camera is None else np.asarray(
            fallback_T_base_camera, dtype=np.float64)
        self._fallback_laser = DEFAULT_T_BASE_LASER if fallback_T_base_laser is None else np.asarray(
            fallback_T_base_laser, dtype=np.float64)
        self._len: Optional[int] = None
        # Filled while iterating: where each sensor's mount came from (first frame), what the
        # last full iteration did.
        self.mounts: dict[str, Mount] = {}
        self.last_read: Optional[BagRead] = None
        reader = _open_reader(self.path)
        try:
            available = {name: info.msgtype for name, info in reader.topics.items()}
            self.message_counts = {name: info.msgcount for name, info in reader.topics.items()}
            self.tf = _TfTree()
            if TF_STATIC_TOPIC in available:
                self._read_tf_static(reader)
        finally:
            reader.close()
        self.available_topics = available
        self.stream_topics = self._resolve_topics(available, use)
        if not self.stream_topics:
            raise BagError(f"bag {self.path} has none of the topics {[topics.of(s) for s in STREAMS]}; "
                           f"it has: {self._describe(available)}")
        self.streams = tuple(s for s in STREAMS if s in self.stream_topics)

    def unread_topics_of(self, stream: str) -> list[str]:
        """The bag's topics of ``stream``'s message type that no stream is read from: where a stream
        missing under its topic name may have been recorded."""
        read = set(self.stream_topics.values())
        return [topic for topic, msgtype in sorted(self.available_topics.items())
                if msgtype in STREAM_TYPES[stream] and topic not in read]

    @staticmethod
    def _describe(available: dict[str, str]) -> str:
        return ", ".join(f"{t} ({ty})" for t, ty in sorted(available.items())) or "no topics"

    def _resolve_topics(self, available: dict[str, str], use: Optional[Iterable[str]]) -> dict[str, str]:
        """Stream -> topic actually read (raw topic, else its compressed variant)."""
        requested = None if use is None else list(use)
        if requested is not None:
            unknown = [s for s in requested if s not in STREAMS]
            if unknown:
                raise BagError(f"unknown stream(s) {unknown} in use=; choose among {list(STREAMS)}")
        out = {}
        for s in STREAMS:
            if requested is not None and s not in requested:
                continue
            base = self.topics.of(s)
            candidates = [base]
            if s == "rgb":
                candidates.append(base + COMPRESSED_SUFFIX)
            elif s == "depth":
                candidates += [base + COMPRESSED_DEPTH_SUFFIX, base + COMPRESSED_SUFFIX]
            found = next((t for t in candidates if t in available), None)
            if found is None:
                if requested is not None:
                    raise BagError(
                        f"bag {self.path} has no topic {base}"
                        + (f" (nor {', '.join(candidates[1:])})" if len(candidates) > 1 else "")
                        + f" for stream {s!r}; topics in the bag: {self._describe(available)}")
                continue
            out[s] = found
        if "depth" in out and "camera_info" not in out:
            raise BagError(f"bag {self.path} has depth images on {out['depth']} but no camera_info topic "
                           f"{self.topics.camera_info}; topics in the bag: {self._describe(available)}")
        return out

    def _read_tf_static(self, reader) -> None:
        conns = [c for c in reader.connections if c.topic == TF_STATIC_TOPIC]
        for conn, _, raw in reader.messages(connections=conns):
            try:
                msg = reader.deserialize(raw, conn.msgtype)
                for tfs in msg.transforms:
                    parent, child, T = transform_from_msg(tfs)
                    self.tf.add(parent, child, T)
            except Exception as exc:
                logger.warning("bag %s: skipping an unreadable /tf_static message: %s", self.path, exc)

    def _sensor_transform(self, sensor: str, frame_id: str, explicit: Optional[np.ndarray], default: np.ndarray,
                          base_frame: str) -> np.ndarray:
        """base -> sensor transform of ``sensor`` ("camera", "laser"); where it came from is kept in
        :attr:`mounts` (the first frame's)."""
        T, kind = explicit, "argument"
        if T is None and frame_id:
            T = self.tf.lookup(base_frame, frame_id)
            kind = "same_frame" if frame_id.lstrip("/") == base_frame.lstrip("/") else "tf_static"
        if T is None:
            T, kind = np.array(default), "fallback"
        self.mounts.setdefault(sensor, Mount(kind, base_frame, frame_id))
        return T

    def __len__(self) -> int:
        """Frames in the bag: synchronised sets, counted without decoding their images (a set
        whose message cannot be converted is counted here and skipped when iterating); exact
        once the bag has been iterated."""
        if self._len is None:
            reader = _open_reader(self.path)
            try:
                self._len = sum(1 for _ in self._synced(reader, {"camera_info": None}))
            finally:
                reader.close()
        return self._len

    def __iter__(self) -> Iterator[SensorFrame]:
        reader = _open_reader(self.path)
        try:
            yield from self._frames(reader)
        finally:
            reader.close()

    def _frames(self, reader) -> Iterator[SensorFrame]:
        state = {"camera_info": None, "base_frame": self._base_frame}
        count = sets = 0
        for synced in self._synced(reader, state):
            sets += 1
            frame = self._frame(synced, state)
            if frame is not None:
                count += 1
                yield frame
        self._len = count
        dropped = dict(state.get("dropped", {}))
        rate_limited = dropped.pop("rate_limited", 0)
        self.last_read = BagRead(sets + rate_limited, rate_limited, count, sets - count, dropped)

    def _synced(self, reader, state: dict) -> Iterator[SyncedSet]:
        """The bag's synchronised message sets in order (camera_info kept in ``state``)."""
        topic_stream = {t: s for s, t in self.stream_topics.items()}
        conns = [c for c in reader.connections if c.topic in topic_stream]
        sync_streams = {s for s in self.streams if s != "camera_info"}
        synchronizer = FrameSynchronizer(self.sync, sync_streams) if sync_streams else None
        for conn, bag_ns, raw in reader.messages(connections=conns):
            stream = topic_stream[conn.topic]
            try:
                msg = reader.deserialize(raw, conn.msgtype)
            except Exception as exc:
                logger.warning("bag %s: cannot deserialise a %s message on %s at %.9f s (skipped): %s",
                               self.path, conn.msgtype, conn.topic, bag_ns / NS_PER_S, exc)
                continue
            header = getattr(msg, "header", None)
            stamp_ns = stamp_from_msg(header.stamp) if header is not None else 0
            if stamp_ns == 0:
                stamp_ns = bag_ns   # unstamped header: fall back on the recording time
            item = _Raw(conn.topic, conn.msgtype, stamp_ns, msg)
            if stream == "camera_info":
                state["camera_info"] = item
                continue
            if synchronizer is None:
                continue
            yield from synchronizer.add(stream, stamp_ns, item)
        if synchronizer is not None:
            yield from synchronizer.flush()
            state["dropped"] = dict(synchronizer.dropped)
            if any(synchronizer.dropped.values()) or synchronizer.resets:
                logger.debug("bag %s: synchroniser dropped %s, resets %d", self.path,
                             synchronizer.dropped, synchronizer.resets)

    def _frame(self, synced: SyncedSet, state: dict) -> Optional[SensorFrame]:
        """Convert one synchronised set to a SensorFrame; None (with a warning) when a message is bad."""
        frame = SensorFrame(stamp_ns=synced.stamp_ns)
        current: Optional[_Raw] = None
        try:
            odom = synced.values.get("odom")
            if odom is not None:
                current = odom
                frame.T_odom_base, frame.odom_covariance = odometry_from_msg(odom.msg)
                if state["base_frame"] is None and odom.msg.child_frame_id:
                    state["base_frame"] = odom.msg.child_frame_id.lstrip("/")
            base_frame = state["base_frame"] or DEFAULT_BASE_FRAME
            scan = synced.values.get("scan")
            if scan is not None:
                current = scan
                T = self._sensor_transform("laser", scan.msg.header.frame_id, self._T_base_laser,
                                           self._fallback_laser, base_frame)
                frame.scan = scan_from_msg(scan.msg, T)
            rgb = synced.values.get("rgb")
            if rgb is not None:
                current = rgb
                if rgb.msgtype == COMPRESSED_TYPE:
                    frame.rgb, frame.rgb_jpeg = compressed_image_and_jpeg(rgb.msg)
                else:
                    frame.rgb = image_from_msg(rgb.msg)
            depth = synced.values.get("depth")
            if depth is not None:
                current = depth
                if depth.msgtype == COMPRESSED_TYPE:
                    frame.depth_m, frame.depth_png16_mm = compressed_depth_and_png(depth.msg)
                else:
                    frame.depth_m = depth_from_msg(depth.msg)
            if rgb is not None or depth is not None:
                info = state["camera_info"]
                if info is None:
                    if "camera_info" in self.stream_topics:
                        logger.warning("bag %s: frame at %.9f s skipped: no camera_info received yet on %s",
                                       self.path, synced.stamp_ns / NS_PER_S, self.stream_topics["camera_info"])
                        return None
                else:
                    current = info
                    if not state.get("distortion_checked"):
                        state["distortion_checked"] = True
                        _warn_if_not_rectified(self.path, info)
                    image_frame_id = (rgb or depth).msg.header.frame_id or info.msg.header.frame_id
                    T = self._sensor_transform("camera", image_frame_id, self._T_base_camera,
                                               self._fallback_camera, base_frame)
                    frame.camera = camera_info_from_msg(info.msg, T)
            register_to_rgb(frame).validate(self.sync)
        except (SensorDataError, ValueError) as exc:
            where = (f"{current.topic} ({current.msgtype}, encoding "
                     f"{getattr(current.msg, 'encoding', getattr(current.msg, 'format', '-'))!r}) "
                     f"at {current.stamp_ns / NS_PER_S:.9f} s") if current is not None else "?"
            logger.warning("bag %s: frame at %.9f s skipped: bad message on %s: %s",
                           self.path, synced.stamp_ns / NS_PER_S, where, exc)
            return None
        return frame


def _warn_if_not_rectified(path: Path, info: "_Raw") -> None:
    """Say once per bag how a camera's raw images are used when its CameraInfo has distortion
    coefficients and no rectified projection (P = K): keypoints and depth points undistorted with D
    (RTAB-Map assumes rectified images, Rtabmap/ImagesAlreadyRectified), or as they are when OpenCV
    cannot model D."""
    d = _raw_image_d(info.msg)
    if not d.size:
        return
    coefficients = " ".join(f"{v:g}" for v in d)
    if raw_image_distortion(info.msg):
        logger.warning("bag %s: %s has distortion coefficients D = [%s] and P = K: the images are not rectified; "
                       "visual words and depth points (grid, clouds) are placed on their undistorted rays with D; "
                       "the images themselves are stored as recorded",
                       path, info.topic, coefficients)
    else:
        logger.warning("bag %s: %s has distortion coefficients D = [%s] (model %r) and P = K: the images are not "
                       "rectified and are used as they are (undistort them first, e.g. image_proc's image_rect)",
                       path, info.topic, coefficients, getattr(info.msg, "distortion_model", ""))


# --------------------------------------------------------------------------------------------
# Writing
# --------------------------------------------------------------------------------------------

class _MessageSink:
    """Lazily created connections of a rosbags writer, one per topic."""

    def __init__(self, writer, ts, serialize, ros1: bool) -> None:
        self.writer, self.ts, self.serialize, self.ros1 = writer, ts, serialize, ros1
        self.connections: dict[str, object] = {}

    def write(self, topic: str, msg, stamp_ns: int) -> None:
        conn = self.connections.get(topic)
        if conn is None:
            conn = self.writer.add_connection(topic, msg.__msgtype__, typestore=self.ts)
            self.connections[topic] = conn
        self.writer.write(conn, int(stamp_ns), self.serialize(msg, msg.__msgtype__))


def _write_frames(sink: _MessageSink, frames: Iterable[SensorFrame], topics: TopicNames, frame_ids: FrameIds,
                  rgb_format: str, depth_format: str, tf_static: bool = True,
                  camera_distortion: Optional[Iterable[float]] = None) -> int:
    ts = sink.ts
    tf_written: set[str] = set()
    n = 0
    for frame in frames:
        t = int(frame.stamp_ns)
        static = []
        if not tf_static:
            pass
        elif frame.camera is not None and frame_ids.camera not in tf_written:
            static.append(transform_to_msg(frame.camera.T_base_camera, frame_ids.base, frame_ids.camera, t, ts))
            tf_written.add(frame_ids.camera)
        if tf_static and frame.scan is not None and frame_ids.laser not in tf_written:
            static.append(transform_to_msg(frame.scan.T_base_laser, frame_ids.base, frame_ids.laser, t, ts))
            tf_written.add(frame_ids.laser)
        if static:
            sink.write(TF_STATIC_TOPIC, _make(ts, TF_TYPE, transforms=static), t)
        if frame.T_odom_base is not None:
            sink.write(topics.odom, odometry_to_msg(frame.T_odom_base, frame.odom_covariance, t, frame_ids.odom,
                                                    frame_ids.base, ts), t)
        if frame.scan is not None:
            sink.write(topics.scan, scan_to_msg(frame.scan, t, frame_ids.laser, ts), t)
        if frame.camera is not None:
            sink.write(topics.camera_info, camera_info_to_msg(frame.camera, t, frame_ids.camera, ts,
                                                              camera_distortion), t)
        if frame.rgb is not None:
            if rgb_format == "jpeg":
                sink.write(topics.rgb + COMPRESSED_SUFFIX, compressed_image_to_msg(frame.rgb, t, frame_ids.camera,
                                                                                   ts=ts), t)
            else:
                sink.write(topics.rgb, image_to_msg(frame.rgb, t, frame_ids.camera, ts), t)
        if frame.depth_m is not None:
            if depth_format == "png":
                sink.write(topics.depth + COMPRESSED_DEPTH_SUFFIX,
                           compressed_depth_to_msg(frame.depth_m, t, frame_ids.camera, ts), t)
            else:
                sink.write(topics.depth, depth_to_msg(frame.depth_m, t, frame_ids.camera, ts,
                                                      DEPTH_ENCODINGS[depth_format]), t)
        n += 1
    return n


def _check_formats(rgb_format: str, depth_format: str) -> None:
    if rgb_format not in ("raw", "jpeg"):
        raise BagError(f"rgb_format must be 'raw' or 'jpeg', got {rgb_format!r}")
    if depth_format not in ("raw", "float", "png"):
        raise BagError(f"depth_format must be 'raw' (16UC1 mm), 'float' (32FC1 m) or 'png' (compressedDepth), "
                       f"got {depth_format!r}")


def write_bag(path, frames: Iterable[SensorFrame], topics: TopicNames = TopicNames(), storage: str = "sqlite3",
              frame_ids: FrameIds = FrameIds(), rgb_format: str = "raw", depth_format: str = "raw",
              tf_static: bool = True, camera_distortion: Optional[Iterable[float]] = None) -> Path:
    """Write frames to a new ROS 2 bag folder (Jazzy typestore); return its path.

    Per frame, with the frame's stamp as header and bag time: Odometry (pose + covariance), LaserScan,
    CameraInfo (K, P = K, D = ``camera_distortion`` or zeros), rgb as Image rgb8 on ``topics.rgb`` or,
    with ``rgb_format="jpeg"``, CompressedImage on ``<rgb>/compressed``; depth as Image 16UC1 (mm)
    on ``topics.depth``, 32FC1 (m) with ``depth_format="float"``, or, with ``depth_format="png"``,
    compressedDepth on ``<depth>/compressedDepth``. ``/tf_static`` (TFMessage) holds base -> camera
    optical and base -> laser from the first frame carrying each (not written with ``tf_static=False``).

    Args:
        path: bag folder to create (must not exist).
        frames: frames in time order.
        storage: ``"sqlite3"`` (``.db3``) or ``"mcap"``.
        camera_distortion: plumb_bob coefficients (k1 k2 p1 p2 k3) written in every CameraInfo's
            ``D``, for images as recorded (not rectified).
    """
    from rosbags.rosbag2 import StoragePlugin, Writer
    _check_formats(rgb_format, depth_format)
    plugins = {"sqlite3": StoragePlugin.SQLITE3, "mcap": StoragePlugin.MCAP}
    if storage not in plugins:
        raise BagError(f"storage must be 'sqlite3' or 'mcap', got {storage!r}")
    path = Path(path)
    if path.exists():
        raise BagError(f"bag {path} already exists: remove it or choose another path")
    path.parent.mkdir(parents=True, exist_ok=True)
    ts = typestore()
    with Writer(path, version=Writer.VERSION_LATEST, storage_plugin=plugins[storage]) as writer:
        n = _write_frames(_MessageSink(writer, ts, ts.serialize_cdr, ros1=False), frames, topics, frame_ids,
                          rgb_format, depth_format, tf_static, camera_distortion)
    logger.info("wrote %d frames to %s (%s)", n, path, storage)
    return path


def write_ros1_bag(path, frames: Iterable[SensorFrame], topics: TopicNames = TopicNames(),
                   frame_ids: FrameIds = FrameIds(), rgb_format: str = "raw", depth_format: str = "raw") -> Path:
    """Write frames to a new ROS 1 ``.bag`` file (Noetic typestore), same topics as :func:`write_bag`."""
    from rosbags.rosbag1 import Writer
    _check_formats(rgb_format, depth_format)
    path = Path(path)
    if path.exists():
        raise BagError(f"bag {path} already exists: remove it or choose another path")
    path.parent.mkdir(parents=True, exist_ok=True)
    ts = typestore(ros1=True)
    with Writer(path) as writer:
        n = _write_frames(_MessageSink(writer, ts, ts.serialize_ros1, ros1=True), frames, topics, frame_ids,
                          rgb_format, depth_format)
    logger.info("wrote %d frames to %s (ROS 1)", n, path)
    return path
