"""Bayes filter of the 2013 paper (§III-C, D): observation model, transition model, selection."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from rtabmap_ros2.core.bayes import (NEW_LOCATION, NO_STANDOUT_NEW_LIKELIHOOD, BayesFilter, TransitionModel,
                                     likelihood)
from rtabmap_ros2.core.graph import Graph, Link, LinkType
from rtabmap_ros2.core.params import BayesParams


def chain(ids, loops=()) -> Graph:
    """Neighbour links between consecutive ids, plus loop closure links (a, b)."""
    graph = Graph([Link(a, b, LinkType.NEIGHBOR) for a, b in zip(ids[:-1], ids[1:])]
                  + [Link(a, b, LinkType.LOOP_INTRA) for a, b in loops])
    for node in ids:
        graph.add_node(node)
    return graph


def test_likelihood_matches_rtabmap_adjust_likelihood_by_hand():
    # Non-null scores 0.1, 0.2, 0.6: mu = 0.3, sigma the sample std (n - 1) = sqrt(0.14 / 2).
    out = likelihood({1: 0.1, 2: 0.2, 3: 0.6, 4: 0.0})
    mu, sigma = 0.3, math.sqrt(0.14 / 2)
    # Eq. 3: only s_j > mu + sigma (0.565) gets (s_j - (sigma - 1e-4)) / mu; others (and zeros) get 1.
    assert out[3] == pytest.approx((0.6 - (sigma - 1e-4)) / mu)
    assert out[1] == out[2] == out[4] == 1.0
    # Eq. 4: new location likelihood mu / sigma + 1.
    assert out[NEW_LOCATION] == pytest.approx(mu / sigma + 1.0)


def test_likelihood_of_equal_scores_has_no_spread():
    out = likelihood({1: 0.2, 2: 0.2, 3: 0.0})
    assert out[1] == out[2] == out[3] == 1.0  # sigma = 0: none stands out
    assert out[NEW_LOCATION] == 2.0


def test_likelihood_without_any_shared_word_favours_a_new_location():
    # RTAB-Map gives the new location 2 when no WM location shares a word with the image: with 1
    # (as before issue 32) the filter only diffused and its value drifted up towards 0.5.
    out = likelihood({1: 0.0, 2: 0.0})
    assert out == {1: 1.0, 2: 1.0, NEW_LOCATION: 2.0}


def test_uninformative_observations_with_spikes_stay_below_t_loop():
    """The filter's resting value when the likelihood says little (issue 32's sharp test): chance
    scores everywhere, now and then one location spiking once. RTAB-Map's value settles just under
    0.1 (0.9 virtual place prior, new-place likelihood ~2), below T_loop = 0.11."""
    rng = np.random.default_rng(3)
    ids = np.arange(1, 301)
    bayes = BayesFilter(BayesParams(virtual_place_prior=0.9, loop_threshold=0.11), chain(ids.tolist()))
    values = []
    for frame in range(200):
        scores = {int(i): 0.0 for i in ids}
        if frame % 2 == 0:  # every other frame shares chance words with 25 locations, the rest none
            for i in rng.choice(ids, 25, replace=False):
                scores[int(i)] = float(rng.uniform(0.005, 0.03))
        if frame % 10 == 0:  # and now and then one location spikes once
            scores[int(rng.choice(ids))] = 0.08
        bayes.update(ids, likelihood(scores))
        values.append(bayes.highest().probability)
    settled = np.array(values[50:])
    # (Before issue 32: median 0.14, 90th percentile 0.18, over T_loop.)
    assert np.median(settled) < 0.1
    assert settled.max() < 0.11


def test_prediction_from_new_location_uses_the_0_9_0_1_transitions():
    bayes = BayesFilter(BayesParams(virtual_place_prior=0.9), chain([1, 2, 3, 4, 5]))  # the paper's value
    belief = bayes.predict(np.array([1, 2, 3, 4, 5]))
    assert belief[0] == pytest.approx(0.9)  # p(S_t=-1 | S_t-1=-1)
    np.testing.assert_allclose(belief[1:], 0.1 / 5)  # the rest spread uniformly over WM
    assert belief.sum() == pytest.approx(1.0)


def test_prediction_from_a_location_keeps_mass_and_peaks_on_it():
    ids = np.arange(1, 41)
    bayes = BayesFilter(BayesParams(virtual_place_prior=0.9), chain(ids.tolist()))
    bayes.posterior = {NEW_LOCATION: 0.2, 20: 0.5, 30: 0.3}
    belief = bayes.predict(ids)
    assert belief.sum() == pytest.approx(1.0)
    # p(S_t=-1) = 0.9 * 0.2 + 0.1 * (0.5 + 0.3)
    assert belief[0] == pytest.approx(0.9 * 0.2 + 0.1 * 0.8)
    # Location 20 (col 20) peaks, its Gaussian falls off with hops: hop 1 / hop 0 = exp(-1/(2 sigma^2)).
    around = belief[1:]
    assert around.argmax() == 19
    uniform = 0.1 * 0.2 / len(ids)
    ratio = (around[20] - uniform) / (around[19] - uniform)
    assert ratio == pytest.approx(math.exp(-0.5 / 1.6 ** 2), rel=1e-6)
    # Beyond the 16-hop neighbourhood of both 20 and 30 only the uniform part is left.
    assert around[0] == pytest.approx(uniform)


def test_neighbourhood_reaches_through_a_node_not_in_wm():
    # 1 - 2 - 3 and a loop closure 3 - 10; 2 and 3 are in LTM (not hypotheses this frame).
    graph = chain([1, 2, 3], loops=[(3, 10)])
    graph.add_node(10)
    bayes = BayesFilter(BayesParams(), graph)
    bayes.posterior = {NEW_LOCATION: 0.0, 1: 1.0}
    wm = np.array([1, 10, 11])
    belief = bayes.predict(wm)
    # 10 is 2 hops away through 2 and 3: the loop closure link is crossed without a hop (RTAB-Map's).
    assert belief[2] > 0.0
    assert belief[3] == 0.0  # 11 is not linked to 1
    # The 0.9 of location 1 is shared by 1 and 10 only (normalised over WM neighbours).
    assert belief[1] + belief[2] == pytest.approx(0.9)
    assert belief[1] / belief[2] == pytest.approx(1.0 / math.exp(-0.5 * (2 / 1.6) ** 2))


def test_without_a_loop_closure_hop_a_place_and_its_revisit_share_the_belief_equally():
    """As RTAB-Map's (Memory::getNeighborsId, incrementMarginOnLoop false): a location and the one it
    closed a loop with are the same place, so the belief carried from it is shared equally by both
    visits' chains."""
    # First visit 1..20, second visit 101..120; 110 closed a loop with 10.
    ids = list(range(1, 21)) + list(range(101, 121))
    graph = Graph([Link(a, b, LinkType.NEIGHBOR) for a, b in zip(range(1, 20), range(2, 21))]
                  + [Link(a, b, LinkType.NEIGHBOR) for a, b in zip(range(101, 120), range(102, 121))]
                  + [Link(110, 10, LinkType.LOOP_INTRA)])
    wm = np.array(ids)
    bayes = BayesFilter(BayesParams(), graph)
    bayes.posterior = {NEW_LOCATION: 0.0, 10: 1.0}
    belief = bayes.predict(wm)
    assert belief[0] == pytest.approx(0.1) and belief.sum() == pytest.approx(1.0)
    same = dict(zip(ids, belief[1:]))
    assert same[110] == pytest.approx(same[10]) and same[111] == pytest.approx(same[11])
    assert same[109] == pytest.approx(same[9])
    # One hop along either visit weighs the Gaussian's first step.
    assert same[11] == pytest.approx(same[10] * math.exp(-0.5 / 1.6 ** 2))


def test_repeated_strong_observation_drives_the_posterior_up_until_accepted():
    ids = np.arange(1, 31)
    bayes = BayesFilter(BayesParams(), chain(ids.tolist()))
    scores = {int(i): 0.05 for i in ids}
    scores[12] = 0.6  # the current images keep looking like location 12
    values = []
    for _ in range(5):
        bayes.update(ids, likelihood(scores))
        hypothesis = bayes.highest()
        values.append(hypothesis.probability)
        assert hypothesis.location_id == 12
    assert all(b > a for a, b in zip(values, values[1:]))
    assert not bayes.accepted(type(hypothesis)(12, 0.05, 0.95), values[-2])  # below T_loop
    assert bayes.accepted(bayes.highest(), values[-2])
    assert sum(bayes.posterior.values()) == pytest.approx(1.0)


def test_uniform_observations_keep_the_new_location_hypothesis():
    ids = np.arange(1, 31)
    bayes = BayesFilter(BayesParams(), chain(ids.tolist()))
    for _ in range(5):
        bayes.update(ids, likelihood({int(i): 0.05 for i in ids}))
    assert bayes.posterior[NEW_LOCATION] > 0.5
    assert not bayes.accepted(bayes.highest())


def test_loop_ratio_rejects_a_falling_or_lone_hypothesis():
    """Rtabmap/LoopRatio (0.9): the value must reach 0.9 x the previous frame's, which must not be 0."""
    ids = np.arange(1, 31)
    bayes = BayesFilter(BayesParams(loop_ratio=0.9), chain(ids.tolist()))
    scores = {int(i): 0.05 for i in ids}
    scores[12] = 0.6
    for _ in range(5):
        bayes.update(ids, likelihood(scores))
    best = bayes.highest()
    assert best.probability >= 0.11
    assert bayes.accepted(best, best.probability / 0.9)
    assert not bayes.accepted(best, best.probability / 0.85)  # fell by more than 10 %
    assert not bayes.accepted(best, 0.0)  # the previous frame had no hypothesis
    off = BayesFilter(BayesParams(loop_ratio=0.0), chain(ids.tolist()))
    off.posterior = dict(bayes.posterior)
    assert off.accepted(best, 0.0) and off.accepted(best, 1.0)


def test_single_hypothesis_is_never_accepted():
    bayes = BayesFilter(BayesParams(loop_threshold=0.0), chain([1]))
    bayes.update(np.array([1]), {NEW_LOCATION: 0.1, 1: 10.0})
    assert bayes.highest().location_id == 1
    assert not bayes.accepted(bayes.highest())


def test_an_exact_tie_of_the_posterior_names_the_newest_location():
    # Two identical images far apart (a place seen twice with nothing to tell them apart) end with
    # the same posterior: RTAB-Map walks the posterior from the highest id and keeps the first
    # strictly greater value, so the newest of them is the hypothesis, whatever the dict's order.
    bayes = BayesFilter(BayesParams(), chain(list(range(1, 21))))
    for ids in (range(1, 21), range(20, 0, -1)):
        bayes.posterior = {NEW_LOCATION: 0.2, **{i: 0.3 if i in (3, 17) else 0.01 for i in ids}}
        assert bayes.highest().location_id == 17


def test_prediction_spreads_the_peak_and_pools_the_uniform_floor():
    # Every location has a floor of belief and location 20 a peak: mass is kept, the floor stays
    # uniform, the peak keeps its Gaussian shape on top of it.
    ids = np.arange(1, 41)
    graph = chain(ids.tolist(), loops=[(5, 35)])
    bayes = BayesFilter(BayesParams(), graph)
    floor = 0.5 / len(ids)
    bayes.posterior = {NEW_LOCATION: 0.2, **{int(i): floor for i in ids}}
    bayes.posterior[20] += 0.3
    belief = bayes.predict(ids)
    assert belief.sum() == pytest.approx(1.0)
    around = belief[1:]
    assert around.argmax() == 19
    base = around[0]  # far from the peak: floor and the uniform transition from S_t-1 = -1 only
    np.testing.assert_allclose(around[30:], base)
    ratio = (around[19] - base) / (around[20] - base)
    assert ratio == pytest.approx(math.exp(0.5 / 1.6 ** 2), rel=1e-6)


def test_forgotten_nodes_lose_their_cached_neighbourhood():
    graph = Graph([Link(i, i + 1, LinkType.NEIGHBOR) for i in range(1, 20)])
    model = TransitionModel(BayesParams(), graph)
    for node in (3, 4, 5):
        model.neighbourhood(node)
    model.forget([3, 4])
    assert set(model._cache) == {5}
