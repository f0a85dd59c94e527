"""``map`` reads the next frames in a background thread: same frames, same order, same errors."""

from __future__ import annotations

import threading

import pytest

from rtabmap_ros2.cli.cmd_map import prefetched
from rtabmap_ros2.errors import BagError


def test_prefetched_keeps_every_item_in_order():
    assert list(prefetched(iter(range(100)), depth=2)) == list(range(100))


def test_an_error_while_reading_is_raised_after_the_items_before_it():
    def frames():
        yield 1
        yield 2
        raise BagError("bag x: truncated")

    got = []
    with pytest.raises(BagError, match="truncated"):
        for item in prefetched(frames()):
            got.append(item)
    assert got == [1, 2]


def test_stopping_early_ends_the_reader_thread():
    before = threading.active_count()
    for item in prefetched(iter(range(10_000)), depth=2):
        if item == 3:
            break
    assert threading.active_count() == before
