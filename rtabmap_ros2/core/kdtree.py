"""RTAB-Map's approximate word search: FLANN randomized kd-trees over binary descriptors' bits.

RTAB-Map 0.22 quantises binary descriptors (ORB) with ``Kp/NNStrategy`` 1: each descriptor's bits
become 0/1 floats (``Kp/ByteToFloat`` false: VWDictionary::convertBinTo32F, byte j's bit b is
dimension 8 j + b), indexed by FLANN's randomized kd-trees with the L1 distance (on bits, the Hamming
distance) and searched for the 2 nearest words with 32 checks (VWDictionary.cpp ``KNN_CHECKS``).
Words are added one at a time into every tree (FlannIndex::addPoints, incremental FLANN) until the
index holds ``Kp/FlannRebalancingFactor`` (2) times the words it was built with, removed ones
included; then it is rebuilt from the words left. Removed words stay in the trees, skipped.

The search is approximate: a descriptor often misses its nearest word, then either becomes a new
word or matches a word of an unrelated place that passes the ratio test among the few words
checked. That is why RTAB-Map's vocabulary is ~1.5x an exact search's and why many WM locations
share a word or two with any image by chance (issue 32: the mean of the non-zero scores, hence
Eq. 3's likelihood, depends on them). This module is FLANN's algorithm (rtflann
``kdtree_index.h``) written for that case, so that ``vocabulary.index: kdtree``
(``config/rtabmap_reference.yaml``) behaves as the reference does:

* build (``divideTree`` / ``meanSplit``): each tree over a random permutation of the words; a node
  takes the mean and variance of each dimension over its first 101 words, picks one of the 5
  highest-variance dimensions at random and splits at its mean; leaves hold one word;
* insertion (``addPointToTree``): down to a leaf, which becomes a node splitting the two words on
  the first dimension where they differ, at 0.5;
* search (``getNeighbors``): one descent per tree, the branches not taken queued by their lower
  bound (the sum of ``|bit - split|`` on the way), then best-bin-first from that queue until 32
  words have been checked and two found; a word is checked once across trees.

Deterministic: the random choices come from a seeded generator (FLANN's differ run to run, so the
reference itself is not repeatable). Pure Python over Python ints (``int.bit_count`` for the
Hamming distance): ~0.3 ms per query; a full rebuild 2.6 s at 20k words, 19 s at 256k.
"""

from __future__ import annotations

import heapq
import random

import numpy as np

# FLANN's KDTreeIndexParams default, RTAB-Map's KNN_CHECKS and Kp/FlannRebalancingFactor default.
TREES = 4
CHECKS = 32
REBALANCING = 2.0
# kdtree_index.h: the split dimension is drawn among the RAND_DIM highest variances, estimated on
# the first SAMPLE_MEAN + 1 words of the node.
RAND_DIM = 5
SAMPLE_MEAN = 100
_LEAF = -1


class RandomizedKdTrees:
    """FLANN's randomized kd-trees (L1 over bits) holding binary words by id."""

    def __init__(self, n_bytes: int, seed: int = 0) -> None:
        self.n_bits = 8 * n_bytes
        self._rng = random.Random(seed)
        self._words: list[int] = []  # each word's bits as one int (bit 8 j + b = byte j's bit b)
        self._ids: list[int] = []  # word id of each point
        self._removed: list[bool] = []
        self._point_of: dict[int, int] = {}  # word id -> point (live words only)
        self._n_removed = 0
        self._size_at_build = 0
        # Nodes of all trees: a leaf has child1 == _LEAF and its point in feat.
        self._feat: list[int] = []
        self._val: list[float] = []
        self._child1: list[int] = []
        self._child2: list[int] = []
        self._roots: list[int] = []

    def __len__(self) -> int:
        return len(self._point_of)

    # ------------------------------------------------------------------ changes
    def add(self, descriptors: np.ndarray, ids: np.ndarray) -> None:
        """Add words ((N, n_bytes) uint8 with their ids), one at a time (FlannIndex::addPoints)."""
        descriptors = np.ascontiguousarray(descriptors, np.uint8)
        first = not self._roots
        for row, word_id in zip(descriptors, np.asarray(ids, np.int64).tolist()):
            point = len(self._words)
            self._words.append(int.from_bytes(row.tobytes(), "little"))
            self._ids.append(word_id)
            self._removed.append(False)
            self._point_of[word_id] = point
            if first:
                continue
            if self._size_at_build * REBALANCING < len(self._words):
                self._build()
            else:
                for root in self._roots:
                    self._insert(root, point)
        if first and self._words:
            # The first words are indexed at once (VWDictionary::update's first update).
            self._build()

    def remove(self, ids: np.ndarray) -> None:
        """Mark words removed (FLANN removePoint): searches skip them until the next rebuild."""
        for word_id in np.asarray(ids, np.int64).tolist():
            point = self._point_of.pop(word_id, None)
            if point is not None:
                self._removed[point] = True
                self._n_removed += 1

    def _build(self) -> None:
        """buildIndex: drop the removed words, then TREES trees over random permutations."""
        if self._n_removed:
            kept = [p for p, gone in enumerate(self._removed) if not gone]
            self._words = [self._words[p] for p in kept]
            self._ids = [self._ids[p] for p in kept]
            self._removed = [False] * len(kept)
            self._point_of = {word_id: p for p, word_id in enumerate(self._ids)}
            self._n_removed = 0
        n = len(self._words)
        packed = np.frombuffer(b"".join(w.to_bytes(self.n_bits // 8, "little") for w in self._words),
                               np.uint8).reshape(n, self.n_bits // 8)
        bits = np.unpackbits(packed, axis=1, bitorder="little")
        self._feat, self._val, self._child1, self._child2, self._roots = [], [], [], [], []
        order = list(range(n))
        for _ in range(TREES):
            self._rng.shuffle(order)
            self._roots.append(self._divide(np.asarray(order, np.int64), bits))
        self._size_at_build = n

    def _node(self) -> int:
        self._feat.append(0)
        self._val.append(0.0)
        self._child1.append(_LEAF)
        self._child2.append(_LEAF)
        return len(self._feat) - 1

    def _divide(self, points: np.ndarray, bits: np.ndarray) -> int:
        """divideTree + meanSplit (explicit stack): the root of a tree over ``points`` (rows of
        ``bits``, every word's bits unpacked)."""
        root = self._node()
        stack = [(root, points)]
        while stack:
            node, points = stack.pop()
            count = points.size
            if count == 1:
                self._feat[node] = int(points[0])
                continue
            sample = bits[points[: min(SAMPLE_MEAN + 1, count)]].astype(np.float32)
            mean = sample.mean(axis=0)
            variance = ((sample - mean) ** 2).sum(axis=0)
            # selectDivision: the RAND_DIM largest variances, the lower dimension first on a tie.
            top = np.argsort(-variance, kind="stable")[:RAND_DIM]
            cut = int(top[self._rng.randrange(top.size)])
            cut_value = float(mean[cut])
            column = bits[points, cut]
            below, equal = column < cut_value, column == cut_value
            lim1 = int(below.sum())
            lim2 = lim1 + int(equal.sum())
            points = np.concatenate([points[below], points[equal], points[~below & ~equal]])
            half = count // 2
            index = lim1 if lim1 > half else lim2 if lim2 < half else half
            if lim1 == count or lim2 == 0:
                index = half  # all alike on this dimension: split in the middle
            left, right = self._node(), self._node()
            self._feat[node], self._val[node] = cut, cut_value
            self._child1[node], self._child2[node] = left, right
            stack.append((right, points[index:]))
            stack.append((left, points[:index]))
        return root

    def _insert(self, node: int, point: int) -> None:
        """addPointToTree: descend to a leaf and split it between its word and the new one."""
        feat, val, child1, child2 = self._feat, self._val, self._child1, self._child2
        word = self._words[point]
        while child1[node] != _LEAF:
            node = child1[node] if ((word >> feat[node]) & 1) < val[node] else child2[node]
        leaf_point = feat[node]
        leaf_word = self._words[leaf_point]
        differ = word ^ leaf_word
        cut = (differ & -differ).bit_length() - 1 if differ else 0  # the first dimension of largest span
        word_bit, leaf_bit = (word >> cut) & 1, (leaf_word >> cut) & 1
        left, right = self._node(), self._node()
        feat[left], feat[right] = (point, leaf_point) if word_bit < leaf_bit else (leaf_point, point)
        feat[node], val[node] = cut, (word_bit + leaf_bit) / 2
        child1[node], child2[node] = left, right

    # ------------------------------------------------------------------ search
    def search(self, descriptors: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The 2 nearest words found of each descriptor: Hamming distances (N, 2) float32 and word
        ids (N, 2) int64, inf / -1 where fewer than two words were found."""
        n = descriptors.shape[0]
        distances = np.full((n, 2), np.inf, np.float32)
        ids = np.full((n, 2), -1, np.int64)
        if not self._roots:
            return distances, ids
        for row, descriptor in enumerate(np.ascontiguousarray(descriptors, np.uint8)):
            for k, (distance, point) in enumerate(self._nearest_two(int.from_bytes(descriptor.tobytes(), "little"))):
                distances[row, k] = distance
                ids[row, k] = self._ids[point]
        return distances, ids

    def _nearest_two(self, query: int) -> list[tuple[int, int]]:
        """getNeighbors with a 2-NN result set: [(distance, point)], nearest first."""
        feat, val, child1, child2 = self._feat, self._val, self._child1, self._child2
        words, removed = self._words, self._removed
        found: list[tuple[int, int]] = []
        checked: set[int] = set()
        branches: list[tuple[float, int, int]] = []
        state = [0, 0]  # checks made, branches queued (the queue's tie order)
        inf = float("inf")

        def descend(node: int, lower_bound: float) -> None:
            while True:
                worst = found[1][0] if len(found) == 2 else inf
                if worst < lower_bound:
                    return
                if child1[node] == _LEAF:
                    point = feat[node]
                    if removed[point] or point in checked or (state[0] >= CHECKS and len(found) == 2):
                        return
                    checked.add(point)
                    state[0] += 1
                    distance = (words[point] ^ query).bit_count()
                    if distance < worst:
                        # KNNSimpleResultSet: a tie goes after the words already found.
                        found.append((distance, point))
                        if len(found) == 2 and found[1][0] < found[0][0]:
                            found.reverse()
                        elif len(found) == 3:
                            found.sort(key=lambda f: f[0])
                            del found[2]
                    return
                bit = (query >> feat[node]) & 1
                offset = bit - val[node]
                if offset < 0:
                    near, far = child1[node], child2[node]
                else:
                    near, far = child2[node], child1[node]
                bound = lower_bound + abs(offset)
                if bound < worst or len(found) < 2:
                    state[1] += 1
                    heapq.heappush(branches, (bound, state[1], far))
                node = near

        for root in self._roots:
            descend(root, 0.0)
        while branches and (state[0] < CHECKS or len(found) < 2):
            bound, _, node = heapq.heappop(branches)
            descend(node, bound)
        return found
