"""io/merge.py: input databases read back as frames with their stored features, the checks, the
report's node accounting, and rehearsal kept from merging nodes an input kept."""

from __future__ import annotations

import numpy as np
import pytest

from rtabmap_ros2.core.database import Database
from rtabmap_ros2.core.params import Params, default_config_path
from rtabmap_ros2.core.rtabmap import Rtabmap
from rtabmap_ros2.errors import DatabaseError
from rtabmap_ros2.io.merge import StoredFeatures, StoredSession, inspect_inputs, merge_report

SEED = 3
FRAMES = 8
# Session 2 of the small simulation starts with a stop: its first frames see the same view.
STOPPED_FRAMES = 10


@pytest.fixture(scope="module")
def sim():
    from rtabmap_ros2.sim import build_world, make_sessions

    world = build_world(seed=SEED)
    return world, make_sessions(world, small=True, session_gap_s=0)


def make_db(path, sim, session: int, frames: int, overrides=()):
    from rtabmap_ros2.sim import render_frame

    world, sessions = sim
    params = Params.from_yaml(default_config_path()).with_overrides(list(overrides))
    with Rtabmap(params, path) as rtabmap:
        for i in range(frames):
            rtabmap.process(render_frame(world, sessions[session], i))
    return path


@pytest.fixture(scope="module")
def two(sim, tmp_path_factory):
    out = tmp_path_factory.mktemp("merge_unit")
    return make_db(out / "a.db", sim, 0, FRAMES), make_db(out / "b.db", sim, 1, FRAMES)


def test_a_stored_session_gives_back_its_nodes_as_frames_with_their_stored_features(two):
    a, b = inspect_inputs(list(two), reextract=False)
    assert a.label == "a.db" and list(a.sessions) == [0] and a.nodes == FRAMES and a.descriptor == ("uint8", 32)
    features = StoredFeatures(Params().features)
    dataset = StoredSession(a, 0, features)
    frames = list(dataset)
    assert len(frames) == len(dataset) == FRAMES
    with Database(a.path, read_only=True) as db:
        for frame, node_id in zip(frames, a.sessions[0]):
            sig = db.load_signature(node_id)
            assert frame.stamp_ns == sig.stamp_ns and np.array_equal(frame.T_odom_base, sig.T_odom_base)
            assert np.array_equal(frame.scan.ranges, sig.scan.ranges)
            assert np.array_equal(frame.camera.T_base_camera, sig.camera.T_base_camera)
            assert frame.rgb.shape == (sig.camera.height, sig.camera.width, 3)
            stored = features.extract(frame.rgb)
            assert np.array_equal(stored.keypoints, sig.keypoints)
            words = db.load_words(sig.word_ids.tolist())
            assert np.array_equal(stored.descriptors, np.stack([words[w] for w in sig.word_ids.tolist()]))
            with pytest.raises(DatabaseError, match="out of step"):
                features.extract(frame.rgb)   # handed out once


def test_inputs_made_with_other_word_parameters_are_refused(sim, two, tmp_path):
    other = make_db(tmp_path / "other.db", sim, 1, 2, ["features.max_features=300"])
    with pytest.raises(DatabaseError, match=r"features.max_features 300 against 400.*--reextract"):
        inspect_inputs([two[0], other], reextract=False)
    assert len(inspect_inputs([two[0], other], reextract=True)) == 2
    empty = tmp_path / "empty.db"
    Database(empty).close()
    with pytest.raises(DatabaseError, match="has no node"):
        inspect_inputs([two[0], empty], reextract=False)


def _replay(inputs, out, skip=None):
    """Replay the inputs' sessions into ``out`` as merge does (optionally dropping the frame of
    ``skip`` = (input label, stamp): the robots' stamps coincide); the report's origins."""
    from rtabmap_ros2.cli.cmd_map import map_datasets

    params = Params.from_yaml(default_config_path())
    features = StoredFeatures(params.features)
    datasets = [StoredSession(item, m, features) for item in inputs for m in item.sessions]

    class Dropping:
        def __init__(self, dataset):
            self.dataset = dataset

        def __len__(self):
            return len(self.dataset)

        def __iter__(self):
            for frame in self.dataset:
                if (self.dataset.source.label, frame.stamp_ns) == skip:
                    features.forget(frame.rgb)
                    continue
                yield frame

    with Rtabmap(params, out) as rtabmap:
        rtabmap.extractor = features
        sessions = map_datasets(rtabmap, [(d.name, Dropping(d)) for d in datasets], progress=False,
                                print_line=lambda line: None)
    return [(d, [s.map_id for s in sessions if s.source == d.name], 0, 0) for d in datasets], params


def test_the_report_finds_every_input_node_and_counts_a_missing_one(two, tmp_path):
    inputs = inspect_inputs(list(two), reextract=False)
    origins, params = _replay(inputs, tmp_path / "merged.db")
    report = merge_report(tmp_path / "merged.db", origins, params)
    assert report.every_node_present and report.nodes == inputs[0].nodes + inputs[1].nodes
    assert [(s.source, s.output_map_ids, s.present) for s in report.sessions] == [
        ("a.db", [0], inputs[0].nodes), ("b.db", [1], inputs[1].nodes)]
    with Database(two[1], read_only=True) as db:
        last = db.load_nodes()[inputs[1].sessions[0][-1]].stamp_ns
    origins, params = _replay(inputs, tmp_path / "dropped.db", skip=("b.db", last))
    report = merge_report(tmp_path / "dropped.db", origins, params)
    assert not report.every_node_present
    assert [s.missing for s in report.sessions] == [0, 1]


def node_count_of(path) -> int:
    with Database(path, read_only=True) as db:
        return db.node_count()


def test_rehearsal_does_not_merge_nodes_an_input_kept(sim, two, tmp_path):
    """An input mapped without rehearsal keeps the nodes of a stop; the merge keeps them too (with
    the config's rehearsal they would merge)."""
    from rtabmap_ros2.cli.cli import main as cli

    kept = make_db(tmp_path / "kept.db", sim, 1, STOPPED_FRAMES, ["memory.rehearsal_similarity=1.0"])
    rehearsed = make_db(tmp_path / "rehearsed.db", sim, 1, STOPPED_FRAMES)
    with Database(kept, read_only=True) as k, Database(rehearsed, read_only=True) as r:
        assert k.node_count() == STOPPED_FRAMES > r.node_count()   # the config's rehearsal merges the stop
    assert cli(["merge", str(two[0]), str(kept), "--out", str(tmp_path / "merged.db"), "--no-progress"]) == 0
    with Database(tmp_path / "merged.db", read_only=True) as db:
        assert db.node_count() == node_count_of(two[0]) + STOPPED_FRAMES
