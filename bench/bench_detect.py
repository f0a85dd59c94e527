"""Loop closure detection with and without memory management (issue 2 bench, 2013 Table III style).

A 640x480 revisiting sequence (``rtabmap_ros2.sim.sequence``, >= 3,000 images; ``--quick``: 500)
is written once as JPEG files under ``--data`` (default ``/tmp/rtabmap_ros2_bench_detect``, not in
the repository), then processed like ``rtabmap-ros2 detect`` (JPEG decode, ``Rtabmap.process``
with ``location_id=k``, paper defaults) once per T_time value, each run in its own subprocess so
its resident memory is its own. T_time = 0 is "no memory management" (the baseline, Table III's
infinity column). Reported per run: median / p95 / max pTime, the frame of the max pTime and the
vocabulary size there, largest WM held (STM excluded, as the paper's "Max WM size"), largest
vocabulary, transferred / retrieved totals, loop closures, precision / recall and best recall
at 100 % precision (merged policy of ``rtabmap_ros2.io.evaluation``, strict in the JSON), RSS
(VmRSS) at start and end.

Targets (issue 2): T_time = 0.7 s -> largest WM >= 2,210 locations at 400 features per image and
max pTime <= 0.93 s. Our pTime is far below the paper's, so small T_time values (0.05, 0.02 s)
are included for transfer and retrieval to act.

    python bench/bench_detect.py [--quick] [--n 3000] [--time-thresholds 0.7 0 0.1 0.05 0.02]

Issue 50 mode, long runs (``--long 10000 25000``): ``rtabmap-ros2 detect`` itself (a subprocess,
as a user runs it) over ``../shared/tools/make_sequence.py`` images of a seed no other bench uses
(``--long-seed``, default 61; ``--long-size``, default 320x240), T_time 0.7 s
(``memory.time_threshold_ms=700``). Reported per run: max, p95 and median process time, frames over
T_time, WM and vocabulary size (last and largest), transfers, peak RSS of the process (wait4), the
machine's load, and the steps of the slowest frames (from the database's statistics table)
(-> ``long_runs`` in ``results/detect.json``, the T_time sweep's runs and the long runs of other sizes kept). Target: max process
time <= 0.7 s. ``--long-report-only`` summarises the runs' outputs as they are (one still running
or stopped: the frames done so far), running nothing.

    nice -n 10 python bench/bench_detect.py --long 10000 25000 [--data DIR] [--long-report-only]

Issue 12 modes (T_time 0.7 s, one sequence per seed of ``--seeds``, default 7 11 13):

* ``--ablation``: precision / recall at the default T_loop and recall at 100 % precision of the
  issue-12 changes, each alone on top of the old defaults and all together (the new defaults),
  per seed and averaged (-> ``results/detect_ablation.json``). Features are extracted once per
  image and cached beside the sequence (``features.npz``): pTime excludes them anyway.
* ``--reference``: the reference implementation (RTAB-Map 0.22.1 C++, ``../shared/reference``,
  when it is there) on the same images, side by side with our defaults (the ablation's run of them
  when it is kept beside the images): precision, recall, recall at 100 % precision, median and max
  time per image (-> ``results/detect_reference.json``). The reference's time per image is its whole
  iteration, feature extraction included; ours is pTime, without it.
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
SEEDS = (7, 11, 13)
REFERENCE = REPO.parent / "shared" / "reference"
# Issue 12 ablation: (label, --set overrides). "old defaults" are the defaults before issue 12
# (the NNDR test d1 <= T_NNDR * d2 is in every run); each change alone on top of them, then all
# together = the new defaults (an empty override list).
# Epipolar verification (VhEp/Enabled) is off in the old defaults, as it was before issue 12.
OLD_DEFAULTS = ("Kp/TfIdfLikelihoodUsed=false", "Kp/NewWordsComparedTogether=false",
                "Mem/RehearsalSimilarity=0.2", "Rtabmap/LoopRatio=0", "Bayes/VirtualPlacePriorThr=0.9",
                "VhEp/Enabled=false")
# The epipolar inliers' coverage of the image (not in RTAB-Map) came after the rest: off in the rows
# that measured epipolar verification alone.
NO_COVERAGE = "bayes.epipolar_min_coverage=0"
ABLATION = (
    ("old defaults", OLD_DEFAULTS),
    ("+ tf-idf likelihood", OLD_DEFAULTS + ("Kp/TfIdfLikelihoodUsed=true",)),
    ("+ new words compared together", OLD_DEFAULTS + ("Kp/NewWordsComparedTogether=true",)),
    ("+ rehearsal similarity 0.6", OLD_DEFAULTS + ("Mem/RehearsalSimilarity=0.6",)),
    ("+ loop ratio 0.9", OLD_DEFAULTS + ("Rtabmap/LoopRatio=0.9",)),
    ("+ virtual place prior 0.95", OLD_DEFAULTS + ("Bayes/VirtualPlacePriorThr=0.95",)),
    ("+ epipolar verification", OLD_DEFAULTS + ("VhEp/Enabled=true", NO_COVERAGE)),
    ("+ epipolar verification, coverage 0.1", OLD_DEFAULTS + ("VhEp/Enabled=true", "bayes.epipolar_min_coverage=0.1")),
    ("all but virtual place prior", ("Bayes/VirtualPlacePriorThr=0.9",)),
    ("all but epipolar verification", ("VhEp/Enabled=false",)),
    ("all but inlier coverage", (NO_COVERAGE,)),
    ("all, coverage 0.05", ("bayes.epipolar_min_coverage=0.05",)),
    ("all, coverage 0.2", ("bayes.epipolar_min_coverage=0.2",)),
    ("all + loop ratio 0.9", ("Rtabmap/LoopRatio=0.9",)),
    ("previous: loop ratio, no VhEp", ("Rtabmap/LoopRatio=0.9", "VhEp/Enabled=false")),
    ("new defaults (all)", ()),
)
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


def ensure_sequence(n: int, data: Path, seed: int = SEED) -> Path:
    """Write the sequence once (``<data>/seq_<n>_<seed>/1.jpg...``, ground truth beside it)."""
    from rtabmap_ros2.sim.sequence import make_sequence, write_sequence

    folder = data / f"seq_{n}_{seed}"
    done = folder / "COMPLETE"
    if not done.exists():
        t0 = time.perf_counter()
        print(f"writing {n} images to {folder} ...", flush=True)
        write_sequence(make_sequence(n, seed=seed, revisit_ratio=REVISIT_RATIO), folder)
        done.write_text(f"{time.perf_counter() - t0:.1f} s\n")
    return folder


class _CachedFeatures:
    """The default extractor's features of the sequence's images, extracted once and kept in
    ``<folder>/features.npz`` (the ablation runs the same images many times; pTime excludes
    feature extraction, so the figures are those of ``detect``)."""

    def __init__(self, folder: Path, n: int, extractor) -> None:
        from rtabmap_ros2.core.features import Features
        from rtabmap_ros2.io.datasets import read_rgb

        path = folder / "features.npz"
        if not path.exists():
            parts = [extractor.extract(read_rgb(folder / f"{k}.jpg")) for k in range(1, n + 1)]
            counts = np.array([len(f.keypoints) for f in parts])
            tmp = folder / "features.tmp.npz"
            np.savez(tmp, counts=counts, keypoints=np.concatenate([f.keypoints for f in parts]),
                     descriptors=np.concatenate([f.descriptors for f in parts]),
                     responses=np.concatenate([f.responses for f in parts]))
            tmp.rename(path)
        with np.load(path) as data:
            counts, keypoints, descriptors, responses = (data[k] for k in ("counts", "keypoints", "descriptors",
                                                                            "responses"))
        bounds = np.r_[0, np.cumsum(counts)]
        self.features = [Features(keypoints[a:b].copy(), descriptors[a:b].copy(), responses[a:b].copy())
                         for a, b in zip(bounds[:-1], bounds[1:])]
        self.next = 0

    def extract(self, image, depth_m=None) -> object:
        features = self.features[self.next]
        self.next += 1
        return features


def run_one(folder: Path, n: int, t_time_s: float, overrides: tuple[str, ...] = (),
            cached_features: bool = False) -> dict:
    """One detect-equivalent run (in this process); returns its summary."""
    import logging

    logging.basicConfig(level=logging.WARNING)
    from rtabmap_ros2.core.params import Params
    from rtabmap_ros2.core.rtabmap import Rtabmap
    from rtabmap_ros2.core.sensor import SensorFrame
    from rtabmap_ros2.io.datasets import read_rgb
    from rtabmap_ros2.io.evaluation import evaluate_rows, load_ground_truth

    rss_start = rss_mb()
    params = Params().with_overrides(list(overrides)).with_value("memory.time_threshold_ms", t_time_s * 1000.0)
    gt = load_ground_truth(folder / "ground_truth.png", n)
    db = folder.parent / f"bench_{folder.name}_{t_time_s:g}_{os.getpid()}.db"
    rows = []
    t0 = time.perf_counter()
    with Rtabmap(params, db, delete_existing=True) as rtabmap:
        if cached_features:
            rtabmap.extractor = _CachedFeatures(folder, n, rtabmap.extractor)
        for k in range(1, n + 1):
            rgb = read_rgb(folder / f"{k}.jpg")  # stored with the location, as by detect
            s = rtabmap.process(SensorFrame(stamp_ns=k * 10**9, rgb=rgb), location_id=k)
            rows.append(dict(location_id=s.location_id, loop_closure_id=s.loop_closure_id,
                             highest_hypothesis_id=s.highest_hypothesis_id,
                             highest_hypothesis_value=s.highest_hypothesis_value, merged_id=s.merged_id,
                             process_time_ms=s.process_time_ms, total_time_ms=s.total_time_ms,
                             wm_size=s.wm_size, stm_size=s.stm_size, vocabulary_size=s.vocabulary_size,
                             retrieved=s.retrieved, transferred=s.transferred, timings_ms=dict(s.timings_ms)))
    wall = time.perf_counter() - t0
    rss_end = rss_mb()
    for suffix in ("", "-wal", "-shm"):
        Path(f"{db}{suffix}").unlink(missing_ok=True)
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
        o = r["evaluation"]["merged"]
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


def single(folder: Path, n: int, t_time_s: float, overrides: tuple[str, ...] = (), cached: bool = False) -> dict:
    """``run_one`` in a subprocess of its own (its own resident memory, no state shared)."""
    command = [sys.executable, __file__, "--n", str(n), "--data", str(folder.parent),
               "--seeds", folder.name.rsplit("_", 1)[1], "--single", str(t_time_s)]
    command += [f"--set={o}" for o in overrides] + (["--cached-features"] if cached else [])
    # The package of this tree, not whichever one is installed (a worktree measures its own code).
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(filter(None, (str(REPO), os.environ.get("PYTHONPATH")))))
    out = subprocess.run(command, capture_output=True, text=True, check=False, env=env)
    if out.returncode != 0:
        raise RuntimeError(f"{' '.join(command)} failed:\n{out.stderr[-3000:]}")
    result = json.loads(out.stdout.strip().splitlines()[-1])
    result["load_avg_after"] = os.getloadavg()
    return result


def _summary(ev: dict) -> dict:
    o = ev["merged"]
    return {"precision": o["precision"], "recall": o["recall"], "recall_at_100_precision": o["recall_at_100_precision"],
            "accepted": o["accepted"], "positives": o["positives"]}


def ablation(n: int, args: argparse.Namespace) -> int:
    """Issue 12: each change alone on the old defaults and all together, on every seed (T_time 0.7 s)."""
    folders = [ensure_sequence(n, args.data, seed) for seed in args.seeds]
    configs = [c for c in ABLATION if not args.configs or any(k in c[0] for k in args.configs)]
    runs = []
    # The new and old defaults first: the rest of the table explains their difference.
    order = sorted(configs, key=lambda c: (c[0] not in ("new defaults (all)", "old defaults"), configs.index(c)))
    jobs = [(label, overrides, folder) for label, overrides in order for folder in folders]
    from concurrent.futures import ThreadPoolExecutor

    def work(job):
        label, overrides, folder = job
        # Each run's result is kept beside the images: an interrupted ablation resumes where it stopped.
        key = "_".join(o.replace("/", "-").replace("=", "-") for o in overrides) or "defaults"
        done = folder / f"ablation_{key}.json"
        if done.exists() and not args.rerun:
            r = json.loads(done.read_text())
        elif args.report_only:
            return None
        else:
            t0 = time.perf_counter()
            r = single(folder, n, 0.7, overrides, cached=True)
            done.write_text(json.dumps(r))
            print(f"{label} / {folder.name}: {time.perf_counter() - t0:.0f} s", flush=True)
        return {"config": label, "overrides": list(overrides), "seed": int(folder.name.rsplit('_', 1)[1]),
                **_summary(r["evaluation"]), "ptime_median_ms": r["ptime_median_ms"], "ptime_max_ms": r["ptime_max_ms"],
                "max_wm_size": r["max_wm_size"], "merged": r["merged"], "load_avg_after": r["load_avg_after"]}

    with ThreadPoolExecutor(max_workers=args.jobs) as pool:
        runs = [r for r in pool.map(work, jobs) if r is not None]
    configs = [c for c in configs if any(r["config"] == c[0] for r in runs)]
    runs.sort(key=lambda r: ([c[0] for c in configs].index(r["config"]), r["seed"]))
    head = (f"{'configuration':32} {'seed':>5} {'prec %':>6} {'rec %':>6} {'R@100P %':>8} {'med pT ms':>9} "
            f"{'maxWM':>6} {'merged':>6}")
    lines = [f"{n} images per seed, T_time 0.7 s, T_loop 0.11 (merged policy)", head, "-" * len(head)]
    for label, _ in configs:
        mine = [r for r in runs if r["config"] == label]
        for r in mine + [None]:
            row = r or {k: float(np.mean([m[k] for m in mine])) for k in
                        ("precision", "recall", "recall_at_100_precision", "ptime_median_ms", "max_wm_size", "merged")}
            lines.append(f"{label if r is None else '':32} {('mean' if r is None else r['seed']):>5} "
                         f"{100 * row['precision']:6.1f} {100 * row['recall']:6.1f} "
                         f"{100 * row['recall_at_100_precision']:8.1f} {row['ptime_median_ms']:9.1f} "
                         f"{row['max_wm_size']:6.0f} {row['merged']:6.0f}")
    print("\n".join(lines))
    RESULTS.mkdir(parents=True, exist_ok=True)
    path = RESULTS / ("detect_ablation.json" if n == FULL_IMAGES else f"detect_ablation_{n}.json")
    path.write_text(json.dumps({"images": n, "seeds": list(args.seeds), "t_time_s": 0.7, "cpu_count": os.cpu_count(),
                                "load_avg": os.getloadavg(), "table": lines, "runs": runs}, indent=1))
    print(f"-> {path}")
    return 0


def _reference_runnable(reference: Path, scratch: Path) -> Path:
    """The reference's folder, or a copy in ``scratch`` whose library symlinks are repaired (a copy
    of the folder that turned its symlinks into text files naming their target)."""
    lib = reference / "lib"
    broken = [f for f in lib.iterdir() if f.is_file() and f.stat().st_size < 256 and not f.is_symlink()]
    if not broken:
        return reference
    import shutil

    copy = scratch / "reference"
    if not (copy / "rtabmap-reference").exists():
        shutil.copytree(reference, copy, symlinks=True, dirs_exist_ok=True)
        for f in broken:
            target = (copy / "lib" / f.name)
            name = f.read_text().strip()
            target.chmod(0o644)
            target.unlink()
            target.symlink_to(name)
    return copy


def reference_side_by_side(n: int, args: argparse.Namespace) -> int:
    """Issue 12: the reference (RTAB-Map C++) and our defaults on the same images, per seed."""
    import csv

    from rtabmap_ros2.io.evaluation import evaluate_rows, load_ground_truth

    if not (args.reference_dir / "rtabmap-reference").exists():
        print(f"no reference at {args.reference_dir}: nothing to compare with", file=sys.stderr)
        return 1
    scratch = args.data / "reference"
    scratch.mkdir(parents=True, exist_ok=True)
    runner = _reference_runnable(args.reference_dir, scratch) / "rtabmap-reference"
    out = []
    for seed in args.seeds:
        folder = ensure_sequence(n, args.data, seed)
        # Images only: the reference would take ground_truth.png for image N+1.
        images = scratch / f"images_{n}_{seed}"
        images.mkdir(exist_ok=True)
        for k in range(1, n + 1):
            link = images / f"{k}.jpg"
            if not link.exists():
                link.symlink_to(folder / f"{k}.jpg")
        result_dir = scratch / f"out_{n}_{seed}"
        csv_path = result_dir / "detections.csv"
        if not csv_path.exists() or args.rerun_reference:
            t0 = time.perf_counter()
            subprocess.run([str(runner), str(images), str(result_dir)], check=True)
            print(f"reference / seed {seed}: {time.perf_counter() - t0:.0f} s", flush=True)
        rows = []
        for r in list(csv.DictReader(open(csv_path)))[:n]:
            rows.append({"location_id": int(r["location_id"]), "loop_closure_id": int(r["loop_closure_id"]),
                         "highest_hypothesis_id": int(r["highest_hypothesis_id"]),
                         "highest_hypothesis_value": float(r["highest_hypothesis_value"]),
                         "process_time_ms": float(r["process_time_ms"]),
                         # The reference keeps the older id when rehearsal merges, as ours does.
                         "merged_id": 0})
        gt = load_ground_truth(folder / "ground_truth.png", n)
        times = np.array([r["process_time_ms"] for r in rows])
        ref = {"seed": seed, "implementation": "RTAB-Map 0.22.1 C++", **_summary(evaluate_rows(gt, rows)),
               "ptime_median_ms": float(np.median(times)), "ptime_max_ms": float(times.max())}
        # Our defaults on these images: the ablation's run kept beside them when there is one
        # (the same code path; its features were extracted once, which pTime excludes anyway).
        kept = folder / "ablation_defaults.json"
        mine = json.loads(kept.read_text()) if kept.exists() and not args.rerun else single(folder, n, 0.7)
        ours = {"seed": seed, "implementation": "rtabmap_ros2", **_summary(mine["evaluation"]),
                "ptime_median_ms": mine["ptime_median_ms"], "ptime_max_ms": mine["ptime_max_ms"]}
        out += [ref, ours]
    head = f"{'implementation':22} {'seed':>5} {'prec %':>6} {'rec %':>6} {'R@100P %':>8} {'med ms':>7} {'max ms':>8}"
    lines = [f"{n} images per seed, defaults, T_time 0.7 s, T_loop 0.11 (the reference prints hypothesis values "
             "with 2 decimals: its R@100P is coarse)", head, "-" * len(head)]
    for r in out:
        lines.append(f"{r['implementation']:22} {r['seed']:>5} {100 * r['precision']:6.1f} {100 * r['recall']:6.1f} "
                     f"{100 * r['recall_at_100_precision']:8.1f} {r['ptime_median_ms']:7.1f} {r['ptime_max_ms']:8.1f}")
    print("\n".join(lines))
    path = RESULTS / ("detect_reference.json" if n == FULL_IMAGES else f"detect_reference_{n}.json")
    path.write_text(json.dumps({"images": n, "seeds": list(args.seeds), "load_avg": os.getloadavg(),
                                "table": lines, "runs": out}, indent=1))
    print(f"-> {path}")
    return 0


LONG_SEED = 61
LONG_SIZE = "320x240"
LONG_T_TIME_MS = 700.0
MAKE_SEQUENCE = REPO.parent / "shared" / "tools" / "make_sequence.py"


def ensure_long_sequence(n: int, data: Path, seed: int, size: str) -> Path:
    """make_sequence.py's images, written once (``<data>/long_<n>_<seed>_<size>/images``, ``gt.png``)."""
    width, height = size.split("x")
    folder = data / f"long_{n}_{seed}_{size}"
    if not (folder / "COMPLETE").exists():
        print(f"writing {n} images to {folder} ...", flush=True)
        subprocess.run([sys.executable, str(MAKE_SEQUENCE), "--out", str(folder), "--frames", str(n),
                        "--seed", str(seed), "--width", width, "--height", height], check=True)
        (folder / "COMPLETE").write_text("")
    return folder


def long_summary(out_dir: Path, t_time_ms: float, top: int = TOP_SPIKES) -> dict:
    """Figures of a detect run from its detections.csv and database statistics (a finished run,
    or the part done so far of one still running)."""
    import csv
    import sqlite3

    rows = [r for r in csv.DictReader(open(out_dir / "detections.csv")) if r["status"] == "ok"]
    ptime = np.array([float(r["process_time_ms"]) for r in rows])
    wm = [int(r["wm_size"]) for r in rows]
    words = [int(r["vocabulary_size"]) for r in rows]
    with sqlite3.connect(f"file:{out_dir / 'database.db'}?mode=ro", uri=True) as db:
        stats = [json.loads(d) for (d,) in db.execute("SELECT data FROM statistics")]
    stats.sort(key=lambda r: -r["process_time_ms"])
    return {"frames": len(rows), "ptime_max_ms": round(float(ptime.max()), 1),
            "ptime_p95_ms": round(float(np.percentile(ptime, 95)), 1),
            "ptime_median_ms": round(float(np.median(ptime)), 1),
            "frames_over_t_time": int((ptime > t_time_ms).sum()),
            "wm_size_last": wm[-1], "wm_size_max": max(wm), "vocabulary_last": words[-1],
            "vocabulary_max": max(words), "transferred": int(sum(int(r["transferred"]) for r in rows)),
            "retrieved": int(sum(int(r["retrieved"]) for r in rows)),
            "slowest": [{"frame": r["frame_index"] + 1, "ptime_ms": round(r["process_time_ms"], 1),
                         "wm_size": r["wm_size"], "vocabulary_size": r["vocabulary_size"],
                         "transferred": r["transferred"], "retrieved": r["retrieved"],
                         "steps_ms": {k[5:-3]: round(v, 1) for k, v in r.items()
                                      if k.startswith("time_") and v >= 1.0}} for r in stats[:top]]}


def long_runs(args: argparse.Namespace) -> int:
    """Issue 50 item 5: ``rtabmap-ros2 detect`` over --long images each, T_time 0.7 s."""
    import resource

    RESULTS.mkdir(parents=True, exist_ok=True)
    path = RESULTS / "detect.json"
    runs = []
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(filter(None, (str(REPO), os.environ.get("PYTHONPATH")))))
    for n in args.long:
        folder = ensure_long_sequence(n, args.data, args.long_seed, args.long_size)
        out_dir = args.data / f"detect_long_{n}_{args.long_seed}"
        if args.long_report_only:
            run = {"images": n, "seed": args.long_seed, "partial": True, **long_summary(out_dir, LONG_T_TIME_MS)}
            print(json.dumps(run, indent=1))
            continue
        command = [sys.executable, "-m", "rtabmap_ros2.cli.cli", "detect", str(folder / "images"),
                   "--out", str(out_dir), "--set", f"memory.time_threshold_ms={LONG_T_TIME_MS:g}",
                   "--ground-truth", str(folder / "gt.png"), "--no-progress"]
        t0 = time.perf_counter()
        load_before = os.getloadavg()
        with open(args.data / f"detect_long_{n}.log", "w") as log:
            process = subprocess.Popen(command, stdout=log, stderr=subprocess.STDOUT, env=env)
            _, status, usage = os.wait4(process.pid, 0)
            process.returncode = os.waitstatus_to_exitcode(status)
        if process.returncode != 0:
            print(f"{' '.join(command)} failed ({process.returncode}): see {log.name}", file=sys.stderr)
            return 1
        run = {"images": n, "seed": args.long_seed, "size": args.long_size, "t_time_ms": LONG_T_TIME_MS,
               "wall_s": round(time.perf_counter() - t0, 1),
               "peak_rss_mb": round(usage.ru_maxrss / 1024.0, 1),  # KiB on Linux
               "cpu_s": round(usage.ru_utime + usage.ru_stime, 1),
               "load_avg_before": load_before, "load_avg_after": os.getloadavg(),
               **long_summary(out_dir, LONG_T_TIME_MS)}
        run["max_met"] = run["ptime_max_ms"] <= LONG_T_TIME_MS
        runs.append(run)
        print(f"{n} images: max {run['ptime_max_ms']:.0f} ms, p95 {run['ptime_p95_ms']:.0f} ms, median "
              f"{run['ptime_median_ms']:.0f} ms, {run['frames_over_t_time']} over T_time; WM {run['wm_size_last']} "
              f"(max {run['wm_size_max']}), vocabulary {run['vocabulary_last']} (max {run['vocabulary_max']}); "
              f"peak RSS {run['peak_rss_mb']:.0f} MB; {run['wall_s']:.0f} s wall, load "
              f"{run['load_avg_after'][0]:.1f}", flush=True)
        for spike in run["slowest"]:
            print(f"  frame {spike['frame']}: {spike['ptime_ms']:.0f} ms, WM {spike['wm_size']}, "
                  f"transferred {spike['transferred']}, steps {spike['steps_ms']}", flush=True)
        report = json.loads(path.read_text()) if path.exists() else {}
        # Runs of other sizes stay (``--long 10000`` and ``--long 25000`` may run apart).
        done = {r["images"] for r in runs}
        kept = [r for r in report.get("long_runs", {}).get("runs", []) if r["images"] not in done]
        report["long_runs"] = {"cpu_count": os.cpu_count(), "runs": sorted(kept + runs, key=lambda r: r["images"])}
        path.write_text(json.dumps(report, indent=1))
    if runs:
        print(f"-> {path}")
    return 0


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help=f"{QUICK_IMAGES} images, fewer T_time values")
    parser.add_argument("--n", type=int, default=None, help=f"images (default {FULL_IMAGES})")
    parser.add_argument("--time-thresholds", type=float, nargs="+", default=None, metavar="S",
                        help="T_time values in seconds (0 = no memory management)")
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA, help="where the images are cached")
    parser.add_argument("--append", action="store_true",
                        help="keep the runs of other T_time values already in the results JSON (same images)")
    parser.add_argument("--ablation", action="store_true", help="issue 12's ablation table over --seeds")
    parser.add_argument("--configs", nargs="+", default=None, metavar="WORD",
                        help="--ablation: only the configurations whose label contains one of these")
    parser.add_argument("--reference", action="store_true",
                        help="run the reference (RTAB-Map C++) on the same sequences, side by side with ours")
    parser.add_argument("--reference-dir", type=Path, default=REFERENCE, help=f"default {REFERENCE}")
    parser.add_argument("--rerun-reference", action="store_true", help="do not reuse its detections.csv")
    parser.add_argument("--seeds", type=int, nargs="+", default=list(SEEDS), help="sequences (--ablation, --reference)")
    parser.add_argument("--jobs", type=int, default=2, help="--ablation: runs at a time")
    parser.add_argument("--parallel-sweep", action="store_true",
                        help="T_time sweep: --jobs runs at a time (faster, timings less comparable)")
    parser.add_argument("--report-only", action="store_true",
                        help="--ablation: table of the runs kept beside the images, running none")
    parser.add_argument("--rerun", action="store_true",
                        help="--ablation, --reference: do not reuse our runs kept beside the images")
    parser.add_argument("--long", type=int, nargs="+", default=None, metavar="N",
                        help="issue 50: rtabmap-ros2 detect over N make_sequence images each (e.g. 10000 25000)")
    parser.add_argument("--long-seed", type=int, default=LONG_SEED, help=f"--long: sequence seed (default {LONG_SEED})")
    parser.add_argument("--long-size", default=LONG_SIZE, help=f"--long: WIDTHxHEIGHT (default {LONG_SIZE})")
    parser.add_argument("--long-report-only", action="store_true",
                        help="--long: summarise the runs' outputs so far (partial ones too), running nothing")
    parser.add_argument("--single", type=float, default=None, help=argparse.SUPPRESS)
    parser.add_argument("--set", action="append", default=[], help=argparse.SUPPRESS)
    parser.add_argument("--cached-features", action="store_true",
                        help="T_time sweep: features extracted once per image (features.npz beside the images)")
    args = parser.parse_args()
    if args.long:
        return long_runs(args)
    n = args.n or (QUICK_IMAGES if args.quick else FULL_IMAGES)
    if args.single is not None:
        folder = ensure_sequence(n, args.data, args.seeds[0])
        print(json.dumps(run_one(folder, n, args.single, tuple(args.set), args.cached_features)))
        return 0
    if args.ablation:
        return ablation(n, args)
    if args.reference:
        return reference_side_by_side(n, args)
    folder = ensure_sequence(n, args.data)
    thresholds = args.time_thresholds or (QUICK_T_TIME_S if args.quick else DEFAULT_T_TIME_S)
    gt_positives = None
    results = previous_runs(n, args, thresholds) if args.append else []
    from concurrent.futures import ThreadPoolExecutor

    pool = ThreadPoolExecutor(max_workers=args.jobs if args.parallel_sweep else 1)
    pending = [(t, time.perf_counter(), pool.submit(single, folder, n, t, (), args.cached_features)) for t in thresholds]
    for t, t0, future in pending:
        try:
            result = future.result()
        except RuntimeError as exc:
            print(exc, file=sys.stderr)
            return 1
        results.append(result)
        gt_positives = result["evaluation"]["merged"]["positives"]
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
