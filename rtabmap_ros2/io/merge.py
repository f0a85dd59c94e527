"""Map databases made apart (several robots, several days) read back for ``rtabmap-ros2 merge``.

As RTAB-Map's ``rtabmap-reprocess "a.db;b.db" out.db``, a merge replays every stored node of
every input through the full pipeline (``cli/cmd_merge.py`` feeds them to ``map``'s loop): each
input session becomes a session (map) of the output, and the sessions meet through the same loop
closure detection, verification and merge checks as ``map``. This module holds what is specific
to databases as input:

* :func:`inspect_inputs`: everything about the inputs is checked before the output is created
  (readable, ours, schema, SQLite's quick check, not the same file twice, same descriptors and
  word parameters, images stored when ``--reextract``), with a :class:`DatabaseError` naming the
  file and the problem;
* :class:`StoredSession`: one input session as a :class:`~rtabmap_ros2.core.sensor.Dataset` of
  :class:`~rtabmap_ros2.core.sensor.SensorFrame` (stamp, odometry and its covariance, RGB-D,
  camera, scan as stored), read-only;
* :class:`StoredFeatures`: the feature extractor given to the merge's ``Rtabmap``, which hands out
  each node's stored keypoints with its words' descriptors instead of extracting new ones (unless
  ``--reextract``), so inputs keep their features;
* :func:`merge_report`: what the merge did, read from the output database alone: every input node
  found again (stamp and odometry pose), the inter-session loop closures per pair of sessions, the
  connected components of one global optimisation, and for sessions left apart the best
  candidate's reason.

Inputs are opened with SQLite's ``mode=ro`` and never written.
"""

from __future__ import annotations

import filecmp
import logging
import os
import threading
from collections import Counter, defaultdict
from dataclasses import dataclass
from itertools import combinations
from pathlib import Path
from typing import Iterator, Optional

import numpy as np

from rtabmap_ros2.core.database import Database, SensorBlobs
from rtabmap_ros2.core.features import FeatureExtractor, Features
from rtabmap_ros2.core.params import Params, flatten
from rtabmap_ros2.core.sensor import SensorFrame
from rtabmap_ros2.errors import DatabaseError, ParameterError, RegistrationError

log = logging.getLogger(__name__)

# Parameters that decide what a stored word is: inputs whose stored features are reused must agree
# on them (the vocabulary's search settings, index and rebuild_swap_frames, only change how words are found).
WORD_PARAMETERS = ("features.detector", "features.max_features", "features.response_threshold",
                   "features.roi_ratios", "vocabulary.nndr", "vocabulary.new_words_compared_together")
# Nodes read from an input per query.
READ_BATCH_NODES = 32
# An output node is the input node it came from when both have this stamp and odometry pose (m, rad
# entries of the 4x4 matrix; the database stores float64, so equal means equal).
POSE_TOLERANCE = 1e-9
# Rejected candidates re-verified per pair of sessions left apart (the highest hypotheses first).
MAX_REVERIFIED = 20


@dataclass
class MergeInput:
    """One input database, as :func:`inspect_inputs` found it.

    Attributes:
        path: the file (absolute).
        label: how the summary names it (the file name, or the path when two inputs share a name).
        sessions: input map id -> its node ids (increasing), sessions in increasing map id.
        descriptor: (dtype name, size) of its words, or None when it has no word.
        word_parameters: the :data:`WORD_PARAMETERS` stored with it (name -> value).
        nodes_without_rgb: nodes with no stored RGB image.
    """

    path: Path
    label: str
    sessions: dict[int, list[int]]
    descriptor: Optional[tuple[str, int]]
    word_parameters: dict[str, object]
    nodes_without_rgb: int

    @property
    def nodes(self) -> int:
        return sum(len(ids) for ids in self.sessions.values())


def inspect_inputs(paths: list[str | os.PathLike], reextract: bool) -> list[MergeInput]:
    """Open every input read-only and check they can be merged; nothing is written.

    Args:
        paths: the input databases, in merge order.
        reextract: features will be extracted again from the stored images: the inputs' descriptors
            and word parameters may differ, but every node must have its RGB image.

    Raises:
        DatabaseError: naming the input and the problem (missing, not a database, truncated or
            damaged, foreign or newer schema, empty, given twice, descriptors or word parameters
            that differ from the first input's, images missing for ``--reextract``).
    """
    if len(paths) < 2:
        raise DatabaseError(f"merge needs at least two databases, got {len(paths)}")
    resolved = [Path(p).expanduser().absolute() for p in paths]
    names = Counter(p.name for p in resolved)
    inputs: list[MergeInput] = []
    for path in resolved:
        if not path.exists():
            raise DatabaseError(f"input {path} does not exist")
        for earlier in inputs:
            if os.path.samefile(path, earlier.path):
                raise DatabaseError(f"input {path} is given twice (it is the same file as {earlier.path}): "
                                    "each database is merged once")
        inputs.append(_inspect(path, path.name if names[path.name] == 1 else str(path)))
    first = inputs[0]
    for other in inputs[1:]:
        _check_copy(first, other)
        if reextract:
            continue
        if first.descriptor and other.descriptor and other.descriptor != first.descriptor:
            raise DatabaseError(
                f"input {other.path} has {_descriptor_text(other.descriptor)} descriptors, {first.path} has "
                f"{_descriptor_text(first.descriptor)}: their words cannot go into one vocabulary. "
                + _reextract_hint(inputs))
        differing = [name for name in WORD_PARAMETERS
                     if other.word_parameters.get(name) != first.word_parameters.get(name)]
        if differing:
            detail = ", ".join(f"{name} {other.word_parameters.get(name)!r} against {first.word_parameters.get(name)!r}"
                               for name in differing)
            raise DatabaseError(f"input {other.path} was made with other feature / vocabulary settings than "
                                f"{first.path} ({detail}): their stored words are not comparable. "
                                + _reextract_hint(inputs))
    if reextract:
        for item in inputs:
            if item.nodes_without_rgb:
                raise DatabaseError(f"input {item.path}: {item.nodes_without_rgb} of its {item.nodes} nodes have no "
                                    "stored image, so --reextract cannot extract their features again")
    return inputs


def _inspect(path: Path, label: str) -> MergeInput:
    """Read what the checks need from one input (read-only); DatabaseError naming it."""
    try:
        with Database(path, read_only=True) as db:
            problems = [m for m in db.quick_check() if m != "ok"]
            if problems:
                raise DatabaseError(f"input {path} is damaged (SQLite quick_check: {'; '.join(problems[:3])}); "
                                    "restore it from a backup")
            nodes = db.load_nodes()
            if not nodes:
                raise DatabaseError(f"input {path} has no node: nothing to merge")
            sessions: dict[int, list[int]] = defaultdict(list)
            for node_id, info in nodes.items():   # load_nodes is ordered by id
                sessions[info.map_id].append(node_id)
            kinds = db.descriptor_kinds()
            if len(kinds) > 1:
                raise DatabaseError(f"input {path} mixes descriptor types {kinds}: the database is damaged")
            stored = db.get_parameters()
            without_rgb = db.nodes_without_rgb()
    except DatabaseError as exc:
        if str(path) in str(exc):
            raise
        raise DatabaseError(f"input {path}: {exc}") from exc
    return MergeInput(path, label, dict(sorted(sessions.items())), kinds[0] if kinds else None,
                      _word_parameters(path, stored), without_rgb)


def _word_parameters(path: Path, stored: dict) -> dict[str, object]:
    """The stored :data:`WORD_PARAMETERS` (defaults for those an older database lacks)."""
    if not stored:
        raise DatabaseError(f"input {path} has no stored parameters: it was not written by rtabmap_ros2's map, "
                            "node or merge")
    try:
        params = Params.from_stored(stored)
    except ParameterError as exc:
        raise DatabaseError(f"input {path} holds parameters this rtabmap_ros2 does not know ({exc}): it was "
                            "made by another version") from exc
    values = flatten(params.to_dict())
    return {name: values[name] for name in WORD_PARAMETERS}


def _check_copy(first: MergeInput, other: MergeInput) -> None:
    """A byte copy of an input is the same map twice (it would only loop-close with itself)."""
    if first.sessions == other.sessions and filecmp.cmp(first.path, other.path, shallow=False):
        raise DatabaseError(f"input {other.path} is a copy of {first.path} (same content): each map is merged once")


def _descriptor_text(kind: tuple[str, int]) -> str:
    dtype, size = kind
    return f"{size}-byte binary" if dtype == "uint8" else f"{size}-d {dtype}"


def _reextract_hint(inputs: list[MergeInput]) -> str:
    if all(item.nodes_without_rgb == 0 for item in inputs):
        return ("Every node of the inputs has its image stored: --reextract extracts the features again from "
                "them, with the merge's parameters, and makes the merge possible.")
    return "Some nodes have no stored image, so --reextract cannot help either."


def word_parameters_of(inputs: list[MergeInput], params: Params) -> tuple[Params, list[str]]:
    """``params`` with the inputs' :data:`WORD_PARAMETERS` (their stored words are reused), and the
    ``name: ours -> theirs`` of those that changed."""
    ours = flatten(params.to_dict())
    changed = []
    for name, value in inputs[0].word_parameters.items():
        if ours[name] != value:
            changed.append(f"{name}: {ours[name]!r} -> {value!r}")
            params = params.with_value(name, value)
    return params, changed


class StoredFeatures(FeatureExtractor):
    """A feature extractor that hands out each node's stored features instead of extracting them.

    :class:`StoredSession` registers the features of every frame it reads with the frame's RGB
    image (:meth:`register`); ``Rtabmap.process`` asks its extractor for the features of that
    image (:meth:`extract`) and gets them back. The stored features are the node's keypoints
    (strongest first, as extracted) with the descriptors of the words they were quantised to, so
    the merge's vocabulary quantises what the input's did.
    """

    def __init__(self, params) -> None:
        super().__init__(params)
        self._lock = threading.Lock()
        self._pending: dict[int, tuple[np.ndarray, Features]] = {}

    def register(self, rgb: np.ndarray, features: Features) -> None:
        """Hand out ``features`` for the image ``rgb`` (this very array), once."""
        with self._lock:
            self._pending[id(rgb)] = (rgb, features)

    def forget(self, rgb: np.ndarray) -> None:
        """Drop what was registered for ``rgb`` (a frame that was skipped)."""
        with self._lock:
            self._pending.pop(id(rgb), None)

    def extract(self, image: np.ndarray, depth_m: Optional[np.ndarray] = None) -> Features:
        """The features registered for ``image`` (``depth_m`` plays no part: they were found once)."""
        with self._lock:
            entry = self._pending.pop(id(image), None)
        if entry is None or entry[0] is not image:
            raise DatabaseError("merge: an image was given to the stored-features extractor that no stored node "
                                "registered (the replay and the extractor are out of step)")
        return entry[1]


class StoredSession:
    """One session of an input database as a Dataset of SensorFrames, oldest node first.

    The database is opened read-only in the thread that iterates (``map``'s frame reader runs in
    its own thread; a SQLite connection stays in the thread that opened it).

    Args:
        source: the input.
        map_id: the input session.
        features: hand each node's stored features to this extractor (None: ``--reextract``, the
            merge extracts features from the images).
    """

    def __init__(self, source: MergeInput, map_id: int, features: Optional[StoredFeatures] = None) -> None:
        self.source = source
        self.map_id = map_id
        self.node_ids = source.sessions[map_id]
        self.features = features

    @property
    def name(self) -> str:
        return f"{self.source.label} session {self.map_id}"

    def __len__(self) -> int:
        return len(self.node_ids)

    def __iter__(self) -> Iterator[SensorFrame]:
        with Database(self.source.path, read_only=True) as db:
            words = _WordTable(db) if self.features is not None else None
            for start in range(0, len(self.node_ids), READ_BATCH_NODES):
                batch = self.node_ids[start:start + READ_BATCH_NODES]
                for sig in db.load_signatures(batch):
                    blobs = db.load_sensor_blobs(sig.id)
                    frame = _frame(sig, blobs)
                    if words is not None and frame.rgb is not None:
                        self.features.register(frame.rgb, words.features(sig))
                    yield frame


def _frame(sig, blobs: SensorBlobs) -> SensorFrame:
    """The frame a stored node was made from (images as stored: JPEG RGB, depth in mm; their bytes
    stored again as they are, not encoded a second time)."""
    return SensorFrame(stamp_ns=sig.stamp_ns, T_odom_base=sig.T_odom_base, odom_covariance=blobs.odom_covariance,
                       rgb=blobs.rgb(), depth_m=blobs.depth_m(), camera=sig.camera, scan=sig.scan,
                       rgb_jpeg=blobs.rgb_jpeg, depth_png16_mm=blobs.depth_png16_mm)


class _WordTable:
    """An input's words, to give a node's keypoints their word's descriptor."""

    def __init__(self, db: Database) -> None:
        self.path = db.path
        self.ids, self.descriptors = db.load_descriptors()

    def features(self, sig) -> Features:
        word_ids = np.asarray(sig.word_ids, dtype=np.int64)
        n = len(word_ids)
        if n == 0:
            dim = self.descriptors.shape[1] if self.descriptors.ndim == 2 else 0
            return Features(np.zeros((0, 2), np.float32), np.zeros((0, dim), self.descriptors.dtype),
                            np.zeros(0, np.float32))
        index = np.searchsorted(self.ids, word_ids)
        found = (index < len(self.ids)) & (self.ids[np.minimum(index, len(self.ids) - 1)] == word_ids)
        if not found.all():
            raise DatabaseError(f"node {sig.id} of {self.path} refers to words {word_ids[~found][:5].tolist()} that "
                                "are not in its words table: the database is damaged")
        # Stored strongest first (features.py); the responses themselves are not stored.
        return Features(np.ascontiguousarray(sig.keypoints, dtype=np.float32), self.descriptors[index],
                        np.arange(n, 0, -1, dtype=np.float32))


# --------------------------------------------------------------------------------------------
# The report, from the output database
# --------------------------------------------------------------------------------------------

@dataclass
class SessionOrigin:
    """Where an output session's nodes came from, and whether they are all there.

    Attributes:
        source: input label; input_map_id: its session.
        output_map_ids: the output sessions holding them (one, or more when odometry was reset
            inside the input session).
        input_nodes: nodes of the input session.
        present: input nodes found in the output (same stamp and odometry pose).
        merged_by_rehearsal: frames merged into the previous node by rehearsal.
        skipped: frames refused as bad sensor data.
    """

    source: str
    input_map_id: int
    output_map_ids: list[int]
    input_nodes: int
    present: int = 0
    merged_by_rehearsal: int = 0
    skipped: int = 0

    @property
    def missing(self) -> int:
        return self.input_nodes - self.present - self.merged_by_rehearsal - self.skipped


@dataclass
class PairOutcome:
    """Two output sessions: merged by loop closures, or why not."""

    map_a: int
    map_b: int
    loop_closures: int
    same_component: bool
    reason: str = ""


@dataclass
class MergeReport:
    """What a merge gave (see :func:`merge_report`)."""

    sessions: list[SessionOrigin]
    pairs: list[PairOutcome]
    components: list[list[int]]       # output map ids per connected component, largest first
    nodes: int
    chi2_initial: float
    chi2_final: float
    optimization_time_s: float

    @property
    def every_node_present(self) -> bool:
        return all(s.missing == 0 and s.merged_by_rehearsal == 0 and s.skipped == 0 for s in self.sessions)


def merge_report(output: str | os.PathLike, origins: list[tuple[StoredSession, list[int], int, int]],
                 params: Params) -> MergeReport:
    """Read the merged database (read-only) and say what the merge gave.

    Args:
        output: the merged database.
        origins: per replayed input session: (its dataset, the output map ids its frames went to,
            frames merged by rehearsal, frames skipped).
        params: the merge's parameters (global optimisation, T_loop, registration).
    """
    from rtabmap_ros2.core.global_map import load_global_map

    global_map = load_global_map(output, params)
    with Database(output, read_only=True) as db:
        nodes = db.load_nodes()
        statistics = db.load_statistics()
        inter = db.inter_session_pairs()
        sessions = [_origin(dataset, nodes, map_ids, merged, skipped)
                    for dataset, map_ids, merged, skipped in origins]
        node_map = {i: n.map_id for i, n in nodes.items()}
        components = [sorted({node_map[n] for n in component}) for component in global_map.components]
        component_of = {m: k for k, maps in enumerate(components) for m in maps}
        counts = Counter(tuple(sorted((node_map[a], node_map[b]))) for a, b in inter)
        pairs = []
        for a, b in combinations(sorted({n.map_id for n in nodes.values()}), 2):
            outcome = PairOutcome(a, b, counts.get((a, b), 0), component_of.get(a) == component_of.get(b))
            if not outcome.same_component:
                outcome.reason = _why_apart(db, statistics, node_map, a, b, params)
            pairs.append(outcome)
    return MergeReport(sessions, pairs, components, len(nodes), global_map.chi2_initial, global_map.chi2_final,
                       global_map.optimization_time_s)


def _origin(dataset: StoredSession, nodes: dict, map_ids: list[int], merged: int, skipped: int) -> SessionOrigin:
    """Find the input session's nodes among the output sessions ``map_ids``: same stamp, same odometry."""
    origin = SessionOrigin(dataset.source.label, dataset.map_id, map_ids, len(dataset), merged_by_rehearsal=merged,
                           skipped=skipped)
    by_stamp: dict[int, list] = defaultdict(list)
    for info in nodes.values():
        if info.map_id in map_ids:
            by_stamp[info.stamp_ns].append(info.T_odom_base)
    with Database(dataset.source.path, read_only=True) as source:
        stored = source.load_nodes()
    for node_id in dataset.node_ids:
        info = stored[node_id]
        candidates = by_stamp.get(info.stamp_ns, [])
        for k, pose in enumerate(candidates):
            if _same_pose(pose, info.T_odom_base):
                del candidates[k]
                origin.present += 1
                break
    return origin


def _same_pose(a: Optional[np.ndarray], b: Optional[np.ndarray]) -> bool:
    if a is None or b is None:
        return a is None and b is None
    return bool(np.abs(a - b).max() <= POSE_TOLERANCE)


def _why_apart(db: Database, statistics: list[dict], node_map: dict[int, int], a: int, b: int,
               params: Params) -> str:
    """The best candidate's reason why sessions ``a`` and ``b`` were not joined, from the frames'
    statistics (their highest hypothesis, the loop closures rejected) and a new verification of the
    best rejected ones."""
    t_loop = params.bayes.loop_threshold
    toward = [(row, other) for row in statistics for other in (a, b)
              if row.get("map_id") in (a, b) and row.get("map_id") != other]
    rejected = sorted((row for row, other in toward
                       if node_map.get(row.get("rejected_loop_closure_id")) == other and row.get("location_id")),
                      key=lambda row: -row.get("highest_hypothesis_value", 0.0))
    if rejected:
        failures: list[str] = []
        verified = 0
        for row in rejected[:MAX_REVERIFIED]:
            outcome = _verify_again(db, row["location_id"], row["rejected_loop_closure_id"], params)
            if outcome is None:
                verified += 1
            else:
                failures.append(outcome)
        if verified:
            return (f"rejected by the merge checks: {verified} loop closure(s) passed verification but never "
                    f"{params.graph.merge_min_loop_closures} agreeing ones at least "
                    f"{params.graph.merge_min_separation:g} m apart whose scans agree (or the graph refused them); "
                    f"{len(rejected)} candidate(s) over T_loop rejected in all")
        return f"too few inliers: {len(rejected)} candidate(s) over T_loop failed verification; best: {failures[0]}"
    over = [row for row, other in toward if node_map.get(row.get("highest_hypothesis_id")) == other
            and row.get("highest_hypothesis_value", 0.0) >= t_loop]
    if over:
        best = max(over, key=lambda row: row["highest_hypothesis_value"])
        return (f"{len(over)} hypothesis(es) over T_loop (best p = {best['highest_hypothesis_value']:.2f}, node "
                f"{best['location_id']} -> {best['highest_hypothesis_id']}) not accepted (loop ratio or evidence)")
    seen = [row["highest_hypothesis_value"] for row, other in toward
            if node_map.get(row.get("highest_hypothesis_id")) == other]
    if seen:
        return (f"no hypothesis over T_loop: best p = {max(seen):.3f} < {t_loop:g} over {len(seen)} frame(s) whose "
                "highest hypothesis was in the other session")
    return ("no hypothesis over T_loop: no frame of one session had its highest hypothesis in the other "
            "(they never saw the same place)")


def _verify_again(db: Database, new_id: int, old_id: int, params: Params) -> Optional[str]:
    """None when ``new_id`` -> ``old_id`` passes verification (2014 §II-A) again, else why not."""
    from rtabmap_ros2.core.registration import register

    try:
        new, old = db.load_signatures([new_id, old_id])
    except DatabaseError:
        return f"node {new_id} or {old_id} is no longer in the map"
    # The two nodes' features paired by their words' descriptors, as mapping pairs them.
    ids = np.concatenate([new.word_ids, old.word_ids]).tolist()
    words = db.load_words(ids)
    descriptors = None
    if len(new.word_ids) and len(old.word_ids) and all(w in words for w in ids):
        descriptors = tuple(np.stack([words[w] for w in sig.word_ids.tolist()]) for sig in (new, old))
    try:
        register(new, old, params.registration, descriptors=descriptors)   # planar as mapping used it
    except RegistrationError as exc:
        return str(exc)
    return None


__all__ = ["MergeInput", "MergeReport", "PairOutcome", "SessionOrigin", "StoredFeatures", "StoredSession",
           "WORD_PARAMETERS", "inspect_inputs", "merge_report", "word_parameters_of"]
