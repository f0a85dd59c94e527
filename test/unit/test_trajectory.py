"""TUM trajectories, rigid alignment (Umeyama without scale) and ATE."""

from __future__ import annotations

import numpy as np
import pytest

from rtabmap_ros2.core import transforms
from rtabmap_ros2.errors import DatasetError
from rtabmap_ros2.io.trajectory import (Trajectory, align_rigid, associate, ate, read_tum, seconds_to_ns, stamp_text,
                                       write_tum)

NS = 1_000_000_000


def random_walk(rng, n: int = 200) -> Trajectory:
    """A planar-ish wandering trajectory, 1 Hz stamps from a large epoch."""
    poses = [transforms.identity()]
    for _ in range(n - 1):
        step = transforms.from_xy_yaw(rng.uniform(0.2, 0.5), rng.normal(0, 0.05), rng.normal(0, 0.2), rng.normal(0, 0.01))
        poses.append(poses[-1] @ step)
    stamps = 1_700_000_000 * NS + np.arange(n, dtype=np.int64) * NS + 123_456_789
    return Trajectory(stamps, np.stack(poses))


def test_tum_round_trip_keeps_stamps_exactly(tmp_path, rng, random_se3):
    poses = np.stack([random_se3() for _ in range(5)])
    stamps = np.array([1_700_000_000_000_000_001, 1_700_000_000_500_000_000, 2, 3, 4], np.int64)
    write_tum(tmp_path / "t.txt", stamps, poses, header="stamp x y z qx qy qz qw")
    back = read_tum(tmp_path / "t.txt")
    np.testing.assert_array_equal(back.stamps_ns, stamps)
    np.testing.assert_allclose(back.poses, poses, atol=2e-6)
    assert (tmp_path / "t.txt").read_text().splitlines()[1].split()[0] == "1700000000.000000001"


@pytest.mark.parametrize("stamp_ns, text", [(1305031229528748000, "1305031229.528748000"), (0, "0.000000000"),
                                            (5, "0.000000005"), (-1_500_000_000, "-1.500000000")])
def test_stamp_text_is_exact(stamp_ns, text):
    """Integer arithmetic: a float division gave 1305031229.528748035 for the first (issue 49)."""
    assert stamp_text(stamp_ns) == text and seconds_to_ns(text) == stamp_ns


def test_read_tum_names_the_bad_line(tmp_path):
    (tmp_path / "t.txt").write_text("# header\n1.0 0 0 0 0 0 0 1\n2.0 0 0 0 0 0 1\n")
    with pytest.raises(DatasetError, match=r"t.txt:3: expected 8 values"):
        read_tum(tmp_path / "t.txt")


def test_align_rigid_recovers_transform(rng, random_se3):
    pts = rng.uniform(-5, 5, (50, 3))
    T = random_se3()
    moved = pts @ T[:3, :3].T + T[:3, 3]
    np.testing.assert_allclose(align_rigid(pts, moved), T, atol=1e-9)


def test_align_rigid_never_reflects(rng):
    pts = rng.uniform(-1, 1, (30, 3))
    mirrored = pts * np.array([1, 1, -1])
    T = align_rigid(pts, mirrored)
    assert np.linalg.det(T[:3, :3]) == pytest.approx(1.0)


def test_ate_is_invariant_to_one_rigid_transform_and_measures_noise(rng, random_se3):
    gt = random_walk(rng)
    T = random_se3()
    noise = rng.normal(0, 0.03, (len(gt), 3))
    est_poses = np.einsum("ij,njk->nik", T, gt.poses)
    est_poses[:, :3, 3] += noise
    est = Trajectory(gt.stamps_ns + 1_000_000, est_poses)  # 1 ms stamp offset: still matched
    result = ate(est, gt)
    assert result.matched == len(gt)
    # RMSE of 3D Gaussian noise sigma 3 cm is about sqrt(3) x 3 cm.
    assert result.rmse_m == pytest.approx(np.sqrt(3) * 0.03, rel=0.15)
    np.testing.assert_allclose(result.T_gt_est[:3, :3], transforms.inverse(T)[:3, :3], atol=0.01)


def test_ate_sees_drift_that_one_alignment_cannot_remove(rng):
    gt = random_walk(rng)
    drift = np.stack([transforms.from_xy_yaw(0, 0, 0.002 * k) for k in range(len(gt))])
    est = Trajectory(gt.stamps_ns, np.einsum("nij,njk->nik", drift, gt.poses))
    assert ate(est, gt).rmse_m > 0.05
    assert ate(gt, gt).rmse_m < 1e-9


def test_associate_tolerance_and_one_to_one():
    a = np.array([0, 10, 20, 1000], np.int64) * 1_000_000  # ms -> ns
    b = np.array([1, 11, 12, 500], np.int64) * 1_000_000
    ia, ib = associate(a, b, max_difference_s=0.005)
    assert sorted(zip(ia.tolist(), ib.tolist())) == [(0, 0), (1, 1)]


def test_ate_without_common_stamps_raises(rng):
    gt = random_walk(rng, 10)
    with pytest.raises(DatasetError, match="match a ground-truth stamp"):
        ate(Trajectory(gt.stamps_ns + 10 * NS * 1000, gt.poses), gt)


def test_ate_sessions_matches_each_session_with_its_own_ground_truth():
    """Two robots with the same stamps: matched by stamp alone, they would mix (ate() needs unique
    stamps); per session, an estimate off by a rigid motion has no error, a moved node some."""
    from rtabmap_ros2.core import transforms
    from rtabmap_ros2.io.trajectory import Trajectory, ate_sessions

    stamps = np.arange(10, dtype=np.int64) * 1_000_000_000
    line = np.stack([transforms.from_xyz_rpy([x, 0, 0, 0, 0, 0]) for x in range(10)])
    other = np.stack([transforms.from_xyz_rpy([0, y, 0, 0, 0, 0]) for y in range(10)])
    truths = {0: Trajectory(stamps, line), 1: Trajectory(stamps, other)}
    moved = transforms.from_xyz_rpy([3, -2, 0, 0, 0, 0.4])
    estimates = {k: Trajectory(t.stamps_ns, moved @ t.poses) for k, t in truths.items()}
    result = ate_sessions(estimates, truths)
    assert result.matched == 20 and result.rmse_m < 1e-9
    estimates[1].poses[4, 0, 3] += 0.5
    assert ate_sessions(estimates, truths).max_m > 0.3
    with pytest.raises(DatasetError, match="no ground truth"):
        ate_sessions(estimates, {0: truths[0]})
