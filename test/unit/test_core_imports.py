"""rtabmap_ros2.core never imports rclpy or any *_msgs package (CONVENTIONS: layers)."""

from __future__ import annotations

import ast
import json
import pkgutil
import subprocess
import sys
from pathlib import Path

import rtabmap_ros2.core

CORE_DIR = Path(rtabmap_ros2.core.__file__).parent
CORE_MODULES = sorted(f"rtabmap_ros2.core.{m.name}" for m in pkgutil.iter_modules([str(CORE_DIR)]))
# ament_index_python (a guarded lookup of the shipped config in params.py) is not a ROS runtime import.
FORBIDDEN_PREFIXES = ("rclpy", "rosidl", "rcl_interfaces", "builtin_interfaces")


def _forbidden(name: str) -> bool:
    top = name.split(".")[0]
    return top.startswith(FORBIDDEN_PREFIXES) or top.endswith("_msgs") or top.endswith("_srvs") \
        or top == "rtabmap_ros2" and name.startswith("rtabmap_ros2.ros")


def test_core_has_the_paper_modules():
    for name in ("params", "features", "vocabulary", "signature", "bayes", "memory", "database", "rtabmap"):
        assert f"rtabmap_ros2.core.{name}" in CORE_MODULES


def test_importing_every_core_module_loads_no_ros_module():
    code = ("import importlib, json, sys\n"
            f"for m in {CORE_MODULES!r}: importlib.import_module(m)\n"
            "print(json.dumps(sorted(sys.modules)))\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    loaded = json.loads(out.stdout.strip().splitlines()[-1])
    assert set(CORE_MODULES) <= set(loaded)
    assert [m for m in loaded if _forbidden(m)] == []


def test_core_sources_do_not_import_ros_or_print():
    offenders = []
    for path in sorted(CORE_DIR.glob("*.py")):
        tree = ast.parse(path.read_text(), filename=str(path))
        for node in ast.walk(tree):
            names = []
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                names = [node.module]
            offenders += [f"{path.name}: import {n}" for n in names if _forbidden(n)]
            if isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id in ("print", "exit"):
                offenders.append(f"{path.name}:{node.lineno}: {node.func.id}()")
            if isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) \
                    and node.value.id == "sys" and node.attr == "exit":
                offenders.append(f"{path.name}:{node.lineno}: sys.exit")
    assert offenders == []


def test_the_static_check_would_catch_an_import():
    assert _forbidden("rclpy.node") and _forbidden("sensor_msgs.msg") and _forbidden("rtabmap_ros2.ros.node")
    assert not _forbidden("numpy") and not _forbidden("rtabmap_ros2.core.graph")


def test_optimize_command_imports_neither_numba_nor_the_front_end():
    """``rtabmap-ros2 optimize`` imports what it calls: numba alone cost each run 0.47 s of a 1 s process."""
    code = ("import json, sys\n"
            "from rtabmap_ros2.cli import cmd_optimize\n"
            "from rtabmap_ros2.core.optimizer import optimize\n"
            "from rtabmap_ros2.io.g2o import read_g2o, write_optimised\n"
            "print(json.dumps(sorted(sys.modules)))\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    loaded = set(json.loads(out.stdout.strip().splitlines()[-1]))
    assert not loaded & {"numba", "cv2", "rtabmap_ros2.core.graph_compiled", "rtabmap_ros2.core.features"}
