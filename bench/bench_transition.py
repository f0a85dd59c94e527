"""How much of the predicted belief lands where the image matches: ours beside RTAB-Map (issue 32).

Per image, the loop hypotheses' likelihood weighted by their predicted belief,
``LE = Σ_j L_j b_j / Σ_j b_j`` (their share of Eq. 2's normaliser): above 1 when the prediction
carried belief to the places the image then favours, so a revisit's value compounds. It is read

* for ours from the filter's state after each step: the posterior is ``L_j b_j / sum`` and
  ``L_new b_new / sum``, so ``LE = (1 - p_new) / Σ_j (p_j / L_j)``;
* for the reference from its debug log (``debug.txt`` of a ``bench_lcd.py`` reference run): the
  posterior's sum before normalisation (``computePosterior() sum=``), ``adjustLikelihood``'s mean and
  deviation (the new place's likelihood, ``mean / std + 1``, or 2 when nothing stands out) and the new
  place's posterior (``reference_stats.csv``); its prediction of the new place is ``0.9 p + 0.1 (1 - p)``,
  p the new place's posterior of the image before (checked: ``sum * p_new / (L_new b_new)``, printed).

Ours runs in the conformance setting (``config/rtabmap_reference.yaml``, memory management off; a
loop closure link crossed without a hop, as RTAB-Map's; issue 32 measured a hop here, issue 48 removed
it with the other additions that lost on real images); the reference with
``--Rtabmap/TimeThr 0`` (its first kept run, run once if there is none). Printed and written to
``bench/results/transition.json``: the median LE - 1 on the ground truth's loop images, recall.

    python bench/bench_transition.py [--set ms:44] [--data DIR] [--quick]   # --quick: the 84 real images
"""

from __future__ import annotations

import argparse
import csv
import json
import re
import sys
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_lcd import CONFORMANCE, DEFAULT_DATA, DEFAULT_FRAMES, REPO, _gt_rows, prepare, run_reference  # noqa: E402

RESULTS = REPO / "bench" / "results"
REFERENCE_OPTIONS = ("--Rtabmap/TimeThr", "0")
VIRTUAL_PLACE_PRIOR = 0.9  # Bayes/VirtualPlacePriorThr, both sides
NO_STANDOUT_NEW_LIKELIHOOD = 2.0


def ours(images: str) -> dict:
    """LE per image (None where the filter did not update) and accepted loop closures."""
    import tempfile

    from rtabmap_ros2.core.bayes import NEW_LOCATION
    from rtabmap_ros2.core.params import Params
    from rtabmap_ros2.core.rtabmap import Rtabmap
    from rtabmap_ros2.io.datasets import ImageFolderDataset

    params = Params.from_yaml(CONFORMANCE[1]).with_overrides(["memory.time_threshold_ms=0"])
    shares, loops = [], []
    with tempfile.TemporaryDirectory() as tmp, Rtabmap(params, Path(tmp) / "db.db", delete_existing=True) as rtabmap:
        observation = None
        for index, _, frame in ImageFolderDataset(images).items():
            stats = rtabmap.process(frame, location_id=index)
            loops.append(stats.loop_closure_id)
            bayes = rtabmap.bayes
            if bayes.observation is observation:  # no filter step this image
                shares.append(None)
                continue
            observation = bayes.observation
            weighted = sum(p / observation[j] for j, p in bayes.posterior.items() if j != NEW_LOCATION)
            shares.append((1.0 - bayes.posterior[NEW_LOCATION]) / weighted if weighted > 0 else None)
    return {"shares": shares, "loops": loops}


def reference(run: Path) -> tuple[list, list]:
    """The reference's LE per image from its debug log (None where the log lacks a figure), and the check
    of its new place's prediction per image (1 when it is 0.9 p + 0.1 (1 - p))."""
    blocks: list[dict] = []
    for line in open(run / "debug.txt", errors="replace"):
        if "::process() Processing signature" in line:
            blocks.append({})
        elif blocks and (m := re.search(r"adjustLikelihood\(\) mean=([\d.e+-]+), stdDev=([\d.e+-]+), max=([\d.e+-]+)", line)):
            blocks[-1].update(zip(("mean", "std", "max"), map(float, m.groups())))
        elif blocks and (m := re.search(r"computePosterior\(\) sum=([\d.e+-]+)", line)):
            blocks[-1]["sum"] = float(m.group(1))
    with open(run / "reference_stats.csv", newline="") as f:
        new_place = [float(r["virtual_place_hypothesis"]) for r in csv.DictReader(f)]
    shares, checks = [None], []
    for k in range(1, min(len(blocks), len(new_place))):
        b = blocks[k]
        if not {"mean", "std", "max", "sum"} <= b.keys():
            shares.append(None)
            continue
        standout = b["std"] > 1e-4 and b["max"] > b["mean"] + b["std"]
        like_new = b["mean"] / b["std"] + 1.0 if standout else NO_STANDOUT_NEW_LIKELIHOOD
        p = new_place[k - 1]
        belief_new = VIRTUAL_PLACE_PRIOR * p + (1.0 - VIRTUAL_PLACE_PRIOR) * (1.0 - p)
        shares.append((b["sum"] - like_new * belief_new) / (1.0 - belief_new))
        if new_place[k] > 0:
            checks.append(b["sum"] * new_place[k] / (like_new * belief_new))
    return shares, checks


def _summary(shares: list, loops: list, gt: np.ndarray, loop_rows: np.ndarray) -> dict:
    on_loops = [s - 1.0 for s, loop in zip(shares, loop_rows) if loop and s is not None]
    true = sum(1 for i, l in enumerate(loops) if l > 0 and gt[i, l - 1])
    return {"median_share_minus_1_loop_images": float(np.median(on_loops)),
            "recall": true / int(loop_rows.sum()), "accepted": sum(1 for l in loops if l > 0)}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--set", default="ms:44", help="lcd, ms:SEED or sim:SEED (bench_lcd.py's data sets)")
    parser.add_argument("--frames", type=int, default=DEFAULT_FRAMES, help="images of a generated sequence")
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA, help="where bench_lcd.py keeps sequences and runs")
    parser.add_argument("--quick", action="store_true", help="RTAB-Map's 84 real images instead of --set")
    args = parser.parse_args()
    if args.quick:
        args.set = "lcd"
    import cv2

    ds = prepare(args.set, args.frames, args.data)
    gt = cv2.imread(str(ds.gt), cv2.IMREAD_GRAYSCALE) == 255
    loop_rows = _gt_rows(ds.gt)
    run = run_reference(ds, args.data, False, REFERENCE_OPTIONS)
    with ProcessPoolExecutor(max_workers=2) as pool:
        job = pool.submit(ours, str(ds.images))
        ref_shares, checks = reference(run)
        with open(run / "detections.csv", newline="") as f:
            ref_loops = [int(float(r["loop_closure_id"])) for r in csv.DictReader(f)]
        result = {"set": args.set, "reference_run": str(run),
                  "reference_check_median": float(np.median(checks)),
                  "reference_check_99th_deviation": float(np.percentile(np.abs(np.array(checks) - 1), 99)),
                  "reference": _summary(ref_shares, ref_loops, gt, loop_rows)}
        out = job.result()
        result["ours"] = _summary(out["shares"], out["loops"], gt, loop_rows)
    for key, value in result.items():
        print(f"{key}: {value}")
    path = RESULTS / "transition.json"
    path.write_text(json.dumps(result, indent=1))
    print(f"-> {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
