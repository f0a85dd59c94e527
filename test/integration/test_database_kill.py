"""A writer process SIGKILLed mid-mapping leaves a database holding every committed frame.

A child Python process writes one WriteBatch per "frame" (a location with its words, images,
links and statistics row) and prints the frame index once the commit has returned (directly, or
after ``BackgroundWriter.join()``). The parent kills it with SIGKILL after frame N, reopens the
database and checks that SQLite finds it sound and that every reported frame is there, whole.
"""

from __future__ import annotations

import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest

from rtabmap_ros2.core.database import Database

KILL_AFTER_FRAME = 30
WORDS_PER_FRAME = 100
CHILD_TIMEOUT_S = 60.0
KILL_DELAYS_S = (0.0, 0.25)  # after frame N: the later kill lands after (or during) WAL checkpoints

CHILD = textwrap.dedent("""
    import sys
    import numpy as np
    from rtabmap_ros2.core.database import BackgroundWriter, Database, SensorBlobs, WriteBatch
    from rtabmap_ros2.core.graph import Link, LinkType
    from rtabmap_ros2.core.signature import Signature

    path, mode, words_per_frame = sys.argv[1], sys.argv[2], int(sys.argv[3])
    JOIN_EVERY = 3  # background mode: frames submitted between two joins
    rng = np.random.default_rng(0)
    db = Database(path)
    writer = BackgroundWriter(db) if mode == "background" else None
    rgb = rng.integers(0, 256, (120, 160, 3), dtype=np.uint8)
    depth = rng.uniform(0.5, 4.0, (120, 160)).astype(np.float32)
    blobs = SensorBlobs.encode(rgb, depth)
    unjoined = []
    frame = 0
    while True:  # until killed
        frame += 1
        first = 1 + (frame - 1) * words_per_frame
        word_ids = np.arange(first, first + words_per_frame, dtype=np.int64)
        sig = Signature(id=frame, map_id=0, stamp_ns=frame * 10**9, word_ids=word_ids,
                        keypoints=rng.uniform(0, 100, (words_per_frame, 2)).astype(np.float32),
                        points3d=rng.normal(size=(words_per_frame, 3)).astype(np.float32), T_odom_base=np.eye(4))
        batch = WriteBatch(locations=[(sig, blobs)],
                           words={int(w): rng.integers(0, 256, 32, dtype=np.uint8) for w in word_ids},
                           links=[Link(frame - 1, frame, LinkType.NEIGHBOR)] if frame > 1 else [],
                           weights={frame - 1: frame} if frame > 1 else {},
                           statistics=[{"frame_index": frame, "location_id": frame}])
        if writer is None:
            db.write(batch)
            print(frame, flush=True)
        else:
            writer.submit(batch)
            unjoined.append(frame)
            if len(unjoined) == JOIN_EVERY:
                writer.join()
                print("\\n".join(map(str, unjoined)), flush=True)
                unjoined.clear()
""")


def run_and_kill(path: Path, mode: str, delay_s: float) -> int:
    """Start the child, SIGKILL it ``delay_s`` after it reported frame KILL_AFTER_FRAME.

    Returns the last frame the child reported committed (including reports printed during the
    delay, read after the kill).
    """
    child = subprocess.Popen([sys.executable, "-c", CHILD, str(path), mode, str(WORDS_PER_FRAME)],
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    last = 0
    try:
        for line in child.stdout:
            last = int(line)
            if last >= KILL_AFTER_FRAME:
                break
        time.sleep(delay_s)  # the child keeps writing: the kill lands anywhere in a transaction
    finally:
        child.send_signal(signal.SIGKILL)
        child.wait(timeout=CHILD_TIMEOUT_S)
    reported_later = [int(line) for line in child.stdout.read().split()]
    last = max([last, *reported_later])
    assert child.returncode == -signal.SIGKILL, child.stderr.read()
    assert last >= KILL_AFTER_FRAME, f"child stopped early: {child.stderr.read()}"
    return last


@pytest.mark.parametrize("delay_s", KILL_DELAYS_S)
@pytest.mark.parametrize("mode", ["direct", "background"])
def test_sigkill_keeps_every_committed_frame(tmp_path, mode, delay_s):
    path = tmp_path / "map.db"
    last_reported = run_and_kill(path, mode, delay_s)

    with Database(path) as db:
        assert db.integrity_check() == ["ok"]
        nodes = db.load_nodes()
        frames = sorted(nodes)
        # Every frame reported committed is there; frames are whole (one transaction each), so
        # what is present is a prefix 1..K (K may exceed the last report: killed after a commit).
        assert frames == list(range(1, len(frames) + 1))
        assert len(frames) >= last_reported
        stats = db.load_statistics()
        assert [s["frame_index"] for s in stats] == frames
        assert db.max_word_id() == len(frames) * WORDS_PER_FRAME
        assert len(db.load_links()) == len(frames) - 1
        last = db.load_signature(frames[-1])
        assert last.word_ids.shape == (WORDS_PER_FRAME,)
        assert db.load_sensor_blobs(frames[-1]).depth_m().shape == (120, 160)
        # Weights updated in a later frame's batch are present exactly when that frame is.
        assert [nodes[i].weight for i in frames[:-1]] == [i + 1 for i in frames[:-1]]
        ids, descriptors = db.load_descriptors()
        assert np.array_equal(ids, np.arange(1, len(frames) * WORDS_PER_FRAME + 1))
        assert descriptors.shape == (ids.size, 32)
        # Mapping continues after the crash.
        assert db.max_location_id() == frames[-1]
