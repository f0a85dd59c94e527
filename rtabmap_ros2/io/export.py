"""Export of the global map (issue 4's ``export`` command and the node's export service).

:func:`export_global_map` optimises every node and link of a database offline (2014 §II-C,
:func:`rtabmap_ros2.core.global_map.load_global_map`) and writes, in ``out_dir``:

* ``poses.txt``: TUM ``stamp x y z qx qy qz qw`` per node (base frame in the map frame, stamp in s);
* ``nodes.csv``: ``id,map_id,stamp,x,y,z,qx,qy,qz,qw,weight`` (stamp in s, as in poses.txt);
* ``links.csv``: ``from_id,to_id,type,x,y,z,qx,qy,qz,qw`` (``T_from_to``; type neighbor,
  loop_intra or loop_inter), the links kept by the optimisation;
* ``graph.g2o``: the optimised graph (SE2 when planar, else SE3:QUAT);
* ``map.pgm`` + ``map.yaml``: the occupancy grid in map_server format (0 occupied, 254 free,
  205 unknown; top image row = largest y);
* ``map.png``: the grid with the graph drawn as in the paper's figures (neighbour links blue,
  intra-session loop closures red, inter-session loop closures green);
* ``cloud.ply``: the assembled, voxel-filtered RGB-D point cloud (binary PLY, x y z + RGB);
* ``summary.json``: nodes, links by type, sessions, components, optimisation chi2 and time, the
  mode (``planar``), what the grid was made from (``grid.source``, and ``grid.empty_reason`` when no
  cell is known), and ``loop_closures_rejected_by_global_optimization`` (the stored loop closures
  the robust optimisation of the global map dropped: ``[from_id, to_id, type]``; not the hypotheses
  rejected online while mapping, which ``map`` counts per session).

The grid, picture and cloud show the largest connected component (the map); the poses, nodes,
links and g2o files hold every node with a pose. The database is opened read-only.
"""

from __future__ import annotations

import csv
import json
import logging
import os
import time
from pathlib import Path

import numpy as np

from rtabmap_ros2.core import files, transforms
from rtabmap_ros2.core.database import Database
from rtabmap_ros2.core.global_map import GlobalGrid, GlobalMap, assemble_global_grid, global_cloud, load_global_map
from rtabmap_ros2.core.graph import LinkType
from rtabmap_ros2.core.grid import OccupancyGrid, write_ply
from rtabmap_ros2.core.params import Params
from rtabmap_ros2.errors import DatabaseError, DatasetError
from rtabmap_ros2.io.g2o import write_g2o
from rtabmap_ros2.io.trajectory import Trajectory, seconds_to_ns, stamp_text, write_tum

log = logging.getLogger(__name__)

NODES_COLUMNS = ["id", "map_id", "stamp", "x", "y", "z", "qx", "qy", "qz", "qw", "weight"]
LINKS_COLUMNS = ["from_id", "to_id", "type", "x", "y", "z", "qx", "qy", "qz", "qw"]
# map_server thresholds written in map.yaml (ROS defaults).
OCCUPIED_THRESH = 0.65
FREE_THRESH = 0.196
# map.png link colours (RGB), as in the paper's figures.
LINK_COLORS = {LinkType.NEIGHBOR: (0, 0, 255), LinkType.LOOP_INTRA: (255, 0, 0), LinkType.LOOP_INTER: (0, 160, 0)}
# Loop closures are drawn over the neighbour links (and links over the node dots).
LINK_DRAW_ORDER = (LinkType.NEIGHBOR, LinkType.LOOP_INTRA, LinkType.LOOP_INTER)
NODE_COLOR = (0, 0, 128)
# map.png is upscaled so that it is at least this wide (small maps stay readable).
PNG_MIN_WIDTH_PX = 800
PNG_MAX_SCALE = 4

FILES = ("poses.txt", "nodes.csv", "links.csv", "graph.g2o", "map.pgm", "map.yaml", "map.png", "cloud.ply",
         "summary.json")


def export_global_map(database_path: str | os.PathLike, out_dir: str | os.PathLike, params: Params) -> dict:
    """Optimise the database's global map and write the export files (see the module doc).

    Each file is written under a temporary name in ``out_dir`` and renamed
    (:mod:`rtabmap_ros2.core.files`): a symlink planted at one of the names is replaced, never
    followed. When the export fails, the files it wrote and the folders it created are removed.

    Args:
        database_path: map database (opened read-only, never modified).
        out_dir: output folder (created if missing; files in it are overwritten).
        params: graph (optimiser, robust), registration.planar and grid parameters.

    Returns:
        The summary written to ``summary.json`` (plain dict).

    Raises:
        DatabaseError: missing or invalid database, unwritable output folder.
        OptimizationError: the optimiser failed.
    """
    out = Path(out_dir).expanduser()
    created = _missing_folders(out)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise DatabaseError(f"cannot create export folder {out}: {exc.strerror}") from exc
    written: list[Path] = []
    try:
        return _export(database_path, out, params, written)
    except BaseException:
        for path in written:
            path.unlink(missing_ok=True)
        for folder in created:   # deepest first; only if empty (nothing of anyone else's in it)
            try:
                folder.rmdir()
            except OSError:
                break
        raise


def _missing_folders(folder: Path) -> list[Path]:
    """``folder`` and its ancestors that do not exist yet, deepest first."""
    missing = []
    while not folder.exists() and not folder.is_symlink() and folder != folder.parent:
        missing.append(folder)
        folder = folder.parent
    return missing


def _export(database_path, out: Path, params: Params, written: list[Path]) -> dict:
    """The export proper; appends each file to ``written`` once it is complete."""
    t0 = time.perf_counter()

    def write(name: str, writer, *args) -> None:
        try:
            writer(out / name, *args)
        except OSError as exc:
            raise DatabaseError(f"cannot write {out / name}: {exc.strerror or exc}") from exc
        written.append(out / name)

    gmap = load_global_map(database_path, params)
    t_optimized = time.perf_counter()
    order = sorted(gmap.poses, key=lambda n: (gmap.stamps_ns[n], n))
    write("poses.txt", write_tum, [gmap.stamps_ns[n] for n in order], [gmap.poses[n] for n in order],
          "timestamp x y z qx qy qz qw (T_map_base of every node, global map optimised offline)")
    write("nodes.csv", write_nodes_csv, gmap, order)
    write("links.csv", write_links_csv, gmap)
    write("graph.g2o", write_g2o, gmap.poses, gmap.links, gmap.planar)
    with Database(database_path, read_only=True) as db:
        grid_result = assemble_global_grid(gmap, db, params)
        grid = grid_result.grid
        t_grid = time.perf_counter()
        points, colors = global_cloud(gmap, db, params)
    t_cloud = time.perf_counter()
    write("map.pgm", write_map_pgm, grid)
    write("map.yaml", write_map_yaml, grid, "map.pgm")
    write("map.png", write_map_png, grid, gmap)
    write("cloud.ply", write_ply, points, colors)
    summary = _summary(gmap, grid_result, len(points), database_path)
    summary["time_s"] = {"optimization": round(t_optimized - t0, 3), "grid": round(t_grid - t_optimized, 3),
                         "cloud": round(t_cloud - t_grid, 3), "total": round(time.perf_counter() - t0, 3)}
    summary["files"] = list(FILES)
    write("summary.json", files.write_text, json.dumps(summary, indent=2) + "\n")
    log.info("exported %d nodes, %d links, %d component(s) to %s", len(gmap.poses), len(gmap.links),
             len(gmap.components), out)
    return summary


def write_nodes_csv(path: Path, gmap: GlobalMap, order: list[int]) -> None:
    """``nodes.csv``: one row per posed node (optimised pose in the map frame)."""
    with files.new_file(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(NODES_COLUMNS)
        for n in order:
            T = gmap.poses[n]
            q = transforms.quat_xyzw(T)
            w.writerow([n, gmap.map_ids[n], stamp_text(gmap.stamps_ns[n]), *(f"{v:.6f}" for v in T[:3, 3]),
                        *(f"{v:.9f}" for v in q), gmap.weights[n]])


def read_nodes_csv(path: str | os.PathLike) -> dict[int, Trajectory]:
    """An export's ``nodes.csv`` as one trajectory per session (map id), nodes in file order."""
    rows: dict[int, tuple[list[int], list[np.ndarray]]] = {}
    try:
        with open(path, newline="") as f:
            for row in csv.DictReader(f):
                stamps, poses = rows.setdefault(int(row["map_id"]), ([], []))
                stamps.append(seconds_to_ns(row["stamp"]))
                poses.append(transforms.from_xyz_quat_xyzw([float(row[c]) for c in ("x", "y", "z")],
                                                           [float(row[c]) for c in ("qx", "qy", "qz", "qw")]))
    except (OSError, KeyError, ValueError) as exc:
        raise DatasetError(f"cannot read the export's nodes {path}: {exc}") from exc
    return {m: Trajectory(np.asarray(stamps, dtype=np.int64), np.stack(poses)) for m, (stamps, poses) in rows.items()}


def write_links_csv(path: Path, gmap: GlobalMap) -> None:
    """``links.csv``: one row per kept link, ``T_from_to`` as translation + quaternion."""
    with files.new_file(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(LINKS_COLUMNS)
        for link in sorted(gmap.links, key=lambda l: (l.from_id, l.to_id)):
            T = link.T_from_to
            q = transforms.quat_xyzw(T)
            w.writerow([link.from_id, link.to_id, link.type.value, *(f"{v:.6f}" for v in T[:3, 3]),
                        *(f"{v:.9f}" for v in q)])


def write_map_pgm(path: Path, grid: OccupancyGrid) -> None:
    """``map.pgm``: binary P5, map_server grey levels, top row = largest y."""
    image = grid.to_image()
    height, width = image.shape
    header = f"P5\n# rtabmap_ros2 occupancy grid, {grid.resolution} m/cell\n{width} {height}\n255\n"
    files.write_bytes(path, header.encode("ascii") + np.ascontiguousarray(image).tobytes())


def write_map_yaml(path: Path, grid: OccupancyGrid, image_name: str) -> None:
    """``map.yaml``: map_server's description of the image ``image_name`` (same folder)."""
    files.write_text(
        path,
        f"image: {image_name}\n"
        f"resolution: {grid.resolution:.6g}\n"
        f"origin: [{grid.origin_xy[0]:.6f}, {grid.origin_xy[1]:.6f}, 0.0]\n"
        "negate: 0\n"
        f"occupied_thresh: {OCCUPIED_THRESH}\n"
        f"free_thresh: {FREE_THRESH}\n")


def write_map_png(path: Path, grid: OccupancyGrid, gmap: GlobalMap) -> None:
    """The grid (grey) with the graph of its component drawn over it (2014 Fig. 7 colours)."""
    import cv2

    grey = grid.to_image()
    scale = int(min(PNG_MAX_SCALE, max(1, np.ceil(PNG_MIN_WIDTH_PX / max(grid.width, 1)))))
    rgb = np.repeat(grey[:, :, None], 3, axis=2)
    if scale > 1:
        rgb = cv2.resize(rgb, (grid.width * scale, grid.height * scale), interpolation=cv2.INTER_NEAREST)
    shown = gmap.components[0] if gmap.components else set()

    def pixel(node: int) -> tuple[int, int]:
        # Cell centre -> image pixel (rows flipped: image row 0 = largest y).
        x, y = gmap.poses[node][:2, 3]
        col = (x - grid.origin_xy[0]) / grid.resolution * scale
        row = (grid.height - (y - grid.origin_xy[1]) / grid.resolution) * scale
        return int(round(col)), int(round(row))

    for node in shown:
        cv2.circle(rgb, pixel(node), 1, NODE_COLOR, -1)
    # Links over the nodes, loop closures last: a loop closure between two nodes seen from
    # nearly the same place is only a few pixels long.
    for link_type in LINK_DRAW_ORDER:
        color = LINK_COLORS[link_type]
        for link in gmap.links:
            if link.type is link_type and link.from_id in shown and link.to_id in shown:
                cv2.line(rgb, pixel(link.from_id), pixel(link.to_id), color, 1, cv2.LINE_8)
    ok, png = cv2.imencode(".png", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    if not ok:
        raise DatabaseError(f"cannot PNG-encode {path}")
    files.write_bytes(path, png.tobytes())


def _summary(gmap: GlobalMap, grid_result: GlobalGrid, cloud_points: int, database_path) -> dict:
    grid = grid_result.grid
    sessions = {}
    for n, m in gmap.map_ids.items():
        s = sessions.setdefault(int(m), {"map_id": int(m), "nodes": 0, "in_wm": 0})
        s["nodes"] += 1
        s["in_wm"] += int(gmap.in_wm[n])
    return {
        "database": str(Path(database_path).expanduser().absolute()),
        "nodes": len(gmap.poses),
        "nodes_in_wm": int(sum(gmap.in_wm.values())),
        "links": len(gmap.links),
        "links_by_type": dict(gmap.links_by_type),
        "loop_closures_rejected_by_global_optimization": [[l.from_id, l.to_id, l.type.value] for l in gmap.rejected],
        "sessions": [sessions[k] for k in sorted(sessions)],
        "components": len(gmap.components),
        "component_sizes": [len(c) for c in gmap.components],
        "component_roots": list(gmap.roots),
        "planar": gmap.planar,
        "optimization": {
            "chi2_initial": gmap.chi2_initial, "chi2_final": gmap.chi2_final,
            "iterations": int(sum(r.iterations for r in gmap.optimizations)),
            "time_s": round(gmap.optimization_time_s, 4)},
        "grid": {"width": grid.width, "height": grid.height, "resolution": grid.resolution,
                 "origin": [grid.origin_xy[0], grid.origin_xy[1]], "sensor": grid_result.sensor,
                 "laser_nodes": grid_result.laser_nodes, "depth_nodes": grid_result.depth_nodes,
                 "source": grid_result.source(), "empty_reason": grid_result.empty_reason},
        "cloud_points": int(cloud_points),
    }


__all__ = ["FILES", "LINKS_COLUMNS", "NODES_COLUMNS", "export_global_map", "read_nodes_csv", "write_links_csv", "write_map_pgm",
           "write_map_png", "write_map_yaml", "write_nodes_csv"]
