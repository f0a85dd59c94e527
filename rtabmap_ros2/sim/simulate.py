"""Multi-session recordings of the simulated building, as in Labbé & Michaud 2014 §III.

Five sessions (about 770 m, 1,800 frames at 1 Hz) start at different places with odometry reset
to identity; each revisits parts of earlier sessions. Outputs of :func:`simulate` in ``out_dir``:

* ``session_1`` ... ``session_K``: one ROS 2 bag per session (:func:`rtabmap_ros2.io.bag.write_bag`,
  default :class:`~rtabmap_ros2.io.bag.TopicNames`; JPEG colour + PNG depth unless ``raw_images``);
* ``ground_truth.txt``: TUM ``stamp_s x y z qx qy qz qw`` of ``T_world_base``, one world frame for
  all sessions, stamps equal to the bag stamps; session k starts :data:`SESSION_GAP_S` after
  session k-1 started (no overlap), or ``session_gap_s`` (0: robots mapping at the same time, whose
  stamps coincide);
* ``ground_truth_1.txt`` ... ``ground_truth_K.txt``: the same, one file per session (unambiguous
  when sessions overlap in time);
* ``loops.csv``: for each frame, the nearest earlier frame (earlier session, or >= 20 s earlier
  in the same one) within 1 m and 30 deg: where a correct loop closure can be found;
* ``world.png`` (floor plan, walls by texture kind, ground-truth paths) and ``world.json``.

In-memory use (tests of other modules), no bag needed::

    from rtabmap_ros2.sim import build_world, make_sessions, session_frames
    world = build_world(seed=0)
    sessions = make_sessions(world, small=True)          # 2 short sessions (~50 frames each)
    for frame in session_frames(world, sessions[0]):     # SensorFrame: odom, scan, rgb, depth
        ...
    sessions[0].T_world_base                              # (N,4,4) ground truth of those frames
    revisits = find_revisits(sessions)                    # the loops.csv rows as dicts

Every frame's sensor noise is drawn from ``(world.seed, session, frame index)``, so iterating a
session twice (or in another process) gives identical frames.
"""

from __future__ import annotations

import csv
import json
import logging
import os
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Iterator, Optional

import numpy as np

from rtabmap_ros2.core import transforms
from rtabmap_ros2.core.sensor import SensorFrame
from rtabmap_ros2.errors import RtabmapError
from rtabmap_ros2.sim.render import SensorRig, render_rgbd, render_scan, sensor_rig
from rtabmap_ros2.sim.robot import (
    FRAME_PERIOD_S, SESSION_PLANS, SMALL_SESSION_PLANS, Trajectory, plan_trajectory, step_covariance, wheel_odometry,
)
from rtabmap_ros2.sim.world import KIND_NAMES, World, build_world

logger = logging.getLogger(__name__)

START_STAMP_S = 1_700_000_000      # wall time of session 1's first frame (2023-11-14)
SESSION_GAP_S = 3600               # session k starts one hour after session k-1 started
REVISIT_MAX_DISTANCE_M = 1.0
REVISIT_MAX_HEADING_RAD = np.deg2rad(30.0)
REVISIT_MIN_AGE_S = 20.0           # same-session revisits must be at least this much older
NS_PER_S = 1_000_000_000


@dataclass(frozen=True)
class SessionTruth:
    """One session's frames: stamps, ground truth and wheel odometry.

    Attributes:
        index: session number, 1-based.
        plan: the waypoint goals driven through.
        stamps_ns: (N,) int64 frame stamps (ns since the epoch).
        T_world_base: (N,4,4) ground-truth poses in the world frame shared by all sessions.
        T_odom_base: (N,4,4) wheel odometry, identity at the first frame.
        odom_covariance: (6,6) fixed per-step covariance written with every odometry.
        trajectory: the 1 Hz drive (route, speed).
    """

    index: int
    plan: tuple[str, ...]
    stamps_ns: np.ndarray
    T_world_base: np.ndarray
    T_odom_base: np.ndarray
    odom_covariance: np.ndarray
    trajectory: Trajectory

    def __len__(self) -> int:
        return len(self.stamps_ns)

    @property
    def length_m(self) -> float:
        return self.trajectory.length_m


@dataclass
class SimulationSummary:
    """What :func:`simulate` wrote."""

    out_dir: Path
    seed: int
    small: bool
    sessions: list[dict] = field(default_factory=list)
    total_frames: int = 0
    total_length_m: float = 0.0
    revisits: int = 0
    elapsed_s: float = 0.0

    def to_dict(self) -> dict:
        d = asdict(self)
        d["out_dir"] = str(self.out_dir)
        return d


def make_sessions(world: World, sessions: Optional[int] = None, small: bool = False,
                  session_gap_s: float = SESSION_GAP_S,
                  plans: Optional[tuple[tuple[str, ...], ...]] = None,
                  frame_rate_hz: float = 1.0 / FRAME_PERIOD_S) -> list[SessionTruth]:
    """Ground truth and odometry of the sessions (all 5 by default, the 2 short ones with ``small``).

    Session k starts ``session_gap_s`` after session k-1 started (0: all at once, as a fleet).
    ``plans`` replaces the sessions' routes (waypoint names of :mod:`rtabmap_ros2.sim.world`),
    e.g. a robot kept to a part of the building the others never see.

    More sessions than plans (long runs: ``--sessions 30`` is about 10,000 frames) drive the plans
    again in turn, each time with its own speeds, stops and odometry noise (session k's random
    draws), in the same building: session 6 revisits session 1's route.

    ``frame_rate_hz`` (1 by default) samples the same drives faster: at 2 Hz twice the frames, as a
    driver publishing faster than the detection rate (the odometry covariance stays that of a 1 s
    increment, the neighbour link between nodes one detection period apart).
    """
    if not frame_rate_hz > 0:
        raise RtabmapError(f"frame rate {frame_rate_hz} Hz is out of range: > 0")
    plans = plans or (SMALL_SESSION_PLANS if small else SESSION_PLANS)
    sessions = len(plans) if sessions is None else sessions
    if sessions < 1:
        raise RtabmapError(f"sessions={sessions} is out of range: at least 1 session")
    out = []
    for k in range(1, sessions + 1):
        rng = np.random.default_rng([world.seed, k, int(small)])
        plan = plans[(k - 1) % len(plans)]
        traj = plan_trajectory(world, plan, rng, frame_period_s=1.0 / frame_rate_hz)
        start_ns = START_STAMP_S * NS_PER_S + int(round((k - 1) * session_gap_s * NS_PER_S))
        stamps = start_ns + np.round(traj.times_s * NS_PER_S).astype(np.int64)
        out.append(SessionTruth(index=k, plan=plan, stamps_ns=stamps, T_world_base=traj.poses,
                                T_odom_base=wheel_odometry(traj.xy_yaw, rng),
                                odom_covariance=step_covariance(traj.speed_mps), trajectory=traj))
    return out


def render_frame(world: World, session: SessionTruth, i: int, rig: SensorRig = SensorRig()) -> SensorFrame:
    """Frame ``i`` of ``session``: odometry, laser scan, RGB-D image (deterministic)."""
    rng = np.random.default_rng([world.seed, session.index, i, 1])
    T = session.T_world_base[i]
    rgb, depth = render_rgbd(world, T, rng, rig)
    return SensorFrame(stamp_ns=int(session.stamps_ns[i]), T_odom_base=session.T_odom_base[i].copy(),
                       odom_covariance=session.odom_covariance.copy(), rgb=rgb, depth_m=depth,
                       camera=rig.camera, scan=render_scan(world, T, rng, rig))


def session_frames(world: World, session: SessionTruth, rig: SensorRig = SensorRig()) -> Iterator[SensorFrame]:
    """The session's frames in time order (rendered lazily, ~40 ms each)."""
    for i in range(len(session)):
        yield render_frame(world, session, i, rig)


class SessionDataset:
    """A simulated session as a :class:`~rtabmap_ros2.core.sensor.Dataset` (iterate, ``len``)."""

    def __init__(self, world: World, session: SessionTruth, rig: SensorRig = SensorRig()) -> None:
        self.world, self.session, self.rig = world, session, rig

    def __iter__(self) -> Iterator[SensorFrame]:
        return session_frames(self.world, self.session, self.rig)

    def __len__(self) -> int:
        return len(self.session)


def find_revisits(sessions: list[SessionTruth], max_distance_m: float = REVISIT_MAX_DISTANCE_M,
                  max_heading_rad: float = REVISIT_MAX_HEADING_RAD,
                  min_age_s: float = REVISIT_MIN_AGE_S) -> list[dict]:
    """For each frame, the nearest earlier frame seen from about the same pose (loops.csv rows).

    Earlier = any frame of an earlier session, or of the same session at least ``min_age_s``
    older; "same pose" = within ``max_distance_m`` and ``max_heading_rad`` of heading.
    """
    sid = np.concatenate([np.full(len(s), s.index) for s in sessions])
    fidx = np.concatenate([np.arange(len(s)) for s in sessions])
    stamps = np.concatenate([s.stamps_ns for s in sessions])
    T = np.concatenate([s.T_world_base for s in sessions])
    xy = T[:, :2, 3]
    yaw = np.arctan2(T[:, 1, 0], T[:, 0, 0])
    rows = []
    min_age_ns = int(min_age_s * NS_PER_S)
    for k in range(len(stamps)):
        d = np.hypot(xy[:, 0] - xy[k, 0], xy[:, 1] - xy[k, 1])
        dyaw = np.abs((yaw - yaw[k] + np.pi) % (2 * np.pi) - np.pi)
        earlier = (sid < sid[k]) | ((sid == sid[k]) & (stamps <= stamps[k] - min_age_ns))
        ok = earlier & (d <= max_distance_m) & (dyaw <= max_heading_rad)
        if not ok.any():
            continue
        j = int(np.flatnonzero(ok)[np.argmin(d[ok])])
        rows.append({"session": int(sid[k]), "frame_index": int(fidx[k]), "stamp": stamps[k] / NS_PER_S,
                     "revisits_session": int(sid[j]), "revisits_frame_index": int(fidx[j]),
                     "revisits_stamp": stamps[j] / NS_PER_S, "distance_m": float(d[j])})
    return rows


def write_ground_truth(path: Path, sessions: list[SessionTruth]) -> None:
    """TUM file ``stamp_s x y z qx qy qz qw`` of ``T_world_base`` for all sessions."""
    with open(path, "w") as f:
        f.write("# timestamp tx ty tz qx qy qz qw (T_world_base, one world frame for all sessions)\n")
        for s in sessions:
            for stamp, T in zip(s.stamps_ns, s.T_world_base):
                q = transforms.quat_xyzw(T)
                f.write(f"{stamp / NS_PER_S:.9f} {T[0, 3]:.6f} {T[1, 3]:.6f} {T[2, 3]:.6f} "
                        f"{q[0]:.9f} {q[1]:.9f} {q[2]:.9f} {q[3]:.9f}\n")


def write_revisits(path: Path, rows: list[dict]) -> None:
    """``loops.csv``: one row per frame with a revisited earlier frame (stamps in s)."""
    columns = ["session", "frame_index", "stamp", "revisits_session", "revisits_frame_index",
               "revisits_stamp", "distance_m"]
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(columns)
        for r in rows:
            w.writerow([r["session"], r["frame_index"], f"{r['stamp']:.9f}", r["revisits_session"],
                        r["revisits_frame_index"], f"{r['revisits_stamp']:.9f}", f"{r['distance_m']:.3f}"])


def plot_world(path: Path, world: World, sessions: list[SessionTruth]) -> None:
    """Floor plan (walls coloured by texture kind) with the ground-truth paths and start markers."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.collections import LineCollection
    from matplotlib.lines import Line2D

    kind_colors = {0: "#1f3b73", 1: "#d62728", 2: "#a0a0a0"}
    fig, ax = plt.subplots(figsize=(14, 10.5), dpi=100)
    segs = np.stack([world.p0, world.p1], axis=1)
    ax.add_collection(LineCollection(segs, colors=[kind_colors[int(k)] for k in world.kind], linewidths=2.0))
    path_colors = plt.get_cmap("tab10")
    handles = [Line2D([], [], color=c, lw=2, label=f"{KIND_NAMES[k]} wall") for k, c in kind_colors.items()]
    for s in sessions:
        xy = s.T_world_base[:, :2, 3]
        color = path_colors((s.index + 1) % 10)
        offset = 0.12 * (s.index - (len(sessions) + 1) / 2)  # separate overlapping paths a little
        ax.plot(xy[:, 0] + offset, xy[:, 1] + offset, "-", color=color, lw=1.3, alpha=0.9)
        ax.plot(xy[0, 0], xy[0, 1], "o", color=color, ms=10, mec="k")
        ax.annotate(f"S{s.index}", xy[0], textcoords="offset points", xytext=(6, 6), fontsize=11,
                    fontweight="bold", color=color)
        handles.append(Line2D([], [], color=color, lw=2, marker="o",
                              label=f"session {s.index}: {len(s)} frames, {s.length_m:.0f} m"))
    ax.set_aspect("equal")
    ax.autoscale()
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title(f"Simulated building (seed {world.seed}): ground-truth paths, start = circle")
    ax.legend(handles=handles, loc="upper left", fontsize=8)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


_WORKER_WORLD: Optional[World] = None


def _init_worker(seed: int) -> None:
    global _WORKER_WORLD
    _WORKER_WORLD = build_world(seed)


def _write_session_bag(out_dir: Path, seed: int, session: SessionTruth, raw_images: bool,
                       rig: SensorRig = SensorRig(), tf_static: bool = True) -> str:
    from rtabmap_ros2.io.bag import TopicNames, write_bag

    world = _WORKER_WORLD if _WORKER_WORLD is not None and _WORKER_WORLD.seed == seed else build_world(seed)
    path = out_dir / f"session_{session.index}"
    write_bag(path, session_frames(world, session, rig), topics=TopicNames(),
              rgb_format="raw" if raw_images else "jpeg", depth_format="raw" if raw_images else "png",
              tf_static=tf_static)
    return str(path)


def simulate(out_dir, sessions: Optional[int] = None, seed: int = 0, small: bool = False, jobs: Optional[int] = None,
             raw_images: bool = False, laser_mount=None, camera_mount=None,
             tf_static: bool = True, session_gap_s: float = SESSION_GAP_S,
             frame_rate_hz: float = 1.0 / FRAME_PERIOD_S) -> SimulationSummary:
    """Write the bags, ground truth, revisits, plot and summary of a simulated multi-session run.

    Args:
        out_dir: output folder (created; existing ``session_*`` bags in it raise).
        sessions: number of sessions (default 5, or 2 with ``small``; more drive the plans again).
        seed: textures, speeds, stops, odometry and sensor noise.
        small: 2 short sessions (~50 frames each, the second revisits the first) for tests.
        jobs: worker processes rendering sessions in parallel (default: min(2, CPUs)).
        raw_images: write raw rgb8 / 16UC1 images instead of JPEG / PNG (about 1.5 MB per frame).
        laser_mount, camera_mount: ``[x, y, z, roll, pitch, yaw]`` of the laser / the camera's optical
            frame on the base (default: :mod:`rtabmap_ros2.sim.render`'s); the scans and images are in
            those frames, as real drivers publish them.
        tf_static: write the mounts on ``/tf_static`` (False: a bag without it, as recorded by a
            user who forgot it; the mounts must then be given to ``map`` / the node).
        session_gap_s: time between the starts of consecutive sessions (s, >= 0; 0: robots mapping
            at the same time, each in its own bag).
        frame_rate_hz: frames per second of every stream (1 by default; 2: twice the frames of the
            same drives, as a driver faster than the 1 Hz detection rate).
    """
    if not session_gap_s >= 0:
        raise RtabmapError(f"session gap {session_gap_s} s is out of range: >= 0")
    t0 = time.perf_counter()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    sessions = len(SMALL_SESSION_PLANS if small else SESSION_PLANS) if sessions is None else sessions
    for k in range(1, sessions + 1):
        if (out / f"session_{k}").exists():
            raise RtabmapError(f"{out / f'session_{k}'} already exists: remove it or choose another --out")
    rig = sensor_rig(laser_mount, camera_mount)
    world = build_world(seed)
    truths = make_sessions(world, sessions, small, session_gap_s, frame_rate_hz=frame_rate_hz)
    jobs = jobs or min(2, os.cpu_count() or 1)
    if jobs > 1 and sessions > 1:
        with ProcessPoolExecutor(max_workers=min(jobs, sessions), initializer=_init_worker, initargs=(seed,)) as pool:
            bags = list(pool.map(_write_session_bag, [out] * sessions, [seed] * sessions, truths,
                                 [raw_images] * sessions, [rig] * sessions, [tf_static] * sessions))
    else:
        global _WORKER_WORLD
        _WORKER_WORLD = world
        bags = [_write_session_bag(out, seed, s, raw_images, rig, tf_static) for s in truths]
    write_ground_truth(out / "ground_truth.txt", truths)
    for s in truths:
        write_ground_truth(out / f"ground_truth_{s.index}.txt", [s])
    revisits = find_revisits(truths)
    write_revisits(out / "loops.csv", revisits)
    plot_world(out / "world.png", world, truths)
    summary = SimulationSummary(out_dir=out, seed=seed, small=small)
    for s, bag in zip(truths, bags):
        n_rev = sum(1 for r in revisits if r["session"] == s.index)
        summary.sessions.append({
            "session": s.index, "bag": Path(bag).name, "frames": len(s), "length_m": round(s.length_m, 2),
            "duration_s": round((s.stamps_ns[-1] - s.stamps_ns[0]) / NS_PER_S, 3),
            "start_stamp": s.stamps_ns[0] / NS_PER_S, "speed_mps": round(s.trajectory.speed_mps, 3),
            "start_xy_yaw": [round(float(v), 4) for v in s.trajectory.xy_yaw[0]], "plan": list(s.plan),
            "revisit_frames": n_rev,
            "revisited_sessions": sorted({r["revisits_session"] for r in revisits if r["session"] == s.index}),
        })
    summary.total_frames = sum(len(s) for s in truths)
    summary.total_length_m = round(sum(s.length_m for s in truths), 2)
    summary.revisits = len(revisits)
    summary.elapsed_s = round(time.perf_counter() - t0, 2)
    info = summary.to_dict()
    info["world"] = {
        "walls": int(world.n_walls), "wall_length_m": round(float(world.lengths.sum()), 1),
        "walls_by_kind": {KIND_NAMES[k]: int((world.kind == k).sum()) for k in KIND_NAMES},
        "extent_m": [float(world.p0[:, 0].min()), float(world.p0[:, 1].min()),
                     float(world.p0[:, 0].max()), float(world.p0[:, 1].max())],
    }
    info["images"] = "raw" if raw_images else "jpeg+png"
    info["session_gap_s"] = session_gap_s
    info["frame_rate_hz"] = frame_rate_hz
    info["mounts"] = {"base_to_laser": [round(float(v), 6) for v in transforms.to_xyz_rpy(rig.T_base_laser)],
                      "base_to_camera": [round(float(v), 6) for v in transforms.to_xyz_rpy(rig.camera.T_base_camera)],
                      "tf_static": tf_static}
    with open(out / "world.json", "w") as f:
        json.dump(info, f, indent=2)
    logger.info("simulated %d sessions, %d frames, %.0f m in %.1f s -> %s", sessions, summary.total_frames,
                summary.total_length_m, summary.elapsed_s, out)
    return summary
