"""The Long-Term Memory (LTM) in SQLite: one file per map database (2013 §III-E, Fig. 3; 2014 §II).

The 2013 paper stores the LTM in a SQLite3 database (Fig. 3): a table of locations, a table of
links carrying a *link type* (neighbor or loop closure), a table of visual words with their
descriptors and the references from locations to words. The 2014 graph SLAM adds what a node
needs to rebuild a map from the database alone: the session (map) of each node, its odometry
pose, laser scan, camera model, the 3D positions of its words and its RGB-D images.

Tables (schema version :data:`SCHEMA_VERSION`, ``PRAGMA application_id`` = :data:`APPLICATION_ID`):

* ``info(key, value)``: schema version, creation time, parameters (JSON), id high-water marks.
* ``maps(id, first_stamp_ns, created_unix_ns)``: sessions (2014 §II-C), one row per map id seen.
* ``nodes``: a location / node: ``map_id``, ``stamp_ns``, ``weight``, ``in_wm`` (1 while held in
  STM/WM in RAM, 0 once transferred to LTM), ``bad``, ``T_odom_base`` (4x4 float64 blob or NULL),
  ``n_words`` and the word_ids (int64), keypoints (N,2 float32 px) and points3d (N,3 float32 m,
  base frame) blobs, all ``ndarray.tobytes()`` with dtype and shape implied by ``n_words``.
* ``scans``: ranges (float32 blob, m) and geometry (angles rad, limits m, ``T_base_laser`` blob).
* ``cameras``: ``fx fy cx cy`` (px), ``width height`` (px), ``T_base_camera`` blob.
* ``sensor_data``: RGB as JPEG, depth as 16-bit PNG in millimetres, optional 6x6 odometry
  covariance; kept apart from ``nodes`` so graph-only queries never page through images.
* ``words(id, dtype, dim, descriptor)``: the visual words (uint8 binary or float32 descriptors).
* ``node_words(node_id, word_id, count)``: Fig. 3's location -> word references.
* ``links(from_id, to_id, type, T_from_to, information)``: ``pose_to = pose_from @ T_from_to``;
  at most one link per pair of nodes (either orientation).
* ``statistics(frame_index, stamp_ns, data)``: one JSON row per processed frame.

Writes go through :class:`WriteBatch`: everything one frame changed, committed in one
``BEGIN IMMEDIATE ... COMMIT`` transaction (WAL, ``synchronous=NORMAL``), so a process killed at
any moment leaves a database holding every batch whose commit returned. :class:`BackgroundWriter`
commits batches from one worker thread (the "trash thread" of Alg. 1 line 17 / Alg. 4 line 10).

Closing a writable :class:`Database` checkpoints the WAL and switches the file back to rollback
journal mode (when no other connection holds it), so a closed map is one self-contained file and
a later ``read_only=True`` open creates no ``-wal``/``-shm`` files. A database left in WAL mode (a
writer still running or killed) needs them: a read-only open then creates/uses ``-wal`` and
``-shm`` next to the file (SQLite's WAL index), but never writes the database file itself.
"""

from __future__ import annotations

import json
import logging
import queue
import sqlite3
import struct
import threading
import time
import urllib.parse
import weakref
from dataclasses import dataclass, field
from itertools import repeat
from pathlib import Path
from typing import Any, Iterable, Optional

import cv2
import numpy as np

from rtabmap_ros2.core import files
from rtabmap_ros2.core.graph import Link, LinkType
from rtabmap_ros2.core.sensor import CameraModel, LaserScan
from rtabmap_ros2.core.signature import Signature
from rtabmap_ros2.errors import DatabaseError, SensorDataError

logger = logging.getLogger(__name__)

SCHEMA_VERSION = 1
APPLICATION_ID = 0x52544232  # "RTB2" in PRAGMA application_id: marks the file as ours
BUSY_TIMEOUT_S = 30.0  # wait this long for another connection's write lock before failing
JPEG_QUALITY = 90  # RGB images are stored as JPEG at this quality (0-100)
MM_PER_M = 1000.0  # depth PNGs hold millimetres
MAX_DEPTH_MM = 65535  # largest value of a 16-bit PNG: depth is clipped to 65.535 m
SQLITE_HEADER_SIZE = 100
SQLITE_MAGIC = b"SQLite format 3\x00"
SQLITE_MAX_PAGE_SIZE_CODE = 1  # a page size field of 1 means 65536 bytes
SQLITE_MAX_PAGE_SIZE = 65536
DESCRIPTOR_DTYPES = ("uint8", "float32")  # binary (Hamming) or float (L2) descriptors
# The background writer checkpoints the WAL itself, after the batches it was given are committed
# (join() returns before), at most this often, and after at most this many batches.
CHECKPOINT_INTERVAL_S = 1.0
CHECKPOINT_MAX_BATCHES = 30

_SCHEMA = """
CREATE TABLE info (key TEXT PRIMARY KEY, value) WITHOUT ROWID;
CREATE TABLE maps (
    id INTEGER PRIMARY KEY,
    first_stamp_ns INTEGER,
    created_unix_ns INTEGER NOT NULL);
CREATE TABLE nodes (
    id INTEGER PRIMARY KEY,
    map_id INTEGER NOT NULL,
    stamp_ns INTEGER NOT NULL,
    weight INTEGER NOT NULL,
    in_wm INTEGER NOT NULL DEFAULT 1,
    bad INTEGER NOT NULL DEFAULT 0,
    T_odom_base BLOB,
    n_words INTEGER NOT NULL,
    word_ids BLOB NOT NULL,
    keypoints BLOB NOT NULL,
    points3d BLOB NOT NULL);
CREATE INDEX nodes_map_id ON nodes(map_id);
CREATE INDEX nodes_in_wm ON nodes(id) WHERE in_wm = 1;
CREATE TABLE scans (
    node_id INTEGER PRIMARY KEY,
    ranges BLOB NOT NULL,
    angle_min REAL NOT NULL,
    angle_increment REAL NOT NULL,
    range_min REAL NOT NULL,
    range_max REAL NOT NULL,
    T_base_laser BLOB NOT NULL);
CREATE TABLE cameras (
    node_id INTEGER PRIMARY KEY,
    fx REAL NOT NULL, fy REAL NOT NULL, cx REAL NOT NULL, cy REAL NOT NULL,
    width INTEGER NOT NULL, height INTEGER NOT NULL,
    T_base_camera BLOB NOT NULL);
CREATE TABLE sensor_data (
    node_id INTEGER PRIMARY KEY,
    rgb_jpeg BLOB,
    depth_png16_mm BLOB,
    odom_covariance BLOB);
CREATE TABLE words (
    id INTEGER PRIMARY KEY,
    dtype TEXT NOT NULL,
    dim INTEGER NOT NULL,
    descriptor BLOB NOT NULL);
CREATE TABLE node_words (
    node_id INTEGER NOT NULL,
    word_id INTEGER NOT NULL,
    count INTEGER NOT NULL,
    PRIMARY KEY (node_id, word_id)) WITHOUT ROWID;
CREATE INDEX node_words_word_id ON node_words(word_id);
CREATE TABLE links (
    from_id INTEGER NOT NULL,
    to_id INTEGER NOT NULL,
    type TEXT NOT NULL,
    T_from_to BLOB NOT NULL,
    information BLOB NOT NULL,
    PRIMARY KEY (from_id, to_id)) WITHOUT ROWID;
CREATE INDEX links_to_id ON links(to_id);
CREATE TABLE statistics (
    frame_index INTEGER PRIMARY KEY,
    stamp_ns INTEGER,
    data TEXT NOT NULL);
"""

_TABLES = ("info", "maps", "nodes", "scans", "cameras", "sensor_data", "words", "node_words",
           "links", "statistics")

_SIGNATURE_COLUMNS = """
    n.id, n.map_id, n.stamp_ns, n.weight, n.bad, n.T_odom_base, n.n_words, n.word_ids, n.keypoints,
    n.points3d, s.ranges, s.angle_min, s.angle_increment, s.range_min, s.range_max, s.T_base_laser,
    c.fx, c.fy, c.cx, c.cy, c.width, c.height, c.T_base_camera
    FROM nodes n LEFT JOIN scans s ON s.node_id = n.id LEFT JOIN cameras c ON c.node_id = n.id"""


# --------------------------------------------------------------------------------------------
# Image encoding (done once, when a node is created)
# --------------------------------------------------------------------------------------------

def encode_rgb(rgb: np.ndarray) -> bytes:
    """JPEG bytes (quality :data:`JPEG_QUALITY`) of an HxWx3 uint8 image in RGB order."""
    if rgb.dtype != np.uint8 or rgb.ndim != 3 or rgb.shape[2] != 3:
        raise SensorDataError(f"encode_rgb needs an HxWx3 uint8 RGB image, got shape {rgb.shape} dtype {rgb.dtype}")
    ok, buf = cv2.imencode(".jpg", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
    if not ok:
        raise SensorDataError(f"OpenCV could not JPEG-encode an image of shape {rgb.shape}")
    return buf.tobytes()


def decode_rgb(data: bytes) -> np.ndarray:
    """HxWx3 uint8 RGB image of JPEG bytes written by :func:`encode_rgb`."""
    bgr = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
    if bgr is None:
        raise DatabaseError(f"stored RGB image ({len(data)} bytes) is not a readable JPEG: the database is damaged")
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)


def encode_depth(depth_m: np.ndarray) -> bytes:
    """16-bit PNG bytes of an HxW depth image (m) stored in millimetres.

    NaN, inf and values <= 0 become 0 (invalid); depths beyond 65.535 m are clipped to it.
    """
    if depth_m.ndim != 2:
        raise SensorDataError(f"encode_depth needs an HxW depth image (m), got shape {depth_m.shape}")
    d = np.asarray(depth_m, dtype=np.float64)
    with np.errstate(invalid="ignore"):
        invalid = ~np.isfinite(d) | (d <= 0)
        mm = np.clip(np.rint(np.where(invalid, 0.0, d) * MM_PER_M), 0, MAX_DEPTH_MM).astype(np.uint16)
    ok, buf = cv2.imencode(".png", mm)
    if not ok:
        raise SensorDataError(f"OpenCV could not PNG-encode a depth image of shape {depth_m.shape}")
    return buf.tobytes()


def decode_depth(data: bytes) -> np.ndarray:
    """HxW float32 depth (m) of a PNG written by :func:`encode_depth`; 0 (invalid) becomes NaN."""
    mm = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    if mm is None or mm.dtype != np.uint16 or mm.ndim != 2:
        raise DatabaseError(f"stored depth image ({len(data)} bytes) is not a 16-bit PNG: the database is damaged")
    depth = mm.astype(np.float32) / np.float32(MM_PER_M)
    depth[mm == 0] = np.nan
    return depth


# --------------------------------------------------------------------------------------------
# Data classes of the API
# --------------------------------------------------------------------------------------------

@dataclass
class SensorBlobs:
    """A node's raw sensor data, encoded once at node creation.

    Attributes:
        rgb_jpeg: the RGB image as JPEG (:func:`encode_rgb`), or None.
        depth_png16_mm: the depth image as a 16-bit PNG in mm (:func:`encode_depth`), or None.
        odom_covariance: 6x6 float64 covariance of the odometry pose (x y z roll pitch yaw), or None.

    The laser scan and camera model are stored from the :class:`Signature`.
    """

    rgb_jpeg: Optional[bytes] = None
    depth_png16_mm: Optional[bytes] = None
    odom_covariance: Optional[np.ndarray] = None
    # Images still to encode (:meth:`deferred`): (rgb, depth_m), encoded by :meth:`encoded`.
    pending: Optional[tuple[Optional[np.ndarray], Optional[np.ndarray]]] = field(default=None, repr=False,
                                                                                  compare=False)

    @classmethod
    def encode(cls, rgb: Optional[np.ndarray] = None, depth_m: Optional[np.ndarray] = None,
               odom_covariance: Optional[np.ndarray] = None) -> "SensorBlobs":
        """Encode an HxWx3 uint8 RGB image and an HxW float32 depth (m), either may be None."""
        return cls.deferred(rgb, depth_m, odom_covariance).encoded()

    @classmethod
    def deferred(cls, rgb: Optional[np.ndarray] = None, depth_m: Optional[np.ndarray] = None,
                 odom_covariance: Optional[np.ndarray] = None) -> "SensorBlobs":
        """The images kept (copied) as they are, encoded later by :meth:`encoded`: the background
        writer does it, off the frame's critical path (JPEG + 16-bit PNG took ~8 ms a frame)."""
        return cls(None, None, None if odom_covariance is None else np.asarray(odom_covariance, dtype=np.float64),
                   pending=(None if rgb is None else np.array(rgb), None if depth_m is None else np.array(depth_m)))

    def encoded(self) -> "SensorBlobs":
        """These blobs with the pending images encoded (self when none is pending)."""
        if self.pending is None:
            return self
        rgb, depth_m = self.pending
        return SensorBlobs(self.rgb_jpeg if rgb is None else encode_rgb(rgb),
                           self.depth_png16_mm if depth_m is None else encode_depth(depth_m), self.odom_covariance)

    def rgb(self) -> Optional[np.ndarray]:
        """Decoded HxWx3 uint8 RGB image, or None."""
        return None if self.rgb_jpeg is None else decode_rgb(self.rgb_jpeg)

    def depth_m(self) -> Optional[np.ndarray]:
        """Decoded HxW float32 depth (m, NaN invalid), or None."""
        return None if self.depth_png16_mm is None else decode_depth(self.depth_png16_mm)


@dataclass
class WriteBatch:
    """Everything one frame changed in the map; :meth:`Database.write` commits it in ONE transaction.

    Applied in this order: deleted links, deleted locations (with their links, word references
    and sensor data), new words, locations (insert or replace), re-quantised word ids, weights,
    in_wm flags, links (insert or replace, either orientation), statistics.

    Attributes:
        locations: (signature, blobs) to insert or replace. A new location starts with
            ``in_wm = True``; replacing keeps its in_wm flag. ``blobs=None`` keeps the stored
            images (a location re-saved when transferred to LTM).
        deleted_locations: ids of locations merged by rehearsal (2013 §III-B).
        weights: location id -> new weight.
        in_wm: location id -> True while in STM/WM (RAM), False once in LTM.
        words: new word id -> (D,) descriptor, uint8 or float32.
        location_words: location id -> (N,) int64 re-quantised word ids (same N as stored).
        links: links to insert or replace.
        deleted_links: (a, b) pairs whose link (either orientation) is removed.
        statistics: per-frame rows (``Statistics.to_dict()``), each with a ``frame_index`` key.
    """

    locations: list[tuple[Signature, Optional[SensorBlobs]]] = field(default_factory=list)
    deleted_locations: list[int] = field(default_factory=list)
    weights: dict[int, int] = field(default_factory=dict)
    in_wm: dict[int, bool] = field(default_factory=dict)
    words: dict[int, np.ndarray] = field(default_factory=dict)
    location_words: dict[int, np.ndarray] = field(default_factory=dict)
    links: list[Link] = field(default_factory=list)
    deleted_links: list[tuple[int, int]] = field(default_factory=list)
    statistics: list[dict] = field(default_factory=list)

    def add_link(self, link: Link) -> None:
        """Insert or replace ``link``; cancels a deletion of the same pair earlier in this batch."""
        pair = {link.from_id, link.to_id}
        self.deleted_links = [d for d in self.deleted_links if set(d) != pair]
        self.links = [l for l in self.links if {l.from_id, l.to_id} != pair]
        self.links.append(link)

    def delete_link(self, a: int, b: int) -> None:
        """Remove the link between ``a`` and ``b``: from the database, and from this batch if it
        was added here (deletions are applied before insertions, so a link added and removed in
        the same frame would otherwise be written)."""
        self.links = [l for l in self.links if {l.from_id, l.to_id} != {a, b}]
        self.deleted_links.append((a, b))

    def is_empty(self) -> bool:
        """True when the batch changes nothing."""
        return not (self.locations or self.deleted_locations or self.weights or self.in_wm or self.words
                    or self.location_words or self.links or self.deleted_links or self.statistics)


@dataclass(frozen=True)
class NodeInfo:
    """The graph part of a node, for the global map (no words, no sensor data).

    Attributes:
        map_id: session of the node.
        stamp_ns: acquisition time (ns).
        weight: the node's weight.
        T_odom_base: odometry pose (4x4 float64) or None.
        in_wm: True while the node is in STM/WM (RAM), False in LTM.
        bad: the node is a bad signature (graph node only).
    """

    map_id: int
    stamp_ns: int
    weight: int
    T_odom_base: Optional[np.ndarray]
    in_wm: bool
    bad: bool


# --------------------------------------------------------------------------------------------
# Batch -> rows (done in the caller's thread: it snapshots the arrays and validates early)
# --------------------------------------------------------------------------------------------

@dataclass
class _Rows:
    """SQL parameter rows of one WriteBatch, independent of the caller's (mutable) objects."""

    deleted_links: list[tuple] = field(default_factory=list)
    deleted_locations: list[tuple] = field(default_factory=list)
    words: list[tuple] = field(default_factory=list)
    maps: list[tuple] = field(default_factory=list)
    nodes: list[tuple] = field(default_factory=list)
    scans: list[tuple] = field(default_factory=list)
    scan_deletes: list[tuple] = field(default_factory=list)
    cameras: list[tuple] = field(default_factory=list)
    camera_deletes: list[tuple] = field(default_factory=list)
    sensor_data: list[tuple] = field(default_factory=list)
    references: dict[int, list[tuple]] = field(default_factory=dict)  # node id -> its reference rows
    word_updates: list[tuple] = field(default_factory=list)
    weights: list[tuple] = field(default_factory=list)
    in_wm: list[tuple] = field(default_factory=list)
    links: list[tuple] = field(default_factory=list)
    statistics: list[tuple] = field(default_factory=list)
    max_location_id: int = 0
    max_word_id: int = 0


def _transform_blob(T: np.ndarray, what: str) -> bytes:
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4):
        raise DatabaseError(f"{what} must be a 4x4 transform, got shape {T.shape}")
    return np.ascontiguousarray(T).tobytes()


def _transform(blob: Optional[bytes]) -> Optional[np.ndarray]:
    return None if blob is None else np.frombuffer(blob, np.float64).reshape(4, 4).copy()


def _array_blob(values: np.ndarray, dtype: type, columns: int, n: int, what: str) -> bytes:
    a = np.ascontiguousarray(values, dtype=dtype)
    expected = (n,) if columns == 0 else (n, columns)
    if a.shape != expected:
        raise DatabaseError(f"{what} has shape {a.shape}, expected {expected} (one row per word)")
    return a.tobytes()


def _reference_rows(node_id: int, word_ids: np.ndarray) -> list[tuple]:
    """Fig. 3 location -> word references: (node, word, occurrences) for every distinct word."""
    ids, counts = np.unique(word_ids, return_counts=True)
    return list(zip(repeat(node_id), ids.tolist(), counts.tolist()))


def _word_rows(words: dict[int, np.ndarray]) -> list[tuple]:
    """(id, dtype, dim, descriptor bytes) rows; one dtype and size check for the whole batch."""
    if not words:
        return []
    descriptors = [np.asarray(d) for d in words.values()]
    kinds = {(d.dtype, d.shape) for d in descriptors}
    if len(kinds) != 1:
        raise DatabaseError(f"words of one batch mix descriptor types/shapes {sorted(map(str, kinds))}")
    dtype, shape = kinds.pop()
    if dtype.name not in DESCRIPTOR_DTYPES or len(shape) != 1 or shape[0] == 0:
        first = next(iter(words))
        raise DatabaseError(f"word {first}: descriptors must be non-empty (D,) uint8 or float32 arrays, "
                            f"got shape {shape} dtype {dtype}")
    return list(zip([int(i) for i in words], repeat(dtype.name), repeat(shape[0]),
                    [d.tobytes() for d in descriptors]))


def _json_default(value: Any) -> Any:
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    raise TypeError(f"statistics value {value!r} of type {type(value).__name__} is not JSON serialisable")


def _prepare(batch: WriteBatch) -> _Rows:
    """Turn a batch into SQL parameter rows (copies every array: the caller may reuse them)."""
    rows = _Rows()
    rows.deleted_links = [(int(a), int(b), int(b), int(a)) for a, b in batch.deleted_links]
    rows.deleted_locations = [(int(i),) for i in batch.deleted_locations]
    rows.words = _word_rows(batch.words)
    if rows.words:
        rows.max_word_id = max(row[0] for row in rows.words)
    for sig, blobs in batch.locations:
        node_id = int(sig.id)
        if node_id <= 0:
            raise DatabaseError(f"location id must be > 0, got {sig.id}")
        n = int(np.asarray(sig.word_ids).shape[0])
        what = f"location {node_id}"
        word_ids = _array_blob(sig.word_ids, np.int64, 0, n, f"{what} word_ids")
        keypoints = _array_blob(sig.keypoints, np.float32, 2, n, f"{what} keypoints")
        points3d = _array_blob(sig.points3d, np.float32, 3, n, f"{what} points3d")
        pose = None if sig.T_odom_base is None else _transform_blob(sig.T_odom_base, f"{what} T_odom_base")
        rows.nodes.append((node_id, int(sig.map_id), int(sig.stamp_ns), int(sig.weight), int(bool(sig.bad)),
                           pose, n, word_ids, keypoints, points3d))
        rows.maps.append((int(sig.map_id), int(sig.stamp_ns), time.time_ns()))
        rows.references[node_id] = _reference_rows(node_id, np.asarray(sig.word_ids))
        rows.max_location_id = max(rows.max_location_id, node_id)
        if sig.scan is None:
            rows.scan_deletes.append((node_id,))
        else:
            s = sig.scan
            rows.scans.append((node_id, np.ascontiguousarray(s.ranges, dtype=np.float32).tobytes(),
                               float(s.angle_min), float(s.angle_increment), float(s.range_min),
                               float(s.range_max), _transform_blob(s.T_base_laser, f"{what} T_base_laser")))
        if sig.camera is None:
            rows.camera_deletes.append((node_id,))
        else:
            c = sig.camera
            rows.cameras.append((node_id, float(c.fx), float(c.fy), float(c.cx), float(c.cy), int(c.width),
                                 int(c.height), _transform_blob(c.T_base_camera, f"{what} T_base_camera")))
        if blobs is not None:
            covariance = None
            if blobs.odom_covariance is not None:
                cov = np.asarray(blobs.odom_covariance, dtype=np.float64)
                if cov.shape != (6, 6):
                    raise DatabaseError(f"{what} odometry covariance must be 6x6, got shape {cov.shape}")
                covariance = np.ascontiguousarray(cov).tobytes()
            rows.sensor_data.append((node_id, blobs, covariance))  # images encoded by _apply
    for node_id, word_ids in batch.location_words.items():
        ids = np.ascontiguousarray(word_ids, dtype=np.int64)
        if ids.ndim != 1:
            raise DatabaseError(f"location {node_id}: re-quantised word_ids must be (N,), got shape {ids.shape}")
        rows.word_updates.append((ids.tobytes(), int(node_id), int(ids.size)))
        rows.references[int(node_id)] = _reference_rows(int(node_id), ids)  # replaces the location's
    rows.weights = [(int(w), int(i)) for i, w in batch.weights.items()]
    rows.in_wm = [(int(bool(flag)), int(i)) for i, flag in batch.in_wm.items()]
    for link in batch.links:
        a, b = int(link.from_id), int(link.to_id)
        info = np.asarray(link.information, dtype=np.float64)
        if info.shape != (6, 6):
            raise DatabaseError(f"link {a}->{b}: information must be 6x6, got shape {info.shape}")
        rows.links.append((a, b, LinkType(link.type).value,
                           _transform_blob(link.T_from_to, f"link {a}->{b} T_from_to"),
                           np.ascontiguousarray(info).tobytes()))
    for stats in batch.statistics:
        if "frame_index" not in stats:
            raise DatabaseError(f"statistics row has no 'frame_index' key (keys: {sorted(stats)[:10]}...)")
        stamp = stats.get("stamp_ns")
        rows.statistics.append((int(stats["frame_index"]), None if stamp is None else int(stamp),
                                json.dumps(stats, default=_json_default)))
    return rows


def _apply(conn: sqlite3.Connection, path: Path, rows: _Rows) -> None:
    """Commit the rows of one batch in ONE transaction; roll back and raise DatabaseError on failure."""
    try:
        conn.execute("BEGIN IMMEDIATE")
    except sqlite3.Error as e:
        raise DatabaseError(f"cannot start a write transaction on database {path}: {e}") from e
    try:
        _apply_statements(conn, rows)
        conn.execute("COMMIT")
    except BaseException as e:
        try:
            conn.execute("ROLLBACK")
        except sqlite3.Error:
            logger.exception("rollback failed on database %s", path)
        if isinstance(e, DatabaseError):
            raise DatabaseError(f"write to database {path} rolled back: {e}") from e
        if isinstance(e, sqlite3.Error):
            raise DatabaseError(f"write to database {path} failed and was rolled back: {e}") from e
        raise


def _apply_statements(conn: sqlite3.Connection, rows: _Rows) -> None:
    """The batch's statements, as few as possible: this runs on the writer thread, and every
    statement (and every row of an executemany) needs the GIL back from the main thread, which
    holds it while it computes: a frame's batch took 170-380 ms then instead of 2 ms with one
    statement per row (bench/bench_database.py's "main thread busy" rows measure it). So empty row lists run
    nothing, and the many-row inserts and updates are ONE statement over a JSON array each."""
    ex = conn.execute

    def many(sql: str, rows: list) -> None:
        if rows:
            conn.executemany(sql, rows)

    many("DELETE FROM links WHERE (from_id = ? AND to_id = ?) OR (from_id = ? AND to_id = ?)", rows.deleted_links)
    # Rehearsal (2013 §III-B) merged these locations into others: remove them and what hangs on them.
    many("DELETE FROM links WHERE from_id = ?1 OR to_id = ?1", rows.deleted_locations)
    for table, column in (("node_words", "node_id"), ("scans", "node_id"), ("cameras", "node_id"),
                          ("sensor_data", "node_id"), ("nodes", "id")):
        many(f"DELETE FROM {table} WHERE {column} = ?", rows.deleted_locations)
    if rows.words:
        # The descriptors cut out of one blob (one dtype and size per batch, _word_rows).
        _, dtype, dim, first = rows.words[0]
        ex("""INSERT OR REPLACE INTO words (id, dtype, dim, descriptor)
              SELECT j.value, ?2, ?3, substr(?4, j.key * ?5 + 1, ?5) FROM json_each(?1) AS j""",
           (json.dumps([row[0] for row in rows.words]), dtype, dim, b"".join(row[3] for row in rows.words),
            len(first)))
    many("""INSERT INTO maps (id, first_stamp_ns, created_unix_ns) VALUES (?, ?, ?)
            ON CONFLICT(id) DO UPDATE SET first_stamp_ns = min(first_stamp_ns, excluded.first_stamp_ns)""",
         rows.maps)
    many("""INSERT INTO nodes (id, map_id, stamp_ns, weight, bad, T_odom_base, n_words, word_ids, keypoints,
                               points3d) VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?)
            ON CONFLICT(id) DO UPDATE SET map_id = excluded.map_id, stamp_ns = excluded.stamp_ns,
                weight = excluded.weight, bad = excluded.bad, T_odom_base = excluded.T_odom_base,
                n_words = excluded.n_words, word_ids = excluded.word_ids, keypoints = excluded.keypoints,
                points3d = excluded.points3d""", rows.nodes)
    many("DELETE FROM scans WHERE node_id = ?", rows.scan_deletes)
    many("INSERT OR REPLACE INTO scans VALUES (?, ?, ?, ?, ?, ?, ?)", rows.scans)
    many("DELETE FROM cameras WHERE node_id = ?", rows.camera_deletes)
    many("INSERT OR REPLACE INTO cameras VALUES (?, ?, ?, ?, ?, ?, ?, ?)", rows.cameras)
    sensor_rows = []
    for node_id, blobs, covariance in rows.sensor_data:
        blobs = blobs.encoded()
        sensor_rows.append((node_id, blobs.rgb_jpeg, blobs.depth_png16_mm, covariance))
    many("INSERT OR REPLACE INTO sensor_data VALUES (?, ?, ?, ?)", sensor_rows)
    for blob, node_id, n in rows.word_updates:
        stored = ex("SELECT n_words FROM nodes WHERE id = ?", (node_id,)).fetchone()
        if stored is None:
            raise DatabaseError(f"re-quantised words of location {node_id}, which is not in the database")
        if stored[0] != n:
            raise DatabaseError(f"re-quantised words of location {node_id}: {n} word ids for {stored[0]} keypoints")
        ex("UPDATE nodes SET word_ids = ? WHERE id = ?", (blob, node_id))
    many("DELETE FROM node_words WHERE node_id = ?", [(node_id,) for node_id in rows.references])
    references = [row for node_rows in rows.references.values() for row in node_rows]
    if references:
        ex("""INSERT INTO node_words (node_id, word_id, count)
              SELECT json_extract(j.value, '$[0]'), json_extract(j.value, '$[1]'), json_extract(j.value, '$[2]')
              FROM json_each(?) AS j""", (json.dumps(references),))
    for column, updates in (("weight", rows.weights), ("in_wm", rows.in_wm)):
        if not updates:
            continue
        # 800 in_wm updates of a WM cap drop one row at a time took 1.2 s while the main thread
        # ran Python, 8 ms alone (one statement: 23 ms / 11 ms); the 10,000-frame run's frame
        # after a cap drop waited 67-84 ms for this writer.
        changed = ex(f"""UPDATE nodes SET {column} = json_extract(u.value, '$[0]') FROM json_each(?) AS u
                         WHERE nodes.id = json_extract(u.value, '$[1]')""", (json.dumps(updates),)).rowcount
        if changed != len(updates):
            ids = [node_id for _, node_id in updates]
            stored = {r[0] for r in ex("SELECT id FROM nodes WHERE id IN (SELECT value FROM json_each(?))",
                                       (json.dumps(ids),))}
            missing = sorted(set(ids) - stored)
            raise DatabaseError(f"{column} update of location {', '.join(map(str, missing[:10]))}, which is not "
                                "in the database")
    many("DELETE FROM links WHERE from_id = ?2 AND to_id = ?1", [(r[0], r[1]) for r in rows.links])
    many("INSERT OR REPLACE INTO links VALUES (?, ?, ?, ?, ?)", rows.links)
    many("INSERT OR REPLACE INTO statistics VALUES (?, ?, ?)", rows.statistics)
    # Ids are never reused (CONVENTIONS): keep high-water marks that survive deleted locations.
    for key, value in (("max_location_id", rows.max_location_id), ("max_word_id", rows.max_word_id)):
        if value:
            ex("""INSERT INTO info (key, value) VALUES (?1, ?2)
                  ON CONFLICT(key) DO UPDATE SET value = max(CAST(value AS INTEGER), ?2)""", (key, value))


# --------------------------------------------------------------------------------------------
# Opening: refuse anything that is not one of our databases, never modify it
# --------------------------------------------------------------------------------------------

def _check_header(path: Path) -> bool:
    """Check an existing file's SQLite header; True if the file is empty (a new database).

    Catches random bytes ("file is not a database") and truncated copies (fewer pages than the
    header declares) before SQLite touches the file.
    """
    size = path.stat().st_size
    if size == 0:
        return True
    with open(path, "rb") as f:
        header = f.read(SQLITE_HEADER_SIZE)
    if len(header) < SQLITE_HEADER_SIZE or not header.startswith(SQLITE_MAGIC):
        raise DatabaseError(f"{path} is not a database (file is not a database: no SQLite header in its "
                            f"{size} bytes); pass the path of an rtabmap_ros2 map database")
    page_size_code, = struct.unpack(">H", header[16:18])
    page_size = SQLITE_MAX_PAGE_SIZE if page_size_code == SQLITE_MAX_PAGE_SIZE_CODE else page_size_code
    change_counter, page_count = struct.unpack(">II", header[24:32])
    valid_for, = struct.unpack(">I", header[92:96])
    wal = path.with_name(path.name + "-wal")
    wal_has_frames = wal.exists() and wal.stat().st_size > 0
    if valid_for == change_counter and page_count * page_size > size and not wal_has_frames:
        raise DatabaseError(f"{path} is truncated or corrupt: its header declares {page_count} pages of "
                            f"{page_size} bytes but the file holds {size} bytes; restore it from a backup")
    return False


class Database:
    """One map's long-term memory (SQLite, WAL). Not thread-safe: use it from one thread.

    Args:
        path: database file. Created with the schema if missing (its folder must exist); an
            existing file must be one of ours with schema version :data:`SCHEMA_VERSION`,
            otherwise :class:`DatabaseError` is raised and the file is left untouched.
        read_only: open with the URI ``file:...?mode=ro``; every write raises DatabaseError.
    """

    def __init__(self, path: str | Path, read_only: bool = False) -> None:
        self.path = Path(path).expanduser().absolute()
        self.read_only = read_only
        self._conn: Optional[sqlite3.Connection] = None
        self._writers: weakref.WeakSet[BackgroundWriter] = weakref.WeakSet()
        if not self.path.parent.is_dir():
            raise DatabaseError(f"cannot open database {self.path}: folder {self.path.parent} does not exist")
        exists = self.path.exists()
        if read_only and not exists:
            raise DatabaseError(f"cannot open database {self.path} read-only: the file does not exist")
        if exists and not self.path.is_file():
            raise DatabaseError(f"cannot open database {self.path}: it is not a regular file")
        new = _check_header(self.path) if exists else True
        if new and read_only:
            raise DatabaseError(f"{self.path} is empty: not an rtabmap_ros2 database")
        self._conn = self._connect()
        try:
            if new:
                self._create_schema()
            else:
                self._check_schema()
            if not read_only:
                self._conn.execute("PRAGMA journal_mode=WAL")
        except sqlite3.Error as e:
            self._conn.close()
            self._conn = None
            raise DatabaseError(f"{self.path} is not a database we can use ({e}); "
                                "pass the path of an rtabmap_ros2 map database") from e
        except DatabaseError:
            self._conn.close()
            self._conn = None
            raise

    # -- connections ---------------------------------------------------------------------------

    def _connect(self) -> sqlite3.Connection:
        """A new connection (autocommit: transactions are explicit) for the calling thread."""
        try:
            if self.read_only:
                uri = "file:" + urllib.parse.quote(str(self.path)) + "?mode=ro"
                conn = sqlite3.connect(uri, uri=True, timeout=BUSY_TIMEOUT_S, isolation_level=None)
            else:
                conn = sqlite3.connect(str(self.path), timeout=BUSY_TIMEOUT_S, isolation_level=None)
                conn.execute("PRAGMA synchronous=NORMAL")
        except sqlite3.Error as e:
            raise DatabaseError(f"cannot open database {self.path}: {e} (the file was left untouched; "
                                "if it is damaged, restore it from a backup)") from e
        return conn

    def _create_schema(self) -> None:
        conn = self._conn
        conn.execute("BEGIN IMMEDIATE")
        try:
            conn.execute(f"PRAGMA application_id={APPLICATION_ID}")
            conn.execute(f"PRAGMA user_version={SCHEMA_VERSION}")
            for statement in _SCHEMA.split(";"):
                if statement.strip():
                    conn.execute(statement)
            conn.executemany("INSERT INTO info (key, value) VALUES (?, ?)",
                             [("schema_version", SCHEMA_VERSION), ("created_unix_ns", time.time_ns()),
                              ("max_location_id", 0), ("max_word_id", 0)])
            conn.execute("COMMIT")
        except BaseException:
            conn.execute("ROLLBACK")
            raise
        logger.info("created database %s (schema version %d)", self.path, SCHEMA_VERSION)

    def _check_schema(self) -> None:
        app_id = self._conn.execute("PRAGMA application_id").fetchone()[0]
        if app_id != APPLICATION_ID:
            tables = [r[0] for r in self._conn.execute("SELECT name FROM sqlite_master WHERE type = 'table'")]
            raise DatabaseError(f"{self.path} is a SQLite file but not an rtabmap_ros2 database "
                                f"(application_id {app_id}, tables {tables[:8]}); it was left untouched")
        version = self._conn.execute("PRAGMA user_version").fetchone()[0]
        if version != SCHEMA_VERSION:
            raise DatabaseError(f"{self.path} has schema version {version}, this rtabmap_ros2 reads version "
                                f"{SCHEMA_VERSION}; use a matching rtabmap_ros2 version")
        missing = set(_TABLES) - {r[0] for r in self._conn.execute("SELECT name FROM sqlite_master")}
        if missing:
            raise DatabaseError(f"{self.path} lacks tables {sorted(missing)}: the database is damaged")

    @property
    def conn(self) -> sqlite3.Connection:
        """The connection of this object (raises DatabaseError once closed)."""
        if self._conn is None:
            raise DatabaseError(f"database {self.path} is closed")
        return self._conn

    def _query(self, sql: str, params: Iterable[Any] = ()) -> list[tuple]:
        try:
            return self.conn.execute(sql, tuple(params)).fetchall()
        except sqlite3.Error as e:
            raise DatabaseError(f"reading database {self.path} failed ({e}); the file may be damaged") from e

    def _writable(self) -> None:
        if self.read_only:
            raise DatabaseError(f"database {self.path} is open read-only: cannot write")

    # -- writes ----------------------------------------------------------------------------------

    def write(self, batch: WriteBatch) -> None:
        """Commit everything a frame changed in ONE transaction (rolled back on any error)."""
        self._writable()
        _apply(self.conn, self.path, _prepare(batch))

    def set_parameters(self, parameters: dict) -> None:
        """Store the configuration used (a JSON-serialisable dict)."""
        self._writable()
        try:
            text = json.dumps(parameters, default=_json_default, sort_keys=True)
        except TypeError as e:
            raise DatabaseError(f"parameters cannot be stored in {self.path}: {e}") from e
        try:
            self.conn.execute("INSERT OR REPLACE INTO info (key, value) VALUES ('parameters', ?)", (text,))
        except sqlite3.Error as e:
            raise DatabaseError(f"writing parameters to database {self.path} failed: {e}") from e

    # -- reads -----------------------------------------------------------------------------------

    def get_parameters(self) -> dict:
        """The configuration stored by :meth:`set_parameters` ({} if none)."""
        rows = self._query("SELECT value FROM info WHERE key = 'parameters'")
        return json.loads(rows[0][0]) if rows else {}

    def load_signature(self, node_id: int) -> Signature:
        """The signature of one location (DatabaseError if absent)."""
        return self.load_signatures([node_id])[0]

    def load_signatures(self, ids: Iterable[int]) -> list[Signature]:
        """Signatures of locations ``ids`` (in that order) read in one query (Retrieval, Alg. 3)."""
        ids = [int(i) for i in ids]
        if not ids:
            return []
        rows = self._query(f"SELECT {_SIGNATURE_COLUMNS} WHERE n.id IN (SELECT value FROM json_each(?))",
                           (json.dumps(ids),))
        by_id = {row[0]: row for row in rows}
        missing = [i for i in ids if i not in by_id]
        if missing:
            raise DatabaseError(f"locations {missing[:10]} are not in database {self.path}")
        return [self._signature(by_id[i]) for i in ids]

    def _signature(self, row: tuple) -> Signature:
        (node_id, map_id, stamp_ns, weight, bad, pose, n, word_ids, keypoints, points3d,
         ranges, angle_min, angle_increment, range_min, range_max, T_base_laser,
         fx, fy, cx, cy, width, height, T_base_camera) = row
        try:
            scan = None if ranges is None else LaserScan(
                np.frombuffer(ranges, np.float32).copy(), angle_min, angle_increment, range_min, range_max,
                _transform(T_base_laser))
            camera = None if fx is None else CameraModel(fx, fy, cx, cy, width, height, _transform(T_base_camera))
            return Signature(
                id=node_id, map_id=map_id, stamp_ns=stamp_ns, weight=weight, bad=bool(bad),
                T_odom_base=_transform(pose),
                word_ids=np.frombuffer(word_ids, np.int64).copy(),
                keypoints=np.frombuffer(keypoints, np.float32).reshape(n, 2).copy(),
                points3d=np.frombuffer(points3d, np.float32).reshape(n, 3).copy(),
                scan=scan, camera=camera)
        except (ValueError, SensorDataError) as e:
            raise DatabaseError(f"location {node_id} in database {self.path} is damaged: {e}") from e

    def load_descriptors(self, word_ids: Optional[Iterable[int]] = None) -> tuple[np.ndarray, np.ndarray]:
        """Words found among ``word_ids`` (all words if None) as ((M,) int64 ids, (M,D) descriptors).

        Absent ids are skipped. Raises DatabaseError if the words mix descriptor types or sizes.
        """
        if word_ids is None:
            rows = self._query("SELECT id, dtype, dim, descriptor FROM words ORDER BY id")
        else:
            ids = [int(i) for i in word_ids]
            rows = self._query("SELECT id, dtype, dim, descriptor FROM words "
                               "WHERE id IN (SELECT value FROM json_each(?)) ORDER BY id", (json.dumps(ids),))
        if not rows:
            return np.zeros(0, np.int64), np.zeros((0, 0), np.uint8)
        ids_col, dtypes, dims, blobs = zip(*rows)
        kinds = set(zip(dtypes, dims))
        if len(kinds) != 1:
            raise DatabaseError(f"words in {self.path} mix descriptor types {sorted(kinds)}")
        dtype, dim = kinds.pop()
        descriptors = np.frombuffer(b"".join(blobs), np.dtype(dtype)).reshape(len(rows), dim).copy()
        return np.asarray(ids_col, dtype=np.int64), descriptors

    def load_words(self, word_ids: Optional[Iterable[int]] = None) -> dict[int, np.ndarray]:
        """Word id -> (D,) descriptor for the words found among ``word_ids`` (all if None)."""
        ids, descriptors = self.load_descriptors(word_ids)
        return dict(zip(ids.tolist(), descriptors))

    def load_sensor_blobs(self, node_id: int) -> SensorBlobs:
        """Encoded images (and odometry covariance) of a location; fields are None if not stored."""
        if not self._query("SELECT 1 FROM nodes WHERE id = ?", (int(node_id),)):
            raise DatabaseError(f"location {node_id} is not in database {self.path}")
        rows = self._query("SELECT rgb_jpeg, depth_png16_mm, odom_covariance FROM sensor_data WHERE node_id = ?",
                           (int(node_id),))
        if not rows:
            return SensorBlobs()
        rgb, depth, cov = rows[0]
        return SensorBlobs(rgb, depth, None if cov is None else np.frombuffer(cov, np.float64).reshape(6, 6).copy())

    def load_scans(self, ids: Optional[Iterable[int]] = None) -> dict[int, LaserScan]:
        """Laser scans of locations ``ids`` (all if None) that have one (for grids of the global map)."""
        sql = "SELECT node_id, ranges, angle_min, angle_increment, range_min, range_max, T_base_laser FROM scans"
        params: tuple = ()
        if ids is not None:
            sql += " WHERE node_id IN (SELECT value FROM json_each(?))"
            params = (json.dumps([int(i) for i in ids]),)
        return {row[0]: LaserScan(np.frombuffer(row[1], np.float32).copy(), row[2], row[3], row[4], row[5],
                                  _transform(row[6]))
                for row in self._query(sql, params)}

    def load_links(self, node_ids: Optional[Iterable[int]] = None) -> list[Link]:
        """Every link (or those touching ``node_ids``), as stored (``pose_to = pose_from @ T_from_to``)."""
        sql = "SELECT from_id, to_id, type, T_from_to, information FROM links"
        params: tuple = ()
        if node_ids is not None:
            sql += (" WHERE from_id IN (SELECT value FROM json_each(?1))"
                    " OR to_id IN (SELECT value FROM json_each(?1))")
            params = (json.dumps([int(i) for i in node_ids]),)
        return [Link(a, b, self._link_type(a, b, kind), _transform(T),
                     np.frombuffer(info, np.float64).reshape(6, 6).copy())
                for a, b, kind, T, info in self._query(sql, params)]

    def _link_type(self, a: int, b: int, kind: str) -> LinkType:
        """The LinkType spelled ``kind`` (DatabaseError naming the link when there is none)."""
        try:
            return LinkType(kind)
        except ValueError as e:
            raise DatabaseError(f"link {a}->{b} in {self.path} has unknown type {kind!r}") from e

    def link_ends(self, node_ids: Iterable[int]) -> list[tuple[int, int, LinkType]]:
        """(node, other end, type) of every link of the nodes ``node_ids`` (either orientation):
        the graph search through LTM, without reading transforms."""
        ids = json.dumps([int(i) for i in node_ids])
        rows = self._query("SELECT from_id, to_id, type FROM links WHERE from_id IN (SELECT value FROM json_each(?1))"
                           " UNION ALL SELECT to_id, from_id, type FROM links"
                           " WHERE to_id IN (SELECT value FROM json_each(?1))", (ids,))
        return [(a, b, self._link_type(a, b, kind)) for a, b, kind in rows]

    def first_node_of_maps(self) -> dict[int, int]:
        """Map id -> its first node id (sessions are ranges of node ids)."""
        return dict(self._query("SELECT map_id, min(id) FROM nodes GROUP BY map_id"))

    def node_count(self) -> int:
        return int(self._query("SELECT count(*) FROM nodes")[0][0])

    def inter_session_pairs(self) -> list[tuple[int, int]]:
        """(from_id, to_id) of every inter-session loop closure."""
        return self._query("SELECT from_id, to_id FROM links WHERE type = ?", (LinkType.LOOP_INTER.value,))

    def load_nodes(self) -> dict[int, NodeInfo]:
        """Graph part of every node (WM and LTM): id -> NodeInfo, for the global map."""
        rows = self._query("SELECT id, map_id, stamp_ns, weight, T_odom_base, in_wm, bad FROM nodes ORDER BY id")
        return {i: NodeInfo(m, s, w, _transform(p), bool(wm), bool(bad)) for i, m, s, w, p, wm, bad in rows}

    def wm_ids(self) -> list[int]:
        """Ids of the locations flagged in STM/WM (in RAM when the database was last written)."""
        return [r[0] for r in self._query("SELECT id FROM nodes WHERE in_wm = 1 ORDER BY id")]

    def max_location_id(self) -> int:
        """Largest location id ever written (0 if none): new ids start above it."""
        row = self._query("SELECT max(coalesce((SELECT max(id) FROM nodes), 0), "
                          "(SELECT CAST(value AS INTEGER) FROM info WHERE key = 'max_location_id'))")
        return int(row[0][0] or 0)

    def max_word_id(self) -> int:
        """Largest word id ever written (0 if none): new word ids start above it."""
        row = self._query("SELECT max(coalesce((SELECT max(id) FROM words), 0), "
                          "(SELECT CAST(value AS INTEGER) FROM info WHERE key = 'max_word_id'))")
        return int(row[0][0] or 0)

    def max_map_id(self) -> int:
        """Largest map (session) id, or -1 if the database has no map yet (next map = this + 1)."""
        row = self._query("SELECT max(coalesce((SELECT max(id) FROM maps), -1), "
                          "coalesce((SELECT max(map_id) FROM nodes), -1))")
        return int(row[0][0])

    def max_frame_index(self) -> int:
        """Largest frame index with statistics, or -1 when none (a reopened map continues after it)."""
        row = self._query("SELECT max(frame_index) FROM statistics")
        return -1 if row[0][0] is None else int(row[0][0])

    def load_statistics(self) -> list[dict]:
        """Per-frame statistics rows, by increasing frame index."""
        return [json.loads(r[0]) for r in self._query("SELECT data FROM statistics ORDER BY frame_index")]

    def descriptor_kinds(self) -> list[tuple[str, int]]:
        """The distinct (dtype name, size) of the stored words' descriptors ([] without words)."""
        return [(dtype, int(dim)) for dtype, dim in self._query("SELECT DISTINCT dtype, dim FROM words ORDER BY dtype")]

    def nodes_without_rgb(self) -> int:
        """Number of nodes with no stored RGB image."""
        return int(self._query("SELECT count(*) FROM nodes n LEFT JOIN sensor_data s ON s.node_id = n.id "
                               "WHERE s.rgb_jpeg IS NULL")[0][0])

    def quick_check(self) -> list[str]:
        """SQLite's ``PRAGMA quick_check`` messages (``["ok"]`` for a sound file): integrity_check
        without the index contents, linear in the file size."""
        return [r[0] for r in self._query("PRAGMA quick_check")]

    def integrity_check(self) -> list[str]:
        """SQLite's ``PRAGMA integrity_check`` messages (``["ok"]`` for a sound file)."""
        return [r[0] for r in self._query("PRAGMA integrity_check")]

    # -- maintenance -----------------------------------------------------------------------------

    def backup(self, path: str | Path) -> None:
        """Copy the database to a NEW file with SQLite's online backup API (consistent snapshot).

        The copy is written under a temporary name in the target folder and linked to ``path``
        only when complete (:mod:`rtabmap_ros2.core.files`): ``path`` is never followed (a
        planted symlink, even dangling, makes the backup fail) and never overwritten.
        """
        dest_path = Path(path).expanduser().absolute()
        if dest_path.exists() or dest_path.is_symlink():
            raise DatabaseError(f"backup target {dest_path} already exists: choose a new file name")
        if not dest_path.parent.is_dir():
            raise DatabaseError(f"backup target folder {dest_path.parent} does not exist")
        try:
            with files.new_path(dest_path, exclusive=True) as tmp:
                dest = sqlite3.connect(str(tmp))
                try:
                    self.conn.backup(dest)
                    dest.execute("PRAGMA journal_mode=DELETE")
                finally:
                    dest.close()
        except FileExistsError as e:
            raise DatabaseError(f"backup target {dest_path} appeared while the backup was written (a file or a "
                                "symlink): not overwritten, not followed; choose a new file name") from e
        except sqlite3.Error as e:
            raise DatabaseError(f"backup of database {self.path} to {dest_path} failed: {e}") from e
        except OSError as e:
            raise DatabaseError(f"backup of database {self.path} to {dest_path} failed: {e.strerror or e}") from e

    def close(self) -> None:
        """Finish background writers, checkpoint the WAL and close (idempotent).

        A writable database is switched back to rollback-journal mode when no other connection
        uses it, leaving one self-contained file (read-only opens then create no -wal/-shm).
        """
        if self._conn is None:
            return
        error: Optional[DatabaseError] = None
        for writer in list(self._writers):
            try:
                writer.close()
            except DatabaseError as e:
                error = error or e
        conn, self._conn = self._conn, None
        if not self.read_only:
            try:
                conn.execute("PRAGMA busy_timeout=0")
                conn.execute("PRAGMA wal_checkpoint(TRUNCATE)")
                conn.execute("PRAGMA journal_mode=DELETE")
            except sqlite3.Error as e:
                logger.debug("database %s stays in WAL mode at close: %s", self.path, e)
        conn.close()
        if error is not None:
            raise error

    def __enter__(self) -> "Database":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __del__(self) -> None:
        if getattr(self, "_conn", None) is not None:
            logger.warning("database %s was not closed", self.path)


class BackgroundWriter:
    """Commits WriteBatches from ONE worker thread: the "trash thread" of Alg. 1 line 17 / Alg. 4 line 10.

    The worker opens its own SQLite connection, used from that thread only; the
    :class:`Database` keeps reading on the caller's thread meanwhile (WAL readers do not block
    the writer). :meth:`submit` snapshots the batch (the caller may reuse its arrays) and
    validates it, raising at once on malformed data. After a failed commit, the batches already
    queued are skipped (they may depend on the failed one) until :meth:`join` reports the error.

    WAL checkpoints (copying the log into the database file, with an fsync) are asked for by the
    worker once its queue is empty, at most every :data:`CHECKPOINT_INTERVAL_S` (or after
    :data:`CHECKPOINT_MAX_BATCHES` batches), instead of inside the commit that fills the log past
    SQLite's 1,000 pages: that commit took 6x an ordinary one, and 50 ms on a 1.8 GB map for a WM
    cap drop's 600 in_wm updates, which the next frame waited for (Alg. 1 line 17). They run on a
    thread and connection of their own (a PASSIVE checkpoint does not block WAL writers): run by
    the worker, a checkpoint whose fsync took 0.6 s on a machine busy with other I/O held back the
    next frame's batch, and the frame with it (issue 50, ``detect`` over 10,000 images).
    """

    def __init__(self, db: Database) -> None:
        if db.read_only:
            raise DatabaseError(f"cannot write to database {db.path}: it is open read-only")
        self._db = db
        self._path = db.path
        self._queue: queue.Queue[Optional[_Rows]] = queue.Queue()
        self._error: Optional[DatabaseError] = None
        self._skipped = 0
        self._lock = threading.Lock()
        self._closed = False
        self._thread = threading.Thread(target=self._run, name=f"rtabmap-db-writer:{db.path.name}", daemon=True)
        self._checkpoint_due = threading.Event()
        self._stopping = False
        self._checkpointer = threading.Thread(target=self._run_checkpoints, daemon=True,
                                              name=f"rtabmap-db-checkpoint:{db.path.name}")
        self._thread.start()
        self._checkpointer.start()
        db._writers.add(self)

    def submit(self, batch: WriteBatch) -> None:
        """Queue a batch for commit in one transaction (returns at once)."""
        if self._closed:
            raise DatabaseError(f"background writer of database {self._path} is closed")
        self._queue.put(_prepare(batch))

    @property
    def pending(self) -> int:
        """Batches submitted and not yet committed (approximate)."""
        return self._queue.unfinished_tasks

    def join(self) -> None:
        """Wait until every submitted batch is committed; re-raise the first error as DatabaseError."""
        self._queue.join()
        with self._lock:
            error, skipped, self._error, self._skipped = self._error, self._skipped, None, 0
        if error is not None:
            if skipped:
                raise DatabaseError(f"{error} ({skipped} later batch(es) were not written)") from error
            raise error

    def close(self) -> None:
        """Commit what is queued, stop the worker thread and re-raise a pending error (idempotent)."""
        if self._closed:
            return
        self._closed = True
        self._queue.put(None)
        self._thread.join()
        self._stopping = True
        self._checkpoint_due.set()
        self._checkpointer.join()
        self._db._writers.discard(self)
        self.join()

    def _run(self) -> None:
        conn: Optional[sqlite3.Connection] = None
        open_error: Optional[DatabaseError] = None
        try:
            conn = self._db._connect()
        except DatabaseError as e:
            open_error = e
        else:
            try:
                conn.execute("PRAGMA wal_autocheckpoint=0")  # _checkpoint() below instead
            except sqlite3.Error as e:
                logger.warning("database %s: SQLite keeps checkpointing inside commits: %s", self._path, e)
        last_checkpoint, batches = time.monotonic(), 0
        while True:
            rows = self._queue.get()
            try:
                if rows is None:
                    break
                if self._error is not None:
                    with self._lock:
                        self._skipped += 1
                    logger.error("batch for database %s skipped after an earlier write error", self._path)
                    continue
                if conn is None:
                    raise open_error
                _apply(conn, self._path, rows)
                batches += 1
            except Exception as e:  # the worker must survive to report; the error goes to join()
                error = e if isinstance(e, DatabaseError) else DatabaseError(
                    f"background write to database {self._path} failed: {e!r}")
                logger.error("%s", error)
                with self._lock:
                    if self._error is None:
                        self._error = error
            finally:
                self._queue.task_done()
            if batches and (batches >= CHECKPOINT_MAX_BATCHES or (
                    self._queue.empty() and time.monotonic() - last_checkpoint >= CHECKPOINT_INTERVAL_S)):
                self._checkpoint_due.set()
                last_checkpoint, batches = time.monotonic(), 0
        if conn is not None:
            conn.close()

    def _run_checkpoints(self) -> None:
        """Checkpoint the WAL when the worker asks (own connection; ends at close())."""
        conn: Optional[sqlite3.Connection] = None
        while True:
            self._checkpoint_due.wait()
            self._checkpoint_due.clear()
            if self._stopping:
                break
            if conn is None:
                try:
                    conn = self._db._connect()
                except DatabaseError as e:
                    logger.warning("WAL checkpoints of database %s: %s (the log is copied at close)", self._path, e)
                    return
            _checkpoint(conn, self._path)
        if conn is not None:
            conn.close()


def _checkpoint(conn: sqlite3.Connection, path: Path) -> None:
    """Copy the committed WAL into the database file without blocking readers (PASSIVE); a
    failure loses nothing (the log keeps it, the next checkpoint or close copies it)."""
    try:
        conn.execute("PRAGMA wal_checkpoint(PASSIVE)").fetchall()
    except sqlite3.Error as e:
        logger.warning("WAL checkpoint of database %s failed (retried later): %s", path, e)


__all__ = [
    "APPLICATION_ID", "SCHEMA_VERSION", "BackgroundWriter", "Database", "NodeInfo", "SensorBlobs", "WriteBatch",
    "decode_depth", "decode_rgb", "encode_depth", "encode_rgb",
]
