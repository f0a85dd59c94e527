"""The merge check's scan conflict (grid.scan_conflict) on real laser scans: time and ratios.

Usage: ``python bench/bench_scan_conflict.py [--quick]``. Prints a table and writes
``bench/results/scan_conflict.json``.

Data: the Intel lab CARMEN log (real SICK scans, corrected poses). Each case is two passes of the
robot through one place, as two sessions would see it: up to 40 scans of an earlier pass within
10 m of a place (rtabmap's MERGE_CHECK_RADIUS / MERGE_CHECK_SCANS) and up to 40 of a pass at
least 200 scans later, placed at their corrected poses (the true alignment), then the second
pass moved 0.5 m and 1 m sideways (look-alike alignments). Baseline in the same run: the previous
method, which sampled every beam every half cell into sorted sets of cell keys (kept here,
``sampled_scan_conflict``). Reported: median time per call of each, their ratio, the conflict
ratios of each at each shift, and how often the two fall on different sides of
graph.merge_max_conflict.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from rtabmap_ros2.core import transforms
from rtabmap_ros2.core.grid import _beam_samples, _beams_map, _samples_per_beam, scan_conflict
from rtabmap_ros2.core.params import GraphParams
from rtabmap_ros2.core.loop_validation import MERGE_CHECK_BEAMS, MERGE_CHECK_CELL, MERGE_CHECK_RADIUS, MERGE_CHECK_SCANS
from rtabmap_ros2.io.carmen import read_carmen_log

REPO = Path(__file__).resolve().parents[1]
DATA = REPO.parent / "shared" / "data"
RESULTS = REPO / "bench" / "results" / "scan_conflict.json"
MIN_GAP_SCANS = 200  # a later pass, not the same one
MIN_PASS_SCANS = 10
SHIFTS_M = (0.0, 0.5, 1.0)
REPEATS = 3


def sampled_scan_conflict(a, b, cell: float, range_max: float, max_beams: int) -> tuple[float, int]:
    """The method before 7fbb090: beams sampled every half cell, cells as sorted int64 keys."""
    base, offset = 1 << 31, 1 << 30

    def keys(xy):
        ij = np.floor(xy / cell).astype(np.int64) + offset
        return ij[:, 0] * base + ij[:, 1]

    def cells(scans):
        hits, crossed = [np.zeros(0, np.int64)], [np.zeros(0, np.int64)]
        for T, scan in scans:
            origins, ends, is_hit = _beams_map(T, scan, range_max)
            step = max(1, -(-len(ends) // max_beams))
            origins, ends, is_hit = origins[::step], ends[::step], is_hit[::step]
            hits.append(keys(ends[is_hit]))
            vec = ends - origins
            crossed.append(keys(_beam_samples(origins, vec, np.maximum(_samples_per_beam(vec, cell), 1))[1]))
        return np.unique(np.concatenate(hits)), np.unique(np.concatenate(crossed))

    def dilated(k):
        return np.unique(np.concatenate([k + dx * base + dy for dx in (-1, 0, 1) for dy in (-1, 0, 1)]))

    hits_a, crossed_a = cells(a)
    hits_b, crossed_b = cells(b)
    near_a, near_b = dilated(hits_a), dilated(hits_b)
    free_a, free_b = np.setdiff1d(crossed_a, near_a), np.setdiff1d(crossed_b, near_b)
    conflict = int(np.isin(hits_a, free_b).sum() + np.isin(hits_b, free_a).sum())
    support = int(np.isin(hits_a, np.union1d(free_b, near_b)).sum() + np.isin(hits_b, np.union1d(free_a, near_a)).sum())
    return (conflict / support if support else 0.0), support


def passes(poses: list[np.ndarray], cases: int) -> list[tuple[list[int], list[int]]]:
    """(earlier pass, later pass) scan indices around places the robot came back to."""
    xy = np.array([T[:2, 3] for T in poses])
    out = []
    for k in range(0, len(poses), max(1, len(poses) // (4 * cases))):
        later = [j for j in range(k + MIN_GAP_SCANS, len(poses)) if np.linalg.norm(xy[j] - xy[k]) < 1.0]
        if not later:
            continue
        j = later[0]
        first = [i for i in range(max(0, k - 100), k + 1) if np.linalg.norm(xy[i] - xy[k]) <= MERGE_CHECK_RADIUS]
        second = [i for i in range(j, min(len(poses), j + 100)) if np.linalg.norm(xy[i] - xy[k]) <= MERGE_CHECK_RADIUS]
        if len(first) < MIN_PASS_SCANS:
            continue
        thin = lambda ids: ids[::max(1, -(-len(ids) // MERGE_CHECK_SCANS))]
        out.append((thin(first), thin(second)))
        if len(out) == cases:
            break
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="4 places instead of 12")
    ap.add_argument("--out", type=Path, default=RESULTS)
    args = ap.parse_args(argv)
    log = read_carmen_log(DATA / "carmen" / "intel-corrected.log.gz")
    scans, poses = log.laser_scans(), log.poses()
    threshold = GraphParams().merge_max_conflict
    check = (MERGE_CHECK_CELL, MERGE_CHECK_RADIUS, MERGE_CHECK_BEAMS)
    times = {"lines": [], "sampled": []}
    ratios = {s: {"lines": [], "sampled": []} for s in SHIFTS_M}
    across = 0
    cases = passes(poses, 4 if args.quick else 12)
    for first, second in cases:
        a = [(poses[i], scans[i]) for i in first]
        for shift in SHIFTS_M:
            moved = transforms.from_xy_yaw(0.0, shift, 0.0)
            b = [(moved @ poses[i], scans[i]) for i in second]
            results = {}
            for name, fn in (("lines", scan_conflict), ("sampled", sampled_scan_conflict)):
                for _ in range(REPEATS):
                    t0 = time.perf_counter()
                    results[name] = fn(a, b, *check)
                    times[name].append((time.perf_counter() - t0) * 1000.0)
                ratios[shift][name].append(round(results[name][0], 4))
            across += (results["lines"][0] > threshold) != (results["sampled"][0] > threshold)
    median = {k: float(np.median(v)) for k, v in times.items()}
    diffs = [abs(x - y) for s in SHIFTS_M for x, y in zip(ratios[s]["lines"], ratios[s]["sampled"])]
    out = {"cases": len(cases), "scans_per_pass": [[len(f), len(s)] for f, s in cases],
           "median_ms": median, "speedup": median["sampled"] / median["lines"],
           "ratios_by_shift_m": {str(s): r for s, r in ratios.items()},
           "max_ratio_difference": max(diffs), "across_merge_max_conflict": int(across),
           "merge_max_conflict": threshold}
    print(f"{len(cases)} places of intel-corrected, two passes each, {len(SHIFTS_M)} alignments")
    print(f"median time per call: lines {median['lines']:.1f} ms, sampled (before) {median['sampled']:.1f} ms "
          f"({out['speedup']:.1f}x)")
    for s in SHIFTS_M:
        print(f"  shifted {s:.1f} m: conflict lines {np.median(ratios[s]['lines']):.3f}, "
              f"sampled {np.median(ratios[s]['sampled']):.3f} (medians)")
    print(f"largest difference of the ratios {out['max_ratio_difference']:.3f}; "
          f"on different sides of {threshold}: {across}")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(out, indent=1))
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
