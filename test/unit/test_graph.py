"""graph: connected components and the agreement test of two alignments."""

from __future__ import annotations

import numpy as np

from rtabmap_ros2.core import transforms
from rtabmap_ros2.core.graph import Link, LinkType, agree, agree_many, connected_components


def _link(a: int, b: int) -> Link:
    return Link(a, b, LinkType.NEIGHBOR)


def test_components_of_a_node_set_largest_first():
    links = [_link(1, 2), _link(2, 3), _link(5, 6), _link(3, 99)]  # 99 is not in the set: not a path
    assert connected_components([1, 2, 3, 4, 5, 6], links) == [{1, 2, 3}, {5, 6}, {4}]
    assert connected_components([1, 3], [_link(1, 2), _link(2, 3)]) in ([{1}, {3}], [{3}, {1}])
    assert connected_components([], links) == []


def test_agree_many_is_agree_of_each():
    differences = np.stack([transforms.from_xy_yaw(0.1, 0.0, 0.05),  # close
                            transforms.from_xy_yaw(0.6, 0.0, 0.0),  # too far
                            transforms.from_xy_yaw(0.0, 0.0, np.deg2rad(12.0))])  # too rotated
    assert agree_many(differences).tolist() == [True, False, False]
    assert [agree(d) for d in differences] == [True, False, False]
