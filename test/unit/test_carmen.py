"""CARMEN log -> ROS 2 bag with drifting odometry, read back through BagDataset."""

from __future__ import annotations

import gzip
import math
import subprocess
import sys

import numpy as np
import pytest

from rtabmap_ros2.core import transforms
from rtabmap_ros2.core.params import SyncParams
from rtabmap_ros2.errors import DatasetError
from rtabmap_ros2.io.bag import BagDataset
from rtabmap_ros2.io.carmen import (angle_increment, carmen_to_bag, drifting_odometry, read_carmen_log)

INTEL_SCANS = 910


def small_log(path, n=5):
    lines = ["# comment", "PARAM robot_frontlaser_offset 0.1 nohost 0"]
    for i in range(n):
        ranges = " ".join(["2.5"] * 179 + ["81.83"])
        lines.append(f"FLASER 180 {ranges} {i * 0.5} 0.0 {i * 0.1} 0 0 0 {10 + i * 0.2:.6f} host {10 + i * 0.2:.6f}")
        lines.append(f"ODOM 0 0 0 0 0 0 {10 + i * 0.2} host {10 + i * 0.2}")
    with gzip.open(path, "wt") as f:
        f.write("\n".join(lines) + "\n")
    return path


def test_read_small_log_and_angles(tmp_path):
    log = read_carmen_log(small_log(tmp_path / "x.log.gz"))
    assert len(log.scans) == 5 and log.laser_offset_m == 0.1
    s = log.scans[2]
    assert (s.x, s.y, s.theta, s.stamp_ns) == (1.0, 0.0, pytest.approx(0.2), 10_400_000_000)
    assert len(s.ranges) == 180
    assert angle_increment(180) == pytest.approx(math.radians(1))
    assert angle_increment(361) == pytest.approx(math.radians(0.5))


def test_bad_logs(tmp_path):
    with pytest.raises(DatasetError, match="does not exist"):
        read_carmen_log(tmp_path / "none.log")
    (tmp_path / "empty.log").write_text("ODOM 0 0 0 0 0 0 1 h 1\n")
    with pytest.raises(DatasetError, match="no FLASER"):
        read_carmen_log(tmp_path / "empty.log")
    (tmp_path / "bad.log").write_text("FLASER 180 1 2 3\n")
    with pytest.raises(DatasetError, match="bad.log:1"):
        read_carmen_log(tmp_path / "bad.log")


def test_drift_is_seeded_and_grows(rng):
    ref = [transforms.from_xy_yaw(0.1 * i, 0.0, 0.0) for i in range(200)]   # 20 m straight
    a, covs = drifting_odometry(ref, np.random.default_rng(1))
    b, _ = drifting_odometry(ref, np.random.default_rng(1))
    c, _ = drifting_odometry(ref, np.random.default_rng(2))
    np.testing.assert_array_equal(a[-1], b[-1])
    assert not np.allclose(a[-1], c[-1])
    np.testing.assert_array_equal(a[0], ref[0])
    assert np.linalg.norm(a[-1][:2, 3] - ref[-1][:2, 3]) > 0.05
    assert covs[5][0, 0] == pytest.approx((0.02 * 0.1) ** 2)
    exact, _ = drifting_odometry(ref, rng, noise_trans=0.0, noise_rot_deg_per_m=0.0)
    np.testing.assert_allclose(exact[-1], ref[-1], atol=1e-9)


def test_small_log_round_trip(tmp_path):
    result = carmen_to_bag(small_log(tmp_path / "x.log.gz"), tmp_path / "bag", noise_trans=0, noise_rot_deg_per_m=0)
    frames = list(BagDataset(result.bag_path, sync=SyncParams(rate_hz=0)))
    assert len(frames) == 5
    f = frames[3]
    assert f.rgb is None and f.scan is not None
    assert transforms.to_xy_yaw(f.T_odom_base) == pytest.approx((1.5, 0.0, 0.3))
    assert not f.scan.valid_mask()[-1] and f.scan.valid_mask()[:-1].all()   # 81.83 = no return
    np.testing.assert_allclose(f.scan.T_base_laser[:3, 3], [0.1, 0, 0])


@pytest.mark.slow
def test_intel_converts_and_reads_back(tmp_path, shared_data):
    log = shared_data / "carmen" / "intel-corrected.log.gz"
    result = carmen_to_bag(log, tmp_path / "intel", seed=3)
    assert result.scans == INTEL_SCANS
    ds = BagDataset(result.bag_path, sync=SyncParams(rate_hz=0))
    assert ds.streams == ("odom", "scan")
    frames = list(ds)
    assert len(frames) == INTEL_SCANS
    gt = np.loadtxt(result.ground_truth_path)
    assert gt.shape == (INTEL_SCANS, 8)
    first = read_carmen_log(log).scans[0]
    assert gt[0, 1:3] == pytest.approx([first.x, first.y])
    assert [f.stamp_ns for f in frames] == [int(round(t * 1e9)) for t in gt[:, 0]]
    # The odometry starts on the reference and drifts away from it.
    np.testing.assert_allclose(frames[0].T_odom_base[:2, 3], gt[0, 1:3], atol=1e-6)
    assert np.linalg.norm(frames[-1].T_odom_base[:2, 3] - gt[-1, 1:3]) > 0.1


def test_cli_subcommand(tmp_path):
    log = small_log(tmp_path / "x.log.gz")
    out = subprocess.run([sys.executable, "-m", "rtabmap_ros2.cli.cli", "carmen2bag", str(log), "--out",
                          str(tmp_path / "b"), "--seed", "4", "--noise-trans", "0.05", "--noise-rot", "2"],
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert "5 scans" in out.stdout
    assert (tmp_path / "b" / "ground_truth.txt").is_file()
    again = subprocess.run([sys.executable, "-m", "rtabmap_ros2.cli.cli", "carmen2bag", str(log), "--out",
                            str(tmp_path / "b")], capture_output=True, text=True, timeout=120)
    assert again.returncode == 2 and "already exists" in again.stderr


def test_non_increasing_stamps_are_repaired(tmp_path):
    path = small_log(tmp_path / "x.log.gz", n=6)
    text = gzip.open(path, "rt").read().replace("10.800000", "10.500000")   # scan 4 goes back in time
    with gzip.open(path, "wt") as f:
        f.write(text)
    stamps = [s.stamp_ns for s in read_carmen_log(path).scans]
    assert all(b > a for a, b in zip(stamps, stamps[1:]))
    assert stamps[4] == stamps[3] + 1_000_000
    same = tmp_path / "same.log"
    same.write_text("".join(f"FLASER 3 1 1 1 {i} 0 0 0 0 0 1.13486e+09 h 1.13486e+09\n" for i in range(4)))
    stamps = [s.stamp_ns for s in read_carmen_log(same).scans]
    assert np.diff(stamps).tolist() == [1_000_000_000] * 3
