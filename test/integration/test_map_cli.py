"""``rtabmap-ros2 map`` on two small simulated bags, then ``export``: one connected map."""

from __future__ import annotations

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
    result = run("map", small_bags / "session_1", small_bags / "session_2", "--db", db, "--no-progress")
    assert result.returncode == 0, result.stderr
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


def test_export_missing_database_is_an_error(tmp_path):
    result = run("export", tmp_path / "nope.db", "--out", tmp_path / "out")
    assert result.returncode == 2 and "does not exist" in result.stderr
