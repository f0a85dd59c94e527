"""graph: connected components and the agreement test of two alignments."""

from __future__ import annotations

import numpy as np

from rtabmap_ros2.core import transforms
import pytest

from rtabmap_ros2.core.graph import (Graph, Link, LinkTable, LinkType, PoseStack, agree, agree_many, component_labels,
                                     connected_components, residuals)


def _link(a: int, b: int) -> Link:
    return Link(a, b, LinkType.NEIGHBOR)


def test_components_of_a_node_set_largest_first():
    links = [_link(1, 2), _link(2, 3), _link(5, 6), _link(3, 99)]  # 99 is not in the set: not a path
    assert connected_components([1, 2, 3, 4, 5, 6], links) == [{1, 2, 3}, {5, 6}, {4}]
    assert connected_components([1, 3], [_link(1, 2), _link(2, 3)]) in ([{1}, {3}], [{3}, {1}])
    assert connected_components([], links) == []


def test_link_table_and_residuals_are_each_links_own():
    links = [Link(3, 7, LinkType.NEIGHBOR, transforms.from_xy_yaw(1.0, 0.5, 0.3), np.diag([1.0, 2, 3, 4, 5, 6])),
             Link(7, 12, LinkType.LOOP_INTER, transforms.from_xy_yaw(-2.0, 0.0, -1.2), np.eye(6) * 9.0)]
    table = LinkTable(links)
    assert table.ends.tolist() == [[3, 7], [7, 12]]
    for link, T_inverse, diagonal in zip(links, table.T_inverse, table.information_diagonal):
        np.testing.assert_allclose(T_inverse, transforms.inverse(link.T_from_to), atol=1e-12)
        np.testing.assert_array_equal(diagonal, np.diagonal(link.information))
    poses = {3: transforms.from_xy_yaw(0.2, 0.1, 0.4), 7: transforms.from_xy_yaw(1.0, 2.0, 0.1),
             12: transforms.from_xy_yaw(-1.0, 1.0, -0.7)}
    for link, residual in zip(links, residuals(poses, table)):
        np.testing.assert_allclose(residual, link.residual(poses[link.from_id], poses[link.to_id]), atol=1e-12)
    with pytest.raises(KeyError, match="12"):
        residuals({3: poses[3], 7: poses[7]}, table)


def test_pose_stack_from_arrays_is_the_stack_of_their_dict():
    """A solver's (ids, poses) arrays make the same stack as the dict of them, unsorted ids included;
    gather returns poses in the order asked and names a node that has none."""
    ids = np.array([12, 3, 7])
    poses = np.stack([transforms.from_xy_yaw(float(i), -1.0, 0.1 * i) for i in ids])
    from_arrays, from_dict = PoseStack.of_arrays(ids, poses), PoseStack(dict(zip(ids.tolist(), poses)))
    np.testing.assert_array_equal(from_arrays.ids, from_dict.ids)
    np.testing.assert_array_equal(from_arrays.poses, from_dict.poses)
    assert PoseStack.of(from_arrays) is from_arrays and len(from_arrays) == 3
    np.testing.assert_array_equal(from_arrays.gather([7, 12]), poses[[2, 0]])
    with pytest.raises(KeyError, match="5"):
        from_arrays.gather([3, 5])


def test_agree_many_is_agree_of_each():
    differences = np.stack([transforms.from_xy_yaw(0.1, 0.0, 0.05),  # close
                            transforms.from_xy_yaw(0.6, 0.0, 0.0),  # too far
                            transforms.from_xy_yaw(0.0, 0.0, np.deg2rad(12.0))])  # too rotated
    assert agree_many(differences).tolist() == [True, False, False]
    assert [agree(d) for d in differences] == [True, False, False]


def _components_by_search(count: int, ends: np.ndarray) -> list[set[int]]:
    """Reference: breadth-first search over an adjacency list."""
    adjacency: dict[int, set[int]] = {i: set() for i in range(count)}
    for a, b in ends.tolist():
        adjacency[a].add(b)
        adjacency[b].add(a)
    seen, out = set(), []
    for start in range(count):
        if start in seen:
            continue
        component, frontier = {start}, [start]
        while frontier:
            frontier = [m for n in frontier for m in adjacency[n] if m not in component]
            component.update(frontier)
        seen |= component
        out.append(component)
    return out


def test_component_labels_match_a_graph_search(rng):
    """Random graphs, and chains visited in random order (the slowest case for label propagation):
    same partition as a breadth-first search, each label the smallest index of its component."""
    for trial in range(200):
        count = int(rng.integers(1, 120))
        if trial % 2:
            order = rng.permutation(count)
            ends = np.column_stack([order[:-1], order[1:]])[: int(rng.integers(0, count))]
        else:
            ends = rng.integers(0, count, (int(rng.integers(0, 2 * count)), 2))
        labels = component_labels(count, ends.reshape(-1, 2))
        expected = _components_by_search(count, ends.reshape(-1, 2))
        got: dict[int, set[int]] = {}
        for node, label in enumerate(labels.tolist()):
            got.setdefault(label, set()).add(node)
        assert sorted(map(sorted, got.values())) == sorted(map(sorted, expected))
        assert all(label == min(got[label]) for label in got)


def test_hops_cross_free_link_types_without_counting():
    """RTAB-Map's neighbourhoods (Memory::getNeighborsId, incrementMarginOnLoop false): a loop
    closure joins two places at the same distance, also at the edge of the reach."""
    # 1 - 2 - 3 - 4 and 10 - 11 - 12, loop closure 2 - 11, loop closure 4 - 20.
    links = [_link(a, b) for a, b in ((1, 2), (2, 3), (3, 4), (10, 11), (11, 12))]
    links += [Link(2, 11, LinkType.LOOP_INTRA), Link(4, 20, LinkType.LOOP_INTER)]
    graph = Graph(links)
    loops = (LinkType.LOOP_INTRA, LinkType.LOOP_INTER)
    assert graph.hops_from(2, 2) == {2: 0, 1: 1, 3: 1, 11: 1, 4: 2, 10: 2, 12: 2}
    assert graph.hops_from(2, 2, free=loops) == {2: 0, 11: 0, 1: 1, 3: 1, 10: 1, 12: 1, 4: 2, 20: 2}
    assert graph.hops_from(1, 1, free=loops) == {1: 0, 2: 1, 11: 1}
    assert graph.hops_from(12, 3, types=(LinkType.NEIGHBOR,), free=loops) == {12: 0, 11: 1, 10: 2}


def test_rigid_products_equal_the_matrix_products():
    """The compiled L @ inv(A) @ B (and inv(A) @ B) of rigid transforms is numpy's 4x4 product."""
    from rtabmap_ros2.core.graph import rigid_products

    rng = np.random.default_rng(3)
    L, A, B = (np.stack([transforms.from_xyz_rpy(rng.normal(size=6)) for _ in range(50)]) for _ in range(3))
    expected = L @ np.linalg.inv(A) @ B
    assert np.allclose(rigid_products(L, A, B), expected, atol=1e-12)
    assert np.allclose(rigid_products(None, A, B), np.linalg.inv(A) @ B, atol=1e-12)
    assert rigid_products(None, A[:0], B[:0]).shape == (0, 4, 4)
