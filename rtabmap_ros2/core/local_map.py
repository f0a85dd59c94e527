"""The local map and its incremental optimisation (2014 §II-B, C).

The local map is the WM nodes linked to the newest node; it is optimised every frame with the
graph rooted at the newest node (its odometry pose), so the newest pose never moves (2014 §II-B).
:class:`LocalMapper` keeps the last solution and the cheap ways to the next one, beyond the
papers because they keep a frame's optimisation time flat: a new node joined by one link is a
leaf added in O(n) with the exact optimum (``_leaf_update``); a frame whose loop closures
RGBD/OptimizeMaxError rejects keeps the last solution as RTAB-Map does
(``_last_solution_kept``); a re-solve starts warm from the previous solution (``_warm_start``)
and, with ``graph.incremental``, continues it in iSAM2 (``optimizer.IncrementalOptimizer``): a loop
closure frame then costs what its new links touch, not a solve of the whole local map.

It also keeps, for every node that left the local map (to LTM, or in a map not joined to the
current one), its last optimised pose in one "world" frame that does not move with the
solutions (``kept_poses``, ``map_pose``): the multi-session merge checks of
``loop_validation.LoopValidator`` and a part of the map coming back from LTM start from them. And
the local occupancy grid, drawn incrementally (``grid``), and the nodes near the robot that
memory management keeps in WM or brings back from LTM (``near_robot``, ``retrieval_candidates``:
RTAB-Map's RGBD/LocalImmunizationRatio, RGBD/LocalRadius).
"""

from __future__ import annotations

import logging
from collections import deque
from dataclasses import dataclass, field, replace
from typing import Optional

import numpy as np

from rtabmap_ros2.core import transforms
from rtabmap_ros2.core.graph import Graph, Link, LinkType, PoseStack, chain_poses, consensus_guess
from rtabmap_ros2.core.grid import DepthPoints, OccupancyGrid
from rtabmap_ros2.core.local_grid import LocalGrid
from rtabmap_ros2.core.loop_validation import fits_inter_session_majority, judged_links, max_error_ratio, only_bridges
from rtabmap_ros2.core.memory import Memory
from rtabmap_ros2.core.node_tables import PoseTable
from rtabmap_ros2.core.optimizer import IncrementalOptimizer, optimize
from rtabmap_ros2.core.params import Params
from rtabmap_ros2.core.sensor import LaserScan
from rtabmap_ros2.core.registration import assemble_scan_map, refine_neighbor_link
from rtabmap_ros2.core.signature import Signature
from rtabmap_ros2.errors import RegistrationError

log = logging.getLogger(__name__)



@dataclass
class LocalMap:
    """The optimised local map (2014 §II-C): WM nodes connected to the newest node; what its
    occupancy grid is drawn from: ``scans``, the laser scan of each node that has one, and
    ``depth``, the depth points of each node whose grid uses its depth image (``grid.sensor``)."""

    poses: dict[int, np.ndarray]
    links: list[Link]
    map_ids: dict[int, int]
    T_map_odom: np.ndarray
    scans: dict[int, LaserScan] = field(default_factory=dict)
    depth: dict[int, DepthPoints] = field(default_factory=dict)


class LocalMapper:
    """The local map's last solution, how to get the next one, and the poses kept in the world frame."""

    def __init__(self, params: Params, memory: Memory) -> None:
        self.params = params
        self.memory = memory
        # Planar (3 DoF) mode, decided at the first frame with odometry (Rtabmap._check_planar).
        self.planar: Optional[bool] = None
        # The last solution: poses of the local map's nodes, the links among them (without those
        # the robust optimiser made inactive), and map -> odom at the newest node.
        self.poses: dict[int, np.ndarray] = {}
        self.links: list[Link] = []
        self.T_map_odom = transforms.identity()
        # The frame's new loop closures, with what add_loop_closure returned to undo them, and the keys
        # of those proximity detection found (graph.proximity_by_space).
        self.new_loops: list[tuple[Link, tuple[int, int, int]]] = []
        self.proximity_keys: set[tuple[int, int]] = set()
        # Last optimised pose of every node that left the local map, in one frame that does not
        # move with the solutions ("world"): map_pose(). T_world_local: the current solution's
        # frame in it.
        self.kept_poses = PoseTable()
        self.T_world_local = transforms.identity()
        self.inactive_links: set[tuple[int, int]] = set()
        # The last solution kept in iSAM2 for the next loop closure (graph.incremental), and whether
        # nodes left the local map since the last solve (then it is not worth starting again).
        self._solver: Optional[IncrementalOptimizer] = None
        self._nodes_left = False
        # The last optimize_component's solution as a stack (follow_local_frame reads it), or None.
        self._solution_stack: Optional[PoseStack] = None
        # Graph version of the current solution (None: no valid solution to extend), and whether
        # WM changed since (transfer, retrieval): see _leaf_update. _resolve_next: the local map
        # is the last solution kept (_last_solution_kept), not a solution.
        self.solved_version: Optional[int] = None
        self.wm_changed = True
        self._resolve_next = False
        self._grid = LocalGrid(params.grid)

    def neighbor_link(self, previous: Signature, new: Signature, T_odom: np.ndarray, info: np.ndarray) -> Link:
        """Neighbour link from odometry, refined by scan matching when enabled (planar, scans)."""
        params = self.params.registration
        if params.neighbor_link_refining and self.planar and previous.scan is not None and new.scan is not None:
            try:
                T_odom, info = refine_neighbor_link(self._scan_map(previous), new.scan, T_odom, info, params)
            except RegistrationError as exc:
                log.debug("neighbour link %d -> %d kept from odometry: %s", previous.id, new.id, exc)
        return Link(previous.id, new.id, LinkType.NEIGHBOR, T_odom, info)

    def _scan_map(self, previous: Signature) -> np.ndarray:
        """The scans of ``previous`` and the nodes before it in its session (up to
        ``registration.neighbor_scan_map_nodes``, following neighbour links while they are in
        memory with a scan), assembled in ``previous``'s base frame."""
        memory = self.memory
        params = self.params.registration
        scans = [(transforms.identity(), previous.scan)]
        node, T_previous_node = previous.id, transforms.identity()
        while len(scans) < params.neighbor_scan_map_nodes:
            older = [n for n in memory.graph.neighbors(node, (LinkType.NEIGHBOR,)) if n < node]
            sig = memory.signatures.get(older[0]) if older else None
            if sig is None or sig.scan is None:
                break
            T_previous_node = T_previous_node @ memory.graph.link(node, sig.id).T_from_to
            scans.append((T_previous_node, sig.scan))
            node = sig.id
        return assemble_scan_map(scans, params.scan_map_voxel_size)

    def snapshot(self) -> LocalMap:
        """A copy of the local map (poses in the map frame) for publishing or export; the scans and
        depth points are shared, not copied (never modified)."""
        scans, depth = self._grid_views()
        return LocalMap(dict(self.poses), list(self.links), {n: self.memory.map_ids[n] for n in self.poses},
                        self.T_map_odom.copy(), scans, depth)

    def _grid_views(self) -> tuple[dict[int, LaserScan], dict[int, DepthPoints]]:
        """The laser scans and the depth points of the local map's nodes that have them."""
        signatures = [self.memory.signatures[n] for n in self.poses if n in self.memory.signatures]
        return ({sig.id: sig.scan for sig in signatures if sig.scan is not None},
                {sig.id: sig.depth_points for sig in signatures if sig.depth_points is not None})

    def forget(self, nodes: list[int], transferred_to_ltm: bool = False) -> None:
        """Nodes that left WM (transferred to LTM, or merged into the previous location by
        rehearsal) leave the local map too: it names only nodes in memory, also when the next
        optimisation fails and the last solution is kept. Transferred nodes keep their last
        optimised pose in ``kept_poses``: an old map whose nodes come back from LTM is aligned
        with them for a merge."""
        solved = False  # a node of the last solution leaves
        for node in nodes:
            pose = self.poses.pop(node, None)
            solved |= pose is not None
            if not transferred_to_ltm:
                self.kept_poses.pop(node, None)
            elif pose is not None:
                self._keep_map_pose(node, pose)
        gone = set(nodes)
        self.links = [link for link in self.links if not {link.from_id, link.to_id} & gone]
        # A frame's own node merged by rehearsal was in no solution yet: the iSAM2 solution goes on
        # (dropping it made the next two loop closure frames batch solves, 50-100 ms each, after
        # every merge: 35 of 201 loop closure solves on simulated sessions 1-3).
        self._nodes_left |= solved
        if self._solver is not None and self._solver.holds(gone):
            self._solver.invalidate()

    def grid(self, max_casts: Optional[int] = None) -> Optional[OccupancyGrid]:
        """Occupancy grid of the local map from the nodes' laser scans and / or depth points, or None
        without either, updated incrementally (:meth:`LocalGrid.update
        <rtabmap_ros2.core.local_grid.LocalGrid.update>`; ``max_casts`` bounds the nodes cast per
        call, ``grid_pending`` says how many wait)."""
        if self._grid.params is not self.params.grid:   # other grid parameters: a grid of its own
            self._grid = LocalGrid(self.params.grid)
        scans, depth = self._grid_views()
        return self._grid.update(self.poses, scans, max_casts, depth)

    @property
    def grid_pending(self) -> int:
        """Nodes not cast at their current pose after the last :meth:`grid`."""
        return self._grid.pending

    def new_node_pose(self, node: int) -> Optional[np.ndarray]:
        """Pose in the current local map of the new node (not optimised yet: verification comes
        first), chained by odometry from the session's newest optimised node (None: no such node)."""
        previous = max((n for n in self.poses if self.memory.map_ids.get(n) == self.memory.map_id),
                       default=None)
        if previous is None:
            return None
        signatures = self.memory.signatures
        return (self.poses[previous] @ transforms.inverse(signatures[previous].T_odom_base)
                @ signatures[node].T_odom_base)

    def optimize_component(self, root: int) -> tuple[dict[int, np.ndarray], list[Link]]:
        """Optimised poses of the WM nodes connected to ``root`` (root at its odometry pose), and
        the links among them.

        Loop closures the robust optimiser finds inconsistent stay in the graph, inactive for
        this solution: when later loop closures outvote them they can be right after all (a
        false inter-session link found first must not make every true one after it look wrong);
        the next re-solve starts without them and re-admits those its solution agrees with.
        The initial guess is the previous solution (few iterations) unless it contradicts the
        majority of some pair of sessions' loop closures; then sessions are placed by consensus of
        their loop closures, for the same reason. With ``graph.incremental`` the last solution is
        continued in iSAM2 when it can be (not after a merge placed by consensus, nodes leaving the
        local map or an undone frame), else solved in batch and iSAM2 started again from that
        solution. The frame's new loop closures are then checked (RTAB-Map's
        RGBD/OptimizeMaxError; not a map merge's, which bends nothing: only_bridges): if they put a
        link more than ``graph.optimize_max_error`` standard deviations off (max_error_ratio: a link
        already off before them counts by how far they moved it), they are removed and, as RTAB-Map
        does, the last solution is kept (_last_solution_kept): one solve per frame; the next frame
        re-solves.
        """
        memory = self.memory
        component = memory.graph.component(root, allowed=memory.signatures)
        links = memory.graph.links_within(component)
        root_pose = memory.signatures[root].T_odom_base
        rejected_before, self.inactive_links = self.inactive_links, set()
        if not any(link.type.is_loop_closure for link in links):
            # A tree of neighbour links: chaining them is the optimum. (Re-using the previous
            # poses here fed round-off back every frame: rotations lost orthonormality
            # exponentially, x2 per frame, and poses overflowed after ~1,000 frames.) Planar:
            # Pose2 chaining, as the optimiser's solution would be (and _leaf_update is).
            if self.planar:
                planar_links = [replace(link, T_from_to=transforms.project_planar(link.T_from_to)) for link in links]
                return chain_poses(root, transforms.project_planar(root_pose), planar_links), links
            return chain_poses(root, root_pose, links), links
        previous = self._previous_poses(component)
        guess = _warm_start(root, root_pose, memory.graph, component, previous, planar=False)
        result = None
        if guess is None or not fits_inter_session_majority(guess, links, memory.map_ids):
            guess = consensus_guess(root, root_pose, links)
        elif self.params.graph.incremental:
            result = self._incremental().solve(component, links, root, root_pose, guess)
        if result is None:
            result = optimize(guess, links, root, self.params.graph, planar=bool(self.planar),
                              rejected_before=rejected_before)
            # Started again from this solution, unless nodes are leaving the local map (transfers to
            # LTM come frame after frame once T_time is reached): iSAM2 cannot drop them, so each
            # solve would be a batch one plus the restart.
            if self.params.graph.incremental and not self._nodes_left:
                self._incremental().reset(result.poses, links, {link.key() for link in result.rejected})
        self._nodes_left = False
        self.inactive_links = {link.key() for link in result.rejected}
        solution = result.pose_stack()
        fresh = [(link, before) for link, before in self.new_loops
                 if link.from_id in component and link.to_id in component]
        limit = self.params.graph.optimize_max_error
        if fresh and limit > 0:
            new = {link.key() for link, _ in fresh}
            judged = judged_links(links, self.inactive_links, result.switched_off, new)
            worst = max_error_ratio(solution, judged, bool(self.planar), before=previous, new=new)
            if worst > limit and not only_bridges(links, [link for link, _ in fresh]):
                nearby = [(link, before) for link, before in fresh if link.key() in self.proximity_keys]
                if nearby and len(nearby) < len(fresh):
                    # A proximity detection must not take the frame's appearance-based loop closure
                    # down with it: judged again without the proximity ones.
                    for link, before in nearby:
                        log.info("proximity loop closure %d -> %d rejected: a link ends %.1f std devs off after "
                                 "optimisation (> %.1f)", link.from_id, link.to_id, worst, limit)
                        memory.undo_loop_closure(link, before)
                    self.new_loops = [(link, before) for link, before in self.new_loops
                                      if link.key() not in self.proximity_keys]
                    self.proximity_keys = set()
                    self.inactive_links = rejected_before
                    return self.optimize_component(root)
                for link, before in fresh:
                    log.info("loop closure %d -> %d rejected: a link ends %.1f std devs off after "
                             "optimisation (> %.1f)", link.from_id, link.to_id, worst, limit)
                    memory.undo_loop_closure(link, before)
                self.new_loops = []
                kept = self._last_solution_kept(root, rejected_before)
                return kept if kept is not None else self.optimize_component(root)
        self._solution_stack = solution
        return result.poses, links

    def _incremental(self) -> IncrementalOptimizer:
        """The iSAM2 solution of the local map (made again if the planar mode changed)."""
        planar = bool(self.planar)
        if self._solver is None or self._solver.planar != planar:
            self._solver = IncrementalOptimizer(self.params.graph, planar)
        return self._solver

    def _last_solution_kept(self, root: int, inactive_before: set[tuple[int, int]]
                            ) -> Optional[tuple[dict[int, np.ndarray], list[Link]]]:
        """After the frame's loop closures were rejected: the last solution, with what else the
        frame brought (its node, retrieved nodes) chained onto it, and the links among them; None
        when chaining does not reach every node (then the caller re-solves).

        RTAB-Map keeps its last optimised poses when RGBD/OptimizeMaxError rejects the frame's
        loop closures (Rtabmap.cpp: ``updateConstraints = false``). Solving again without them
        made such a frame the slowest of the 30-session run: two re-solves of ~820 nodes, 187 ms,
        290 ms in all at T_time 200 ms. The graph is now the last solution's plus the frame's
        additions: for a leaf alone this is the optimum (_leaf_update); nodes retrieved this frame
        sit where their links put them until the next frame re-solves (``_resolve_next``).
        """
        memory = self.memory
        component = memory.graph.component(root, allowed=memory.signatures)
        poses = _warm_start(root, self._root_pose(root), memory.graph, component, self._previous_poses(component),
                            bool(self.planar))
        if poses is None:
            return None
        self.inactive_links = set(inactive_before)
        self._resolve_next = True
        return poses, memory.graph.links_within(component)

    def _root_pose(self, node: int) -> np.ndarray:
        """Odometry pose of ``node`` as the local map's root: x, y and yaw only when planar (as
        the optimiser's Pose2 solution has it)."""
        T = self.memory.signatures[node].T_odom_base
        return transforms.project_planar(T) if self.planar else T

    def _previous_poses(self, nodes: set[int]) -> dict[int, np.ndarray]:
        """Initial guess of a re-solve over ``nodes``, in the last solution's frame: the last
        solution, and for nodes not in it their kept poses (``kept_poses``, brought from the world
        frame), a map merged this frame included (``LoopValidator.allows`` moves its kept poses
        onto the current map).

        A part of the map that comes back into the local map (a node retrieved, a loop closure
        joining it again through WM) thus starts where it was left. Chained from the last
        solution through whatever links reached it first, 2,500 nodes of 13 old sessions
        started tens of metres off, the optimiser settled there, and the next 134 true loop
        closures were rejected against the kept poses, 30-110 m away (30 sessions, WM 2,700)."""
        to_local = transforms.inverse(self.T_world_local)
        kept = self.kept_poses.items_in(n for n in nodes if n not in self.poses)
        poses = dict(zip(kept, np.einsum("ij,njk->nik", to_local, np.array(list(kept.values())).reshape(-1, 4, 4))))
        poses.update((n, self.poses[n]) for n in nodes if n in self.poses)
        return poses

    def update(self, newest: int) -> bool:
        """Optimise the local map rooted at the newest node (2014 §II-B, C).

        Returns True when the frame's new loop closures were rejected as inconsistent.
        """
        memory = self.memory
        if memory.signatures[newest].T_odom_base is None:
            return False
        had_loops = bool(self.new_loops)
        solved, self.solved_version = self.solved_version, None
        leaf = self._leaf_link(newest, solved)
        self._solution_stack = None
        if leaf is None:
            poses, links = self.optimize_component(newest)
            inactive = self.inactive_links
            self.links = [link for link in links if link.key() not in inactive] if inactive else links
        else:
            poses = self._leaf_update(newest, leaf)
            self.links.append(leaf)
        self.follow_local_frame(poses, rigid=leaf is not None, stack=self._solution_stack)
        self.poses = poses
        self.solved_version = None if self._resolve_next else memory.graph.version
        self._resolve_next = False
        self.wm_changed = False
        self.T_map_odom = poses[newest] @ transforms.inverse(memory.signatures[newest].T_odom_base)
        return had_loops and not any(memory.graph.link(l.from_id, l.to_id) and l.key() not in self.inactive_links
                                     for l, _ in self.new_loops)

    def follow_local_frame(self, poses: dict[int, np.ndarray], rigid: bool, stack: Optional[PoseStack] = None) -> None:
        """Before ``poses`` replaces the last solution: nodes leaving the local map keep their
        last pose in the world frame, and the world frame follows the new solution's (the rigid
        change that best maps the nodes in both solutions; exact for a ``rigid`` leaf update).

        Each solution is rooted at its newest node's odometry pose, so its frame moves with the
        odometry drift: poses kept from solutions minutes apart were metres apart in one old
        map, no two loop closures to it agreed, and the last of 5 sessions at T_time 0.1 s never
        merged. ``stack``: ``poses`` as a stack, when the solver gave one."""
        previous = self.poses
        for node, pose in previous.items():
            if node not in poses:
                self._keep_map_pose(node, pose)
        common = [n for n in poses if n in previous]
        if not common:
            return  # a map not connected to the last one: its frame is as good as any
        if rigid:
            change = previous[common[0]] @ transforms.inverse(poses[common[0]])
        else:
            new = stack.gather(common) if stack is not None else np.array([poses[n] for n in common])
            change = _rigid_change(np.array([previous[n] for n in common]), new)
        self.T_world_local = self.T_world_local @ change

    def _keep_map_pose(self, node: int, pose: np.ndarray) -> None:
        """Keep the pose (in the current solution) of a node leaving the local map, in the world
        frame: a node of the session being mapped always, a node of an older session only when
        none is kept yet. An old session's geometry stays as its own session optimised it (moved
        as a whole when it merges): the local map holds only the WM parts of an old map, and a
        part joined to the rest only through LTM follows a false loop closure without tension
        (seed 5 at T_time 0.1 s: 4 false loop closures moved such a part 26 m, and no two loop
        closures of the next sessions to that map agreed any more)."""
        if self._local_map_sets_pose(node):
            self.kept_poses[node] = self.T_world_local @ pose

    def _local_map_sets_pose(self, node: int) -> bool:
        """True when the local map's pose of ``node`` is to replace its kept one: a node of the
        session being mapped, or one with no kept pose yet (_keep_map_pose says why)."""
        return node not in self.kept_poses or self.memory.map_ids.get(node) == self.memory.map_id

    def map_pose(self, node: int) -> Optional[np.ndarray]:
        """Kept pose of ``node`` in the world frame (see _keep_map_pose; None: never in a local map)."""
        if node in self.poses and self._local_map_sets_pose(node):
            return self.T_world_local @ self.poses[node]
        return self.kept_poses.get(node)

    def _leaf_link(self, newest: int, solved: Optional[int]) -> Optional[Link]:
        """The link from the last solution to ``newest`` when that one link is all that changed.

        True when, since the last solution (graph version ``solved``), exactly one link was added,
        it joins ``newest`` to a node of that solution, no loop closure came or went, no map was
        merged, and WM neither lost nor gained a node. Returns it oriented towards ``newest``.
        """
        memory = self.memory
        if (solved is None or self.wm_changed or self.new_loops
                or memory.graph.version != solved + 1 or newest in self.poses):
            return None
        links = memory.graph.links_of(newest)
        if len(links) != 1 or links[0].to_id not in self.poses:
            return None
        return links[0].inverted()

    def _leaf_update(self, newest: int, link: Link) -> dict[int, np.ndarray]:
        """The local map grown by one leaf, rooted at ``newest``: exact and O(n).

        A node joined by a single link adds a factor that its own pose satisfies exactly, so the
        optimum of the other nodes does not change (the robust kernel's decisions neither); only
        the root moves to the new node (2014 §II-B), a rigid change of gauge of the previous
        solution, which the between factors do not see. The result equals a batch solve's within
        its convergence tolerance (test_local_map_incremental).
        """
        planar = bool(self.planar)
        previous = self.poses
        T_link = transforms.project_planar(link.T_from_to) if planar else link.T_from_to
        root_pose = self._root_pose(newest)
        grown = previous[link.from_id] @ T_link
        # Re-orthonormalised: round-off of the previous poses must not feed back frame after
        # frame (poses are composed again at every leaf).
        align = _rigid(root_pose @ transforms.inverse(grown), planar)
        ids = list(previous)
        stacked = np.einsum("ij,njk->nik", align, np.array([previous[n] for n in ids]))
        poses = dict(zip(ids, stacked))
        poses[newest] = root_pose
        return poses

    def near_robot(self, newest: int) -> set[int]:
        """SLAM mode: the WM nodes of the local map nearest the newest node, within
        ``memory.local_radius``, at most ``memory.local_immunization_ratio`` of WM: they stay
        in WM so the local map around the robot survives transfers (RTAB-Map's
        RGBD/LocalImmunizationRatio and RGBD/LocalRadius, Rtabmap::process before Memory::forget)."""
        budget = int(self.params.memory.local_immunization_ratio * len(self.memory.wm))
        if budget <= 0 or newest not in self.poses:
            return set()
        nearest = self.nodes_near(self.poses[newest][:3, 3])
        return set([n for n in nearest if n in self.memory.wm][:budget])

    def retrieval_candidates(self, newest: int) -> list[int]:
        """SLAM mode: LTM locations linked to the local map's nodes near the robot (up to
        ``memory.max_local_retrieved``), located by the last solution and the new node's odometry.
        Nothing when the last solution is not the new node's map (first node of a session)."""
        memory = self.memory
        limit = self.params.memory.max_local_retrieved
        sig = memory.signatures.get(newest)
        if (limit <= 0 or sig is None or sig.T_odom_base is None or not memory.ltm_size
                or not any(n in self.poses for n in memory.graph.neighbors(newest, (LinkType.NEIGHBOR,)))):
            return []
        position = (self.T_map_odom @ sig.T_odom_base)[:3, 3]
        return memory.local_retrieval_candidates(self.nodes_near(position), limit)

    def nodes_near(self, position: np.ndarray) -> list[int]:
        """Nodes of the local map within ``memory.local_radius`` of ``position``, nearest first."""
        ids = list(self.poses)
        if not ids:
            return []
        xyz = np.array([self.poses[n][:3, 3] for n in ids])
        distance = np.linalg.norm(xyz - position, axis=1)
        return [ids[i] for i in np.argsort(distance, kind="stable") if distance[i] <= self.params.memory.local_radius]


def _rigid_change(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """The rigid transform ``C`` that best maps poses ``B`` (N,4,4) onto ``A``, ``A ≈ C @ B``:
    chordal mean of the rotations, then the translation of the centroids (well defined for
    nodes on a line, where a fit of positions alone leaves the roll free)."""
    U, _, Vt = np.linalg.svd((A[:, :3, :3] @ B[:, :3, :3].transpose(0, 2, 1)).sum(axis=0))
    R = U @ np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))]) @ Vt
    C = transforms.identity()
    C[:3, :3] = R
    C[:3, 3] = A[:, :3, 3].mean(axis=0) - R @ B[:, :3, 3].mean(axis=0)
    return C


def _warm_start(root: int, root_pose: np.ndarray, graph: Graph, nodes: set[int],
                previous: dict[int, np.ndarray], planar: bool) -> Optional[dict[int, np.ndarray]]:
    """Initial guess from the previous optimised poses, new nodes chained from them by their
    links (in ``graph``, within ``nodes``; ``planar``: the links' x, y, yaw, so planar poses stay
    planar), all moved rigidly so the root sits at ``root_pose``;
    None without a previous solution or when it does not reach every node (a map merged this
    frame: its nodes are reached only against the links' direction, and a guess without them put
    the merged map 195 std devs off)."""
    poses = {n: previous[n] for n in nodes if n in previous}
    if not poses:
        return None
    # Breadth-first from the placed nodes next to a missing one (usually the previous newest).
    frontier = {other for n in nodes if n not in poses for other in graph.neighbors(n) if other in poses}
    queue = deque(frontier)
    while queue:
        node = queue.popleft()
        for link in graph.links_of(node):
            if link.to_id in nodes and link.to_id not in poses:
                poses[link.to_id] = poses[node] @ (transforms.project_planar(link.T_from_to) if planar
                                                   else link.T_from_to)
                queue.append(link.to_id)
    if len(poses) < len(nodes):
        return None
    align = root_pose @ transforms.inverse(poses[root])
    return dict(zip(poses, align @ np.array(list(poses.values()), dtype=float)))


def _rigid(T: np.ndarray, planar: bool) -> np.ndarray:
    """``T`` with its rotation projected back onto SO(3) (onto yaw only when ``planar``)."""
    if planar:
        return transforms.project_planar(T)
    U, _, Vt = np.linalg.svd(T[:3, :3])
    out = np.array(T, dtype=float)
    out[:3, :3] = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
    return out
