"""What one frame changed in the map, committed to the database in one transaction (Alg. 1 line 17).

:class:`WriteBatch` gathers a frame's changes (new and merged locations, words, weights, WM flags,
links, statistics); :func:`prepare` turns it into SQL parameter rows in the caller's thread
(snapshotting the arrays and validating early) and :func:`commit` writes those rows in ONE
``BEGIN IMMEDIATE ... COMMIT`` transaction, on the caller's connection
(:meth:`Database.write <rtabmap_ros2.core.database.Database.write>`) or on the background
writer's (:class:`BackgroundWriter <rtabmap_ros2.core.database.BackgroundWriter>`).
"""

from __future__ import annotations

import json
import logging
import sqlite3
import time
from dataclasses import dataclass, field
from itertools import repeat
from pathlib import Path
from typing import Optional

import numpy as np

from rtabmap_ros2.core.database_blobs import SensorBlobs
from rtabmap_ros2.core.database_schema import DESCRIPTOR_DTYPES, encode_transform, json_default
from rtabmap_ros2.core.graph import Link, LinkType
from rtabmap_ros2.core.signature import Signature
from rtabmap_ros2.errors import DatabaseError

logger = logging.getLogger(__name__)


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



# --------------------------------------------------------------------------------------------
# Batch -> rows (done in the caller's thread: it snapshots the arrays and validates early)
# --------------------------------------------------------------------------------------------

@dataclass
class BatchRows:
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

def prepare(batch: WriteBatch) -> BatchRows:
    """Turn a batch into SQL parameter rows (copies every array: the caller may reuse them)."""
    rows = BatchRows()
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
        pose = None if sig.T_odom_base is None else encode_transform(sig.T_odom_base, f"{what} T_odom_base")
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
                               float(s.range_max), encode_transform(s.T_base_laser, f"{what} T_base_laser")))
        if sig.camera is None:
            rows.camera_deletes.append((node_id,))
        else:
            c = sig.camera
            rows.cameras.append((node_id, float(c.fx), float(c.fy), float(c.cx), float(c.cy), int(c.width),
                                 int(c.height), encode_transform(c.T_base_camera, f"{what} T_base_camera"),
                                 np.asarray(c.distortion, dtype=np.float64).tobytes() if c.distortion else None))
        if blobs is not None:
            covariance = None
            if blobs.odom_covariance is not None:
                cov = np.asarray(blobs.odom_covariance, dtype=np.float64)
                if cov.shape != (6, 6):
                    raise DatabaseError(f"{what} odometry covariance must be 6x6, got shape {cov.shape}")
                covariance = np.ascontiguousarray(cov).tobytes()
            rows.sensor_data.append((node_id, blobs, covariance))  # images encoded by commit
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
                           encode_transform(link.T_from_to, f"link {a}->{b} T_from_to"),
                           np.ascontiguousarray(info).tobytes()))
    for stats in batch.statistics:
        if "frame_index" not in stats:
            raise DatabaseError(f"statistics row has no 'frame_index' key (keys: {sorted(stats)[:10]}...)")
        stamp = stats.get("stamp_ns")
        rows.statistics.append((int(stats["frame_index"]), None if stamp is None else int(stamp),
                                json.dumps(stats, default=json_default)))
    return rows


def commit(conn: sqlite3.Connection, path: Path, rows: BatchRows) -> None:
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


def _apply_statements(conn: sqlite3.Connection, rows: BatchRows) -> None:
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
    many("INSERT OR REPLACE INTO cameras VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?)", rows.cameras)
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
