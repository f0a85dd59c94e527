"""Graph optimisation (2014 §II-B) with gtsam.

The paper used TORO with the newest node as the root of the tree: with several sessions each
having its own origin, the newest node is the one node always uniquely defined. Here the root is
held fixed by a strong prior at its given pose and every link becomes a ``BetweenFactor``
(Pose2 when the robot is planar, Pose3 otherwise), optimised by Levenberg-Marquardt,
Gauss-Newton or Powell's dogleg. Dogleg starts as Gauss-Newton (a wide trust region) and needs one
factorisation per iteration, where Levenberg-Marquardt factorises again for every damping it tries;
where the Gauss-Newton system is singular it hands over to Levenberg-Marquardt.

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

Information matrices are used as given, as gtsam's own g2o reader uses them: each link's noise
model is ``noiseModel.Gaussian.Information`` of its matrix (in gtsam's order). One that is not
positive definite is accepted: gtsam takes Eigen's Cholesky factor ``R`` of it, which stops at the
first pivot that is not positive and keeps the matrix's own entries from there on, and minimises
``|R e|^2`` (:func:`information_check`). Matrices gtsam cannot whiten with (no positive
eigenvalue; diagonal with a negative entry, which gtsam turns into a NaN sigma) are refused.
"""

from __future__ import annotations

import logging
import time
import weakref
from collections.abc import Collection
from dataclasses import dataclass, field
from typing import NamedTuple, Optional

import numpy as np

from rtabmap_ros2.core import transforms
from rtabmap_ros2.core.graph import Link, PoseStack, bridges, connected_components
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
# Robust mode: reject / re-optimise / re-admit rounds at most.
ROBUST_ROUNDS = 3
# Information matrices: largest asymmetry accepted (relative to the largest entry; float noise).
SYMMETRY_RTOL = 1e-6
# gtsam's noiseModel.Gaussian.Information reads a matrix whose off-diagonal entries are all at most
# this (absolute) as diagonal, one sigma per axis (checkIfDiagonal, gtsam/linear/NoiseModel.cpp).
GTSAM_DIAGONAL_TOL = 1e-9
# Relative error decrease at which the optimisers stop.
RELATIVE_ERROR_TOL = 1e-5
ABSOLUTE_ERROR_TOL = 1e-5
# Dogleg: trust region radius of the first step (tangent units, rad and m together). Large, so the
# first step is Gauss-Newton's unless it fails; a failed trial halves the radius and costs one
# error evaluation, no new factorisation (GTSAM's DoglegOptimizerImpl). gtsam's default 1.0 held
# the first steps short: bench_optimizers.py, 5-13 iterations where Gauss-Newton takes 3-6
# (city10000 13 vs 6, sphere2500 12 vs 6, parking-garage 10 vs 4); 1e4 and 1e8 took the same.
DOGLEG_DELTA_INITIAL = 1e4
# gtsam's message when a Gauss-Newton system is singular (IndeterminateSystemException): dogleg,
# which solves it undamped, hands over to Levenberg-Marquardt from where it stopped, with Nielsen's
# damping update (gtsam's useFixedLambdaFactor False) rather than gtsam's default x10 / /10: on
# graphs like cubicle.g2o the default alternates a failed and a successful damping every iteration
# (cubicle: 201 factorisations in its 100 iterations, stopped short of the optimum) where Nielsen's
# took 77 to the optimum; on the other benchmarks the same iterations or up to 3 more.
INDETERMINATE_SYSTEM = "Indeterminate linear system"
# Optimizer auto: Levenberg-Marquardt (gtsam's defaults) as long as its damping works, dogleg once a
# damping has failed in this many iterations running. On 9 of the 10 benchmarks LM spends a failed
# damping in its first iteration at most (torus3D: 4 there, none after), and Gauss-Newton-like steps
# follow; on cubicle.g2o one fails in every iteration (201 factorisations in 100 iterations), where
# dogleg, retrying along one factorisation, reaches the optimum in 9 iterations. Dogleg is not
# used throughout: its iterations cost 1.2-1.7x LM's in-process (gradient search and error of the
# Bayes tree; manhattan, city10000, sphere2500 at the same iteration counts) and it needs 40
# iterations on torus3D where LM needs 30.
LM_FAILING_ITERATIONS = 2
# ... and only while the damping is at least this times its initial value (gtsam's 1e-5). On
# w20000 (gtsam's example data, 20,061 poses) LM fails one damping an iteration at 1e-10, close to
# Gauss-Newton, and converges in 14 iterations; handed to dogleg there it took 27 and 2.5x the time.
LM_DAMPED = 1.0


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
        stack: the same poses as one :class:`PoseStack` when the solver made them so (the checks
            after a solve read them as arrays), else None.
    """

    poses: dict[int, np.ndarray]
    chi2_initial: float
    chi2_final: float
    iterations: int
    rejected: list[Link] = field(default_factory=list)
    time_s: float = 0.0
    switched_off: list[Link] = field(default_factory=list)
    stack: Optional[PoseStack] = None

    def pose_stack(self) -> PoseStack:
        """The poses as one stack (made from ``poses`` when the solver did not give one)."""
        return self.stack if self.stack is not None else PoseStack(self.poses)


# -- conversions ---------------------------------------------------------------------------------

def load_backend() -> None:
    """Import gtsam now: its first import takes 0.06-0.15 s, which would otherwise land in the
    processing time of the first frame that optimises a loop."""
    import gtsam  # noqa: F401


def _to_gtsam(T: np.ndarray, planar: bool):
    """gtsam Pose2 or Pose3 of one 4x4 transform (:func:`_gtsam_poses`)."""
    return _gtsam_poses(np.asarray(T, dtype=np.float64)[None], planar)[0]


def gtsam_information(information: np.ndarray, planar: bool) -> np.ndarray:
    """Our 6x6 information (x, y, z, roll, pitch, yaw) in gtsam's tangent order (3x3 or 6x6),
    symmetrised; a stack (n, 6, 6) gives (n, 3, 3) or (n, 6, 6)."""
    order = POSE2_FROM_OURS if planar else POSE3_FROM_OURS
    info = np.asarray(information, dtype=np.float64)[..., order, :][..., :, order]
    return 0.5 * (info + np.swapaxes(info, -1, -2))


class InformationCheck(NamedTuple):
    """How gtsam's ``noiseModel.Gaussian.Information`` reads a stack of information matrices.

    Attributes:
        positive_definite: (n,) bool; the others are used as given (see :func:`information_check`).
        unusable: index of the first matrix gtsam cannot whiten with, or None.
        reason: why that one is unusable ("" when none is).
    """

    positive_definite: np.ndarray
    unusable: int | None
    reason: str


def information_check(information: np.ndarray) -> InformationCheck:
    """Which of (n, d, d) symmetric finite information matrices are positive definite, and the
    first one gtsam cannot whiten with.

    gtsam's ``Gaussian.Information`` (what its ``readG2o`` builds every edge's noise model with)
    takes a matrix that is not positive definite as it is: Eigen's Cholesky factor stops at the
    first pivot that is not positive and keeps the matrix's own entries from that pivot on, so
    ``R`` weighs those axes by the entries rather than their square roots, and the error
    ``|R e|^2`` stays >= 0 (``test_optimizer.py`` checks this on gtsam itself). Unusable: a matrix
    with no positive eigenvalue (no axis carries information), and a diagonal one (gtsam's test:
    every off-diagonal entry within :data:`GTSAM_DIAGONAL_TOL`) with a negative entry, whose sigma
    gtsam computes as NaN. Congruent matrices (reordered, or axes scaled) get the same answer.
    """
    info = np.asarray(information, dtype=np.float64)
    eigenvalues = np.linalg.eigvalsh(info)   # ascending
    positive_definite = eigenvalues[:, 0] > 0
    if positive_definite.all():
        return InformationCheck(positive_definite, None, "")
    others = np.flatnonzero(~positive_definite)
    no_information = ~(eigenvalues[others, -1] > 0)
    diagonal_entries = np.diagonal(info[others], axis1=1, axis2=2)
    off_diagonal = np.abs(info[others] - diagonal_entries[:, :, None] * np.eye(info.shape[1])).max(axis=(1, 2))
    negative_diagonal = (off_diagonal <= GTSAM_DIAGONAL_TOL) & (diagonal_entries < 0).any(axis=1)
    unusable = no_information | negative_diagonal
    if not unusable.any():
        return InformationCheck(positive_definite, None, "")
    j = int(np.argmax(unusable))
    if no_information[j]:
        reason = "information matrix has no positive eigenvalue (no axis carries information)"
    else:
        reason = (f"information matrix is diagonal with a negative entry ({diagonal_entries[j].tolist()}): gtsam's "
                  "noise model of it has a NaN sigma on that axis")
    return InformationCheck(positive_definite, int(others[j]), reason)


def _checked_information(links: list[Link], planar: bool) -> tuple[np.ndarray, np.ndarray]:
    """The links' information in gtsam's tangent order ((n, 3, 3) or (n, 6, 6)) and their
    transforms ((n, 4, 4)), every link checked at once (transform and information finite,
    information symmetric and usable by gtsam: :func:`information_check`; not positive definite is
    accepted, as gtsam accepts it); OptimizationError naming the first link that fails."""
    raw = np.stack([np.asarray(link.information, dtype=np.float64) for link in links])
    steps = np.stack([np.asarray(link.T_from_to, dtype=np.float64) for link in links])
    scale = np.maximum(np.abs(raw).max(axis=(1, 2), initial=0.0), np.finfo(float).tiny)
    with np.errstate(invalid="ignore"):
        finite = np.isfinite(raw).all(axis=(1, 2))
        symmetric = np.abs(raw - raw.transpose(0, 2, 1)).max(axis=(1, 2), initial=0.0) <= SYMMETRY_RTOL * scale
    info = gtsam_information(raw, planar)
    usable = finite.copy()
    check = information_check(info[finite])
    if check.unusable is not None:
        usable[np.flatnonzero(finite)[check.unusable]] = False
    steps_finite = np.isfinite(steps).all(axis=(1, 2))
    bad = ~(finite & symmetric & usable & steps_finite)
    if bad.any():
        i = int(np.argmax(bad))
        what = f"link {links[i].from_id} -> {links[i].to_id}"
        if not finite[i]:
            raise OptimizationError(f"{what}: information matrix has NaN or inf values ({raw[i].tolist()})")
        if not symmetric[i]:
            raise OptimizationError(f"{what}: information matrix is not symmetric ({raw[i].tolist()})")
        if not usable[i]:
            raise OptimizationError(
                f"{what}: {information_check(info[i:i + 1]).reason}: check the link's covariance "
                "(every axis needs a finite variance > 0)")
        raise OptimizationError(f"{what}: transform has NaN or inf values")
    return info, steps


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
        infos, steps = _checked_information(missing, planar)
        steps = _gtsam_poses(steps, planar)
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

    return gtsam.noiseModel.Gaussian.Information(_checked_information([link], planar)[0][0])


def _between(link: Link, planar: bool, noise):
    import gtsam

    factor = gtsam.BetweenFactorPose2 if planar else gtsam.BetweenFactorPose3
    return factor(link.from_id, link.to_id, _to_gtsam(link.T_from_to, planar), noise)


def _gtsam_poses(T: np.ndarray, planar: bool) -> list:
    """gtsam Pose2 (x, y, yaw) or Pose3 of each of (n, 4, 4) transforms."""
    import gtsam

    if planar:
        return [gtsam.Pose2(x, y, yaw) for x, y, yaw in transforms.to_xy_yaws(T).tolist()]
    T = np.asarray(T, dtype=np.float64)
    # From (Rot3, translation): a quarter faster than from the 4x4 matrix (bench: 8,000 poses).
    return [gtsam.Pose3(gtsam.Rot3(R), t) for R, t in zip(T[:, :3, :3], T[:, :3, 3])]


def _pose_stack(values, planar: bool) -> tuple[list[int], np.ndarray]:
    """The keys of ``values`` and their poses as one (n, 4, 4) array (key order)."""
    return list(values.keys()), _stack_of_vectors(_pose_vectors(values, planar), planar)


def _stack_of_vectors(vectors: np.ndarray, planar: bool) -> np.ndarray:
    """(n, 4, 4) poses of :func:`_pose_vectors`' (n, 3) x, y, yaw or (n, 12) rotation and translation."""
    out = np.zeros((len(vectors), 4, 4))
    out[:, 3, 3] = 1.0
    if planar:
        c, s = np.cos(vectors[:, 2]), np.sin(vectors[:, 2])
        out[:, 0, 0], out[:, 0, 1], out[:, 1, 0], out[:, 1, 1] = c, -s, s, c
        out[:, 2, 2] = 1.0
        out[:, :2, 3] = vectors[:, :2]
    else:
        out[:, :3, :3] = vectors[:, :9].reshape(-1, 3, 3)
        out[:, :3, 3] = vectors[:, 9:]
    return out


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
    # The Gaussian factors of every link in one graph: chi2 (initial, final) and the solve without
    # a robust kernel use it as it is.
    plain_graph = _graph(plain[id(link)] for link in used)
    chi2_initial = 2.0 * float(plain_graph.error(initial))

    kept = list(used)
    rejected: list[Link] = []
    if params.robust and rejected_before:
        out_before = [link for link in used if link.type.is_loop_closure and link.key() in rejected_before]
        trial = [link for link in used if not (link.type.is_loop_closure and link.key() in rejected_before)]
        # Only while the rest holds the graph together (a bridge is never dropped).
        if out_before and len(connected_components(poses.keys(), trial)) == 1:
            kept, rejected = trial, out_before
    values, iterations = _solve(_graph(factors[id(link)] for link in kept) if params.robust else plain_graph,
                                initial, root_id, poses[root_id], params, planar)
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
            values, more = _solve(_graph(factors[id(link)] for link in kept), values, root_id, poses[root_id],
                                  params, planar)
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
    kept_graph = plain_graph if len(kept) == len(used) else _graph(plain[id(link)] for link in kept)
    chi2_final = 2.0 * float(kept_graph.error(values))
    keys, stacked = _pose_stack(values, planar)
    return OptimizationResult(dict(zip(keys, stacked)), chi2_initial, chi2_final, iterations, rejected,
                              time.perf_counter() - start, switched_off, PoseStack.of_arrays(np.array(keys), stacked))


def _graph(factors):
    """A gtsam ``NonlinearFactorGraph`` of ``factors`` (its ``error`` sums them in C++)."""
    import gtsam

    graph = gtsam.NonlinearFactorGraph()
    for factor in factors:
        graph.add(factor)
    return graph


def _solve(links_graph, initial, root_id: int, root_pose: np.ndarray, params: GraphParams, planar: bool):
    """Run the optimiser on the links' factors (``links_graph``, robust on loop closures if
    asked) with the root held by a strong prior."""
    import gtsam

    graph = gtsam.NonlinearFactorGraph()
    dim = 3 if planar else 6
    root_noise = gtsam.noiseModel.Isotropic.Sigma(dim, ROOT_PRIOR_SIGMA)
    prior = gtsam.PriorFactorPose2 if planar else gtsam.PriorFactorPose3
    graph.add(prior(root_id, _to_gtsam(root_pose, planar), root_noise))
    graph.push_back(links_graph)
    try:
        if params.optimizer == "auto":
            values, iterations = _levenberg_marquardt_then_dogleg(graph, initial, params.iterations)
        else:
            values, iterations = _optimize(params.optimizer, graph, initial, params.iterations)
    except RuntimeError as exc:
        detail = " ".join(str(exc).split()).split(" Thrown when")[0].rstrip(".")
        raise OptimizationError(
            f"{params.optimizer} optimisation of {links_graph.size()} links failed: {detail}; an undamped solver (gn) "
            "can fail from a poor initial guess: use lm, or check that every node is constrained") from exc
    if not np.isfinite(graph.error(values)):
        raise OptimizationError(f"{params.optimizer} optimisation diverged (non-finite error)")
    return values, iterations


def _optimize(name: str, graph, initial, iterations: int):
    """(values, iterations) of gtsam's optimiser ``name`` (lm, gn, dogleg) run on ``graph`` from
    ``initial``; dogleg hands over to Levenberg-Marquardt (:data:`INDETERMINATE_SYSTEM`)."""
    optimizer = _optimizer(name, graph, initial, iterations)
    try:
        return optimizer.optimize(), int(optimizer.iterations())
    except RuntimeError as exc:
        if name != "dogleg" or INDETERMINATE_SYSTEM not in str(exc):
            raise
        # A Gauss-Newton system gtsam finds singular (MIT.g2o at its start; the first 3,000 poses of
        # cubicle.g2o): Levenberg-Marquardt's damping solves it; from the last values.
        done = int(optimizer.iterations())
        logger.debug("dogleg: singular Gauss-Newton system after %d iteration(s), Levenberg-Marquardt goes on", done)
        optimizer = _optimizer("lm", graph, optimizer.values(), max(1, iterations - done), fixed_lambda_factor=False)
        return optimizer.optimize(), done + int(optimizer.iterations())


def _levenberg_marquardt_then_dogleg(graph, initial, iterations: int):
    """(values, iterations) of gtsam's Levenberg-Marquardt on ``graph`` from ``initial``, iteration
    by iteration with gtsam's own stopping rule, handing over to dogleg once a damping failed in
    :data:`LM_FAILING_ITERATIONS` iterations running (``optimizer auto``)."""
    import gtsam

    lm = _optimizer("lm", graph, initial, iterations)
    lambda_initial = gtsam.LevenbergMarquardtParams().getlambdaInitial()
    error, failing = lm.error(), 0
    while lm.iterations() < iterations:
        damping = lm.lambda_()
        lm.iterate()
        new_error = lm.error()
        if (gtsam.checkConvergence(RELATIVE_ERROR_TOL, ABSOLUTE_ERROR_TOL, 0.0, error, new_error)
                or not np.isfinite(new_error)):
            break
        error = new_error
        # A success divides the damping by gtsam's factor, a failure multiplies it: it ends no lower
        # than it began only when a factorisation was spent on a failed damping. Counted only while
        # the damping is at or above where it started (LM_DAMPED): a near Gauss-Newton step failing
        # once, repaired by a damping of 1e-10, is LM converging, not LM stalled.
        damped = lm.lambda_() >= LM_DAMPED * lambda_initial
        failing = failing + 1 if lm.lambda_() >= damping and damped else 0
        if failing >= LM_FAILING_ITERATIONS and lm.iterations() < iterations:
            logger.debug("lm: a damping failed in %d iterations running, dogleg goes on", failing)
            values, more = _optimize("dogleg", graph, lm.values(), iterations - int(lm.iterations()))
            return values, int(lm.iterations()) + more
    return lm.values(), int(lm.iterations())


def _optimizer(name: str, graph, initial, iterations: int, fixed_lambda_factor: bool = True):
    """gtsam's optimiser ``name`` (lm, gn, dogleg) on ``graph`` from ``initial``, stopping after
    ``iterations`` or when the error decreases by less than the tolerances; ``fixed_lambda_factor``
    False: LM's damping follows Nielsen's update instead of gtsam's default."""
    import gtsam

    if name == "lm":
        opt_params, cls = gtsam.LevenbergMarquardtParams(), gtsam.LevenbergMarquardtOptimizer
        opt_params.setUseFixedLambdaFactor(fixed_lambda_factor)
    elif name == "gn":
        opt_params, cls = gtsam.GaussNewtonParams(), gtsam.GaussNewtonOptimizer
    else:
        opt_params, cls = gtsam.DoglegParams(), gtsam.DoglegOptimizer
        opt_params.setDeltaInitial(DOGLEG_DELTA_INITIAL)
    opt_params.setMaxIterations(iterations)
    opt_params.setRelativeErrorTol(RELATIVE_ERROR_TOL)
    opt_params.setAbsoluteErrorTol(ABSOLUTE_ERROR_TOL)
    return cls(graph, initial, opt_params)


def _dcs_scale(factor, values) -> float:
    """DCS scale ``min(1, 2 phi / (phi + chi2_i))`` of one link's Gaussian factor at ``values``."""
    chi2_i = 2.0 * factor.error(values)
    return min(1.0, 2.0 * DCS_PHI / (DCS_PHI + chi2_i))


# -- incremental (iSAM2) -------------------------------------------------------------------------

# iSAM2 relinearises a variable whose update exceeds this (rad and m). RTAB-Map's OptimizerISAM2 uses
# 0.01, gtsam's default is 0.1. 0.003 keeps the solution within 1 mm / 1e-4 rad of the batch one
# (test_local_map_incremental; 0.01 is 1.5 mm off on the Intel graph) at 0.6x the extra updates' time
# of 0.001 (simulated sessions 1-3, seed 9: 6.1 against 10.7 ms a loop closure frame).
ISAM2_RELINEARIZE_THRESHOLD = 0.003
# Extra iSAM2 updates after the one that added the frame's factors, at most: each relinearises
# the variables whose update exceeds ISAM2_RELINEARIZE_THRESHOLD and re-solves the affected part
# (Gauss-Newton steps), until one relinearises nothing (the linear system no longer changes, so
# neither would the estimate).
ISAM2_EXTRA_UPDATES = 4


class IncrementalOptimizer:
    """The local map's optimisation kept between frames with gtsam's iSAM2 (Kaess et al. 2012; as
    RTAB-Map's OptimizerISAM2, corelib/src/optimizer/OptimizerISAM2.cpp, which keeps one iSAM2 and
    adds each call's new poses and links): a frame adds its nodes and links to the solution of the
    frames before instead of solving the whole local map again, so a loop closure frame costs what
    its new factors touch and the relinearisation they cause, not a solve of the map (issue 50).

    It gives the batch solution of :func:`optimize` (the same factors: DCS on loop closures, the
    same rejection and re-admission rounds by DCS scale) or none: ``solve`` returns None whenever
    it cannot continue from what it holds (nodes left the local map, a map merged this frame and
    placed by consensus, the frame's loop closures were undone), and the caller solves in batch and
    hands the result to ``reset``. Its poses are in the frame of the node it was started at and are
    moved rigidly to put the root at its given pose (between factors do not see the gauge).
    """

    def __init__(self, params: GraphParams, planar: bool) -> None:
        self.params = params
        self.planar = planar
        self._isam = None
        self._nodes: set[int] = set()
        self._links: dict[tuple[int, int], Link] = {}  # every link held, active or rejected
        self._held: dict[int, tuple[int, int]] = {}  # id() of each held link -> its key
        self._loops: dict[tuple[int, int], Link] = {}  # the loop closures among them
        self._factor: dict[tuple[int, int], int] = {}  # active link key -> iSAM2 factor index
        self._values = None  # the current estimate (gtsam Values)

    def invalidate(self) -> None:
        """Forget the solution: the next ``solve`` returns None (the caller solves in batch)."""
        self._isam = None
        self._values = None

    def holds(self, nodes: Collection[int]) -> bool:
        """True when any of ``nodes`` is a variable of the solution held."""
        return self._isam is not None and not self._nodes.isdisjoint(nodes)

    def reset(self, poses: dict[int, np.ndarray], links: list[Link], rejected: Collection[tuple[int, int]]) -> None:
        """Start over from a batch solution: ``poses`` of one connected component, the ``links``
        optimised among them and the keys of the loop closures that solution ``rejected``."""
        import gtsam

        used = [link for link in links if link.from_id in poses and link.to_id in poses and link.from_id != link.to_id]
        isam_params = gtsam.ISAM2Params()
        isam_params.setRelinearizeThreshold(ISAM2_RELINEARIZE_THRESHOLD)
        isam_params.relinearizeSkip = 1
        self._isam = gtsam.ISAM2(isam_params)
        self._nodes = set(poses)
        self._links, self._held, self._loops = {}, {}, {}
        self._hold(used)
        self._factor = {}
        values = gtsam.Values()
        for node_id, pose in zip(poses, _gtsam_poses(np.stack(list(poses.values())), self.planar)):
            values.insert(node_id, pose)
        anchor = min(poses)
        graph = gtsam.NonlinearFactorGraph()
        graph.add(self._prior(anchor, poses[anchor]))
        active = [link for link in used if link.key() not in rejected]
        for factor in self._factors(active):
            graph.add(factor)
        result = self._isam.update(graph, values)
        self._factor = dict(zip((link.key() for link in active), list(result.getNewFactorsIndices())[1:]))
        self._set_estimate()

    def solve(self, component: set[int], links: list[Link], root_id: int, root_pose: np.ndarray,
              guess: dict[int, np.ndarray]) -> OptimizationResult | None:
        """The optimised poses of ``component`` (every node in ``guess``, root at ``root_pose``) with
        ``links`` among them (both ends in ``component``), continuing from the last solution; None
        when that is not possible."""
        import gtsam

        start = time.perf_counter()
        if self._isam is None or not self._nodes <= component:
            return None
        # What changed since the last solution, by identity (links are immutable: a link replaced
        # is a new object): a frame changes a few links of ~2,000, and comparing them key by key
        # was a third of a loop closure frame's bookkeeping (issue 50).
        current = set(map(id, links))
        gone = sorted(self._held[i] for i in self._held.keys() - current)
        if any(not self._links[key].type.is_loop_closure for key in gone):
            return None  # a neighbour link changed or left: not what a frame does
        new_nodes = component - self._nodes
        # The guess is the last solution moved rigidly to the root; into this solution's frame.
        held = next(iter(self._nodes))
        T_here_guess = _poses_of_keys(self._values, [held], self.planar)[held] @ transforms.inverse(guess[held])
        values = gtsam.Values()
        if new_nodes:
            ids = sorted(new_nodes)
            for node_id, pose in zip(ids, _gtsam_poses(np.einsum("ij,njk->nik", T_here_guess,
                                                                 np.stack([guess[n] for n in ids])), self.planar)):
                values.insert(node_id, pose)
        remove = [self._factor.pop(key) for key in gone if key in self._factor]
        self._release(gone)
        rejected_keys = [key for key in self._links if key not in self._factor]
        fresh = [link for link in links if id(link) not in self._held and link.from_id != link.to_id]
        graph = gtsam.NonlinearFactorGraph()
        for factor in self._factors(fresh):
            graph.add(factor)
        iterations = self._update(graph, values, remove, fresh)
        self._nodes |= new_nodes
        self._hold(fresh)
        rejected = [self._links[key] for key in rejected_keys]
        switched_off: list[Link] = []
        if self.params.robust:
            rejected, switched_off, more = self._robust_rounds(component, rejected)
            iterations += more
        keys, stacked = _pose_stack(self._values, self.planar)
        if self.planar:
            root_pose = transforms.project_planar(root_pose)
        align = root_pose @ transforms.inverse(stacked[keys.index(root_id)])
        aligned = np.einsum("ij,njk->nik", align, stacked)
        return OptimizationResult(dict(zip(keys, aligned)), float("nan"), float("nan"), iterations, rejected,
                                  time.perf_counter() - start, switched_off, PoseStack.of_arrays(np.array(keys), aligned))

    def _hold(self, links: list[Link]) -> None:
        """Hold ``links`` (a link of a key already held replaces it)."""
        for link in links:
            key = link.key()
            if key in self._links:
                del self._held[id(self._links[key])]
            self._links[key] = link
            self._held[id(link)] = key
            if link.type.is_loop_closure:
                self._loops[key] = link

    def _release(self, keys: list[tuple[int, int]]) -> None:
        """Stop holding the links of ``keys``."""
        for key in keys:
            del self._held[id(self._links.pop(key))]
            self._loops.pop(key, None)

    def _prior(self, node_id: int, pose: np.ndarray):
        import gtsam

        prior = gtsam.PriorFactorPose2 if self.planar else gtsam.PriorFactorPose3
        return prior(node_id, _to_gtsam(pose, self.planar),
                     gtsam.noiseModel.Isotropic.Sigma(3 if self.planar else 6, ROOT_PRIOR_SIGMA))

    def _factors(self, links: list[Link]) -> list:
        """The factors of ``links`` as :func:`optimize` makes them (cached; DCS on loop closures)."""
        plain = _plain_factors(links, self.planar)
        return [_cached("robust factor", link, self.planar, _robust_factor)
                if self.params.robust and link.type.is_loop_closure else plain[id(link)] for link in links]

    def _update(self, graph, values, remove: list[int], added: list[Link]) -> int:
        """One iSAM2 update with the factors of ``added`` in ``graph``, the new ``values`` and the
        factors ``remove`` removed, then the extra updates that converge it (:meth:`_converge`) and
        the estimate; returns how many extra updates."""
        result = self._isam.update(graph, values, remove)
        self._factor.update(zip((link.key() for link in added), list(result.getNewFactorsIndices())))
        iterations = self._converge()
        self._set_estimate()
        return iterations

    def _set_estimate(self) -> None:
        self._values = self._isam.calculateEstimate()

    def _converge(self) -> int:
        """Further iSAM2 updates (relinearisation and Gauss-Newton steps) until one relinearises no
        variable. The estimate is not read between them: calculating and extracting the poses of a
        1,600-node map after each update was a third of a long loop closure's solve (issue 50)."""
        for done in range(1, ISAM2_EXTRA_UPDATES + 1):
            if self._isam.update().getVariablesRelinearized() == 0:
                return done
        return ISAM2_EXTRA_UPDATES

    def _robust_rounds(self, component: set[int], rejected: list[Link]) -> tuple[list[Link], list[Link], int]:
        """:func:`optimize`'s robust rounds on the incremental solution: loop closures whose DCS
        scale is below ``robust_reject_scale`` leave it (never a bridge), rejected ones that agree
        again come back; returns (rejected, switched off, iterations)."""
        import gtsam

        threshold = self.params.robust_reject_scale
        loops = list(self._loops.values())
        plain = _plain_factors(loops, self.planar)
        iterations = 0
        for _ in range(ROBUST_ROUNDS):
            scales = {link.key(): _dcs_scale(plain[id(link)], self._values) for link in loops}
            out = {link.key() for link in rejected}
            bad = sorted((link for link in loops if link.key() not in out and scales[link.key()] < threshold),
                         key=lambda link: scales[link.key()])
            good_again = [link for link in rejected if scales[link.key()] >= threshold]
            if not bad and not good_again:
                break
            rejected = [link for link in rejected if scales[link.key()] < threshold]
            out = {link.key() for link in rejected}
            kept = [link for key, link in self._links.items() if key not in out]
            dropped = []
            for link in bad:  # worst first; a bridge stays (nothing in the graph contradicts it)
                trial = [k for k in kept if k is not link]
                if len(connected_components(component, trial)) == 1:
                    kept, dropped = trial, dropped + [link]
            if not dropped and not good_again:
                break
            rejected += dropped
            graph = gtsam.NonlinearFactorGraph()
            for factor in self._factors(good_again):
                graph.add(factor)
            iterations += 1 + self._update(graph, gtsam.Values(), [self._factor.pop(link.key()) for link in dropped],
                                           good_again)
        else:
            scales = {link.key(): _dcs_scale(plain[id(link)], self._values) for link in loops}
        out = {link.key() for link in rejected}
        switched_off = [link for link in loops if link.key() not in out and scales[link.key()] < threshold]
        return rejected, switched_off, iterations


def _poses_of_keys(values, keys: list[int], planar: bool) -> dict[int, np.ndarray]:
    """4x4 poses of ``keys`` in ``values``."""
    if not planar:
        return {k: np.asarray(values.atPose3(k).matrix(), dtype=np.float64) for k in keys}
    poses = {}
    for k in keys:
        pose = values.atPose2(k)
        poses[k] = transforms.from_xy_yaw(pose.x(), pose.y(), pose.theta())
    return poses


def _pose_vectors(values, planar: bool) -> np.ndarray:
    """(n, 3) x, y, yaw or (n, 12) rotation and translation of every pose in ``values`` (key order)."""
    import gtsam

    return (gtsam.utilities.extractPose2(values).reshape(-1, 3) if planar
            else gtsam.utilities.extractPose3(values).reshape(-1, 12))


__all__ = ["IncrementalOptimizer", "InformationCheck", "OptimizationResult", "gtsam_information",
           "information_check", "optimize"]
