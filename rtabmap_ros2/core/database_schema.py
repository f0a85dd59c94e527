"""The map database file: its tables, and how a file is recognised as one (2013 Fig. 3; 2014 §II).

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
* ``cameras``: ``fx fy cx cy`` (px), ``width height`` (px), ``T_base_camera`` blob and, for images
  not rectified, their lens ``distortion`` (float64 coefficients, NULL when rectified; schema 2).
* ``sensor_data``: RGB as JPEG, depth as 16-bit PNG in millimetres, optional 6x6 odometry
  covariance; kept apart from ``nodes`` so graph-only queries never page through images.
* ``words(id, dtype, dim, descriptor)``: the visual words (uint8 binary or float32 descriptors).
* ``node_words(node_id, word_id, count)``: Fig. 3's location -> word references.
* ``links(from_id, to_id, type, T_from_to, information)``: ``pose_to = pose_from @ T_from_to``;
  at most one link per pair of nodes (either orientation).
* ``statistics(frame_index, stamp_ns, data)``: one JSON row per processed frame.

Columns holding arrays are ``ndarray.tobytes()`` (:func:`encode_transform` for 4x4 transforms);
images are encoded by :mod:`rtabmap_ros2.core.database_blobs`. An existing file is opened only
when its header (:func:`check_header`), application id, schema version and tables
(:func:`check_schema`) say it is one of ours; it is never modified before that. A file of schema
version 1 (no ``cameras.distortion``) is read as it is and upgraded in place when opened for writing
(:func:`upgrade_schema`: one column added, nothing else touched).
"""

from __future__ import annotations

import sqlite3
import struct
import time
import urllib.parse
from pathlib import Path
from typing import Any, Optional

import numpy as np

from rtabmap_ros2.errors import DatabaseError

SCHEMA_VERSION = 2
READABLE_SCHEMA_VERSIONS = (1, 2)  # 1: before cameras.distortion
APPLICATION_ID = 0x52544232  # "RTB2" in PRAGMA application_id: marks the file as ours
BUSY_TIMEOUT_S = 30.0  # wait this long for another connection's write lock before failing
SQLITE_HEADER_SIZE = 100
SQLITE_MAGIC = b"SQLite format 3\x00"
SQLITE_MAX_PAGE_SIZE_CODE = 1  # a page size field of 1 means 65536 bytes
SQLITE_MAX_PAGE_SIZE = 65536
DESCRIPTOR_DTYPES = ("uint8", "float32")  # binary (Hamming) or float (L2) descriptors

SCHEMA = """
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
    T_base_camera BLOB NOT NULL,
    distortion BLOB);
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


TABLES = ("info", "maps", "nodes", "scans", "cameras", "sensor_data", "words", "node_words",
          "links", "statistics")


# --------------------------------------------------------------------------------------------
# Column encodings shared by writes and reads
# --------------------------------------------------------------------------------------------

def encode_transform(T: np.ndarray, what: str) -> bytes:
    """Blob of a 4x4 transform (float64, row-major); DatabaseError naming ``what`` otherwise."""
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4):
        raise DatabaseError(f"{what} must be a 4x4 transform, got shape {T.shape}")
    return np.ascontiguousarray(T).tobytes()


def decode_transform(blob: Optional[bytes]) -> Optional[np.ndarray]:
    """4x4 float64 transform of a blob written by :func:`encode_transform` (None for NULL)."""
    return None if blob is None else np.frombuffer(blob, np.float64).reshape(4, 4).copy()


def json_default(value: Any) -> Any:
    """``json.dumps`` default for numpy scalars and arrays (statistics rows, parameters)."""
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    raise TypeError(f"statistics value {value!r} of type {type(value).__name__} is not JSON serialisable")


# --------------------------------------------------------------------------------------------
# Opening: refuse anything that is not one of our databases, never modify it
# --------------------------------------------------------------------------------------------

def check_header(path: Path) -> bool:
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


def connect(path: Path, read_only: bool) -> sqlite3.Connection:
    """A new connection to ``path`` (autocommit: transactions are explicit) for the calling thread."""
    try:
        if read_only:
            uri = "file:" + urllib.parse.quote(str(path)) + "?mode=ro"
            conn = sqlite3.connect(uri, uri=True, timeout=BUSY_TIMEOUT_S, isolation_level=None)
        else:
            conn = sqlite3.connect(str(path), timeout=BUSY_TIMEOUT_S, isolation_level=None)
            conn.execute("PRAGMA synchronous=NORMAL")
    except sqlite3.Error as e:
        raise DatabaseError(f"cannot open database {path}: {e} (the file was left untouched; "
                            "if it is damaged, restore it from a backup)") from e
    return conn


def create_schema(conn: sqlite3.Connection, path: Path) -> None:
    """Create the tables of an empty database in one transaction."""
    conn.execute("BEGIN IMMEDIATE")
    try:
        conn.execute(f"PRAGMA application_id={APPLICATION_ID}")
        conn.execute(f"PRAGMA user_version={SCHEMA_VERSION}")
        for statement in SCHEMA.split(";"):
            if statement.strip():
                conn.execute(statement)
        conn.executemany("INSERT INTO info (key, value) VALUES (?, ?)",
                         [("schema_version", SCHEMA_VERSION), ("created_unix_ns", time.time_ns()),
                          ("max_location_id", 0), ("max_word_id", 0)])
        conn.execute("COMMIT")
    except BaseException:
        conn.execute("ROLLBACK")
        raise


def check_schema(conn: sqlite3.Connection, path: Path) -> int:
    """The schema version of the opened file; DatabaseError when it is not one of our databases at
    a version this code reads (:data:`READABLE_SCHEMA_VERSIONS`)."""
    app_id = conn.execute("PRAGMA application_id").fetchone()[0]
    if app_id != APPLICATION_ID:
        tables = [r[0] for r in conn.execute("SELECT name FROM sqlite_master WHERE type = 'table'")]
        raise DatabaseError(f"{path} is a SQLite file but not an rtabmap_ros2 database "
                            f"(application_id {app_id}, tables {tables[:8]}); it was left untouched")
    version = conn.execute("PRAGMA user_version").fetchone()[0]
    if version not in READABLE_SCHEMA_VERSIONS:
        raise DatabaseError(f"{path} has schema version {version}, this rtabmap_ros2 reads versions "
                            f"{', '.join(map(str, READABLE_SCHEMA_VERSIONS))}; use a matching rtabmap_ros2 version")
    missing = set(TABLES) - {r[0] for r in conn.execute("SELECT name FROM sqlite_master")}
    if missing:
        raise DatabaseError(f"{path} lacks tables {sorted(missing)}: the database is damaged")
    return version


def upgrade_schema(conn: sqlite3.Connection, version: int) -> None:
    """Bring a file of an older schema ``version`` to :data:`SCHEMA_VERSION` in one transaction:
    version 1 gains ``cameras.distortion`` (NULL: its images read as rectified, as they were)."""
    conn.execute("BEGIN IMMEDIATE")
    try:
        if version < 2:
            conn.execute("ALTER TABLE cameras ADD COLUMN distortion BLOB")
        conn.execute(f"PRAGMA user_version={SCHEMA_VERSION}")
        conn.execute("UPDATE info SET value = ? WHERE key = 'schema_version'", (SCHEMA_VERSION,))
        conn.execute("COMMIT")
    except BaseException:
        conn.execute("ROLLBACK")
        raise
