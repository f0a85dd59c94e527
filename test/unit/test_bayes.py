"""Bayes filter of the 2013 paper (§III-C, D): observation model, transition model, selection."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from rtabmap_ros2.core.bayes import (NEW_LOCATION, NO_STANDOUT_NEW_LIKELIHOOD, BayesFilter, Hypothesis, TransitionModel,
                                     discounted, likelihood)
from rtabmap_ros2.core.graph import Graph, Link, LinkType
from rtabmap_ros2.core.params import BayesParams
from rtabmap_ros2.core.signature import Signature, aligned_words


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


def test_trimmed_likelihood_lets_a_revisited_place_stand_out_of_its_neighbours():
    """A revisit with an exact vocabulary search: the place and its graph neighbours share many words
    with the image, chance matches are few. Their scores make up most of the non-zero ones: RTAB-Map's
    mu and sigma rise with them and the place barely beats a new one; leaving the highest half out
    measures the chance level instead."""
    scores = {j: 0.0 for j in range(1, 201)}
    scores.update({100: 0.66, 99: 0.5, 101: 0.45, 98: 0.3, 102: 0.3, 97: 0.2, 103: 0.15})
    scores.update({j: 0.01 for j in (5, 20, 40, 60, 150, 170, 190)})
    plain, trimmed = likelihood(scores), likelihood(scores, trim=0.5)
    assert plain[100] / plain[NEW_LOCATION] < 2.0
    assert trimmed[100] / trimmed[NEW_LOCATION] > 10 * plain[100] / plain[NEW_LOCATION]
    assert trimmed[5] == 1.0  # chance scores still do not stand out
    # Nothing to trim below three scores; the same values as RTAB-Map's then.
    assert likelihood({1: 0.2, 2: 0.4}, trim=0.5) == likelihood({1: 0.2, 2: 0.4})


@pytest.mark.parametrize("trim", [0.0, 0.5])
def test_uninformative_observations_with_spikes_stay_below_t_loop(trim):
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
        bayes.update(ids, likelihood(scores, trim))
        values.append(bayes.highest().probability)
    settled = np.array(values[50:])
    # (Before issue 32: median 0.14, 90th percentile 0.18, over T_loop.)
    assert np.median(settled) < 0.1
    assert settled.max() < 0.11


def test_discounted_likelihood_leans_towards_no_information():
    like = np.array([8.0, 4.0, 1.0])  # the new location's, then locations 1 and 2
    assert discounted(like, 1.0) is like
    half = discounted(like, 0.5)
    assert half[1] == pytest.approx(2.0) and half[2] == 1.0
    assert half[0] == pytest.approx(NO_STANDOUT_NEW_LIKELIHOOD * 2.0)  # 2 (8 / 2) ** 0.5
    nothing = discounted(like, 0.0)  # a frame identical to the previous one: no information
    assert nothing.tolist() == [NO_STANDOUT_NEW_LIKELIHOOD, 1.0, 1.0]


def _stop_in_front_of(location: int, weight: float, frames: int = 10) -> list[float]:
    """A camera standing still in front of a place that resembles ``location``: every frame the same
    chance scores plus the same match, each counted as ``weight`` of an observation."""
    rng = np.random.default_rng(5)
    ids = np.arange(1, 201)
    bayes = BayesFilter(BayesParams(loop_threshold=0.11), chain(ids.tolist()))
    scores = {int(i): 0.0 for i in ids}
    for i in rng.choice(ids, 40, replace=False):
        scores[int(i)] = float(rng.uniform(0.005, 0.03))
    scores[location] = 0.3
    values = []
    for _ in range(frames):
        bayes.update(ids, likelihood(scores, 0.5), weight)
        values.append(bayes.highest().probability)
    return values


def test_repeated_frames_of_a_stopped_camera_do_not_compound_into_a_loop_closure():
    """bayes.discount_repeated_evidence: ten frames of a stopped camera (rehearsal similarity 0.7
    with the previous frame: weight 0.3) repeat one weak match; counted as ten observations it
    passes T_loop (the runs of false loop closures at sim/sequence.py's stops), counted as 0.3 each
    it stays at the no-information level."""
    independent = _stop_in_front_of(100, 1.0)
    assert max(independent) > 0.11  # T_loop
    discounted_values = _stop_in_front_of(100, 0.3)
    assert max(discounted_values) < 0.11  # T_loop
    # A frame that shares nothing with the previous one (weight 1) is a whole observation, as in RTAB-Map.
    ids = np.arange(1, 31)
    scores = {int(i): 0.05 for i in ids}
    scores[12] = 0.6
    plain, weighted = BayesFilter(BayesParams(), chain(ids.tolist())), BayesFilter(BayesParams(), chain(ids.tolist()))
    plain.update(ids, likelihood(scores))
    weighted.update(ids, likelihood(scores), 1.0)
    assert weighted.posterior == plain.posterior


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
    assert belief[2] > 0.0  # 10 is 3 hops away through 2 and 3
    assert belief[3] == 0.0  # 11 is not linked to 1
    # The 0.9 of location 1 is shared by 1 and 10 only (normalised over WM neighbours).
    assert belief[1] + belief[2] == pytest.approx(0.9)
    assert belief[1] / belief[2] == pytest.approx(1.0 / math.exp(-0.5 * (3 / 1.6) ** 2))


def test_without_a_loop_closure_hop_a_place_and_its_revisit_share_the_belief_equally():
    """bayes.loop_closure_hop false (RTAB-Map's): a location and the one it closed a loop with are
    the same place, so the belief carried from it is shared equally by both visits' chains."""
    # First visit 1..20, second visit 101..120; 110 closed a loop with 10.
    ids = list(range(1, 21)) + list(range(101, 121))
    graph = Graph([Link(a, b, LinkType.NEIGHBOR) for a, b in zip(range(1, 20), range(2, 21))]
                  + [Link(a, b, LinkType.NEIGHBOR) for a, b in zip(range(101, 120), range(102, 121))]
                  + [Link(110, 10, LinkType.LOOP_INTRA)])
    wm = np.array(ids)
    beliefs = {}
    for hop in (True, False):
        bayes = BayesFilter(BayesParams(loop_closure_hop=hop), graph)
        bayes.posterior = {NEW_LOCATION: 0.0, 10: 1.0}
        belief = bayes.predict(wm)
        beliefs[hop] = dict(zip(ids, belief[1:]))
        assert belief[0] == pytest.approx(0.1) and belief.sum() == pytest.approx(1.0)
    same = beliefs[False]
    assert same[110] == pytest.approx(same[10]) and same[111] == pytest.approx(same[11])
    assert same[109] == pytest.approx(same[9])
    hop = beliefs[True]
    assert hop[110] == pytest.approx(hop[10] * math.exp(-0.5 / 1.6 ** 2))
    # The first visit keeps less of the belief at the place itself: it shares it with the second.
    assert same[10] < hop[10]


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


def test_a_hypothesis_needs_this_frames_evidence_when_asked():
    """bayes.min_evidence_ratio: the belief carried from earlier frames is not enough, the current
    likelihood of the place (or of a graph neighbour) must reach the new location's."""
    ids = np.arange(1, 31)
    graph = chain(ids.tolist())
    bayes = BayesFilter(BayesParams(min_evidence_ratio=1.0), graph)
    scores = {int(i): 0.01 for i in ids}
    scores.update({11: 0.3, 12: 0.6, 13: 0.3})
    for _ in range(10):
        bayes.update(ids, likelihood(scores, trim=0.5))
    best = bayes.highest()
    assert best.location_id == 12 and best.probability > 0.9 and bayes.accepted(best)
    assert bayes.supported_by_observation(12) and bayes.supported_by_observation(13)  # 13: a neighbour
    assert not bayes.supported_by_observation(20)
    # The revisit ends: the image shares nothing with the place, its belief lingers over T_loop.
    bayes.update(ids, likelihood({int(i): 0.0 for i in ids}))
    stale = bayes.highest()
    assert stale.location_id in (11, 12, 13) and bayes.accepted(stale)
    assert not bayes.supported_by_observation(stale.location_id)
    off = BayesFilter(BayesParams(), graph)
    off.observation = dict(bayes.observation)
    assert off.supported_by_observation(stale.location_id)  # 0: RTAB-Map's behaviour


def test_a_hypothesis_the_image_argues_against_is_not_accepted():
    """bayes.min_evidence_ratio at its default: a revisit ends on a jump to another place; the
    belief lingers over T_loop on the old place, and this image's words stand out on other
    locations (25-27) but not on it nor its neighbours: not accepted, even though the new
    location's likelihood is low enough for the ratio alone to pass. An image that favours no
    place at all (one word shared by chance) leaves the carried belief be."""
    ids = np.arange(1, 61)
    graph = chain(ids.tolist())

    def revisit() -> BayesFilter:
        bayes = BayesFilter(BayesParams(min_evidence_ratio=0.5), graph)
        scores = {int(i): 0.01 for i in ids}
        scores.update({11: 0.3, 12: 0.6, 13: 0.3})
        for _ in range(10):
            bayes.update(ids, likelihood(scores, trim=0.5))
        return bayes

    bayes = revisit()
    jump = {int(i): 0.0 for i in ids}
    jump.update({j: 0.004 for j in (3, 5, 40, 50)})
    jump.update({25: 0.006, 26: 0.007, 27: 0.006})
    bayes.update(ids, likelihood(jump, trim=0.5))
    stale = bayes.highest()
    assert stale.location_id in (11, 12, 13) and bayes.accepted(stale)
    assert bayes.observation[26] > 1.0 and bayes.observation[NEW_LOCATION] <= 2.0
    assert all(bayes.observation[n] == 1.0 for n in (10, 11, 12, 13, 14))
    assert not bayes.supported_by_observation(stale.location_id)

    bayes = revisit()
    bayes.update(ids, likelihood({**{int(i): 0.0 for i in ids}, 30: 0.005}, trim=0.5))
    carried = bayes.highest()
    assert bayes.observation[NEW_LOCATION] == NO_STANDOUT_NEW_LIKELIHOOD
    assert carried.location_id in (11, 12, 13) and bayes.supported_by_observation(carried.location_id)


def test_refined_hypothesis_follows_a_revisit_faster_than_the_first_pass():
    """The image shows location 17 now (its neighbours 16 and 18 overlap it), the belief still
    peaks on 14 (the previous frames showed it): the posterior's peak lags; refine_hops moves the
    hypothesis along the trajectory to where this frame's likelihood, over a location and its two
    neighbours, is highest."""
    ids = np.arange(1, 61)
    for refine, expected in ((0, 14), (8, 17)):
        bayes = BayesFilter(BayesParams(refine_hops=refine), chain(ids.tolist()))
        bayes.posterior = {NEW_LOCATION: 0.01, 13: 0.2, 14: 0.6, 15: 0.19}
        scores = {int(i): 0.0 for i in ids}
        scores.update({j: 0.05 for j in (3, 30, 45, 50, 55, 58)})
        scores.update({14: 0.1, 15: 0.1, 16: 0.12, 17: 0.15, 18: 0.12})
        bayes.update(ids, likelihood(scores, trim=0.5))
        assert bayes.highest().location_id == expected


def test_refinement_ignores_a_lone_spike_and_other_visits():
    """One location's likelihood is noisy: a single spike a few hops away, without its
    neighbours, does not move the hypothesis off a place the image matches over three
    locations; nor does a place reached only through a loop closure link (another visit), nor
    one beyond the reach."""
    ids = np.arange(1, 61)
    bayes = BayesFilter(BayesParams(refine_hops=8), chain(ids.tolist(), loops=[(10, 40)]))
    bayes.posterior = {NEW_LOCATION: 0.05, 13: 0.2, 14: 0.55, 15: 0.2}
    scores = {int(i): 0.0 for i in ids}
    scores.update({j: 0.01 for j in (3, 5, 7, 9, 50, 52)})
    scores.update({13: 0.2, 14: 0.22, 15: 0.2, 18: 0.3, 40: 0.5, 41: 0.4, 39: 0.4})
    bayes.update(ids, likelihood(scores, trim=0.5))
    assert bayes.observation[18] > bayes.observation[14] and bayes.observation[40] > bayes.observation[18]
    assert bayes.highest().location_id == 14
    # Without the window (refine_window 0, SLAM's) the spike's own likelihood wins.
    single = BayesFilter(BayesParams(refine_hops=8, refine_window=0), chain(ids.tolist(), loops=[(10, 40)]))
    single.posterior = {NEW_LOCATION: 0.05, 13: 0.2, 14: 0.55, 15: 0.2}
    single.update(ids, likelihood(scores, trim=0.5))
    assert single.highest().location_id == 18
    # The same spike with its neighbours: the image shows 18.
    scores.update({17: 0.25, 19: 0.25})
    bayes.posterior = {NEW_LOCATION: 0.05, 13: 0.2, 14: 0.55, 15: 0.2}
    bayes.update(ids, likelihood(scores, trim=0.5))
    assert bayes.highest().location_id == 18
    # Beyond the reach, along the trajectory: it stays.
    bayes = BayesFilter(BayesParams(refine_hops=3), chain(ids.tolist()))
    bayes.posterior = {NEW_LOCATION: 0.05, 14: 0.95}
    far = {int(i): 0.0 for i in ids}
    far.update({j: 0.01 for j in (3, 5, 7, 9)})
    far.update({19: 0.5, 20: 0.5, 21: 0.5})
    bayes.update(ids, likelihood(far, trim=0.5))
    assert bayes.observation[20] > 1.0 and bayes.highest().location_id == 14


def _view(node: int, words: np.ndarray, xs: np.ndarray) -> Signature:
    """A location whose image shows ``words`` at columns ``xs`` (rows spread over the image, the
    same for a word in every view)."""
    rows = 20.0 + (words * 37 % 440).astype(float)
    return Signature(id=node, map_id=0, stamp_ns=node, word_ids=words.astype(np.int64),
                     keypoints=np.stack([xs, rows], axis=1).astype(np.float32))


def test_view_alignment_moves_the_hypothesis_to_the_view_showing_the_words_in_place():
    """The image shares more words with location 14 (a view 300 px further along the street),
    but they sit 300 px to the left in 14's image; location 11, three locations back, shows 40
    of them at the same place: the hypothesis moves to 11. Not to 30, as well aligned but reached
    only through a loop closure (another visit), nor with align_radius 0. A view with only a
    handful of words in place does not move it (fewer than 7 agree by chance)."""
    ids = np.arange(1, 41)
    rng = np.random.default_rng(3)
    words = np.arange(100, 160)
    xs = rng.uniform(20, 620, len(words))
    query = _view(0, words, xs)
    signatures = {
        14: _view(14, words, xs + 300.0),                              # all 60 shared, displaced
        11: _view(11, words[:40], xs[:40] + rng.normal(0, 3, 40)),     # 40 in place
        30: _view(30, words, xs),                                     # another visit, in place
    }
    for params, graph, expected in ((BayesParams(align_radius=0.1), chain(ids.tolist(), loops=[(14, 30)]), 11),
                                    (BayesParams(align_radius=0.0), chain(ids.tolist()), 14)):
        bayes = BayesFilter(params, graph, kept=set(ids.tolist()))
        bayes.posterior = {NEW_LOCATION: 0.1, 11: 0.1, 14: 0.7, 30: 0.1}
        hypothesis = Hypothesis(14, 0.9, 0.1)
        assert bayes.aligned(hypothesis, query, signatures) == replace(hypothesis, location_id=expected)
    # A handful in place against none: chance, it stays.
    signatures[11] = _view(11, words[:5], xs[:5])
    bayes = BayesFilter(BayesParams(align_radius=0.1), chain(ids.tolist()), kept=set(ids.tolist()))
    bayes.posterior = {NEW_LOCATION: 0.1, 11: 0.1, 14: 0.8}
    assert bayes.aligned(Hypothesis(14, 0.9, 0.1), query, signatures).location_id == 14
    five, displaced = aligned_words(query, [signatures[11], signatures[14]], 60.0)
    assert five == pytest.approx(5.0) and displaced == pytest.approx(60 * (1 - 300 / np.ptp(xs)), rel=1e-4)


def test_single_hypothesis_is_never_accepted():
    bayes = BayesFilter(BayesParams(loop_threshold=0.0), chain([1]))
    bayes.update(np.array([1]), {NEW_LOCATION: 0.1, 1: 10.0})
    assert bayes.highest().location_id == 1
    assert not bayes.accepted(bayes.highest())


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
