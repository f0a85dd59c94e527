"""Occupancy grid (ray casting, hit/miss counting), point cloud assembly, voxel filter, PLY."""

from __future__ import annotations

from dataclasses import replace

import cv2
import numpy as np
import pytest

from rtabmap_ros2.core import transforms
from rtabmap_ros2.core.grid import (FREE, OCCUPIED, UNKNOWN, GridAccumulator, assemble_cloud, build_grid,
                                    depth_cells, depth_points, points_cells, scan_conflict, voxel_filter,
                                    write_ply)
from rtabmap_ros2.core.local_grid import LocalGrid
from rtabmap_ros2.io.bag import DEFAULT_T_BASE_CAMERA
from rtabmap_ros2.core.params import GridParams
from rtabmap_ros2.core.sensor import CameraModel, LaserScan
from rtabmap_ros2.errors import ParameterError

HALF = 2.0  # half side of the square room (m)
RES = 0.05


def room_scan(x: float, y: float, n: int = 720) -> LaserScan:
    """Scan of the square room [-HALF, HALF]^2 taken from (x, y) with yaw 0."""
    angles = -np.pi + 2 * np.pi * np.arange(n) / n
    c, s = np.cos(angles), np.sin(angles)
    with np.errstate(divide="ignore"):
        tx = np.where(c > 0, (HALF - x) / c, np.where(c < 0, (-HALF - x) / c, np.inf))
        ty = np.where(s > 0, (HALF - y) / s, np.where(s < 0, (-HALF - y) / s, np.inf))
    return LaserScan(np.minimum(tx, ty), -np.pi, 2 * np.pi / n, 0.1, 10.0)


def test_square_room_walls_free_inside_unknown_outside():
    grid = build_grid({1: transforms.identity()}, {1: room_scan(0.0, 0.0)}, GridParams(resolution=RES))
    # Walls: occupied within one cell of the wall line.
    t = np.linspace(-HALF + 0.2, HALF - 0.2, 40)
    for wall in ([np.full_like(t, HALF), t], [np.full_like(t, -HALF), t], [t, np.full_like(t, HALF)],
                 [t, np.full_like(t, -HALF)]):
        pts = np.stack(wall, axis=1)
        near = np.stack([grid.value_at(pts + d) for d in
                         ([0, 0], [RES, 0], [-RES, 0], [0, RES], [0, -RES])], axis=0)
        assert np.all((near == OCCUPIED).any(axis=0)), "a wall point has no occupied cell within one cell"
    # Inside: free (away from the walls).
    g = np.linspace(-HALF + 0.3, HALF - 0.3, 15)
    inside = np.stack(np.meshgrid(g, g), axis=-1).reshape(-1, 2)
    assert np.all(grid.value_at(inside) == FREE)
    # Outside the room: never observed.
    outside = np.array([[HALF + 0.5, 0.0], [0.0, -HALF - 0.5], [HALF + 1.0, HALF + 1.0]])
    assert np.all(grid.value_at(outside) == UNKNOWN)
    occupied = np.argwhere(grid.data == OCCUPIED)
    # nav_msgs layout: row = y index. Top wall (y = +HALF) cells are at the highest rows.
    assert occupied[:, 0].max() * RES + grid.origin_xy[1] > HALF - 2 * RES


def test_two_poses_combine():
    # Two 170-degree scans (front only) from opposite headings cover the two halves of the room.
    full = room_scan(0.0, 0.0)
    front = np.abs(full.angles) < np.radians(85)
    half = LaserScan(np.asarray(full.ranges)[front], float(full.angles[front][0]), full.angle_increment, 0.1, 10.0)
    params = GridParams(resolution=RES, range_max=5.0)
    one = build_grid({1: transforms.identity()}, {1: half}, params)
    two = build_grid({1: transforms.identity(), 2: transforms.from_xy_yaw(0, 0, np.pi)}, {1: half, 2: half}, params)
    left, right = np.array([[-HALF, 0.5]]), np.array([[HALF, 0.5]])
    near = lambda g, p: (np.stack([g.value_at(p + [d, 0]) for d in (-RES, 0, RES)]) == OCCUPIED).any()
    assert near(one, right) and not near(one, left)
    assert near(two, right) and near(two, left)


def test_a_scan_taken_back_leaves_the_grid_of_the_others():
    """weight -1 undoes an add at the same pose exactly: the local grid moves a node by taking its
    scan back at the old pose and casting it at the new one, which must equal casting the scans
    at their current poses from scratch."""
    params = GridParams(resolution=RES, range_max=5.0)
    scans = {1: room_scan(0.0, 0.0), 2: room_scan(0.5, -0.3), 3: room_scan(-0.8, 0.6)}
    old = {1: transforms.identity(), 2: transforms.from_xy_yaw(0.5, -0.3, 0.0), 3: transforms.from_xy_yaw(-0.8, 0.6, 0.0)}
    new = dict(old)
    new[2] = transforms.from_xy_yaw(0.55, -0.25, 0.1)   # moved (as after a loop closure)
    accumulator = GridAccumulator(params)
    for n in old:
        accumulator.add(old[n], scans[n])
    # A node far away first: the canvas grows (its corner moves) between a scan's add and take-back.
    scans[4] = room_scan(0.0, 0.0)
    old[4] = new[4] = transforms.from_xy_yaw(-6.0, -5.0, 0.0)
    accumulator.add(old[4], scans[4])
    accumulator.add(old[2], scans[2], weight=-1)
    accumulator.add(new[2], scans[2])
    accumulator.add(old[3], scans[3], weight=-1)          # node 3 left the local map
    del new[3]
    incremental = accumulator.grid()
    from_scratch = GridAccumulator(params)   # the same first scan: the same cell boundaries
    for n in (1, 2, 4):
        from_scratch.add(new[n], scans[n])
    scratch = from_scratch.grid()
    # Same cell values everywhere (the empty margin around the observed cells may be cropped by
    # the canvas edge, so the arrays are compared at map points, every cell centre).
    g = np.arange(-10.0, 5.0, RES) + RES / 2
    points = np.stack(np.meshgrid(g, g), axis=-1).reshape(-1, 2)
    assert np.array_equal(incremental.value_at(points), scratch.value_at(points))
    stale = build_grid(old, scans, params)
    assert not np.array_equal(incremental.value_at(points), stale.value_at(points))


def test_no_return_beams_clear_to_range_max():
    ranges = np.full(90, np.inf)
    scan = LaserScan(ranges, -np.pi / 4, np.pi / 2 / 90, 0.1, 4.0)
    grid = build_grid({1: transforms.identity()}, {1: scan}, GridParams(resolution=RES, range_max=2.0))
    assert grid.value_at(np.array([[1.5, 0.0]]))[0] == FREE
    assert grid.value_at(np.array([[2.5, 0.0]]))[0] == UNKNOWN
    assert not (grid.data == OCCUPIED).any()


def test_to_image_levels():
    grid = build_grid({1: transforms.identity()}, {1: room_scan(0.0, 0.0)}, GridParams(resolution=RES))
    img = grid.to_image()
    assert img.dtype == np.uint8 and set(np.unique(img)) <= {0, 205, 254}
    assert (img == 0).sum() == (grid.data == OCCUPIED).sum()


def test_voxel_filter_removes_duplicates(rng):
    pts = rng.uniform(0, 1, (100, 3))
    dup = np.concatenate([pts, pts + 1e-4, pts])
    cols = np.tile(np.array([[10, 20, 30]], np.uint8), (len(dup), 1))
    out, out_cols = voxel_filter(dup, cols, 0.01)
    assert len(out) <= 110 and len(out) >= 90
    assert np.all(out_cols == [10, 20, 30])


def test_assemble_cloud_and_ply(tmp_path):
    cam = CameraModel(100.0, 100.0, 31.5, 23.5, 64, 48)
    depth = np.full((48, 64), 2.0, np.float32)
    depth[:10] = np.nan
    rgb = np.zeros((48, 64, 3), np.uint8)
    rgb[..., 0] = 200
    pts, cols = assemble_cloud({1: transforms.from_xy_yaw(1.0, 0, 0)}, {1: depth}, {1: rgb}, {1: cam},
                               decimation=2, voxel=0.0)
    assert len(pts) == 32 * 19 and np.allclose(pts[:, 2], 2.0) and np.all(cols[:, 0] == 200)
    assert np.isclose(pts[:, 0].mean(), 1.0, atol=0.02)
    path = tmp_path / "cloud.ply"
    write_ply(path, pts, cols)
    raw = path.read_bytes()
    header, body = raw.split(b"end_header\n", 1)
    lines = header.decode().splitlines()
    assert lines[0] == "ply" and "format binary_little_endian 1.0" in lines
    n = int(next(l for l in lines if l.startswith("element vertex")).split()[-1])
    assert n == len(pts) and len(body) == n * 15
    rec = np.frombuffer(body, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("r", "u1"), ("g", "u1"), ("b", "u1")])
    assert np.allclose(rec["z"], 2.0) and np.all(rec["r"] == 200)


def test_the_cloud_of_a_raw_image_lies_on_its_pixels_true_rays():
    """Depth images that are not rectified (a CameraInfo's D, P = K): each point lies on its pixel's
    undistorted ray, so the cloud projected through the lens falls back on the pixels it came from
    (the grid's depth cells back-project the same way)."""
    fr1 = (0.2624, -0.9531, -0.0054, 0.0026, 1.1633)
    K = np.array([[517.3, 0, 318.6], [0, 516.5, 255.3], [0, 0, 1.0]])
    raw = CameraModel(517.3, 516.5, 318.6, 255.3, 640, 480, distortion=fr1)
    depth = np.full((480, 640), 2.0, np.float32)   # a wall facing the camera, 2 m along its axis
    pts, _ = assemble_cloud({1: transforms.identity()}, {1: depth}, {}, {1: raw}, decimation=40, voxel=0.0)
    rows, cols = np.mgrid[0:480:40, 0:640:40]
    pixels = np.stack([cols.ravel(), rows.ravel()], axis=1).astype(np.float64)
    seen, _ = cv2.projectPoints(pts.astype(np.float64), np.zeros(3), np.zeros(3), K, np.array(fr1))
    np.testing.assert_allclose(seen.reshape(-1, 2), pixels, atol=0.1)   # OpenCV's iterative undistortion
    pinhole, _ = assemble_cloud({1: transforms.identity()}, {1: depth}, {}, {1: replace(raw, distortion=())},
                                decimation=40, voxel=0.0)
    assert np.abs(pinhole - pts).max() > 0.02   # read as a pinhole's, the corners are centimetres off


def test_scan_conflict_tells_a_wrong_alignment_from_the_right_one(rng):
    """Two sessions' scans of the square room: placed right (up to 3 cm / 0.3 deg of pose error)
    they agree; moved 0.5 or 1 m, the walls of one fall in the other's free space."""
    a = [(transforms.from_xy_yaw(x, y, 0), room_scan(x, y)) for x, y in ((-1, -1), (0, 0), (1, 0.5))]
    places = ((-0.5, 0.5), (0.5, -0.5), (1.0, 1.0))

    def b(shift: float):
        return [(transforms.from_xy_yaw(x + shift + rng.normal(0, 0.03), y + rng.normal(0, 0.03),
                                        rng.normal(0, 0.005)), room_scan(x, y)) for x, y in places]

    right, cells = scan_conflict(a, b(0.0), 0.2, 10.0, 180)
    assert cells > 200 and right < 0.02
    for shift in (0.5, 1.0):
        assert scan_conflict(a, b(shift), 0.2, 10.0, 180)[0] > 0.2
    # Nothing observed in common: no evidence either way.
    assert scan_conflict(a, [(transforms.from_xy_yaw(100, 0, 0), room_scan(0, 0))], 0.2, 10.0, 180) == (0.0, 0)


# -- depth images (grid.sensor depth) --------------------------------------------------------------

WALL_X = 2.02          # a wall across the view, 2.02 m ahead of the camera (m; mid-cell)
CAMERA_HEIGHT = 1.0    # the camera's height above the floor (m): the base at z = 1, looking along x
DEPTH_CAMERA = CameraModel(80.0, 80.0, 79.5, 59.5, 160, 120, np.array(DEFAULT_T_BASE_CAMERA))  # +-37 deg down


def wall_and_floor_depth(camera: CameraModel = DEPTH_CAMERA, height: float = CAMERA_HEIGHT) -> np.ndarray:
    """HxW depth (m) of a camera ``height`` above a floor (z = 0), looking along +x at a wall x = WALL_X."""
    rows, cols = np.mgrid[0:camera.height, 0:camera.width]
    down = (rows - camera.cy) / camera.fy           # optical y (down) per unit of depth
    with np.errstate(divide="ignore"):
        floor = np.where(down > 0, height / down, np.inf)   # depth at which the ray meets z = 0
    return np.minimum(floor, WALL_X).astype(np.float32)


def test_depth_cells_put_the_wall_in_obstacles_and_the_floor_in_ground():
    T_map_base = transforms.from_xy_yaw(0.0, 0.0, 0.0, z=CAMERA_HEIGHT)
    cells = depth_cells(T_map_base, wall_and_floor_depth(), DEPTH_CAMERA, GridParams(resolution=RES))
    np.testing.assert_allclose(cells.origin_xy, (0.0, 0.0), atol=1e-9)
    # The wall (above the ground height, 1 cell) lies in the cell column holding it, [2.00, 2.05) m.
    assert len(cells.obstacles_xy) and np.allclose(cells.obstacles_xy[:, 0], 2.025)
    # The floor seen between the camera and the wall: ground, never in an obstacle's cell.
    assert len(cells.ground_xy) and cells.ground_xy[:, 0].max() < WALL_X + RES
    obstacle = {tuple(c) for c in np.round(cells.obstacles_xy / RES, 3).tolist()}
    assert not obstacle & {tuple(c) for c in np.round(cells.ground_xy / RES, 3).tolist()}


def test_depth_cells_height_limits_and_range():
    T_map_base = transforms.from_xy_yaw(0.0, 0.0, 0.0, z=CAMERA_HEIGHT)
    depth = wall_and_floor_depth()
    full = depth_cells(T_map_base, depth, DEPTH_CAMERA, GridParams(resolution=RES))
    # Obstacles only up to 0.5 m: the wall's upper part is dropped, its lower part stays.
    low = depth_cells(T_map_base, depth, DEPTH_CAMERA, GridParams(resolution=RES, max_obstacle_height=0.5))
    assert 0 < len(low.obstacles_xy) <= len(full.obstacles_xy)
    assert len(depth_cells(T_map_base, depth, DEPTH_CAMERA, GridParams(resolution=RES, max_obstacle_height=0.06))
               .obstacles_xy) < len(low.obstacles_xy)
    # Ground from 0.02 m only: the floor (z = 0) is dropped.
    assert not len(depth_cells(T_map_base, depth, DEPTH_CAMERA, GridParams(resolution=RES, min_ground_height=0.02,
                                                                          max_ground_height=0.05)).ground_xy)
    # Depth beyond range_max is not used: with 1.5 m, no wall and only the near floor.
    near = depth_cells(T_map_base, depth, DEPTH_CAMERA, GridParams(resolution=RES, range_max=1.5))
    assert not len(near.obstacles_xy) and near.ground_xy[:, 0].max() < 1.5


def test_a_depth_image_makes_the_wall_occupied_and_the_floor_before_it_free():
    params = GridParams(resolution=RES, depth_decimation=1)
    acc = GridAccumulator(params)
    T_map_base = transforms.from_xy_yaw(0.0, 0.0, 0.0, z=CAMERA_HEIGHT)
    acc.add_depth(depth_cells(T_map_base, wall_and_floor_depth(), DEPTH_CAMERA, params))
    grid = acc.grid()
    assert (grid.value_at(np.stack([np.full(21, WALL_X), np.linspace(-0.5, 0.5, 21)], axis=1)) == OCCUPIED).all()
    assert (grid.value_at(np.array([[x, 0.0] for x in (0.5, 1.0, 1.5, 1.9)])) == FREE).all()
    assert grid.value_at(np.array([[WALL_X + 0.5, 0.0]]))[0] == UNKNOWN


def test_a_depth_view_counts_once_per_cell_however_many_beams_cross_it():
    """A desk seen twice stays occupied when a third view's rays pass over it to the wall behind:
    one view is one vote per cell, not one per beam (thousands of beams cross the cells near it)."""
    desk = 1.0
    params = GridParams(resolution=RES)
    acc = GridAccumulator(params)
    from rtabmap_ros2.core.grid import DepthCells
    for _ in range(2):   # two views of the desk cell at (1.0, 0)
        acc.add_depth(DepthCells(np.zeros(2), np.array([[desk + RES / 2, RES / 2]]), np.zeros((0, 2))))
    ends = np.stack([np.full(200, WALL_X), np.linspace(-0.02, 0.07, 200)], axis=1)
    acc.add_depth(DepthCells(np.zeros(2), ends, np.zeros((0, 2))))   # 200 beams over it to the wall
    assert acc.grid().value_at(np.array([[desk + 0.01, 0.01]]))[0] == OCCUPIED


def test_a_depth_view_taken_back_leaves_the_counts_it_found():
    params = GridParams(resolution=RES)
    T = transforms.from_xy_yaw(0.3, -0.2, 0.4, z=CAMERA_HEIGHT)
    cells = depth_cells(T, wall_and_floor_depth(), DEPTH_CAMERA, params)
    acc = GridAccumulator(params)
    acc.add(transforms.identity(), room_scan(0.0, 0.0))
    before = acc.grid()
    acc.add_depth(cells)
    acc.add_depth(cells, weight=-1)
    after = acc.grid()
    np.testing.assert_array_equal(after.data, before.data)
    assert acc.observed and not GridAccumulator(params).observed


def test_depth_points_keep_one_point_per_half_cell_and_give_the_same_cells():
    """What a node keeps of its depth image for the live grid: base-frame points, far fewer than
    the image's pixels, and the cells they give at any pose are those of the image itself."""
    params = GridParams(resolution=RES, depth_decimation=1)
    camera = DEPTH_CAMERA.scaled(640, 480)
    depth = wall_and_floor_depth(camera, height=1.013)   # the floor inside a cube, not on its border
    points = depth_points(depth, camera, params)
    assert points.points.dtype == np.float32 and len(points.points) < depth.size / 10
    every_pixel = depth_points(depth, camera, GridParams(resolution=1e-6, depth_decimation=1)).points
    assert len(every_pixel) == np.isfinite(depth).sum()
    cubes = np.unique(np.floor(every_pixel.astype(np.float64) / (RES / 2)), axis=0)
    assert abs(len(points.points) - len(cubes)) < 0.01 * len(cubes)   # one per cube of half a cell
    np.testing.assert_allclose(points.camera_xyz, np.asarray(DEFAULT_T_BASE_CAMERA)[:3, 3])
    for T in (transforms.from_xy_yaw(0.0, 0.0, 0.0, z=1.013), transforms.from_xy_yaw(3.0, -1.0, 2.0, z=1.013)):
        cells = points_cells(T, points, params)
        np.testing.assert_allclose(cells.origin_xy, (T @ DEFAULT_T_BASE_CAMERA)[:2, 3], atol=1e-6)
        wall = (T @ DEFAULT_T_BASE_CAMERA @ [0.0, 0.0, WALL_X, 1.0])[:2]   # straight ahead of the camera
        assert np.min(np.linalg.norm(cells.obstacles_xy - wall, axis=1)) < RES
        assert len(cells.ground_xy) > 50
    # Nothing valid (NaN, 0): no point, no cell.
    empty = depth_points(np.full_like(depth, np.nan), camera, params)
    assert empty.points.shape == (0, 3)
    cells = points_cells(transforms.identity(), empty, params)
    assert not len(cells.obstacles_xy) and not len(cells.ground_xy)


def test_local_grid_of_depth_points_follows_moved_poses_exactly():
    """A camera-only local map: the grid is its nodes' depth points; after a loop closure moved a
    node, the incremental grid is the one drawn from scratch at the new poses."""
    params = GridParams(resolution=RES)
    views = {n: depth_points(wall_and_floor_depth(), DEPTH_CAMERA, params) for n in (1, 2, 3)}
    poses = {n: transforms.from_xy_yaw(0.0, 0.3 * n, 0.0, z=CAMERA_HEIGHT) for n in views}   # the wall ahead of all
    grid = LocalGrid(params)
    first = grid.update(poses, {}, depth=views)
    assert first is not None
    wall = np.stack([np.full(30, WALL_X), np.linspace(-0.5, 1.5, 30)], axis=1)
    near = np.stack([first.value_at(wall + d) for d in ([0, 0], [0, RES], [0, -RES])])
    assert (near == OCCUPIED).any(axis=0).all()
    assert (first.value_at(np.array([[1.0, 0.3], [1.5, 0.6], [1.9, 0.9]])) == FREE).all()
    assert LocalGrid(params).update(poses, {}) is None                # nothing to draw from
    moved = dict(poses)
    moved[2] = transforms.from_xy_yaw(0.6, 0.5, 0.3, z=CAMERA_HEIGHT)
    moved[4] = transforms.from_xy_yaw(0.0, -1.0, -0.5, z=CAMERA_HEIGHT)
    views[4] = views[1]
    del moved[1]                                                       # left the local map
    incremental = grid.update(moved, {}, max_casts=10, depth=views)
    assert grid.pending == 0
    replayed = GridAccumulator(params)        # the same casts and take-backs, in one go
    for node in (1, 2, 3):
        replayed.add_depth(points_cells(poses[node], views[node], params))
    for node in (1, 2):
        replayed.add_depth(points_cells(poses[node], views[node], params), weight=-1)
    for node in (2, 4):
        replayed.add_depth(points_cells(moved[node], views[node], params))
    expected = replayed.grid()
    np.testing.assert_allclose(incremental.origin_xy, expected.origin_xy)
    np.testing.assert_array_equal(incremental.data, expected.data)
    # and the map drawn from scratch at the new poses (cells on a border may round the other way)
    fresh = LocalGrid(params).update(moved, {}, depth=views)
    assert incremental.data.shape == fresh.data.shape and (incremental.data != fresh.data).mean() < 0.005
    # A node with a scan and depth points (grid.sensor both) adds both.
    both = LocalGrid(params).update({1: poses[1]}, {1: room_scan(0.0, 0.3)}, depth={1: views[1]})
    scan_only = LocalGrid(params).update({1: poses[1]}, {1: room_scan(0.0, 0.3)})
    assert (both.data != UNKNOWN).sum() >= (scan_only.data != UNKNOWN).sum()


def test_returns_nearer_than_grid_range_min_are_left_out():
    """Grid/RangeMin: the robot's own body in a laser's or a camera's view is no obstacle."""
    scan = room_scan(0.0, 0.0)
    ranges = np.array(scan.ranges, dtype=np.float32)
    ranges[:60] = 0.2                         # a mast 0.2 m behind the laser hides 30 degrees of the room
    body = LaserScan(ranges, scan.angle_min, scan.angle_increment, scan.range_min, scan.range_max)
    mast = np.array([[0.2 * np.cos(scan.angles[30]), 0.2 * np.sin(scan.angles[30])]])
    assert build_grid({1: transforms.identity()}, {1: body}, GridParams(resolution=RES)).value_at(mast)[0] == OCCUPIED
    without = build_grid({1: transforms.identity()}, {1: body}, GridParams(resolution=RES, range_min=0.3))
    assert without.value_at(mast)[0] != OCCUPIED
    assert (without.value_at(np.array([[HALF, 0.0], [0.0, HALF]])) == OCCUPIED).all()   # the walls stay
    T = transforms.from_xy_yaw(0.0, 0.0, 0.0, z=CAMERA_HEIGHT)
    near = depth_points(wall_and_floor_depth(), DEPTH_CAMERA, GridParams(resolution=RES, range_min=1.8))
    assert len(near.points) and (near.points[:, 0] >= 1.79).all()      # only the wall and the floor before it
    assert len(points_cells(T, near, GridParams(resolution=RES)).obstacles_xy)
    with pytest.raises(ParameterError, match="grid.range_min"):
        GridParams(range_min=6.0, range_max=5.0)
