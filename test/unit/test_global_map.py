"""Global map (2014 §II-C): every node and link of a database, optimised offline."""

from __future__ import annotations

import numpy as np
import pytest

from rtabmap_ros2.core import transforms
from rtabmap_ros2.core.database import Database, SensorBlobs, WriteBatch
from rtabmap_ros2.core.global_map import assemble_global_grid, global_cloud, global_grid, load_global_map
from rtabmap_ros2.core.grid import FREE, OCCUPIED
from rtabmap_ros2.core.graph import Link, LinkType
from rtabmap_ros2.core.params import Params
from rtabmap_ros2.core.sensor import CameraModel, LaserScan
from rtabmap_ros2.core.signature import Signature
from rtabmap_ros2.io.trajectory import align_rigid

NS = 1_000_000_000
ROOM_RADIUS_M = 4.0
ODOM_SIGMA = (0.02, np.deg2rad(1.0))  # m, rad per step
LOOP_VARIANCE = 1e-4
# Camera optical frame (z forward, x right, y down) in the base frame (x forward, z up).
R_BASE_OPTICAL = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def square_path(n: int, side: float = 4.0) -> list[np.ndarray]:
    """n planar poses (4x4) walking counter-clockwise around a square of ``side`` metres."""
    perimeter = 4 * side
    poses = []
    for k in range(n):
        s = perimeter * k / n
        edge, along = int(s // side), s % side
        corners = [(0, 0), (side, 0), (side, side), (0, side)]
        x0, y0 = corners[edge]
        yaw = edge * np.pi / 2
        poses.append(transforms.from_xy_yaw(x0 + along * np.cos(yaw), y0 + along * np.sin(yaw), yaw))
    return poses


def make_database(path, rng, sessions: int = 2, n: int = 24, wrong_loop: bool = False, scans: bool = True):
    """A database of ``sessions`` sessions driving the same square, each with its own odometry frame.

    Returns ``(ground_truth poses by node id, loop closure links)``. Session 2 starts half-way
    round; each session has noisy neighbour links; every node of session k > 1 is linked to the
    node of session 1 at the same place by an exact inter-session loop closure (every 4th node),
    and session 1 closes its loop with an intra-session one. ``wrong_loop`` adds a loop closure
    whose transform is 2 m and 90 degrees off. ``scans`` False: a camera-only robot (no laser scan).
    """
    truth = square_path(n)
    T_base_camera = transforms.identity()
    T_base_camera[:3, :3] = R_BASE_OPTICAL
    T_base_camera[:3, 3] = (0.1, 0.0, 0.5)
    camera = CameraModel(20.0, 20.0, 8.0, 6.0, 16, 12, T_base_camera)
    angles = np.linspace(-np.pi, np.pi, 90, endpoint=False)
    gt: dict[int, np.ndarray] = {}
    batch = WriteBatch()
    node = 0
    first_of_session = []
    for m in range(sessions):
        shift = (m * n) // 2
        first_of_session.append(node + 1)
        T_odom = transforms.identity()
        previous = None
        for k in range(n):
            node += 1
            T_true = truth[(k + shift) % n]
            if previous is not None:
                true_step = transforms.relative(gt[node - 1], T_true)
                noise = transforms.from_xy_yaw(*rng.normal(0, ODOM_SIGMA[0], 2), rng.normal(0, ODOM_SIGMA[1]))
                step = true_step @ noise
                T_odom = T_odom @ step
                info = np.diag([1 / ODOM_SIGMA[0] ** 2] * 3 + [1 / ODOM_SIGMA[1] ** 2] * 3)
                batch.links.append(Link(node - 1, node, LinkType.NEIGHBOR, step, info))
            gt[node] = T_true
            scan = LaserScan(np.full(90, ROOM_RADIUS_M + 0.3 * np.cos(3 * angles), np.float32), -np.pi,
                             2 * np.pi / 90, 0.1, 10.0)
            sig = Signature(id=node, map_id=m, stamp_ns=(m * 1000 + k) * NS, T_odom_base=T_odom.copy(),
                            scan=scan if scans else None, camera=camera)
            rgb = np.full((12, 16, 3), 40 * (m + 1), np.uint8)
            depth = np.full((12, 16), 2.0, np.float32)
            batch.locations.append((sig, SensorBlobs.encode(rgb, depth)))
            previous = node
    loops = []
    info = np.eye(6) / LOOP_VARIANCE
    # Intra-session loop closure of session 1 (last node back near the first).
    loops.append(Link(1, n, LinkType.LOOP_INTRA, transforms.relative(gt[1], gt[n]), info))
    for m in range(1, sessions):
        for k in range(0, n, 4):
            a = first_of_session[m] + k
            b = 1 + (k + (m * n) // 2) % n
            loops.append(Link(b, a, LinkType.LOOP_INTER, transforms.relative(gt[b], gt[a]), info))
    if wrong_loop:
        bad = transforms.relative(gt[3], gt[n // 2 + 3]) @ transforms.from_xy_yaw(2.0, 0.0, np.pi / 2)
        loops.append(Link(3, n // 2 + 3, LinkType.LOOP_INTRA, bad, info))
    batch.links.extend(loops)
    with Database(path) as db:
        db.write(batch)
    return gt, loops


def aligned_error(poses: dict[int, np.ndarray], gt: dict[int, np.ndarray]) -> float:
    """Max position error (m) after one rigid alignment of ``poses`` on the ground truth."""
    ids = sorted(gt)
    est = np.array([poses[i][:3, 3] for i in ids])
    ref = np.array([gt[i][:3, 3] for i in ids])
    T = align_rigid(est, ref)
    return float(np.max(np.linalg.norm(est @ T[:3, :3].T + T[:3, 3] - ref, axis=1)))


@pytest.fixture
def params():
    return Params().with_value("registration.planar", True)   # make_database's robot moves on a plane


def test_two_sessions_merge_into_one_component_rooted_at_newest(tmp_path, rng, params):
    gt, _ = make_database(tmp_path / "map.db", rng)
    gmap = load_global_map(tmp_path / "map.db", params)
    assert len(gmap.components) == 1 and len(gmap.components[0]) == len(gt)
    assert gmap.planar  # registration.planar
    newest = max(gt)
    assert gmap.roots == [newest]
    # Root at its odometry pose: the map frame is the last session's odometry frame.
    np.testing.assert_allclose(gmap.poses[newest], gmap.odom_poses[newest], atol=1e-6)
    assert gmap.links_by_type["loop_inter"] > 0 and gmap.links_by_type["neighbor"] == len(gt) - 2
    assert set(gmap.map_ids.values()) == {0, 1}
    # Exact loop closures pull the noisy odometry onto the ground truth (a few cm).
    assert aligned_error(gmap.poses, gt) < 0.1
    odom_error = aligned_error(gmap.odom_poses, {i: gt[i] for i in gt if gmap.map_ids[i] == 0})
    assert aligned_error(gmap.poses, gt) < odom_error
    assert gmap.chi2_final < gmap.chi2_initial


def test_unconnected_session_is_its_own_component(tmp_path, rng, params):
    gt, loops = make_database(tmp_path / "map.db", rng)
    with Database(tmp_path / "map.db") as db:
        db.write(WriteBatch(deleted_links=[(l.from_id, l.to_id) for l in loops if l.type is LinkType.LOOP_INTER]))
    gmap = load_global_map(tmp_path / "map.db", params)
    assert sorted(len(c) for c in gmap.components) == [len(gt) // 2, len(gt) // 2]
    assert len(gmap.optimizations) == 2 and len(gmap.poses) == len(gt)
    # Each component rooted at its own newest node's odometry pose.
    for comp, root in zip(gmap.components, gmap.roots):
        assert root == max(comp)
        np.testing.assert_allclose(gmap.poses[root], gmap.odom_poses[root], atol=1e-6)


def test_wrong_loop_closure_in_database_is_rejected_by_robust_option(tmp_path, rng, params):
    gt, _ = make_database(tmp_path / "map.db", rng, wrong_loop=True)
    n = len(gt) // 2
    robust = load_global_map(tmp_path / "map.db", params)
    assert [(l.from_id, l.to_id) for l in robust.rejected] == [(3, n // 2 + 3)]
    assert all(l.key() != (3, n // 2 + 3) for l in robust.links)
    assert aligned_error(robust.poses, gt) < 0.1
    plain = load_global_map(tmp_path / "map.db", params.with_value("graph.robust", False))
    assert not plain.rejected
    assert aligned_error(plain.poses, gt) > 3 * aligned_error(robust.poses, gt)


def test_database_is_opened_read_only(tmp_path, rng, params):
    make_database(tmp_path / "map.db", rng)
    before = (tmp_path / "map.db").read_bytes()
    gmap = load_global_map(tmp_path / "map.db", params)
    with Database(tmp_path / "map.db", read_only=True) as db:
        global_grid(gmap, db, params)
        global_cloud(gmap, db, params)
    assert (tmp_path / "map.db").read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["map.db"]


def test_grid_and_cloud_at_optimised_poses(tmp_path, rng, params):
    gt, _ = make_database(tmp_path / "map.db", rng)
    gmap = load_global_map(tmp_path / "map.db", params)
    with Database(tmp_path / "map.db", read_only=True) as db:
        grid = global_grid(gmap, db, params)
        points, colors = global_cloud(gmap, db, params)
    # Every node's own position was crossed by beams: free; the ring of walls is occupied.
    xy = np.array([gmap.poses[i][:2, 3] for i in gmap.poses])
    assert np.all(grid.value_at(xy) == 0)
    assert (grid.data == 100).sum() > 50
    assert len(points) > 0 and points.shape == colors.shape and colors.dtype == np.uint8
    # A wall 2 m in front of the camera (0.5 m high, fy 20 px, cy 6 px); decimation 4 keeps image
    # rows 0, 4, 8: z = 0.5 + (6 - v) / 20 * 2 = 1.1, 0.7, 0.3 m (top row highest: optical y down).
    np.testing.assert_allclose(sorted(set(np.round(points[:, 2], 2).tolist())), [0.3, 0.7, 1.1], atol=0.02)


@pytest.mark.slow
def test_simulated_two_sessions_merge_into_one_map(tmp_path):
    """The 2 small simulated sessions through Rtabmap (in memory): one component, inter-session loops."""
    from rtabmap_ros2.core.params import default_config_path
    from rtabmap_ros2.core.rtabmap import Rtabmap
    from rtabmap_ros2.sim import build_world, make_sessions, session_frames

    params = Params.from_yaml(default_config_path())
    world = build_world(seed=0)
    sessions = make_sessions(world, small=True)
    with Rtabmap(params, tmp_path / "sim.db") as rtabmap:
        for k, session in enumerate(sessions):
            if k:
                rtabmap.trigger_new_map()
            for frame in session_frames(world, session):
                rtabmap.process(frame)
    gmap = load_global_map(tmp_path / "sim.db", params)
    assert len(gmap.components) == 1
    assert set(gmap.map_ids.values()) == {0, 1}
    assert gmap.links_by_type["loop_inter"] > 0
    # Positions against the ground truth after one rigid alignment for both sessions.
    from rtabmap_ros2.io.trajectory import Trajectory, ate

    truth = Trajectory(np.concatenate([s.stamps_ns for s in sessions]),
                       np.concatenate([s.T_world_base for s in sessions]))
    ids = sorted(gmap.poses)
    est = Trajectory(np.array([gmap.stamps_ns[i] for i in ids]), np.stack([gmap.poses[i] for i in ids]))
    assert ate(est, truth).rmse_m < 0.3


def test_false_inter_session_loops_at_the_root_do_not_shape_the_guess(tmp_path, rng, params):
    """Three mutually consistent false loop closures (a look-alike place 10 m away) from the
    newest nodes to the first session are all rejected. (On this small graph DCS also recovers
    from the plain breadth-first guess; the consensus guess was needed on the simulated 5
    sessions, see bench/bench_slam.py.)"""
    gt, _ = make_database(tmp_path / "map.db", rng)
    newest = max(gt)
    offset = transforms.from_xy_yaw(10.0, 0.0, 0.5)
    bad = [Link(newest - k, 1 + k, LinkType.LOOP_INTER,
                transforms.relative(gt[newest - k], offset @ gt[1 + k]), np.eye(6) / LOOP_VARIANCE)
           for k in range(3)]
    with Database(tmp_path / "map.db") as db:
        db.write(WriteBatch(links=bad))
    gmap = load_global_map(tmp_path / "map.db", params)
    assert sorted(l.key() for l in gmap.rejected) == sorted(l.key() for l in bad)
    assert aligned_error(gmap.poses, gt) < 0.1


# -- what the grid is made from (grid.sensor) -------------------------------------------------------

def _grid(path, params):
    gmap = load_global_map(path, params)
    with Database(path, read_only=True) as db:
        return gmap, assemble_global_grid(gmap, db, params)


def test_a_laser_robot_grid_comes_from_its_scans_by_default(tmp_path, rng, params):
    make_database(tmp_path / "map.db", rng)
    gmap, result = _grid(tmp_path / "map.db", params)
    assert (result.sensor, result.laser_nodes, result.depth_nodes) == ("auto", len(gmap.poses), 0)
    laser_only = _grid(tmp_path / "map.db", params.with_value("Grid/Sensor", 0))[1]
    np.testing.assert_array_equal(result.grid.data, laser_only.grid.data)
    both = _grid(tmp_path / "map.db", params.with_value("Grid/Sensor", 2))[1]
    assert both.laser_nodes == both.depth_nodes == len(gmap.poses) and not both.empty_reason


def test_a_camera_only_map_gets_its_grid_from_the_depth_images(tmp_path, rng, params):
    """No laser: the depth images (2 m ahead of a camera 0.5 m up) make walls and free floor, not an
    empty 1x1 grid."""
    make_database(tmp_path / "map.db", rng, scans=False)
    gmap, result = _grid(tmp_path / "map.db", params)
    assert (result.laser_nodes, result.depth_nodes, result.empty_reason) == (0, len(gmap.poses), "")
    assert result.grid.width > 10 and (result.grid.data == OCCUPIED).any() and (result.grid.data == FREE).any()
    assert "depth images of" in result.source()
    # What the node's get_map and the report use is the same grid.
    with Database(tmp_path / "map.db", read_only=True) as db:
        np.testing.assert_array_equal(global_grid(gmap, db, params).data, result.grid.data)


def test_an_empty_grid_says_why(tmp_path, rng, params, caplog):
    make_database(tmp_path / "map.db", rng, scans=False)
    gmap, result = _grid(tmp_path / "map.db", params.with_value("Grid/Sensor", 0))
    assert result.grid.width == result.grid.height == 1 and result.laser_nodes == result.depth_nodes == 0
    assert "Grid/Sensor" in result.empty_reason and "laser scan" in result.empty_reason
    assert any("occupancy grid is empty" in r.message and r.levelname == "WARNING" for r in caplog.records)
    # Depth points all out of reach: the reason names range and heights.
    far = params.with_value("grid.range_max", 1.0)
    assert "grid.range_max (1 m)" in _grid(tmp_path / "map.db", far)[1].empty_reason


def test_planar_follows_the_parameter_whatever_the_sensors(tmp_path, rng, params):
    """Reg/Force3DoF as in RTAB-Map: applied as given, with or without a laser."""
    make_database(tmp_path / "map.db", rng, scans=False)
    assert load_global_map(tmp_path / "map.db", params).planar
    assert not load_global_map(tmp_path / "map.db", params.with_value("Reg/Force3DoF", False)).planar
