"""``demo --small`` end to end in a subprocess, and ``report`` on a database without ground truth."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import pytest

from rtabmap_ros2.io.report import FIGURES

GROUND_TRUTH_FIGURES = {"trajectories.png", "precision_recall.png"}
DEMO_TIMEOUT_S = 600


def _cli(*args: str, timeout: float = DEMO_TIMEOUT_S) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "rtabmap_ros2", *args], capture_output=True, text=True,
                          timeout=timeout, check=False)


@pytest.fixture(scope="module")
def demo_run(tmp_path_factory) -> tuple[Path, subprocess.CompletedProcess]:
    """One ``demo --small`` run shared by the tests of this file."""
    out = tmp_path_factory.mktemp("demo")
    proc = _cli("demo", "--small", "--no-progress", "--out", str(out))
    return out, proc


@pytest.mark.slow
def test_demo_small_end_to_end(demo_run):
    out, proc = demo_run
    assert proc.returncode == 0, proc.stderr[-3000:]
    # The printed summary.
    nodes = int(re.search(r"^nodes:\s+(\d+)", proc.stdout, re.M).group(1))
    components = int(re.search(r"^connected components:\s+(\d+)", proc.stdout, re.M).group(1))
    inter = int(re.search(r"inter-session (\d+)", proc.stdout).group(1))
    assert nodes > 0
    assert components == 1  # the second session was joined to the first by inter-session loop closures
    assert inter > 0
    assert re.search(r"^ATE .*RMSE (\d+\.\d+) m", proc.stdout, re.M)
    assert re.search(r"^max pTime:\s+\d+ ms", proc.stdout, re.M)
    # The outputs.
    assert (out / "map.db").is_file()
    assert (out / "export" / "map.png").is_file()
    index = out / "report" / "index.html"
    assert index.is_file()
    page = index.read_text()
    for name in FIGURES:  # with the simulator's ground truth every figure is drawn
        assert (out / "report" / name).stat().st_size > 10_000, name
        assert f'src="{name}"' in page, name
    summary = json.loads((out / "report" / "summary.json").read_text())
    assert summary["nodes"] == nodes
    assert summary["ate"]["rmse_m"] < 1.0  # the small building, joined: well under a metre


@pytest.mark.slow
def test_demo_reuses_matching_simulation(demo_run, tmp_path):
    out, proc = demo_run
    assert proc.returncode == 0, proc.stderr[-3000:]
    from rtabmap_ros2.cli.cmd_demo import _simulation_matches

    assert _simulation_matches(out / "sim", sessions=2, seed=0, small=True)
    assert not _simulation_matches(out / "sim", sessions=2, seed=1, small=True)
    assert not _simulation_matches(out / "sim", sessions=5, seed=0, small=False)


@pytest.mark.slow
def test_report_without_ground_truth(demo_run, tmp_path):
    out, proc = demo_run
    assert proc.returncode == 0, proc.stderr[-3000:]
    report_dir = tmp_path / "report"
    result = _cli("report", str(out / "map.db"), "--out", str(report_dir))
    assert result.returncode == 0, result.stderr[-3000:]
    drawn = {p.name for p in report_dir.glob("*.png")}
    assert drawn == set(FIGURES) - GROUND_TRUTH_FIGURES
    for name in GROUND_TRUTH_FIGURES:
        assert f"skipped {name}: no ground truth" in result.stdout
    page = (report_dir / "index.html").read_text()
    assert "Not drawn" in page and "no ground truth" in page
    for name in drawn:
        assert f'src="{name}"' in page


def test_report_of_a_missing_path_is_an_error(tmp_path):
    result = _cli("report", str(tmp_path / "nothing.db"), "--out", str(tmp_path / "r"), timeout=60)
    assert result.returncode == 2
    assert "does not exist" in result.stderr
