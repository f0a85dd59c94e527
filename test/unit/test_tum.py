"""TUM RGB-D folders -> ROS 2 bags (io/tum.py, ``tum2bag``; issue 49) on real fr1_rpy frames."""

from __future__ import annotations

import logging
import math

import cv2
import numpy as np
import pytest

from rtabmap_ros2.core import transforms
from rtabmap_ros2.core.params import SyncParams
from rtabmap_ros2.errors import DatasetError
from rtabmap_ros2.io.bag import DEFAULT_T_BASE_CAMERA, BagDataset
from rtabmap_ros2.io.trajectory import read_tum
from rtabmap_ros2.io.tum import (CAMERAS, camera_for_folder, camera_from_text, drifting_odometry, interpolate_pose,
                                 tum_frames, tum_to_bag)

NS = 1_000_000_000
EVERY_FRAME = SyncParams(rate_hz=0.0)


def test_calibration_by_name_numbers_or_folder(tmp_path):
    assert camera_from_text("fr2") is CAMERAS["fr2"] and CAMERAS["fr1"].fx == pytest.approx(517.306408)
    plain = camera_from_text("500,501,320,240")
    assert (plain.fx, plain.fy, plain.cx, plain.cy, plain.distortion) == (500, 501, 320, 240, (0.0,) * 5)
    assert camera_from_text("500 501 320 240 0.1 -0.2 0 0 0.05").distortion == (0.1, -0.2, 0.0, 0.0, 0.05)
    for bad in ("fr4", "500,501,320", "0,500,320,240", "a,b,c,d"):
        with pytest.raises(DatasetError, match="--camera"):
            camera_from_text(bad)
    assert camera_for_folder(tmp_path / "rgbd_dataset_freiburg3_long_office_household")[0] == "fr3"
    assert camera_for_folder(tmp_path / "tum_fr2_desk")[0] == "fr2"
    with pytest.raises(DatasetError, match="--camera"):
        camera_for_folder(tmp_path / "my_recording")


def test_ground_truth_is_interpolated_between_close_samples_only():
    a, b = transforms.from_xy_yaw(0.0, 0.0, 0.0), transforms.from_xyz_rpy([1.0, 2.0, 0.4, 0.0, 0.0, 0.2])
    stamps, poses = np.array([10 * NS, 10 * NS + 50_000_000]), np.stack([a, b])
    mid = interpolate_pose(stamps, poses, 10 * NS + 25_000_000, 0.1)
    np.testing.assert_allclose(mid[:3, 3], [0.5, 1.0, 0.2])
    assert transforms.yaw_of(mid) == pytest.approx(0.1)
    np.testing.assert_array_equal(interpolate_pose(stamps, poses, 10 * NS, 0.1), a)
    assert interpolate_pose(stamps, poses, 9 * NS, 0.1) is None           # before the first sample
    assert interpolate_pose(stamps, poses, 10 * NS + 25_000_000, 0.01) is None   # samples too far apart


def test_drift_grows_at_the_given_rates_and_is_seeded():
    """Heading error = rate x elapsed time, about the vertical; position error from both."""
    stamps = [k * NS // 10 for k in range(101)]   # 10 s at 10 Hz
    truth = [transforms.from_xyz_rpy([0.01 * k, 0.0, 1.5, 0.3, -0.2, 0.01 * k]) for k in range(101)]   # 1 m
    same, cov = drifting_odometry(stamps, truth, 0.0, 0.0, np.random.default_rng(0))
    assert cov is None and all(np.allclose(o, t) for o, t in zip(same, truth))
    odom, cov = drifting_odometry(stamps, truth, 0.5, 0.01, np.random.default_rng(3))
    np.testing.assert_allclose(odom[0], truth[0])
    R_err = odom[-1][:3, :3] @ truth[-1][:3, :3].T
    assert abs(math.degrees(math.atan2(R_err[1, 0], R_err[0, 0]))) == pytest.approx(5.0)   # 0.5 deg/s x 10 s
    assert R_err[2, 2] == pytest.approx(1.0)   # about the vertical only: roll and pitch kept
    assert odom[-1][2, 3] == pytest.approx(truth[-1][2, 3])
    assert 0.05 < np.linalg.norm(odom[-1][:3, 3] - truth[-1][:3, 3]) < 0.15   # 0.1 m drift + 1 m walked 2.5 deg off
    # The covariance in the body's axes: 1 cm over 1 s on each axis; the heading drift (0.5 deg over
    # 1 s about the vertical) shared by roll, pitch and yaw as the tilted body sees the vertical.
    var_heading = math.radians(0.5) ** 2
    for T, C in ((odom[0], cov[0]), (odom[-1], cov[-1])):
        assert np.allclose(np.diag(C)[:3], 1e-4) and np.count_nonzero(C - np.diag(np.diag(C))) == 0
        np.testing.assert_allclose(np.diag(C)[3:], np.maximum(var_heading * T[2, :3] ** 2, 1e-6))
    assert np.diag(cov[0])[3] > 1e-6 and np.diag(cov[0])[4] > 1e-6   # rolled 0.3 and pitched -0.2 rad
    level, level_cov = drifting_odometry(stamps[:2], [transforms.from_xy_yaw(0.0, 0.0, 0.4)] * 2, 0.5, 0.01,
                                         np.random.default_rng(0))
    assert np.diag(level_cov[1])[5] == pytest.approx(var_heading) and np.diag(level_cov[1])[3] == 1e-6
    again, _ = drifting_odometry(stamps, truth, 0.5, 0.01, np.random.default_rng(3))
    np.testing.assert_array_equal(again[-1], odom[-1])


def test_bag_round_trip_on_real_frames(tum_rpy_folder, tmp_path, caplog):
    """Depth in metres as TUM's 5000 per metre says (mm, or exact metres with 32FC1), the fr1
    calibration with its distortion, odometry = ground truth without drift, the truth file."""
    folder = tum_rpy_folder(4)
    result = tum_to_bag(folder, tmp_path / "bag")
    assert result.frames == 4 and result.camera is CAMERAS["fr1"] and not result.left_out
    with caplog.at_level(logging.WARNING):
        dataset = BagDataset(result.bag_path, sync=EVERY_FRAME)
        frames = list(dataset)
    assert len(frames) == 4 and dataset.mounts["camera"].kind == "tf_static"
    assert any("not rectified" in r.message for r in caplog.records)   # D in camera_info, P = K
    first = sorted((folder / "depth").iterdir())[0]
    raw = cv2.imread(str(first), cv2.IMREAD_UNCHANGED)
    valid = raw > 0
    np.testing.assert_allclose(frames[0].depth_m[valid], raw[valid] / 5000.0, atol=0.0005 + 1e-6)
    assert np.isnan(frames[0].depth_m[~valid]).all()
    assert frames[0].camera.fx == pytest.approx(517.306408) and frames[0].camera.height == 480
    assert frames[0].camera.distortion == pytest.approx(CAMERAS["fr1"].distortion)   # keypoints undistorted with D
    np.testing.assert_allclose(frames[0].camera.T_base_camera, DEFAULT_T_BASE_CAMERA)
    truth = read_tum(result.ground_truth_path)
    assert list(truth.stamps_ns) == [f.stamp_ns for f in frames]
    for frame, T in zip(frames, truth.poses):
        np.testing.assert_allclose(frame.T_odom_base, T, atol=1e-6)
    # The base (camera body) times the optical mount is the listed optical-frame pose.
    stamp, pose = (folder / "groundtruth.txt").read_text().splitlines()[1].split(maxsplit=1)
    values = [float(v) for v in pose.split()]
    np.testing.assert_allclose(truth.poses[0] @ DEFAULT_T_BASE_CAMERA,
                               transforms.from_xyz_quat_xyzw(values[:3], values[3:]), atol=1e-6)
    metres = tum_to_bag(folder, tmp_path / "bag32", depth_encoding="32FC1")
    exact = next(iter(BagDataset(metres.bag_path, sync=EVERY_FRAME)))
    np.testing.assert_array_equal(exact.depth_m[valid], (raw[valid] / np.float32(5000)).astype(np.float32))
    rectified = tum_to_bag(folder, tmp_path / "rectified", rectify=True)
    caplog.clear()
    with caplog.at_level(logging.WARNING):
        undistorted = next(iter(BagDataset(rectified.bag_path, sync=EVERY_FRAME)))
    assert not any("not rectified" in r.message for r in caplog.records)   # D = 0 written
    assert undistorted.camera.distortion == ()
    assert np.isfinite(undistorted.depth_m).mean() > 0.5 and not np.array_equal(undistorted.rgb, frames[0].rgb)


def test_bad_folders_are_clear_errors(tum_rpy_folder, tmp_path):
    folder = tum_rpy_folder(2)
    lines = (folder / "rgb.txt").read_text().splitlines()
    (folder / "rgb.txt").write_text("\n".join(lines[:2] + [lines[2] + " extra"]) + "\n")
    with pytest.raises(DatasetError, match=r"rgb.txt:3: expected 'stamp path'"):
        tum_frames(folder)
    (folder / "rgb.txt").write_text("\n".join(lines[:2] + ["12x.5 rgb/a.png"]) + "\n")
    with pytest.raises(DatasetError, match=r"rgb.txt:3: stamp '12x.5' is not a number"):
        tum_frames(folder)
    (folder / "rgb.txt").write_text("\n".join(lines) + "\n")
    image = sorted((folder / "rgb").iterdir())[1]
    image.rename(image.with_suffix(".bak"))
    with pytest.raises(DatasetError, match=r"rgb.txt:3: image .* is missing"):
        tum_frames(folder)
    image.with_suffix(".bak").rename(image)
    truth = (folder / "groundtruth.txt").read_text().splitlines()
    (folder / "groundtruth.txt").write_text("\n".join(truth[:2] + [truth[2].rsplit(" ", 4)[0] + " 0 0 0 0"]) + "\n")
    with pytest.raises(DatasetError, match=r"groundtruth.txt:3: not a pose"):
        tum_frames(folder)
    (folder / "groundtruth.txt").unlink()
    with pytest.raises(DatasetError, match="groundtruth.txt is missing"):
        tum_frames(folder)


def test_a_depth_image_of_the_wrong_size_or_kind_is_named(tum_rpy_folder, tmp_path):
    folder = tum_rpy_folder(2)
    depth = sorted((folder / "depth").iterdir())[1]
    raw = cv2.imread(str(depth), cv2.IMREAD_UNCHANGED)
    cv2.imwrite(str(depth), cv2.resize(raw, (320, 240), interpolation=cv2.INTER_NEAREST))
    with pytest.raises(DatasetError, match=r"is 320x240, its colour image 640x480"):
        tum_to_bag(folder, tmp_path / "bag")
    cv2.imwrite(str(depth), (raw // 256).astype(np.uint8))
    with pytest.raises(DatasetError, match="16-bit single channel"):
        tum_to_bag(folder, tmp_path / "bag2")
    with pytest.raises(DatasetError, match="drift"):
        tum_to_bag(folder, tmp_path / "bag3", drift_m_s=-1.0)
