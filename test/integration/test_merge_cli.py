"""``rtabmap-ros2 merge``: databases made apart (robots mapping at the same time) merged into one map.

The simulator at seed 3 (the demo's is 0) with ``--session-gap 0``: every robot starts at the same
instant, so their stamps coincide. Each robot's bag is mapped into its own database in its own
process (``map``; the node in test_merge_node.py), then merged: one component, every input node
found again, the exported map within 3 cm of the ground truth, the inputs unchanged byte for byte.
A robot kept to a part of the building the others never see stays a component of its own, and the
summary says why. Bad inputs each give one ``error:`` line and exit 2, and no output is written.
"""

from __future__ import annotations

import csv
import hashlib
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from rtabmap_ros2.core.params import Params, default_config_path
from rtabmap_ros2.core.rtabmap import Rtabmap
from rtabmap_ros2.io.trajectory import read_tum

from cli_result import error_line

CLI = [sys.executable, "-m", "rtabmap_ros2"]
TIMEOUT_S = 900
SEED = 3
MAX_ATE_M = 0.03
# A route in the T-shaped wing (sim/world.py), which the small sessions' routes never reach.
ELSEWHERE_PLAN = ("T_nw", "T_ne", "T_e", "T_m")
# Frames per robot of the small databases of the bad-input tests.
FEW_FRAMES = 6


def run(*args) -> subprocess.CompletedProcess:
    return subprocess.run([*CLI, *map(str, args)], capture_output=True, text=True, timeout=TIMEOUT_S)


def digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def merged_ate(export_dir: Path, truths: list[Path]) -> tuple[float, int]:
    """ATE (m) of an export whose session k is the robot of ``truths[k]`` (a TUM file): the robots'
    stamps coincide, so each session is matched with its own ground truth; one alignment for all."""
    from rtabmap_ros2.io.export import read_nodes_csv
    from rtabmap_ros2.io.trajectory import ate_sessions

    result = ate_sessions(read_nodes_csv(export_dir / "nodes.csv"), dict(enumerate(map(read_tum, truths))))
    return result.rmse_m, result.matched


def node_count(db: Path) -> int:
    from rtabmap_ros2.core.database import Database

    with Database(db, read_only=True) as d:
        return d.node_count()


@pytest.fixture(scope="module")
def fleet(tmp_path_factory) -> Path:
    """Three robots of ``simulate --session-gap 0`` (the third drives the first's route again), each
    mapped by ``map`` into its own database, and a fourth robot elsewhere in the building."""
    out = tmp_path_factory.mktemp("fleet")
    result = run("simulate", "--out", out / "sim", "--small", "--sessions", 3, "--seed", SEED, "--session-gap", 0)
    assert result.returncode == 0, result.stderr
    for k in (1, 2, 3):
        result = run("map", out / "sim" / f"session_{k}", "--db", out / f"robot_{k}.db", "--no-progress")
        assert result.returncode == 0, result.stderr
    from rtabmap_ros2.sim import build_world, make_sessions, session_frames
    from rtabmap_ros2.sim.simulate import write_ground_truth

    world = build_world(seed=SEED)
    elsewhere = make_sessions(world, sessions=1, small=True, session_gap_s=0, plans=(ELSEWHERE_PLAN,))[0]
    write_ground_truth(out / "ground_truth_elsewhere.txt", [elsewhere])
    params = Params.from_yaml(default_config_path())
    with Rtabmap(params, out / "robot_elsewhere.db") as rtabmap:
        for frame in session_frames(world, elsewhere):
            rtabmap.process(frame)
    return out


@pytest.mark.slow
def test_three_robots_at_once_merge_into_one_map(fleet, tmp_path):
    inputs = [fleet / f"robot_{k}.db" for k in (1, 2, 3)]
    before = [digest(p) for p in inputs]
    stats = tmp_path / "stats.csv"
    result = run("merge", *inputs, "--out", tmp_path / "merged.db", "--no-progress", "--stats", stats)
    assert result.returncode == 0, result.stderr
    print(result.stdout)
    assert [digest(p) for p in inputs] == before
    lines = result.stdout.splitlines()
    for k in (1, 2, 3):
        assert any(line.startswith(f"robot_{k}.db session 0: ") and line.endswith("every node present")
                   for line in lines), result.stdout
    assert "1 component(s) (sessions 0, 1, 2)" in result.stdout
    assert node_count(tmp_path / "merged.db") == sum(node_count(p) for p in inputs)
    with open(stats, newline="") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == sum(node_count(p) for p in inputs)
    assert {r["map_id"] for r in rows} == {"0", "1", "2"}
    # The stamps coincide across robots: the nodes are told apart by their session only.
    stamps = [r["stamp"] for r in rows]
    assert len(set(stamps)) < len(stamps)

    export = run("export", tmp_path / "merged.db", "--out", tmp_path / "export")
    assert export.returncode == 0, export.stderr
    summary = json.loads((tmp_path / "export" / "summary.json").read_text())
    assert summary["components"] == 1 and [s["map_id"] for s in summary["sessions"]] == [0, 1, 2]
    error, matched = merged_ate(tmp_path / "export", [fleet / "sim" / f"ground_truth_{k}.txt" for k in (1, 2, 3)])
    print(f"three robots: ATE {error:.4f} m over {matched} nodes")
    assert matched == summary["nodes"] and error <= MAX_ATE_M


@pytest.mark.slow
def test_a_robot_that_never_sees_the_others_places_stays_apart_and_the_summary_says_why(fleet, tmp_path):
    inputs = [fleet / "robot_1.db", fleet / "robot_elsewhere.db"]
    before = [digest(p) for p in inputs]
    result = run("merge", *inputs, "--out", tmp_path / "merged.db", "--no-progress")
    assert result.returncode == 0, result.stderr
    print(result.stdout)
    assert [digest(p) for p in inputs] == before
    assert "2 component(s)" in result.stdout
    reason = [line for line in result.stdout.splitlines() if line.startswith("sessions 0 and 1: not merged: ")]
    assert len(reason) == 1, result.stdout
    # The best candidate's reason, one of three (here look-alike walls raise hypotheses over T_loop
    # that verification rejects: "too few inliers", with the counts).
    assert any(kind in reason[0] for kind in ("no hypothesis over T_loop", "too few inliers",
                                              "rejected by the merge checks")), reason
    assert any(ch.isdigit() for ch in reason[0].split("not merged: ")[1]), reason
    assert result.stdout.count("every node present") == 2


# -- bad inputs: small databases of a few frames --------------------------------------------------

@pytest.fixture(scope="module")
def few(tmp_path_factory) -> dict[str, Path]:
    """Databases of a few frames: two robots, and the first robot again with SIFT descriptors."""
    from rtabmap_ros2.sim import build_world, make_sessions, render_frame

    out = tmp_path_factory.mktemp("few")
    world = build_world(seed=SEED)
    sessions = make_sessions(world, small=True, session_gap_s=0)
    params = Params.from_yaml(default_config_path())
    made = {}
    for name, session, overrides in (("a", sessions[0], []), ("b", sessions[1], []),
                                     ("sift", sessions[0], ["features.detector=sift"])):
        made[name] = out / f"{name}.db"
        with Rtabmap(params.with_overrides(overrides), made[name]) as rtabmap:
            for i in range(FEW_FRAMES):
                rtabmap.process(render_frame(world, session, i))
    return made


def test_a_database_of_other_descriptors_is_refused_and_reextract_is_offered(few, tmp_path):
    before = digest(few["sift"])
    line = error_line(run("merge", few["a"], few["sift"], "--out", tmp_path / "merged.db"))
    assert str(few["sift"]) in line and "128-d float32" in line and "32-byte binary" in line, line
    assert "--reextract" in line
    assert not (tmp_path / "merged.db").exists() and os.listdir(tmp_path) == []
    assert digest(few["sift"]) == before


def test_reextract_merges_databases_of_other_descriptors(few, tmp_path):
    before = [digest(few["a"]), digest(few["sift"])]
    result = run("merge", few["a"], few["sift"], "--out", tmp_path / "merged.db", "--reextract", "--no-progress")
    assert result.returncode == 0, result.stderr
    assert [digest(few["a"]), digest(few["sift"])] == before
    assert result.stdout.count("every node present") == 2, result.stdout
    assert node_count(tmp_path / "merged.db") == 2 * FEW_FRAMES
    from rtabmap_ros2.core.database import Database

    with Database(tmp_path / "merged.db", read_only=True) as db:   # the config's detector, gftt_orb
        assert db.descriptor_kinds() == [("uint8", 32)]


def test_a_truncated_database_is_refused(few, tmp_path):
    truncated = tmp_path / "inputs" / "truncated.db"
    truncated.parent.mkdir()
    data = few["b"].read_bytes()
    truncated.write_bytes(data[: len(data) // 2])
    line = error_line(run("merge", few["a"], truncated, "--out", tmp_path / "merged.db"))
    assert str(truncated) in line and "truncated" in line, line
    assert not (tmp_path / "merged.db").exists()
    assert truncated.read_bytes() == data[: len(data) // 2]


def test_a_file_that_is_not_a_database_is_refused(few, tmp_path):
    notes = tmp_path / "notes.db"
    notes.write_text("robot 2 map, see the wiki\n" * 50)
    line = error_line(run("merge", few["a"], notes, "--out", tmp_path / "merged.db"))
    assert str(notes) in line and "not a database" in line, line
    assert not (tmp_path / "merged.db").exists()


def test_the_same_database_twice_is_refused(few, tmp_path):
    before = digest(few["a"])
    line = error_line(run("merge", few["a"], few["b"], few["a"], "--out", tmp_path / "merged.db"))
    assert "given twice" in line and str(few["a"]) in line, line
    link = tmp_path / "link.db"
    link.symlink_to(few["a"])
    assert "given twice" in error_line(run("merge", few["a"], link, "--out", tmp_path / "merged.db"))
    copy = tmp_path / "copy.db"
    copy.write_bytes(few["a"].read_bytes())
    assert "is a copy of" in error_line(run("merge", few["a"], copy, "--out", tmp_path / "merged.db"))
    assert not (tmp_path / "merged.db").exists()
    assert digest(few["a"]) == before


def test_the_output_is_never_an_input_nor_an_existing_file(few, tmp_path):
    before = digest(few["a"])
    line = error_line(run("merge", few["a"], few["b"], "--out", few["a"], "--overwrite"))
    assert "is one of the inputs" in line
    assert digest(few["a"]) == before
    existing = tmp_path / "merged.db"
    existing.write_bytes(b"keep me")
    assert "already exists" in error_line(run("merge", few["a"], few["b"], "--out", existing))
    assert existing.read_bytes() == b"keep me"
