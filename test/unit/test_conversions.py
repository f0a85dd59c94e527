"""Round trips of the ROS message conversions on messages built in memory (no DDS needed)."""

from __future__ import annotations

import math

import cv2

import numpy as np
import pytest

pytest.importorskip("rclpy")

from diagnostic_msgs.msg import DiagnosticStatus  # noqa: E402
from nav_msgs.msg import Odometry  # noqa: E402
from sensor_msgs.msg import Image  # noqa: E402
from sensor_msgs.msg import LaserScan as LaserScanMsg  # noqa: E402
from visualization_msgs.msg import Marker  # noqa: E402

from rtabmap_ros2.core import transforms  # noqa: E402
from rtabmap_ros2.core.graph import Link, LinkType  # noqa: E402
from rtabmap_ros2.core.sensor import CameraModel, LaserScan  # noqa: E402
from rtabmap_ros2.errors import SensorDataError  # noqa: E402
from rtabmap_ros2.ros import conversions as conv  # noqa: E402


@pytest.fixture
def rgb(rng):
    return rng.integers(0, 256, size=(6, 5, 3), dtype=np.uint8)


def test_stamp_round_trip():
    for ns in (0, 1, 999_999_999, 1_700_000_000_123_456_789):
        assert conv.stamp_to_ns(conv.stamp_from_ns(ns)) == ns
    with pytest.raises(ValueError):
        conv.stamp_from_ns(-1)


def test_pose_round_trip(random_se3):
    for _ in range(20):
        T = random_se3()
        np.testing.assert_allclose(conv.pose_from_msg(conv.pose_to_msg(T)), T, atol=1e-12)


def test_transform_round_trip(random_se3):
    T = random_se3()
    msg = conv.transform_to_msg(T, 5, "map", "odom")
    assert (msg.header.frame_id, msg.child_frame_id) == ("map", "odom")
    np.testing.assert_allclose(conv.transform_from_msg(msg), T, atol=1e-12)


def test_odometry_round_trip_with_covariance(random_se3):
    T = random_se3()
    cov = np.diag([1e-2, 2e-2, 3e-2, 4e-3, 5e-3, 6e-3])
    cov[0, 5] = cov[5, 0] = 1e-4
    msg = conv.odometry_to_msg(T, 42, covariance=cov)
    T2, cov2 = conv.odometry_from_msg(msg)
    np.testing.assert_allclose(T2, T, atol=1e-12)
    np.testing.assert_array_equal(cov2, cov)
    assert conv.stamp_to_ns(msg.header.stamp) == 42


@pytest.mark.parametrize("field,value,reason", [
    ("position.x", math.nan, "NaN"),
    ("orientation.w", math.inf, "NaN or inf"),
])
def test_odometry_with_nan_is_rejected(field, value, reason):
    msg = Odometry()
    msg.pose.pose.orientation.w = 1.0
    part, attr = field.split(".")
    setattr(getattr(msg.pose.pose, part), attr, value)
    with pytest.raises(SensorDataError, match=reason):
        conv.odometry_from_msg(msg)


def test_odometry_zero_quaternion_is_rejected():
    msg = Odometry()
    msg.pose.pose.orientation.w = 0.0  # Jazzy's default is the identity (w = 1)
    with pytest.raises(SensorDataError, match="quaternion"):
        conv.odometry_from_msg(msg)


def test_odometry_nan_covariance_is_rejected():
    msg = conv.odometry_to_msg(np.eye(4), 0)
    cov = np.zeros(36)
    cov[7] = np.nan
    msg.pose.covariance = cov
    with pytest.raises(SensorDataError, match="covariance"):
        conv.odometry_from_msg(msg)


@pytest.mark.parametrize("encoding", ["rgb8", "bgr8"])
def test_color_image_round_trip(rgb, encoding):
    msg = conv.image_to_msg(rgb, 7, "camera", encoding)
    assert msg.encoding == encoding and msg.step == rgb.shape[1] * 3
    out = conv.image_from_msg(msg)
    np.testing.assert_array_equal(out, rgb)
    assert out.flags.writeable


def test_bgr8_bytes_are_reversed(rgb):
    msg = conv.image_to_msg(rgb, 0, "camera", "bgr8")
    first = np.frombuffer(msg.data, np.uint8)[:3]
    np.testing.assert_array_equal(first, rgb[0, 0, ::-1])


def test_mono8_becomes_gray_rgb(rgb):
    msg = conv.image_to_msg(rgb, 0, "camera", "mono8")
    out = conv.image_from_msg(msg)
    gray = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)   # luma weights (cv_bridge's)
    for c in range(3):
        np.testing.assert_array_equal(out[:, :, c], gray)


def _padded(msg: Image, pad: int) -> Image:
    """The same image with ``pad`` junk bytes at the end of each row."""
    rows = np.frombuffer(msg.data, np.uint8).reshape(msg.height, msg.step)
    junk = np.full((msg.height, pad), 0xAB, np.uint8)
    msg.data = np.hstack([rows, junk]).tobytes()
    msg.step = msg.step + pad
    return msg


@pytest.mark.parametrize("encoding", ["rgb8", "bgr8", "mono8"])
def test_image_step_padding_is_honoured(rgb, encoding):
    reference = conv.image_from_msg(conv.image_to_msg(rgb, 0, "c", encoding))
    padded = _padded(conv.image_to_msg(rgb, 0, "c", encoding), pad=7)
    np.testing.assert_array_equal(conv.image_from_msg(padded), reference)


def test_unsupported_image_encoding_names_it(rgb):
    msg = conv.image_to_msg(rgb, 0, "c")
    msg.encoding = "yuv444"
    with pytest.raises(SensorDataError, match="yuv444"):
        conv.image_from_msg(msg)


def test_truncated_image_is_rejected(rgb):
    msg = conv.image_to_msg(rgb, 0, "c")
    msg.data = bytes(msg.data)[:-1]
    with pytest.raises(SensorDataError, match="bytes"):
        conv.image_from_msg(msg)


def test_step_smaller_than_width_is_rejected(rgb):
    msg = conv.image_to_msg(rgb, 0, "c")
    msg.step = 4
    with pytest.raises(SensorDataError, match="step"):
        conv.image_from_msg(msg)


def test_depth_16uc1_round_trip_mm_and_zero_is_nan():
    depth = np.array([[0.0, 1.0, 1.234], [np.nan, 4.5, 65.535]], dtype=np.float32)
    msg = conv.depth_to_msg(depth, 0, "camera", "16UC1")
    assert np.frombuffer(msg.data, "<u2").tolist() == [0, 1000, 1234, 0, 4500, 65535]
    out = conv.depth_from_msg(msg)
    assert out.dtype == np.float32
    np.testing.assert_allclose(out, [[np.nan, 1.0, 1.234], [np.nan, 4.5, 65.535]], rtol=1e-6)


def test_depth_32fc1_round_trip_with_padding():
    depth = np.array([[0.5, np.nan, 0.0], [2.25, 3.0, 9.0]], dtype=np.float32)
    msg = _padded(conv.depth_to_msg(depth, 0, "camera", "32FC1"), pad=4)
    out = conv.depth_from_msg(msg)
    np.testing.assert_array_equal(out, [[0.5, np.nan, np.nan], [2.25, 3.0, 9.0]])


def test_depth_big_endian_16uc1():
    values = np.array([[1000, 2000]], dtype=">u2")
    msg = Image(height=1, width=2, encoding="16UC1", is_bigendian=1, step=4)
    msg.data = values.tobytes()
    np.testing.assert_allclose(conv.depth_from_msg(msg), [[1.0, 2.0]])


def test_depth_inf_is_rejected():
    depth = np.array([[1.0, np.inf]], dtype=np.float32)
    with pytest.raises(SensorDataError, match="inf"):
        conv.depth_from_msg(conv.depth_to_msg(depth, 0, "c", "32FC1"))


def test_depth_bad_encoding_names_it(rgb):
    with pytest.raises(SensorDataError, match="rgb8"):
        conv.depth_from_msg(conv.image_to_msg(rgb, 0, "c"))


def test_camera_info_round_trip():
    cam = CameraModel(525.0, 526.0, 319.5, 239.5, 640, 480)
    model = conv.camera_model_from_msg(conv.camera_info_to_msg(cam, 0, "camera"))
    assert (model.fx, model.fy, model.cx, model.cy, model.width, model.height) == (525.0, 526.0, 319.5, 239.5, 640, 480)
    np.testing.assert_array_equal(model.T_base_camera, conv.DEFAULT_T_BASE_CAMERA)
    # The default maps the optical axis (z) onto the base's forward axis (x).
    np.testing.assert_allclose(model.T_base_camera[:3, :3] @ [0, 0, 1], [1, 0, 0])


def test_empty_camera_info_is_rejected():
    from sensor_msgs.msg import CameraInfo

    with pytest.raises(SensorDataError, match="camera_info"):
        conv.camera_model_from_msg(CameraInfo(width=640, height=480))


def test_scan_round_trip():
    ranges = np.array([1.0, np.nan, 2.5, np.inf, 3.0], dtype=np.float32)
    scan = LaserScan(ranges, angle_min=-0.5, angle_increment=0.25, range_min=0.1, range_max=10.0)
    msg = conv.scan_to_msg(scan, 3, "laser")
    assert msg.angle_max == pytest.approx(0.5)
    out = conv.scan_from_msg(msg)
    np.testing.assert_array_equal(out.ranges, ranges)
    assert (out.angle_min, out.angle_increment, out.range_min, out.range_max) == pytest.approx((-0.5, 0.25, 0.1, 10.0))


@pytest.mark.parametrize("ranges,reason", [([], "empty"), ([np.nan, np.nan], "no finite"),
                                           ([20.0, 30.0], "no range inside")])
def test_bad_scans_are_rejected(ranges, reason):
    msg = LaserScanMsg(angle_min=0.0, angle_increment=0.1, range_min=0.1, range_max=10.0)
    msg.ranges = [float(r) for r in ranges]
    with pytest.raises(SensorDataError, match=reason):
        conv.scan_from_msg(msg)


class _Grid:
    def __init__(self, data, resolution, origin_xy):
        self.data, self.resolution, self.origin_xy = data, resolution, origin_xy


def test_grid_round_trip(rng):
    data = rng.choice(np.array([-1, 0, 100], np.int8), size=(4, 7))
    msg = conv.grid_to_msg(_Grid(data, 0.05, (-1.5, 2.0)), 9, "map")
    assert (msg.info.width, msg.info.height, msg.header.frame_id) == (7, 4, "map")
    out, resolution, origin = conv.grid_from_msg(msg)
    np.testing.assert_array_equal(out, data)
    assert resolution == pytest.approx(0.05) and origin == (-1.5, 2.0)
    # nav_msgs: row-major from cell (0, 0), x along columns.
    assert msg.data[1] == data[0, 1]


def test_path_is_ordered_by_id(random_se3):
    poses = {5: random_se3(), 1: random_se3(), 3: random_se3()}
    msg = conv.path_to_msg(poses, 11, "map")
    assert msg.header.frame_id == "map" and all(p.header.frame_id == "map" for p in msg.poses)
    out = conv.path_from_msg(msg)
    for T, i in zip(out, [1, 3, 5]):
        np.testing.assert_allclose(T, poses[i], atol=1e-12)


def test_path_poses_equal_the_single_pose_message_on_every_quaternion_branch(random_se3):
    """path_to_msg computes all quaternions at once: each pose message equals pose_to_msg's, on
    rotations of every branch of the conversion (trace > 0, and 180 deg about x, y and z, where
    the largest diagonal term decides), and an empty map is an empty path."""
    turns = [transforms.from_xyz_rpy([1, 2, 3, np.pi, 0, 0]), transforms.from_xyz_rpy([0, 0, 0, 0, np.pi, 0]),
             transforms.from_xyz_rpy([-1, 0, 0.5, 0, 0, np.pi]), transforms.from_xyz_rpy([0, 1, 0, 3.0, 0.1, -2.9])]
    poses = dict(enumerate(turns + [random_se3() for _ in range(20)]))
    msg = conv.path_to_msg(poses, 11, "map")
    def values(pose):
        return [pose.position.x, pose.position.y, pose.position.z,
                pose.orientation.x, pose.orientation.y, pose.orientation.z, pose.orientation.w]

    # to rounding, not bit for bit: the machine's vector units may order a sum differently
    np.testing.assert_allclose([values(p.pose) for p in msg.poses],
                               [values(conv.pose_to_msg(poses[i])) for i in sorted(poses)], rtol=0, atol=1e-12)
    assert conv.path_to_msg({}, 11, "map").poses == []
    assert conv.graph_to_markers({}, [], 0, "map").markers[1].points == []


def test_graph_markers_colour_links_by_type():
    poses = {i: transforms.from_xy_yaw(float(i), 0.0, 0.0) for i in (1, 2, 3, 4)}
    links = [Link(1, 2, LinkType.NEIGHBOR), Link(2, 3, LinkType.NEIGHBOR), Link(3, 1, LinkType.LOOP_INTRA),
             Link(4, 1, LinkType.LOOP_INTER), Link(4, 99, LinkType.NEIGHBOR)]  # 99 unknown: skipped
    msg = conv.graph_to_markers(poses, links, 0, "map")
    assert msg.markers[0].action == Marker.DELETEALL
    by_ns = {m.ns: m for m in msg.markers[1:]}
    assert [p.x for p in by_ns["nodes"].points] == [1.0, 2.0, 3.0, 4.0]
    assert len(by_ns["neighbor_links"].points) == 4
    assert (by_ns["neighbor_links"].color.b, by_ns["neighbor_links"].color.r) == (1.0, 0.0)
    intra, inter = by_ns["loop_closures_intra"], by_ns["loop_closures_inter"]
    assert [p.x for p in intra.points] == [3.0, 1.0] and intra.color.r == 1.0 and intra.color.g == 0.0
    assert [p.x for p in inter.points] == [4.0, 1.0] and inter.color.g == 1.0 and inter.color.r == 0.0
    assert len({m.id for m in msg.markers[1:]}) == 4


def test_statistics_round_trip():
    class Stats:
        def to_dict(self):
            return {"location_id": 12, "loop_closure_id": 3, "highest_hypothesis_value": 0.25,
                    "new_map": False, "timings_ms": {"bayes": 1.5}}

    msg = conv.statistics_to_msg(Stats(), 5, "map")
    assert msg.status[0].level == DiagnosticStatus.OK
    assert "location 12" in msg.status[0].message and "loop closure 3" in msg.status[0].message
    values = conv.statistics_from_msg(msg)
    assert values == {"location_id": "12", "loop_closure_id": "3", "highest_hypothesis_value": "0.25",
                      "new_map": "false", "timings_ms/bayes": "1.5"}


# -- issue 13: the encodings drivers publish, compressed transports, P, registration, mounts --------
def _smooth_rgb(h: int = 48, w: int = 64) -> np.ndarray:
    """A smooth colour image (demosaicing and 4:2:2 chroma are exact only where colour varies slowly)."""
    y, x = np.mgrid[0:h, 0:w]
    rgb = np.stack([(x * 4) % 256, (y * 5) % 256, ((x + y) * 2) % 256], axis=2).astype(np.uint8)
    return cv2.GaussianBlur(rgb, (7, 7), 2)


@pytest.mark.parametrize("encoding, max_mean_error", [
    ("rgba8", 0), ("bgra8", 0), ("rgb16", 0), ("bgr16", 0),
    ("bayer_rggb8", 1), ("bayer_bggr8", 1), ("bayer_gbrg8", 1), ("bayer_grbg8", 1), ("bayer_rggb16", 1),
    ("yuv422", 1.5), ("yuv422_yuy2", 1.5), ("yuyv", 1.5)])
def test_colour_encodings_round_trip(encoding, max_mean_error):
    rgb = _smooth_rgb()
    msg = conv.image_to_msg(rgb, 0, "c", encoding)
    out = conv.image_from_msg(_padded(msg, pad=6))
    error = np.abs(out.astype(int) - rgb.astype(int))[4:-4, 4:-4]   # demosaicing borders aside
    assert out.shape == rgb.shape and error.mean() <= max_mean_error, (encoding, error.mean())


@pytest.mark.parametrize("encoding, other", [("bayer_rggb8", "bayer_bggr8"), ("bayer_gbrg8", "bayer_grbg8"),
                                             ("yuv422", "yuyv")])
def test_colour_encodings_are_told_apart(encoding, other):
    """Reading a mosaic with the wrong pattern (or UYVY as YUYV) gives other colours: the table is not a no-op."""
    rgb = _smooth_rgb()
    msg = conv.image_to_msg(rgb, 0, "c", encoding)
    msg.encoding = other
    assert np.abs(conv.image_from_msg(msg).astype(int) - rgb.astype(int)).mean() > 10


def test_mono16_colour_is_grey():
    rgb = _smooth_rgb()
    msg = conv.image_to_msg(rgb, 0, "c", "mono16")
    assert msg.step == 2 * rgb.shape[1]
    out = conv.image_from_msg(msg)
    np.testing.assert_array_equal(out[..., 0], cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY))
    np.testing.assert_array_equal(out[..., 0], out[..., 2])


def test_compressed_image_and_depth_round_trip():
    rgb = _smooth_rgb()
    out = conv.compressed_image_from_msg(conv.compressed_image_to_msg(rgb, 5, "c"))
    assert np.abs(out.astype(int) - rgb.astype(int)).mean() < 3   # JPEG
    depth = np.array([[0.0, 1.0, 1.234], [np.nan, 4.5, 65.535]], dtype=np.float32)
    msg = conv.compressed_depth_to_msg(depth, 5, "c")
    assert msg.format == "16UC1; compressedDepth png"
    np.testing.assert_allclose(conv.compressed_depth_from_msg(msg), [[np.nan, 1.0, 1.234], [np.nan, 4.5, 65.535]],
                               rtol=1e-6)


def test_rectified_projection_is_used_when_p_differs_from_k():
    cam = CameraModel(525.0, 526.0, 319.5, 239.5, 640, 480)
    msg = conv.camera_info_to_msg(cam, 0, "camera")
    msg.d = np.array([0.1, -0.2, 0.0, 0.0, 0.05])   # a distorted camera: P is the rectified image's
    msg.p = np.array([500.0, 0, 321.0, 0, 0, 501.0, 238.0, 0, 0, 0, 1, 0])
    model = conv.camera_model_from_msg(msg)
    assert (model.fx, model.fy, model.cx, model.cy) == (500.0, 501.0, 321.0, 238.0)
    assert model.distortion == ()                      # rectified images: nothing to undistort
    msg.p = np.zeros(12)   # P unset: K
    assert conv.camera_model_from_msg(msg).fx == 525.0


def test_raw_images_keep_their_distortion_for_the_visual_words():
    """D with P = K: raw images, the model keeps D (the words are undistorted with it); a model OpenCV's
    undistortPoints does not take (equidistant, a fisheye) or D = 0 gives a plain pinhole."""
    msg = conv.camera_info_to_msg(CameraModel(525.0, 526.0, 319.5, 239.5, 640, 480), 0, "camera")
    msg.d = np.array([0.1, -0.2, 0.001, 0.002, 0.05])
    assert conv.camera_model_from_msg(msg).distortion == pytest.approx((0.1, -0.2, 0.001, 0.002, 0.05))
    msg.distortion_model = "equidistant"
    msg.d = np.array([0.1, -0.2, 0.001, 0.002])
    assert conv.camera_model_from_msg(msg).distortion == ()
    msg.distortion_model, msg.d = "plumb_bob", np.zeros(5)
    assert conv.camera_model_from_msg(msg).distortion == ()


def test_depth_at_half_resolution_is_registered_by_scaling():
    from rtabmap_ros2.core.sensor import SensorFrame
    from rtabmap_ros2.io.bag import register_to_rgb

    rgb = np.zeros((480, 640, 3), np.uint8)
    depth = np.arange(240 * 320, dtype=np.float32).reshape(240, 320) / 1000 + 0.5
    half = CameraModel(262.5, 262.5, 159.75, 119.75, 320, 240)   # camera_info of the depth stream
    frame = register_to_rgb(SensorFrame(stamp_ns=1, rgb=rgb, depth_m=depth, camera=half))
    frame.validate()
    assert frame.depth_m.shape == (480, 640) and frame.depth_m[101, 201] == depth[50, 100]   # nearest
    assert (frame.camera.fx, frame.camera.cx, frame.camera.width) == (525.0, 319.5, 640)
    # Another aspect ratio is not a registered depth: rejected, naming both sizes.
    with pytest.raises(SensorDataError, match="200x240 and rgb 640x480: sizes differ"):
        register_to_rgb(SensorFrame(stamp_ns=1, rgb=rgb, depth_m=depth[:, :200].copy(), camera=half))


def test_mounts_from_parameters_without_tf2():
    from rtabmap_ros2.core.params import NodeParams
    from rtabmap_ros2.ros.frames import CAMERA, LASER, SensorMounts

    params = NodeParams(base_to_laser=(0.2, 0.0, 0.3, 0.0, 0.0, np.pi / 2))
    mounts = SensorMounts(None, params, tf2=None)
    assert mounts.source == "parameters" and "tf2_ros is not available" in mounts.describe()
    T = mounts.T_base(LASER, "laser", 0)
    np.testing.assert_allclose(T[:3, 3], [0.2, 0.0, 0.3])
    np.testing.assert_allclose(T[:3, :3] @ [1, 0, 0], [0, 1, 0], atol=1e-12)   # laser x = base y
    # The default camera mount is the optical frame at the base origin looking forward.
    np.testing.assert_allclose(mounts.T_base(CAMERA, "camera_optical", 0), conv.DEFAULT_T_BASE_CAMERA, atol=1e-12)


# -- reasons of rejected messages (the node logs once and counts per (topic, reason)) ---------------
def _reason(convert, msg) -> str:
    with pytest.raises(SensorDataError) as info:
        convert(msg)
    return info.value.reason


def test_rejections_name_their_reason(rgb):
    image = conv.image_to_msg(rgb, 0, "c")
    image.encoding = "yuv444"
    assert _reason(conv.image_from_msg, image) == "encoding"
    image = conv.image_to_msg(rgb, 0, "c")
    image.data = bytes(image.data)[:-1]
    assert _reason(conv.image_from_msg, image) == "short_data"
    image = conv.image_to_msg(rgb, 0, "c")
    image.step = 4
    assert _reason(conv.image_from_msg, image) == "bad_step"
    depth = conv.depth_to_msg(np.full(rgb.shape[:2], np.inf, np.float32), 0, "c", "32FC1")
    assert _reason(conv.depth_from_msg, depth) == "inf_depth"
    odom = Odometry()
    odom.pose.pose.orientation.w = 0.0
    assert _reason(conv.odometry_from_msg, odom) == "invalid_quaternion"
    odom.pose.pose.position.x = math.nan
    assert _reason(conv.odometry_from_msg, odom) == "non_finite_pose"
    camera = CameraModel(500.0, 500.0, 10.0, 10.0, 20, 20)
    info = conv.camera_info_to_msg(camera, 0, "c")
    info.k = np.zeros(9)
    assert _reason(conv.camera_model_from_msg, info) == "invalid_intrinsics"
    scan = conv.scan_to_msg(LaserScan(np.ones(10, np.float32), 0.0, 0.1, 0.1, 10.0), 0, "laser")
    scan.ranges = [math.nan] * 10
    assert _reason(conv.scan_from_msg, scan) == "no_valid_scan"


def test_frame_id_from_header():
    scan = conv.scan_to_msg(LaserScan(np.ones(10, np.float32), 0.0, 0.1, 0.1, 10.0), 0, "laser")
    assert conv.frame_id_from_header(scan) == "laser"
    scan.header.frame_id = " "
    assert _reason(conv.frame_id_from_header, scan) == "empty_frame_id"
