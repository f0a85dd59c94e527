"""Pose graph optimisation (gtsam): optimum on intel, multi-session, robust rejection, Pose3 information."""

from __future__ import annotations

import numpy as np
import pytest

from rtabmap_ros2.core import transforms
from rtabmap_ros2.core.graph import Link, LinkType, chain_poses, default_information
from rtabmap_ros2.core.optimizer import gtsam_information, optimize, read_g2o, release, write_g2o
from rtabmap_ros2.core.params import GraphParams
from rtabmap_ros2.errors import OptimizationError

PLAIN = GraphParams(robust=False)


def test_intel_reaches_optimum(shared_data):
    poses, links, planar = read_g2o(shared_data / "posegraphs" / "intel.g2o")
    assert planar and len(poses) == 1728 and len(links) == 2512
    root = min(poses)
    first = optimize(poses, links, root, PLAIN, planar)
    again = optimize(first.poses, links, root, PLAIN, planar)
    print(f"intel chi2 {first.chi2_initial:.1f} -> {first.chi2_final:.3f} ({first.iterations} it); "
          f"from the optimum {again.chi2_final:.3f}")
    assert first.chi2_final <= 1.01 * again.chi2_final
    assert first.chi2_final < 0.2 * first.chi2_initial
    assert np.allclose(first.poses[root], poses[root], atol=1e-6)


def _chain(ids, step, start=transforms.identity(), info=None):
    poses, links, T = {}, [], start
    for a, b in zip(ids, ids[1:]):
        links.append(Link(a, b, LinkType.NEIGHBOR, step, info if info is not None else default_information(1e-2)))
    for i in ids:
        poses[i] = T
        T = T @ step
    return poses, links


def test_multi_session_joined_by_one_link_in_root_frame():
    step = transforms.from_xy_yaw(1.0, 0.0, 0.0)
    # Session 1 (ids 1-5) and session 2 (ids 11-15), each starting at its own origin (identity).
    p1, l1 = _chain([1, 2, 3, 4, 5], step)
    p2, l2 = _chain([11, 12, 13, 14, 15], step)
    # Truth: session 2 starts 2 m to the left of node 3, heading the same way.
    T_3_11 = transforms.from_xy_yaw(0.0, 2.0, 0.0)
    inter = Link(3, 11, LinkType.LOOP_INTER, T_3_11, default_information(1e-4))
    links = l1 + l2 + [inter]
    root = 15  # newest node (2014 §II-B), fixed at its odometry pose
    initial = chain_poses(root, p2[root], links)
    assert set(initial) == set(p1) | set(p2)
    result = optimize(initial, links, root, GraphParams(robust=True), planar=True)
    assert np.allclose(result.poses[root], p2[root], atol=1e-6)
    expected_3 = p2[11] @ transforms.inverse(T_3_11)
    assert np.allclose(result.poses[3][:3, 3], expected_3[:3, 3], atol=1e-3)
    assert np.allclose(result.poses[1][:3, 3], (expected_3 @ transforms.inverse(step) @ transforms.inverse(step))[:3, 3],
                       atol=1e-3)
    assert not result.rejected


def test_disconnected_nodes_raise():
    step = transforms.from_xy_yaw(1.0, 0.0, 0.0)
    p1, l1 = _chain([1, 2, 3], step)
    p2, l2 = _chain([11, 12], step)
    with pytest.raises(OptimizationError, match="not connected to the root"):
        optimize({**p1, **p2}, l1 + l2, 3, PLAIN, planar=True)


def test_links_to_unknown_nodes_are_ignored():
    step = transforms.from_xy_yaw(1.0, 0.0, 0.0)
    poses, links = _chain([1, 2, 3], step)
    links.append(Link(3, 99, LinkType.LOOP_INTRA, step))  # node 99 is in LTM: not given
    result = optimize(poses, links, 3, PLAIN, planar=True)
    assert set(result.poses) == {1, 2, 3}


def _square_loop_graph(rng, laps=3, side=5, noise=0.02):
    """A robot going around a square several times, noisy odometry, true loop closures between laps."""
    truth, ids = {}, []
    T = transforms.identity()
    n = 4 * side * laps
    for i in range(n):
        ids.append(i + 1)
        truth[i + 1] = T
        T = T @ (transforms.from_xy_yaw(0.0, 0.0, np.pi / 2) if (i + 1) % side == 0 else transforms.from_xy_yaw(1.0, 0, 0))
    links, odom = [], {1: transforms.identity()}
    for a, b in zip(ids, ids[1:]):
        rel = transforms.relative(truth[a], truth[b])
        noisy = rel @ transforms.from_xy_yaw(*rng.normal(0, [noise, noise, noise]))
        links.append(Link(a, b, LinkType.NEIGHBOR, noisy, default_information(noise ** 2)))
        odom[b] = odom[a] @ noisy
    period = 4 * side
    for i in range(period + 1, n + 1, 3):
        links.append(Link(i - period, i, LinkType.LOOP_INTRA, transforms.relative(truth[i - period], truth[i]),
                          default_information(1e-3)))
    return truth, odom, links


def test_robust_rejects_wrong_loop_closure(rng):
    truth, odom, links = _square_loop_graph(rng)
    root = max(odom)
    clean = optimize(odom, links, root, PLAIN, planar=True).poses
    wrong = Link(3, 45, LinkType.LOOP_INTRA, transforms.from_xy_yaw(0.5, 0.0, 0.0), default_information(1e-3))
    robust = optimize(odom, links + [wrong], root, GraphParams(robust=True), planar=True)
    plain = optimize(odom, links + [wrong], root, PLAIN, planar=True)
    assert [l.key() for l in robust.rejected] == [wrong.key()]
    dev_robust = max(np.linalg.norm(robust.poses[k][:2, 3] - clean[k][:2, 3]) for k in clean)
    dev_plain = max(np.linalg.norm(plain.poses[k][:2, 3] - clean[k][:2, 3]) for k in clean)
    print(f"max deviation from the clean solution: robust {dev_robust:.4f} m, plain {dev_plain:.3f} m")
    assert dev_robust < 0.03
    assert dev_plain > 0.3


def test_loop_closures_rejected_before_start_out_and_true_ones_come_back(rng):
    """A re-solve told which loop closures the last solution rejected starts without them: the
    false one stays rejected in fewer iterations, at the same solution; a true one passed as
    rejected is re-admitted."""
    truth, odom, links = _square_loop_graph(rng)
    root = max(odom)
    wrong = Link(3, 45, LinkType.LOOP_INTRA, transforms.from_xy_yaw(0.5, 0.0, 0.0), default_information(1e-3))
    first = optimize(odom, links + [wrong], root, GraphParams(robust=True), planar=True)
    again = optimize(odom, links + [wrong], root, GraphParams(robust=True), planar=True,
                     rejected_before={wrong.key()})
    assert [l.key() for l in again.rejected] == [wrong.key()]
    assert again.iterations < first.iterations
    assert max(np.linalg.norm(again.poses[k][:3, 3] - first.poses[k][:3, 3]) for k in odom) < 1e-3
    true = next(l for l in links if l.type is LinkType.LOOP_INTRA)
    back = optimize(odom, links + [wrong], root, GraphParams(robust=True), planar=True,
                    rejected_before={wrong.key(), true.key()})
    assert [l.key() for l in back.rejected] == [wrong.key()]
    assert max(np.linalg.norm(back.poses[k][:3, 3] - first.poses[k][:3, 3]) for k in odom) < 1e-3


@pytest.mark.parametrize("optimizer", ["lm", "gn", "dogleg"])
def test_optimizers_agree(rng, optimizer):
    truth, odom, links = _square_loop_graph(rng)
    result = optimize(odom, links, max(odom), GraphParams(optimizer=optimizer, robust=False), planar=True)
    reference = optimize(odom, links, max(odom), PLAIN, planar=True)
    assert result.chi2_final == pytest.approx(reference.chi2_final, rel=1e-3)
    assert result.chi2_final < result.chi2_initial


def test_pose3_information_reordering():
    # Two measurements of node 2's position from node 1 that disagree in z and in x. The first is
    # precise in z only, the second precise in x only: the solution takes z from the first, x from the second.
    root = transforms.identity()
    poses = {1: root, 2: transforms.identity()}
    info_z = np.diag([1.0, 1.0, 1e6, 1e4, 1e4, 1e4])  # x y z roll pitch yaw
    info_x = np.diag([1e6, 1.0, 1.0, 1e4, 1e4, 1e4])
    a = Link(1, 2, LinkType.NEIGHBOR, transforms.from_xyz_quat_xyzw([1.0, 0, 0.5], [0, 0, 0, 1]), info_z)
    b = Link(1, 2, LinkType.LOOP_INTRA, transforms.from_xyz_quat_xyzw([2.0, 0, 0.0], [0, 0, 0, 1]), info_x)
    result = optimize(poses, [a, b], 1, PLAIN, planar=False)
    p = result.poses[2][:3, 3]
    assert p[2] == pytest.approx(0.5, abs=1e-3) and p[0] == pytest.approx(2.0, abs=1e-3)
    # Our yaw information ends up on gtsam's rz (index 2), our x on gtsam's tx (index 3).
    g = gtsam_information(np.diag([1, 2, 3, 4, 5, 6.0]), planar=False)
    assert np.allclose(np.diag(g), [4, 5, 6, 1, 2, 3])
    assert np.allclose(np.diag(gtsam_information(np.diag([1, 2, 3, 4, 5, 6.0]), planar=True)), [1, 2, 6])


def test_g2o_round_trip_se2_and_se3(tmp_path, random_se3, rng):
    for planar in (True, False):
        poses = {i: (transforms.project_planar(random_se3()) if planar else random_se3()) for i in range(4)}
        links = []
        for a, b in [(0, 1), (1, 2), (2, 3), (0, 3)]:
            A = rng.normal(size=(6, 6))
            info = A @ A.T + 6 * np.eye(6)
            if planar:
                keep = np.zeros((6, 6))
                keep[np.ix_([0, 1, 5], [0, 1, 5])] = info[np.ix_([0, 1, 5], [0, 1, 5])]
                info = keep + np.diag([0, 0, 1, 1, 1, 0]) * keep[0, 0]
            links.append(Link(a, b, LinkType.NEIGHBOR if b == a + 1 else LinkType.LOOP_INTRA,
                              transforms.relative(poses[a], poses[b]), info))
        path = tmp_path / f"graph_{planar}.g2o"
        write_g2o(path, poses, links, planar)
        poses2, links2, planar2 = read_g2o(path)
        assert planar2 == planar and poses2.keys() == poses.keys()
        for k in poses:
            assert np.allclose(poses2[k], poses[k], atol=1e-6)
        for l1, l2 in zip(links, links2):
            assert (l1.from_id, l1.to_id, l1.type) == (l2.from_id, l2.to_id, l2.type)
            assert np.allclose(l1.T_from_to, l2.T_from_to, atol=1e-6)
            assert np.allclose(l1.information, l2.information, rtol=1e-6)


def test_edges_only_file_is_chained(tmp_path):
    path = tmp_path / "edges.g2o"
    path.write_text("EDGE_SE2 0 1 1 0 0 1 0 0 1 0 1\nEDGE_SE2 1 2 1 0 1.5707963 1 0 0 1 0 1\n"
                    "EDGE_SE2 2 3 1 0 0 1 0 0 1 0 1\n")
    poses, links, planar = read_g2o(path)
    assert planar and len(links) == 3
    assert np.allclose(poses[3][:2, 3], [2.0, 1.0], atol=1e-6)


def test_bad_information_raises():
    step = transforms.from_xy_yaw(1.0, 0.0, 0.0)
    poses, _ = _chain([1, 2], step)
    bad = Link(1, 2, LinkType.NEIGHBOR, step, np.zeros((6, 6)))
    with pytest.raises(OptimizationError, match="positive definite"):
        optimize(poses, [bad], 1, PLAIN, planar=True)


def test_robust_keeps_a_loop_closure_whose_removal_would_disconnect_the_graph():
    """Two sessions joined only by two mutually inconsistent loop closures, from a guess that
    satisfies neither (DCS flags both): one must stay, the optimiser must not fail."""
    info = default_information(1e-3)
    step = transforms.from_xy_yaw(1.0, 0.0, 0.0)
    links = [Link(i, i + 1, LinkType.NEIGHBOR, step, info) for i in range(1, 10)]
    links += [Link(i, i + 1, LinkType.NEIGHBOR, step, info) for i in range(11, 20)]
    links += [Link(15, 5, LinkType.LOOP_INTER, transforms.identity(), info),
              Link(18, 3, LinkType.LOOP_INTER, transforms.from_xy_yaw(9.0, 3.0, 1.0), info)]
    poses = chain_poses(20, transforms.identity(), links)
    far = transforms.from_xy_yaw(50.0, -40.0, 2.0)
    poses.update({n: far @ poses[n] for n in range(1, 11)})
    result = optimize(poses, links, 20, GraphParams(robust=True), planar=True)
    assert len(result.rejected) == 1
    assert set(result.poses) == set(range(1, 21))


def test_released_links_lose_their_cached_gtsam_objects():
    from rtabmap_ros2.core import optimizer as optimizer_module

    poses = {i: transforms.from_xy_yaw(i * 1.0, 0.0, 0.0) for i in range(3)}
    info = np.eye(6) * 100.0
    links = [Link(0, 1, LinkType.NEIGHBOR, transforms.from_xy_yaw(1.0, 0.0, 0.0), info.copy()),
             Link(1, 2, LinkType.NEIGHBOR, transforms.from_xy_yaw(1.0, 0.0, 0.0), info.copy()),
             Link(2, 0, LinkType.LOOP_INTRA, transforms.from_xy_yaw(-2.0, 0.0, 0.0), info.copy())]
    before = len(optimizer_module._GTSAM_CACHE)
    optimize(poses, links, 2, GraphParams(), planar=True)
    assert len(optimizer_module._GTSAM_CACHE) >= before + 3 * 2  # factor, noise (+ robust)
    release(links)
    assert len(optimizer_module._GTSAM_CACHE) == before
    result = optimize(poses, links, 2, GraphParams(), planar=True)  # made again when needed
    assert np.allclose(result.poses[0][:3, 3], [0.0, 0.0, 0.0], atol=1e-6)
    release(links)
    once = optimize(poses, links, 2, GraphParams(), planar=True, cache=False)   # a one-off solve
    assert len(optimizer_module._GTSAM_CACHE) == before
    assert all(np.array_equal(once.poses[n], result.poses[n]) for n in poses)


def test_a_false_loop_closure_the_robust_mode_cannot_drop_is_reported_switched_off():
    """Two chains joined only by one loop closure that says they are 40 m from where the guess
    puts them (a bridge: dropping it would disconnect the graph). DCS leaves it barely weighted,
    so the solution keeps the guess and the link is reported switched off, not silently
    'satisfied'; a true bridge is not."""
    info = default_information(1e-4)
    step = transforms.from_xy_yaw(1.0, 0.0, 0.0)
    links = [Link(i, i + 1, LinkType.NEIGHBOR, step, info) for i in range(1, 5)]
    links += [Link(i, i + 1, LinkType.NEIGHBOR, step, info) for i in range(11, 15)]
    guess = {i: transforms.from_xy_yaw(i - 1.0, 0.0, 0.0) for i in range(1, 6)}
    guess.update({i: transforms.from_xy_yaw(i - 11.0, 1.0, 0.0) for i in range(11, 16)})
    beside = transforms.from_xy_yaw(0.0, 1.0, 0.0)  # node 13 is 1 m to the side of node 3
    true = Link(3, 13, LinkType.LOOP_INTER, beside, info)
    result = optimize(guess, links + [true], 5, GraphParams(), planar=True)
    assert result.switched_off == [] and result.rejected == []
    false = Link(3, 13, LinkType.LOOP_INTER, transforms.from_xy_yaw(40.0, 1.0, 0.0), info)
    result = optimize(guess, links + [false], 5, GraphParams(), planar=True)
    assert result.rejected == [] and result.switched_off == [false]


def test_many_at_once_conversions_match_one_at_a_time(rng, random_se3):
    """The vectorised transforms read_g2o / write_g2o use agree with the one-pose functions,
    including rotations near 180 degrees (each quaternion branch)."""
    T = np.stack([random_se3() for _ in range(200)]
                 + [transforms.from_xyz_quat_xyzw([0, 0, 0], q) for q in np.eye(4)]
                 + [transforms.from_xyz_quat_xyzw([1, 2, 3], [1, 1e-9, 0, 1e-9])])
    q = transforms.quats_xyzw(T)
    assert np.allclose(q, [transforms.quat_xyzw(t) for t in T], atol=1e-12)
    assert np.allclose(transforms.from_xyz_quats_xyzw(T[:, :3, 3], q), T, atol=1e-12)
    xy_yaw = rng.uniform(-4, 4, (50, 3))
    assert np.allclose(transforms.from_xy_yaws(xy_yaw), [transforms.from_xy_yaw(*v) for v in xy_yaw])
    with pytest.raises(ValueError, match="quaternion 1 .* is not a rotation"):
        transforms.from_xyz_quats_xyzw(np.zeros((2, 3)), [[0, 0, 0, 1], [0, 0, 0, 0]])


def test_the_first_bad_link_is_named_when_links_are_checked_together():
    """Links are checked together before the factors are made: the message names the first bad one."""
    step = transforms.from_xy_yaw(1.0, 0.0, 0.0)
    poses = {i: transforms.from_xy_yaw(float(i), 0.0, 0.0) for i in range(4)}
    indefinite = np.eye(6)
    indefinite[0, 0] = -1.0
    links = [Link(0, 1, LinkType.NEIGHBOR, step, np.eye(6)), Link(1, 2, LinkType.NEIGHBOR, step, indefinite),
             Link(2, 3, LinkType.NEIGHBOR, step, indefinite.copy())]
    with pytest.raises(OptimizationError, match="link 1 -> 2: information matrix is not positive definite"):
        optimize(poses, links, 0, PLAIN, planar=True)
