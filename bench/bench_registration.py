"""Registration: RANSAC and ICP accuracy/time on real data, neighbour links, min_inliers.

Usage: ``python bench/bench_registration.py [--quick]``. Prints tables and writes
``bench/results/registration.json``.

1. RANSAC (3D words, Kabsch): TUM fr1_xyz pairs with mocap ground truth; ORB (1000) features,
   word ids from mutual brute-force matches; error of the recovered relative pose and time of
   ``register`` (median over seeds). Baseline in the same run: the plain least-squares refit
   (Kabsch on every inlier) instead of the reweighted one.
2. ICP (2D point-to-line): Intel lab corrected log, scans k -> k+5 overlapping >= 50 % at the
   reference, started 10 cm / 3 degrees off; error and time (median). Baseline: the start error.
3. Neighbour links (RGBD/NeighborLinkRefining): wheel odometry, ICP against the previous scan and
   ICP against the last ``neighbor_scan_map_nodes`` scans, on the simulated sessions and on the
   real CARMEN logs (with simulated wheel errors); per-link error and the drift of the chained
   links. Baseline in the same run: the odometry and the previous scan alone.
4. min_inliers: RANSAC inlier counts of true pairs (same scene) vs wrong pairs (TUM frames vs
   the RTAB-Map repository frames, different scenes), with mutual matches, and with mutual
   matches + the NNDR test (0.8) that the vocabulary applies.
"""

from __future__ import annotations

import argparse
import itertools
import json
import statistics
import sys
import time
from pathlib import Path

import cv2
import numpy as np
from scipy.spatial import cKDTree

from rtabmap_ros2.core import registration, transforms
from rtabmap_ros2.core.params import RegistrationParams
from rtabmap_ros2.core.registration import correspondences, icp_2d, kabsch, register, words_3d
from rtabmap_ros2.core.sensor import CameraModel
from rtabmap_ros2.core.signature import Signature
from rtabmap_ros2.errors import RegistrationError
from rtabmap_ros2.io.carmen import read_carmen_log
from rtabmap_ros2.io.trajectory import Trajectory, ate

REPO = Path(__file__).resolve().parents[1]
DATA = REPO.parent / "shared" / "data"
RESULTS = REPO / "bench" / "results" / "registration.json"
CAMERA = CameraModel(525.0, 525.0, 319.5, 239.5, 640, 480)
NNDR = 0.8


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
    return (Signature(1, 1, 0, ids_a, kpa, words_3d(kpa, a[1], CAMERA)),
            Signature(2, 1, 0, ids_b, kpb, words_3d(kpb, b[1], CAMERA)))


def pose_error(T, truth):
    e = transforms.inverse(truth) @ T
    return float(np.linalg.norm(e[:3, 3])), float(np.degrees(transforms.rotation_angle(e)))


def ransac_accuracy(seeds: int) -> list[dict]:
    params = RegistrationParams(planar=False, icp_refine=False)
    rows = []
    for case in ("case_1", "case_2"):
        a, b = load_image("tum", f"{case}/prev"), load_image("tum", f"{case}/curr")
        sa, sb = signatures(a, b, nndr=False)
        truth = transforms.relative(a[2], b[2])
        pf, pt = correspondences(sa, sb)
        errs, base_errs, times, inliers = [], [], [], []
        for seed in range(seeds):
            t0 = time.perf_counter()
            reg = register(sa, sb, params, np.random.default_rng(seed))
            times.append((time.perf_counter() - t0) * 1e3)
            errs.append(pose_error(reg.T_from_to, truth))
            inliers.append(reg.inliers)
            # Baseline: best 3-point hypothesis + one plain least-squares refit on its inliers.
            base_errs.append(pose_error(_plain_refit(pf, pt, params, seed), truth))
        rows.append({
            "case": case, "correspondences": len(pf), "inliers": int(np.median(inliers)),
            "translation_error_cm": 100 * statistics.median(e[0] for e in errs),
            "rotation_error_deg": statistics.median(e[1] for e in errs),
            "baseline_translation_error_cm": 100 * statistics.median(e[0] for e in base_errs),
            "baseline_rotation_error_deg": statistics.median(e[1] for e in base_errs),
            "register_ms": statistics.median(times),
            "motion_cm": 100 * float(np.linalg.norm(truth[:3, 3])),
            "motion_deg": float(np.degrees(transforms.rotation_angle(truth)))})
    return rows


def _plain_refit(pf, pt, params, seed):
    """RANSAC's best hypothesis refit once by unweighted Kabsch on its inliers (the baseline)."""
    rng = np.random.default_rng(seed)
    n = len(pf)
    samples = np.argpartition(rng.random((params.ransac_iterations, n)), 2, axis=1)[:, :3]
    Ts = kabsch(pf[samples], pt[samples])
    moved = Ts[:, :3, :3] @ pt.T + Ts[:, :3, 3:]
    inl = np.sum((moved - pf.T[None]) ** 2, axis=1) < params.inlier_distance ** 2
    mask = inl[int(np.argmax(inl.sum(axis=1)))]
    return kabsch(pf[mask], pt[mask])


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
            "normal_neighbors": registration.ICP_NORMAL_NEIGHBORS, "robust_scale_m": registration.ICP_ROBUST_SCALE}


def inlier_counts() -> list[dict]:
    images = {f"tum/{c}/{w}": ("tum", f"{c}/{w}") for c in ("case_1", "case_2") for w in ("prev", "curr")}
    images.update({f"rtabmap/{n}": ("rtabmap", n) for n in ("17", "154")})
    loaded = {k: load_image(*v) for k, v in images.items()}
    params = RegistrationParams(planar=False, icp_refine=False, min_inliers=3)
    rows = []
    for x, y in itertools.combinations(loaded, 2):
        same = x.startswith("tum") and y.startswith("tum")
        label = "true (same scene)" if same else ("rtabmap 17 vs 154" if x.startswith("rtabmap") else "wrong")
        row = {"pair": f"{x} vs {y}", "kind": label}
        for nndr in (False, True):
            sa, sb = signatures(loaded[x], loaded[y], nndr)
            pf, _ = correspondences(sa, sb)
            try:
                n = register(sa, sb, params).inliers
            except RegistrationError:
                n = 0
            row["nndr" if nndr else "mutual"] = {"correspondences": len(pf), "inliers": n}
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


def print_neighbor_links(title: str, table: dict) -> None:
    print(f"\nNeighbour links, {title}, error vs ground truth ({table['odometry']['links']} links):")
    print(f"  {'':<22} {'median mm':>9} {'deg':>6} {'yaw p99':>8} {'max':>6} {'mean signed':>11} {'ms':>5}  "
          "links chained per sequence: ATE m")
    for name, r in table.items():
        label = f"{name} ({r['scan_map_nodes']})" if r["scan_map_nodes"] else name
        print(f"  {label:<22} {r['median_mm']:>9.1f} {r['median_deg']:>6.3f} {r['p99_deg']:>8.2f} {r['max_deg']:>6.2f} "
              f"{r['mean_deg']:>11.4f} {r['median_ms']:>5.1f}  {' / '.join(f'{v:.3f}' for v in r['chain_ate_m'])}"
              f"{'  (' + str(r['refused']) + ' refused)' if r['refused'] else ''}")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="fewer seeds and ICP pairs")
    args = parser.parse_args(argv)
    if not DATA.is_dir():
        print(f"no shared data at {DATA}", file=sys.stderr)
        return 1
    ransac = ransac_accuracy(3 if args.quick else 11)
    print("RANSAC on TUM fr1_xyz (median over seeds; baseline = plain least-squares refit)")
    print(f"{'case':<8} {'corr':>5} {'inl':>5} {'t err cm':>9} {'r err deg':>10} {'base t cm':>10} "
          f"{'base r deg':>10} {'ms':>7} {'motion':>14}")
    for r in ransac:
        print(f"{r['case']:<8} {r['correspondences']:>5} {r['inliers']:>5} {r['translation_error_cm']:>9.2f} "
              f"{r['rotation_error_deg']:>10.3f} {r['baseline_translation_error_cm']:>10.2f} "
              f"{r['baseline_rotation_error_deg']:>10.3f} {r['register_ms']:>7.1f} "
              f"{r['motion_cm']:>5.1f} cm {r['motion_deg']:.2f} deg")
    icp = icp_accuracy(20 if args.quick else 10)
    print(f"\nICP on intel-corrected k -> k+5 ({icp['pairs']} pairs, start 10 cm / 3 deg off): median "
          f"{icp['median_translation_error_cm']:.2f} cm / {icp['median_rotation_error_deg']:.3f} deg, p90 "
          f"{icp['p90_translation_error_cm']:.2f} cm / {icp['p90_rotation_error_deg']:.3f} deg, "
          f"overlap {icp['median_overlap']:.2f}, {icp['median_ms']:.2f} ms")
    nlr = neighbor_link_refining(1, 60) if args.quick else neighbor_link_refining(5, None)
    print_neighbor_links(f"{1 if args.quick else 5} simulated session(s)", nlr)
    real_logs = ("intel",) if args.quick else ("intel", "aces", "csail")
    nlr_real = neighbor_links_real(real_logs)
    print_neighbor_links(f"real CARMEN logs {' / '.join(real_logs)} with simulated wheel errors", nlr_real)
    counts = inlier_counts()
    print("\nInliers (inlier_distance 0.1 m): mutual matches | mutual + NNDR 0.8")
    for r in counts:
        print(f"  {r['pair']:<38} {r['kind']:<18} corr {r['mutual']['correspondences']:>4} inl "
              f"{r['mutual']['inliers']:>4} | corr {r['nndr']['correspondences']:>4} inl {r['nndr']['inliers']:>4}")
    wrong = [r for r in counts if r["kind"] == "wrong"]
    true = [r for r in counts if r["kind"].startswith("true")]
    summary = {key: {"max_wrong_inliers": max(r[key]["inliers"] for r in wrong),
                     "min_true_inliers": min(r[key]["inliers"] for r in true)} for key in ("mutual", "nndr")}
    print(f"  summary: {summary}")
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    RESULTS.write_text(json.dumps({"ransac": ransac, "icp": icp, "neighbor_link_refining": nlr,
                                   "neighbor_links_real": nlr_real, "inlier_counts": counts, "summary": summary,
                                   "quick": args.quick}, indent=2))
    print(f"wrote {RESULTS}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
