"""The Long-Term Memory (LTM) in SQLite: one file per map database (2013 §III-E, Fig. 3; 2014 §II).

:class:`Database` opens one map's file and reads it (signatures for Retrieval, words, links,
the graph of every node for the global map); :class:`BackgroundWriter` commits a frame's
:class:`WriteBatch` from a worker thread. The parts it is built from, one job each:

* :mod:`rtabmap_ros2.core.database_schema`: the tables (the 2013 paper's Fig. 3 and what the
  2014 graph SLAM adds), schema version, and how a file is recognised as ours and opened;
* :mod:`rtabmap_ros2.core.database_batch`: :class:`WriteBatch`, everything one frame changed,
  turned into rows and committed in one transaction;
* :mod:`rtabmap_ros2.core.database_blobs`: :class:`SensorBlobs`, a node's images as JPEG and
  16-bit PNG.

Those names are importable from here too (``from rtabmap_ros2.core.database import WriteBatch``).

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
import threading
import time
import weakref
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterable, Optional

import numpy as np

from rtabmap_ros2.core import files
from rtabmap_ros2.core.database_batch import BatchRows, WriteBatch, commit, prepare
from rtabmap_ros2.core.database_blobs import SensorBlobs, decode_depth, decode_rgb, encode_depth, encode_rgb
from rtabmap_ros2.core.database_schema import (APPLICATION_ID, SCHEMA_VERSION, check_header, check_schema, connect,
                                               create_schema, decode_transform, json_default, upgrade_schema)
from rtabmap_ros2.core.graph import Link, LinkType
from rtabmap_ros2.core.sensor import CameraModel, LaserScan
from rtabmap_ros2.core.signature import Signature
from rtabmap_ros2.errors import DatabaseError, SensorDataError

logger = logging.getLogger(__name__)

# The background writer checkpoints the WAL itself, after the batches it was given are committed
# (join() returns before), at most this often, and after at most this many batches.
CHECKPOINT_INTERVAL_S = 1.0
CHECKPOINT_MAX_BATCHES = 30

# {distortion}: c.distortion, or NULL in a schema 1 file opened read-only (not upgraded).
_SIGNATURE_COLUMNS = """
    n.id, n.map_id, n.stamp_ns, n.weight, n.bad, n.T_odom_base, n.n_words, n.word_ids, n.keypoints,
    n.points3d, s.ranges, s.angle_min, s.angle_increment, s.range_min, s.range_max, s.T_base_laser,
    c.fx, c.fy, c.cx, c.cy, c.width, c.height, c.T_base_camera, {distortion}
    FROM nodes n LEFT JOIN scans s ON s.node_id = n.id LEFT JOIN cameras c ON c.node_id = n.id"""


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


class Database:
    """One map's long-term memory (SQLite, WAL). Not thread-safe: use it from one thread.

    Args:
        path: database file. Created with the schema if missing (its folder must exist); an
            existing file must be one of ours at a schema version this code reads, otherwise
            :class:`DatabaseError` is raised and the file is left untouched; an older version is
            upgraded in place when opened for writing (``database_schema.upgrade_schema``).
        read_only: open with the URI ``file:...?mode=ro``; every write raises DatabaseError.
    """

    def __init__(self, path: str | Path, read_only: bool = False) -> None:
        self.path = Path(path).expanduser().absolute()
        self.read_only = read_only
        self._conn: Optional[sqlite3.Connection] = None
        self._signature_columns = _SIGNATURE_COLUMNS.format(distortion="c.distortion")
        self._writers: weakref.WeakSet[BackgroundWriter] = weakref.WeakSet()
        if not self.path.parent.is_dir():
            raise DatabaseError(f"cannot open database {self.path}: folder {self.path.parent} does not exist")
        exists = self.path.exists()
        if read_only and not exists:
            raise DatabaseError(f"cannot open database {self.path} read-only: the file does not exist")
        if exists and not self.path.is_file():
            raise DatabaseError(f"cannot open database {self.path}: it is not a regular file")
        new = check_header(self.path) if exists else True
        if new and read_only:
            raise DatabaseError(f"{self.path} is empty: not an rtabmap_ros2 database")
        self._conn = self._connect()
        try:
            if new:
                create_schema(self._conn, self.path)
                logger.info("created database %s (schema version %d)", self.path, SCHEMA_VERSION)
            else:
                version = check_schema(self._conn, self.path)
                if version < SCHEMA_VERSION and not read_only:
                    upgrade_schema(self._conn, version)
                    logger.info("database %s upgraded from schema version %d to %d", self.path, version,
                                SCHEMA_VERSION)
                    version = SCHEMA_VERSION
                if version < 2:
                    self._signature_columns = _SIGNATURE_COLUMNS.format(distortion="NULL")
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
        return connect(self.path, self.read_only)

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
        commit(self.conn, self.path, prepare(batch))

    def set_parameters(self, parameters: dict) -> None:
        """Store the configuration used (a JSON-serialisable dict)."""
        self._writable()
        try:
            text = json.dumps(parameters, default=json_default, sort_keys=True)
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
        rows = self._query(f"SELECT {self._signature_columns} WHERE n.id IN (SELECT value FROM json_each(?))",
                           (json.dumps(ids),))
        by_id = {row[0]: row for row in rows}
        missing = [i for i in ids if i not in by_id]
        if missing:
            raise DatabaseError(f"locations {missing[:10]} are not in database {self.path}")
        return [self._signature(by_id[i]) for i in ids]

    def _signature(self, row: tuple) -> Signature:
        (node_id, map_id, stamp_ns, weight, bad, pose, n, word_ids, keypoints, points3d,
         ranges, angle_min, angle_increment, range_min, range_max, T_base_laser,
         fx, fy, cx, cy, width, height, T_base_camera, distortion) = row
        try:
            scan = None if ranges is None else LaserScan(
                np.frombuffer(ranges, np.float32).copy(), angle_min, angle_increment, range_min, range_max,
                decode_transform(T_base_laser))
            camera = None if fx is None else CameraModel(
                fx, fy, cx, cy, width, height, decode_transform(T_base_camera),
                () if distortion is None else tuple(np.frombuffer(distortion, np.float64).tolist()))
            return Signature(
                id=node_id, map_id=map_id, stamp_ns=stamp_ns, weight=weight, bad=bool(bad),
                T_odom_base=decode_transform(pose),
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
                                  decode_transform(row[6]))
                for row in self._query(sql, params)}

    def load_links(self, node_ids: Optional[Iterable[int]] = None) -> list[Link]:
        """Every link (or those touching ``node_ids``), as stored (``pose_to = pose_from @ T_from_to``)."""
        sql = "SELECT from_id, to_id, type, T_from_to, information FROM links"
        params: tuple = ()
        if node_ids is not None:
            sql += (" WHERE from_id IN (SELECT value FROM json_each(?1))"
                    " OR to_id IN (SELECT value FROM json_each(?1))")
            params = (json.dumps([int(i) for i in node_ids]),)
        return [Link(a, b, self._link_type(a, b, kind), decode_transform(T),
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
        return {i: NodeInfo(m, s, w, decode_transform(p), bool(wm), bool(bad)) for i, m, s, w, p, wm, bad in rows}

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
        self._queue: queue.Queue[Optional[BatchRows]] = queue.Queue()
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
        self._queue.put(prepare(batch))

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
                commit(conn, self._path, rows)
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
