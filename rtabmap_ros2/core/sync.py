"""The one frame synchroniser, shared by the bag reader and the live ROS 2 node.

Messages of several streams (``"rgb"``, ``"depth"``, ``"scan"``, ``"odom"``...) arrive one by one
with their stamps; :class:`FrameSynchronizer` groups them into :class:`SyncedSet` s, one message
per required stream, and rate-limits the sets to the detection rate (the 2013 paper processes
images at 1 Hz, Section IV; the 2014 robot at 1 Hz too).

Rules (message time everywhere: stamps, never the wall clock):

* **Pivot.** One stream is the pivot (by default the first present of :data:`PIVOT_PRIORITY`:
  rgb, then scan, depth, odom; or the ``pivot`` argument). Each pivot message proposes a set
  whose reference stamp is the pivot's stamp.
* **Approximate time** (``approx_sync=True``). For every other stream the match is the message
  nearest to the reference stamp, accepted when ``|stamp - reference| <= tolerance_s``. The match
  of a stream is *decided* as soon as that stream holds a message stamped at or after the
  reference (nothing that arrives later in order can be nearer), so a set is emitted when its last
  needed message arrives: latency is one message period of the slowest stream, no more.
  A stream whose nearest message is outside the tolerance has a gap: the pivot message is dropped
  (``dropped["unmatched"]``) and the next one is tried. A message may serve two consecutive sets
  when it is the nearest to both (a slow stream such as odometry at 5 Hz under 10 Hz images).
* **Exact time** (``approx_sync=False``). Same, but the match must have the reference stamp exactly.
* **Rate limit.** Time is cut into periods of ``1 / rate_hz`` starting at the first emitted set.
  The first complete set of a period is emitted as soon as it completes, and later sets of the
  same period are dropped (``dropped["rate_limited"]``). This keeps the live node's latency low;
  the cost is that the emitted set is the period's first complete one, not its newest.
  ``rate_hz = 0`` emits every set.
* **Queues.** Each stream buffers at most ``queue_size`` messages, sorted by stamp (out-of-order
  arrivals are inserted in place); the oldest is dropped when full (``dropped["queue_full"]``).
  A pivot message older than the last decided one cannot form a set any more
  (``dropped["late"]``). A silent stream therefore never wedges the synchroniser: its partners'
  queues just overflow until it comes back. Every drop but ``rate_limited`` (the rate limit's
  purpose) is also reported to ``on_drop(reason, stream, detail)`` when given: the stream at
  fault and a sentence saying why (for ``queue_full``, which stream is how far behind).
* **Time jumps.** A stamp more than one period (at least :data:`MIN_RESET_JUMP_S`) older than the
  newest stamp of the *same* stream means the bag looped or the clock jumped (a message merely
  delivered later than other streams' newer ones is not a jump): every queue and the rate limiter are
  reset, ``resets`` is incremented and a warning is logged; the message then starts the new
  timeline.

At the end of a finite input (a bag) call :meth:`FrameSynchronizer.flush` to decide the sets that
still wait for a later message that will never come.
"""

from __future__ import annotations

import bisect
import logging
from dataclasses import dataclass, field
from typing import Callable, Iterable, Optional

from rtabmap_ros2.core.params import SyncParams
from rtabmap_ros2.errors import ParameterError

logger = logging.getLogger(__name__)

NS_PER_S = 1_000_000_000

# Pivot stream chosen when none is given: the first of these that is required.
PIVOT_PRIORITY = ("rgb", "scan", "depth", "odom", "camera_info")

# Smallest backward jump (s) taken as a time reset when the rate is unlimited (rate_hz = 0).
MIN_RESET_JUMP_S = 1.0

# Reasons counted in FrameSynchronizer.dropped.
DROP_REASONS = ("queue_full", "late", "unmatched", "rate_limited")


@dataclass(frozen=True)
class SyncedSet:
    """One synchronised set: the reference (pivot) stamp and one value per required stream."""

    stamp_ns: int
    values: dict[str, object]
    stamps_ns: dict[str, int] = field(default_factory=dict)


class _Queue:
    """Messages of one stream sorted by stamp, bounded in size."""

    def __init__(self, size: int) -> None:
        self.size = size
        self.stamps: list[int] = []
        self.values: list[object] = []

    def insert(self, stamp_ns: int, value: object) -> bool:
        """Insert in stamp order; return True when the oldest message had to be dropped."""
        i = bisect.bisect_right(self.stamps, stamp_ns)
        self.stamps.insert(i, stamp_ns)
        self.values.insert(i, value)
        if len(self.stamps) > self.size:
            del self.stamps[0], self.values[0]
            return True
        return False

    def drop_before(self, stamp_ns: int) -> None:
        """Forget messages stamped strictly before ``stamp_ns``."""
        i = bisect.bisect_left(self.stamps, stamp_ns)
        del self.stamps[:i], self.values[:i]

    def clear(self) -> None:
        self.stamps.clear()
        self.values.clear()


class FrameSynchronizer:
    """Group messages of several streams into rate-limited synchronised sets (rules: module doc)."""

    def __init__(self, params: SyncParams, streams: Iterable[str], pivot: Optional[str] = None,
                 on_drop: Optional[Callable[[str, str, str], None]] = None) -> None:
        """Create a synchroniser for the required ``streams`` (e.g. ``{"rgb", "depth", "odom"}``).

        Args:
            params: tolerance, exact/approximate, queue size and rate.
            streams: names of the streams every set must contain (at least one).
            pivot: stream whose stamps are the sets' reference stamps; default: the first of
                :data:`PIVOT_PRIORITY` in ``streams``, else the alphabetically first stream.
            on_drop: called as ``on_drop(reason, stream, detail)`` for every message dropped
                (``queue_full``, ``late``, ``unmatched``; module doc).
        """
        self.params = params
        self.streams = frozenset(streams)
        if not self.streams:
            raise ParameterError("FrameSynchronizer needs at least one stream to synchronise")
        if pivot is None:
            pivot = next((s for s in PIVOT_PRIORITY if s in self.streams), min(self.streams))
        if pivot not in self.streams:
            raise ParameterError(f"pivot stream {pivot!r} is not one of the streams {sorted(self.streams)}")
        self.pivot = pivot
        self._tolerance_ns = int(round(params.tolerance_s * NS_PER_S)) if params.approx_sync else 0
        self._period_ns = int(round(NS_PER_S / params.rate_hz)) if params.rate_hz > 0 else 0
        self._reset_jump_ns = max(self._period_ns, int(MIN_RESET_JUMP_S * NS_PER_S))
        self.dropped: dict[str, int] = dict.fromkeys(DROP_REASONS, 0)
        self._on_drop = on_drop
        self.resets = 0
        self.emitted = 0
        self._queues = {s: _Queue(params.queue_size) for s in self.streams}
        self._clear_timeline()

    def _clear_timeline(self) -> None:
        for q in self._queues.values():
            q.clear()
        self._stream_newest_ns: dict[str, int] = {}
        self._last_pivot_ns: Optional[int] = None   # newest pivot stamp already decided
        self._anchor_ns: Optional[int] = None       # start of the rate limiter's periods
        self._last_period: Optional[int] = None

    def reset(self) -> None:
        """Forget every buffered message and the rate limiter (counters are kept)."""
        self._clear_timeline()

    def add(self, stream: str, stamp_ns: int, value: object) -> list[SyncedSet]:
        """Add one message; return the sets it completed that pass the rate limit (oldest first).

        Messages of streams that are not required are ignored.
        """
        if stream not in self._queues:
            return []
        stamp_ns = int(stamp_ns)
        # A time jump is a stream going back on itself; a message merely arriving later than
        # other streams' newer ones (network or DDS delay) is not one.
        previous = self._stream_newest_ns.get(stream)
        if previous is not None and stamp_ns < previous - self._reset_jump_ns:
            self.resets += 1
            logger.warning(
                "time went backwards by %.3f s on stream %r (bag loop or clock jump): synchroniser reset",
                (previous - stamp_ns) / NS_PER_S, stream)
            self._clear_timeline()
        if previous is None or stamp_ns > previous:
            self._stream_newest_ns[stream] = stamp_ns
        if stream == self.pivot and self._last_pivot_ns is not None and stamp_ns <= self._last_pivot_ns:
            self._drop("late", stream, f"{stream} message stamped {stamp_ns / NS_PER_S:.3f} s is not after the "
                                       f"last one decided ({self._last_pivot_ns / NS_PER_S:.3f} s)")
            return []
        if self._queues[stream].insert(stamp_ns, value):
            self._drop("queue_full", stream, self._queue_full_detail(stream))
        return self._process(final=False)

    def _drop(self, reason: str, stream: str, detail: str) -> None:
        self.dropped[reason] += 1
        if self._on_drop is not None:
            self._on_drop(reason, stream, detail)

    def _queue_full_detail(self, stream: str) -> str:
        """Why ``stream``'s queue overflowed: the stream furthest behind and by how much."""
        newest = self._stream_newest_ns
        text = (f"{stream} queue full ({self.params.queue_size} messages): its oldest message was dropped "
                f"while waiting for the other streams")
        # A queue fills only while another stream holds the pivot back: there is one to name.
        laggard = min((s for s in self.streams if s != stream), key=lambda s: newest.get(s, -1))
        if laggard not in newest:
            return f"{text}; {laggard} has sent nothing yet"
        return (f"{text}; {laggard} is {(newest[stream] - newest[laggard]) / NS_PER_S:.2f} s behind "
                f"(a silent stream, or a reliable topic waiting for a DDS repair)")

    def flush(self) -> list[SyncedSet]:
        """End of input: decide the pending sets with the messages at hand and return the emitted ones."""
        out = self._process(final=True)
        self._clear_timeline()
        return out

    # Internals ---------------------------------------------------------------------------------

    def _match(self, stream: str, ref_ns: int, final: bool) -> tuple[bool, int]:
        """(decided, index of the match or -1) of ``stream`` for the reference stamp ``ref_ns``."""
        q = self._queues[stream]
        i = bisect.bisect_left(q.stamps, ref_ns)   # first message at or after ref
        decided = final or i < len(q.stamps)
        best, best_dt = -1, None
        for j in (i - 1, i):
            if 0 <= j < len(q.stamps):
                dt = abs(q.stamps[j] - ref_ns)
                if dt <= self._tolerance_ns and (best_dt is None or dt < best_dt):
                    best, best_dt = j, dt
        return decided, best

    def _process(self, final: bool) -> list[SyncedSet]:
        out: list[SyncedSet] = []
        pivot_q = self._queues[self.pivot]
        while pivot_q.stamps:
            ref_ns = pivot_q.stamps[0]
            matches: dict[str, int] = {}
            undecided = False
            missing = None
            for s in self.streams:
                if s == self.pivot:
                    continue
                decided, j = self._match(s, ref_ns, final)
                if not decided:
                    # A later message of this stream may still be (or be nearer) a match: wait.
                    undecided = True
                    break
                if j < 0:
                    # A gap in this stream: the pivot message cannot form a set.
                    missing = s
                    break
                matches[s] = j
            if undecided:
                break
            value = pivot_q.values[0]
            pivot_q.drop_before(ref_ns + 1)
            self._last_pivot_ns = ref_ns
            if missing is not None:
                self._drop("unmatched", missing, f"no {missing} message within {self._tolerance_ns / NS_PER_S:g} s of the "
                                                 f"{self.pivot} message stamped {ref_ns / NS_PER_S:.3f} s")
                continue
            values = {self.pivot: value}
            stamps = {self.pivot: ref_ns}
            for s, j in matches.items():
                q = self._queues[s]
                values[s], stamps[s] = q.values[j], q.stamps[j]
                # Older messages can no longer be the nearest to a later pivot.
                q.drop_before(q.stamps[j])
            if self._rate_allows(ref_ns):
                self.emitted += 1
                out.append(SyncedSet(ref_ns, values, stamps))
            else:
                self.dropped["rate_limited"] += 1
        return out

    def _rate_allows(self, stamp_ns: int) -> bool:
        """Rate limit (module doc): the first complete set of each period passes."""
        if self._period_ns == 0:
            return True
        if self._anchor_ns is None:
            self._anchor_ns = stamp_ns
        period = (stamp_ns - self._anchor_ns) // self._period_ns
        if self._last_period is not None and period <= self._last_period:
            return False
        self._last_period = period
        return True
