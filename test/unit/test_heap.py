"""Freed heap memory goes back to the operating system after a large transfer (core/heap.py)."""

from __future__ import annotations

import pytest

from rtabmap_ros2.core import heap
from rtabmap_ros2.core import rtabmap as rtabmap_module
from rtabmap_ros2.core.params import Params
from rtabmap_ros2.core.rtabmap import HEAP_RELEASE_MIN_TRANSFERRED, Rtabmap
from rtabmap_ros2.core.sensor import SensorFrame
from rtabmap_ros2.sim.sequence import make_sequence

NS = 10**9


def anonymous_rss_mb() -> float:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("RssAnon:"):
                return int(line.split()[1]) / 1024.0
    pytest.skip("no RssAnon in /proc/self/status")


@pytest.mark.skipif(heap._MALLOC_TRIM is None, reason="the C library has no malloc_trim (not glibc)")
def test_freed_blocks_below_one_in_use_leave_rss_only_when_released():
    # 3,000 blocks of 64 KB come from the heap (under glibc's mmap threshold); the last one
    # stays in use, so the heap's top cannot shrink and free() alone keeps the pages.
    blocks = [bytearray(64 * 1024) for _ in range(3000)]
    del blocks[:-1]
    held = anonymous_rss_mb()
    assert heap.release_free_heap()
    assert anonymous_rss_mb() < held - 100
    assert blocks  # in use until here


def test_a_transfer_of_many_locations_releases_the_heap_an_ordinary_frame_does_not(tmp_path, monkeypatch):
    calls = []
    monkeypatch.setattr(rtabmap_module, "release_free_heap", lambda: calls.append(1) or True)
    sequence = make_sequence(HEAP_RELEASE_MIN_TRANSFERRED + 60, seed=2)
    path = tmp_path / "m.db"
    with Rtabmap(Params(), path) as rtabmap:
        stats = [rtabmap.process(SensorFrame(stamp_ns=(i + 1) * NS, rgb=sequence.image(i)))
                 for i in range(len(sequence))]
        wm = len(rtabmap.memory.wm)
    assert not any(s.transferred for s in stats) and not calls
    assert wm >= HEAP_RELEASE_MIN_TRANSFERRED + 10
    # Reopened with Rtabmap/MemoryThr 10: the first frame cuts WM to it in one transfer.
    with Rtabmap(Params().with_value("memory.max_wm_size", 10), path) as again:
        first = again.process(SensorFrame(stamp_ns=10**12, rgb=sequence.image(0)))
        assert first.transferred >= HEAP_RELEASE_MIN_TRANSFERRED and len(calls) == 1
        # Frames of other places: each transfers a few locations (retrieval brings some back, so not every one
        # transfers), far fewer than a release needs, and none releases the heap.
        later = [again.process(SensorFrame(stamp_ns=10**12 + (k + 1) * NS, rgb=sequence.image(len(sequence) // 2 + k))).transferred
                 for k in range(5)]
        assert any(later) and max(later) < HEAP_RELEASE_MIN_TRANSFERRED and len(calls) == 1
