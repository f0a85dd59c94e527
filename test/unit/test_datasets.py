"""Image folders and TUM RGB-D folders."""

from __future__ import annotations

import logging
import shutil

import cv2
import numpy as np
import pytest

from rtabmap_ros2.core import transforms
from rtabmap_ros2.core.sensor import Dataset
from rtabmap_ros2.errors import DatasetError
from rtabmap_ros2.io.datasets import ImageFolderDataset, TumRgbdDataset, associate, natural_key

NS = 1_000_000_000


def test_natural_order_and_stamps(tmp_path):
    for i in (10, 2, 1):
        img = np.full((8, 10, 3), i, np.uint8)
        cv2.imwrite(str(tmp_path / f"img{i}.png"), img)
    cv2.imwrite(str(tmp_path / "img3.pgm"), np.full((8, 10), 3, np.uint8))
    (tmp_path / "notes.txt").write_text("not an image")
    ds = ImageFolderDataset(tmp_path)
    assert isinstance(ds, Dataset)
    assert [p.name for _, p in ds.paths] == ["img1.png", "img2.png", "img3.pgm", "img10.png"]
    frames = list(ds)
    assert len(ds) == len(frames) == 4
    assert [f.stamp_ns for f in frames] == [1 * NS, 2 * NS, 3 * NS, 4 * NS]
    assert [int(f.rgb[0, 0, 0]) for f in frames] == [1, 2, 3, 10]
    assert all(f.rgb.shape == (8, 10, 3) and f.depth_m is None for f in frames)


def test_unreadable_image_is_skipped_but_keeps_numbering(tmp_path, caplog):
    for i in (1, 3):
        cv2.imwrite(str(tmp_path / f"{i}.jpg"), np.zeros((4, 4, 3), np.uint8))
    (tmp_path / "2.jpg").write_bytes(b"broken")
    ds = ImageFolderDataset(tmp_path)
    with caplog.at_level(logging.WARNING):
        items = list(ds.items())
    assert [(i, p.name, f is None) for i, p, f in items] == [(1, "1.jpg", False), (2, "2.jpg", True),
                                                             (3, "3.jpg", False)]
    assert "2.jpg" in caplog.text
    assert [f.stamp_ns for f in ds] == [1 * NS, 3 * NS]


def test_missing_or_empty_folder(tmp_path):
    with pytest.raises(DatasetError, match="does not exist"):
        ImageFolderDataset(tmp_path / "nope")
    with pytest.raises(DatasetError, match="no image"):
        ImageFolderDataset(tmp_path)


def test_natural_key():
    assert sorted(["a10", "a9", "A1", "b"], key=natural_key) == ["A1", "a9", "a10", "b"]


def test_associate_is_greedy_and_unique():
    a = np.array([100, 200, 300])
    b = np.array([105, 110, 290, 500])
    assert associate(a, b, 20) == [(0, 0), (2, 2)]


@pytest.fixture
def tum_folder(tmp_path, shared_data):
    """A 2-frame TUM folder from the fr1_xyz pair, depth stamps 10 ms after rgb, plus an orphan."""
    src = shared_data / "rgbd" / "tum_fr1_xyz_pairs" / "case_1"
    (tmp_path / "rgb").mkdir()
    (tmp_path / "depth").mkdir()
    for name in ("prev", "curr"):
        shutil.copy(src / f"img_{name}.png", tmp_path / "rgb" / f"{name}.png")
        shutil.copy(src / f"dep_{name}.png", tmp_path / "depth" / f"{name}.png")
    (tmp_path / "rgb.txt").write_text("# color images\n1305031102.175304 rgb/prev.png\n"
                                      "1305031102.211214 rgb/curr.png\n1305031109.0 rgb/orphan.png\n")
    (tmp_path / "depth.txt").write_text("# depth\n1305031102.185304 depth/prev.png\n"
                                        "1305031102.221214 depth/curr.png\n")
    gt = [(src / f"pose_{n}.txt").read_text().split() for n in ("prev", "curr")]
    (tmp_path / "groundtruth.txt").write_text(
        "# timestamp tx ty tz qx qy qz qw\n"
        f"1305031102.1753 {' '.join(gt[0])}\n1305031102.2112 {' '.join(gt[1])}\n")
    return tmp_path, gt


def test_tum_frames_depth_and_ground_truth(tum_folder):
    path, gt = tum_folder
    ds = TumRgbdDataset(path)
    assert len(ds) == 2
    frames = list(ds)
    assert [f.stamp_ns for f in frames] == [1305031102175304000, 1305031102211214000]
    f = frames[0]
    assert f.rgb.shape == (480, 640, 3) and f.depth_m.shape == (480, 640)
    raw = cv2.imread(str(path / "depth" / "prev.png"), cv2.IMREAD_UNCHANGED)
    r, c = np.argwhere(raw > 0)[0]
    assert f.depth_m[r, c] == pytest.approx(raw[r, c] / 5000.0)
    assert np.isnan(f.depth_m[raw == 0]).all()
    assert (f.camera.fx, f.camera.cx, f.camera.cy) == (525.0, 319.5, 239.5)
    f.validate()
    poses = ds.ground_truth()
    T_world_camera = transforms.from_xyz_quat_xyzw([float(v) for v in gt[0][:3]], [float(v) for v in gt[0][3:]])
    np.testing.assert_allclose(poses[0] @ ds.T_base_camera, T_world_camera, atol=1e-9)


def test_tum_intrinsics_override_and_missing_files(tum_folder, tmp_path_factory):
    path, _ = tum_folder
    f = next(iter(TumRgbdDataset(path, fx=500, fy=501, cx=320, cy=240)))
    assert (f.camera.fx, f.camera.fy, f.camera.cx, f.camera.cy) == (500, 501, 320, 240)
    (path / "depth.txt").unlink()
    with pytest.raises(DatasetError, match="depth.txt"):
        TumRgbdDataset(path)
