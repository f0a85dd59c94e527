#!/usr/bin/env python3
"""Where a frame's CPU goes, by kind of frame (issue 50): ``rtabmap-ros2 map`` over the simulator's
five sessions of one seed, in this process, with the parts of a frame timed in thread CPU time.

Each part is a function of the package (below, :data:`PARTS`), wrapped for the run only: its thread
time is added to the frame being processed (a part called inside itself counts once). Frames are
told apart as ``map --stats`` does: ``accepted`` (a loop closure kept), ``rejected`` (one found and
rejected) and ``other``. Prints each part's mean by kind of frame, its p95 and maximum over all
frames, and the p95 of the frames' total by kind (the ratio issue 50 asks to bring to 1.5); writes
the same to ``--out``.

Thread time leaves out the time a frame waits (the database writer thread, the interpreter lock), so
the totals are below ``map --stats``' wall-clock process_time_ms (``bench_slam.py`` measures that).

    python3 bench/profile_frames.py --seed 9
    python3 bench/profile_frames.py --gil   # only: does another thread run while gtsam solves?

``--gil`` measures whether a loop closure frame's optimisation could overlap the next frame's work
in a thread: a pose graph like the local map's is solved by gtsam while a second Python thread
counts, and the count it reaches is compared with the same thread's count alone (1: gtsam releases
the interpreter lock; 0: the thread waits for the whole solve). Written under ``gtsam_gil`` in
``--out``, the rest of the file kept.
"""

from __future__ import annotations

import argparse
import functools
import importlib.metadata
import json
import platform
import sys
import tempfile
import threading
import time
from collections import defaultdict
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "bench"))

from rtabmap_ros2.core import (bayes, kdtree, local_map, loop_validation, memory, optimizer,  # noqa: E402
                               registration, rtabmap)

# (owner, function name, part): what a frame does, in the order it does it.
PARTS = (
    (rtabmap, "frame_features", "features"),
    (memory.Memory, "quantize", "quantization"),
    (kdtree.RandomizedKdTrees, "search", "kd-tree search"),
    (kdtree.RandomizedKdTrees, "add", "kd-tree insertion"),
    (rtabmap, "words_3d", "3D words"),
    (memory.Memory, "add_location", "add location"),
    (local_map.LocalMapper, "neighbor_link", "neighbour link (ICP)"),
    (memory.Memory, "similarities", "rehearsal similarity"),
    (memory.Memory, "rehearse", "rehearsal merge"),
    (bayes.BayesFilter, "update", "Bayes filter"),
    (loop_validation.LoopValidator, "verify", "verification (registration)"),
    (registration, "_refine_with_icp", "verification: ICP"),
    (loop_validation.LoopValidator, "allows", "multi-session checks"),
    (local_map.LocalMapper, "update", "local map"),
    (optimizer.IncrementalOptimizer, "solve", "local map: iSAM2"),
    (optimizer.IncrementalOptimizer, "_update", "local map: iSAM2 new factors"),
    (optimizer.IncrementalOptimizer, "_converge", "local map: iSAM2 convergence"),
    (optimizer.IncrementalOptimizer, "_robust_rounds", "local map: iSAM2 robust rounds"),
    (local_map, "optimize", "local map: batch solve"),
    (local_map, "max_error_ratio", "local map: OptimizeMaxError"),
    (local_map, "fits_inter_session_majority", "local map: session majority"),
    (local_map, "_warm_start", "local map: warm start"),
    (local_map.LocalMapper, "follow_local_frame", "local map: world frame"),
    (memory.Memory, "transfer", "transfer to LTM"),
    (memory.Memory, "retrieve", "retrieval"),
    (memory.Memory, "commit", "database hand-off"),
)


class FrameParts:
    """Thread CPU time (ms) of each part in the frame being processed."""

    def __init__(self) -> None:
        self.current: dict[str, float] = defaultdict(float)
        self.thread = threading.get_ident()   # the thread processing frames (other threads' calls not counted)
        self._inside: dict[str, int] = defaultdict(int)

    def wrap(self, owner, name: str, part: str) -> None:
        function = getattr(owner, name)

        @functools.wraps(function)
        def timed(*args, **kwargs):
            if self._inside[part] or threading.get_ident() != self.thread:
                return function(*args, **kwargs)
            self._inside[part] += 1
            start = time.thread_time()
            try:
                return function(*args, **kwargs)
            finally:
                self.current[part] += (time.thread_time() - start) * 1000.0
                self._inside[part] -= 1

        setattr(owner, name, timed)


def profile(data: Path) -> list[dict]:
    """Every frame's kind, total and parts over the sessions in ``data``."""
    from bench_slam import bags_of

    from rtabmap_ros2.cli import cli
    from rtabmap_ros2.core.params import default_config_path

    parts = FrameParts()
    missing = [f"{getattr(owner, '__name__', owner)}.{name}" for owner, name, _ in PARTS if not hasattr(owner, name)]
    if missing:
        raise SystemExit(f"profile_frames: the package no longer has {missing}: update PARTS")
    for owner, name, part in PARTS:
        parts.wrap(owner, name, part)
    frames: list[dict] = []
    process = rtabmap.Rtabmap._process

    def timed_process(self, frame, location_id, features):
        parts.current.clear()
        parts.thread = threading.get_ident()
        start = time.thread_time()
        stats = process(self, frame, location_id, features)
        kind = "accepted" if stats.loop_closure_id else "rejected" if stats.rejected_loop_closure_id else "other"
        frames.append({"kind": kind, "total": (time.thread_time() - start) * 1000.0,
                       "process_time_ms": stats.process_time_ms, **parts.current})
        return stats

    rtabmap.Rtabmap._process = timed_process
    with tempfile.TemporaryDirectory(prefix="profile_frames_") as tmp:
        rc = cli.main(["map", *map(str, bags_of(data)), "--db", str(Path(tmp) / "map.db"), "--no-progress",
                       "--config", str(default_config_path())])
    if rc != 0:
        raise SystemExit(f"profile_frames: map failed with exit code {rc}")
    return frames


def summarise(frames: list[dict]) -> dict:
    kinds = np.array([f["kind"] for f in frames])
    names = [part for _, _, part in PARTS]

    def column(name: str) -> np.ndarray:
        return np.array([f.get(name, 0.0) for f in frames])

    table = {}
    for name in ("total", *names):
        v = column(name)
        table[name] = {**{f"mean_{k}": float(v[kinds == k].mean()) if (kinds == k).any() else None
                          for k in ("accepted", "rejected", "other")},
                       "p95": float(np.percentile(v, 95)), "max": float(v.max())}
    total = column("total")
    p95 = {k: float(np.percentile(total[kinds == k], 95)) for k in ("accepted", "rejected", "other")
           if (kinds == k).any()}
    return {"frames": {k: int((kinds == k).sum()) for k in ("accepted", "rejected", "other")}, "parts_ms": table,
            "total_p95_ms": p95, "accepted_over_other_p95": p95.get("accepted", float("nan")) / p95["other"]}


def gtsam_gil(nodes: int = 3000, seconds: float = 0.5) -> dict:
    """Another Python thread's progress while gtsam solves a ``nodes``-pose graph (chain + loop
    closures every 10 poses, Levenberg-Marquardt), as a fraction of its progress alone."""
    import gtsam

    rng = np.random.default_rng(0)
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    noise = gtsam.noiseModel.Isotropic.Sigma(6, 0.1)
    graph.add(gtsam.PriorFactorPose3(0, gtsam.Pose3(), noise))
    step, loop = gtsam.Pose3(gtsam.Rot3.Yaw(0.01), np.array([1.0, 0, 0])), gtsam.Pose3(gtsam.Rot3(), np.array([50.0, 0, 0]))
    for i in range(nodes):
        values.insert(i, gtsam.Pose3(gtsam.Rot3.Ypr(*rng.normal(0, 0.1, 3)), rng.normal(0, 1, 3)))
        if i:
            graph.add(gtsam.BetweenFactorPose3(i - 1, i, step, noise))
        if i > 50 and i % 10 == 0:
            graph.add(gtsam.BetweenFactorPose3(i - 50, i, loop, noise))

    def counted(work) -> tuple[float, float]:
        """(counts per second of a spinning thread, seconds) while ``work`` runs."""
        stop, count = threading.Event(), [0]

        def spin() -> None:
            while not stop.is_set():
                count[0] += 1

        thread = threading.Thread(target=spin)
        thread.start()
        start = time.perf_counter()
        work()
        elapsed = time.perf_counter() - start
        stop.set()
        thread.join()
        return count[0] / elapsed, elapsed

    alone, _ = counted(lambda: time.sleep(seconds))
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(20)
    during, solve_s = counted(lambda: gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize())
    return {"poses": nodes, "solve_ms": solve_s * 1e3, "other_thread_progress": during / alone,
            "gtsam": importlib.metadata.version("gtsam")}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seed", type=int, default=9, help="simulator seed (bench_slam's data of that seed)")
    parser.add_argument("--data", type=Path, help="sessions folder instead of the seed's")
    parser.add_argument("--out", type=Path, default=REPO / "bench" / "results" / "frame_parts.json")
    parser.add_argument("--gil", action="store_true", help="only measure whether gtsam lets other threads run")
    args = parser.parse_args(argv)
    if args.gil:
        gil = gtsam_gil()
        print(f"gtsam {gil['gtsam']} solving {gil['poses']} poses ({gil['solve_ms']:.0f} ms): another Python thread "
              f"ran at {gil['other_thread_progress']:.2f} of its speed alone")
        previous = json.loads(args.out.read_text()) if args.out.exists() else {}
        args.out.write_text(json.dumps({**previous, "gtsam_gil": {
            **gil, "written": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())}}, indent=1))
        return 0
    from bench_slam import ensure_data

    data = args.data or ensure_data(REPO / "bench" / "data" / ("sim5" if args.seed == 0 else f"sim5_seed{args.seed}"),
                                    False, args.seed)
    frames = profile(data)
    summary = summarise(frames)
    print(f"\n{len(frames)} frames: " + ", ".join(f"{n} {k}" for k, n in summary["frames"].items()))
    print(f"{'part (thread CPU, ms)':32s} {'accepted':>9s} {'rejected':>9s} {'other':>9s} {'p95':>8s} {'max':>8s}")
    for name, row in summary["parts_ms"].items():
        means = [row[f"mean_{k}"] for k in ("accepted", "rejected", "other")]
        print(f"{name:32s} " + " ".join("        -" if m is None else f"{m:9.2f}" for m in means)
              + f" {row['p95']:8.2f} {row['max']:8.1f}")
    print("total p95 by kind: " + ", ".join(f"{k} {v:.1f} ms" for k, v in summary["total_p95_ms"].items())
          + f"; accepted / other {summary['accepted_over_other_p95']:.2f}")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    header = {"data": str(data), "machine": platform.platform(), "python": platform.python_version(),
              "written": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())}
    args.out.write_text(json.dumps({**header, **summary}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
