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
