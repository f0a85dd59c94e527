"""The online local map's defences: neighbour link refining, consensus guess, max error check."""

from __future__ import annotations

import numpy as np
import pytest

from rtabmap_ros2.core import transforms
from rtabmap_ros2.core.graph import Link, LinkType, consensus_guess, default_information
from rtabmap_ros2.core.params import Params, RegistrationParams
from rtabmap_ros2.core.registration import refine_neighbor_link
from rtabmap_ros2.core.rtabmap import Rtabmap, _judged_links, _max_error_ratio
from rtabmap_ros2.core.sensor import LaserScan, SensorFrame
from rtabmap_ros2.errors import RegistrationError

ODOM_INFO = np.diag(1.0 / np.array([1e-4, 1e-4, 1e-6, 1e-6, 1e-6, 1e-5]))


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
    params = Params().with_overrides(["registration.neighbor_link_refining=true",
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


def test_max_error_ratio_flags_a_link_bent_beyond_its_standard_deviation():
    info = np.diag(1.0 / np.array([1e-4, 1e-4, 1e-4, 1e-4, 1e-4, 1e-4]))  # sigma 1 cm, 0.57 deg
    link = Link(1, 2, LinkType.NEIGHBOR, transforms.from_xy_yaw(1.0, 0, 0), info)
    poses = {1: transforms.identity(), 2: transforms.from_xy_yaw(1.02, 0, 0)}
    assert _max_error_ratio(poses, [link], planar=True) == pytest.approx(2.0, rel=1e-6)
    poses[2] = transforms.from_xy_yaw(1.0, 0, np.deg2rad(2.0))
    assert _max_error_ratio(poses, [link], planar=True) == pytest.approx(np.deg2rad(2.0) / 0.01, rel=1e-3)


def test_max_error_ratio_counts_an_old_strain_only_by_how_far_the_new_loop_closures_moved_it():
    """A link already 3.1 std devs off before the frame's loop closure (a 2,000-link local map has
    a few) does not make a true loop closure that moves it by 0.2 look wrong; a link the loop
    closure bends from 0 to 5 std devs, and the new loop closure's own error, still count."""
    info = np.diag(1.0 / np.array([1e-4, 1e-4, 1e-4, 1e-4, 1e-4, 1e-4]))  # sigma 1 cm
    strained = Link(1, 2, LinkType.NEIGHBOR, transforms.from_xy_yaw(1.0, 0, 0), info)
    loop = Link(2, 3, LinkType.LOOP_INTER, transforms.from_xy_yaw(1.0, 0, 0), info)
    before = {1: transforms.identity(), 2: transforms.from_xy_yaw(1.031, 0, 0), 3: transforms.from_xy_yaw(2.031, 0, 0)}
    after = {1: transforms.identity(), 2: transforms.from_xy_yaw(1.033, 0, 0), 3: transforms.from_xy_yaw(2.033, 0, 0)}
    assert _max_error_ratio(after, [strained, loop], planar=True) == pytest.approx(3.3, rel=1e-6)
    assert _max_error_ratio(after, [strained, loop], planar=True, before=before,
                            new={loop.key()}) == pytest.approx(0.2, abs=1e-6)
    bent = {**after, 2: transforms.from_xy_yaw(1.081, 0, 0), 3: transforms.from_xy_yaw(2.081, 0, 0)}
    assert _max_error_ratio(bent, [strained, loop], planar=True, before=before,
                            new={loop.key()}) == pytest.approx(5.0, rel=1e-6)
    off = {**after, 3: transforms.from_xy_yaw(2.083, 0, 0)}  # the new loop closure itself 5 cm off
    assert _max_error_ratio(off, [strained, loop], planar=True, before=before,
                            new={loop.key()}) == pytest.approx(5.0, rel=1e-6)
    relaxed = {**after, 2: transforms.from_xy_yaw(1.078, 0, 0), 3: transforms.from_xy_yaw(2.078, 0, 0)}
    strained_more = {**before, 2: transforms.from_xy_yaw(1.11, 0, 0)}  # 11 std devs off before
    assert _max_error_ratio(relaxed, [strained], planar=True, before=strained_more) == 0.0  # 11 -> 7.8: not worse
    turned = {**after, 2: transforms.from_xy_yaw(1.031, 0, np.deg2rad(4.0))}  # rotation moved 4 deg
    assert _max_error_ratio(turned, [strained], planar=True, before=before) == pytest.approx(
        np.deg2rad(4.0) / 0.01, rel=1e-3)


def test_optimize_max_error_skips_switched_off_loop_closures_but_never_the_frames_own():
    info = default_information(1e-3)
    neighbour = Link(1, 2, LinkType.NEIGHBOR, transforms.identity(), info)
    dropped = Link(2, 7, LinkType.LOOP_INTRA, transforms.identity(), info)
    old_bridge = Link(3, 8, LinkType.LOOP_INTER, transforms.identity(), info)
    fresh = Link(4, 9, LinkType.LOOP_INTER, transforms.identity(), info)
    links = [neighbour, dropped, old_bridge, fresh]
    judged = _judged_links(links, {dropped.key()}, [old_bridge, fresh], {fresh.key()})
    assert judged == [neighbour, fresh]


def test_poses_kept_for_nodes_that_left_the_local_map_stay_consistent_as_its_frame_moves(tmp_path):
    """Each local map solution is rooted at its newest node's odometry pose, so its frame moves
    from one solution to the next; the poses kept for nodes that left it (transferred to LTM)
    must still be placed right relative to each other and to the map, or no two loop closures to
    that map agree on a merge."""
    rtabmap = Rtabmap(Params(), tmp_path / "frames.db")
    truth = {n: transforms.from_xy_yaw(1.0 * n, 0.2 * n * n / 10, 0.1 * n) for n in range(1, 8)}

    def seen(nodes, frame):  # a solution holding ``nodes``, in a frame ``frame`` away from the truth's
        return {n: frame @ truth[n] for n in nodes}

    rtabmap._optimized = seen([1, 2, 3, 4], transforms.identity())
    moves = [transforms.from_xy_yaw(0.3, -0.2, 0.05), transforms.from_xy_yaw(-1.0, 0.5, -0.4),
             transforms.from_xy_yaw(2.0, 1.0, 1.2)]
    for step, (nodes, frame) in enumerate(zip([[2, 3, 4, 5], [3, 4, 5, 6], [5, 6, 7]], moves)):
        if step == 1:
            rtabmap._forget([2], transferred_to_ltm=True)
        poses = seen(nodes, frame)
        rtabmap._follow_local_frame(poses, rigid=step == 0)
        rtabmap._optimized = poses
    for a, b in [(1, 2), (1, 4), (2, 7), (4, 6), (3, 7)]:
        np.testing.assert_allclose(transforms.relative(rtabmap._map_pose(a), rtabmap._map_pose(b)),
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
    rtabmap._optimized = {n: truth[n] for n in (1, 2, 3)}
    rtabmap._follow_local_frame({3: truth[3]}, rigid=False)  # session 0's nodes 1 and 2 leave
    rtabmap._optimized = {3: truth[3]}
    kept = rtabmap._map_pose(2).copy()
    memory.map_id = 1  # session 1: node 2 comes back, bent 26 m by a false loop closure, and leaves
    bent = transforms.from_xy_yaw(26.0, 0.0, 0.0) @ truth[2]
    rtabmap._follow_local_frame({2: bent, 10: truth[10]}, rigid=False)
    rtabmap._optimized = {2: bent, 10: truth[10]}
    np.testing.assert_allclose(rtabmap._map_pose(2), kept)
    rtabmap._follow_local_frame({10: truth[10], 11: truth[11]}, rigid=False)
    rtabmap._optimized = {10: truth[10], 11: truth[11]}
    np.testing.assert_allclose(rtabmap._map_pose(2), kept)
    # The session being mapped keeps its nodes' latest poses.
    rtabmap._follow_local_frame({11: truth[11]}, rigid=False)
    np.testing.assert_allclose(transforms.relative(rtabmap._map_pose(10), rtabmap._map_pose(11)),
                               transforms.relative(truth[10], truth[11]), atol=1e-9)
    rtabmap.close()


def _two_corridor_sessions(tmp_path):
    """Rtabmap whose memory holds two unconnected sessions driving one corridor (0.5 m steps).

    Session 0 = nodes 1..30 from odometry origin x = 0; session 1 = nodes 31..60, 0.5 m to the
    side, its odometry frame starting at world (0, 0.5): world = odom for session 0, and
    world = T_world_odom1 @ odom for session 1.
    """
    from rtabmap_ros2.core.params import Params
    from rtabmap_ros2.core.rtabmap import Rtabmap
    from rtabmap_ros2.core.signature import Signature

    rtabmap = Rtabmap(Params(), tmp_path / "merge.db")
    memory = rtabmap.memory
    for map_id, first in ((0, 1), (1, 31)):
        memory.map_id = map_id
        for k in range(30):
            sig = Signature(id=first + k, map_id=map_id, stamp_ns=first + k,
                            T_odom_base=transforms.from_xy_yaw(0.5 * k, 0.0, 0.0))
            neighbor = None
            if k:
                neighbor = Link(first + k - 1, first + k, LinkType.NEIGHBOR,
                                transforms.from_xy_yaw(0.5, 0.0, 0.0), ODOM_INFO)
            memory.add_location(sig, None, neighbor)
    return rtabmap


def _inter_link(new_id: int, old_id: int, error_xy=(0.0, 0.0)) -> Link:
    """Session-1 node ``new_id`` -> session-0 node ``old_id`` (true relative pose, plus an error)."""
    T_world_new = transforms.from_xy_yaw(0.5 * (new_id - 31), 0.5, 0.0)
    T_world_old = transforms.from_xy_yaw(0.5 * (old_id - 1), 0.0, 0.0)
    T = transforms.inverse(T_world_new) @ T_world_old @ transforms.from_xy_yaw(*error_xy, 0.0)
    return Link(new_id, old_id, LinkType.LOOP_INTER, T, ODOM_INFO)


def test_merge_agreement_takes_the_session_side_from_the_local_map_not_the_drifting_odometry(tmp_path):
    """Session 1's odometry overestimates every step by 10 % (its local map, refined by the
    scans, does not): two true loop closures 6 m apart imply old-map alignments 0.6 m apart by
    odometry, over the agreement tolerance, and agree on the local map's poses."""
    rtabmap = _two_corridor_sessions(tmp_path)
    rtabmap.params = rtabmap.params.with_value("graph.merge_min_loop_closures", 2)
    try:
        for k in range(30):
            rtabmap.memory.signatures[31 + k].T_odom_base = transforms.from_xy_yaw(0.55 * k, 0.0, 0.0)
        assert rtabmap._merge_allows(_inter_link(37, 7)) is False
        # Without a local map the odometry is all there is: the second one disagrees, held.
        assert rtabmap._merge_allows(_inter_link(49, 19)) is False
        rtabmap._merge_candidates = [_inter_link(37, 7)]
        rtabmap._optimized = {31 + k: transforms.from_xy_yaw(0.5 * k, 0.5, 0.0) for k in range(18)}
        assert rtabmap._merge_allows(_inter_link(49, 19)) is True
    finally:
        rtabmap.close()


def test_a_loop_closure_to_a_joined_session_far_from_its_kept_pose_is_rejected(tmp_path):
    """Once the sessions are joined, an inter-session loop closure that puts the old node farther
    than graph.merge_min_separation from its kept pose is a look-alike: rejected before the
    optimiser, which may have nothing to judge it against (the old node's part of the map in WM
    joined to the local map only through it). A true one is added."""
    rtabmap = _two_corridor_sessions(tmp_path)
    try:
        rtabmap._map_poses.update({1 + k: transforms.from_xy_yaw(0.5 * k, 0.0, 0.0) for k in range(30)})  # session 0
        rtabmap._optimized = {31 + k: transforms.from_xy_yaw(0.5 * k, 0.5, 0.0) for k in range(25)}
        rtabmap.memory.add_loop_closure(_inter_link(37, 7))  # the sessions are joined
        assert rtabmap._merge_allows(_inter_link(55, 25, error_xy=(15.0, 0.0))) is False
        assert rtabmap._merge_allows(_inter_link(55, 25, error_xy=(0.3, 0.1))) is True
    finally:
        rtabmap.close()


def test_a_loop_closure_within_the_session_far_from_its_local_map_pose_is_rejected(tmp_path):
    """Within the session being mapped, a loop closure that puts the old node farther than
    graph.merge_min_separation from where the session's own local map puts it is a look-alike
    (seed 5 with WM 300: a poster 33.8 m along a corridor, accepted, bent the session's 64-node
    local map, and its later true loop closures to other sessions no longer agreed). A true
    one, a few centimetres off, is added."""
    rtabmap = _two_corridor_sessions(tmp_path)
    try:
        rtabmap._optimized = {31 + k: transforms.from_xy_yaw(0.5 * k, 0.5, 0.0) for k in range(29)}

        def intra_link(error_x: float) -> Link:
            # Node 59 (14 m along) -> node 33 (1 m along): 13 m behind, plus the error.
            return Link(59, 33, LinkType.LOOP_INTRA, transforms.from_xy_yaw(-13.0 + error_x, 0.0, 0.0), ODOM_INFO)

        assert rtabmap._merge_allows(intra_link(12.0)) is False
        assert rtabmap._merge_allows(intra_link(0.05)) is True
    finally:
        rtabmap.close()


def test_a_map_merge_waits_for_agreeing_loop_closures_far_enough_apart(tmp_path):
    rtabmap = _two_corridor_sessions(tmp_path)
    try:
        # A look-alike place 15 m away: held, nothing to judge it against.
        assert rtabmap._merge_allows(_inter_link(35, 5, error_xy=(15.0, 0.0))) is False
        # A true one: held too (it disagrees with the false one).
        assert rtabmap._merge_allows(_inter_link(37, 7)) is False
        # True ones 1.5 and 2.5 m further agree with it, but are not independent evidence yet.
        assert rtabmap._merge_allows(_inter_link(40, 10)) is False
        assert rtabmap._merge_allows(_inter_link(42, 12)) is False
        # A true one 6 m further on both maps agrees with them: the merge happens.
        confirming = _inter_link(49, 19)
        assert rtabmap._merge_allows(confirming) is True
        rtabmap.memory.add_loop_closure(confirming)
        # Once connected, a loop closure is added at once (the optimiser judges it).
        assert rtabmap._merge_allows(_inter_link(52, 22)) is True
    finally:
        rtabmap.close()


def test_two_agreeing_loop_closures_do_not_merge_maps(tmp_path):
    """Look-alikes shifted alike along parallel corridors agree in pairs: a merge takes
    graph.merge_min_loop_closures (3) agreeing loop closures."""
    rtabmap = _two_corridor_sessions(tmp_path)
    try:
        assert rtabmap._merge_allows(_inter_link(37, 7)) is False
        assert rtabmap._merge_allows(_inter_link(49, 19)) is False   # 6 m apart, agreeing: two only
        assert rtabmap._merge_allows(_inter_link(52, 22)) is True
    finally:
        rtabmap.close()


def _corridor_scan(x: float, y: float, n: int = 481) -> LaserScan:
    """A 360-degree scan from (x, y), yaw 0, in the corridor both sessions drive (x -2..16, y -1..1.5,
    door frames at x = 3, 8 and 14.5)."""
    walls = [(-2, -1, 16, -1), (-2, 1.5, 16, 1.5), (-2, -1, -2, 1.5), (16, -1, 16, 1.5)]
    for door in (3.0, 8.0, 14.5):
        walls += [(door, -1, door, -0.4), (door, 0.9, door, 1.5)]
    walls = np.array(walls, float)
    angles = -np.pi + 2 * np.pi * np.arange(n) / n
    d = np.stack([np.cos(angles), np.sin(angles)], axis=1)[:, None, :]
    p, e = walls[None, :, :2] - np.array([x, y]), (walls[:, 2:] - walls[:, :2])[None]
    cross = d[..., 0] * e[..., 1] - d[..., 1] * e[..., 0]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (p[..., 0] * e[..., 1] - p[..., 1] * e[..., 0]) / cross
        u = (p[..., 0] * d[..., 1] - p[..., 1] * d[..., 0]) / cross
    t = np.where((t > 0) & (u >= 0) & (u <= 1), t, np.inf).min(axis=1)
    return LaserScan(np.where(t < 30, t, np.inf), -np.pi, 2 * np.pi / n, 0.1, 30.0)


def test_a_map_merge_the_scans_contradict_is_refused(tmp_path):
    """Three look-alike loop closures shifted alike (15 m along the corridor) agree with each other;
    the sessions' scans do not: one session's end wall and door frames fall in the other's free
    corridor. Refused, and the held ones dropped; three true ones then merge the maps."""
    rtabmap = _two_corridor_sessions(tmp_path)
    try:
        memory = rtabmap.memory
        for k in range(30):
            memory.signatures[1 + k].scan = _corridor_scan(0.5 * k, 0.0)
            memory.signatures[31 + k].scan = _corridor_scan(0.5 * k, 0.5)
        rtabmap._map_poses.update({1 + k: transforms.from_xy_yaw(0.5 * k, 0.0, 0.0) for k in range(30)})  # session 0
        rtabmap._optimized = {31 + k: transforms.from_xy_yaw(0.5 * k, 0.5, 0.0) for k in range(25)}
        look_alikes = [_inter_link(a, b, error_xy=(15.0, 0.0)) for a, b in ((35, 5), (41, 11), (47, 17))]
        assert [rtabmap._merge_allows(link) for link in look_alikes] == [False, False, False]
        assert rtabmap._merge_candidates == []
        true_ones = [_inter_link(a, b) for a, b in ((37, 7), (43, 13), (49, 19))]
        assert [rtabmap._merge_allows(link) for link in true_ones] == [False, False, True]
    finally:
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
    rtabmap = _two_corridor_sessions(tmp_path)
    try:
        rtabmap.params = rtabmap.params.with_value("graph.robust", True)
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
        rtabmap._T_world_local = transforms.from_xy_yaw(3.0, -2.0, 0.7)
        to_local = transforms.inverse(rtabmap._T_world_local)
        rtabmap._map_poses.update({n: truth[n] for n in range(1, 31) if n in memory.signatures})
        rtabmap._optimized = {n: to_local @ truth[n] for n in range(31, 56)}
        memory.add_loop_closure(_inter_link(33, 3))
        poses, _ = rtabmap._optimize_component(55)
        assert set(range(18, 31)) <= set(poses)
        for a, b in [(1, 30), (3, 25), (10, 20), (25, 55), (1, 55)]:
            error = transforms.relative(transforms.relative(poses[a], poses[b]), transforms.relative(truth[a], truth[b]))
            assert np.linalg.norm(error[:3, 3]) < 0.05, (a, b, error[:3, 3])
    finally:
        rtabmap.close()
