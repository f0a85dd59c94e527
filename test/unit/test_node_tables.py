"""node_tables: what RAM keeps about every node, WM and LTM (session ids, kept poses)."""

from __future__ import annotations

import numpy as np
import pytest

from rtabmap_ros2.core import transforms
from rtabmap_ros2.core.node_tables import PoseTable, SessionIds


def test_session_ids_are_ranges_of_node_ids():
    ids = SessionIds({0: 1, 1: 40}, last_id=55)
    assert ids[1] == 0 and ids[39] == 0 and ids[40] == 1 and ids[55] == 1
    assert ids.get(56) is None and 0 not in ids and 56 not in ids
    with pytest.raises(KeyError):
        ids[0]
    ids.add(56, 1)
    ids.add(60, 3)  # a new session (ids may skip)
    assert ids[56] == 1 and ids[58] == 1 and ids[60] == 3
    assert ids.id_range(1) == range(40, 60) and ids.id_range(3) == range(60, 61) and ids.id_range(2) == range(0)
    with pytest.raises(ValueError):
        ids.add(59, 3)  # ids only grow
    nodes = np.array([[1, 40], [59, 60], [39, 56]])
    assert ids.of(nodes).tolist() == [[ids[n] for n in row] for row in nodes.tolist()]
    for unknown in (0, 61):
        with pytest.raises(KeyError):
            ids.of(np.array([1, unknown]))


def test_pose_table_keeps_rigid_poses_by_node_id():
    table = PoseTable()
    poses = {n: transforms.from_xy_yaw(0.1 * n, -0.2 * n, 0.01 * n) for n in (3, 5, 2000)}  # 2000: grows
    table.update(poses)
    assert len(table) == 3 and 5 in table and 4 not in table and -1 not in table and 10**6 not in table
    np.testing.assert_array_equal(table[2000], poses[2000])
    assert table.get(4) is None
    assert set(table.items_in(range(0, 10))) == {3, 5}
    np.testing.assert_array_equal(table.items_in(range(4, 2001))[5], poses[5])
    assert table.items_in(range(6, 2000)) == {}
    assert set(table.items_in([2000, 4, -1, 10**6, 3])) == {2000, 3}  # any ids, absent ones skipped
    assert table.items_in(n for n in ()) == {}
    table[5] = poses[3]  # replaced, not added
    assert len(table) == 3
    np.testing.assert_array_equal(table.pop(5), poses[3])
    assert table.pop(5) is None and len(table) == 2 and list(table) == [3, 2000]
