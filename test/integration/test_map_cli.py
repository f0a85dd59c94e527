"""``rtabmap-ros2 map`` on two small simulated bags, then ``export``: one connected map."""

from __future__ import annotations

import csv
import json
import subprocess
import sys

import pytest

CLI = [sys.executable, "-m", "rtabmap_ros2.cli.cli"]


def run(*args, cwd=None) -> subprocess.CompletedProcess:
    return subprocess.run([*CLI, *map(str, args)], capture_output=True, text=True, timeout=900, cwd=cwd)


@pytest.fixture(scope="module")
def small_bags(tmp_path_factory):
    out = tmp_path_factory.mktemp("sim")
    result = run("simulate", "--out", out / "sim", "--small")
    assert result.returncode == 0, result.stderr
    return out / "sim"


@pytest.mark.slow
def test_map_then_export_gives_one_connected_map(small_bags, tmp_path):
    db = tmp_path / "map.db"
    stats = tmp_path / "stats.csv"
    result = run("map", small_bags / "session_1", small_bags / "session_2", "--db", db, "--no-progress",
                 "--stats", stats)
    assert result.returncode == 0, result.stderr
    with open(stats, newline="") as f:
        reader = csv.DictReader(f)
        rows = list(reader)
    assert reader.fieldnames == ["frame", "stamp", "location_id", "map_id", "loop_closure_id", "loop_closure_type",
                                 "process_time_ms", "time_optimization_ms", "wm_size", "local_map_size",
                                 "retrieved", "transferred"]
    frames = int(result.stdout.splitlines()[-1].split(" frames,")[0].split()[-1])
    assert len(rows) == frames and [int(r["frame"]) for r in rows] == list(range(frames))
    assert {r["map_id"] for r in rows} == {"0", "1"}
    loops = [r for r in rows if int(r["loop_closure_id"])]
    assert loops and {r["loop_closure_type"] for r in loops} <= {"loop_intra", "loop_inter"}
    assert all(float(r["process_time_ms"]) >= float(r["time_optimization_ms"]) >= 0 for r in rows)
    assert int(rows[-1]["local_map_size"]) > 0 and int(rows[-1]["wm_size"]) > 0
    session_lines = [l for l in result.stdout.splitlines() if l.startswith("session ")]
    assert len(session_lines) == 2, result.stdout
    assert "inter 0 " not in session_lines[1]  # the second session closed loops with the first
    assert result.stdout.splitlines()[-1].startswith("total: 2 sessions")
    assert (tmp_path / "params.yaml").is_file()
    before = db.read_bytes()
    result = run("export", db, "--out", tmp_path / "export")
    assert result.returncode == 0, result.stderr
    assert db.read_bytes() == before
    summary = json.loads((tmp_path / "export" / "summary.json").read_text())
    assert summary["components"] == 1
    assert [s["map_id"] for s in summary["sessions"]] == [0, 1]
    assert summary["links_by_type"]["loop_inter"] > 0
    assert "connected components: 1" in result.stdout


def test_map_missing_bag_is_an_error(tmp_path):
    result = run("map", tmp_path / "nope", "--db", tmp_path / "map.db")
    assert result.returncode == 2 and result.stderr.splitlines()[-1].startswith("error: bag")


def test_map_stats_in_a_missing_folder_is_an_error(small_bags, tmp_path):
    result = run("map", small_bags / "session_1", "--db", tmp_path / "map.db", "--stats", tmp_path / "no" / "s.csv")
    assert result.returncode == 2 and "--stats" in result.stderr.splitlines()[-1]
    assert not (tmp_path / "map.db").exists()


def test_export_missing_database_is_an_error(tmp_path):
    result = run("export", tmp_path / "nope.db", "--out", tmp_path / "out")
    assert result.returncode == 2 and "does not exist" in result.stderr


def test_a_bag_with_its_drivers_topic_names_is_read_through_remap(tmp_path):
    # A RealSense-and-robot_localization bag: none of the default topics but the laser. map says
    # which of the bag's topics could be each stream and refuses without odometry (it made a map of
    # 0 nodes before, exit 0); --remap NAME:=TOPIC, the node's remapping names, reads them.
    from rtabmap_ros2 import sim
    from rtabmap_ros2.io.bag import TopicNames, write_bag

    world = sim.build_world(seed=0)
    session = sim.make_sessions(world, small=True, sessions=1)[0]
    bag = write_bag(tmp_path / "bag", [sim.render_frame(world, session, i) for i in range(4)], topics=TopicNames(
        odom="/odometry/filtered", rgb="/camera/color/image_raw", depth="/camera/aligned_depth_to_color/image_raw",
        camera_info="/camera/color/camera_info"))
    db = tmp_path / "map.db"
    result = run("map", bag, "--db", db, "--no-progress")
    assert result.returncode == 2 and not db.exists()
    assert "--remap odom:=TOPIC" in result.stderr.splitlines()[-1] and "/odometry/filtered" in result.stderr
    assert "/camera/color/image_raw" in result.stdout and "--remap rgb/image:=TOPIC" in result.stdout
    result = run("map", bag, "--db", db, "--no-progress", "--remap", "odom:=/odometry/filtered",
                 "--remap", "rgb/image:=/camera/color/image_raw",
                 "--remap", "depth/image:=camera/aligned_depth_to_color/image_raw",
                 "--remap", "/rgb/camera_info:=/camera/color/camera_info")
    assert result.returncode == 0, result.stderr
    assert "reading /odometry/filtered (odom), /scan (scan), /camera/color/image_raw (rgb)" in result.stdout
    assert "session 0 (bag): 4 nodes from 4 frames" in result.stdout
    result = run("map", bag, "--db", db, "--remap", "camera:=/x")
    assert result.returncode == 2 and "expected NAME:=TOPIC" in result.stderr.splitlines()[-1]
