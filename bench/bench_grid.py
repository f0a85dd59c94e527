"""The occupancy grid from depth images, as the live node draws it for a robot without a laser.

Each node whose grid uses its depth image (``grid.sensor`` auto without a scan, depth, both) keeps
the image's points in its base frame (``core/grid.py`` ``depth_points``: every ``depth_decimation``-th
pixel, one point per cube of half a grid cell), and the node's grid thread casts them at the node's
optimised pose (``points_cells`` + ``GridAccumulator.add_depth``). On real Kinect depth images
(the 48 of ``../shared/data/rgbd/tum_fr1_rpy_loops``, each at its motion capture pose, and the two of
``rtabmap_frames``), at the default grid parameters, per image:

* what a node keeps: points and bytes;
* what it costs: ``depth_points`` (made once, on the worker, when the node is created),
  ``points_cells`` and ``add_depth`` (the grid thread, at every recast);
* what the thinning changes: the grid of the 48 fr1 views cast together at their poses (one desk
  room) from the kept points against the same from every decimated pixel's point (no thinning):
  the share of its observed cells that differ, and the occupied and free cells of both.

Usage: ``python bench/bench_grid.py [--quick]``. Writes ``bench/results/grid.json``.
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from pathlib import Path

import cv2
import numpy as np

from rtabmap_ros2.core import grid, transforms
from rtabmap_ros2.core.grid import FREE, OCCUPIED, UNKNOWN, GridAccumulator, depth_points, points_cells
from rtabmap_ros2.core.params import GridParams
from rtabmap_ros2.core.sensor import CameraModel
from rtabmap_ros2.io.bag import DEFAULT_T_BASE_CAMERA

REPO = Path(__file__).resolve().parents[1]
DATA = REPO.parent / "shared" / "data" / "rgbd"
RESULTS = Path(__file__).resolve().parent / "results" / "grid.json"
TUM_DEPTH_SCALE = 5000.0
FR1 = (517.3, 516.5, 318.6, 255.3)       # TUM fr1 intrinsics (the loop pairs' README)
RTABMAP_FRAMES = (525.0, 525.0, 319.5, 239.5)
REPEATS = 5


def images(quick: bool) -> list[tuple[str, np.ndarray, CameraModel, np.ndarray]]:
    """(name, depth (m), camera, T_map_base) of every real depth image used."""
    out = []
    T_base_camera = np.asarray(DEFAULT_T_BASE_CAMERA)
    for case in sorted((DATA / "tum_fr1_rpy_loops").glob("case_*")):
        for side in ("prev", "curr"):
            raw = cv2.imread(str(case / f"dep_{side}.png"), cv2.IMREAD_UNCHANGED)
            depth = raw.astype(np.float32) / TUM_DEPTH_SCALE
            depth[raw == 0] = np.nan
            T_map_camera = _pose(case / f"pose_{side}.txt")
            camera = CameraModel(*FR1, raw.shape[1], raw.shape[0], T_base_camera)
            out.append((f"{case.name}/{side}", depth, camera, T_map_camera @ np.linalg.inv(T_base_camera)))
    for path in sorted((DATA / "rtabmap_frames" / "depth").glob("*.png")):
        raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        depth = raw.astype(np.float32) / 1000.0
        depth[raw == 0] = np.nan
        camera = CameraModel(*RTABMAP_FRAMES, raw.shape[1], raw.shape[0], T_base_camera)
        # No pose: the base on the floor's origin, the camera 1 m up looking level.
        out.append((f"rtabmap_frames/{path.stem}", depth, camera, transforms.from_xy_yaw(0.0, 0.0, 0.0, z=1.0)))
    return out[:10] if quick else out


def _pose(path: Path) -> np.ndarray:
    """4x4 of the motion capture pose of the RGB optical frame (``x y z qx qy qz qw``)."""
    values = [float(v) for v in path.read_text().split()]
    tx, ty, tz, qx, qy, qz, qw = values[-7:]
    T = np.eye(4)
    T[:3, :3] = _quaternion_matrix(qx, qy, qz, qw)
    T[:3, 3] = (tx, ty, tz)
    return T


def _quaternion_matrix(x: float, y: float, z: float, w: float) -> np.ndarray:
    n = np.sqrt(x * x + y * y + z * z + w * w)
    x, y, z, w = x / n, y / n, z / n, w / n
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def _ms(call) -> float:
    """Median wall time (ms) of ``call`` over REPEATS calls."""
    times = []
    for _ in range(REPEATS):
        t0 = time.perf_counter()
        call()
        times.append((time.perf_counter() - t0) * 1000.0)
    return float(np.median(times))


def measure(name: str, depth: np.ndarray, camera: CameraModel, T_map_base: np.ndarray, params: GridParams) -> dict:
    kept = depth_points(depth, camera, params)
    cells = points_cells(T_map_base, kept, params)

    def add() -> None:
        GridAccumulator(params).add_depth(cells)

    return {"image": name, "points": len(kept.points), "kB": round(kept.points.nbytes / 1024, 1),
            "depth_points_ms": round(_ms(lambda: depth_points(depth, camera, params)), 2),
            "points_cells_ms": round(_ms(lambda: points_cells(T_map_base, kept, params)), 2),
            "add_depth_ms": round(_ms(add), 2)}


def thinning(views: list[tuple[str, np.ndarray, CameraModel, np.ndarray]], params: GridParams) -> dict:
    """The grid of ``views`` cast together from the kept points and from every decimated pixel's."""
    def cast(fraction: float):
        kept = grid.DEPTH_POINT_CELL_FRACTION
        grid.DEPTH_POINT_CELL_FRACTION = fraction
        try:
            accumulator = GridAccumulator(params)
            for _, depth, camera, T in views:
                accumulator.add_depth(points_cells(T, depth_points(depth, camera, params), params))
            return accumulator.grid().data
        finally:
            grid.DEPTH_POINT_CELL_FRACTION = kept

    thinned, every = cast(grid.DEPTH_POINT_CELL_FRACTION), cast(1e-9)
    observed = (thinned != UNKNOWN) | (every != UNKNOWN)
    return {"views": len(views), "cells_differing": round(float((thinned != every)[observed].mean()), 4),
            "occupied": int((thinned == OCCUPIED).sum()), "occupied_every_point": int((every == OCCUPIED).sum()),
            "free": int((thinned == FREE).sum()), "free_every_point": int((every == FREE).sum())}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="the first 10 images only")
    args = parser.parse_args()
    params = GridParams()
    views = images(args.quick)
    rows = [measure(*image, params) for image in views]
    thinned = thinning([v for v in views if v[0].startswith("case_")], params)

    def median(key: str) -> float:
        return float(np.median([r[key] for r in rows]))

    summary = {key: median(key) for key in ("points", "kB", "depth_points_ms", "points_cells_ms", "add_depth_ms")}
    summary.update({"kB_max": max(r["kB"] for r in rows), "images": len(rows)})
    out = {"machine": platform.platform(), "python": platform.python_version(),
           "written": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()), "quick": args.quick,
           "grid": {"resolution": params.resolution, "range_max": params.range_max,
                    "depth_decimation": params.depth_decimation},
           "median": summary, "thinning": thinned, "images": rows}
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    RESULTS.write_text(json.dumps(out, indent=1) + "\n")
    print(f"{len(rows)} real depth images, grid {params.resolution} m, decimation {params.depth_decimation}:")
    print(f"  kept per node: {summary['points']:.0f} points, {summary['kB']:.1f} kB (max {summary['kB_max']} kB)")
    print(f"  depth_points {summary['depth_points_ms']:.2f} ms, points_cells {summary['points_cells_ms']:.2f} ms, "
          f"add_depth {summary['add_depth_ms']:.2f} ms (medians)")
    print(f"  the {thinned['views']} fr1 views cast together: {100 * thinned['cells_differing']:.2f} % of the observed "
          f"cells differ from every pixel's point; occupied {thinned['occupied']} against "
          f"{thinned['occupied_every_point']}, free {thinned['free']} against {thinned['free_every_point']}")
    print(f"wrote {RESULTS}")


if __name__ == "__main__":
    main()
