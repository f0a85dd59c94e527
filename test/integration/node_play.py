"""One way for the integration tests to play a bag into an ``rtabmap`` node in this process.

The node and a player node spin on one executor (:func:`ros_spin.spinning`); the bag is played in
real time (``rate``; faster replay interleaves consecutive sets and the synchroniser emits fewer),
then the helper waits until every synchronised set is processed or dropped.
"""

from __future__ import annotations

import threading
import time
from pathlib import Path
from typing import Any, Callable, Optional

from rclpy.node import Node
from rclpy.parameter import Parameter

from rtabmap_ros2.ros.executor import NodeExecutor
from rtabmap_ros2.ros.node import RtabmapNode
from rtabmap_ros2.ros.play import play_bag

from ros_spin import spinning

# Real time, as a robot's drivers publish: faster replay interleaves the next set's messages with
# the current one's, and the approximate synchroniser then emitted 39-44 of the 47 sets (none lost
# in transport) depending on thread scheduling.
PLAY_RATE = 1.0
# Longest wait for the node to finish the sets it received after the last message (s).
PROCESS_TIMEOUT_S = 30.0


def play_into_node(context, bag: Path, params: dict[str, Any], seconds: Optional[float] = None,
                   before_destroy: Optional[Callable[[RtabmapNode], Any]] = None,
                   rate: float = PLAY_RATE) -> tuple[RtabmapNode, Any]:
    """Play ``bag`` (its first ``seconds`` of wall time, or all of it, every message acknowledged)
    into a node with ``params`` at ``rate`` (faster: fewer sets synchronised, see PLAY_RATE); wait
    until every synchronised set is processed; call ``before_destroy(node)``;
    destroy the node (its database is closed). Returns the node and what ``before_destroy`` returned."""
    node = RtabmapNode(context=context, parameter_overrides=[Parameter(k, value=v) for k, v in params.items()])
    player = Node("player", context=context)
    executor = NodeExecutor(num_threads=3, context=context)
    executor.add_node(node)
    executor.add_node(player)
    stop = threading.Event()
    timer = threading.Timer(seconds, stop.set) if seconds else None
    try:
        with spinning(executor):
            if timer:
                timer.start()
            stats = play_bag(bag, player, rate=rate, delay_s=1.5, stop=stop)
            assert timer or not stats.unacknowledged, stats
            deadline = time.monotonic() + PROCESS_TIMEOUT_S
            while time.monotonic() < deadline and node.frames_processed + node.frames_dropped < node._sync.emitted:
                time.sleep(0.1)
            result = before_destroy(node) if before_destroy else None
    finally:
        if timer:
            timer.cancel()
        player.destroy_node()
        node.destroy_node()
    return node, result
