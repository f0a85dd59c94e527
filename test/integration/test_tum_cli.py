"""A camera-only, hand-held user end to end (issue 49): ``tum2bag`` on a TUM RGB-D folder of 48 real
fr1_rpy frames, ``map`` with the documented options only, ``export`` with none: 6 DoF throughout,
a grid from the depth images, every pose written, and the run saying what it did."""

from __future__ import annotations

import csv
import json
import subprocess
import sys

import cv2
import numpy as np
import pytest

from cli_result import error_line
from rtabmap_ros2.core.database import Database
from rtabmap_ros2.io.trajectory import read_tum

CLI = [sys.executable, "-m", "rtabmap_ros2.cli.cli"]


def run(*args) -> subprocess.CompletedProcess:
    return subprocess.run([*CLI, *map(str, args)], capture_output=True, text=True, timeout=600)


@pytest.mark.slow
def test_hand_held_camera_from_tum_folder_to_exported_6dof_map(tum_rpy_folder, tmp_path):
    folder = tum_rpy_folder()
    bag = tmp_path / "fr1_rpy"
    converted = run("tum2bag", folder, "--out", bag, "--drift-yaw-deg-s", "0.5", "--drift-m-s", "0.01")
    assert converted.returncode == 0, converted.stderr
    assert converted.stdout.startswith("48 frames") and "fr1, from the folder name" in converted.stdout
    assert "Reg/Force3DoF=false" in converted.stdout   # the next command, as the README gives it

    db, stats = tmp_path / "map.db", tmp_path / "stats.csv"
    mapped = run("map", bag, "--db", db, "--no-progress", "--stats", stats, "--set", "Reg/Force3DoF=false")
    assert mapped.returncode == 0, mapped.stderr
    out = mapped.stdout
    assert out.startswith("mode: 6 DoF") and "occupancy grid: each node's laser scan, else its depth image" in out
    assert "fr1_rpy: reading /odom (odom), /rgb/image (rgb), /depth/image (depth), /rgb/camera_info" in out
    assert "not in the bag: /scan" in out
    assert "camera mount from /tf_static (base_link -> camera_optical)" in out
    # 48 frames over 24 s: the 1 Hz default keeps about one a second and says how many it skipped.
    line = next(l for l in out.splitlines() if "synchronised frames" in l)
    synchronised, processed, skipped = (int(line.split(w)[0].split()[-1])
                                        for w in (" synchronised", " processed", " skipped by the detection rate"))
    assert synchronised == 48 and processed + skipped == 48 and 15 <= processed <= 30
    assert "leaves the plane" not in mapped.stderr          # 6 DoF: nothing to warn about
    assert "not rectified" in mapped.stderr                 # the images are used as recorded, and it says so
    with Database(db, read_only=True) as database:          # and export back-projects depth with their lens
        first = database.load_signature(min(database.load_nodes()))
    assert first.camera.distortion == pytest.approx((0.2624, -0.9531, -0.0054, 0.0026, 1.1633), abs=1e-3)
    with open(stats, newline="") as f:
        rows = list(csv.DictReader(f))
    listed = {line.split()[0] for line in (folder / "rgb.txt").read_text().splitlines()[1:]}
    assert len(rows) == processed and all(r["stamp"][:-3] in listed and r["stamp"].endswith("000") for r in rows)

    exported = run("export", db, "--out", tmp_path / "export")
    assert exported.returncode == 0, exported.stderr
    assert "parameters: those stored with the database" in exported.stdout
    assert "6 DoF (registration.planar false)" in exported.stdout and "from depth images of" in exported.stdout
    summary = json.loads((tmp_path / "export" / "summary.json").read_text())
    assert summary["planar"] is False and summary["grid"]["depth_nodes"] == summary["nodes"] == processed
    pgm = cv2.imread(str(tmp_path / "export" / "map.pgm"), cv2.IMREAD_UNCHANGED)
    assert pgm.shape[0] > 20 and pgm.shape[1] > 20 and (pgm == 0).any() and (pgm == 254).any()
    poses = read_tum(tmp_path / "export" / "poses.txt")
    truth = read_tum(bag / "ground_truth.txt")
    assert len(poses.stamps_ns) == processed and set(poses.stamps_ns) <= set(truth.stamps_ns)
    # Heights kept (6 DoF): the hand-held camera's 1.4-1.6 m above the floor, not flattened to 0.
    assert np.ptp(poses.positions[:, 2]) > 0.02 and np.abs(poses.positions[:, 2]).max() > 1.0


@pytest.mark.slow
@pytest.mark.parametrize("drift_seed, rate_hz, nodes, proximity", [(0, 0, 48, False), (2, 2, 40, False),
                                                                  (1, 0, 48, True)])
def test_real_hand_held_frames_loop_closures_kept_near_the_truth(tum_rpy_folder, tmp_path, drift_seed, rate_hz,
                                                                 nodes, proximity):
    """Issue 49's recording yardstick on the 48 real fr1_rpy frames (revisits 3-19 s apart, the camera
    turning up to 117 deg/s) with drifting odometry, every frame a node and at 2 Hz: at least 5 loop
    closures kept, none off the motion capture by more than 5 cm or 3 deg, the map's ATE at most half
    the odometry's. Drift seed 2 at 2 Hz kept 4 while tum2bag's covariance put the heading drift on the
    body's yaw alone (this camera looks down at a desk: most of the drift is roll there). With proximity
    detection (RGBD/ProximityBySpace) the frames near earlier ones are registered with them too: more
    loop closures kept (14 against 9 measured), as near the truth."""
    from rtabmap_ros2.core import transforms
    from rtabmap_ros2.core.global_map import load_global_map
    from rtabmap_ros2.core.params import Params, default_config_path
    from rtabmap_ros2.io.trajectory import Trajectory, ate

    bag, db = tmp_path / "fr1_rpy", tmp_path / "map.db"
    converted = run("tum2bag", tum_rpy_folder(), "--out", bag, "--drift-yaw-deg-s", "0.5", "--drift-m-s", "0.01",
                    "--seed", str(drift_seed))
    assert converted.returncode == 0, converted.stderr
    mapped = run("map", bag, "--db", db, "--no-progress", "--set", "Reg/Force3DoF=false",
                 "--set", f"Rtabmap/DetectionRate={rate_hz}", "--set", f"RGBD/ProximityBySpace={proximity}")
    assert mapped.returncode == 0, mapped.stderr
    assert ("by proximity" in mapped.stdout) == proximity
    gmap = load_global_map(db, Params.from_yaml(default_config_path()).with_overrides(["registration.planar=false"]))
    truth = read_tum(bag / "ground_truth.txt")
    at = dict(zip(truth.stamps_ns.tolist(), truth.poses))
    loops = [link for link in gmap.links if link.type.is_loop_closure]
    assert len(gmap.poses) == nodes and len(loops) >= (12 if proximity else 5)
    for link in loops:
        E = link.residual(at[gmap.stamps_ns[link.from_id]], at[gmap.stamps_ns[link.to_id]])
        assert np.linalg.norm(E[:3, 3]) <= 0.05 and np.degrees(transforms.rotation_angle(E)) <= 3.0, \
            (link.from_id, link.to_id)

    def ate_of(poses):
        ids = sorted(poses)
        return ate(Trajectory(np.array([gmap.stamps_ns[i] for i in ids]), np.stack([poses[i] for i in ids])),
                   truth).rmse_m

    assert ate_of(gmap.poses) <= 0.5 * ate_of(gmap.odom_poses)

def test_tum2bag_names_what_is_missing(tmp_path):
    (tmp_path / "rgbd_dataset_freiburg1_empty").mkdir()
    line = error_line(run("tum2bag", tmp_path / "rgbd_dataset_freiburg1_empty", "--out", tmp_path / "bag"))
    assert "rgb.txt is missing" in line and not (tmp_path / "bag").exists()
    line = error_line(run("tum2bag", tmp_path / "rgbd_dataset_freiburg1_empty", "--out", tmp_path / "bag",
                          "--camera", "kinect"))
    assert "--camera 'kinect'" in line
