"""Incremental visual vocabulary and inverted index (2013 §III-A, Alg. 2 lines 4-5).

Each word is one feature descriptor. A new image's descriptors are quantised by a 2-nearest-
neighbour search over the current words and the nearest neighbour distance ratio (NNDR) test:
a descriptor is the nearest word if ``d1 <= T_NNDR * d2`` (RTAB-Map's form: an exact duplicate,
d1 = d2 = 0, matches); otherwise it becomes a new word. A frame's new words are compared together
(``new_words_compared_together``, RTAB-Map's Kp/NewWordsComparedTogether): a feature repeated in
one image gives one word.

The word search (``vocabulary.index``):

* kdtree (default): RTAB-Map's own approximate search (``Kp/NNStrategy`` 1: FLANN randomized
  kd-trees over the descriptors' bits, 32 checks; ``core/kdtree.py``). A frame's new words enter
  the trees when the next frame searches, as RTAB-Map's VWDictionary::update; the trees are
  rebuilt when they have doubled, in a background thread swapped in at a fixed search count
  (``rebuild_swap_frames``, and past 20,000 words one search per 1,000 words), as soon after RTAB-Map's rebuild in the
  call as a frame's time bound allows; the same images give the same words whatever the load. Binary
  descriptors only: with float ones (``features.detector: sift``) the exact search below is used
  (logged at construction).
* flat: exact brute force (faiss ``knn_hamming`` / ``knn``, one OpenMP thread) over a contiguous
  numpy buffer of the words. Removing a word moves a last row into its slot: O(removed).

The paper rebuilt its kd-trees over the whole vocabulary at every frame, its most expensive step;
here they are rebuilt only when they have doubled, off the frame. Exact search was the default
before issue 48: Eq. 3-4's mean and deviation are taken over the chance scores an approximate
search gives many WM locations, and without them the likelihood needed a trim that broke real
images (docs/benchmarks.md).

Distances: Hamming (bits) for binary descriptors, Euclidean for float ones (faiss returns squared
L2: the square root is taken before the ratio test). Fewer than two words: the NNDR test needs a
second neighbour, so every descriptor is a new word.

The inverted index maps word -> {location id: occurrences} and gives the numerator of Eq. 1 (the
matched word pairs) for every location sharing a word with a query signature (:meth:`scores`).
It is stored in two parts. Most words occur once in one location (81 % of 151 k words on a
simulated run): that location is kept in a numpy column beside the word's row (``_owner``), with no
Python object per word. Every other word (several locations or occurrences, or a word not in the
vocabulary) has a dict in ``_shared``. A dict per word cost ~300 B of CPython's small objects
(~130 MB at 455 k words); churned by transfers and retrievals, those objects fragmented the
allocator's arenas and RSS crept at a constant WM (``bench/bench_slam.py``'s memory samples).
"""

from __future__ import annotations

import logging
import math
from collections import defaultdict
from contextlib import contextmanager
from typing import Iterable

import faiss
import numpy as np

from rtabmap_ros2.core import kdtree
from rtabmap_ros2.core.id_index import IdIndex
from rtabmap_ros2.core.params import VocabularyParams
from rtabmap_ros2.errors import SensorDataError

logger = logging.getLogger(__name__)

# Initial capacity (words) of the descriptor buffer; it doubles when full.
INITIAL_CAPACITY = 4096
# A word's dict in the inverted index is copied into a smaller one when it shrinks to a power of
# two from this size on (remove_references).
_COMPACT_MIN = 8
NEAREST_NEIGHBOURS = 2
# OpenMP threads of the exact search's faiss calls, set around each call and restored. 400 queries,
# 20k ORB words, 2 cores shared with load 16: knn_hamming median 115 ms wall (19 ms CPU) on one
# thread, 192 ms (44 ms CPU) on two: the team waits for a descheduled thread.
SEARCH_THREADS = 1


@contextmanager
def _omp_threads(n_threads: int):
    """Run this thread's faiss calls with n_threads OpenMP threads, then restore the setting."""
    previous = faiss.omp_get_max_threads()
    faiss.omp_set_num_threads(n_threads)
    try:
        yield
    finally:
        faiss.omp_set_num_threads(previous)


def _as_ids(word_ids: Iterable[int] | np.ndarray) -> np.ndarray:
    """(N,) int64 contiguous array of word ids."""
    return np.ascontiguousarray(np.asarray(word_ids, dtype=np.int64).reshape(-1))


def _pairwise_distances(descriptors: np.ndarray, binary: bool) -> np.ndarray:
    """(N,N) distances between the rows of one frame: Hamming bits (faiss, no BLAS call whose
    spinning threads would slow the vocabulary search that follows) or L2."""
    n = descriptors.shape[0]
    if binary:
        descriptors = np.ascontiguousarray(descriptors)
        out = np.empty((n, n), np.int32)
        faiss.hammings(faiss.swig_ptr(descriptors), faiss.swig_ptr(descriptors), n, n, descriptors.shape[1],
                       faiss.swig_ptr(out))
        return out
    x = descriptors.astype(np.float64)
    norms = np.einsum("ij,ij->i", x, x)
    return np.sqrt(np.maximum(norms[:, None] + norms[None, :] - 2.0 * (x @ x.T), 0.0))


def _nndr_accepts(d1, d2, nndr: float):
    """NNDR (§III-A) as RTAB-Map: the nearest candidate at d1 is matched when d1 <= T_NNDR * d2 (an
    exact duplicate, d1 = d2 = 0, matches); a missing second candidate (d2 inf) fails. Scalars or arrays."""
    return np.isfinite(d2) & (d1 <= nndr * d2)


class Vocabulary:
    """Words (descriptors) with int64 ids, a nearest-neighbour index and the inverted index."""

    def __init__(self, params: VocabularyParams, binary: bool, next_word_id: int = 1, *,
                 background_rebuild: bool = True):
        """Empty vocabulary.

        Args:
            params: NNDR threshold and index choice.
            binary: True for binary descriptors (uint8 rows, Hamming), False for float32 (L2).
            next_word_id: first id given to a new word (ids are never reused: pass the database's
                largest word id + 1 when continuing a map).
            background_rebuild: rebuild the kd-trees in a background thread (True) or in the call
                that doubles them (False: blocks that frame); the same words either way.
        """
        if next_word_id < 1:
            raise ValueError(f"next_word_id={next_word_id} is invalid: word ids start at 1")
        self.params = params
        self.binary = binary
        self.next_word_id = int(next_word_id)
        self._dtype = np.uint8 if binary else np.float32
        self._dim: int | None = None  # descriptor length (bytes or floats), set by the first words
        # Words: rows [0, _count) of _descriptors, with their ids in _ids; _row_of maps id -> row.
        self._descriptors: np.ndarray | None = None
        self._ids = np.zeros(0, np.int64)
        self._row_of = IdIndex()
        self._count = 0
        self.background_rebuild = bool(background_rebuild)
        # index="kdtree" with binary words: the trees (made with the first words), and the words not
        # indexed yet: as RTAB-Map's VWDictionary::update at the start of the next frame
        # (Memory::preUpdate), a word is put in the trees when the next frame searches, in id order,
        # unless it left the vocabulary since (the words of a location that rehearsal merged never
        # enter the trees).
        self.uses_kdtree = params.index == "kdtree" and binary
        if params.index == "kdtree" and not binary:
            logger.info("vocabulary.index kdtree searches binary descriptors; these are float descriptors "
                        "(features.detector sift): the exact search (flat) is used")
        if self.uses_kdtree:
            kdtree.warm_up()  # numba's compile or cache load, here rather than in the first frame
        self._kdtree: kdtree.RandomizedKdTrees | None = None
        self._kdtree_pending: dict[int, np.ndarray] = {}
        # Inverted index (word -> {location: occurrences}, module docstring): the location of a
        # word of the vocabulary that occurs once in one location is _owner[row] (0: none); any
        # other referenced word has a dict in _shared (never both).
        self._owner = np.zeros(0, np.int64)
        self._shared: dict[int, dict[int, int]] = {}
        # Word occurrences of every referencing location (RTAB-Map's
        # VWDictionary::getTotalActiveReferences): the bad-signature test's mean (Memory.is_bad_signature).
        self.total_references = 0

    # ------------------------------------------------------------------ words
    def __len__(self) -> int:
        """Number of words currently indexed."""
        return self._count

    def contains(self, word_id: int) -> bool:
        """True if the word is in the vocabulary (in RAM)."""
        return self._row_of.row(int(word_id)) >= 0

    def present(self, word_ids) -> np.ndarray:
        """(N,) bool: True where the word is in the vocabulary (one lookup for all of them)."""
        return self._row_of.rows(_as_ids(word_ids)) >= 0

    def word_ids(self) -> np.ndarray:
        """(N,) int64 ids of all words, in storage order."""
        return self._ids[: self._count].copy()

    def quantize(self, descriptors: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Quantise an image's descriptors (Alg. 2 line 5); unmatched ones become new words.

        With ``new_words_compared_together`` (RTAB-Map's Kp/NewWordsComparedTogether, default),
        the descriptors are taken in order and each is compared with the vocabulary *and* with
        the new words this image created before it: the two nearest of both go to the NNDR test,
        so a feature seen twice in one image gives one word (twice), not two words. Without it,
        matching uses the words present before the call only.

        Args:
            descriptors: (N,D) uint8 (binary) or float32 (float) descriptors.

        Returns:
            ``(word_ids, is_new)``: (N,) int64 word of each descriptor and (N,) bool, True where a
            new word was created.
        """
        descriptors = self._check_descriptors(descriptors)
        if self.params.new_words_compared_together:
            word_ids, is_new = self._match_with_new_words(descriptors)
        else:
            word_ids = self.match(descriptors)
            is_new = word_ids < 0
            word_ids[is_new] = np.arange(self.next_word_id, self.next_word_id + int(is_new.sum()), dtype=np.int64)
        n_new = int(is_new.sum())
        if n_new:
            # New words (§III-A): "a new word is created with the feature's descriptor".
            self.next_word_id += n_new
            self._insert(word_ids[is_new], descriptors[is_new])
        return word_ids, is_new

    def _match_with_new_words(self, descriptors: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Word ids and new-word flags when a frame's new words are compared together
        (RTAB-Map VWDictionary::addNewWords): per descriptor, in order, the two nearest among the
        vocabulary's 2-NN and this frame's earlier new words pass the NNDR test or a new word is
        made (ids from ``next_word_id`` on, in descriptor order, not inserted yet).

        Only an earlier row of the frame nearer than a descriptor's second vocabulary neighbour
        can change its answer, so the vocabulary's answer is taken for all rows at once and only
        rows with such a neighbour are walked in order."""
        n = descriptors.shape[0]
        if self._count:
            distances, neighbours = self._search(descriptors)
            distances = self._distances(distances)
        else:
            distances = np.full((n, NEAREST_NEIGHBOURS), np.inf, np.float32)
            neighbours = np.full((n, NEAREST_NEIGHBOURS), -1, np.int64)
        distances = np.where(neighbours >= 0, distances, np.inf).astype(np.float64)
        nndr = self.params.nndr
        best = neighbours[:, 0].copy()
        is_new = ~((best >= 0) & _nndr_accepts(distances[:, 0], distances[:, 1], nndr))
        same_word_as = np.full(n, -1, np.int64)  # row of an earlier new word of the frame matched
        if n > 1:
            within = _pairwise_distances(descriptors, self.binary).astype(np.float64)
            nearer = np.tril(within < distances[:, 1:2], k=-1)  # earlier rows nearer than d2
            for i in np.flatnonzero(nearer.any(axis=1)).tolist():
                rows = np.flatnonzero(nearer[i] & is_new)
                if rows.size == 0:
                    continue
                d1, d2 = float(distances[i, 0]), float(distances[i, 1])
                matched = -1
                # The frame's two nearest earlier new words, the earlier row first on a tie.
                for j in rows[np.argsort(within[i, rows], kind="stable")[:NEAREST_NEIGHBOURS]].tolist():
                    d = float(within[i, j])
                    if d < d1:
                        d1, d2, matched = d, d1, j
                    elif d < d2:
                        d2 = d
                accepted = (matched >= 0 or best[i] >= 0) and bool(_nndr_accepts(d1, d2, nndr))
                if matched >= 0 and accepted:
                    same_word_as[i] = matched
                is_new[i] = not accepted
        word_ids = np.where(is_new, -1, best)
        word_ids[is_new] = np.arange(self.next_word_id, self.next_word_id + int(is_new.sum()), dtype=np.int64)
        frame_matches = same_word_as >= 0
        word_ids[frame_matches] = word_ids[same_word_as[frame_matches]]
        return word_ids, is_new

    def _distances(self, distances: np.ndarray) -> np.ndarray:
        """faiss distances as distances: Hamming bits, or L2 (faiss returns it squared)."""
        return distances if self.binary else np.sqrt(np.maximum(distances, 0.0))

    def match(self, descriptors: np.ndarray) -> np.ndarray:
        """Nearest word of each descriptor passing the NNDR test, or -1; adds nothing.

        Args:
            descriptors: (N,D) uint8 (binary) or float32 (float) descriptors.

        Returns:
            (N,) int64 word ids, -1 where the NNDR test failed (or fewer than two words exist).
        """
        descriptors = self._check_descriptors(descriptors)
        n = descriptors.shape[0]
        result = np.full(n, -1, np.int64)
        if n == 0 or self._count < NEAREST_NEIGHBOURS:
            return result
        distances, neighbours = self._search(descriptors)
        distances = self._distances(distances)
        # A missing second neighbour (kd-tree: fewer than two words found) fails the NNDR test.
        found = (neighbours[:, 0] >= 0) & (neighbours[:, 1] >= 0)
        accepted = found & _nndr_accepts(distances[:, 0], distances[:, 1], self.params.nndr)
        result[accepted] = neighbours[accepted, 0]
        return result

    def add_words(self, word_ids, descriptors: np.ndarray) -> None:
        """Re-insert words with their ids (retrieval from LTM, Alg. 3).

        Args:
            word_ids: (N,) int64 ids, not currently in the vocabulary.
            descriptors: (N,D) descriptors of these words.
        """
        ids = _as_ids(word_ids)
        descriptors = self._check_descriptors(descriptors)
        if ids.shape[0] != descriptors.shape[0]:
            raise ValueError(f"add_words got {ids.shape[0]} ids for {descriptors.shape[0]} descriptors")
        if ids.size == 0:
            return
        if ids.min() < 1:
            raise ValueError(f"word id {int(ids.min())} is invalid: word ids are >= 1")
        present = ids[self.present(ids)].tolist()
        if present or np.unique(ids).size != ids.size:
            raise ValueError(f"add_words: ids already in the vocabulary or repeated: {present[:10]} "
                             "(remove them first or re-quantise their descriptors)")
        self._insert(ids, descriptors)
        self.next_word_id = max(self.next_word_id, int(ids.max()) + 1)

    def remove_words(self, word_ids) -> None:
        """Remove words from the vocabulary and the index (transfer to LTM, rehearsal), O(removed).

        Their inverted-index entries are dropped too.

        Raises:
            KeyError: a word is not in the vocabulary.
        """
        ids = np.unique(_as_ids(word_ids))
        if ids.size == 0:
            return
        rows = self._row_of.rows(ids)
        missing = ids[rows < 0].tolist()
        if missing:
            raise KeyError(f"remove_words: words not in the vocabulary: {missing[:10]}")
        if self.uses_kdtree:
            # A word not indexed yet just leaves the pending ones; the others are marked removed.
            pending = self._kdtree_pending
            indexed = [word for word in ids.tolist() if pending.pop(word, None) is None] if pending else ids
            if len(indexed) and self._kdtree is not None:
                self._kdtree.remove(np.asarray(indexed, np.int64))
        # The last rows of the buffer that stay fill the holes the removed rows leave below them
        # (in increasing order: deterministic), all at once.
        count = self._count - ids.size
        holes = np.sort(rows[rows < count])
        tail = np.ones(self._count - count, bool)
        tail[rows[rows >= count] - count] = False
        movers = count + np.flatnonzero(tail)
        self._descriptors[holes] = self._descriptors[movers]
        self._ids[holes] = self._ids[movers]
        self._owner[holes] = self._owner[movers]
        self._owner[count: self._count] = 0
        self._count = count
        shared = self._shared
        for word in ids.tolist():
            shared.pop(word, None)
        self._row_of.remove(ids)
        if holes.size:
            self._row_of.set_rows(self._ids[holes], holes)

    def descriptors_of(self, word_ids) -> np.ndarray:
        """(N,D) descriptors of the given words (KeyError if one is absent)."""
        ids = _as_ids(word_ids)
        if self._dim is None:
            if ids.size:
                raise KeyError(f"descriptors_of: the vocabulary is empty (asked {ids[:10].tolist()})")
            return np.zeros((0, 0), self._dtype)
        slots = self._row_of.rows(ids)
        if (slots < 0).any():
            raise KeyError(f"descriptors_of: word {int(ids[slots < 0][0])} is not in the vocabulary")
        return self._descriptors[slots].copy()

    @property
    def rebuilding(self) -> bool:
        """True while a background kd-tree rebuild is pending (not swapped in yet)."""
        return self._kdtree is not None and self._kdtree.rebuilding

    def close(self) -> None:
        """Wait for a pending kd-tree rebuild and discard it (idempotent; the vocabulary stays
        usable). Without close() the rebuild thread (a daemon) finishes on its own and the
        vocabulary is garbage-collectable."""
        if self._kdtree is not None:
            self._kdtree.close()

    # ------------------------------------------------------- inverted index
    def add_references(self, location_id: int, word_ids: np.ndarray) -> None:
        """Record that a location contains these words (one entry per occurrence)."""
        location_id = int(location_id)
        words, counts = np.unique(_as_ids(word_ids), return_counts=True)
        self.total_references += int(counts.sum())
        shared, owner = self._shared, self._owner
        for word, count, row in zip(words.tolist(), counts.tolist(), self._row_of.rows(words).tolist()):
            locations = shared.get(word)
            if locations is not None:
                locations[location_id] = locations.get(location_id, 0) + count
                continue
            previous = int(owner[row]) if row >= 0 else 0
            if row >= 0 and previous == 0 and count == 1:
                owner[row] = location_id
                continue
            # A second location or occurrence (or a word outside the vocabulary): a dict.
            locations = {previous: 1} if previous else {}
            locations[location_id] = locations.get(location_id, 0) + count
            shared[word] = locations
            if row >= 0:
                owner[row] = 0

    def remove_references(self, location_id: int, word_ids: np.ndarray) -> list[int]:
        """Remove a location's occurrences of these words.

        Returns:
            Sorted ids of the words left referenced by no location (candidates for removal).
        """
        location_id = int(location_id)
        orphans = []
        words, counts = np.unique(_as_ids(word_ids), return_counts=True)
        shared, owner = self._shared, self._owner
        for word, count, row in zip(words.tolist(), counts.tolist(), self._row_of.rows(words).tolist()):
            locations = shared.get(word)
            if locations is None:
                if row >= 0 and owner[row] == location_id:
                    owner[row] = 0
                    orphans.append(word)
                    self.total_references -= 1
                continue
            if location_id not in locations:
                continue
            self.total_references -= min(count, locations[location_id])
            remaining = locations[location_id] - count
            if remaining > 0:
                locations[location_id] = remaining
            else:
                del locations[location_id]
                n = len(locations)
                if n >= _COMPACT_MIN and n & (n - 1) == 0:
                    # A dict never gives back its table: shrinking through a power of two, it is
                    # copied into one sized for what is left (else each word's dict stays at its
                    # most-shared size, and RAM creeps up at a constant WM).
                    locations = shared[word] = dict(locations)
            if not locations:
                del shared[word]
                orphans.append(word)
            elif len(locations) == 1 and row >= 0:
                (last, n), = locations.items()
                if n == 1:  # back to one occurrence in one location: no dict
                    owner[row] = last
                    del shared[word]
        return orphans

    def references(self, word_id: int) -> dict[int, int]:
        """Location id -> occurrences of the word (a copy; empty if unreferenced)."""
        word = int(word_id)
        locations = self._shared.get(word)
        if locations is not None:
            return dict(locations)
        row = self._row_of.row(word)
        location = int(self._owner[row]) if row >= 0 else 0
        return {location: 1} if location else {}

    def _single_owners(self, words) -> np.ndarray:
        """Locations (one per word, repeats kept) of the given words that occur once in one
        location; the words with a dict in ``_shared`` or no reference are left out."""
        shared = self._shared
        rows = self._row_of.rows(np.fromiter((w for w in words if w not in shared), np.int64))
        owners = self._owner[rows[rows >= 0]]
        return owners[owners != 0]

    def scores(self, word_counts: dict[int, int], candidates: set[int] | None = None) -> dict[int, int]:
        """Matched word pairs (Eq. 1 numerator) between a signature and every location sharing a word.

        Args:
            word_counts: word id -> occurrences in the query signature.
            candidates: restrict to these location ids (None: all referenced locations).

        Returns:
            location id -> sum over shared words of min(occurrences in query, in location).
        """
        pairs: defaultdict[int, int] = defaultdict(int)
        shared = self._shared
        for word, count in word_counts.items():
            locations = shared.get(word)
            if not locations:
                continue
            if candidates is None:
                for location, n in locations.items():
                    pairs[location] += n if n < count else count
            else:
                for location, n in locations.items():
                    if location in candidates:
                        pairs[location] += n if n < count else count
        # A word occurring once in one location pairs once with the query (min(1, count) = 1).
        owners, n_words = np.unique(self._single_owners(word_counts), return_counts=True)
        for location, n in zip(owners.tolist(), n_words.tolist()):
            if candidates is None or location in candidates:
                pairs[location] += n
        return dict(pairs)

    def tf_idf_scores(self, word_counts: dict[int, int], candidates: set[int], n_locations: int) -> dict[int, float]:
        """Sum over the query's distinct words w of ``n_wj log10(N / n_w)`` for every candidate j
        holding a word (RTAB-Map's tf-idf likelihood, before the division by n_j).

        Args:
            word_counts: word id -> occurrences in the query signature (only the keys are used).
            candidates: the location ids to score.
            n_locations: N, the locations in memory (every location the inverted index holds).
        """
        out: defaultdict[int, float] = defaultdict(float)
        shared = self._shared
        for word in word_counts:
            locations = shared.get(word)
            if not locations:
                continue
            idf = math.log10(n_locations / len(locations)) if n_locations > len(locations) else 0.0
            if idf <= 0.0:
                continue
            for location, n in locations.items():
                if location in candidates:
                    out[location] += n * idf
        # A word occurring once in one location: n = 1, idf = log10(N / 1).
        if n_locations > 1:
            idf = math.log10(n_locations)
            owners, n_words = np.unique(self._single_owners(word_counts), return_counts=True)
            for location, n in zip(owners.tolist(), n_words.tolist()):
                if location in candidates:
                    out[location] += n * idf
        return dict(out)

    # -------------------------------------------------------------- internals
    def _check_descriptors(self, descriptors: np.ndarray) -> np.ndarray:
        """Validated contiguous (N,D) descriptors of the vocabulary's dtype."""
        if not isinstance(descriptors, np.ndarray) or descriptors.ndim != 2:
            shape = getattr(descriptors, "shape", None)
            raise SensorDataError(f"descriptors must be a 2-D numpy array (N,D), got shape {shape}")
        if self.binary and descriptors.dtype != np.uint8:
            raise SensorDataError(f"binary descriptors must be uint8, got {descriptors.dtype}")
        if not self.binary and not np.issubdtype(descriptors.dtype, np.floating):
            raise SensorDataError(f"float descriptors must be float32, got {descriptors.dtype}")
        if self._dim is not None and descriptors.shape[1] != self._dim and descriptors.shape[0]:
            raise SensorDataError(
                f"descriptors have {descriptors.shape[1]} columns, the vocabulary's words have {self._dim}")
        return np.ascontiguousarray(descriptors, dtype=self._dtype)

    def _insert(self, ids: np.ndarray, descriptors: np.ndarray) -> None:
        """Append words to the buffer (O(added), amortised); the kd-trees take them at the next search."""
        n = ids.size
        if self._descriptors is None:
            self._dim = int(descriptors.shape[1])
            self._descriptors = np.zeros((INITIAL_CAPACITY, self._dim), self._dtype)
            self._ids = np.zeros(INITIAL_CAPACITY, np.int64)
            self._owner = np.zeros(INITIAL_CAPACITY, np.int64)
        needed = self._count + n
        if needed > self._descriptors.shape[0]:
            capacity = max(needed, 2 * self._descriptors.shape[0])
            grown = np.zeros((capacity, self._dim), self._dtype)
            grown[: self._count] = self._descriptors[: self._count]
            grown_ids = np.zeros(capacity, np.int64)
            grown_ids[: self._count] = self._ids[: self._count]
            grown_owner = np.zeros(capacity, np.int64)
            grown_owner[: self._count] = self._owner[: self._count]
            self._descriptors, self._ids, self._owner = grown, grown_ids, grown_owner
        start = self._count
        self._descriptors[start:needed] = descriptors
        self._ids[start:needed] = ids
        self._row_of.insert(ids, np.arange(start, needed, dtype=np.int64))
        self._count = needed
        if self.uses_kdtree:
            self._kdtree_pending.update(zip(ids.tolist(), descriptors.copy()))

    def _search(self, descriptors: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """2-NN distances (N,2) and word ids (N,2) (-1 where not found)."""
        if self.uses_kdtree:
            if self._kdtree is None:
                self._kdtree = kdtree.RandomizedKdTrees(self._dim, seed=self.params.kdtree_seed,
                                                        background_rebuild=self.background_rebuild,
                                                        swap_searches=self.params.rebuild_swap_frames,
                                                        search_threads=self.params.kdtree_search_threads)
            if self._kdtree_pending:
                ids = sorted(self._kdtree_pending)
                self._kdtree.add(np.stack([self._kdtree_pending[i] for i in ids]), np.asarray(ids, np.int64))
                self._kdtree_pending.clear()
            return self._kdtree.search(descriptors)
        words = self._descriptors[: self._count]
        with _omp_threads(SEARCH_THREADS):
            if self.binary:
                distances, slots = faiss.knn_hamming(descriptors, words, NEAREST_NEIGHBOURS)
            else:
                distances, slots = faiss.knn(descriptors, words, NEAREST_NEIGHBOURS)
        ids = np.where(slots >= 0, self._ids[np.maximum(slots, 0)], -1)
        return distances.astype(np.float32), ids
