"""Proximity detection by space: loop closures with nodes the local map puts near the robot, found by
registration instead of by appearance (RTAB-Map's RGBD/ProximityBySpace, visual part: Rtabmap.cpp,
"LOCAL LOOP CLOSURE SPACE", step 1 "compare visually with nearest locations"; its step 2, one-to-many
ICP against a path's assembled scans, RGBD/ProximityPathMaxNeighbors, is off by default there and not
made here).

Neither paper describes it: the Bayes filter (2013 §III-C) finds a revisit only when the new image's
words single one location out, so a place seen again a few metres on, or with the view partly changed,
can go without a loop closure although odometry and the last optimisation say where the robot is.
Here, as in RTAB-Map: the WM nodes (STM left out, as in the Bayes filter) within ``max_graph_depth``
links of the new node and ``radius`` of its pose in the local map are split into paths (runs of
nodes joined by neighbour links); the paths, highest likelihood this frame first (then the most
recent), each give at most one candidate: the path's most likely node if it faces the way the robot
does (``angle``), else the nearest that does, if it is within ``filtering_radius`` of the robot and not
linked to it yet; up to ``max_paths`` candidates are registered with the new node, and a link is kept
when its transform is within ``filtering_radius`` too. The loop closures found join the
frame's appearance-based one: the local map's optimisation and RGBD/OptimizeMaxError judge them all.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Mapping

import numpy as np

from rtabmap_ros2.core.graph import Graph, LinkType


@dataclass(frozen=True)
class ProximitySearch:
    """Where to look (RTAB-Map's parameters, ours in ``graph.proximity_*``)."""

    radius: float  # RGBD/LocalRadius (memory.local_radius)
    max_graph_depth: int  # RGBD/ProximityMaxGraphDepth; 0 = any depth
    max_paths: int  # RGBD/ProximityMaxPaths; 0 = every path
    filtering_radius: float  # RGBD/ProximityPathFilteringRadius
    angle_deg: float  # RGBD/ProximityAngle; 0 = any direction


def proximity_candidates(graph: Graph, memory_nodes: Mapping[int, object], wm: Mapping[int, object],
                         poses: Mapping[int, np.ndarray], new_id: int, new_pose: np.ndarray,
                         likelihood: Mapping[int, float], search: ProximitySearch) -> list[int]:
    """Nodes to register with the new node ``new_id`` at ``new_pose``, one per path, best path first.

    ``memory_nodes``: the nodes the graph search goes through (WM and STM); ``wm``: those that may be
    candidates (WM without STM); ``poses``: their poses in the local map (a node without one is left
    out); ``likelihood``: this frame's score of each location (0 when absent)."""
    depth_limit = search.max_graph_depth if search.max_graph_depth > 0 else len(memory_nodes) + 1
    reachable = graph.hops_from(new_id, depth_limit, allowed=memory_nodes)
    position = new_pose[:3, 3]
    distance = {n: float(np.linalg.norm(poses[n][:3, 3] - position))
                for n in reachable if n != new_id and n in wm and n in poses}
    paths = _paths(graph, sorted(n for n, d in distance.items() if d <= search.radius))
    ranked = sorted(((_path_key(path, likelihood), path) for path in paths), reverse=True)
    candidates: list[int] = []
    for (best_likelihood, best_id), path in ranked:
        if 0 < search.max_paths <= len(candidates):
            break  # RTAB-Map counts the paths it registers with, not those it looks at
        facing = [n for n in path if _facing(poses[n], new_pose, search.angle_deg)]
        if not facing:
            continue
        if best_likelihood > 0.0 and best_id in facing:
            chosen = best_id
        else:
            chosen = min(facing, key=distance.__getitem__)
        if graph.link(new_id, chosen) is not None:
            continue
        if distance[chosen] < search.filtering_radius:
            candidates.append(chosen)
    return candidates


def _paths(graph: Graph, nodes: list[int]) -> list[list[int]]:
    """``nodes`` (sorted) split into runs joined by neighbour links (RTAB-Map's getPaths: one
    proximity detection per path)."""
    paths: list[list[int]] = []
    for node in nodes:
        if paths:
            link = graph.link(paths[-1][-1], node)
            if link is not None and link.type is LinkType.NEIGHBOR:
                paths[-1].append(node)
                continue
        paths.append([node])
    return paths


def _path_key(path: list[int], likelihood: Mapping[int, float]) -> tuple[float, int]:
    """RTAB-Map's NearestPathKey: the path's highest likelihood, then the id having it (the path's
    first node when none has one)."""
    best = max(path, key=lambda n: (likelihood.get(n, 0.0), -n))
    value = likelihood.get(best, 0.0)
    return (value, best) if value > 0.0 else (0.0, path[0])


def _facing(pose: np.ndarray, new_pose: np.ndarray, angle_deg: float) -> bool:
    """True when the two bases' forward (x) axes are within ``angle_deg`` (RTAB-Map's
    graph::findNearestPoses angle test); any direction when it is 0."""
    if angle_deg <= 0.0:
        return True
    cos = float(np.clip(pose[:3, 0] @ new_pose[:3, 0], -1.0, 1.0))
    return math.degrees(math.acos(cos)) <= angle_deg


__all__ = ["ProximitySearch", "proximity_candidates"]
