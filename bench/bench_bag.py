"""Bag I/O speed: writing and reading 640x480 RGB-D + scan + odometry bags, message conversion.

Measured in one run:

* write: ``write_bag`` of N frames (rgb8 640x480, depth 16UC1, 360-beam scan, odometry,
  camera_info), sqlite3 and mcap storage: frames/s (one run each; the bags are then read);
* read: ``BagDataset`` (rate unlimited) yielding all N SensorFrames: frames/s, median of 3 runs;
  baseline: rosbags ``AnyReader`` reading + deserialising the same messages with no
  synchronisation or numpy conversion (the floor of what reading costs);
* convert: ``image_from_msg`` + ``depth_from_msg`` of one 640x480 rgb8 + 16UC1 message pair:
  median µs over many calls; baseline: the bare ``np.frombuffer(...).reshape`` views.

Images are the real TUM fr1_xyz frames of ``../shared/data/rgbd`` when present (else noise).

Usage: ``python bench/bench_bag.py [--quick]`` (quick: 60 frames instead of 300).
Writes ``bench/results/bag.json``.
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

from rtabmap_ros2.core import transforms
from rtabmap_ros2.core.params import SyncParams
from rtabmap_ros2.core.sensor import CameraModel, LaserScan, SensorFrame
from rtabmap_ros2.io import bag

RESULTS = Path(__file__).resolve().parent / "results" / "bag.json"
SHARED_PAIR = Path(__file__).resolve().parents[2] / "shared" / "data" / "rgbd" / "tum_fr1_xyz_pairs" / "case_1"
FRAMES = 300
QUICK_FRAMES = 60
READ_REPEATS = 3
CONVERT_CALLS = 300
QUICK_CONVERT_CALLS = 60
SCAN_BEAMS = 360
FRAME_PERIOD_NS = 100_000_000   # 10 Hz
TUM_DEPTH_SCALE = 5000.0
H, W = 480, 640


def sample_images(rng) -> tuple[np.ndarray, np.ndarray]:
    rgb_path, depth_path = SHARED_PAIR / "img_prev.png", SHARED_PAIR / "dep_prev.png"
    if rgb_path.is_file() and depth_path.is_file():
        rgb = cv2.cvtColor(cv2.imread(str(rgb_path)), cv2.COLOR_BGR2RGB)
        depth = cv2.imread(str(depth_path), cv2.IMREAD_UNCHANGED).astype(np.float32) / TUM_DEPTH_SCALE
        depth[depth == 0] = np.nan
        return rgb, depth
    return rng.integers(0, 256, (H, W, 3), dtype=np.uint8), rng.uniform(0.5, 5, (H, W)).astype(np.float32)


def make_frames(n: int, rng) -> list[SensorFrame]:
    rgb, depth = sample_images(rng)
    camera = CameraModel(525, 525, 319.5, 239.5, W, H, bag.DEFAULT_T_BASE_CAMERA)
    ranges = rng.uniform(0.5, 10, SCAN_BEAMS).astype(np.float32)
    return [SensorFrame(stamp_ns=10**18 + i * FRAME_PERIOD_NS, T_odom_base=transforms.from_xy_yaw(0.05 * i, 0, 0.01 * i),
                        odom_covariance=np.eye(6) * 1e-3, rgb=rgb, depth_m=depth, camera=camera,
                        scan=LaserScan(ranges, -np.pi, 2 * np.pi / SCAN_BEAMS, 0.1, 30.0))
            for i in range(n)]


def bench_raw_read(path: Path) -> float:
    from rosbags.highlevel import AnyReader
    t0 = time.perf_counter()
    with AnyReader([path], default_typestore=bag.typestore()) as reader:
        for conn, _, raw in reader.messages():
            reader.deserialize(raw, conn.msgtype)
    return time.perf_counter() - t0


def bench_read(path: Path) -> tuple[float, int]:
    t0 = time.perf_counter()
    n = sum(1 for _ in bag.BagDataset(path, sync=SyncParams(rate_hz=0)))
    return time.perf_counter() - t0, n


def bench_convert(frame: SensorFrame, calls: int) -> dict:
    ts = bag.typestore()
    rgb_msg = ts.deserialize_cdr(ts.serialize_cdr(bag.image_to_msg(frame.rgb, 1), bag.IMAGE_TYPE), bag.IMAGE_TYPE)
    depth_msg = ts.deserialize_cdr(ts.serialize_cdr(bag.depth_to_msg(frame.depth_m, 1), bag.IMAGE_TYPE),
                                   bag.IMAGE_TYPE)
    conv, base = [], []
    for _ in range(calls):
        t0 = time.perf_counter()
        bag.image_from_msg(rgb_msg)
        bag.depth_from_msg(depth_msg)
        conv.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        np.frombuffer(rgb_msg.data, np.uint8).reshape(H, W, 3)
        np.frombuffer(depth_msg.data, np.uint16).reshape(H, W)
        base.append(time.perf_counter() - t0)
    return {"convert_pair_us_median": statistics.median(conv) * 1e6,
            "baseline_frombuffer_views_us_median": statistics.median(base) * 1e6}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help=f"{QUICK_FRAMES} frames instead of {FRAMES}")
    args = parser.parse_args()
    n = QUICK_FRAMES if args.quick else FRAMES
    rng = np.random.default_rng(0)
    frames = make_frames(n, rng)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for storage in ("sqlite3", "mcap"):
            path = Path(tmp) / storage
            t0 = time.perf_counter()
            bag.write_bag(path, frames, storage=storage)
            write_s = time.perf_counter() - t0
            size_mb = sum(f.stat().st_size for f in path.iterdir()) / 1e6
            reads = [bench_read(path) for _ in range(READ_REPEATS)]
            assert all(k == n for _, k in reads), f"read {reads} frames, wrote {n}"
            raw = [bench_raw_read(path) for _ in range(READ_REPEATS)]
            rows.append({"storage": storage, "frames": n, "size_mb": round(size_mb, 1),
                         "write_fps": n / write_s,
                         "read_fps_median": n / statistics.median(t for t, _ in reads),
                         "baseline_raw_deserialize_fps_median": n / statistics.median(raw)})
    conv = bench_convert(frames[0], QUICK_CONVERT_CALLS if args.quick else CONVERT_CALLS)
    print(f"{'storage':8} {'frames':>6} {'MB':>7} {'write f/s':>10} {'read f/s':>9} {'raw read f/s (baseline)':>24}")
    for r in rows:
        print(f"{r['storage']:8} {r['frames']:6d} {r['size_mb']:7.1f} {r['write_fps']:10.1f} "
              f"{r['read_fps_median']:9.1f} {r['baseline_raw_deserialize_fps_median']:24.1f}")
    print(f"640x480 rgb8 + 16UC1 -> numpy: {conv['convert_pair_us_median']:.0f} µs median "
          f"(baseline frombuffer views: {conv['baseline_frombuffer_views_us_median']:.1f} µs)")
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    RESULTS.write_text(json.dumps({"machine": platform.platform(), "python": platform.python_version(),
                                   "quick": args.quick, "bags": rows, "conversion": conv}, indent=2))
    print(f"wrote {RESULTS}")


if __name__ == "__main__":
    main()
