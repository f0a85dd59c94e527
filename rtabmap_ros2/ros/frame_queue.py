"""The synchronised frames waiting for the node's worker, their features extracted ahead (issue 50).

The worker processes frames one at a time, in order (the core is one thread's). Extracting a
frame's features (Alg. 2: GFTT corners + ORB descriptors, OpenCV, which releases the GIL) does not
depend on the map, so :class:`FrameQueue` has a thread of its own extract them for the frames
waiting, in order, while the worker processes the frames before them: on two cores the worker's
time per frame loses the extraction. The worker takes a frame with :meth:`FrameQueue.pop` and its
features with :meth:`FrameQueue.features`, which waits for the extraction under way, or extracts
them itself when the thread has not started on that frame yet. The features are the same whoever
extracts them (same parameters, same image): the map does not depend on the timing.

Bounded: past ``size`` frames the oldest is dropped (:meth:`FrameQueue.put` says so); the node
counts and logs it.
"""

from __future__ import annotations

import threading
from collections import deque
from typing import Callable, Optional

from rtabmap_ros2.core.features import FeatureExtractor, Features
from rtabmap_ros2.core.rtabmap import frame_features
from rtabmap_ros2.core.sensor import SensorFrame
from rtabmap_ros2.ros.frame_times import FrameTimer, FrameTimes

# Thread name and its part in FrameTimes.
FEATURES_THREAD = "features"
# Wake-up period of the extraction thread when idle, so a stop is noticed (s).
POLL_S = 0.1

_QUEUED, _EXTRACTING, _DONE = "queued", "extracting", "done"


class QueuedFrame:
    """A frame waiting for the worker: the synchronised frame, when its last message arrived
    (``time.monotonic()``), and its features once extracted (or the error extracting them)."""

    __slots__ = ("frame", "arrival", "features", "error", "_state", "_done")

    def __init__(self, frame: SensorFrame, arrival: float) -> None:
        self.frame = frame
        self.arrival = arrival
        self.features: Optional[Features] = None
        self.error: Optional[BaseException] = None
        self._state = _QUEUED
        self._done = threading.Event()


class FrameQueue:
    """Frames for the worker, oldest first, with a thread extracting their features ahead.

    Args:
        make_extractor: a new :class:`FeatureExtractor` with the core's feature parameters (the
            thread's own: OpenCV detectors are not shared between threads).
        size: frames kept at most (the oldest is dropped beyond).
        times: where the thread's time per frame goes (``features``).
    """

    def __init__(self, make_extractor: Callable[[], FeatureExtractor], size: int, times: FrameTimes) -> None:
        self.size = size
        self._make_extractor = make_extractor
        self._times = times
        self._items: deque[QueuedFrame] = deque()
        self._lock = threading.Lock()
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._extract_ahead, name="rtabmap_features", daemon=True)
        self._thread.start()

    def __len__(self) -> int:
        with self._lock:
            return len(self._items)

    def put(self, frame: SensorFrame, arrival: float) -> bool:
        """Queue ``frame``; True when the queue was full and its oldest frame was dropped."""
        with self._lock:
            dropped = len(self._items) >= self.size
            if dropped:
                self._items.popleft()
            self._items.append(QueuedFrame(frame, arrival))
        self._wake.set()
        return dropped

    def pop(self) -> Optional[QueuedFrame]:
        """The oldest frame (removed), or None."""
        with self._lock:
            return self._items.popleft() if self._items else None

    def clear(self) -> None:
        """Drop every waiting frame (an extraction under way finishes, unused)."""
        with self._lock:
            self._items.clear()

    def features(self, item: QueuedFrame, extractor: FeatureExtractor) -> Features:
        """``item``'s features: extracted ahead, or being extracted (waited for), or extracted
        here with ``extractor`` (the caller's own). Raises what the extraction raised."""
        with self._lock:
            mine = item._state == _QUEUED
            if mine:
                item._state = _EXTRACTING
        if mine:
            _extract(item, extractor)
        item._done.wait()
        if item.error is not None:
            raise item.error
        return item.features

    def stop(self) -> None:
        """End the extraction thread (after the frame under way)."""
        self._stop.set()
        self._wake.set()
        self._thread.join()

    def _extract_ahead(self) -> None:
        extractor = self._make_extractor()
        while not self._stop.is_set():
            self._wake.wait(POLL_S)
            with self._lock:
                item = next((q for q in self._items if q._state == _QUEUED), None)
                if item is None:
                    self._wake.clear()
                    continue
                item._state = _EXTRACTING
            timer = FrameTimer()
            with timer.part(FEATURES_THREAD):
                _extract(item, extractor)
            self._times.add(timer, FEATURES_THREAD)


def _extract(item: QueuedFrame, extractor: FeatureExtractor) -> None:
    """Extract ``item``'s features (or keep the error), then tell who waits."""
    try:
        item.features = frame_features(extractor, item.frame)
    except Exception as exc:  # noqa: BLE001 - raised again in the worker, which handles it as a frame error
        item.error = exc
    finally:
        item._state = _DONE
        item._done.set()


__all__ = ["FEATURES_THREAD", "FrameQueue", "QueuedFrame"]
