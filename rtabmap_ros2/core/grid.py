"""Occupancy grid from laser scans and depth images, and an RGB-D point cloud, at the optimised poses.

Grid conventions are nav_msgs/OccupancyGrid's: ``data[row, col]`` with row = y index and col = x
index counted from ``origin_xy`` (the map position of cell (0, 0)'s corner), values -1 unknown,
0 free, 100 occupied.

Method: each beam's end cell gets a hit; the cells the beam crosses before it get a miss (ray
casting by sampling each beam every half cell, all beams at once in numpy). A cell is occupied
when its hits dominate (hits > misses), free when it was crossed more often than hit, unknown
when never observed. Beams without a return (NaN, inf or >= range_max) clear free space up to
range_max: the laser saw nothing there, which is evidence of free space; this is what lets
open areas appear free. RTAB-Map does the same with ``Grid/RayTracing`` and its
``Grid/RangeMax``.

Depth images (RTAB-Map's ``Grid/Sensor`` 1, its LocalGridMaker with the passthrough segmentation):
every ``depth_decimation``-th pixel within ``range_min``..``range_max`` (one per cube of half a
cell: :func:`depth_points`, what a node keeps for the live grid) is placed in the map frame at the
node's pose; points at or below the ground height (map-frame z) are ground, those above it (up to
``max_obstacle_height``) obstacles. Projected on the ground plane, one beam per cell runs from the
camera to each obstacle cell (a hit at its end) and to each ground cell (free up to and including
it), cast like the laser's (:func:`depth_cells`, :meth:`GridAccumulator.add_depth`).
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass

import cv2
import numpy as np

from rtabmap_ros2.core import files
from rtabmap_ros2.core.params import GridParams
from rtabmap_ros2.core.sensor import CameraModel, LaserScan

logger = logging.getLogger(__name__)

UNKNOWN = -1
FREE = 0
OCCUPIED = 100
# Ray casting: samples per cell along each beam (2 = every half cell).
SAMPLES_PER_CELL = 2
# Empty margin (cells) around the observed area.
GRID_MARGIN_CELLS = 2
# Ray casting: beams are cast in chunks of about this many samples (bounds memory to ~100 MB).
MAX_SAMPLES_PER_CHUNK = 2_000_000
# to_image() grey levels, as map_server writes them.
IMAGE_UNKNOWN, IMAGE_FREE, IMAGE_OCCUPIED = 205, 254, 0


@dataclass
class OccupancyGrid:
    """A 2D occupancy grid.

    Attributes:
        data: (H,W) int8, -1 unknown / 0 free / 100 occupied; ``data[row = y index, col = x index]``.
        resolution: cell size (m).
        origin_xy: map position (m) of the corner of cell (0, 0).
    """

    data: np.ndarray
    resolution: float
    origin_xy: tuple[float, float]

    @property
    def height(self) -> int:
        return int(self.data.shape[0])

    @property
    def width(self) -> int:
        return int(self.data.shape[1])

    def cell_of(self, xy: np.ndarray) -> np.ndarray:
        """(N,2) int (col, row) indices of (N,2) map points (m); may fall outside the grid."""
        xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        return np.floor((xy - np.asarray(self.origin_xy)) / self.resolution).astype(np.int64)

    def value_at(self, xy: np.ndarray) -> np.ndarray:
        """(N,) cell values at (N,2) map points (m); -1 outside the grid."""
        cells = self.cell_of(xy)
        inside = (cells[:, 0] >= 0) & (cells[:, 0] < self.width) & (cells[:, 1] >= 0) & (cells[:, 1] < self.height)
        out = np.full(len(cells), UNKNOWN, dtype=np.int8)
        out[inside] = self.data[cells[inside, 1], cells[inside, 0]]
        return out

    def to_image(self) -> np.ndarray:
        """(H,W) uint8 image as map_server saves it: unknown 205, free 254, occupied 0, y up."""
        img = np.full(self.data.shape, IMAGE_UNKNOWN, dtype=np.uint8)
        img[self.data == FREE] = IMAGE_FREE
        img[self.data == OCCUPIED] = IMAGE_OCCUPIED
        return img[::-1]  # image row 0 = top = largest y


class GridAccumulator:
    """Hit and miss counts of scans cast at map poses, on a canvas that grows as needed.

    Adding a node ray-casts its scan once; :meth:`grid` thresholds the counts. The local map
    keeps one accumulator and only rebuilds it when optimised poses move (a loop closure), as
    RTAB-Map's map assembler does, so a frame costs one scan's ray casting, not the whole map's.
    """

    def __init__(self, params: GridParams) -> None:
        self.resolution = params.resolution
        self.range_max = params.range_max
        self.range_min = params.range_min
        self._origin_cell = np.zeros(2, np.int64)  # cell index of array element (0, 0)
        self._anchor_cell: np.ndarray | None = None   # _origin_cell at the first scan (see add)
        self._hits = np.zeros((0, 0), np.int32)
        self._misses = np.zeros((0, 0), np.int32)
        # Cells (x, y, absolute) every beam so far fell within, one cell of rounding either side:
        # grid() looks there only, not over the canvas and its growth slack.
        self._box_lo: np.ndarray | None = None
        self._box_hi: np.ndarray | None = None

    def add(self, T_map_base: np.ndarray, scan: LaserScan, weight: int = 1) -> None:
        """Ray-cast one scan taken at ``T_map_base`` (4x4) into the counts; ``weight`` -1 takes
        back a scan added before at the same pose (the counts are sums: exactly)."""
        self._add_beams(*_beams_map(T_map_base, scan, self.range_max, self.range_min), weight)

    def add_depth(self, cells: "DepthCells", weight: int = 1) -> None:
        """Cast one depth image's cells (:func:`depth_cells`): a beam from the camera to each
        obstacle cell (hit) and to each ground cell (free, its own cell included); ``weight`` -1
        takes them back."""
        ends = np.concatenate([cells.obstacles_xy, cells.ground_xy])
        if not len(ends):
            return
        origins = np.broadcast_to(cells.origin_xy, ends.shape)
        is_hit = np.arange(len(ends)) < len(cells.obstacles_xy)
        self._add_beams(origins, ends, is_hit, weight, free_ends=~is_hit, once_per_cell=True)

    @property
    def observed(self) -> bool:
        """Whether any cell was hit or crossed."""
        return bool(((self._hits + self._misses) > 0).any())

    def _add_beams(self, origin_pts: np.ndarray, end_pts: np.ndarray, is_hit: np.ndarray, weight: int,
                   free_ends: np.ndarray | None = None, once_per_cell: bool = False) -> None:
        """Ray-cast beams (origins and ends (N,2), map frame, m): a hit on the end cell of every
        beam with ``is_hit``, a miss on each cell crossed before the end, and a miss on the end cell
        of every beam with ``free_ends`` (ground seen there).

        ``once_per_cell`` (a depth image: thousands of beams fan out from one camera): one miss per
        cell however many beams cross it, and none on a cell the same beams hit, so that a view
        counts once for or against a cell, as a laser scan's sparse beams do.
        """
        res = self.resolution
        if not len(end_pts):
            return
        lo = np.floor(np.minimum(origin_pts.min(axis=0), end_pts.min(axis=0)) / res).astype(np.int64)
        hi = np.floor(np.maximum(origin_pts.max(axis=0), end_pts.max(axis=0)) / res).astype(np.int64)
        self._ensure(lo - GRID_MARGIN_CELLS, hi + GRID_MARGIN_CELLS)
        self._box_lo = lo - 1 if self._box_lo is None else np.minimum(self._box_lo, lo - 1)
        self._box_hi = hi + 1 if self._box_hi is None else np.maximum(self._box_hi, hi + 1)
        height, width = self._hits.shape
        if self._anchor_cell is None:
            self._anchor_cell = self._origin_cell.copy()
        anchor = self._anchor_cell
        base = anchor * res
        shift = anchor - self._origin_cell

        def flat(points: np.ndarray) -> np.ndarray:
            # Cells counted from the first canvas's corner (the anchor), then shifted to the
            # current canvas: a point falls in the same cell however the canvas grew since, so a
            # scan taken back (weight -1) leaves exactly the counts it added.
            cells = np.floor((points - base) / res).astype(np.int64) + shift
            return cells[:, 1] * width + cells[:, 0]

        end_cells = flat(end_pts)
        hits = self._hits.reshape(-1)
        misses = self._misses.reshape(-1)
        # Counts are added cell by cell where the beams went, not over the whole canvas: a scan costs
        # its beams, not the map's area (bincount over a 4-million-cell canvas was 120 ms a scan).
        # Hits: the end cell of every beam with a return.
        _count(hits, end_cells[is_hit], weight)
        # Misses: cells crossed by each beam before its end (ray casting, SAMPLES_PER_CELL per cell),
        # in chunks of about MAX_SAMPLES_PER_CHUNK samples (bounded memory); the end cells of the
        # beams with ``free_ends``.
        crossed = [end_cells[free_ends]] if free_ends is not None else []
        vec = end_pts - origin_pts
        n_samples = _samples_per_beam(vec, res)
        chunk_of = np.cumsum(n_samples) // MAX_SAMPLES_PER_CHUNK
        bounds = np.flatnonzero(np.diff(chunk_of)) + 1
        for lo_b, hi_b in zip(np.r_[0, bounds], np.r_[bounds, len(vec)]):
            cells = _crossed_cells(origin_pts[lo_b:hi_b], vec[lo_b:hi_b], n_samples[lo_b:hi_b],
                                   end_cells[lo_b:hi_b], flat)
            if once_per_cell:
                crossed.append(np.unique(cells))
            else:
                _count(misses, cells, weight)
        if once_per_cell:
            cells = np.unique(np.concatenate(crossed)) if crossed else np.zeros(0, np.int64)
            _count(misses, np.setdiff1d(cells, end_cells[is_hit], assume_unique=False), weight)
        elif crossed:
            _count(misses, crossed[0], weight)

    def _ensure(self, lo_cell: np.ndarray, hi_cell: np.ndarray) -> None:
        """Grow the canvas (with slack, so growth is rare) to hold cells lo_cell..hi_cell."""
        height, width = self._hits.shape
        cur_lo = self._origin_cell
        cur_hi = cur_lo + np.array([width, height]) - 1
        if height and np.all(lo_cell >= cur_lo) and np.all(hi_cell <= cur_hi):
            return
        if not height:
            new_lo, new_hi = lo_cell, hi_cell
        else:
            slack = np.array([width, height]) // 2
            new_lo = np.where(lo_cell < cur_lo, np.minimum(lo_cell, cur_lo - slack), cur_lo)
            new_hi = np.where(hi_cell > cur_hi, np.maximum(hi_cell, cur_hi + slack), cur_hi)
        new_w, new_h = (new_hi - new_lo + 1).tolist()
        hits = np.zeros((new_h, new_w), np.int32)
        misses = np.zeros((new_h, new_w), np.int32)
        if height:
            dx, dy = (cur_lo - new_lo).tolist()
            hits[dy:dy + height, dx:dx + width] = self._hits
            misses[dy:dy + height, dx:dx + width] = self._misses
        self._hits, self._misses, self._origin_cell = hits, misses, new_lo

    def grid(self) -> OccupancyGrid:
        """The occupancy grid cropped to the observed cells (plus a small margin)."""
        res = self.resolution
        if self._box_lo is None:
            return OccupancyGrid(np.full((1, 1), UNKNOWN, np.int8), res, (0.0, 0.0))
        (bc0, br0), (bc1, br1) = (np.maximum(self._box_lo - self._origin_cell, 0).tolist(),
                                  (self._box_hi - self._origin_cell + 1).tolist())
        observed = (self._hits[br0:br1, bc0:bc1] + self._misses[br0:br1, bc0:bc1]) > 0
        if not observed.any():
            return OccupancyGrid(np.full((1, 1), UNKNOWN, np.int8), res, (0.0, 0.0))
        rows = np.flatnonzero(observed.any(axis=1)) + br0
        cols = np.flatnonzero(observed.any(axis=0)) + bc0
        r0 = max(int(rows[0]) - GRID_MARGIN_CELLS, 0)
        r1 = min(int(rows[-1]) + GRID_MARGIN_CELLS + 1, self._hits.shape[0])
        c0 = max(int(cols[0]) - GRID_MARGIN_CELLS, 0)
        c1 = min(int(cols[-1]) + GRID_MARGIN_CELLS + 1, self._hits.shape[1])
        hits = self._hits[r0:r1, c0:c1]
        misses = self._misses[r0:r1, c0:c1]
        data = np.full(hits.shape, UNKNOWN, np.int8)
        data[(hits + misses) > 0] = FREE
        data[hits > misses] = OCCUPIED
        origin = (self._origin_cell + np.array([c0, r0])) * res
        return OccupancyGrid(data, res, (float(origin[0]), float(origin[1])))


@dataclass(frozen=True)
class DepthCells:
    """What one depth image says about the ground plane, in the map frame (m).

    Attributes:
        origin_xy: (2,) the camera centre projected on the ground plane.
        obstacles_xy: (N,2) centres of the cells holding an obstacle point.
        ground_xy: (M,2) centres of the cells holding ground points and no obstacle point.
    """

    origin_xy: np.ndarray
    obstacles_xy: np.ndarray
    ground_xy: np.ndarray


@dataclass(frozen=True)
class DepthPoints:
    """What the grid keeps of one depth image, in the node's base frame (m): the live node's local
    grid casts these at each new optimised pose instead of the image, which working memory does not
    hold (RTAB-Map keeps a node's local grid with it the same way).

    Attributes:
        points: (N,3) float32 points of every ``depth_decimation``-th pixel with a valid depth within
            ``range_min``..``range_max``, one per cube of :data:`DEPTH_POINT_CELL_FRACTION` of a grid cell.
        camera_xyz: (3,) the camera centre.
    """

    points: np.ndarray
    camera_xyz: np.ndarray


# depth_points keeps one point per cube of this fraction of a grid cell: a 640x480 image decimated by 4
# has 19,200 points, 2-9k after thinning (tens of kB per node kept in WM), and a cell's content
# (ground, obstacle) is decided by its points' heights, which the thinning keeps within the cube.
DEPTH_POINT_CELL_FRACTION = 0.5


def depth_points(depth_m: np.ndarray, camera: CameraModel, params: GridParams) -> DepthPoints:
    """The points of a depth image the grid uses (:class:`DepthPoints`).

    Args:
        depth_m: HxW float32 depth (m), NaN or 0 invalid, registered to ``camera``.
        camera: pinhole model (``T_base_camera`` to the optical frame).
        params: resolution, range_min and range_max (depth limits, 0 = none) and depth_decimation.
    """
    step = params.depth_decimation
    d = np.asarray(depth_m)[::step, ::step]
    rows, cols = np.mgrid[0:depth_m.shape[0]:step, 0:depth_m.shape[1]:step]
    with np.errstate(invalid="ignore"):
        valid = np.isfinite(d) & (d > 0)
        if params.range_max > 0:
            valid &= d <= params.range_max
        if params.range_min > 0:
            valid &= d >= params.range_min
    if depth_m.shape != (camera.height, camera.width):
        camera = camera.scaled(depth_m.shape[1], depth_m.shape[0])
    T = camera.T_base_camera
    p_cam = camera.back_project(np.stack([cols[valid], rows[valid]], axis=1).astype(np.float64), d[valid])
    points = p_cam @ T[:3, :3].T + T[:3, 3]
    if len(points):
        cubes = np.floor(points / (params.resolution * DEPTH_POINT_CELL_FRACTION)).astype(np.int64)
        cubes -= cubes.min(axis=0)
        span = cubes.max(axis=0) + 1
        # One integer per cube (4x faster than unique rows) unless the cubes are too many to number.
        keys = (np.ravel_multi_index(cubes.T, tuple(span)) if float(np.prod(span, dtype=np.float64)) < 2.0 ** 62
                else cubes)
        points = points[np.sort(np.unique(keys, axis=0, return_index=True)[1])]
    return DepthPoints(points.astype(np.float32), T[:3, 3].copy())


def points_cells(T_map_base: np.ndarray, depth: DepthPoints, params: GridParams) -> DepthCells:
    """Obstacle and ground cells of a depth image's points (:func:`depth_points`) seen from
    ``T_map_base`` (module doc).

    Args:
        T_map_base: 4x4 pose of the node's base in the map frame.
        depth: the image's points in the base frame.
        params: resolution and the heights (map-frame z, m): ground up to ``ground_height``,
            obstacles above it up to ``max_obstacle_height`` (0 = no limit), nothing below
            ``min_ground_height`` (0 = no limit).
    """
    points = depth.points.astype(np.float64) @ T_map_base[:3, :3].T + T_map_base[:3, 3]
    z = points[:, 2]
    ground = z <= params.ground_height
    obstacle = ~ground
    if params.min_ground_height:
        ground &= z >= params.min_ground_height
    if params.max_obstacle_height:
        obstacle &= z <= params.max_obstacle_height
    res = params.resolution
    obstacle_cells = np.unique(np.floor(points[obstacle, :2] / res).astype(np.int64), axis=0)
    ground_cells = np.unique(np.floor(points[ground, :2] / res).astype(np.int64), axis=0)
    if len(obstacle_cells) and len(ground_cells):
        # A cell holding both is an obstacle (a chair's legs stand on the floor).
        lo = np.minimum(obstacle_cells.min(axis=0), ground_cells.min(axis=0))
        dims = tuple(np.maximum(obstacle_cells.max(axis=0), ground_cells.max(axis=0)) - lo + 1)
        taken = np.ravel_multi_index((obstacle_cells - lo).T, dims)
        ground_cells = ground_cells[~np.isin(np.ravel_multi_index((ground_cells - lo).T, dims), taken)]
    origin = T_map_base[:3, :3] @ depth.camera_xyz + T_map_base[:3, 3]
    return DepthCells(origin[:2].copy(), (obstacle_cells.reshape(-1, 2) + 0.5) * res,
                      (ground_cells.reshape(-1, 2) + 0.5) * res)


def grid_sources(sensor: str, has_scan: bool) -> tuple[bool, bool]:
    """Whether a node's laser scan and whether its depth image go into the occupancy grid, by
    ``grid.sensor``: laser, depth, both, or auto (the scan when the node has one, else the depth)."""
    return sensor in ("laser", "both") or (sensor == "auto" and has_scan), \
        sensor in ("depth", "both") or (sensor == "auto" and not has_scan)


def depth_cells(T_map_base: np.ndarray, depth_m: np.ndarray, camera: CameraModel, params: GridParams) -> DepthCells:
    """Obstacle and ground cells of a depth image taken at ``T_map_base``: :func:`points_cells` of
    its :func:`depth_points`."""
    return points_cells(T_map_base, depth_points(depth_m, camera, params), params)


def build_grid(poses: dict[int, np.ndarray], scans: dict[int, LaserScan], params: GridParams) -> OccupancyGrid:
    """Occupancy grid of the scans of the nodes in ``poses`` (nodes without a scan are skipped).

    Args:
        poses: node id -> 4x4 ``T_map_base`` (the optimised poses).
        scans: node id -> laser scan (``T_base_laser`` inside).
        params: resolution (m) and range_max (m, 0 = each scan's own).

    Returns:
        :class:`OccupancyGrid` covering every observed cell (with a small margin); an empty
        1x1 unknown grid when no node has a scan.
    """
    accumulator = GridAccumulator(params)
    for node_id, T_map_base in poses.items():
        scan = scans.get(node_id)
        if scan is not None:
            accumulator.add(T_map_base, scan)
    return accumulator.grid()


def scan_conflict(a: list[tuple[np.ndarray, LaserScan]], b: list[tuple[np.ndarray, LaserScan]], cell: float,
                  range_max: float, max_beams: int) -> tuple[float, int]:
    """How much two sets of scans, each placed at its poses in one common frame, contradict each
    other: the fraction of the cells one set hits (a wall) that the other crossed with nothing hit
    within a cell (free space), among the cells one set hits and the other observed. Birk and
    Carpin's acceptance index for merging two maps (agreeing vs disagreeing cells), taken on the
    scans, so no finished grid is needed. The one-cell tolerance absorbs pose error up to a cell.
    Along a straight corridor a shift keeps most walls on walls: only unmatched doorways and end
    walls contradict it, a few per cent of the cells; junctions and rooms seen by both tell more.

    Only whether a cell was crossed matters here (not how often, as for the occupancy grid), so
    the beams are drawn as lines (OpenCV, 8-connected, 1/16-cell end points) on boolean grids over
    the cells both sets can have observed. Sampling every beam every half cell into sets of cell
    keys took 3.9x as long (``bench/bench_scan_conflict.py``, real scans of the Intel lab: 5.9 vs
    23.3 ms a call; 6-8 vs 26-45 ms on the simulated sessions' merges, where it made the merge
    frames the ones over T_time 0.1 s) for ratios within 0.018 of these, none on the other side
    of graph.merge_max_conflict.

    Args:
        a, b: (T_frame_base 4x4, scan) pairs.
        cell: cell size (m).
        range_max: beams are cut at this range (longer ones end without a hit: free space).
        max_beams: each scan's beams are thinned to at most this many.

    Returns:
        (conflict ratio in [0, 1], number of cells it was taken over); (0.0, 0) when the sets see
        nothing in common.
    """
    beams_a, beams_b = _thinned_beams(a, range_max, max_beams), _thinned_beams(b, range_max, max_beams)
    if not beams_a or not beams_b:
        return 0.0, 0
    (lo_a, hi_a), (lo_b, hi_b) = _cell_box(beams_a, cell), _cell_box(beams_b, cell)
    # Cells one set hits and the other observed lie in both boxes; their neighbours within 2.
    lo, hi = np.maximum(lo_a, lo_b) - 2, np.minimum(hi_a, hi_b) + 2
    if np.any(hi < lo):
        return 0.0, 0
    shape = (int(hi[1] - lo[1]) + 1, int(hi[0] - lo[0]) + 1)  # rows = y cells, cols = x cells
    hits_a, crossed_a = _hit_and_crossed_cells(beams_a, cell, lo, shape)
    hits_b, crossed_b = _hit_and_crossed_cells(beams_b, cell, lo, shape)
    near_a, near_b = _dilated(hits_a), _dilated(hits_b)
    free_a, free_b = crossed_a & ~near_a, crossed_b & ~near_b
    conflict = int(np.count_nonzero(hits_a & free_b) + np.count_nonzero(hits_b & free_a))
    support = int(np.count_nonzero(hits_a & (free_b | near_b)) + np.count_nonzero(hits_b & (free_a | near_a)))
    return (conflict / support if support else 0.0), support


# scan_conflict's line end points: fixed point with this many fractional bits (cv2's ``shift``).
_LINE_SHIFT = 4


def _thinned_beams(scans: list[tuple[np.ndarray, LaserScan]], range_max: float,
                   max_beams: int) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Each scan's beams (origins, ends, ended on a return; :func:`_beams_map`), at most
    ``max_beams`` of them, evenly spread; scans without a beam left out."""
    beams = []
    for T, scan in scans:
        origins, ends, is_hit = _beams_map(T, scan, range_max)
        step = max(1, -(-len(ends) // max_beams))
        if len(ends):
            beams.append((origins[::step], ends[::step], is_hit[::step]))
    return beams


def _cell_box(beams: list[tuple[np.ndarray, np.ndarray, np.ndarray]], cell: float) -> tuple[np.ndarray, np.ndarray]:
    """Smallest and largest (x, y) cell indices the beams reach."""
    ij = np.floor(np.concatenate([np.concatenate([o[:1], e]) for o, e, _ in beams]) / cell).astype(np.int64)
    return ij.min(axis=0), ij.max(axis=0)


def _hit_and_crossed_cells(beams: list[tuple[np.ndarray, np.ndarray, np.ndarray]], cell: float, lo: np.ndarray,
                           shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Boolean grids (``shape``, cell (0, 0) = cell ``lo``) of the cells the beams end on with a
    return, and of those they cross."""
    hits = np.zeros(shape, np.uint8)
    crossed = np.zeros(shape, np.uint8)
    scale = float(1 << _LINE_SHIFT)
    for origins, ends, is_hit in beams:
        ij = np.floor(ends[is_hit] / cell).astype(np.int64) - lo
        inside = (ij[:, 0] >= 0) & (ij[:, 0] < shape[1]) & (ij[:, 1] >= 0) & (ij[:, 1] < shape[0])
        hits[ij[inside, 1], ij[inside, 0]] = 1
        # OpenCV's pixel k has its centre at k: cell coordinates minus half a cell.
        segments = np.stack([origins, ends], axis=1) / cell - lo - 0.5
        cv2.polylines(crossed, np.round(segments * scale).astype(np.int32), False, 1, 1, cv2.LINE_8, _LINE_SHIFT)
    return hits.astype(bool), crossed.astype(bool)


def _dilated(cells: np.ndarray) -> np.ndarray:
    """The cells within one cell (8-neighbourhood) of the True ones."""
    out = cells.copy()
    out[1:] |= cells[:-1]
    out[:-1] |= cells[1:]
    rows = out.copy()
    out[:, 1:] |= rows[:, :-1]
    out[:, :-1] |= rows[:, 1:]
    return out


def _count(counts: np.ndarray, cells: np.ndarray, weight: int) -> None:
    """Add ``weight`` to the flat ``counts`` once per occurrence of each index in ``cells``."""
    if len(cells):
        unique, times = np.unique(cells, return_counts=True)
        counts[unique] += (weight * times).astype(counts.dtype)


def _crossed_cells(origins: np.ndarray, vec: np.ndarray, n_samples: np.ndarray, end_cells: np.ndarray,
                   flat) -> np.ndarray:
    """Flat indices of the cells each beam crosses before its end cell, once per (beam, cell)
    (ray casting; a cell crossed by two beams is listed twice)."""
    total = int(n_samples.sum())
    if not total:
        return np.zeros(0, np.int64)
    beam, samples = _beam_samples(origins, vec, n_samples)
    cells = flat(samples)
    # One miss per (beam, cell) and never on the beam's own end cell. A segment crosses each
    # cell in one run of consecutive samples, so dropping repeats of the previous sample
    # dedupes exactly in O(N) (np.unique over (beam, cell) rows was 70 % of the time).
    first = np.ones(total, bool)
    first[1:] = (cells[1:] != cells[:-1]) | (beam[1:] != beam[:-1])
    keep = first & (cells != end_cells[beam])
    return cells[keep]


def _samples_per_beam(vec: np.ndarray, cell: float) -> np.ndarray:
    """(N,) int64 samples along each beam (N,2 vectors, m) for SAMPLES_PER_CELL per cell of ``cell`` m."""
    return np.ceil(np.linalg.norm(vec, axis=1) / cell * SAMPLES_PER_CELL).astype(np.int64)


def _beam_samples(origins: np.ndarray, vec: np.ndarray, n_samples: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``n_samples[i]`` evenly spaced points along beam i, from its origin to just before its end,
    all beams at once: (beam index of each sample, (total,2) sample points)."""
    total = int(n_samples.sum())
    beam = np.repeat(np.arange(len(vec)), n_samples)
    step = np.arange(total) - np.repeat(np.cumsum(n_samples) - n_samples, n_samples)
    frac = step / np.repeat(np.maximum(n_samples, 1), n_samples)
    # Per-beam values repeated (contiguous copies), not gathered by beam index: 2-3x faster.
    points = np.empty((total, 2))
    for axis in (0, 1):
        np.multiply(np.repeat(vec[:, axis], n_samples), frac, out=points[:, axis])
        points[:, axis] += np.repeat(origins[:, axis], n_samples)
    return beam, points


def _beams_map(T_map_base: np.ndarray, scan: LaserScan, range_max: float, range_min: float = 0.0):
    """Beam origins (N,2), ends (N,2) in the map frame and whether each ended on a return; returns
    nearer than the scan's range_min or ``range_min`` are left out (no information)."""
    r = np.asarray(scan.ranges, dtype=np.float64)
    limit = scan.range_max if range_max <= 0 else min(range_max, scan.range_max)
    with np.errstate(invalid="ignore"):
        returned = np.isfinite(r) & (r >= max(scan.range_min, range_min)) & (r < limit)
        no_return = ~np.isfinite(r) | (r >= limit)
    use = returned | no_return
    ranges = np.where(returned, r, limit)[use]
    angles = scan.angles[use]
    pts_laser = np.stack([ranges * np.cos(angles), ranges * np.sin(angles)], axis=1)
    T = T_map_base @ scan.T_base_laser
    ends = pts_laser @ T[:2, :2].T + T[:2, 3]
    origins = np.broadcast_to(T[:2, 3], ends.shape)
    return origins, ends, returned[use]


def voxel_filter(points: np.ndarray, colors: np.ndarray | None, voxel: float):
    """One point per occupied voxel (the centroid, mean colour).

    Args:
        points: (N,3) float points (m), or (N,2) for planar points (laser scans).
        colors: (N,3) uint8 RGB, or None.
        voxel: voxel edge (m), > 0.

    Returns:
        ``(points (M,D) float32, colors (M,3) uint8 or None)``, D the points' dimension.
    """
    points = np.asarray(points, dtype=np.float64)
    dim = 2 if points.ndim == 2 and points.shape[1] == 2 else 3
    pts = points.reshape(-1, dim)
    if len(pts) == 0:
        return pts.astype(np.float32), None if colors is None else np.zeros((0, 3), np.uint8)
    keys = np.floor(pts / voxel).astype(np.int64)
    # One int64 key per voxel (1D np.unique is ~10x faster than over rows).
    keys -= keys.min(axis=0)
    flat_keys = np.ravel_multi_index(keys.T, tuple(keys.max(axis=0) + 1))
    _, inverse, counts = np.unique(flat_keys, return_inverse=True, return_counts=True)
    inverse = inverse.ravel()
    # Per-voxel sums by bincount, one column at a time (np.add.at took ~10x as long).
    def voxel_means(values: np.ndarray) -> np.ndarray:
        return np.column_stack([np.bincount(inverse, weights=column, minlength=len(counts))
                                for column in values.T]) / counts[:, None]

    out_pts = voxel_means(pts).astype(np.float32)
    if colors is None:
        return out_pts, None
    return out_pts, np.rint(voxel_means(np.asarray(colors, dtype=np.float64).reshape(-1, 3))).astype(np.uint8)


def assemble_cloud(poses: dict[int, np.ndarray], depths: dict[int, np.ndarray], rgbs: dict[int, np.ndarray],
                   cameras: dict[int, CameraModel], decimation: int, voxel: float):
    """Coloured point cloud of the depth images at the nodes' poses (map frame).

    Args:
        poses: node id -> 4x4 ``T_map_base``.
        depths: node id -> HxW float32 depth (m), NaN or 0 invalid.
        rgbs: node id -> HxWx3 uint8 RGB registered to the depth (missing: grey points).
        cameras: node id -> camera model of the depth image.
        decimation: use every n-th pixel in each direction.
        voxel: voxel size (m) of the final filter (0 = none).

    Returns:
        ``(points (N,3) float32 m, colors (N,3) uint8)``.
    """
    all_pts, all_cols = [], []
    for node_id, T_map_base in poses.items():
        depth = depths.get(node_id)
        camera = cameras.get(node_id)
        if depth is None or camera is None:
            continue
        d = np.asarray(depth)[::decimation, ::decimation]
        rows, cols = np.mgrid[0:depth.shape[0]:decimation, 0:depth.shape[1]:decimation]
        with np.errstate(invalid="ignore"):
            valid = np.isfinite(d) & (d > 0)
        uv = np.stack([cols[valid], rows[valid]], axis=1).astype(np.float64)
        if depth.shape != (camera.height, camera.width):
            camera = camera.scaled(depth.shape[1], depth.shape[0])
        p_cam = camera.back_project(uv, d[valid])
        T = T_map_base @ camera.T_base_camera
        all_pts.append(p_cam @ T[:3, :3].T + T[:3, 3])
        rgb = rgbs.get(node_id)
        if rgb is not None and rgb.shape[:2] == depth.shape:
            all_cols.append(rgb[::decimation, ::decimation][valid])
        else:
            all_cols.append(np.full((len(uv), 3), 128, np.uint8))
    if not all_pts:
        return np.zeros((0, 3), np.float32), np.zeros((0, 3), np.uint8)
    pts = np.concatenate(all_pts)
    cols = np.concatenate(all_cols).astype(np.uint8)
    if voxel > 0:
        return voxel_filter(pts, cols, voxel)
    return pts.astype(np.float32), cols


def write_ply(path: str | os.PathLike, points: np.ndarray, colors: np.ndarray | None = None) -> None:
    """Binary little-endian PLY with ``x y z`` float and ``red green blue`` uchar per vertex
    (written through a temporary file, :mod:`rtabmap_ros2.core.files`).

    Args:
        path: output file.
        points: (N,3) points (m).
        colors: (N,3) uint8 RGB, or None (written grey).
    """
    pts = np.asarray(points, dtype=np.float32).reshape(-1, 3)
    cols = (np.full((len(pts), 3), 128, np.uint8) if colors is None
            else np.asarray(colors, dtype=np.uint8).reshape(-1, 3))
    vertex = np.empty(len(pts), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"),
                                       ("red", "u1"), ("green", "u1"), ("blue", "u1")])
    vertex["x"], vertex["y"], vertex["z"] = pts[:, 0], pts[:, 1], pts[:, 2]
    vertex["red"], vertex["green"], vertex["blue"] = cols[:, 0], cols[:, 1], cols[:, 2]
    header = ("ply\nformat binary_little_endian 1.0\ncomment rtabmap_ros2 assembled cloud\n"
              f"element vertex {len(pts)}\nproperty float x\nproperty float y\nproperty float z\n"
              "property uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n")
    with files.new_file(path, "wb") as f:
        f.write(header.encode("ascii"))
        f.write(vertex.tobytes())


__all__ = ["FREE", "OCCUPIED", "UNKNOWN", "DepthCells", "GridAccumulator", "OccupancyGrid", "assemble_cloud",
           "build_grid", "depth_cells", "voxel_filter", "write_ply"]
