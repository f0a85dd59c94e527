"""Loop closure verification (2014 §II-A): a rigid transform between two nodes.

The RGB image's visual words get a 3D position from the registered depth image
(:func:`words_3d`). When a loop closure is detected, the words that occur exactly once in both
signatures are the correspondences, and the rigid transform is estimated one of two ways
(``registration.estimation``, RTAB-Map's Vis/EstimationType):

* ``pnp`` (RTAB-Map's default, 1; :func:`register_pnp`; ``auto`` in 6 DoF): the 3D words of one
  node against the 2D keypoints of the other, RANSAC on the reprojection error in pixels
  (``cv2.solvePnPRansac``),
  refined on the inliers of both directions (each node's words, from its own depth, reprojected in
  the other's image: a two-view bundle adjustment of the pose), optionally with more matches found
  around where the first estimate projects the keypoints (``guided_window``);
* ``3d`` (the 2014 paper's, 0; ``auto`` when planar with laser scans, ICP then deciding x, y and
  yaw): RANSAC on the 3D-3D correspondences (Kabsch / Umeyama without
  scale on 3 samples, every hypothesis scored against all correspondences, in compiled loops), refit
  by reweighted least squares.

The loop closure is accepted with at least ``I`` (``min_inliers``) inliers. On a robot moving on a
plane the transform is limited to x, y, yaw and refined with 2D point-to-line ICP on the laser
scans of the two nodes (core/icp.py).

Frames: a transform ``T_from_to`` maps points of the *to* node's base frame into the *from*
node's base frame (``from_points ≈ T_from_to @ to_points``); it equals
``inv(pose_from) @ pose_to``, the ``T_from_to`` of a :class:`~rtabmap_ros2.core.graph.Link`.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace

import cv2
import numpy as np
import scipy.linalg
from scipy.spatial import cKDTree

from rtabmap_ros2.core import icp, transforms
from rtabmap_ros2.core.compiled import jit
from rtabmap_ros2.core.grid import voxel_filter
from rtabmap_ros2.core.icp import icp_fit
from rtabmap_ros2.core.params import RegistrationParams
from rtabmap_ros2.core.sensor import CameraModel, LaserScan, depth_in_range
from rtabmap_ros2.core.signature import Signature
from rtabmap_ros2.errors import RegistrationError

logger = logging.getLogger(__name__)

# RANSAC: seed used when the caller gives no generator, so loop closures are reproducible.
DEFAULT_SEED = 0
# RANSAC: a 3-point sample whose triangle is smaller than this (area, m^2) is degenerate.
MIN_SAMPLE_AREA = 1e-4
# RANSAC refit: iteratively reweighted least squares, Cauchy scale = this ratio x inlier_distance
# (0.2 x 0.1 m = 2 cm, about the Kinect's depth noise at 2 m).
IRLS_SCALE_RATIO = 0.2
IRLS_ITERATIONS = 20
IRLS_CONVERGENCE = 1e-6  # m and rad
# RANSAC stops once a hypothesis free of outliers has been drawn with this probability, given the best
# inlier ratio w so far (k = log(1 - p) / log(1 - w^3) non-degenerate samples, at most
# registration.ransac_iterations): PCL's RandomSampleConsensus, which RTAB-Map's 3D-3D estimate uses
# (util3d::transformFromXYZCorrespondences) with PCL's default probability.
RANSAC_PROBABILITY = 0.99
# Information matrix floors: variances never go below these (1 cm, ~0.6 degree standard deviation),
# so a lucky near-zero residual cannot make one link dominate the whole graph.
MIN_TRANSLATION_VARIANCE = 1e-4  # m^2
MIN_ROTATION_VARIANCE = 1e-4  # rad^2
# PnP (RTAB-Map's util3d::estimateMotion3DTo2D): solvePnPRansac's confidence (RTAB-Map's), and the
# fewest 2D-3D pairs it is given or a refinement is fitted to (its minimal sample is 4 pairs, which a
# pose fits exactly whatever they are).
PNP_CONFIDENCE = 0.99
PNP_MIN_PAIRS = 6
# PnP RANSAC's minimal solver: AP3P (4 pairs a hypothesis) took a third to a half of the time of
# RTAB-Map's default iterative solver (Vis/PnPFlags 0) on the loop pairs of bench/bench_registration.py
# (a scratch comparison), accepting the same pairs but one; the refinement below fits all the inliers.
PNP_RANSAC_SOLVER = cv2.SOLVEPNP_AP3P
# PnP refinement: Gauss-Newton steps per refinement iteration (the Huber weights make it converge
# linearly, ~3x per step), Huber threshold as a ratio of the inlier reprojection error (pixels beyond
# it weigh less), and the update size at which it stops.
PNP_GAUSS_NEWTON_STEPS = 5
PNP_HUBER_RATIO = 0.5
PNP_CONVERGENCE = 1e-4  # rad and m (0.006 deg, 0.1 mm)
# Guided matching: a first estimate needs this many inliers before its projections are trusted to
# look for more matches (a random 2D-3D match reprojects within 2 px with probability ~1e-5 on a
# 640x480 image, so 8 consistent pairs do not come by chance; a look-alike place is judged at the
# end by min_inliers like any other).
GUIDED_MIN_INLIERS = 8
# Guided matching, binary descriptors (ORB, 256 bits): a match is at most this many bits apart (random
# pairs are ~128 +- 8 apart, the same corner seen twice mostly under 50) and passes the nearest
# neighbour ratio test against the next candidate in the window.
GUIDED_MAX_HAMMING = 64
GUIDED_NNDR = 0.8
# NNDR of the two nodes' descriptor matching (RTAB-Map's Vis/CorNNDR default).
CORRESPONDENCE_NNDR = 0.8
# Guided matching: the keypoints nearest to a projection that are compared (a 10 px window at GFTT's
# 7 px minimum distance between corners holds a few).
GUIDED_CANDIDATES = 4
# Covariance of a PnP estimate (RTAB-Map's computeVariance of sac_model.h): the variance of a 1-D
# Gaussian is 2.1981 times the median of its squared samples (the median of chi^2_1 is 0.4549).
VARIANCE_OF_MEDIAN_SQUARE = 2.1981
# Neighbour link refinement: the odometry information is scaled by this inside the ICP iterations,
# enough to hold a featureless corridor's free direction at the odometry, too little to hold the
# scans away from a turn the odometry got wrong. (With the full information, a turn whose odometry
# was 2 deg off while stating 0.13 deg -- the simulated robot's wheels on 34 deg turns -- kept the
# odometry: 2 deg off, the scans' residuals were down-weighted as outliers and the prior won.)
NEIGHBOR_ICP_PRIOR_SCALE = 1e-3
# Neighbour link refinement: the odometry is used only along directions where the scans' information
# is below this ratio of the odometry's (generalised eigenvalues): where the scans constrain the
# motion at least as well as the wheels, the scan match decides alone. Wheel odometry errors are
# systematic (a wheel base slightly off, slip on turns): averaged into every well-constrained scan
# match, a fraction of them stays in every link and adds up along a session.
NEIGHBOR_SCAN_DOMINANCE = 1.0


@dataclass
class Registration:
    """A verified rigid transform between two nodes.

    Attributes:
        T_from_to: 4x4 transform, to-node base frame -> from-node base frame.
        information: 6x6 information matrix over (x, y, z, roll, pitch, yaw), (1/m^2, 1/rad^2).
        inliers: RANSAC inliers (visual words supporting the transform).
        icp_refined: True when 2D ICP on the laser scans refined the visual estimate.
        rmse: root mean square residual (m) of the inliers (of the ICP correspondences if refined).
    """

    T_from_to: np.ndarray
    information: np.ndarray
    inliers: int
    icp_refined: bool
    rmse: float


def words_3d(keypoints: np.ndarray, depth_m: np.ndarray, camera: CameraModel) -> np.ndarray:
    """3D positions of visual words in the base frame.

    Args:
        keypoints: (N,2) pixel coordinates (x = column, y = row).
        depth_m: HxW depth (m) registered to the image of the keypoints; NaN or 0 = invalid.
        camera: model of the image; ``T_base_camera`` maps optical -> base frame. With a lens
            distortion (images not rectified) the depth is read at the keypoint's pixel and the
            point placed along its undistorted ray (:meth:`CameraModel.undistort`).

    Returns:
        (N,3) float32 points (m) in the base frame; NaN rows where the depth at the keypoint's
        rounded pixel is invalid or the keypoint falls outside the image.
    """
    kp = np.asarray(keypoints, dtype=np.float64).reshape(-1, 2)
    depth = np.asarray(depth_m)
    out = np.full((len(kp), 3), np.nan, dtype=np.float32)
    if len(kp) == 0:
        return out
    cols = np.rint(kp[:, 0]).astype(np.int64)
    rows = np.rint(kp[:, 1]).astype(np.int64)
    inside = (cols >= 0) & (cols < depth.shape[1]) & (rows >= 0) & (rows < depth.shape[0])
    z = np.full(len(kp), np.nan)
    z[inside] = depth[rows[inside], cols[inside]]
    with np.errstate(invalid="ignore"):
        valid = np.isfinite(z) & (z > 0)
    if not valid.any():
        return out
    p_cam = camera.back_project(kp[valid], z[valid])
    T = camera.T_base_camera
    out[valid] = (p_cam @ T[:3, :3].T + T[:3, 3]).astype(np.float32)
    return out


def feature_pairs(from_sig: Signature, to_sig: Signature,
                  descriptors: tuple[np.ndarray, np.ndarray] | None) -> tuple[np.ndarray, np.ndarray]:
    """The pairs a loop closure transform is estimated from: :func:`matched_pairs` with the two
    nodes' ``descriptors``, :func:`word_pairs` without."""
    return word_pairs(from_sig, to_sig) if descriptors is None else matched_pairs(from_sig, to_sig, descriptors)


def word_pairs(from_sig: Signature, to_sig: Signature) -> tuple[np.ndarray, np.ndarray]:
    """Feature indices of the words occurring exactly once in both signatures (RTAB-Map's
    findPairsUnique): ``(i_from, i_to)``, each (K,) int64, in word id order."""
    from_words = from_sig.unique_words()
    to_words = to_sig.unique_words()
    common = sorted(from_words.keys() & to_words.keys())
    i_from = np.fromiter((from_words[w] for w in common), dtype=np.int64, count=len(common))
    i_to = np.fromiter((to_words[w] for w in common), dtype=np.int64, count=len(common))
    return i_from, i_to


def matched_pairs(from_sig: Signature, to_sig: Signature,
                  descriptors: tuple[np.ndarray, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Feature indices of the two nodes' features that match each other (RTAB-Map's Vis/CorType 0,
    RegistrationVis.cpp: one node's descriptors made a dictionary, the other's quantised into it
    with the NNDR test, Vis/CorNNDR 0.8), kept when unique in both: ``(i_from, i_to)``.

    The pairs do not depend on which word the vocabulary's approximate search gave each feature:
    two views of a place whose features fell on neighbouring words still pair (with the kd-tree
    search, seed 4242's last session shared 0-16 words with the place it revisited, below the 20
    inliers, while its Bayes filter was sure of the place). Two features of one word have the
    same descriptor (``descriptors`` are the words'), so every pair of :func:`word_pairs` is one of
    these (a superset of them). Binary descriptors only (Hamming); float ones return
    :func:`word_pairs`.
    """
    desc_from, desc_to = (np.ascontiguousarray(d) for d in descriptors)
    if desc_from.dtype != np.uint8 or desc_to.dtype != np.uint8:
        return word_pairs(from_sig, to_sig)
    if len(desc_from) < 2 or not len(desc_to):
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    matches = cv2.BFMatcher(cv2.NORM_HAMMING).knnMatch(desc_to, desc_from, k=2)
    i_to = np.fromiter((m[0].queryIdx for m in matches), np.int64, len(matches))
    i_from = np.fromiter((m[0].trainIdx for m in matches), np.int64, len(matches))
    d1 = np.fromiter((m[0].distance for m in matches), np.float64, len(matches))
    d2 = np.fromiter((m[1].distance for m in matches), np.float64, len(matches))
    keep = (d1 <= CORRESPONDENCE_NNDR * d2) & (d2 > 0)
    # A feature whose word occurs twice in its node pairs with nothing (RTAB-Map keeps the words
    # found once on each side).
    keep &= _found_once(from_sig)[i_from] & _found_once(to_sig)[i_to]
    i_from, i_to, d1 = i_from[keep], i_to[keep], d1[keep]
    # A from feature several to features chose pairs with none of them (RTAB-Map's rule: a word
    # found twice in the other node), unless the nearest shares its word (distance 0): a shared
    # word always keeps its pair.
    order = np.lexsort((d1, i_from))
    i_from, i_to, d1 = i_from[order], i_to[order], d1[order]
    _, best, choosers = np.unique(i_from, return_index=True, return_counts=True)
    runner_up = d1[np.minimum(best + 1, len(d1) - 1)]
    keep = best[(choosers == 1) | ((d1[best] == 0) & (runner_up > 0))]
    return i_from[keep], i_to[keep]


def _found_once(sig: Signature) -> np.ndarray:
    """Per feature of ``sig``, whether its word occurs once in the node."""
    once = np.zeros(len(sig.word_ids), bool)
    once[sig.words_found_once()[1]] = True
    return once


def epipolar_check(from_sig: Signature, to_sig: Signature, min_pairs: int, max_distance_px: float,
                   confidence: float) -> tuple[int, float]:
    """Inliers of a fundamental matrix fitted by RANSAC to the two images' word pairs (RTAB-Map's
    EpipolarGeometry::check, hypothesis verification VhEp), and how much of the images they cover.

    Args:
        from_sig, to_sig: signatures with 2D keypoints (px) per word.
        min_pairs: pairs needed before fitting (at least 8, the 8-point algorithm's).
        max_distance_px: largest distance of an inlier from its epipolar line.
        confidence: RANSAC's confidence.

    Returns:
        ``(inliers, coverage)``: 0 inliers when fewer than ``min_pairs`` pairs; ``coverage`` is,
        in the image where it is smaller, the area of the inliers' convex hull over that of all the
        image's keypoints (0 with fewer than 3 inliers).
    """
    import cv2

    i_from, i_to = word_pairs(from_sig, to_sig)
    if len(i_from) < max(min_pairs, 8):
        return 0, 0.0
    keypoints_from = np.asarray(from_sig.keypoints, dtype=np.float64)[:, :2]
    keypoints_to = np.asarray(to_sig.keypoints, dtype=np.float64)[:, :2]
    p_from, p_to = keypoints_from[i_from], keypoints_to[i_to]
    # OpenCV's FM_RANSAC seeds its own generator on every call: the same pairs, the same decision.
    F, mask = cv2.findFundamentalMat(p_from, p_to, cv2.FM_RANSAC, max_distance_px, confidence)
    if F is None or mask is None:
        return 0, 0.0
    inlier = mask.ravel().astype(bool)
    coverage = min(_hull_area(p_from[inlier]) / max(_hull_area(keypoints_from), 1.0),
                   _hull_area(p_to[inlier]) / max(_hull_area(keypoints_to), 1.0))
    return int(inlier.sum()), float(coverage)


def _hull_area(points: np.ndarray) -> float:
    """Area (px^2) of the convex hull of 2D points, 0 for fewer than 3."""
    import cv2

    if len(points) < 3:
        return 0.0
    return float(cv2.contourArea(cv2.convexHull(np.asarray(points, dtype=np.float32))))


def correspondences(from_sig: Signature, to_sig: Signature,
                    descriptors: tuple[np.ndarray, np.ndarray] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """3D-3D correspondences: the two nodes' matching features (:func:`matched_pairs`) with
    ``descriptors``, else the words occurring exactly once in both signatures.

    Returns:
        ``(from_points, to_points)``, each (K,3) float64 (m) in its node's base frame, only
        pairs with finite positions in both.
    """
    i_from, i_to = feature_pairs(from_sig, to_sig, descriptors)
    if not len(i_from):
        return np.zeros((0, 3)), np.zeros((0, 3))
    p_from = np.asarray(from_sig.points3d, dtype=np.float64)[i_from]
    p_to = np.asarray(to_sig.points3d, dtype=np.float64)[i_to]
    finite = np.isfinite(p_from).all(axis=1) & np.isfinite(p_to).all(axis=1)
    return p_from[finite], p_to[finite]


def ransac_rigid(from_points: np.ndarray, to_points: np.ndarray, inlier_distance: float, iterations: int,
                 rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """RANSAC + Kabsch on 3D-3D correspondences, then an iteratively reweighted refit.

    Args:
        from_points, to_points: (N,3) corresponding points (m), finite, N >= 3.
        inlier_distance: a correspondence is an inlier when ``|from - T @ to| < inlier_distance`` (m).
        iterations: number of 3-point hypotheses at most (fewer once :data:`RANSAC_PROBABILITY` is
            reached, as PCL's RANSAC in RTAB-Map).
        rng: random generator for the samples.

    Returns:
        ``(T_from_to 4x4, inlier mask (N,) bool)`` after refitting on the inliers.

    The hypotheses, their scores and the refit run compiled (:func:`_ransac_compiled`): as numpy
    arrays over all hypotheses at once they cost ~8 ms of a loop closure's ~15 ms of verification
    (issue 50), mostly in the refit's ~15 small Kabsch fits, each a dozen numpy calls.
    """
    n = len(from_points)
    samples = _distinct_triples(n, iterations, rng)
    T = np.eye(4)
    mask = np.zeros(n, dtype=np.bool_)
    # Refit: Cauchy weights of scale IRLS_SCALE_RATIO x inlier_distance. A plain least-squares refit on
    # every point within inlier_distance is pulled by the noisiest far words (depth noise grows with
    # range): measured on TUM fr1_xyz it left 2-11 cm errors, the weighted refit 0.5-1 cm.
    found = _ransac_compiled(np.ascontiguousarray(from_points, dtype=np.float64),
                             np.ascontiguousarray(to_points, dtype=np.float64), samples, float(inlier_distance),
                             MIN_SAMPLE_AREA, RANSAC_PROBABILITY, IRLS_SCALE_RATIO * inlier_distance,
                             IRLS_ITERATIONS, IRLS_CONVERGENCE, T, mask)
    if not found:
        raise RegistrationError(
            f"RANSAC: all {iterations} samples of the {n} correspondences are degenerate (collinear or "
            "coincident words): the scene has no 3D structure to register")
    return T, mask


@jit()
def _fit_rigid(from_points, to_points, index, weights, T):
    """Weighted least-squares rigid transform (Kabsch) with ``from ≈ T @ to`` over the rows
    ``index`` (weights (len(index),)), written into ``T`` (4x4)."""
    total = 0.0
    cp = np.zeros(3)
    cq = np.zeros(3)
    for k in range(index.shape[0]):
        total += weights[k]
    for k in range(index.shape[0]):
        w = weights[k] / total
        for d in range(3):
            cp[d] += w * from_points[index[k], d]
            cq[d] += w * to_points[index[k], d]
    H = np.zeros((3, 3))
    for k in range(index.shape[0]):
        w = weights[k] / total
        for i in range(3):
            qi = to_points[index[k], i] - cq[i]
            for j in range(3):
                H[i, j] += w * qi * (from_points[index[k], j] - cp[j])
    U, _, Vt = np.linalg.svd(H)
    V = Vt.T.copy()
    R = V @ U.T
    if np.linalg.det(R) < 0.0:  # a reflection: flip the axis of the smallest singular value
        V[:, 2] = -V[:, 2]
        R = V @ U.T
    T[:, :] = 0.0
    T[:3, :3] = R
    for i in range(3):
        T[i, 3] = cp[i] - (R[i, 0] * cq[0] + R[i, 1] * cq[1] + R[i, 2] * cq[2])
    T[3, 3] = 1.0


@jit()
def _inliers(T, from_points, to_points, inlier_distance, out):
    """Marks in ``out`` the pairs with ``|from - T @ to| < inlier_distance``; returns their count."""
    count = 0
    bound = inlier_distance * inlier_distance
    for n in range(from_points.shape[0]):
        d2 = 0.0
        for i in range(3):
            e = (T[i, 0] * to_points[n, 0] + T[i, 1] * to_points[n, 1] + T[i, 2] * to_points[n, 2] + T[i, 3]
                 - from_points[n, i])
            d2 += e * e
        out[n] = d2 < bound
        count += out[n]
    return count


@jit()
def _ransac_compiled(from_points, to_points, samples, inlier_distance, min_area, probability, scale, refits,
                     convergence, T, mask):
    """:func:`ransac_rigid`'s work: the best-scoring hypothesis of the non-degenerate ``samples``
    (the first of equal scores), drawn until one free of outliers has come with ``probability``
    (PCL's RandomSampleConsensus::computeModel), refitted into ``T``, its final inliers into ``mask``;
    False when every sample is degenerate."""
    n = from_points.shape[0]
    ones = np.ones(3)
    trial = np.zeros((4, 4))
    inliers = np.zeros(n, dtype=np.bool_)
    best = -1
    drawn = 0  # non-degenerate samples scored
    needed = np.inf
    log_miss = np.log(1.0 - probability)
    eps = np.finfo(np.float64).eps
    for h in range(samples.shape[0]):
        if drawn >= needed:
            break
        a, b, c = to_points[samples[h, 0]], to_points[samples[h, 1]], to_points[samples[h, 2]]
        u, v = b - a, c - a
        cross = np.array([u[1] * v[2] - u[2] * v[1], u[2] * v[0] - u[0] * v[2], u[0] * v[1] - u[1] * v[0]])
        if 0.5 * np.sqrt(np.sum(cross * cross)) <= min_area:
            continue
        drawn += 1
        _fit_rigid(from_points, to_points, samples[h], ones, trial)
        count = _inliers(trial, from_points, to_points, inlier_distance, inliers)
        if count > best:
            best = count
            T[:, :] = trial
            p_outlier_in_sample = min(1.0 - eps, max(eps, 1.0 - (count / n) ** 3))
            needed = log_miss / np.log(p_outlier_in_sample)
    if best < 0:
        return False
    residual = np.empty(n)
    for _ in range(refits):
        for k in range(n):
            d2 = 0.0
            for i in range(3):
                e = (T[i, 0] * to_points[k, 0] + T[i, 1] * to_points[k, 1] + T[i, 2] * to_points[k, 2] + T[i, 3]
                     - from_points[k, i])
                d2 += e * e
            residual[k] = np.sqrt(d2)
        gate = np.nonzero(residual < inlier_distance)[0]
        if gate.shape[0] < 3:
            break
        weights = 1.0 / (1.0 + (residual[gate] / scale) ** 2)
        _fit_rigid(from_points, to_points, gate, weights, trial)
        # The step from T to the refit: R^T R' (its angle) and R^T (t' - t).
        trace = 0.0
        moved_sq = 0.0
        for i in range(3):
            t_i = 0.0
            for j in range(3):
                trace += T[j, i] * trial[j, i]
                t_i += T[j, i] * (trial[j, 3] - T[j, 3])
            moved_sq += t_i * t_i
        angle = np.arccos(min(1.0, max(-1.0, (trace - 1.0) / 2.0)))
        T[:, :] = trial
        if np.sqrt(moved_sq) < convergence and angle < convergence:
            break
    _inliers(T, from_points, to_points, inlier_distance, mask)
    return True


def _distinct_triples(n: int, count: int, rng: np.random.Generator) -> np.ndarray:
    """(count, 3) indices in [0, n), three distinct per row, each triple equally likely: the second
    drawn among n - 1 and the third among n - 2 values, shifted past the ones drawn before (O(count),
    where ranking n random keys per row cost O(count n): 3-4 ms of a 150-pair RANSAC)."""
    a = rng.integers(0, n, count)
    b = rng.integers(0, n - 1, count)
    b += b >= a
    c = rng.integers(0, n - 2, count)
    low, high = np.minimum(a, b), np.maximum(a, b)
    c += c >= low
    c += c >= high
    return np.column_stack([a, b, c])


def _residuals(T: np.ndarray, from_points: np.ndarray, to_points: np.ndarray) -> np.ndarray:
    """Distances (N,) between ``from_points`` and ``T @ to_points`` (m)."""
    return np.linalg.norm(to_points @ T[:3, :3].T + T[:3, 3] - from_points, axis=1)


def _information(rmse: float, spread: float, planar: bool) -> np.ndarray:
    """6x6 information (x, y, z, roll, pitch, yaw) from the residual RMSE and the points' spread.

    Translation variance = RMSE^2 of the residuals (conservative: residuals of neighbouring
    words are correlated, so it is not divided by the inlier count, as in RTAB-Map). Rotation
    variance = RMSE^2 / spread^2: a residual of ``rmse`` at a lever arm of ``spread`` metres is
    an angle of ``rmse / spread``. Both have a floor (MIN_*_VARIANCE).
    """
    var_t = max(rmse ** 2, MIN_TRANSLATION_VARIANCE)
    var_r = max(rmse ** 2 / max(spread, 1e-6) ** 2, MIN_ROTATION_VARIANCE)
    info = np.diag([1 / var_t] * 3 + [1 / var_r] * 3)
    if planar:
        # z, roll and pitch are not estimated in 3 DoF: keep them at the floor's information so
        # the matrix stays invertible (Pose2 optimisation ignores them).
        info[2, 2] = 1 / MIN_TRANSLATION_VARIANCE
        info[3, 3] = info[4, 4] = 1 / MIN_ROTATION_VARIANCE
    return info


def register(from_sig: Signature, to_sig: Signature, params: RegistrationParams,
             rng: np.random.Generator | None = None,
             descriptors: tuple[np.ndarray, np.ndarray] | None = None) -> Registration:
    """Rigid transform between two nodes from their visual words (and laser scans).

    Args:
        from_sig: the from node (e.g. the new node); its ``points3d`` in its base frame (m), NaN
            without depth, its ``keypoints`` (px) and ``camera``.
        to_sig: the to node (e.g. the loop closure hypothesis).
        params: estimation (PnP or 3D-3D RANSAC), ICP settings.
        rng: random generator for the 3D-3D RANSAC (default: seeded with DEFAULT_SEED, reproducible;
            PnP's RANSAC is OpenCV's, seeded the same on every call).
        descriptors: ``(from, to)`` descriptors of every keypoint of the two signatures ((N,D) and
            (M,D), binary uint8), for the PnP's guided matching (``params.guided_window``); None
            = the shared words only.

    The estimate (``params.estimation``, :func:`uses_pnp`): PnP, or the 3D-3D RANSAC (without a
    camera model too); with laser scans on both nodes and ``icp_refine``, then 2D ICP.

    Returns:
        :class:`Registration` with ``T_from_to`` (``from_points ≈ T_from_to @ to_points``).

    Raises:
        RegistrationError: fewer than ``params.min_inliers`` inliers, or ICP refinement rejected.
    """
    icp = params.icp_refine and from_sig.scan is not None and to_sig.scan is not None
    if params.min_depth > 0 or params.max_depth > 0:
        (from_sig, from_kept), (to_sig, to_kept) = (words_within_depth(sig, params) for sig in (from_sig, to_sig))
        if descriptors is not None:
            descriptors = (descriptors[0][from_kept], descriptors[1][to_kept])
    if uses_pnp(params, icp) and from_sig.camera is not None and to_sig.camera is not None:
        # Loop closure transform by PnP (RTAB-Map's Vis/EstimationType 1).
        result = register_pnp(from_sig, to_sig, params, descriptors)
    else:
        result = _register_3d(from_sig, to_sig, params, rng, descriptors)
    if icp:
        result = _refine_with_icp(from_sig, to_sig, result, params)
    return result


def words_within_depth(sig: Signature, params: RegistrationParams) -> tuple[Signature, np.ndarray]:
    """``sig`` with only its words whose depth (along the camera's optical axis) is within
    ``params.min_depth``..``params.max_depth`` (RTAB-Map's Vis/MinDepth, Vis/MaxDepth: words without
    depth go too), and the kept features' indices."""
    points = np.asarray(sig.points3d, dtype=np.float64).reshape(-1, 3)
    if sig.camera is not None:
        T = transforms.inverse(sig.camera.T_base_camera)
        points = points @ T[:3, :3].T + T[:3, 3]
    depth = points[:, 2] if sig.camera is not None else np.linalg.norm(points, axis=1)
    kept = np.flatnonzero(depth_in_range(depth, params.min_depth, params.max_depth))
    return replace(sig, word_ids=sig.word_ids[kept], keypoints=sig.keypoints[kept], points3d=sig.points3d[kept]), kept


def uses_pnp(params: RegistrationParams, icp_refined: bool) -> bool:
    """Whether the visual estimate is PnP: ``estimation`` pnp, or auto unless the robot is planar and
    2D ICP refines the estimate (the 2014 paper's RANSAC on 3D words then ICP)."""
    if params.estimation == "auto":
        return not (params.planar and icp_refined)
    return params.estimation == "pnp"


def _register_3d(from_sig: Signature, to_sig: Signature, params: RegistrationParams,
                 rng: np.random.Generator | None,
                 descriptors: tuple[np.ndarray, np.ndarray] | None = None) -> Registration:
    """The 2014 paper's estimate (Vis/EstimationType 0): RANSAC on 3D-3D pairs, reweighted refit."""
    rng = np.random.default_rng(DEFAULT_SEED) if rng is None else rng
    p_from, p_to = correspondences(from_sig, to_sig, descriptors)
    if len(p_from) < max(3, params.min_inliers):
        what = "features matched" if descriptors is not None else "words"
        raise RegistrationError(
            f"nodes {from_sig.id} -> {to_sig.id}: only {len(p_from)} correspondences ({what} unique in "
            f"both signatures with depth) < min_inliers={params.min_inliers}: loop closure rejected")
    # Loop closure transform (2014 §II-A): RANSAC on the 3D visual word correspondences.
    T, mask = ransac_rigid(p_from, p_to, params.inlier_distance, params.ransac_iterations, rng)
    n_inliers = int(mask.sum())
    if n_inliers < params.min_inliers:
        raise RegistrationError(
            f"nodes {from_sig.id} -> {to_sig.id}: {n_inliers} inliers < min_inliers={params.min_inliers} "
            f"({len(p_from)} correspondences): loop closure rejected")
    if params.planar:
        # Robot on a plane (2014 §III): keep x, y and the rotation about z.
        T = transforms.project_planar(T)
    residuals = _residuals(T, p_from[mask], p_to[mask])
    rmse = float(np.sqrt(np.mean(residuals ** 2)))
    centred = p_from[mask] - p_from[mask].mean(axis=0)
    spread = float(np.sqrt(np.mean(np.sum(centred ** 2, axis=1))))
    info = _information(rmse, spread, params.planar)
    return Registration(T, info, n_inliers, False, rmse)


@dataclass
class _WordPairs:
    """Corresponding features of two nodes, K pairs, with both ends' data in their own frames.

    Attributes:
        i_from, i_to: (K,) int64 feature indices in the from / to signature.
        uv_from, uv_to: (K,2) float64 keypoints (px) in the from / to image.
        p_from, p_to: (K,3) float64 word positions (m) in the from / to base frame; NaN rows
            without depth.
    """

    i_from: np.ndarray
    i_to: np.ndarray
    uv_from: np.ndarray
    uv_to: np.ndarray
    p_from: np.ndarray
    p_to: np.ndarray

    @classmethod
    def of(cls, from_sig: Signature, to_sig: Signature, i_from: np.ndarray, i_to: np.ndarray) -> "_WordPairs":
        return cls(i_from, i_to,
                   np.asarray(from_sig.keypoints, dtype=np.float64).reshape(-1, 2)[i_from],
                   np.asarray(to_sig.keypoints, dtype=np.float64).reshape(-1, 2)[i_to],
                   np.asarray(from_sig.points3d, dtype=np.float64).reshape(-1, 3)[i_from],
                   np.asarray(to_sig.points3d, dtype=np.float64).reshape(-1, 3)[i_to])

    def __len__(self) -> int:
        return len(self.i_from)

    @property
    def forward(self) -> np.ndarray:
        """(K,) bool: pairs whose from end has depth (from word in the to image)."""
        return np.isfinite(self.p_from).all(axis=1)

    @property
    def backward(self) -> np.ndarray:
        """(K,) bool: pairs whose to end has depth (to word in the from image)."""
        return np.isfinite(self.p_to).all(axis=1)


def register_pnp(from_sig: Signature, to_sig: Signature, params: RegistrationParams,
                 descriptors: tuple[np.ndarray, np.ndarray] | None = None) -> Registration:
    """Loop closure transform by PnP (RTAB-Map's Vis/EstimationType 1, util3d::estimateMotion3DTo2D).

    1. RANSAC PnP (``cv2.solvePnPRansac``, ``params.pnp_reprojection_error`` px) of the 3D words of
       the node with more of them with depth against the 2D keypoints of the other;
    2. refinement (``pnp_refine_iterations``): the inliers re-selected at the current estimate, in
       both directions when ``bundle_adjustment`` (each node's words from its own depth in the other
       image), and the pose fitted to their reprojection errors (Gauss-Newton, Huber weights);
    3. with ``guided_window`` and descriptors: every keypoint with depth matched in a window around
       its projection, then 1-2 again on these matches;
    4. the inlier count against ``min_inliers``; the information matrix from the inliers' 3D
       residuals (both nodes' depths, RTAB-Map's PnP variance) or their reprojection errors, its
       translation variance against ``pnp_max_variance``.

    Args and returns: see :func:`register` (``descriptors`` index like the signatures' keypoints).

    Raises:
        RegistrationError: too few pairs, RANSAC found no pose, fewer than ``min_inliers`` inliers,
            or a translation variance above ``pnp_max_variance``.
    """
    cam_from, cam_to = from_sig.camera, to_sig.camera
    i_from, i_to = feature_pairs(from_sig, to_sig, descriptors)
    pairs = _WordPairs.of(from_sig, to_sig, i_from, i_to)
    T, inliers = _pnp_estimate(pairs, cam_from, cam_to, params, f"nodes {from_sig.id} -> {to_sig.id}")
    if params.guided_window > 0 and descriptors is not None and int(inliers.sum()) >= GUIDED_MIN_INLIERS:
        # Guided matching (RTAB-Map's Vis/CorGuessWinSize, here with the first estimate as the guess).
        guided = _guided_pairs(from_sig, to_sig, descriptors, T, pairs, params.guided_window)
        if len(guided) > int(inliers.sum()):
            T_guided, inliers_guided = _refine_pnp(T, guided, cam_from, cam_to, params)
            if inliers_guided.sum() > inliers.sum():
                pairs, T, inliers = guided, T_guided, inliers_guided
    n_inliers = int(inliers.sum())
    if n_inliers < params.min_inliers:
        raise RegistrationError(
            f"nodes {from_sig.id} -> {to_sig.id}: {n_inliers} PnP inliers < min_inliers={params.min_inliers} "
            f"({len(pairs)} word pairs, {int(pairs.forward.sum())} with depth in {from_sig.id}, "
            f"{int(pairs.backward.sum())} in {to_sig.id}): loop closure rejected")
    info, rmse = _pnp_information(T, pairs, inliers, cam_from, cam_to, params)
    variance = 1.0 / info[0, 0]
    if params.pnp_max_variance > 0 and variance > params.pnp_max_variance:
        # RTAB-Map's Vis/PnPMaxVariance, on the 6-DoF estimate (before Reg/Force3DoF's projection, as
        # there): the words still disagree by centimetres after the fit (motion blur, rolling
        # shutter); the graph check would let such a loose link in, so it is rejected here.
        raise RegistrationError(
            f"nodes {from_sig.id} -> {to_sig.id}: PnP translation variance {variance:.4f} m^2 ({n_inliers} "
            f"inliers) > pnp_max_variance={params.pnp_max_variance}: loop closure rejected")
    if params.planar:
        T = transforms.project_planar(T)
        info, rmse = _pnp_information(T, pairs, inliers, cam_from, cam_to, params)
    return Registration(T, info, n_inliers, False, rmse)


def _pnp_estimate(pairs: _WordPairs, cam_from: CameraModel, cam_to: CameraModel, params: RegistrationParams,
                  what: str) -> tuple[np.ndarray, np.ndarray]:
    """RANSAC PnP then refinement: ``(T_from_to, (K,) bool inliers)``, or RegistrationError."""
    forward, backward = pairs.forward, pairs.backward
    # The direction with more 3D words (RTAB-Map estimates from -> to, Vis/ForwardEstOnly).
    use_forward = forward.sum() >= backward.sum()
    usable = forward if use_forward else backward
    if usable.sum() < PNP_MIN_PAIRS:
        raise RegistrationError(
            f"{what}: {int(usable.sum())} word pairs with depth (of {len(pairs)} shared words) < "
            f"{PNP_MIN_PAIRS}: loop closure rejected")
    if use_forward:
        T_camera_points = pnp_ransac(pairs.p_from[usable], pairs.uv_to[usable], cam_to,
                                     params.pnp_reprojection_error, params.ransac_iterations)
        T = None if T_camera_points is None else transforms.inverse(cam_to.T_base_camera @ T_camera_points)
    else:
        T_camera_points = pnp_ransac(pairs.p_to[usable], pairs.uv_from[usable], cam_from,
                                     params.pnp_reprojection_error, params.ransac_iterations)
        T = None if T_camera_points is None else cam_from.T_base_camera @ T_camera_points
    if T is None:
        raise RegistrationError(f"{what}: PnP RANSAC found no pose from {int(usable.sum())} word pairs: "
                                "loop closure rejected")
    return _refine_pnp(T, pairs, cam_from, cam_to, params)


def pnp_ransac(points: np.ndarray, pixels: np.ndarray, camera: CameraModel, reprojection_error: float,
               iterations: int) -> np.ndarray | None:
    """RANSAC PnP: the pose of ``camera`` seeing ``points`` at ``pixels``.

    Args:
        points: (N,3) points (m) in some frame F, N >= 4.
        pixels: (N,2) their keypoints (px) in the camera's image.
        camera: pinhole model of the image.
        reprojection_error: inlier threshold (px).
        iterations: RANSAC hypotheses.

    Returns:
        ``T_camera_F`` (4x4, F -> the camera's optical frame), or None when RANSAC found none.
        (OpenCV's RANSAC seeds its generator on every call: the same pairs give the same pose.)
    """
    K = _intrinsics(camera)
    ok, rvec, tvec, inliers = cv2.solvePnPRansac(
        np.ascontiguousarray(points, dtype=np.float64), np.ascontiguousarray(pixels, dtype=np.float64), K, None,
        iterationsCount=int(iterations), reprojectionError=float(reprojection_error), confidence=PNP_CONFIDENCE,
        flags=PNP_RANSAC_SOLVER)
    if not ok or inliers is None or not np.all(np.isfinite(tvec)):
        return None
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(rvec)[0]
    T[:3, 3] = tvec.ravel()
    return T


def _intrinsics(camera: CameraModel) -> np.ndarray:
    """3x3 intrinsic matrix K of a pinhole camera."""
    return np.array([[camera.fx, 0.0, camera.cx], [0.0, camera.fy, camera.cy], [0.0, 0.0, 1.0]])


def _reprojection(T_camera_frame: np.ndarray, points: np.ndarray, camera: CameraModel) -> tuple[np.ndarray, np.ndarray]:
    """Points (N,3, m) of a frame in the camera's image: ``(pixels (N,2), points in the optical
    frame (N,3))``; NaN pixels behind the camera."""
    X = points @ T_camera_frame[:3, :3].T + T_camera_frame[:3, 3]
    return camera.project(X), X


def _refine_pnp(T: np.ndarray, pairs: _WordPairs, cam_from: CameraModel, cam_to: CameraModel,
                params: RegistrationParams) -> tuple[np.ndarray, np.ndarray]:
    """Refinement of ``T_from_to`` (RTAB-Map's Vis/PnPRefineIterations, with Vis/BundleAdjustment the
    errors of both directions): Gauss-Newton steps on the Huber-weighted reprojection errors of the
    inliers, the inliers re-selected at the current estimate before each step, until the selection
    stops changing and the step is below PNP_CONVERGENCE (at most ``pnp_refine_iterations`` x
    PNP_GAUSS_NEWTON_STEPS steps). The update is on the right, ``T exp(xi)``, xi = (rotation vector,
    translation) in the to node's base frame.

    Returns:
        ``(T_from_to, (K,) bool)``: a pair is an inlier when a word of it with depth reprojects within
        ``pnp_reprojection_error`` of its keypoint in the other image.
    """
    threshold = params.pnp_reprojection_error
    huber_px = PNP_HUBER_RATIO * threshold
    selected = None
    for _ in range(params.pnp_refine_iterations * PNP_GAUSS_NEWTON_STEPS):
        r, J = _reprojection_system(T, pairs, cam_from, cam_to, params.bundle_adjustment)
        errors = np.hypot(r[:, 0], r[:, 1])  # (2K,): forward pairs, then backward pairs
        selection = errors < threshold  # NaN (no depth, behind the camera) compares False
        if selection.sum() < PNP_MIN_PAIRS:
            break
        r, J, errors = r[selection], J[selection], errors[selection]
        w = np.where(errors <= huber_px, 1.0, huber_px / np.maximum(errors, 1e-12))
        H = np.einsum("n,nki,nkj->ij", w, J, J)
        try:
            xi = np.linalg.solve(H, -np.einsum("n,nki,nk->i", w, J, r))
        except np.linalg.LinAlgError:
            break
        step = np.eye(4)
        step[:3, :3] = cv2.Rodrigues(xi[:3])[0]
        step[:3, 3] = xi[3:]
        T = T @ step
        unchanged = selected is not None and np.array_equal(selection, selected)
        selected = selection
        if unchanged and np.linalg.norm(xi) < PNP_CONVERGENCE:
            break
    r, _ = _reprojection_system(T, pairs, cam_from, cam_to, params.bundle_adjustment)
    with np.errstate(invalid="ignore"):
        inlier = np.hypot(r[:, 0], r[:, 1]) < threshold
    return T, inlier[:len(pairs)] | inlier[len(pairs):]


def _reprojection_system(T: np.ndarray, pairs: _WordPairs, cam_from: CameraModel, cam_to: CameraModel,
                         backward: bool) -> tuple[np.ndarray, np.ndarray]:
    """Reprojection residuals (2K,2) (px) of the K pairs at ``T = T_from_to`` and their (2K,2,6)
    Jacobians in xi (``T exp(xi)``): rows 0..K-1 forward (the from word, from its depth, in the to
    image), rows K..2K-1 backward (the to word in the from image); NaN rows where the word has no
    depth, lands behind the camera, or (``backward`` False) for every backward row."""
    T_inv = transforms.inverse(T)
    # Forward: X = C_to^-1 exp(-xi) q with q = T^-1 p_from (the from words in the to base frame).
    q = pairs.p_from @ T_inv[:3, :3].T + T_inv[:3, 3]
    r_f, J_f = _reprojection_jacobian(q, transforms.inverse(cam_to.T_base_camera), pairs.uv_to, cam_to, -1.0)
    if not backward:
        return (np.concatenate([r_f, np.full_like(r_f, np.nan)]),
                np.concatenate([J_f, np.zeros_like(J_f)]))
    # Backward: X = C_from^-1 T exp(xi) p_to.
    r_b, J_b = _reprojection_jacobian(pairs.p_to, transforms.inverse(cam_from.T_base_camera) @ T, pairs.uv_from,
                                      cam_from, 1.0)
    return np.concatenate([r_f, r_b]), np.concatenate([J_f, J_b])


def _reprojection_jacobian(points: np.ndarray, T_camera_points: np.ndarray, pixels: np.ndarray, camera: CameraModel,
                           sign: float) -> tuple[np.ndarray, np.ndarray]:
    """Reprojection residuals (n,2) (px) of (n,3) points moved into the camera by
    ``T_camera_points @ exp(sign xi)``, and their (n,2,6) Jacobian in xi = (rotation vector,
    translation) of the points' frame; NaN residuals for points without depth or behind the camera."""
    R, t = T_camera_points[:3, :3], T_camera_points[:3, 3]
    X = points @ R.T + t
    x, y, z = X[:, 0], X[:, 1], X[:, 2]
    with np.errstate(invalid="ignore", divide="ignore"):
        z = np.where(z > 0, z, np.nan)
        r = np.stack([camera.fx * x / z + camera.cx - pixels[:, 0], camera.fy * y / z + camera.cy - pixels[:, 1]],
                     axis=1)
        # d pixel / d X (2x3 per point), times R: the derivative along the points' frame axes.
        d_u = np.stack([camera.fx / z, np.zeros_like(z), -camera.fx * x / z ** 2], axis=1) @ R
        d_v = np.stack([np.zeros_like(z), camera.fy / z, -camera.fy * y / z ** 2], axis=1) @ R
    J = np.empty((len(X), 2, 6))
    # d(R (p + omega x p + t))/d omega = -R [p]x: row . (omega x p) = omega . (p x row).
    J[:, 0, :3], J[:, 1, :3] = sign * _cross(points, d_u), sign * _cross(points, d_v)
    J[:, 0, 3:], J[:, 1, 3:] = sign * d_u, sign * d_v
    return r, J


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise cross products of (n,3) arrays (np.cross costs more than the arithmetic at this size)."""
    return np.stack([a[:, 1] * b[:, 2] - a[:, 2] * b[:, 1], a[:, 2] * b[:, 0] - a[:, 0] * b[:, 2],
                     a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]], axis=1)


def _guided_pairs(from_sig: Signature, to_sig: Signature, descriptors: tuple[np.ndarray, np.ndarray],
                  T: np.ndarray, word: _WordPairs, window_px: float) -> _WordPairs:
    """Word pairs plus the matches found around the projections of ``T = T_from_to``.

    Every keypoint with depth of one node is projected into the other image; among the
    GUIDED_CANDIDATES keypoints there nearest to the projection within ``window_px``, the nearest
    descriptor is its match if at most GUIDED_MAX_HAMMING bits away and GUIDED_NNDR times nearer
    than the next one (binary descriptors only: float ones return the word pairs). A keypoint keeps
    its word pair, else its nearest match; each keypoint is used once.
    """
    desc = tuple(np.asarray(d) for d in descriptors)
    if any(d.dtype != np.uint8 for d in desc):
        return word
    kp = (np.asarray(from_sig.keypoints, dtype=np.float64).reshape(-1, 2),
          np.asarray(to_sig.keypoints, dtype=np.float64).reshape(-1, 2))
    points = (np.asarray(from_sig.points3d, dtype=np.float64).reshape(-1, 3),
              np.asarray(to_sig.points3d, dtype=np.float64).reshape(-1, 3))
    cameras = (from_sig.camera, to_sig.camera)
    # T_camera(other)_base(mine): the from words into the to camera, the to words into the from camera.
    T_into = (transforms.inverse(to_sig.camera.T_base_camera) @ transforms.inverse(T),
              transforms.inverse(from_sig.camera.T_base_camera) @ T)
    found = []  # (bits apart, from index, to index)
    for mine, other in ((0, 1), (1, 0)):
        with_depth = np.flatnonzero(np.isfinite(points[mine]).all(axis=1))
        n_other = len(kp[other])
        if not len(with_depth) or n_other < 2:
            continue
        projected, _ = _reprojection(T_into[mine], points[mine][with_depth], cameras[other])
        seen = np.isfinite(projected).all(axis=1)
        with_depth, projected = with_depth[seen], projected[seen]
        _, candidates = cKDTree(kp[other]).query(projected, k=min(GUIDED_CANDIDATES, n_other),
                                                 distance_upper_bound=window_px)
        in_window = candidates < n_other  # a missing neighbour has index n_other
        xor = np.bitwise_xor(desc[mine][with_depth][:, None, :], desc[other][np.minimum(candidates, n_other - 1)])
        bits = np.where(in_window, np.unpackbits(xor, axis=2).sum(axis=2), np.iinfo(np.int32).max)
        order = np.argsort(bits, axis=1, kind="stable")
        best = np.take_along_axis(bits, order[:, :1], axis=1)[:, 0]
        second = np.take_along_axis(bits, order[:, 1:2], axis=1)[:, 0]
        keep = (best <= GUIDED_MAX_HAMMING) & (best < GUIDED_NNDR * second)
        matched = np.take_along_axis(candidates, order[:, :1], axis=1)[:, 0][keep]
        ends = (with_depth[keep], matched) if mine == 0 else (matched, with_depth[keep])
        found.extend(zip(best[keep].tolist(), ends[0].tolist(), ends[1].tolist()))
    # Each keypoint once: the word pairs first, then the guided matches nearest first.
    used_from, used_to = set(word.i_from.tolist()), set(word.i_to.tolist())
    i_from, i_to = list(word.i_from.tolist()), list(word.i_to.tolist())
    for _, a, b in sorted(found):
        if a in used_from or b in used_to:
            continue
        used_from.add(a)
        used_to.add(b)
        i_from.append(a)
        i_to.append(b)
    return _WordPairs.of(from_sig, to_sig, np.asarray(i_from, np.int64), np.asarray(i_to, np.int64))


def _pnp_information(T: np.ndarray, pairs: _WordPairs, inliers: np.ndarray, cam_from: CameraModel,
                     cam_to: CameraModel, params: RegistrationParams) -> tuple[np.ndarray, float]:
    """6x6 information of a PnP estimate and the inliers' RMS 3D residual (m).

    As RTAB-Map's PnP variance (util3d::estimateMotion3DTo2D, PCL's computeVariance): over the inliers
    with depth in both nodes, translation variance = VARIANCE_OF_MEDIAN_SQUARE x the median squared
    distance between the from word and the to word moved by ``T`` (both nodes' depth noise, and
    whatever the pose gets wrong, in metres), rotation variance = the same of the squared angle
    between the two seen from the from camera. Inliers with depth on one side only: the reprojection
    errors instead (px over the focal length as an angle, times the median depth as a distance).
    The variances have the floors MIN_TRANSLATION_VARIANCE / MIN_ROTATION_VARIANCE.
    """
    both = inliers & pairs.forward & pairs.backward
    if both.sum() >= PNP_MIN_PAIRS:
        moved = pairs.p_to[both] @ T[:3, :3].T + T[:3, 3]
        residuals = np.linalg.norm(pairs.p_from[both] - moved, axis=1)
        centre = cam_from.T_base_camera[:3, 3]
        a, b = pairs.p_from[both] - centre, moved - centre
        cos = np.sum(a * b, axis=1) / (np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1))
        angles = np.arccos(np.clip(cos, -1.0, 1.0))
        var_t = VARIANCE_OF_MEDIAN_SQUARE * float(np.median(residuals ** 2))
        var_r = VARIANCE_OF_MEDIAN_SQUARE * float(np.median(angles ** 2))
        rmse = float(np.sqrt(np.mean(residuals ** 2)))
    else:
        r, _ = _reprojection_system(T, pairs, cam_from, cam_to, backward=True)
        errors = np.hypot(r[:, 0], r[:, 1]).reshape(2, -1)
        errors = np.fmin(errors[0], errors[1])[inliers]  # the direction(s) with depth; fmin skips NaN
        focal = 0.5 * (cam_from.fx + cam_from.fy)
        depth = np.concatenate([pairs.p_from[inliers & pairs.forward], pairs.p_to[inliers & pairs.backward]])
        range_m = float(np.median(np.linalg.norm(depth, axis=1)))
        var_r = VARIANCE_OF_MEDIAN_SQUARE * float(np.median((errors / focal) ** 2))
        var_t = var_r * range_m ** 2
        rmse = float(np.sqrt(np.mean((errors / focal * range_m) ** 2)))
    var_t = max(var_t, MIN_TRANSLATION_VARIANCE)
    var_r = max(var_r, MIN_ROTATION_VARIANCE)
    info = np.diag([1 / var_t] * 3 + [1 / var_r] * 3)
    if params.planar:
        info[2, 2] = 1 / MIN_TRANSLATION_VARIANCE
        info[3, 3] = info[4, 4] = 1 / MIN_ROTATION_VARIANCE
    return info, rmse


def _refine_with_icp(from_sig: Signature, to_sig: Signature, visual: Registration,
                     params: RegistrationParams) -> Registration:
    """2D ICP refinement of a visual loop closure (2014 §II-A), or RegistrationError.

    A refinement is accepted only if the scans overlap enough (``icp_min_overlap``) and ICP moved
    the visual estimate by less than ``icp_max_translation``. Otherwise the loop closure is
    *rejected*, not kept with its visual estimate: laser and vision disagreeing means one of them
    matched the wrong structure (repetitive texture, a moved object, a look-alike corridor), so
    the hypothesis itself is doubtful, and a wrong link costs the graph far more than a missed one.
    """
    source = to_sig.scan.points_base()
    target = from_sig.scan.points_base()
    fit = icp_fit(source, target, visual.T_from_to, None, params.icp_max_correspondence_distance,
                  params.icp_iterations)
    T_icp, overlap, rmse = fit.T, fit.overlap, fit.rmse
    correction = float(np.linalg.norm(T_icp[:2, 3] - visual.T_from_to[:2, 3]))
    if overlap < params.icp_min_overlap:
        raise RegistrationError(
            f"nodes {from_sig.id} -> {to_sig.id}: ICP overlap {overlap:.2f} < icp_min_overlap="
            f"{params.icp_min_overlap}: the scans do not agree with the visual estimate, loop closure rejected")
    if correction >= params.icp_max_translation:
        raise RegistrationError(
            f"nodes {from_sig.id} -> {to_sig.id}: ICP moved the visual estimate by {correction:.3f} m >= "
            f"icp_max_translation={params.icp_max_translation} m: loop closure rejected")
    # Apply the planar correction found by ICP to the visual estimate (equal to T_icp when the
    # visual estimate is already planar; keeps z, roll, pitch otherwise).
    T = T_icp @ transforms.inverse(transforms.project_planar(visual.T_from_to)) @ visual.T_from_to
    # The scans' information on x, y, yaw (as for refined neighbour links, so loop closures and
    # odometry are weighed on one scale); the visual estimate's elsewhere.
    info = _information(rmse, _spread_2d(target), planar=True)
    planar_axes = [0, 1, 5]
    info[np.ix_(planar_axes, planar_axes)] = fit.information
    logger.debug("ICP refined %d -> %d: correction %.3f m, overlap %.2f, rmse %.3f m",
                 from_sig.id, to_sig.id, correction, overlap, rmse)
    return Registration(T, info, visual.inliers, True, rmse)


def _spread_2d(points: np.ndarray) -> float:
    """RMS distance (m) of (N,2) points from their centroid."""
    centred = points - points.mean(axis=0)
    return float(np.sqrt(np.mean(np.sum(centred ** 2, axis=1))))


def assemble_scan_map(scans: list[tuple[np.ndarray, LaserScan]], voxel_size: float) -> np.ndarray:
    """(M,2) points (m) of several scans in one frame, one centroid per voxel of ``voxel_size``.

    Overlapping scans are merged by the voxel filter (one denoised point per cell, an even density
    for the point-to-line normals); a single scan is returned as it is.

    Args:
        scans: ``(T_frame_base, scan)`` pairs: each scan and the pose of its node in the frame.
        voxel_size: voxel edge (m).
    """
    parts = [scan.points_base() @ T[:2, :2].T + T[:2, 3] for T, scan in scans]
    if len(parts) == 1:
        return parts[0]
    points = np.concatenate(parts) if parts else np.zeros((0, 2))
    return voxel_filter(points, None, voxel_size)[0].astype(np.float64)


def refine_neighbor_link(scan_map: np.ndarray, new_scan: LaserScan, T_odom: np.ndarray,
                         odom_information: np.ndarray, params: RegistrationParams) -> tuple[np.ndarray, np.ndarray]:
    """Refine the odometry between two consecutive nodes by scan matching (RGBD/NeighborLinkRefining).

    Matching against the scans of several previous nodes (:func:`assemble_scan_map`) rather than
    the previous one alone ties each link to what the robot saw over the last metres, so the
    scan-matching noise of consecutive links does not add up as a random walk.

    Args:
        scan_map: (M,2) points (m) in the previous node's base frame: its scan's, or the previous
            nodes' scans assembled there.
        new_scan: the new node's scan.
        T_odom: 4x4 odometry motion ``T_previous_new``.
        odom_information: 6x6 information of the odometry motion (x y z roll pitch yaw).
        params: ICP gate, iterations, overlap and largest correction.

    Returns:
        ``(T_previous_new, information)``: the scan match, with the odometry fused in only along
        the directions the scans leave nearly free (:data:`NEIGHBOR_SCAN_DOMINANCE`), and its 6x6
        information (z, roll, pitch kept from odometry).

    Raises:
        RegistrationError: the scans overlap too little or ICP moved the odometry by more than
        ``icp_max_translation``; the caller keeps the odometry link.
    """
    planar = [0, 1, 5]
    odom_planar = odom_information[np.ix_(planar, planar)]
    # 1. Scan match from the odometry, held only weakly by it (NEIGHBOR_ICP_PRIOR_SCALE).
    fit = icp_fit(new_scan.points_base(), scan_map, T_odom,
                  NEIGHBOR_ICP_PRIOR_SCALE * odom_planar, params.icp_max_correspondence_distance,
                  params.icp_iterations)
    correction = float(np.linalg.norm(fit.T[:2, 3] - T_odom[:2, 3]))
    if fit.overlap < params.icp_min_overlap or correction >= params.icp_max_translation:
        raise RegistrationError(
            f"neighbour link refinement rejected: overlap {fit.overlap:.2f} (min {params.icp_min_overlap}), "
            f"correction {correction:.3f} m (max {params.icp_max_translation} m)")
    # 2. Combine per direction: in the generalised eigenvectors of (scan, odometry) information the
    # two are diagonal; along those the scans constrain at least NEIGHBOR_SCAN_DOMINANCE times as
    # well as the odometry, the scan match is kept as is; along the others (a featureless
    # corridor's axis) the odometry is fused in (information-weighted mean).
    x_odom = np.array(transforms.to_xy_yaw(T_odom))
    x_scan = np.array(transforms.to_xy_yaw(fit.T))
    d = x_scan - x_odom
    d[2] = transforms.wrap_angle(d[2])
    I_scan = fit.information
    ratios, V = scipy.linalg.eigh(I_scan, odom_planar)  # V' I_odom V = 1, V' I_scan V = diag(ratios)
    V_inv = np.linalg.inv(V)
    odom_kept = V_inv.T @ np.diag((ratios < NEIGHBOR_SCAN_DOMINANCE).astype(float)) @ V_inv
    fused_info = odom_kept + I_scan
    x = x_odom + np.linalg.solve(fused_info, I_scan @ d)
    info = np.array(odom_information, dtype=np.float64, copy=True)
    info[np.ix_(planar, planar)] = fused_info
    T_planar = transforms.from_xy_yaw(*x)
    T = T_planar @ transforms.inverse(transforms.project_planar(T_odom)) @ T_odom
    return T, info



def warm_up() -> None:
    """Compile the RANSAC and the ICP (or load them from numba's cache) here rather than in a frame."""
    icp.warm_up()
    angles = np.linspace(0.0, 2.0 * np.pi, 60, endpoint=False)
    points = np.column_stack([2.0 * np.cos(angles), 2.0 * np.sin(angles), angles])
    ransac_rigid(points, points, 0.1, 10, np.random.default_rng(DEFAULT_SEED))


__all__ = ["Registration", "assemble_scan_map", "correspondences", "pnp_ransac", "ransac_rigid",
           "refine_neighbor_link", "register", "register_pnp", "uses_pnp", "warm_up", "words_3d"]
