"""The running node fed bad input interleaved with good frames (issue 15: cases 4-6, 8 and the fuzz).

Real rclpy publishers in one process (the harness of ``test_node.py``). Every bad input must be
dropped with one log line per (topic, reason) and counted on ``info``; the node stays alive and
every good frame around the bad ones is mapped.
"""

from __future__ import annotations

import random
from datetime import datetime, timedelta

import numpy as np
import pytest

pytest.importorskip("rclpy")

from rtabmap_ros2.core.database import Database  # noqa: E402
from rtabmap_ros2.ros import conversions as conv  # noqa: E402
from rtabmap_ros2.ros.node import new_backup_path  # noqa: E402
from test_node import TIMEOUT_S, Harness, frames, wait_for  # noqa: E402,F401 - frames is a fixture

pytestmark = pytest.mark.ros

DOMAIN_ID = random.randint(100, 199)
MS = 1_000_000
# Bad inputs between two good frames (1 s apart) are stamped this far apart after the first one.
BAD_STAMP_STEP_NS = 200 * MS


def _messages(frame, stamp):
    """The five messages of a good frame at ``stamp`` (rgb as bgr8, depth as 16UC1)."""
    return {
        "camera_info": conv.camera_info_to_msg(frame.camera, stamp, "camera_optical"),
        "odom": conv.odometry_to_msg(frame.T_odom_base, stamp, covariance=frame.odom_covariance),
        "scan": conv.scan_to_msg(frame.scan, stamp, "laser"),
        "depth": conv.depth_to_msg(frame.depth_m, stamp, "camera_optical"),
        "rgb": conv.image_to_msg(frame.rgb, stamp, "camera_optical", "bgr8"),
    }


def _bad_inputs(frame):
    """(name, expected (topic, reason), function stamp -> {stream: message}) for each kind of bad input.

    A bad single message is published alone (its set never completes); a bad *frame* (each
    message fine on its own, the set unusable) is published as a full set.
    """
    def alone(stream, mutate):
        def make(stamp):
            msgs = _messages(frame, stamp)
            mutate(msgs[stream])
            return {stream: msgs[stream]}
        return make

    def full_set(stream, replace):
        def make(stamp):
            msgs = _messages(frame, stamp)
            msgs[stream] = replace(stamp, msgs[stream])
            return msgs
        return make

    def encoding(m):
        m.encoding = "yuv444"   # yuv422 is read (issue 13)

    def short(m):
        m.data = bytes(m.data)[: len(m.data) // 2]

    def huge_claimed(m):
        m.width, m.height, m.step = 100_000, 100_000, 300_000

    def bad_step(m):
        m.step = m.width   # bgr8 needs 3 bytes per pixel

    def empty_frame_id(m):
        m.header.frame_id = ""

    def zero_intrinsics(m):
        m.k = np.zeros(9)

    def nan_odom(m):
        m.pose.pose.position.x = float("nan")

    def zero_quaternion(m):
        q = m.pose.pose.orientation
        q.x = q.y = q.z = q.w = 0.0

    def inf_depth(stamp, m):
        return conv.depth_to_msg(np.full_like(frame.depth_m, np.inf), stamp, "camera_optical", "32FC1")

    def nan_depth(stamp, m):
        return conv.depth_to_msg(np.full_like(frame.depth_m, np.nan), stamp, "camera_optical", "32FC1")

    def zero_depth(stamp, m):
        return conv.depth_to_msg(np.zeros_like(frame.depth_m), stamp, "camera_optical", "16UC1")

    def other_aspect_depth(stamp, m):
        # Half the size would be registered by scaling (issue 13); another aspect ratio cannot be.
        return conv.depth_to_msg(np.ascontiguousarray(frame.depth_m[:, :400]), stamp, "camera_optical")

    def huge_rgb(stamp, m):
        return conv.image_to_msg(np.zeros((1500, 2000, 3), np.uint8), stamp, "camera_optical", "bgr8")

    def empty_scan(m):
        m.ranges = []

    def nan_scan(m):
        m.ranges = [float("nan")] * len(m.ranges)

    def one_return_scan(stamp, m):
        ranges = np.full(len(frame.scan.ranges), np.inf, np.float32)
        ranges[0] = 2.0
        scan = conv.scan_to_msg(frame.scan, stamp, "laser")
        scan.ranges = ranges.tolist()
        return scan

    return [
        ("wrong encoding", ("/rgb/image", "encoding"), alone("rgb", encoding)),
        ("short data", ("/rgb/image", "short_data"), alone("rgb", short)),
        ("huge image size with little data", ("/rgb/image", "short_data"), alone("rgb", huge_claimed)),
        ("step smaller than a row", ("/rgb/image", "bad_step"), alone("rgb", bad_step)),
        ("empty frame_id", ("/scan", "empty_frame_id"), alone("scan", empty_frame_id)),
        ("zero intrinsics", ("/rgb/camera_info", "invalid_intrinsics"), alone("camera_info", zero_intrinsics)),
        ("NaN odometry", ("/odom", "non_finite_pose"), alone("odom", nan_odom)),
        ("zero quaternion", ("/odom", "invalid_quaternion"), alone("odom", zero_quaternion)),
        ("empty scan", ("/scan", "empty_scan"), alone("scan", empty_scan)),
        ("all-NaN scan", ("/scan", "no_valid_scan"), alone("scan", nan_scan)),
        ("inf depth", ("/depth/image", "inf_depth"), full_set("depth", inf_depth)),
        ("all-NaN depth (32FC1)", ("/depth/image", "no_valid_depth"), full_set("depth", nan_depth)),
        ("all-zero depth (16UC1)", ("/depth/image", "no_valid_depth"), full_set("depth", zero_depth)),
        ("depth size differs from rgb", ("/depth/image", "size_mismatch"), full_set("depth", other_aspect_depth)),
        ("huge rgb image", ("/depth/image", "size_mismatch"), full_set("rgb", huge_rgb)),
        ("one return in a scan", ("/scan", "no_valid_scan"), full_set("scan", one_return_scan)),
    ]


@pytest.fixture
def fuzz_harness(context, tmp_path):
    # Every synchronised set is processed (no detection-rate limit), so a bad set just before a
    # good frame cannot hide it.
    h = Harness(context, tmp_path, detection_rate=0.0)
    yield h
    h.close()


def _inject(harness, msgs: dict, key: tuple[str, str]) -> None:
    """Publish bad messages and wait until the node has dropped them under ``key``."""
    node, t = harness.node, harness.tester
    before = node.bad_messages.get(key, 0)
    for stream, msg in msgs.items():
        t.pubs[stream].publish(msg)
    assert wait_for(lambda: node.bad_messages.get(key, 0) > before), (key, node.bad_messages)


def test_fuzzed_node_stays_alive_logs_each_reason_once_and_maps_every_good_frame(fuzz_harness, frames, capfd,
                                                                                   tmp_path):
    harness = fuzz_harness
    node = harness.node
    bad = _bad_inputs(frames[0])
    expected: dict[tuple[str, str], int] = {}
    good_infos = [harness.feed(frames[0])]
    k = 0   # next bad input
    for previous, frame in zip(frames, frames[1:]):
        for j in range(3):
            if k == len(bad) + 2:
                break
            if k < len(bad):
                _, key, make = bad[k]
                msgs = make(previous.stamp_ns + (j + 1) * BAD_STAMP_STEP_NS)
            else:   # time going back on odometry, then on the scan (sub-second: not a clock reset)
                stream = "odom" if k == len(bad) else "scan"
                key = (f"/{stream}", "stamp_not_increasing")
                msgs = {stream: _messages(previous, previous.stamp_ns - 3 * BAD_STAMP_STEP_NS)[stream]}
            _inject(harness, msgs, key)
            expected[key] = expected.get(key, 0) + 1
            k += 1
        good_infos.append(harness.feed(frame))
    assert k == len(bad) + 2, "too few frames to interleave every bad input"
    # The inf depth is dropped on arrival, so the synchroniser finds no depth for its RGB image
    # (the other depth faults are found after synchronisation, in the frame).
    expected[("/depth/image", "sync_unmatched")] = 1

    # Alive, every good frame mapped, every bad input dropped and counted under its reason.
    assert [int(i["location_id"]) > 0 for i in good_infos] == [True] * len(frames)
    assert node.frames_processed == len(frames) and node.frames_dropped == 0
    assert dict(node.bad_messages) == expected
    last = good_infos[-1]
    for (topic, reason), count in expected.items():
        assert int(last[f"node_dropped:{topic}:{reason}"]) == count
    assert int(last["node_dropped_messages"]) == sum(expected.values())
    t = harness.tester
    assert wait_for(lambda: len(t.last("mapPath").poses) == int(last["local_map_size"]))
    ids = {int(i["location_id"]) for i in good_infos}

    # One log line per (topic, reason), however many times it happened.
    err = capfd.readouterr().err
    for topic, reason in expected:
        lines = [line for line in err.splitlines() if f"dropped bad input on {topic} [{reason}]" in line]
        assert len(lines) == 1, (topic, reason, lines)
    assert "Traceback" not in err

    # The database holds every good frame's location (the node flushes it at shutdown).
    harness.close()
    harness.close = lambda: None
    with Database(tmp_path / "rtabmap.db", read_only=True) as db:
        nodes = db.load_nodes()
    assert ids <= set(nodes) and len(nodes) == len(ids)


def test_two_reasons_on_one_topic_are_both_logged(fuzz_harness, frames, capfd):
    """Issue 15 case 6: the second, different fault on a topic was invisible."""
    harness = fuzz_harness
    harness.feed(frames[0])
    f = frames[1]
    nan_depth = conv.depth_to_msg(np.full_like(f.depth_m, np.nan), f.stamp_ns, "camera_optical", "32FC1")
    msgs = _messages(f, f.stamp_ns)
    _inject(harness, {**msgs, "depth": nan_depth}, ("/depth/image", "no_valid_depth"))
    wrong = conv.depth_to_msg(f.depth_m, frames[2].stamp_ns, "camera_optical")
    wrong.encoding = "8UC3"
    _inject(harness, {"depth": wrong}, ("/depth/image", "encoding"))
    info = harness.feed(frames[3])
    assert int(info["node_dropped:/depth/image:no_valid_depth"]) == 1
    assert int(info["node_dropped:/depth/image:encoding"]) == 1
    err = capfd.readouterr().err
    assert "[no_valid_depth]" in err and "[encoding]" in err and "8UC3" in err


def test_backup_skips_a_symlink_planted_at_its_name(fuzz_harness, frames, tmp_path):
    """Issue 15 case 8: the predictable backup name, planted as a dangling symlink, is never followed."""
    harness = fuzz_harness
    harness.feed(frames[0])
    db_path = tmp_path / "rtabmap.db"
    stolen = tmp_path / "stolen"
    stolen.mkdir()
    now = datetime.now()
    planted = [new_backup_path(db_path, now + timedelta(seconds=s)) for s in range(-1, int(TIMEOUT_S))]
    for i, path in enumerate(planted):
        path.symlink_to(stolen / f"{i}.db")
    harness.tester.call("backup")
    assert list(stolen.iterdir()) == []
    backups = [p for p in tmp_path.glob("rtabmap-backup-*.db") if not p.is_symlink()]
    assert len(backups) == 1 and backups[0].name.endswith("-1.db")
    with Database(backups[0], read_only=True) as copy:
        assert len(copy.load_nodes()) == 1
