"""Graph optimisation (2014 §II-B) with gtsam, and g2o file input/output.

The paper used TORO with the newest node as the root of the tree: with several sessions each
having its own origin, the newest node is the one node always uniquely defined. Here the root is
held fixed by a strong prior at its given pose and every link becomes a ``BetweenFactor``
(Pose2 when the robot is planar, Pose3 otherwise), optimised by Levenberg-Marquardt,
Gauss-Newton or Powell's dogleg.

Robust mode: loop closures get dynamic covariance scaling (DCS, Agarwal et al. 2013). After the
optimisation each loop closure's DCS scale ``s = min(1, 2 phi / (phi + chi2_i))`` is computed from
its whitened squared error ``chi2_i``; those with ``s < robust_reject_scale`` are dropped as
inconsistent with the rest of the graph and the graph is re-optimised without them; a rejected loop
closure that agrees with the re-optimised solution is re-admitted (at most ``ROBUST_ROUNDS``
rounds), since DCS started from a poor initial guess can settle in a local minimum that leaves a
few true loop closures unsatisfied.

Graph content: only nodes in ``poses`` are optimised; links with an end outside ``poses`` are
ignored (the local map case: the node at the other end is in LTM). Nodes not connected to the
root raise :class:`~rtabmap_ros2.errors.OptimizationError`: callers pass one connected component
(``graph.connected_components``), since a disconnected part has no defined pose in the root's frame.

Information order: our 6x6 matrices are over (x, y, z, roll, pitch, yaw); gtsam's Pose3 tangent
is (rx, ry, rz, tx, ty, tz) and Pose2's is (x, y, theta).
"""

from __future__ import annotations

import logging
import time
import weakref
from collections.abc import Collection
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from rtabmap_ros2.core import files, transforms
from rtabmap_ros2.core.graph import Link, LinkType, bridges, chain_poses, connected_components
from rtabmap_ros2.core.params import GraphParams
from rtabmap_ros2.errors import OptimizationError

logger = logging.getLogger(__name__)

# DCS parameter Phi. Agarwal et al. (2013) suggest 1-10, but Phi is relative to the links'
# chi2 scale: measured in bench/bench_optimizers.py (manhattan + 50 false loop closures,
# reject below scale 0.1), Phi = 1 dropped 279 true loop closures, 10 dropped 14 (a local minimum
# from manhattan's poor initial guess), 100 dropped all 50 false and no true one, 1000 kept 4 false.
DCS_PHI = 100.0
# Standard deviation of the root's prior: "fixed" without a hard constraint (which LM handles badly).
ROOT_PRIOR_SIGMA = 1e-6  # m and rad
# Our (x, y, z, roll, pitch, yaw) index of each gtsam Pose3 tangent coordinate (rx, ry, rz, tx, ty, tz).
POSE3_FROM_OURS = [3, 4, 5, 0, 1, 2]
# Our index of each gtsam Pose2 tangent coordinate (x, y, theta).
POSE2_FROM_OURS = [0, 1, 5]
# g2o EDGE_SE3:QUAT errors are (x, y, z, qx, qy, qz): the quaternion's vector part is about half
# the rotation angle, so information on qxyz = 4 x information on the angles (cross terms x 2).
G2O_QUAT_PER_ANGLE = 0.5
# Robust mode: reject / re-optimise / re-admit rounds at most.
ROBUST_ROUNDS = 3
# Information matrices: largest asymmetry accepted (relative to the largest entry; float noise).
SYMMETRY_RTOL = 1e-6
# Nearest positive definite projection: smallest eigenvalue kept, relative to the largest one.
PD_FLOOR_RATIO = 1e-6
# Projected g2o edges named in the reader's warning (the rest are counted).
G2O_EDGES_NAMED = 10
# Relative error decrease at which the optimisers stop.
RELATIVE_ERROR_TOL = 1e-5
ABSOLUTE_ERROR_TOL = 1e-5


@dataclass
class OptimizationResult:
    """Optimised poses and statistics.

    Attributes:
        poses: node id -> 4x4 optimised pose (the root's frame, root at its given pose).
        chi2_initial: sum of whitened squared errors of every link at the initial guess.
        chi2_final: the same over the links kept (not rejected), at the optimised poses
            (plain Gaussian errors, no robust kernel).
        iterations: optimiser iterations (summed over the robust re-optimisation).
        rejected: loop closures dropped by the robust mode.
        switched_off: loop closures kept in the solution whose DCS scale ended below
            ``robust_reject_scale`` (bridges the robust mode may not drop, or ones left when its
            rounds ran out): barely weighted, so their error says nothing about the rest.
        time_s: wall time of the optimisation (s).
    """

    poses: dict[int, np.ndarray]
    chi2_initial: float
    chi2_final: float
    iterations: int
    rejected: list[Link] = field(default_factory=list)
    time_s: float = 0.0
    switched_off: list[Link] = field(default_factory=list)


# -- conversions ---------------------------------------------------------------------------------

def load_backend() -> None:
    """Import gtsam now: its first import takes 0.06-0.15 s, which would otherwise land in the
    processing time of the first frame that optimises a loop."""
    import gtsam  # noqa: F401


def _to_gtsam(T: np.ndarray, planar: bool):
    import gtsam

    if planar:
        x, y, yaw = transforms.to_xy_yaw(T)
        return gtsam.Pose2(x, y, yaw)
    return gtsam.Pose3(np.asarray(T, dtype=np.float64))


def gtsam_information(information: np.ndarray, planar: bool) -> np.ndarray:
    """Our 6x6 information (x, y, z, roll, pitch, yaw) in gtsam's tangent order (3x3 or 6x6)."""
    order = POSE2_FROM_OURS if planar else POSE3_FROM_OURS
    info = np.asarray(information, dtype=np.float64)[np.ix_(order, order)]
    return 0.5 * (info + info.T)


def _checked_information(links: list[Link], planar: bool) -> np.ndarray:
    """The links' information in gtsam's tangent order ((n, 3, 3) or (n, 6, 6)), every link
    checked at once (transform and information finite, information symmetric and positive
    definite); OptimizationError naming the first link that fails."""
    raw = np.stack([np.asarray(link.information, dtype=np.float64) for link in links])
    steps = np.stack([np.asarray(link.T_from_to, dtype=np.float64) for link in links])
    scale = np.maximum(np.abs(raw).max(axis=(1, 2), initial=0.0), np.finfo(float).tiny)
    with np.errstate(invalid="ignore"):
        finite = np.isfinite(raw).all(axis=(1, 2))
        symmetric = np.abs(raw - raw.transpose(0, 2, 1)).max(axis=(1, 2), initial=0.0) <= SYMMETRY_RTOL * scale
    order = POSE2_FROM_OURS if planar else POSE3_FROM_OURS
    info = raw[:, order][:, :, order]
    info = 0.5 * (info + info.transpose(0, 2, 1))
    positive = np.zeros(len(links), dtype=bool)
    positive[finite] = np.linalg.eigvalsh(info[finite]).min(axis=1) > 0
    steps_finite = np.isfinite(steps).all(axis=(1, 2))
    bad = ~(finite & symmetric & positive & steps_finite)
    if bad.any():
        i = int(np.argmax(bad))
        what = f"link {links[i].from_id} -> {links[i].to_id}"
        if not finite[i]:
            raise OptimizationError(f"{what}: information matrix has NaN or inf values ({raw[i].tolist()})")
        if not symmetric[i]:
            raise OptimizationError(f"{what}: information matrix is not symmetric ({raw[i].tolist()})")
        if not positive[i]:
            raise OptimizationError(
                f"{what}: information matrix is not positive definite ({info[i].tolist()}): check the link's "
                "covariance (every axis needs a finite variance > 0)")
        raise OptimizationError(f"{what}: transform has NaN or inf values")
    return info


# gtsam objects made from arrays or links still alive ((kind, id) -> (weak reference, planar,
# object)): a local map is optimised again at every loop closure with mostly the same links, and
# building the noise models (eigenvalue check), measurements and factors was most of the solve's
# Python time at 2,000 links.
_GTSAM_CACHE: dict[tuple[str, int], tuple] = {}


def _cached(kind: str, array, planar: bool, make):
    key = (kind, id(array))
    hit = _GTSAM_CACHE.get(key)
    if hit is not None and hit[0]() is array and hit[1] == planar:
        return hit[2]
    value = make(array, planar)
    try:
        ref = weakref.ref(array, lambda _, key=key: _GTSAM_CACHE.pop(key, None))
    except TypeError:  # not weakly referable (a nested list): no caching
        return value
    _GTSAM_CACHE[key] = (ref, planar, value)
    return value


def release(links) -> None:
    """Drop the cached gtsam objects of links that will not be optimised soon (their nodes left
    WM); they are made again if the links come back."""
    for link in links:
        for kind, source in (("factor", link), ("robust factor", link), ("noise", link.information)):
            hit = _GTSAM_CACHE.get((kind, id(source)))
            if hit is not None and hit[0]() is source:
                del _GTSAM_CACHE[(kind, id(source))]


def _plain_factors(links: list[Link], planar: bool, cache: bool = True) -> dict[int, object]:
    """id(link) -> the link's Gaussian ``BetweenFactor``, made once per link (cached unless
    ``cache`` is False): the links not made yet are checked together
    (:func:`_checked_information`), then one noise model per information array."""
    import gtsam

    factors = {}
    missing = []
    for link in links:
        hit = _GTSAM_CACHE.get(("factor", id(link))) if cache else None
        if hit is not None and hit[0]() is link and hit[1] == planar:
            factors[id(link)] = hit[2]
        else:
            missing.append(link)
    if missing:
        infos = _checked_information(missing, planar)
        steps = _gtsam_poses(np.stack([link.T_from_to for link in missing]), planar)
        between = gtsam.BetweenFactorPose2 if planar else gtsam.BetweenFactorPose3
        for link, info, step in zip(missing, infos, steps):
            if not cache:
                factors[id(link)] = between(link.from_id, link.to_id, step,
                                            gtsam.noiseModel.Gaussian.Information(info))
                continue
            noise = _cached("noise", link.information, planar,
                            lambda _, __, info=info: gtsam.noiseModel.Gaussian.Information(info))
            factors[id(link)] = _cached("factor", link, planar,
                                        lambda l, _, step=step, noise=noise: between(l.from_id, l.to_id, step, noise))
    return factors


def _robust_factor(link: Link, planar: bool, cache: bool = True):
    """The link's factor with DCS on its noise model (made after its plain factor, which checked it
    and cached the noise model)."""
    import gtsam

    noise = (_cached("noise", link.information, planar, lambda information, p: _checked_noise(link, p)) if cache
             else _checked_noise(link, planar))
    robust = gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.DCS(DCS_PHI), noise)
    return _between(link, planar, robust)


def _checked_noise(link: Link, planar: bool):
    import gtsam

    return gtsam.noiseModel.Gaussian.Information(_checked_information([link], planar)[0])


def is_symmetric(matrix: np.ndarray) -> bool:
    """True when ``matrix`` equals its transpose up to :data:`SYMMETRY_RTOL` of its largest entry."""
    m = np.asarray(matrix, dtype=np.float64)
    scale = max(float(np.abs(m).max(initial=0.0)), np.finfo(float).tiny)
    return bool(np.abs(m - m.T).max(initial=0.0) <= SYMMETRY_RTOL * scale)


def nearest_positive_definite(matrix: np.ndarray) -> np.ndarray | None:
    """The positive definite matrix nearest to a symmetric ``matrix`` (Frobenius norm), or None.

    Higham (1988), "Computing a nearest symmetric positive semidefinite matrix": keep the
    eigenvectors and clip the eigenvalues at 0; here at :data:`PD_FLOOR_RATIO` x the largest one,
    so the result is strictly positive definite (an axis with no information keeps a tiny one
    rather than none). None when no eigenvalue is positive: no direction carries information.
    """
    m = 0.5 * (np.asarray(matrix, dtype=np.float64) + np.asarray(matrix, dtype=np.float64).T)
    eigenvalues, vectors = np.linalg.eigh(m)
    largest = float(eigenvalues.max())
    if not largest > 0:
        return None
    clipped = np.maximum(eigenvalues, PD_FLOOR_RATIO * largest)
    out = (vectors * clipped) @ vectors.T
    return 0.5 * (out + out.T)


def _between(link: Link, planar: bool, noise):
    import gtsam

    factor = gtsam.BetweenFactorPose2 if planar else gtsam.BetweenFactorPose3
    return factor(link.from_id, link.to_id, _to_gtsam(link.T_from_to, planar), noise)


def _gtsam_poses(T: np.ndarray, planar: bool) -> list:
    """gtsam Pose2 (x, y, yaw) or Pose3 of each of (n, 4, 4) transforms."""
    import gtsam

    if planar:
        return [gtsam.Pose2(x, y, yaw) for x, y, yaw in _xy_yaws(T).tolist()]
    return [gtsam.Pose3(t) for t in np.asarray(T, dtype=np.float64)]


def _poses_of(values, planar: bool) -> dict[int, np.ndarray]:
    """Every pose of ``values`` as a 4x4 array, at once."""
    import gtsam

    keys = list(values.keys())
    out = np.zeros((len(keys), 4, 4))
    out[:, 3, 3] = 1.0
    if planar:
        xyt = gtsam.utilities.extractPose2(values).reshape(-1, 3)
        c, s = np.cos(xyt[:, 2]), np.sin(xyt[:, 2])
        out[:, 0, 0], out[:, 0, 1], out[:, 1, 0], out[:, 1, 1] = c, -s, s, c
        out[:, 2, 2] = 1.0
        out[:, :2, 3] = xyt[:, :2]
    else:
        rt = gtsam.utilities.extractPose3(values).reshape(-1, 12)
        out[:, :3, :3] = rt[:, :9].reshape(-1, 3, 3)
        out[:, :3, 3] = rt[:, 9:]
    return dict(zip(keys, out))


# -- optimisation --------------------------------------------------------------------------------

def optimize(poses: dict[int, np.ndarray], links: list[Link], root_id: int, params: GraphParams,
             planar: bool, rejected_before: Collection[tuple[int, int]] = (), cache: bool = True) -> OptimizationResult:
    """Optimise a pose graph with the root held at its given pose.

    Args:
        poses: node id -> 4x4 initial pose ``T_map_base`` (callers chain links with
            ``graph.chain_poses`` for multi-session graphs).
        links: constraints (``pose_to = pose_from @ T_from_to``); links with an end not in
            ``poses`` are ignored.
        root_id: node fixed at its given pose (2014 §II-B: the newest node).
        params: optimiser, iterations, robust settings.
        planar: optimise x, y, yaw only (Pose2); else full SE(3) (Pose3).
        rejected_before: keys of loop closures a previous solution of this graph rejected
            (robust mode): they start out of the solution, and the robust rounds re-admit those
            that agree with it. Without it a re-solve of a local map first solved with every
            link it had rejected before, which DCS switched off again, then solved a second
            time without them: two solves where one does.
        cache: keep the gtsam objects made for the links for later calls with the same links (a
            local map is solved again at every loop closure); a one-off solve (``rtabmap-ros2
            optimize``) skips the bookkeeping (0.2 s of city10000's 20,687 links).

    Returns:
        :class:`OptimizationResult`.

    Raises:
        OptimizationError: unknown root, nodes not connected to the root, bad information
            matrix, or a solver failure.
    """
    import gtsam

    start = time.perf_counter()
    if root_id not in poses:
        raise OptimizationError(f"root node {root_id} is not among the {len(poses)} poses to optimise")
    used = [link for link in links if link.from_id in poses and link.to_id in poses
            and link.from_id != link.to_id]
    components = connected_components(poses.keys(), used)
    if len(components) > 1:
        root_component = next(c for c in components if root_id in c)
        raise OptimizationError(
            f"{len(poses) - len(root_component)} of {len(poses)} nodes are not connected to the root "
            f"{root_id}: pass one connected component (graph.connected_components)")
    if not used:
        return OptimizationResult({k: np.array(v, dtype=float) for k, v in poses.items()}, 0.0, 0.0, 0,
                                  [], time.perf_counter() - start)

    initial = gtsam.Values()
    for node_id, pose in zip(poses, _gtsam_poses(np.stack(list(poses.values())), planar)):
        initial.insert(node_id, pose)
    # One Gaussian factor per link, made once: chi2 and the DCS scales are read from them.
    plain = _plain_factors(used, planar, cache)
    robust = {}
    if params.robust:
        # DCS on loop closures (Agarwal et al. 2013), the paper's successors' choice.
        robust = {id(link): (_cached("robust factor", link, planar, _robust_factor) if cache
                             else _robust_factor(link, planar, cache=False))
                  for link in used if link.type.is_loop_closure}
    factors = {**plain, **robust}
    chi2_initial = _chi2(plain.values(), initial)

    kept = list(used)
    rejected: list[Link] = []
    if params.robust and rejected_before:
        out_before = [link for link in used if link.type.is_loop_closure and link.key() in rejected_before]
        trial = [link for link in used if not (link.type.is_loop_closure and link.key() in rejected_before)]
        # Only while the rest holds the graph together (a bridge is never dropped).
        if out_before and len(connected_components(poses.keys(), trial)) == 1:
            kept, rejected = trial, out_before
    values, iterations = _solve(kept, factors, initial, root_id, poses[root_id], params, planar)
    if params.robust:
        # Robust (DCS) pass: drop loop closures the rest of the graph disagrees with, re-optimise.
        # From a poor initial guess DCS can leave a few true loop closures unsatisfied: rejected
        # links that agree with the re-optimised solution are re-admitted (bounded rounds).
        threshold = params.robust_reject_scale
        for _ in range(ROBUST_ROUNDS):
            scales = {key: _dcs_scale(plain[key], values) for key in robust}
            bad = sorted((link for link in kept if link.type.is_loop_closure and scales[id(link)] < threshold),
                         key=lambda link: scales[id(link)])
            good_again = [link for link in rejected if scales[id(link)] >= threshold]
            if not bad and not good_again:
                break
            readmitted = {id(link) for link in good_again}
            rejected = [link for link in rejected if id(link) not in readmitted]
            out = {id(r) for r in rejected}
            kept = [link for link in used if id(link) not in out]
            # Worst first, but never a link whose removal disconnects the graph (a bridge): with
            # no other path between its ends, nothing in the graph contradicts it.
            # Usually dropping every bad link but the bridges keeps the graph connected (then each
            # was no bridge at its turn either); otherwise one at a time, bridges recomputed.
            cut = {id(kept[i]) for i in bridges(poses.keys(), kept)} if bad else set()
            dropped = [link for link in bad if id(link) not in cut]
            out = {id(d) for d in dropped}
            trial = [k for k in kept if id(k) not in out]
            if dropped and len(connected_components(poses.keys(), trial)) > 1:
                dropped, trial = [], kept
                for link in bad:
                    cut = {id(trial[i]) for i in bridges(poses.keys(), trial)}
                    if id(link) not in cut:
                        trial = [k for k in trial if k is not link]
                        dropped.append(link)
            kept = trial
            if not dropped and not good_again:
                break
            rejected += dropped
            values, more = _solve(kept, factors, values, root_id, poses[root_id], params, planar)
            iterations += more
        else:  # rounds used up: the last solve moved the values the scales were taken at
            scales = {key: _dcs_scale(plain[key], values) for key in robust}
        if rejected:
            logger.debug("robust optimisation rejected %d loop closure(s): %s", len(rejected),
                        [(l.from_id, l.to_id) for l in rejected])
        # Both breaks above leave ``scales`` taken at the final values.
        switched_off = [link for link in kept if id(link) in robust and scales[id(link)] < threshold]
    else:
        switched_off = []
    chi2_final = _chi2((plain[id(link)] for link in kept), values)
    out = _poses_of(values, planar)
    return OptimizationResult(out, chi2_initial, chi2_final, iterations, rejected, time.perf_counter() - start,
                              switched_off)


def _solve(links: list[Link], factors: dict, initial, root_id: int, root_pose: np.ndarray,
           params: GraphParams, planar: bool):
    """Run the optimiser on the links' factors (``factors``: id(link) -> factor, robust on loop
    closures if asked) with the root held by a strong prior."""
    import gtsam

    graph = gtsam.NonlinearFactorGraph()
    dim = 3 if planar else 6
    root_noise = gtsam.noiseModel.Isotropic.Sigma(dim, ROOT_PRIOR_SIGMA)
    prior = gtsam.PriorFactorPose2 if planar else gtsam.PriorFactorPose3
    graph.add(prior(root_id, _to_gtsam(root_pose, planar), root_noise))
    for link in links:
        graph.add(factors[id(link)])
    if params.optimizer == "lm":
        opt_params = gtsam.LevenbergMarquardtParams()
        cls = gtsam.LevenbergMarquardtOptimizer
    elif params.optimizer == "gn":
        opt_params = gtsam.GaussNewtonParams()
        cls = gtsam.GaussNewtonOptimizer
    else:
        opt_params = gtsam.DoglegParams()
        cls = gtsam.DoglegOptimizer
    opt_params.setMaxIterations(params.iterations)
    opt_params.setRelativeErrorTol(RELATIVE_ERROR_TOL)
    opt_params.setAbsoluteErrorTol(ABSOLUTE_ERROR_TOL)
    optimizer = cls(graph, initial, opt_params)
    try:
        values = optimizer.optimize()
    except RuntimeError as exc:
        detail = " ".join(str(exc).split()).split(" Thrown when")[0].rstrip(".")
        raise OptimizationError(
            f"{params.optimizer} optimisation of {len(links)} links failed: {detail}; an undamped solver (gn, "
            "dogleg) can fail from a poor initial guess: use lm, or check that every node is constrained") from exc
    if not np.isfinite(graph.error(values)):
        raise OptimizationError(f"{params.optimizer} optimisation diverged (non-finite error)")
    return values, int(optimizer.iterations())


def _chi2(factors, values) -> float:
    """Sum of whitened squared errors of Gaussian factors (2 x gtsam's error)."""
    return 2.0 * float(sum(factor.error(values) for factor in factors))


def _dcs_scale(factor, values) -> float:
    """DCS scale ``min(1, 2 phi / (phi + chi2_i))`` of one link's Gaussian factor at ``values``."""
    chi2_i = 2.0 * factor.error(values)
    return min(1.0, 2.0 * DCS_PHI / (DCS_PHI + chi2_i))


# -- g2o files -----------------------------------------------------------------------------------

def _upper(matrix: np.ndarray) -> list[float]:
    n = matrix.shape[0]
    return [float(matrix[i, j]) for i in range(n) for j in range(i, n)]


def _se3_g2o_scaling() -> np.ndarray:
    """Diagonal map from our (x, y, z, roll, pitch, yaw) errors to g2o's (x, y, z, qx, qy, qz)."""
    return np.diag([1.0, 1.0, 1.0] + [G2O_QUAT_PER_ANGLE] * 3)


def read_g2o(path) -> tuple[dict[int, np.ndarray], list[Link], bool]:
    """Read a g2o pose graph (VERTEX_SE2/EDGE_SE2 or VERTEX_SE3:QUAT/EDGE_SE3:QUAT).

    Information matrices: one that is symmetric (g2o
    stores the upper triangle) but not positive definite is replaced by the nearest positive
    definite matrix (:func:`nearest_positive_definite`), with one warning naming those edges.

    Returns:
        ``(poses, links, planar)``: vertex poses (4x4); links with their 6x6 information over
        (x, y, z, roll, pitch, yaw) (planar files: z, roll, pitch get the x information's value,
        unused by Pose2); ``planar`` True for SE2 files. A file with edges only (CSAIL.g2o) gets
        poses chained from the first edge's from vertex. Edges are typed NEIGHBOR when they join
        consecutive ids, LOOP_INTRA otherwise.

    Raises:
        OptimizationError: unreadable or binary file; unknown, malformed or non-finite lines,
            an information matrix with no positive eigenvalue (each naming the line); an edge
            to a vertex the file does not define (naming the edge).
    """
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise OptimizationError(f"cannot read g2o file {path}: {exc.strerror}") from exc
    try:
        lines = data.decode("utf-8").splitlines()
    except UnicodeDecodeError as exc:
        raise OptimizationError(
            f"{path} is not a g2o text file (byte {exc.start} is not text): expected lines such as "
            "'VERTEX_SE2 id x y theta' and 'EDGE_SE2 i j dx dy dtheta I11 I12 I13 I22 I23 I33'") from exc
    # Lines grouped by element (line numbers kept for the messages), then each group read at once.
    groups: dict[str, tuple[list[int], list[list[str]]]] = {tag: ([], []) for tag in _G2O_FIELDS}
    planar: bool | None = None
    for number, line in enumerate(lines, 1):
        f = line.split()
        if not f or f[0].startswith("#") or f[0] in _G2O_IGNORED:
            continue
        tag = f[0]
        try:
            if tag not in _G2O_FIELDS:
                raise ValueError(f"unsupported element {tag}")
            element_planar = tag.endswith("SE2")
            if planar is not None and element_planar != planar:
                raise ValueError(f"{tag} in a file of {'SE2' if planar else 'SE3:QUAT'} elements")
        except ValueError as exc:
            raise OptimizationError(f"{path}:{number}: cannot read {line.strip()[:60]!r}: {exc}") from exc
        planar = element_planar
        numbers, rows = groups[tag]
        numbers.append(number)
        rows.append(f)
    if planar is None:
        raise OptimizationError(f"{path} holds no vertex or edge")
    vertex_tag, edge_tag = ("VERTEX_SE2", "EDGE_SE2") if planar else ("VERTEX_SE3:QUAT", "EDGE_SE3:QUAT")
    numbers, rows = groups[vertex_tag]
    vertex_ids, v = _g2o_block(path, lines, vertex_tag, numbers, rows)
    poses: dict[int, np.ndarray] = {}
    if len(rows):
        if planar:
            vertex_poses = transforms.from_xy_yaws(v)
        else:
            vertex_poses = _g2o_transforms(path, lines, numbers, v[:, :3], v[:, 3:7])
        poses = dict(zip(vertex_ids[:, 0].tolist(), vertex_poses))
    edge_numbers, rows = groups[edge_tag]
    ids, v = _g2o_block(path, lines, edge_tag, edge_numbers, rows)
    if planar:
        steps = transforms.from_xy_yaws(v[:, :3])
        upper = v[:, 3:]
    else:
        steps = _g2o_transforms(path, lines, edge_numbers, v[:, :3], v[:, 3:7])
        upper = v[:, 7:]
    info, projected_at = _g2o_information(path, lines, edge_numbers, upper, 3 if planar else 6)
    if planar:
        # Pose2 uses x, y, yaw; z, roll, pitch get the x information (unused).
        information = np.eye(6) * info[:, :1, :1]
        rows, cols = np.ix_(POSE2_FROM_OURS, POSE2_FROM_OURS)
        information[:, rows, cols] = info
    else:
        scale = np.diag(_se3_g2o_scaling())
        information = info * np.outer(scale, scale)
    pairs = ids.tolist()
    links = [Link(i, j, _g2o_type(i, j), T, I) for (i, j), T, I in zip(pairs, steps, information)]
    if poses:
        known = np.array(sorted(poses), dtype=np.int64)
        missing = ~np.isin(ids, known)
        if missing.any():
            k = int(np.argmax(missing.any(axis=1)))
            link = links[k]
            vertex = link.from_id if missing[k, 0] else link.to_id
            raise OptimizationError(
                f"{path}:{edge_numbers[k]}: edge {link.from_id} -> {link.to_id} refers to vertex {vertex}, "
                "which the file does not define (no VERTEX line): fix or remove the edge")
    elif links:
        # Edges only (CSAIL.g2o): initial guess by chaining the edges from the first vertex.
        first = int(ids.min())
        poses = chain_poses(first, transforms.identity(), links)
    if projected_at:
        named = ", ".join(f"line {edge_numbers[k]} (edge {links[k].from_id} -> {links[k].to_id})"
                          for k in projected_at[:G2O_EDGES_NAMED])
        more = f" and {len(projected_at) - G2O_EDGES_NAMED} more" if len(projected_at) > G2O_EDGES_NAMED else ""
        logger.warning(
            "%s: %d edge(s) have a symmetric information matrix that is not positive definite, replaced by "
            "the nearest positive definite matrix (eigenvalues clipped at %g x the largest): %s%s",
            path, len(projected_at), PD_FLOOR_RATIO, named, more)
    return poses, links, planar


# Numbers after the tag of each g2o element: (ids, floats).
_G2O_FIELDS = {"VERTEX_SE2": (1, 3), "EDGE_SE2": (2, 3 + 6),
               "VERTEX_SE3:QUAT": (1, 7), "EDGE_SE3:QUAT": (2, 7 + 21)}
# g2o elements read and ignored (the root is the lowest id, not a FIX line).
_G2O_IGNORED = ("FIX", "PARAMS_SE3OFFSET")


def _g2o_numbers(f: list[str], tag: str) -> tuple[list[int], list[float]]:
    """The ids and the finite values of a g2o line (ValueError naming what is wrong)."""
    n_ids, n_values = _G2O_FIELDS[tag]
    if len(f) - 1 != n_ids + n_values:
        raise ValueError(f"{tag} needs {n_ids + n_values} numbers ({n_ids} id(s), {n_values} values), "
                         f"found {len(f) - 1}")
    ids = [int(x) for x in f[1:1 + n_ids]]
    values = [float(x) for x in f[1 + n_ids:]]
    if not np.all(np.isfinite(values)):
        raise ValueError("NaN or inf value")
    return ids, values


def _g2o_line_error(path: Path, lines: list[str], number: int, reason: str) -> OptimizationError:
    return OptimizationError(f"{path}:{number}: cannot read {lines[number - 1].strip()[:60]!r}: {reason}")


def _g2o_block(path: Path, lines: list[str], tag: str, numbers: list[int],
               rows: list[list[str]]) -> tuple[np.ndarray, np.ndarray]:
    """Ids ((n, ids) int64) and values ((n, values) float64) of every line of one element; a bad
    line is found again line by line (:func:`_g2o_numbers`) to name it."""
    n_ids, n_values = _G2O_FIELDS[tag]
    if not rows:
        return np.zeros((0, n_ids), dtype=np.int64), np.zeros((0, n_values))
    try:
        if any(len(f) != 1 + n_ids + n_values for f in rows):
            raise ValueError("field count")
        ids = np.array([f[1:1 + n_ids] for f in rows], dtype=np.int64)
        values = np.array([f[1 + n_ids:] for f in rows], dtype=np.float64)
        finite = np.isfinite(values).all(axis=1)
        if not finite.all():
            raise ValueError("not finite")
    except (ValueError, OverflowError):
        for number, f in zip(numbers, rows):
            try:
                _g2o_numbers(f, tag)
            except (ValueError, OverflowError) as exc:
                raise _g2o_line_error(path, lines, number, str(exc)) from exc
        raise   # unreachable: the line-by-line reading finds the line
    return ids, values


def _g2o_transforms(path: Path, lines: list[str], numbers: list[int], xyz: np.ndarray,
                    quat_xyzw: np.ndarray) -> np.ndarray:
    """(n, 4, 4) transforms of g2o SE3 lines; the line of a quaternion that is no rotation named."""
    try:
        return transforms.from_xyz_quats_xyzw(xyz, quat_xyzw)
    except ValueError:
        norms = np.linalg.norm(quat_xyzw, axis=1)
        k = int(np.argmax(~(np.isfinite(norms) & (norms >= 1e-9))))
        raise _g2o_line_error(path, lines, numbers[k],
                              f"quaternion {quat_xyzw[k].tolist()} is not a rotation (norm {norms[k]})") from None


def _g2o_information(path: Path, lines: list[str], numbers: list[int], upper: np.ndarray,
                     dim: int) -> tuple[np.ndarray, list[int]]:
    """(n, dim, dim) symmetric information of g2o edges from their upper triangles, those not
    positive definite projected (:func:`nearest_positive_definite`); and the indices projected."""
    info = np.zeros((len(upper), dim, dim))
    rows, cols = np.triu_indices(dim)
    info[:, rows, cols] = upper
    info[:, cols, rows] = upper
    if not len(info):
        return info, []
    projected = np.flatnonzero(~(np.linalg.eigvalsh(info).min(axis=1) > 0)).tolist()
    for k in projected:
        nearest = nearest_positive_definite(info[k])
        if nearest is None:
            raise _g2o_line_error(path, lines, numbers[k],
                                  "information matrix has no positive eigenvalue (no axis carries information)")
        info[k] = nearest
    return info, projected


def _g2o_type(i: int, j: int) -> LinkType:
    return LinkType.NEIGHBOR if abs(i - j) == 1 else LinkType.LOOP_INTRA


def write_g2o(path, poses: dict[int, np.ndarray], links: list[Link], planar: bool) -> None:
    """Write a g2o pose graph (SE2 when ``planar``, else SE3:QUAT); inverse of :func:`read_g2o`."""
    ids = sorted(poses)
    T = np.stack([poses[i] for i in ids]) if ids else np.zeros((0, 4, 4))
    steps = np.stack([link.T_from_to for link in links]) if links else np.zeros((0, 4, 4))
    info = np.stack([np.asarray(link.information, dtype=np.float64) for link in links]) if links \
        else np.zeros((0, 6, 6))
    if planar:
        vertex_values = _xy_yaws(T)
        order = POSE2_FROM_OURS
        edge_values = _xy_yaws(steps)
    else:
        vertex_values = np.column_stack([T[:, :3, 3], transforms.quats_xyzw(T)]) if ids else np.zeros((0, 7))
        scale = 1.0 / np.diag(_se3_g2o_scaling())
        info = info * np.outer(scale, scale)
        order = list(range(6))
        edge_values = np.column_stack([steps[:, :3, 3], transforms.quats_xyzw(steps)]) if links \
            else np.zeros((0, 7))
    rows, cols = np.triu_indices(len(order))
    upper = info[:, np.asarray(order)[rows], np.asarray(order)[cols]]
    vertex_tag, edge_tag = ("VERTEX_SE2", "EDGE_SE2") if planar else ("VERTEX_SE3:QUAT", "EDGE_SE3:QUAT")
    vertex_line = vertex_tag + " %d" + " %.9g" * vertex_values.shape[1]
    edge_line = edge_tag + " %d %d" + " %.9g" * (edge_values.shape[1] + upper.shape[1])
    out = [vertex_line % (i, *row) for i, row in zip(ids, vertex_values.tolist())]
    out += [edge_line % (link.from_id, link.to_id, *row)
            for link, row in zip(links, np.column_stack([edge_values, upper]).tolist())]
    try:
        files.write_text(path, "\n".join(out) + "\n")
    except OSError as exc:
        raise OptimizationError(f"cannot write g2o file {path}: {exc.strerror}") from exc


def _xy_yaws(T: np.ndarray) -> np.ndarray:
    """(n, 3) planar parts (x, y, yaw) of (n, 4, 4) transforms."""
    return np.column_stack([T[:, 0, 3], T[:, 1, 3], np.arctan2(T[:, 1, 0], T[:, 0, 0])])


__all__ = ["OptimizationResult", "gtsam_information", "is_symmetric", "nearest_positive_definite", "optimize",
           "read_g2o", "write_g2o"]
