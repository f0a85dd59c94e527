"""Odometry reset detection on the simulated sessions' wheel odometry: resets seen, false ones.

Frames hold odometry only (each becomes a node without words), so a run is fast and the figures
are about :meth:`Sessions.reset_reason` (core/sessions.py) alone (default parameters):

* resets anywhere: in each of the 5 sessions, the odometry is restarted at identity every
  ``--every`` frames (one restart per run, ``sim.robot.reset_odometry``), the ``lost`` frames
  right after it are dropped (0, 1, 3, 8) and about half of all the others too (DDS, as the
  issue's 103 of 200). Seen = a new map exactly at the first frame received after the restart;
  missed restarts are listed with the previous pose's distance from its origin (a reset close to
  the origin, with frames lost, is ambiguous with driving on);
* false resets: every session with 0, 25, 50 % of its frames lost, at the simulated speed
  (0.45-0.55 m/s) and 4 times faster (odometry scaled): new maps inside a session.

Usage: ``python bench/bench_reset.py [--quick] [--every N]``. Writes ``bench/results/reset.json``.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import tempfile
import time
from pathlib import Path

import numpy as np

from rtabmap_ros2.core.params import Params
from rtabmap_ros2.core.rtabmap import Rtabmap
from rtabmap_ros2.core.sensor import SensorFrame
from rtabmap_ros2.sim import build_world, make_sessions
from rtabmap_ros2.sim.robot import reset_odometry

RESULTS = Path(__file__).resolve().parent / "results" / "reset.json"
LOST_AFTER_RESET = (0, 1, 3, 8)
LOSS_RATIOS = (0.0, 0.25, 0.5)
SPEED_SCALES = (1.0, 4.0)


def new_maps(db: Path, stamps_ns, poses, covariance) -> list[int]:
    with Rtabmap(Params(), db, delete_existing=True) as rtabmap:
        return [k for k, (t, T) in enumerate(zip(stamps_ns, poses))
                if rtabmap.process(SensorFrame(int(t), T, covariance)).new_map]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="2 sessions, a restart every 60 frames")
    parser.add_argument("--every", type=int, default=20, help="frames between restart positions")
    args = parser.parse_args()
    logging.disable(logging.WARNING)
    sessions = make_sessions(build_world(seed=0))[:2 if args.quick else None]
    every = 60 if args.quick else args.every
    t0 = time.perf_counter()
    seen = {k: [0, 0] for k in LOST_AFTER_RESET}
    missed = []
    with tempfile.TemporaryDirectory() as tmp:
        db = Path(tmp) / "reset.db"
        for s in sessions:
            rng = np.random.default_rng(s.index)
            for at in range(every, len(s) - 10, every):
                for lost in LOST_AFTER_RESET:
                    T = reset_odometry(s.T_odom_base, at)
                    arrived = [i for i in range(len(s)) if (i == at + lost or rng.random() < 0.5)
                               and not at <= i < at + lost]
                    first = next(k for k, i in enumerate(arrived) if i >= at)
                    got = new_maps(db, s.stamps_ns[arrived], T[arrived], s.odom_covariance)
                    seen[lost][1] += 1
                    if got == [first]:
                        seen[lost][0] += 1
                    else:
                        missed.append({"session": s.index, "at": at, "lost": lost, "new_maps_at_frames": [arrived[k] for k in got],
                                       "previous_from_origin_m": round(float(np.linalg.norm(T[arrived[first - 1]][:3, 3])), 1)})
        false = []
        for scale in SPEED_SCALES:
            for ratio in LOSS_RATIOS:
                count = 0
                for s in sessions:
                    keep = np.random.default_rng([s.index, int(100 * ratio)]).random(len(s)) >= ratio
                    keep[0] = True
                    T = s.T_odom_base[keep].copy()
                    T[:, :3, 3] *= scale
                    count += len(new_maps(db, s.stamps_ns[keep], T, s.odom_covariance))
                false.append({"speed_scale": scale, "lost_ratio": ratio, "false_new_maps": count})
    out = {
        "sessions": len(sessions), "restart_every_frames": every,
        "seen": [{"lost_after_reset": k, "seen": v[0], "restarts": v[1]} for k, v in seen.items()],
        "missed": missed, "false_resets": false, "elapsed_s": round(time.perf_counter() - t0, 1),
        "load_average": os.getloadavg()[0],
    }
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    RESULTS.write_text(json.dumps(out, indent=2) + "\n")
    for row in out["seen"]:
        print(f"restart, {row['lost_after_reset']} frames lost after it: seen {row['seen']} / {row['restarts']}")
    for row in missed:
        print(f"  missed: session {row['session']} frame {row['at']}, {row['lost']} lost, previous pose "
              f"{row['previous_from_origin_m']} m from its origin")
    for row in false:
        print(f"false new maps, speed x{row['speed_scale']:g}, {row['lost_ratio']:.0%} lost: {row['false_new_maps']}")
    print(f"{out['elapsed_s']} s, load {out['load_average']:.1f} -> {RESULTS}")


if __name__ == "__main__":
    main()
