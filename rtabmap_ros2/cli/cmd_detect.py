"""``rtabmap-ros2 detect IMAGE_DIR --out OUT_DIR``: the 2013 paper's loop closure detection.

Appearance only: every image of the folder (natural order: 1.jpg, 2.jpg, ..., 10.jpg) is one
frame without odometry; image k creates location k (RTAB-Map's ``rtabmap-console`` numbering), so
RTAB-Map's ground-truth matrices apply directly.
"""

from __future__ import annotations

import argparse
import csv
import logging
import sys
from pathlib import Path

from rtabmap_ros2.cli.common_args import add_param_arguments

log = logging.getLogger(__name__)

# detections.csv columns: the ones issue 2 requires first, then the other statistics, then (issue 32)
# the detection's diagnostics, to put beside RTAB-Map's own (reference_stats.csv).
COLUMNS = ("image", "location_id", "loop_closure_id", "highest_hypothesis_id", "highest_hypothesis_value",
           "process_time_ms", "total_time_ms", "wm_size", "vocabulary_size",
           "stm_size", "ltm_size", "retrieved", "transferred", "merged_id", "rejected_loop_closure_id",
           "words_added", "status", "words_extracted", "rehearsal_similarity", "new_location_probability",
           "likelihood_nonzero", "likelihood_mean", "likelihood_max", "likelihood_std")
STATUS_OK, STATUS_BAD, STATUS_UNREADABLE, STATUS_REJECTED = "ok", "bad_signature", "unreadable", "rejected"

EPILOG = """\
outputs (in OUT_DIR):
  detections.csv  one row per image, in input order (location_id 0: unreadable or rejected)
  database.db     the long-term memory (an existing OUT_DIR/database.db is DELETED first)
  timing.png      process time per image with the T_time line, WM size on a second axis (Fig. 7)
  params.yaml     the parameters used (the defaults; config/rtabmap.yaml detects alike, with SLAM memory settings)

ground truth (--ground-truth GT.png): RTAB-Map's N x N matrix, pixel (i, j) = 255 when image i+1
closes a loop with image j+1. The strict count (GT[i, L] only, as ../shared/tools/score_lcd.py)
is printed, and the "merged" one: rehearsal merges an image's location into the previous one (the
older location stays; the row's location_id is it, merged_id the image merged), and a loop closure
i -> L also counts when GT[i, m] for an image m merged into L. Recall is over the images
with a ground-truth loop closure; the best recall at 100 % precision is searched over
thresholds on highest_hypothesis_value. A ground-truth file inside IMAGE_DIR is not an image.
"""


def add_parser(subparsers) -> None:
    parser = subparsers.add_parser(
        "detect", help="appearance-based loop closure detection over a folder of images (2013 paper)",
        description=__doc__.splitlines()[0] + " Image k of the folder is location k.",
        epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("image_dir", metavar="IMAGE_DIR", help="folder of images (natural sort order)")
    parser.add_argument("--out", required=True, metavar="OUT_DIR",
                        help="output folder (created; its database.db is deleted first)")
    add_param_arguments(parser)
    parser.add_argument("--ground-truth", metavar="GT.png", default=None,
                        help="RTAB-Map ground-truth matrix: print precision, recall, recall at 100%% precision")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    logging.getLogger("faiss.loader").setLevel(logging.WARNING)  # its INFO lines say nothing useful here
    from tqdm import tqdm
    from tqdm.contrib.logging import logging_redirect_tqdm

    from rtabmap_ros2.core.rtabmap import Rtabmap
    from rtabmap_ros2.errors import DatasetError, SensorDataError
    from rtabmap_ros2.cli.common_args import params_from_args
    from rtabmap_ros2.io.datasets import ImageFolderDataset
    from rtabmap_ros2.io.evaluation import evaluate_rows, load_ground_truth

    params = params_from_args(args)
    dataset = ImageFolderDataset(args.image_dir)
    if args.ground_truth:
        _exclude_ground_truth(dataset, Path(args.ground_truth))
    gt = load_ground_truth(args.ground_truth, len(dataset)) if args.ground_truth else None
    dataset.check_readable()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    params.to_yaml(out / "params.yaml")
    rows: list[dict] = []
    with Rtabmap(params, out / "database.db", delete_existing=True) as rtabmap, \
            open(out / "detections.csv", "w", newline="") as f, logging_redirect_tqdm():
        writer = csv.DictWriter(f, fieldnames=COLUMNS, extrasaction="ignore")
        writer.writeheader()
        progress = tqdm(dataset.items(), total=len(dataset), unit="img", file=sys.stderr,
                        disable=args.no_progress)
        for index, path, frame in progress:
            row = dict.fromkeys(COLUMNS, 0)
            row.update(image=path.name, status=STATUS_UNREADABLE)
            if frame is not None:
                try:
                    stats = rtabmap.process(frame, location_id=index)
                except SensorDataError as exc:
                    log.warning("image %d (%s) rejected: %s", index, path, exc)
                    row["status"] = STATUS_REJECTED
                else:
                    row.update({k: v for k, v in stats.to_dict().items() if k in row and k != "image"})
                    for name in ("highest_hypothesis_value", "rehearsal_similarity", "new_location_probability",
                                 "likelihood_mean", "likelihood_max", "likelihood_std"):
                        row[name] = round(float(row[name]), 6)
                    row["process_time_ms"] = round(stats.process_time_ms, 3)
                    row["total_time_ms"] = round(stats.total_time_ms, 3)
                    row["status"] = STATUS_BAD if stats.bad_signature else STATUS_OK
                    progress.set_postfix(wm=stats.wm_size, loop=stats.loop_closure_id, refresh=False)
            writer.writerow(row)
            rows.append(row)
    if not any(r["status"] in (STATUS_OK, STATUS_BAD) for r in rows):
        raise DatasetError(f"none of the {len(rows)} images of {args.image_dir} could be processed "
                           f"(see the warnings above); {out / 'detections.csv'} lists why")
    _plot_timing(rows, params.memory.time_threshold_ms, out / "timing.png")
    loops = sum(1 for r in rows if int(r["loop_closure_id"]) > 0)
    print(f"{len(rows)} images, {loops} loop closures -> {out / 'detections.csv'}")
    if gt is not None:
        _print_evaluation(evaluate_rows(gt, rows))
    return 0


def _exclude_ground_truth(dataset, gt_path: Path) -> None:
    """The ground-truth PNG may sit in the image folder (``write_sequence`` puts it there): not an image."""
    target = gt_path.resolve()
    kept = [p for _, p in dataset.paths if p.resolve() != target]
    if len(kept) < len(dataset.paths):
        log.info("%s is the ground truth, not an image of the sequence", gt_path)
        dataset.paths = list(enumerate(kept, start=1))


def _print_evaluation(result: dict) -> None:
    for policy in ("merged", "strict"):
        r = result[policy]
        threshold = r["threshold_at_100_precision"]
        at = f" (highest_hypothesis_value >= {threshold:.4f})" if threshold is not None else ""
        print(f"[{policy}] precision {100 * r['precision']:.1f} % ({r['true_positives']}/{r['accepted']}), "
              f"recall {100 * r['recall']:.1f} % ({r['true_positives']}/{r['positives']}), "
              f"best recall at 100 % precision {100 * r['recall_at_100_precision']:.1f} %{at}")


def _plot_timing(rows: list[dict], time_threshold_ms: float, path: Path) -> None:
    """Process time per image with the T_time line and WM size on a second axis (2013 Fig. 7)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    images = range(1, len(rows) + 1)
    processed = [(k, float(r["process_time_ms"]) / 1000.0) for k, r in enumerate(rows, start=1)
                 if r["status"] in (STATUS_OK, STATUS_BAD)]
    fig, ax = plt.subplots(figsize=(10, 4))
    ax.plot([k for k, _ in processed], [t for _, t in processed], ".", ms=2, color="tab:blue",
            label="process time")
    if time_threshold_ms > 0:
        ax.axhline(time_threshold_ms / 1000.0, color="tab:red", lw=1, label=f"T_time = {time_threshold_ms / 1000:g} s")
    ax.set_xlabel("image")
    ax.set_ylabel("process time (s)")
    wm = ax.twinx()
    wm.plot(images, [int(r["wm_size"]) for r in rows], color="tab:green", lw=1, label="WM size")
    wm.set_ylabel("WM size (locations)")
    handles = ax.get_legend_handles_labels()[0] + wm.get_legend_handles_labels()[0]
    ax.legend(handles=handles, loc="upper left")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
