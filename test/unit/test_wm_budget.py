"""The WM cap of SLAM mode (core/wm_budget.py), fed processing times directly."""

from __future__ import annotations

from rtabmap_ros2.core.params import Params
from rtabmap_ros2.core.wm_budget import WorkingMemoryBudget


def budget(*overrides: str) -> WorkingMemoryBudget:
    return WorkingMemoryBudget(Params().with_overrides(["memory.time_threshold_ms=100", *overrides]).memory)


def test_no_cap_until_a_frame_takes_longer_than_t_time():
    wm = budget()
    for size in range(1000):
        wm.observe(99.0, 50.0, size)
    assert wm.cap() is None


def test_a_frame_over_t_time_caps_wm_where_it_would_have_taken_the_target_time():
    wm = budget("memory.time_target_ratio=0.8")
    wm.observe(125.0, 125.0, 1000)  # 1000 x 80 / 125
    assert wm.cap() == 640
    wm.observe(110.0, 110.0, 640)  # a second frame over T_time lowers the cap again, never raises it
    assert wm.cap() == 465


def test_a_cap_halves_wm_at_most_at_once():
    wm = budget()
    wm.observe(1000.0, 1000.0, 1000)  # a one-off 10x frame
    assert wm.cap() == 500


def test_the_cap_rises_by_its_growth_per_frame_under_the_target_time_only():
    wm = budget("memory.time_target_ratio=0.8", "memory.wm_cap_growth=1")
    wm.observe(200.0, 200.0, 800)
    assert wm.cap() == 400
    for _ in range(10):
        wm.observe(50.0, 50.0, 400)
    for _ in range(10):
        wm.observe(90.0, 90.0, 410)  # between the target and T_time: holds
    assert wm.cap() == 410


def test_memory_thr_is_a_fixed_cap_with_or_without_t_time():
    assert budget("Rtabmap/MemoryThr=300").cap() == 300
    wm = WorkingMemoryBudget(Params().with_overrides(["memory.time_threshold_ms=0", "Rtabmap/MemoryThr=300"]).memory)
    wm.observe(10_000.0, 10_000.0, 5000)
    assert wm.cap() == 300
    wm = budget("Rtabmap/MemoryThr=300")
    wm.observe(200.0, 200.0, 400)  # learnt cap 200 < 300
    assert wm.cap() == 200


def test_the_cap_regrows_slower_than_the_robot_adds_locations_by_default():
    wm = budget()
    wm.observe(200.0, 200.0, 800)
    for _ in range(100):
        wm.observe(50.0, 50.0, 400)
    assert 400 < wm.cap() <= 450


def test_only_the_part_of_the_time_that_grows_with_wm_is_scaled():
    wm = budget("memory.time_target_ratio=0.8")
    wm.observe(120.0, 80.0, 1000)  # fixed 40 ms: 1000 x (80 - 40) / 80
    assert wm.cap() == 500
    wm = budget("memory.time_target_ratio=0.8")
    wm.observe(120.0, 100.0, 1000)  # 1000 x (80 - 20) / 100
    assert wm.cap() == 600


def test_a_frame_over_t_time_by_its_fixed_part_alone_sets_no_cap():
    """A cold start's first ICP (0.17 s at 19 locations): a smaller WM would not have helped."""
    wm = budget()
    wm.observe(183.0, 16.0, 19)
    assert wm.cap() is None


def test_the_cap_never_regrows_above_the_largest_wm_that_went_over_t_time():
    wm = budget("memory.time_target_ratio=0.8", "memory.wm_cap_growth=1")
    wm.observe(110.0, 110.0, 1000)  # cap 727, ceiling 1000
    for _ in range(500):
        wm.observe(50.0, 50.0, 900)
    assert wm.cap() == 1000
    wm.observe(120.0, 120.0, 900)  # over again at 900: the cap comes down, the ceiling stays
    assert wm.cap() == 600
    for _ in range(500):
        wm.observe(50.0, 50.0, 850)
    assert wm.cap() == 1000
