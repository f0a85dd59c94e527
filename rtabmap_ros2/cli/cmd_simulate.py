"""``rtabmap-ros2 simulate --out DIR``: multi-session bags of a simulated lab building.

Imitates Labbé & Michaud 2014 §III: a robot with wheel odometry, a 2D laser and a Kinect maps a
building in 5 sessions (about 770 m), each starting elsewhere with odometry reset. Writes one
ROS 2 bag per session, ``ground_truth.txt`` (TUM), ``loops.csv``, ``world.png`` and ``world.json``
(see :mod:`rtabmap_ros2.sim.simulate`).
"""

from __future__ import annotations

import argparse


def add_parser(subparsers) -> None:
    parser = subparsers.add_parser(
        "simulate", help="write multi-session bags of a simulated building (laser, RGB-D, odometry)",
        description=__doc__.splitlines()[0])
    parser.add_argument("--out", required=True, help="output folder")
    parser.add_argument("--sessions", type=int, default=None,
                        help="number of sessions (default: 5, or 2 with --small); more drive the same routes "
                             "again with other speeds and noise (30: about 10,000 frames)")
    parser.add_argument("--seed", type=int, default=0, help="textures, speeds, odometry and sensor noise")
    parser.add_argument("--small", action="store_true",
                        help="2 short sessions (~50 frames each) for quick tests")
    parser.add_argument("--jobs", type=int, default=None, help="worker processes (default: min(2, CPUs))")
    parser.add_argument("--raw-images", action="store_true",
                        help="raw rgb8/16UC1 images instead of JPEG/PNG (about 1.5 MB per frame)")
    parser.add_argument("--laser-mount", type=_mount, default=None, metavar="X,Y,Z,ROLL,PITCH,YAW",
                        help="laser pose on the base (m, rad; level), e.g. 0.2,0,0.3,0,0,0 (default 0,0,0.3,0,0,0)")
    parser.add_argument("--camera-mount", type=_mount, default=None, metavar="X,Y,Z,ROLL,PITCH,YAW",
                        help="camera optical frame on the base (m, rad; level: roll -1.5708, pitch 0), "
                             "default 0.1,0,0.5,-1.5708,0,-1.5708")
    parser.add_argument("--session-gap", type=float, default=None, metavar="SECONDS",
                        help="time between session starts (default 3600; 0: all sessions at once, as robots "
                             "mapping at the same time, e.g. for merge)")
    parser.add_argument("--frame-rate", type=float, default=None, metavar="HZ",
                        help="frames per second of every stream (default 1; e.g. 2: twice the frames of the same "
                             "drives, as drivers publishing faster than the 1 Hz detection rate)")
    parser.add_argument("--no-tf-static", action="store_true",
                        help="do not write /tf_static (the mounts must then be given to map / the node)")
    parser.set_defaults(func=run)


def _mount(text: str) -> list[float]:
    try:
        values = [float(v) for v in text.replace(" ", "").split(",")]
    except ValueError:
        values = []
    if len(values) != 6:
        raise argparse.ArgumentTypeError(f"{text!r}: expected 6 comma-separated numbers x,y,z,roll,pitch,yaw")
    return values


def run(args: argparse.Namespace) -> int:
    from rtabmap_ros2.sim.simulate import simulate

    sessions = args.sessions if args.sessions is not None else (2 if args.small else 5)
    summary = simulate(args.out, sessions=sessions, seed=args.seed, small=args.small, jobs=args.jobs,
                       raw_images=args.raw_images, laser_mount=args.laser_mount, camera_mount=args.camera_mount,
                       tf_static=not args.no_tf_static,
                       **({} if args.session_gap is None else {"session_gap_s": args.session_gap}),
                       **({} if args.frame_rate is None else {"frame_rate_hz": args.frame_rate}))
    for s in summary.sessions:
        print(f"session {s['session']}: {s['frames']} frames, {s['length_m']:.1f} m, "
              f"{s['revisit_frames']} frames revisit sessions {s['revisited_sessions']}")
    print(f"total: {summary.total_frames} frames, {summary.total_length_m:.1f} m, "
          f"{summary.elapsed_s:.1f} s -> {summary.out_dir}")
    return 0
