"""``rtabmap-ros2 play BAG``: publish a ROS 2 bag's messages on their topics with the recorded timing.

The ``ros2 bag play`` equivalent that needs no ROS install (rclpy from PyPI): see
:mod:`rtabmap_ros2.ros.play`. Ctrl-C stops the playback.
"""

from __future__ import annotations

import argparse


def add_parser(subparsers) -> None:
    parser = subparsers.add_parser(
        "play", help="publish a bag's messages with their recorded timing (ros2 bag play without ROS)",
        description=__doc__.splitlines()[0])
    parser.add_argument("bag", help="ROS 2 bag folder (sqlite3 or mcap)")
    parser.add_argument("--rate", type=float, default=1.0, help="speed factor (default 1: real time)")
    parser.add_argument("--loop", action="store_true", help="play again from the start until Ctrl-C")
    parser.add_argument("--topics", nargs="+", metavar="TOPIC", default=None,
                        help="only these topics (default: all whose message type is importable)")
    parser.add_argument("--clock", action="store_true",
                        help="publish the bag time on /clock (for nodes with use_sim_time:=true)")
    parser.add_argument("--start-offset", type=float, default=0.0, metavar="S",
                        help="skip the bag's first S seconds")
    parser.add_argument("--delay", type=float, default=0.5, metavar="S",
                        help="wait S seconds after creating the publishers so subscribers discover them "
                             "(default 0.5)")
    parser.add_argument("--ack-timeout", type=float, default=None, metavar="S",
                        help="after the last message, wait up to S seconds until reliable subscribers have "
                             "acknowledged every message (default 10; 0: exit at once)")
    parser.add_argument("--ros-args", nargs=argparse.REMAINDER, default=[], dest="ros_args",
                        help="ROS arguments for the player node (remapping, namespace...)")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import logging
    import os
    import signal
    import threading

    import rclpy
    from rclpy.node import Node
    from rclpy.signals import SignalHandlerOptions

    from rtabmap_ros2.ros.play import ACK_TIMEOUT_S, WRITER_HEARTBEAT_S, play_bag, use_writer_heartbeat_profile

    log = logging.getLogger("rtabmap_ros2.play")
    stop = threading.Event()
    profile = use_writer_heartbeat_profile()
    if profile is not None:
        log.info("Fast DDS writers resend lost samples every %g s (profile %s; set FASTRTPS_DEFAULT_PROFILES_FILE "
                 "to use your own)", WRITER_HEARTBEAT_S, profile)
    rclpy.init(args=["play", "--ros-args", *args.ros_args] if args.ros_args else None,
               signal_handler_options=SignalHandlerOptions.NO)
    previous = {sig: signal.signal(sig, lambda *_: stop.set()) for sig in (signal.SIGINT, signal.SIGTERM)}
    node = Node("rtabmap_play")
    try:
        stats = _in_worker_thread(lambda: play_bag(
            args.bag, node, rate=args.rate, loop=args.loop, topics=args.topics, clock=args.clock,
            start_offset_s=args.start_offset, delay_s=args.delay, stop=stop,
            ack_timeout_s=ACK_TIMEOUT_S if args.ack_timeout is None else args.ack_timeout))
        for topic, count in sorted(stats.published.items()):
            log.info("%s: %d messages", topic, count)
        if args.clock:
            log.info("/clock: %d messages", stats.clock_messages)
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        if profile is not None:
            os.unlink(profile)
    return 0


def _in_worker_thread(play):
    """``play()`` run on another thread while this (main) thread only waits for it; its result or exception.

    The Ctrl-C handler sets the playback's ``threading.Event``, and Python runs signal handlers on
    the main thread between two bytecodes. Had the main thread been the one playing, a signal
    arriving while it was inside ``Event.wait`` (which holds the Event's non-reentrant lock around
    the wait) would run ``Event.set`` there and block for ever on that same lock: the CLI hung
    after Ctrl-C once in CI. Waiting in ``Thread.join`` holds no lock the handler needs.
    """
    import threading

    outcome = {}

    def target():
        try:
            outcome["result"] = play()
        except BaseException as exc:  # noqa: BLE001 - re-raised on the main thread below
            outcome["error"] = exc

    worker = threading.Thread(target=target, name="rtabmap_play", daemon=True)
    worker.start()
    while worker.is_alive():
        worker.join(0.1)
    if "error" in outcome:
        raise outcome["error"]
    return outcome["result"]
