"""Incremental visual vocabulary and inverted index (2013 §III-A, Alg. 2 lines 4-5).

Each word is one feature descriptor. A new image's descriptors are quantised by a 2-nearest-
neighbour search over the current words and the nearest neighbour distance ratio (NNDR) test:
a descriptor is the nearest word if ``d1 <= T_NNDR * d2`` (RTAB-Map's form: an exact duplicate,
d1 = d2 = 0, matches); otherwise it becomes a new word. A frame's new words are compared together
(``new_words_compared_together``, RTAB-Map's Kp/NewWordsComparedTogether): a feature repeated in
one image gives one word.

The paper rebuilt FLANN kd-trees over the whole vocabulary at every frame, its most expensive
step. Here the index is incremental (``bench/bench_vocabulary.py`` measured the choice):

* flat: exact brute force (faiss ``knn_hamming`` / ``knn``) over a contiguous numpy buffer of the
  words. Removing a word moves the last row into its slot: O(removed), never a rebuild.
* kdtree: RTAB-Map's own approximate search (FLANN randomized kd-trees over the descriptors' bits,
  32 checks: ``core/kdtree.py``), binary descriptors only. Slower and less exact than the others; it
  is what makes ``config/rtabmap_reference.yaml`` behave as RTAB-Map does (issue 32).
* IVF: a faiss inverted file (``IndexBinaryIVF`` for ORB, ``IndexIVFFlat`` for SIFT) holding the
  word ids natively, with a hash-table direct map so ``remove_ids`` costs O(removed). Used from
  ``ivf_min_words`` words on (``index=auto``). Its coarse quantiser is trained on the current words
  and retrained only when the vocabulary has grown by ``ivf_retrain_growth`` since the last
  training; between trainings words are added to / removed from the lists incrementally. Once
  built, the IVF stays in use even if removals shrink the vocabulary below ``ivf_min_words``.

IVF (re)builds run off the frame's critical path (``background_training=True``, the default):
training the coarse quantiser takes 0.5-1.5 s at 20-80 k ORB words and several seconds at
200-320 k, far above T_time (2013 §III-F). The frame that crosses the threshold only copies the
words (a snapshot: ~1 ms for 80 k ORB words); a daemon thread trains the quantiser on a sample of
the snapshot and adds all its words to a private new index (faiss releases the GIL; the thread
uses ``BUILD_THREADS`` OpenMP threads so the frame loop keeps a core). Meanwhile the current index
(flat, or the previous IVF) keeps serving queries and receiving adds/removes, which are also
logged. The swap point is deterministic (the same images give the same words whatever the load):
the ``ivf_swap_frames``-th :meth:`quantize` call (frame) after the build started swaps the new
index in, waiting for the thread if it has not finished by then; the changes logged since the
snapshot are replayed into the new index call by call once the thread has finished, the rest at
the swap (the same changes in the same order whenever the thread finished) (issue 12: a swap at the first call after the thread finished made
``detections.csv`` depend on the machine's load). Only the main thread calls the public methods; the thread
touches nothing but its snapshot and its result. ``background_training=False`` builds in the
calling frame (deterministic tests, benchmarks of the build itself); both modes end with the same
index content once the swap happened. :meth:`join_training` waits for a pending build and swaps it
in; :meth:`close` waits for it and discards it.

The frame's own faiss calls run with ``SEARCH_THREADS`` OpenMP threads (set around each call and
restored): with faiss's default team over all cores of a shared machine, frames after the switch
took 0.5-1.4 s instead of ~10-60 ms (bench_vocabulary.py growth run).

Distances: Hamming (bits) for binary descriptors, Euclidean for float ones (faiss returns squared
L2: the square root is taken before the ratio test).

Fewer than two words: the NNDR test needs a second neighbour, so every descriptor is a new word.
The same holds when the IVF probes find fewer than two words for a descriptor.

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
import threading
import time
from collections import defaultdict
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Iterable

import faiss
import numpy as np

from rtabmap_ros2.core.kdtree import RandomizedKdTrees
from rtabmap_ros2.core.params import VocabularyParams
from rtabmap_ros2.errors import ParameterError, SensorDataError

logger = logging.getLogger(__name__)

# Initial capacity (words) of the descriptor buffer; it doubles when full.
INITIAL_CAPACITY = 4096
# A word's dict in the inverted index is copied into a smaller one when it shrinks to a power of
# two from this size on (remove_references).
_COMPACT_MIN = 8
# Smallest vocabulary an IVF is trained on when index="ivf" (below it the flat index is used).
IVF_MIN_TRAIN_WORDS = 1000
# IVF lists: IVF_LISTS_PER_SQRT * sqrt(words at training). bench_vocabulary.py, 200 k ORB words:
# 2 sqrt(n) lists with nprobe 32 agree with exact search on 99.7 % of decisions; 4 sqrt(n) lists
# query faster but k-means training (cost ~ lists^2) blocked the frame for 15-50 s.
IVF_LISTS_PER_SQRT = 2.0
# k-means training sample per list: faiss's minimum, since training blocks the frame it runs in
# (200 k words, 894 lists: ~6 s; retraining happens at 4x growth only).
IVF_TRAIN_POINTS_PER_LIST = 39
IVF_MIN_POINTS_PER_LIST = 39
# Seed of the training sample draw (deterministic vocabularies).
IVF_TRAIN_SEED = 1234
NEAREST_NEIGHBOURS = 2
# OpenMP threads of a background IVF build (faiss's setting is per calling thread): one, so that on
# a 2-core machine the frame loop keeps the other core (bench_vocabulary.py, growth run).
BUILD_THREADS = 1
# OpenMP threads of the frame's faiss calls (search, add, replay), set around each call and restored
# (0: leave the caller's setting). bench_vocabulary.py growth run, 2 cores shared with other jobs:
# with faiss's default (all cores) the OpenMP team waits for a descheduled thread, and while a
# background build runs, p99 quantize time went from 80 ms to 1.4 s; one thread avoids that.
SEARCH_THREADS = 1


def _remove_ids(index, ids: np.ndarray) -> None:
    """Remove (N,) int64 contiguous ids from a faiss IVF index with a hash-table direct map."""
    index.remove_ids(faiss.IDSelectorArray(ids.size, faiss.swig_ptr(ids)))


@contextmanager
def _omp_threads(n_threads: int):
    """Run faiss calls of this thread with n_threads OpenMP threads (0: unchanged), then restore."""
    if n_threads <= 0:
        yield
        return
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


def _ivf_lists(n_words: int) -> int:
    """Number of IVF lists for a vocabulary of n_words (``IVF_LISTS_PER_SQRT`` sqrt(n))."""
    return max(1, min(int(round(IVF_LISTS_PER_SQRT * math.sqrt(n_words))), n_words // IVF_MIN_POINTS_PER_LIST))


def _build_ivf(words: np.ndarray, ids: np.ndarray, binary: bool, n_lists: int, nprobe: int):
    """A new IVF index holding the given words: k-means on a sample of them, then add them all.

    Touches nothing but its arguments (it runs in the background build thread).

    Args:
        words: (N,D) uint8 (binary, D bytes) or float32 descriptors; not modified.
        ids: (N,) int64 word ids of the rows.
        binary: Hamming (IndexBinaryIVF) or L2 (IndexIVFFlat).
        n_lists: number of inverted lists (k-means centroids).
        nprobe: lists visited per query.

    Returns:
        ``(index, n_train)``: the faiss index and the number of training points used.
    """
    n_words, dim = words.shape
    n_train = min(n_words, IVF_TRAIN_POINTS_PER_LIST * n_lists)
    sample = np.random.default_rng(IVF_TRAIN_SEED).choice(n_words, n_train, replace=False)
    sample.sort()
    training = np.ascontiguousarray(words[sample])
    if binary:
        bits = 8 * dim
        index = faiss.IndexBinaryIVF(faiss.IndexBinaryFlat(bits), bits, n_lists)
    else:
        index = faiss.IndexIVFFlat(faiss.IndexFlatL2(dim), dim, n_lists)
    index.train(training)
    # Hash-table direct map: remove_ids in O(removed) instead of scanning every list.
    index.set_direct_map_type(faiss.DirectMap.Hashtable)
    index.nprobe = nprobe
    index.add_with_ids(words, ids)
    return index, n_train


@dataclass(eq=False)
class _IvfBuild:
    """One IVF (re)build: its snapshot size, the changes made since the snapshot, its result.

    The build thread writes ``index``/``n_train``/``error``/``seconds`` and then sets ``done``;
    the main thread reads them only once ``done`` is set (the Event is the lock of the handoff).
    ``log`` belongs to the main thread: ("add", ids, descriptors) / ("remove", ids, None) in order;
    once ``done``, the main thread also owns ``index`` and replays the log into it as it goes.
    """

    size: int
    n_lists: int
    swap_frame: int = 0  # the quantize call (Vocabulary._frames) at which it is swapped in
    done: threading.Event = field(default_factory=threading.Event)
    log: list = field(default_factory=list)
    replayed: int = 0  # changes of the log already applied to ``index`` (once ``done``)
    thread: threading.Thread | None = None
    index: object = None
    n_train: int = 0
    error: BaseException | None = None
    seconds: float = 0.0

    def run(self, words: np.ndarray, ids: np.ndarray, binary: bool, nprobe: int) -> None:
        """Build the index from the snapshot (thread target; never raises, stores the error)."""
        start = time.perf_counter()
        try:
            faiss.omp_set_num_threads(BUILD_THREADS)  # this thread only (OpenMP per-thread setting)
            self.index, self.n_train = _build_ivf(words, ids, binary, self.n_lists, nprobe)
        except BaseException as error:  # noqa: BLE001 - handed to the main thread, re-raised there
            self.error = error
        finally:
            self.seconds = time.perf_counter() - start
            self.done.set()


class _RowIndex:
    """Word id -> row of the vocabulary's buffer, with no Python object per word: the ids in
    increasing order (``np.searchsorted``) beside their rows. A removed id keeps its place with row
    -1 until removed ones are a quarter of the entries (then they are compacted away). Ids larger
    than every id held are appended: new words get increasing ids, so that is the usual insert."""

    def __init__(self) -> None:
        self._ids = np.zeros(INITIAL_CAPACITY, np.int64)  # [0, _n) sorted; removed ones have row -1
        self._rows = np.zeros(INITIAL_CAPACITY, np.int64)
        self._n = 0
        self._removed = 0

    def rows(self, ids: np.ndarray) -> np.ndarray:
        """Row of each id (int64 array), -1 where the id is not held."""
        ids = np.asarray(ids, np.int64)
        if self._n == 0:
            return np.full(ids.shape, -1, np.int64)
        pos = np.minimum(np.searchsorted(self._ids[: self._n], ids), self._n - 1)
        return np.where(self._ids[pos] == ids, self._rows[pos], -1)

    def row(self, word_id: int) -> int:
        """Row of one id, -1 if it is not held."""
        return int(self.rows(np.array([word_id]))[0])

    def insert(self, ids: np.ndarray, rows: np.ndarray) -> None:
        """Add ids (none of them held) with their rows."""
        order = np.argsort(ids, kind="stable")
        ids, rows = ids[order], rows[order]
        if self._n and ids[0] <= self._ids[self._n - 1]:
            # Not above every id held (a word re-added with its id): merge, without the removed.
            keep = self._rows[: self._n] >= 0
            ids = np.concatenate([self._ids[: self._n][keep], ids])
            rows = np.concatenate([self._rows[: self._n][keep], rows])
            order = np.argsort(ids, kind="stable")
            ids, rows = ids[order], rows[order]
            self._n = self._removed = 0
        needed = self._n + ids.size
        if needed > self._ids.size:
            capacity = max(needed, 2 * self._ids.size)
            self._ids = np.resize(self._ids, capacity)
            self._rows = np.resize(self._rows, capacity)
        self._ids[self._n: needed] = ids
        self._rows[self._n: needed] = rows
        self._n = needed

    def set_rows(self, ids: np.ndarray, rows: np.ndarray) -> None:
        """New rows of held ids (the buffer moved them)."""
        self._rows[np.searchsorted(self._ids[: self._n], ids)] = rows

    def remove(self, ids: np.ndarray) -> None:
        """Drop held ids."""
        self._rows[np.searchsorted(self._ids[: self._n], ids)] = -1
        self._removed += ids.size
        if self._removed > max(INITIAL_CAPACITY, self._n // 4):
            keep = np.flatnonzero(self._rows[: self._n] >= 0)
            self._ids[: keep.size] = self._ids[keep]
            self._rows[: keep.size] = self._rows[keep]
            self._n, self._removed = keep.size, 0


class Vocabulary:
    """Words (descriptors) with int64 ids, a nearest-neighbour index and the inverted index."""

    def __init__(self, params: VocabularyParams, binary: bool, next_word_id: int = 1, *,
                 background_training: bool = True):
        """Empty vocabulary.

        Args:
            params: NNDR threshold and index choice.
            binary: True for binary descriptors (uint8 rows, Hamming), False for float32 (L2).
            next_word_id: first id given to a new word (ids are never reused: pass the database's
                largest word id + 1 when continuing a map).
            background_training: build IVF indexes in a background thread (True) or in the
                frame that triggers them (False: deterministic, blocks that frame).
        """
        if next_word_id < 1:
            raise ValueError(f"next_word_id={next_word_id} is invalid: word ids start at 1")
        if params.index == "kdtree" and not binary:
            raise ParameterError("vocabulary.index=kdtree searches binary descriptors (features.detector "
                                 "gftt_orb or orb) only; these are float descriptors: use auto, flat or ivf")
        self.params = params
        self.binary = binary
        self.next_word_id = int(next_word_id)
        self._dtype = np.uint8 if binary else np.float32
        self._dim: int | None = None  # descriptor length (bytes or floats), set by the first words
        # Words: rows [0, _count) of _descriptors, with their ids in _ids; _row_of maps id -> row.
        self._descriptors: np.ndarray | None = None
        self._ids = np.zeros(0, np.int64)
        self._row_of = _RowIndex()
        self._count = 0
        # IVF index (None while the flat index is used) and the size it was trained at.
        self._ivf = None
        self._ivf_trained_size = 0
        self.background_training = bool(background_training)
        self._build: _IvfBuild | None = None  # pending background (re)build
        self._frames = 0  # quantize calls so far: the clock of the IVF swap
        # index="kdtree" (made with the first words), and the words not indexed yet: as RTAB-Map's
        # VWDictionary::update at the start of the next frame (Memory::preUpdate), a word is put in
        # the trees when the next frame searches, in id order, unless it left the vocabulary since
        # (the words of a location that rehearsal merged never enter the trees).
        self._kdtree: RandomizedKdTrees | None = None
        self._kdtree_pending: dict[int, np.ndarray] = {}
        # Inverted index (word -> {location: occurrences}, module docstring): the location of a
        # word of the vocabulary that occurs once in one location is _owner[row] (0: none); any
        # other referenced word has a dict in _shared (never both).
        self._owner = np.zeros(0, np.int64)
        self._shared: dict[int, dict[int, int]] = {}

    # ------------------------------------------------------------------ words
    def __len__(self) -> int:
        """Number of words currently indexed."""
        return self._count

    @property
    def uses_ivf(self) -> bool:
        """True when queries go through the (approximate) IVF index."""
        return self._ivf is not None

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

        Each call is one frame for the IVF swap (see :meth:`_poll_build`).

        Args:
            descriptors: (N,D) uint8 (binary) or float32 (float) descriptors.

        Returns:
            ``(word_ids, is_new)``: (N,) int64 word of each descriptor and (N,) bool, True where a
            new word was created.
        """
        descriptors = self._check_descriptors(descriptors)
        self._frames += 1
        self._poll_build()
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
        self._poll_build()
        n = descriptors.shape[0]
        result = np.full(n, -1, np.int64)
        if n == 0 or self._count < NEAREST_NEIGHBOURS:
            return result
        distances, neighbours = self._search(descriptors)
        distances = self._distances(distances)
        # A missing second neighbour (IVF) fails the NNDR test.
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
        self._poll_build()
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
        self._poll_build()
        if self._ivf is not None:
            _remove_ids(self._ivf, ids)
        if self.params.index == "kdtree":
            # A word not indexed yet just leaves the pending ones; the others are marked removed.
            indexed = [word for word in ids.tolist() if self._kdtree_pending.pop(word, None) is None]
            if indexed and self._kdtree is not None:
                self._kdtree.remove(np.asarray(indexed, np.int64))
        if self._build is not None:
            self._build.log.append(("remove", ids, None))
        row_of_removed = dict(zip(ids.tolist(), rows.tolist()))  # kept current as rows move
        moved_rows: dict[int, int] = {}  # the words kept that moved -> their new row
        for word in ids.tolist():
            # Move the last row into the freed slot.
            slot = row_of_removed[word]
            last = self._count - 1
            if slot != last:
                moved = int(self._ids[last])
                self._descriptors[slot] = self._descriptors[last]
                self._ids[slot] = moved
                self._owner[slot] = self._owner[last]
                if moved in row_of_removed:
                    row_of_removed[moved] = slot
                else:
                    moved_rows[moved] = slot
            self._owner[last] = 0
            self._count = last
            self._shared.pop(word, None)
        self._row_of.remove(ids)
        if moved_rows:
            self._row_of.set_rows(np.fromiter(moved_rows, np.int64, len(moved_rows)),
                                  np.fromiter(moved_rows.values(), np.int64, len(moved_rows)))

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
    def training(self) -> bool:
        """True while a background IVF build is pending (not yet swapped in)."""
        return self._build is not None

    def join_training(self) -> None:
        """Wait for a pending background IVF build and swap it in (no-op when none is pending)."""
        self._poll_build(wait=True)

    def close(self) -> None:
        """Wait for a pending background IVF build and discard it (idempotent).

        The vocabulary stays usable; a later growth starts a new build. Without close() the
        build thread (a daemon) finishes on its own and the vocabulary is garbage-collectable.
        """
        build, self._build = self._build, None
        if build is not None and build.thread is not None:
            build.thread.join()
        if self._kdtree is not None:
            self._kdtree.close()

    # ------------------------------------------------------- inverted index
    def add_references(self, location_id: int, word_ids: np.ndarray) -> None:
        """Record that a location contains these words (one entry per occurrence)."""
        location_id = int(location_id)
        words, counts = np.unique(_as_ids(word_ids), return_counts=True)
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
                continue
            if location_id not in locations:
                continue
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
        """Append words to the buffer and the index (O(added), amortised)."""
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
        if self.params.index == "kdtree":
            self._kdtree_pending.update(zip(ids.tolist(), descriptors.copy()))
        if self._ivf is not None:
            with _omp_threads(SEARCH_THREADS):
                self._ivf.add_with_ids(descriptors, ids)
        if self._build is not None:
            self._build.log.append(("add", ids.copy(), descriptors.copy()))
        self._maybe_train_ivf()

    def _ivf_threshold(self) -> int | None:
        """Vocabulary size from which the IVF index is used (None: never)."""
        if self.params.index in ("flat", "kdtree"):
            return None
        if self.params.index == "ivf":
            return IVF_MIN_TRAIN_WORDS
        return self.params.ivf_min_words

    def _maybe_train_ivf(self) -> None:
        """Build the IVF once big enough; rebuild it after ``ivf_retrain_growth`` growth."""
        threshold = self._ivf_threshold()
        if threshold is None or self._count < threshold or self._build is not None:
            return
        if self._ivf is not None and self._count < self.params.ivf_retrain_growth * self._ivf_trained_size:
            return
        self._start_build()

    def _start_build(self) -> None:
        """Snapshot the words and (re)build the IVF from it, in a thread or right here."""
        # The snapshot is private to the build: the main thread keeps moving rows of the buffer.
        words = self._descriptors[: self._count].copy()
        ids = self._ids[: self._count].copy()
        build = _IvfBuild(size=self._count, n_lists=_ivf_lists(self._count),
                          swap_frame=self._frames + self.params.ivf_swap_frames)
        self._build = build
        if not self.background_training:
            build.run(words, ids, self.binary, self.params.ivf_nprobe)
            self._poll_build(wait=True)
            return
        build.thread = threading.Thread(target=build.run, args=(words, ids, self.binary, self.params.ivf_nprobe),
                                        name="vocabulary-ivf-build", daemon=True)
        build.thread.start()
        logger.info("vocabulary: IVF build of %d words (%d lists) started in the background",
                    build.size, build.n_lists)

    def _poll_build(self, wait: bool = False) -> None:
        """Swap in the background build at its swap frame, or now with ``wait`` (main thread):
        wait for it, then replay the changes logged since the snapshot.

        Once the thread has finished, each call replays the changes logged so far, so the swap
        frame replays only the last ones: replaying 300 frames of changes at once took up to
        0.4 s on a 10,000-frame run with large transfers. The replay order is the same whenever
        it happens, so the swapped-in index is too."""
        build = self._build
        if build is None:
            return
        swap = wait or self._frames >= build.swap_frame
        if not swap and not build.done.is_set():
            return
        if build.thread is not None:
            build.thread.join()
        if build.error is not None:
            self._build = None
            raise build.error
        start = time.perf_counter()
        with _omp_threads(SEARCH_THREADS):
            for kind, ids, descriptors in build.log:
                if kind == "add":
                    build.index.add_with_ids(descriptors, ids)
                else:
                    _remove_ids(build.index, ids)
        build.replayed += len(build.log)
        build.log.clear()
        if not swap:
            return
        self._build = None
        index = build.index
        if index.ntotal != self._count:
            raise RuntimeError(f"vocabulary: the rebuilt IVF holds {index.ntotal} words, the vocabulary "
                               f"{self._count}: a change was lost (report this bug)")
        self._ivf = index
        self._ivf_trained_size = build.size
        logger.info("vocabulary: IVF trained on %d of %d words, %d lists, in %.2f s; %d changes replayed, "
                    "the last in %.1f ms", build.n_train, build.size, build.n_lists, build.seconds,
                    build.replayed, 1e3 * (time.perf_counter() - start))

    def _search(self, descriptors: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """2-NN distances (N,2) and word ids (N,2) (-1 where not found)."""
        if self.params.index == "kdtree":
            if self._kdtree is None:
                self._kdtree = RandomizedKdTrees(self._dim, seed=self.params.kdtree_seed,
                                                 background_rebuild=self.background_training,
                                                 swap_searches=self.params.ivf_swap_frames)
            if self._kdtree_pending:
                ids = sorted(self._kdtree_pending)
                self._kdtree.add(np.stack([self._kdtree_pending[i] for i in ids]), np.asarray(ids, np.int64))
                self._kdtree_pending.clear()
            return self._kdtree.search(descriptors)
        if self._ivf is not None:
            with _omp_threads(SEARCH_THREADS):
                distances, ids = self._ivf.search(descriptors, NEAREST_NEIGHBOURS)
            return distances.astype(np.float32), ids
        words = self._descriptors[: self._count]
        with _omp_threads(SEARCH_THREADS):
            if self.binary:
                distances, slots = faiss.knn_hamming(descriptors, words, NEAREST_NEIGHBOURS)
            else:
                distances, slots = faiss.knn(descriptors, words, NEAREST_NEIGHBOURS)
        ids = np.where(slots >= 0, self._ids[np.maximum(slots, 0)], -1)
        return distances.astype(np.float32), ids
