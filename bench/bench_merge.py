"""``merge`` against ``map``: the same robots' bags mapped into one database, or each into its own then merged.

A fleet from ``simulate --session-gap 0`` (all robots start at the same instant; the full 5
sessions, about 1,800 frames, or the 2 small ones with ``--quick``), seed 7 by default (the demo's
is 0). In one run, on one machine:

* ``map``: every bag into one database (``rtabmap-ros2 map bag_1 ... bag_K --db``), the way a
  single computer would map them;
* per robot: each bag into its own database (``map``, one process per robot, as each robot's
  computer would), not part of the ratio;
* ``merge``: the robots' databases into one (stored features reused), and again with
  ``--reextract`` (features extracted from the stored images).

Times are wall times of the CLI processes (the import, ~1-2 s, included in each). The ratio is
merge time / map time. Both results are exported: components, nodes and the ATE against each
robot's ground truth (sessions matched with their own, one alignment). Writes
``bench/results/merge.json``.

Usage: ``python bench/bench_merge.py [--quick] [--seed N] [--sessions K]``.
"""

from __future__ import annotations

import argparse
import json
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from rtabmap_ros2.io.export import read_nodes_csv
from rtabmap_ros2.io.trajectory import ate_sessions, read_tum

RESULTS = Path(__file__).resolve().parent / "results" / "merge.json"
CLI = [sys.executable, "-m", "rtabmap_ros2"]
DEFAULT_SEED = 7


def timed(*args) -> tuple[float, str]:
    """Run the CLI; (wall time s, stdout); raises on failure."""
    t0 = time.perf_counter()
    result = subprocess.run([*CLI, *map(str, args)], capture_output=True, text=True)
    elapsed = time.perf_counter() - t0
    if result.returncode != 0:
        raise SystemExit(f"{' '.join(map(str, args))} failed:\n{result.stderr[-3000:]}")
    return elapsed, result.stdout


def evaluate(db: Path, sim: Path, robots: int, out: Path) -> dict:
    """Export ``db`` and measure it: components, nodes, ATE with session k = robot k+1."""
    timed("export", db, "--out", out)
    summary = json.loads((out / "summary.json").read_text())
    truths = {k: read_tum(sim / f"ground_truth_{k + 1}.txt") for k in range(robots)}
    result = ate_sessions(read_nodes_csv(out / "nodes.csv"), truths)
    return {"components": summary["components"], "nodes": summary["nodes"],
            "loop_inter": summary["links_by_type"].get("loop_inter", 0), "ate_m": round(result.rmse_m, 4),
            "ate_max_m": round(result.max_m, 4)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="the 2 small sessions (~100 frames)")
    parser.add_argument("--seed", type=int, default=DEFAULT_SEED)
    parser.add_argument("--sessions", type=int, default=None, help="robots (default 5, 2 with --quick)")
    args = parser.parse_args()
    robots = args.sessions or (2 if args.quick else 5)
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        sim = tmp / "sim"
        timed("simulate", "--out", sim, "--seed", args.seed, "--sessions", robots, "--session-gap", 0,
              *(["--small"] if args.quick else []))
        bags = [sim / f"session_{k}" for k in range(1, robots + 1)]
        frames = sum(s["frames"] for s in json.loads((sim / "world.json").read_text())["sessions"])
        map_s, _ = timed("map", *bags, "--db", tmp / "all.db", "--no-progress")
        per_robot_s = []
        for k, bag in enumerate(bags, 1):
            per_robot_s.append(round(timed("map", bag, "--db", tmp / f"robot_{k}.db", "--no-progress")[0], 2))
        inputs = [tmp / f"robot_{k}.db" for k in range(1, robots + 1)]
        merge_s, merge_out = timed("merge", *inputs, "--out", tmp / "merged.db", "--no-progress")
        reextract_s, _ = timed("merge", *inputs, "--out", tmp / "reextracted.db", "--no-progress", "--reextract")
        quality = {name: evaluate(tmp / f"{name}.db", sim, robots, tmp / f"export_{name}")
                   for name in ("all", "merged", "reextracted")}
    result = {
        "mode": "quick" if args.quick else "full", "seed": args.seed, "robots": robots, "frames": frames,
        "map_s": round(map_s, 2), "merge_s": round(merge_s, 2), "merge_reextract_s": round(reextract_s, 2),
        "ratio_merge_to_map": round(merge_s / map_s, 3), "ratio_reextract_to_map": round(reextract_s / map_s, 3),
        "per_robot_map_s": per_robot_s, "map": quality["all"], "merge": quality["merged"],
        "merge_reextract": quality["reextracted"],
        "merge_summary": [line for line in merge_out.splitlines() if not line.startswith("session ")],
        "machine": platform.platform(), "python": platform.python_version(),
    }
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    RESULTS.write_text(json.dumps(result, indent=2) + "\n")
    print(f"{robots} robots at once, {frames} frames (seed {args.seed}):")
    print(f"  map (all bags, one database): {map_s:.1f} s, {quality['all']}")
    print(f"  merge of the {robots} databases: {merge_s:.1f} s (ratio {merge_s / map_s:.2f}), {quality['merged']}")
    print(f"  merge --reextract: {reextract_s:.1f} s (ratio {reextract_s / map_s:.2f}), {quality['reextracted']}")
    print(f"  each robot mapped alone: {per_robot_s} s -> {RESULTS}")


if __name__ == "__main__":
    main()
