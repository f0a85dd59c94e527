"""Loop closure registration: PnP and RANSAC on 3D words (TUM RGB-D ground truth, real loop pairs of a
hand-held Kinect), 2D ICP (Intel lab laser)."""

from __future__ import annotations

import functools
from dataclasses import replace

import cv2
import numpy as np
import pytest
from scipy.spatial import cKDTree

from rgbd_pairs import TUM_DEPTH_SCALE, load_tum, product_signatures
from rtabmap_ros2.core import transforms
from rtabmap_ros2.core.features import FeatureExtractor
from rtabmap_ros2.core.params import Params, RegistrationParams, default_config_path
from rtabmap_ros2.core.icp import icp_2d
from rtabmap_ros2.core.registration import (epipolar_check, matched_pairs, ransac_rigid, register, word_pairs,
                                            words_3d, words_within_depth)
from rtabmap_ros2.core.sensor import CameraModel
from rtabmap_ros2.core.signature import Signature
from rtabmap_ros2.core.vocabulary import Vocabulary
from rtabmap_ros2.errors import RegistrationError
from rtabmap_ros2.io.carmen import read_carmen_log

TUM_CAMERA = CameraModel(525.0, 525.0, 319.5, 239.5, 640, 480)  # T_base_camera = identity


def signatures_from_images(gray_a, depth_a, gray_b, depth_b, camera_b=TUM_CAMERA):
    """Two signatures whose word ids come from mutual ORB matches (distinct ids otherwise)."""
    orb = cv2.ORB_create(1000)
    ka, da = orb.detectAndCompute(gray_a, None)
    kb, db = orb.detectAndCompute(gray_b, None)
    matches = cv2.BFMatcher(cv2.NORM_HAMMING, crossCheck=True).match(da, db)
    ids_a = np.arange(len(ka), dtype=np.int64) + 1
    ids_b = np.arange(len(kb), dtype=np.int64) + 1 + len(ka)
    for m in matches:
        ids_b[m.trainIdx] = ids_a[m.queryIdx]
    kpa = np.array([k.pt for k in ka], np.float32)
    kpb = np.array([k.pt for k in kb], np.float32)
    sa = Signature(1, 1, 0, ids_a, kpa, words_3d(kpa, depth_a, TUM_CAMERA))
    sb = Signature(2, 1, 0, ids_b, kpb, words_3d(kpb, depth_b, camera_b))
    return sa, sb


def test_words_3d_back_projects_and_marks_invalid():
    depth = np.full((480, 640), 2.0, np.float32)
    depth[100, 200] = np.nan
    T_base_camera = transforms.from_xyz_quat_xyzw([0.1, 0, 0.5], [0.5, -0.5, 0.5, -0.5])  # optical -> base
    cam = CameraModel(525, 525, 319.5, 239.5, 640, 480, T_base_camera)
    pts = words_3d(np.array([[319.5, 239.5], [200.2, 99.7], [844.5, 10.0], [319.5 + 262.5, 239.5]]), depth, cam)
    assert pts.dtype == np.float32
    # Centre pixel: 2 m along the optical axis = base x with this mounting.
    assert np.allclose(pts[0], [2.1, 0.0, 0.5], atol=1e-5)
    assert np.isnan(pts[1]).all() and np.isnan(pts[2]).all()  # NaN depth (rounded pixel); outside
    assert np.allclose(pts[3], [2.1, -1.0, 0.5], atol=1e-5)  # 1 m right in optical x = -y in base



def test_words_of_raw_images_lie_on_their_undistorted_rays():
    """Images that are not rectified (a CameraInfo's D, P = K): a point seen at its distorted pixel is
    placed along its true ray at the depth read at that pixel, and its keypoint becomes the pinhole's."""
    fr1 = (0.2624, -0.9531, -0.0054, 0.0026, 1.1633)
    raw = CameraModel(517.3, 516.5, 318.6, 255.3, 640, 480, distortion=fr1)
    pinhole = CameraModel(517.3, 516.5, 318.6, 255.3, 640, 480)
    truth = np.array([[0.7, -0.5, 1.5], [-0.8, 0.5, 2.0], [0.05, 0.02, 1.0]])   # optical frame, m
    K = np.array([[517.3, 0, 318.6], [0, 516.5, 255.3], [0, 0, 1.0]])
    seen, _ = cv2.projectPoints(truth, np.zeros(3), np.zeros(3), K, np.array(fr1))
    seen = seen.reshape(-1, 2)
    assert np.abs(seen - pinhole.project(truth)).max() > 5.0          # the lens moves the corners by pixels
    depth = np.zeros((480, 640), np.float32)
    for (u, v), z in zip(np.rint(seen).astype(int), truth[:, 2]):
        depth[v, u] = z
    np.testing.assert_allclose(words_3d(seen, depth, raw), truth, atol=1e-3)
    np.testing.assert_allclose(raw.undistort(seen), pinhole.project(truth), atol=0.01)
    np.testing.assert_array_equal(pinhole.undistort(seen), seen.astype(np.float32))   # rectified: as they are
    assert raw.scaled(320, 240).distortion == fr1

@pytest.mark.parametrize("case", ["case_1", "case_2"])
def test_3d_ransac_recovers_tum_relative_pose(shared_data, case):
    folder = shared_data / "rgbd" / "tum_fr1_xyz_pairs" / case
    gray_a, depth_a, pose_a = load_tum(folder, "prev")
    gray_b, depth_b, pose_b = load_tum(folder, "curr")
    sa, sb = signatures_from_images(gray_a, depth_a, gray_b, depth_b)
    reg = register(sa, sb, RegistrationParams(planar=False, icp_refine=False))
    truth = transforms.relative(pose_a, pose_b)
    err = transforms.inverse(truth) @ reg.T_from_to
    t_err, r_err = np.linalg.norm(err[:3, 3]), np.degrees(transforms.rotation_angle(err))
    print(f"{case}: {reg.inliers} inliers, translation error {t_err * 100:.2f} cm, rotation error {r_err:.3f} deg "
          f"(motion {np.linalg.norm(truth[:3, 3]) * 100:.1f} cm, {np.degrees(transforms.rotation_angle(truth)):.2f} deg)")
    assert t_err < 0.03 and r_err < 2.0
    assert reg.inliers >= 20 and not reg.icp_refined
    assert np.all(np.linalg.eigvalsh(reg.information) > 0)


def test_planar_projection_keeps_x_y_yaw(rng):
    points = rng.uniform(-3, 3, (200, 3))
    T_true = transforms.from_xy_yaw(0.4, -0.2, 0.3) @ transforms.from_xyz_quat_xyzw([0, 0, 0.05], [0.02, 0.01, 0, 1])
    to_points = (points - T_true[:3, 3]) @ T_true[:3, :3]  # from = T @ to
    ids = np.arange(200, dtype=np.int64)
    sa = Signature(1, 1, 0, ids, np.zeros((200, 2), np.float32), points.astype(np.float32))
    sb = Signature(2, 1, 0, ids, np.zeros((200, 2), np.float32), to_points.astype(np.float32))
    reg = register(sa, sb, RegistrationParams(planar=True, icp_refine=False))
    T = reg.T_from_to
    assert np.allclose(T[2, :3], [0, 0, 1]) and T[2, 3] == 0  # no z, roll, pitch left
    assert np.allclose(transforms.to_xy_yaw(T), (0.4, -0.2, 0.3), atol=0.02)


def test_too_few_inliers_raises(rng):
    ids = np.arange(30, dtype=np.int64)
    sa = Signature(1, 1, 0, ids, np.zeros((30, 2), np.float32), rng.uniform(-3, 3, (30, 3)).astype(np.float32))
    sb = Signature(2, 1, 0, ids, np.zeros((30, 2), np.float32), rng.uniform(-3, 3, (30, 3)).astype(np.float32))
    with pytest.raises(RegistrationError, match="inliers < min_inliers"):
        register(sa, sb, RegistrationParams(min_inliers=10))
    few = Signature(3, 1, 0, ids[:5], np.zeros((5, 2), np.float32), sa.points3d[:5])
    with pytest.raises(RegistrationError, match="min_inliers"):
        register(sa, few, RegistrationParams(min_inliers=10))


def test_ransac_keeps_the_true_pairs_among_outliers_and_refuses_collinear_words(rng):
    to_points = rng.uniform(-3, 3, (120, 3))
    T_true = transforms.from_xy_yaw(0.7, -0.3, 0.4) @ transforms.from_xyz_quat_xyzw([0, 0, 0.1], [0.05, -0.03, 0, 1])
    from_points = to_points @ T_true[:3, :3].T + T_true[:3, 3] + rng.normal(0, 0.005, (120, 3))
    wrong = rng.choice(120, 40, replace=False)
    from_points[wrong] = rng.uniform(-3, 3, (40, 3))  # a third of the pairs matched the wrong word
    T, inliers = ransac_rigid(from_points, to_points, 0.1, 500, np.random.default_rng(0))
    assert np.abs(T[:3, 3] - T_true[:3, 3]).max() < 0.01
    assert transforms.rotation_angle(transforms.inverse(T) @ T_true) < np.radians(0.5)
    assert not inliers[wrong].any() and inliers.sum() == 80
    on_a_line = np.outer(np.linspace(0, 2, 30), [1.0, 0.5, 0.2])
    with pytest.raises(RegistrationError, match="degenerate"):
        ransac_rigid(on_a_line, on_a_line, 0.1, 100, np.random.default_rng(0))


def read_carmen(path):
    """(LaserScans, corrected poses) of a CARMEN log."""
    log = read_carmen_log(path)
    return log.laser_scans(), log.poses()


@functools.lru_cache(maxsize=1)
def _read_carmen_cached(path):
    return read_carmen(path)


@pytest.fixture
def intel(shared_data):
    path = shared_data / "carmen" / "intel-corrected.log.gz"
    if not path.exists():
        pytest.skip(f"{path} absent")
    return _read_carmen_cached(path)


def test_icp_recovers_corrected_relative_pose(intel):
    scans, poses = intel
    perturbation = transforms.from_xy_yaw(0.10, 0.0, np.radians(3.0))
    errors = []
    for k in range(0, len(scans) - 5, 10):
        truth = transforms.relative(poses[k], poses[k + 5])
        source, target = scans[k + 5].points_base(), scans[k].points_base()
        # Only pairs that see the same structure (>= 50 % of points within 10 cm at the reference).
        d, _ = cKDTree(target).query(source @ truth[:2, :2].T + truth[:2, 3])
        if np.mean(d < 0.1) < 0.5:
            continue
        T, overlap, rmse = icp_2d(source, target, truth @ perturbation)
        err = transforms.inverse(truth) @ T
        errors.append((np.hypot(err[0, 3], err[1, 3]), abs(np.degrees(transforms.yaw_of(err)))))
    errors = np.array(errors)
    median = np.median(errors, axis=0)
    print(f"ICP over {len(errors)} pairs k -> k+5: median error {median[0] * 100:.2f} cm, {median[1]:.3f} deg "
          f"(start: 10 cm, 3 deg)")
    assert len(errors) >= 10
    # The corrected log itself is good to a few cm: the median error stays at that level.
    assert median[0] < 0.05 and median[1] < 1.0


def _scan_signature(node_id, points3d, ids, scan):
    return Signature(node_id, 1, 0, ids, np.zeros((len(ids), 2), np.float32), points3d.astype(np.float32),
                     scan=scan)


def test_icp_refinement_and_rejection(intel, rng):
    scans, poses = intel
    k = 240
    truth = transforms.relative(poses[k], poses[k + 5])
    # Visual words consistent with a 5 cm / 2 deg wrong visual estimate.
    visual = truth @ transforms.from_xy_yaw(0.05, 0.0, np.radians(2.0))
    pts_from = rng.uniform(-3, 3, (100, 3))
    pts_to = (pts_from - visual[:3, 3]) @ visual[:3, :3]
    ids = np.arange(100, dtype=np.int64)
    sa = _scan_signature(1, pts_from, ids, scans[k])
    sb = _scan_signature(2, pts_to, ids, scans[k + 5])
    params = RegistrationParams(planar=True, icp_refine=True)
    reg = register(sa, sb, params)
    assert reg.icp_refined
    err_icp = np.linalg.norm((transforms.inverse(truth) @ reg.T_from_to)[:2, 3])
    err_visual = np.linalg.norm((transforms.inverse(truth) @ visual)[:2, 3])
    assert err_icp < err_visual / 2
    # Scans from far apart places (no overlap): the loop closure is rejected, not kept visually.
    sc = _scan_signature(3, pts_to, ids, scans[k + 300])
    with pytest.raises(RegistrationError, match="ICP"):
        register(sa, sc, params)
    # Without icp_refine the same pair is accepted on the visual estimate alone.
    assert not register(sa, sc, RegistrationParams(planar=True, icp_refine=False)).icp_refined


def test_epipolar_check_accepts_a_consistent_view_and_rejects_a_chance_overlap():
    """RTAB-Map's VhEp check: pairs of words found once in both images must fit a fundamental matrix."""
    rng = np.random.default_rng(4)
    points = rng.uniform((0, 0), (640, 480), (120, 2)).astype(np.float32)
    # The same wall seen again, turned by 2 degrees, 3 % closer, shifted: every pair fits.
    H = cv2.getRotationMatrix2D((320, 240), 2.0, 1.03)
    moved = (points @ H[:, :2].T + H[:, 2] + (40, -15) + rng.normal(0, 0.5, points.shape)).astype(np.float32)
    ids = np.arange(1, 121, dtype=np.int64)
    a = Signature(1, 1, 0, ids, points)
    b = Signature(2, 1, 0, ids, moved)
    inliers, coverage = epipolar_check(a, b, 8, 3.0, 0.99)
    assert inliers >= 110 and coverage > 0.9
    assert epipolar_check(a, b, 8, 3.0, 0.99) == (inliers, coverage)  # deterministic
    # Ten words shared by chance, anywhere in the other image: a fundamental matrix fits 7 of any 10.
    chance = Signature(3, 1, 0, np.r_[ids[:10], ids[10:] + 1000], rng.uniform((0, 0), (640, 480), (120, 2)))
    assert epipolar_check(a, chance, 8, 3.0, 0.99)[0] < 8
    # Fewer pairs than needed: 0 without fitting. A word seen twice in an image makes no pair.
    assert epipolar_check(a, Signature(4, 1, 0, np.r_[ids[:7], ids[7:] + 1000], moved), 8, 3.0, 0.99) == (0, 0.0)
    twice = np.r_[ids[:60], ids[:60]]
    assert epipolar_check(a, Signature(5, 1, 0, twice, moved), 8, 3.0, 0.99) == (0, 0.0)


def test_epipolar_coverage_is_small_when_only_one_object_of_the_image_matches():
    """A poster seen again elsewhere: its words fit a fundamental matrix, but cover a corner only."""
    rng = np.random.default_rng(5)
    poster = rng.uniform((40, 40), (160, 130), (40, 2))  # 120 x 90 px of a 640 x 480 image
    around = rng.uniform((0, 0), (640, 480), (200, 2))
    ids = np.arange(1, 241, dtype=np.int64)
    a = Signature(1, 1, 0, ids, np.r_[poster, around])
    b = Signature(2, 1, 0, np.r_[ids[:40], ids[40:] + 1000], np.r_[poster + (300, 200), around[::-1]])
    inliers, coverage = epipolar_check(a, b, 8, 3.0, 0.99)
    assert inliers >= 35
    assert coverage < 0.05


# -- PnP (registration.estimation = pnp, RTAB-Map's Vis/EstimationType 1) ------------------------------

# Issue 49's yardstick: an accepted loop closure farther than this from the ground truth is off.
OFF_M, OFF_DEG = 0.03, 1.5
# Real loop pairs whose two images agree with the motion capture (their photometric optimum within
# 1 cm / 0.6 deg of it, bench/bench_registration.py): what an estimator gets there is its own error.
AGREEING_LOOP_PAIRS = ("case_11", "case_18", "case_22", "case_23")


def _errors(T, truth):
    e = transforms.inverse(truth) @ T
    return float(np.linalg.norm(e[:3, 3])), float(np.degrees(transforms.rotation_angle(e)))


@pytest.fixture
def slam_params() -> Params:
    """config/rtabmap.yaml in 6 DoF (Reg/Force3DoF false), without a laser."""
    params = Params.from_yaml(default_config_path())
    return params.with_value("registration.planar", False).with_value("registration.icp_refine", False)


@pytest.mark.parametrize("case", ["case_1", "case_2"])
def test_pnp_recovers_slow_tum_pairs_within_a_centimetre(shared_data, slam_params, case):
    new, old, descriptors, truth = product_signatures(shared_data / "rgbd" / "tum_fr1_xyz_pairs" / case, slam_params)
    reg = register(new, old, slam_params.registration, descriptors=descriptors)
    t_err, r_err = _errors(reg.T_from_to, truth)
    assert reg.inliers >= slam_params.registration.min_inliers and not reg.icp_refined
    assert t_err < 0.01 and r_err < 0.5, (t_err, r_err)
    assert np.all(np.linalg.eigvalsh(reg.information) > 0)


@pytest.mark.parametrize("case", AGREEING_LOOP_PAIRS)
def test_pnp_loop_closure_on_real_hand_held_pairs_is_within_the_issue_tolerance(shared_data, slam_params, case):
    """Loop pairs of a hand-held Kinect turning fast (fr1_rpy: motion blur, rolling shutter, 7-30 deg
    apart) where the images agree with the motion capture: accepted, within 3 cm and 1.5 deg, and
    the link's standard deviations are not smaller than its error by more than the 3 std devs the
    graph check allows."""
    new, old, descriptors, truth = product_signatures(shared_data / "rgbd" / "tum_fr1_rpy_loops" / case, slam_params)
    reg = register(new, old, slam_params.registration, descriptors=descriptors)
    t_err, r_err = _errors(reg.T_from_to, truth)
    print(f"{case}: {reg.inliers} inliers, {t_err * 100:.2f} cm, {r_err:.2f} deg")
    assert t_err < OFF_M and r_err < OFF_DEG
    sigma_t = 1 / np.sqrt(reg.information[:3, :3].diagonal().min())
    sigma_r = np.degrees(1 / np.sqrt(reg.information[3:, 3:].diagonal().min()))
    assert t_err < 3 * sigma_t and r_err < 3 * sigma_r


def test_vis_depth_limits_register_from_the_words_within_them(shared_data, slam_params):
    """RTAB-Map's Vis/MinDepth, Vis/MaxDepth: the transform comes from the words within the limits
    only (both nodes; words without depth left out too): a limit beyond the scene gives the slow pair
    within a centimetre still, one in front of it leaves too few words."""
    new, old, descriptors, truth = product_signatures(shared_data / "rgbd" / "tum_fr1_xyz_pairs" / "case_1",
                                                      slam_params)
    within = replace(slam_params.registration, min_depth=0.3, max_depth=8.0)
    kept, indices = words_within_depth(new, within)
    depth = (kept.points3d @ np.linalg.inv(new.camera.T_base_camera)[:3, :3].T
             + np.linalg.inv(new.camera.T_base_camera)[:3, 3])[:, 2]
    assert 0 < len(kept.word_ids) < len(new.word_ids) and ((depth > 0.3) & (depth <= 8.0)).all()
    np.testing.assert_array_equal(kept.word_ids, new.word_ids[indices])
    reg = register(new, old, within, descriptors=descriptors)
    t_err, r_err = _errors(reg.T_from_to, truth)
    assert t_err < 0.01 and r_err < 0.5, (t_err, r_err)
    with pytest.raises(RegistrationError):
        register(new, old, replace(slam_params.registration, max_depth=0.4), descriptors=descriptors)


def test_guided_matching_finds_the_matches_the_shared_words_missed(shared_data, slam_params):
    """A pair turning fast (fr1_rpy case 18) shares too few words for min_inliers with
    config/rtabmap.yaml's word search; matching the keypoints around where the first estimate
    projects them finds enough, and the estimate agrees with the motion capture."""
    new, old, descriptors, truth = product_signatures(shared_data / "rgbd" / "tum_fr1_rpy_loops" / "case_18",
                                                      slam_params)
    without = replace(slam_params.registration, guided_window=0.0)
    with pytest.raises(RegistrationError, match="PnP inliers < min_inliers"):
        register(new, old, without, descriptors=descriptors)
    with pytest.raises(RegistrationError):
        register(new, old, slam_params.registration)  # no descriptors: the shared words only
    reg = register(new, old, slam_params.registration, descriptors=descriptors)
    assert reg.inliers >= slam_params.registration.min_inliers
    t_err, r_err = _errors(reg.T_from_to, truth)
    assert t_err < OFF_M and r_err < OFF_DEG


@pytest.mark.parametrize("case", ["case_03", "case_20"])
def test_pnp_rejects_a_real_loop_closure_whose_words_still_disagree_by_centimetres(shared_data, slam_params, case):
    """RTAB-Map's Vis/PnPMaxVariance on hand-held pairs turning fast (fr1_rpy 03 and 20):
    PnP finds enough inliers, but their 3D words still disagree by more than 5 cm (standard deviation)
    and the estimate is off the motion capture by more than 3 cm or 1.5 deg; such a loose link would
    pass the graph check, so registration rejects it. Without the limit it is accepted."""
    new, old, descriptors, truth = product_signatures(shared_data / "rgbd" / "tum_fr1_rpy_loops" / case, slam_params)
    limit = slam_params.registration.pnp_max_variance
    assert limit > 0
    with pytest.raises(RegistrationError, match="pnp_max_variance"):
        register(new, old, slam_params.registration, descriptors=descriptors)
    reg = register(new, old, replace(slam_params.registration, pnp_max_variance=0.0), descriptors=descriptors)
    assert reg.inliers >= slam_params.registration.min_inliers
    assert 1 / reg.information[0, 0] > limit
    t_err, r_err = _errors(reg.T_from_to, truth)
    assert t_err > OFF_M or r_err > OFF_DEG


def test_pnp_max_variance_keeps_the_slow_pairs(shared_data, slam_params):
    """The limit is far above what PnP leaves on slow real pairs (fr1_xyz: 1.0-1.3 cm)."""
    for case in ("case_1", "case_2"):
        new, old, descriptors, _ = product_signatures(shared_data / "rgbd" / "tum_fr1_xyz_pairs" / case, slam_params)
        reg = register(new, old, slam_params.registration, descriptors=descriptors)
        assert 1 / reg.information[0, 0] < 0.25 * slam_params.registration.pnp_max_variance


def test_pnp_rejects_frames_of_another_scene(shared_data, slam_params):
    tum = shared_data / "rgbd" / "tum_fr1_xyz_pairs" / "case_1"
    other = shared_data / "rgbd" / "rtabmap_frames"
    camera = CameraModel(525.0, 525.0, 319.5, 239.5, 640, 480)
    extractor = FeatureExtractor(slam_params.features)
    vocabulary = Vocabulary(slam_params.vocabulary, True, background_rebuild=False)
    made = []
    for k, (rgb_path, depth, scale) in enumerate((
            (tum / "img_prev.png", tum / "dep_prev.png", TUM_DEPTH_SCALE),
            (sorted((other / "rgb").glob("*.jpg"))[0], sorted((other / "depth").glob("*.png"))[0], 1000.0))):
        features = extractor.extract(cv2.cvtColor(cv2.imread(str(rgb_path)), cv2.COLOR_BGR2RGB))
        depth_m = cv2.imread(str(depth), cv2.IMREAD_UNCHANGED).astype(np.float32) / scale
        depth_m[depth_m == 0] = np.nan
        made.append(Signature(k + 1, 1, 0, vocabulary.quantize(features.descriptors)[0], features.keypoints,
                              words_3d(features.keypoints, depth_m, camera), camera=camera))
    descriptors = tuple(vocabulary.descriptors_of(s.word_ids) for s in made)
    with pytest.raises(RegistrationError):
        register(made[1], made[0], slam_params.registration, descriptors=descriptors[::-1])


def _synthetic_views(rng, T_world_a, T_world_b, T_base_camera, n=200, noise_px=0.3):
    """Two views of random points 1-4 m in front of the cameras: signatures a (from) and b (to) with
    shared word ids, keypoints with pixel noise, 3D words from exact depth; and the truth T_a_b."""
    camera = CameraModel(520.0, 515.0, 320.0, 240.0, 640, 480, T_base_camera)
    T_world_cam_a = T_world_a @ T_base_camera
    in_cam = np.column_stack([rng.uniform(-1.2, 1.2, n), rng.uniform(-0.9, 0.9, n), rng.uniform(1.0, 4.0, n)])
    world = in_cam @ T_world_cam_a[:3, :3].T + T_world_cam_a[:3, 3]
    signatures = []
    for node, T_world in ((1, T_world_a), (2, T_world_b)):
        T_cam_world = transforms.inverse(T_world @ T_base_camera)
        X = world @ T_cam_world[:3, :3].T + T_cam_world[:3, 3]
        uv = camera.project(X) + rng.normal(0, noise_px, (n, 2))
        points = (X @ T_base_camera[:3, :3].T + T_base_camera[:3, 3]).astype(np.float32)
        signatures.append(Signature(node, 1, 0, np.arange(1, n + 1, dtype=np.int64), uv.astype(np.float32), points,
                                    camera=camera))
    return signatures[0], signatures[1], transforms.relative(T_world_a, T_world_b)


def test_pnp_recovers_a_synthetic_motion_with_the_camera_mounted_off_the_base(rng):
    """T_from_to's convention (from_points = T @ to_points, base frames) holds with a camera that is
    neither at the base's origin nor looking along its x axis; 30 % of the pairs are wrong."""
    T_base_camera = transforms.from_xyz_rpy([0.2, -0.05, 0.6, -np.pi / 2 - 0.1, 0.05, -np.pi / 2])
    T_world_a = transforms.from_xyz_rpy([1.0, 2.0, 0.0, 0.02, -0.03, 0.4])
    T_world_b = T_world_a @ transforms.from_xyz_rpy([0.15, -0.08, 0.02, 0.03, 0.05, -0.2])
    a, b, truth = _synthetic_views(rng, T_world_a, T_world_b, T_base_camera)
    wrong = rng.choice(len(b.word_ids), 60, replace=False)
    b.word_ids[wrong] = b.word_ids[np.roll(wrong, 1)]  # 60 words paired with the wrong feature
    for bundle_adjustment in (False, True):
        reg = register(a, b, RegistrationParams(planar=False, icp_refine=False, bundle_adjustment=bundle_adjustment))
        t_err, r_err = _errors(reg.T_from_to, truth)
        assert t_err < 0.005 and r_err < 0.1, (bundle_adjustment, t_err, r_err)
        assert 130 <= reg.inliers <= 145  # the 140 right pairs (a wrong one may fall near its truth)
    planar = register(a, b, RegistrationParams(planar=True, icp_refine=False))
    assert np.allclose(planar.T_from_to[2, :3], [0, 0, 1]) and planar.T_from_to[2, 3] == 0


def test_pnp_uses_the_node_with_more_depth_and_rejects_too_few_inliers(rng):
    """Without depth on the from side the PnP runs the other way (to words in the from image)."""
    a, b, truth = _synthetic_views(rng, transforms.identity(), transforms.from_xyz_rpy([0.1, 0, 0, 0, 0.1, 0]),
                                   transforms.from_xyz_rpy([0, 0, 0, -np.pi / 2, 0, -np.pi / 2]))
    a.points3d[:] = np.nan
    reg = register(a, b, RegistrationParams(planar=False, icp_refine=False))
    assert _errors(reg.T_from_to, truth)[0] < 0.005
    with pytest.raises(RegistrationError, match="PnP inliers < min_inliers=500"):
        register(a, b, RegistrationParams(planar=False, icp_refine=False, min_inliers=500))
    b.points3d[:] = np.nan
    with pytest.raises(RegistrationError, match="with depth"):
        register(a, b, RegistrationParams(planar=False, icp_refine=False))


def test_auto_estimation_is_pnp_in_6dof_and_the_papers_ransac_under_planar_icp():
    """``estimation: auto``: PnP for a camera in 6 DoF (and planar without scans to refine on); the
    2014 paper's RANSAC on 3D words when 2D ICP on the laser scans decides x, y and yaw anyway."""
    from rtabmap_ros2.core.params import Params as AllParams
    from rtabmap_ros2.core.registration import uses_pnp

    auto = RegistrationParams()
    assert auto.estimation == "auto"
    assert uses_pnp(replace(auto, planar=False), icp_refined=True)
    assert uses_pnp(replace(auto, planar=True), icp_refined=False)
    assert not uses_pnp(replace(auto, planar=True), icp_refined=True)
    assert uses_pnp(replace(auto, estimation="pnp", planar=True), icp_refined=True)
    assert not uses_pnp(replace(auto, estimation="3d", planar=False), icp_refined=False)
    # RTAB-Map's names: Vis/EstimationType 0 / 1, and one it has that we do not.
    assert AllParams().with_overrides(["Vis/EstimationType=1"]).registration.estimation == "pnp"
    assert AllParams().with_overrides(["Vis/EstimationType=0"]).registration.estimation == "3d"
    with pytest.raises(Exception, match="estimation"):
        AllParams().with_overrides(["Vis/EstimationType=2"])
    assert AllParams().with_overrides(["Vis/PnPMaxVariance=0.01"]).registration.pnp_max_variance == 0.01


def test_auto_estimation_follows_the_planar_flag_as_defaulted_and_configured():
    """Reg/Force3DoF is false by default (6 DoF: PnP even with scans); config/rtabmap.yaml sets it for
    its wheeled robot with a laser, whose loop closures stay the paper's 3D-3D RANSAC then 2D ICP."""
    from rtabmap_ros2.core.params import Params as AllParams
    from rtabmap_ros2.core.registration import uses_pnp

    defaults = AllParams().registration
    assert not defaults.planar and uses_pnp(defaults, icp_refined=True)
    configured = AllParams.from_yaml(default_config_path()).registration
    assert configured.planar and not uses_pnp(configured, icp_refined=True)
    assert uses_pnp(configured, icp_refined=False)


def test_matching_the_two_nodes_features_pairs_what_their_shared_words_miss(shared_data, slam_params):
    """fr1_rpy case 20 (78 deg/s): config/rtabmap.yaml's approximate word search gave the two views
    too few shared words for the 2014 paper's 3D-3D estimate (19 inliers < 20); matching the two
    nodes' descriptors (RTAB-Map's Vis/CorType 0) keeps every shared-word pair and adds the ones
    whose features fell on neighbouring words, and the estimate is accepted within 3 cm / 1.5 deg."""
    params = replace(slam_params.registration, estimation="3d")
    new, old, descriptors, truth = product_signatures(shared_data / "rgbd" / "tum_fr1_rpy_loops" / "case_20",
                                                      slam_params)
    words = set(zip(*(a.tolist() for a in word_pairs(new, old))))
    matched = set(zip(*(a.tolist() for a in matched_pairs(new, old, descriptors))))
    assert words <= matched and len(matched) > len(words)
    assert len({f for f, _ in matched}) == len(matched) == len({t for _, t in matched})  # each feature once
    with pytest.raises(RegistrationError, match="inliers < min_inliers"):
        register(new, old, params)  # no descriptors: the shared words only
    reg = register(new, old, params, descriptors=descriptors)
    t_err, r_err = _errors(reg.T_from_to, truth)
    assert reg.inliers >= params.min_inliers and t_err < OFF_M and r_err < OFF_DEG, (reg.inliers, t_err, r_err)
