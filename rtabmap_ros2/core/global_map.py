"""The global map (2014 §II-C): every node and link of the database, optimised offline.

Online, only the local map (WM nodes connected to the newest node) is optimised. Offline, "the
approach is still able to create a global map by using all constraints from LTM and conduct
offline a global graph optimization" (2014 §II-C): :func:`load_global_map` reads every node and
link of a database (WM and LTM) read-only and optimises each connected component of the graph:

* root = the newest node of the component, held at its odometry pose (2014 §II-B: the newest
  node is always uniquely defined across sessions), so the largest component's map frame is the
  one the robot used online at the end of the last session;
* initial guess = each session's odometry chain, sessions placed by the loop closures that
  agree with most others (:func:`consensus_guess`: robust to false loop closures);
* gtsam optimisation (``core.optimizer.optimize``) with all links, robust per ``graph.robust``
  (dynamic covariance scaling; loop closures inconsistent with the rest are dropped);
* planar (x, y, yaw) when ``registration.planar`` (RTAB-Map's Reg/Force3DoF), as online, else 6 DoF.

Components other than the largest are maps never connected to it by a loop closure (the paper's
§IV worst case): each is optimised on its own, rooted at its own newest node's odometry pose.

:func:`global_grid` and :func:`global_cloud` build the occupancy grid (laser scans and / or depth
images, ``grid.sensor``) and the RGB-D point cloud of the optimised global map;
:func:`assemble_global_grid` also says what the grid was made from, and why it is empty when it is.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass, field
from typing import Iterable, Optional

import numpy as np

from rtabmap_ros2.core.database import Database
from rtabmap_ros2.core.graph import Link, LinkType, connected_components, consensus_guess
from rtabmap_ros2.core.grid import (GridAccumulator, OccupancyGrid, assemble_cloud, depth_cells, grid_sources,
                                   voxel_filter)
from rtabmap_ros2.core.optimizer import OptimizationResult, optimize
from rtabmap_ros2.core.params import Params

log = logging.getLogger(__name__)

# Point cloud: nodes whose depth images are decoded and assembled at once (bounds the memory used:
# 50 x 640x480 float32 depth = 60 MB), each chunk voxel-filtered before the final filter.
CLOUD_CHUNK_NODES = 50
# Initial guess: two loop closures propose the same alignment of two sessions within these.


@dataclass
class GlobalMap:
    """Every node and link of a database, optimised (2014 §II-C).

    Attributes:
        poses: node id -> 4x4 optimised ``T_map_base`` (m). Nodes without odometry (appearance-only
            mode) have no pose and are absent.
        odom_poses: node id -> 4x4 ``T_odom_base`` as recorded (each session in its own odometry frame).
        links: the links kept by the optimisation (every stored link between posed nodes, minus
            the loop closures rejected by the robust option), ``pose_to = pose_from @ T_from_to``.
        rejected: loop closures dropped by the robust option (inconsistent with the graph).
        map_ids, stamps_ns, weights, in_wm: per node id: session, stamp (ns), weight, True in WM.
        components: connected components of the graph (sets of node ids), largest first;
            ``components[0]`` is the map; the others could not be connected to it.
        roots: root node (newest node) of each component, same order.
        optimizations: one :class:`OptimizationResult` per component, same order.
        planar: optimised in 3 DoF (x, y, yaw).
    """

    poses: dict[int, np.ndarray]
    odom_poses: dict[int, np.ndarray]
    links: list[Link]
    rejected: list[Link]
    map_ids: dict[int, int]
    stamps_ns: dict[int, int]
    weights: dict[int, int]
    in_wm: dict[int, bool]
    components: list[set[int]]
    roots: list[int]
    optimizations: list[OptimizationResult]
    planar: bool
    links_by_type: dict[str, int] = field(default_factory=dict)

    @property
    def chi2_initial(self) -> float:
        """Sum over components of the initial chi2 (whitened squared errors)."""
        return float(sum(r.chi2_initial for r in self.optimizations))

    @property
    def chi2_final(self) -> float:
        """Sum over components of the final chi2 over the kept links."""
        return float(sum(r.chi2_final for r in self.optimizations))

    @property
    def optimization_time_s(self) -> float:
        return float(sum(r.time_s for r in self.optimizations))

    def node_ids(self) -> list[int]:
        """Posed node ids in increasing order."""
        return sorted(self.poses)


def load_global_map(database_path: str | os.PathLike, params: Params) -> GlobalMap:
    """Read a database read-only and optimise all its nodes and links (2014 §II-C).

    Args:
        database_path: the map database (never modified).
        params: ``graph`` (optimiser, robust) and ``registration.planar``.

    Returns:
        :class:`GlobalMap`.

    Raises:
        DatabaseError: the file is missing or not a map database.
        OptimizationError: the optimiser failed.
    """
    with Database(database_path, read_only=True) as db:
        nodes = db.load_nodes()
        stored_links = db.load_links()
    odom = {i: n.T_odom_base for i, n in nodes.items() if n.T_odom_base is not None}
    if len(odom) < len(nodes):
        log.warning("%d of %d nodes have no odometry pose (appearance-only mode): left out of the global map",
                    len(nodes) - len(odom), len(nodes))
    links = [link for link in stored_links if link.from_id in odom and link.to_id in odom]
    planar = bool(params.registration.planar)
    components = connected_components(odom.keys(), links)
    poses: dict[int, np.ndarray] = {}
    roots, results, rejected = [], [], []
    for component in components:
        # Root = the newest node, at its odometry pose (2014 §II-B).
        root = max(component, key=lambda n: (nodes[n].stamp_ns, n))
        comp_links = [link for link in links if link.from_id in component]
        guess = consensus_guess(root, odom[root], comp_links)
        result = optimize(guess, comp_links, root, params.graph, planar)
        poses.update(result.poses)
        roots.append(root)
        results.append(result)
        rejected.extend(result.rejected)
    rejected_keys = {link.key() for link in rejected}
    kept = [link for link in links if link.key() not in rejected_keys]
    by_type = {t.value: sum(1 for link in kept if link.type is t) for t in LinkType}
    if rejected:
        log.info("global optimisation rejected %d loop closure(s): %s", len(rejected),
                 [(l.from_id, l.to_id) for l in rejected])
    return GlobalMap(
        poses=poses, odom_poses=odom, links=kept, rejected=rejected,
        map_ids={i: nodes[i].map_id for i in odom}, stamps_ns={i: nodes[i].stamp_ns for i in odom},
        weights={i: nodes[i].weight for i in odom}, in_wm={i: nodes[i].in_wm for i in odom},
        components=components, roots=roots, optimizations=results, planar=planar, links_by_type=by_type)


def _selected(global_map: GlobalMap, nodes: Optional[Iterable[int]]) -> dict[int, np.ndarray]:
    """Optimised poses of ``nodes`` (default: the largest component, the map)."""
    if nodes is None:
        nodes = global_map.components[0] if global_map.components else ()
    return {n: global_map.poses[n] for n in nodes if n in global_map.poses}


@dataclass
class GlobalGrid:
    """The global map's occupancy grid and what it was made from.

    Attributes:
        grid: the grid (1x1 unknown when nothing was observed).
        sensor: ``grid.sensor`` as given (auto, laser, depth, both).
        laser_nodes: nodes whose laser scan was cast.
        depth_nodes: nodes whose depth image was cast.
        empty_reason: why no cell is known ('' when some are): a sentence naming the cause and the
            parameter to change.
    """

    grid: OccupancyGrid
    sensor: str
    laser_nodes: int = 0
    depth_nodes: int = 0
    empty_reason: str = ""

    def source(self) -> str:
        """What the cells come from, e.g. ``laser scans of 94 nodes`` (grid.sensor auto)."""
        parts = [f"{what} of {n} nodes" for what, n in (("laser scans", self.laser_nodes),
                                                       ("depth images", self.depth_nodes)) if n]
        return f"{' and '.join(parts) or 'nothing'} (grid.sensor {self.sensor})"


def assemble_global_grid(global_map: GlobalMap, database: Database, params: Params,
                         nodes: Optional[Iterable[int]] = None) -> GlobalGrid:
    """Occupancy grid of the laser scans and / or depth images (``grid.sensor``) at the optimised
    poses; an empty grid is logged as a warning with its reason.

    Args:
        global_map: from :func:`load_global_map`.
        database: the same database (open, read-only is fine).
        params: ``grid`` (resolution, range_max, sensor, depth decimation and heights).
        nodes: node ids to use; default the largest component (other components are in frames
            unrelated to it and would be drawn over it).
    """
    poses = _selected(global_map, nodes)
    sensor = params.grid.sensor
    scans = database.load_scans(ids=list(poses)) if sensor != "depth" and poses else {}
    depth_ids = sorted(n for n in poses if grid_sources(sensor, n in scans)[1])
    scans = {n: scan for n, scan in scans.items() if grid_sources(sensor, True)[0]}
    accumulator = GridAccumulator(params.grid)
    for node_id, scan in scans.items():
        accumulator.add(poses[node_id], scan)
    depth_nodes = 0
    for start in range(0, len(depth_ids), CLOUD_CHUNK_NODES):
        chunk = depth_ids[start:start + CLOUD_CHUNK_NODES]
        cameras = {s.id: s.camera for s in database.load_signatures(chunk) if s.camera is not None}
        for node_id, camera in cameras.items():
            depth = database.load_sensor_blobs(node_id).depth_m()
            if depth is not None:
                accumulator.add_depth(depth_cells(poses[node_id], depth, camera, params.grid))
                depth_nodes += 1
    result = GlobalGrid(accumulator.grid(), sensor, len(scans), depth_nodes)
    if not accumulator.observed:
        result.empty_reason = _empty_grid_reason(len(poses), result, params)
        log.warning("the occupancy grid is empty: %s", result.empty_reason)
    return result


def _empty_grid_reason(posed: int, result: GlobalGrid, params: Params) -> str:
    """Why nothing reached the grid (a sentence naming the parameter to change)."""
    g = params.grid
    if not posed:
        return "the map has no node with a pose (appearance-only mapping, no odometry)"
    if not result.laser_nodes and not result.depth_nodes:
        if g.sensor == "laser":
            return (f"grid.sensor is laser (Grid/Sensor 0) and none of the map's {posed} nodes has a laser scan: "
                    "set grid.sensor to auto or depth (Grid/Sensor=1) to build it from the depth images")
        return (f"none of the map's {posed} nodes has a depth image with a camera model"
                + ("" if g.sensor == "depth" else " or a laser scan") + ": no sensor to build it from")
    heights = (f"ground up to {g.ground_height:g} m, obstacles up to "
               + (f"{g.max_obstacle_height:g} m" if g.max_obstacle_height else "any height")
               + (f", nothing below {g.min_ground_height:g} m" if g.min_ground_height else ""))
    return (f"no point of the {result.depth_nodes} depth images lies within grid.range_max ({g.range_max:g} m) "
            f"and the height limits ({heights}; map-frame z)")


def global_grid(global_map: GlobalMap, database: Database, params: Params,
                nodes: Optional[Iterable[int]] = None) -> OccupancyGrid:
    """Occupancy grid of the optimised global map (:func:`assemble_global_grid`'s grid)."""
    return assemble_global_grid(global_map, database, params, nodes).grid


def global_cloud(global_map: GlobalMap, database: Database, params: Params,
                 nodes: Optional[Iterable[int]] = None) -> tuple[np.ndarray, np.ndarray]:
    """Coloured RGB-D point cloud (map frame) of the nodes' depth images at the optimised poses.

    Decimation and voxel size from ``params.grid``; images decoded :data:`CLOUD_CHUNK_NODES`
    nodes at a time. ``nodes`` as in :func:`global_grid`.

    Returns:
        ``(points (N,3) float32 m, colors (N,3) uint8 RGB)``.
    """
    poses = _selected(global_map, nodes)
    ids = sorted(poses)
    decimation, voxel = params.grid.cloud_decimation, params.grid.cloud_voxel_size
    chunks_pts, chunks_cols = [], []
    for start in range(0, len(ids), CLOUD_CHUNK_NODES):
        chunk = ids[start:start + CLOUD_CHUNK_NODES]
        cameras = {s.id: s.camera for s in database.load_signatures(chunk) if s.camera is not None}
        depths, rgbs = {}, {}
        for node_id in cameras:
            blobs = database.load_sensor_blobs(node_id)
            depth = blobs.depth_m()
            if depth is None:
                continue
            depths[node_id] = depth
            rgb = blobs.rgb()
            if rgb is not None:
                rgbs[node_id] = rgb
        pts, cols = assemble_cloud({n: poses[n] for n in depths}, depths, rgbs, cameras, decimation, voxel)
        chunks_pts.append(pts)
        chunks_cols.append(cols)
    if not chunks_pts:
        return np.zeros((0, 3), np.float32), np.zeros((0, 3), np.uint8)
    pts, cols = voxel_filter(np.concatenate(chunks_pts), np.concatenate(chunks_cols), voxel)
    return pts, (cols if cols is not None else np.zeros((0, 3), np.uint8))


__all__ = ["GlobalGrid", "GlobalMap", "assemble_global_grid", "consensus_guess", "global_cloud", "global_grid",
           "load_global_map"]
