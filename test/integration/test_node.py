"""The ``rtabmap`` node with real rclpy (Fast DDS): in one process, and as a subprocess.

A small simulated session (``rtabmap_ros2.sim``) is converted to messages and published frame by
frame; each frame waits for its ``info`` so the tests are deterministic (no timing assertions).
"""

from __future__ import annotations

import contextlib
import random
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

rclpy = pytest.importorskip("rclpy")

from diagnostic_msgs.msg import DiagnosticArray  # noqa: E402
from nav_msgs.msg import OccupancyGrid, Odometry  # noqa: E402
from nav_msgs.msg import Path as PathMsg  # noqa: E402
from nav_msgs.srv import GetMap  # noqa: E402
from rclpy.executors import MultiThreadedExecutor  # noqa: E402
from rclpy.node import Node  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy  # noqa: E402
from sensor_msgs.msg import CameraInfo, Image, LaserScan  # noqa: E402
from std_srvs.srv import Empty, Trigger  # noqa: E402
from visualization_msgs.msg import MarkerArray  # noqa: E402

from rtabmap_ros2.errors import RtabmapError  # noqa: E402
from rtabmap_ros2.ros import conversions as conv  # noqa: E402
from rtabmap_ros2.ros.executor import NodeExecutor  # noqa: E402
from rtabmap_ros2.ros.node import (  # noqa: E402
    FRAME_QUEUE_SIZE, RtabmapNode, checked_export_path, new_export_folder)

from ros_spin import SPIN_WAIT_S, spinning  # noqa: E402

pytestmark = pytest.mark.ros

DOMAIN_ID = random.randint(1, 99)
N_FRAMES = 14
# Frame queue size in the burst test (the node's own, FRAME_QUEUE_SIZE, is larger).
QUEUE_UNDER_TEST = 10
TIMEOUT_S = 30.0
RELIABLE = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
LATCHED = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)


@pytest.fixture(scope="module")
def frames():
    """The first frames of the small simulation's two sessions (RGB-D, scan, odometry)."""
    sim = pytest.importorskip("rtabmap_ros2.sim")
    world = sim.build_world(seed=0)
    sessions = sim.make_sessions(world, small=True, sessions=1)
    return [sim.render_frame(world, sessions[0], i) for i in range(N_FRAMES)]


class SensorRig(Node):
    """Publishes sensor messages to the node under test and records what it publishes."""

    def __init__(self, context):
        super().__init__("rtabmap_tester", context=context)
        self.pubs = {
            "odom": self.create_publisher(Odometry, "odom", RELIABLE),
            "scan": self.create_publisher(LaserScan, "scan", RELIABLE),
            "rgb": self.create_publisher(Image, "rgb/image", RELIABLE),
            "depth": self.create_publisher(Image, "depth/image", RELIABLE),
            "camera_info": self.create_publisher(CameraInfo, "rgb/camera_info", RELIABLE),
        }
        self.received: dict[str, list] = {"mapPath": [], "map": [], "mapGraph": [], "info": []}
        self.lock = threading.Lock()
        self.subs = {topic: self.create_subscription(msg_type, topic, self._recorder(topic), qos)
                     for topic, msg_type, qos in (("mapPath", PathMsg, 10), ("map", OccupancyGrid, LATCHED),
                                                  ("mapGraph", MarkerArray, 10), ("info", DiagnosticArray, 10))}
        self.clients_ = {}

    def connected(self) -> bool:
        """Discovery done both ways: the node subscribes to every sensor topic and publishes every
        topic recorded here (a volatile message published before that is lost to the recorder)."""
        return (all(p.get_subscription_count() > 0 for p in self.pubs.values())
                and all(s.get_publisher_count() > 0 for s in self.subs.values()))

    def _recorder(self, topic):
        def record(msg):
            with self.lock:
                self.received[topic].append(msg)
        return record

    def count(self, topic: str) -> int:
        with self.lock:
            return len(self.received[topic])

    def last(self, topic: str):
        with self.lock:
            return self.received[topic][-1]

    def infos(self) -> list[dict[str, str]]:
        with self.lock:
            return [conv.statistics_from_msg(m) for m in self.received["info"]]

    def publish_frame(self, frame, stamp_ns=None, skip=(), encoding="bgr8", depth_m=None):
        stamp = frame.stamp_ns if stamp_ns is None else stamp_ns
        msgs = {
            "camera_info": conv.camera_info_to_msg(frame.camera, stamp, "camera_optical"),
            "odom": conv.odometry_to_msg(frame.T_odom_base, stamp, covariance=frame.odom_covariance),
            "scan": conv.scan_to_msg(frame.scan, stamp, "laser"),
            "depth": conv.depth_to_msg(frame.depth_m if depth_m is None else depth_m, stamp, "camera_optical"),
            "rgb": conv.image_to_msg(frame.rgb, stamp, "camera_optical", encoding),
        }
        for name, msg in msgs.items():
            if name not in skip and name in self.pubs:
                self.pubs[name].publish(msg)

    def call(self, name: str, srv_type=Empty, timeout: float = TIMEOUT_S):
        client = self.clients_.get(name)
        if client is None:
            client = self.clients_[name] = self.create_client(srv_type, name)
        assert client.wait_for_service(timeout_sec=timeout), f"service {name} not available"
        future = client.call_async(srv_type.Request())
        assert wait_for(future.done, timeout), f"service {name} did not answer"
        return future.result()


def wait_for(condition, timeout: float = TIMEOUT_S) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if condition():
            return True
        time.sleep(0.02)
    return bool(condition())


class Harness:
    def __init__(self, context, tmp_path: Path, **overrides):
        params = {"database_path": str(tmp_path / "rtabmap.db"), "export_dir": str(tmp_path / "exports"),
                  "qos": "reliable", **overrides}
        self.node = RtabmapNode(context=context, parameter_overrides=[Parameter(k, value=v) for k, v in params.items()])
        self.tester = SensorRig(context)
        if overrides.get("subscribe_scan") is False:   # a robot without a laser
            self.tester.destroy_publisher(self.tester.pubs.pop("scan"))
        self.executor = NodeExecutor(num_threads=4, context=context)
        self.executor.add_node(self.node)
        self.executor.add_node(self.tester)
        self._spinning = contextlib.ExitStack()
        self._spinning.enter_context(spinning(self.executor))
        assert wait_for(self.tester.connected)

    def feed(self, frame, stamp_ns=None, **publish) -> dict[str, str]:
        """Publish one frame and wait until the node reports it on info."""
        before = self.tester.count("info")
        self.tester.publish_frame(frame, stamp_ns, **publish)
        assert wait_for(lambda: self.tester.count("info") > before), "no info for a published frame"
        return self.tester.infos()[-1]

    def close(self):
        self._spinning.close()
        self.node.destroy_node()
        self.tester.destroy_node()


@pytest.fixture
def harness(context, tmp_path):
    h = Harness(context, tmp_path)
    yield h
    h.close()


# -- parameters and export paths (no messages) ---------------------------------------------------
def test_parameters_are_declared_with_descriptions(harness):
    node = harness.node
    for name in ("database_path", "frame_id", "map_frame_id", "odom_frame_id", "detection_rate", "approx_sync",
                 "sync_queue_size", "export_dir", "delete_db_on_start", "memory.stm_size", "bayes.loop_threshold"):
        assert node.has_parameter(name), name
    assert not node.has_parameter("sync.rate_hz")   # declared once, as detection_rate
    assert node.get_parameter("detection_rate").value == 1.0
    assert "Short-Term Memory" in node.describe_parameter("memory.stm_size").description
    assert "[Hz]" in node.describe_parameter("detection_rate").description


def test_parameter_overrides_reach_the_core(context, tmp_path):
    node = RtabmapNode(context=context, parameter_overrides=[
        Parameter("database_path", value=str(tmp_path / "o.db")), Parameter("memory.stm_size", value=7),
        Parameter("detection_rate", value=2), Parameter("subscribe_scan", value=False)])
    try:
        assert node.params.memory.stm_size == 7 and node.params.sync.rate_hz == 2.0
        assert "scan" not in node._topics and node._sync.streams == {"odom", "rgb", "depth"}
    finally:
        node.destroy_node()


def test_export_folders_are_new_and_stay_inside(tmp_path):
    from datetime import datetime

    now = datetime(2026, 11, 3, 14, 5, 9)
    a = new_export_folder(tmp_path, now)
    b = new_export_folder(tmp_path, now)
    assert a.name == "20261103-140509" and b.name == "20261103-140509-1" and a.is_dir() and b.is_dir()
    with pytest.raises(RtabmapError, match="outside"):
        checked_export_path(tmp_path, "../elsewhere")
    (tmp_path / "20261103-140509-2").symlink_to(tmp_path.parent)
    assert new_export_folder(tmp_path, now).name == "20261103-140509-3"   # the symlink is not reused
    with pytest.raises(RtabmapError, match="outside"):
        checked_export_path(tmp_path, "20261103-140509-2/x")


# -- mapping ---------------------------------------------------------------------------------------
def test_mapping_publishes_path_map_graph_info(harness, frames):
    infos = [harness.feed(f) for f in frames]
    assert [int(i["location_id"]) > 0 for i in infos] == [True] * len(frames)
    assert all(float(i["node_latency_ms"]) >= 0 for i in infos)
    # The worker's time on this frame, by part, and its total; the publisher's last round beside it
    # (none before its first round).
    worker = ("wait", "process", "local_map")
    for info in infos:
        times = {part: float(info[f"node_time_ms/{part}"]) for part in worker}
        assert all(ms >= 0 for ms in times.values()) and times["process"] > 0
        assert float(info["node_time_ms/total"]) == pytest.approx(sum(times.values()), abs=0.01)
    assert not any(k.startswith("node_time_ms/path") for k in infos[0])
    for info in infos[1:]:
        assert all(float(info[f"node_time_ms/{part}"]) >= 0 for part in ("path", "markers", "tf", "info"))
    assert any("node_time_ms/local_grid" in info and "node_time_ms/map" in info for info in infos)
    t = harness.tester
    assert wait_for(lambda: t.count("mapPath") >= len(frames) and t.count("mapGraph") >= len(frames))
    path = t.last("mapPath")
    assert path.header.frame_id == "map" and len(path.poses) == int(infos[-1]["local_map_size"]) >= 2
    # No loop closure in these first frames: the newest pose is the odometry pose (map = odom).
    newest = conv.pose_from_msg(path.poses[-1].pose)
    np.testing.assert_allclose(newest[:2, 3], frames[-1].T_odom_base[:2, 3], atol=0.05)
    graph = {m.ns: m for m in t.last("mapGraph").markers}
    assert len(graph["nodes"].points) == len(path.poses)
    assert len(graph["neighbor_links"].points) == 2 * (len(path.poses) - 1)
    assert wait_for(lambda: t.count("map") > 0)
    grid, resolution, _ = conv.grid_from_msg(t.last("map"))
    assert resolution == pytest.approx(0.05)
    assert (grid == 100).any() and (grid == 0).any() and (grid == -1).any()
    assert harness.node.frames_dropped == 0 and not harness.node.bad_messages


def _hold_worker(node) -> threading.Event:
    """Keep the node's worker busy (a command waiting on the returned event) until it is set."""
    release, started = threading.Event(), threading.Event()

    def busy():
        started.set()
        release.wait()

    def hold():
        try:
            node._in_worker(busy, "held by the test")
        except RtabmapError:   # service_timeout_s passed: the command still holds the worker
            pass
    threading.Thread(target=hold, daemon=True).start()
    assert started.wait(TIMEOUT_S)
    return release


def test_frames_completed_together_are_all_processed(harness, frames):
    """Sets that complete at once (a reliable transport repairing a lost sample releases the ones held
    behind it) wait in the frame queue instead of replacing each other; past its size the oldest go."""
    node, t = harness.node, harness.tester
    assert QUEUE_UNDER_TEST < FRAME_QUEUE_SIZE
    node.frame_queue_size = QUEUE_UNDER_TEST   # fewer frames to make than the node's own size
    burst = frames[:QUEUE_UNDER_TEST + 2]
    assert len(burst) == QUEUE_UNDER_TEST + 2, "N_FRAMES too small for this test"
    release = _hold_worker(node)
    try:
        for i, f in enumerate(burst, 1):
            # One set at a time: the synchroniser's own queues (sync_queue_size) are not under test.
            t.publish_frame(f)
            assert wait_for(lambda: node._sync.emitted == i), node._sync.dropped
    finally:
        release.set()   # a held worker would block the harness's shutdown
    assert wait_for(lambda: t.count("info") == QUEUE_UNDER_TEST)
    assert node.frames_processed == QUEUE_UNDER_TEST and node.frames_dropped == 2
    # The newest frames are kept, in order.
    stamps = [m.header.stamp for m in t.received["info"]]
    assert stamps == [conv.header(f.stamp_ns, "map").stamp for f in burst[2:]]
    assert not node.messages_lost   # reliable, in one process: nothing lost in transport


def test_frames_arriving_fast_are_all_processed_into_the_map_the_core_makes_alone(context, tmp_path, frames):
    """Sets completing faster than the worker processes them (features extracted ahead by the frame
    queue's thread, the maps published beside the worker) are all processed, in order, into the same
    map as the core makes of the same frames one by one: the threads change the timing, not the map."""
    from rtabmap_ros2.core.rtabmap import Rtabmap

    # No time-driven memory management: the same frames must make the same map on a loaded machine.
    h = Harness(context, tmp_path, **{"memory.time_threshold_ms": 0.0})
    node, t = h.node, h.tester
    seen = []
    process = node._core.process

    def recorded(frame, **kwargs):
        seen.append(frame)
        return process(frame, **kwargs)

    node._core.process = recorded
    try:
        for i, f in enumerate(frames, 1):
            t.publish_frame(f)   # the next set as soon as this one is synchronised, not processed
            assert wait_for(lambda: node._sync.emitted == i), node._sync.dropped
        assert wait_for(lambda: t.count("info") == len(frames))
        infos = t.infos()
        assert node.frames_processed == len(frames) and node.frames_dropped == 0
        assert [m.header.stamp for m in t.received["info"]] == [conv.header(f.stamp_ns, "map").stamp for f in frames]
        assert wait_for(lambda: t.count("mapPath") and len(t.last("mapPath").poses) == int(infos[-1]["local_map_size"]))
        path = np.stack([conv.pose_from_msg(p.pose) for p in t.last("mapPath").poses])
    finally:
        h.close()
    with Rtabmap(node.params, tmp_path / "alone.db") as alone:
        stats = [alone.process(f) for f in seen]
        local = alone.local_map()
    assert [s.location_id for s in stats] == [int(i["location_id"]) for i in infos]
    assert [s.merged_id for s in stats] == [int(i["merged_id"]) for i in infos]
    np.testing.assert_allclose(path, np.stack([local.poses[n] for n in sorted(local.poses)]), atol=1e-9)


def test_first_frame_waits_for_a_late_camera_info(harness, frames):
    """Callbacks of one instant run in any order: a driver's first camera_info may come just after
    its images. The set it completes is held for it, not dropped; only a set replaced while waiting is."""
    node, t = harness.node, harness.tester
    t.publish_frame(frames[0], skip=("camera_info",))
    assert wait_for(lambda: node._sync.emitted == 1)
    t.publish_frame(frames[1], skip=("camera_info",))   # replaces the held set: frame 0 is lost
    assert wait_for(lambda: node._sync.emitted == 2)
    assert t.count("info") == 0 and node.bad_messages == {("/rgb/camera_info", "no_camera_info"): 1}
    t.pubs["camera_info"].publish(conv.camera_info_to_msg(frames[1].camera, frames[1].stamp_ns, "camera_optical"))
    assert wait_for(lambda: t.count("info") == 1)
    assert t.received["info"][0].header.stamp == conv.header(frames[1].stamp_ns, "map").stamp
    assert int(harness.feed(frames[2])["location_id"]) > 0


def test_map_is_latched_for_late_subscribers(harness, frames, context):
    for f in frames[:3]:
        harness.feed(f)
    late = Node("late_subscriber", context=context)
    got = []
    late.create_subscription(OccupancyGrid, "map", got.append, LATCHED)
    harness.executor.add_node(late)
    try:
        assert wait_for(lambda: len(got) == 1)
    finally:
        harness.executor.remove_node(late)
        # The spin thread may be building a wait set with the node's subscription right now:
        # destroyed under it, rclpy raises InvalidHandle in that thread. A few spin rounds later
        # its wait sets no longer hold the node.
        time.sleep(4 * SPIN_WAIT_S)
        late.destroy_node()


def test_pause_resume_trigger_new_map_and_reset(harness, frames):
    t, node = harness.tester, harness.node
    first = [harness.feed(f) for f in frames[:4]]
    t.call("pause")
    processed = node.frames_processed
    for f in frames[4:6]:
        t.publish_frame(f)
    time.sleep(1.0)   # give the paused node the chance to (wrongly) process them
    assert node.frames_processed == processed and t.count("info") == len(first)
    t.call("resume")
    resumed = harness.feed(frames[6])
    assert int(resumed["location_id"]) > int(first[-1]["location_id"])

    t.call("trigger_new_map")
    new_map = harness.feed(frames[7])
    assert int(new_map["map_id"]) == int(resumed["map_id"]) + 1

    t.call("reset")
    assert wait_for(lambda: len(t.last("mapPath").poses) == 0)   # the reset map is published empty
    after = harness.feed(frames[8])
    assert int(after["location_id"]) == 1 and int(after["map_id"]) == 0
    assert len(t.last("mapPath").poses) == 1


def test_an_odometry_reset_with_its_first_frames_lost_starts_a_new_map(harness, frames):
    # A second recording played two minutes after the first: its odometry restarted at frame 8
    # (identity there), but frames 8 and 9 never arrived; the first one received is 1 m away
    # from the new origin. The core sees the reset (a move across a silence), not the node.
    from dataclasses import replace

    from rtabmap_ros2.sim.robot import reset_odometry

    first = [harness.feed(f) for f in frames[:6]]
    restarted = reset_odometry(np.stack([f.T_odom_base for f in frames]), 8)
    later = 120 * 10**9
    second = [harness.feed(replace(f, T_odom_base=restarted[i], stamp_ns=f.stamp_ns + later))
              for i, f in enumerate(frames[10:13], start=10)]
    assert {int(i["map_id"]) for i in first} == {0}
    assert [int(i["map_id"]) for i in second] == [1, 1, 1]
    assert [i["new_map"] for i in second] == ["true", "false", "false"]


def test_localization_mode_adds_no_node(harness, frames):
    t = harness.tester
    for f in frames[:5]:
        harness.feed(f)
    t.call("set_mode_localization")
    nodes_before = len(t.last("mapPath").poses)
    info = harness.feed(frames[5])
    assert int(info["location_id"]) == 0
    assert len(t.last("mapPath").poses) == nodes_before
    t.call("set_mode_mapping")
    assert int(harness.feed(frames[6])["location_id"]) > 0


def test_frames_of_a_robot_that_did_not_move_add_no_node_with_rgbd_linear_update(context, tmp_path, frames, capfd):
    """-p RGBD/LinearUpdate:=0.1 (RTAB-Map's): the same pose again half a second later adds no node,
    says so on info and in the node's closing line; the next frame, 0.5 m on, is a node."""
    h = Harness(context, tmp_path, **{"RGBD/LinearUpdate": 0.1, "detection_rate": 0.0})
    try:
        assert int(h.feed(frames[0])["location_id"]) > 0
        info = h.feed(frames[0], stamp_ns=frames[0].stamp_ns + 500_000_000)
        assert int(info["location_id"]) == 0 and info["small_displacement"] == "true", info
        assert int(h.feed(frames[1])["location_id"]) > 0
        assert h.node.frames_not_moved == 1
    finally:
        h.close()
    assert "1 not added: the robot moved less than RGBD/LinearUpdate" in capfd.readouterr().err


def test_backup_service_copies_the_database(harness, frames, tmp_path):
    for f in frames[:3]:
        harness.feed(f)
    harness.tester.call("backup")
    backups = list(tmp_path.glob("rtabmap-backup-*.db"))
    assert len(backups) == 1 and backups[0].stat().st_size > 0
    from rtabmap_ros2.core.database import Database

    db = Database(backups[0], read_only=True)
    try:
        assert len(db.load_nodes()) >= 1
    finally:
        db.close()


def test_global_map_services(harness, frames, tmp_path):
    pytest.importorskip("rtabmap_ros2.core.global_map")
    pytest.importorskip("rtabmap_ros2.io.export")
    t = harness.tester
    for f in frames[:6]:
        harness.feed(f)
    response = t.call("export_global_map", Trigger)
    assert response.success, response.message
    folder = Path(response.message)
    assert folder.parent == (tmp_path / "exports").resolve()
    assert (folder / "poses.txt").is_file() and (folder / "graph.g2o").is_file()
    second = t.call("export_global_map", Trigger)
    assert second.success and Path(second.message) != folder   # a new folder per call
    grid = t.call("get_map", GetMap).map
    assert grid.info.width > 0 and grid.header.frame_id == "map"
    paths_before = t.count("mapPath")
    t.call("publish_map")
    assert wait_for(lambda: t.count("mapPath") > paths_before)
    assert len(t.last("mapPath").poses) >= len(frames[:6]) // 2


def test_a_camera_only_robot_gets_its_map_grid_from_the_depth_images(context, tmp_path, frames):
    """No laser (subscribe_scan false): the live grid on ``map`` is drawn from the nodes' depth images,
    walls occupied and the floor before them free, and ``get_map`` builds the global one from them."""
    harness = Harness(context, tmp_path, subscribe_scan=False)
    try:
        infos = [harness.feed(f) for f in frames[:6]]
        assert all(int(i["location_id"]) > 0 for i in infos)
        t = harness.tester
        assert wait_for(lambda: t.count("map") > 0)
        grid, resolution, _ = conv.grid_from_msg(t.last("map"))
        assert resolution == pytest.approx(0.05)
        assert (grid == 100).sum() > 20 and (grid == 0).sum() > 100 and (grid == -1).any()
        global_grid = t.call("get_map", GetMap).map
        assert global_grid.info.width > 1 and global_grid.info.height > 1
        data = np.asarray(global_grid.data)
        assert (data == 100).any() and (data == 0).any()
        assert harness.node.frames_dropped == 0 and not harness.node.bad_messages
    finally:
        harness.close()


def test_bad_messages_are_dropped_and_the_node_keeps_running(harness, frames):
    t, node = harness.tester, harness.node
    harness.feed(frames[0])
    f = frames[1]
    stamp = f.stamp_ns
    bad_rgb = conv.image_to_msg(f.rgb, stamp, "c")
    bad_rgb.encoding = "yuv444"
    t.pubs["rgb"].publish(bad_rgb)
    t.pubs["depth"].publish(conv.depth_to_msg(np.full_like(f.depth_m, np.inf), stamp, "c", "32FC1"))
    empty_scan = conv.scan_to_msg(f.scan, stamp, "laser")
    empty_scan.ranges = []
    t.pubs["scan"].publish(empty_scan)
    nan_odom = conv.odometry_to_msg(f.T_odom_base, stamp)
    nan_odom.pose.pose.position.x = float("nan")
    t.pubs["odom"].publish(nan_odom)
    t.pubs["odom"].publish(conv.odometry_to_msg(f.T_odom_base, frames[0].stamp_ns - 500_000_000))  # backwards
    # Another aspect ratio than the RGB image: not registrable by scaling (half size would be registered).
    small_depth = conv.depth_to_msg(np.ascontiguousarray(f.depth_m[:, :400]), frames[2].stamp_ns, "c")
    t.publish_frame(frames[2], skip=("depth",))
    t.pubs["depth"].publish(small_depth)
    expected = {("/rgb/image", "encoding"), ("/depth/image", "inf_depth"), ("/scan", "empty_scan"),
                ("/odom", "non_finite_pose"), ("/odom", "stamp_not_increasing"), ("/depth/image", "size_mismatch")}
    assert wait_for(lambda: set(node.bad_messages) >= expected), node.bad_messages
    assert node.bad_messages[("/odom", "stamp_not_increasing")] == 1
    assert node.frames_processed == 1
    info = harness.feed(frames[3])   # still alive
    assert int(info["location_id"]) > 0


def test_silent_topics_are_reported_once(context, tmp_path, frames, capfd):
    h = Harness(context, tmp_path, topic_timeout_s=1.0)
    try:
        deadline = time.monotonic() + 3.5
        while time.monotonic() < deadline:   # only odometry arrives
            h.tester.pubs["odom"].publish(conv.odometry_to_msg(np.eye(4), time.time_ns()))
            time.sleep(0.1)
        assert h.node._silence_warned == {"scan", "rgb", "depth", "camera_info"}
        # The synchroniser's odometry queue overflowed waiting for the others: counted, said once.
        assert h.node.bad_messages[("/odom", "sync_queue_full")] >= 15
    finally:
        h.close()
    err = capfd.readouterr().err
    warnings = [line for line in err.splitlines() if "no message for" in line]
    assert len(warnings) == 1, err
    assert "/scan" in warnings[0] and "receiving: /odom" in warnings[0]
    overflow = [line for line in err.splitlines() if "[sync_queue_full]" in line]
    assert len(overflow) == 1 and "has sent nothing yet" in overflow[0] and "heartbeat" in overflow[0], err


def test_a_topic_subscribed_late_is_not_reported_silent_before_it_had_time(context, tmp_path, frames, capfd):
    """With qos auto a stream is subscribed when its publisher appears (under load, seconds after the
    node started): its silence counts from that subscription, not from the node's start (issue 50:
    /rgb/camera_info reported silent for 5 s while it had been subscribed for less)."""
    timeout = 2.0
    h = Harness(context, tmp_path, qos="auto", topic_timeout_s=timeout)
    late = Node("late_camera_driver", context=context)
    h.executor.add_node(late)
    try:
        start = h.node._start_time
        camera_pub = None
        f = frames[0]
        while time.monotonic() - start < timeout + 1.5:
            age = time.monotonic() - start
            if camera_pub is None and age >= timeout - 0.4:   # the driver's camera_info appears late...
                camera_pub = late.create_publisher(CameraInfo, "rgb/camera_info", RELIABLE)
            stamp = time.time_ns()
            for name in ("odom", "scan", "rgb", "depth"):
                msg = {"odom": lambda: conv.odometry_to_msg(f.T_odom_base, stamp),
                       "scan": lambda: conv.scan_to_msg(f.scan, stamp, "laser"),
                       "rgb": lambda: conv.image_to_msg(f.rgb, stamp, "camera_optical", "bgr8"),
                       "depth": lambda: conv.depth_to_msg(f.depth_m, stamp, "camera_optical")}[name]()
                h.tester.pubs[name].publish(msg)
            if camera_pub is not None and age >= timeout + 0.6:   # ...and publishes a moment after
                camera_pub.publish(conv.camera_info_to_msg(f.camera, stamp, "camera_optical"))
            time.sleep(0.1)
        assert "camera_info" in h.node.subscriptions_.current
        assert wait_for(lambda: "camera_info" in h.node._last_arrival)
        assert "camera_info" not in h.node._silence_warned
        # What the node logged while the streams ran; once they stop (the teardown below can take
        # seconds on a loaded machine) a warning of silence would be right.
        assert "no message for" not in capfd.readouterr().err
    finally:
        h.executor.remove_node(late)
        time.sleep(4 * SPIN_WAIT_S)
        late.destroy_node()
        h.close()


# -- across processes ------------------------------------------------------------------------------

@contextlib.contextmanager
def spinning_rig(context, proc: subprocess.Popen):
    """A SensorRig spun in a background executor next to a node process; the process is killed on exit if still running."""
    tester = SensorRig(context)
    executor = MultiThreadedExecutor(num_threads=2, context=context)
    executor.add_node(tester)
    try:
        with spinning(executor):
            yield tester
    finally:
        if proc.poll() is None:
            proc.kill()
        tester.destroy_node()


def test_node_subprocess_sigterm_flushes_database(ros_env, context, tmp_path, frames):
    db_path = tmp_path / "proc.db"
    proc = subprocess.Popen(
        [sys.executable, "-m", "rtabmap_ros2.ros.node", "--ros-args", "-p", f"database_path:={db_path}",
         "-p", "qos:=reliable", "-p", f"export_dir:={tmp_path / 'exports'}"],
        env=ros_env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    with spinning_rig(context, proc) as tester:
        assert wait_for(tester.connected, 60)
        for i, f in enumerate(frames[:5]):
            tester.publish_frame(f)
            if not wait_for(lambda: tester.count("info") > i, 60):  # a loaded machine: the subprocess starts cold
                proc.kill()
                pytest.fail(f"subprocess node did not report frame {i}; its output:\n{proc.communicate()[0]}")
        last_id = int(tester.infos()[-1]["location_id"])
        proc.send_signal(signal.SIGTERM)
        out, _ = proc.communicate(timeout=60)
    assert proc.returncode == 0, out
    assert "flushed and closed" in out
    from rtabmap_ros2.core.database import Database

    db = Database(db_path, read_only=True)
    try:
        nodes = db.load_nodes()
    finally:
        db.close()
    assert last_id in nodes and len(nodes) >= 2


# -- issue 13: RTAB-Map names, QoS auto, a worker that survives, services with a timeout --------------
def test_rtabmap_named_parameters_take_effect(context, tmp_path, frames, capfd):
    """-p Mem/STMSize:=3 (also as a string) reaches the core; an unknown Group/Name is named with the
    closest known one; Mem/IncrementalMemory:=false starts in localization mode."""
    h = Harness(context, tmp_path, **{"Mem/STMSize": "3", "Rtabmap/LoopThr": 0.2, "Mem/STMSiz": 4})
    try:
        assert h.node.params.memory.stm_size == 3 and h.node._core.params.memory.stm_size == 3
        assert h.node.params.bayes.loop_threshold == pytest.approx(0.2)
        assert h.node.get_parameter("Mem/STMSize").value == "3"
        infos = [h.feed(f) for f in frames[:6]]
        assert [int(i["stm_size"]) for i in infos] == [1, 2, 3, 3, 3, 3]   # the STM holds 3 nodes
    finally:
        h.close()
    err = capfd.readouterr().err
    assert "unknown RTAB-Map parameter Mem/STMSiz" in err and "did you mean Mem/STMSize?" in err, err

    h = Harness(context, tmp_path / "loc", **{"Mem/IncrementalMemory": "false"})
    try:
        assert h.node._core.localization_mode
        assert int(h.feed(frames[0])["location_id"]) == 0   # localization: no node added
    finally:
        h.close()


def test_qos_auto_follows_the_publishers(context, tmp_path):
    from rclpy.qos import qos_profile_sensor_data

    h = Harness(context, tmp_path, qos="auto")
    node, subs = h.node, h.node.subscriptions_
    extra = Node("best_effort_driver", context=context)
    try:
        # The rig's publishers are reliable: so is the subscription (every message, repaired if lost).
        assert wait_for(lambda: all(subs.current.get(s, (None, None))[1] == ReliabilityPolicy.RELIABLE
                                    for s in ("odom", "scan", "rgb", "depth", "camera_info")))
        assert subs.current["rgb"][0].topic == "/rgb/image"   # raw published, not compressed
        # A best-effort publisher appears on scan: the subscription is recreated best effort (else it
        # would not match that publisher); the others stay.
        extra.create_publisher(LaserScan, "scan", qos_profile_sensor_data)
        assert wait_for(lambda: subs.current["scan"][1] == ReliabilityPolicy.BEST_EFFORT)
        assert subs.current["odom"][1] == ReliabilityPolicy.RELIABLE
        scan_subs = [s for s in node.subscriptions if s.topic_name == "/scan"]
        assert len(scan_subs) == 1 and scan_subs[0].qos_profile.reliability == ReliabilityPolicy.BEST_EFFORT
    finally:
        extra.destroy_node()
        h.close()


def test_unexpected_error_in_a_frame_is_logged_once_and_the_node_goes_on(harness, frames, capfd):
    node = harness.node
    process = node._core.process
    failures = []

    def flaky(frame, **kwargs):
        if len(failures) < 2:   # the first two frames hit a bug deep in the core
            failures.append(frame.stamp_ns)
            return np.linalg.inv(np.zeros((3, 3)))
        return process(frame, **kwargs)

    node._core.process = flaky
    harness.tester.publish_frame(frames[0])
    harness.tester.publish_frame(frames[1])
    assert wait_for(lambda: sum(node.frame_errors.values()) == 2), node.frame_errors
    info = harness.feed(frames[2])   # still processing
    assert int(info["location_id"]) > 0 and info["node_frame_errors"] == "2"
    assert list(node.frame_errors) == [next(iter(node.frame_errors))] and "LinAlgError" in next(iter(node.frame_errors))
    err = capfd.readouterr().err
    assert err.count("unexpected LinAlgError") == 1 and "Traceback" in err, err


def test_services_answer_while_the_worker_is_busy(context, tmp_path, frames, capfd):
    h = Harness(context, tmp_path, service_timeout_s=1.0)
    try:
        h.feed(frames[0])
        release = _hold_worker(h.node)
        try:
            h.tester.call("backup")   # answers (Empty) although the worker is held
            response = h.tester.call("export_global_map", Trigger)
            assert not response.success and "did not answer within 1 s" in response.message, response.message
            assert not release.is_set()
        finally:
            release.set()
        info = h.feed(frames[1])   # the worker goes on
        assert int(info["location_id"]) > 0
        assert not list(tmp_path.glob("rtabmap-backup-*.db"))   # the timed-out backup was cancelled
    finally:
        h.close()
    assert "service backup failed" in capfd.readouterr().err


FATAL_NODE = """
import sys
from rtabmap_ros2.core.rtabmap import Rtabmap
from rtabmap_ros2.errors import DatabaseError

def process(self, frame, **kwargs):
    raise DatabaseError("write to database failed: database or disk is full")

Rtabmap.process = process   # the disk fills up at the first frame
from rtabmap_ros2.ros.node import main
main(sys.argv[1:])
"""


def test_unrecoverable_error_ends_the_process_non_zero(ros_env, context, tmp_path, frames):
    from rtabmap_ros2.ros.node import EXIT_UNRECOVERABLE

    proc = subprocess.Popen(
        [sys.executable, "-c", FATAL_NODE, "--ros-args", "-p", f"database_path:={tmp_path / 'full.db'}",
         "-p", "qos:=reliable", "-p", f"export_dir:={tmp_path / 'exports'}"],
        env=ros_env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    with spinning_rig(context, proc) as tester:
        assert wait_for(tester.connected, 60)
        # Published again until the process ends: a frame sent while discovery is still completing
        # on the node's side can be lost (seen once in CI, the process then waited for input).
        for attempt in range(30):
            tester.publish_frame(frames[0], stamp_ns=frames[0].stamp_ns + attempt)
            if wait_for(lambda: proc.poll() is not None, 2):
                break
        out, _ = proc.communicate(timeout=60)
    assert proc.returncode == EXIT_UNRECOVERABLE, out
    assert "unrecoverable error" in out and "disk is full" in out


def test_a_shutdown_landing_mid_wait_ends_the_spin_as_an_external_shutdown():
    """The worker's unrecoverable error shuts the context down from its thread; if that lands while
    the executor builds its wait set, rclpy raises RCLError, not ExternalShutdownException (seen in
    CI under load: the process then ended with a traceback and status 1, not EXIT_UNRECOVERABLE).
    After a shutdown any error of the spin is that shutdown; before it, an error is an error."""
    import rclpy
    from rclpy.executors import ExternalShutdownException

    from rtabmap_ros2.ros.node import _spin

    class WaitSetFails:
        def spin(self):
            raise RuntimeError("failed to initialize wait set: the given context is not valid")

    context = rclpy.Context()
    rclpy.init(context=context)
    with pytest.raises(RuntimeError, match="wait set"):
        _spin(WaitSetFails(), context)
    context.try_shutdown()
    with pytest.raises(ExternalShutdownException):
        _spin(WaitSetFails(), context)


@pytest.mark.parametrize("encoding", ["rgba8", "bgra8", "mono16", "bayer_rggb8", "bayer_grbg16", "yuv422", "yuyv"])
def test_drivers_encodings_are_mapped(harness, frames, encoding):
    """Frames whose colour image comes in each encoding drivers publish (and a depth image at half the
    RGB resolution, registered by scaling) are processed: nodes with visual words."""
    half_depth = np.ascontiguousarray(frames[1].depth_m[::2, ::2])
    infos = [harness.feed(frames[0], encoding=encoding), harness.feed(frames[1], encoding=encoding,
                                                                      depth_m=half_depth)]
    assert all(int(i["location_id"]) > 0 for i in infos) and int(infos[0]["words_added"]) > 0, infos
    assert not harness.node.bad_messages and not harness.node.frame_errors
