"""``rtabmap-ros2 carmen2bag LOG --out BAGDIR``: a CARMEN laser log as a ROS 2 bag with drifting odometry."""

from __future__ import annotations

import argparse


def add_parser(subparsers) -> None:
    """Add the ``carmen2bag`` sub-parser."""
    from rtabmap_ros2.io.carmen import DEFAULT_NOISE_ROT_DEG_PER_M, DEFAULT_NOISE_TRANS
    p = subparsers.add_parser(
        "carmen2bag", help="convert a CARMEN log (FLASER) to a ROS 2 bag with /scan and drifting /odom",
        description="Write /scan (LaserScan) and /odom (Odometry: the log's corrected poses with seeded noise "
                    "added to each relative motion) to a new ROS 2 bag folder, and the corrected poses to "
                    "BAGDIR/ground_truth.txt (TUM format).",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("log", metavar="LOG", help="CARMEN log (.log or .log.gz)")
    p.add_argument("--out", metavar="BAGDIR", required=True, help="bag folder to create (must not exist)")
    p.add_argument("--seed", type=int, default=0, help="seed of the odometry noise")
    p.add_argument("--noise-trans", type=float, default=DEFAULT_NOISE_TRANS,
                   help="translation noise std-dev, fraction of the distance travelled")
    p.add_argument("--noise-rot", type=float, default=DEFAULT_NOISE_ROT_DEG_PER_M,
                   help="heading noise std-dev, degrees per metre travelled")
    p.add_argument("--storage", choices=("sqlite3", "mcap"), default="sqlite3", help="ROS 2 bag storage")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Convert; print what was written."""
    from rtabmap_ros2.io.carmen import carmen_to_bag
    result = carmen_to_bag(args.log, args.out, seed=args.seed, noise_trans=args.noise_trans,
                           noise_rot_deg_per_m=args.noise_rot, storage=args.storage)
    print(f"{result.scans} scans -> {result.bag_path} (final odometry drift {result.odometry_final_error_m:.2f} m)")
    print(f"reference poses -> {result.ground_truth_path}")
    return 0
