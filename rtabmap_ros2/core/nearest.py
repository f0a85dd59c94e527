"""Nearest points within a distance, in 2D: ICP's neighbour searches (registration.py).

ICP asks, at every iteration, for each scan point the nearest reference point closer than the
correspondence distance, and once per call for each reference point its nearest neighbours (its
local line's normal, valid when they lie within a radius). ``scipy.spatial.cKDTree`` answered them
in ~0.4 ms a query of ~480 points against ~1,000 (about 10 per ICP, an ICP every frame: two
thirds of a neighbour link's time) and ~1.5 ms for the normals. With the distance known, square
cells of that size hold every candidate of a point in the 3 x 3 cells around it, and a compiled
loop over them gives the same answers (same squared distances, same bounds, neighbours in the same
order) at a fraction of the cost.
"""

from __future__ import annotations

import numpy as np

from rtabmap_ros2.core.compiled import jit

# Cells a hair wider than the gate: a point nearer than the gate is then never two cells away from
# the query, whatever the round-off of the cell coordinates.
CELL_MARGIN = 1e-9


@jit(inline="always")
def _cell_range(keys, col, row_lo, row_hi, max_row):
    """First and past-last positions in ``keys`` of the cells (col, row_lo..row_hi)."""
    first = np.searchsorted(keys, col * (max_row + 1) + row_lo, side="left")
    last = np.searchsorted(keys, col * (max_row + 1) + row_hi, side="right")
    return first, last


@jit()
def nearest_in_cells(points, order, keys, origin, cell, max_col, max_row, queries, bound_sq, out):
    """For each query, the index of the point of smallest squared distance below ``bound_sq``
    (-1: none); candidates from the cells ``(col, row)`` around it, sorted by ``col * (max_row + 1) + row``."""
    for i in range(queries.shape[0]):
        qx, qy = queries[i, 0], queries[i, 1]
        fx = np.floor((qx - origin[0]) / cell)
        fy = np.floor((qy - origin[1]) / cell)
        out[i] = -1
        if not (-1.0 <= fx <= max_col + 1.0 and -1.0 <= fy <= max_row + 1.0):  # also NaN
            continue
        cx, cy = int(fx), int(fy)
        row_lo, row_hi = max(cy - 1, 0), min(cy + 1, max_row)
        best = bound_sq
        for col in range(max(cx - 1, 0), min(cx + 1, max_col) + 1):
            first, last = _cell_range(keys, col, row_lo, row_hi, max_row)
            for s in range(first, last):
                j = order[s]
                dx = points[j, 0] - qx
                dy = points[j, 1] - qy
                d = dx * dx + dy * dy
                if d < best:
                    best = d
                    out[i] = j


@jit()
def _k_nearest(points, order, keys, cells, max_col, max_row, out_index, out_distance):
    """For each point, the ``k`` nearest points (itself included) among the 3 x 3 cells around it,
    nearest first (the earlier one in cell order on a tie), and the distance of the k-th (inf when
    the cells hold fewer than k)."""
    k = out_index.shape[1]
    best = np.empty(k)
    for i in range(points.shape[0]):
        best[:] = np.inf
        out_index[i, :] = i
        cx, cy = cells[i, 0], cells[i, 1]
        row_lo, row_hi = max(cy - 1, 0), min(cy + 1, max_row)
        for col in range(max(cx - 1, 0), min(cx + 1, max_col) + 1):
            first, last = _cell_range(keys, col, row_lo, row_hi, max_row)
            for s in range(first, last):
                j = order[s]
                dx = points[j, 0] - points[i, 0]
                dy = points[j, 1] - points[i, 1]
                d = dx * dx + dy * dy
                if d < best[k - 1]:
                    m = k - 1
                    while m > 0 and best[m - 1] > d:
                        best[m] = best[m - 1]
                        out_index[i, m] = out_index[i, m - 1]
                        m -= 1
                    best[m] = d
                    out_index[i, m] = j
        out_distance[i] = np.sqrt(best[k - 1])


class NearestWithin:
    """Reference points (N, 2) (m) binned in square cells of the gate's size."""

    def __init__(self, points: np.ndarray, max_distance: float) -> None:
        """``points``: (N, 2) reference points (m); ``max_distance``: the gate (m), > 0."""
        self.points = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 2)
        # cKDTree's bound on the squared distance (distance_upper_bound ** 2), strict.
        self.bound_sq = float(max_distance) ** 2
        self.cell = float(max_distance) * (1.0 + CELL_MARGIN)
        self.origin = self.points.min(axis=0) if len(self.points) else np.zeros(2)
        cells = np.floor((self.points - self.origin) / self.cell).astype(np.int64)
        self.cells = cells
        self.max_col = int(cells[:, 0].max()) if len(cells) else -2
        self.max_row = int(cells[:, 1].max()) if len(cells) else -2
        keys = cells[:, 0] * (self.max_row + 1) + cells[:, 1]
        self.order = np.argsort(keys, kind="stable")
        self.keys = keys[self.order]

    def query(self, queries: np.ndarray) -> np.ndarray:
        """(M,) int64 index of the point nearest each of (M, 2) ``queries`` (m) at a distance below
        the gate, -1 where there is none (as ``cKDTree.query(queries, distance_upper_bound=gate)``,
        whose ``N`` is -1 here)."""
        queries = np.ascontiguousarray(queries, dtype=np.float64).reshape(-1, 2)
        out = np.empty(len(queries), np.int64)
        nearest_in_cells(*self.cells_of_points(), queries, self.bound_sq, out)
        return out

    def cells_of_points(self) -> tuple:
        """The arguments of :func:`nearest_in_cells` before its queries: the points and their cells,
        for compiled callers (registration's ICP)."""
        return self.points, self.order, self.keys, self.origin, self.cell, self.max_col, self.max_row

    def k_nearest(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        """Each reference point's ``k`` nearest reference points (itself first), nearest first, and
        the distance (m) of the k-th: ``(index (N, k) int64, distance (N,))``. Exact where that
        distance is within the gate, as ``cKDTree.query(points, k=k)``; beyond it the distance is
        only known to be beyond the gate (inf, or the k-th found among the cells near the point)."""
        index = np.empty((len(self.points), k), np.int64)
        distance = np.empty(len(self.points))
        _k_nearest(self.points, self.order, self.keys, self.cells, self.max_col, self.max_row, index, distance)
        return index, distance

