"""Behaviour of the SQLite long-term memory (core/database.py and its parts database_schema.py,
database_batch.py, database_blobs.py)."""

from __future__ import annotations

import sqlite3
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from rtabmap_ros2.core import transforms
from rtabmap_ros2.core.database import (BackgroundWriter, Database, NodeInfo, SensorBlobs, WriteBatch,
                                        decode_depth, decode_rgb, encode_depth, encode_rgb)
from rtabmap_ros2.core.graph import Link, LinkType
from rtabmap_ros2.core.sensor import CameraModel, LaserScan
from rtabmap_ros2.core.signature import Signature
from rtabmap_ros2.errors import DatabaseError

N_WORDS = 120
IMAGE_H, IMAGE_W = 48, 64


def make_signature(rng, node_id: int, map_id: int = 0, n: int = N_WORDS, first_word: int = 1) -> Signature:
    """A full signature: words (some repeated), keypoints, points3d with NaNs, pose, scan, camera."""
    word_ids = np.arange(first_word, first_word + n, dtype=np.int64)
    word_ids[-5:] = word_ids[:5]  # repeated words (count 2 in the references)
    points3d = rng.normal(size=(n, 3)).astype(np.float32)
    points3d[::7] = np.nan
    scan = LaserScan(rng.uniform(0.1, 5.0, 181).astype(np.float32), -np.pi / 2, np.pi / 180, 0.05, 5.6,
                     transforms.from_xyz_quat_xyzw([0.1, 0, 0.2], [0, 0, 0, 1]))
    camera = CameraModel(525.0, 526.0, 31.5, 23.5, IMAGE_W, IMAGE_H,
                         transforms.from_xyz_quat_xyzw([0.05, 0, 0.3], [-0.5, 0.5, -0.5, 0.5]))
    return Signature(id=node_id, map_id=map_id, stamp_ns=1_700_000_000_000_000_000 + node_id, weight=node_id % 3,
                     word_ids=word_ids, keypoints=rng.uniform(0, 60, (n, 2)).astype(np.float32),
                     points3d=points3d,
                     T_odom_base=transforms.from_xyz_quat_xyzw(rng.normal(size=3), rng.normal(size=4)),
                     scan=scan, camera=camera)


def make_images(rng) -> tuple[np.ndarray, np.ndarray]:
    """A smooth RGB image (JPEG-friendly) and a depth image (m) with invalid pixels."""
    yy, xx = np.mgrid[0:IMAGE_H, 0:IMAGE_W]
    rgb = np.stack([xx * 4, yy * 5, (xx + yy) * 2], axis=2).clip(0, 255).astype(np.uint8)
    depth = rng.uniform(0.3, 8.0, (IMAGE_H, IMAGE_W)).astype(np.float32)
    depth[0, :] = np.nan
    depth[1, :3] = 0.0
    return rgb, depth


def make_words(rng, first: int, n: int, dtype=np.uint8) -> dict[int, np.ndarray]:
    if dtype == np.uint8:
        return {first + i: rng.integers(0, 256, 32, dtype=np.uint8) for i in range(n)}
    return {first + i: rng.normal(size=128).astype(np.float32) for i in range(n)}


@pytest.fixture
def db_path(tmp_path) -> Path:
    return tmp_path / "map.db"


@pytest.fixture
def db(db_path):
    database = Database(db_path)
    yield database
    database.close()


def test_signature_and_sensor_round_trip(db, rng):
    sig = make_signature(rng, 7, map_id=2)
    rgb, depth = make_images(rng)
    covariance = np.diag([0.01, 0.02, 0.03, 0.001, 0.002, 0.003])
    db.write(WriteBatch(locations=[(sig, SensorBlobs.encode(rgb, depth, covariance))]))

    got = db.load_signature(7)
    assert (got.id, got.map_id, got.stamp_ns, got.weight, got.bad) == (7, 2, sig.stamp_ns, sig.weight, False)
    np.testing.assert_array_equal(got.word_ids, sig.word_ids)
    assert got.word_ids.dtype == np.int64
    np.testing.assert_array_equal(got.keypoints, sig.keypoints)
    np.testing.assert_array_equal(got.points3d, sig.points3d)  # NaN positions equal too
    assert np.isnan(got.points3d[::7]).all()
    np.testing.assert_array_equal(got.T_odom_base, sig.T_odom_base)
    np.testing.assert_array_equal(got.scan.ranges, sig.scan.ranges)
    assert (got.scan.angle_min, got.scan.angle_increment, got.scan.range_min, got.scan.range_max) == pytest.approx(
        (sig.scan.angle_min, sig.scan.angle_increment, sig.scan.range_min, sig.scan.range_max))
    np.testing.assert_array_equal(got.scan.T_base_laser, sig.scan.T_base_laser)
    assert (got.camera.fx, got.camera.fy, got.camera.cx, got.camera.cy, got.camera.width, got.camera.height) == (
        525.0, 526.0, 31.5, 23.5, IMAGE_W, IMAGE_H)
    np.testing.assert_array_equal(got.camera.T_base_camera, sig.camera.T_base_camera)
    got.word_ids[0] = -1  # loaded arrays are writable copies

    blobs = db.load_sensor_blobs(7)
    rgb_back, depth_back = blobs.rgb(), blobs.depth_m()
    assert rgb_back.shape == rgb.shape and rgb_back.dtype == np.uint8
    assert np.abs(rgb_back.astype(int) - rgb.astype(int)).mean() < 3.0  # JPEG: approximately equal
    invalid = ~np.isfinite(depth) | (depth <= 0)
    assert np.array_equal(np.isnan(depth_back), invalid)
    assert np.abs(depth_back[~invalid] - depth[~invalid]).max() <= 0.0005 + 1e-6  # within 1 mm (rounded)
    np.testing.assert_array_equal(blobs.odom_covariance, covariance)


def test_a_raw_cameras_lens_distortion_round_trips(db, rng):
    fr1 = (0.2624, -0.9531, -0.0054, 0.0026, 1.1633)
    sig = make_signature(rng, 4)
    raw = replace(sig, id=5, camera=replace(sig.camera, distortion=fr1))
    db.write(WriteBatch(locations=[(sig, None), (raw, None)]))
    assert db.load_signature(5).camera.distortion == fr1
    assert db.load_signature(4).camera.distortion == ()   # rectified images: none stored


def _as_schema_1(path: Path) -> None:
    """Turn a database file into what schema version 1 wrote (no cameras.distortion)."""
    conn = sqlite3.connect(str(path), isolation_level=None)
    conn.execute("ALTER TABLE cameras DROP COLUMN distortion")
    conn.execute("PRAGMA user_version=1")
    conn.execute("UPDATE info SET value = 1 WHERE key = 'schema_version'")
    conn.close()


def test_a_schema_1_file_is_read_as_it_is_and_upgraded_when_written(db_path, rng):
    sig = make_signature(rng, 1)
    with Database(db_path) as database:
        database.write(WriteBatch(locations=[(sig, None)], links=[Link(1, 2, LinkType.NEIGHBOR)]))
    _as_schema_1(db_path)
    content = db_path.read_bytes()
    with Database(db_path, read_only=True) as database:   # export, report: the file is not touched
        got = database.load_signature(1)
        assert got.camera.distortion == () and got.camera.fx == sig.camera.fx
    assert db_path.read_bytes() == content
    with Database(db_path) as database:                   # map, merge: upgraded in place, nothing lost
        np.testing.assert_array_equal(database.load_signature(1).word_ids, sig.word_ids)
        assert len(database.load_links()) == 1
        raw = replace(sig, id=3, camera=replace(sig.camera, distortion=(0.1, -0.2, 0, 0)))
        database.write(WriteBatch(locations=[(raw, None)]))
    with Database(db_path, read_only=True) as database:
        assert database.load_signature(3).camera.distortion == (0.1, -0.2, 0.0, 0.0)
        assert database.conn.execute("PRAGMA user_version").fetchone()[0] == 2


def test_a_newer_schema_is_refused_and_untouched(db_path, rng):
    with Database(db_path) as database:
        database.write(WriteBatch(locations=[(make_signature(rng, 1), None)]))
    conn = sqlite3.connect(str(db_path), isolation_level=None)
    conn.execute("PRAGMA user_version=99")
    conn.close()
    content = db_path.read_bytes()
    with pytest.raises(DatabaseError, match="schema version 99"):
        Database(db_path)
    assert db_path.read_bytes() == content


def test_signature_without_optional_parts(db):
    sig = Signature(id=3, map_id=0, stamp_ns=5, bad=True)
    db.write(WriteBatch(locations=[(sig, None)]))
    got = db.load_signature(3)
    assert got.bad and got.T_odom_base is None and got.scan is None and got.camera is None
    assert got.word_ids.shape == (0,) and got.keypoints.shape == (0, 2) and got.points3d.shape == (0, 3)
    assert db.load_sensor_blobs(3) == SensorBlobs()


def test_load_signatures_keeps_order_and_reports_missing(db, rng):
    db.write(WriteBatch(locations=[(make_signature(rng, i), None) for i in (1, 2, 3)]))
    assert [s.id for s in db.load_signatures([3, 1])] == [3, 1]
    with pytest.raises(DatabaseError, match=r"\[9\]"):
        db.load_signatures([1, 9])


def test_words_round_trip_exactly(db, rng):
    binary = make_words(rng, 1, 50)
    db.write(WriteBatch(words=binary))
    loaded = db.load_words(list(binary) + [999])  # absent ids are skipped
    assert loaded.keys() == binary.keys()
    for word_id, descriptor in binary.items():
        assert loaded[word_id].dtype == np.uint8
        np.testing.assert_array_equal(loaded[word_id], descriptor)
    ids, matrix = db.load_descriptors([5, 2])
    np.testing.assert_array_equal(ids, [2, 5])
    np.testing.assert_array_equal(matrix, np.stack([binary[2], binary[5]]))
    assert db.max_word_id() == 50


def test_float_words_round_trip(tmp_path, rng):
    with Database(tmp_path / "sift.db") as database:
        words = make_words(rng, 10, 5, dtype=np.float32)
        database.write(WriteBatch(words=words))
        loaded = database.load_words()
        for word_id, descriptor in words.items():
            assert loaded[word_id].dtype == np.float32
            np.testing.assert_array_equal(loaded[word_id], descriptor)


def test_bad_descriptor_dtype_rejected_and_nothing_written(db, rng):
    with pytest.raises(DatabaseError, match="word 4"):
        db.write(WriteBatch(words={4: np.zeros(32, np.int32)}, locations=[(make_signature(rng, 1), None)]))
    assert db.load_nodes() == {}


def test_links_round_trip_and_replace(db, random_se3):
    info = np.diag([100.0, 100.0, 1e6, 1e6, 1e6, 400.0])
    neighbor = Link(1, 2, LinkType.NEIGHBOR, random_se3(), info)
    loop = Link(5, 1, LinkType.LOOP_INTER, random_se3(), np.eye(6) * 3)
    db.write(WriteBatch(links=[neighbor, loop, Link(2, 3, LinkType.NEIGHBOR)]))
    by_key = {link.key(): link for link in db.load_links()}
    assert set(by_key) == {(1, 2), (1, 5), (2, 3)}
    got = by_key[(1, 5)]
    assert (got.from_id, got.to_id, got.type) == (5, 1, LinkType.LOOP_INTER)
    np.testing.assert_array_equal(got.T_from_to, loop.T_from_to)
    np.testing.assert_array_equal(got.information, loop.information)
    np.testing.assert_array_equal(by_key[(1, 2)].information, info)

    # Re-adding the link in the other orientation replaces it; deleting works either way round.
    db.write(WriteBatch(links=[Link(1, 5, LinkType.LOOP_INTRA, random_se3())], deleted_links=[(3, 2)]))
    links = db.load_links()
    assert {link.key() for link in links} == {(1, 2), (1, 5)}
    assert [link.type for link in links if link.key() == (1, 5)] == [LinkType.LOOP_INTRA]
    assert {link.key() for link in db.load_links(node_ids=[2])} == {(1, 2)}


def test_link_ends_and_a_link_of_unknown_type(db, random_se3):
    """The graph search's reader gives each link from the asked node's side; a link whose type is
    not one we write (a damaged or foreign database) is an error naming it, from either reader."""
    db.write(WriteBatch(links=[Link(1, 2, LinkType.NEIGHBOR, random_se3()), Link(5, 1, LinkType.LOOP_INTER)]))
    assert sorted(db.link_ends([1])) == [(1, 2, LinkType.NEIGHBOR), (1, 5, LinkType.LOOP_INTER)]
    assert db.link_ends([2, 7]) == [(2, 1, LinkType.NEIGHBOR)]
    db.conn.execute("UPDATE links SET type = 'teleport' WHERE from_id = 5")
    for read in (lambda: db.load_links(), lambda: db.link_ends([1])):
        with pytest.raises(DatabaseError, match="unknown type 'teleport'"):
            read()


def test_weights_in_wm_and_node_infos(db, rng):
    sigs = [make_signature(rng, i, map_id=i // 3) for i in range(1, 6)]
    db.write(WriteBatch(locations=[(s, None) for s in sigs]))
    assert db.wm_ids() == [1, 2, 3, 4, 5]  # new locations start in WM
    db.write(WriteBatch(weights={2: 9, 4: 0}, in_wm={1: False, 3: False}))
    nodes = db.load_nodes()
    assert isinstance(nodes[2], NodeInfo)
    assert nodes[2].weight == 9 and nodes[4].weight == 0
    assert db.wm_ids() == [2, 4, 5]
    assert [nodes[i].in_wm for i in (1, 2, 3)] == [False, True, False]
    assert nodes[5].map_id == 1 and nodes[5].stamp_ns == sigs[4].stamp_ns
    np.testing.assert_array_equal(nodes[4].T_odom_base, sigs[3].T_odom_base)
    # Re-saving a location (transfer to LTM) keeps its stored images and in_wm flag.
    rgb, depth = make_images(rng)
    db.write(WriteBatch(locations=[(sigs[0], SensorBlobs.encode(rgb, depth))]))
    db.write(WriteBatch(locations=[(sigs[0], None)]))
    assert db.load_sensor_blobs(1).rgb_jpeg is not None
    assert not db.load_nodes()[1].in_wm


def test_update_of_unknown_location_rolls_back_the_whole_batch(db, rng):
    db.write(WriteBatch(locations=[(make_signature(rng, 1), None)]))
    with pytest.raises(DatabaseError, match=r"location 42.*rolled back|rolled back.*location 42"):
        db.write(WriteBatch(weights={1: 7, 42: 1}, statistics=[{"frame_index": 0}]))
    assert db.load_nodes()[1].weight == make_signature(rng, 1).weight
    assert db.load_statistics() == []


def test_in_wm_update_of_many_locations_names_the_unknown_one_and_rolls_back(db, rng):
    db.write(WriteBatch(locations=[(make_signature(rng, i), None) for i in range(1, 101)]))
    with pytest.raises(DatabaseError, match=r"in_wm update of location 500\b"):
        db.write(WriteBatch(in_wm={**{i: False for i in range(1, 101)}, 500: False}))
    assert all(node.in_wm for node in db.load_nodes().values())
    db.write(WriteBatch(in_wm={i: False for i in range(1, 101)}))  # a WM cap drop: all at once
    assert not any(node.in_wm for node in db.load_nodes().values())


def test_deleted_locations_are_gone_with_their_links(db, rng):
    rgb, depth = make_images(rng)
    db.write(WriteBatch(locations=[(make_signature(rng, i), SensorBlobs.encode(rgb, depth)) for i in (1, 2, 3)],
                        links=[Link(1, 2, LinkType.NEIGHBOR), Link(2, 3, LinkType.NEIGHBOR)]))
    # Rehearsal (2013 §III-B) merges 2 into 3.
    db.write(WriteBatch(deleted_locations=[2], links=[Link(1, 3, LinkType.NEIGHBOR)], weights={3: 4}))
    assert set(db.load_nodes()) == {1, 3}
    with pytest.raises(DatabaseError, match="location"):
        db.load_signature(2)
    with pytest.raises(DatabaseError):
        db.load_sensor_blobs(2)
    assert {link.key() for link in db.load_links()} == {(1, 3)}
    assert db.conn.execute("SELECT count(*) FROM node_words WHERE node_id = 2").fetchone()[0] == 0
    assert db.max_location_id() == 3


def test_requantised_words_update_signature_and_references(db, rng):
    sig = make_signature(rng, 1)
    db.write(WriteBatch(locations=[(sig, None)]))
    new_ids = sig.word_ids + 1000
    db.write(WriteBatch(location_words={1: new_ids}))
    np.testing.assert_array_equal(db.load_signature(1).word_ids, new_ids)
    refs = dict(db.conn.execute("SELECT word_id, count FROM node_words WHERE node_id = 1").fetchall())
    assert refs == {w + 1000: c for w, c in sig.word_counts().items()}
    assert max(refs.values()) == 2  # repeated words are counted
    with pytest.raises(DatabaseError, match="word ids for"):
        db.write(WriteBatch(location_words={1: new_ids[:3]}))
    # A location inserted and re-quantised in the same batch ends with the re-quantised words.
    sig2 = make_signature(rng, 2)
    db.write(WriteBatch(locations=[(sig2, None)], location_words={2: sig2.word_ids + 5000}))
    np.testing.assert_array_equal(db.load_signature(2).word_ids, sig2.word_ids + 5000)
    refs2 = db.conn.execute("SELECT min(word_id) FROM node_words WHERE node_id = 2").fetchone()[0]
    assert refs2 == sig2.word_ids.min() + 5000


def test_statistics_round_trip(db):
    rows = [{"frame_index": i, "stamp_ns": 10 * i, "location_id": i + 1, "process_time_ms": np.float64(1.5 * i),
             "loop_closure_type": "" if i else "loop_intra", "new_map": bool(i == 0),
             "timings_ms": {"features": 2.5}} for i in range(4)]
    assert db.max_frame_index() == -1
    db.write(WriteBatch(statistics=rows[2:]))
    db.write(WriteBatch(statistics=rows[:2]))
    loaded = db.load_statistics()
    assert [r["frame_index"] for r in loaded] == [0, 1, 2, 3]
    assert db.max_frame_index() == 3
    assert loaded[3] == {**rows[3], "process_time_ms": 4.5}
    with pytest.raises(DatabaseError, match="frame_index"):
        db.write(WriteBatch(statistics=[{"stamp_ns": 1}]))


def test_parameters_round_trip(db):
    assert db.get_parameters() == {}
    db.set_parameters({"memory": {"stm_size": 10}, "bayes": {"loop_threshold": 0.11}})
    assert db.get_parameters()["memory"]["stm_size"] == 10


def test_reopen_continues_ids_and_maps(db_path, rng):
    with Database(db_path) as database:
        assert (database.max_location_id(), database.max_word_id(), database.max_map_id()) == (0, 0, -1)
        database.write(WriteBatch(locations=[(make_signature(rng, i, map_id=0), None) for i in (1, 2, 3)],
                                  words=make_words(rng, 1, 20)))
        database.write(WriteBatch(deleted_locations=[3]))  # the highest id is gone, but never reused
    with Database(db_path) as database:
        assert database.max_location_id() == 3
        assert database.max_word_id() == 20
        assert database.max_map_id() == 0
        database.write(WriteBatch(locations=[(make_signature(rng, 4, map_id=1), None)]))
        assert database.max_map_id() == 1
        assert sorted(database.load_nodes()) == [1, 2, 4]


def test_missing_folder_and_wrong_files(tmp_path):
    with pytest.raises(DatabaseError, match="does not exist"):
        Database(tmp_path / "nope" / "map.db")
    with pytest.raises(DatabaseError, match="does not exist"):
        Database(tmp_path / "absent.db", read_only=True)
    other = tmp_path / "other.db"
    conn = sqlite3.connect(other)
    conn.execute("CREATE TABLE t (x)")
    conn.commit()
    conn.close()
    before = other.read_bytes()
    with pytest.raises(DatabaseError, match="not an rtabmap_ros2 database"):
        Database(other)
    assert other.read_bytes() == before


def test_random_bytes_file_is_refused_and_untouched(tmp_path, rng):
    path = tmp_path / "random.db"
    content = rng.integers(0, 256, 8192, dtype=np.uint8).tobytes()
    path.write_bytes(content)
    for read_only in (False, True):
        with pytest.raises(DatabaseError, match="random.db.*not a database"):
            Database(path, read_only=read_only)
    assert path.read_bytes() == content
    assert sorted(p.name for p in tmp_path.iterdir()) == ["random.db"]


@pytest.mark.parametrize("fraction", [0.5, 0.9, 0.003])
def test_truncated_copy_is_refused_and_untouched(tmp_path, rng, fraction):
    real = tmp_path / "real.db"
    rgb, depth = make_images(rng)
    with Database(real) as database:
        for i in range(1, 8):
            database.write(WriteBatch(locations=[(make_signature(rng, i), SensorBlobs.encode(rgb, depth))],
                                      words=make_words(rng, 1 + 200 * i, 100)))
    data = real.read_bytes()
    truncated = tmp_path / "truncated.db"
    truncated.write_bytes(data[:int(len(data) * fraction)])
    before = truncated.read_bytes()
    with pytest.raises(DatabaseError, match="truncated.db"):
        Database(truncated)
    assert truncated.read_bytes() == before
    assert not (tmp_path / "truncated.db-wal").exists()


def test_damaged_schema_page_is_refused_and_untouched(tmp_path, rng):
    path = tmp_path / "damaged.db"
    with Database(path) as database:
        database.write(WriteBatch(locations=[(make_signature(rng, 1), None)]))
    data = bytearray(path.read_bytes())
    page_size = int.from_bytes(data[16:18], "big")
    data[100:page_size] = rng.integers(0, 256, page_size - 100, dtype=np.uint8).tobytes()  # sqlite_master
    path.write_bytes(bytes(data))
    with pytest.raises(DatabaseError, match="damaged.db"):
        Database(path)
    assert path.read_bytes() == bytes(data)


def test_paths_with_uri_characters(tmp_path, rng):
    path = tmp_path / "a dir #1" / "map?v=2%.db"
    path.parent.mkdir()
    with Database(path) as database:
        database.write(WriteBatch(locations=[(make_signature(rng, 1), None)]))
    with Database(path, read_only=True) as database:
        assert list(database.load_nodes()) == [1]
    assert sorted(p.name for p in path.parent.iterdir()) == ["map?v=2%.db"]


def test_read_only_never_modifies_the_file(db_path, rng):
    rgb, depth = make_images(rng)
    with Database(db_path) as database:
        database.write(WriteBatch(locations=[(make_signature(rng, 1), SensorBlobs.encode(rgb, depth))],
                                  links=[Link(1, 2, LinkType.NEIGHBOR)], statistics=[{"frame_index": 0}]))
    content, mtime = db_path.read_bytes(), db_path.stat().st_mtime_ns
    with Database(db_path, read_only=True) as database:
        assert database.load_signature(1).id == 1
        assert len(database.load_links()) == 1 and database.load_statistics()
        database.load_sensor_blobs(1).rgb()
        with pytest.raises(DatabaseError, match="read-only"):
            database.write(WriteBatch(weights={1: 3}))
        with pytest.raises(DatabaseError, match="read-only"):
            database.set_parameters({"a": 1})
        with pytest.raises(DatabaseError, match="read-only"):
            BackgroundWriter(database)
    assert db_path.read_bytes() == content
    assert db_path.stat().st_mtime_ns == mtime
    # A cleanly closed database is back in rollback-journal mode: reading creates no side files.
    assert sorted(p.name for p in db_path.parent.iterdir()) == ["map.db"]


def test_read_only_sees_a_live_writer(db_path, rng):
    with Database(db_path) as writer:
        writer.write(WriteBatch(locations=[(make_signature(rng, 1), None)]))
        with Database(db_path, read_only=True) as reader:
            assert list(reader.load_nodes()) == [1]
            writer.write(WriteBatch(locations=[(make_signature(rng, 2), None)]))
            assert list(reader.load_nodes()) == [1, 2]


def test_background_writer_commits_and_main_thread_reads(db, rng):
    writer = BackgroundWriter(db)
    main_thread_reads = []
    for i in range(1, 21):
        sig = make_signature(rng, i, first_word=1 + N_WORDS * i)
        writer.submit(WriteBatch(locations=[(sig, None)], words=make_words(rng, 1 + N_WORDS * i, N_WORDS),
                                 statistics=[{"frame_index": i}]))
        sig.word_ids[:] = -1  # the writer snapshotted the batch at submit()
        main_thread_reads.append(len(db.load_nodes()))  # reading while the worker writes
    writer.join()
    assert main_thread_reads == sorted(main_thread_reads)
    assert sorted(db.load_nodes()) == list(range(1, 21))
    assert (db.load_signature(20).word_ids >= 0).all()
    assert len(db.load_statistics()) == 20
    writer.close()


def test_background_writer_reports_first_error_then_recovers(db, rng):
    writer = BackgroundWriter(db)
    writer.submit(WriteBatch(locations=[(make_signature(rng, 1), None)]))
    writer.submit(WriteBatch(weights={99: 1}))  # unknown location: fails in the worker
    writer.submit(WriteBatch(weights={1: 5}))  # skipped: it may depend on the failed batch
    with pytest.raises(DatabaseError, match="location 99"):
        writer.join()
    assert db.load_nodes()[1].weight != 5
    writer.submit(WriteBatch(weights={1: 6}))
    writer.join()
    assert db.load_nodes()[1].weight == 6
    with pytest.raises(DatabaseError, match="word 3"):
        writer.submit(WriteBatch(words={3: np.zeros((2, 2), np.uint8)}))  # malformed: raised at submit
    writer.close()
    with pytest.raises(DatabaseError, match="closed"):
        writer.submit(WriteBatch())


def test_background_writer_checkpoints_the_wal_into_the_file_after_the_batches(db, rng, monkeypatch):
    import rtabmap_ros2.core.database as database_module

    monkeypatch.setattr(database_module, "CHECKPOINT_INTERVAL_S", 0.0)  # after every batch
    db.write(WriteBatch(locations=[(make_signature(rng, 1), None)]))
    db.conn.execute("PRAGMA wal_checkpoint(TRUNCATE)")
    size = db.path.stat().st_size
    writer = BackgroundWriter(db)
    rgb, depth = make_images(rng)
    for i in range(2, 12):  # ~10 pages a location with its images: far from SQLite's own 1,000
        writer.submit(WriteBatch(locations=[(make_signature(rng, i), SensorBlobs.encode(rgb, depth))]))
    writer.join()
    deadline = time.monotonic() + 10.0
    while db.path.stat().st_size == size and time.monotonic() < deadline:
        time.sleep(0.01)
    assert db.path.stat().st_size > size  # the database file itself holds the new locations
    writer.close()
    assert sorted(db.load_nodes()) == list(range(1, 12))


def test_a_slow_checkpoint_does_not_hold_back_the_next_batch(db, rng, monkeypatch):
    """Issue 50: a checkpoint's fsync took 0.6 s on a machine busy with I/O, and the next frame's
    batch waited for it (its join, Alg. 1 line 17); checkpoints now have a thread of their own."""
    import threading

    import rtabmap_ros2.core.database as database_module

    monkeypatch.setattr(database_module, "CHECKPOINT_INTERVAL_S", 0.0)  # after every batch
    checkpointing, release = threading.Event(), threading.Event()
    checkpoint = database_module._checkpoint

    def slow_checkpoint(conn, path):
        checkpointing.set()
        release.wait(10)
        checkpoint(conn, path)
    monkeypatch.setattr(database_module, "_checkpoint", slow_checkpoint)
    writer = BackgroundWriter(db)
    writer.submit(WriteBatch(locations=[(make_signature(rng, 1), None)]))
    writer.join()
    assert checkpointing.wait(10)  # a checkpoint is under way, and stays so until released
    start = time.monotonic()
    writer.submit(WriteBatch(locations=[(make_signature(rng, 2), None)]))
    writer.join()
    assert time.monotonic() - start < 2.0, "the batch waited for the checkpoint"
    assert sorted(db.load_nodes()) == [1, 2]
    release.set()
    writer.close()
    assert not writer._checkpointer.is_alive()


def test_close_finishes_background_writes(db_path, rng):
    database = Database(db_path)
    writer = BackgroundWriter(database)
    for i in range(1, 6):
        writer.submit(WriteBatch(locations=[(make_signature(rng, i), None)]))
    database.close()  # joins the writer first
    assert not writer._thread.is_alive()
    with Database(db_path, read_only=True) as reopened:
        assert sorted(reopened.load_nodes()) == [1, 2, 3, 4, 5]


def test_backup_is_a_consistent_copy(db, rng, tmp_path):
    db.write(WriteBatch(locations=[(make_signature(rng, 1), None)], words=make_words(rng, 1, 10)))
    target = tmp_path / "backup.db"
    db.backup(target)
    with Database(target, read_only=True) as copy:
        assert list(copy.load_nodes()) == [1] and len(copy.load_words()) == 10
        assert copy.integrity_check() == ["ok"]
    with pytest.raises(DatabaseError, match="already exists"):
        db.backup(target)


def test_depth_encoding_rules():
    depth = np.array([[np.nan, np.inf, -1.0, 0.0], [0.0014, 1.2344, 70.0, 65.535]], np.float32)
    png = encode_depth(depth)
    back = decode_depth(png)
    assert back.dtype == np.float32
    assert np.isnan(back[0]).all()
    np.testing.assert_allclose(back[1], [0.001, 1.234, 65.535, 65.535], atol=1e-6)  # clipped to 65.535 m
    # Any float depth: -inf invalid, a huge finite one clipped, a tie rounded as float64 arithmetic does.
    wide = decode_depth(encode_depth(np.array([[-np.inf, 1e300, np.float32(1.2345), 2.0004999]])))
    assert np.isnan(wide[0, 0]) and wide[0, 1] == np.float32(65.535)
    np.testing.assert_allclose(wide[0, 2:], [1.235, 2.0], atol=1e-6)


def test_rgb_encoding_rules(rng):
    rgb = np.zeros((8, 8, 3), np.uint8)
    rgb[..., 0] = 200  # pure red stays red: channel order is preserved
    back = decode_rgb(encode_rgb(rgb))
    assert back[..., 0].min() > 180 and back[..., 2].max() < 20
    with pytest.raises(Exception, match="HxWx3"):
        encode_rgb(np.zeros((8, 8), np.uint8))
    with pytest.raises(DatabaseError, match="JPEG"):
        decode_rgb(b"not a jpeg")


def test_backup_never_follows_a_symlink_at_its_name(db, rng, tmp_path):
    """Issue 15 case 8: a dangling symlink at the backup name must not receive the database."""
    db.write(WriteBatch(locations=[(make_signature(rng, 1), None)], words=make_words(rng, 1, 10)))
    target = tmp_path / "backup.db"
    target.symlink_to(tmp_path / "stolen.db")
    with pytest.raises(DatabaseError, match="already exists"):
        db.backup(target)
    assert not (tmp_path / "stolen.db").exists() and target.is_symlink()
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".backup.db")]   # no temporary left
