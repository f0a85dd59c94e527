"""What happened to one frame: :class:`Statistics` (one row of ``detections.csv`` and of the
database's statistics table, one ``info`` message) and the per-step timer behind its timings.
pTime (2013 §IV) is ``process_time_ms``: from after feature extraction to before the transfer."""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field

TIMING_KEYS = ("features", "quantization", "rehearsal", "bayes", "verification", "retrieval",
               "optimization", "transfer", "database")


@dataclass
class Statistics:
    """What happened to one frame (one row of ``detections.csv``, one ``info`` message)."""

    frame_index: int
    stamp_ns: int
    location_id: int = 0
    map_id: int = 0
    loop_closure_id: int = 0
    loop_closure_type: str = ""
    rejected_loop_closure_id: int = 0
    proximity_links: int = 0  # loop closures added by proximity detection (graph.proximity_by_space)
    highest_hypothesis_id: int = 0
    highest_hypothesis_value: float = 0.0
    process_time_ms: float = 0.0
    total_time_ms: float = 0.0
    wm_size: int = 0
    stm_size: int = 0
    ltm_size: int = 0
    vocabulary_size: int = 0
    words_added: int = 0
    retrieved: int = 0
    transferred: int = 0
    local_map_size: int = 0
    new_map: bool = False
    merged_id: int = 0
    bad_signature: bool = False
    localized: bool = False
    small_displacement: bool = False  # no node: odometry moved less than graph.linear_update / angular_update
    # Diagnostics of the detection (side by side with RTAB-Map's own statistics, issue 32):
    words_extracted: int = 0  # features of the image (before quantisation)
    rehearsal_similarity: float = 0.0  # Eq. 1 with the previous STM location (0: not compared)
    new_location_probability: float = 1.0  # posterior p(S_t = -1)
    likelihood_nonzero: int = 0  # WM locations with a raw score above 0
    likelihood_mean: float = 0.0  # mean of those raw scores
    likelihood_max: float = 0.0  # largest raw score
    likelihood_std: float = 0.0  # sample standard deviation of the non-zero raw scores (Eq. 3-4's sigma)
    timings_ms: dict[str, float] = field(default_factory=dict)

    def to_dict(self) -> dict:
        """Flat dict (timings as ``time_<step>_ms``) for CSV rows, the database and ``info``."""
        out = asdict(self)
        timings = out.pop("timings_ms")
        out.update({f"time_{k}_ms": round(float(timings.get(k, 0.0)), 3) for k in TIMING_KEYS})
        return out


class Stopwatch:
    """Accumulates named step durations (ms)."""

    def __init__(self) -> None:
        self.ms: dict[str, float] = {}
        self._t = time.perf_counter()

    def lap(self, name: str) -> None:
        now = time.perf_counter()
        self.ms[name] = self.ms.get(name, 0.0) + (now - self._t) * 1000.0
        self._t = now
