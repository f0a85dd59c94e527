"""When a new map starts (core/sessions.py; issue 14 item 5): odometry reset detection.

Reset detection is exercised through :meth:`Rtabmap.process` on frames holding only odometry
(each becomes a node without words: cheap), from synthetic drives and from the simulator's
wheel odometry, with frames dropped as DDS drops them (103 of 200 arrived in the issue's run).
The end-to-end runs render the simulated sessions and check the exported map against ground truth.
"""

from __future__ import annotations

import numpy as np
import pytest

from rtabmap_ros2.core import transforms
from rtabmap_ros2.core.params import Params
from rtabmap_ros2.core.rtabmap import Rtabmap
from rtabmap_ros2.core.sensor import SensorFrame
from rtabmap_ros2.core.sessions import (ODOM_RESET_VARIANCE, PLANAR_TOLERANCE_M, PLANAR_TOLERANCE_RAD, REQUESTED,
                                        PlanarOdometryCheck, Sessions, odometry_information)
from rtabmap_ros2.sim import build_world, make_sessions
from rtabmap_ros2.sim.robot import reset_odometry, step_covariance

NS = 10**9
COVARIANCE = step_covariance(0.5)


@pytest.fixture(scope="module")
def sessions():
    """The 5 simulated sessions (ground truth and wheel odometry only, nothing rendered)."""
    return make_sessions(build_world(seed=0))


def pose_frames(stamps_s, poses, covariance=COVARIANCE) -> list[SensorFrame]:
    return [SensorFrame(int(round(t * NS)), np.asarray(T, dtype=float), covariance) for t, T in zip(stamps_s, poses)]


def new_maps(tmp_path, frames, params: Params = Params()) -> list[int]:
    """Indices of the frames that started a new map."""
    with Rtabmap(params, tmp_path / "reset.db", delete_existing=True) as rtabmap:
        return [k for k, frame in enumerate(frames) if rtabmap.process(frame).new_map]


def drive(waypoints, speed=0.5, period=1.0):
    """Poses (N,4,4) every ``period`` s along straight segments between (x, y) waypoints at
    ``speed``, heading along the motion."""
    points = [np.asarray(waypoints[0], float)]
    for a, b in zip(waypoints[:-1], waypoints[1:]):
        a, b = np.asarray(a, float), np.asarray(b, float)
        steps = max(1, int(np.ceil(np.linalg.norm(b - a) / (speed * period))))
        points += [a + (b - a) * k / steps for k in range(1, steps + 1)]
    points = np.array(points)
    step = np.diff(points, axis=0)
    heading = np.append(np.arctan2(step[:, 1], step[:, 0]), np.arctan2(step[-1, 1], step[-1, 0]))
    return np.stack([transforms.from_xy_yaw(x, y, a) for (x, y), a in zip(points, heading)])


def keep_about_half(n: int, seed: int) -> np.ndarray:
    """Indices of the frames that arrive when about half are lost (always the first)."""
    keep = np.random.default_rng(seed).random(n) < 0.52
    keep[0] = True
    return np.flatnonzero(keep)


# -- (a) the previous session ended near its origin ---------------------------------------------

def test_reset_to_identity_is_seen_however_near_its_origin_the_previous_session_ended(tmp_path):
    # A robot drives a 3 x 2 m loop back to 2 cm of its start (no reset: odometry never lands
    # on identity), drives the loop again and docks 8 cm from where it started; its odometry
    # is then reset to identity for the next session.
    lap = drive([(0, 0), (3, 0), (3, 2), (0, 2), (0.02, 0.0)])
    docked = lap[-1].copy()
    docked[:3, 3] = (0.08, -0.03, 0.0)
    first = np.concatenate([lap, lap[1:-1], [docked]])
    second = drive([(0, 0), (2, 0)])
    stamps = np.arange(len(first) + len(second), dtype=float)
    assert new_maps(tmp_path, pose_frames(stamps, np.concatenate([first, second]))) == [len(first)]


def test_a_robot_parked_at_its_origin_is_not_a_new_session(tmp_path):
    # Standing still at identity for a while, driving, then the same: nothing resets.
    poses = np.concatenate([np.repeat(np.eye(4)[None], 5, axis=0), drive([(0, 0), (2, 0), (0, 0)])])
    assert new_maps(tmp_path, pose_frames(np.arange(len(poses), dtype=float), poses)) == []


# -- (b) the first frames after the reset were lost --------------------------------------------

@pytest.mark.parametrize("lost", [3, 8])
def test_reset_is_seen_when_its_first_frames_were_lost(tmp_path, sessions, lost):
    # Session 2's wheel odometry restarted at three places of the route; the frames right after
    # each restart are lost and about half of all others too (the 103 of 200), so the
    # first frame received after a restart is already metres away from its origin.
    session = sessions[1]
    restarts = (100, 180, 260)
    T = session.T_odom_base
    for at in restarts:
        T = reset_odometry(T, at)
    arrived = [i for i in keep_about_half(len(session), seed=lost)
               if not any(at <= i < at + lost for at in restarts)]
    stamps = session.stamps_ns[arrived] / NS
    frames = pose_frames(stamps, T[arrived])
    first_after = [next(k for k, i in enumerate(arrived) if i >= at) for at in restarts]
    assert all(arrived[k] - at >= lost for k, at in zip(first_after, restarts))
    assert new_maps(tmp_path, frames) == first_after


def test_sessions_played_back_to_back_with_their_first_frames_lost_are_separate_maps(tmp_path, sessions):
    # The 5 sessions in one stream, about half of the frames lost and the first 8 of each
    # session too: with their recorded stamps (an hour apart) and with the sessions following
    # each other 1 s apart (one recording, the odometry restarted in it).
    for back_to_back in (False, True):
        frames, starts, offset = [], [], 0.0
        for k, session in enumerate(sessions):
            arrived = [i for i in keep_about_half(len(session), seed=k) if i >= 8 or k == 0]
            stamps = session.stamps_ns[arrived] / NS
            if back_to_back:
                offset = (frames[-1].stamp_ns / NS + 1.0 - stamps[0]) if frames else 0.0
            starts.append(len(frames))
            frames += pose_frames(stamps + offset, session.T_odom_base[arrived])
        assert new_maps(tmp_path, frames) == starts[1:], f"back to back: {back_to_back}"


# -- (c) a reset signalled only by a time gap and a pose jump ----------------------------------

def test_reset_signalled_only_by_a_pose_jump_the_elapsed_time_cannot_explain(tmp_path):
    # Odometry restarted at an arbitrary pose (an EKF re-initialised), no identity, no
    # covariance flag: 2 s after the last frame the pose is 25 m away.
    before = drive([(0, 0), (6, 0), (6, 4)])
    restart = transforms.from_xy_yaw(-12.0, 20.0, 1.0)
    after = restart @ drive([(0, 0), (4, 0)])
    stamps = np.concatenate([np.arange(len(before)), len(before) + 1 + np.arange(len(after))]).astype(float)
    assert new_maps(tmp_path, pose_frames(stamps, np.concatenate([before, after]))) == [len(before)]


def test_a_long_silence_is_a_reset_only_if_the_robot_moved_across_it(tmp_path):
    # 10 minutes without a frame. Parked meanwhile: the same map goes on. Moved 3 m (the
    # odometry that bridged the silence is not trusted): a new map.
    route = drive([(0, 0), (5, 0)])
    moved = transforms.from_xy_yaw(3.0, 0.0, 0.0) @ drive([(5, 0), (5, 3)])
    for later, expected in ((drive([(5, 0), (5, 3)]), []), (moved, [len(route)])):
        stamps = np.concatenate([np.arange(len(route)), len(route) + 600 + np.arange(len(later))]).astype(float)
        assert new_maps(tmp_path, pose_frames(stamps, np.concatenate([route, later]))) == expected


def test_no_reset_on_ordinary_gaps_and_fast_driving(tmp_path, sessions):
    # Every session with about half of its frames lost (gaps of 1-8 s), driven at the simulated
    # speed (0.45-0.55 m/s) and 4 times faster (odometry scaled: about 2 m/s, faster than
    # graph.odom_reset_speed, so the robot's own speed must be learnt): no new map inside any.
    for scale in (1.0, 4.0):
        for k, session in enumerate(sessions):
            arrived = keep_about_half(len(session), seed=10 + k)
            T = session.T_odom_base[arrived].copy()
            T[:, :3, 3] *= scale
            assert new_maps(tmp_path, pose_frames(session.stamps_ns[arrived] / NS, T)) == [], \
                f"session {session.index} x{scale}"


def test_lost_odometry_covariance_starts_one_new_map(tmp_path):
    route = drive([(0, 0), (4, 0)])
    lost = np.diag([9999.0] * 6)
    frames = pose_frames(np.arange(len(route), dtype=float), route)
    frames += [SensorFrame(int((len(route) + k) * NS), route[-1], lost) for k in range(3)]
    frames += pose_frames(len(route) + 3 + np.arange(3, dtype=float), route[-1:].repeat(3, axis=0))
    assert new_maps(tmp_path, frames) == [len(route)]


def test_reset_detection_parameters(tmp_path):
    # RTAB-Map's RGBD/NewMapOdomChangeDistance = 0 turns the jump rules off (identity and
    # covariance remain, as RTAB-Map's defaults).
    params = Params().with_overrides(["RGBD/NewMapOdomChangeDistance=0"])
    assert params.graph.odom_reset_jump == 0
    before = drive([(0, 0), (6, 0)])
    after = transforms.from_xy_yaw(-12.0, 20.0, 1.0) @ drive([(0, 0), (2, 0)])
    frames = pose_frames(np.arange(len(before) + len(after), dtype=float), np.concatenate([before, after]))
    assert new_maps(tmp_path, frames, params) == []
    assert new_maps(tmp_path, frames) == [len(before)]
    for bad in ("graph.odom_reset_jump=-1", "graph.odom_reset_speed=nan", "graph.odom_reset_max_gap=0"):
        with pytest.raises(ValueError):
            Params().with_overrides([bad])


def test_reset_odometry_restarts_at_identity_and_keeps_the_motion(sessions):
    T = sessions[0].T_odom_base
    reset = reset_odometry(T, 50)
    assert np.array_equal(reset[:50], T[:50]) and np.array_equal(reset[50], np.eye(4))
    for k in (51, 120, len(T) - 1):
        np.testing.assert_allclose(transforms.relative(reset[k - 1], reset[k]), transforms.relative(T[k - 1], T[k]),
                                   atol=1e-9)


# -- Sessions alone -------------------------------------------------------------------------------

def test_a_request_starts_a_new_map_only_once_the_current_one_has_a_node():
    sessions = Sessions(Params().graph)
    frame = pose_frames([0.0], [transforms.from_xy_yaw(1.0, 0.0, 0.0)])[0]
    assert sessions.request_new_map() is False  # the current map is still empty: it is the new one
    assert sessions.new_map_reason(frame) == ""
    sessions.nodes_in_map = 3
    assert sessions.request_new_map() is True
    next_frame = pose_frames([1.0], [transforms.from_xy_yaw(1.2, 0.0, 0.0)])[0]
    assert sessions.new_map_reason(next_frame) == REQUESTED
    assert sessions.nodes_in_map == 0
    assert sessions.new_map_reason(next_frame) == ""  # one request, one new map


def test_reset_reasons_name_what_was_seen():
    sessions = Sessions(Params().graph)
    first, reset = pose_frames([0.0, 1.0], [transforms.from_xy_yaw(3.0, 1.0, 0.2), np.eye(4)])
    sessions.new_map_reason(first)
    sessions.nodes_in_map = 5
    assert sessions.new_map_reason(reset) == "odometry reset: identity pose"
    lost = np.diag([ODOM_RESET_VARIANCE] * 6)
    frame = pose_frames([2.0], [transforms.from_xy_yaw(0.1, 0.0, 0.0)], covariance=lost)[0]
    assert sessions.reset_reason(frame).startswith("odometry reset: covariance")


def test_neighbour_link_information_ignores_unusable_variances():
    cov = np.diag([0.01, 0.0, ODOM_RESET_VARIANCE, 0.04, np.nan, 0.25])
    frame = SensorFrame(0, np.eye(4), cov)
    info = odometry_information(frame, default_variance=0.5)
    np.testing.assert_allclose(np.diag(info), [100.0, 2.0, 2.0, 25.0, 2.0, 4.0])
    assert np.count_nonzero(info - np.diag(np.diag(info))) == 0


# -- planar mode meeting odometry that is not planar (issue 49) ----------------------------------

def hand_held(n: int = 12) -> list[np.ndarray]:
    """A camera body carried by hand: 0.5 m forward, rising 0.3 m and pitching 20 deg as it goes."""
    return [transforms.from_xyz_rpy([0.05 * k, 0.0, 0.03 * k, 0.0, np.deg2rad(-2.0 * k), 0.1 * k]) for k in range(n)]


def planar_warnings(caplog) -> list[str]:
    return [r.message for r in caplog.records if "leaves the plane" in r.message]


def test_planar_mode_on_hand_held_odometry_is_warned_once_per_session(tmp_path, caplog):
    poses = hand_held()
    frames = pose_frames(range(len(poses)), poses) + pose_frames(range(100, 100 + len(poses)), poses)
    planar = Params().with_value("Reg/Force3DoF", True)
    with Rtabmap(planar, tmp_path / "hand.db", delete_existing=True) as rtabmap:
        for k, frame in enumerate(frames):
            if k == len(poses):
                rtabmap.trigger_new_map()
            rtabmap.process(frame)
        assert rtabmap.local.planar   # applied without a laser, as RTAB-Map applies Reg/Force3DoF
        out = rtabmap.planarity.sessions
    warnings = planar_warnings(caplog)
    assert len(warnings) == 2 and "map 0" in warnings[0] and "map 1" in warnings[1]
    assert "Reg/Force3DoF=false" in warnings[0]
    assert out[0].height_m == pytest.approx(0.33) and out[0].tilt_rad == pytest.approx(np.deg2rad(22), abs=1e-6)


def test_6dof_mode_and_a_robot_on_a_floor_give_no_warning(tmp_path, caplog):
    with Rtabmap(Params(), tmp_path / "six.db", delete_existing=True) as rtabmap:   # RTAB-Map's default: 6 DoF
        for frame in pose_frames(range(12), hand_held()):
            rtabmap.process(frame)
        assert rtabmap.local.planar is False and not rtabmap.planarity.sessions
    floor = drive([(0, 0), (4, 0), (4, 3)])
    with Rtabmap(Params().with_value("registration.planar", True), tmp_path / "floor.db") as rtabmap:
        for frame in pose_frames(range(len(floor)), floor):
            rtabmap.process(frame)
        assert rtabmap.planarity.sessions[0].planar
    assert not planar_warnings(caplog)


def test_the_plane_is_the_first_pose_of_the_session():
    """A camera body tilted from the start (a hand-held start, a robot on a ramp) that then moves
    in its own plane is planar; the tolerances are what separates the two."""
    check = PlanarOdometryCheck()
    start = transforms.from_xyz_rpy([1.0, 2.0, 1.5, 0.4, -0.3, 1.0])
    for k in range(5):
        assert check.update(0, start @ transforms.from_xy_yaw(0.3 * k, 0.1 * k, 0.2 * k)) is None
    assert check.sessions[0].planar
    assert check.update(0, start @ transforms.from_xy_yaw(0.0, 0.0, 0.0, z=0.9 * PLANAR_TOLERANCE_M)) is None
    assert check.update(0, start @ transforms.from_xyz_rpy([0, 0, 0, 0.9 * PLANAR_TOLERANCE_RAD, 0, 0])) is None
    assert check.update(0, start @ transforms.from_xyz_rpy([0, 0, 0, 0, 1.1 * PLANAR_TOLERANCE_RAD, 0]))
    assert check.update(0, start @ transforms.from_xy_yaw(0.0, 0.0, 0.0, z=2.0)) is None   # said once


# -- RGBD/LinearUpdate, RGBD/AngularUpdate: a robot that did not move adds no node ------------------

def added_nodes(tmp_path, frames, params: Params) -> tuple[list[int], list[bool], int]:
    """Per frame: its location id (0: none) and whether it was left out for a small displacement;
    and the nodes in the database after the run."""
    with Rtabmap(params, tmp_path / "update.db", delete_existing=True) as rtabmap:
        stats = [rtabmap.process(frame) for frame in frames]
        rtabmap.flush()
        stored = rtabmap.db.node_count()
    return [s.location_id for s in stats], [s.small_displacement for s in stats], stored


def test_frames_of_a_robot_standing_still_do_not_become_nodes(tmp_path):
    # Parked for 5 frames (odometry noise of a few mm), then 2 m at 0.5 m per frame, then parked.
    rng = np.random.default_rng(3)
    parked = [transforms.from_xy_yaw(*rng.normal(0.0, 0.003, 3)) for _ in range(5)]
    route = list(drive([(0, 0), (2, 0)])[1:])
    poses = parked + route + [route[-1]] * 4
    frames = pose_frames(np.arange(len(poses), dtype=float), poses)
    params = Params().with_overrides(["RGBD/LinearUpdate=0.1", "RGBD/AngularUpdate=0.1"])
    ids, small, stored = added_nodes(tmp_path, frames, params)
    assert small == [False] + [True] * 4 + [False] * len(route) + [True] * 4
    assert [i > 0 for i in ids] == [not s for s in small]
    assert stored == 1 + len(route)
    # The defaults (both 0): every frame a node, as before.
    ids, small, stored = added_nodes(tmp_path, frames, Params())
    assert not any(small) and all(ids) and stored == len(frames)


def test_rotation_alone_adds_a_node_only_when_angular_update_is_set(tmp_path):
    # Turning on the spot, 0.3 rad a frame.
    poses = [transforms.from_xy_yaw(0.0, 0.0, 0.3 * k) for k in range(6)]
    frames = pose_frames(np.arange(6, dtype=float), poses)
    both = Params().with_overrides(["graph.linear_update=0.1", "graph.angular_update=0.1"])
    assert added_nodes(tmp_path, frames, both)[2] == 6
    # Translation only: a robot turning on the spot has not moved.
    assert added_nodes(tmp_path, frames, Params().with_value("graph.linear_update", 0.1))[2] == 1


def test_an_odometry_reset_while_parked_starts_a_new_map_with_a_node(tmp_path):
    # Parked at identity, odometry reset to identity (covariance 9999, RTAB-Map's reset signal):
    # the new session's first frame is a node although odometry shows no motion.
    lost = np.diag([9999.0] * 6)
    frames = pose_frames([0.0, 1.0, 2.0], [np.eye(4)] * 3)
    frames.insert(2, SensorFrame(int(1.5 * NS), np.eye(4), lost))
    frames.append(SensorFrame(int(3 * NS), np.eye(4), COVARIANCE))
    params = Params().with_value("graph.linear_update", 0.1)
    with Rtabmap(params, tmp_path / "parked.db", delete_existing=True) as rtabmap:
        stats = [rtabmap.process(frame) for frame in frames]
    assert [s.small_displacement for s in stats][:2] == [False, True]
    first_of_new_map = next(s for s in stats if s.new_map)
    assert first_of_new_map.location_id > 0 and not first_of_new_map.small_displacement
