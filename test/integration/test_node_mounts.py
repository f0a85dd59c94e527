"""Sensors mounted off the base: a simulated session recorded without /tf_static is played into the node.

The laser is 0.25 m ahead, 0.1 m left and turned 0.3 rad; the camera 0.15 m ahead, 0.05 m right and
turned 0.27 rad; their messages are in their own frames (``laser``, ``camera_optical``), as a real
robot's drivers publish them, and the bag has no /tf_static (there is no tf2 here either). Played
with ``play`` at the node's default parameters (qos auto, image_transport auto: the bag carries
``rgb/image/compressed`` and ``depth/image/compressedDepth``), with the mounts given as the
``base_to_laser`` / ``base_to_camera`` parameters the exported poses match the ground truth; without
them they are measurably worse; the compressed images are stored as they came. ``map --set`` takes
the same two for a bag without /tf_static.
"""

from __future__ import annotations

import random
from pathlib import Path

import pytest

rclpy = pytest.importorskip("rclpy")

from std_srvs.srv import Trigger  # noqa: E402

from rtabmap_ros2.core.database import Database  # noqa: E402
from rtabmap_ros2.core.params import SyncParams  # noqa: E402
from rtabmap_ros2.io.bag import BagDataset  # noqa: E402
from rtabmap_ros2.io.trajectory import ate, read_tum  # noqa: E402
from rtabmap_ros2.ros.node import RtabmapNode  # noqa: E402

from node_play import play_into_node  # noqa: E402

pytestmark = pytest.mark.ros

DOMAIN_ID = random.randint(1, 99)
LASER_MOUNT = [0.25, 0.1, 0.3, 0.0, 0.0, 0.3]
CAMERA_MOUNT = [0.15, -0.05, 0.5, -1.5708, 0.0, -1.3]
ATE_MAX_M = 0.02
MIN_PROCESSED_RATIO = 0.95


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    from rtabmap_ros2.sim.simulate import simulate

    out = tmp_path_factory.mktemp("mounted")
    summary = simulate(out, sessions=1, small=True, laser_mount=LASER_MOUNT, camera_mount=CAMERA_MOUNT,
                       tf_static=False)
    return out, summary.sessions[0]["frames"]


def _play_into_node(context, tmp_path, bag, rate=1.0, **params) -> tuple[RtabmapNode, float]:
    """Play ``bag`` at ``rate`` into a node with ``params``; export; return the node (destroyed) and the ATE (m)."""
    overrides = {"database_path": str(tmp_path / "map.db"), "export_dir": str(tmp_path / "exports"), **params}

    def export(node):
        response = node._export_global_map(Trigger.Request(), Trigger.Response())
        assert response.success, response.message
        return Path(response.message)

    node, folder = play_into_node(context, bag, overrides, before_destroy=export, rate=rate)
    estimate = read_tum(folder / "poses.txt")
    return node, ate(estimate, read_tum(bag.parent / "ground_truth.txt")).rmse_m


def test_mounts_as_parameters_give_the_ground_truth(context, tmp_path, recording, capfd):
    out, n_frames = recording
    bag = out / "session_1"
    node, with_mounts = _play_into_node(context, tmp_path / "with", bag,
                                        base_to_laser=LASER_MOUNT, base_to_camera=CAMERA_MOUNT)
    # The project's own (compressed) bag replays as it is, at the default qos/image_transport (auto).
    assert node.subscriptions_.current["rgb"][0].topic == "/rgb/image/compressed"
    assert node.subscriptions_.current["depth"][0].topic == "/depth/image/compressedDepth"
    assert node.frames_processed >= MIN_PROCESSED_RATIO * n_frames, (node.frames_processed, n_frames)
    assert node.mounts.source == "parameters"
    # The compressed topics' JPEG and compressedDepth PNG are stored as they came, not encoded again.
    published = [(f.rgb_jpeg, f.depth_png16_mm) for f in BagDataset(bag, sync=SyncParams(rate_hz=0))]
    assert all(jpeg and png for jpeg, png in published)
    with Database(tmp_path / "with" / "map.db", read_only=True) as db:
        stored = [db.load_sensor_blobs(n) for n in db.load_nodes()]
    assert len(stored) >= MIN_PROCESSED_RATIO * n_frames / 2
    assert all((blobs.rgb_jpeg, blobs.depth_png16_mm) in published for blobs in stored)
    log = capfd.readouterr().err
    assert log.count("tf2_ros is not available") == 1, log
    assert with_mounts <= ATE_MAX_M

    # Without them (played twice as fast: fewer nodes, the same wrong mounts).
    _, without = _play_into_node(context, tmp_path / "without", bag, rate=2.0)
    print(f"node ATE with the mount parameters {with_mounts:.4f} m, without {without:.4f} m")
    assert without > 3 * with_mounts and without > 2 * ATE_MAX_M, (with_mounts, without)


def test_map_takes_the_mounts_for_a_bag_without_tf_static(tmp_path, recording):
    from rtabmap_ros2.cli.cli import main as cli

    out, _ = recording
    db = tmp_path / "map.db"
    assert cli(["map", str(out / "session_1"), "--db", str(db), "--no-progress",
                f"--set=base_to_laser={LASER_MOUNT}", f"--set=base_to_camera={CAMERA_MOUNT}"]) == 0
    assert cli(["export", str(db), "--out", str(tmp_path / "export")]) == 0
    error = ate(read_tum(tmp_path / "export" / "poses.txt"), read_tum(out / "ground_truth.txt")).rmse_m
    assert error <= ATE_MAX_M   # without them: 0.12 m (README)
