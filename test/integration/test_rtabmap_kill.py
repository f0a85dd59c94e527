"""An Rtabmap process SIGKILLed mid-run leaves a database that reopens and continues (issue 2).

The child runs ``Rtabmap.process`` over a generated sequence (small STM so locations reach WM,
tiny T_time so transfer writes LTM flags too) and prints each completed frame's location id and
merged id. The parent kills it with SIGKILL after a few frames, then checks SQLite's integrity
check, that every location of a frame completed before the last reported one is stored (the
last frame's writes may still be in the background writer: Alg. 1 joins them at the next
frame), and that Rtabmap reopens the database and continues with larger ids in a new map.
"""

from __future__ import annotations

import signal
import subprocess
import sys
import textwrap

import pytest

from rtabmap_ros2.core.database import Database
from rtabmap_ros2.core.params import Params
from rtabmap_ros2.core.rtabmap import Rtabmap
from rtabmap_ros2.core.sensor import SensorFrame
from rtabmap_ros2.sim.sequence import make_sequence

KILL_AFTER_FRAMES = 12
CHILD_TIMEOUT_S = 300.0

CHILD = textwrap.dedent("""
    import sys
    from rtabmap_ros2.core.params import Params
    from rtabmap_ros2.core.rtabmap import Rtabmap
    from rtabmap_ros2.core.sensor import SensorFrame
    from rtabmap_ros2.sim.sequence import make_sequence

    sequence = make_sequence(200, seed=5, segment_length=(10, 20))
    params = Params().with_overrides(["memory.stm_size=3", "memory.time_threshold_ms=5"])
    rtabmap = Rtabmap(params, sys.argv[1], delete_existing=True)
    for i in range(len(sequence)):  # until killed
        s = rtabmap.process(SensorFrame(stamp_ns=(i + 1) * 10**9, rgb=sequence.image(i)), location_id=i + 1)
        print(i + 1, s.location_id, s.merged_id, flush=True)
""")


@pytest.mark.slow
def test_killed_mid_run_database_reopens_with_every_completed_location(tmp_path):
    path = tmp_path / "killed.db"
    child = subprocess.Popen([sys.executable, "-c", CHILD, str(path)], stdout=subprocess.PIPE,
                             stderr=subprocess.PIPE, text=True)
    reported: list[tuple[int, int, int]] = []
    try:
        for line in child.stdout:
            reported.append(tuple(int(v) for v in line.split()))
            if len(reported) >= KILL_AFTER_FRAMES:
                child.send_signal(signal.SIGKILL)
                break
    finally:
        child.kill()
        rest, err = child.communicate(timeout=CHILD_TIMEOUT_S)
    assert len(reported) >= KILL_AFTER_FRAMES, err[-2000:]
    assert child.returncode == -signal.SIGKILL
    reported += [tuple(int(v) for v in line.split()) for line in rest.splitlines() if line.strip()]

    db = Database(path)
    try:
        assert db.integrity_check() == ["ok"]
        nodes = db.load_nodes()
        # Every location created before the last completed frame, and not merged away later.
        merged_away = {merged for _, _, merged in reported if merged}
        expected = {loc for _, loc, _ in reported[:-1] if loc} - merged_away
        assert expected <= set(nodes), sorted(expected - set(nodes))
        # The last completed frame's writes (its new location, the deletion of the location it
        # merged) may still be in the background writer when the kill lands.
        _, last_location, last_merged = reported[-1]
        assert not (merged_away - {last_merged}) & (set(nodes) - {last_location})
        last_id = db.max_location_id()
        map_id = db.max_map_id()
    finally:
        db.close()

    # Reopening continues: WM restored, new map, ids after the last stored one.
    sequence = make_sequence(3, seed=9)
    with Rtabmap(Params(), path) as rtabmap:
        assert len(rtabmap.memory.wm) > 0
        s = rtabmap.process(SensorFrame(stamp_ns=10**12, rgb=sequence.image(0)))
        assert s.location_id == last_id + 1
        assert s.map_id == map_id + 1
