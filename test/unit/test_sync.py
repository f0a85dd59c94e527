"""FrameSynchronizer: approximate/exact matching, gaps, out-of-order input, rate limit, time jumps."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from rtabmap_ros2.core.params import SyncParams
from rtabmap_ros2.core.sync import FrameSynchronizer
from rtabmap_ros2.errors import ParameterError

MS = 1_000_000
S = 1_000_000_000


def feed(sync, messages):
    """Add (stream, stamp_ns) messages in order; value = (stream, stamp); return all sets + flush."""
    out = []
    for stream, stamp in messages:
        out += sync.add(stream, stamp, (stream, stamp))
    return out + sync.flush()


def interleaved(streams_offsets, n, period_ns, start=10 * S):
    """Messages of several streams at ``period_ns``, each with its offset (ns), sorted by stamp."""
    msgs = [(s, start + i * period_ns + off) for s, off in streams_offsets.items() for i in range(n)]
    return sorted(msgs, key=lambda m: m[1])


def test_approximate_sets_pair_nearest_within_tolerance():
    sync = FrameSynchronizer(SyncParams(rate_hz=0, tolerance_s=0.02), {"rgb", "depth", "odom"})
    sets = feed(sync, interleaved({"rgb": 0, "depth": 5 * MS, "odom": -3 * MS}, 10, 100 * MS))
    assert len(sets) == 10
    for s in sets:
        assert set(s.values) == {"rgb", "depth", "odom"}
        assert s.values["rgb"][1] == s.stamp_ns  # rgb is the pivot: the reference stamp
        assert abs(s.stamps_ns["depth"] - s.stamp_ns) == 5 * MS
        assert abs(s.stamps_ns["odom"] - s.stamp_ns) == 3 * MS


def test_messages_outside_tolerance_make_no_set():
    sync = FrameSynchronizer(SyncParams(rate_hz=0, tolerance_s=0.02), {"rgb", "depth"})
    sets = feed(sync, interleaved({"rgb": 0, "depth": 50 * MS}, 10, 100 * MS))
    assert sets == []
    assert sync.dropped["unmatched"] == 10


def test_exact_sync_needs_equal_stamps():
    sync = FrameSynchronizer(SyncParams(rate_hz=0, approx_sync=False), {"rgb", "depth"})
    msgs = interleaved({"rgb": 0, "depth": 0}, 5, 100 * MS) + [("rgb", 20 * S), ("depth", 20 * S + 1)]
    sets = feed(sync, msgs)
    assert [s.stamp_ns for s in sets] == [10 * S + i * 100 * MS for i in range(5)]


def test_out_of_order_arrivals_still_pair(rng):
    msgs = interleaved({"rgb": 0, "depth": 2 * MS, "scan": -4 * MS}, 30, 100 * MS)
    # Swap neighbours at random: a message may come before an older one of another stream.
    order = np.arange(len(msgs))
    for i in rng.choice(len(msgs) - 1, 20, replace=False):
        order[i], order[i + 1] = order[i + 1], order[i]
    shuffled = [msgs[i] for i in order]
    sync = FrameSynchronizer(SyncParams(rate_hz=0, tolerance_s=0.01), {"rgb", "depth", "scan"})
    sets = feed(sync, shuffled)
    assert len(sets) >= 28
    for s in sets:
        assert s.stamps_ns["depth"] - s.stamp_ns == 2 * MS
        assert s.stamps_ns["scan"] - s.stamp_ns == -4 * MS


def test_missing_messages_skip_only_their_frames():
    msgs = interleaved({"rgb": 0, "depth": 1 * MS}, 20, 100 * MS)
    gap = {10 * S + i * 100 * MS + 1 * MS for i in (5, 6, 7)}
    msgs = [m for m in msgs if not (m[0] == "depth" and m[1] in gap)]
    sync = FrameSynchronizer(SyncParams(rate_hz=0, tolerance_s=0.02), {"rgb", "depth"})
    sets = feed(sync, msgs)
    assert len(sets) == 17
    assert sync.dropped["unmatched"] == 3


def test_silent_stream_does_not_wedge():
    sync = FrameSynchronizer(SyncParams(rate_hz=0, tolerance_s=0.02, queue_size=5), {"rgb", "depth"})
    # depth silent for 50 rgb messages, then both streams come back.
    out = [sync.add("rgb", 10 * S + i * 100 * MS, i) for i in range(50)]
    assert all(o == [] for o in out)
    assert sync.dropped["queue_full"] >= 40
    later = feed(sync, interleaved({"rgb": 0, "depth": 0}, 10, 100 * MS, start=20 * S))
    assert len(later) == 10


def test_rate_limit_one_set_per_second_from_10hz():
    sync = FrameSynchronizer(SyncParams(rate_hz=1.0, tolerance_s=0.02), {"rgb", "scan"})
    sets = feed(sync, interleaved({"rgb": 0, "scan": 3 * MS}, 100, 100 * MS))  # 10 s at 10 Hz
    assert len(sets) == 10
    gaps = np.diff([s.stamp_ns for s in sets]) / S
    assert np.allclose(gaps, 1.0)
    assert sync.dropped["rate_limited"] == 90


def test_rate_limit_emits_as_soon_as_set_completes():
    sync = FrameSynchronizer(SyncParams(rate_hz=1.0, tolerance_s=0.02), {"rgb", "depth"})
    assert sync.add("rgb", 5 * S, "a") == []
    sets = sync.add("depth", 5 * S + 1 * MS, "b")  # completes the set: emitted now, not at period end
    assert len(sets) == 1 and sets[0].values == {"rgb": "a", "depth": "b"}


def test_time_going_backwards_resets(caplog):
    sync = FrameSynchronizer(SyncParams(rate_hz=1.0, tolerance_s=0.02), {"rgb", "depth"})
    first = []
    for stream, stamp in interleaved({"rgb": 0, "depth": 0}, 30, 100 * MS, start=100 * S):
        first += sync.add(stream, stamp, None)
    with caplog.at_level(logging.WARNING, logger="rtabmap_ros2.core.sync"):
        # Bag loop: the same 3 s again without flush in between.
        again = []
        for stream, stamp in interleaved({"rgb": 0, "depth": 0}, 30, 100 * MS, start=100 * S):
            again += sync.add(stream, stamp, None)
    assert sync.resets == 1
    assert "backwards" in caplog.text
    assert len(first) == 3 and len(again) >= 2  # the limiter restarted with the new timeline


def test_small_backward_step_is_not_a_reset():
    sync = FrameSynchronizer(SyncParams(rate_hz=1.0), {"rgb"})
    sync.add("rgb", 10 * S, None)
    sync.add("rgb", 10 * S - 200 * MS, None)
    assert sync.resets == 0
    assert sync.dropped["late"] == 1


def test_pivot_choice_and_validation():
    assert FrameSynchronizer(SyncParams(), {"odom", "scan"}).pivot == "scan"
    assert FrameSynchronizer(SyncParams(), {"odom", "scan", "rgb"}).pivot == "rgb"
    with pytest.raises(ParameterError):
        FrameSynchronizer(SyncParams(), set())
    with pytest.raises(ParameterError):
        FrameSynchronizer(SyncParams(), {"rgb"}, pivot="scan")


def test_unrequired_streams_are_ignored():
    sync = FrameSynchronizer(SyncParams(rate_hz=0), {"rgb"})
    assert sync.add("imu", 1, None) == []
    assert len(sync.add("rgb", 1, None)) == 1


def test_message_delivered_late_relative_to_other_streams_is_not_a_time_jump():
    """DDS can deliver a scan seconds after newer images: it must still join its set."""
    sync = FrameSynchronizer(SyncParams(rate_hz=0.0, tolerance_s=0.05), {"rgb", "scan"})
    emitted = []
    for k in range(5):
        emitted += sync.add("rgb", k * S, f"rgb{k}")
    # The scans of the five frames arrive only now, 3 s late.
    for k in range(5):
        emitted += sync.add("scan", k * S, f"scan{k}")
    emitted += sync.flush()
    assert sync.resets == 0
    assert [s.values["scan"] for s in emitted] == [f"scan{k}" for k in range(5)]


def test_drops_are_reported_with_the_stream_at_fault():
    """queue_full names the stream that is behind and by how much; unmatched the stream with the
    gap; late the pivot; the rate limit's drops are its purpose and are not reported."""
    reports = []
    sync = FrameSynchronizer(SyncParams(rate_hz=0, tolerance_s=0.02, queue_size=3), {"rgb", "scan"},
                             on_drop=lambda *r: reports.append(r))
    # scan held back (a DDS repair): rgb runs 4 messages ahead of it, then scan catches up.
    for k in range(5):
        sync.add("rgb", 10 * S + k * S, k)
    assert [r[:2] for r in reports] == [("queue_full", "rgb")] * 2
    assert "scan has sent nothing yet" in reports[0][2]
    sync.add("scan", 10 * S, "s0")
    reports.clear()
    sync.add("rgb", 15 * S, 5)
    assert reports[0][:2] == ("queue_full", "rgb") and "scan is 5.00 s behind" in reports[0][2]
    reports.clear()
    sync.add("scan", 13 * S + 500 * MS, "s")   # rgb 13 s (12 s was pushed out): scans 10 s and 13.5 s too far
    assert [r[:2] for r in reports] == [("unmatched", "scan")]
    assert "no scan message within 0.02 s of the rgb message stamped 13.000 s" in reports[0][2]
    assert sync.dropped == {"queue_full": 3, "late": 0, "unmatched": 1, "rate_limited": 0}
    reports.clear()
    sync = FrameSynchronizer(SyncParams(rate_hz=1), {"rgb", "scan"}, on_drop=lambda *r: reports.append(r))
    feed(sync, [("rgb", 10 * S), ("scan", 10 * S), ("rgb", 11 * S), ("scan", 11 * S + 500 * MS),
                ("rgb", 10 * S + 800 * MS)])
    assert [r[:2] for r in reports] == [("unmatched", "scan"), ("late", "rgb")]
    assert "not after the last one decided (11.000 s)" in reports[1][2]
