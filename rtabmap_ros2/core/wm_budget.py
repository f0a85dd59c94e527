"""How many locations WM may hold for a frame to stay under T_time (memory management, SLAM mode).

The 2013 paper transfers locations WM -> LTM when a frame takes longer than T_time (Alg. 4), as
many as came in (RTAB-Map's Memory::forget: one more). That bounds WM when every frame costs in
proportion to WM, as the paper's did. Here most SLAM frames extend the local map by a leaf
(constant time, see LocalMapper._leaf_update) and only some re-solve it, in time proportional to the
local map; and the local map itself jumps from one session's nodes to all of WM when a loop
closure merges two maps. So frames under T_time kept adding locations, the few over it let out
three, and WM grew without bound (10,000 frames: WM 9,971 of 10,338, pTime p99 990 ms at T_time
350 ms). So, besides Alg. 4, :class:`WorkingMemoryBudget` caps WM at the smaller of:

* the learnt cap: a frame over T_time caps WM at the size it would have taken
  ``time_target_ratio`` x T_time at, the part of its time that grows with WM (quantisation over
  the vocabulary, the Bayes filter, the local map optimisation) taken as proportional to WM and
  the rest as fixed (at most halving WM at once; no cap when the fixed part alone is over the
  target: a cold start's first ICP took 0.17 s at 19 locations, and capping WM there starved it
  for the whole run); the cap rises by ``wm_cap_growth`` locations per frame under that time, never
  above the largest WM a frame went over T_time at. Without that ceiling WM regrew between two such
  frames, up to 2,750 locations on the 10,000-frame run, and RSS followed its high-water mark;
  with the smallest such WM as the ceiling, every slow frame of another kind (a retrieval) lowered
  it for good, down to WM 660 and few merges by session 15. The frames
  that exceed T_time are rare kinds (a merge, a rejected loop closure: 2-4x an ordinary
  re-solve per node), so WM must not regrow much between two of them: at one location per
  frame (as fast as the robot adds them) WM had grown 50-100 % past the last cap when the next
  one came, and that frame took 1.5-2.4x T_time (10,000 frames, T_time 0.2 s); at 0.1 WM
  stayed so small that fewer loop closures were found (5 sessions at T_time 0.1 s: ATE 0.042 m,
  0.017 m at 0.3 and 1);
* ``max_wm_size`` (RTAB-Map's Rtabmap/MemoryThr), a fixed cap.

(Predicting the cap instead, from the recent re-solves' cost per local map node, was tried: a
re-solve's cost per node varies 4x with its iterations and robust passes, so a cap from the
typical cost let merges exceed T_time and a cap from the worst cost shrank WM until a session
no longer merged: 2 components on the 5-session demo at T_time 0.1 s.)

Appearance-only frames teach it nothing: their time is proportional to WM, the paper's setting,
where Alg. 4 alone bounds WM (2013 Table III).
"""

from __future__ import annotations

from typing import Optional

from rtabmap_ros2.core.params import MemoryParams


class WorkingMemoryBudget:
    """Cap on the number of locations in WM, learnt from the SLAM frames' processing times."""

    def __init__(self, params: MemoryParams) -> None:
        self.params = params
        self._learnt: Optional[float] = None
        self._ceiling: Optional[int] = None  # the largest WM a frame went over T_time at

    def over(self, process_ms: float) -> bool:
        """True when a frame took longer than T_time (never without T_time)."""
        threshold = self.params.time_threshold_ms
        return threshold > 0 and process_ms > threshold

    def observe(self, process_ms: float, scaling_ms: float, wm_size: int) -> None:
        """Account for one processed SLAM frame: ``process_ms`` of which ``scaling_ms`` grow with
        WM, ``wm_size`` locations in WM."""
        if self.params.time_threshold_ms <= 0:
            return
        target_ms = self.params.time_target_ratio * self.params.time_threshold_ms
        fixed_ms = process_ms - scaling_ms
        if self.over(process_ms) and fixed_ms < target_ms and scaling_ms > 0:
            fits = max(int(wm_size * (target_ms - fixed_ms) / scaling_ms), wm_size // 2)
            self._learnt = fits if self._learnt is None else min(self._learnt, fits)
            self._ceiling = wm_size if self._ceiling is None else max(self._ceiling, wm_size)
        elif self._learnt is not None and process_ms < target_ms:
            self._learnt = min(self._learnt + self.params.wm_cap_growth, self._ceiling)

    def cap(self) -> Optional[int]:
        """Most locations WM should hold now (None: no cap)."""
        learnt = int(self._learnt) if self._learnt is not None else None
        caps = [c for c in (learnt, self.params.max_wm_size or None) if c is not None]
        return min(caps) if caps else None
