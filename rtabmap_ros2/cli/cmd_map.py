"""``rtabmap-ros2 map BAG [BAG ...] --db map.db``: multi-session graph SLAM on bags, offline.

The 2014 paper's second experiment: bags are processed one after the other, as in a real
multi-session trial, with one memory (one :class:`~rtabmap_ros2.core.rtabmap.Rtabmap`, one
database) kept between them. A new map (session) starts with every bag and whenever odometry
is reset inside a bag. Prints the mode (planar or 6 DoF, detection rate, grid sensor), per bag the
topics it reads, a progress bar, one line per session (nodes, WM size, intra / inter-session loop
closures, loop closures rejected while mapping, max pTime), per bag how many synchronised frames
the detection rate skipped and where the sensor mounts came from, and a final line; writes the
parameters used to ``params.yaml`` next to the database (they are stored in the database too,
where ``export`` reads them), and with ``--stats FILE.csv`` one row per frame
(:data:`STATS_COLUMNS`, as ``detect``'s ``detections.csv``; ``stamp`` in seconds, exact). Sensor
mounts come from each bag's ``/tf_static``; for a bag without it, ``--set
base_to_laser=[x,y,z,roll,pitch,yaw]`` and ``--set base_to_camera=[...]`` (the camera's optical
frame) give them. Frames with bad sensor data are skipped with a warning. Topics are the node's
(``/odom``, ``/scan``, ``/rgb/image``, ``/depth/image``, ``/rgb/camera_info``); ``--remap
NAME:=TOPIC`` reads a bag made with other names, and a missing stream is listed with the bag's
topics of its type (a bag without odometry is refused).

A hand-held camera or a robot moving in 3D: ``--set Reg/Force3DoF=false`` (6 DoF; the shipped
config is a wheeled robot's, planar); every frame rather than 1 Hz: ``--set Rtabmap/DetectionRate=0``.
"""

from __future__ import annotations

import argparse
import contextlib
import csv
import logging
import queue
import threading
import time
from dataclasses import dataclass, field
from typing import Callable, Iterable, Iterator, Optional

from rtabmap_ros2.cli.common_args import add_param_arguments

log = logging.getLogger(__name__)

# --stats FILE.csv columns (issue 14): one row per processed frame; stamp in seconds (exact, 9 decimals).
STATS_COLUMNS = ("frame", "stamp", "location_id", "map_id", "loop_closure_id", "loop_closure_type",
                 "process_time_ms", "time_optimization_ms", "wm_size", "local_map_size", "retrieved",
                 "transferred")


def stats_row(stats) -> dict:
    """The :data:`STATS_COLUMNS` of one frame's Statistics."""
    from rtabmap_ros2.io.trajectory import stamp_text

    return {"frame": stats.frame_index, "stamp": stamp_text(stats.stamp_ns), "location_id": stats.location_id,
            "map_id": stats.map_id, "loop_closure_id": stats.loop_closure_id,
            "loop_closure_type": stats.loop_closure_type, "process_time_ms": round(stats.process_time_ms, 3),
            "time_optimization_ms": round(float(stats.timings_ms.get("optimization", 0.0)), 3),
            "wm_size": stats.wm_size, "local_map_size": stats.local_map_size, "retrieved": stats.retrieved,
            "transferred": stats.transferred}


@contextlib.contextmanager
def statistics_csv(path) -> Iterator[Optional[Callable]]:
    """``--stats FILE.csv``: yields a function writing one :data:`STATS_COLUMNS` row per frame's
    Statistics into ``path`` (None when ``path`` is None)."""
    if path is None:
        yield None
        return
    with open(path, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=STATS_COLUMNS)
        writer.writeheader()
        yield lambda stats: writer.writerow(stats_row(stats))


@dataclass
class SessionSummary:
    """What one session (map) added, as printed per session.

    ``frames`` counts the frames processed (after the detection rate); ``rejected_online`` the loop
    closure hypotheses turned down while mapping (verification, the merge checks, RGBD/OptimizeMaxError),
    not the stored loop closures ``export``'s global optimisation drops
    (``loop_closures_rejected_by_global_optimization`` in its summary.json).
    """

    map_id: int
    source: str
    frames: int = 0
    nodes: int = 0
    skipped: int = 0
    not_moved: int = 0
    loop_intra: int = 0
    loop_inter: int = 0
    proximity: int = 0
    rejected_online: int = 0
    wm_size: int = 0
    local_map_size: int = 0
    max_process_time_ms: float = 0.0
    process_times_ms: list[float] = field(default_factory=list)

    def line(self) -> str:
        return (f"session {self.map_id} ({self.source}): {self.nodes} nodes from {self.frames} frames processed, "
                f"WM {self.wm_size}, local map {self.local_map_size}, loop closures intra {self.loop_intra} "
                f"/ inter {self.loop_inter} ({self.rejected_online} rejected while mapping)"
                + (f", {self.proximity} by proximity" if self.proximity else "") + ", "
                f"max pTime {self.max_process_time_ms:.0f} ms"
                + (f", {self.skipped} bad frames skipped" if self.skipped else "")
                + (f", {self.not_moved} frames not added: the robot moved less than graph.linear_update / "
                   "angular_update (RGBD/LinearUpdate, RGBD/AngularUpdate)" if self.not_moved else ""))


# What map --help says of the settings a camera-only or hand-held user needs (README "Hand-held
# RGB-D camera").
HELP_MODES = ("Planar or 6 DoF: registration.planar (Reg/Force3DoF) keeps x, y and yaw only; the shipped "
              "config sets it for a wheeled robot with a laser: a hand-held camera or a robot moving in 3D needs "
              "--set Reg/Force3DoF=false (a warning says so when the odometry leaves the plane). The detection "
              "rate (Rtabmap/DetectionRate, 1 Hz) keeps one frame per second; 0 keeps every frame. The occupancy "
              "grid comes from each node's laser scan, else its depth image (Grid/Sensor: 0 laser, 1 depth, 2 "
              "both). Sensor mounts come from /tf_static, else --set base_to_camera=[x,y,z,roll,pitch,yaw] / "
              "base_to_laser=[...]. The parameters are stored in the database: export reuses them.")


def add_parser(subparsers) -> None:
    parser = subparsers.add_parser(
        "map", help="multi-session graph SLAM on ROS 2 bags (one session per bag), offline",
        description=__doc__.splitlines()[0] + " " + HELP_MODES)
    parser.add_argument("bags", nargs="+", metavar="BAG", help="ROS 2 bags (folders), processed in this order")
    parser.add_argument("--db", required=True, metavar="FILE",
                        help="map database; an existing one is continued in a new session")
    parser.add_argument("--overwrite", action="store_true", help="delete an existing database first")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    parser.add_argument("--stats", metavar="FILE.csv", default=None,
                        help="write one row per frame: " + ", ".join(STATS_COLUMNS))
    parser.add_argument("--remap", metavar="NAME:=TOPIC", action="append", default=[],
                        help="read a stream from another topic, named as the node's topics are remapped: "
                             + ", ".join(f"{name}:=TOPIC" for name in REMAP_NAMES)
                             + " (e.g. --remap rgb/image:=/camera/color/image_raw; repeatable)")
    add_param_arguments(parser, default_config="rtabmap.yaml")
    parser.set_defaults(func=run)


# --remap names: the node's topic names (what `ros2 run ... -r rgb/image:=...` remaps) -> bag stream.
REMAP_NAMES = {"odom": "odom", "scan": "scan", "rgb/image": "rgb", "depth/image": "depth",
               "rgb/camera_info": "camera_info"}


def topic_names(remaps: list[str]):
    """``--remap NAME:=TOPIC`` values -> the bag's TopicNames (the defaults for the others)."""
    from rtabmap_ros2.errors import BagError
    from rtabmap_ros2.io.bag import TopicNames

    chosen = {}
    for remap in remaps:
        name, sep, topic = remap.partition(":=")
        stream = REMAP_NAMES.get(name.strip().strip("/"))
        if not sep or stream is None or not topic.strip():
            raise BagError(f"--remap {remap!r}: expected NAME:=TOPIC with NAME one of {', '.join(REMAP_NAMES)}, "
                           "e.g. --remap odom:=/odometry/filtered")
        topic = topic.strip()
        chosen[stream] = topic if topic.startswith("/") else "/" + topic
    return TopicNames(**chosen)


# Frames decoded ahead by a reader thread while the current one is processed (JPEG / PNG decoding
# releases the GIL: on 2 cores it overlaps with the frame's processing).
PREFETCH_FRAMES = 2


def prefetched(frames: Iterable, depth: int = PREFETCH_FRAMES) -> Iterator:
    """Items of ``frames`` produced by a background thread, up to ``depth`` ahead; an exception
    raised while producing them is raised here, in order."""
    items: queue.Queue = queue.Queue(maxsize=depth)
    stop = threading.Event()
    end = object()

    def produce() -> None:
        try:
            for item in frames:
                while not stop.is_set():
                    try:
                        items.put((item, None), timeout=0.1)
                        break
                    except queue.Full:
                        continue
                if stop.is_set():
                    return
            items.put((end, None))
        except BaseException as exc:  # handed to the consumer
            items.put((end, exc))

    thread = threading.Thread(target=produce, name="rtabmap-frame-reader", daemon=True)
    thread.start()
    try:
        while True:
            item, exc = items.get()
            if exc is not None:
                raise exc
            if item is end:
                return
            yield item
    finally:
        stop.set()
        while thread.is_alive():
            try:
                items.get_nowait()
            except queue.Empty:
                thread.join(0.05)


def map_datasets(rtabmap, datasets: Iterable[tuple[str, object]], progress: bool = True,
                 on_statistics: Optional[Callable] = None,
                 print_line: Callable[[str], None] = print,
                 on_dataset_end: Optional[Callable[[str, object], None]] = None) -> list[SessionSummary]:
    """Process datasets one after the other with one memory, a new map per dataset.

    Args:
        rtabmap: the :class:`~rtabmap_ros2.core.rtabmap.Rtabmap` (kept between datasets).
        datasets: (name, dataset) pairs; a dataset iterates SensorFrames and has ``len``.
        progress: show a tqdm progress bar.
        on_statistics: called with every frame's Statistics.
        print_line: where the per-session lines go.
        on_dataset_end: called with (name, dataset) once a dataset is done, after its last
            session's line.

    Returns:
        One :class:`SessionSummary` per session, in order.
    """
    from tqdm import tqdm
    from tqdm.contrib.logging import logging_redirect_tqdm

    from rtabmap_ros2.errors import SensorDataError

    sessions: list[SessionSummary] = []
    current: Optional[SessionSummary] = None
    # Log lines (a merge, a skipped frame) go through the bar, each on a line of its own, as in
    # detect: written straight to the terminal they were glued to the bar's last redraw.
    with logging_redirect_tqdm() if progress else contextlib.nullcontext():
        for index, (name, dataset) in enumerate(datasets):
            if index:
                rtabmap.trigger_new_map()  # one session per bag
            bar = tqdm(total=len(dataset), desc=name, unit="frame", disable=not progress, leave=False)
            for frame in prefetched(dataset):
                bar.update(1)
                try:
                    stats = rtabmap.process(frame)
                except SensorDataError as exc:
                    log.warning("%s: frame at %.9f s skipped: %s", name, frame.stamp_ns / 1e9, exc)
                    if current is not None:
                        current.skipped += 1
                    continue
                if current is None or stats.map_id != current.map_id:
                    if current is not None:
                        bar.clear()
                        print_line(current.line())
                    current = SessionSummary(stats.map_id, name)
                    sessions.append(current)
                _count(current, stats)
                if on_statistics is not None:
                    on_statistics(stats)
            bar.close()
            if current is not None:   # each dataset is a session of its own (or several)
                print_line(current.line())
                current = None
            if on_dataset_end is not None:
                on_dataset_end(name, dataset)
    return sessions


def _count(session: SessionSummary, stats) -> None:
    session.frames += 1
    session.nodes += int(bool(stats.location_id) and not stats.merged_id)
    session.not_moved += int(stats.small_displacement)
    if stats.loop_closure_type == "loop_intra":
        session.loop_intra += 1
    elif stats.loop_closure_type == "loop_inter":
        session.loop_inter += 1
    session.rejected_online += int(bool(stats.rejected_loop_closure_id))
    session.proximity += stats.proximity_links
    session.wm_size = stats.wm_size
    session.local_map_size = stats.local_map_size
    session.process_times_ms.append(stats.process_time_ms)
    session.max_process_time_ms = max(session.max_process_time_ms, stats.process_time_ms)


def mode_line(params) -> str:
    """What the run does that a user must know before reading the rest: planar or 6 DoF, the
    detection rate, what the occupancy grid is made from; each with the setting that changes it."""
    if params.registration.planar:
        mode = ("planar, x / y / yaw only (registration.planar = Reg/Force3DoF true; a hand-held camera or a "
                "robot moving in 3D: --set Reg/Force3DoF=false)")
    else:
        mode = ("6 DoF (registration.planar = Reg/Force3DoF false; a wheeled robot on a floor: "
                "--set Reg/Force3DoF=true)")
    rate = params.sync.rate_hz
    rate_text = (f"{rate:g} Hz, one synchronised frame per period" if rate > 0 else "every frame")
    grid = {"auto": "each node's laser scan, else its depth image", "laser": "laser scans",
            "depth": "depth images", "both": "laser scans and depth images"}[params.grid.sensor]
    graph = params.graph
    thresholds = ((graph.linear_update, "m"), (graph.angular_update, "rad"))
    moved = " or ".join(f"{value:g} {unit}" for value, unit in thresholds if value > 0)
    nodes = (f"; a frame becomes a node once the robot moved {moved} since the last one (RGBD/LinearUpdate, "
             "RGBD/AngularUpdate)" if moved else "")
    return (f"mode: {mode}; detection rate: {rate_text} (Rtabmap/DetectionRate, 0 = every frame){nodes}; "
            f"occupancy grid: {grid} (grid.sensor = Grid/Sensor {params.grid.sensor})")


def topics_line(name: str, dataset) -> str:
    """The topics a bag is read from, and the streams it does not have with the bag's topics of
    their type (what to ``--remap``)."""
    from rtabmap_ros2.io.bag import STREAMS

    used = ", ".join(f"{dataset.stream_topics[s]} ({s})" for s in STREAMS if s in dataset.stream_topics)
    missing = [f"{dataset.topics.of(s)}{_remap_hint(s, dataset)}" for s in STREAMS if s not in dataset.stream_topics]
    return f"{name}: reading {used or 'nothing'}" + (f"; not in the bag: {', '.join(missing)}" if missing else "")


def _remap_hint(stream: str, dataset) -> str:
    """`` (the bag has TOPIC, ...: --remap NAME:=TOPIC)``: the bag's unread topics of the stream's type."""
    candidates = dataset.unread_topics_of(stream)
    name = next(n for n, s in REMAP_NAMES.items() if s == stream)
    return f" (the bag has {', '.join(candidates)}: --remap {name}:=TOPIC)" if candidates else ""


def bag_line(name: str, dataset, params) -> str:
    """After a bag: how many synchronised frames the detection rate skipped, and where the sensor
    mounts came from (/tf_static, the base_to_camera / base_to_laser parameters, or the default)."""
    read = dataset.last_read
    parts = []
    if read is not None:
        rate = params.sync.rate_hz
        parts.append(f"{read.synchronised} synchronised frames, {read.frames} processed"
                     + (f", {read.rate_limited} skipped by the detection rate ({rate:g} Hz: --set "
                        f"Rtabmap/DetectionRate=0 keeps every frame)" if read.rate_limited else "")
                     + (f", {read.bad} with a bad message skipped" if read.bad else ""))
    for sensor, mount in dataset.mounts.items():
        parts.append(f"{sensor} mount from {_mount_source(sensor, mount, params)}")
    return f"{name}: " + "; ".join(parts)


def _mount_source(sensor: str, mount, params) -> str:
    from rtabmap_ros2.core.params import NodeParams

    frames = f"{mount.base_frame} -> {mount.sensor_frame or '(no frame_id)'}"
    if mount.kind == "tf_static":
        return f"/tf_static ({frames})"
    if mount.kind == "same_frame":
        return f"the base itself ({mount.sensor_frame} is the odometry's child frame: identity)"
    if mount.kind == "argument":
        return "the caller"
    name = f"base_to_{sensor}"
    value = getattr(params.node, name)
    if value != getattr(NodeParams(), name):
        return f"the {name} parameter {list(value)} (no /tf_static {frames})"
    default = ("the optical frame at the base origin, looking along base x" if sensor == "camera"
               else "the laser at the base origin")
    return f"the default, {default} (no /tf_static {frames}, {name} not set)"


def run(args: argparse.Namespace) -> int:
    from pathlib import Path

    from rtabmap_ros2.core.rtabmap import Rtabmap
    from rtabmap_ros2.core.transforms import from_xyz_rpy
    from rtabmap_ros2.errors import BagError
    from rtabmap_ros2.io.bag import BagDataset
    from rtabmap_ros2.cli.common_args import params_from_args

    params = params_from_args(args)
    print(mode_line(params))
    db_path = Path(args.db).expanduser()
    if not db_path.parent.is_dir():
        raise BagError(f"--db {db_path}: folder {db_path.parent} does not exist")
    stats_path = Path(args.stats).expanduser() if args.stats else None
    if stats_path is not None and not stats_path.parent.is_dir():
        raise BagError(f"--stats {stats_path}: folder {stats_path.parent} does not exist")
    # Sensor mounts: the bag's /tf_static; where it has none, --set base_to_laser / base_to_camera.
    mounts = {"fallback_T_base_laser": from_xyz_rpy(params.node.base_to_laser),
              "fallback_T_base_camera": from_xyz_rpy(params.node.base_to_camera)}
    topics = topic_names(args.remap)
    datasets = [(Path(b).name, BagDataset(b, topics=topics, sync=params.sync, **mounts)) for b in args.bags]
    for name, dataset in datasets:
        print(topics_line(name, dataset))
        if "odom" not in dataset.stream_topics:
            raise BagError(f"bag {dataset.path} has no odometry on {topics.odom}: map needs the robot's odometry"
                           f"{_remap_hint('odom', dataset) or ' (nav_msgs/Odometry; --remap odom:=TOPIC)'}")
    t0 = time.perf_counter()
    with Rtabmap(params, db_path, delete_existing=args.overwrite) as rtabmap, \
            statistics_csv(stats_path) as on_statistics:
        sessions = map_datasets(rtabmap, datasets, progress=not args.no_progress, on_statistics=on_statistics,
                                on_dataset_end=lambda name, dataset: print(bag_line(name, dataset, params)))
        rtabmap.flush()
    elapsed = time.perf_counter() - t0
    params.to_yaml(db_path.parent / "params.yaml")
    frames = sum(s.frames for s in sessions)
    print(f"total: {len(sessions)} sessions, {frames} frames, {sum(s.nodes for s in sessions)} nodes, "
          f"loop closures intra {sum(s.loop_intra for s in sessions)} / inter {sum(s.loop_inter for s in sessions)}, "
          f"max pTime {max((s.max_process_time_ms for s in sessions), default=0.0):.0f} ms, "
          f"{elapsed:.1f} s ({frames / max(elapsed, 1e-9):.2f} frames/s) -> {db_path}"
          + (f", statistics -> {stats_path}" if stats_path else ""))
    return 0
