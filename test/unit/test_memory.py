"""Memory (2013 §III-B, E, F): rehearsal, STM -> WM, transfer (Alg. 4), retrieval (Alg. 3).

Locations are built from random ORB-like descriptors (every one a new word), so the tests control
exactly which words each location holds.
"""

from __future__ import annotations

import numpy as np
import pytest

from rtabmap_ros2.core.database import Database
from rtabmap_ros2.core import transforms
from rtabmap_ros2.core.graph import Graph, Link, LinkType, default_information
from rtabmap_ros2.core.memory import Memory
from rtabmap_ros2.core.params import Params
from rtabmap_ros2.core.signature import Signature

WORDS = 50


def make_memory(tmp_path, **memory_overrides) -> Memory:
    params = Params().with_overrides([f"memory.{k}={v}" for k, v in memory_overrides.items()])
    return Memory(params, Database(tmp_path / "m.db"), binary_descriptors=True)


def add(memory: Memory, node_id: int, descriptors: np.ndarray) -> int:
    """One frame of Alg. 1 (quantise, STM insertion, rehearsal, STM -> WM, commit); returns merged id.
    No descriptors: a bad signature, kept without words."""
    before = memory.vocabulary.next_word_id
    word_ids = memory.quantize(descriptors)
    sig = Signature(id=node_id, map_id=memory.map_id, stamp_ns=node_id, word_ids=word_ids,
                    keypoints=np.zeros((len(word_ids), 2), np.float32),
                    points3d=np.full((len(word_ids), 3), np.nan, np.float32), bad=len(word_ids) == 0)
    previous = memory.last_location()
    memory.add_location(sig, None, Link(previous.id, node_id, LinkType.NEIGHBOR) if previous else None)
    merged, _ = memory.rehearse(sig, [w for w in word_ids.tolist() if w >= before])
    memory.update_stm()
    memory.commit()
    memory.join()
    return merged


@pytest.fixture
def descriptors(rng):
    return lambda: rng.integers(0, 256, (WORDS, 32), dtype=np.uint8)


def test_rehearsal_merges_the_same_view_into_the_older_location(tmp_path, descriptors):
    """RTAB-Map's rehearsal merge: the new location is deleted, the older one stays (its id, its
    words) and takes the new one's weight plus one."""
    memory = make_memory(tmp_path)
    view = descriptors()
    assert add(memory, 1, view) == 0
    words = len(memory.vocabulary)
    assert add(memory, 2, view) == 2
    assert add(memory, 3, view) == 3
    assert list(memory.signatures) == [1] and memory.stm == [1]
    assert memory.signatures[1].weight == 2
    assert len(memory.vocabulary) == words  # no word added by the repeated views
    assert all(memory.vocabulary.references(int(w)) == {1: 1} for w in memory.signatures[1].word_ids[:5])
    assert 2 not in memory.graph and 3 not in memory.graph
    stored = memory.db.load_nodes()
    assert set(stored) == {1} and stored[1].weight == 2


def test_different_views_are_not_merged(tmp_path, descriptors):
    memory = make_memory(tmp_path)
    assert add(memory, 1, descriptors()) == 0
    assert add(memory, 2, descriptors()) == 0
    assert memory.signatures[2].weight == 0
    assert memory.graph.link(1, 2) is not None


def test_stm_holds_t_stm_locations_the_older_go_to_wm(tmp_path, descriptors):
    memory = make_memory(tmp_path, stm_size=3)
    for node in range(1, 7):
        add(memory, node, descriptors())
        assert len(memory.stm) <= 3
    assert memory.stm == [4, 5, 6]
    assert list(memory.wm) == [1, 2, 3]
    np.testing.assert_array_equal(memory.hypothesis_ids(), [1, 2, 3])  # STM is not a hypothesis


def filled(tmp_path, descriptors, weights: dict[int, int]) -> Memory:
    memory = make_memory(tmp_path, stm_size=2, recent_wm_ratio=0.0)
    for node in range(1, len(weights) + 3):
        add(memory, node, descriptors())
    for node, weight in weights.items():
        memory.signatures[node].weight = weight
    return memory


def test_transfer_moves_the_oldest_lowest_weighted_until_enough_words_left(tmp_path, descriptors):
    memory = filled(tmp_path, descriptors, {1: 3, 2: 0, 3: 0, 4: 5, 5: 0, 6: 1})
    words_before = len(memory.vocabulary)
    memory.words_added = 2 * WORDS + 1  # needs three locations' words to leave the vocabulary
    moved = memory.transfer(protected={3}, locations=2, balance_words=True)
    assert moved == [2, 5, 6]
    assert len(memory.vocabulary) == words_before - 3 * WORDS
    assert set(memory.wm) == {1, 3, 4} and memory.stm == [7, 8]
    memory.commit()
    memory.join()
    assert set(memory.db.wm_ids()) == {1, 3, 4, 7, 8}  # LTM flag written
    assert memory.ltm_size == 3


def test_transfer_moves_at_least_the_locations_asked_lowest_weight_first(tmp_path, descriptors):
    memory = filled(tmp_path, descriptors, {1: 1, 2: 0, 3: 2})
    memory.words_added = 0
    assert memory.transfer(protected=set(), locations=2, balance_words=True) == [2, 1]


def test_transfer_without_word_balance_stops_at_the_locations_asked(tmp_path, descriptors):
    """A WM over its cap (not over T_time) lets out exactly the excess, whatever words came in."""
    memory = filled(tmp_path, descriptors, {1: 1, 2: 0, 3: 2})
    memory.words_added = 10 * WORDS
    assert memory.transfer(protected=set(), locations=1, balance_words=False) == [2]


def test_recent_part_of_wm_is_protected(tmp_path, descriptors):
    memory = filled(tmp_path, descriptors, {1: 0, 2: 0, 3: 0, 4: 0})
    memory.params = Params().with_overrides(["memory.stm_size=2", "memory.recent_wm_ratio=0.5"])
    memory.last_loop_closure_id = 2
    memory.signatures[4].weight = 1
    memory.words_added = 10 * WORDS
    moved = memory.transfer(protected=set(), locations=2, balance_words=True)
    # T_recent: half of WM (2 locations) after the last loop closure (3, 4) stays.
    assert moved == [1, 2]


def test_retrieval_brings_back_time_neighbours_first_with_their_words(tmp_path, descriptors):
    memory = filled(tmp_path, descriptors, {1: 3, 2: 0, 3: 0, 4: 5, 5: 0, 6: 1})
    memory.add_link(Link(4, 1, LinkType.LOOP_INTRA))  # a space neighbour of 4 (1 hop)
    memory.words_added = 4 * WORDS
    moved = memory.transfer(protected={4}, locations=2, balance_words=True)
    assert moved == [2, 3, 5, 6]
    memory.commit()
    memory.join()
    lost = memory.db.load_signature(5).word_ids
    assert not any(memory.vocabulary.contains(int(w)) for w in lost)
    # Time neighbours of 4 by hops: 5 and 3 (1 hop), then 2 and 6 (2 hops); 1 is in WM.
    assert memory.retrieval_candidates(4) == [3, 5, 2, 6]
    assert memory.retrieve(memory.retrieval_candidates(4)[:2]) == [3, 5]  # Rtabmap/MaxRetrieved = 2
    assert {3, 5} <= set(memory.wm)
    assert all(memory.vocabulary.contains(int(w)) for w in lost)
    assert memory.vocabulary.references(int(lost[0])) == {5: 1}
    memory.commit()
    memory.join()
    assert {3, 5} <= set(memory.db.wm_ids())
    # Retrieved locations are not transferred again in the same frame.
    memory.retrieved_now = [3, 5]
    memory.words_added = 100 * WORDS
    assert not {3, 5} & set(memory.transfer(protected=set(), locations=4, balance_words=True))


def test_local_retrieval_takes_ltm_links_of_the_nearest_nodes_first_then_their_neighbours(tmp_path, descriptors):
    memory = filled(tmp_path, descriptors, {n: 0 for n in range(1, 9)})
    memory.add_link(Link(8, 2, LinkType.LOOP_INTRA))
    memory.words_added = 10 * WORDS
    assert memory.transfer(protected={1, 4, 8}, locations=3, balance_words=False) == [2, 3, 5]
    # Node 4 is nearest the robot: its LTM links first (newest first: 5, 3), then node 8's (its
    # loop closure to 2) ...
    assert memory.local_retrieval_candidates([4, 8], limit=3) == [5, 3, 2]
    assert memory.local_retrieval_candidates([4, 8], limit=2) == [5, 3]
    # ... then, with room left, the LTM neighbours of those found (3 -> 2).
    assert memory.local_retrieval_candidates([4], limit=10) == [5, 3, 2]
    assert memory.local_retrieval_candidates([4], limit=0) == []
    assert memory.retrieve([5, 3]) == [5, 3]
    assert memory.retrieve([5, 3, 4]) == []  # already in WM: nothing to load
    # The bad-signature mean's count follows the locations held through transfer and retrieval.
    held = sum(len(sig.word_ids) for sig in memory.signatures.values())
    assert memory.vocabulary.total_references == held == len(memory.signatures) * WORDS


def test_bad_signature_threshold_is_rtabmaps_mean_over_the_locations_held(tmp_path, descriptors):
    """RTAB-Map's Memory::createSignature: bad below Kp/BadSignRatio x (word occurrences of the
    locations in WM and STM // their number), bad ones counted without words; none held, only an
    image without features is bad."""
    memory = make_memory(tmp_path, bad_signature_ratio=0.5)
    assert memory.is_bad_signature(0) and not memory.is_bad_signature(1)
    add(memory, 1, descriptors())
    add(memory, 2, descriptors())
    assert memory.vocabulary.total_references == 2 * WORDS
    assert memory.is_bad_signature(WORDS // 2 - 1) and not memory.is_bad_signature(WORDS // 2)
    # Two bad signatures held without words halve the mean: 100 occurrences over 4 locations.
    add(memory, 3, descriptors()[:0])
    add(memory, 4, descriptors()[:0])
    assert memory.is_bad_signature(12) and not memory.is_bad_signature(13)  # 0.5 x (100 // 4)
    # A location merged by rehearsal leaves the count with its words.
    view = descriptors()
    add(memory, 5, view)
    assert add(memory, 6, view) == 6
    assert memory.vocabulary.total_references == sum(len(sig.word_ids) for sig in memory.signatures.values()) == 3 * WORDS


def test_merged_location_leaves_no_link_in_the_database(tmp_path, descriptors):
    memory = make_memory(tmp_path)
    view = descriptors()
    add(memory, 1, descriptors())
    add(memory, 2, view)
    assert add(memory, 3, view) == 3  # 2 -> 3 was in the batch that deletes 3
    stored = {(link.from_id, link.to_id) for link in memory.db.load_links()}
    nodes = set(memory.db.load_nodes())
    assert nodes == {1, 2}
    assert all(a in nodes and b in nodes for a, b in stored)
    assert stored in ({(1, 2)}, {(2, 1)})


def test_loop_closure_undone_in_its_own_frame_is_not_written(tmp_path, descriptors):
    """A loop closure rejected after optimisation (RGBD/OptimizeMaxError) in the frame that added it
    must not reach the database: the export's global map would otherwise optimise with it."""
    memory = make_memory(tmp_path)
    for node in (1, 2, 3):
        add(memory, node, descriptors())
    kept = Link(3, 1, LinkType.LOOP_INTRA)
    memory.add_loop_closure(kept)
    memory.commit()
    memory.join()
    add(memory, 4, descriptors())
    rejected = Link(4, 2, LinkType.LOOP_INTRA)
    before = memory.add_loop_closure(rejected)
    memory.undo_loop_closure(rejected, before)
    memory.commit()
    memory.join()
    stored = {(link.from_id, link.to_id) for link in memory.db.load_links()}
    assert (3, 1) in stored
    assert (4, 2) not in stored and (2, 4) not in stored
    assert memory.graph.link(4, 2) is None


def add_moving(memory: Memory, node_id: int, descriptors: np.ndarray, T_odom: np.ndarray,
               T_link: np.ndarray | None = None) -> int:
    """A SLAM-mode frame: odometry pose, neighbour link from the previous node (``T_link``, e.g.
    refined by scan matching; default: the odometry's relative pose). Returns the merged id."""
    word_ids = memory.quantize(descriptors)
    sig = Signature(id=node_id, map_id=memory.map_id, stamp_ns=node_id, word_ids=word_ids,
                    keypoints=np.zeros((len(word_ids), 2), np.float32),
                    points3d=np.zeros((len(word_ids), 3), np.float32), T_odom_base=T_odom)
    previous = memory.last_location()
    link = None
    if previous is not None:
        T = T_link if T_link is not None else transforms.relative(previous.T_odom_base, T_odom)
        link = Link(previous.id, node_id, LinkType.NEIGHBOR, T, default_information(0.01))
    memory.add_location(sig, None, link)
    merged, _ = memory.rehearse(sig, [])
    memory.update_stm()
    memory.commit()
    memory.join()
    return merged


@pytest.mark.parametrize("weight_ignored", [False, True])
def test_rehearsal_keeps_both_locations_of_a_moving_camera(tmp_path, descriptors, weight_ignored):
    """SLAM mode, same view but the odometry moved 0.3 m: no merge (Mem/RehearsalMaxDistance);
    the weight moves to the new node unless Mem/RehearsalWeightIgnoredWhileMoving."""
    memory = make_memory(tmp_path, rehearsal_weight_ignored_while_moving=weight_ignored)
    view = descriptors()
    add_moving(memory, 1, view, transforms.from_xy_yaw(0.0, 0.0, 0.0))
    memory.signatures[1].weight = 4
    assert add_moving(memory, 2, view, transforms.from_xy_yaw(0.3, 0.0, 0.0)) == 0
    assert set(memory.signatures) == {1, 2} and memory.graph.link(1, 2) is not None
    assert (memory.signatures[1].weight, memory.signatures[2].weight) == ((4, 0) if weight_ignored else (0, 5))
    # Turning on the spot (0.3 rad > Mem/RehearsalMaxAngle) is moving too.
    assert add_moving(memory, 3, view, transforms.from_xy_yaw(0.3, 0.0, 0.3)) == 0
    # Standing still (1 cm, Mem/RehearsalMaxDistance 5 cm): merged as in appearance-only mode.
    assert add_moving(memory, 4, view, transforms.from_xy_yaw(0.31, 0.0, 0.3)) == 4
    assert set(memory.signatures) == {1, 2, 3}


def test_rehearsal_merge_keeps_the_older_node_and_its_links(tmp_path, descriptors):
    """SLAM mode, standing still: the new node 3 goes, node 2 keeps its pose, its (scan-refined)
    link to 1 and its sensor data; nothing of 3 reaches the database."""
    memory = make_memory(tmp_path)
    view = descriptors()
    add_moving(memory, 1, descriptors(), transforms.from_xy_yaw(0.0, 0.0, 0.0))
    refined = transforms.from_xy_yaw(0.9, 0.1, 0.05)
    add_moving(memory, 2, view, transforms.from_xy_yaw(1.0, 0.0, 0.0), T_link=refined)
    assert add_moving(memory, 3, view, transforms.from_xy_yaw(1.04, 0.0, 0.0)) == 3
    assert set(memory.signatures) == {1, 2} and memory.stm == [1, 2]
    np.testing.assert_allclose(memory.graph.link(1, 2).T_from_to, refined)
    np.testing.assert_allclose(memory.signatures[2].T_odom_base, transforms.from_xy_yaw(1.0, 0.0, 0.0))
    assert memory.signatures[2].weight == 1
    assert set(memory.db.load_nodes()) == {1, 2}


def test_rehearsal_id_updated_to_new_one_keeps_the_newer_location(tmp_path, descriptors):
    """Mem/RehearsalIdUpdatedToNewOne (SLAM's config/rtabmap.yaml): the older location goes, the
    newer one keeps its id and takes the older one's words and weight plus one."""
    memory = make_memory(tmp_path, rehearsal_id_updated_to_new_one=True)
    view = descriptors()
    assert add(memory, 1, view) == 0
    words = len(memory.vocabulary)
    first_words = memory.signatures[1].word_ids.copy()
    assert add(memory, 2, view) == 1
    assert add(memory, 3, view) == 2
    assert list(memory.signatures) == [3] and memory.stm == [3]
    assert memory.signatures[3].weight == 2
    np.testing.assert_array_equal(memory.signatures[3].word_ids, first_words)
    assert len(memory.vocabulary) == words
    assert all(memory.vocabulary.references(int(w)) == {3: 1} for w in memory.signatures[3].word_ids[:5])
    assert 1 not in memory.graph and 2 not in memory.graph
    stored = memory.db.load_nodes()
    assert set(stored) == {3} and stored[3].weight == 2


def test_rehearsal_id_updated_to_new_one_reanchors_through_the_refined_link(tmp_path, descriptors):
    """Merging 2 into 3 re-anchors 2's links on 3 through the stored (scan-refined) link 2 -> 3,
    not through raw odometry: 3 -> 1 = inverse(T_2_3 refined) @ T_2_1; 3 keeps its odometry pose."""
    memory = make_memory(tmp_path, rehearsal_id_updated_to_new_one=True)
    view = descriptors()
    add_moving(memory, 1, descriptors(), transforms.from_xy_yaw(0.0, 0.0, 0.0))
    add_moving(memory, 2, view, transforms.from_xy_yaw(1.0, 0.0, 0.0), T_link=transforms.from_xy_yaw(0.9, 0.1, 0.05))
    refined = transforms.from_xy_yaw(0.02, -0.01, 0.02)  # odometry says 0.04 m, 0 rad
    assert add_moving(memory, 3, view, transforms.from_xy_yaw(1.04, 0.0, 0.0), T_link=refined) == 2
    assert set(memory.signatures) == {1, 3} and memory.stm == [1, 3]
    T_3_1 = memory.graph.link(3, 1).T_from_to
    expected = transforms.inverse(refined) @ transforms.inverse(transforms.from_xy_yaw(0.9, 0.1, 0.05))
    np.testing.assert_allclose(T_3_1, expected, atol=1e-9)
    # The two links' uncertainties add up (RTAB-Map's Link::merge).
    np.testing.assert_allclose(memory.graph.link(3, 1).information, default_information(0.02))
    np.testing.assert_allclose(memory.signatures[3].T_odom_base, transforms.from_xy_yaw(1.04, 0.0, 0.0))
    assert set(memory.db.load_nodes()) == {1, 3}


def test_transfer_takes_equal_weights_from_the_session_holding_most_of_wm(tmp_path, descriptors):
    """A session being mapped must not drain the older ones out of WM: among equal weights the
    locations go from the session with the most of WM (then the oldest), so each keeps a share."""
    memory = make_memory(tmp_path, stm_size=1, recent_wm_ratio=0.0)
    for node in (1, 2):
        add(memory, node, descriptors())
    memory.flush_stm()
    memory.map_id = 1
    for node in range(3, 9):
        add(memory, node, descriptors())
    assert set(memory.wm) == set(range(1, 8)) and memory.stm == [8]
    memory.words_added = 0
    # Map 1 holds 5 of WM's 7, map 0 two: 3 go from map 1 (its oldest), then one from each.
    assert memory.transfer(protected=set(), locations=5, balance_words=False) == [3, 4, 5, 1, 6]


def _candidates_on_the_whole_graph(graph: Graph, memory: Memory, hypothesis: int) -> list[int]:
    """Reference for retrieval_candidates: the whole graph in RAM (what the memory held before
    LTM links went to the database only)."""
    reach = memory.params.bayes.neighborhood
    time_hops = graph.hops_from(hypothesis, reach, types=(LinkType.NEIGHBOR,))
    all_hops = graph.hops_from(hypothesis, reach)
    first = sorted((n for n in time_hops if n not in memory.signatures), key=lambda n: (time_hops[n], n))
    rest = sorted((n for n in all_hops if n not in memory.signatures and n not in time_hops),
                  key=lambda n: (all_hops[n], n))
    return first + rest


def test_ltm_links_leave_ram_and_come_back_with_retrieval(tmp_path, descriptors):
    """Links between two LTM locations are in the database only (RAM stays flat once WM stops
    growing); the retrieval search reads them there and finds what the whole graph gives."""
    memory = filled(tmp_path, descriptors, {n: 0 for n in range(1, 13)})  # 14 nodes, STM 13-14
    memory.add_link(Link(12, 3, LinkType.LOOP_INTRA))
    memory.add_link(Link(9, 2, LinkType.LOOP_INTRA))
    memory.commit()
    memory.join()
    moved = memory.transfer(protected={1, 6, 12}, locations=8, balance_words=False)
    assert moved == [2, 3, 4, 5, 7, 8, 9, 10]
    memory.commit()
    memory.join()
    # In RAM: links touching memory (5-6, 6-7, 10-11, 12-3, 1-2); not 3-4 nor 9-2.
    assert memory.graph.link(3, 4) is None and memory.graph.link(9, 2) is None and memory.graph.link(8, 9) is None
    assert all(memory.graph.link(a, b) is not None for a, b in ((5, 6), (6, 7), (10, 11), (12, 3), (1, 2)))
    assert 8 not in memory.graph and 9 not in memory.graph
    assert memory.ltm_size == 8
    whole = Graph(memory.db.load_links())
    for hypothesis in (1, 6, 11, 12):
        expected = _candidates_on_the_whole_graph(whole, memory, hypothesis)
        assert memory.retrieval_candidates(hypothesis) == expected
        for limit in (1, 2, 3):
            assert memory.retrieval_candidates(hypothesis, limit) == expected[:limit]
        assert memory.retrieval_candidates(hypothesis, 2, exclude=expected[:1]) == expected[1:3]
    # The transition model's hops (RAM and database alike), loop closures counted as a hop or not.
    for free in ((), (LinkType.LOOP_INTRA, LinkType.LOOP_INTER)):
        for start in (1, 6, 12):
            assert memory.hops_from(start, 4, free=free) == whole.hops_from(start, 4, free=free)
    # 6's time neighbours in LTM: 5, 7 (1 hop), 4, 8 (2 hops), 3, 9 (3 hops)...
    assert memory.retrieval_candidates(6)[:6] == [5, 7, 4, 8, 3, 9]
    # A retrieved location's links come back, LTM ends included, as stored.
    assert memory.retrieve([9]) == [9]
    for other in (8, 10, 2):
        stored = next(l for l in memory.db.load_links([9]) if {l.from_id, l.to_id} == {9, other})
        np.testing.assert_array_equal(memory.graph.link(stored.from_id, stored.to_id).T_from_to, stored.T_from_to)


def test_sessions_joined_by_inter_session_loop_closures(tmp_path, descriptors):
    """connected_maps: the sessions of a map id's connected component, following inter-session
    loop closures as they are added and removed, and after reopening."""
    memory = make_memory(tmp_path, stm_size=2)
    for node in range(1, 10):
        if node in (4, 7):
            memory.map_id += 1  # sessions 0: 1-3, 1: 4-6, 2: 7-9
            memory.flush_stm()
        add(memory, node, descriptors())
    assert [memory.map_ids[n] for n in (1, 3, 4, 6, 7, 9)] == [0, 0, 1, 1, 2, 2]
    assert memory.connected_maps(2) == {2}
    memory.add_link(Link(8, 2, LinkType.LOOP_INTER))
    assert memory.connected_maps(0) == {0, 2} and memory.connected_maps(1) == {1}
    memory.add_link(Link(9, 5, LinkType.LOOP_INTER))
    assert memory.connected_maps(1) == {0, 1, 2}
    memory.remove_link(8, 2)
    assert memory.connected_maps(0) == {0}
    memory.close()
    reopened = Memory(Params(), Database(tmp_path / "m.db"), binary_descriptors=True)
    assert reopened.connected_maps(1) == {1, 2} and reopened.map_id == 3
    assert reopened.ltm_size == 0 and reopened.map_ids[5] == 1
    reopened.close()
