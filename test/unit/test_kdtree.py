"""RTAB-Map's approximate word search (core/kdtree.py: FLANN randomized kd-trees over bits)."""

from __future__ import annotations

import faiss
import numpy as np
import pytest

from rtabmap_ros2.core import kdtree
from rtabmap_ros2.core.kdtree import RandomizedKdTrees
from rtabmap_ros2.core.params import Params, VocabularyParams
from rtabmap_ros2.core.vocabulary import Vocabulary
from rtabmap_ros2.errors import ParameterError

from test_vocabulary import flip_bits, random_binary


def _exact(queries: np.ndarray, words: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return faiss.knn_hamming(queries, words, 2)


def test_near_copies_find_their_word_with_true_distances(rng):
    """A view of a word with a few bits flipped (what a revisit gives) finds that word, at its
    true Hamming distance, whether the word was in the first build or inserted since."""
    words = random_binary(rng, 3000)
    trees = RandomizedKdTrees(32)
    trees.add(words[:1000], np.arange(1, 1001))  # built at once
    trees.add(words[1000:1500], np.arange(1001, 1501))  # inserted into the trees (below 2x)
    assert trees._size_at_build == 1000
    trees.add(words[1500:], np.arange(1501, 3001))  # crosses 2x: rebuilt
    assert trees._size_at_build > 2000
    queries = flip_bits(rng, words[::7], 8)
    distances, ids = trees.search(queries)
    expected = np.arange(1, 3001)[::7]
    assert np.mean(ids[:, 0] == expected) > 0.95
    true = np.array([bin(int.from_bytes((q ^ words[i - 1]).tobytes(), "little")).count("1")
                     for q, i in zip(queries, ids[:, 0])])
    np.testing.assert_array_equal(distances[:, 0], true)
    assert (distances[:, 0] <= distances[:, 1]).all()


def test_search_is_approximate_as_flann_with_32_checks(rng):
    """Unlike the exact index, a query far from every word checks only ~32 of 20,000 words: it
    misses the true nearest word most of the time (the reason RTAB-Map's vocabulary is larger),
    and never reports a distance below the true one."""
    words = random_binary(rng, 20000)
    trees = RandomizedKdTrees(32)
    trees.add(words, np.arange(20000))
    queries = random_binary(rng, 200)
    distances, ids = trees.search(queries)
    exact_distances, exact_ids = _exact(queries, words)
    assert (distances[:, 0] >= exact_distances[:, 0]).all()
    assert np.mean(ids[:, 0] == exact_ids[:, 0]) < 0.5
    assert np.isfinite(distances).all()


def test_removed_words_are_never_returned_and_re_added_ids_are_found(rng):
    words = random_binary(rng, 500)
    trees = RandomizedKdTrees(32)
    trees.add(words, np.arange(500))
    trees.remove(np.arange(0, 500, 2))
    assert len(trees) == 250
    _, ids = trees.search(words[:100])
    assert not np.isin(ids[ids >= 0], np.arange(0, 500, 2)).any()
    # Word 0 comes back with its id (retrieval from LTM) and another descriptor.
    moved = flip_bits(rng, words[1:2], 3)
    trees.add(moved, np.array([0]))
    distances, ids = trees.search(moved)
    assert ids[0, 0] == 0 and distances[0, 0] == 0


def test_same_seed_same_answers(rng):
    """Deterministic: the same words in the same order give the same trees and answers."""
    words = random_binary(rng, 4000)
    queries = flip_bits(rng, words[::13], 20)
    answers = []
    for _ in range(2):
        trees = RandomizedKdTrees(32, seed=7)
        for start in range(0, 4000, 400):  # frames of 400 words, rebuilt at each doubling
            trees.add(words[start:start + 400], np.arange(start, start + 400))
        answers.append(trees.search(queries))
    np.testing.assert_array_equal(answers[0][1], answers[1][1])
    np.testing.assert_array_equal(answers[0][0], answers[1][0])


def test_threads_find_the_same_words_as_one(rng):
    """vocabulary.kdtree_search_threads: the queries are shared out in chunks over threads, and
    every answer is the one a single thread gives (each query's checks are its own), through
    insertions, removals and a background rebuild; a short batch stays in the calling thread."""
    words = random_binary(rng, 6000)
    queries = [flip_bits(rng, words[i:i + 400], 12) for i in range(0, 6000, 400)]
    answers = {}
    for threads in (1, 2, 3):
        trees = RandomizedKdTrees(32, seed=5, background_rebuild=True, swap_searches=1, search_threads=threads)
        found = []
        for frame, start in enumerate(range(0, 6000, 400)):
            trees.add(words[start:start + 400], np.arange(start, start + 400))
            if frame % 3 == 2:
                trees.remove(np.arange(start, start + 40))
            found.append(trees.search(queries[frame]))
        found.append(trees.search(queries[0][:kdtree.SEARCH_CHUNK]))  # one chunk: no helper
        trees.close()
        answers[threads] = found
    for threads in (2, 3):
        for (d1, i1), (dn, i_n) in zip(answers[1], answers[threads]):
            np.testing.assert_array_equal(i1, i_n)
            np.testing.assert_array_equal(d1, dn)
    with pytest.raises(ValueError, match="search_threads"):
        RandomizedKdTrees(32, search_threads=0)


def test_a_single_word_gives_one_neighbour(rng):
    trees = RandomizedKdTrees(32)
    distances, ids = trees.search(random_binary(rng, 2))
    assert (ids == -1).all()
    trees.add(random_binary(rng, 1), np.array([5]))
    distances, ids = trees.search(random_binary(rng, 3))
    assert (ids[:, 0] == 5).all() and (ids[:, 1] == -1).all() and np.isinf(distances[:, 1]).all()


def test_vocabulary_with_kdtree_quantises_a_revisit_into_its_words(rng):
    """vocabulary.index=kdtree (Kp/NNStrategy 1): an image seen again, a few bits changed, maps
    mostly to its words; the few it misses become new words."""
    vocabulary = Vocabulary(VocabularyParams(index="kdtree"), binary=True)
    first = random_binary(rng, 400)
    ids, is_new = vocabulary.quantize(first)
    assert is_new.all()
    for _ in range(5):  # other places in between
        vocabulary.quantize(random_binary(rng, 400))
    again, is_new = vocabulary.quantize(flip_bits(rng, first, 6))
    assert np.mean(again == ids) > 0.9
    assert is_new.sum() < 40
    vocabulary.remove_words(ids[:100])
    third, _ = vocabulary.quantize(first[:100])
    assert not np.isin(third, ids[:100]).any()


def test_vocabulary_kdtree_seed_changes_the_approximate_words_not_the_exact_ones(rng):
    """vocabulary.kdtree_seed seeds the trees (RTAB-Map's FLANN draws its own every run): the same
    seed gives the same words; another seed changes which of a far view's descriptors the search
    finds the word of (or makes a new word), while a view close to its place finds its words."""
    places = [random_binary(rng, 300) for _ in range(8)]
    revisit = flip_bits(rng, places[0], 4)
    far = flip_bits(rng, places[3], 40)

    def words(seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        vocabulary = Vocabulary(VocabularyParams(index="kdtree", kdtree_seed=seed), binary=True)
        first, _ = vocabulary.quantize(places[0])
        for place in places[1:]:
            vocabulary.quantize(place)
        again, _ = vocabulary.quantize(revisit)
        chance, _ = vocabulary.quantize(far)
        return first, again, chance

    first, again, chance = words(0)
    np.testing.assert_array_equal(np.concatenate(words(0)), np.concatenate([first, again, chance]))
    other_first, other_again, other_chance = words(1)
    assert np.mean(again == first) > 0.9 and np.mean(other_again == other_first) > 0.9
    assert not np.array_equal(chance, other_chance)


def test_kdtree_with_float_descriptors_uses_the_exact_search(rng, caplog):
    """SIFT (float descriptors) with the default kdtree: the exact search, said once in the log."""
    with caplog.at_level("INFO", logger="rtabmap_ros2.core.vocabulary"):
        vocabulary = Vocabulary(VocabularyParams(index="kdtree"), binary=False)
    assert not vocabulary.uses_kdtree
    assert any("exact search" in record.getMessage() for record in caplog.records)
    words = rng.standard_normal((50, 128)).astype(np.float32)
    ids, _ = vocabulary.quantize(words)
    again = vocabulary.match(words + np.float32(1e-3))
    np.testing.assert_array_equal(again, ids)


def test_rtabmap_nn_strategy_names_the_index():
    assert Params().with_value("Kp/NNStrategy", 1).vocabulary.index == "kdtree"
    assert Params().with_value("Kp/NNStrategy", 3).vocabulary.index == "flat"
    with pytest.raises(ParameterError, match="Kp/NNStrategy 2"):
        Params().with_value("Kp/NNStrategy", 2)


def test_background_rebuild_answers_as_a_rebuild_at_its_snapshot_then_the_same_changes(rng, monkeypatch):
    monkeypatch.setattr(kdtree, "SWAP_WORDS_PER_SEARCH", 10**9)  # the swap at swap_searches
    """The rebuild after the index doubled runs in a thread; the swap_searches-th search after it
    started swaps it in with the words added and removed meanwhile replayed. Until then the current
    trees answer; from then on the answers are those of a rebuild made right away, whatever the
    thread's timing (the swap counts searches, not time)."""
    words = random_binary(rng, 5000)
    queries = flip_bits(rng, words[::11], 12)
    later = random_binary(rng, 300)

    def run(background: bool) -> list:
        trees = RandomizedKdTrees(32, seed=3, background_rebuild=background, swap_searches=2)
        trees.add(words[:1000], np.arange(1000))
        trees.add(words[1000:2500], np.arange(1000, 2500))  # crosses 2x: a rebuild
        assert trees.rebuilding == background
        answers = [trees.search(queries)]
        trees.add(later, np.arange(10_000, 10_300))  # during the rebuild: replayed at the swap
        trees.remove(np.arange(0, 500, 5))
        answers.append(trees.search(queries))  # the second search after the start: swapped in
        assert not trees.rebuilding
        answers.append(trees.search(queries))
        return answers

    synchronous, background = run(False), run(True)
    # The last answers are the same; before the swap, the background run answered from the old trees.
    for k in (1, 2):
        np.testing.assert_array_equal(background[k][1], synchronous[k][1])
        np.testing.assert_array_equal(background[k][0], synchronous[k][0])
    assert not np.isin(background[2][1], np.arange(0, 500, 5)).any()


def test_a_large_rebuild_gets_more_searches_and_its_replay_is_spread(rng, monkeypatch):
    """Issue 50: the swap comes one search per SWAP_WORDS_PER_SEARCH words after the rebuild started
    (not before swap_searches), so the swap search need not wait for a long build; once the thread
    is done, each search replays at most REPLAY_WORDS_PER_SEARCH logged words, the rest at the swap."""
    monkeypatch.setattr(kdtree, "SWAP_WORDS_PER_SEARCH", 500)
    monkeypatch.setattr(kdtree, "REPLAY_WORDS_PER_SEARCH", 150)
    monkeypatch.setattr(kdtree, "IN_TIME_REBUILD_WORDS", 1000)
    words = random_binary(rng, 3000)
    trees = RandomizedKdTrees(32, seed=1, background_rebuild=True, swap_searches=2)
    trees.add(words[:1000], np.arange(1000))
    trees.add(words[1000:2500], np.arange(1000, 2500))  # 2,500 words: swapped 5 searches on
    rebuild = trees._rebuild
    assert rebuild.swap_at == trees._searches + 5
    rebuild.thread.join(30)
    for k in range(5):  # 100 words a search, logged
        trees.add(words[2500 + 100 * k: 2600 + 100 * k], np.arange(2500 + 100 * k, 2600 + 100 * k))
    trees.search(words[:3])  # replays two changes (200 words, the bound reached after the second)
    assert len(rebuild.log) == 3 and trees.rebuilding
    for _ in range(3):
        trees.search(words[:3])
    assert trees.rebuilding
    trees.search(words[:3])  # the fifth: swapped in, with every change
    assert not trees.rebuilding and trees.last_wait_seconds < 1.0
    _, found = trees.search(words)
    assert np.mean(found[:, 0] == np.arange(3000)) > 0.95



def test_a_small_rebuild_is_swapped_in_when_swap_searches_allow(rng, monkeypatch):
    """Issue 48: a rebuild of at most IN_TIME_REBUILD_WORDS words comes at the swap_searches-th search
    (detect's 1: the search of the frame that started it, as RTAB-Map rebuilds in the call that doubled
    its index), not one search per SWAP_WORDS_PER_SEARCH words later; a larger one still gets those."""
    monkeypatch.setattr(kdtree, "SWAP_WORDS_PER_SEARCH", 500)
    words = random_binary(rng, 2500)
    for limit, delay in ((2500, 1), (2000, 5)):
        monkeypatch.setattr(kdtree, "IN_TIME_REBUILD_WORDS", limit)
        trees = RandomizedKdTrees(32, seed=1, background_rebuild=True, swap_searches=1)
        trees.add(words[:1000], np.arange(1000))
        trees.add(words[1000:2500], np.arange(1000, 2500))  # 2,500 words: a rebuild
        assert trees._rebuild.swap_at == trees._searches + delay
        trees.search(words[:3])
        assert trees.rebuilding == (delay > 1)
