"""Long-term memory in SQLite: cost of writing a frame, of Retrieval, and disk use per node.

One frame batch is what the mapper writes when it creates a node (2014 §II): a location with
400 words (ORB-sized 32-byte descriptors, new words, 3D points, keypoints), its RGB image as JPEG,
its depth as a 16-bit PNG in mm, a 360-beam laser scan, the camera model, the neighbour link,
a weight update and the frame's statistics row. Images are the real 640x480 RGB-D frames of
``../shared/data/rgbd`` (TUM fr1_xyz and RTAB-Map's samples), cycled; without them, a photo
bundled with scikit-image and a synthetic depth ramp stand in.

Measured (medians over the frames, warm page cache, one process):

* encode: ``encode_rgb`` (JPEG q90) and ``encode_depth`` (16-bit PNG) of one 640x480 frame;
* write: ``Database.write`` of one frame batch (one transaction, WAL, synchronous=NORMAL); its
  p99 and max are the commits that ran SQLite's auto-checkpoint (the BackgroundWriter
  checkpoints after the commit instead);
* submit: main-thread cost of ``BackgroundWriter.submit`` (snapshot + queue), the part of the
  write that pTime sees when the background writer is used (Alg. 1 line 17);
* retrieval: ``load_signatures`` of 2 random stored locations (Alg. 3 loads at most two);
* blobs: ``load_sensor_blobs`` + decode of one node (map export);
* load_nodes / load_links of the whole map (global map export), median of 5 calls;
* file size per node after close (checkpointed, rollback-journal mode);
* busy frame: one frame batch through the BackgroundWriter while the main thread runs Python
  (every statement needs the GIL back from it: database_batch._apply_statements);
* transfer: every stored location leaving WM at once (a WM cap drop: in_wm and weight of each)
  through the BackgroundWriter while the main thread runs Python, until the writer is done.
  Baseline: the same UPDATEs one row at a time (executemany) on a writer thread of their own.

Baseline in the same run, interleaved frame by frame with ours: the same bytes (one frame's blobs
concatenated) written as ONE row of a one-table SQLite file with the same pragmas, and read back
by id: the floor of what SQLite costs, so the difference is the schema's (words table, location ->
word references, one row per table).

Usage: ``python bench/bench_database.py [--quick]`` (quick: 60 frames instead of 300).
Writes ``bench/results/database.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sqlite3
import statistics
import sys
import tempfile
import threading
import time
from pathlib import Path

import cv2
import numpy as np

from rtabmap_ros2.core import transforms
from rtabmap_ros2.core.database import (BackgroundWriter, Database, SensorBlobs, WriteBatch, decode_depth,
                                        decode_rgb, encode_depth, encode_rgb)
from rtabmap_ros2.core.graph import Link, LinkType
from rtabmap_ros2.core.sensor import CameraModel, LaserScan
from rtabmap_ros2.core.signature import Signature

RESULTS = Path(__file__).resolve().parent / "results" / "database.json"
SHARED_RGBD = Path(__file__).resolve().parents[2] / "shared" / "data" / "rgbd"
FRAMES = 300
QUICK_FRAMES = 60
BUSY_FRAMES = 10
WORDS_PER_FRAME = 400
DESCRIPTOR_BYTES = 32  # ORB
SCAN_BEAMS = 360
RETRIEVED_PER_ITERATION = 2  # Alg. 3: at most two locations retrieved per iteration
TUM_DEPTH_SCALE = 5000.0  # TUM 16-bit depth: value / 5000 = metres
RTABMAP_DEPTH_SCALE = 1000.0  # RTAB-Map sample depth: millimetres
IMAGE_SIZE = (480, 640)
GLOBAL_MAP_REPEATS = 5  # load_nodes / load_links of the whole map: median of this many calls


def load_frames() -> list[tuple[np.ndarray, np.ndarray, str]]:
    """Real RGB-D frames (RGB uint8, depth float32 m, source name)."""
    frames = []
    for case in sorted((SHARED_RGBD / "tum_fr1_xyz_pairs").glob("case_*")):
        for which in ("prev", "curr"):
            bgr = cv2.imread(str(case / f"img_{which}.png"), cv2.IMREAD_COLOR)
            depth = cv2.imread(str(case / f"dep_{which}.png"), cv2.IMREAD_UNCHANGED)
            if bgr is not None and depth is not None:
                frames.append((cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB), depth.astype(np.float32) / TUM_DEPTH_SCALE,
                               f"tum/{case.name}/{which}"))
    for rgb_path in sorted((SHARED_RGBD / "rtabmap_frames" / "rgb").glob("*.jpg")):
        bgr = cv2.imread(str(rgb_path), cv2.IMREAD_COLOR)
        depth = cv2.imread(str(rgb_path.parents[1] / "depth" / f"{rgb_path.stem}.png"), cv2.IMREAD_UNCHANGED)
        if bgr is not None and depth is not None and depth.shape == bgr.shape[:2]:
            frames.append((cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB), depth.astype(np.float32) / RTABMAP_DEPTH_SCALE,
                           f"rtabmap/{rgb_path.stem}"))
    if not frames:
        import skimage.data

        rgb = cv2.resize(skimage.data.astronaut(), IMAGE_SIZE[::-1])
        depth = np.tile(np.linspace(0.5, 6.0, IMAGE_SIZE[1], dtype=np.float32), (IMAGE_SIZE[0], 1))
        frames.append((rgb, depth, "skimage/astronaut (shared data absent)"))
    return frames


def make_batch(rng, node_id: int, blobs: SensorBlobs, camera: CameraModel) -> WriteBatch:
    """One frame's batch: a new location with new words, its link, a weight update, statistics."""
    first = 1 + (node_id - 1) * WORDS_PER_FRAME
    word_ids = np.arange(first, first + WORDS_PER_FRAME, dtype=np.int64)
    points3d = rng.normal(size=(WORDS_PER_FRAME, 3)).astype(np.float32)
    points3d[::10] = np.nan
    sig = Signature(
        id=node_id, map_id=0, stamp_ns=node_id * 10**9, word_ids=word_ids,
        keypoints=rng.uniform(0, 640, (WORDS_PER_FRAME, 2)).astype(np.float32), points3d=points3d,
        T_odom_base=transforms.from_xyz_quat_xyzw([0.1 * node_id, 0, 0], [0, 0, 0, 1]),
        scan=LaserScan(rng.uniform(0.1, 5.0, SCAN_BEAMS).astype(np.float32), -np.pi, 2 * np.pi / SCAN_BEAMS,
                       0.05, 5.6),
        camera=camera)
    words = {int(w): d for w, d in zip(word_ids, rng.integers(0, 256, (WORDS_PER_FRAME, DESCRIPTOR_BYTES),
                                                               dtype=np.uint8))}
    stats = {"frame_index": node_id, "stamp_ns": sig.stamp_ns, "location_id": node_id, "process_time_ms": 12.5,
             "wm_size": node_id, "timings_ms": {"features": 8.0, "database": 1.0}}
    return WriteBatch(locations=[(sig, blobs)], words=words,
                      links=[Link(node_id - 1, node_id, LinkType.NEIGHBOR)] if node_id > 1 else [],
                      weights={node_id - 1: 1} if node_id > 1 else {}, statistics=[stats])


def timed(fn, *args) -> tuple[float, object]:
    start = time.perf_counter()
    out = fn(*args)
    return (time.perf_counter() - start) * 1e3, out


def median(values: list[float]) -> float:
    return float(statistics.median(values))


class Baseline:
    """The same bytes as ONE row of a one-table SQLite file (same pragmas), timed alongside ours."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.conn = sqlite3.connect(str(path), isolation_level=None)
        self.conn.execute("PRAGMA journal_mode=WAL")
        self.conn.execute("PRAGMA synchronous=NORMAL")
        self.conn.execute("CREATE TABLE frames (id INTEGER PRIMARY KEY, data BLOB)")

    def write(self, node_id: int, data: bytes) -> None:
        self.conn.execute("BEGIN IMMEDIATE")
        self.conn.execute("INSERT INTO frames VALUES (?, ?)", (node_id, data))
        self.conn.execute("COMMIT")

    def read(self, ids: list[int]) -> list:
        return self.conn.execute("SELECT data FROM frames WHERE id IN (SELECT value FROM json_each(?))",
                                 (json.dumps(ids),)).fetchall()

    def close(self) -> int:
        """Checkpoint, close; the file size (bytes)."""
        self.conn.execute("PRAGMA wal_checkpoint(TRUNCATE)")
        self.conn.close()
        return self.path.stat().st_size


def frame_bytes(batch: WriteBatch) -> bytes:
    """Every byte of a frame batch's payload, concatenated (the baseline's row)."""
    sig, blobs = batch.locations[0]
    return (blobs.rgb_jpeg + blobs.depth_png16_mm + b"".join(d.tobytes() for d in batch.words.values())
            + sig.keypoints.tobytes() + sig.points3d.tobytes() + sig.word_ids.tobytes() + sig.scan.ranges.tobytes())


def busy_until(done) -> None:
    """The main thread running Python (as the mapper's graph code does) until ``done()``."""
    poses = {i: np.eye(4) for i in range(2000)}
    while not done():
        sum(float(T[0, 0]) for T in poses.values())


def written_while_busy_ms(writer: BackgroundWriter, batch: WriteBatch) -> float:
    """Time from submit until the writer committed ``batch``, the main thread running Python."""
    start = time.perf_counter()
    writer.submit(batch)
    busy_until(lambda: writer.pending == 0)
    writer.join()
    return (time.perf_counter() - start) * 1e3


def per_row_updates_ms(path: Path, ids) -> float:
    """Baseline of the transfer: in_wm and weight updated one row at a time (executemany) on a
    thread of their own while the main thread runs Python."""
    finished = threading.Event()

    def write() -> None:
        conn = sqlite3.connect(path)
        with conn:
            conn.executemany("UPDATE nodes SET in_wm = ? WHERE id = ?", [(1, i) for i in ids])
            conn.executemany("UPDATE nodes SET weight = ? WHERE id = ?", [(2, i) for i in ids])
        conn.close()
        finished.set()

    start = time.perf_counter()
    thread = threading.Thread(target=write)
    thread.start()
    busy_until(finished.is_set)
    thread.join()
    return (time.perf_counter() - start) * 1e3


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help=f"{QUICK_FRAMES} frames instead of {FRAMES}")
    args = parser.parse_args(argv)
    n_frames = QUICK_FRAMES if args.quick else FRAMES
    load_before = os.getloadavg()[0]
    rng = np.random.default_rng(7)
    images = load_frames()
    camera = CameraModel(525.0, 525.0, 319.5, 239.5, IMAGE_SIZE[1], IMAGE_SIZE[0])

    # Encoding (once per node at creation).
    rgb_ms, depth_ms, rgb_bytes, depth_bytes, decode_ms = [], [], [], [], []
    encoded = []
    for i in range(n_frames):
        rgb, depth, _ = images[i % len(images)]
        t_rgb, jpeg = timed(encode_rgb, rgb)
        t_depth, png = timed(encode_depth, depth)
        rgb_ms.append(t_rgb)
        depth_ms.append(t_depth)
        rgb_bytes.append(len(jpeg))
        depth_bytes.append(len(png))
        if i < len(images) * 4:
            decode_ms.append(timed(decode_rgb, jpeg)[0] + timed(decode_depth, png)[0])
        encoded.append(SensorBlobs(jpeg, png))

    with tempfile.TemporaryDirectory(prefix="bench_database_") as tmp:
        folder = Path(tmp)
        batches = [make_batch(rng, i + 1, encoded[i], camera) for i in range(n_frames)]

        # Direct writes: Database.write, one transaction per frame, interleaved with the baseline
        # so both see the same machine load.
        write_ms, base_write_ms = [], []
        db = Database(folder / "direct.db")
        base = Baseline(folder / "baseline.db")
        for i, batch in enumerate(batches, start=1):
            base_write_ms.append(timed(base.write, i, frame_bytes(batch))[0])
            write_ms.append(timed(db.write, batch)[0])
        retrieval_ms, base_read_ms, blobs_ms = [], [], []
        for _ in range(n_frames):
            ids = rng.choice(np.arange(1, n_frames + 1), RETRIEVED_PER_ITERATION, replace=False).tolist()
            base_read_ms.append(timed(base.read, ids)[0])
            retrieval_ms.append(timed(db.load_signatures, ids)[0])
            start = time.perf_counter()
            blobs = db.load_sensor_blobs(ids[0])
            blobs.rgb(), blobs.depth_m()
            blobs_ms.append((time.perf_counter() - start) * 1e3)
        nodes_ms = median([timed(db.load_nodes)[0] for _ in range(GLOBAL_MAP_REPEATS)])
        links_ms = median([timed(db.load_links)[0] for _ in range(GLOBAL_MAP_REPEATS)])
        db.close()
        file_bytes = (folder / "direct.db").stat().st_size
        base_bytes = base.close()

        # Background writer: what the main thread pays per frame, and the total to drain the queue.
        db = Database(folder / "background.db")
        writer = BackgroundWriter(db)
        submit_ms = []
        start = time.perf_counter()
        for batch in batches:
            submit_ms.append(timed(writer.submit, batch)[0])
        writer.join()
        background_total_s = time.perf_counter() - start
        busy_frame_ms = [written_while_busy_ms(writer, make_batch(rng, n_frames + 1 + i, encoded[i], camera))
                         for i in range(BUSY_FRAMES)]
        ids = range(1, n_frames + 1)
        transfer_ms = written_while_busy_ms(writer, WriteBatch(in_wm={i: False for i in ids},
                                                               weights={i: 1 for i in ids}))
        db.close()
        base_transfer_ms = per_row_updates_ms(folder / "background.db", ids)

    result = {
        "frames": n_frames,
        "images": [name for _, _, name in images],
        "words_per_frame": WORDS_PER_FRAME,
        "encode_rgb_ms": median(rgb_ms), "encode_depth_ms": median(depth_ms),
        "decode_rgb_plus_depth_ms": median(decode_ms),
        "rgb_jpeg_kib": median(rgb_bytes) / 1024, "depth_png_kib": median(depth_bytes) / 1024,
        "write_frame_ms": median(write_ms), "write_frame_p90_ms": float(np.percentile(write_ms, 90)),
        "write_frame_p99_ms": float(np.percentile(write_ms, 99)), "write_frame_max_ms": float(np.max(write_ms)),
        "submit_frame_ms": median(submit_ms), "background_total_s": background_total_s,
        "load_2_signatures_ms": median(retrieval_ms), "load_blobs_decoded_ms": median(blobs_ms),
        "load_nodes_ms": nodes_ms, "load_links_ms": links_ms,
        "file_kib_per_node": file_bytes / n_frames / 1024,
        "frame_busy_main_ms": median(busy_frame_ms), "transfer_all_busy_main_ms": transfer_ms,
        "baseline_per_row_transfer_busy_main_ms": base_transfer_ms,
        "baseline_one_row_write_ms": median(base_write_ms), "baseline_one_row_read2_ms": median(base_read_ms),
        "baseline_kib_per_node": base_bytes / n_frames / 1024,
        "load_average_1min": [load_before, os.getloadavg()[0]],
        "machine": {"python": sys.version.split()[0], "sqlite": sqlite3.sqlite_version,
                    "opencv": cv2.__version__, "platform": platform.platform()},
    }
    rows = [
        ("encode RGB 640x480 -> JPEG q90", f"{result['encode_rgb_ms']:.2f} ms", f"{result['rgb_jpeg_kib']:.0f} KiB"),
        ("encode depth 640x480 -> PNG16 mm", f"{result['encode_depth_ms']:.2f} ms",
         f"{result['depth_png_kib']:.0f} KiB"),
        ("decode RGB + depth", f"{result['decode_rgb_plus_depth_ms']:.2f} ms", ""),
        ("write one frame batch (Database.write)", f"{result['write_frame_ms']:.2f} ms",
         f"p90 {result['write_frame_p90_ms']:.2f}, p99 {result['write_frame_p99_ms']:.2f}, "
         f"max {result['write_frame_max_ms']:.2f} ms (SQLite's checkpoint inside the commit)"),
        ("  baseline: same bytes as one row", f"{result['baseline_one_row_write_ms']:.2f} ms", ""),
        ("BackgroundWriter.submit (main thread)", f"{result['submit_frame_ms']:.2f} ms",
         f"drain all {result['background_total_s']:.2f} s"),
        ("load_signatures(2 ids) (Retrieval)", f"{result['load_2_signatures_ms']:.2f} ms", ""),
        ("  baseline: 2 rows by id", f"{result['baseline_one_row_read2_ms']:.2f} ms", ""),
        ("load_sensor_blobs + decode", f"{result['load_blobs_decoded_ms']:.2f} ms", ""),
        (f"load_nodes / load_links ({n_frames} nodes)", f"{nodes_ms:.2f} / {links_ms:.2f} ms", ""),
        ("file size per node", f"{result['file_kib_per_node']:.1f} KiB",
         f"baseline {result['baseline_kib_per_node']:.1f} KiB"),
        ("one frame batch, main thread busy", f"{median(busy_frame_ms):.1f} ms", "BackgroundWriter until done"),
        (f"transfer {n_frames} locations, main thread busy", f"{transfer_ms:.1f} ms",
         f"baseline row by row {base_transfer_ms:.1f} ms"),
    ]
    width = max(len(r[0]) for r in rows)
    print(f"database benchmark: {n_frames} frames, {WORDS_PER_FRAME} words/frame, medians "
          f"(load average {load_before:.1f} -> {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores)")
    for name, value, extra in rows:
        print(f"  {name:<{width}}  {value:>16}  {extra}")
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    RESULTS.write_text(json.dumps(result, indent=2) + "\n")
    print(f"wrote {RESULTS}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
