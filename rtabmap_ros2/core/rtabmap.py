"""Algorithm 1 of the 2013 paper, extended into the graph SLAM of the 2014 paper.

One call of :meth:`Rtabmap.process` per synchronised frame, each step a call into the module
named for it:

1. location creation (Alg. 2): features, quantisation to the incremental vocabulary, bad
   signature check, 3D word positions from depth (features.py, memory.py, registration.py);
2. a new map (session) starts on an odometry reset or a request (2014 §III; sessions.py);
3. STM insertion with a neighbour link (local_map.py), weight update / rehearsal (§III-B), STM
   -> WM (memory.py);
4. Bayes filter over WM (§III-C) and hypothesis selection with T_loop (§III-D; bayes.py);
5. loop closure verification: RANSAC on 3D words, 2D ICP refinement (2014 §II-A), and whether
   the link is kept, held for a merge or rejected (loop_validation.py);
6. join of the previous frame's database writes (Alg. 1 line 17), retrieval (Alg. 3; memory.py);
7. local map optimisation rooted at the newest node (2014 §II-B, C; local_map.py);
8. pTime; transfer WM -> LTM when pTime > T_time (Alg. 4) or WM is over its cap (wm_budget.py);
   this frame's writes go to the background writer (database.py).

CPython's automatic garbage collection waits while a frame is processed (heap.collection_deferred).
"""

from __future__ import annotations

import logging
import os
import time
from pathlib import Path
from typing import Optional

import numpy as np

from rtabmap_ros2.core import registration, transforms
from rtabmap_ros2.core.bayes import BayesFilter, Hypothesis, likelihood
from rtabmap_ros2.core.database import Database, SensorBlobs
from rtabmap_ros2.core.features import FeatureExtractor, Features
from rtabmap_ros2.core.graph import warm_up_residuals
from rtabmap_ros2.core.grid import DepthPoints, OccupancyGrid, depth_points, grid_sources
from rtabmap_ros2.core.heap import collection_deferred, release_free_heap
from rtabmap_ros2.core.local_map import LocalMap, LocalMapper
from rtabmap_ros2.core.loop_validation import LoopValidator
from rtabmap_ros2.core.memory import Memory
from rtabmap_ros2.core.optimizer import load_backend, release
from rtabmap_ros2.core.params import Params
from rtabmap_ros2.core.proximity import ProximitySearch, proximity_candidates
from rtabmap_ros2.core.registration import words_3d
from rtabmap_ros2.core.sensor import CameraModel, SensorFrame
from rtabmap_ros2.core.sessions import REQUESTED, PlanarOdometryCheck, Sessions, odometry_information
from rtabmap_ros2.core.signature import Signature
from rtabmap_ros2.core.statistics import Statistics, Stopwatch
from rtabmap_ros2.core.wm_budget import WorkingMemoryBudget
from rtabmap_ros2.errors import DatabaseError, OptimizationError, RegistrationError, SensorDataError

log = logging.getLogger(__name__)

# A transfer of this many locations at once (a WM cap drop; Alg. 4 moves a few a frame) is
# followed by returning the freed heap to the system (core/heap.py).
HEAP_RELEASE_MIN_TRANSFERRED = 100
# Steps whose time grows with WM (vocabulary, Bayes filter, local map): see WorkingMemoryBudget.
SCALING_STEPS = ("quantization", "bayes", "optimization")
# Nodes from the database (retrieved, or in WM when reopened) given their depth points per frame at
# most (~5 ms each: the depth PNG decoded, its points made; grid.sensor using depth only).
DEPTH_POINTS_LOADS_PER_FRAME = 4


class Rtabmap:
    """Memory-managed loop closure detection and multi-session graph SLAM over one database."""

    def __init__(self, params: Params, database_path: str | os.PathLike, *, delete_existing: bool = False) -> None:
        self.params = params
        self.database_path = Path(database_path).expanduser()
        if delete_existing:
            _delete_database(self.database_path)
        self.extractor = FeatureExtractor(params.features)
        self._likelihood: dict[int, float] = {}  # this frame's raw score of each WM location (proximity detection)
        self._open()

    def _open(self) -> None:
        load_backend()
        registration.warm_up()  # RANSAC and ICP compiled or loaded here rather than in a frame
        warm_up_residuals()  # the error check's residuals, likewise
        self.db = Database(self.database_path)
        self.db.set_parameters(self.params.to_dict())
        self.memory = Memory(self.params, self.db, self.extractor.binary)
        self.bayes = BayesFilter(self.params.bayes, self.memory, kept=self.memory.signatures)
        self.memory.on_graph_change = self.bayes.transitions.invalidate_around
        self.frame_index = self.db.max_frame_index() + 1
        self.localization_mode = False
        self.localization_pose: Optional[np.ndarray] = None
        # The previous frame's highest hypothesis value (Rtabmap/LoopRatio), 0 after a frame without one.
        self._previous_hypothesis_value = 0.0
        self.sessions = Sessions(self.params.graph)
        self.planarity = PlanarOdometryCheck()
        self.local = LocalMapper(self.params, self.memory)
        self.validator = LoopValidator(self.params, self.memory, self.bayes, self.local)
        self._wm_budget = WorkingMemoryBudget(self.params.memory)
        # Nodes in WM whose depth points are still to be made from the database (_load_depth_points).
        self._depth_points_awaited = {n for n, sig in self.memory.signatures.items() if self._lacks_depth_points(sig)}

    # -- public API ----------------------------------------------------------------------------
    @property
    def map_id(self) -> int:
        return self.memory.map_id

    def process(self, frame: SensorFrame, location_id: int | None = None,
                features: Optional[Features] = None) -> Statistics:
        """Process one frame (Alg. 1). Bad frames raise :class:`SensorDataError`, storing nothing.

        Args:
            frame: the synchronised sensor data.
            location_id: id to give the new location (e.g. the image index of ``detect``);
                default: the next free id. Must be larger than every id already used.
            features: the frame's features when extracted ahead (:func:`frame_features` with an
                extractor of the same ``params.features``; the live node extracts the next frame's
                while this one is processed); default: extracted here.
        """
        with collection_deferred():
            return self._process(frame, location_id, features)

    def _process(self, frame: SensorFrame, location_id: int | None, features: Optional[Features]) -> Statistics:
        frame.validate(self.params.sync)
        if location_id is not None and location_id < self.memory.next_location_id:
            raise SensorDataError(
                f"location id {location_id} is not larger than the last one ({self.memory.next_location_id - 1})")
        t_start = time.perf_counter()
        watch = Stopwatch()
        # Location creation (Alg. 2), lines 2-3: features (excluded from pTime, 2013 §IV).
        if features is None:
            features = frame_features(self.extractor, frame)
        watch.lap("features")
        t_process = time.perf_counter()
        self.local.new_loops = []
        self.local.proximity_keys = set()
        stats = Statistics(frame_index=self.frame_index, stamp_ns=frame.stamp_ns)
        self.frame_index += 1
        stats.new_map = self._maybe_start_new_map(frame)
        stats.map_id = self.memory.map_id
        self._check_planar(frame)
        if not self.localization_mode and not stats.new_map and self._small_displacement(frame):
            return self._skip(stats, t_start, t_process, watch)
        if self.localization_mode:
            hypothesis = self._localize(frame, features, stats, watch)
        else:
            hypothesis = self._map(frame, features, stats, watch, location_id)
        self._previous_hypothesis_value = hypothesis.probability
        # Alg. 1 line 17: join the thread writing the previous frame to LTM (counts in pTime).
        self.memory.join()
        watch.lap("database")
        # Retrieval (Alg. 3): neighbours of the highest hypothesis come back from LTM, after (SLAM
        # mode) those of the local map around the robot.
        retrieving = self.local.retrieval_candidates(stats.location_id)
        if hypothesis.location_id:
            retrieving += self.memory.retrieval_candidates(hypothesis.location_id, self.params.memory.max_retrieved,
                                                           exclude=retrieving)
        if retrieving:
            retrieved = self.memory.retrieve(retrieving)
            self._depth_points_awaited.update(n for n in retrieved
                                              if self._lacks_depth_points(self.memory.signatures[n]))
            stats.retrieved = len(retrieved)
            self.local.wm_changed |= bool(stats.retrieved)
        self._load_depth_points()
        watch.lap("retrieval")
        # Local map (2014 §II-C), optimised every frame; graph work counts in pTime.
        if stats.location_id and frame.T_odom_base is not None:
            try:
                rejected_now = self.local.update(stats.location_id)
            except OptimizationError as exc:
                # The node is stored; the local map keeps its last solution until the next frame.
                log.warning("local map not optimised at node %d: %s", stats.location_id, exc)
                rejected_now = False
            if rejected_now and stats.loop_closure_id:
                stats.rejected_loop_closure_id = stats.loop_closure_id
                stats.loop_closure_id = 0
                stats.loop_closure_type = ""
            if stats.proximity_links:  # those the optimisation kept
                graph, inactive = self.memory.graph, self.local.inactive_links
                stats.proximity_links = sum(graph.link(*key) is not None and key not in inactive
                                            for key in self.local.proximity_keys)
        watch.lap("optimization")
        stats.process_time_ms = (time.perf_counter() - t_process) * 1000.0
        self._manage_memory(stats, hypothesis, watch.ms, slam=frame.T_odom_base is not None)
        watch.lap("transfer")
        return self._recorded(stats, t_start, watch)

    def _recorded(self, stats: Statistics, t_start: float, watch: Stopwatch) -> Statistics:
        """The end of every frame: memory sizes, total time and step times into ``stats``, which are
        recorded in the database with what the frame changed (one commit)."""
        self._fill_sizes(stats)
        stats.total_time_ms = (time.perf_counter() - t_start) * 1000.0
        stats.timings_ms = watch.ms
        self.memory.record_statistics(stats.to_dict())
        self.memory.commit()
        return stats

    def _small_displacement(self, frame: SensorFrame) -> bool:
        """RTAB-Map's RGBD/LinearUpdate and RGBD/AngularUpdate (Rtabmap.cpp, ``smallDisplacement``): True
        when ``graph.linear_update`` or ``graph.angular_update`` is set and the frame's odometry moved less
        than the one along each of x, y and z since the session's last node, and less than the other about
        each axis (a threshold at 0 is not checked)."""
        linear, angular = self.params.graph.linear_update, self.params.graph.angular_update
        previous = self.memory.last_location()
        if ((linear <= 0.0 and angular <= 0.0) or frame.T_odom_base is None or previous is None
                or previous.map_id != self.memory.map_id or previous.T_odom_base is None):
            return False
        moved = np.abs(transforms.to_xyz_rpy(transforms.relative(previous.T_odom_base, frame.T_odom_base)))
        return bool((linear <= 0.0 or np.all(moved[:3] < linear)) and (angular <= 0.0 or np.all(moved[3:] < angular)))

    def _skip(self, stats: Statistics, t_start: float, t_process: float, watch: Stopwatch) -> Statistics:
        """A frame that does not become a node (_small_displacement): nothing is added, detected,
        retrieved, optimised or transferred (RTAB-Map deletes such a location at the end of its
        frame); its statistics are recorded with ``small_displacement`` set and no location."""
        stats.small_displacement = True
        self.memory.join()
        watch.lap("database")
        stats.process_time_ms = (time.perf_counter() - t_process) * 1000.0
        return self._recorded(stats, t_start, watch)

    def local_map(self) -> LocalMap:
        """The optimised local map of the newest node (poses in the map frame)."""
        return self.local.snapshot()

    def local_grid(self, max_casts: Optional[int] = None) -> Optional[OccupancyGrid]:
        """Occupancy grid of the local map from the nodes' laser scans and / or depth images
        (``grid.sensor``), or None without either; ``max_casts`` bounds the nodes cast per call
        (LocalMapper.grid)."""
        return self.local.grid(max_casts)

    def trigger_new_map(self) -> int:
        """Start a new map (session) at the next frame; returns its id."""
        return self.memory.map_id + 1 if self.sessions.request_new_map() else self.memory.map_id

    def reset(self) -> None:
        """Forget everything: the database is deleted and a new empty one started."""
        self.memory.close()
        _delete_database(self.database_path)
        self._open()

    def flush(self) -> None:
        """Commit everything processed so far to the database."""
        self.memory.commit()
        self.memory.join()

    def backup(self, path: str | os.PathLike) -> Path:
        """Flush, then copy the database to ``path`` (SQLite online backup)."""
        self.flush()
        self.db.backup(path)
        return Path(path)

    def close(self) -> None:
        """Flush and close the database."""
        self.memory.close()

    def __enter__(self) -> "Rtabmap":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # -- steps ---------------------------------------------------------------------------------
    def _maybe_start_new_map(self, frame: SensorFrame) -> bool:
        """Multi-session (2014 §III): a new map on request or when odometry was reset (sessions.py)."""
        reason = self.sessions.new_map_reason(frame)
        if not reason:
            return False
        self.memory.flush_stm()
        self.memory.map_id += 1
        self.validator.candidates = []
        self.bayes.reset()
        if reason == REQUESTED:
            log.info("new map %d (requested)", self.memory.map_id)
        else:
            log.warning("new map %d (%s)", self.memory.map_id, reason)
        return True

    def _forget(self, nodes: list[int], transferred_to_ltm: bool = False) -> None:
        """Nodes that left WM (transferred to LTM, or merged into the previous location by
        rehearsal) leave the local map (LocalMapper.forget); transferred ones also leave the
        caches of the Bayes filter's neighbourhoods and of the optimiser's factors (else these
        grow with every node ever in WM)."""
        self.local.forget(nodes, transferred_to_ltm)
        if transferred_to_ltm:
            self.bayes.transitions.forget(nodes)
            release(link for node in nodes for link in self.memory.graph.stored_links_of(node))

    def _check_planar(self, frame: SensorFrame) -> None:
        """Planar (3 DoF) mode: the parameter as given, whatever the sensors (RTAB-Map's
        Reg/Force3DoF; 2014 §III: the robot is on a plane); warned about when the odometry is not
        planar (sessions.PlanarOdometryCheck)."""
        if frame.T_odom_base is None:
            return
        if self.local.planar is None:
            self.local.planar = bool(self.params.registration.planar)
        if self.local.planar:
            warning = self.planarity.update(self.memory.map_id, frame.T_odom_base)
            if warning:
                log.warning("%s", warning)

    def _map(self, frame: SensorFrame, features: Features, stats: Statistics, watch: Stopwatch,
             location_id: int | None) -> Hypothesis:
        memory = self.memory
        node_id = location_id if location_id is not None else memory.next_location_id
        memory.next_location_id = node_id + 1
        bad = memory.is_bad_signature(len(features.keypoints))
        stats.bad_signature = bad
        if bad:
            # A bad signature stays as a location without words (RTAB-Map's Mem/BadSignaturesIgnored
            # false, rather than Alg. 1 lines 4-5's deletion): it keeps the neighbour chain the
            # prediction spreads along, counts in the next images' bad-signature mean, and has no
            # Bayes step (below).
            word_ids = np.zeros(0, np.int64)
            new_words: list[int] = []
            features = self.extractor.empty()
        else:
            before = memory.vocabulary.next_word_id
            word_ids = memory.quantize(features.descriptors)
            new_words = [w for w in word_ids.tolist() if w >= before]
        points3d = np.full((len(word_ids), 3), np.nan, np.float32)
        if frame.depth_m is not None and frame.camera is not None and len(word_ids):
            points3d = words_3d(features.keypoints, frame.depth_m, frame.camera)
        watch.lap("quantization")
        sig = Signature(id=node_id, map_id=memory.map_id, stamp_ns=frame.stamp_ns, word_ids=word_ids,
                        keypoints=_pinhole_keypoints(features, frame), points3d=points3d, T_odom_base=frame.T_odom_base,
                        scan=frame.scan, camera=frame.camera, bad=bad,
                        depth_points=self._depth_points(frame.depth_m, frame.camera, frame.scan is not None))
        blobs = SensorBlobs.deferred(frame.rgb, frame.depth_m, frame.odom_covariance, frame.rgb_jpeg,
                                     frame.depth_png16_mm)
        watch.lap("database")
        # Alg. 1 line 7: insert into STM with a neighbour link to the previous location.
        previous = memory.last_location()
        neighbor = None
        if previous is not None and previous.map_id == sig.map_id:
            T = transforms.identity()
            if previous.T_odom_base is not None and sig.T_odom_base is not None:
                T = transforms.relative(previous.T_odom_base, sig.T_odom_base)
            neighbor = self.local.neighbor_link(previous, sig, T,
                                                odometry_information(frame, self.params.graph.odom_default_variance))
        memory.add_location(sig, blobs, neighbor)
        self.sessions.nodes_in_map += 1
        stats.location_id = sig.id
        stats.words_extracted = len(features.keypoints)
        # Weight update (§III-B) and STM -> WM (Alg. 1 lines 8-10).
        stats.merged_id, stats.rehearsal_similarity = memory.rehearse(sig, new_words)
        if stats.merged_id:
            # Merged into the previous location, which stays (RTAB-Map's rehearsal): this frame is
            # that location now. With memory.rehearsal_id_updated_to_new_one the previous location was
            # merged into this frame's, which stays.
            self._forget([stats.merged_id])
            sig = memory.last_location()
            stats.location_id = sig.id
        memory.update_stm()
        watch.lap("rehearsal")
        if bad:
            return Hypothesis(0, 0.0, 1.0)
        # Bayes filter update in WM (Eq. 2-4) and hypothesis selection (§III-D).
        hypothesis = self._hypothesis(sig, stats)
        stats.highest_hypothesis_id = hypothesis.location_id
        stats.highest_hypothesis_value = hypothesis.probability
        watch.lap("bayes")
        if self.validator.accepts(sig, hypothesis, self._previous_hypothesis_value, stats):
            old = memory.signatures[hypothesis.location_id]
            try:
                link = self.validator.verify(sig, old)
            except RegistrationError as exc:
                stats.rejected_loop_closure_id = old.id
                log.debug("loop closure %d -> %d rejected: %s", sig.id, old.id, exc)
            else:
                if self.validator.allows(link):
                    self.local.new_loops.append((link, memory.add_loop_closure(link)))
                    stats.loop_closure_id = old.id
                    stats.loop_closure_type = link.type.value
                else:
                    stats.rejected_loop_closure_id = old.id
        if self.params.graph.proximity_by_space and sig.T_odom_base is not None:
            stats.proximity_links = self._proximity_detection(sig)
        watch.lap("verification")
        return hypothesis

    def _proximity_detection(self, sig: Signature) -> int:
        """Loop closures with the WM nodes the local map puts near the new node (core/proximity.py,
        RTAB-Map's RGBD/ProximityBySpace), each registered as a loop closure is verified; returns how
        many were added (judged with the frame's other loop closures by the local map's
        optimisation)."""
        memory, graph_params = self.memory, self.params.graph
        pose = self.local.new_node_pose(sig.id)
        if pose is None:
            return 0
        search = ProximitySearch(self.params.memory.local_radius, graph_params.proximity_max_graph_depth,
                                 graph_params.proximity_max_paths, graph_params.proximity_filtering_radius,
                                 graph_params.proximity_angle)
        candidates = proximity_candidates(memory.graph, memory.signatures, memory.wm, self.local.poses, sig.id, pose,
                                          self._likelihood, search)
        for old_id in candidates:
            try:
                link = self.validator.verify(sig, memory.signatures[old_id])
            except RegistrationError as exc:
                log.debug("proximity %d -> %d rejected: %s", sig.id, old_id, exc)
                continue
            if np.linalg.norm(link.T_from_to[:3, 3]) > search.filtering_radius or not self.validator.allows(link):
                continue
            self.local.new_loops.append((link, memory.add_loop_closure(link, transfer_weight=False)))
            self.local.proximity_keys.add(link.key())
        return len(self.local.proximity_keys)

    def _hypothesis(self, sig: Signature, stats: Statistics) -> Hypothesis:
        candidates = self.memory.hypothesis_ids()
        self._likelihood = {}
        if not len(candidates) or not len(sig.word_ids):
            return Hypothesis(0, 0.0, self.bayes.posterior.get(-1, 1.0))
        scores = self.memory.similarities(sig, candidates)
        raw = np.fromiter(scores.values(), dtype=float, count=len(scores))
        non_null = raw[raw > 0]
        stats.likelihood_nonzero = int(non_null.size)
        stats.likelihood_mean = float(non_null.mean()) if non_null.size else 0.0
        stats.likelihood_max = float(raw.max()) if raw.size else 0.0
        stats.likelihood_std = float(non_null.std(ddof=1)) if non_null.size > 1 else 0.0
        self._likelihood = scores
        self.bayes.update(candidates, likelihood(scores))
        hypothesis = self.bayes.highest()
        stats.new_location_probability = hypothesis.new_location_probability
        return hypothesis

    def _depth_points(self, depth_m: Optional[np.ndarray], camera: Optional[CameraModel],
                      has_scan: bool) -> Optional[DepthPoints]:
        """The points of a node's depth image its local occupancy grid is drawn from, when
        ``grid.sensor`` uses the depth for it (RTAB-Map makes a node's local grid when it creates
        the node, RGBD/CreateOccupancyGrid): kept with the signature, as the laser scan is."""
        if depth_m is None or camera is None or not grid_sources(self.params.grid.sensor, has_scan)[1]:
            return None
        return depth_points(depth_m, camera, self.params.grid)

    def _lacks_depth_points(self, sig: Signature) -> bool:
        """Whether ``sig`` came from the database without the depth points its grid uses."""
        return sig.depth_points is None and sig.camera is not None \
            and grid_sources(self.params.grid.sensor, sig.scan is not None)[1]

    def _load_depth_points(self) -> None:
        """Depth points of nodes in WM that came from the database (retrieved from LTM, or in WM
        when it was reopened): it keeps their depth image, not its points. At most
        :data:`DEPTH_POINTS_LOADS_PER_FRAME` a frame, the newest first (reopening a map whose WM
        holds a thousand camera-only nodes does not stall a frame); until then the local grid
        goes without them."""
        signatures = self.memory.signatures
        waiting = sorted((n for n in self._depth_points_awaited if n in signatures), reverse=True)
        self._depth_points_awaited = set(waiting[DEPTH_POINTS_LOADS_PER_FRAME:])
        for node in waiting[:DEPTH_POINTS_LOADS_PER_FRAME]:
            sig = signatures[node]
            try:
                depth = self.memory.db.load_sensor_blobs(node).depth_m()
            except DatabaseError as exc:
                log.warning("node %d stays out of the local occupancy grid: %s", node, exc)
                continue
            sig.depth_points = self._depth_points(depth, sig.camera, sig.scan is not None)

    def _localize(self, frame: SensorFrame, features: Features, stats: Statistics,
                  watch: Stopwatch) -> Hypothesis:
        """Localization mode: match against WM without adding a location; publish the pose."""
        memory = self.memory
        self.localization_pose = None
        word_ids = memory.vocabulary.match(features.descriptors) if len(features.descriptors) else np.zeros(0, np.int64)
        known = word_ids >= 0
        points3d = np.full((len(word_ids), 3), np.nan, np.float32)
        if frame.depth_m is not None and frame.camera is not None and len(word_ids):
            points3d = words_3d(features.keypoints, frame.depth_m, frame.camera)
        sig = Signature(id=0, map_id=memory.map_id, stamp_ns=frame.stamp_ns, word_ids=word_ids[known],
                        keypoints=_pinhole_keypoints(features, frame)[known], points3d=points3d[known],
                        T_odom_base=frame.T_odom_base, scan=frame.scan, camera=frame.camera)
        watch.lap("quantization")
        hypothesis = self._hypothesis(sig, stats)
        stats.highest_hypothesis_id = hypothesis.location_id
        stats.highest_hypothesis_value = hypothesis.probability
        watch.lap("bayes")
        if frame.T_odom_base is not None and self.validator.accepts(sig, hypothesis, self._previous_hypothesis_value, stats):
            old = memory.signatures[hypothesis.location_id]
            try:
                link = self.validator.verify(sig, old)
                poses = self.local.poses if old.id in self.local.poses else self.local.optimize_component(old.id)[0]
            except (RegistrationError, OptimizationError) as exc:
                stats.rejected_loop_closure_id = old.id
                log.debug("localization on %d rejected: %s", old.id, exc)
            else:
                self.localization_pose = poses[old.id] @ transforms.inverse(link.T_from_to)
                self.local.T_map_odom = self.localization_pose @ transforms.inverse(frame.T_odom_base)
                stats.loop_closure_id = old.id
                stats.localized = True
        watch.lap("verification")
        return hypothesis

    def _manage_memory(self, stats: Statistics, hypothesis: Hypothesis, timings: dict[str, float],
                       slam: bool) -> None:
        """Transfer WM -> LTM (Alg. 4) when pTime > T_time, and whenever WM is over the cap of
        :class:`WorkingMemoryBudget` (why the paper's rule alone does not bound WM here: there)."""
        wm_size = len(self.memory.wm)
        over = self._wm_budget.over(stats.process_time_ms)
        if slam:
            # A frame that stopped before a step (a bad signature has no Bayes step) spent nothing in it.
            self._wm_budget.observe(stats.process_time_ms, sum(timings.get(k, 0.0) for k in SCALING_STEPS),
                                    wm_size)
        cap = self._wm_budget.cap()
        excess = wm_size - cap if cap is not None else 0
        if not over and excess <= 0:
            return
        # Over T_time: one location more out than came in (this frame's and the retrieved ones).
        locations = max(excess, 2 + len(self.memory.retrieved_now) if over else 0)
        protected = self.memory.time_neighbours(hypothesis.location_id) if hypothesis.location_id else set()
        # Loop closures held for a merge need both ends in WM to be confirmed.
        protected |= self.validator.held_nodes()
        transferred = self.memory.transfer(protected | self.local.near_robot(stats.location_id), locations,
                                           balance_words=over)
        stats.transferred = len(transferred)
        self.local.wm_changed |= bool(transferred)
        self._forget(transferred, transferred_to_ltm=True)
        if len(transferred) >= HEAP_RELEASE_MIN_TRANSFERRED:
            # A cap drop freed hundreds of locations all over the heap: give the pages back
            # (core/heap.py), or RSS stays at WM's high-water mark.
            t0 = time.perf_counter()
            released = release_free_heap()
            log.debug("%d locations transferred, free heap %s to the system in %.1f ms", len(transferred),
                      "returned" if released else "not returned", (time.perf_counter() - t0) * 1000.0)

    def _fill_sizes(self, stats: Statistics) -> None:
        memory = self.memory
        stats.wm_size = len(memory.wm)
        stats.stm_size = len(memory.stm)
        stats.ltm_size = memory.ltm_size
        stats.vocabulary_size = len(memory.vocabulary)
        stats.words_added = memory.words_added
        stats.local_map_size = len(self.local.poses)


def frame_features(extractor: FeatureExtractor, frame: SensorFrame) -> Features:
    """The features of ``frame``'s RGB image (none without one), detected where its depth is valid
    when it has one (FeatureParams.depth_as_mask): Alg. 2 lines 2-3."""
    if frame.rgb is None:
        return extractor.empty()
    return extractor.extract(frame.rgb, frame.depth_m)


def _pinhole_keypoints(features: Features, frame: SensorFrame) -> np.ndarray:
    """The keypoints as the camera model's pinhole sees them: undistorted when the images are not
    rectified (registration projects words with the pinhole model), as they are otherwise."""
    return features.keypoints if frame.camera is None else frame.camera.undistort(features.keypoints)


def _delete_database(path: Path) -> None:
    for suffix in ("", "-wal", "-shm"):
        candidate = Path(f"{path}{suffix}")
        if candidate.exists():
            candidate.unlink()
