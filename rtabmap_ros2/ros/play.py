"""Publish a ROS 2 bag's messages with their recorded timing: ``ros2 bag play`` without a ROS install.

The bag is read with rosbags' ``AnyReader`` as raw CDR and each message is published as those
exact bytes (rclpy's ``Publisher.publish`` accepts a serialized ``bytes`` message and calls
``publish_raw``): nothing is deserialised, so any message type whose rclpy class can be imported
is replayed bit for bit. Topics whose type has no Python package here (``tf2_msgs/msg/TFMessage``
without a ROS install) are skipped with one log line each.

Timing: message ``i`` recorded at ``t_i`` (the bag's record time) is published at wall time
``start + (t_i - t_first) / rate``. With ``clock=True`` the bag time is also published on
``/clock`` (``rosgraph_msgs/Clock``) before every message and at :data:`CLOCK_RATE_HZ` while
waiting, for nodes running with ``use_sim_time:=true``.

Delivery: the publishers are reliable. A Fast DDS writer resends a lost sample only at its next
heartbeat, every 3 s by default, and a reliable reader delivers nothing of that topic until the
gap is repaired. Raw RGB-D images crowd out the small messages published with them: played at 4x
(seed 7's two sessions, raw 640x480 images) into a bare subscriber, /scan and /rgb/camera_info
stalled 26-29 times for up to 3.0 s and lost 3-10 messages each, /odom 9-12 times, so a
synchroniser saw one stream seconds behind the others. :func:`use_writer_heartbeat_profile`
(called by ``rtabmap-ros2 play`` before ``rclpy.init``) gives this process's Fast DDS writers a
:data:`WRITER_HEARTBEAT_S` heartbeat instead, unless the user set a Fast DDS profile file: same
replay, no stall over 0.5 s, nothing lost. After the last message :func:`play_bag` waits (at most
``ack_timeout_s``) until every reliable subscriber has acknowledged every message, so a player
that exits right after publishing does not lose what was still being repaired (measured: the
last 2 of 15 RGB-D frames of a simulated session never reached a reliable subscriber in another
process). Best-effort subscribers do not acknowledge and are not waited for; what they lose is lost.

ROS 1 bags are refused (their messages would need converting, e.g. ``Header.seq``): convert them
with ``rosbags-convert`` first.
"""

from __future__ import annotations

import importlib
import logging
import os
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable

from rtabmap_ros2.errors import BagError

logger = logging.getLogger(__name__)

NS_PER_S = 1_000_000_000
CLOCK_RATE_HZ = 100.0
CLOCK_TOPIC = "/clock"
# Publishers keep this many messages for late (reliable) subscribers; matches ros2 bag play.
PUBLISHER_DEPTH = 10
# Longest wait for the reliable subscribers' acknowledgements after the last message (s): three
# of Fast DDS's default 3 s heartbeat periods, i.e. three chances to repair a lost sample.
ACK_TIMEOUT_S = 10.0
# Heartbeat period of the player's Fast DDS writers (s): a lost sample is resent within this.
WRITER_HEARTBEAT_S = 0.1
# Environment variables naming a Fast DDS XML profile file (2.x reads the first, 3.x the second).
FASTDDS_PROFILE_VARIABLES = ("FASTRTPS_DEFAULT_PROFILES_FILE", "FASTDDS_DEFAULT_PROFILES_FILE")
_WRITER_PROFILE_XML = """<?xml version="1.0" encoding="UTF-8" ?>
<profiles xmlns="http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles">
  <data_writer profile_name="rtabmap_ros2_play_writer" is_default_profile="true">
    <times><heartbeatPeriod><sec>0</sec><nanosec>{nanosec}</nanosec></heartbeatPeriod></times>
  </data_writer>
</profiles>
"""


@dataclass
class PlayStats:
    """What one :func:`play_bag` call published."""

    published: dict[str, int] = field(default_factory=dict)  # topic -> messages
    skipped_topics: dict[str, str] = field(default_factory=dict)  # topic -> reason
    loops: int = 0
    clock_messages: int = 0
    unacknowledged: list[str] = field(default_factory=list)  # topics not acknowledged within ack_timeout_s

    @property
    def total(self) -> int:
        return sum(self.published.values())


def use_writer_heartbeat_profile(environ=os.environ) -> str | None:
    """Make this process's Fast DDS writers send a heartbeat every :data:`WRITER_HEARTBEAT_S`
    (module doc, Delivery): writes a profile file and names it in ``environ``; must run before
    ``rclpy.init``. Does nothing when ``environ`` already names a Fast DDS profile file (the
    user's configuration wins) or selects another RMW than Fast DDS.

    Returns:
        The profile file written, or None when nothing was done.
    """
    if any(environ.get(name) for name in FASTDDS_PROFILE_VARIABLES):
        return None
    if environ.get("RMW_IMPLEMENTATION", "rmw_fastrtps_cpp") not in ("rmw_fastrtps_cpp", "rmw_fastrtps_dynamic_cpp"):
        return None
    fd, path = tempfile.mkstemp(prefix="rtabmap_ros2_play_", suffix=".xml")
    with os.fdopen(fd, "w") as f:
        f.write(_WRITER_PROFILE_XML.format(nanosec=int(round(WRITER_HEARTBEAT_S * NS_PER_S))))
    for name in FASTDDS_PROFILE_VARIABLES:
        environ[name] = path
    return path


def message_class(msgtype: str):
    """The rclpy message class of a ROS 2 type name such as ``sensor_msgs/msg/Image``.

    Raises:
        ImportError: the type's Python package is not installed.
    """
    package, kind, name = msgtype.split("/")
    return getattr(importlib.import_module(f"{package}.{kind}"), name)


def play_bag(path: str | Path, node, *, rate: float = 1.0, loop: bool = False,
             topics: Iterable[str] | None = None, clock: bool = False, start_offset_s: float = 0.0,
             delay_s: float = 0.0, stop: threading.Event | None = None,
             ack_timeout_s: float = ACK_TIMEOUT_S) -> PlayStats:
    """Publish the bag at ``path`` on ``node`` (an rclpy Node) in (scaled) real time.

    Args:
        path: ROS 2 bag folder (sqlite3 or mcap).
        node: publishers are created on it (one per topic, reliable, depth 10: compatible with
            both reliable and best-effort subscribers).
        rate: playback speed factor (2 = twice as fast); > 0.
        loop: start again from ``start_offset_s`` after the last message, until ``stop`` is set.
        topics: only these topics (all when None or empty).
        clock: also publish the bag time on ``/clock``.
        start_offset_s: skip the bag's first seconds.
        delay_s: wait this long after creating the publishers (discovery) before the first message.
        stop: set it to end the playback early (another thread, a signal handler).
        ack_timeout_s: after the last message, wait at most this long for the reliable subscribers
            to acknowledge everything (0, or ``stop`` set: do not wait); topics still unacknowledged
            are listed in ``PlayStats.unacknowledged``.

    Raises:
        BagError: missing or unreadable bag, ROS 1 bag, unknown topic requested, bad arguments.
    """
    from rosbags.highlevel import AnyReader

    if rate <= 0:
        raise BagError(f"--rate {rate} must be > 0")
    if start_offset_s < 0:
        raise BagError(f"--start-offset {start_offset_s} must be >= 0")
    if ack_timeout_s < 0:
        raise BagError(f"--ack-timeout {ack_timeout_s} must be >= 0")
    path = Path(path).expanduser()
    if not path.exists():
        raise BagError(f"bag {path} does not exist")
    stop = stop or threading.Event()
    stats = PlayStats()
    try:
        reader = AnyReader([path])
        reader.open()
    except Exception as exc:  # noqa: BLE001 - rosbags raises several unrelated types
        raise BagError(f"cannot open bag {path}: {exc}") from exc
    try:
        if not reader.is2:
            raise BagError(f"{path} is a ROS 1 bag: convert it with rosbags-convert, then play the ROS 2 bag")
        wanted = set(topics or ())
        unknown = wanted - set(reader.topics)
        if unknown:
            raise BagError(f"topics {sorted(unknown)} are not in {path}; it holds {sorted(reader.topics)}")
        connections, publishers = [], {}
        for conn in reader.connections:
            if wanted and conn.topic not in wanted:
                continue
            if conn.topic not in publishers:
                try:
                    cls = message_class(conn.msgtype)
                except (ImportError, AttributeError, ValueError):
                    stats.skipped_topics[conn.topic] = f"type {conn.msgtype} is not importable here"
                    logger.warning("not playing %s: message type %s has no Python package here",
                                   conn.topic, conn.msgtype)
                    continue
                publishers[conn.topic] = node.create_publisher(cls, conn.topic, PUBLISHER_DEPTH)
                stats.published[conn.topic] = 0
            connections.append(conn)
        if not connections:
            raise BagError(f"nothing to play in {path} (topics {sorted(reader.topics)})")
        clock_pub = _ClockPublisher(node) if clock else None
        if delay_s > 0:
            stop.wait(delay_s)
        start_ns = reader.start_time + int(start_offset_s * NS_PER_S)
        while not stop.is_set():
            _play_once(reader, connections, publishers, clock_pub, start_ns, rate, stop, stats)
            if not loop:
                break
            stats.loops += 1
        if clock_pub is not None:
            stats.clock_messages = clock_pub.count
        if not stop.is_set():   # stopped (Ctrl-C): exit at once
            stats.unacknowledged = _wait_for_acknowledgements(publishers, ack_timeout_s)
    finally:
        reader.close()
    return stats


def _wait_for_acknowledgements(publishers: dict, timeout_s: float) -> list[str]:
    """Wait until every reliable subscriber acknowledged every message; the topics that did not."""
    from rclpy.duration import Duration

    if timeout_s <= 0:
        return []
    deadline = time.monotonic() + timeout_s
    late = []
    for topic, publisher in publishers.items():
        remaining = max(0.0, deadline - time.monotonic())
        if not publisher.wait_for_all_acked(Duration(nanoseconds=int(remaining * NS_PER_S))):
            late.append(topic)
    if late:
        logger.warning("reliable subscribers did not acknowledge every message of %s within %g s",
                       ", ".join(sorted(late)), timeout_s)
    return late


def _play_once(reader, connections, publishers, clock_pub, start_ns: int, rate: float,
               stop: threading.Event, stats: PlayStats) -> None:
    """One pass over the bag from ``start_ns`` (bag time)."""
    wall_start = time.monotonic()
    first_ns = None
    for conn, stamp_ns, raw in reader.messages(connections=connections, start=start_ns):
        if first_ns is None:
            first_ns = stamp_ns
        due = wall_start + (stamp_ns - first_ns) / NS_PER_S / rate
        if not _wait_until(due, stop, clock_pub, first_ns, stamp_ns, wall_start, rate):
            return
        if clock_pub is not None:
            clock_pub.publish(stamp_ns)
        publishers[conn.topic].publish(bytes(raw))
        stats.published[conn.topic] += 1


def _wait_until(due: float, stop: threading.Event, clock_pub, first_ns: int, next_ns: int,
                wall_start: float, rate: float) -> bool:
    """Sleep until the monotonic time ``due``, publishing /clock meanwhile; False if stopped.

    The interpolated clock never passes ``next_ns``, the stamp of the message about to be published,
    so /clock does not go backwards when a wake-up is late.
    """
    clock_period = 1.0 / CLOCK_RATE_HZ
    while True:
        remaining = due - time.monotonic()
        if remaining <= 0:
            return not stop.is_set()
        if stop.wait(min(remaining, clock_period) if clock_pub is not None else remaining):
            return False
        if clock_pub is not None:
            elapsed_ns = int((time.monotonic() - wall_start) * rate * NS_PER_S)
            clock_pub.publish(min(first_ns + elapsed_ns, next_ns))


class _ClockPublisher:
    """Publisher of the bag time on ``/clock`` (``rosgraph_msgs/Clock``)."""

    def __init__(self, node) -> None:
        from rosgraph_msgs.msg import Clock

        self._clock_cls = Clock
        self._pub = node.create_publisher(Clock, CLOCK_TOPIC, PUBLISHER_DEPTH)
        self.count = 0

    def publish(self, stamp_ns: int) -> None:
        from builtin_interfaces.msg import Time

        msg = self._clock_cls(clock=Time(sec=stamp_ns // NS_PER_S, nanosec=stamp_ns % NS_PER_S))
        self._pub.publish(msg)
        self.count += 1
