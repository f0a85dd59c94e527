"""Which topic each input stream is read from, with which QoS: matched to the publishers.

Per stream the node has candidate topics, in order of preference: ``rgb/image`` (sensor_msgs/Image)
then ``rgb/image/compressed`` (sensor_msgs/CompressedImage), ``depth/image`` then
``depth/image/compressedDepth``; the compressed names follow image_transport: the *resolved* raw name
(after remapping) + ``/compressed`` or ``/compressedDepth``. ``image_transport`` ``raw`` or
``compressed`` keeps one candidate; ``auto`` keeps both and subscribes to the first one published.

QoS (``qos``): ``reliable`` and ``sensor_data`` (best effort) are fixed. ``auto`` decides per topic
from its publishers, as rosbag2's recorder does: reliable when every publisher is reliable (the
subscriber then gets every message, repaired if lost), best effort as soon as one is best effort (a
reliable subscriber would not match it). A best-effort subscriber matches every publisher but
receives what a reliable publisher sends only once: under CPU load large images are lost.

:meth:`StreamSubscriptions.refresh` runs at start and then from a timer (publishers appear and go
at any time); when a stream's answer (topic, reliability) changes, its subscription is recreated. A
stream that needs the graph (``auto`` in either setting) is subscribed once a publisher appears;
a fixed one at once.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Callable, Optional

from rclpy.qos import QoSProfile, ReliabilityPolicy, qos_profile_sensor_data

# Depth of the reliable subscriptions (and of best-effort ones chosen by qos auto).
QUEUE_DEPTH = 10
# How often the publishers of every candidate topic are re-read (s).
GRAPH_CHECK_PERIOD_S = 0.25


@dataclass(frozen=True)
class Candidate:
    """One topic a stream can be read from."""

    topic: str            # resolved name
    msg_type: type
    convert: Callable     # message -> value fed to the synchroniser (raises SensorDataError)
    transport: str = "raw"


def reliability_of(publishers) -> Optional[ReliabilityPolicy]:
    """RELIABLE when every publisher (``TopicEndpointInfo``) is reliable, BEST_EFFORT when one is not,
    None without publishers."""
    if not publishers:
        return None
    reliable = all(p.qos_profile.reliability == ReliabilityPolicy.RELIABLE for p in publishers)
    return ReliabilityPolicy.RELIABLE if reliable else ReliabilityPolicy.BEST_EFFORT


def qos_profile(reliability: ReliabilityPolicy) -> QoSProfile:
    """The subscription profile of a reliability: reliable depth 10, or ROS's sensor_data profile."""
    if reliability == ReliabilityPolicy.RELIABLE:
        return QoSProfile(depth=QUEUE_DEPTH, reliability=ReliabilityPolicy.RELIABLE)
    return qos_profile_sensor_data


class StreamSubscriptions:
    """The current subscription of every stream, re-decided by :meth:`refresh`.

    Args:
        node: the rclpy node (graph queries, subscription creation and destruction).
        qos: ``auto``, ``reliable`` or ``sensor_data``.
        create: ``create(stream, candidate, qos_profile) -> Subscription``.
        log: ``log(text)`` for the one line per (re)subscription.
    """

    def __init__(self, node, qos: str, create: Callable, log: Callable[[str], None]) -> None:
        self._node = node
        self._qos = qos
        self._create = create
        self._log = log
        self.candidates: dict[str, list[Candidate]] = {}
        self.current: dict[str, tuple[Candidate, ReliabilityPolicy]] = {}
        self.since: dict[str, float] = {}   # stream -> when its current subscription was made (monotonic s)
        self._subscriptions: dict[str, object] = {}
        self.changes = 0

    def add(self, stream: str, candidates: list[Candidate]) -> None:
        self.candidates[stream] = candidates

    def topic(self, stream: str) -> str:
        """The topic read for ``stream`` (the preferred candidate while none is subscribed)."""
        current = self.current.get(stream)
        return current[0].topic if current else self.candidates[stream][0].topic

    def topics_text(self, stream: str) -> str:
        """``/rgb/image`` or ``/rgb/image (or /rgb/image/compressed)`` for log lines."""
        if stream in self.current or len(self.candidates[stream]) == 1:
            return self.topic(stream)
        names = [c.topic for c in self.candidates[stream]]
        return f"{names[0]} (or {', '.join(names[1:])})"

    @property
    def needs_graph(self) -> bool:
        return self._qos == "auto" or any(len(c) > 1 for c in self.candidates.values())

    def refresh(self) -> None:
        """Re-read the publishers; (re)subscribe the streams whose answer changed."""
        for stream, candidates in self.candidates.items():
            choice = self._decide(candidates)
            if choice is None or self.current.get(stream) == choice:
                continue
            old = self._subscriptions.pop(stream, None)
            if old is not None:
                self._node.destroy_subscription(old)
            candidate, reliability = choice
            self._subscriptions[stream] = self._create(stream, candidate, qos_profile(reliability))
            previous = self.current.get(stream)
            self.current[stream] = choice
            self.since[stream] = time.monotonic()
            self.changes += 1
            why = {"auto": "every publisher is reliable" if reliability == ReliabilityPolicy.RELIABLE
                   else "a publisher is best effort"}.get(self._qos, f"qos {self._qos}")
            kind = "reliable" if reliability == ReliabilityPolicy.RELIABLE else "best effort"
            self._log(f"{'re' if previous else ''}subscribed to {candidate.topic} "
                      f"({candidate.msg_type.__name__}, {kind}: {why})")

    def _decide(self, candidates: list[Candidate]) -> Optional[tuple[Candidate, ReliabilityPolicy]]:
        fixed = {"reliable": ReliabilityPolicy.RELIABLE, "sensor_data": ReliabilityPolicy.BEST_EFFORT}.get(self._qos)
        if fixed is not None and len(candidates) == 1:
            return candidates[0], fixed
        for candidate in candidates:
            found = reliability_of(self._node.get_publishers_info_by_topic(candidate.topic))
            if found is not None:
                return candidate, fixed or found
        return None
