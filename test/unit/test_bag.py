"""Bag I/O: round trips through ROS 2 (sqlite3, mcap) and ROS 1 bags, conversions, bad input."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from rtabmap_ros2.core import transforms
from rtabmap_ros2.core.params import SyncParams
from rtabmap_ros2.core.sensor import CameraModel, Dataset, LaserScan, SensorFrame
from rtabmap_ros2.errors import BagError, SensorDataError
from rtabmap_ros2.io import bag
from rtabmap_ros2.io.bag import BagDataset, TopicNames, write_bag, write_ros1_bag

ALL = SyncParams(rate_hz=0)
W, H = 64, 48
DEPTH_TOL_M = 0.0005 + 1e-6   # 16UC1 millimetres: half a millimetre of rounding


def smooth_rgb(i: int) -> np.ndarray:
    yy, xx = np.mgrid[0:H, 0:W]
    return np.stack([xx * 3 + i, yy * 4, (xx + yy) * 2], -1).astype(np.uint8)


@pytest.fixture
def frames(rng):
    T_base_camera = bag.DEFAULT_T_BASE_CAMERA.copy()
    T_base_camera[:3, 3] = [0.1, 0.0, 0.4]
    T_base_laser = transforms.from_xy_yaw(0.2, 0.0, 0.0, z=0.3)
    out = []
    for i in range(6):
        depth = rng.uniform(0.4, 6.0, (H, W)).astype(np.float32)
        depth[0, :5] = np.nan
        out.append(SensorFrame(
            stamp_ns=1_700_000_000_000_000_000 + i * 100_000_000,
            T_odom_base=transforms.from_xyz_quat_xyzw(rng.uniform(-3, 3, 3), rng.normal(size=4)),
            odom_covariance=np.diag(rng.uniform(0.01, 0.1, 6)),
            rgb=rng.integers(0, 256, (H, W, 3), dtype=np.uint8),
            depth_m=depth,
            camera=CameraModel(52.0, 53.0, 31.5, 23.5, W, H, T_base_camera),
            scan=LaserScan(rng.uniform(0.5, 9.0, 180).astype(np.float32), -np.pi / 2, np.pi / 180, 0.1, 30.0,
                           T_base_laser)))
    return out


def assert_same_frames(expected, got, rgb_exact=True):
    assert len(got) == len(expected)
    for a, b in zip(expected, got):
        assert a.stamp_ns == b.stamp_ns
        np.testing.assert_allclose(b.T_odom_base, a.T_odom_base, atol=1e-9)
        np.testing.assert_allclose(b.odom_covariance, a.odom_covariance)
        if rgb_exact:
            np.testing.assert_array_equal(b.rgb, a.rgb)
        np.testing.assert_allclose(b.depth_m, a.depth_m, atol=DEPTH_TOL_M, equal_nan=True)
        np.testing.assert_allclose(b.scan.ranges, a.scan.ranges)
        assert (b.scan.angle_min, b.scan.angle_increment) == pytest.approx((a.scan.angle_min, a.scan.angle_increment))
        np.testing.assert_allclose(b.scan.T_base_laser, a.scan.T_base_laser, atol=1e-9)
        cam_a, cam_b = a.camera, b.camera
        assert (cam_b.fx, cam_b.fy, cam_b.cx, cam_b.cy, cam_b.width, cam_b.height) == \
            (cam_a.fx, cam_a.fy, cam_a.cx, cam_a.cy, cam_a.width, cam_a.height)
        np.testing.assert_allclose(cam_b.T_base_camera, cam_a.T_base_camera, atol=1e-9)


@pytest.mark.parametrize("storage", ["sqlite3", "mcap"])
def test_round_trip_ros2(tmp_path, frames, storage):
    path = write_bag(tmp_path / "bag", frames, storage=storage)
    ds = BagDataset(path, sync=ALL)
    assert isinstance(ds, Dataset)
    assert ds.streams == ("odom", "scan", "rgb", "depth", "camera_info")
    assert len(ds) == len(frames)
    assert_same_frames(frames, list(ds))


def test_round_trip_ros1_with_compressed_images(tmp_path, frames):
    for f in frames:
        f.rgb = smooth_rgb(int(f.stamp_ns % 7))
    path = write_ros1_bag(tmp_path / "in.bag", frames, rgb_format="jpeg", depth_format="png")
    ds = BagDataset(path, sync=ALL)
    assert ds.stream_topics["rgb"] == "/rgb/image/compressed"
    assert ds.stream_topics["depth"] == "/depth/image/compressedDepth"
    got = list(ds)
    assert_same_frames(frames, got, rgb_exact=False)
    for a, b in zip(frames, got):
        assert np.abs(a.rgb.astype(int) - b.rgb).mean() < 3


def test_storage_file_path_and_custom_topics(tmp_path, frames):
    topics = TopicNames(odom="/robot/odom", scan="/robot/scan", rgb="/cam/color", depth="/cam/depth",
                        camera_info="/cam/info")
    path = write_bag(tmp_path / "bag", frames, topics=topics, storage="mcap")
    mcap_file = next(path.glob("*.mcap"))
    ds = BagDataset(mcap_file, topics=topics, sync=ALL, use=["odom", "scan"])
    got = list(ds)
    assert len(got) == len(frames) and all(f.rgb is None and f.scan is not None for f in got)


def test_rate_limit_on_bag(tmp_path, frames):
    path = write_bag(tmp_path / "bag", frames)
    assert len(BagDataset(path, sync=SyncParams(rate_hz=2.0))) == 2  # 0.6 s of 10 Hz data at 2 Hz


def test_explicit_transforms_override_tf_static(tmp_path, frames):
    path = write_bag(tmp_path / "bag", frames)
    T = transforms.from_xy_yaw(1.0, 2.0, 0.5)
    f = next(iter(BagDataset(path, sync=ALL, T_base_laser=T, T_base_camera=bag.DEFAULT_T_BASE_CAMERA)))
    np.testing.assert_allclose(f.scan.T_base_laser, T)
    np.testing.assert_allclose(f.camera.T_base_camera, bag.DEFAULT_T_BASE_CAMERA)


def test_missing_topic_is_an_error_naming_it(tmp_path, frames):
    for f in frames:
        f.scan = None
    path = write_bag(tmp_path / "bag", frames)
    with pytest.raises(BagError, match=r"/scan.*/rgb/image \(sensor_msgs/msg/Image\)"):
        BagDataset(path, use=["odom", "scan"])
    assert "scan" not in BagDataset(path).streams   # default: the streams present


def test_missing_and_bad_paths(tmp_path, frames):
    with pytest.raises(BagError, match="does not exist"):
        BagDataset(tmp_path / "nope")
    (tmp_path / "empty").mkdir()
    with pytest.raises(BagError, match="metadata.yaml"):
        BagDataset(tmp_path / "empty")
    junk = tmp_path / "junk.bag"
    junk.write_bytes(b"not a bag at all")
    with pytest.raises(BagError, match="junk.bag"):
        BagDataset(junk)


def test_truncated_ros1_bag(tmp_path, frames):
    path = write_ros1_bag(tmp_path / "full.bag", frames)
    data = path.read_bytes()
    cut = tmp_path / "cut.bag"
    cut.write_bytes(data[: len(data) // 2])
    with pytest.raises(BagError, match="cut.bag"):
        list(BagDataset(cut, sync=ALL))


def test_truncated_ros2_bag(tmp_path, frames):
    path = write_bag(tmp_path / "bag", frames)
    db = next(path.glob("*.db3"))
    data = db.read_bytes()
    db.write_bytes(data[: len(data) // 3])
    with pytest.raises(BagError, match="bag"):
        list(BagDataset(path, sync=ALL))


def test_unknown_encoding_skips_only_that_frame(tmp_path, frames, caplog):
    path = tmp_path / "bag"
    from rosbags.rosbag2 import Writer
    ts = bag.typestore()
    with Writer(path, version=9) as w:
        conn_rgb = w.add_connection("/rgb/image", bag.IMAGE_TYPE, typestore=ts)
        conn_odom = w.add_connection("/odom", bag.ODOM_TYPE, typestore=ts)
        for i, f in enumerate(frames):
            msg = bag.image_to_msg(f.rgb, f.stamp_ns)
            if i == 2:
                msg.encoding = "yuv422_weird"
            w.write(conn_rgb, f.stamp_ns, ts.serialize_cdr(msg, bag.IMAGE_TYPE))
            odom = bag.odometry_to_msg(f.T_odom_base, f.odom_covariance, f.stamp_ns)
            w.write(conn_odom, f.stamp_ns, ts.serialize_cdr(odom, bag.ODOM_TYPE))
    with caplog.at_level(logging.WARNING, logger="rtabmap_ros2.io.bag"):
        got = list(BagDataset(path, sync=ALL))
    assert len(got) == len(frames) - 1
    assert frames[2].stamp_ns not in [f.stamp_ns for f in got]
    assert "yuv422_weird" in caplog.text and "/rgb/image" in caplog.text


# Conversions on messages built in memory --------------------------------------------------

def test_image_encodings_and_step():
    rgb = smooth_rgb(0)
    msg = bag.image_to_msg(rgb, 1)
    np.testing.assert_array_equal(bag.image_from_msg(msg), rgb)
    bgr = np.ascontiguousarray(rgb[..., ::-1])
    padded = np.zeros((H, W * 3 + 8), np.uint8)   # rows padded: step > width * 3
    padded[:, : W * 3] = bgr.reshape(H, -1)
    msg.encoding, msg.step, msg.data = "bgr8", W * 3 + 8, padded.reshape(-1)
    np.testing.assert_array_equal(bag.image_from_msg(msg), rgb)
    gray = rgb[..., 1].copy()
    msg.encoding, msg.step, msg.data = "mono8", W, gray.reshape(-1)
    np.testing.assert_array_equal(bag.image_from_msg(msg), np.stack([gray] * 3, -1))
    msg.encoding = "yuv444"
    with pytest.raises(SensorDataError, match="yuv444"):
        bag.image_from_msg(msg)


def test_depth_16uc1_and_32fc1():
    depth = np.full((H, W), 1.2344, np.float32)
    depth[3, 4] = np.nan
    depth[5, 6] = 0.0
    msg = bag.depth_to_msg(depth, 1)
    assert msg.encoding == "16UC1"
    back = bag.depth_from_msg(msg)
    assert np.isnan(back[3, 4]) and np.isnan(back[5, 6])
    assert back[0, 0] == pytest.approx(1.234, abs=1e-6)   # millimetres
    msg.encoding, msg.step = "32FC1", W * 4
    msg.data = depth.reshape(-1).view(np.uint8)
    back = bag.depth_from_msg(msg)
    assert back.dtype == np.float32 and back[0, 0] == np.float32(1.2344)
    assert np.isnan(back[3, 4]) and np.isnan(back[5, 6])
    big_endian = depth.astype(">f4")
    msg.is_bigendian, msg.data = 1, big_endian.reshape(-1).view(np.uint8)
    assert bag.depth_from_msg(msg)[0, 0] == np.float32(1.2344)


def test_compressed_depth_png_and_32fc1_inverse_depth():
    depth = np.linspace(0.5, 5.0, H * W, dtype=np.float32).reshape(H, W)
    depth[0, 0] = np.nan
    back = bag.compressed_depth_from_msg(bag.compressed_depth_to_msg(depth, 1))
    np.testing.assert_allclose(back, depth, atol=DEPTH_TOL_M, equal_nan=True)
    # 32FC1 compressedDepth: quantised inverse depth, depth = A / (q - B).
    import cv2
    quant_a, quant_b = 100.0, 10.0
    q = np.where(np.isnan(depth), 0, np.rint(quant_a / depth + quant_b)).astype(np.uint16)
    png = cv2.imencode(".png", q)[1].tobytes()
    msg = bag.compressed_depth_to_msg(depth, 1)
    msg.format = "32FC1; compressedDepth png"
    msg.data = np.frombuffer(bag.COMPRESSED_DEPTH_HEADER.pack(0, quant_a, quant_b) + png, np.uint8)
    back = bag.compressed_depth_from_msg(msg)
    np.testing.assert_allclose(back, depth, rtol=0.03, equal_nan=True)
    # Inverse depth is not the database's millimetres: its PNG is not kept for storing as it came.
    assert bag.compressed_depth_and_png(msg)[1] is None


def test_corrupt_compressed_images_name_the_problem():
    """Bytes that do not decode give a clear decode error (the node and the bag reader drop the frame),
    with or without the stored bytes asked for."""
    rgb_msg = bag.compressed_image_to_msg(smooth_rgb(0), 1)
    rgb_msg.data = np.frombuffer(bag.JPEG_MAGIC + b"not a picture", np.uint8)
    for decode in (bag.compressed_image_from_msg, bag.compressed_image_and_jpeg):
        with pytest.raises(SensorDataError, match="could not decode the compressed image") as err:
            decode(rgb_msg)
        assert err.value.reason == "decode"
    depth_msg = bag.compressed_depth_to_msg(np.ones((H, W), np.float32), 1)
    depth_msg.data = np.frombuffer(b"neither a header nor a PNG", np.uint8)
    for decode in (bag.compressed_depth_from_msg, bag.compressed_depth_and_png):
        with pytest.raises(SensorDataError, match="holds no PNG"):
            decode(depth_msg)


def test_odometry_scan_camera_transform_pairs(random_se3):
    T = random_se3()
    cov = np.arange(36, dtype=float).reshape(6, 6)
    T2, cov2 = bag.odometry_from_msg(bag.odometry_to_msg(T, cov, 5))
    np.testing.assert_allclose(T2, T, atol=1e-12)
    np.testing.assert_array_equal(cov2, cov)
    cam = CameraModel(525, 526, 319.5, 239.5, 640, 480, T)
    cam2 = bag.camera_info_from_msg(bag.camera_info_to_msg(cam, 5), T)
    assert (cam2.fx, cam2.fy, cam2.cx, cam2.cy, cam2.width, cam2.height) == (525, 526, 319.5, 239.5, 640, 480)
    parent, child, T3 = bag.transform_from_msg(bag.transform_to_msg(T, "base_link", "laser", 5))
    assert (parent, child) == ("base_link", "laser")
    np.testing.assert_allclose(T3, T, atol=1e-12)
    assert bag.stamp_from_msg(bag.stamp_to_msg(1_700_000_000_123_456_789)) == 1_700_000_000_123_456_789
    scan = LaserScan(np.array([1.0, np.nan, 3.0], np.float32), -0.1, 0.1, 0.05, 10.0)
    scan2 = bag.scan_from_msg(bag.scan_to_msg(scan, 5))
    np.testing.assert_array_equal(scan2.ranges, scan.ranges)


def test_write_refuses_existing_path(tmp_path, frames):
    path = write_bag(tmp_path / "bag", frames[:1])
    with pytest.raises(BagError, match="already exists"):
        write_bag(path, frames[:1])
    with pytest.raises(BagError, match="storage"):
        write_bag(tmp_path / "b2", frames, storage="zip")


def test_frames_without_valid_depth_or_scan_are_skipped(tmp_path, frames, caplog):
    """Checked where frames are made (issue 15): the bag reader drops them as the node does."""
    from dataclasses import replace

    bad = list(frames)
    bad[1] = replace(frames[1], depth_m=np.full_like(frames[1].depth_m, np.nan))
    bad[2] = replace(frames[2], depth_m=np.zeros_like(frames[2].depth_m))
    few = np.full_like(frames[3].scan.ranges, np.inf)
    few[0] = 2.0   # 1 return of 180 beams: below sync.min_valid_scan_ratio (1 %)
    bad[3] = replace(frames[3], scan=replace(frames[3].scan, ranges=few))
    path = write_bag(tmp_path / "bag", bad)
    with caplog.at_level(logging.WARNING, logger="rtabmap_ros2.io.bag"):
        got = list(BagDataset(path, sync=ALL))
    assert [f.stamp_ns for f in got] == [frames[i].stamp_ns for i in (0, 4, 5)]
    assert "0 valid pixels of" in caplog.text and "1 valid returns of 180" in caplog.text
    lenient = SyncParams(rate_hz=0.0, min_valid_scan_ratio=0.0)
    assert len(list(BagDataset(path, sync=lenient))) == 4   # the one-return scan passes at ratio 0


def test_compressed_images_are_stored_as_they_came(tmp_path, frames):
    """A JPEG CompressedImage and a 16UC1 compressedDepth reach the database as their own bytes (no
    second JPEG generation, no PNG encoded again); raw images and a depth scaled to the RGB size are
    encoded; each stored image decodes to the frame that was processed."""
    from rtabmap_ros2.core.database import decode_depth, decode_rgb
    from rtabmap_ros2.core.params import Params
    from rtabmap_ros2.core.rtabmap import Rtabmap

    for f in frames:
        f.rgb = smooth_rgb(int(f.stamp_ns % 7))
    compressed = list(BagDataset(write_bag(tmp_path / "compressed", frames, rgb_format="jpeg", depth_format="png"),
                                 sync=ALL))
    raw = list(BagDataset(write_bag(tmp_path / "raw", frames), sync=ALL))
    assert all(f.rgb_jpeg is None and f.depth_png16_mm is None for f in raw)
    for f in compressed:
        np.testing.assert_array_equal(decode_rgb(f.rgb_jpeg), f.rgb)
        np.testing.assert_array_equal(decode_depth(f.depth_png16_mm), f.depth_m)
    with Rtabmap(Params(), tmp_path / "map.db") as rtabmap:
        stored = [(f, rtabmap.process(f).location_id) for f in compressed + raw]
        rtabmap.memory.join()
        for f, node in stored:
            blobs = rtabmap.db.load_sensor_blobs(node)
            if f.rgb_jpeg is not None:
                assert blobs.rgb_jpeg == f.rgb_jpeg and blobs.depth_png16_mm == f.depth_png16_mm
            np.testing.assert_array_equal(blobs.depth_m(), f.depth_m)
            assert np.abs(blobs.rgb().astype(int) - f.rgb).mean() < 3
    half = SensorFrame(stamp_ns=0, rgb=np.zeros((H, W, 3), np.uint8), depth_m=np.ones((H // 2, W // 2), np.float32),
                       depth_png16_mm=b"the input's PNG, at half size")
    assert bag.register_to_rgb(half).depth_png16_mm is None and half.depth_m.shape == (H, W)
