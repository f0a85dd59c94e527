"""The launch file and the RViz config: valid, consistent with the node, installed by setup.py.

``launch`` / ``launch_ros`` are not importable without a ROS 2 install, so the launch file is checked
as Python source (it parses; it starts the ``rtabmap`` executable with the shipped parameters file
and remaps the node's inputs) rather than run.
"""

from __future__ import annotations

import ast
import runpy
from pathlib import Path

import pytest
import setuptools
import yaml

REPO = Path(__file__).resolve().parents[2]
LAUNCH = REPO / "launch" / "rtabmap.launch.py"
RVIZ = REPO / "config" / "rtabmap.rviz"


def _strings(tree: ast.AST) -> set[str]:
    return {n.value for n in ast.walk(tree) if isinstance(n, ast.Constant) and isinstance(n.value, str)}


def test_launch_file_parses_and_starts_the_node_with_remappings():
    tree = ast.parse(LAUNCH.read_text(), filename=str(LAUNCH))
    functions = {n.name for n in tree.body if isinstance(n, ast.FunctionDef)}
    assert "generate_launch_description" in functions
    strings = _strings(tree)
    assert {"rtabmap", "rtabmap.yaml", "rtabmap.rviz", "params_file", "respawn"} <= strings
    # Every input of the node can be remapped, under its relative name.
    assert {"odom", "scan", "rgb/image", "depth/image", "rgb/camera_info"} <= strings
    # The parameters it passes are the node's.
    from rtabmap_ros2.core.params import NodeParams
    from dataclasses import fields

    node_fields = {f.name for f in fields(NodeParams)}
    assert {"database_path", "frame_id", "qos", "image_transport", "subscribe_scan"} <= node_fields & strings


def test_rviz_config_shows_the_node_outputs():
    config = yaml.safe_load(RVIZ.read_text())
    manager = config["Visualization Manager"]
    assert manager["Global Options"]["Fixed Frame"] == "map"
    displays = {d["Class"].split("/")[-1]: d for d in manager["Displays"]}
    assert displays["Map"]["Topic"]["Value"] == "/map"
    assert displays["Map"]["Topic"]["Durability Policy"] == "Transient Local"   # map is latched
    assert displays["Path"]["Topic"]["Value"] == "/mapPath"
    assert displays["MarkerArray"]["Topic"]["Value"] == "/mapGraph"
    assert "TF" in displays


def test_setup_installs_launch_and_rviz(monkeypatch):
    captured = {}
    monkeypatch.setattr(setuptools, "setup", lambda **kwargs: captured.update(kwargs))
    monkeypatch.chdir(REPO)
    runpy.run_path(str(REPO / "setup.py"), run_name="__main__")
    installed = {dest: files for dest, files in captured["data_files"]}
    assert "launch/rtabmap.launch.py" in installed["share/rtabmap_ros2/launch"]
    assert {"config/rtabmap.rviz", "config/rtabmap.yaml"} <= set(installed["share/rtabmap_ros2/config"])
    for files in installed.values():
        for f in files:
            assert (REPO / f).is_file(), f
