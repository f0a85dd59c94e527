"""Short-Term, Working and Long-Term Memory (2013 §III, Fig. 2; 2014 §II-C).

* STM: the newest ``T_STM`` locations; rehearsal (weight update, §III-B) happens here; they are
  not loop closure hypotheses.
* WM: locations used for loop closure detection and the local map; their words form the
  vocabulary.
* LTM: the SQLite database. Every location is written there when created (so a killed process
  loses at most the frame in flight); *transfer* (Alg. 4) only drops a location from RAM and from
  the vocabulary, *retrieval* (Alg. 3) brings it back. RAM keeps of an LTM location only its
  session (id ranges) and, in SLAM mode, its kept pose (``node_tables``); its links to other LTM
  locations are read from the database when a graph search (retrieval, the Bayes filter's
  neighbourhoods) walks through LTM.

All database writes of a frame go in one :class:`WriteBatch` committed by the background writer
(Alg. 1 line 17 joins it at the next frame).
"""

from __future__ import annotations

import logging
from collections import Counter, deque
from typing import Callable, Container, Iterable, Iterator, Optional

import numpy as np

from rtabmap_ros2.core import transforms
from rtabmap_ros2.core.database import BackgroundWriter, Database, SensorBlobs, WriteBatch
from rtabmap_ros2.core.graph import Graph, Link, LinkType, loop_type
from rtabmap_ros2.core.node_tables import SessionIds
from rtabmap_ros2.core.params import Params
from rtabmap_ros2.core.sensor import LaserScan
from rtabmap_ros2.core.signature import Signature, similarity
from rtabmap_ros2.core.vocabulary import Vocabulary

log = logging.getLogger(__name__)


class Memory:
    """The memory of locations, its vocabulary, its graph and its database."""

    def __init__(self, params: Params, database: Database, binary_descriptors: bool) -> None:
        self.params = params
        self.db = database
        self.writer = BackgroundWriter(database)
        # In RAM, as in RTAB-Map: the links that touch a location in memory (STM/WM); a link
        # between two LTM locations is in the database only (RAM stays flat once WM stops
        # growing). Session of every node as id ranges, and how many inter-session loop closures
        # join each pair of sessions (which maps are one: connected_maps).
        self.graph = Graph()
        self.map_ids = SessionIds(database.first_node_of_maps(), database.max_location_id())
        self.node_count = database.node_count()
        self.session_links: Counter[tuple[int, int]] = Counter()
        for a, b in database.inter_session_pairs():
            self.session_links[_pair(self.map_ids[a], self.map_ids[b])] += 1
        self.vocabulary = Vocabulary(params.vocabulary, binary=binary_descriptors,
                                     next_word_id=database.max_word_id() + 1)
        self.signatures: dict[int, Signature] = {}
        self.stm: list[int] = []
        self.wm: dict[int, None] = {}  # insertion-ordered set
        self.last_loop_closure_id = 0
        self.next_location_id = database.max_location_id() + 1
        self.map_id = database.max_map_id() + 1
        self.words_added = 0
        self.retrieved_now: list[int] = []
        self.on_graph_change: Callable[..., None] = lambda *ids: None
        self._batch = WriteBatch()
        self._new_locations: dict[int, SensorBlobs | None] = {}
        self._load_working_memory()

    # -- reopening ---------------------------------------------------------------------------
    def _load_working_memory(self) -> None:
        """Reopen: what was in STM/WM becomes WM again; mapping continues in a new map (2014 §II-C)."""
        ids = self.db.wm_ids()
        if not ids:
            return
        for link in self.db.load_links(ids):
            self.graph.add_link(link)
        signatures = self.db.load_signatures(ids)
        missing = sorted({int(w) for s in signatures for w in s.word_ids.tolist()})
        descriptors = self.db.load_words(missing)
        if descriptors:
            word_ids = np.fromiter(descriptors.keys(), dtype=np.int64, count=len(descriptors))
            self.vocabulary.add_words(word_ids, np.stack(list(descriptors.values())))
        for sig in signatures:
            self.signatures[sig.id] = sig
            self.wm[sig.id] = None
            self.vocabulary.add_references(sig.id, sig.word_ids)
        log.info("reopened %s: %d locations in WM, %d words, continuing as map %d",
                 self.db.path, len(self.wm), len(self.vocabulary), self.map_id)

    # -- sizes -------------------------------------------------------------------------------
    @property
    def ltm_size(self) -> int:
        return self.node_count - len(self.signatures)

    def connected_maps(self, map_id: int) -> set[int]:
        """Map ids joined to ``map_id`` by inter-session loop closures (itself included): the
        sessions of its connected component (each session is connected by its neighbour links)."""
        adjacent: dict[int, list[int]] = {}
        for a, b in self.session_links:  # pairs with at least one link (_count_session_link)
            adjacent.setdefault(a, []).append(b)
            adjacent.setdefault(b, []).append(a)
        found = {map_id}
        stack = [map_id]
        while stack:
            for other in adjacent.get(stack.pop(), ()):
                if other not in found:
                    found.add(other)
                    stack.append(other)
        return found

    def last_location(self) -> Signature | None:
        """The newest location in STM (or WM when STM is empty)."""
        if self.stm:
            return self.signatures[self.stm[-1]]
        return self.signatures[next(reversed(self.wm))] if self.wm else None

    # -- location creation (Alg. 2) and bad signatures -----------------------------------------
    def is_bad_signature(self, n_features: int) -> bool:
        """T_bad (2013 §III-A): no feature, or fewer than ``T_bad`` x the mean words of the locations
        in WM and STM, as RTAB-Map's Memory::createSignature decides (Kp/BadSignRatio): their word
        occurrences over their number, bad signatures (kept without words) counted, in integers.

        The mean over the locations held, not over every image seen: low-texture stretches lower it
        (their bad signatures count without words), so the next weak image of the stretch keeps its
        words (the 84 images halved: RTAB-Map's logged mean is 208 words, 174 after bad image 6 and
        135 at image 17, which stays a location with words)."""
        held = len(self.signatures)
        mean = self.vocabulary.total_references // held if held else 0
        return n_features == 0 or n_features < self.params.memory.bad_signature_ratio * mean

    def quantize(self, descriptors: np.ndarray) -> np.ndarray:
        """Quantise descriptors to words, adding the unmatched ones to the vocabulary (§III-A)."""
        if len(descriptors) == 0:
            return np.zeros(0, np.int64)
        word_ids, is_new = self.vocabulary.quantize(descriptors)
        new_ids = word_ids[is_new]
        for word_id, desc in zip(new_ids.tolist(), descriptors[is_new]):
            self._batch.words[word_id] = desc
        self.words_added += int(is_new.sum())
        return word_ids

    def add_location(self, sig: Signature, blobs: SensorBlobs | None, neighbor: Link | None) -> None:
        """Insert a new location in STM with its neighbour link (Alg. 1 line 7)."""
        self.signatures[sig.id] = sig
        self.map_ids.add(sig.id, sig.map_id)
        self.node_count += 1
        self.stm.append(sig.id)
        self.graph.add_node(sig.id)
        self.vocabulary.add_references(sig.id, sig.word_ids)
        self._new_locations[sig.id] = blobs
        if neighbor is not None:
            self.add_link(neighbor)

    def add_link(self, link: Link) -> None:
        self._count_session_link(self.graph.link(link.from_id, link.to_id), -1)
        self.graph.add_link(link)
        self._count_session_link(link, +1)
        self._batch.add_link(link)
        self.on_graph_change(link.from_id, link.to_id)

    def remove_link(self, a: int, b: int) -> None:
        """Drop a link (e.g. a loop closure the robust optimiser found inconsistent)."""
        self.on_graph_change(a, b)
        self._count_session_link(self.graph.link(a, b), -1)
        self.graph.remove_link(a, b)
        self._batch.delete_link(a, b)

    def _count_session_link(self, link: Link | None, change: int) -> None:
        if link is not None and link.type is LinkType.LOOP_INTER:
            pair = _pair(self.map_ids[link.from_id], self.map_ids[link.to_id])
            self.session_links[pair] += change
            if self.session_links[pair] <= 0:
                del self.session_links[pair]

    # -- weight update / rehearsal (§III-B, Eq. 1) ------------------------------------------------
    def rehearse(self, sig: Signature, new_word_ids: Iterable[int]) -> tuple[int, float]:
        """Merge the new location ``sig`` into the previous STM location when Eq. 1 reaches T_similarity.

        As RTAB-Map's Memory::rehearsalMerge at its default (Mem/RehearsalIdUpdatedToNewOne false):
        the older location L_c stays, with its id, words and sensor data, and its weight grows by
        L_t's plus one; L_t, whose only link is the neighbour link to L_c, is deleted, and the words
        it had just added leave the vocabulary. A loop closure found later names the image that
        holds the words (issue 32: keeping the newer id with the older image's words made loop
        closures 1-4 images off the ground truth's pairs: 32 of 37 false ones on a 3,000-image run).

        With ``memory.rehearsal_id_updated_to_new_one`` (RTAB-Map's Mem/RehearsalIdUpdatedToNewOne,
        config/rtabmap.yaml's for SLAM) the merge goes the other way: ``sig`` stays, with its id,
        odometry pose, scan and stamp, takes L_c's words (L_c's 3D points moved into its frame through
        their neighbour link), and L_c's links are re-anchored on it; L_c is deleted.

        SLAM mode (odometry): when the neighbour link between them shows the camera moved
        (``memory.rehearsal_max_distance`` / ``rehearsal_max_angle``), both locations are kept and
        only the weight moves to ``sig`` (or nothing happens with
        ``rehearsal_weight_ignored_while_moving``), as RTAB-Map does: merging a moving camera's
        locations would drop places the map needs.

        Returns ``(merged, similarity)``: the id of the deleted location (``sig.id``, or L_c's with
        ``rehearsal_id_updated_to_new_one``), or 0, and the Eq. 1 similarity with the previous location
        (0 when not compared).
        """
        if sig.bad or len(self.stm) < 2:
            return 0, 0.0
        prev = self.signatures[self.stm[-2]]
        if prev.bad or prev.map_id != sig.map_id:
            return 0, 0.0
        params = self.params.memory
        value = similarity(sig.word_counts(), prev.word_counts())
        if value < params.rehearsal_similarity:
            return 0, value
        neighbor = self.graph.link(prev.id, sig.id)
        if sig.T_odom_base is not None and neighbor is not None and self._moved(neighbor.T_from_to):
            if not params.rehearsal_weight_ignored_while_moving:
                sig.weight += prev.weight + 1
                prev.weight = 0
                self._batch.weights[prev.id] = 0
            return 0, value
        orphans = set(self.vocabulary.remove_references(sig.id, sig.word_ids))
        fresh = [w for w in new_word_ids if w in orphans]
        if fresh:
            self.vocabulary.remove_words(np.asarray(fresh, dtype=np.int64))
            for w in fresh:
                self._batch.words.pop(w, None)
            self.words_added -= len(fresh)
        if params.rehearsal_id_updated_to_new_one:
            return self._merge_into_new(sig, prev, neighbor), value
        prev.weight += sig.weight + 1
        self._batch.weights[prev.id] = prev.weight
        self._delete_stm_location(sig.id)
        return sig.id, value

    def _delete_stm_location(self, node: int) -> list[Link]:
        """Rehearsal's deletion of an STM location merged into another: it leaves the graph (its
        links deleted), STM and the database's pending writes. Returns its links, oriented from it."""
        self.on_graph_change(node)
        links = self.graph.remove_node(node)
        for link in links:
            self._count_session_link(link, -1)
            self._batch.delete_link(link.from_id, link.to_id)
        self.stm.remove(node)
        del self.signatures[node]
        self.node_count -= 1
        self._new_locations.pop(node, None)
        self._batch.deleted_locations.append(node)
        return links

    def _merge_into_new(self, sig: Signature, prev: Signature, neighbor: Optional[Link]) -> int:
        """Rehearsal at ``rehearsal_id_updated_to_new_one``: ``prev`` merged into ``sig`` (see
        :meth:`rehearse`); ``sig``'s own new words have already left the vocabulary. Returns ``prev.id``."""
        # sig -> prev from the stored neighbour link (scan-refined when it was), not raw odometry:
        # prev's links are re-anchored on sig through it (issue 14 item 5).
        T_t_c = transforms.identity()
        if neighbor is not None:
            T_t_c = transforms.inverse(neighbor.T_from_to)
        elif sig.T_odom_base is not None and prev.T_odom_base is not None:
            T_t_c = transforms.relative(sig.T_odom_base, prev.T_odom_base)
        sig.word_ids = prev.word_ids
        sig.keypoints = prev.keypoints
        sig.points3d = _transform_points(T_t_c, prev.points3d)
        self.vocabulary.add_references(sig.id, sig.word_ids)
        self.vocabulary.remove_references(prev.id, prev.word_ids)
        # Weight of L_t increased by L_c's plus one; L_c's links redirected to L_t; L_c deleted.
        sig.weight += prev.weight + 1
        for link in self._delete_stm_location(prev.id):
            if link.to_id == sig.id:
                continue
            kind = (LinkType.NEIGHBOR if link.type is LinkType.NEIGHBOR
                    else loop_type(sig.map_id, self.map_ids[link.to_id]))
            information = link.information
            if neighbor is not None:
                information = _composed_information(neighbor.information, link.information)
            self.add_link(Link(sig.id, link.to_id, kind, T_t_c @ link.T_from_to, information))
        if self.last_loop_closure_id == prev.id:
            self.last_loop_closure_id = sig.id
        return prev.id

    def _moved(self, T: np.ndarray) -> bool:
        """True when a neighbour link shows the camera moved (RTAB-Map's rehearsal isMoving)."""
        params = self.params.memory
        return bool(np.abs(T[:3, 3]).max() > params.rehearsal_max_distance
                    or transforms.rotation_angle(T) > params.rehearsal_max_angle)

    # -- STM -> WM ------------------------------------------------------------------------------
    def update_stm(self) -> None:
        """Move the oldest STM locations to WM while STM holds more than T_STM (Alg. 1 l. 9-10)."""
        while len(self.stm) > self.params.memory.stm_size:
            self.wm[self.stm.pop(0)] = None

    def flush_stm(self) -> None:
        """A new map starts: the previous session's STM joins WM (memory is kept, 2014 §III)."""
        for node in self.stm:
            self.wm[node] = None
        self.stm.clear()

    # -- Bayes filter support -------------------------------------------------------------------
    def hypothesis_ids(self) -> np.ndarray:
        """Sorted ids of WM locations that can be loop closure hypotheses (not bad signatures)."""
        ids = [i for i in self.wm if not self.signatures[i].bad]
        return np.asarray(sorted(ids), dtype=np.int64)

    def similarities(self, sig: Signature, candidates: np.ndarray) -> dict[int, float]:
        """Raw score of every candidate (0 for those sharing no word), ``bayes.likelihood``'s:

        * ``eq1``: Eq. 1, matched word pairs over the size of the larger signature;
        * ``tf_idf``: RTAB-Map's Memory::computeLikelihood with Kp/TfIdfLikelihoodUsed,
          ``sum over the distinct words w of sig of n_wj log10(N / n_w) / n_j``: n_wj occurrences
          of w in location j, n_j words of j, n_w locations in memory (STM, WM and this one)
          holding w, N locations in memory. A word seen everywhere weighs nothing.
        """
        counts = sig.word_counts()
        wanted = set(candidates.tolist())
        out = dict.fromkeys(candidates.tolist(), 0.0)
        if self.params.bayes.likelihood == "tf_idf":
            for loc, score in self.vocabulary.tf_idf_scores(counts, wanted, len(self.signatures)).items():
                out[loc] = score / max(len(self.signatures[loc].word_ids), 1)
            return out
        n_t = len(sig.word_ids)
        for loc, n_pair in self.vocabulary.scores(counts, wanted).items():
            out[loc] = n_pair / max(n_t, len(self.signatures[loc].word_ids))
        return out

    def add_loop_closure(self, link: Link, transfer_weight: bool = True) -> tuple[int, int, int]:
        """Loop closure link and weight transfer (§III-D): w_t += w_i, w_i = 0 (not for a proximity
        detection, ``transfer_weight`` False: the link alone, the Bayes filter did not choose it).

        Returns what :meth:`undo_loop_closure` needs: (w_t, w_i, last loop closure id) before.
        """
        current = self.signatures[link.from_id]
        old = self.signatures[link.to_id]
        before = (current.weight, old.weight, self.last_loop_closure_id)
        if not transfer_weight:
            self.add_link(link)
            return before
        current.weight += old.weight
        old.weight = 0
        self._batch.weights[old.id] = 0
        self.last_loop_closure_id = max(current.id, old.id)
        self.add_link(link)
        return before

    def undo_loop_closure(self, link: Link, before: tuple[int, int, int]) -> None:
        """Remove a loop closure found inconsistent after optimisation, restoring the weights."""
        self.remove_link(link.from_id, link.to_id)
        current_weight, old_weight, last_id = before
        for node, weight in ((link.from_id, current_weight), (link.to_id, old_weight)):
            if node in self.signatures:
                self.signatures[node].weight = weight
                self._batch.weights[node] = weight
        self.last_loop_closure_id = last_id

    # -- retrieval (Alg. 3) ---------------------------------------------------------------------
    def retrieval_candidates(self, hypothesis_id: int, limit: Optional[int] = None,
                             exclude: Iterable[int] = ()) -> list[int]:
        """LTM neighbours of the hypothesis within ``bayes.neighborhood`` hops: time neighbours
        first, then space neighbours, nearest first (then by id) (§III-E); the first ``limit``
        not in ``exclude``. The search reads an LTM location's links from the database
        (RTAB-Map's Memory::getNeighborsId) and stops at the first hop that gives enough. Nothing
        to search while LTM is empty (every frame until memory management first transfers)."""
        if hypothesis_id not in self.signatures or not self.ltm_size:
            return []
        excluded = set(exclude)
        found: list[int] = []

        def collect(levels: Iterator[list[int]], skip: set[int]) -> bool:
            for level in levels:
                found.extend(n for n in sorted(level) if n not in self.signatures and n not in skip
                             and n not in excluded)
                if limit is not None and len(found) >= limit:
                    return True
            return False

        reach = self.params.bayes.neighborhood
        time_hops: set[int] = set()
        if collect(self._levels(hypothesis_id, reach, (LinkType.NEIGHBOR,), reached=time_hops), set()):
            return found[:limit]
        collect(self._levels(hypothesis_id, reach, None), time_hops)
        return found[:limit]

    def hops_from(self, start: int, max_hops: int, types: Optional[tuple[LinkType, ...]] = None,
                  allowed: Optional[Container[int]] = None, free: tuple[LinkType, ...] = ()) -> dict[int, int]:
        """Hop distance to every node within ``max_hops`` of ``start`` over the whole graph, WM
        and LTM (``Graph.hops_from``, LTM links read from the database): the Bayes filter's
        neighbourhoods, as when every link was in RAM. With ``allowed``, only through nodes in it;
        links of ``free`` types are crossed without counting a hop."""
        return {node: hop for hop, level in enumerate(self._levels(start, max_hops, types, allowed=allowed, free=free))
                for node in level}

    def neighbors(self, node: int, types: Optional[tuple[LinkType, ...]] = None) -> list[int]:
        """Nodes linked to ``node`` by a link of ``types`` (None: all; ``Graph.neighbors`` over the whole graph)."""
        return self._adjacent([node], types)

    def _levels(self, start: int, reach: int, types: Optional[tuple[LinkType, ...]],
                reached: Optional[set[int]] = None, allowed: Optional[Container[int]] = None,
                free: tuple[LinkType, ...] = ()) -> Iterator[list[int]]:
        """Breadth-first levels from ``start`` (itself first) up to ``reach`` hops over links of
        ``types`` (None: all) and nodes in ``allowed`` (None: all), RAM for locations in memory,
        the database for LTM ones; every node reached goes into ``reached``. Nodes reached through
        links of ``free`` types (among ``types``) join the level they are reached from."""
        reached = set() if reached is None else reached
        free = tuple(t for t in free if types is None or t in types)

        def unreached(nodes: list[int], through: Optional[tuple[LinkType, ...]]) -> list[int]:
            out = []
            for other in self._adjacent(nodes, through):
                if other not in reached and (allowed is None or other in allowed):
                    reached.add(other)
                    out.append(other)
            return out

        reached.add(start)
        level = [start]
        for hop in range(reach + 1):
            frontier = level
            while free and frontier:
                frontier = unreached(frontier, free)
                level.extend(frontier)
            yield level
            if hop == reach:
                return
            level = unreached(level, types)
            if not level:
                return

    def _adjacent(self, nodes: list[int], types: Optional[tuple[LinkType, ...]]) -> list[int]:
        """Nodes linked to any of ``nodes`` by a link of ``types`` (None: all), in link order."""
        out: list[int] = []
        in_ltm = []
        for node in nodes:
            if node in self.signatures:
                out.extend(self.graph.neighbors(node, types))
            else:
                in_ltm.append(node)
        if in_ltm:
            out.extend(other for _, other, kind in self.db.link_ends(in_ltm) if types is None or kind in types)
        return out

    def local_retrieval_candidates(self, nearest: list[int], limit: int) -> list[int]:
        """SLAM mode: up to ``limit`` LTM locations linked to ``nearest`` (the local map's nodes
        nearest the robot, nearest first; newest link first), then LTM neighbours of those: the
        map around the robot comes back when it revisits a place whose locations went to LTM,
        not only around the highest hypothesis (RTAB-Map's RGBD/MaxLocalRetrieved,
        Rtabmap::process retrieval 2/3)."""
        found: list[int] = []
        for sources in (nearest, found):
            for node in sources:  # ``found`` grows while its neighbours are looked at
                for other in sorted(self.neighbors(node), reverse=True):
                    if len(found) >= limit:
                        return found
                    if other not in self.signatures and other not in found:
                        found.append(other)
        return found

    def scans(self, ids: Iterable[int]) -> dict[int, LaserScan]:
        """Laser scans of locations ``ids`` that have one: from WM, else read from LTM (not retrieved)."""
        ids = list(ids)
        found = {n: self.signatures[n].scan for n in ids
                 if n in self.signatures and self.signatures[n].scan is not None}
        in_ltm = [n for n in ids if n not in self.signatures]
        if in_ltm:
            found.update(self.db.load_scans(in_ltm))
        return found

    def retrieve(self, ids: list[int]) -> list[int]:
        """Bring the LTM locations ``ids`` back to WM (Alg. 3); returns the ids retrieved."""
        ids = [n for n in dict.fromkeys(ids) if n not in self.signatures]
        if not ids:
            return []
        signatures = self.db.load_signatures(ids)
        for sig in signatures:
            self._requantize(sig)
            self.signatures[sig.id] = sig
            self.wm[sig.id] = None
            self.vocabulary.add_references(sig.id, sig.word_ids)
            self._batch.in_wm[sig.id] = True
        ids = [sig.id for sig in signatures]
        # Their links come back to RAM with them (also those to other LTM locations).
        for link in self.db.load_links(ids):
            self.graph.add_link(link)
        self.retrieved_now.extend(ids)
        return ids

    def _requantize(self, sig: Signature) -> None:
        """Old words no longer in the vocabulary are matched to current ones, or re-added (Alg. 3)."""
        words = sig.word_ids
        gone = np.unique(words[~self.vocabulary.present(words)])
        if not len(gone):
            return
        descriptors = self.db.load_words(gone.tolist())
        gone = np.asarray([w for w in gone.tolist() if w in descriptors], dtype=np.int64)
        if not len(gone):
            return
        desc = np.stack([descriptors[int(w)] for w in gone])
        matched = self.vocabulary.match(desc)
        replace = matched >= 0
        if replace.any():
            mapping = dict(zip(gone[replace].tolist(), matched[replace].tolist()))
            sig.word_ids = np.asarray([mapping.get(w, w) for w in words.tolist()], dtype=np.int64)
            self._batch.location_words[sig.id] = sig.word_ids
        if (~replace).any():
            self.vocabulary.add_words(gone[~replace], desc[~replace])
            self.words_added += int((~replace).sum())

    # -- transfer (Alg. 4) ----------------------------------------------------------------------
    def transfer(self, protected: set[int], locations: int, balance_words: bool) -> list[int]:
        """Move the lowest-weighted WM locations to LTM (among equal weights, from the session
        holding most of WM, then the oldest): at least ``locations`` of them and, with
        ``balance_words``, until as many words left the vocabulary as came in this frame
        (Alg. 4). Returns the transferred ids."""
        immune = set(protected) | set(self.retrieved_now) | self._recent_immune()
        per_map: dict[int, int] = {}
        for node in self.wm:
            m = self.signatures[node].map_id
            per_map[m] = per_map.get(m, 0) + 1
        # Lowest weight first (Alg. 4); among equal weights, from the session holding the most
        # of WM, then the oldest: a session being mapped must not drain the others out of WM, or
        # the next one finds nothing to close a loop with (5 sessions at T_time 0.1 s, oldest
        # first: 1-5 nodes left of each of the first three, 3 components).
        by_weight: dict[int, dict[int, deque[int]]] = {}
        for n in sorted(n for n in self.wm if n not in immune):
            sig = self.signatures[n]
            by_weight.setdefault(sig.weight, {}).setdefault(sig.map_id, deque()).append(n)
        # (Not at least one word: with no new word, e.g. revisiting, every location whose words
        # others share would go, and without words at all WM emptied in one frame.)
        wanted = self.words_added if balance_words else 0
        transferred: list[int] = []
        words_out = 0
        orphaned: list[int] = []  # words no WM location references: out of the vocabulary at once
        keep_one = self.params.memory.keep_one_node_per_session
        for weight in sorted(by_weight):
            maps = by_weight[weight]
            while maps and (words_out < wanted or len(transferred) < locations):
                m = max(maps, key=lambda k: (per_map[k], -maps[k][0]))
                node = maps[m].popleft()
                if not maps[m]:
                    del maps[m]
                if keep_one and per_map[m] <= 1:
                    continue
                sig = self.signatures[node]
                orphans = self.vocabulary.remove_references(node, sig.word_ids)
                orphaned.extend(orphans)
                words_out += len(orphans)
                per_map[m] -= 1
                del self.wm[node]
                del self.signatures[node]
                self._drop_ltm_links(node)
                self._batch.in_wm[node] = False
                self._batch.weights[node] = sig.weight
                transferred.append(node)
            if words_out >= wanted and len(transferred) >= locations:
                break
        # One removal for all (a WM cap drop of 429 locations: 0.26 s one by one, most of it per call).
        self.vocabulary.remove_words(np.asarray(orphaned, dtype=np.int64))
        return transferred

    def _drop_ltm_links(self, node: int) -> None:
        """``node`` left memory: its links to other LTM locations leave RAM (they are in the
        database, or in this frame's batch, committed before anything reads them back)."""
        for other in self.graph.neighbors(node):
            if other not in self.signatures:
                self.graph.remove_link(node, other)
                self.graph.discard_isolated(other)
        self.graph.discard_isolated(node)

    def _recent_immune(self) -> set[int]:
        """T_recent: the highest-weighted WM locations after the last loop closure (§III-F)."""
        budget = int(self.params.memory.recent_wm_ratio * len(self.wm))
        if budget <= 0:
            return set()
        recent = [n for n in self.wm if n > self.last_loop_closure_id]
        ranked = sorted(recent, key=lambda n: (self.signatures[n].weight, n), reverse=True)
        return set(ranked[:budget])

    def time_neighbours(self, node_id: int) -> set[int]:
        """Neighbours in time of a node within the transition model's range (protected from transfer)."""
        if node_id not in self.signatures:
            return set()
        return set(self.hops_from(node_id, self.params.bayes.neighborhood, types=(LinkType.NEIGHBOR,)))

    # -- database --------------------------------------------------------------------------------
    def record_statistics(self, row: dict) -> None:
        self._batch.statistics.append(row)

    def commit(self) -> None:
        """Hand this frame's changes to the background writer (one transaction)."""
        batch = self._batch
        for node, blobs in self._new_locations.items():
            sig = self.signatures.get(node)
            if sig is not None:
                batch.locations.append((sig, blobs))  # a new location starts in WM (in_wm = 1)
        for node in list(batch.weights):
            if node in self.signatures:
                batch.weights[node] = self.signatures[node].weight
        self.writer.submit(batch)
        self._batch = WriteBatch()
        self._new_locations = {}
        self.words_added = 0
        self.retrieved_now = []

    def join(self) -> None:
        """Wait for the previous frame's database writes (Alg. 1 line 17)."""
        self.writer.join()

    def close(self) -> None:
        """Write what is pending and close the database."""
        self.commit()
        self.writer.join()
        self.vocabulary.close()
        self.db.close()


def _composed_information(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Information of two links chained: their covariances add (RTAB-Map's Link::merge)."""
    return np.linalg.inv(np.linalg.inv(a) + np.linalg.inv(b))


def _transform_points(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply a 4x4 transform to (N,3) points (NaN rows stay NaN)."""
    if not len(points):
        return points
    out = points.astype(np.float64) @ T[:3, :3].T + T[:3, 3]
    return out.astype(np.float32)


def _pair(a: int, b: int) -> tuple[int, int]:
    return (a, b) if a <= b else (b, a)
