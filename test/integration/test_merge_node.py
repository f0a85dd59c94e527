"""Two robots mapping at the same time, one with the ``rtabmap`` node, one with ``map``, merged.

``simulate --small --seed 3 --raw-images --session-gap 0`` with the sensors mounted off the base:
robot 1's bag is played into the node (in this process, the mounts as parameters: no tf2 here),
robot 2's is mapped by ``map`` in another process; both maps cover the same stamps. ``merge`` gives
one component, every node of both inputs, the exported map within 3 cm of the ground truth, and
leaves both inputs byte for byte as they were. The node then starts from the merged database
(``database_path``): it localizes in it without adding a node, and continues mapping it in a new
session.
"""

from __future__ import annotations

import json
import random

import pytest

rclpy = pytest.importorskip("rclpy")

from rtabmap_ros2.core.database import Database  # noqa: E402

from node_play import play_into_node  # noqa: E402
from test_merge_cli import MAX_ATE_M, SEED, digest, merged_ate, node_count, run  # noqa: E402
from test_node_mounts import CAMERA_MOUNT, LASER_MOUNT  # noqa: E402

pytestmark = [pytest.mark.ros, pytest.mark.slow]

DOMAIN_ID = random.randint(1, 99)
# Seconds of a bag played into the node started from the merged database, per mode.
LOCALIZE_S = 12.0
CONTINUE_S = 20.0


def play(context, bag, database, seconds=None, rate=1.0, **params):
    """``bag`` played at ``rate`` into a node on ``database`` with the mounts as parameters (no tf2 here)."""
    overrides = {"database_path": str(database), "base_to_laser": LASER_MOUNT, "base_to_camera": CAMERA_MOUNT,
                 **params}
    return play_into_node(context, bag, overrides, seconds, rate=rate)[0]


def test_node_and_map_databases_of_robots_at_the_same_time_merge_and_the_node_goes_on(context, tmp_path):
    sim = tmp_path / "sim"
    mounts = ["--laser-mount", ",".join(map(str, LASER_MOUNT)), "--camera-mount", ",".join(map(str, CAMERA_MOUNT))]
    result = run("simulate", "--out", sim, "--small", "--seed", SEED, "--raw-images", "--session-gap", 0, *mounts)
    assert result.returncode == 0, result.stderr
    node = play(context, sim / "session_1", tmp_path / "robot_1.db", rate=2.0)   # the whole session, fewer nodes
    assert node.frames_processed > 0
    result = run("map", sim / "session_2", "--db", tmp_path / "robot_2.db", "--no-progress")
    assert result.returncode == 0, result.stderr
    inputs = [tmp_path / "robot_1.db", tmp_path / "robot_2.db"]
    with Database(inputs[0], read_only=True) as a, Database(inputs[1], read_only=True) as b:
        stamps = [(min(n.stamp_ns for n in db.load_nodes().values()), max(n.stamp_ns for n in db.load_nodes().values()))
                  for db in (a, b)]
    assert stamps[0][0] < stamps[1][1] and stamps[1][0] < stamps[0][1], stamps   # the same time range
    before = [digest(p) for p in inputs]

    merged = tmp_path / "merged.db"
    result = run("merge", *inputs, "--out", merged, "--no-progress")
    assert result.returncode == 0, result.stderr
    print(result.stdout)
    assert [digest(p) for p in inputs] == before
    assert result.stdout.count("every node present") == 2, result.stdout
    assert "1 component(s) (sessions 0, 1)" in result.stdout
    nodes = node_count(merged)
    assert nodes == node_count(inputs[0]) + node_count(inputs[1])
    result = run("export", merged, "--out", tmp_path / "export")
    assert result.returncode == 0, result.stderr
    summary = json.loads((tmp_path / "export" / "summary.json").read_text())
    assert summary["components"] == 1 and summary["nodes"] == nodes
    error, matched = merged_ate(tmp_path / "export", [sim / "ground_truth_1.txt", sim / "ground_truth_2.txt"])
    print(f"node + map, merged: ATE {error:.4f} m over {matched} nodes ({node_count(inputs[0])} + "
          f"{node_count(inputs[1])})")
    assert matched == nodes and error <= MAX_ATE_M

    # Localization in the merged map: no node added, poses found.
    with Database(merged, read_only=True) as db:
        frames_before = db.max_frame_index()
    node = play(context, sim / "session_2", merged, LOCALIZE_S, localization=True)
    assert node.frames_processed > 0
    with Database(merged, read_only=True) as db:
        assert db.node_count() == nodes
        rows = [row for row in db.load_statistics() if row["frame_index"] > frames_before]
    assert len(rows) == node.frames_processed and sum(row["localized"] for row in rows) > 0, rows

    # Mapping goes on in the merged map: a new session, joined to it.
    node = play(context, sim / "session_1", merged, CONTINUE_S)
    with Database(merged, read_only=True) as db:
        infos = db.load_nodes()
        assert {n.map_id for n in infos.values()} == {0, 1, 2}
        assert sum(n.map_id == 2 for n in infos.values()) > 0
        inter = [(infos[a].map_id, infos[b].map_id) for a, b in db.inter_session_pairs()]
    joined = sorted({m for pair in inter if 2 in pair for m in pair} - {2})
    print(f"continued: {sum(n.map_id == 2 for n in infos.values())} nodes in session 2, loop closures to sessions "
          f"{joined}")
    assert joined, inter   # the new session closed loops with the merged map
