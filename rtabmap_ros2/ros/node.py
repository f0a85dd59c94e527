"""The ``rtabmap`` ROS 2 node: subscribe, convert, synchronise, call the core, publish.

Interface (issue 5; relative names, so namespaces and remapping work):

Subscriptions (QoS ``qos``: ``auto`` per topic from its publishers, ``reliable`` or ``sensor_data``;
see :mod:`rtabmap_ros2.ros.subscriptions`)
    ``odom`` (nav_msgs/Odometry), ``scan`` (sensor_msgs/LaserScan), ``rgb/image`` (sensor_msgs/Image:
    rgb8, bgr8, rgba8, bgra8, mono8, mono16, bayer_*, yuv422, yuyv) or ``rgb/image/compressed``,
    ``depth/image`` (16UC1 mm or 32FC1 m) or ``depth/image/compressedDepth`` (``image_transport``
    ``auto``: whichever is published; ``raw``; ``compressed``), ``rgb/camera_info``
    (sensor_msgs/CameraInfo; P's intrinsics when P differs from K). A depth image at another resolution
    than the RGB one (same aspect ratio) is registered by scaling. ``subscribe_scan``,
    ``subscribe_rgb`` (image and camera_info) and ``subscribe_depth`` turn them off.
Sensor mounts and TF (:mod:`rtabmap_ros2.ros.frames`)
    with ``tf2_ros`` importable: ``frame_id`` -> each message's ``header.frame_id`` from tf2 (waiting up
    to ``wait_for_transform``), and ``map_frame_id -> odom_frame_id`` broadcast at ``tf_publish_rate``
    stamped now + ``tf_delay`` (``publish_tf``); without it: ``base_to_laser`` / ``base_to_camera``.
Publications (frame ``map_frame_id``)
    ``mapPath`` (nav_msgs/Path: the optimised local map, the newest when frames come faster than it is
    published), ``map`` (nav_msgs/OccupancyGrid, transient local; at most once per :data:`GRID_PERIOD_S`),
    ``mapGraph`` (visualization_msgs/MarkerArray), ``info`` (diagnostic_msgs/DiagnosticArray, one per
    processed frame: one status ``rtabmap`` whose key/values are the frame's ``Statistics.to_dict()``
    plus the node's ``node_time_ms/<part>`` (the worker's time on this frame by part and ``total``, the
    other threads' last rounds, :mod:`rtabmap_ros2.ros.frame_times`), ``node_latency_ms``, ``node_frames_dropped``,
    ``node_messages_lost``, ``node_paused``, ``node_frame_errors`` and the dropped bad inputs
    ``node_dropped:<topic>:<reason>``, ``node_dropped_messages``), ``localization_pose``
    (geometry_msgs/PoseStamped, localization mode only).
Services
    ``get_map`` (nav_msgs/GetMap), ``export_global_map`` (std_srvs/Trigger), and std_srvs/Empty:
    ``publish_map``, ``reset``, ``pause``, ``resume``, ``trigger_new_map``, ``backup``,
    ``set_mode_localization``, ``set_mode_mapping``.
    Every service answers within ``service_timeout_s``: when the worker is busy longer, with an error
    (Trigger's message, else a log line) instead of waiting.
Parameters
    every field of :class:`~rtabmap_ros2.core.params.Params` (see :mod:`rtabmap_ros2.ros.params`), and
    RTAB-Map's names (``-p Mem/STMSize:=10``); ``Mem/IncrementalMemory:=false`` starts in localization.

Threads (issue 50: the worker does the core's work only). Sensor callbacks (one mutually exclusive
group) convert each message and feed the one :class:`~rtabmap_ros2.core.sync.FrameSynchronizer` (a
message it drops, e.g. when one stream lags seconds behind the others waiting for a DDS repair, is
counted on ``info`` as ``node_dropped:<topic>:sync_<reason>`` and the first of each logged); a completed
set becomes a ``SensorFrame`` put in a :class:`~rtabmap_ros2.ros.frame_queue.FrameQueue` of
:data:`FRAME_QUEUE_SIZE` frames (when it is full the oldest is dropped, counted in ``frames_dropped`` and
on ``info``, and the first drop is logged with the reason), whose own thread extracts the waiting
frames' features ahead. The synchroniser already keeps one set per detection period, so the queue only
absorbs sets that arrive together (a reliable transport repairing a lost sample releases the sets
held behind it at once) instead of dropping all but the newest. One worker thread owns the core
(SQLite connections belong to the thread that opened them): it creates the ``Rtabmap``, runs
``process`` on the queued frames in order with their features, takes a snapshot of the local map and
hands both to the :class:`~rtabmap_ros2.ros.map_publisher.MapPublisher`, whose threads publish every
frame's ``info`` and the newest local map (``mapPath``, ``mapGraph``, TF; the grid on ``map`` at most
once per :data:`GRID_PERIOD_S`) without holding the worker; it also runs the services' core calls
(reset, backup...) handed to it as commands. Services run in their own callback group, so a long
export does not stall the sensors. The map depends on the frames only, not on the threads' timing.
Where each thread's time goes: ``node_time_ms/<part>`` on ``info`` (:mod:`rtabmap_ros2.ros.frame_times`).

Bad input (wrong encoding, short data, sizes that disagree, NaN/inf, depth or scans with (almost)
no valid value, empty frame_id, timestamps going backwards, NaN odometry, a missing transform) is
dropped: logged once per (topic, reason) and counted on ``info`` as ``node_dropped:<topic>:<reason>``
(:mod:`rtabmap_ros2.ros.dropped`).

Errors while processing a frame: any unexpected exception (a gtsam, numpy, sqlite or OpenCV error) is
logged once per kind (type and place) with its traceback, counted in ``frame_errors``, and the frame
dropped; the worker goes on. An unrecoverable one (the database cannot be written: DatabaseError,
sqlite3 errors, a full or read-only disk; MemoryError) is logged, the worker stops and the process
exits with status :data:`EXIT_UNRECOVERABLE`, so a launch file's ``respawn`` restarts the node.

Messages lost in transport (DDS reports gaps in a writer's sequence numbers, the ``message_lost``
event) are counted per topic in ``messages_lost`` and logged once per topic. With best effort
(``qos:=sensor_data``, or ``auto`` facing a best-effort publisher), Fast DDS loses large images under
CPU load even between two processes on one machine (measured by ``bench/bench_node.py``); ``auto``
(the default) subscribes reliably to reliable publishers such as ``rtabmap-ros2 play`` and receives
every frame.

Shutdown: rclpy (7.1) installs handlers for SIGINT and SIGTERM that stop ``spin``; ``main``'s
``finally`` then destroys the node, which joins the worker (finishing the frame in flight) and
flushes and closes the database.
"""

from __future__ import annotations

import errno
import sqlite3
import sys
import threading
import time
import traceback
from collections import deque
from datetime import datetime
from pathlib import Path
from typing import Any, Callable, Optional

import numpy as np
import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped
from nav_msgs.msg import OccupancyGrid as OccupancyGridMsg
from nav_msgs.msg import Odometry, Path as PathMsg
from nav_msgs.srv import GetMap
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.event_handler import SubscriptionEventCallbacks, UnsupportedEventTypeError
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import CameraInfo, CompressedImage, Image, LaserScan
from std_srvs.srv import Empty, Trigger
from visualization_msgs.msg import MarkerArray

from rtabmap_ros2.core.features import FeatureExtractor
from rtabmap_ros2.core.sensor import SensorFrame
from rtabmap_ros2.core.sync import MIN_RESET_JUMP_S, FrameSynchronizer, SyncedSet
from rtabmap_ros2.errors import DatabaseError, RtabmapError, SensorDataError
from rtabmap_ros2.io.bag import register_to_rgb
from rtabmap_ros2.ros import conversions as conv
from rtabmap_ros2.ros.frames import CAMERA, LASER, MapOdomBroadcaster, SensorMounts, import_tf2
from rtabmap_ros2.ros.dropped import DroppedInputs
from rtabmap_ros2.ros.executor import NodeExecutor
from rtabmap_ros2.ros.frame_queue import FrameQueue, QueuedFrame
from rtabmap_ros2.ros.frame_times import CALLBACKS, FrameTimer, FrameTimes
from rtabmap_ros2.ros.map_publisher import MapPublisher, Outputs, Published
from rtabmap_ros2.ros.params import declare_parameters
from rtabmap_ros2.ros.subscriptions import GRAPH_CHECK_PERIOD_S, Candidate, StreamSubscriptions

NODE_NAME = "rtabmap"
NS_PER_S = 1_000_000_000
# Depth of the reliable publishers.
QUEUE_DEPTH = 10
# Exit status of main() after an unrecoverable error (database unwritable): launch's respawn restarts.
EXIT_UNRECOVERABLE = 3
# How often the silent-topic check runs (s).
SILENCE_CHECK_PERIOD_S = 1.0
# Synchronised frames waiting for the worker. A reliable Fast DDS writer resends a lost sample at its
# next heartbeat (every 3 s by default), and the sets held behind it then complete together: stalls
# of 5-6 s were measured (bench_node.py, 2 loaded cores). The worker also falls behind for a few
# frames when a loop closure makes it cast the local grid again: two sessions replayed at 4x
# (bench_node.py, load 5-8 on 2 cores) overflowed 10 frames by 1-4; 30 (about 60 MB of raw
# 640x480 RGB-D) lets it catch up in order. Beyond, the oldest goes (logged once, counted on info).
FRAME_QUEUE_SIZE = 30
# The local occupancy grid is built and published (by the MapPublisher's grid thread, from the newest
# local map) at most once per this period of wall time: just under the default 1 Hz detection
# period, so a 1 Hz robot gets one every frame despite arrival jitter (at 1.0 s, half the frames of a
# 1x replay had none), while a bag replayed at 4x gets one every 3-4 frames (the new scans cast
# together). The grid was the dominant part of the worker's time on info (issue 33) before it left
# the worker (issue 50).
GRID_PERIOD_S = 0.9
# Scans cast into the local grid per update at most (3-15 ms each here, 2 cores, load 1-16): after a
# loop closure moved a large map, the grid around the robot is right first and the rest follows over
# the next updates, instead of one update recasting it all (1-4 s for 700 nodes). The grid thread
# shares the two cores with the worker: 40 a 0.9 s update kept it busy 60 % of the time at load 16
# (issue 50), 16 leaves room for 4x replay's 4 new nodes a second and a loop closure's recasting.
GRID_MAX_CASTS = 16
# Worker wake-up period when idle, so shutdown is noticed (s).
WORKER_POLL_S = 0.1
# Latencies kept for `latencies_s` (benchmarks).
LATENCY_HISTORY = 10000
EXPORT_STAMP_FORMAT = "%Y%m%d-%H%M%S"


class _Command:
    """A core call handed to the worker thread, with its result or error."""

    def __init__(self, fn: Callable[[], Any], name: str = "command") -> None:
        self.fn = fn
        self.name = name
        self._done = threading.Event()
        self._value: Any = None
        self._error: Optional[BaseException] = None
        self._lock = threading.Lock()
        self._state = "queued"   # queued -> running -> done, or queued -> cancelled

    def run(self) -> None:
        with self._lock:
            if self._state == "cancelled":
                return
            self._state = "running"
        try:
            self._value = self.fn()
        except Exception as exc:  # noqa: BLE001 - re-raised in the calling thread
            self._error = exc
        finally:
            self._done.set()

    def result(self, timeout_s: Optional[float] = None) -> Any:
        """The command's value (or its error raised here); RtabmapError after ``timeout_s``.

        A command still queued at the timeout is cancelled (it will not run later); one already
        running finishes in the worker, its result unused.
        """
        if not self._done.wait(timeout_s):
            with self._lock:
                cancelled = self._state == "queued"
                if cancelled:
                    self._state = "cancelled"
            raise RtabmapError(
                f"{self.name}: the rtabmap worker did not answer within {timeout_s:g} s (busy with a frame or "
                f"another command); " + ("not done, try again" if cancelled else "it finishes in the background"))
        if self._error is not None:
            raise self._error
        return self._value


def unrecoverable(exc: BaseException) -> bool:
    """True for errors the node cannot go on after: the database cannot be written (DatabaseError,
    sqlite3 errors), the disk is full or read-only, memory is exhausted."""
    if isinstance(exc, (DatabaseError, sqlite3.Error, MemoryError)):
        return True
    return isinstance(exc, OSError) and exc.errno in (errno.ENOSPC, errno.EROFS, errno.EDQUOT)


def error_kind(exc: BaseException) -> str:
    """``Type at file.py:line`` (the innermost frame): errors of one kind are logged once."""
    frames = traceback.extract_tb(exc.__traceback__)
    where = f" at {Path(frames[-1].filename).name}:{frames[-1].lineno}" if frames else ""
    return f"{type(exc).__name__}{where}"


def new_export_folder(export_dir: str | Path, now: Optional[datetime] = None) -> Path:
    """A new, not yet existing ``export_dir/<YYYYmmdd-HHMMSS[-n]>`` folder (created).

    Raises:
        RtabmapError: the folder would resolve outside ``export_dir`` (e.g. through a symlink).
    """
    root = Path(export_dir).expanduser().resolve()
    root.mkdir(parents=True, exist_ok=True)
    name = (now or datetime.now()).strftime(EXPORT_STAMP_FORMAT)
    candidate, n = root / name, 1
    while candidate.exists() or candidate.is_symlink():
        candidate, n = root / f"{name}-{n}", n + 1
    return checked_export_path(root, candidate, create=True)


def new_backup_path(database_path: Path, now: Optional[datetime] = None) -> Path:
    """A free ``<stem>-backup-<YYYYmmdd-HHMMSS[-n]>.db`` next to ``database_path`` (nothing, not even
    a dangling symlink, at that name)."""
    stamp = (now or datetime.now()).strftime(EXPORT_STAMP_FORMAT)
    name, n = f"{database_path.stem}-backup-{stamp}", 1
    candidate = database_path.with_name(f"{name}.db")
    while candidate.exists() or candidate.is_symlink():
        candidate, n = database_path.with_name(f"{name}-{n}.db"), n + 1
    return candidate


def checked_export_path(export_dir: str | Path, path: str | Path, create: bool = False) -> Path:
    """``path`` resolved, refusing anything that leaves ``export_dir``."""
    root = Path(export_dir).expanduser().resolve()
    resolved = (root / Path(path).expanduser()).resolve()
    if resolved == root or not resolved.is_relative_to(root):
        raise RtabmapError(f"export path {path} resolves to {resolved}, outside export_dir {root}: refused")
    if create:
        resolved.mkdir(parents=False, exist_ok=False)
    return resolved


def _remove_if_empty(folder: Path) -> None:
    try:
        folder.rmdir()
    except OSError:
        pass


def _image_and_bytes(value) -> tuple[Optional[np.ndarray], Optional[bytes]]:
    """A synchronised image stream's value: a raw topic's pixels, or a compressed topic's pixels and
    the bytes the database stores as they came (``conv.compressed_image_and_jpeg`` /
    ``compressed_depth_and_png``; None when they are not what it stores)."""
    return value if isinstance(value, tuple) else (value, None)


class RtabmapNode(Node):
    """The thin ROS 2 layer around :class:`~rtabmap_ros2.core.rtabmap.Rtabmap`."""

    def __init__(self, **node_kwargs: Any) -> None:
        super().__init__(NODE_NAME, **node_kwargs)
        from rtabmap_ros2.core.rtabmap import Rtabmap

        self.params = declare_parameters(self)
        p = self.params.node
        self.database_path = Path(p.database_path).expanduser()
        self.database_path.parent.mkdir(parents=True, exist_ok=True)

        # Bookkeeping read by tests and benchmarks.
        self.frames_processed = 0
        self.frames_dropped = 0          # pushed out of the full frame queue before being processed
        self.rehearsal_merges = 0        # processed frames merged into the previous node (no new node)
        self.frames_not_moved = 0        # processed frames that added no node: RGBD/LinearUpdate, AngularUpdate
        self.dropped = DroppedInputs(self.get_logger())
        self.bad_messages = self.dropped.counts   # (topic, reason) -> dropped inputs
        self.messages_lost: dict[str, int] = {}   # topic -> messages lost in transport (DDS gaps)
        self.latencies_s: deque[float] = deque(maxlen=LATENCY_HISTORY)
        self.frame_times = FrameTimes(LATENCY_HISTORY)   # each thread's time per frame, by part
        self.frame_errors: dict[str, int] = {}   # unexpected errors while processing, per kind
        self.fatal_error: Optional[BaseException] = None
        self.last_statistics = None
        self.paused = False

        # Streams: odometry always; the others per subscribe_*; camera_info is attached, not synced.
        streams = {"odom"}
        if p.subscribe_scan:
            streams.add("scan")
        if p.subscribe_rgb:
            streams.add("rgb")
        if p.subscribe_depth:
            streams.add("depth")
        self._sync = FrameSynchronizer(self.params.sync, streams, on_drop=self._sync_drop)
        self._sync_lock = threading.Lock()
        self._reset_jump_ns = int(max(MIN_RESET_JUMP_S, 1.0 / self.params.sync.rate_hz
                                      if self.params.sync.rate_hz > 0 else 0.0) * NS_PER_S)
        self._last_stamp: dict[str, int] = {}
        self._camera = None
        self._needs_camera = p.subscribe_rgb or p.subscribe_depth
        # The newest set completed before the first camera_info: callbacks of one instant run in any
        # order, so the driver's first camera_info can come just after its images. Held, not dropped.
        self._waiting_for_camera: tuple[SyncedSet, float] | None = None

        # Worker: a bounded queue of frames (oldest dropped when full; features extracted ahead) and the
        # services' commands.
        self._frames = FrameQueue(lambda: FeatureExtractor(self.params.features), FRAME_QUEUE_SIZE, self.frame_times)
        self._commands: list[_Command] = []
        self._worker_lock = threading.Lock()
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._destroyed = False
        self._core = None
        self._worker = threading.Thread(target=self._work, args=(Rtabmap, p.delete_db_on_start),
                                        name="rtabmap_worker", daemon=True)
        self._core_ready = threading.Event()
        self._core_error: Optional[BaseException] = None
        self._worker.start()
        self._core_ready.wait()
        if self._core_error is not None:
            self._stop.set()
            self._frames.stop()
            super().destroy_node()
            raise self._core_error
        self.get_logger().info(f"database {self.database_path} (map {self._core.map_id})")

        self._sensor_group = MutuallyExclusiveCallbackGroup()
        self._service_group = MutuallyExclusiveCallbackGroup()
        tf2 = import_tf2()
        self.mounts = SensorMounts(self, p, tf2)
        self.get_logger().info(self.mounts.describe())
        self.tf_broadcaster = (MapOdomBroadcaster(self, p, tf2, MutuallyExclusiveCallbackGroup())
                               if tf2 is not None and p.publish_tf else None)
        self._subscribe(p)
        self._advertise()

    @property
    def frame_queue_size(self) -> int:
        """Frames waiting for the worker at most (FRAME_QUEUE_SIZE)."""
        return self._frames.size

    @frame_queue_size.setter
    def frame_queue_size(self, size: int) -> None:
        self._frames.size = size

    # -- subscriptions -------------------------------------------------------------------------
    def _subscribe(self, p) -> None:
        self._last_arrival: dict[str, float] = {}
        self._silence_warned: set[str] = set()
        self._start_time = time.monotonic()
        self.subscriptions_ = StreamSubscriptions(self, p.qos, self._create_sensor_subscription,
                                                  self.get_logger().info)
        subs = self.subscriptions_
        subs.add("odom", [Candidate(self.resolve_topic_name("odom"), Odometry, conv.odometry_from_msg)])
        if p.subscribe_scan:
            subs.add("scan", [Candidate(self.resolve_topic_name("scan"), LaserScan, self._scan_from_msg)])
        if p.subscribe_rgb:
            subs.add("rgb", self._image_candidates("rgb/image", "/compressed", conv.image_from_msg,
                                                   conv.compressed_image_and_jpeg, p.image_transport))
            subs.add("camera_info", [Candidate(self.resolve_topic_name("rgb/camera_info"), CameraInfo,
                                               self._camera_from_msg)])
        if p.subscribe_depth:
            subs.add("depth", self._image_candidates("depth/image", "/compressedDepth", conv.depth_from_msg,
                                                     conv.compressed_depth_and_png, p.image_transport))
        subs.refresh()
        if subs.needs_graph:
            self.create_timer(GRAPH_CHECK_PERIOD_S, subs.refresh, callback_group=self._sensor_group)
        self.create_timer(SILENCE_CHECK_PERIOD_S, self._check_silence, callback_group=self._sensor_group)

    @property
    def _topics(self) -> dict[str, str]:
        """Stream -> the topic it is read from (its preferred one until a publisher appears)."""
        return {stream: self.subscriptions_.topic(stream) for stream in self.subscriptions_.candidates}

    def _image_candidates(self, raw: str, suffix: str, raw_convert: Callable, compressed_convert: Callable,
                          transport: str) -> list[Candidate]:
        """raw and/or image_transport's compressed variant of an image topic (the resolved raw name + suffix)."""
        name = self.resolve_topic_name(raw)
        candidates = {"raw": Candidate(name, Image, raw_convert),
                      "compressed": Candidate(name + suffix, CompressedImage, compressed_convert, "compressed")}
        return list(candidates.values()) if transport == "auto" else [candidates[transport]]

    def _scan_from_msg(self, msg: LaserScan):
        T = self.mounts.T_base(LASER, msg.header.frame_id, conv.stamp_to_ns(msg.header.stamp))
        return conv.scan_from_msg(msg, T)

    def _camera_from_msg(self, msg: CameraInfo):
        T = self.mounts.T_base(CAMERA, msg.header.frame_id, conv.stamp_to_ns(msg.header.stamp))
        return conv.camera_model_from_msg(msg, T)

    def _create_sensor_subscription(self, stream: str, candidate: Candidate, qos):
        """A subscription in the sensor group that also reports messages lost in transport."""
        msg_type, topic = candidate.msg_type, candidate.topic
        callback = self._callback(stream, candidate.convert)
        events = SubscriptionEventCallbacks(message_lost=self._lost_callback(topic))
        try:
            sub = self.create_subscription(msg_type, topic, callback, qos, callback_group=self._sensor_group,
                                           event_callbacks=events)
        except UnsupportedEventTypeError:   # an RMW without the message_lost event
            sub = self.create_subscription(msg_type, topic, callback, qos, callback_group=self._sensor_group)
        return sub

    def _lost_callback(self, topic: str) -> Callable:
        def on_lost(info) -> None:
            name = self.resolve_topic_name(topic)
            count = self.messages_lost.get(name, 0) + info.total_count_change
            self.messages_lost[name] = count
            if count == info.total_count_change:
                hint = (" With best effort (qos sensor_data, or auto with a best-effort publisher) large "
                        "messages are lost under load: publish reliably (rtabmap-ros2 play does) with qos auto."
                        if self.params.node.qos != "reliable" else "")
                self.get_logger().warning(f"{info.total_count_change} message(s) lost in transport on {name} "
                                          f"(further losses are counted, not logged).{hint}")
        return on_lost

    def _callback(self, stream: str, convert: Callable) -> Callable:
        def on_message(msg) -> None:
            self._on_message(stream, msg, convert)
        return on_message

    def _on_message(self, stream: str, msg, convert: Callable) -> None:
        timer = FrameTimer()
        with timer.part(stream):
            self._take_message(stream, msg, convert)
        self.frame_times.add(timer, CALLBACKS)

    def _take_message(self, stream: str, msg, convert: Callable) -> None:
        """One sensor message: converted, then fed to the synchroniser (camera_info kept aside)."""
        topic = self.subscriptions_.topic(stream)
        arrival = time.monotonic()
        self._last_arrival[stream] = arrival
        self._silence_warned.discard(stream)
        stamp_ns = conv.stamp_to_ns(msg.header.stamp)
        try:
            conv.frame_id_from_header(msg)
            value = convert(msg)
        except SensorDataError as exc:
            self._bad(topic, exc.reason, str(exc))
            return
        if stream == "camera_info":
            self._camera = value
            if self._waiting_for_camera is not None:
                held, self._waiting_for_camera = self._waiting_for_camera, None
                self._submit(*held)
            return
        last = self._last_stamp.get(stream)
        if last is not None and stamp_ns <= last and last - stamp_ns < self._reset_jump_ns:
            self._bad(topic, "stamp_not_increasing", f"timestamp {stamp_ns / NS_PER_S:.9f} s is not after the previous "
                                      f"{last / NS_PER_S:.9f} s (going backwards or repeated)")
            return
        # A larger jump back is a clock reset or a looping bag: the synchroniser starts a new timeline.
        self._last_stamp[stream] = stamp_ns
        with self._sync_lock:
            sets = self._sync.add(stream, stamp_ns, value)
        for synced in sets:
            self._submit(synced, arrival)

    def _submit(self, synced: SyncedSet, arrival: float) -> None:
        """A synchronised set -> SensorFrame -> the worker's frame queue (oldest dropped when full)."""
        values = synced.values
        rgb, rgb_jpeg = _image_and_bytes(values.get("rgb"))
        depth, depth_png = _image_and_bytes(values.get("depth"))
        frame = SensorFrame(stamp_ns=synced.stamp_ns, rgb=rgb, depth_m=depth, scan=values.get("scan"),
                            rgb_jpeg=rgb_jpeg, depth_png16_mm=depth_png)
        if "odom" in values:
            frame.T_odom_base, frame.odom_covariance = values["odom"]
        if self._needs_camera:
            if self._camera is None:
                if self._waiting_for_camera is not None:   # a newer set replaces it: that one is lost
                    self._bad(self._topics.get("camera_info", "rgb/camera_info"), "no_camera_info",
                              "no camera_info received yet: image frames are dropped until one arrives "
                              "(the newest is held for it)")
                self._waiting_for_camera = (synced, arrival)
                return
            frame.camera = self._camera
        try:
            register_to_rgb(frame).validate(self.params.sync)
        except SensorDataError as exc:
            self._bad_frame(exc)
            return
        if self.paused:
            return
        dropped = self._frames.put(frame, arrival)
        if dropped:
            self.frames_dropped += 1
        self._wake.set()
        if dropped and self.frames_dropped == 1:
            self.get_logger().warning(
                f"frames are being skipped: the worker is slower than the input and its queue of "
                f"{self.frame_queue_size} frames is full, so the oldest is dropped (counted on info as "
                "node_frames_dropped, not logged again; where the worker's time goes: info's "
                "node_time_ms/<part>). Lower sync.rate_hz (detection_rate) or play the bag slower.")

    def _bad(self, topic: str, reason: str, message: str) -> None:
        """Drop a bad input: logged once per (topic, reason), counted on info."""
        self.dropped.drop(topic, reason, message)

    def _sync_drop(self, reason: str, stream: str, detail: str) -> None:
        """A message the synchroniser dropped: counted as ``sync_<reason>`` on the stream's topic."""
        hint = (" If a topic lags by seconds, a lost sample is waiting for its writer's next heartbeat (Fast DDS: "
                "every 3 s by default): raise sync_queue_size or shorten the publishers' heartbeat (docs/node.md, "
                "QoS)." if reason == "queue_full" else "")
        self._bad(self._topics.get(stream, stream), f"sync_{reason}", detail + hint)

    def _bad_frame(self, exc: SensorDataError) -> None:
        """Drop a synchronised frame, counted on the topic of the part at fault (``exc.source``)."""
        self._bad(self._topics.get(exc.source, "synchronised set"), exc.reason, str(exc))

    def _check_silence(self) -> None:
        """Warn once per silence when an expected topic has been quiet for topic_timeout_s.

        Quiet since its last message, or since its subscription was made when none came yet: with qos
        or image_transport ``auto`` a stream is subscribed when its publisher is discovered, which
        under load can be seconds after the node started, and its first messages need the publisher
        to match the new subscription (issue 50: ``/rgb/camera_info`` was reported silent for 5 s
        counted from the node's start while it had been subscribed for less)."""
        timeout = self.params.node.topic_timeout_s
        now = time.monotonic()
        if now - self._start_time < timeout:
            return
        since = self.subscriptions_.since
        quiet = {s: now - max(self._last_arrival.get(s, self._start_time), since.get(s, self._start_time))
                 for s in self._topics if s not in self._silence_warned}
        if not any(q >= timeout for q in quiet.values()):
            return
        # With them, the streams the next check would report (subscribed a moment later): one warning.
        silent = [s for s, q in quiet.items() if q >= timeout - SILENCE_CHECK_PERIOD_S]
        self._silence_warned.update(silent)
        arrived = [s for s in self._topics if now - self._last_arrival.get(s, -1e18) < timeout]
        unpublished = [s for s in silent if s not in self.subscriptions_.current]
        waiting = ("; image frames wait for a camera_info (the newest is held)"
                   if "camera_info" in silent and {"rgb", "depth"} & set(arrived) else "")
        self.get_logger().warning(
            f"no message for {timeout:g} s on {', '.join(self.subscriptions_.topics_text(s) for s in silent)}; "
            f"receiving: {', '.join(self._topics[s] for s in arrived) if arrived else 'nothing'}"
            + (f"; no publisher at all on {', '.join(self.subscriptions_.topics_text(s) for s in unpublished)}"
               if unpublished else "") + waiting
            + ". Check the topic names, remapping, image_transport and QoS (parameter qos: auto, reliable or "
              "sensor_data), or turn the input off (subscribe_*).")

    # -- worker --------------------------------------------------------------------------------
    def _work(self, rtabmap_cls, delete_existing: bool) -> None:
        """The worker thread: owns the core from creation to close."""
        try:
            self._core = rtabmap_cls(self.params, self.database_path, delete_existing=delete_existing)
        except BaseException as exc:  # noqa: BLE001 - handed to __init__, which raises it
            self._core_error = exc
            return
        finally:
            self._core_ready.set()
        if self.params.node.localization:
            self._core.localization_mode = True
            self.get_logger().info("localization mode (Mem/IncrementalMemory false): no node is added to the map")
        try:
            while True:
                self._wake.wait(WORKER_POLL_S)
                self._wake.clear()   # before looking: a frame or command added after is not missed
                with self._worker_lock:
                    commands, self._commands = self._commands, []
                for command in commands:
                    command.run()
                item = self._frames.pop()
                if len(self._frames):
                    self._wake.set()
                if item is not None and not self._stop.is_set():
                    self._process(item)
                if self.fatal_error is not None:
                    break
                if self._stop.is_set():
                    with self._worker_lock:
                        if not self._commands:
                            break
        finally:
            try:
                self._core.close()
            except Exception as exc:  # noqa: BLE001 - already failing (unwritable database); say it, end
                self.get_logger().error(f"closing {self.database_path} failed: {type(exc).__name__}: {exc}")

    def _in_worker(self, fn: Callable[[], Any], name: str = "command") -> Any:
        """Run ``fn`` (a core call) in the worker thread and return its result or raise its error
        (RtabmapError when the worker does not take it within ``service_timeout_s``)."""
        command = _Command(fn, name)
        with self._worker_lock:
            if self.fatal_error is not None:
                raise RtabmapError(f"the rtabmap worker stopped on an unrecoverable error: {self.fatal_error}")
            if self._stop.is_set() or not self._worker.is_alive():
                raise RtabmapError("the rtabmap worker has stopped (node shutting down)")
            self._commands.append(command)
        self._wake.set()
        return command.result(self.params.node.service_timeout_s)

    def _process(self, item: QueuedFrame) -> None:
        """Process one frame; any error is contained here (the worker goes on) unless unrecoverable."""
        try:
            self._process_frame(item)
        except Exception as exc:  # noqa: BLE001 - the worker must survive a gtsam/numpy/sqlite/cv2 error
            if unrecoverable(exc):
                self._fail(exc)
            else:
                self._frame_error(item.frame, exc)

    def _frame_error(self, frame: SensorFrame, exc: Exception) -> None:
        """An unexpected error in one frame: counted per kind, logged once per kind with its traceback."""
        kind = error_kind(exc)
        count = self.frame_errors.get(kind, 0) + 1
        self.frame_errors[kind] = count
        if count == 1:
            self.get_logger().error(
                f"frame at {frame.stamp_ns / NS_PER_S:.9f} s dropped: unexpected {kind}: {exc} (the node goes on; "
                f"further errors of this kind are counted in info's node_frame_errors, not logged)\n"
                + "".join(traceback.format_exception(exc)).rstrip())

    def _fail(self, exc: BaseException) -> None:
        """An unrecoverable error: log it, stop the worker and end the process (main exits non-zero)."""
        self.fatal_error = exc
        self._stop.set()
        self.get_logger().fatal(
            f"unrecoverable error, the node stops (exit status {EXIT_UNRECOVERABLE}; a launch respawn restarts "
            f"it): {type(exc).__name__}: {exc}\n" + "".join(traceback.format_exception(exc)).rstrip())
        self.context.try_shutdown()

    def _process_frame(self, item: QueuedFrame) -> None:
        """The worker's part of a frame (the critical path): its features (extracted ahead), the core,
        a snapshot of the local map; the rest is published beside it (MapPublisher)."""
        frame, timer = item.frame, FrameTimer()
        try:
            with timer.part("wait"):
                features = self._frames.features(item, self._core.extractor)
            with timer.part("process"):
                stats = self._core.process(frame, features=features)
            with timer.part("local_map"):
                local = self._core.local_map()
            localization_pose = self._core.localization_pose if self._core.localization_mode else None
        except SensorDataError as exc:
            self._bad_frame(exc)
            return
        except DatabaseError:
            raise
        except RtabmapError as exc:
            self.get_logger().error(f"frame at {frame.stamp_ns / NS_PER_S:.9f} s not processed: {exc}")
            return
        self.frames_processed += 1
        self.rehearsal_merges += int(bool(stats.merged_id))
        self.frames_not_moved += int(stats.small_displacement)
        self.last_statistics = stats
        row = self.frame_times.add(timer)
        self._publisher.submit(Published(frame.stamp_ns, item.arrival, stats.to_dict(), local, localization_pose,
                                         FrameTimes.info_of(row), self._publisher.generation))

    def _info_counters(self) -> dict[str, Any]:
        """The node's counters on every ``info``."""
        return {"node_frames_dropped": self.frames_dropped, "node_messages_lost": sum(self.messages_lost.values()),
                "node_paused": self.paused, "node_frame_errors": sum(self.frame_errors.values()),
                **self.dropped.info()}

    # -- publishers and services ---------------------------------------------------------------
    def _advertise(self) -> None:
        latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL)
        self._pub_path = self.create_publisher(PathMsg, "mapPath", QUEUE_DEPTH)
        self._pub_map = self.create_publisher(OccupancyGridMsg, "map", latched)
        self._pub_graph = self.create_publisher(MarkerArray, "mapGraph", QUEUE_DEPTH)
        self._pub_info = self.create_publisher(DiagnosticArray, "info", QUEUE_DEPTH)
        self._pub_localization = self.create_publisher(PoseStamped, "localization_pose", QUEUE_DEPTH)
        self._publisher = MapPublisher(
            Outputs(self._pub_path, self._pub_graph, self._pub_map, self._pub_info, self._pub_localization,
                    self.tf_broadcaster, self.params.node.map_frame_id, self._info_counters,
                    self.get_logger().error),
            self.params.grid, self.frame_times, self.latencies_s, GRID_PERIOD_S, GRID_MAX_CASTS)
        group = self._service_group
        self.create_service(GetMap, "get_map", self._get_map, callback_group=group)
        self.create_service(Trigger, "export_global_map", self._export_global_map, callback_group=group)
        empty_services: dict[str, Callable[[], None]] = {
            "publish_map": self.publish_global_map,
            "reset": self.reset,
            "pause": lambda: self._set_paused(True),
            "resume": lambda: self._set_paused(False),
            "trigger_new_map": self.trigger_new_map,
            "backup": self.backup,
            "set_mode_localization": lambda: self._set_localization(True),
            "set_mode_mapping": lambda: self._set_localization(False),
        }
        for name, action in empty_services.items():
            self.create_service(Empty, name, self._empty_service(name, action), callback_group=group)

    def _empty_service(self, name: str, action: Callable[[], None]) -> Callable:
        def serve(request, response):
            try:
                action()
            except Exception as exc:  # noqa: BLE001 - a service must answer; the node keeps running
                self.get_logger().error(f"service {name} failed: {type(exc).__name__}: {exc}")
            return response
        return serve

    def _set_paused(self, paused: bool) -> None:
        self.paused = paused
        self.get_logger().info("paused: incoming frames are ignored" if paused else "resumed")

    def _set_localization(self, on: bool) -> None:
        self._in_worker(lambda: setattr(self._core, "localization_mode", on), "set_mode")
        self.get_logger().info("localization mode: no node is added to the map" if on else "mapping mode")

    def trigger_new_map(self) -> int:
        """Start a new map (session) at the next frame; returns its id."""
        map_id = self._in_worker(lambda: self._core.trigger_new_map(), "trigger_new_map")
        self.get_logger().info(f"new map {map_id} starts at the next frame")
        return map_id

    def reset(self) -> None:
        """Forget everything (database deleted and restarted) and clear the published map."""
        self._frames.clear()

        def reset_core() -> None:   # in the worker, between frames: the maps handed over before are old
            self._core.reset()
            self._publisher.reset()
        self._in_worker(reset_core, "reset")
        with self._sync_lock:
            self._sync.reset()
        self._last_stamp.clear()
        stamp = self.get_clock().now().nanoseconds
        map_frame = self.params.node.map_frame_id
        with self._publisher.round_lock:   # after the publishing round under way, if any
            self._pub_path.publish(conv.path_to_msg({}, stamp, map_frame))
            self._pub_graph.publish(conv.graph_to_markers({}, [], stamp, map_frame))
        self.get_logger().info(f"reset: {self.database_path} emptied")

    def backup(self) -> Path:
        """Copy the database next to itself as ``<stem>-backup-<YYYYmmdd-HHMMSS[-n]>.db``.

        A name already taken (a file, or a symlink someone planted at the predictable name) is
        skipped, never followed; the core writes the copy under a temporary name and links it.
        """
        path = new_backup_path(self.database_path)
        self._in_worker(lambda: self._core.backup(path), "backup")
        self.get_logger().info(f"database backed up to {path}")
        return path

    def _global_map(self):
        """``(GlobalMap, GlobalGrid or None)`` of the whole database (all sessions, all
        constraints), read through a read-only connection after a flush; the grid from the laser
        scans and / or depth images as ``grid.sensor`` says (None without a posed node)."""
        from rtabmap_ros2.core.database import Database
        from rtabmap_ros2.core.global_map import assemble_global_grid, load_global_map

        self._in_worker(lambda: self._core.flush(), "flush")
        global_map = load_global_map(self.database_path, self.params)
        grid = None
        if global_map.poses:
            db = Database(self.database_path, read_only=True)
            try:
                grid = assemble_global_grid(global_map, db, self.params)
            finally:
                db.close()
        return global_map, grid

    def publish_global_map(self) -> None:
        """Publish the global map on mapPath, mapGraph and (when its occupancy grid has cells) map."""
        global_map, grid = self._global_map()
        stamp = self.get_clock().now().nanoseconds
        map_frame = self.params.node.map_frame_id
        self._pub_path.publish(conv.path_to_msg(global_map.poses, stamp, map_frame))
        self._pub_graph.publish(conv.graph_to_markers(global_map.poses, global_map.links, stamp, map_frame))
        if grid is not None and not grid.empty_reason:
            self._pub_map.publish(conv.grid_to_msg(grid.grid, stamp, map_frame))
        self.get_logger().info(f"published the global map ({len(global_map.poses)} nodes"
                               + (f", occupancy grid from {grid.source()})" if grid and not grid.empty_reason
                                  else ", no occupancy grid)"))

    def _get_map(self, request, response):
        try:
            _, grid = self._global_map()
        except Exception as exc:  # noqa: BLE001 - a service must answer; the node keeps running
            self.get_logger().error(f"get_map failed: {type(exc).__name__}: {exc}")
            return response
        if grid is None or grid.empty_reason:
            self.get_logger().warning("get_map: no occupancy grid: "
                                      + (grid.empty_reason if grid else "the map has no node with a pose"))
            return response
        response.map = conv.grid_to_msg(grid.grid, self.get_clock().now().nanoseconds,
                                        self.params.node.map_frame_id)
        return response

    def _export_global_map(self, request, response):
        try:
            from rtabmap_ros2.io.export import export_global_map

            folder = new_export_folder(self.params.node.export_dir)
        except Exception as exc:  # noqa: BLE001 - a service must answer; the node keeps running
            response.success, response.message = False, f"export failed: {type(exc).__name__}: {exc}"
            self.get_logger().error(response.message)
            return response
        try:
            self._in_worker(lambda: self._core.flush(), "flush")
            summary = export_global_map(self.database_path, folder, self.params)
        except Exception as exc:  # noqa: BLE001 - a service must answer; the node keeps running
            _remove_if_empty(folder)   # export_global_map removed the files it wrote
            response.success, response.message = False, f"export failed: {type(exc).__name__}: {exc}"
            self.get_logger().error(response.message)
            return response
        response.success = True
        response.message = str(folder)
        self.get_logger().info(f"global map exported to {folder}: {summary}")
        return response

    # -- shutdown ------------------------------------------------------------------------------
    def destroy_node(self) -> None:
        """Finish the frame in flight, flush and close the database, then destroy the node."""
        if self._destroyed:
            return
        self._destroyed = True
        self._stop.set()
        self._wake.set()
        self._worker.join()   # finishes the frame in flight, then flushes and closes the database
        self._frames.stop()
        self._publisher.stop()
        self.get_logger().info(f"database {self.database_path} flushed and closed "
                               f"({self.frames_processed} frames processed, {self.frames_dropped} dropped"
                               + (f", {self.frames_not_moved} not added: the robot moved less than "
                                  "RGBD/LinearUpdate / AngularUpdate" if self.frames_not_moved else "") + ")")
        super().destroy_node()


def _spin(executor: NodeExecutor, context) -> None:
    """``executor.spin()``, ended by a shutdown from another thread (the worker's unrecoverable error)
    as ExternalShutdownException wherever it lands: mid-wait, rclpy raises RCLError ("the given context
    is not valid") instead, which would end the process with a traceback and status 1 instead of
    EXIT_UNRECOVERABLE."""
    try:
        executor.spin()
    except ExternalShutdownException:
        raise
    except Exception:
        if context.ok():
            raise
        raise ExternalShutdownException() from None


def main(args: Optional[list[str]] = None) -> None:
    """Console script ``rtabmap`` (``ros2 run rtabmap_ros2 rtabmap``)."""
    rclpy.init(args=args)
    node = None
    try:
        node = RtabmapNode()
        # Sensors, services, and tf2's listener (served while a sensor callback waits for a transform).
        executor = NodeExecutor(num_threads=3)
        executor.add_node(node)
        _spin(executor, node.context)
    except KeyboardInterrupt:
        pass
    except ExternalShutdownException:
        if node is None or node.fatal_error is None:
            sys.exit(1)
    except RtabmapError as exc:
        print(f"error: {exc}", file=sys.stderr)
        sys.exit(2)
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    if node is not None and node.fatal_error is not None:
        sys.exit(EXIT_UNRECOVERABLE)


if __name__ == "__main__":
    main()
