"""The map's graph (2014 §II): nodes joined by typed links carrying rigid transforms.

A :class:`Link` from ``from_id`` to ``to_id`` holds ``T_from_to`` such that
``pose_to = pose_from @ T_from_to`` (poses are ``T_map_base``), and a 6x6 information matrix over
(x, y, z, roll, pitch, yaw). Neighbour links join consecutive nodes of one session (odometry);
loop closure links are intra-session or inter-session.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field
from enum import Enum
from functools import cached_property
from typing import Iterable, Mapping

import numpy as np

from rtabmap_ros2.core import transforms


class LinkType(str, Enum):
    """Link types, spelled as in ``links.csv``."""

    NEIGHBOR = "neighbor"
    LOOP_INTRA = "loop_intra"
    LOOP_INTER = "loop_inter"

    @property
    def is_loop_closure(self) -> bool:
        return self is not LinkType.NEIGHBOR


def loop_type(map_id_a: int, map_id_b: int) -> LinkType:
    """Intra-session or inter-session loop closure type for two nodes' map ids."""
    return LinkType.LOOP_INTRA if map_id_a == map_id_b else LinkType.LOOP_INTER


def default_information(variance: float) -> np.ndarray:
    """Diagonal 6x6 information matrix for one variance on every axis."""
    return np.eye(6) / variance


@dataclass(frozen=True)
class Link:
    """A rigid constraint between two nodes (``pose_to = pose_from @ T_from_to``)."""

    from_id: int
    to_id: int
    type: LinkType
    T_from_to: np.ndarray = field(default_factory=transforms.identity)
    information: np.ndarray = field(default_factory=lambda: default_information(1e-3))

    def __post_init__(self) -> None:
        # key() is asked millions of times a run (sets of link keys every frame): computed once.
        object.__setattr__(self, "_key", (min(self.from_id, self.to_id), max(self.from_id, self.to_id)))

    def residual(self, pose_from: np.ndarray, pose_to: np.ndarray) -> np.ndarray:
        """4x4 error of two poses against the link: identity when ``pose_to = pose_from @ T_from_to``."""
        return transforms.inverse(self.T_from_to) @ transforms.relative(pose_from, pose_to)

    def inverted(self) -> "Link":
        """The same constraint seen from the other end."""
        return Link(self.to_id, self.from_id, self.type, transforms.inverse(self.T_from_to), self.information)

    def key(self) -> tuple[int, int]:
        """Order-independent identity of the link."""
        return self._key

    @cached_property
    def row(self) -> np.ndarray:
        """(24,) float64: ``from_id``, ``to_id``, the inverse of ``T_from_to`` (16, row-major), the
        information's diagonal (6); made once per link (:class:`LinkTable` stacks them)."""
        return np.concatenate(((self.from_id, self.to_id), transforms.inverse(self.T_from_to).ravel(),
                               np.diagonal(self.information)), dtype=np.float64)

    def other(self, node_id: int) -> int:
        """The node at the other end."""
        return self.to_id if node_id == self.from_id else self.from_id

    def oriented_from(self, node_id: int) -> "Link":
        """This link with ``from_id == node_id``."""
        return self if node_id == self.from_id else self.inverted()


class Graph:
    """Adjacency of nodes and links: ids, types and transforms. The memory's graph holds the links
    that touch a location in memory (STM/WM) only; the global map's, every link."""

    def __init__(self, links: Iterable[Link] = ()) -> None:
        self._adjacency: dict[int, dict[int, Link]] = {}
        # Bumped by every link added or removed: tells a caller whether anything changed since
        # it last looked (the local map's leaf update).
        self.version = 0
        for link in links:
            self.add_link(link)

    def add_node(self, node_id: int) -> None:
        self._adjacency.setdefault(node_id, {})

    def add_link(self, link: Link) -> None:
        """Add (or replace) the link between two nodes."""
        self.version += 1
        self._adjacency.setdefault(link.from_id, {})[link.to_id] = link
        self._adjacency.setdefault(link.to_id, {})[link.from_id] = link

    def remove_link(self, a: int, b: int) -> None:
        self.version += 1
        self._adjacency.get(a, {}).pop(b, None)
        self._adjacency.get(b, {}).pop(a, None)

    def remove_node(self, node_id: int) -> list[Link]:
        """Remove a node and return its links (oriented from it)."""
        self.version += 1
        links = [link.oriented_from(node_id) for link in self._adjacency.pop(node_id, {}).values()]
        for link in links:
            self._adjacency.get(link.to_id, {}).pop(node_id, None)
        return links

    def discard_isolated(self, node_id: int) -> None:
        """Forget a node that has no link left (a no-op otherwise)."""
        if not self._adjacency.get(node_id, True):
            del self._adjacency[node_id]

    def __contains__(self, node_id: int) -> bool:
        return node_id in self._adjacency

    def __len__(self) -> int:
        return len(self._adjacency)

    def nodes(self) -> list[int]:
        return list(self._adjacency)

    def links_of(self, node_id: int) -> list[Link]:
        """Links of a node, oriented from it."""
        return [link.oriented_from(node_id) for link in self._adjacency.get(node_id, {}).values()]

    def stored_links_of(self, node_id: int) -> list[Link]:
        """Links of a node as stored (either orientation): the objects ``links_within`` returns."""
        return list(self._adjacency.get(node_id, {}).values())

    def link(self, a: int, b: int) -> Link | None:
        link = self._adjacency.get(a, {}).get(b)
        return None if link is None else link.oriented_from(a)

    def neighbors(self, node_id: int, types: Iterable[LinkType] | None = None) -> list[int]:
        wanted = None if types is None else set(types)
        return [other for other, link in self._adjacency.get(node_id, {}).items()
                if wanted is None or link.type in wanted]

    def links(self) -> list[Link]:
        """Every link once."""
        seen: dict[tuple[int, int], Link] = {}
        for adjacent in self._adjacency.values():
            for link in adjacent.values():
                seen.setdefault(link.key(), link)
        return list(seen.values())

    def hops_from(self, start: int, max_hops: int, types: Iterable[LinkType] | None = None,
                  allowed: Mapping[int, object] | set[int] | None = None,
                  free: Iterable[LinkType] = ()) -> dict[int, int]:
        """Hop distance to every node within ``max_hops`` (start included, at 0); links of ``free``
        types are crossed without counting a hop (0-1 breadth-first search)."""
        wanted = None if types is None else set(types)
        free = set(free)
        dist = {start: 0}
        queue = deque([start])
        while queue:
            node = queue.popleft()
            d = dist[node]
            for other, link in self._adjacency.get(node, {}).items():
                if (wanted is not None and link.type not in wanted) or (allowed is not None and other not in allowed):
                    continue
                step = 0 if link.type in free else 1
                if d + step > max_hops or dist.get(other, max_hops + 1) <= d + step:
                    continue
                dist[other] = d + step
                if step:
                    queue.append(other)
                else:
                    queue.appendleft(other)
        return dist

    def links_within(self, nodes: set[int] | Mapping[int, object]) -> list[Link]:
        """Links whose two ends are in ``nodes``, each once, as stored (no re-orientation)."""
        out = []
        for node in nodes:
            for other, link in self._adjacency.get(node, {}).items():
                if node < other and other in nodes:
                    out.append(link)
        return out

    def component(self, start: int, allowed: Mapping[int, object] | set[int] | None = None) -> set[int]:
        """Nodes connected to ``start`` (through ``allowed`` nodes only, if given).

        Breadth-first as ``hops_from`` without its hop counts and link types (a loop closure frame
        asks this of ~2,000 nodes); the set is made from the nodes in the order found, as from
        ``hops_from``'s dict, so that iterating it gives the same order."""
        found = {start: None}
        queue = deque([start])
        while queue:
            for other in self._adjacency.get(queue.popleft(), {}):
                if other not in found and (allowed is None or other in allowed):
                    found[other] = None
                    queue.append(other)
        return set(found)


def connected_components(node_ids: Iterable[int], links: Iterable[Link]) -> list[set[int]]:
    """Connected components of a node set (through links with both ends in it), largest first."""
    ids = list(dict.fromkeys(node_ids))
    index = {n: i for i, n in enumerate(ids)}
    ends = np.array([(index[link.from_id], index[link.to_id]) for link in links
                     if link.from_id in index and link.to_id in index], dtype=np.int64).reshape(-1, 2)
    labels = component_labels(len(ids), ends)
    components: dict[int, set[int]] = {}
    for node, label in zip(ids, labels.tolist()):
        components.setdefault(label, set()).add(node)
    return sorted(components.values(), key=len, reverse=True)


def component_labels(count: int, ends: np.ndarray) -> np.ndarray:
    """Component label of each of ``count`` nodes joined by ``ends`` ((m, 2) node indices): the
    smallest index in its component.

    Label propagation with pointer jumping (Shiloach & Vishkin 1982), in numpy: each link hooks the
    larger of its ends' labels onto the smaller, then every label jumps to its label's label until
    none moves; repeated until no link joins two labels. A few rounds on pose graphs (a chain of
    consecutive ids takes 2), without scipy's import (0.15-0.25 s of ``rtabmap-ros2 optimize``).
    """
    label = np.arange(count)
    if len(ends) == 0:
        return label
    a, b = ends[:, 0], ends[:, 1]
    while True:
        la, lb = label[a], label[b]
        joined = la != lb
        if not joined.any():
            return label
        la, lb = la[joined], lb[joined]
        low = np.minimum(la, lb)
        np.minimum.at(label, np.maximum(la, lb), low)
        while True:
            jumped = label[label]
            if np.array_equal(jumped, label):
                break
            label = jumped


def bridges(node_ids: Iterable[int], links: list[Link]) -> set[int]:
    """Indices in ``links`` of the bridges: links whose removal disconnects their two ends
    (Tarjan's low-link, iterative; parallel links are never bridges)."""
    adjacency: dict[int, list[tuple[int, int]]] = {n: [] for n in node_ids}
    for index, link in enumerate(links):
        adjacency.setdefault(link.from_id, []).append((link.to_id, index))
        adjacency.setdefault(link.to_id, []).append((link.from_id, index))
    order: dict[int, int] = {}
    low: dict[int, int] = {}
    found: set[int] = set()
    for start in adjacency:
        if start in order:
            continue
        order[start] = low[start] = len(order)
        stack = [(start, -1, iter(adjacency[start]))]
        while stack:
            node, via, edges = stack[-1]
            advanced = False
            for other, index in edges:
                if index == via:
                    continue
                if other in order:
                    low[node] = min(low[node], order[other])
                else:
                    order[other] = low[other] = len(order)
                    stack.append((other, index, iter(adjacency[other])))
                    advanced = True
                    break
            if advanced:
                continue
            stack.pop()
            if stack:
                parent = stack[-1][0]
                low[parent] = min(low[parent], low[node])
                if low[node] > order[parent]:
                    found.add(via)
    return found


def chain_poses(root_id: int, root_pose: np.ndarray, links: Iterable[Link]) -> dict[int, np.ndarray]:
    """Initial guess of every pose connected to the root by composing links breadth-first.

    Nodes of several sessions (each with its own odometry origin) get poses in one frame, the
    root's (2014 §II-B: the root is the newest node, always uniquely defined). Neighbour links are
    preferred over loop closures so odometry shapes the guess.
    """
    graph = Graph(links)
    poses = {root_id: np.asarray(root_pose, dtype=float)}
    queue = deque([root_id])
    while queue:
        node = queue.popleft()
        ordered = sorted(graph.links_of(node), key=lambda l: l.type is not LinkType.NEIGHBOR)
        for link in ordered:
            if link.to_id not in poses:
                poses[link.to_id] = poses[node] @ link.T_from_to
                queue.append(link.to_id)
    return poses


# consensus_guess: two alignments of a segment agree within these (translation, rotation).
CONSENSUS_DISTANCE_M = 0.5
CONSENSUS_ANGLE_RAD = np.deg2rad(10.0)


def residuals(poses: Mapping[int, np.ndarray], table: LinkTable) -> np.ndarray:
    """(N, 4, 4) residuals of the links of ``table`` at ``poses``: identity where a link holds exactly.
    Only the links' ends are stacked (a loop closure frame asks this of its ~300 inter-session links
    over a local map of ~1,600 poses)."""
    ends = np.unique(table.ends)
    missing = [n for n in ends.tolist() if n not in poses]
    if missing:
        raise KeyError(f"link end {missing[0]} has no pose")
    stack = PoseStack.of_arrays(ends, np.array([poses[n] for n in ends.tolist()], dtype=float))
    return stack.residuals(stack.rows(table.ends)[0], table.T_inverse)


class LinkTable:
    """Links as arrays, gathered from each link's :attr:`Link.row` in one conversion: ``ends``
    ((N, 2) int64 ``from_id``, ``to_id``), ``T_inverse`` ((N, 4, 4) inverses of ``T_from_to``) and
    ``information_diagonal`` ((N, 6)). A loop closure frame's checks read ~2,000 links; building
    these arrays link by link from Python was 5 of their 8 ms (seed 5, line profile)."""

    def __init__(self, links: list[Link]) -> None:
        rows = np.array([link.row for link in links], dtype=np.float64).reshape(-1, 24)
        self.ends = rows[:, :2].astype(np.int64)
        self.T_inverse = rows[:, 2:18].reshape(-1, 4, 4)
        self.information_diagonal = rows[:, 18:]


class PoseStack:
    """Poses as one (n, 4, 4) stack sorted by node id, looked up by arrays of ids: the local map's
    checks gather ~2,000 links a loop closure frame, and gathering 4x4 arrays or dict entries per
    link from Python was most of their time."""

    def __init__(self, poses: Mapping[int, np.ndarray]) -> None:
        ids = np.fromiter(poses, np.int64, len(poses))
        order = np.argsort(ids, kind="stable")
        self.ids = ids[order]
        self.poses = np.array(list(poses.values()), dtype=float).reshape(-1, 4, 4)[order]

    @classmethod
    def of_arrays(cls, ids: np.ndarray, poses: np.ndarray) -> "PoseStack":
        """The stack of (n,) ``ids`` and their (n, 4, 4) ``poses`` as a solver holds them (sorted here
        unless they already are), without going through a dict."""
        stack = cls.__new__(cls)
        ids = np.asarray(ids, np.int64)
        if ids.size > 1 and not (np.diff(ids) > 0).all():
            order = np.argsort(ids, kind="stable")
            ids, poses = ids[order], poses[order]
        stack.ids, stack.poses = ids, np.asarray(poses, dtype=float).reshape(-1, 4, 4)
        return stack

    @classmethod
    def of(cls, poses: "PoseStack | Mapping[int, np.ndarray]") -> "PoseStack":
        """``poses`` as a stack (itself when it is one)."""
        return poses if isinstance(poses, PoseStack) else cls(poses)

    def __len__(self) -> int:
        return len(self.ids)

    def gather(self, nodes: list[int]) -> np.ndarray:
        """(len(nodes), 4, 4) poses of ``nodes``, in that order (each must be in the stack)."""
        rows, found = self.rows(np.asarray(nodes, np.int64))
        if not found.all():
            raise KeyError(f"node {int(np.asarray(nodes)[~found][0])} has no pose")
        return self.poses[rows]

    def rows(self, nodes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Row of each of ``nodes`` (any shape) in the stack, and whether it has one (else row 0)."""
        rows = np.minimum(np.searchsorted(self.ids, nodes), max(len(self.ids) - 1, 0))
        found = self.ids[rows] == nodes if len(self.ids) else np.zeros(np.shape(nodes), bool)
        return np.where(found, rows, 0), found

    def residuals(self, rows: np.ndarray, T_inverse: np.ndarray) -> np.ndarray:
        """(N, 4, 4) ``T_inverse @ inv(P[from]) @ P[to]`` of links whose ends are at ``rows`` (N, 2)."""
        return rigid_products(T_inverse, self.poses[rows[:, 0]], self.poses[rows[:, 1]])


def rigid_products(L: np.ndarray | None, A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """(N, 4, 4) ``L @ inv(A) @ B`` of (N, 4, 4) rigid transforms (``inv(A) @ B`` when ``L`` is None).

    Compiled, on the rotation and translation blocks: a loop closure frame's error check takes
    these of its ~2,000 links three times, and numpy's stacked 4x4 products were 4-5 ms of it
    (issue 50). The kernel's module is imported here, not with this one: importing numba cost
    every ``rtabmap-ros2 optimize`` process 0.47 s, which never calls it."""
    from rtabmap_ros2.core.graph_compiled import rigid_products_into

    A = np.ascontiguousarray(A, dtype=np.float64)
    B = np.ascontiguousarray(B, dtype=np.float64)
    out = np.empty((len(A), 4, 4))
    if L is None:
        rigid_products_into(A, A, B, False, out)
    else:
        rigid_products_into(np.ascontiguousarray(L, dtype=np.float64), A, B, True, out)
    return out


def warm_up_residuals() -> None:
    """Compile :func:`rigid_products` (or load it from numba's cache) here rather than in a frame."""
    T = transforms.identity()[None]
    rigid_products(T, T, T)
    rigid_products(None, T, T)


def agree(difference: np.ndarray) -> bool:
    """True when two alignments whose 4x4 ``difference`` (inv(A) @ B) is given agree within
    :data:`CONSENSUS_DISTANCE_M` / :data:`CONSENSUS_ANGLE_RAD` (``_support`` does all pairs at once)."""
    return bool(agree_many(difference[None])[0])


def agree_many(differences: np.ndarray) -> np.ndarray:
    """:func:`agree` of each of (N, 4, 4) ``differences``, as a (N,) bool array."""
    cos = np.clip((np.trace(differences[:, :3, :3], axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0)
    return (np.linalg.norm(differences[:, :3, 3], axis=1) < CONSENSUS_DISTANCE_M) & (np.arccos(cos) < CONSENSUS_ANGLE_RAD)


def consensus_guess(root: int, root_pose: np.ndarray, links: list[Link]) -> dict[int, np.ndarray]:
    """Initial guess robust to false loop closures: odometry chains placed by consensus.

    Chaining every link breadth-first from the root (``graph.chain_poses``) can reach a whole
    session through one false loop closure (perceptual aliasing: look-alike posters 15 m apart),
    and the robust optimisation then starts from a guess tens of metres off and settles in a
    wrong minimum (measured on the simulated 5 sessions: guess ATE 21.8 m, result 17 m). Here:

    1. segments = nodes joined by neighbour links (one per session, odometry only);
    2. every loop closure between two segments proposes a rigid alignment of one on the other;
       a proposal's support = the proposals of the same pair agreeing with it within
       :data:`CONSENSUS_DISTANCE_M` / :data:`CONSENSUS_ANGLE_RAD`;
    3. segments are placed from the root's one along the best-supported proposals (a maximum
       spanning tree), so an isolated false loop closure never shapes the guess.

    Loop closures inside a segment do not change the guess (odometry). Returns node -> 4x4 pose.
    """
    neighbor_links = [l for l in links if l.type is LinkType.NEIGHBOR]
    nodes = {l.from_id for l in links} | {l.to_id for l in links} | {root}
    segments = connected_components(nodes, neighbor_links)
    segment_of = {n: k for k, seg in enumerate(segments) for n in seg}
    # Odometry chain of each segment, in the frame of its first-placed node.
    local: dict[int, dict[int, np.ndarray]] = {}
    for k, seg in enumerate(segments):
        start = root if root in seg else max(seg)
        local[k] = chain_poses(start, transforms.identity(), [l for l in neighbor_links if l.from_id in seg])
    proposals: dict[tuple[int, int], list[np.ndarray]] = {}
    for link in links:
        a, b = segment_of[link.from_id], segment_of[link.to_id]
        if a == b:
            continue
        # Pose of segment b's frame in segment a's frame implied by this link.
        T_a_b = local[a][link.from_id] @ link.T_from_to @ transforms.inverse(local[b][link.to_id])
        proposals.setdefault((a, b), []).append(T_a_b)
        proposals.setdefault((b, a), []).append(transforms.inverse(T_a_b))
    best: dict[tuple[int, int], tuple[int, np.ndarray]] = {}
    for pair, candidates in proposals.items():
        support = _support(np.stack(candidates))
        i = int(np.argmax(support))
        best[pair] = (int(support[i]), candidates[i])
    # Maximum spanning tree from the root's segment (Prim).
    start = segment_of[root]
    frame = {start: root_pose @ transforms.inverse(local[start][root])}
    while True:
        options = [(sup, a, b, T) for (a, b), (sup, T) in best.items() if a in frame and b not in frame]
        if not options:
            break
        _, a, b, T = max(options, key=lambda o: o[0])
        frame[b] = frame[a] @ T
    poses = {}
    for k, T_map_seg in frame.items():
        for n, T in local[k].items():
            poses[n] = T_map_seg @ T
    # Segments unreachable by loop closures cannot be in this component; keep the plain chain otherwise.
    missing = nodes - set(poses)
    if missing:
        chained = chain_poses(root, root_pose, links)
        poses.update({n: chained[n] for n in missing})
    return poses


def _support(alignments: np.ndarray) -> np.ndarray:
    """(K,) how many of K 4x4 alignments agree with each one (itself included), all pairs at once."""
    R = alignments[:, :3, :3]
    t = alignments[:, :3, 3]
    # D_ij = inv(A_i) @ A_j: rotation R_i^T R_j, translation R_i^T (t_j - t_i).
    rel_R = np.einsum("iba,jbc->ijac", R, R)
    cos = np.clip((np.trace(rel_R, axis1=2, axis2=3) - 1.0) / 2.0, -1.0, 1.0)
    dist = np.linalg.norm(t[None, :, :] - t[:, None, :], axis=2)  # |R_i^T (t_j - t_i)| = |t_j - t_i|
    agree = (dist < CONSENSUS_DISTANCE_M) & (np.arccos(cos) < CONSENSUS_ANGLE_RAD)
    return agree.sum(axis=1)
