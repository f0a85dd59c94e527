"""RTAB-Map's approximate word search: FLANN randomized kd-trees over binary descriptors' bits.

RTAB-Map 0.22 quantises binary descriptors (ORB) with ``Kp/NNStrategy`` 1: each descriptor's bits
become 0/1 floats (``Kp/ByteToFloat`` false: VWDictionary::convertBinTo32F, byte j's bit b is
dimension 8 j + b), indexed by FLANN's randomized kd-trees with the L1 distance (on bits, the Hamming
distance) and searched for the 2 nearest words with 32 checks (VWDictionary.cpp ``KNN_CHECKS``).
New words are inserted into every tree (FlannIndex::addPoints, rtflann ``addPointToTree``), a frame's
words at once; when the index then holds more than ``Kp/FlannRebalancingFactor`` (2) times the words
it was built with, removed ones included, it is rebuilt from the words left. Removed words stay in
the trees, skipped.

The search is approximate: a descriptor often misses its nearest word, then either becomes a new
word or matches a word of an unrelated place that passes the ratio test among the few words
checked. That is why RTAB-Map's vocabulary is larger than an exact search's and why many WM
locations share a word or two with any image by chance: the mean and deviation of Eq. 3-4 (the
2013 paper's likelihood) are taken over those chance scores, and with an exact search they are not
there (issue 48: make_sequence's recall 0.17 against the reference's 0.80 without them). This module
is FLANN's algorithm (rtflann ``kdtree_index.h``, ``heap.h``, ``result_set.h``) so that the word
search, and with it every parameter of RTAB-Map's, behaves as the reference's:

* build (``divideTree`` / ``meanSplit`` / ``planeSplit``): each tree over a random permutation of
  the words; a node takes the mean and variance of each dimension over its first 101 words, picks
  one of the 5 highest-variance dimensions at random and splits at its mean (in place, as FLANN);
  leaves hold one word;
* insertion (``addPointToTree``): down to a leaf, which becomes a node splitting the two words on
  the first dimension where they differ, at 0.5;
* search (``getNeighbors``): one descent per tree, the branches not taken queued by their lower
  bound (the sum of ``|bit - split|`` on the way) in FLANN's binary heap (``std::push_heap`` /
  ``std::pop_heap`` order), then best-bin-first from that heap until 32 words have been checked and
  two found; a word is checked once across trees.

Compiled with numba (the loops are FLANN's, node by node: ~1,000x the pure-Python version's speed).
Deterministic: the random choices come from a seeded numpy generator (FLANN's differ run to run, so
the reference itself is not repeatable).
"""

from __future__ import annotations

import itertools
import logging
import threading
import time
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from rtabmap_ros2.core.compiled import UNCACHED, jit as _jit
from rtabmap_ros2.core.id_index import IdIndex

# FLANN's KDTreeIndexParams default, RTAB-Map's KNN_CHECKS and Kp/FlannRebalancingFactor default.
TREES = 4
CHECKS = 32
REBALANCING = 2.0
# kdtree_index.h: the split dimension is drawn among the RAND_DIM highest variances, estimated on
# the first SAMPLE_MEAN + 1 words of the node.
RAND_DIM = 5
SAMPLE_MEAN = 100
NEAREST = 2
_LEAF = -1
_BITS = 64  # the words are held as little-endian uint64 lanes: dimension d is lane d // 64, bit d % 64
_INITIAL_POINTS = 1024
# Room a build reserves for the words inserted after it, x its words: the REBALANCING growth that
# starts the next rebuild, and as much again while that rebuild runs in the background (it is swapped
# in n / SWAP_WORDS_PER_SEARCH searches later at the earliest). The arrays are np.zeros (calloc): the
# room costs address space, its pages become resident only when written. Growing an array instead
# copies it in the frame that overflows it: at 1.75M words the node array is ~220 MB, and its copy
# was the slowest frame of the 10,000- and 25,000-image detect runs (0.40 and 0.67 s of quantisation).
INSERTION_ROOM = 2.0
# Nodes: int32 indices (points and nodes < 2**31) and a float32 split value, 16 bytes a node in one
# row (_Forest.nodes); a forest reserves 24 nodes a word it was built over (4 trees of 2 n - 1 nodes,
# and 2 nodes per tree for each of the INSERTION_ROOM x n insertions), resident only once used.
_NODE = np.int32
# Background rebuild (issue 50). Its swap comes at least one search per SWAP_WORDS_PER_SEARCH words
# of the snapshot after it started, so the swap search does not wait for the thread: a build costs
# ~8.5 us of CPU a word (980k ORB words: 8.4 s, this 2-core machine), a detect frame at least ~40 ms
# of the main thread's, and the two threads share the CPU; at 1,000 words a search the thread has
# ~5x the CPU it needs. Before: 300 searches whatever the size, reached by 1M-word rebuilds that
# took 56 s on a loaded machine (load 19), a wait of seconds in one frame.
SWAP_WORDS_PER_SEARCH = 1000
# A rebuild of at most this many words (~0.2 s of CPU) is swapped in at the ``swap_searches``-th search
# (detect's 1: the search of the frame that started it, which waits for it, as RTAB-Map rebuilds in the
# call that doubled its index), whatever SWAP_WORDS_PER_SEARCH would give it: with the 84 images
# upscaled 2x the 10k-word rebuild came 11 searches late, over the first revisit, and image 59 closed on
# 25 in 10 of 15 seeds against 4 of the reference's 15 runs; swapped in at once, 4 of 15 (issue 48).
IN_TIME_REBUILD_WORDS = 20_000
# Once the thread has finished, each search replays at most this many logged words (added or
# removed) into the new trees (~50 us a word inserted in 4 trees): a frame's worth or two, so the
# replay catches up well before the swap without one search replaying hundreds of frames at once.
REPLAY_WORDS_PER_SEARCH = 2000
# A swap search that still had to wait for the thread longer than this is logged (warning).
WAIT_WARNING_S = 0.05
# A search over several threads (``search_threads``) cuts the queries into chunks of this many,
# claimed in turn by the calling thread and the helpers: a helper that the machine's load keeps
# waiting claims fewer, and the calling thread never waits for one that has not started (it waits
# only for the chunks others claimed). Fewer queries than two chunks are searched in the caller.
SEARCH_CHUNK = 50

logger = logging.getLogger(__name__)

@_jit(inline="always")
def _popcount(x):
    """Set bits of a uint64 (SWAR)."""
    x = x - ((x >> np.uint64(1)) & np.uint64(0x5555555555555555))
    x = (x & np.uint64(0x3333333333333333)) + ((x >> np.uint64(2)) & np.uint64(0x3333333333333333))
    x = (x + (x >> np.uint64(4))) & np.uint64(0x0F0F0F0F0F0F0F0F)
    return (x * np.uint64(0x0101010101010101)) >> np.uint64(56)


@_jit(inline="always")
def _bit(words, point, dim):
    return (words[point, dim >> 6] >> np.uint64(dim & 63)) & np.uint64(1)


@_jit()
def _divide_tree(words, n_dims, ind, choices, feat, val, child1, child2, n_nodes):
    """divideTree + meanSplit + planeSplit over ``ind`` (a permutation of the points, split in
    place); ``words`` (n_points, lanes) uint64, the words' ``n_dims`` bits (read in place: unpacked
    they took 256 bytes a word, 400 MB more during a 1.5M-word rebuild); ``choices`` one random
    draw in [0, RAND_DIM) per inner node, in FLANN's depth-first order. Returns (root, number of
    nodes used)."""
    count_all = ind.size
    stack_node = np.empty(2 * count_all + 1, np.int64)
    stack_start = np.empty(2 * count_all + 1, np.int64)
    stack_count = np.empty(2 * count_all + 1, np.int64)
    ones = np.zeros(n_dims, np.int32)
    root = n_nodes
    n_nodes += 1
    top = 0
    stack_node[0], stack_start[0], stack_count[0] = root, 0, count_all
    drawn = 0
    while top >= 0:
        node, start, count = stack_node[top], stack_start[top], stack_count[top]
        top -= 1
        if count == 1:
            feat[node] = ind[start]
            child1[node] = _LEAF
            child2[node] = _LEAF
            continue
        # meanSplit: mean and (unnormalised) variance of every bit over the first 101 points.
        cnt = min(SAMPLE_MEAN + 1, count)
        ones[:] = 0
        for j in range(cnt):
            point = ind[start + j]
            for lane in range(words.shape[1]):
                w = words[point, lane]
                for b in range(min(_BITS, n_dims - lane * _BITS)):
                    ones[lane * _BITS + b] += np.int32((w >> np.uint64(b)) & np.uint64(1))
        # selectDivision: the RAND_DIM largest variances (a bubble insertion, as FLANN), one at random.
        # The variance of a 0/1 dimension over cnt words is ones (cnt - ones) / cnt: compared as integers.
        topind = np.empty(RAND_DIM, np.int64)
        topvar = np.empty(RAND_DIM, np.int64)
        num = 0
        for d in range(n_dims):
            v = ones[d] * (cnt - ones[d])
            if num < RAND_DIM or v > topvar[num - 1]:
                if num < RAND_DIM:
                    num += 1
                topind[num - 1] = d
                topvar[num - 1] = v
                j = num - 1
                while j > 0 and topvar[j] > topvar[j - 1]:
                    topind[j], topind[j - 1] = topind[j - 1], topind[j]
                    topvar[j], topvar[j - 1] = topvar[j - 1], topvar[j]
                    j -= 1
        cut = topind[choices[drawn] % num]
        drawn += 1
        cutval = np.float32(ones[cut] / cnt)
        # planeSplit: [< cutval | == cutval | > cutval], swapped in place.
        left, right = 0, count - 1
        while True:
            while left <= right and np.float32(_bit(words, ind[start + left], cut)) < cutval:
                left += 1
            while left <= right and np.float32(_bit(words, ind[start + right], cut)) >= cutval:
                right -= 1
            if left > right:
                break
            ind[start + left], ind[start + right] = ind[start + right], ind[start + left]
            left += 1
            right -= 1
        lim1 = left
        right = count - 1
        while True:
            while left <= right and np.float32(_bit(words, ind[start + left], cut)) <= cutval:
                left += 1
            while left <= right and np.float32(_bit(words, ind[start + right], cut)) > cutval:
                right -= 1
            if left > right:
                break
            ind[start + left], ind[start + right] = ind[start + right], ind[start + left]
            left += 1
            right -= 1
        lim2 = left
        half = count // 2
        index = lim1 if lim1 > half else (lim2 if lim2 < half else half)
        if lim1 == count or lim2 == 0:
            index = half  # all alike on this dimension: split in the middle
        a, b = n_nodes, n_nodes + 1
        n_nodes += 2
        feat[node], val[node], child1[node], child2[node] = cut, cutval, a, b
        # child1 first (FLANN recurses into it first): pushed last.
        top += 1
        stack_node[top], stack_start[top], stack_count[top] = b, start + index, count - index
        top += 1
        stack_node[top], stack_start[top], stack_count[top] = a, start, index
    return root, n_nodes


@_jit()
def _insert(words, roots, first, last, feat, val, child1, child2, n_nodes):
    """addPointToTree of points [first, last) in every tree, in order; returns the number of nodes used."""
    for point in range(first, last):
        n_nodes = _insert_point(words, roots, point, feat, val, child1, child2, n_nodes)
    return n_nodes


@_jit(inline="always")
def _insert_point(words, roots, point, feat, val, child1, child2, n_nodes):
    """addPointToTree in every tree; returns the number of nodes used."""
    for t in range(roots.size):
        node = roots[t]
        while child1[node] != _LEAF:
            if np.float32(_bit(words, point, feat[node])) < val[node]:
                node = child1[node]
            else:
                node = child2[node]
        leaf_point = feat[node]
        cut = 0  # the first dimension of largest span (|0 - 1| = 1); 0 for an identical word
        for lane in range(words.shape[1]):
            differ = words[point, lane] ^ words[leaf_point, lane]
            if differ:
                low = differ & (~differ + np.uint64(1))
                b = 0
                while low > np.uint64(1):
                    low >>= np.uint64(1)
                    b += 1
                cut = lane * 64 + b
                break
        word_bit = np.float32(_bit(words, point, cut))
        leaf_bit = np.float32(_bit(words, leaf_point, cut))
        a, b = n_nodes, n_nodes + 1
        n_nodes += 2
        child1[a] = _LEAF
        child2[a] = _LEAF
        child1[b] = _LEAF
        child2[b] = _LEAF
        if word_bit < leaf_bit:
            feat[a], feat[b] = point, leaf_point
        else:
            feat[a], feat[b] = leaf_point, point
        feat[node], val[node] = cut, (word_bit + leaf_bit) / np.float32(2.0)
        child1[node], child2[node] = a, b
    return n_nodes


@_jit(inline="always")
def _heap_push(bounds, nodes, size, bound, node):
    """std::push_heap with FLANN's comparator (a min-heap on the bound)."""
    hole = size
    parent = (hole - 1) // 2
    while hole > 0 and bound < bounds[parent]:
        bounds[hole], nodes[hole] = bounds[parent], nodes[parent]
        hole = parent
        parent = (hole - 1) // 2
    bounds[hole], nodes[hole] = bound, node
    return size + 1


@_jit()
def _heap_pop(bounds, nodes, size):
    """std::pop_heap (libstdc++'s __adjust_heap) with FLANN's comparator; the heap's new size. The
    popped branch is left at index ``size - 1``."""
    if size <= 1:
        return size - 1
    last = size - 1
    value_b, value_n = bounds[last], nodes[last]
    bounds[last], nodes[last] = bounds[0], nodes[0]
    length = last
    hole = 0
    child = 0
    while child < (length - 1) // 2:
        child = 2 * (child + 1)
        if bounds[child - 1] < bounds[child]:  # comp(first[child], first[child - 1])
            child -= 1
        bounds[hole], nodes[hole] = bounds[child], nodes[child]
        hole = child
    if (length & 1) == 0 and child == (length - 2) // 2:
        child = 2 * (child + 1)
        bounds[hole], nodes[hole] = bounds[child - 1], nodes[child - 1]
        hole = child - 1
    parent = (hole - 1) // 2
    while hole > 0 and value_b < bounds[parent]:
        bounds[hole], nodes[hole] = bounds[parent], nodes[parent]
        hole = parent
        parent = (hole - 1) // 2
    bounds[hole], nodes[hole] = value_b, value_n
    return last


@_jit()
def _search_level(words, removed, query, q, node, mindist, feat, val, child1, child2, checked, stamp,
                  state, found_d, found_p, heap_b, heap_n):
    """searchLevel: one descent from ``node``; state = [checks, found, heap size]."""
    while True:
        worst = found_d[1] if state[1] == NEAREST else np.inf
        if worst < mindist:  # result_set.worstDist() < mindist
            return
        if child1[node] == _LEAF:
            point = feat[node]
            if removed[point] or checked[point] == stamp or (state[0] >= CHECKS and state[1] == NEAREST):
                return
            checked[point] = stamp
            state[0] += 1
            dist = 0.0
            for lane in range(words.shape[1]):
                dist += float(_popcount(words[point, lane] ^ query[q, lane]))
            # KNNSimpleResultSet::addPoint
            if dist >= worst:
                return
            if state[1] < NEAREST:
                state[1] += 1
            i = state[1] - 1
            while i > 0:
                if found_d[i - 1] > dist:
                    found_d[i] = found_d[i - 1]
                    found_p[i] = found_p[i - 1]
                    i -= 1
                else:
                    break
            found_d[i] = dist
            found_p[i] = point
            return
        bit = np.float32((query[q, feat[node] >> 6] >> np.uint64(feat[node] & 63)) & np.uint64(1))
        diff = bit - val[node]
        if diff < 0:
            best, other = child1[node], child2[node]
        else:
            best, other = child2[node], child1[node]
        new_dist = mindist + abs(diff)
        if new_dist < worst or state[1] < NEAREST:
            if state[2] < heap_b.size:  # FLANN's Heap holds at most size_ branches
                state[2] = _heap_push(heap_b, heap_n, state[2], new_dist, other)
        node = best


@_jit()
def _search(words, removed, roots, feat, val, child1, child2, queries, checked, stamp0, out_d, out_p):
    """getNeighbors (2-NN, 32 checks) of every query."""
    heap_b = np.empty(max(words.shape[0], 1), np.float32)
    heap_n = np.empty(max(words.shape[0], 1), np.int64)
    found_d = np.empty(NEAREST, np.float64)
    found_p = np.empty(NEAREST, np.int64)
    state = np.zeros(3, np.int64)
    for q in range(queries.shape[0]):
        stamp = stamp0 + q
        state[:] = 0
        found_d[:] = np.inf
        found_p[:] = -1
        for t in range(roots.size):
            _search_level(words, removed, queries, q, roots[t], np.float32(0.0), feat, val, child1, child2, checked, stamp,
                          state, found_d, found_p, heap_b, heap_n)
        while state[2] > 0 and (state[0] < CHECKS or state[1] < NEAREST):
            state[2] = _heap_pop(heap_b, heap_n, state[2])
            _search_level(words, removed, queries, q, heap_n[state[2]], heap_b[state[2]], feat, val, child1,
                          child2, checked, stamp, state, found_d, found_p, heap_b, heap_n)
        for k in range(NEAREST):
            out_d[q, k] = found_d[k]
            out_p[q, k] = found_p[k]


def _as_lanes(descriptors: np.ndarray, lanes: int) -> np.ndarray:
    """(N, n_bytes) uint8 -> (N, lanes) little-endian uint64 (zero-padded to whole lanes)."""
    descriptors = np.ascontiguousarray(descriptors, np.uint8)
    padded = np.zeros((descriptors.shape[0], lanes * 8), np.uint8)
    padded[:, : descriptors.shape[1]] = descriptors
    return padded.view("<u8")


def _grown(array: np.ndarray, size: int, keep: int) -> np.ndarray:
    """``array`` with room for ``size`` rows, its first ``keep`` rows kept, the rest zero. The room is
    ``np.zeros`` (calloc): its pages are resident only once written."""
    out = np.zeros((size,) + array.shape[1:], array.dtype)
    out[:keep] = array[:keep]
    return out


def _draws(rng: np.random.Generator, n: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """The random choices of a build over ``n`` words: a permutation and one draw per inner node per tree."""
    return [(rng.permutation(n).astype(np.int64), rng.integers(0, RAND_DIM, size=max(n - 1, 1)).astype(np.int64))
            for _ in range(TREES)]


class _Forest:
    """One index state: the words (points), their ids and removed flags, and the nodes of the trees."""

    def __init__(self, lanes: int, n_bits: int, words: np.ndarray, ids: np.ndarray) -> None:
        self.lanes, self.n_bits = lanes, n_bits
        n = ids.size
        size = max(_INITIAL_POINTS, int((1.0 + INSERTION_ROOM) * n))
        self.words = _grown(words, size, n)
        self.ids = _grown(ids, size, n)
        self.removed = np.zeros(size, np.bool_)
        self.n_points = n
        self.point_of = IdIndex()  # word id -> point (live words only)
        self.point_of.insert(ids, np.arange(n, dtype=np.int64))
        self.n_removed = 0
        self.size_at_build = 0
        # Nodes of all trees, one row of 16 bytes each (feat, val, child1, child2, as FLANN's Node struct):
        # a descent reads one cache line per node, not four (searches 1.3-1.5x faster at 100k words).
        # A leaf has child1 == _LEAF and its point in feat.
        self._set_nodes(np.zeros((0, 4), _NODE))
        self.n_nodes = 0
        self.roots = np.zeros(0, np.int64)

    def build(self, draws: list[tuple[np.ndarray, np.ndarray]]) -> None:
        """divideTree for each tree over all points, with one (permutation, choices) draw per tree.
        Room is reserved for the insertions until the next rebuild is swapped in (2 nodes per tree
        per word, INSERTION_ROOM x the words): no node array grows in a frame."""
        n = self.n_points
        self.n_nodes = 0
        self._set_nodes(np.zeros((0, 4), _NODE))
        self.reserve_nodes(TREES * (2 * n - 1) + 2 * TREES * (int(INSERTION_ROOM * n) + 1) + 16)
        roots = []
        for ind, choices in draws:
            root, self.n_nodes = _divide_tree(self.words, self.n_bits, ind.copy(), choices, self.feat, self.val,
                                              self.child1, self.child2, self.n_nodes)
            roots.append(root)
        self.roots = np.asarray(roots, np.int64)
        self.size_at_build = n

    def add(self, lanes: np.ndarray, ids: np.ndarray) -> None:
        """Append words (distinct ids) and insert them into every tree (addPointToTree)."""
        n = ids.size
        first = self.n_points
        self.reserve_points(first + n)
        self.words[first:first + n] = lanes
        self.ids[first:first + n] = ids
        self.removed[first:first + n] = False
        points = np.arange(first, first + n, dtype=np.int64)
        old = self.point_of.rows(ids)
        again = old >= 0
        if again.any():  # re-added under the same id: the old point goes
            self.removed[old[again]] = True
            self.n_removed += int(again.sum())
            self.point_of.set_rows(ids[again], points[again])
        self.point_of.insert(ids[~again], points[~again])
        self.n_points = first + n
        if self.roots.size:
            self.reserve_nodes(self.n_nodes + 2 * TREES * n)
            self.n_nodes = _insert(self.words, self.roots, first, first + n, self.feat, self.val, self.child1,
                                   self.child2, self.n_nodes)

    def remove(self, ids: np.ndarray) -> None:
        """Mark words (distinct ids) removed; ids not held are ignored."""
        points = self.point_of.rows(ids)
        live = points >= 0
        self.removed[points[live]] = True
        self.n_removed += int(live.sum())
        self.point_of.remove(ids[live])

    def needs_rebuild(self) -> bool:
        """FlannIndex::addPoints: the index holds more than REBALANCING x its size at the last build."""
        return self.size_at_build * REBALANCING < self.n_points

    def reserve_points(self, needed: int) -> None:
        if needed <= self.ids.size:
            return
        size = max(needed, 2 * self.ids.size)
        keep = self.n_points
        self.words = _grown(self.words, size, keep)
        self.ids = _grown(self.ids, size, keep)
        self.removed = _grown(self.removed, size, keep)

    def _set_nodes(self, nodes: np.ndarray) -> None:
        """The node rows and the column views the numba functions take (strided, no copy)."""
        self.nodes = nodes
        self.feat, self.child1, self.child2 = nodes[:, 0], nodes[:, 2], nodes[:, 3]
        self.val = nodes.view(np.float32)[:, 1]

    def reserve_nodes(self, needed: int) -> None:
        if needed <= self.nodes.shape[0]:
            return
        self._set_nodes(_grown(self.nodes, max(needed, 2 * self.nodes.shape[0]), self.n_nodes))

    def search(self, queries: np.ndarray, checked: np.ndarray, stamp: int, distances: np.ndarray,
               points: np.ndarray) -> None:
        """The 2 nearest words of each query into ``distances`` / ``points``; ``checked`` (at least
        n_points stamps) marks the words checked, query i's with ``stamp + i``."""
        n = self.n_points
        _search(self.words[:n], self.removed[:n], self.roots, self.feat, self.val, self.child1, self.child2,
                queries, checked, stamp, distances, points)


class _Rebuild:
    """A rebuild (cleanRemovedPoints + buildIndex) over a snapshot of the index: the live words of its
    first ``n`` points. Run here or in a thread (numba releases the GIL); the changes made since the
    snapshot are logged and replayed into the result in order.

    The snapshot costs the frame a copy of the removed flags only: points below ``n`` never change
    (new words are appended, a re-added id gets a new point), so the thread reads the current
    arrays, or the ones they were copied from if they grow meanwhile."""

    def __init__(self, forest: _Forest, rng: np.random.Generator, swap_at: int) -> None:
        n = forest.n_points
        self._snapshot = (forest.lanes, forest.n_bits, forest.words, forest.ids, forest.removed[:n].copy())
        self._rng = rng  # used by the thread only until ``done`` (no other build meanwhile)
        self.swap_at = swap_at
        self.log: list[tuple[str, np.ndarray | None, np.ndarray]] = []
        self.forest: _Forest | None = None
        self.error: BaseException | None = None
        self.seconds = 0.0
        self.done = threading.Event()
        self.thread = threading.Thread(target=self.run, name="vocabulary-kdtree-build", daemon=True)

    def run(self) -> None:
        """Build (the thread's target; an error is kept for the main thread)."""
        start = time.perf_counter()
        try:
            lanes, n_bits, words, ids, removed = self._snapshot
            kept = np.flatnonzero(~removed)
            forest = _Forest(lanes, n_bits, words[kept], ids[kept])
            forest.build(_draws(self._rng, kept.size))
            self.forest = forest
        except BaseException as exc:  # noqa: BLE001 - re-raised in the main thread
            self.error = exc
        finally:
            self._snapshot = None
            self.seconds = time.perf_counter() - start
            self.done.set()

    def replay(self, max_words: int | None = None) -> None:
        """Apply the changes logged so far, in order, to the rebuilt forest (main thread, once
        ``done``): all of them, or whole changes until ``max_words`` words were replayed."""
        replayed = done = 0
        for kind, lanes, ids in self.log:
            if max_words is not None and replayed >= max_words:
                break
            if kind == "add":
                self.forest.add(lanes, ids)
            else:
                self.forest.remove(ids)
            replayed += ids.size
            done += 1
        del self.log[:done]


class RandomizedKdTrees:
    """FLANN's randomized kd-trees (L1 over bits) holding binary words by id.

    ``background_rebuild``: when the index has doubled, its rebuild (seconds at a million words: more
    than T_time) runs in a thread on a snapshot of the live words while the current trees keep serving
    and taking words; the ``swap_searches``-th search after it started (past IN_TIME_REBUILD_WORDS
    words, the ``max(swap_searches, words / SWAP_WORDS_PER_SEARCH)``-th) swaps the new trees in
    (waiting for the thread if needed), the words added and removed since replayed into them (from the
    first search after the thread finished on, up to REPLAY_WORDS_PER_SEARCH words a search, the rest
    at the swap). The swap point counts searches (frames), not time, so the same words give the same answers whatever the machine's load; the
    answers are those of a rebuild made at the snapshot followed by the same changes. Without it, the
    rebuild happens in the call that doubles the index, as RTAB-Map's."""

    def __init__(self, n_bytes: int, seed: int = 0, *, background_rebuild: bool = False,
                 swap_searches: int = 1, search_threads: int = 1) -> None:
        if swap_searches < 1:
            raise ValueError(f"swap_searches={swap_searches} is invalid: >= 1")
        if search_threads < 1:
            raise ValueError(f"search_threads={search_threads} is invalid: >= 1")
        self.n_bits = 8 * n_bytes
        self._lanes = -(-n_bytes // 8)
        self._rng = np.random.default_rng(seed)
        self._forest = _Forest(self._lanes, self.n_bits, np.zeros((0, self._lanes), np.uint64), np.zeros(0, np.int64))
        self._stamp = 1  # checked[] starts at 0
        # One array of check stamps per searching thread (query i of a search is stamp _stamp + i).
        self._checked = [np.zeros(0, np.int64) for _ in range(search_threads)]
        self._pool: ThreadPoolExecutor | None = None
        self._searches = 0
        self.background_rebuild = background_rebuild
        self.swap_searches = swap_searches
        self._rebuild: _Rebuild | None = None
        self.rebuilds = 0  # rebuilds swapped in (the first build excluded)
        self.last_rebuild_seconds = 0.0  # the last one's time in its thread
        self.last_wait_seconds = 0.0  # what the last swap search waited for its thread

    def __len__(self) -> int:
        return len(self._forest.point_of)

    @property
    def _size_at_build(self) -> int:
        return self._forest.size_at_build

    @property
    def rebuilding(self) -> bool:
        """True while a background rebuild is pending (not swapped in yet)."""
        return self._rebuild is not None

    # ------------------------------------------------------------------ changes
    def add(self, descriptors: np.ndarray, ids: np.ndarray) -> None:
        """Add words ((N, n_bytes) uint8 with distinct ids) as FlannIndex::addPoints: inserted into every
        tree, then the index is rebuilt if it now holds more than REBALANCING x its size at the last
        build (removed words included). The first words are indexed at once (a build)."""
        ids = np.asarray(ids, np.int64)
        if not ids.size:
            return
        lanes = _as_lanes(descriptors, self._lanes)
        forest = self._forest
        forest.add(lanes, ids)
        if self._rebuild is not None:
            self._rebuild.log.append(("add", lanes, ids.copy()))
        elif not forest.roots.size or forest.needs_rebuild():
            self._start_rebuild(first=not forest.roots.size)

    def remove(self, ids: np.ndarray) -> None:
        """Mark words removed (FLANN removePoint; distinct ids): searches skip them until the next rebuild."""
        ids = np.asarray(ids, np.int64)
        self._forest.remove(ids)
        if self._rebuild is not None:
            self._rebuild.log.append(("remove", None, ids.copy()))

    def _start_rebuild(self, first: bool) -> None:
        """buildIndex over the live words (cleanRemovedPoints): here, or in a thread (not the first build)."""
        n_points = self._forest.n_points
        delay = (self.swap_searches if n_points <= IN_TIME_REBUILD_WORDS
                 else max(self.swap_searches, -(-n_points // SWAP_WORDS_PER_SEARCH)))
        rebuild = _Rebuild(self._forest, self._rng, self._searches + delay)
        if first or not self.background_rebuild:
            rebuild.run()
            self._swap_in(rebuild)
            return
        self._rebuild = rebuild
        rebuild.thread.start()

    def _swap_in(self, rebuild: _Rebuild) -> None:
        if rebuild.error is not None:
            raise rebuild.error
        rebuild.replay()
        if self._forest.roots.size:
            self.rebuilds += 1
            self.last_rebuild_seconds = rebuild.seconds
            logger.debug("kd-tree rebuilt over %d words in %.2f s", len(rebuild.forest.point_of), rebuild.seconds)
        self._forest = rebuild.forest
        if self._forest.needs_rebuild():
            self._start_rebuild(first=False)

    def _maybe_swap(self) -> None:
        """At the swap search: wait for the rebuild if needed and swap it in. Before it, once the thread
        has finished, replay what was logged so far (spreads the replay over the searches; the content
        at the swap is the same whenever the thread finished)."""
        rebuild = self._rebuild
        if rebuild is None:
            return
        swap = self._searches >= rebuild.swap_at
        if not swap:
            if rebuild.done.is_set() and rebuild.error is None:
                rebuild.replay(REPLAY_WORDS_PER_SEARCH)
            return
        start = time.perf_counter()
        rebuild.thread.join()
        self.last_wait_seconds = time.perf_counter() - start
        if self.last_wait_seconds > WAIT_WARNING_S:
            logger.warning("kd-tree word search: the frame waited %.2f s for the trees' rebuild (%.1f s in its "
                           "thread): the machine is loaded", self.last_wait_seconds, rebuild.seconds)
        self._rebuild = None
        self._swap_in(rebuild)

    # ------------------------------------------------------------------ search
    def search(self, descriptors: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The 2 nearest words found of each descriptor: Hamming distances (N, 2) float32 and word
        ids (N, 2) int64, inf / -1 where fewer than two words were found."""
        self._searches += 1
        self._maybe_swap()
        forest = self._forest
        n = descriptors.shape[0]
        distances = np.full((n, NEAREST), np.inf, np.float64)
        points = np.full((n, NEAREST), -1, np.int64)
        if forest.roots.size and n:
            self._search_chunks(forest, _as_lanes(descriptors, self._lanes), distances, points)
            self._stamp += n
        ids = np.where(points >= 0, forest.ids[np.maximum(points, 0)], -1)
        return distances.astype(np.float32), ids

    def _search_chunks(self, forest: _Forest, queries: np.ndarray, distances: np.ndarray, points: np.ndarray) -> None:
        """Search ``queries`` in chunks of SEARCH_CHUNK, over this thread and ``search_threads - 1`` helpers
        (numba releases the GIL). Each query's search is independent of the others' (its own stamp), so
        the answers are the same however the chunks are shared out."""
        for slot, checked in enumerate(self._checked):
            if checked.size < forest.n_points:
                self._checked[slot] = np.zeros(max(forest.n_points, 2 * checked.size), np.int64)
        n = queries.shape[0]
        n_chunks = -(-n // SEARCH_CHUNK)
        helpers = min(len(self._checked), n_chunks) - 1
        claim = itertools.count()  # next() is atomic under the GIL
        done = [threading.Event() for _ in range(n_chunks)]
        failed: list[BaseException] = []

        def work(slot: int) -> None:
            while (chunk := next(claim)) < n_chunks:
                a, b = chunk * SEARCH_CHUNK, min(n, (chunk + 1) * SEARCH_CHUNK)
                try:
                    forest.search(queries[a:b], self._checked[slot], self._stamp + a, distances[a:b], points[a:b])
                except BaseException as exc:  # re-raised in the calling thread
                    failed.append(exc)
                finally:
                    done[chunk].set()

        if helpers > 0:
            if self._pool is None:
                self._pool = ThreadPoolExecutor(len(self._checked) - 1, thread_name_prefix="kdtree-search")
            for slot in range(1, helpers + 1):
                self._pool.submit(work, slot)
        work(0)
        for event in done:
            event.wait()
        if failed:
            raise failed[0]

    def close(self) -> None:
        """Wait for a pending rebuild and drop it (the current trees stay in use); stop the search helpers."""
        rebuild, self._rebuild = self._rebuild, None
        if rebuild is not None:
            rebuild.thread.join()
        pool, self._pool = self._pool, None
        if pool is not None:
            pool.shutdown(wait=True)


# The compiled functions called from Python (the others are inlined into them).
_DISPATCHED = (_divide_tree, _insert, _heap_pop, _search_level, _search)
_warm_lock = threading.Lock()
_warmed = False


def warm_up() -> float:
    """Compile every function of the build, the insertion and the search (or load them from numba's
    cache) on a few words, once per process, so that no frame pays it: ~7 s of CPU on the first run of
    an install or source version, ~1 s loading the cache (numba's own start-up). Logged. Returns the
    seconds it took (0.0 once done)."""
    global _warmed
    with _warm_lock:
        if _warmed:
            return 0.0
        start = time.perf_counter()
        words = np.random.default_rng(0).integers(0, 256, (48, 32), dtype=np.uint8)
        trees = RandomizedKdTrees(32)
        trees.add(words[:16], np.arange(16))  # a build
        trees.add(words[16:24], np.arange(16, 24))  # insertions
        trees.remove(np.arange(0, 4))
        trees.search(words[:8])  # search, heap
        trees.add(words[24:], np.arange(24, 48))  # doubled: a rebuild
        trees.search(words[:8])
        seconds = time.perf_counter() - start
        stats = [getattr(f, "stats", None) for f in _DISPATCHED]  # None: NUMBA_DISABLE_JIT (Python)
        compiled = sum(sum(s.cache_misses.values()) for s in stats if s is not None)
        cache = stats[-1].cache_path if stats[-1] is not None else None
        if stats[-1] is None:
            logger.warning("kd-tree word search: numba's JIT is disabled (NUMBA_DISABLE_JIT): it runs as Python, "
                           "100-500x slower")
        elif UNCACHED:
            logger.warning("kd-tree word search: numba compiled it in %.1f s and cannot cache it (no writable cache "
                           "directory beside the package or in the user's cache; set NUMBA_CACHE_DIR): every "
                           "process compiles it again", seconds)
        elif compiled:
            logger.info("kd-tree word search: numba compiled it in %.1f s (once per install; cached in %s)",
                        seconds, cache)
        else:
            logger.info("kd-tree word search: loaded from numba's cache (%s) in %.2f s", cache, seconds)
        _warmed = True
        return seconds
