"""2D point-to-line ICP on laser scans (2014 §II-A: loop closures refined by ICP; neighbour links
refined against a local scan map), optionally held by a Gaussian prior.

Each iteration's correspondences (the nearest target point within the gate, core/nearest.py),
residuals and normal equations run compiled (``_icp_system``): as numpy calls they were most of an
ICP's time, and an ICP runs every frame (issue 50).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rtabmap_ros2.core import transforms
from rtabmap_ros2.core.compiled import jit
from rtabmap_ros2.core.nearest import NearestWithin, nearest_in_cells

# ICP: neighbours (the point included) fitting the local line (normal) at each target point; 3 gave
# the smallest mean error on intel-corrected k -> k+5 pairs (bench/bench_registration.py).
ICP_NORMAL_NEIGHBORS = 3
# ICP: a target point whose neighbours spread farther than this has no reliable normal.
ICP_NORMAL_MAX_RADIUS = 0.5  # m
# ICP: stop when an update moves less than these.
ICP_CONVERGENCE_TRANSLATION = 1e-5  # m
ICP_CONVERGENCE_ROTATION = 1e-6  # rad
# ICP: Cauchy scale of the point-to-line residuals (a few times the laser's noise).
ICP_ROBUST_SCALE = 0.05  # m
# ICP: minimum correspondences for a well-posed 3-DoF Gauss-Newton step.
ICP_MIN_CORRESPONDENCES = 10
# Smallest residual standard deviation assumed for a scan match (m): laser noise of a good sensor.
ICP_MIN_SIGMA = 0.005
# Correspondences per independent measurement in a scan match (neighbouring beams see the same
# wall with correlated errors): the scan information is divided by it.
ICP_DEPENDENCE = 10.0


def line_normals(points: np.ndarray) -> np.ndarray:
    """Unit normals (N,2) of the local line through each point's neighbours; NaN where unreliable
    (the ICP_NORMAL_NEIGHBORS nearest points, itself included, reach beyond ICP_NORMAL_MAX_RADIUS)."""
    idx, reach = NearestWithin(points, ICP_NORMAL_MAX_RADIUS).k_nearest(ICP_NORMAL_NEIGHBORS)
    neighbors = points[idx]
    centred = neighbors - neighbors.mean(axis=1, keepdims=True)
    x, y = centred[..., 0], centred[..., 1]
    # The line's direction is the scatter matrix's principal eigenvector, at angle theta with
    # tan(2 theta) = 2 sxy / (sxx - syy); the normal is perpendicular to it (closed form: ~20x a
    # batched eigh over every point of a scan map, which was a fifth of a neighbour link's ICP).
    theta = 0.5 * np.arctan2(2.0 * np.sum(x * y, axis=1), np.sum(x * x, axis=1) - np.sum(y * y, axis=1))
    normals = np.column_stack([-np.sin(theta), np.cos(theta)])
    normals[reach > ICP_NORMAL_MAX_RADIUS] = np.nan
    return normals


def icp_2d(source_xy: np.ndarray, target_xy: np.ndarray, T_init: np.ndarray, *,
           max_correspondence_distance: float = 0.3, iterations: int = 30) -> tuple[np.ndarray, float, float]:
    """2D point-to-line ICP (Gauss-Newton on x, y, yaw).

    Args:
        source_xy: (N,2) points (m) of the scan to align, in its own (base) frame.
        target_xy: (M,2) points (m) of the reference scan, in its frame.
        T_init: initial ``T_target_source`` as a 3x3 (SE(2)) or 4x4 transform.
        max_correspondence_distance: nearest target point farther than this (m) = no match.
        iterations: maximum Gauss-Newton iterations.

    Returns:
        ``(T, overlap, rmse)``: ``T`` 4x4 planar ``T_target_source`` (``target ≈ T @ source``);
        ``overlap`` the ratio of source points with a correspondence at the final estimate;
        ``rmse`` the point-to-line RMS residual (m) of those correspondences (inf if none).
    """
    fit = icp_fit(source_xy, target_xy, T_init, None, max_correspondence_distance, iterations)
    return fit.T, fit.overlap, fit.rmse


@dataclass(frozen=True)
class IcpFit:
    T: np.ndarray  # 4x4 planar T_target_source
    overlap: float
    rmse: float
    information: np.ndarray  # 3x3 on (x, y, yaw): the scans' information (the prior's excluded)


def icp_fit(source_xy: np.ndarray, target_xy: np.ndarray, T_init: np.ndarray, prior: np.ndarray | None,
         max_correspondence_distance: float, iterations: int) -> IcpFit:
    """Point-to-line ICP, optionally with a Gaussian prior (3x3 information on x, y, yaw) at T_init.

    With a prior the estimate is the maximum a posteriori of scan and prior: along a direction
    the scans do not constrain (a straight featureless corridor) it stays at ``T_init``.
    The scan information is the Gauss-Newton matrix over the residual variance, divided by
    :data:`ICP_DEPENDENCE` because neighbouring beams' residuals are not independent (on the
    simulated scans this matches the measured errors: ICP alone is about 6x more accurate in
    yaw than the wheel odometry, bench/bench_registration.py).
    """
    src = np.asarray(source_xy, dtype=np.float64).reshape(-1, 2)
    tgt = np.asarray(target_xy, dtype=np.float64).reshape(-1, 2)
    T_init = np.asarray(T_init, dtype=np.float64)
    if T_init.shape == (3, 3):
        x0 = np.array([T_init[0, 2], T_init[1, 2], np.arctan2(T_init[1, 0], T_init[0, 0])])
    else:
        x0 = np.array(transforms.to_xy_yaw(T_init))
    P = np.zeros((3, 3)) if prior is None else np.asarray(prior, dtype=np.float64)
    state = x0.copy()
    if len(src) < ICP_MIN_CORRESPONDENCES or len(tgt) < ICP_MIN_CORRESPONDENCES:
        return IcpFit(transforms.from_xy_yaw(*state), 0.0, float("inf"), np.zeros((3, 3)))
    normals = line_normals(tgt)
    has_normal = np.isfinite(normals).all(axis=1)
    nearest = NearestWithin(tgt, max_correspondence_distance)
    grid = nearest.cells_of_points()
    gate_sq = nearest.bound_sq

    def linearise(state: np.ndarray):
        """Gauss-Newton system of the point-to-line residuals at ``state`` (Cauchy weights, so wrong
        correspondences inside the gate do not bias the fit): (H, g, sum w r^2, sum w, sum r^2,
        residuals used, source points matched)."""
        H, g, sums = np.zeros((3, 3)), np.zeros(3), np.zeros(3)
        used, n_matched = _icp_system(src, tgt, normals, has_normal, *grid, gate_sq, state[0], state[1], state[2],
                                      ICP_ROBUST_SCALE, H, g, sums)
        return H, g, sums[0], sums[1], sums[2], used, n_matched

    for _ in range(iterations):
        H, g, weighted_sq, weight, _, used, _ = linearise(state)
        if used < ICP_MIN_CORRESPONDENCES:
            break
        if prior is not None:
            scale = 1.0 / (ICP_DEPENDENCE * max(weighted_sq / weight, ICP_MIN_SIGMA ** 2))
            H = scale * H + P
            g = scale * g + P @ (state - x0)
        try:
            delta = np.linalg.solve(H, -g)
        except np.linalg.LinAlgError:
            break
        state = state + delta
        if np.hypot(delta[0], delta[1]) < ICP_CONVERGENCE_TRANSLATION and abs(delta[2]) < ICP_CONVERGENCE_ROTATION:
            break
    H, _, _, _, squares, used, n_matched = linearise(state)
    overlap = n_matched / len(src)
    rmse = float(np.sqrt(squares / used)) if used else float("inf")
    information = np.zeros((3, 3))
    if used >= ICP_MIN_CORRESPONDENCES:
        information = H / ICP_DEPENDENCE / max(rmse, ICP_MIN_SIGMA) ** 2
    return IcpFit(transforms.from_xy_yaw(*state), overlap, rmse, information)


@jit()
def _icp_system(src, tgt, normals, has_normal, points, order, keys, origin, cell, max_col, max_row, gate_sq,
                x, y, yaw, robust_scale, H, g, sums):
    """One ICP linearisation, compiled (issue 50: a dozen numpy calls an iteration were most of an
    ICP's time): each source point moved by (x, y, yaw), its nearest target point within the gate
    (:func:`nearest_in_cells`), and for those with a line normal the residual ``r = n . (moved -
    target)``, its Jacobian ``J = (n_x, n_y, n x (moved - t))`` and Cauchy weight ``w``, summed into
    ``H += w J J^T``, ``g += w J r`` and ``sums += (w r^2, w, r^2)``. Returns (residuals used,
    source points with a target point within the gate)."""
    c, s = np.cos(yaw), np.sin(yaw)
    moved = np.empty((src.shape[0], 2))
    for i in range(src.shape[0]):
        moved[i, 0] = src[i, 0] * c - src[i, 1] * s + x
        moved[i, 1] = src[i, 0] * s + src[i, 1] * c + y
    index = np.empty(src.shape[0], np.int64)
    nearest_in_cells(points, order, keys, origin, cell, max_col, max_row, moved, gate_sq, index)
    used = 0
    matched = 0
    J = np.empty(3)
    for i in range(src.shape[0]):
        j = index[i]
        if j < 0:
            continue
        matched += 1
        if not has_normal[j]:
            continue
        nx, ny = normals[j, 0], normals[j, 1]
        r = nx * (moved[i, 0] - tgt[j, 0]) + ny * (moved[i, 1] - tgt[j, 1])
        # d(moved)/d(yaw) = perpendicular of (moved - t).
        J[0], J[1], J[2] = nx, ny, -nx * (moved[i, 1] - y) + ny * (moved[i, 0] - x)
        w = 1.0 / (1.0 + (r / robust_scale) ** 2)
        for a in range(3):
            g[a] += w * J[a] * r
            for b in range(3):
                H[a, b] += w * J[a] * J[b]
        sums[0] += w * r * r
        sums[1] += w
        sums[2] += r * r
        used += 1
    return used, matched


def warm_up() -> None:
    """Compile the ICP (or load it from numba's cache) here rather than in a frame."""
    angles = np.linspace(0.0, 2.0 * np.pi, 60, endpoint=False)
    ring = np.column_stack([2.0 * np.cos(angles), 2.0 * np.sin(angles)])
    icp_fit(ring, ring, np.eye(4), None, 0.3, 2)


__all__ = ["IcpFit", "icp_2d", "icp_fit", "line_normals", "warm_up"]
