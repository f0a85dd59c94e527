"""The node's frame queue: features extracted ahead by its thread, or by the worker when it gets there
first; the same features either way; errors and drops (ros/frame_queue.py; no rclpy needed)."""

from __future__ import annotations

import threading

import numpy as np
import pytest

from rtabmap_ros2.core.features import FeatureExtractor
from rtabmap_ros2.core.params import FeatureParams
from rtabmap_ros2.core.sensor import SensorFrame
from rtabmap_ros2.errors import SensorDataError
from rtabmap_ros2.ros.frame_queue import FEATURES_THREAD, FrameQueue
from rtabmap_ros2.ros.frame_times import FrameTimes
from waiting import TIMEOUT_S, wait_for



def textured_frame(seed: int, stamp_ns: int) -> SensorFrame:
    rng = np.random.default_rng(seed)
    rgb = np.kron(rng.integers(0, 256, (48, 64, 3)), np.ones((10, 10, 1))).astype(np.uint8)
    return SensorFrame(stamp_ns=stamp_ns, rgb=rgb)


class GatedExtractor:
    """A FeatureExtractor that waits for ``gate`` before each extraction and counts them."""

    def __init__(self, gate: threading.Event) -> None:
        self.inner = FeatureExtractor(FeatureParams())
        self.gate = gate
        self.extracted = 0

    def extract(self, image, depth_m=None):
        assert self.gate.wait(TIMEOUT_S)
        self.extracted += 1
        return self.inner.extract(image, depth_m)

    def empty(self):
        return self.inner.empty()


def test_features_extracted_ahead_are_those_the_worker_would_extract():
    times = FrameTimes(100)
    queue = FrameQueue(lambda: FeatureExtractor(FeatureParams()), 10, times)
    try:
        frames = [textured_frame(k, k + 1) for k in range(3)]
        for f in frames:
            assert not queue.put(f, 0.0)
        assert wait_for(lambda: len(times.threads.get(FEATURES_THREAD, ())) == 3)   # all three ahead
        mine = FeatureExtractor(FeatureParams())
        for f in frames:
            item = queue.pop()
            assert item.frame is f
            got = queue.features(item, mine)
            expected = mine.extract(f.rgb, f.depth_m)
            np.testing.assert_array_equal(got.descriptors, expected.descriptors)
            np.testing.assert_array_equal(got.keypoints, expected.keypoints)
        assert queue.pop() is None
    finally:
        queue.stop()


def test_the_worker_extracts_a_frame_itself_when_the_thread_is_busy_with_another():
    gate = threading.Event()
    made: list[GatedExtractor] = []
    queue = FrameQueue(lambda: made.append(GatedExtractor(gate)) or made[-1], 10, FrameTimes(100))
    try:
        queue.put(textured_frame(0, 1), 0.0)
        queue.put(textured_frame(1, 2), 0.0)
        assert wait_for(lambda: made)
        first, second = queue.pop(), queue.pop()
        # The thread is held on the first frame: the worker takes the second one itself, at once.
        worker = FeatureExtractor(FeatureParams())
        assert len(queue.features(second, worker).descriptors) > 0
        assert made[0].extracted == 0
        gate.set()   # the thread finishes the first; the worker waits for it rather than doing it twice
        assert len(queue.features(first, worker).descriptors) > 0
        assert made[0].extracted == 1
    finally:
        gate.set()
        queue.stop()


def test_an_extraction_error_reaches_the_worker_and_the_queue_goes_on():
    queue = FrameQueue(lambda: FeatureExtractor(FeatureParams()), 10, FrameTimes(100))
    try:
        bad = SensorFrame(stamp_ns=1, rgb=np.zeros((4, 4, 3), np.float64))   # not uint8
        queue.put(bad, 0.0)
        queue.put(textured_frame(2, 2), 0.0)
        worker = FeatureExtractor(FeatureParams())
        with pytest.raises(SensorDataError):
            queue.features(queue.pop(), worker)
        assert len(queue.features(queue.pop(), worker).descriptors) > 0
    finally:
        queue.stop()


def test_a_full_queue_drops_its_oldest_frame():
    gate = threading.Event()
    queue = FrameQueue(lambda: GatedExtractor(gate), 2, FrameTimes(100))
    try:
        frames = [textured_frame(k, k + 1) for k in range(3)]
        assert [queue.put(f, 0.0) for f in frames] == [False, False, True]
        assert len(queue) == 2 and queue.pop().frame is frames[1] and queue.pop().frame is frames[2]
        queue.put(frames[0], 0.0)
        queue.clear()
        assert queue.pop() is None
    finally:
        gate.set()
        queue.stop()
