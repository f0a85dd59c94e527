"""Simulated building: sensors agree with the ground-truth geometry, odometry drifts, sessions revisit."""

from __future__ import annotations

import csv

import cv2
import numpy as np
import pytest

from rtabmap_ros2.core import transforms
from rtabmap_ros2.sim import (
    SensorRig, build_world, find_revisits, make_sessions, render_frame, render_rgbd, render_scan, simulate,
)
from rtabmap_ros2.sim.render import DEPTH_MAX_M, LASER_NOISE_SIGMA_M, T_BASE_CAMERA
from rtabmap_ros2.sim.robot import ODOM_TRANSLATION_SIGMA, ODOM_YAW_PER_METRE_SIGMA
from rtabmap_ros2.sim.world import PLAIN, POSTER, WALL_HEIGHT_M

NOISE_FREE = SensorRig(laser_noise_sigma_m=0.0, depth_noise_coeff=0.0, pixel_noise_sigma=0.0)


@pytest.fixture(scope="module")
def world():
    return build_world(seed=0)


@pytest.fixture(scope="module")
def sessions(world):
    return make_sessions(world)


def test_laser_ranges_match_a_known_corridor(world):
    # West corridor (walls at x = -1.1 and x = 1.1), robot at (0, 5) facing north (+y).
    T = transforms.from_xy_yaw(0.0, 5.0, np.pi / 2)
    scan = render_scan(world, T, None, NOISE_FREE)
    angles = scan.angles
    left = np.argmin(np.abs(angles - np.pi / 2))     # towards -x
    right = np.argmin(np.abs(angles + np.pi / 2))    # towards +x
    assert scan.ranges[left] == pytest.approx(1.1, abs=1e-4)
    assert scan.ranges[right] == pytest.approx(1.1, abs=1e-4)
    # The beam at angle a (left of forward) has world direction pi/2 + a: it meets x = -1.1 at 1.1 / sin(a).
    diag = np.argmin(np.abs(angles - np.pi / 4))
    assert scan.ranges[diag] == pytest.approx(1.1 / np.sin(angles[diag]), abs=1e-4)
    noisy = render_scan(world, T, np.random.default_rng(1))
    assert abs(noisy.ranges[left] - 1.1) < 5 * LASER_NOISE_SIGMA_M


def test_laser_returns_lie_on_walls(world, sessions):
    rng = np.random.default_rng(3)
    for i in rng.choice(len(sessions[0]), 5, replace=False):
        T = sessions[0].T_world_base[i]
        scan = render_scan(world, T, None, NOISE_FREE)
        p_base = scan.points_base()
        assert len(p_base) > 300
        p_world = p_base @ T[:2, :2].T + T[:2, 3]
        assert world.distance_to_walls(p_world).max() < 1e-6
        # Nothing closer: the segment from the laser to just before each hit is free space.
        for frac in (0.25, 0.5, 0.97):
            inner = T[:2, 3] + frac * (p_world - T[:2, 3])
            assert world.is_free(inner).mean() > 0.99


def test_depth_back_projects_onto_walls_floor_and_ceiling(world, sessions):
    cam = NOISE_FREE.camera
    v, u = np.mgrid[0:cam.height:7, 0:cam.width:7]
    uv = np.stack([u.ravel(), v.ravel()], axis=1).astype(np.float64)
    for i in (10, 150, 250):
        T = sessions[1].T_world_base[i]
        _, depth = render_rgbd(world, T, None, NOISE_FREE)
        z = depth[uv[:, 1].astype(int), uv[:, 0].astype(int)]
        ok = np.isfinite(z)
        assert ok.mean() > 0.5
        p_cam = cam.back_project(uv[ok], z[ok])
        T_world_cam = T @ T_BASE_CAMERA
        p = p_cam @ T_world_cam[:3, :3].T + T_world_cam[:3, 3]
        on_floor = np.abs(p[:, 2]) < 1e-6
        on_ceiling = np.abs(p[:, 2] - WALL_HEIGHT_M) < 1e-6
        on_wall = ~(on_floor | on_ceiling)
        assert on_wall.sum() > 100
        assert world.distance_to_walls(p[on_wall, :2]).max() < 0.02
        assert ((p[on_wall, 2] >= -1e-6) & (p[on_wall, 2] <= WALL_HEIGHT_M + 1e-6)).all()
        # With Kinect noise (sigma 1.5e-3 z^2), wall points stay near the walls.
        _, noisy = render_rgbd(world, T, np.random.default_rng(i))
        zn = noisy[uv[:, 1].astype(int), uv[:, 0].astype(int)][ok][on_wall]
        both = np.isfinite(zn)
        err = np.abs(zn[both] - z[ok][on_wall][both])
        assert np.median(err / (1.5e-3 * z[ok][on_wall][both] ** 2)) < 1.5
        assert np.nanmax(noisy) <= DEPTH_MAX_M


def test_laser_and_depth_agree(world, sessions):
    # The depth row at the laser height (0.3 m) sees the same wall as the laser beams.
    T = sessions[2].T_world_base[40]
    _, depth = render_rgbd(world, T, None, NOISE_FREE)
    scan = render_scan(world, T, None, NOISE_FREE)
    cam = NOISE_FREE.camera
    cols = np.arange(0, cam.width, 20)
    hits_base = scan.points_base()
    compared = 0
    for c in cols:
        # Find the depth of column c at the row where the wall point is at laser height.
        col = depth[:, c]
        rows = np.arange(cam.height)
        heights = 0.5 - (rows - cam.cy) / cam.fy * col
        good = np.isfinite(col) & (np.abs(heights - 0.3) < 0.02)
        if not good.any():
            continue
        r = rows[good][0]
        p_cam = cam.back_project(np.array([[c, r]], float), np.array([col[r]]))
        p_base = (T_BASE_CAMERA[:3, :3] @ p_cam[0] + T_BASE_CAMERA[:3, 3])[:2]
        assert np.min(np.linalg.norm(hits_base - p_base, axis=1)) < 0.05
        compared += 1
    assert compared >= 10


def test_odometry_drifts_but_steps_match_ground_truth(sessions):
    s = sessions[0]
    assert np.allclose(s.T_odom_base[0], np.eye(4))
    T_start = transforms.inverse(s.T_world_base[0])
    final_err = np.linalg.norm((T_start @ s.T_world_base[-1])[:2, 3] - s.T_odom_base[-1][:2, 3])
    assert final_err > 0.3, "odometry should drift over a 140 m session"
    for k in range(1, len(s)):
        gt = transforms.relative(s.T_world_base[k - 1], s.T_world_base[k])
        od = transforms.relative(s.T_odom_base[k - 1], s.T_odom_base[k])
        d = np.linalg.norm(gt[:2, 3])
        assert np.linalg.norm(od[:2, 3] - gt[:2, 3]) <= 6 * ODOM_TRANSLATION_SIGMA * d + 1e-9
        dyaw = transforms.to_xy_yaw(transforms.relative(gt, od))[2]
        assert abs(dyaw) <= 6 * ODOM_YAW_PER_METRE_SIGMA * d + 0.03 * abs(transforms.to_xy_yaw(gt)[2]) + 0.01
    cov = s.odom_covariance
    assert cov.shape == (6, 6) and np.all(np.diag(cov) > 0)


def test_sessions_size_stamps_and_clearance(world, sessions):
    assert len(sessions) == 5
    total_m = sum(s.length_m for s in sessions)
    total_frames = sum(len(s) for s in sessions)
    assert 650 < total_m < 850
    assert 1500 <= total_frames <= 2000
    for prev, s in zip(sessions[:-1], sessions[1:]):
        assert s.stamps_ns[0] > prev.stamps_ns[-1]
    starts = np.array([s.T_world_base[0][:2, 3] for s in sessions])
    assert min(np.linalg.norm(a - b) for i, a in enumerate(starts) for b in starts[i + 1:]) > 5.0
    for s in sessions:
        assert np.all(np.diff(s.stamps_ns) == 1_000_000_000)
        assert world.distance_to_walls(s.T_world_base[:, :2, 3]).min() > 0.3
        speeds = np.linalg.norm(np.diff(s.T_world_base[:, :2, 3], axis=0), axis=1)
        assert speeds.max() < 0.6
        assert (speeds < 0.01).sum() >= 3, "the robot should stop sometimes"


def test_each_session_revisits_an_earlier_one(sessions, world):
    rows = find_revisits(sessions)
    for k in range(2, 6):
        mine = [r for r in rows if r["session"] == k]
        assert any(r["revisits_session"] < k for r in mine), f"session {k} revisits no earlier session"
    for r in rows:
        assert r["distance_m"] <= 1.0
    small = make_sessions(world, small=True)
    assert len(small) == 2 and all(30 <= len(s) <= 70 for s in small)
    assert any(r["session"] == 2 and r["revisits_session"] == 1 for r in find_revisits(small))


def test_deterministic_for_a_seed(world, sessions):
    other = build_world(seed=0)
    again = make_sessions(other, sessions=2)
    assert np.array_equal(again[1].T_odom_base, sessions[1].T_odom_base)
    a = render_frame(world, sessions[1], 17)
    b = render_frame(other, again[1], 17)
    assert np.array_equal(a.rgb, b.rgb)
    assert np.array_equal(a.depth_m, b.depth_m, equal_nan=True)
    assert np.array_equal(a.scan.ranges, b.scan.ranges)
    different = build_world(seed=1)
    c = render_frame(different, make_sessions(different, sessions=2)[1], 17)
    assert not np.array_equal(a.rgb, c.rgb)


def _facing_view(world, wall: int, distance: float) -> np.ndarray | None:
    p0, p1 = world.p0[wall], world.p1[wall]
    length = np.linalg.norm(p1 - p0)
    e = (p1 - p0) / length
    normal = np.array([e[1], -e[0]])  # into the free space
    rect = world.poster_rect[wall]
    u = 0.5 * (rect[0] + rect[1]) if np.isfinite(rect[0]) else 0.5 * length
    base = p0 + u * e + normal * (distance + 0.1)  # camera 0.1 m ahead of the base
    if not world.is_free(base[None])[0] or world.distance_to_walls(base[None])[0] < distance - 1e-6:
        return None
    yaw = np.arctan2(-normal[1], -normal[0])
    rgb, _ = render_rgbd(world, transforms.from_xy_yaw(base[0], base[1], yaw), None, NOISE_FREE)
    return rgb


def test_plain_walls_have_few_orb_features_and_posters_many(world):
    orb = cv2.ORB_create(nfeatures=500)
    counts = {PLAIN: [], POSTER: []}
    for wall in np.argsort(-world.lengths):
        kind = int(world.kind[wall])
        if kind not in counts or len(counts[kind]) >= 8 or world.lengths[wall] < 3.0:
            continue
        rgb = _facing_view(world, wall, 1.2)
        if rgb is None:
            continue
        roi = cv2.cvtColor(rgb[30:230, 140:500], cv2.COLOR_RGB2GRAY)  # the wall at 0.5-1 m height
        counts[kind].append(len(orb.detect(roi, None)))
    assert len(counts[PLAIN]) >= 4 and len(counts[POSTER]) >= 4
    assert np.median(counts[PLAIN]) < 15
    assert np.median(counts[POSTER]) > 60


def test_simulate_writes_readable_bags(tmp_path):
    from rtabmap_ros2.io.bag import BagDataset

    summary = simulate(tmp_path / "sim", sessions=1, seed=0, small=True, jobs=1)
    out = tmp_path / "sim"
    assert summary.total_frames == summary.sessions[0]["frames"]
    for name in ("ground_truth.txt", "loops.csv", "world.png", "world.json"):
        assert (out / name).is_file()
    gt = np.loadtxt(out / "ground_truth.txt")
    frames = list(BagDataset(out / "session_1"))
    assert len(frames) == len(gt) == summary.total_frames
    stamps_bag = np.array([f.stamp_ns for f in frames])
    assert np.array_equal(stamps_bag, np.round(gt[:, 0] * 1e9).astype(np.int64))
    first = frames[0]
    assert np.allclose(first.T_odom_base, np.eye(4), atol=1e-9)
    assert first.rgb.shape == (480, 640, 3) and first.depth_m.shape == (480, 640)
    assert first.scan is not None and first.camera.fx == pytest.approx(525.0)
    assert np.allclose(first.camera.T_base_camera, T_BASE_CAMERA, atol=1e-6)
    # Depth survives the bag (mm quantisation) and matches a fresh render of the same frame.
    world = build_world(seed=0)
    ref = render_frame(world, make_sessions(world, sessions=1, small=True)[0], 0)
    both = np.isfinite(ref.depth_m) & np.isfinite(first.depth_m) & (first.depth_m > 0)
    assert both.mean() > 0.5
    assert np.abs(first.depth_m[both] - ref.depth_m[both]).max() < 2e-3
    with open(out / "loops.csv") as f:
        header = next(csv.reader(f))
    assert header == ["session", "frame_index", "stamp", "revisits_session", "revisits_frame_index",
                      "revisits_stamp", "distance_m"]
