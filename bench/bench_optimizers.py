"""Pose graph optimisers (gtsam LM, Gauss-Newton, dogleg) on the community benchmarks, and DCS.

Usage: ``python bench/bench_optimizers.py [--quick]``. Prints a table and writes
``bench/results/optimizers.json``.

1. For each graph of ``shared/data/posegraphs``: chi2 initial / final, iterations and time (median
   of 3 runs) of each optimiser, root = first vertex, no robust kernel. Baseline: LM, the default.
2. Robustness (2014 §II-B with DCS): manhattan + 50 false loop closures between random node pairs
   (identity transform, the information of the median true loop closure). Final ATE (RMS position
   difference) against the clean graph's solution, without a kernel and with DCS; how many false
   loop closures the robust mode rejects, and how many true ones it also rejects, for DCS phi in
   1, 10, 100, 1000 (--quick: the default phi only); also the true loop closures rejected on the
   clean graph.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
from pathlib import Path

import numpy as np

from rtabmap_ros2.core.graph import Link, LinkType
from rtabmap_ros2.core import optimizer as optimizer_module
from rtabmap_ros2.core.optimizer import optimize, read_g2o
from rtabmap_ros2.core.params import GraphParams
from rtabmap_ros2.errors import OptimizationError

REPO = Path(__file__).resolve().parents[1]
DATA = REPO.parent / "shared" / "data" / "posegraphs"
RESULTS = REPO / "bench" / "results" / "optimizers.json"
GRAPHS = ["intel", "MIT", "manhattan", "city10000", "parking-garage", "sphere2500", "CSAIL", "torus3D",
          "smallGrid3D"]
QUICK_GRAPHS = ["intel", "MIT", "manhattan", "sphere2500"]
OPTIMIZERS = ["lm", "gn", "dogleg"]
FALSE_LOOPS = 50
PHI_SWEEP = [1.0, 10.0, 100.0, 1000.0]
SEED = 7


def run_graph(name: str, repeats: int, iterations: int) -> list[dict]:
    poses, links, planar = read_g2o(DATA / f"{name}.g2o")
    root = min(poses)
    rows = []
    for opt in OPTIMIZERS:
        params = GraphParams(optimizer=opt, robust=False, iterations=iterations)
        times, result, error = [], None, ""
        for _ in range(repeats):
            try:
                result = optimize(poses, links, root, params, planar)
                times.append(result.time_s)
            except OptimizationError as exc:
                error = str(exc).split(";")[0]
                break
        row = {"graph": name, "nodes": len(poses), "links": len(links), "planar": planar, "optimizer": opt}
        if result is None or error:
            row.update(failed=error)
        else:
            row.update(chi2_initial=result.chi2_initial, chi2_final=result.chi2_final,
                       iterations=result.iterations, time_s=statistics.median(times))
        rows.append(row)
        print(_fmt(row), flush=True)
    return rows


def _fmt(row: dict) -> str:
    head = f"{row['graph']:<15} {row['nodes']:>6} {row['links']:>6} {row['optimizer']:<7}"
    if "failed" in row:
        return f"{head} FAILED: {row['failed'][:70]}"
    return (f"{head} {row['chi2_initial']:>12.5g} {row['chi2_final']:>12.6g} {row['iterations']:>5} "
            f"{row['time_s']:>8.3f}")


def robustness(repeats: int, phis: list[float]) -> dict:
    poses, links, planar = read_g2o(DATA / "manhattan.g2o")
    root = min(poses)
    rng = np.random.default_rng(SEED)
    loops = [l for l in links if l.type.is_loop_closure]
    info = loops[len(loops) // 2].information
    ids = np.array(sorted(poses))
    false_links = []
    while len(false_links) < FALSE_LOOPS:
        a, b = rng.choice(ids, 2, replace=False)
        if abs(int(a) - int(b)) > 1:
            false_links.append(Link(int(a), int(b), LinkType.LOOP_INTRA, np.eye(4), info))
    false_keys = {l.key() for l in false_links}
    clean = optimize(poses, links, root, GraphParams(robust=False), planar).poses
    out = {"graph": "manhattan", "false_loop_closures": FALSE_LOOPS, "default_phi": optimizer_module.DCS_PHI}
    times = []
    for _ in range(repeats):
        res = optimize(poses, links + false_links, root, GraphParams(robust=False), planar)
        times.append(res.time_s)
    out["no_kernel"] = {"ate_vs_clean_m": _ate(clean, res.poses), "chi2_final": res.chi2_final,
                        "rejected_false": 0, "rejected_true": 0, "time_s": statistics.median(times)}
    default_phi = optimizer_module.DCS_PHI
    out["dcs"] = {}
    try:
        for phi in phis:
            optimizer_module.DCS_PHI = phi
            on_clean = optimize(poses, links, root, GraphParams(robust=True), planar)
            times = []
            for _ in range(repeats):
                res = optimize(poses, links + false_links, root, GraphParams(robust=True), planar)
                times.append(res.time_s)
            rejected_false = sum(1 for l in res.rejected if l.key() in false_keys)
            out["dcs"][str(phi)] = {
                "ate_vs_clean_m": _ate(clean, res.poses), "chi2_final": res.chi2_final,
                "rejected_false": rejected_false, "rejected_true": len(res.rejected) - rejected_false,
                "time_s": statistics.median(times), "clean_graph_rejected_true": len(on_clean.rejected),
                "clean_graph_ate_m": _ate(clean, on_clean.poses)}
    finally:
        optimizer_module.DCS_PHI = default_phi
    return out


def _ate(reference: dict, poses: dict) -> float:
    d = [np.linalg.norm(reference[k][:3, 3] - poses[k][:3, 3]) for k in reference]
    return float(np.sqrt(np.mean(np.square(d))))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="4 graphs, 1 run each")
    parser.add_argument("--iterations", type=int, default=100)
    args = parser.parse_args(argv)
    if not DATA.is_dir():
        print(f"no pose graphs at {DATA}", file=sys.stderr)
        return 1
    repeats = 1 if args.quick else 3
    print(f"{'graph':<15} {'nodes':>6} {'links':>6} {'opt':<7} {'chi2 init':>12} {'chi2 final':>12} "
          f"{'iter':>5} {'time s':>8}")
    rows = []
    for name in QUICK_GRAPHS if args.quick else GRAPHS:
        if (DATA / f"{name}.g2o").exists():
            rows.extend(run_graph(name, repeats, args.iterations))
    robust = robustness(repeats, [optimizer_module.DCS_PHI] if args.quick else PHI_SWEEP)
    print(f"\nRobustness: manhattan + {FALSE_LOOPS} false loop closures; ATE vs the clean solution; "
          f"default DCS phi = {robust['default_phi']:g}")
    r = robust["no_kernel"]
    print(f"  no kernel      ATE {r['ate_vs_clean_m']:8.4f} m  time {r['time_s']:.2f} s")
    for phi, r in robust["dcs"].items():
        print(f"  DCS phi {float(phi):<6g} ATE {r['ate_vs_clean_m']:8.4f} m  rejected false {r['rejected_false']}/"
              f"{FALSE_LOOPS}  rejected true {r['rejected_true']}  time {r['time_s']:.2f} s  | clean graph: "
              f"{r['clean_graph_rejected_true']} rejected, ATE {r['clean_graph_ate_m']:.4f} m")
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    RESULTS.write_text(json.dumps({"graphs": rows, "robustness": robust, "quick": args.quick,
                                   "iterations": args.iterations}, indent=2))
    print(f"wrote {RESULTS}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
