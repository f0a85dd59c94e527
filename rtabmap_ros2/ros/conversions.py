"""ROS 2 message <-> numpy conversions (rclpy message classes), in matched pairs.

This is the only module of the node that knows message layouts. Every ``*_from_msg`` raises
:class:`~rtabmap_ros2.errors.SensorDataError` with the reason when a message cannot be used
(unknown encoding, sizes that disagree, NaN pose, empty scan...): the node logs it once per kind
and drops the frame.

Conventions (CONTRACT.md): transforms are 4x4 float64 ``T_a_b``; images RGB HxWx3 uint8; depth
HxW float32 metres with NaN invalid; stamps int nanoseconds.

Costs (LIBRARIES.md, re-measured in ``bench/bench_node.py``): pixel buffers are read with
``np.frombuffer`` and written from ``bytes``; ``OccupancyGrid.data`` is written from an
``array.array('b')`` (assigning a numpy array there is ~1000x slower).
"""

from __future__ import annotations

import array
from typing import Any, Iterable, Mapping

import numpy as np
from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import Point, Pose, PoseStamped, Quaternion, Transform, TransformStamped, Vector3
from nav_msgs.msg import OccupancyGrid as OccupancyGridMsg
from nav_msgs.msg import Odometry, Path
from sensor_msgs.msg import CameraInfo, CompressedImage, Image
from sensor_msgs.msg import LaserScan as LaserScanMsg
from std_msgs.msg import ColorRGBA, Header
from visualization_msgs.msg import Marker, MarkerArray

from rtabmap_ros2.core import transforms
from rtabmap_ros2.core.graph import Link, LinkType
from rtabmap_ros2.core.database_blobs import encode_rgb
from rtabmap_ros2.core.params import flatten
from rtabmap_ros2.core.sensor import CameraModel, LaserScan, depth_to_mm
from rtabmap_ros2.errors import SensorDataError
from rtabmap_ros2.io import bag

NS_PER_S = 1_000_000_000

# Base -> camera optical frame when a CameraInfo arrives without an extrinsic calibration (no tf2
# here to read one): the bag reader's default, the optical frame at the base origin with the
# standard optical rotation (optical z forward = base x).
DEFAULT_T_BASE_CAMERA = bag.DEFAULT_T_BASE_CAMERA


# Marker appearance (RViz): node sphere diameter and link line width (m), RGBA colours.
NODE_MARKER_SCALE = 0.05
LINK_MARKER_WIDTH = 0.02
NODE_COLOR = (1.0, 1.0, 0.0, 1.0)      # yellow
NEIGHBOR_COLOR = (0.0, 0.0, 1.0, 1.0)  # blue
LOOP_INTRA_COLOR = (1.0, 0.0, 0.0, 1.0)  # red
LOOP_INTER_COLOR = (0.0, 1.0, 0.0, 1.0)  # green
_LINK_STYLE = {
    LinkType.NEIGHBOR: ("neighbor_links", NEIGHBOR_COLOR),
    LinkType.LOOP_INTRA: ("loop_closures_intra", LOOP_INTRA_COLOR),
    LinkType.LOOP_INTER: ("loop_closures_inter", LOOP_INTER_COLOR),
}


# -- stamps and headers -----------------------------------------------------------------------
def stamp_to_ns(stamp: Time) -> int:
    """Nanoseconds of a ``builtin_interfaces/Time``."""
    return int(stamp.sec) * NS_PER_S + int(stamp.nanosec)


def stamp_from_ns(stamp_ns: int) -> Time:
    """``builtin_interfaces/Time`` of a stamp in nanoseconds (>= 0)."""
    stamp_ns = int(stamp_ns)
    if stamp_ns < 0:
        raise ValueError(f"stamp {stamp_ns} ns is negative: ROS time starts at 0")
    return Time(sec=stamp_ns // NS_PER_S, nanosec=stamp_ns % NS_PER_S)


def header(stamp_ns: int, frame_id: str) -> Header:
    """A ``std_msgs/Header``."""
    return Header(stamp=stamp_from_ns(stamp_ns), frame_id=frame_id)


def frame_id_from_header(msg: Any) -> str:
    """The ``header.frame_id`` of a stamped message; SensorDataError when it is empty.

    An empty frame_id names no sensor frame: its mount cannot be looked up (rtabmap_ros drops
    such messages too, failing the TF look-up).
    """
    frame_id = msg.header.frame_id
    if not frame_id.strip():
        raise SensorDataError(f"{type(msg).__name__} message has an empty header.frame_id: set the sensor frame",
                              "empty_frame_id")
    return frame_id


# -- poses -------------------------------------------------------------------------------------
def pose_to_msg(T: np.ndarray) -> Pose:
    """``geometry_msgs/Pose`` of a 4x4 rigid transform (m)."""
    q = transforms.quat_xyzw(T)
    return Pose(position=Point(x=float(T[0, 3]), y=float(T[1, 3]), z=float(T[2, 3])),
                orientation=Quaternion(x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3])))


def pose_from_msg(pose: Pose) -> np.ndarray:
    """4x4 transform (m) of a ``geometry_msgs/Pose``; SensorDataError on NaN or a zero quaternion."""
    p, o = pose.position, pose.orientation
    return _xyz_quat_to_T((p.x, p.y, p.z), (o.x, o.y, o.z, o.w), "pose")


def transform_to_msg(T_parent_child: np.ndarray, stamp_ns: int, parent_frame: str,
                     child_frame: str) -> TransformStamped:
    """``geometry_msgs/TransformStamped`` (the TF of ``child_frame`` in ``parent_frame``)."""
    q = transforms.quat_xyzw(T_parent_child)
    t = T_parent_child[:3, 3]
    return TransformStamped(
        header=header(stamp_ns, parent_frame), child_frame_id=child_frame,
        transform=Transform(translation=Vector3(x=float(t[0]), y=float(t[1]), z=float(t[2])),
                            rotation=Quaternion(x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3]))))


def transform_from_msg(msg: TransformStamped) -> np.ndarray:
    """4x4 ``T_parent_child`` of a ``geometry_msgs/TransformStamped``."""
    t, r = msg.transform.translation, msg.transform.rotation
    return _xyz_quat_to_T((t.x, t.y, t.z), (r.x, r.y, r.z, r.w), "transform")


def _xyz_quat_to_T(xyz, quat_xyzw, what: str) -> np.ndarray:
    values = np.array([*xyz, *quat_xyzw], dtype=np.float64)
    if not np.all(np.isfinite(values)):
        raise SensorDataError(f"{what} has NaN or inf values {values.tolist()}: check the odometry source",
                              "non_finite_pose")
    try:
        return transforms.from_xyz_quat_xyzw(values[:3], values[3:])
    except ValueError as exc:
        raise SensorDataError(f"{what} has an invalid quaternion: {exc}", "invalid_quaternion") from exc


# -- odometry ----------------------------------------------------------------------------------
def odometry_from_msg(msg: Odometry) -> tuple[np.ndarray, np.ndarray]:
    """``(T_odom_base 4x4, covariance 6x6)`` of a ``nav_msgs/Odometry``.

    The covariance is over (x, y, z, roll, pitch, yaw), row-major as in the message. NaN or inf in
    the pose or the covariance, or a zero quaternion, raise SensorDataError.
    """
    T = pose_from_msg(msg.pose.pose)
    cov = np.asarray(msg.pose.covariance, dtype=np.float64).reshape(6, 6)
    if not np.all(np.isfinite(cov)):
        raise SensorDataError("odometry covariance has NaN or inf values", "non_finite_covariance")
    return T, cov


def odometry_to_msg(T_odom_base: np.ndarray, stamp_ns: int, odom_frame: str = "odom",
                    base_frame: str = "base_link", covariance: np.ndarray | None = None) -> Odometry:
    """``nav_msgs/Odometry`` of a pose (4x4) and its 6x6 covariance (zeros if None)."""
    msg = Odometry(header=header(stamp_ns, odom_frame), child_frame_id=base_frame)
    msg.pose.pose = pose_to_msg(T_odom_base)
    if covariance is not None:
        msg.pose.covariance = np.asarray(covariance, dtype=np.float64).reshape(36)
    return msg


# -- images ------------------------------------------------------------------------------------
# Decoding is the bag reader's (rtabmap_ros2.io.bag), one implementation for rclpy and rosbags
# messages: raw Images in every encoding drivers publish, JPEG/PNG ``compressed`` and
# image_transport's ``compressedDepth``.
image_from_msg = bag.image_from_msg
depth_from_msg = bag.depth_from_msg
compressed_image_from_msg = bag.compressed_image_from_msg
compressed_depth_from_msg = bag.compressed_depth_from_msg
compressed_image_and_jpeg = bag.compressed_image_and_jpeg
compressed_depth_and_png = bag.compressed_depth_and_png


def image_to_msg(rgb: np.ndarray, stamp_ns: int, frame_id: str, encoding: str = "rgb8") -> Image:
    """``sensor_msgs/Image`` of an RGB HxWx3 uint8 image, written in ``encoding`` (any encoding
    :func:`image_from_msg` reads: rgb8, bgr8, rgba8, bgra8, mono8, mono16, bayer_*, yuv422, yuyv...)."""
    rgb = np.asarray(rgb)
    if rgb.dtype != np.uint8 or rgb.ndim != 3 or rgb.shape[2] != 3:
        raise SensorDataError(f"image must be HxWx3 uint8 RGB, got shape {rgb.shape} dtype {rgb.dtype}")
    pixels = bag.pixels_of_rgb(rgb, encoding)
    pixels = pixels.astype(pixels.dtype.newbyteorder("<"), copy=False)   # is_bigendian = 0
    h, w = rgb.shape[:2]
    msg = Image(header=header(stamp_ns, frame_id), height=h, width=w, encoding=encoding,
                is_bigendian=0, step=pixels.strides[0])
    msg.data = pixels.tobytes()
    return msg


def compressed_image_to_msg(rgb: np.ndarray, stamp_ns: int, frame_id: str) -> CompressedImage:
    """``sensor_msgs/CompressedImage`` (JPEG, image_transport's ``compressed``) of an RGB image."""
    msg = CompressedImage(header=header(stamp_ns, frame_id), format=bag.JPEG_FORMAT)
    msg.data = encode_rgb(rgb)
    return msg


def compressed_depth_to_msg(depth_m: np.ndarray, stamp_ns: int, frame_id: str) -> CompressedImage:
    """``sensor_msgs/CompressedImage`` in image_transport's ``compressedDepth`` format of a depth (m)."""
    msg = CompressedImage(header=header(stamp_ns, frame_id), format=bag.COMPRESSED_DEPTH_FORMAT)
    msg.data = bag.compressed_depth_of_depth(depth_m)
    return msg


def depth_to_msg(depth_m: np.ndarray, stamp_ns: int, frame_id: str, encoding: str = "16UC1") -> Image:
    """``sensor_msgs/Image`` of an HxW depth (m, NaN invalid) as 16UC1 (mm, 0 invalid) or 32FC1 (m)."""
    depth_m = np.asarray(depth_m, dtype=np.float32)
    if depth_m.ndim != 2:
        raise SensorDataError(f"depth must be HxW, got shape {depth_m.shape}")
    if encoding in ("16UC1", "mono16"):
        pixels = depth_to_mm(depth_m).astype("<u2")
    elif encoding == "32FC1":
        pixels = depth_m.astype("<f4")
    else:
        raise SensorDataError(f"depth_to_msg: encoding {encoding!r} is not 16UC1 or 32FC1")
    h, w = depth_m.shape
    msg = Image(header=header(stamp_ns, frame_id), height=h, width=w, encoding=encoding,
                is_bigendian=0, step=w * pixels.itemsize)
    msg.data = pixels.tobytes()
    return msg


# -- camera info -------------------------------------------------------------------------------
def camera_model_from_msg(msg: CameraInfo, T_base_camera: np.ndarray | None = None) -> CameraModel:
    """Pinhole model of a ``sensor_msgs/CameraInfo`` (the bag reader's: K, or P when it differs).

    ``T_base_camera`` (4x4 base -> optical frame) defaults to :data:`DEFAULT_T_BASE_CAMERA`.
    """
    try:
        return bag.camera_info_from_msg(msg, DEFAULT_T_BASE_CAMERA if T_base_camera is None else T_base_camera)
    except SensorDataError as exc:
        raise SensorDataError(f"camera_info unusable: {exc}", exc.reason) from exc


def camera_info_to_msg(camera: CameraModel, stamp_ns: int, frame_id: str) -> CameraInfo:
    """``sensor_msgs/CameraInfo`` of a pinhole model (no distortion, P = [K | 0])."""
    msg = CameraInfo(header=header(stamp_ns, frame_id), width=camera.width, height=camera.height,
                     distortion_model="plumb_bob")
    msg.k = np.array([camera.fx, 0, camera.cx, 0, camera.fy, camera.cy, 0, 0, 1], dtype=np.float64)
    msg.r = np.eye(3).reshape(9)
    msg.p = np.array([camera.fx, 0, camera.cx, 0, 0, camera.fy, camera.cy, 0, 0, 0, 1, 0], dtype=np.float64)
    msg.d = array.array("d", [0.0] * 5)
    return msg


# -- laser scans -------------------------------------------------------------------------------
def scan_from_msg(msg: LaserScanMsg, T_base_laser: np.ndarray | None = None) -> LaserScan:
    """Core LaserScan of a ``sensor_msgs/LaserScan``; SensorDataError if empty or without a return."""
    ranges = np.frombuffer(msg.ranges, dtype=np.float32).astype(np.float32)
    if ranges.size == 0:
        raise SensorDataError("laser scan is empty (no ranges)", "empty_scan")
    if not np.isfinite(ranges).any():
        raise SensorDataError(f"laser scan has no finite range ({ranges.size} beams, all NaN/inf)", "no_valid_scan")
    scan = LaserScan(ranges=ranges, angle_min=float(msg.angle_min), angle_increment=float(msg.angle_increment),
                     range_min=float(msg.range_min), range_max=float(msg.range_max),
                     **({} if T_base_laser is None else {"T_base_laser": T_base_laser}))
    if not scan.valid_mask().any():
        raise SensorDataError(
            f"laser scan has no range inside [{scan.range_min}, {scan.range_max}) m", "no_valid_scan")
    return scan


def scan_to_msg(scan: LaserScan, stamp_ns: int, frame_id: str) -> LaserScanMsg:
    """``sensor_msgs/LaserScan`` of a core LaserScan (angles rad, ranges m)."""
    ranges = np.asarray(scan.ranges, dtype=np.float32)
    msg = LaserScanMsg(header=header(stamp_ns, frame_id), angle_min=float(scan.angle_min),
                       angle_max=float(scan.angle_min + scan.angle_increment * (ranges.size - 1)),
                       angle_increment=float(scan.angle_increment), range_min=float(scan.range_min),
                       range_max=float(scan.range_max))
    msg.ranges = array.array("f", ranges.tobytes())
    return msg


# -- map outputs -------------------------------------------------------------------------------
def grid_to_msg(grid: Any, stamp_ns: int, frame_id: str) -> OccupancyGridMsg:
    """``nav_msgs/OccupancyGrid`` of a ``core.grid.OccupancyGrid``.

    ``grid.data`` is (H,W) int8 (-1 unknown, 0 free, 100 occupied) with ``data[row=y, col=x]``,
    ``grid.resolution`` m/cell, ``grid.origin_xy`` the map-frame position (m) of cell (0, 0)'s corner.
    """
    data = np.ascontiguousarray(grid.data, dtype=np.int8)
    msg = OccupancyGridMsg(header=header(stamp_ns, frame_id))
    msg.info.map_load_time = msg.header.stamp
    msg.info.resolution = float(grid.resolution)
    msg.info.height, msg.info.width = int(data.shape[0]), int(data.shape[1])
    msg.info.origin.position.x = float(grid.origin_xy[0])
    msg.info.origin.position.y = float(grid.origin_xy[1])
    msg.info.origin.orientation.w = 1.0
    msg.data = array.array("b", data.tobytes())
    return msg


def grid_from_msg(msg: OccupancyGridMsg) -> tuple[np.ndarray, float, tuple[float, float]]:
    """``(data (H,W) int8, resolution m, origin_xy m)`` of a ``nav_msgs/OccupancyGrid``."""
    h, w = int(msg.info.height), int(msg.info.width)
    data = np.frombuffer(msg.data, dtype=np.int8)
    if data.size != h * w:
        raise SensorDataError(f"occupancy grid holds {data.size} cells, expected {w}x{h}")
    return (data.reshape(h, w).copy(), float(msg.info.resolution),
            (float(msg.info.origin.position.x), float(msg.info.origin.position.y)))


def path_to_msg(poses: Mapping[int, np.ndarray], stamp_ns: int, frame_id: str) -> Path:
    """``nav_msgs/Path`` of ``{node id: T_map_base 4x4}``, ordered by node id.

    The quaternions of all poses are computed at once (``transforms.quats_xyzw``), and each
    PoseStamped's own default Pose is filled in (passing a new Pose, Point and Quaternion made the
    defaults for nothing): a 1,700-node local map took ~50 ms one pose at a time, on the node's
    publisher thread, four times a second at 4x replay (issue 50; ``bench_node.py``'s conversion
    rows)."""
    hdr = header(stamp_ns, frame_id)
    msg = Path(header=hdr)
    if not poses:
        return msg
    T = np.stack([poses[i] for i in sorted(poses)])
    stamped = []
    for (x, y, z), (qx, qy, qz, qw) in zip(T[:, :3, 3].tolist(), transforms.quats_xyzw(T).tolist()):
        pose = PoseStamped(header=hdr)
        position, orientation = pose.pose.position, pose.pose.orientation
        position.x, position.y, position.z = x, y, z
        orientation.x, orientation.y, orientation.z, orientation.w = qx, qy, qz, qw
        stamped.append(pose)
    msg.poses = stamped
    return msg


def path_from_msg(msg: Path) -> list[np.ndarray]:
    """The 4x4 poses of a ``nav_msgs/Path``, in message order."""
    return [pose_from_msg(p.pose) for p in msg.poses]


def _color(rgba: tuple[float, float, float, float]) -> ColorRGBA:
    return ColorRGBA(r=rgba[0], g=rgba[1], b=rgba[2], a=rgba[3])


def graph_to_markers(poses: Mapping[int, np.ndarray], links: Iterable[Link], stamp_ns: int,
                     frame_id: str) -> MarkerArray:
    """``visualization_msgs/MarkerArray`` of a graph: nodes and links coloured by type.

    Markers (namespaces): a DELETEALL first (so a reset map leaves nothing behind), ``nodes``
    (SPHERE_LIST at each ``T_map_base``), ``neighbor_links`` (LINE_LIST, blue),
    ``loop_closures_intra`` (red) and ``loop_closures_inter`` (green). Links with an end not in
    ``poses`` are skipped.
    """
    hdr = header(stamp_ns, frame_id)
    markers = [Marker(header=hdr, action=Marker.DELETEALL)]
    nodes = Marker(header=hdr, ns="nodes", id=0, type=Marker.SPHERE_LIST, action=Marker.ADD)
    nodes.pose.orientation.w = 1.0
    nodes.scale.x = nodes.scale.y = nodes.scale.z = NODE_MARKER_SCALE
    nodes.color = _color(NODE_COLOR)
    # One Point per node, shared by the node list and its links' line ends (a message is
    # serialised by value): 1,700 nodes and 2,000 links made 5,700 Points, now 1,700.
    ids = sorted(poses)
    xyz = np.stack([poses[i] for i in ids])[:, :3, 3].tolist() if ids else []
    points = {i: Point(x=x, y=y, z=z) for i, (x, y, z) in zip(ids, xyz)}
    nodes.points = [points[i] for i in ids]
    markers.append(nodes)
    by_type: dict[LinkType, list[Point]] = {t: [] for t in _LINK_STYLE}
    for link in links:
        if link.from_id in points and link.to_id in points:
            by_type[LinkType(link.type)] += [points[link.from_id], points[link.to_id]]
    for marker_id, (link_type, (ns, rgba)) in enumerate(_LINK_STYLE.items(), start=1):
        m = Marker(header=hdr, ns=ns, id=marker_id, type=Marker.LINE_LIST, action=Marker.ADD)
        m.pose.orientation.w = 1.0
        m.scale.x = LINK_MARKER_WIDTH
        m.color = _color(rgba)
        m.points = by_type[link_type]
        markers.append(m)
    return MarkerArray(markers=markers)


# -- statistics --------------------------------------------------------------------------------
STATUS_NAME = "rtabmap"
HARDWARE_ID = "rtabmap_ros2"


def statistics_to_msg(statistics: Any, stamp_ns: int, frame_id: str = "") -> DiagnosticArray:
    """``diagnostic_msgs/DiagnosticArray`` carrying one frame's statistics (the ``info`` topic).

    ``statistics`` is a ``Statistics`` (anything with ``to_dict()``) or a mapping. The array holds
    one ``DiagnosticStatus`` named ``rtabmap`` (level OK) whose ``values`` are one ``KeyValue`` per
    statistic, values as text (nested mappings flattened as ``parent/child``, e.g.
    ``timings_ms/bayes``) and whose ``message`` summarises the location and loop closure ids.
    """
    values = statistics.to_dict() if hasattr(statistics, "to_dict") else dict(statistics)
    flat = flatten(values, separator="/")
    summary = (f"location {flat.get('location_id', '?')}, map {flat.get('map_id', '?')}, "
               f"loop closure {flat.get('loop_closure_id', '?')}")
    status = DiagnosticStatus(level=DiagnosticStatus.OK, name=STATUS_NAME, hardware_id=HARDWARE_ID,
                              message=summary,
                              values=[KeyValue(key=k, value=_text(v)) for k, v in flat.items()])
    return DiagnosticArray(header=header(stamp_ns, frame_id), status=[status])


def statistics_from_msg(msg: DiagnosticArray) -> dict[str, str]:
    """The ``{key: value text}`` of the ``rtabmap`` status of an ``info`` message."""
    for status in msg.status:
        if status.name == STATUS_NAME:
            return {kv.key: kv.value for kv in status.values}
    raise SensorDataError(f"info message has no {STATUS_NAME!r} status")


def _text(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (float, np.floating)):
        return repr(float(value))
    return str(value)
