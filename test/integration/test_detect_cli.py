"""``rtabmap-ros2 detect`` in a subprocess on a small generated sequence (issue 2's command)."""

from __future__ import annotations

import csv
import subprocess
import sys

import pytest
import yaml

from rtabmap_ros2.sim.sequence import make_sequence, write_sequence

N_IMAGES = 60
UNREADABLE = 5
REQUIRED = ["image", "location_id", "loop_closure_id", "highest_hypothesis_id", "highest_hypothesis_value",
            "process_time_ms", "total_time_ms", "wm_size", "vocabulary_size"]
TIMEOUT_S = 600


def detect(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "rtabmap_ros2", "detect", *map(str, args)],
                          capture_output=True, text=True, timeout=TIMEOUT_S)


@pytest.fixture(scope="module")
def sequence_dir(tmp_path_factory):
    folder = tmp_path_factory.mktemp("seq")
    write_sequence(make_sequence(N_IMAGES, seed=3, segment_length=(12, 25)), folder)
    gt = folder.parent / f"{folder.name}_gt.png"
    (folder / "ground_truth.png").rename(gt)
    (folder / f"{UNREADABLE}.jpg").write_bytes(b"not a jpeg at all")  # garbage named like an image
    return folder, gt


@pytest.mark.slow
def test_detect_writes_one_row_per_image_and_evaluates(sequence_dir, tmp_path):
    folder, gt = sequence_dir
    out = tmp_path / "out"
    out.mkdir()
    (out / "database.db").write_bytes(b"stale")  # deleted first, as --help says
    result = detect(folder, "--out", out, "--ground-truth", gt, "--set", "Mem/STMSize=10", "--no-progress")
    assert result.returncode == 0, result.stderr[-3000:]
    # The unreadable image is named in a warning and the run continues.
    assert f"{UNREADABLE}.jpg" in result.stderr and "WARNING" in result.stderr
    with open(out / "detections.csv", newline="") as f:
        reader = csv.DictReader(f)
        assert reader.fieldnames[:len(REQUIRED)] == REQUIRED
        rows = list(reader)
    assert [r["image"] for r in rows] == [f"{k}.jpg" for k in range(1, N_IMAGES + 1)]  # natural order
    for k, row in enumerate(rows, start=1):
        location = int(row["location_id"])
        # 0: unreadable or bad; an older location when rehearsal merged this image into it.
        assert location == k or (location < k and int(row["merged_id"]) == k) or location == 0
        assert 0 <= int(row["loop_closure_id"]) < k and 0 <= int(row["highest_hypothesis_id"]) < k
        assert 0.0 <= float(row["highest_hypothesis_value"]) <= 1.0
        # The detection's diagnostics (issue 32), beside RTAB-Map's reference_stats.csv.
        assert 0.0 <= float(row["rehearsal_similarity"]) <= 1.0
        assert 0.0 <= float(row["new_location_probability"]) <= 1.0
        assert float(row["likelihood_max"]) >= float(row["likelihood_mean"]) >= 0.0
    assert rows[UNREADABLE - 1]["location_id"] == "0" and rows[UNREADABLE - 1]["status"] == "unreadable"
    assert sum(int(r["location_id"]) == k for k, r in enumerate(rows, 1)) >= N_IMAGES - 3
    assert sum(int(r["words_extracted"]) > 100 for r in rows) >= N_IMAGES - 3
    assert any(int(r["likelihood_nonzero"]) > 0 for r in rows)
    assert max(int(r["wm_size"]) for r in rows) > 0
    assert (out / "database.db").stat().st_size > 1000
    assert (out / "timing.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    used = yaml.safe_load((out / "params.yaml").read_text())
    assert used["memory"]["stm_size"] == 10
    assert used["memory"]["time_threshold_ms"] == 700.0  # paper defaults, not config/rtabmap.yaml
    assert "[merged] precision" in result.stdout and "[strict] precision" in result.stdout
    assert "best recall at 100 % precision" in result.stdout


def test_missing_folder_is_a_clear_error(tmp_path):
    result = detect(tmp_path / "nowhere", "--out", tmp_path / "out")
    assert result.returncode == 2
    assert "error:" in result.stderr and "nowhere" in result.stderr


def test_empty_folder_is_a_clear_error(tmp_path):
    (tmp_path / "empty").mkdir()
    result = detect(tmp_path / "empty", "--out", tmp_path / "out")
    assert result.returncode == 2 and "holds no image" in result.stderr


def test_bad_parameter_is_a_clear_error(sequence_dir, tmp_path):
    folder, _ = sequence_dir
    result = detect(folder, "--out", tmp_path / "out", "--set", "Mem/STMSize=zero")
    assert result.returncode == 2 and "Mem/STMSize" in result.stderr
    result = detect(folder, "--out", tmp_path / "out", "--set", "memory.no_such=1")
    assert result.returncode == 2 and "unknown parameter" in result.stderr


def test_ground_truth_of_another_size_is_a_clear_error(sequence_dir, tmp_path):
    import cv2
    import numpy as np

    folder, _ = sequence_dir
    wrong = tmp_path / "gt.png"
    cv2.imwrite(str(wrong), np.zeros((10, 10), np.uint8))
    result = detect(folder, "--out", tmp_path / "out", "--ground-truth", wrong)
    assert result.returncode == 2 and f"{N_IMAGES} images" in result.stderr
    assert not (tmp_path / "out" / "detections.csv").exists()


def test_merged_policy_and_recall_at_full_precision():
    import numpy as np

    from rtabmap_ros2.io.evaluation import evaluate_rows, merged_images, pr_curve, recall_at_full_precision

    # Image 5 revisits image 2; image 2 was merged into location 1 (the older one stays), 4 into 3.
    gt = np.zeros((6, 6), bool)
    gt[4, 1] = gt[5, 1] = True
    assert merged_images([(1, 0), (1, 2), (3, 0), (3, 4)]) == {1: (2,), 3: (4,)}
    rows = [dict(location_id=k, merged_id=m, loop_closure_id=lc, highest_hypothesis_id=h, highest_hypothesis_value=v)
            for k, m, lc, h, v in [(1, 0, 0, 0, 0.0), (1, 2, 0, 0, 0.0), (3, 0, 0, 1, 0.05), (3, 4, 0, 1, 0.08),
                                   (5, 0, 1, 1, 0.6), (6, 0, 3, 3, 0.3)]]
    result = evaluate_rows(gt, rows)
    assert result["merged"]["true_positives"] == 1 and result["merged"]["accepted"] == 2
    assert result["strict"]["true_positives"] == 0  # GT[5, 1] is not set: only image 2 merged into 1 is
    assert result["merged"]["recall"] == 0.5
    # Threshold 0.6 accepts only 5 -> 1 (right): recall 0.5 at 100 % precision.
    assert result["merged"]["recall_at_100_precision"] == 0.5
    assert result["merged"]["threshold_at_100_precision"] == 0.6
    curve = pr_curve(gt, [r["highest_hypothesis_id"] for r in rows], [r["highest_hypothesis_value"] for r in rows])
    assert recall_at_full_precision(curve) == (0.0, None)  # strict: nothing right
