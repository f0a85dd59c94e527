"""Shared fixtures: paths to the shared real data, random SE(3), temporary databases."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from rtabmap_ros2.core import transforms

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = Path(os.environ.get("RTABMAP_ROS2_SHARED_DATA", REPO.parent / "shared" / "data"))


@pytest.fixture
def shared_data() -> Path:
    """The real data folder (../shared/data); tests needing it skip when it is absent."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"shared data not found at {SHARED_DATA}")
    return SHARED_DATA


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(12345)


@pytest.fixture
def random_se3(rng):
    """A function returning a random rigid transform (translation in [-2, 2] m)."""

    def make(max_translation: float = 2.0) -> np.ndarray:
        q = rng.normal(size=4)
        return transforms.from_xyz_quat_xyzw(rng.uniform(-max_translation, max_translation, 3), q)

    return make


# The 48 real frames of ../shared/data/rgbd/tum_fr1_rpy_loops (24 loop pairs of TUM fr1_rpy) in
# time order: the name says fr1, as the benchmark's folders do (tum2bag picks the calibration by it).
TUM_FOLDER_NAME = "rgbd_dataset_freiburg1_rpy_loops"


def write_tum_folder(shared: Path, out: Path, frames: int | None = None) -> Path:
    """A TUM RGB-D folder (rgb.txt, depth.txt, groundtruth.txt, rgb/, depth/) of the first ``frames``
    of the loop pairs' distinct frames in time order (all 48 by default); depth listed 5 ms after
    its colour image, ground truth at the colour stamps. Returns the folder."""
    import csv
    import shutil

    src = shared / "rgbd" / "tum_fr1_rpy_loops"
    found = {}
    with open(src / "pairs.csv", newline="") as f:
        for row in csv.DictReader(f):
            for which in ("prev", "curr"):
                stamp = Path(row[f"rgb_{which}"]).stem
                found[stamp] = src / row["case"], which
    folder = out / TUM_FOLDER_NAME
    (folder / "rgb").mkdir(parents=True)
    (folder / "depth").mkdir()
    rgb, depth, truth = ["# color images"], ["# depth maps"], ["# timestamp tx ty tz qx qy qz qw"]
    for stamp in sorted(found, key=float)[:frames]:
        case, which = found[stamp]
        shutil.copy(case / f"img_{which}.png", folder / "rgb" / f"{stamp}.png")
        shutil.copy(case / f"dep_{which}.png", folder / "depth" / f"{stamp}.png")
        depth_stamp = f"{float(stamp) + 0.005:.6f}"
        rgb.append(f"{stamp} rgb/{stamp}.png")
        depth.append(f"{depth_stamp} depth/{stamp}.png")
        truth.append(f"{stamp} {(case / f'pose_{which}.txt').read_text().strip()}")
    for name, lines in (("rgb.txt", rgb), ("depth.txt", depth), ("groundtruth.txt", truth)):
        (folder / name).write_text("\n".join(lines) + "\n")
    return folder


@pytest.fixture
def tum_rpy_folder(shared_data, tmp_path_factory):
    """A function making a TUM RGB-D folder of the first ``frames`` real fr1_rpy frames (:func:`write_tum_folder`)."""
    return lambda frames=None: write_tum_folder(shared_data, tmp_path_factory.mktemp("tum"), frames)
