"""``rtabmap-ros2 map BAG [BAG ...] --db map.db``: multi-session graph SLAM on bags, offline.

The 2014 paper's second experiment: bags are processed one after the other, as in a real
multi-session trial, with one memory (one :class:`~rtabmap_ros2.core.rtabmap.Rtabmap`, one
database) kept between them. A new map (session) starts with every bag and whenever odometry
is reset inside a bag. Prints a progress bar, one line per session (nodes, WM size, intra /
inter-session loop closures, max pTime) and a final line; writes the parameters used to
``params.yaml`` next to the database. Sensor mounts come from each bag's ``/tf_static``; for a bag
without it, ``--set base_to_laser=[x,y,z,roll,pitch,yaw]`` and ``--set base_to_camera=[...]`` (the
camera's optical frame) give them. Frames with bad sensor data are skipped with a warning.
"""

from __future__ import annotations

import argparse
import logging
import time
from dataclasses import dataclass, field
from typing import Callable, Iterable, Optional

from rtabmap_ros2.cli.common_args import add_param_arguments

log = logging.getLogger(__name__)


@dataclass
class SessionSummary:
    """What one session (map) added, as printed per session."""

    map_id: int
    source: str
    frames: int = 0
    nodes: int = 0
    skipped: int = 0
    loop_intra: int = 0
    loop_inter: int = 0
    rejected: int = 0
    wm_size: int = 0
    local_map_size: int = 0
    max_process_time_ms: float = 0.0
    process_times_ms: list[float] = field(default_factory=list)

    def line(self) -> str:
        return (f"session {self.map_id} ({self.source}): {self.nodes} nodes from {self.frames} frames, "
                f"WM {self.wm_size}, local map {self.local_map_size}, loop closures intra {self.loop_intra} "
                f"/ inter {self.loop_inter} (rejected {self.rejected}), max pTime {self.max_process_time_ms:.0f} ms"
                + (f", {self.skipped} bad frames skipped" if self.skipped else ""))


def add_parser(subparsers) -> None:
    parser = subparsers.add_parser(
        "map", help="multi-session graph SLAM on ROS 2 bags (one session per bag), offline",
        description=__doc__.splitlines()[0])
    parser.add_argument("bags", nargs="+", metavar="BAG", help="ROS 2 bags (folders), processed in this order")
    parser.add_argument("--db", required=True, metavar="FILE",
                        help="map database; an existing one is continued in a new session")
    parser.add_argument("--overwrite", action="store_true", help="delete an existing database first")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    add_param_arguments(parser, default_config="rtabmap.yaml")
    parser.set_defaults(func=run)


def map_datasets(rtabmap, datasets: Iterable[tuple[str, object]], progress: bool = True,
                 on_statistics: Optional[Callable] = None,
                 print_line: Callable[[str], None] = print) -> list[SessionSummary]:
    """Process datasets one after the other with one memory, a new map per dataset.

    Args:
        rtabmap: the :class:`~rtabmap_ros2.core.rtabmap.Rtabmap` (kept between datasets).
        datasets: (name, dataset) pairs; a dataset iterates SensorFrames and has ``len``.
        progress: show a tqdm progress bar.
        on_statistics: called with every frame's Statistics.
        print_line: where the per-session lines go.

    Returns:
        One :class:`SessionSummary` per session, in order.
    """
    from tqdm import tqdm

    from rtabmap_ros2.errors import SensorDataError

    sessions: list[SessionSummary] = []
    current: Optional[SessionSummary] = None
    for index, (name, dataset) in enumerate(datasets):
        if index:
            rtabmap.trigger_new_map()  # one session per bag
        bar = tqdm(total=len(dataset), desc=name, unit="frame", disable=not progress, leave=False)
        for frame in dataset:
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
    if current is not None:
        print_line(current.line())
    return sessions


def _count(session: SessionSummary, stats) -> None:
    session.frames += 1
    session.nodes += int(bool(stats.location_id) and not stats.merged_id)
    if stats.loop_closure_type == "loop_intra":
        session.loop_intra += 1
    elif stats.loop_closure_type == "loop_inter":
        session.loop_inter += 1
    session.rejected += int(bool(stats.rejected_loop_closure_id))
    session.wm_size = stats.wm_size
    session.local_map_size = stats.local_map_size
    session.process_times_ms.append(stats.process_time_ms)
    session.max_process_time_ms = max(session.max_process_time_ms, stats.process_time_ms)


def run(args: argparse.Namespace) -> int:
    from pathlib import Path

    from rtabmap_ros2.core.rtabmap import Rtabmap
    from rtabmap_ros2.core.transforms import from_xyz_rpy
    from rtabmap_ros2.errors import BagError
    from rtabmap_ros2.io.bag import BagDataset
    from rtabmap_ros2.cli.common_args import params_from_args

    params = params_from_args(args)
    db_path = Path(args.db).expanduser()
    if not db_path.parent.is_dir():
        raise BagError(f"--db {db_path}: folder {db_path.parent} does not exist")
    # Sensor mounts: the bag's /tf_static; where it has none, --set base_to_laser / base_to_camera.
    mounts = {"fallback_T_base_laser": from_xyz_rpy(params.node.base_to_laser),
              "fallback_T_base_camera": from_xyz_rpy(params.node.base_to_camera)}
    datasets = [(Path(b).name, BagDataset(b, sync=params.sync, **mounts)) for b in args.bags]
    t0 = time.perf_counter()
    with Rtabmap(params, db_path, delete_existing=args.overwrite) as rtabmap:
        sessions = map_datasets(rtabmap, datasets, progress=not args.no_progress)
        rtabmap.flush()
    elapsed = time.perf_counter() - t0
    params.to_yaml(db_path.parent / "params.yaml")
    frames = sum(s.frames for s in sessions)
    print(f"total: {len(sessions)} sessions, {frames} frames, {sum(s.nodes for s in sessions)} nodes, "
          f"loop closures intra {sum(s.loop_intra for s in sessions)} / inter {sum(s.loop_inter for s in sessions)}, "
          f"max pTime {max((s.max_process_time_ms for s in sessions), default=0.0):.0f} ms, "
          f"{elapsed:.1f} s ({frames / max(elapsed, 1e-9):.2f} frames/s) -> {db_path}")
    return 0
