"""Figures and an HTML page of a mapping run, drawn like the papers' figures (issue 6).

:func:`write_report` reads a map database read-only (per-frame statistics, nodes, links, the
parameters used), optimises the global map offline
(:func:`rtabmap_ros2.core.global_map.load_global_map`) and writes PNG figures (matplotlib, no
display needed) and ``index.html`` showing them with the run's parameters and summary:

* ``process_time.png``: pTime per frame with T_time and the acquisition period R = 1 / detection
  rate (2013 Fig. 7, 2014 Fig. 6 and 12), session starts marked;
* ``memory.png``: WM size (and local map size) and vocabulary size per frame;
* ``global_map.png``: occupancy grid of the optimised global map with its graph: neighbour links
  blue, intra-session loop closures red, inter-session green (2014 Fig. 7, 9, 11);
* ``sessions_y.png``: y of the odometry poses over time, coloured by session, with the loop
  closures (inter-session green, intra-session red) that join the sessions (2014 Fig. 8);
* ``local_vs_global.png``: the last local map (WM nodes connected to the newest node, optimised
  as online, 2014 §II-C) next to the global map with the WM nodes marked (2014 Fig. 10);
* with ground truth (TUM file, e.g. the simulator's ``ground_truth.txt``):
  ``trajectories.png`` (estimate after one rigid alignment vs truth, ATE in the title);
* with ground truth and ``loops.csv``: ``precision_recall.png`` over T_loop thresholds applied
  to each frame's highest hypothesis (2013 Fig. 4).

Figures that cannot be drawn (no ground truth, no laser scans...) are listed with the reason in
``Report.skipped`` and on the page.
"""

from __future__ import annotations

import html
import json
import logging
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

import numpy as np

from rtabmap_ros2.core.database import Database
from rtabmap_ros2.core.global_map import GlobalMap, assemble_global_grid, load_global_map
from rtabmap_ros2.core.graph import Graph, Link, LinkType, chain_poses
from rtabmap_ros2.core.grid import OccupancyGrid, build_grid
from rtabmap_ros2.core.optimizer import optimize
from rtabmap_ros2.core.params import Params
from rtabmap_ros2.errors import DatabaseError, RtabmapError

log = logging.getLogger(__name__)

MS_PER_S = 1000.0
NS_PER_S = 1_000_000_000
# File names a run folder (the demo's output) holds.
RUN_DATABASE = "map.db"
RUN_GROUND_TRUTH = ("sim/ground_truth.txt", "ground_truth.txt")
RUN_LOOPS = ("sim/loops.csv", "loops.csv")
RUN_EXPORT = "export"
# Figure files, in the order the page shows them.
FIGURES = ("process_time.png", "memory.png", "global_map.png", "sessions_y.png", "local_vs_global.png",
           "trajectories.png", "precision_recall.png")
# Link colours of the paper's figures (2014 Fig. 7-11).
LINK_COLORS = {LinkType.NEIGHBOR: "#1f4fd6", LinkType.LOOP_INTRA: "#e02020", LinkType.LOOP_INTER: "#10a010"}
LINK_LABELS = {LinkType.NEIGHBOR: "neighbour links", LinkType.LOOP_INTRA: "intra-session loop closures",
               LinkType.LOOP_INTER: "inter-session loop closures"}
# Session colours: none close to the links' blue, red and green.
SESSION_COLORS = ("#9467bd", "#ff7f0e", "#8c564b", "#e377c2", "#17becf", "#bcbd22", "#7f7f7f", "#1b1b6b")
# Occupancy grid grey levels (0 black .. 1 white): unknown, free, occupied.
GRID_GREY = {"unknown": 0.82, "free": 1.0, "occupied": 0.1}
DPI = 110
# Map figures show the robot's path with this margin (m) rather than the whole grid.
MAP_MARGIN_M = 4.0
# Ground-truth stamps further apart than this (s) belong to different sessions (drawn apart).
TRAJECTORY_GAP_S = 10.0
# sessions_y.png: loop closure lines get alpha = this / count, within [0.25, 0.8].
SESSION_LINKS_ALPHA_SCALE = 40.0
# A detected loop closure is correct when the true poses of the frame and of the hypothesis are
# this close. The simulator's loops.csv lists revisits within 1 m / 30 deg; the angle is wider
# here because views 30-45 deg apart still overlap (measured: a RANSAC-verified loop closure of
# the --small run is 0.23 m / 35.6 deg from its hypothesis, and would count as false at 30 deg).
CORRECT_MAX_DISTANCE_M = 1.0
CORRECT_MAX_ANGLE_DEG = 45.0


@dataclass
class ReportInputs:
    """What a report is drawn from.

    Attributes:
        database: the map database (opened read-only).
        ground_truth: TUM file of the true base poses (stamps equal to the frames'), or None.
        loops: the simulator's ``loops.csv`` (frames where a loop closure exists), or None.
        export_dir: the export folder of the run (``map.png`` is linked from the page), or None.
    """

    database: Path
    ground_truth: Optional[Path] = None
    loops: Optional[Path] = None
    export_dir: Optional[Path] = None


@dataclass
class Report:
    """What :func:`write_report` wrote.

    Attributes:
        out_dir: the report folder.
        index_html: the page.
        figures: figure file name -> path, for the figures drawn.
        skipped: figure file name -> why it was not drawn.
        summary: the run's numbers (sessions, nodes, loop closures, ATE, pTime...), also in
            ``summary.json``.
    """

    out_dir: Path
    index_html: Path
    figures: dict[str, Path] = field(default_factory=dict)
    skipped: dict[str, str] = field(default_factory=dict)
    summary: dict = field(default_factory=dict)


def find_inputs(path: str | os.PathLike, ground_truth: Optional[str | os.PathLike] = None,
                loops: Optional[str | os.PathLike] = None) -> ReportInputs:
    """Inputs from a database file or a run folder (``map.db``, ``sim/ground_truth.txt``, ``export/``).

    Explicit ``ground_truth`` / ``loops`` win over the files found in a run folder.

    Raises:
        DatabaseError: ``path`` is neither a database file nor a folder holding ``map.db``.
    """
    path = Path(path).expanduser()
    run_dir = None
    if path.is_dir():
        run_dir = path
        database = path / RUN_DATABASE
        if not database.is_file():
            raise DatabaseError(f"{path} is a folder without {RUN_DATABASE}: give the database file or a "
                                f"folder written by 'rtabmap-ros2 demo'")
    elif path.is_file():
        database = path
    else:
        raise DatabaseError(f"{path} does not exist: give a map database or a run folder")

    def found(names: tuple[str, ...]) -> Optional[Path]:
        if run_dir is None:
            return None
        return next((run_dir / n for n in names if (run_dir / n).is_file()), None)

    export_dir = run_dir / RUN_EXPORT if run_dir is not None and (run_dir / RUN_EXPORT).is_dir() else None
    return ReportInputs(
        database=database,
        ground_truth=Path(ground_truth).expanduser() if ground_truth else found(RUN_GROUND_TRUTH),
        loops=Path(loops).expanduser() if loops else found(RUN_LOOPS),
        export_dir=export_dir)


# -- data --------------------------------------------------------------------------------------
@dataclass
class _Run:
    """Everything read from the database once."""

    params: Params
    stats: list[dict]
    gmap: GlobalMap
    grid: Optional[OccupancyGrid]
    local_poses: dict[int, np.ndarray]
    local_links: list[Link]
    local_grid: Optional[OccupancyGrid]
    session_of_map: dict[int, int]


def _params_of(db: Database) -> Params:
    """The parameters stored with the run (defaults if the database has none)."""
    stored = db.get_parameters()
    if not stored:
        log.warning("the database holds no parameters: the report uses the defaults")
        return Params()
    return Params.from_stored(stored)


def _local_map(nodes: dict, links: list[Link], params: Params, planar: bool
               ) -> tuple[dict[int, np.ndarray], list[Link]]:
    """The last local map (2014 §II-C): WM nodes connected to the newest WM node, optimised.

    Root = the newest node at its odometry pose, as the online optimisation and
    :func:`load_global_map` do, so the local map and the largest global component share a frame.
    """
    wm = {n for n, info in nodes.items() if info.in_wm and info.T_odom_base is not None}
    if not wm:
        return {}, []
    newest = max(wm, key=lambda n: (nodes[n].stamp_ns, n))
    component = Graph(links).component(newest, allowed=wm)
    component.add(newest)
    local_links = [link for link in links if link.from_id in component and link.to_id in component]
    guess = chain_poses(newest, nodes[newest].T_odom_base, local_links)
    if not any(link.type.is_loop_closure for link in local_links):
        return guess, local_links
    result = optimize(guess, local_links, newest, params.graph, planar)
    rejected = {link.key() for link in result.rejected}
    return result.poses, [link for link in local_links if link.key() not in rejected]


def _load_run(database: Path, params: Optional[Params]) -> _Run:
    with Database(database, read_only=True) as db:
        params = params if params is not None else _params_of(db)
        stats = db.load_statistics()
        nodes = db.load_nodes()
        links = db.load_links()
        gmap = load_global_map(database, params)
        assembled = assemble_global_grid(gmap, db, params) if gmap.poses else None
        grid = assembled.grid if assembled is not None and not assembled.empty_reason else None
        local_poses, local_links = _local_map(nodes, links, params, gmap.planar)
        same_as_global = bool(gmap.components) and set(local_poses) == gmap.components[0]
        local_scans = db.load_scans(list(local_poses)) if local_poses and not same_as_global else {}
    if same_as_global:
        # Nothing was transferred to LTM: the local map is the global map (same graph, same root).
        local_grid = grid
    else:
        local_grid = build_grid({n: local_poses[n] for n in local_scans}, local_scans, params.grid) if local_scans else None
    map_ids = sorted({int(r["map_id"]) for r in stats} | set(gmap.map_ids.values()))
    return _Run(params, stats, gmap, grid, local_poses, local_links, local_grid,
                {m: k + 1 for k, m in enumerate(map_ids)})


def _column(stats: list[dict], key: str) -> np.ndarray:
    return np.array([float(r.get(key, 0.0) or 0.0) for r in stats])


def _loop_counts(stats: list[dict]) -> dict[str, int]:
    types = [r.get("loop_closure_type", "") for r in stats]
    return {"intra": sum(t == LinkType.LOOP_INTRA.value for t in types),
            "inter": sum(t == LinkType.LOOP_INTER.value for t in types)}


# -- figures -----------------------------------------------------------------------------------
def _figure(width_in: float, height_in: float, rows: int = 1, cols: int = 1, **kw):
    """A matplotlib Figure (object API: no pyplot state, no backend selection) and its axes."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width_in, height_in), dpi=DPI, layout="constrained")
    axes = fig.subplots(rows, cols, **kw)
    return fig, axes


def _session_starts(stats: list[dict]) -> list[tuple[int, int]]:
    """(frame_index, map_id) where each map (session) starts."""
    starts, last = [], None
    for r in stats:
        m = int(r["map_id"])
        if m != last:
            starts.append((int(r["frame_index"]), m))
            last = m
    return starts


def _mark_sessions(ax, run: _Run, label_top: bool = True) -> None:
    """Dotted vertical lines at session starts, labelled 'session k'."""
    for k, (frame, map_id) in enumerate(_session_starts(run.stats)):
        if k:
            ax.axvline(frame, color="0.45", ls=":", lw=1.0)
        if label_top:
            ax.annotate(f"session {run.session_of_map[map_id]}", (frame, 1.0), xycoords=("data", "axes fraction"),
                        xytext=(3, -3), textcoords="offset points", va="top", fontsize=8, color="0.3")


def plot_process_time(run: _Run, path: Path) -> None:
    """pTime per frame with T_time and R (2013 Fig. 7, 2014 Fig. 6 and 12)."""
    frames = _column(run.stats, "frame_index")
    ptime_s = _column(run.stats, "process_time_ms") / MS_PER_S
    t_time_s = run.params.memory.time_threshold_ms / MS_PER_S
    rate = run.params.sync.rate_hz
    fig, ax = _figure(12, 4.2)
    ax.plot(frames, ptime_s, ".", ms=2.5, color="#1f4fd6", label="pTime (process time)")
    if t_time_s > 0:
        ax.axhline(t_time_s, color="#e02020", lw=1.5, label=f"T_time = {t_time_s:.2f} s")
    if rate > 0:
        ax.axhline(1.0 / rate, color="k", ls="--", lw=1.2, label=f"R = 1 / detection rate = {1.0 / rate:.2f} s")
    above = int(np.sum(ptime_s > t_time_s)) if t_time_s > 0 else 0
    ax.set_title(f"Process time per frame: max {ptime_s.max(initial=0):.2f} s, median "
                 f"{np.median(ptime_s) if len(ptime_s) else 0:.2f} s, {above} of {len(ptime_s)} frames over T_time")
    ax.set_xlabel("frame (processed in order, all sessions)")
    ax.set_ylabel("pTime (s)")
    ax.set_ylim(0, max(ptime_s.max(initial=0), t_time_s, 1.0 / rate if rate > 0 else 0) * 1.1 or 1.0)
    ax.set_xlim(frames.min(initial=0), max(frames.max(initial=1), 1))
    _mark_sessions(ax, run)
    ax.grid(alpha=0.3)
    ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8)
    fig.savefig(path)


def plot_memory(run: _Run, path: Path) -> None:
    """WM size (with STM, local map) and vocabulary size per frame (2013 Fig. 11 bottom)."""
    frames = _column(run.stats, "frame_index")
    fig, (ax1, ax2) = _figure(10, 5.5, 2, 1, sharex=True)
    ax1.plot(frames, _column(run.stats, "wm_size"), color="#1f4fd6", label="WM size")
    ax1.plot(frames, _column(run.stats, "local_map_size"), color="#ff8c00", lw=1.0, label="local map size")
    ax1.plot(frames, _column(run.stats, "ltm_size"), color="0.4", lw=1.0, ls="--", label="LTM size")
    ax1.set_ylabel("nodes")
    ax1.set_title("Memory per frame: working memory (used for loop closure detection) and long-term memory")
    ax1.legend(loc="upper left", bbox_to_anchor=(0.0, 0.88), fontsize=8)
    ax2.plot(frames, _column(run.stats, "vocabulary_size") / 1000.0, color="#7b2cbf", label="vocabulary (WM words)")
    ax2.set_ylabel("words (thousands)")
    ax2.set_xlabel("frame (processed in order, all sessions)")
    ax2.set_title("Vocabulary size")
    ax2.legend(loc="upper left", bbox_to_anchor=(0.0, 0.88), fontsize=8)
    for ax in (ax1, ax2):
        _mark_sessions(ax, run)
        ax.grid(alpha=0.3)
        ax.set_ylim(bottom=0)
    fig.savefig(path)


def _draw_grid(ax, grid: OccupancyGrid) -> None:
    """The occupancy grid as a grey image in map coordinates (m)."""
    image = np.full(grid.data.shape, GRID_GREY["unknown"])
    image[grid.data == 0] = GRID_GREY["free"]
    image[grid.data > 0] = GRID_GREY["occupied"]
    x0, y0 = grid.origin_xy
    extent = (x0, x0 + grid.width * grid.resolution, y0, y0 + grid.height * grid.resolution)
    ax.imshow(image, cmap="gray", vmin=0.0, vmax=1.0, origin="lower", extent=extent, interpolation="nearest")


def _draw_graph(ax, poses: dict[int, np.ndarray], links: list[Link], lw: float = 0.8,
                labels: bool = True) -> dict[LinkType, int]:
    """Links coloured by type (loop closures over neighbours); returns the count drawn per type."""
    from matplotlib.collections import LineCollection

    counts = {}
    for kind in (LinkType.NEIGHBOR, LinkType.LOOP_INTRA, LinkType.LOOP_INTER):
        segs = [(poses[l.from_id][:2, 3], poses[l.to_id][:2, 3]) for l in links
                if l.type is kind and l.from_id in poses and l.to_id in poses]
        counts[kind] = len(segs)
        if not segs:
            continue
        loop = kind is not LinkType.NEIGHBOR
        color, zorder = LINK_COLORS[kind], (4 if loop else 3)
        ax.add_collection(LineCollection(segs, colors=color, linewidths=lw * (2.0 if loop else 1.0), zorder=zorder))
        marker = ""
        if loop:
            # Optimised loop closures join nearby poses: their ends are marked so they stay visible.
            marker = "o"
            ends = np.array(segs).reshape(-1, 2)
            ax.plot(ends[:, 0], ends[:, 1], marker, ms=2.5, color=color, zorder=zorder)
        if labels:
            ax.plot([], [], "-" + marker, color=color, lw=lw * 2, ms=3, label=f"{LINK_LABELS[kind]} ({len(segs)})")
    return counts


def _xy(poses: dict[int, np.ndarray]) -> np.ndarray:
    """(N,2) positions (m) of 4x4 poses."""
    return np.array([p[:2, 3] for p in poses.values()]).reshape(-1, 2)


def _bounds(poses: dict[int, np.ndarray], grid: Optional[OccupancyGrid] = None,
            margin_m: float = MAP_MARGIN_M) -> tuple[float, float, float, float]:
    """(xmin, xmax, ymin, ymax) (m): the poses with a margin, within the grid when there is one.

    Laser rays through doors make grids much larger than the mapped area: the view follows the
    robot's path instead.
    """
    xy = _xy(poses)
    if not len(xy):
        xy = np.zeros((1, 2))
    lo, hi = xy.min(axis=0) - margin_m, xy.max(axis=0) + margin_m
    if grid is not None:
        g_lo = np.array(grid.origin_xy)
        g_hi = g_lo + np.array([grid.width, grid.height]) * grid.resolution
        lo, hi = np.maximum(lo, g_lo), np.minimum(hi, g_hi)
    return float(lo[0]), float(hi[0]), float(lo[1]), float(hi[1])


def _fig_size_for(bounds: tuple[float, float, float, float], width_in: float = 11.0) -> tuple[float, float]:
    """Figure size following the aspect ratio of the drawn area, within sane bounds."""
    xmin, xmax, ymin, ymax = bounds
    ratio = float(np.clip((ymax - ymin) / max(xmax - xmin, 1e-6), 0.45, 1.3))
    return width_in, width_in * ratio + 0.8


def _map_axes(ax, bounds: tuple[float, float, float, float]) -> None:
    ax.set_xlim(bounds[0], bounds[1])
    ax.set_ylim(bounds[2], bounds[3])
    ax.set_aspect("equal")
    ax.set_facecolor(str(GRID_GREY["unknown"]))
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")


def plot_global_map(run: _Run, path: Path) -> None:
    """Occupancy grid with the optimised graph (2014 Fig. 7, 9, 11)."""
    gmap = run.gmap
    main = gmap.components[0]
    poses = {n: gmap.poses[n] for n in main}
    bounds = _bounds(poses, run.grid)
    fig, ax = _figure(*_fig_size_for(bounds))
    if run.grid is not None:
        _draw_grid(ax, run.grid)
    _draw_graph(ax, poses, gmap.links)
    others = len(gmap.components) - 1
    sessions = sorted({gmap.map_ids[n] for n in main})
    ax.set_title(f"Global map optimised offline: {len(main)} nodes, {len(sessions)} session(s)"
                 + (f" ({others} other component(s) not shown: never connected)" if others else ", one component"))
    _map_axes(ax, bounds)
    ax.legend(loc="upper left", fontsize=8, framealpha=0.9)
    fig.savefig(path)


def _session_color(session: int) -> str:
    return SESSION_COLORS[(session - 1) % len(SESSION_COLORS)]


def plot_sessions_y(run: _Run, path: Path) -> None:
    """y of the odometry poses over time by session, with the loop closures (2014 Fig. 8)."""
    from matplotlib.collections import LineCollection

    gmap = run.gmap
    order = sorted(gmap.odom_poses, key=lambda n: (gmap.stamps_ns[n], n))
    index = {n: k for k, n in enumerate(order)}
    y = {n: gmap.odom_poses[n][1, 3] for n in order}
    fig, ax = _figure(11, 4.8)
    for map_id in sorted({gmap.map_ids[n] for n in order}):
        ids = [n for n in order if gmap.map_ids[n] == map_id]
        session = run.session_of_map.get(map_id, map_id)
        ax.plot([index[n] for n in ids], [y[n] for n in ids], "-", lw=1.6, color=_session_color(session),
                label=f"session {session} ({len(ids)} nodes)", zorder=3)
    for kind in (LinkType.LOOP_INTRA, LinkType.LOOP_INTER):
        segs = [((index[l.from_id], y[l.from_id]), (index[l.to_id], y[l.to_id])) for l in gmap.links
                if l.type is kind and l.from_id in index and l.to_id in index]
        if segs:
            # Hundreds of links stay readable when they are faint.
            alpha = float(np.clip(SESSION_LINKS_ALPHA_SCALE / len(segs), 0.25, 0.8))
            ax.add_collection(LineCollection(segs, colors=LINK_COLORS[kind], linewidths=0.6, alpha=alpha,
                                             label=f"{LINK_LABELS[kind]} ({len(segs)})", zorder=2))
    ax.set_title("y of the odometry poses (not optimised; each session starts at its own origin) "
                 "and the loop closures joining them")
    ax.set_xlabel("node (in order of acquisition, all sessions)")
    ax.set_ylabel("y in the session's odometry frame (m)")
    ax.grid(alpha=0.3)
    ax.legend(loc="center left", bbox_to_anchor=(1.01, 0.5), fontsize=8)
    fig.savefig(path)


def plot_local_vs_global(run: _Run, path: Path) -> None:
    """The last local map (online, WM only) next to the global map (offline, WM + LTM) (2014 Fig. 10)."""
    gmap = run.gmap
    main = {n: gmap.poses[n] for n in gmap.components[0]}
    bounds = _bounds(main, run.grid)
    width, height = _fig_size_for(bounds, 7.0)
    fig, (ax1, ax2) = _figure(2 * width, height, 1, 2)
    if run.local_grid is not None:
        _draw_grid(ax1, run.local_grid)
    _draw_graph(ax1, run.local_poses, run.local_links)
    ax1.set_title(f"a) last local map: {len(run.local_poses)} WM nodes linked to the newest node,\n"
                  "optimised as online (2014 §II-C)")
    if run.grid is not None:
        _draw_grid(ax2, run.grid)
    _draw_graph(ax2, main, gmap.links, lw=0.6)
    # Nodes in WM marked (the paper's light grey areas), the others are in LTM.
    wm_xy = np.array([main[n][:2, 3] for n in main if gmap.in_wm.get(n)]).reshape(-1, 2)
    ltm_xy = np.array([main[n][:2, 3] for n in main if not gmap.in_wm.get(n)]).reshape(-1, 2)
    ax2.plot(wm_xy[:, 0], wm_xy[:, 1], "o", ms=3, mfc="#ffa500", mec="none", zorder=5, label=f"nodes in WM ({len(wm_xy)})")
    ax2.plot(ltm_xy[:, 0], ltm_xy[:, 1], "o", ms=2, mfc="0.2", mec="none", zorder=5, label=f"nodes in LTM ({len(ltm_xy)})")
    ax2.set_title(f"b) global map: all {len(main)} nodes (WM + LTM), optimised offline")
    for ax in (ax1, ax2):
        _map_axes(ax, bounds)
        ax.legend(loc="upper left", fontsize=7, framealpha=0.9)
    fig.savefig(path)


def _estimate_trajectory(gmap: GlobalMap):
    """Optimised poses of the largest component as a Trajectory (stamp order)."""
    from rtabmap_ros2.io.trajectory import Trajectory

    ids = sorted(gmap.components[0], key=lambda n: (gmap.stamps_ns[n], n))
    return ids, Trajectory(np.array([gmap.stamps_ns[n] for n in ids], dtype=np.int64),
                           np.stack([gmap.poses[n] for n in ids]))


def plot_trajectories(run: _Run, ground_truth, result, ids: list[int], estimate, path: Path) -> None:
    """Estimated trajectory (one rigid alignment) over the true one, coloured by session."""
    T = result.T_gt_est
    est = estimate.positions @ T[:3, :3].T + T[:3, 3]
    gt_xy = ground_truth.positions[result.index_gt]
    est_xy = est[result.index_est]
    bounds = (*(gt_xy[:, 0].min() - 1.0, gt_xy[:, 0].max() + 1.0), *(gt_xy[:, 1].min() - 1.0, gt_xy[:, 1].max() + 1.0))
    fig, ax = _figure(*_fig_size_for(bounds))
    gt = ground_truth.positions
    # One line per session: a stamp gap longer than a few frames starts a new one.
    breaks = np.flatnonzero(np.diff(ground_truth.stamps_ns) > TRAJECTORY_GAP_S * NS_PER_S) + 1
    for k, part in enumerate(np.split(np.arange(len(gt)), breaks)):
        ax.plot(gt[part, 0], gt[part, 1], "-", color="0.6", lw=2.5, label=None if k else "ground truth", zorder=1)
    map_ids = np.array([run.gmap.map_ids[ids[i]] for i in result.index_est])
    for map_id in sorted(set(map_ids.tolist())):
        sel = map_ids == map_id
        session = run.session_of_map.get(map_id, map_id)
        ax.plot(est_xy[sel, 0], est_xy[sel, 1], ".", ms=3, color=_session_color(session),
                label=f"estimate, session {session}", zorder=2)
    ax.set_aspect("equal")
    ax.set_xlabel("x, ground-truth frame (m)")
    ax.set_ylabel("y, ground-truth frame (m)")
    ax.set_title(f"Optimised global map vs ground truth after one rigid alignment: ATE RMSE "
                 f"{result.rmse_m:.2f} m (median {result.median_m:.2f} m, max {result.max_m:.2f} m, "
                 f"{result.matched} nodes)")
    ax.grid(alpha=0.3)
    ax.legend(loc="upper left", fontsize=8, framealpha=0.9)
    fig.savefig(path)


def read_loops(path: str | os.PathLike) -> list[tuple[int, int]]:
    """``loops.csv`` -> (stamp_ns, revisited stamp_ns) per frame with a revisit (simulator format).

    Raises:
        DatasetError: missing file or columns.
    """
    import csv

    from rtabmap_ros2.errors import DatasetError

    try:
        with open(path, newline="") as f:
            rows = list(csv.DictReader(f))
    except OSError as exc:
        raise DatasetError(f"cannot read loops file {path}: {exc.strerror}") from exc
    try:
        return [(round(float(r["stamp"]) * NS_PER_S), round(float(r["revisits_stamp"]) * NS_PER_S)) for r in rows]
    except (KeyError, ValueError) as exc:
        raise DatasetError(f"{path}: expected the simulator's loops.csv columns 'stamp' and 'revisits_stamp' "
                           f"(seconds): {exc}") from exc


def loop_ground_truth(stats: list[dict], truth, loops: list[tuple[int, int]]
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Loop closure ground truth of a mapping run in :func:`evaluation.pr_curve`'s form.

    Frame i (statistics row order) is a positive when ``loops`` lists its stamp. Its detection of
    location L is correct when the true poses of the frame and of the frame that created L are
    within :data:`CORRECT_MAX_DISTANCE_M` and :data:`CORRECT_MAX_ANGLE_DEG`; a frame with a
    correct detection that ``loops`` does not list (a revisit just outside its tolerances) is
    then a positive too.

    Args:
        stats: the run's statistics rows (``stamp_ns``, ``location_id``, ``highest_hypothesis_*``).
        truth: ground-truth :class:`~rtabmap_ros2.io.trajectory.Trajectory` (stamps of the frames).
        loops: (stamp_ns, revisited stamp_ns) pairs, :func:`read_loops`.

    Returns:
        ``(gt (N, L) bool with gt[i, l-1] for location l, hypothesis_ids (N,), values (N,))``.
    """
    from rtabmap_ros2.core import transforms
    from rtabmap_ros2.io.trajectory import associate

    stamps = np.array([int(r["stamp_ns"]) for r in stats], dtype=np.int64)
    locations = np.array([int(r["location_id"]) for r in stats], dtype=np.int64)
    hyp_ids = np.array([int(r["highest_hypothesis_id"]) for r in stats], dtype=np.int64)
    values = np.array([float(r["highest_hypothesis_value"]) for r in stats])
    gt = np.zeros((len(stats), max(int(locations.max(initial=0)), int(hyp_ids.max(initial=0)), 1)), dtype=bool)
    i_frame, i_truth = associate(stamps, truth.stamps_ns)
    true_pose = {int(i): truth.poses[j] for i, j in zip(i_frame, i_truth)}
    row_of_location = {int(l): k for k, l in enumerate(locations) if l > 0}
    loop_stamps = np.array([a for a, _ in loops], dtype=np.int64)
    listed, i_loop = associate(stamps, loop_stamps)
    revisited = np.array([b for _, b in loops], dtype=np.int64)[i_loop]
    rev_rows, rev_k = associate(revisited, stamps)
    revisited_row = dict(zip(rev_rows.tolist(), rev_k.tolist()))
    max_angle = np.deg2rad(CORRECT_MAX_ANGLE_DEG)
    for k, i in enumerate(listed.tolist()):
        # The revisited frame's location makes the row a positive even when the detection is wrong.
        j = revisited_row.get(k)
        if j is not None and locations[j] > 0:
            gt[i, locations[j] - 1] = True
    for i in range(len(stats)):
        h = int(hyp_ids[i])
        row = row_of_location.get(h)
        if h <= 0 or row is None or i not in true_pose or row not in true_pose:
            continue
        delta = transforms.relative(true_pose[row], true_pose[i])
        gt[i, h - 1] |= bool(np.linalg.norm(delta[:3, 3]) <= CORRECT_MAX_DISTANCE_M
                             and transforms.rotation_angle(delta) <= max_angle)
    return gt, hyp_ids, values


def plot_precision_recall(run: _Run, curve, recall: float, threshold: Optional[float], positives: int,
                          path: Path) -> None:
    """Precision-recall over T_loop thresholds on the highest hypothesis (2013 Fig. 4)."""
    t_loop = run.params.bayes.loop_threshold
    fig, ax = _figure(7.5, 6)
    rec = np.array([p.recall for p in curve]) * 100
    prec = np.array([p.precision for p in curve]) * 100
    thr = np.array([p.threshold for p in curve])
    ax.plot(rec, prec, "-", color="#1f4fd6", lw=1.8, label="precision-recall over T_loop")
    if threshold is not None:
        ax.plot([recall * 100], [100], "o", ms=8, color="#e02020",
                label=f"recall at 100 % precision: {recall * 100:.1f} % (T_loop >= {threshold:.3f})")
    if len(thr):
        k = int(np.argmin(np.abs(thr - t_loop)))
        ax.plot([rec[k]], [prec[k]], "s", ms=8, mfc="none", mec="k", mew=1.5,
                label=f"T_loop of the run = {t_loop:.2f}: precision {prec[k]:.1f} %, recall {rec[k]:.1f} %")
    ax.set_xlim(0, 100)
    ax.set_ylim(max(0.0, prec.min(initial=100) - 5), 101)
    ax.set_xlabel("recall (%)")
    ax.set_ylabel("precision (%)")
    ax.set_title(f"Loop closure detection, highest hypothesis per frame\n({positives} frames with a true loop closure, "
                 f"correct = within {CORRECT_MAX_DISTANCE_M:g} m / {CORRECT_MAX_ANGLE_DEG:g} deg)")
    ax.grid(alpha=0.3)
    ax.legend(loc="lower left", fontsize=8)
    fig.savefig(path)


# -- page --------------------------------------------------------------------------------------
CAPTIONS = {
    "process_time.png": "Process time (pTime, feature extraction excluded) of every frame with the time limit "
                        "T_time and the acquisition period R; once pTime reaches T_time, nodes are transferred "
                        "to LTM (cf. 2013 Fig. 7, 2014 Fig. 6 and 12).",
    "memory.png": "Working memory size (nodes used for loop closure detection), local map size, LTM size and "
                  "vocabulary size per frame (cf. 2013 Fig. 11).",
    "global_map.png": "Occupancy grid of the global map optimised offline with all links in LTM: neighbour "
                      "links blue, intra-session loop closures red, inter-session green (cf. 2014 Fig. 7, 9, 11).",
    "sessions_y.png": "y of the odometry poses over time: every session starts at its own origin; only the "
                      "inter-session loop closures (green) join the sessions (cf. 2014 Fig. 8).",
    "local_vs_global.png": "a) the last local map, built online from the WM nodes linked to the newest node; "
                           "b) the global map built offline, WM nodes marked (cf. 2014 Fig. 10).",
    "trajectories.png": "Estimated trajectory (nodes of the optimised global map) after one rigid alignment to "
                        "the ground truth.",
    "precision_recall.png": "Precision-recall of the highest loop closure hypothesis over T_loop thresholds "
                            "(cf. 2013 Fig. 4).",
}


def _flat_params(params: Params) -> list[tuple[str, object, str, str]]:
    return list(params.public_items())


def write_index(report: Report, params: Params, inputs: ReportInputs) -> None:
    """``index.html``: summary, figures with captions, skipped figures, parameters."""
    s = report.summary
    esc = html.escape
    rows = "".join(f"<tr><th>{esc(k)}</th><td>{esc(str(v))}</td></tr>" for k, v in _summary_rows(s))
    figures = "".join(
        f'<figure><a href="{name}"><img src="{name}" alt="{esc(name)}"></a>'
        f"<figcaption><b>{esc(name)}</b>: {esc(CAPTIONS.get(name, ''))}</figcaption></figure>"
        for name in FIGURES if name in report.figures)
    skipped = "".join(f"<li><b>{esc(k)}</b>: {esc(v)}</li>" for k, v in report.skipped.items())
    param_rows = "".join(f"<tr><td><code>{esc(n)}</code></td><td>{esc(json.dumps(v))}</td><td>{esc(u)}</td>"
                         f"<td>{esc(d)}</td></tr>" for n, v, d, u in _flat_params(params))
    export = ""
    if inputs.export_dir is not None and (inputs.export_dir / "map.png").is_file():
        rel = os.path.relpath(inputs.export_dir / "map.png", report.out_dir)
        export = f'<p>Exported map picture: <a href="{esc(rel)}">{esc(rel)}</a> (folder {esc(str(inputs.export_dir))}).</p>'
    page = f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><title>rtabmap_ros2 report: {esc(inputs.database.name)}</title>
<style>
body {{ font-family: sans-serif; margin: 2em auto; max-width: 1200px; color: #222; }}
table {{ border-collapse: collapse; margin-bottom: 1.5em; }}
th, td {{ border: 1px solid #ccc; padding: 3px 8px; text-align: left; font-size: 0.9em; vertical-align: top; }}
th {{ background: #f2f2f2; }}
figure {{ margin: 1.5em 0; }} figure img {{ max-width: 100%; border: 1px solid #ddd; }}
figcaption {{ font-size: 0.9em; color: #444; }}
details {{ margin: 1em 0; }}
</style></head><body>
<h1>rtabmap_ros2 run report</h1>
<p>Database <code>{esc(str(inputs.database))}</code>; ground truth:
<code>{esc(str(inputs.ground_truth) if inputs.ground_truth else "none")}</code>; loops:
<code>{esc(str(inputs.loops) if inputs.loops else "none")}</code>.</p>
{export}
<h2>Summary</h2><table>{rows}</table>
<h2>Figures</h2>{figures}
{"<h2>Not drawn</h2><ul>" + skipped + "</ul>" if skipped else ""}
<h2>Parameters used</h2>
<details open><summary>{len(_flat_params(params))} parameters (from the database)</summary>
<table><tr><th>name</th><th>value</th><th>unit</th><th>description</th></tr>{param_rows}</table></details>
</body></html>
"""
    report.index_html.write_text(page)


def _summary_rows(s: dict) -> list[tuple[str, object]]:
    rows = [
        ("frames processed", s["frames"]), ("sessions", s["sessions"]), ("nodes (global map)", s["nodes"]),
        ("nodes in WM at the end", s["wm_size"]), ("nodes in the last local map", s["local_map_nodes"]),
        ("loop closures detected (intra / inter-session)", f"{s['loop_closures_intra']} / {s['loop_closures_inter']}"),
        ("loop closure links kept by the global optimisation (intra / inter)",
         f"{s['links_intra']} / {s['links_inter']}"),
        ("connected components", s["components"]),
        ("pTime max / median (ms)", f"{s['max_process_time_ms']:.0f} / {s['median_process_time_ms']:.0f}"),
        ("frames over T_time", f"{s['frames_over_time_threshold']} (T_time = {s['time_threshold_ms']:.0f} ms)"),
        ("vocabulary size at the end (words)", s["vocabulary_size"]),
    ]
    if s.get("ate") is not None:
        rows.append(("ATE after one rigid alignment (RMSE / median / max, m)",
                     f"{s['ate']['rmse_m']:.3f} / {s['ate']['median_m']:.3f} / {s['ate']['max_m']:.3f} "
                     f"({s['ate']['matched']} nodes)"))
    if s.get("recall_at_100_precision") is not None:
        rows.append(("recall at 100 % precision", f"{100 * s['recall_at_100_precision']:.1f} %"))
    return rows


def _summary(run: _Run) -> dict:
    stats, gmap = run.stats, run.gmap
    ptime = _column(stats, "process_time_ms")
    loops = _loop_counts(stats)
    threshold = run.params.memory.time_threshold_ms
    last = stats[-1] if stats else {}
    return {
        "frames": len(stats),
        "sessions": len({gmap.map_ids[n] for n in gmap.map_ids}),
        "nodes": len(gmap.poses),
        "wm_size": int(last.get("wm_size", sum(gmap.in_wm.values()))),
        "local_map_nodes": len(run.local_poses),
        "loop_closures_intra": loops["intra"],
        "loop_closures_inter": loops["inter"],
        "links_intra": gmap.links_by_type.get(LinkType.LOOP_INTRA.value, 0),
        "links_inter": gmap.links_by_type.get(LinkType.LOOP_INTER.value, 0),
        "components": len(gmap.components),
        "max_process_time_ms": float(ptime.max(initial=0.0)),
        "median_process_time_ms": float(np.median(ptime)) if len(ptime) else 0.0,
        "frames_over_time_threshold": int(np.sum(ptime > threshold)) if threshold > 0 else 0,
        "time_threshold_ms": threshold,
        "vocabulary_size": int(last.get("vocabulary_size", 0)),
        "ate": None,
        "recall_at_100_precision": None,
    }


def write_report(inputs: ReportInputs, out_dir: str | os.PathLike, params: Optional[Params] = None) -> Report:
    """Draw the figures and write ``index.html`` and ``summary.json`` in ``out_dir``.

    Args:
        inputs: database and optional ground truth / loops / export folder (:func:`find_inputs`).
        out_dir: report folder (created; files in it are overwritten).
        params: parameters for the offline optimisation and the drawn thresholds; default: the
            ones stored in the database (those the run used).

    Raises:
        DatabaseError: missing or invalid database, or one without any node.
    """
    out = Path(out_dir).expanduser()
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise DatabaseError(f"cannot create report folder {out}: {exc.strerror}") from exc
    run = _load_run(inputs.database, params)
    if not run.gmap.poses:
        raise DatabaseError(f"{inputs.database} has no node with a pose: nothing to report")
    report = Report(out_dir=out, index_html=out / "index.html", summary=_summary(run))

    def draw(name: str, plot, *args) -> None:
        plot(run, *args, out / name) if args else plot(run, out / name)
        report.figures[name] = out / name

    draw("process_time.png", plot_process_time)
    draw("memory.png", plot_memory)
    if run.grid is None:
        report.skipped["global_map.png"] = "no laser scans in the database: the graph is drawn without a grid"
    draw("global_map.png", plot_global_map)
    draw("sessions_y.png", plot_sessions_y)
    draw("local_vs_global.png", plot_local_vs_global)
    _ground_truth_figures(run, inputs, report, draw)
    report.summary["figures"] = sorted(report.figures)
    report.summary["skipped"] = dict(report.skipped)
    (out / "summary.json").write_text(json.dumps(report.summary, indent=2) + "\n")
    write_index(report, run.params, inputs)
    return report


def _ground_truth_figures(run: _Run, inputs: ReportInputs, report: Report, draw) -> None:
    """trajectories.png and precision_recall.png, when the ground truth allows them."""
    from rtabmap_ros2.io.trajectory import ate, read_tum

    if inputs.ground_truth is None:
        reason = "no ground truth (give --ground-truth FILE, TUM format)"
        report.skipped["trajectories.png"] = reason
        report.skipped["precision_recall.png"] = reason
        return
    truth = read_tum(inputs.ground_truth)
    ids, estimate = _estimate_trajectory(run.gmap)
    try:
        result = ate(estimate, truth)
    except RtabmapError as exc:
        report.skipped["trajectories.png"] = f"ground truth does not match the run: {exc}"
    else:
        report.summary["ate"] = result.to_dict()
        draw("trajectories.png", plot_trajectories, truth, result, ids, estimate)
    if inputs.loops is None:
        report.skipped["precision_recall.png"] = "no loops.csv (give --loops FILE)"
        return
    gt, ids_hyp, values = loop_ground_truth(run.stats, truth, read_loops(inputs.loops))
    from rtabmap_ros2.io.evaluation import pr_curve, recall_at_full_precision

    curve = pr_curve(gt, ids_hyp, values)
    positives = int(gt.any(axis=1).sum())
    if not positives:
        report.skipped["precision_recall.png"] = f"{inputs.loops} lists no frame of this run: no loop closure to find"
        return
    recall, threshold = recall_at_full_precision(curve)
    report.summary["recall_at_100_precision"] = recall
    report.summary["threshold_at_100_precision"] = threshold
    report.summary["loop_positives"] = positives
    draw("precision_recall.png", plot_precision_recall, curve, recall, threshold, positives)


__all__ = ["FIGURES", "Report", "ReportInputs", "find_inputs", "write_report"]
