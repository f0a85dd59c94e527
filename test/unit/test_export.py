"""export_global_map: the issue's files, their headers and contents; the database is untouched."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest
import yaml

from rtabmap_ros2.io.g2o import read_g2o
from rtabmap_ros2.core.params import Params
from rtabmap_ros2.errors import DatabaseError
from rtabmap_ros2.io.export import FILES, LINKS_COLUMNS, NODES_COLUMNS, export_global_map
from rtabmap_ros2.io.trajectory import read_tum
from test_global_map import make_database


# make_database's robot moves on a plane (its poses x, y, yaw): exported as such.
PLANAR = Params().with_value("registration.planar", True)


@pytest.fixture
def exported(tmp_path, rng):
    gt, loops = make_database(tmp_path / "map.db", rng)
    before = (tmp_path / "map.db").read_bytes()
    summary = export_global_map(tmp_path / "map.db", tmp_path / "out", PLANAR)
    return tmp_path, gt, loops, before, summary


def test_writes_every_file_and_leaves_database_untouched(exported):
    tmp_path, gt, _, before, summary = exported
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == sorted(FILES)
    assert (tmp_path / "map.db").read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["map.db", "out"]  # no -wal / -shm left
    assert summary == json.loads((tmp_path / "out" / "summary.json").read_text())
    assert summary["nodes"] == len(gt) and summary["components"] == 1
    assert summary["links_by_type"]["loop_inter"] == 6 and summary["links_by_type"]["loop_intra"] == 1
    assert [s["nodes"] for s in summary["sessions"]] == [len(gt) // 2] * 2
    assert summary["optimization"]["chi2_final"] < summary["optimization"]["chi2_initial"]


def test_poses_nodes_and_links_agree(exported):
    tmp_path, gt, loops, _, _ = exported
    poses = read_tum(tmp_path / "out" / "poses.txt")
    assert len(poses) == len(gt)
    with open(tmp_path / "out" / "nodes.csv") as f:
        rows = list(csv.reader(f))
    assert rows[0] == NODES_COLUMNS and all(len(r) == len(NODES_COLUMNS) for r in rows)
    by_stamp = {float(r[2]): r for r in rows[1:]}
    for stamp_ns, T in zip(poses.stamps_ns, poses.poses):
        row = by_stamp[stamp_ns / 1e9]
        np.testing.assert_allclose([float(v) for v in row[3:6]], T[:3, 3], atol=1e-5)
    assert {int(r[1]) for r in rows[1:]} == {0, 1}
    with open(tmp_path / "out" / "links.csv") as f:
        links = list(csv.reader(f))
    assert links[0] == LINKS_COLUMNS and all(len(r) == len(LINKS_COLUMNS) for r in links)
    assert {r[2] for r in links[1:]} == {"neighbor", "loop_intra", "loop_inter"}
    assert len(links) - 1 == len(gt) - 2 + len(loops)


def test_g2o_is_readable_with_optimised_poses(exported):
    tmp_path, gt, loops, _, _ = exported
    poses, links, planar = read_g2o(tmp_path / "out" / "graph.g2o")
    assert planar and len(poses) == len(gt) and len(links) == len(gt) - 2 + len(loops)
    tum = read_tum(tmp_path / "out" / "poses.txt")
    ids = sorted(poses)  # node ids increase with stamps in this database
    np.testing.assert_allclose(np.stack([poses[i][:2, 3] for i in ids]), tum.poses[:, :2, 3], atol=1e-5)


def test_map_server_files(exported):
    tmp_path, *_ = exported
    meta = yaml.safe_load((tmp_path / "out" / "map.yaml").read_text())
    assert meta["image"] == "map.pgm" and meta["resolution"] == pytest.approx(0.05)
    assert len(meta["origin"]) == 3 and meta["origin"][2] == 0.0
    assert meta["negate"] == 0 and meta["occupied_thresh"] == 0.65 and meta["free_thresh"] == 0.196
    data = (tmp_path / "out" / "map.pgm").read_bytes()
    header = [line for line in data.split(b"\n", 4)[:4] if not line.startswith(b"#")]
    assert header[0] == b"P5"
    width, height = map(int, header[1].split())
    pixels = np.frombuffer(data[-width * height:], np.uint8)
    assert set(np.unique(pixels).tolist()) <= {0, 205, 254}
    assert (pixels == 0).any() and (pixels == 254).any()
    import cv2

    png = cv2.imread(str(tmp_path / "out" / "map.png"))[:, :, ::-1]  # RGB
    # Neighbour links blue, intra-session red, inter-session green.
    assert ((png[:, :, 2] == 255) & (png[:, :, 0] == 0)).any()
    assert ((png[:, :, 0] == 255) & (png[:, :, 1] == 0)).any()
    assert ((png[:, :, 1] == 160) & (png[:, :, 0] == 0)).any()


def test_cloud_ply_header_matches_body(exported):
    tmp_path, *_, summary = exported
    data = (tmp_path / "out" / "cloud.ply").read_bytes()
    head, body = data.split(b"end_header\n", 1)
    lines = head.decode().splitlines()
    assert lines[0] == "ply" and lines[1] == "format binary_little_endian 1.0"
    n = int(next(l for l in lines if l.startswith("element vertex")).split()[-1])
    assert n == summary["cloud_points"] > 0 and len(body) == n * 15


def test_missing_database_raises(tmp_path):
    with pytest.raises(DatabaseError, match="does not exist"):
        export_global_map(tmp_path / "nope.db", tmp_path / "out", Params())


def test_planted_symlinks_in_the_export_folder_are_not_followed(tmp_path, rng):
    """Issue 15 case 7: a symlink planted at each export file name, pointing at a file elsewhere."""
    make_database(tmp_path / "map.db", rng)
    out, elsewhere = tmp_path / "out", tmp_path / "elsewhere"
    out.mkdir()
    elsewhere.mkdir()
    for name in FILES:
        (elsewhere / name).write_text("not yours")
        (out / name).symlink_to(elsewhere / name)
    export_global_map(tmp_path / "map.db", out, Params())
    assert all((elsewhere / name).read_text() == "not yours" for name in FILES)
    assert all((out / name).is_file() and not (out / name).is_symlink() for name in FILES)
    assert sorted(p.name for p in out.iterdir()) == sorted(FILES)


def test_a_failed_export_removes_what_it_created(tmp_path, rng):
    make_database(tmp_path / "map.db", rng)
    # A new folder (and its missing parent) is removed when the export fails.
    out = tmp_path / "new" / "out"
    with pytest.raises(DatabaseError):
        export_global_map(tmp_path / "nope.db", out, Params())
    assert not (tmp_path / "new").exists()
    # Failing half-way in an existing folder: the files written are removed, the rest is kept.
    existing = tmp_path / "existing"
    existing.mkdir()
    (existing / "notes.txt").write_text("mine")
    (existing / "map.png").mkdir()   # map.png cannot be written: the export fails after poses.txt...
    with pytest.raises(DatabaseError, match="map.png"):
        export_global_map(tmp_path / "map.db", existing, Params())
    assert sorted(p.name for p in existing.iterdir()) == ["map.png", "notes.txt"]


# -- which parameters export uses (issue 49) ------------------------------------------------------

def _export_args(config=None, overrides=()):
    import argparse
    return argparse.Namespace(config=config, overrides=list(overrides), default_config="rtabmap.yaml")


def test_export_uses_the_parameters_stored_with_the_database_then_the_flags(tmp_path, rng):
    """A 6-DoF map exports in 6 DoF without repeating the flag; --set still overrides; the shipped
    config only when the database holds no parameters."""
    from rtabmap_ros2.cli.common_args import params_for_database
    from rtabmap_ros2.core.database import Database

    make_database(tmp_path / "map.db", rng)
    with Database(tmp_path / "map.db") as db:
        assert db.get_parameters() == {}
    params, origin = params_for_database(_export_args(), tmp_path / "map.db")
    assert params.registration.planar and "shipped rtabmap.yaml (the database holds none)" in origin
    mapped_with = Params().with_overrides(["Reg/Force3DoF=false", "Grid/Sensor=1", "grid.resolution=0.1"])
    with Database(tmp_path / "map.db") as db:
        db.set_parameters(mapped_with.to_dict())
    params, origin = params_for_database(_export_args(), tmp_path / "map.db")
    assert params == mapped_with and origin.startswith("those stored with the database")
    params, origin = params_for_database(_export_args(overrides=["Reg/Force3DoF=true"]), tmp_path / "map.db")
    assert params.registration.planar and params.grid.sensor == "depth" and "--set Reg/Force3DoF=true" in origin
    config = tmp_path / "grid.yaml"
    config.write_text("grid:\n  resolution: 0.02\n")
    params, origin = params_for_database(_export_args(config=str(config)), tmp_path / "map.db")
    assert params.grid.resolution == 0.02 and not params.registration.planar and "--config" in origin
    summary = export_global_map(tmp_path / "map.db", tmp_path / "out", params)
    assert summary["planar"] is False and summary["grid"]["sensor"] == "depth"
    assert summary["loop_closures_rejected_by_global_optimization"] == [] and "rejected_loop_closures" not in summary
