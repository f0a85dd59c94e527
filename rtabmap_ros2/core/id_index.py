"""Word id -> row maps with no Python object per word (the vocabulary's buffer, the kd-trees' points).

A million words held as a dict cost ~100 MB of CPython objects and a Python loop per change; here
the ids are kept in increasing order in a numpy array (``np.searchsorted``) beside their rows.
"""

from __future__ import annotations

import numpy as np

# Initial capacity (ids); the arrays double when full.
INITIAL_CAPACITY = 4096


class IdIndex:
    """Id -> row (int64), vectorised. A removed id keeps its place with row -1 until removed ones
    are a quarter of the entries (then they are compacted away). Ids larger than every id held
    are appended (new words get increasing ids: the usual insert); a smaller one (a word retrieved
    from LTM with its id) is inserted in place, O(held) as one memory move, never a sort of all."""

    def __init__(self) -> None:
        self._ids = np.zeros(INITIAL_CAPACITY, np.int64)  # [0, _n) sorted; removed ones have row -1
        self._rows = np.zeros(INITIAL_CAPACITY, np.int64)
        self._n = 0
        self._removed = 0

    def __len__(self) -> int:
        """Ids held (removed ones excluded)."""
        return self._n - self._removed

    def rows(self, ids: np.ndarray) -> np.ndarray:
        """Row of each id (int64 array of the same shape), -1 where the id is not held."""
        ids = np.asarray(ids, np.int64)
        if self._n == 0:
            return np.full(ids.shape, -1, np.int64)
        pos = np.minimum(np.searchsorted(self._ids[: self._n], ids), self._n - 1)
        return np.where(self._ids[pos] == ids, self._rows[pos], -1)

    def row(self, word_id: int) -> int:
        """Row of one id, -1 if it is not held."""
        return int(self.rows(np.array([word_id]))[0])

    def insert(self, ids: np.ndarray, rows: np.ndarray) -> None:
        """Add ids (distinct, none of them held) with their rows."""
        ids = np.asarray(ids, np.int64)
        rows = np.asarray(rows, np.int64)
        if not ids.size:
            return
        order = np.argsort(ids, kind="stable")
        ids, rows = ids[order], rows[order]
        n = self._n
        if n and ids[0] <= self._ids[n - 1]:
            held = self._ids[:n]
            pos = np.minimum(np.searchsorted(held, ids), n - 1)
            placeholder = held[pos] == ids  # a removed id coming back: its place is still there
            if placeholder.any():
                self._rows[pos[placeholder]] = rows[placeholder]
                self._removed -= int(placeholder.sum())
                ids, rows = ids[~placeholder], rows[~placeholder]
            if ids.size and ids[0] <= self._ids[n - 1]:
                at = np.searchsorted(held, ids)
                merged_ids = np.insert(held, at, ids)
                merged_rows = np.insert(self._rows[:n], at, rows)
                capacity = max(self._ids.size, merged_ids.size)
                self._ids = np.resize(merged_ids, capacity)
                self._rows = np.resize(merged_rows, capacity)
                self._n = merged_ids.size
                return
        needed = self._n + ids.size
        if needed > self._ids.size:
            capacity = max(needed, 2 * self._ids.size)
            self._ids = np.resize(self._ids, capacity)
            self._rows = np.resize(self._rows, capacity)
        self._ids[self._n: needed] = ids
        self._rows[self._n: needed] = rows
        self._n = needed

    def set_rows(self, ids: np.ndarray, rows: np.ndarray) -> None:
        """New rows of held ids (their storage moved)."""
        self._rows[np.searchsorted(self._ids[: self._n], ids)] = rows

    def remove(self, ids: np.ndarray) -> None:
        """Drop held ids (distinct)."""
        ids = np.asarray(ids, np.int64)
        self._rows[np.searchsorted(self._ids[: self._n], ids)] = -1
        self._removed += ids.size
        if self._removed > max(INITIAL_CAPACITY, self._n // 4):
            keep = np.flatnonzero(self._rows[: self._n] >= 0)
            self._ids[: keep.size] = self._ids[keep]
            self._rows[: keep.size] = self._rows[keep]
            self._n, self._removed = keep.size, 0
