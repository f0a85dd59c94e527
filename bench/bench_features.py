"""Feature extraction (2013 §III-A, Alg. 2 lines 2-3): which detector by default?

On the real 640x480 frames of ``/work/shared/data/rgbd`` (TUM fr1_xyz pairs and RTAB-Map's
sample frames), for ``gftt_orb``, ``orb`` and ``sift`` at T_maxFeatures = 400:

* ms per image (median over frames x repeats) and keypoints kept;
* matching quality on the TUM pairs (known poses, depth scale 5000, fx = fy = 525,
  cx = 319.5, cy = 239.5): NNDR-0.8 matches from the previous to the current frame, and how many
  are geometrically correct (the previous keypoint back-projected with its depth, moved by the
  ground-truth relative pose and projected lands < 3 px from its match).

The correct-match count is what the vocabulary and the loop-closure hypotheses live on (words
shared by two views of the same place). Usage: ``python bench/bench_features.py [--quick]``;
writes ``bench/results/features.json``.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import cv2
import numpy as np

from rtabmap_ros2.core import transforms
from rtabmap_ros2.core.features import FeatureExtractor
from rtabmap_ros2.core.params import FeatureParams

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "rgbd"
RESULTS = Path(__file__).resolve().parent / "results" / "features.json"
DETECTORS = ("gftt_orb", "orb", "sift")
MAX_FEATURES = (400, 1000)
NNDR = 0.8
CORRECT_PX = 3.0
TUM_DEPTH_SCALE = 5000.0  # depth png units per metre
TUM_K = np.array([[525.0, 0.0, 319.5], [0.0, 525.0, 239.5], [0.0, 0.0, 1.0]])
REPEATS = 5


def read_rgb(path: Path) -> np.ndarray:
    bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if bgr is None:
        raise FileNotFoundError(path)
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)


def read_tum_pose(path: Path) -> np.ndarray:
    """T_world_camera from 'tx ty tz qx qy qz qw'."""
    values = [float(v) for v in path.read_text().split()]
    return transforms.from_xyz_quat_xyzw(values[:3], values[3:7])


def frames() -> list[tuple[str, np.ndarray]]:
    out = []
    for case in sorted((DATA / "tum_fr1_xyz_pairs").glob("case_*")):
        out += [(f"{case.name}/prev", read_rgb(case / "img_prev.png")),
                (f"{case.name}/curr", read_rgb(case / "img_curr.png"))]
    for path in sorted((DATA / "rtabmap_frames" / "rgb").glob("*.jpg")):
        out.append((f"rtabmap/{path.stem}", read_rgb(path)))
    return out


def nndr_matches(a: np.ndarray, b: np.ndarray, binary: bool) -> np.ndarray:
    """(M,2) index pairs (row of a, row of b) passing d1 < NNDR * d2 (2-NN of a's rows in b)."""
    if len(a) == 0 or len(b) < 2:
        return np.zeros((0, 2), int)
    matcher = cv2.BFMatcher(cv2.NORM_HAMMING if binary else cv2.NORM_L2)
    pairs = [(m[0].queryIdx, m[0].trainIdx) for m in matcher.knnMatch(a, b, k=2)
             if len(m) == 2 and m[0].distance < NNDR * m[1].distance]
    return np.array(pairs, int).reshape(-1, 2)


def correct_matches(case: Path, detector: str, max_features: int) -> dict:
    """Matches prev -> curr of one TUM pair and how many agree with the ground truth."""
    extractor = FeatureExtractor(FeatureParams(detector=detector, max_features=max_features))
    prev = extractor.extract(read_rgb(case / "img_prev.png"))
    curr = extractor.extract(read_rgb(case / "img_curr.png"))
    depth_m = cv2.imread(str(case / "dep_prev.png"), cv2.IMREAD_UNCHANGED).astype(np.float64) / TUM_DEPTH_SCALE
    T_curr_prev = transforms.inverse(read_tum_pose(case / "pose_curr.txt")) @ read_tum_pose(case / "pose_prev.txt")
    pairs = nndr_matches(prev.descriptors, curr.descriptors, extractor.binary)
    uv_prev = prev.keypoints[pairs[:, 0]].astype(np.float64)
    uv_curr = curr.keypoints[pairs[:, 1]].astype(np.float64)
    cols = np.clip(np.round(uv_prev[:, 0]).astype(int), 0, depth_m.shape[1] - 1)
    rows = np.clip(np.round(uv_prev[:, 1]).astype(int), 0, depth_m.shape[0] - 1)
    z = depth_m[rows, cols]
    valid = z > 0
    # Back-project in the previous optical frame, move to the current one, project.
    xyz = np.stack([(uv_prev[:, 0] - TUM_K[0, 2]) * z / TUM_K[0, 0],
                    (uv_prev[:, 1] - TUM_K[1, 2]) * z / TUM_K[1, 1], z], axis=1)
    xyz_curr = xyz @ T_curr_prev[:3, :3].T + T_curr_prev[:3, 3]
    projected = (xyz_curr @ TUM_K.T)[:, :2] / xyz_curr[:, 2:3]
    error = np.linalg.norm(projected - uv_curr, axis=1)
    correct = valid & (error < CORRECT_PX)
    return dict(case=case.name, detector=detector, max_features=max_features, kept_prev=len(prev),
                kept_curr=len(curr), matches=int(len(pairs)), with_depth=int(valid.sum()),
                correct=int(correct.sum()),
                precision=float(correct.sum() / max(1, valid.sum())))


def timing(images, detector: str, max_features: int, repeats: int) -> dict:
    extractor = FeatureExtractor(FeatureParams(detector=detector, max_features=max_features))
    samples, kept = [], []
    for _, image in images:
        extractor.extract(image)  # warm-up (allocations)
        for _ in range(repeats):
            t0 = time.perf_counter()
            features = extractor.extract(image)
            samples.append(time.perf_counter() - t0)
        kept.append(len(features))
    return dict(detector=detector, max_features=max_features, ms_median=1e3 * float(np.median(samples)),
                kept_median=float(np.median(kept)), kept_min=int(np.min(kept)), frames=len(images))


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="1 repeat, T_maxFeatures = 400 only")
    args = parser.parse_args(argv)
    images = frames()
    repeats = 1 if args.quick else REPEATS
    sizes = MAX_FEATURES[:1] if args.quick else MAX_FEATURES
    print(f"{len(images)} frames 640x480, cv2 {cv2.__version__}, {cv2.getNumThreads()} OpenCV threads")
    timings, matching = [], []
    print(f"{'detector':<9} {'maxF':>5} {'ms/img':>7} {'kept':>6} {'min':>5} | {'matches':>7} {'depth':>6} "
          f"{'correct':>7} {'precision':>9}")
    for max_features in sizes:
        for detector in DETECTORS:
            t = timing(images, detector, max_features, repeats)
            cases = [correct_matches(c, detector, max_features)
                     for c in sorted((DATA / "tum_fr1_xyz_pairs").glob("case_*"))]
            timings.append(t)
            matching += cases
            m = {k: sum(c[k] for c in cases) for k in ("matches", "with_depth", "correct")}
            print(f"{detector:<9} {max_features:>5} {t['ms_median']:>7.1f} {t['kept_median']:>6.0f} "
                  f"{t['kept_min']:>5} | {m['matches']:>7} {m['with_depth']:>6} {m['correct']:>7} "
                  f"{m['correct'] / max(1, m['with_depth']):>9.2f}", flush=True)
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    RESULTS.write_text(json.dumps(dict(quick=args.quick, opencv=cv2.__version__, threads=cv2.getNumThreads(),
                                       nndr=NNDR, correct_px=CORRECT_PX, timing=timings, matching=matching),
                                  indent=2))
    print(f"(matches/correct summed over the {len(matching) // len(timings)} TUM pairs, prev -> curr)")
    print(f"wrote {RESULTS}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
