"""The node's executor (ros/executor.py): every message reaches its callback once, and each task is
submitted to the thread pool once, where rclpy's MultiThreadedExecutor submitted a task again at every
round until a pool thread started it (issue 50: 97.8 % of its rounds in a 4x replay)."""

from __future__ import annotations

import random
import time

import pytest

pytest.importorskip("rclpy")

from rclpy.node import Node  # noqa: E402
from std_msgs.msg import String  # noqa: E402

from ros_spin import spinning  # noqa: E402
from rtabmap_ros2.ros.executor import NodeExecutor  # noqa: E402

DOMAIN_ID = random.randint(200, 230)


def test_each_message_is_delivered_once_by_one_pool_submission(context):
    node = Node("executor_test", context=context)
    received: list[str] = []

    def slow_callback(msg) -> None:   # busy pool threads: tasks wait to start, as under load
        received.append(msg.data)
        time.sleep(0.005)

    node.create_subscription(String, "chatter", slow_callback, 100)
    publisher = node.create_publisher(String, "chatter", 100)
    executor = NodeExecutor(num_threads=2, context=context)
    submitted = []
    submit = executor._executor.submit
    executor._executor.submit = lambda fn: (submitted.append(fn), submit(fn))[1]
    executor.add_node(node)
    sent = [f"message {i}" for i in range(60)]
    try:
        with spinning(executor):
            time.sleep(0.5)
            for text in sent:
                publisher.publish(String(data=text))
                time.sleep(0.001)
            deadline = time.monotonic() + 10.0
            while len(received) < len(sent) and time.monotonic() < deadline:
                time.sleep(0.05)
    finally:
        node.destroy_node()
    assert received == sent
    assert len(submitted) == len(sent)
