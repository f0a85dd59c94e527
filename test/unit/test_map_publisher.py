"""The node's publishing threads (ros/map_publisher.py): every frame's info in order, the newest local
map only when frames come faster than they are published, the grid from the newest map, a reset."""

from __future__ import annotations

import threading
import time
from collections import deque

import numpy as np
import pytest

pytest.importorskip("rclpy")

from rtabmap_ros2.core import transforms  # noqa: E402
from rtabmap_ros2.core.local_map import LocalMap  # noqa: E402
from rtabmap_ros2.core.params import GridParams  # noqa: E402
from rtabmap_ros2.core.sensor import LaserScan  # noqa: E402
from rtabmap_ros2.ros import conversions as conv  # noqa: E402
from rtabmap_ros2.ros.frame_times import FrameTimes  # noqa: E402
from rtabmap_ros2.ros.map_publisher import MapPublisher, Outputs, Published  # noqa: E402
from waiting import wait_for  # noqa: E402



class Recorder:
    """A publisher stand-in keeping what is published."""

    def __init__(self) -> None:
        self.messages: list = []

    def publish(self, msg) -> None:
        self.messages.append(msg)


def scan() -> LaserScan:
    angles = np.linspace(-np.pi / 2, np.pi / 2, 90)
    return LaserScan(np.full(90, 2.0, np.float32), float(angles[0]), float(angles[1] - angles[0]), 0.1, 5.0,
                     np.eye(4))


def frame(n: int, generation: int = 0) -> Published:
    """Frame ``n``: a local map of nodes 1..n along x, each with a scan."""
    poses = {k: transforms.from_xy_yaw(0.5 * k, 0.0, 0.0) for k in range(1, n + 1)}
    local = LocalMap(poses, [], {k: 0 for k in poses}, np.eye(4), {k: scan() for k in poses})
    return Published(stamp_ns=n * 1_000_000_000, arrival=time.monotonic(), statistics={"location_id": n},
                     local=local, worker_times={"node_time_ms/total": 1.0}, generation=generation)


@pytest.fixture
def publisher():
    outputs = Outputs(path=Recorder(), graph=Recorder(), grid=Recorder(), info=Recorder(), localization=Recorder(),
                      tf_broadcaster=None, map_frame="map", info_extra=lambda: {"node_frames_dropped": 0},
                      log_error=pytest.fail)
    pub = MapPublisher(outputs, GridParams(), FrameTimes(100), deque(), grid_period_s=0.0, grid_max_casts=1000)
    yield pub, outputs
    pub.stop()


def test_frames_faster_than_publishing_get_every_info_and_the_newest_map(publisher):
    pub, out = publisher
    with pub.round_lock:   # a slow round under way: three frames are handed over meanwhile
        for n in (1, 2, 3):
            pub.submit(frame(n))
        time.sleep(0.2)
    assert wait_for(lambda: len(out.info.messages) == 3)
    assert [conv.statistics_from_msg(m)["location_id"] for m in out.info.messages] == ["1", "2", "3"]
    # The newest map, not one per frame: the thread may have taken frame 1's map before the round's lock
    # (a loaded machine wakes it late), never frame 2's.
    assert wait_for(lambda: out.path.messages and len(out.path.messages[-1].poses) == 3)
    assert [len(m.poses) for m in out.path.messages] in ([3], [1, 3])
    # The round publishes the path first, then the graph and the latency: waited for, not raced.
    assert wait_for(lambda: len(out.graph.messages) == len(out.path.messages) and len(pub.latencies_s) == 3)
    info = conv.statistics_from_msg(out.info.messages[-1])
    assert info["node_time_ms/total"] == "1.0" and info["node_frames_dropped"] == "0"
    published = len(out.path.messages)
    pub.submit(frame(4))
    assert wait_for(lambda: len(out.path.messages) == published + 1) and len(out.path.messages[-1].poses) == 4


def test_the_grid_is_drawn_from_the_newest_map(publisher):
    pub, out = publisher
    pub.submit(frame(3))
    assert wait_for(lambda: out.grid.messages)
    grid, resolution, _ = conv.grid_from_msg(out.grid.messages[-1])
    assert resolution == pytest.approx(GridParams().resolution) and (grid == 100).any() and (grid == 0).any()


def test_after_a_reset_older_maps_are_not_published_but_their_info_is(publisher):
    pub, out = publisher
    with pub.round_lock:
        pub.submit(frame(5))
        pub.reset()   # the worker reset the core after handing frame 5 over
        time.sleep(0.2)
    assert wait_for(lambda: len(out.info.messages) == 1)
    time.sleep(0.2)
    assert not out.path.messages and not out.graph.messages
    pub.submit(frame(1, generation=pub.generation))
    assert wait_for(lambda: len(out.path.messages) == 1) and len(out.path.messages[0].poses) == 1


def test_a_failing_publisher_is_logged_once_and_publishing_goes_on():
    errors: list[str] = []

    class Failing(Recorder):
        def publish(self, msg) -> None:
            raise RuntimeError("publisher's context is not valid")

    outputs = Outputs(path=Failing(), graph=Recorder(), grid=Recorder(), info=Recorder(), localization=Recorder(),
                      tf_broadcaster=None, map_frame="map", info_extra=dict, log_error=errors.append)
    pub = MapPublisher(outputs, GridParams(), FrameTimes(100), deque(), grid_period_s=0.0, grid_max_casts=1000)
    try:
        pub.submit(frame(1))
        assert wait_for(lambda: errors)
        pub.submit(frame(2))
        assert wait_for(lambda: pub.grids_published >= 1)
        time.sleep(0.2)
        assert len(errors) == 1 and "RuntimeError" in errors[0]
    finally:
        pub.stop()
    assert threading.active_count() >= 1
