"""The online local map (core/local_map.py): neighbour link refining, consensus guess, the poses
kept for nodes that left it, a part of the map coming back."""

from __future__ import annotations

import numpy as np
import pytest

from corridor_sessions import ODOM_INFO, corridor_scan, inter_link, two_corridor_sessions
from rtabmap_ros2.core import transforms
from rtabmap_ros2.core.graph import Link, LinkType, consensus_guess, default_information
from rtabmap_ros2.core.params import Params, RegistrationParams
from rtabmap_ros2.core.registration import refine_neighbor_link
from rtabmap_ros2.core.rtabmap import Rtabmap
from rtabmap_ros2.core.sensor import LaserScan, SensorFrame
from rtabmap_ros2.errors import RegistrationError
from rtabmap_ros2.sim.sequence import make_sequence


def scan_of_walls(T_world_base: np.ndarray, walls: list[tuple[tuple[float, float], tuple[float, float]]],
                  rng: np.random.Generator, noise: float = 0.005) -> LaserScan:
    """A 240 deg scan (0.5 deg) of wall segments seen from a pose, with range noise."""
    angles = np.deg2rad(np.arange(-120.0, 120.0, 0.5))
    x, y, yaw = transforms.to_xy_yaw(T_world_base)
    ranges = np.full(angles.size, np.inf)
    dirs = np.stack([np.cos(angles + yaw), np.sin(angles + yaw)], axis=1)
    for (ax, ay), (bx, by) in walls:
        e = np.array([bx - ax, by - ay])
        for i, d in enumerate(dirs):
            M = np.array([[d[0], -e[0]], [d[1], -e[1]]])
            if abs(np.linalg.det(M)) < 1e-12:
                continue
            t, u = np.linalg.solve(M, np.array([ax - x, ay - y]))
            if t > 0 and 0 <= u <= 1:
                ranges[i] = min(ranges[i], t)
    ranges = ranges + rng.normal(0, noise, ranges.size)
    return LaserScan(ranges.astype(np.float32), float(angles[0]), float(np.deg2rad(0.5)), 0.1, 30.0)


ROOM = [((-3, -2), (4, -2)), ((4, -2), (4, 3)), ((4, 3), (-3, 3)), ((-3, 3), (-3, -2)),
        ((1, 0.5), (2, 0.5)), ((1, 0.5), (1, 1.5))]
CORRIDOR = [((-20, -1), (20, -1)), ((-20, 1), (20, 1))]


def test_refined_neighbor_link_is_closer_to_the_truth_than_odometry(rng):
    truth = transforms.from_xy_yaw(0.5, 0.05, np.deg2rad(4.0))
    previous = scan_of_walls(transforms.identity(), ROOM, rng)
    new = scan_of_walls(truth, ROOM, rng)
    odometry = truth @ transforms.from_xy_yaw(0.03, -0.02, np.deg2rad(0.8))  # drifted odometry
    T, info = refine_neighbor_link(previous.points_base(), new, odometry, ODOM_INFO, RegistrationParams())
    err = transforms.relative(truth, T)
    assert np.linalg.norm(err[:2, 3]) < 0.01
    assert abs(transforms.yaw_of(err)) < np.deg2rad(0.1)
    # The scans add information on x, y, yaw; z, roll, pitch keep the odometry's.
    assert info[0, 0] > ODOM_INFO[0, 0] and info[5, 5] > ODOM_INFO[5, 5]
    assert info[2, 2] == ODOM_INFO[2, 2]


def test_corridor_direction_the_scans_cannot_see_stays_on_odometry(rng):
    """Two parallel walls constrain y and yaw, not x: x must come from the odometry prior."""
    truth = transforms.from_xy_yaw(0.5, 0.0, 0.0)
    previous = scan_of_walls(transforms.identity(), CORRIDOR, rng)
    new = scan_of_walls(truth, CORRIDOR, rng)
    odometry = transforms.from_xy_yaw(0.53, 0.04, np.deg2rad(1.0))
    T, info = refine_neighbor_link(previous.points_base(), new, odometry, ODOM_INFO, RegistrationParams())
    assert abs(T[0, 3] - 0.53) < 0.005  # along the corridor: odometry
    assert abs(T[1, 3] - 0.0) < 0.01  # across: the walls
    assert abs(transforms.yaw_of(T)) < np.deg2rad(0.2)
    assert info[1, 1] > 10 * info[0, 0]  # the information says so too


def test_turn_with_overconfident_odometry_follows_the_scans(rng):
    """Wheel odometry stating 0.13 deg on a 34 deg turn it got 2 deg wrong (as the simulated
    robot's, and any robot publishing a fixed covariance): the scans must win, and the link's
    information must not claim the odometry's precision for a yaw it got wrong."""
    truth = transforms.from_xy_yaw(0.33, 0.10, np.deg2rad(34.4))
    previous = scan_of_walls(transforms.identity(), ROOM, rng)
    new = scan_of_walls(truth, ROOM, rng)
    odometry = truth @ transforms.from_xy_yaw(0.0, 0.0, np.deg2rad(-2.0))
    overconfident = np.diag(1.0 / np.array([2e-5, 2e-5, 1e-6, 1e-6, 1e-6, np.deg2rad(0.13) ** 2]))
    T, info = refine_neighbor_link(previous.points_base(), new, odometry, overconfident, RegistrationParams())
    err = transforms.relative(truth, T)
    assert abs(transforms.yaw_of(err)) < np.deg2rad(0.2)
    assert np.linalg.norm(err[:2, 3]) < 0.01
    yaw_std = np.sqrt(np.linalg.inv(info[np.ix_([0, 1, 5], [0, 1, 5])])[2, 2])
    assert abs(transforms.yaw_of(err)) < 4 * yaw_std  # the stated precision covers the error


def test_odometry_error_within_its_noise_does_not_leak_into_a_well_constrained_link(rng):
    """Wheel odometry errors are systematic (a wheel base slightly off gives the same yaw error on
    every step): where the scans constrain the motion, the link must not depend on the odometry,
    or a fraction of that error stays in every link and adds up along a session."""
    truth = transforms.from_xy_yaw(0.5, 0.05, np.deg2rad(4.0))
    previous = scan_of_walls(transforms.identity(), ROOM, rng)
    new = scan_of_walls(truth, ROOM, rng)
    info = np.diag(1.0 / np.array([1e-4, 1e-4, 1e-6, 1e-6, 1e-6, np.deg2rad(0.13) ** 2]))
    odometry = [truth @ transforms.from_xy_yaw(0.01 * s, 0.0, np.deg2rad(0.2 * s)) for s in (-1, 1)]
    links = [refine_neighbor_link(previous.points_base(), new, T, info, RegistrationParams())[0] for T in odometry]
    difference = transforms.relative(*links)
    # Odometry 0.4 deg and 2 cm apart (each within 2 sigma); averaging it in moved the link 0.04 deg.
    assert abs(transforms.yaw_of(difference)) < np.deg2rad(0.005)
    assert np.linalg.norm(difference[:2, 3]) < 0.001


HALL = [((-8, -4), (4, -4)), ((4, -4), (4, 4)), ((4, 4), (-8, 4)), ((-8, 4), (-8, -4)),
        ((-3, -1), (-1, -1)), ((-3, -1), (-3, 0.5))]


def drive_circle_in_hall(tmp_path, scan_map_nodes: int, steps: int = 60) -> float:
    """Rtabmap fed odometry and scans only, driving a 3.2 m circle in HALL (laser noise 1 cm);
    returns the yaw error (deg) of the last node when the neighbour links are chained."""
    rng = np.random.default_rng(1)
    params = Params().with_overrides(["registration.planar=true", "registration.neighbor_link_refining=true",
                                      f"registration.neighbor_scan_map_nodes={scan_map_nodes}"])
    covariance = np.diag([1e-4, 1e-4, 1e-6, 1e-6, 1e-6, np.deg2rad(0.13) ** 2])
    step = transforms.from_xy_yaw(0.5, 0.0, np.deg2rad(9.0))
    odometry_error = transforms.from_xy_yaw(0.0, 0.0, np.deg2rad(0.15))  # a wheel base slightly off
    truth, odometry, ids = [transforms.identity()], [transforms.identity()], []
    for _ in range(steps - 1):
        truth.append(truth[-1] @ step)
        odometry.append(odometry[-1] @ step @ odometry_error)
    with Rtabmap(params, tmp_path / f"circle{scan_map_nodes}.db") as rtabmap:
        for k in range(steps):
            frame = SensorFrame(stamp_ns=(k + 1) * 10 ** 9, T_odom_base=odometry[k], odom_covariance=covariance,
                                scan=scan_of_walls(truth[k], HALL, rng, noise=0.01))
            ids.append(rtabmap.process(frame).location_id)
        chained = transforms.identity()
        for a, b in zip(ids, ids[1:]):
            chained = chained @ rtabmap.memory.graph.link(a, b).T_from_to
    return abs(np.degrees(transforms.yaw_of(transforms.relative(truth[-1], chained))))


def test_matching_the_last_nodes_scans_drifts_less_than_the_previous_scan_alone(tmp_path):
    """Scan-to-scan errors add up link after link (here about 1.2 deg of heading over a 30 m
    circle); against the last 10 scans assembled, each link is tied to what the robot saw over
    the last metres and the heading drifts several times less."""
    scan_to_scan = drive_circle_in_hall(tmp_path, 1)
    scan_map = drive_circle_in_hall(tmp_path, 10)
    assert scan_map < 0.4 * scan_to_scan
    assert scan_map < 0.5


def test_refinement_refused_when_scans_do_not_overlap(rng):
    previous = scan_of_walls(transforms.identity(), ROOM, rng)
    elsewhere = scan_of_walls(transforms.identity(), [((10, 10), (11, 10))], rng)
    with pytest.raises(RegistrationError, match="overlap"):
        refine_neighbor_link(previous.points_base(), elsewhere, transforms.identity(), ODOM_INFO, RegistrationParams())


def chain(ids, step=1.0):
    info = default_information(1e-3)
    return [Link(a, b, LinkType.NEIGHBOR, transforms.from_xy_yaw(step, 0, 0), info) for a, b in zip(ids, ids[1:])]


def test_consensus_guess_ignores_a_false_inter_session_loop_closure_outvoted_by_true_ones():
    """Session A = nodes 1..10, session B = 11..20 drives the same corridor 0.5 m to the side.

    One false loop closure (found first, 15 m off) and three true ones: the guess follows the
    true ones, whatever the order the links come in.
    """
    info = default_information(1e-3)
    side = transforms.from_xy_yaw(0.0, 0.5, 0.0)
    true = [Link(10 + k, k, LinkType.LOOP_INTER, transforms.inverse(side), info) for k in (3, 5, 7)]
    false = [Link(12, 2, LinkType.LOOP_INTER, transforms.from_xy_yaw(-15.0, 0, 0), info)]
    links = chain(range(1, 11)) + chain(range(11, 21)) + false + true
    guess = consensus_guess(20, transforms.from_xy_yaw(9.0, 0.5, 0.0), links)
    for k in range(1, 11):
        np.testing.assert_allclose(guess[k][:3, 3], [k - 1.0, 0.0, 0.0], atol=1e-9)


def test_poses_kept_for_nodes_that_left_the_local_map_stay_consistent_as_its_frame_moves(tmp_path):
    """Each local map solution is rooted at its newest node's odometry pose, so its frame moves
    from one solution to the next; the poses kept for nodes that left it (transferred to LTM)
    must still be placed right relative to each other and to the map, or no two loop closures to
    that map agree on a merge."""
    rtabmap = Rtabmap(Params(), tmp_path / "frames.db")
    truth = {n: transforms.from_xy_yaw(1.0 * n, 0.2 * n * n / 10, 0.1 * n) for n in range(1, 8)}

    def seen(nodes, frame):  # a solution holding ``nodes``, in a frame ``frame`` away from the truth's
        return {n: frame @ truth[n] for n in nodes}

    rtabmap.local.poses = seen([1, 2, 3, 4], transforms.identity())
    moves = [transforms.from_xy_yaw(0.3, -0.2, 0.05), transforms.from_xy_yaw(-1.0, 0.5, -0.4),
             transforms.from_xy_yaw(2.0, 1.0, 1.2)]
    for step, (nodes, frame) in enumerate(zip([[2, 3, 4, 5], [3, 4, 5, 6], [5, 6, 7]], moves)):
        if step == 1:
            rtabmap._forget([2], transferred_to_ltm=True)
        poses = seen(nodes, frame)
        rtabmap.local.follow_local_frame(poses, rigid=step == 0)
        rtabmap.local.poses = poses
    for a, b in [(1, 2), (1, 4), (2, 7), (4, 6), (3, 7)]:
        np.testing.assert_allclose(transforms.relative(rtabmap.local.map_pose(a), rtabmap.local.map_pose(b)),
                                   transforms.relative(truth[a], truth[b]), atol=1e-9)
    rtabmap.close()


def test_an_old_sessions_kept_poses_are_not_rewritten_by_a_later_sessions_local_map(tmp_path):
    """A part of an old map in WM, joined to the rest only through LTM, follows whatever the
    current session's loop closures say (a false one moves it without tension): leaving the
    local map again, its nodes keep the pose their own session gave them."""
    rtabmap = Rtabmap(Params(), tmp_path / "frames.db")
    memory = rtabmap.memory
    for node in (1, 2, 3):
        memory.map_ids.add(node, 0)
    for node in (10, 11):
        memory.map_ids.add(node, 1)
    truth = {n: transforms.from_xy_yaw(1.0 * n, 0.0, 0.0) for n in (1, 2, 3, 10, 11)}
    memory.map_id = 0
    rtabmap.local.poses = {n: truth[n] for n in (1, 2, 3)}
    rtabmap.local.follow_local_frame({3: truth[3]}, rigid=False)  # session 0's nodes 1 and 2 leave
    rtabmap.local.poses = {3: truth[3]}
    kept = rtabmap.local.map_pose(2).copy()
    memory.map_id = 1  # session 1: node 2 comes back, bent 26 m by a false loop closure, and leaves
    bent = transforms.from_xy_yaw(26.0, 0.0, 0.0) @ truth[2]
    rtabmap.local.follow_local_frame({2: bent, 10: truth[10]}, rigid=False)
    rtabmap.local.poses = {2: bent, 10: truth[10]}
    np.testing.assert_allclose(rtabmap.local.map_pose(2), kept)
    rtabmap.local.follow_local_frame({10: truth[10], 11: truth[11]}, rigid=False)
    rtabmap.local.poses = {10: truth[10], 11: truth[11]}
    np.testing.assert_allclose(rtabmap.local.map_pose(2), kept)
    # The session being mapped keeps its nodes' latest poses.
    rtabmap.local.follow_local_frame({11: truth[11]}, rigid=False)
    np.testing.assert_allclose(transforms.relative(rtabmap.local.map_pose(10), rtabmap.local.map_pose(11)),
                               transforms.relative(truth[10], truth[11]), atol=1e-9)
    rtabmap.close()


def test_a_part_of_the_map_coming_back_into_the_local_map_starts_at_its_kept_poses(tmp_path):
    """Session 0 left the local map (its nodes have kept poses); a loop closure from session 1
    (33 -> 3) joins it again. Nodes 13-17 are in LTM, so in WM its two parts are joined only by
    loop closures: a true one (10 -> 20) and a false one the robust kernel had rejected (3 -> 25,
    1 m instead of 11 m). Chained from the last solution through the first link that reaches
    them, nodes 18-30 started 10 m off and the robust kernel then kept the false link and dropped
    the true one. The re-solve starts from the kept poses and gives session 0 its geometry back
    (30 sessions, WM 2,700: 2,500 nodes started tens of metres off, the solution settled there and
    134 true loop closures were then rejected)."""
    rtabmap = two_corridor_sessions(tmp_path)
    try:
        rtabmap.local.params = rtabmap.params.with_value("graph.robust", True)
        memory = rtabmap.memory
        truth = {1 + k: transforms.from_xy_yaw(0.5 * k, 0.0, 0.0) for k in range(30)}
        truth.update({31 + k: transforms.from_xy_yaw(0.5 * k, 0.5, 0.0) for k in range(30)})
        memory.add_loop_closure(Link(10, 20, LinkType.LOOP_INTRA, transforms.relative(truth[10], truth[20]), ODOM_INFO))
        memory.add_loop_closure(Link(3, 25, LinkType.LOOP_INTRA, transforms.from_xy_yaw(1.0, 0.0, 0.0), ODOM_INFO))
        for node in range(13, 18):  # in LTM
            del memory.signatures[node]
            memory.wm.pop(node, None)
        memory.map_id = 1
        # The world frame of the kept poses is not the local map's: the solutions' frames move.
        rtabmap.local.T_world_local = transforms.from_xy_yaw(3.0, -2.0, 0.7)
        to_local = transforms.inverse(rtabmap.local.T_world_local)
        rtabmap.local.kept_poses.update({n: truth[n] for n in range(1, 31) if n in memory.signatures})
        rtabmap.local.poses = {n: to_local @ truth[n] for n in range(31, 56)}
        memory.add_loop_closure(inter_link(33, 3))
        poses, _ = rtabmap.local.optimize_component(55)
        assert set(range(18, 31)) <= set(poses)
        for a, b in [(1, 30), (3, 25), (10, 20), (25, 55), (1, 55)]:
            error = transforms.relative(transforms.relative(poses[a], poses[b]), transforms.relative(truth[a], truth[b]))
            assert np.linalg.norm(error[:3, 3]) < 0.05, (a, b, error[:3, 3])
    finally:
        rtabmap.close()


def test_local_map_after_a_rehearsal_merge_and_a_failed_optimisation(tmp_path):
    # The robot drives 5 nodes, a loop closure with a corrupt (NaN) information matrix makes every
    # optimisation fail from then on, and the robot stops: the next location is merged into by
    # rehearsal into the previous one (same image, same pose). The local map keeps its last
    # solution, without the location that no longer exists (it raised KeyError).
    sequence = make_sequence(6, seed=1)
    with Rtabmap(Params(), tmp_path / "m.db") as rtabmap:
        for k in range(5):
            rtabmap.process(SensorFrame(k * 10**9, transforms.from_xy_yaw(0.5 * k, 0, 0), rgb=sequence.image(k)))
        memory = rtabmap.memory
        before = rtabmap.local_map()
        last = max(before.poses)
        first = min(before.poses)
        memory.add_loop_closure(Link(last, first, LinkType.LOOP_INTRA, transforms.relative(
            before.poses[last], before.poses[first]), np.full((6, 6), np.nan)))
        stats = rtabmap.process(SensorFrame(5 * 10**9, transforms.from_xy_yaw(2.0, 0, 0), rgb=sequence.image(4)))
        assert stats.merged_id == last + 1 and stats.location_id == last  # the older location stays
        local = rtabmap.local_map()
        assert last + 1 not in local.poses and set(local.poses) == set(before.poses)
        assert set(local.map_ids) == set(local.poses) <= set(memory.signatures)
        assert all(l.from_id in local.poses and l.to_id in local.poses for l in local.links)
        for node, pose in local.poses.items():
            np.testing.assert_allclose(pose, before.poses[node])


def test_a_bounded_local_grid_update_puts_the_robots_surroundings_right_first_then_converges(tmp_path):
    """The live node bounds the scans cast per local grid update: after a loop closure moved the
    whole map (here 30 nodes by 0.3 m), the first update recasts the nodes nearest the robot, and
    the next ones the rest, until the grid equals casting every scan at its new pose."""
    from rtabmap_ros2.core.grid import GridAccumulator

    rtabmap = two_corridor_sessions(tmp_path)
    try:
        local = rtabmap.local
        local.params = rtabmap.params.with_value("grid.range_max", 2.0)  # each scan touches cells within 2 m
        scans = {1 + k: corridor_scan(0.5 * k, 0.0) for k in range(30)}
        for node, scan in scans.items():
            rtabmap.memory.signatures[node].scan = scan
        old = {node: transforms.from_xy_yaw(0.5 * (node - 1), 0.0, 0.0) for node in scans}
        local.poses = dict(old)
        local.grid(max_casts=100)
        assert local.grid_pending == 0
        new = {node: transforms.from_xy_yaw(0.3, 0.0, 0.0) @ T for node, T in old.items()}
        local.poses = dict(new)
        reference = GridAccumulator(local.params.grid)   # the same casts, in one go
        for node in scans:
            reference.add(old[node], scans[node])
        for node in scans:
            reference.add(old[node], scans[node], weight=-1)
            reference.add(new[node], scans[node])
        expected = reference.grid()
        xs = np.arange(-3.0, 18.0, 0.05) + 0.025
        ys = np.arange(-1.5, 2.0, 0.05) + 0.025
        points = np.stack(np.meshgrid(xs, ys), axis=-1).reshape(-1, 2)
        near_robot = points[:, 0] >= 15.5     # only nodes 28-30 (the nearest) cast there
        far = points[:, 0] <= 3.0
        first = local.grid(max_casts=10)      # a moved node costs 2 casts: the 5 nearest
        assert local.grid_pending == 25
        assert np.array_equal(first.value_at(points[near_robot]), expected.value_at(points[near_robot]))
        assert not np.array_equal(first.value_at(points[far]), expected.value_at(points[far]))
        calls = 1
        while local.grid_pending:
            grid = local.grid(max_casts=10)
            calls += 1
        assert calls == 6
        assert np.array_equal(grid.value_at(points), expected.value_at(points))
    finally:
        rtabmap.close()


def test_a_camera_only_local_map_has_an_occupancy_grid_from_its_depth_images(tum_rpy_folder, tmp_path):
    """No laser: each node keeps its depth image's points and the local grid is drawn from them
    (grid.sensor auto), also for nodes that come back from the database (a reopened map), a few a
    frame; with grid.sensor laser nothing is kept and there is no local grid."""
    from dataclasses import replace

    from rtabmap_ros2.core.grid import FREE, OCCUPIED
    from rtabmap_ros2.core.rtabmap import DEPTH_POINTS_LOADS_PER_FRAME
    from rtabmap_ros2.io.datasets import TumRgbdDataset

    data = TumRgbdDataset(tum_rpy_folder(10))
    frames = [replace(f, T_odom_base=T) for f, T in zip(data, data.ground_truth())]
    params = Params().with_value("registration.planar", False)
    path = tmp_path / "camera.db"
    with Rtabmap(params, path) as rtabmap:
        for f in frames[:7]:
            rtabmap.process(f)
        signatures = list(rtabmap.memory.signatures.values())
        assert len(signatures) >= 5 and all(s.scan is None and s.depth_points is not None for s in signatures)
        grid = rtabmap.local_grid()
        assert grid is not None and (grid.data == OCCUPIED).sum() > 20 and (grid.data == FREE).sum() > 100
        assert set(rtabmap.local_map().depth) == set(rtabmap.local_map().poses)
    with Rtabmap(params, path) as again:          # WM back from the database, without the points
        old = sorted(again.memory.signatures)
        assert all(again.memory.signatures[n].depth_points is None for n in old)
        again.process(frames[7])
        loaded = [n for n in old if again.memory.signatures[n].depth_points is not None]
        assert loaded == old[-DEPTH_POINTS_LOADS_PER_FRAME:]          # the newest first, a few a frame
        for f in frames[8:10]:
            again.process(f)
        assert all(again.memory.signatures[n].depth_points is not None for n in old)
    laser_only = Params().with_value("registration.planar", False).with_value("grid.sensor", "laser")
    with Rtabmap(laser_only, tmp_path / "laser_only.db") as rtabmap:
        for f in frames[:3]:
            rtabmap.process(f)
        assert all(s.depth_points is None for s in rtabmap.memory.signatures.values())
        assert rtabmap.local_grid() is None
