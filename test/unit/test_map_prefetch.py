"""``map``'s loop: the next frames are read in a background thread (same frames, same order, same
errors); log lines get a line of their own under the progress bar."""

from __future__ import annotations

import logging
import sys
import threading

import numpy as np
import pytest

from rtabmap_ros2.cli.cmd_map import map_datasets, prefetched
from rtabmap_ros2.core import transforms
from rtabmap_ros2.core.params import Params
from rtabmap_ros2.core.rtabmap import Rtabmap
from rtabmap_ros2.core.sensor import SensorFrame
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


def test_a_warning_while_mapping_gets_a_line_of_its_own_under_the_progress_bar(tmp_path, capfd):
    """A log line written while the bar is drawn (here: a frame with a NaN pose, skipped) starts a
    line of its own in the terminal, not glued to the bar's last redraw (tqdm's logging redirect,
    as ``detect`` does). The frames around it are mapped."""
    frames = [SensorFrame(stamp_ns=k * 10**9, T_odom_base=transforms.from_xy_yaw(0.1 * k, 0.0, 0.0))
              for k in range(5)]
    frames[3] = SensorFrame(stamp_ns=3 * 10**9, T_odom_base=np.full((4, 4), np.nan))
    console = logging.StreamHandler(sys.stderr)  # what the command line's basicConfig installs
    logging.getLogger().addHandler(console)
    try:
        with Rtabmap(Params(), tmp_path / "map.db") as rtabmap:
            sessions = map_datasets(rtabmap, [("bag", frames)], progress=True, print_line=lambda line: None)
    finally:
        logging.getLogger().removeHandler(console)
    assert sessions[0].frames == 4 and sessions[0].skipped == 1
    err = capfd.readouterr().err
    at = err.index("bag: frame at 3.000000000 s skipped")
    line_start = err[:at].rsplit("\n", 1)[-1].rsplit("\r", 1)[-1]
    assert line_start.strip() == "", repr(err[max(0, at - 80):at + 40])
