"""Loop closure detection with and without memory management (issue 2 bench, 2013 Table III style).

A 640x480 revisiting sequence (``rtabmap_ros2.sim.sequence``, >= 3,000 images; ``--quick``: 500)
is written once as JPEG files under ``--data`` (default ``/tmp/rtabmap_ros2_bench_detect``, not in
the repository), then processed like ``rtabmap-ros2 detect`` (JPEG decode, ``Rtabmap.process``
with ``location_id=k``, paper defaults) once per T_time value, each run in its own subprocess so
its resident memory is its own. T_time = 0 is "no memory management" (the baseline, Table III's
infinity column). Reported per run: median / p95 / max pTime, the frame of the max pTime and the
vocabulary size there, largest WM held (STM excluded, as the paper's "Max WM size"), largest
vocabulary, transferred / retrieved totals, loop closures, precision / recall and best recall
at 100 % precision (origin policy of ``rtabmap_ros2.io.evaluation``, strict in the JSON), RSS
(VmRSS) at start and end.

Targets (issue 2): T_time = 0.7 s -> largest WM >= 2,210 locations at 400 features per image and
max pTime <= 0.93 s. Our pTime is far below the paper's, so small T_time values (0.05, 0.02 s)
are included for transfer and retrieval to act.

    python bench/bench_detect.py [--quick] [--n 3000] [--time-thresholds 0.7 0 0.1 0.05 0.02]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
RESULTS = REPO / "bench" / "results"
DEFAULT_DATA = Path("/tmp/rtabmap_ros2_bench_detect")
FULL_IMAGES, QUICK_IMAGES = 3000, 500
SEED = 7
REVISIT_RATIO = 0.35
DEFAULT_T_TIME_S = (0.7, 0.0, 0.5, 0.3, 0.1, 0.05, 0.03, 0.02)
QUICK_T_TIME_S = (0.7, 0.0, 0.05, 0.02)
TARGET_WM = 2210
TARGET_MAX_PTIME_S = 0.93
TOP_SPIKES = 5


def rss_mb() -> float:
    """Resident set size of this process (VmRSS of /proc/self/status), MB."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024.0
    return float("nan")


def ensure_sequence(n: int, data: Path) -> Path:
    """Write the sequence once (``<data>/seq_<n>_<seed>/1.jpg...``, ground truth beside it)."""
    from rtabmap_ros2.sim.sequence import make_sequence, write_sequence

    folder = data / f"seq_{n}_{SEED}"
    done = folder / "COMPLETE"
    if not done.exists():
        t0 = time.perf_counter()
        print(f"writing {n} images to {folder} ...", flush=True)
        write_sequence(make_sequence(n, seed=SEED, revisit_ratio=REVISIT_RATIO), folder)
        done.write_text(f"{time.perf_counter() - t0:.1f} s\n")
    return folder


def run_one(folder: Path, n: int, t_time_s: float) -> dict:
    """One detect-equivalent run (in this process); returns its summary."""
    import logging

    logging.basicConfig(level=logging.WARNING)
    from rtabmap_ros2.core.params import Params
    from rtabmap_ros2.core.rtabmap import Rtabmap
    from rtabmap_ros2.core.sensor import SensorFrame
    from rtabmap_ros2.io.datasets import read_rgb
    from rtabmap_ros2.io.evaluation import evaluate_rows, load_ground_truth

    rss_start = rss_mb()
    params = Params().with_value("memory.time_threshold_ms", t_time_s * 1000.0)
    gt = load_ground_truth(folder / "ground_truth.png", n)
    db = folder.parent / f"bench_{t_time_s:g}.db"
    rows = []
    t0 = time.perf_counter()
    with Rtabmap(params, db, delete_existing=True) as rtabmap:
        for k in range(1, n + 1):
            rgb = read_rgb(folder / f"{k}.jpg")
            s = rtabmap.process(SensorFrame(stamp_ns=k * 10**9, rgb=rgb), location_id=k)
            rows.append(dict(location_id=s.location_id, loop_closure_id=s.loop_closure_id,
                             highest_hypothesis_id=s.highest_hypothesis_id,
                             highest_hypothesis_value=s.highest_hypothesis_value, merged_id=s.merged_id,
                             process_time_ms=s.process_time_ms, total_time_ms=s.total_time_ms,
                             wm_size=s.wm_size, stm_size=s.stm_size, vocabulary_size=s.vocabulary_size,
                             retrieved=s.retrieved, transferred=s.transferred, timings_ms=dict(s.timings_ms)))
    wall = time.perf_counter() - t0
    rss_end = rss_mb()
    db.unlink(missing_ok=True)
    ptime = np.array([r["process_time_ms"] for r in rows if r["location_id"]])
    spikes = sorted(range(n), key=lambda i: -rows[i]["process_time_ms"])[:TOP_SPIKES]
    ev = evaluate_rows(gt, rows)
    over = int((ptime > t_time_s * 1000).sum()) if t_time_s > 0 else 0
    return {
        "t_time_s": t_time_s, "images": n, "locations": int(sum(1 for r in rows if r["location_id"])),
        "merged": int(sum(1 for r in rows if r["merged_id"])), "wall_s": round(wall, 1),
        "ptime_median_ms": round(float(np.median(ptime)), 2),
        "ptime_p95_ms": round(float(np.percentile(ptime, 95)), 2),
        "ptime_max_ms": round(float(ptime.max()), 2),
        "frames_over_t_time": over,
        "ptime_spikes": [{"image": i + 1, "ptime_ms": round(rows[i]["process_time_ms"], 1),
                          "vocabulary_size": rows[i]["vocabulary_size"], "wm_size": rows[i]["wm_size"],
                          "steps_ms": {k: round(v, 1) for k, v in rows[i]["timings_ms"].items()}} for i in spikes],
        "step_median_ms": {k: round(float(np.median([r["timings_ms"].get(k, 0.0) for r in rows])), 2)
                           for k in rows[0]["timings_ms"]},
        "total_time_median_ms": round(float(np.median([r["total_time_ms"] for r in rows])), 2),
        "max_wm_size": max(r["wm_size"] for r in rows),
        "max_wm_plus_stm": max(r["wm_size"] + r["stm_size"] for r in rows),
        "final_wm_size": rows[-1]["wm_size"],
        "max_vocabulary_size": max(r["vocabulary_size"] for r in rows),
        "transferred": int(sum(r["transferred"] for r in rows)),
        "retrieved": int(sum(r["retrieved"] for r in rows)),
        "loop_closures": int(sum(1 for r in rows if r["loop_closure_id"])),
        "evaluation": ev,
        "rss_start_mb": round(rss_start, 1), "rss_end_mb": round(rss_end, 1),
    }


def table(results: list[dict]) -> str:
    head = (f"{'T_time s':>8} {'med pT ms':>9} {'p95 pT':>7} {'max pT':>8} {'>T':>4} {'maxWM':>6} "
            f"{'dict k':>7} {'transf':>6} {'retr':>5} {'loops':>5} {'prec %':>6} {'rec %':>6} "
            f"{'R@100P %':>8} {'minT_loop':>9} {'RSS MB':>13}")
    lines = [head, "-" * len(head)]
    for r in results:
        o = r["evaluation"]["origin"]
        thr = o["threshold_at_100_precision"]
        label = "inf (0)" if r["t_time_s"] == 0 else f"{r['t_time_s']:g}"
        lines.append(
            f"{label:>8} {r['ptime_median_ms']:9.1f} {r['ptime_p95_ms']:7.1f} {r['ptime_max_ms']:8.1f} "
            f"{r['frames_over_t_time']:4d} {r['max_wm_size']:6d} {r['max_vocabulary_size'] / 1000:7.1f} "
            f"{r['transferred']:6d} {r['retrieved']:5d} {r['loop_closures']:5d} {100 * o['precision']:6.1f} "
            f"{100 * o['recall']:6.1f} {100 * o['recall_at_100_precision']:8.1f} "
            f"{(f'{thr:.3f}' if thr is not None else '-'):>9} {r['rss_start_mb']:6.0f}->{r['rss_end_mb']:<6.0f}")
    return "\n".join(lines)


def targets_of(results: list[dict]) -> dict | None:
    """Issue 2's targets, measured on the T_time = 0.7 s run."""
    main_run = next((r for r in results if r["t_time_s"] == 0.7), None)
    if main_run is None:
        return None
    return {"max_wm_size": main_run["max_wm_size"], "target_max_wm_size": TARGET_WM,
            "max_wm_met": main_run["max_wm_size"] >= TARGET_WM,
            "max_ptime_s": main_run["ptime_max_ms"] / 1000.0, "target_max_ptime_s": TARGET_MAX_PTIME_S,
            "max_ptime_met": main_run["ptime_max_ms"] / 1000.0 <= TARGET_MAX_PTIME_S}


def results_path(args: argparse.Namespace) -> Path:
    if args.quick and args.n is None:
        return RESULTS / "detect_quick.json"
    return RESULTS / ("detect.json" if args.n in (None, FULL_IMAGES) else f"detect_{args.n}.json")


def previous_runs(n: int, args: argparse.Namespace, thresholds) -> list[dict]:
    """Runs of other T_time values from an earlier invocation on the same sequence."""
    path = results_path(args)
    if not path.exists():
        return []
    old = json.loads(path.read_text())
    if old.get("images") != n or old.get("seed") != SEED:
        return []
    return [r for r in old["runs"] if r["t_time_s"] not in thresholds]


def write_report(results: list[dict], n: int, gt_positives: int | None, args: argparse.Namespace) -> Path:
    """JSON of the runs so far (rewritten after every run, so a long benchmark keeps partial results)."""
    report = {"images": n, "seed": SEED, "revisit_ratio": REVISIT_RATIO, "size": "640x480",
              "images_with_gt_loop": gt_positives, "cpu_count": os.cpu_count(), "load_avg": os.getloadavg(),
              "targets_t_time_0.7": targets_of(results), "runs": results}
    RESULTS.mkdir(parents=True, exist_ok=True)
    path = results_path(args)
    path.write_text(json.dumps(report, indent=1))
    return path


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help=f"{QUICK_IMAGES} images, fewer T_time values")
    parser.add_argument("--n", type=int, default=None, help=f"images (default {FULL_IMAGES})")
    parser.add_argument("--time-thresholds", type=float, nargs="+", default=None, metavar="S",
                        help="T_time values in seconds (0 = no memory management)")
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA, help="where the images are cached")
    parser.add_argument("--append", action="store_true",
                        help="keep the runs of other T_time values already in the results JSON (same images)")
    parser.add_argument("--single", type=float, default=None, help=argparse.SUPPRESS)
    args = parser.parse_args()
    n = args.n or (QUICK_IMAGES if args.quick else FULL_IMAGES)
    folder = ensure_sequence(n, args.data)
    if args.single is not None:
        print(json.dumps(run_one(folder, n, args.single)))
        return 0
    thresholds = args.time_thresholds or (QUICK_T_TIME_S if args.quick else DEFAULT_T_TIME_S)
    gt_positives = None
    results = previous_runs(n, args, thresholds) if args.append else []
    for t in thresholds:
        t0 = time.perf_counter()
        out = subprocess.run([sys.executable, __file__, "--n", str(n), "--data", str(args.data), "--single", str(t)],
                             capture_output=True, text=True, check=False)
        if out.returncode != 0:
            print(out.stderr[-3000:], file=sys.stderr)
            return 1
        result = json.loads(out.stdout.strip().splitlines()[-1])
        result["load_avg_after"] = os.getloadavg()
        results.append(result)
        gt_positives = result["evaluation"]["origin"]["positives"]
        print(f"T_time {t:g} s done in {time.perf_counter() - t0:.0f} s", flush=True)
        print(table(results[-1:]).splitlines()[-1], flush=True)
        path = write_report(results, n, gt_positives, args)
    targets = targets_of(results)
    print(f"\n{n} images, {gt_positives} with a ground-truth loop closure; pT = pTime (no feature extraction)")
    print(table(results))
    if targets:
        print(f"targets at T_time 0.7 s: max WM {targets['max_wm_size']} (>= {TARGET_WM}: {targets['max_wm_met']}), "
              f"max pTime {targets['max_ptime_s']:.3f} s (<= {TARGET_MAX_PTIME_S}: {targets['max_ptime_met']})")
    print(f"-> {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
