"""Word id -> row maps (the vocabulary's buffer, the kd-trees' points)."""

from __future__ import annotations

import numpy as np

from rtabmap_ros2.core import id_index


def test_rows_follow_adds_removals_and_re_added_ids(rng, monkeypatch):
    """The id -> row index answers as a dict does through appends, removals (with compaction),
    row moves and ids re-added below the largest one."""
    monkeypatch.setattr(id_index, "INITIAL_CAPACITY", 8)  # compaction every few removals
    index = id_index.IdIndex()
    model: dict[int, int] = {}
    next_id = 1
    for step in range(400):
        action = rng.random()
        if action < 0.4:
            ids = np.arange(next_id, next_id + rng.integers(1, 20))
            next_id = int(ids[-1]) + 1
        elif action < 0.55:
            gone = [w for w in range(1, next_id) if w not in model]
            if not gone:
                continue
            ids = np.array(sorted(rng.choice(gone, min(len(gone), 5), replace=False)))
        elif action < 0.85 and model:
            ids = rng.choice(np.array(sorted(model)), min(len(model), int(rng.integers(1, 12))), replace=False)
            index.remove(ids)
            for w in ids.tolist():
                del model[w]
            continue
        elif model:
            ids = rng.choice(np.array(sorted(model)), min(len(model), 4), replace=False)
            rows = rng.integers(0, 10_000, ids.size)
            index.set_rows(ids, rows)
            model.update(zip(ids.tolist(), rows.tolist()))
            continue
        else:
            continue
        rows = rng.integers(0, 10_000, ids.size)
        index.insert(ids, rows)
        model.update(zip(ids.tolist(), rows.tolist()))
        probe = np.arange(0, next_id + 3)
        assert index.rows(probe).tolist() == [model.get(w, -1) for w in probe.tolist()]
    assert index.row(next_id + 100) == -1


def test_a_removed_id_coming_back_takes_its_place_again():
    index = id_index.IdIndex()
    index.insert(np.array([3, 5, 9]), np.array([0, 1, 2]))
    index.remove(np.array([5]))
    assert len(index) == 2 and index.row(5) == -1
    index.insert(np.array([5, 4]), np.array([7, 8]))  # below the largest id held: in place
    assert len(index) == 4
    assert index.rows(np.array([3, 4, 5, 9, 10])).tolist() == [0, 8, 7, 2, -1]
