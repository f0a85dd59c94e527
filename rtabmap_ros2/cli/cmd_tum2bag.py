"""``rtabmap-ros2 tum2bag FOLDER --out BAGDIR``: a TUM RGB-D folder as a ROS 2 bag with odometry."""

from __future__ import annotations

import argparse


def add_parser(subparsers) -> None:
    """Add the ``tum2bag`` sub-parser."""
    p = subparsers.add_parser(
        "tum2bag", help="convert a TUM RGB-D folder to a ROS 2 bag (/rgb/image, /depth/image, camera_info, /odom)",
        description="Write /rgb/image (rgb8), /depth/image, /rgb/camera_info (the Kinect's calibration, distortion in "
                    "D: the images are as recorded unless --rectify), /odom (the ground truth, optionally with a "
                    "drift) and /tf_static (base_link -> camera_optical) to a new ROS 2 bag folder, and the ground "
                    "truth to BAGDIR/ground_truth.txt (TUM format, base_link = the camera body). Frames: colour "
                    "images with a depth image within 20 ms and ground truth at their stamp. Then: rtabmap-ros2 map "
                    "BAGDIR --db map.db --set Reg/Force3DoF=false (a hand-held camera moves in 6 DoF).",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("folder", metavar="FOLDER",
                   help="TUM RGB-D folder (rgb.txt, depth.txt, groundtruth.txt, rgb/, depth/)")
    p.add_argument("--out", metavar="BAGDIR", required=True, help="bag folder to create (must not exist)")
    p.add_argument("--camera", metavar="NAME|FX,FY,CX,CY[,K1,K2,P1,P2,K3]", default=None,
                   help="calibration: fr1, fr2, fr3 (the benchmark's Kinects), ros (525, 525, 319.5, 239.5), or "
                        "numbers; default: the folder name's freiburg1/2/3")
    p.add_argument("--depth-encoding", choices=("16UC1", "32FC1"), default="16UC1",
                   help="/depth/image as millimetres (16UC1) or metres (32FC1); TUM's 5000 per metre converted")
    p.add_argument("--rectify", action="store_true",
                   help="undistort the images with the calibration (colour bilinear, depth nearest) and write D = 0")
    p.add_argument("--drift-yaw-deg-s", type=float, default=0.0, metavar="DEG_S",
                   help="odometry heading drift about the vertical, degrees per second (0.5: a poor visual odometry)")
    p.add_argument("--drift-m-s", type=float, default=0.0, metavar="M_S",
                   help="odometry position drift along a horizontal direction, metres per second")
    p.add_argument("--seed", type=int, default=0, help="seed of the drift's sign and direction")
    p.add_argument("--storage", choices=("sqlite3", "mcap"), default="sqlite3", help="ROS 2 bag storage")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Convert; print what was written and the next command."""
    from rtabmap_ros2.io.tum import camera_for_folder, camera_from_text, tum_to_bag

    if args.camera is None:
        name, camera = camera_for_folder(args.folder)
        origin = f"{name}, from the folder name"
    else:
        camera, origin = camera_from_text(args.camera), f"--camera {args.camera}"
    result = tum_to_bag(args.folder, args.out, camera=camera, depth_encoding=args.depth_encoding,
                        drift_yaw_deg_s=args.drift_yaw_deg_s, drift_m_s=args.drift_m_s, seed=args.seed,
                        rectify=args.rectify, storage=args.storage)
    left_out = "".join(f", {n} left out ({why})" for why, n in result.left_out.items())
    print(f"{result.frames} frames{left_out} -> {result.bag_path}")
    print(f"camera ({origin}): {camera.describe()}" + (", images rectified (D = 0 written)" if args.rectify else
                                                      ", images as recorded (D written in camera_info)"))
    drift = (f"ground truth + drift {args.drift_yaw_deg_s:g} deg/s yaw, {args.drift_m_s:g} m/s (seed {args.seed}): "
             f"final error {result.odometry_final_error_m:.3f} m" if args.drift_yaw_deg_s or args.drift_m_s
             else "the ground truth (no drift)")
    print(f"/odom: {drift}; /depth/image {args.depth_encoding}")
    print(f"reference poses -> {result.ground_truth_path}")
    print(f"next: rtabmap-ros2 map {result.bag_path} --db map.db --set Reg/Force3DoF=false")
    return 0
