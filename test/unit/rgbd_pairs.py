"""Test helper: real RGB-D pairs (../shared/data/rgbd) made into signatures the way the SLAM path
makes them (used by test_registration.py and test_loop_validation.py)."""

from __future__ import annotations

import cv2
import numpy as np

from rtabmap_ros2.core import transforms
from rtabmap_ros2.core.features import FeatureExtractor
from rtabmap_ros2.core.params import Params
from rtabmap_ros2.core.registration import words_3d
from rtabmap_ros2.core.sensor import CameraModel
from rtabmap_ros2.core.signature import Signature
from rtabmap_ros2.core.vocabulary import Vocabulary

TUM_DEPTH_SCALE = 5000.0  # depth PNG value / 5000 = metres


def load_tum(folder, which):
    """Grey image, depth (m, NaN invalid) and ground-truth pose of the ``prev`` or ``curr`` frame."""
    gray = cv2.imread(str(folder / f"img_{which}.png"), cv2.IMREAD_GRAYSCALE)
    depth = cv2.imread(str(folder / f"dep_{which}.png"), cv2.IMREAD_UNCHANGED).astype(np.float32) / TUM_DEPTH_SCALE
    depth[depth == 0] = np.nan
    v = np.loadtxt(folder / f"pose_{which}.txt")
    return gray, depth, transforms.from_xyz_quat_xyzw(v[:3], v[3:])


def pair_camera(folder) -> CameraModel:
    K = np.loadtxt(folder.parent / "kinect_params.txt")
    return CameraModel(K[0, 0], K[1, 1], K[0, 2], K[1, 2], 640, 480)


def product_signatures(folder, params: Params):
    """A real RGB-D pair as the SLAM path makes it (features, the vocabulary with the older frame
    quantised first, 3D words from depth): ``(new, old, (descriptors new, old), T_new_old truth)``."""
    camera = pair_camera(folder)
    extractor = FeatureExtractor(params.features)
    vocabulary = Vocabulary(params.vocabulary, extractor.binary, background_rebuild=False)
    made, poses = [], []
    for node, which in ((1, "prev"), (2, "curr")):
        bgr = cv2.imread(str(folder / f"img_{which}.png"))
        _, depth, pose = load_tum(folder, which)
        features = extractor.extract(cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB), depth)
        word_ids, _ = vocabulary.quantize(features.descriptors)
        made.append(Signature(node, 1, 0, word_ids, features.keypoints, words_3d(features.keypoints, depth, camera),
                              camera=camera))
        poses.append(pose)
    old, new = made
    descriptors = (vocabulary.descriptors_of(new.word_ids), vocabulary.descriptors_of(old.word_ids))
    return new, old, descriptors, transforms.relative(poses[1], poses[0])
