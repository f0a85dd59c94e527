"""What ``map`` tells its user (issue 49's frictions 1, 3 and 5): the mode, the mounts' sources,
the frames the detection rate skipped, one meaning per word, exact stamps."""

from __future__ import annotations

from types import SimpleNamespace

from rtabmap_ros2.cli import cli
from rtabmap_ros2.cli.cmd_map import SessionSummary, bag_line, mode_line, stats_row
from rtabmap_ros2.core.params import Params
from rtabmap_ros2.core.statistics import Statistics
from rtabmap_ros2.io.bag import BagRead, Mount


def test_the_mode_line_says_planar_or_6dof_and_how_to_change_it():
    shipped = mode_line(Params().with_value("Reg/Force3DoF", True))
    assert shipped.startswith("mode: planar") and "--set Reg/Force3DoF=false" in shipped and "1 Hz" in shipped
    six = mode_line(Params().with_overrides(["Rtabmap/DetectionRate=0", "Grid/Sensor=1"]))
    assert six.startswith("mode: 6 DoF") and "every frame" in six and "occupancy grid: depth images" in six


def test_map_help_documents_what_a_camera_only_user_needs(capsys):
    try:
        cli.main(["map", "--help"])
    except SystemExit:
        pass
    text = " ".join(capsys.readouterr().out.split())
    for needed in ("Reg/Force3DoF=false", "Rtabmap/DetectionRate", "Grid/Sensor", "base_to_camera", "export reuses"):
        assert needed in text, needed


def test_the_bag_line_counts_skipped_frames_and_names_each_mount_source():
    params = Params().with_value("base_to_laser", [0.2, 0.0, 0.3, 0.0, 0.0, 0.0])
    dataset = SimpleNamespace(
        last_read=BagRead(synchronised=60, rate_limited=58, frames=2, bad=0, dropped={}),
        mounts={"camera": Mount("fallback", "base_link", "camera_optical"),
                "laser": Mount("fallback", "base_link", "laser")})
    line = bag_line("bag", dataset, params)
    assert "60 synchronised frames, 2 processed, 58 skipped by the detection rate (1 Hz" in line
    assert "camera mount from the default" in line and "base_to_camera not set" in line
    assert "laser mount from the base_to_laser parameter [0.2, 0.0, 0.3, 0.0, 0.0, 0.0]" in line
    dataset.mounts = {"camera": Mount("tf_static", "base_link", "camera_optical")}
    assert "camera mount from /tf_static (base_link -> camera_optical)" in bag_line("bag", dataset, params)


def test_rejected_while_mapping_is_not_the_global_optimisations_and_stamps_are_exact():
    line = SessionSummary(0, "bag", frames=2, nodes=2, rejected_online=3).line()
    assert "2 nodes from 2 frames processed" in line and "(3 rejected while mapping)" in line
    stats = Statistics(frame_index=0, stamp_ns=1305031229528748000)
    assert stats_row(stats)["stamp"] == "1305031229.528748000"
