"""Registration: loop closure transforms on real RGB-D loop pairs, ICP, neighbour links, min_inliers.

Usage: ``python bench/bench_registration.py [--quick] [--parts loops,icp,neighbors,inliers,recording]``.
Prints tables and writes ``bench/results/registration.json`` (with ``--parts``, only those parts'
entries are replaced).

1. Loop closure transforms (issue 49): the 24 real TUM fr1_rpy loop pairs (hand-held Kinect
   turning fast: motion blur, rolling shutter) and the 2 fr1_xyz pairs, mocap ground truth. Each
   pair becomes two signatures the way the SLAM path makes them (GFTT/ORB features, the
   vocabulary of ``config/rtabmap.yaml``, the older frame quantised first, 3D words from depth)
   and is registered new -> old as a loop closure (6 DoF). Per pair: accepted or not, inliers,
   translation / rotation error against the ground truth, for PnP (``registration.estimation``
   auto in 6 DoF, the default) beside the 3D-3D RANSAC (3d, the estimate before issue 49), and the
   standard deviations of the PnP link's information matrix; then whether RGBD/OptimizeMaxError
   keeps the loop closure in a local map of the camera's way between the two frames (motion capture
   odometry, kept_by_graph_check). Beside them, what the images themselves say: the relative pose
   that best aligns the two images photometrically (every pixel with depth, started at the ground
   truth), against the ground truth, and each estimate's distance from it. Summary per estimator
   and ablation (no two-view refinement, no guided matching, keypoints undistorted with the fr1
   calibration, features only where the depth is valid as RTAB-Map's Mem/DepthAsMask): accepted and
   kept, median and max error, over 3 cm or 1.5 deg, time.
2. ICP (2D point-to-line): Intel lab corrected log, scans k -> k+5 overlapping >= 50 % at the
   reference, started 10 cm / 3 degrees off; error and time (median). Baseline: the start error.
3. Neighbour links (RGBD/NeighborLinkRefining): wheel odometry, ICP against the previous scan and
   ICP against the last ``neighbor_scan_map_nodes`` scans, on the simulated sessions and on the
   real CARMEN logs (with simulated wheel errors); per-link error and the drift of the chained
   links. Baseline in the same run: the odometry and the previous scan alone.
4. min_inliers: inlier counts of true pairs (same scene) vs wrong pairs (TUM frames vs the
   RTAB-Map repository frames, different scenes), ORB 1000 with mutual matches, and with mutual
   matches + the NNDR test (0.8) that the vocabulary applies; PnP and 3D-3D.
5. A real recording (issue 49's recording yardstick, through the commands a user runs): the 48
   distinct fr1_rpy frames of the loop pairs in time order as a TUM folder, ``tum2bag`` with a
   drifting odometry (0.5 deg/s, 1 cm/s; three drift seeds), ``map`` in 6 DoF, every frame a node
   and at 2 Hz; per run the loop closures kept, those off the motion capture by more than 5 cm or
   3 deg, the worst, and the map's ATE against the odometry's. Images as recorded with the
   calibration's distortion in CameraInfo (tum2bag's default), rectified (``--rectify``), and as
   recorded but with D left out (the baseline: what the map made before the distortion was read);
   and the images as recorded mapped with proximity detection by space (RGBD/ProximityBySpace).
"""

from __future__ import annotations

import argparse
import itertools
import json
import statistics
import sys
import time
from pathlib import Path

import csv
import subprocess
import tempfile
from dataclasses import replace

import cv2
import numpy as np
from scipy.ndimage import map_coordinates
from scipy.spatial import cKDTree

from rtabmap_ros2.core import icp, registration, transforms
from rtabmap_ros2.core.features import FeatureExtractor
from rtabmap_ros2.core.graph import Link, LinkType
from rtabmap_ros2.core.icp import icp_2d
from rtabmap_ros2.core.params import Params, RegistrationParams, default_config_path
from rtabmap_ros2.core.registration import correspondences, register, words_3d
from rtabmap_ros2.core.rtabmap import Rtabmap
from rtabmap_ros2.core.sensor import CameraModel
from rtabmap_ros2.core.signature import Signature
from rtabmap_ros2.core.vocabulary import Vocabulary
from rtabmap_ros2.errors import RegistrationError
from rtabmap_ros2.io.carmen import read_carmen_log
from rtabmap_ros2.io.trajectory import Trajectory, ate

REPO = Path(__file__).resolve().parents[1]
DATA = REPO.parent / "shared" / "data"
RESULTS = REPO / "bench" / "results" / "registration.json"
CAMERA = CameraModel(525.0, 525.0, 319.5, 239.5, 640, 480)
NNDR = 0.8
# Loop pairs: the sets, TUM's depth scale (value / 5000 = m), and the issue's yardstick: an accepted
# loop closure more than this far from the ground truth is off.
LOOP_SETS = ("tum_fr1_rpy_loops", "tum_fr1_xyz_pairs")
TUM_DEPTH_SCALE = 5000.0
OFF_CM, OFF_DEG = 3.0, 1.5
# The fr1 RGB camera's distortion (TUM's calibration, OpenCV k1 k2 p1 p2 k3): the images are not rectified.
FR1_DISTORTION = np.array([0.2624, -0.9531, -0.0054, 0.0026, 1.1633])
# Photometric alignment (what the images say): pyramid scales, Gauss-Newton steps per scale, pixels
# used (depth at least this far, intensity gradient at least this steep), Cauchy scale in robust
# standard deviations of the residuals.
PHOTO_SCALES = (4, 2, 1)
PHOTO_STEPS = 20
PHOTO_MIN_DEPTH_M = 0.3
PHOTO_MIN_GRADIENT = 2.0
PHOTO_CAUCHY = 2.0
# Issue 49's median target for the accepted pairs' rotation error (deg).
IMAGES_MEDIAN_DEG = 0.5
# Graph check of a loop pair's loop closure: the camera's way between the two frames as this many
# neighbour links, each good to (m, deg).
GRAPH_CHECK_STEPS = 10
GRAPH_CHECK_STEP_SIGMA = (0.002, 0.1)
# The recording (part 5): tum2bag's drift, its seeds, the detection rates (0: every frame), and the
# issue's yardstick for a loop closure kept in the map (off by more than this: wrong).
RECORDING_DRIFT = ("--drift-yaw-deg-s", "0.5", "--drift-m-s", "0.01")
RECORDING_SEEDS = (0, 1, 2)
RECORDING_RATES = (0.0, 2.0)
RECORDING_OFF_CM, RECORDING_OFF_DEG = 5.0, 3.0
# The fr1 calibration without its distortion (tum2bag --camera numbers): the baseline's CameraInfo.
FR1_PINHOLE = "517.306408,516.469215,318.643040,255.313989"
RECORDING_IMAGES = {"raw, D in CameraInfo": (), "rectified": ("--rectify",),
                    "raw, D left out": ("--camera", FR1_PINHOLE)}
# Settings of ``map`` compared on the images as recorded (tum2bag's default), each its own rows: the
# defaults, and proximity detection by space (RTAB-Map's default, off here: graph.proximity_by_space).
RECORDING_SETTINGS = {"": (), ", proximity by space": ("--set", "RGBD/ProximityBySpace=true")}


def load_image(kind: str, name: str):
    if kind == "tum":
        case, which = name.split("/")
        folder = DATA / "rgbd" / "tum_fr1_xyz_pairs" / case
        gray = cv2.imread(str(folder / f"img_{which}.png"), cv2.IMREAD_GRAYSCALE)
        depth = cv2.imread(str(folder / f"dep_{which}.png"), cv2.IMREAD_UNCHANGED).astype(np.float32) / 5000.0
        v = np.loadtxt(folder / f"pose_{which}.txt")
        pose = transforms.from_xyz_quat_xyzw(v[:3], v[3:])
    else:
        folder = DATA / "rgbd" / "rtabmap_frames"
        gray = cv2.imread(str(folder / "rgb" / f"{name}.jpg"), cv2.IMREAD_GRAYSCALE)
        depth = cv2.imread(str(folder / "depth" / f"{name}.png"), cv2.IMREAD_UNCHANGED).astype(np.float32) / 1000.0
        pose = None
    depth[depth == 0] = np.nan
    return gray, depth, pose


def signatures(a, b, nndr: bool):
    """Signatures of two images with word ids from mutual matches (optionally + NNDR test)."""
    orb = cv2.ORB_create(1000)
    ka, da = orb.detectAndCompute(a[0], None)
    kb, db = orb.detectAndCompute(b[0], None)
    ids_a = np.arange(len(ka), dtype=np.int64) + 1
    ids_b = np.arange(len(kb), dtype=np.int64) + 1 + len(ka)
    matcher = cv2.BFMatcher(cv2.NORM_HAMMING)
    ab = matcher.knnMatch(da, db, k=2)
    ba = {m[0].queryIdx: m[0].trainIdx for m in matcher.knnMatch(db, da, k=2) if m}
    for m in ab:
        if not m or ba.get(m[0].trainIdx) != m[0].queryIdx:
            continue
        if nndr and (len(m) < 2 or m[0].distance >= NNDR * m[1].distance):
            continue
        ids_b[m[0].trainIdx] = ids_a[m[0].queryIdx]
    kpa = np.array([k.pt for k in ka], np.float32)
    kpb = np.array([k.pt for k in kb], np.float32)
    return (Signature(1, 1, 0, ids_a, kpa, words_3d(kpa, a[1], CAMERA), camera=CAMERA),
            Signature(2, 1, 0, ids_b, kpb, words_3d(kpb, b[1], CAMERA), camera=CAMERA))


def pose_error(T, truth):
    e = transforms.inverse(truth) @ T
    return float(np.linalg.norm(e[:3, 3])), float(np.degrees(transforms.rotation_angle(e)))


def _read_frame(folder: Path, which: str):
    """RGB (HxWx3 uint8), depth (HxW float32 m, NaN invalid) and ground-truth pose of one frame of a pair."""
    rgb = cv2.cvtColor(cv2.imread(str(folder / f"img_{which}.png")), cv2.COLOR_BGR2RGB)
    depth = cv2.imread(str(folder / f"dep_{which}.png"), cv2.IMREAD_UNCHANGED).astype(np.float32) / TUM_DEPTH_SCALE
    depth[depth == 0] = np.nan
    v = np.loadtxt(folder / f"pose_{which}.txt")
    return rgb, depth, transforms.from_xyz_quat_xyzw(v[:3], v[3:])


def _pair_camera(folder: Path) -> CameraModel:
    K = np.loadtxt(folder.parent / "kinect_params.txt")
    return CameraModel(K[0, 0], K[1, 1], K[0, 2], K[1, 2], 640, 480)


def loop_pair(folder: Path, params: Params, undistort: bool = False) -> dict:
    """Signatures of a pair as the SLAM path makes them (features, the vocabulary with the older frame
    quantised first, 3D words from depth; ``undistort``: keypoints undistorted with the fr1
    calibration first), their word descriptors (guided matching), the ground truth of new -> old and
    the frames."""
    camera = _pair_camera(folder)
    if undistort:   # as the SLAM path does with a CameraInfo's D and P = K (io/bag.py raw_image_distortion)
        camera = replace(camera, distortion=tuple(FR1_DISTORTION))
    extractor = FeatureExtractor(params.features)
    vocabulary = Vocabulary(params.vocabulary, extractor.binary, background_rebuild=False)
    frames, signatures = {}, {}
    for node, which in ((1, "prev"), (2, "curr")):
        rgb, depth, pose = frames[which] = _read_frame(folder, which)
        features = extractor.extract(rgb, depth)   # as frame_features does
        word_ids, _ = vocabulary.quantize(features.descriptors)
        points = words_3d(features.keypoints, depth, camera)
        signatures[which] = Signature(node, 1, 0, word_ids, camera.undistort(features.keypoints), points, camera=camera)
    new, old = signatures["curr"], signatures["prev"]
    return {"new": new, "old": old, "camera": camera, "frames": frames,
            "descriptors": (vocabulary.descriptors_of(new.word_ids), vocabulary.descriptors_of(old.word_ids)),
            "truth": transforms.relative(frames["curr"][2], frames["prev"][2])}


def photometric_optimum(pair: dict, reverse: bool = False) -> np.ndarray:
    """T_new_old that best aligns the two images photometrically, started at the ground truth.
    ``reverse``: the new frame's depth warped into the old image instead (the same T_new_old): the
    two directions use different pixels and depth, so their difference is the optimum's own
    uncertainty.

    Both images rectified with the fr1 calibration, every pixel of the old frame with depth and
    texture warped into the new image; Gauss-Newton on the intensity differences (a brightness
    offset removed: auto-exposure), Cauchy weights, coarse to fine. An estimator that uses the
    images cannot be expected nearer the ground truth than this: where they differ by degrees, the
    pictures were taken at other poses than the ground truth's at their stamps (blur, rolling
    shutter, time offsets).
    """
    if reverse:
        swapped = {**pair, "frames": {"prev": pair["frames"]["curr"], "curr": pair["frames"]["prev"]},
                   "truth": transforms.inverse(pair["truth"])}
        return transforms.inverse(photometric_optimum(swapped))
    camera = pair["camera"]
    K = np.array([[camera.fx, 0, camera.cx], [0, camera.fy, camera.cy], [0, 0, 1.0]])
    map_x, map_y = cv2.initUndistortRectifyMap(K, FR1_DISTORTION, None, K, (camera.width, camera.height), cv2.CV_32FC1)
    gray = {w: cv2.remap(cv2.cvtColor(f[0], cv2.COLOR_RGB2GRAY), map_x, map_y, cv2.INTER_LINEAR)
            for w, f in pair["frames"].items()}
    depth_old = cv2.remap(np.nan_to_num(pair["frames"]["prev"][1], nan=0.0), map_x, map_y, cv2.INTER_NEAREST)
    T_new_old = pair["truth"].copy()
    for scale in PHOTO_SCALES:
        size = (camera.width // scale, camera.height // scale)
        old = cv2.resize(gray["prev"], size, interpolation=cv2.INTER_AREA).astype(np.float64)
        new = cv2.resize(gray["curr"], size, interpolation=cv2.INTER_AREA).astype(np.float64)
        z_all = cv2.resize(depth_old, size, interpolation=cv2.INTER_NEAREST).astype(np.float64)
        fx, fy = camera.fx / scale, camera.fy / scale
        cx, cy = (camera.cx + 0.5) / scale - 0.5, (camera.cy + 0.5) / scale - 0.5
        grad_x = cv2.Sobel(new, cv2.CV_64F, 1, 0, ksize=3) / 8
        grad_y = cv2.Sobel(new, cv2.CV_64F, 0, 1, ksize=3) / 8
        texture = np.hypot(cv2.Sobel(old, cv2.CV_64F, 1, 0, ksize=3), cv2.Sobel(old, cv2.CV_64F, 0, 1, ksize=3)) / 8
        v, u = np.nonzero((z_all > PHOTO_MIN_DEPTH_M) & (texture > PHOTO_MIN_GRADIENT))
        z = z_all[v, u]
        points = np.column_stack([(u - cx) * z / fx, (v - cy) * z / fy, z])  # old camera frame
        intensity = old[v, u]
        for _ in range(PHOTO_STEPS):
            X = points @ T_new_old[:3, :3].T + T_new_old[:3, 3]
            pu, pv = X[:, 0] / X[:, 2] * fx + cx, X[:, 1] / X[:, 2] * fy + cy
            ok = (X[:, 2] > PHOTO_MIN_DEPTH_M) & (pu > 1) & (pu < size[0] - 2) & (pv > 1) & (pv < size[1] - 2)
            X, pu, pv = X[ok], pu[ok], pv[ok]
            r = map_coordinates(new, [pv, pu], order=1) - intensity[ok]
            r -= np.median(r)
            d_pixel = (map_coordinates(grad_x, [pv, pu], order=1)[:, None] * np.column_stack(
                [fx / X[:, 2], np.zeros(len(X)), -fx * X[:, 0] / X[:, 2] ** 2])
                + map_coordinates(grad_y, [pv, pu], order=1)[:, None] * np.column_stack(
                [np.zeros(len(X)), fy / X[:, 2], -fy * X[:, 1] / X[:, 2] ** 2]))
            J = np.column_stack([np.cross(X, d_pixel), d_pixel])  # left update exp(xi) T_new_old
            sigma = 1.4826 * np.median(np.abs(r)) + 1e-6
            w = 1.0 / (1.0 + (r / (PHOTO_CAUCHY * sigma)) ** 2)
            xi = -np.linalg.solve(J.T @ (w[:, None] * J), J.T @ (w * r))
            step = np.eye(4)
            step[:3, :3] = cv2.Rodrigues(xi[:3])[0]
            step[:3, 3] = xi[3:]
            T_new_old = step @ T_new_old
    return T_new_old


def kept_by_graph_check(pair: dict, T_new_old: np.ndarray, information: np.ndarray) -> bool:
    """RGBD/OptimizeMaxError on a loop closure of a real pair: the local map of the camera's way
    from the old frame to the new one (GRAPH_CHECK_STEPS neighbour links of the motion capture's
    motion, each good to GRAPH_CHECK_STEP_SIGMA), the loop closure added with the new node and the
    map optimised as the SLAM path does (6 DoF); True when it stays."""
    params = Params().with_value("registration.planar", False)
    info = np.diag([GRAPH_CHECK_STEP_SIGMA[0] ** -2] * 3 + [np.deg2rad(GRAPH_CHECK_STEP_SIGMA[1]) ** -2] * 3)
    T_old, T_new = pair["frames"]["prev"][2], pair["frames"]["curr"][2]
    relative = transforms.relative(T_old, T_new)
    rotation = cv2.Rodrigues(relative[:3, :3])[0]
    poses = []
    for k in range(GRAPH_CHECK_STEPS + 1):
        step = np.eye(4)
        step[:3, :3] = cv2.Rodrigues(rotation * k / GRAPH_CHECK_STEPS)[0]
        step[:3, 3] = relative[:3, 3] * k / GRAPH_CHECK_STEPS
        poses.append(T_old @ step)
    with tempfile.TemporaryDirectory(prefix="bench_registration_") as tmp:
        rtabmap = Rtabmap(params, Path(tmp) / "loop.db")
        try:
            rtabmap.local.planar = False
            memory = rtabmap.memory
            for node, pose in enumerate(poses, start=1):
                neighbour = None if node == 1 else Link(node - 1, node, LinkType.NEIGHBOR,
                                                        transforms.relative(poses[node - 2], pose), info)
                memory.add_location(Signature(id=node, map_id=0, stamp_ns=node, T_odom_base=pose), None, neighbour)
                memory.update_stm()
                rtabmap.local.new_loops = []
                if node == len(poses):
                    link = Link(node, 1, LinkType.LOOP_INTRA, T_new_old, information)
                    rtabmap.local.new_loops = [(link, memory.add_loop_closure(link))]
                rejected = rtabmap.local.update(node)
        finally:
            rtabmap.close()
    return not rejected


def _register_row(pair: dict, params: RegistrationParams, with_descriptors: bool = True) -> dict:
    """One estimator on one pair: accepted, inliers, errors (cm, deg) against the motion capture and
    against the images' photometric optimum (``pair["images"]``), standard deviations, ms, and whether
    the graph check keeps it."""
    start = time.perf_counter()
    try:
        reg = register(pair["new"], pair["old"], params, descriptors=pair["descriptors"] if with_descriptors else None)
    except RegistrationError:
        return {"accepted": False, "inliers": 0, "ms": (time.perf_counter() - start) * 1e3}
    ms = (time.perf_counter() - start) * 1e3
    t_err, r_err = pose_error(reg.T_from_to, pair["truth"])
    t_img, r_img = pose_error(reg.T_from_to, pair["images"])
    return {"accepted": True, "inliers": reg.inliers, "translation_error_cm": 100 * t_err, "rotation_error_deg": r_err,
            "vs_images_cm": 100 * t_img, "vs_images_deg": r_img,
            "sigma_cm": 100 / np.sqrt(reg.information[0, 0]),
            "sigma_deg": float(np.degrees(1 / np.sqrt(reg.information[3, 3]))),
            "ms": ms, "kept_by_graph_check": kept_by_graph_check(pair, reg.T_from_to, reg.information)}


def _off(row: dict) -> bool:
    return row["translation_error_cm"] > OFF_CM or row["rotation_error_deg"] > OFF_DEG


def _summary(rows: list[dict]) -> dict:
    """Accepted, median / max errors over the accepted, how many off (> OFF_CM or > OFF_DEG), median
    ms; the same after the graph check."""
    accepted = [r for r in rows if r["accepted"]]
    kept = [r for r in accepted if r["kept_by_graph_check"]]
    out = {"pairs": len(rows), "median_ms": float(np.median([r["ms"] for r in rows]))}
    for name, chosen in (("accepted", accepted), ("kept", kept)):
        t = [r["translation_error_cm"] for r in chosen]
        d = [r["rotation_error_deg"] for r in chosen]
        out[name] = {"count": len(chosen), "median_cm": float(np.median(t)) if t else None,
                     "median_deg": float(np.median(d)) if d else None, "max_cm": max(t, default=None),
                     "max_deg": max(d, default=None), "off": sum(1 for r in chosen if _off(r))}
    for key in ("cm", "deg"):
        values = [r[f"vs_images_{key}"] for r in accepted]
        out["accepted"][f"vs_images_median_{key}"] = float(np.median(values)) if values else None
    return out


def loop_pairs(quick: bool) -> dict:
    """Issue 49's yardstick: every loop pair through PnP (default parameters of config/rtabmap.yaml,
    6 DoF) and the 3D-3D RANSAC, with ablations, and the images' own photometric optimum."""
    params = Params.from_yaml(default_config_path())
    pnp = replace(params.registration, planar=False, icp_refine=False)
    # estimator -> (registration parameters, descriptors paired, the pair's signatures: as the SLAM path
    # makes them ("plain"), keypoints undistorted, features only where the depth is valid)
    estimators = {"pnp": (pnp, True, "plain"), "3d": (replace(pnp, estimation="3d"), True, "plain")}
    if not quick:
        estimators.update({
            "pnp, no two-view refinement": (replace(pnp, bundle_adjustment=False), True, "plain"),
            "pnp, no guided matching": (replace(pnp, guided_window=0.0), False, "plain"),
            "pnp, keypoints undistorted": (pnp, True, "undistorted"),
            "pnp, depth as mask (RTAB-Map's Mem/DepthAsMask)": (pnp, True, "depth as mask")})
    as_mask = params.with_value("features.depth_as_mask", True)
    speeds = {}
    rows = {name: [] for name in estimators}
    pairs_out = []
    for name in LOOP_SETS:
        folder = DATA / "rgbd" / name
        if (folder / "pairs.csv").exists():
            with open(folder / "pairs.csv") as f:
                speeds.update({f"{name}/{r['case']}": max(float(r["angvel_prev_deg_s"]), float(r["angvel_curr_deg_s"]))
                               for r in csv.DictReader(f)})
        for case in sorted(folder.glob("case_*")):
            key = f"{name}/{case.name}"
            pair = loop_pair(case, params)
            pair["images"] = photometric_optimum(pair)
            variants = {"plain": pair}
            if not quick:
                variants["undistorted"] = {**loop_pair(case, params, undistort=True), "images": pair["images"]}
                variants["depth as mask"] = {**loop_pair(case, as_mask), "images": pair["images"]}
            row = {"pair": key, "angular_speed_deg_s": speeds.get(key)}
            for est, (reg_params, with_descriptors, variant) in estimators.items():
                row[est] = _register_row(variants[variant], reg_params, with_descriptors)
                rows[est].append({**row[est], "set": name})
            for field, T in (("images_vs_truth", pair["images"]),
                             ("images_reverse_vs_truth", photometric_optimum(pair, reverse=True))):
                t_img, r_img = pose_error(T, pair["truth"])
                row[field] = {"translation_error_cm": 100 * t_img, "rotation_error_deg": r_img}
            pairs_out.append(row)
    rpy = [r for r in pairs_out if r["pair"].startswith(LOOP_SETS[0])]
    floor = images_floor(rpy)
    summary = {est: {s: _summary([r for r in rs if r["set"] == s]) for s in LOOP_SETS} for est, rs in rows.items()}
    return {"pairs": pairs_out, "summary": summary, "images_vs_truth_rpy": floor,
            "registration_params": {k: getattr(pnp, k) for k in ("estimation", "min_inliers", "pnp_reprojection_error",
                                                                 "pnp_refine_iterations", "bundle_adjustment",
                                                                 "pnp_max_variance", "guided_window",
                                                                 "ransac_iterations")}}


def images_floor(rows: list[dict]) -> dict:
    """What the images allow on these pairs, from their photometric optimum both ways (old depth into
    the new image, new depth into the old): medians against the motion capture, pairs within the
    yardstick (OFF_CM / OFF_DEG) either way, and pairs whose rotation is within issue 49's median
    target (IMAGES_MEDIAN_DEG) either way: a median of that over 18 accepted pairs needs 9 of them."""
    def within(r: dict) -> bool:
        return r["translation_error_cm"] <= OFF_CM and r["rotation_error_deg"] <= OFF_DEG

    out = {}
    for name, field in (("", "images_vs_truth"), ("reverse_", "images_reverse_vs_truth")):
        out[f"{name}median_cm"] = float(np.median([r[field]["translation_error_cm"] for r in rows]))
        out[f"{name}median_deg"] = float(np.median([r[field]["rotation_error_deg"] for r in rows]))
        out[f"{name}within"] = sum(1 for r in rows if within(r[field]))
    out["within_either"] = sum(1 for r in rows if within(r["images_vs_truth"]) or within(r["images_reverse_vs_truth"]))
    out["rotation_within_median_target_either"] = sum(
        1 for r in rows if min(r["images_vs_truth"]["rotation_error_deg"],
                               r["images_reverse_vs_truth"]["rotation_error_deg"]) <= IMAGES_MEDIAN_DEG)
    return out


def print_loop_pairs(result: dict) -> None:
    print("Loop closure transforms on real RGB-D pairs, new -> old, 6 DoF (errors vs motion capture; x after the "
          "inliers: removed by the graph check; 'images' = the photometric optimum vs motion capture, old depth into the new image; 'other way': new depth into the old)")
    print(f"{'pair':<28} {'deg/s':>5} | {'PnP inl':>7} {'cm':>6} {'deg':>5} {'sd cm':>5} {'sd deg':>6} | "
          f"{'3D-3D inl':>9} {'cm':>6} {'deg':>5} | {'images cm':>9} {'deg':>5} | {'other way cm':>12} {'deg':>5}")

    def cells(r: dict, sigma: bool) -> str:
        if not r["accepted"]:
            return f"{'-':>7} {'':>6} {'':>5}" + (f" {'':>5} {'':>6}" if sigma else "")
        text = (f"{r['inliers']:>6d}{'' if r['kept_by_graph_check'] else 'x'} {r['translation_error_cm']:>6.2f} "
                f"{r['rotation_error_deg']:>5.2f}")
        return text + (f" {r['sigma_cm']:>5.2f} {r['sigma_deg']:>6.2f}" if sigma else "")

    for row in result["pairs"]:
        speed = f"{row['angular_speed_deg_s']:>5.0f}" if row["angular_speed_deg_s"] is not None else f"{'':>5}"
        img, rev = row["images_vs_truth"], row["images_reverse_vs_truth"]
        print(f"{row['pair']:<28} {speed} | {cells(row['pnp'], True)} | {cells(row['3d'], False):>22} | "
              f"{img['translation_error_cm']:>9.2f} {img['rotation_error_deg']:>5.2f} | "
              f"{rev['translation_error_cm']:>12.2f} {rev['rotation_error_deg']:>5.2f}")
    print(f"Summary per estimator and set: accepted, then kept by the graph check (RGBD/OptimizeMaxError on the "
          f"loop's {GRAPH_CHECK_STEPS} odometry links, each {GRAPH_CHECK_STEP_SIGMA[0] * 1000:g} mm / "
          f"{GRAPH_CHECK_STEP_SIGMA[1]:g} deg); off = more than {OFF_CM:g} cm or {OFF_DEG:g} deg from the motion capture")
    for est, by_set in result["summary"].items():
        for name, s in by_set.items():
            text = []
            for what in ("accepted", "kept"):
                c = s[what]
                med = (f" median {c['median_cm']:.2f} cm / {c['median_deg']:.2f} deg, max {c['max_cm']:.2f} cm / "
                       f"{c['max_deg']:.2f} deg, off {c['off']}" if c["count"] else "")
                text.append(f"{what} {c['count']:>2}{med}")
            a = s["accepted"]
            near = (f"; accepted vs the images' optimum median {a['vs_images_median_cm']:.2f} cm / "
                    f"{a['vs_images_median_deg']:.2f} deg" if a["count"] else "")
            print(f"  {est:<28} {name:<18} /{s['pairs']:<2} {'; '.join(text)}{near}; {s['median_ms']:.1f} ms")
    floor = result["images_vs_truth_rpy"]
    print(f"  images' photometric optimum vs motion capture, {LOOP_SETS[0]}: median {floor['median_cm']:.2f} cm / "
          f"{floor['median_deg']:.2f} deg (the other way {floor['reverse_median_cm']:.2f} cm / "
          f"{floor['reverse_median_deg']:.2f} deg); within {OFF_CM:g} cm and {OFF_DEG:g} deg on {floor['within']} "
          f"of 24 pairs ({floor['reverse_within']} the other way, {floor['within_either']} either way); rotation "
          f"within {IMAGES_MEDIAN_DEG:g} deg either way on {floor['rotation_within_median_target_either']}")


def read_carmen(path):
    """(LaserScans, corrected poses) of a CARMEN log."""
    log = read_carmen_log(path)
    return log.laser_scans(), log.poses()


def icp_accuracy(stride: int) -> dict:
    scans, poses = read_carmen(DATA / "carmen" / "intel-corrected.log.gz")
    perturbation = transforms.from_xy_yaw(0.10, 0.0, np.radians(3.0))
    errs, times, overlaps = [], [], []
    for k in range(0, len(scans) - 5, stride):
        truth = transforms.relative(poses[k], poses[k + 5])
        src, tgt = scans[k + 5].points_base(), scans[k].points_base()
        d, _ = cKDTree(tgt).query(src @ truth[:2, :2].T + truth[:2, 3])
        if np.mean(d < 0.1) < 0.5:
            continue
        t0 = time.perf_counter()
        T, overlap, _ = icp_2d(src, tgt, truth @ perturbation)
        times.append((time.perf_counter() - t0) * 1e3)
        e = transforms.inverse(truth) @ T
        errs.append((float(np.hypot(e[0, 3], e[1, 3])), abs(float(np.degrees(transforms.yaw_of(e))))))
        overlaps.append(overlap)
    errs = np.array(errs)
    return {"pairs": len(errs), "start_error_cm": 10.0, "start_error_deg": 3.0,
            "median_translation_error_cm": 100 * float(np.median(errs[:, 0])),
            "median_rotation_error_deg": float(np.median(errs[:, 1])),
            "p90_translation_error_cm": 100 * float(np.percentile(errs[:, 0], 90)),
            "p90_rotation_error_deg": float(np.percentile(errs[:, 1], 90)),
            "median_overlap": float(np.median(overlaps)), "median_ms": float(np.median(times)),
            "normal_neighbors": icp.ICP_NORMAL_NEIGHBORS, "robust_scale_m": icp.ICP_ROBUST_SCALE}


def inlier_counts() -> list[dict]:
    images = {f"tum/{c}/{w}": ("tum", f"{c}/{w}") for c in ("case_1", "case_2") for w in ("prev", "curr")}
    images.update({f"rtabmap/{n}": ("rtabmap", n) for n in ("17", "154")})
    loaded = {k: load_image(*v) for k, v in images.items()}
    # Inlier counts, not acceptance: no variance limit (a wrong pair's few inliers would read 0).
    estimators = {"pnp": RegistrationParams(planar=False, icp_refine=False, min_inliers=3, pnp_max_variance=0.0),
                  "3d": RegistrationParams(planar=False, icp_refine=False, min_inliers=3, estimation="3d")}
    rows = []
    for x, y in itertools.combinations(loaded, 2):
        same = x.startswith("tum") and y.startswith("tum")
        label = "true (same scene)" if same else ("rtabmap 17 vs 154" if x.startswith("rtabmap") else "wrong")
        row = {"pair": f"{x} vs {y}", "kind": label}
        for nndr in (False, True):
            sa, sb = signatures(loaded[x], loaded[y], nndr)
            pf, _ = correspondences(sa, sb)
            cell = {"correspondences": len(pf)}
            for est, params in estimators.items():
                try:
                    cell[est] = register(sa, sb, params).inliers
                except RegistrationError:
                    cell[est] = 0
            row["nndr" if nndr else "mutual"] = cell
        rows.append(row)
    return rows


NEIGHBOR_LINK_KINDS = ("odometry", "scan_to_scan", "scan_map")


def _chain_neighbor_links(scans: list, odometry: list[np.ndarray], covariances: list[np.ndarray],
                          truth: list[np.ndarray], stamps: np.ndarray, kind: str, params: RegistrationParams) -> dict:
    """Neighbour links of one sequence of nodes (wheel odometry, or refined as the product does,
    against the previous scan or the last ``neighbor_scan_map_nodes`` scans at the poses of the
    links so far); their errors against ``truth`` and the ATE of the links chained from the first node."""
    nodes = {"odometry": 0, "scan_to_scan": 1, "scan_map": params.neighbor_scan_map_nodes}[kind]
    chained, errors, times, refused = [transforms.identity()], [], [], 0
    for k in range(1, len(scans)):
        T_link = transforms.relative(odometry[k - 1], odometry[k])
        if nodes:
            start = time.perf_counter()
            T_previous_first = transforms.inverse(chained[k - 1])
            scan_map = registration.assemble_scan_map(
                [(T_previous_first @ chained[j], scans[j]) for j in range(max(0, k - nodes), k)],
                params.scan_map_voxel_size)
            try:
                T_link, _ = registration.refine_neighbor_link(scan_map, scans[k], T_link,
                                                              np.linalg.inv(covariances[k]), params)
            except RegistrationError:
                refused += 1
            times.append((time.perf_counter() - start) * 1000.0)
        err = transforms.relative(transforms.relative(truth[k - 1], truth[k]), T_link)
        errors.append((float(np.linalg.norm(err[:2, 3])) * 1000.0, float(np.degrees(transforms.yaw_of(err)))))
        chained.append(chained[-1] @ T_link)
    chain_ate = ate(Trajectory(stamps, np.array(chained)), Trajectory(stamps, np.array(truth))).rmse_m
    return {"errors": errors, "times": times, "refused": refused, "chain_ate_m": chain_ate, "nodes": nodes}


def _summarise_links(runs: list[dict]) -> dict:
    """Medians and extremes over the links of several sequences; the chained ATE of each."""
    errors = np.array([e for r in runs for e in r["errors"]])
    times = [t for r in runs for t in r["times"]]
    yaw = np.abs(errors[:, 1])
    return {"links": len(errors), "refused": sum(r["refused"] for r in runs), "scan_map_nodes": runs[0]["nodes"],
            "median_mm": float(np.median(errors[:, 0])), "median_deg": float(np.median(yaw)),
            "p99_deg": float(np.percentile(yaw, 99)), "max_deg": float(yaw.max()),
            "mean_deg": float(np.mean(errors[:, 1])), "chain_ate_m": [r["chain_ate_m"] for r in runs],
            "median_ms": statistics.median(times) if times else 0.0}


def neighbor_link_refining(sessions: int, frames_used: int | None) -> dict:
    """Per-link error against ground truth between consecutive frames of the simulated building's
    sessions, of wheel odometry and of RGBD/NeighborLinkRefining (ICP from the odometry, which fills
    in only what the scans leave free) against the previous scan alone (``scan_to_scan``) and against
    the last ``neighbor_scan_map_nodes`` scans assembled (``scan_map``, the default): medians, the
    largest yaw errors (turns, where the odometry is worst), the mean signed yaw error (what a
    systematic odometry error leaves in every link) and, per session, the drift of the links chained
    from its first frame (ATE after one rigid alignment)."""
    from rtabmap_ros2.sim import build_world, make_sessions, session_frames

    world = build_world(0)
    params = RegistrationParams()
    runs = {kind: [] for kind in NEIGHBOR_LINK_KINDS}
    for session in make_sessions(world)[:sessions]:
        # Scans and odometry only, frame by frame (a whole session's images would take gigabytes).
        kept = [(f.scan, f.T_odom_base, f.odom_covariance)
                for f in itertools.islice(session_frames(world, session), frames_used)]
        scans, odometry, covariances = (list(column) for column in zip(*kept))
        stamps = np.array(session.stamps_ns[:len(scans)], dtype=np.int64)
        truth = list(session.T_world_base[:len(scans)])
        for kind in NEIGHBOR_LINK_KINDS:
            runs[kind].append(_chain_neighbor_links(scans, odometry, covariances, truth, stamps, kind, params))
    return {kind: _summarise_links(r) for kind, r in runs.items()}


def neighbor_links_real(logs: tuple[str, ...], seed: int = 0) -> dict:
    """The same on the real CARMEN logs: nodes where the corrected pose moved 0.5 m or 15 deg
    (about the simulated robot's 1 Hz at 0.5 m/s), wheel odometry = the corrected motion with the
    simulated robot's wheel errors (robot.wheel_odometry, its covariance per step), truth = the
    corrected poses (themselves a SLAM estimate, good to a few cm)."""
    from rtabmap_ros2.sim.robot import step_covariance, wheel_odometry

    rng = np.random.default_rng(seed)
    params = RegistrationParams()
    runs = {kind: [] for kind in NEIGHBOR_LINK_KINDS}
    for name in logs:
        log = read_carmen_log(DATA / "carmen" / f"{name}-corrected.log.gz")
        all_scans, all_poses = log.laser_scans(), log.poses()
        keep = [0]
        for k in range(1, len(all_poses)):
            step = transforms.relative(all_poses[keep[-1]], all_poses[k])
            if np.hypot(*step[:2, 3]) >= 0.5 or abs(transforms.yaw_of(step)) >= np.radians(15.0):
                keep.append(k)
        truth = [all_poses[k] for k in keep]
        scans = [all_scans[k] for k in keep]
        odometry = list(wheel_odometry(np.array([transforms.to_xy_yaw(T) for T in truth]), rng))
        covariance = step_covariance(0.5)
        stamps = np.array([log.scans[k].stamp_ns for k in keep], dtype=np.int64)
        for kind in NEIGHBOR_LINK_KINDS:
            runs[kind].append(_chain_neighbor_links(scans, odometry, [covariance] * len(scans), truth, stamps, kind,
                                                    params))
    return {kind: _summarise_links(r) for kind, r in runs.items()}


def _cli(*args) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "rtabmap_ros2.cli.cli", *map(str, args)],
                          capture_output=True, text=True, cwd=REPO)


def _recording_run(folder: Path, work: Path, images: tuple[str, ...], seed: int, rate: float,
                   settings: tuple[str, ...] = ()) -> dict:
    """tum2bag + map (6 DoF, with ``settings``) into the empty folder ``work``, then every loop closure
    of the database judged against the motion capture."""
    from rtabmap_ros2.core.global_map import load_global_map
    from rtabmap_ros2.io.trajectory import read_tum

    bag, db = work / "bag", work / "map.db"
    for command in (("tum2bag", folder, "--out", bag, "--seed", seed, *RECORDING_DRIFT, *images),
                    ("map", bag, "--db", db, "--no-progress", "--set", "Reg/Force3DoF=false",
                     "--set", f"Rtabmap/DetectionRate={rate:g}", *settings)):
        done = _cli(*command)
        if done.returncode != 0:
            raise RuntimeError(f"{command[0]} failed: {done.stderr.strip().splitlines()[-1:]}")
    gmap = load_global_map(db, Params.from_yaml(default_config_path()).with_overrides(["registration.planar=false"]))
    truth = read_tum(bag / "ground_truth.txt")
    at = dict(zip(truth.stamps_ns.tolist(), truth.poses))
    errors = []
    for link in gmap.links:
        if link.type.is_loop_closure:
            E = link.residual(at[gmap.stamps_ns[link.from_id]], at[gmap.stamps_ns[link.to_id]])
            errors.append((100 * float(np.linalg.norm(E[:3, 3])), float(np.degrees(transforms.rotation_angle(E)))))

    def ate_of(poses):
        ids = sorted(poses)
        return ate(Trajectory(np.array([gmap.stamps_ns[i] for i in ids]), np.stack([poses[i] for i in ids])),
                   truth).rmse_m

    off = [e for e in errors if e[0] > RECORDING_OFF_CM or e[1] > RECORDING_OFF_DEG]
    return {"seed": seed, "rate_hz": rate, "nodes": len(gmap.poses), "kept": len(errors), "off": len(off),
            "worst_cm": max((e[0] for e in errors), default=0.0), "worst_deg": max((e[1] for e in errors), default=0.0),
            "map_ate_m": ate_of(gmap.poses), "odometry_ate_m": ate_of(gmap.odom_poses)}


def recording(seeds: tuple[int, ...]) -> dict:
    """Part 5: the 48 real frames as a recording, per way of giving the images (RECORDING_IMAGES),
    detection rate and drift seed; the yardstick per run (>= 5 kept, none off, map ATE <= 0.5x)."""
    sys.path.insert(0, str(REPO / "test"))
    from conftest import write_tum_folder  # the integration test's recording, the same frames

    result = {}
    with tempfile.TemporaryDirectory() as tmp:
        folder = write_tum_folder(DATA, Path(tmp))
        variants = [(name, images, ()) for name, images in RECORDING_IMAGES.items()]
        variants += [(f"raw, D in CameraInfo{label}", (), settings) for label, settings in RECORDING_SETTINGS.items()
                     if settings]
        for name, images, settings in variants:
            for rate in RECORDING_RATES:
                runs = [_recording_run(folder, Path(tempfile.mkdtemp(dir=tmp)), images, seed, rate, settings)
                        for seed in seeds]
                result[f"{name} @ {'every frame' if rate == 0 else f'{rate:g} Hz'}"] = runs
    return result


def print_recording(result: dict) -> None:
    print(f"\nThe 48 real fr1_rpy frames as a recording (tum2bag drift {' '.join(RECORDING_DRIFT)}; map 6 DoF); "
          f"per drift seed: nodes, loop closures kept (off > {RECORDING_OFF_CM:g} cm / {RECORDING_OFF_DEG:g} deg), "
          "worst, map ATE / odometry ATE")
    for name, runs in result.items():
        cells = [f"{r['nodes']} n, {r['kept']} kept ({r['off']} off), worst {r['worst_cm']:.2f} cm / "
                 f"{r['worst_deg']:.2f} deg, ATE {r['map_ate_m']:.4f} / {r['odometry_ate_m']:.4f} m" for r in runs]
        held = all(r["kept"] >= 5 and r["off"] == 0 and r["map_ate_m"] <= 0.5 * r["odometry_ate_m"] for r in runs)
        print(f"  {name:<34} {'yardstick held' if held else 'yardstick NOT held'}")
        for seed_cell in cells:
            print(f"    {seed_cell}")


def print_neighbor_links(title: str, table: dict) -> None:
    print(f"\nNeighbour links, {title}, error vs ground truth ({table['odometry']['links']} links):")
    print(f"  {'':<22} {'median mm':>9} {'deg':>6} {'yaw p99':>8} {'max':>6} {'mean signed':>11} {'ms':>5}  "
          "links chained per sequence: ATE m")
    for name, r in table.items():
        label = f"{name} ({r['scan_map_nodes']})" if r["scan_map_nodes"] else name
        print(f"  {label:<22} {r['median_mm']:>9.1f} {r['median_deg']:>6.3f} {r['p99_deg']:>8.2f} {r['max_deg']:>6.2f} "
              f"{r['mean_deg']:>11.4f} {r['median_ms']:>5.1f}  {' / '.join(f'{v:.3f}' for v in r['chain_ate_m'])}"
              f"{'  (' + str(r['refused']) + ' refused)' if r['refused'] else ''}")


PARTS = ("loops", "icp", "neighbors", "inliers", "recording")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="fewer seeds, ICP pairs and drift seeds")
    parser.add_argument("--parts", default=",".join(PARTS),
                        help=f"comma-separated parts of {PARTS} (default: all); the results of the others "
                             "stay as they are in the JSON")
    args = parser.parse_args(argv)
    parts = args.parts.split(",")
    if unknown := set(parts) - set(PARTS):
        parser.error(f"--parts: unknown {sorted(unknown)}; expected some of {PARTS}")
    if not DATA.is_dir():
        print(f"no shared data at {DATA}", file=sys.stderr)
        return 1
    results = json.loads(RESULTS.read_text()) if RESULTS.exists() and len(parts) < len(PARTS) else {}
    if "loops" in parts:
        results["loop_pairs"] = loops = loop_pairs(args.quick)
        print_loop_pairs(loops)
    if "icp" in parts:
        results["icp"] = icp = icp_accuracy(20 if args.quick else 10)
        print(f"\nICP on intel-corrected k -> k+5 ({icp['pairs']} pairs, start 10 cm / 3 deg off): median "
              f"{icp['median_translation_error_cm']:.2f} cm / {icp['median_rotation_error_deg']:.3f} deg, p90 "
              f"{icp['p90_translation_error_cm']:.2f} cm / {icp['p90_rotation_error_deg']:.3f} deg, "
              f"overlap {icp['median_overlap']:.2f}, {icp['median_ms']:.2f} ms")
    if "neighbors" in parts:
        results["neighbor_link_refining"] = nlr = neighbor_link_refining(1, 60) if args.quick \
            else neighbor_link_refining(5, None)
        print_neighbor_links(f"{1 if args.quick else 5} simulated session(s)", nlr)
        real_logs = ("intel",) if args.quick else ("intel", "aces", "csail")
        results["neighbor_links_real"] = nlr_real = neighbor_links_real(real_logs)
        print_neighbor_links(f"real CARMEN logs {' / '.join(real_logs)} with simulated wheel errors", nlr_real)
    if "inliers" in parts:
        results["inlier_counts"] = counts = inlier_counts()
        print("\nInliers, PnP (2 px) / 3D-3D (0.1 m): mutual matches | mutual + NNDR 0.8")
        for r in counts:
            m, n = r["mutual"], r["nndr"]
            print(f"  {r['pair']:<38} {r['kind']:<18} "
                  f"corr {m['correspondences']:>4} inl {m['pnp']:>4} / {m['3d']:>4} | "
                  f"corr {n['correspondences']:>4} inl {n['pnp']:>4} / {n['3d']:>4}")
        wrong = [r for r in counts if r["kind"] == "wrong"]
        true = [r for r in counts if r["kind"].startswith("true")]
        results["summary"] = summary = {f"{key} {est}": {"max_wrong_inliers": max(r[key][est] for r in wrong),
                                                         "min_true_inliers": min(r[key][est] for r in true)}
                                        for key in ("mutual", "nndr") for est in ("pnp", "3d")}
        print(f"  summary: {summary}")
    if "recording" in parts:
        results["recording"] = rec = recording(RECORDING_SEEDS[:1] if args.quick else RECORDING_SEEDS)
        print_recording(rec)
    results["quick"] = args.quick
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    RESULTS.write_text(json.dumps(results, indent=2, default=float))
    print(f"wrote {RESULTS}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
