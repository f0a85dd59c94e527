"""Discrete Bayes filter over loop closure hypotheses (2013 §III-C) and hypothesis selection (§III-D).

States: ``S_t = -1`` (:data:`NEW_LOCATION`, the current location is new) and ``S_t = j`` for every
location j in WM. Eq. 2: ``p(S_t | L^t) = η p(L_t | S_t) Σ_i p(S_t | S_t-1 = i) p(S_t-1 = i | L^t-1)``.

The transition model spreads the belief of a location j over its graph neighbourhood (neighbour
and loop closure links, hops counted through nodes that are not in WM too; a loop closure link
crossed without a hop with ``bayes.loop_closure_hop`` false, as RTAB-Map does) with a discretised
Gaussian of hop distance, restricted to WM and normalised to ``loop_closure_prior`` (0.9).
Neighbourhoods are cached per location and recomputed for the nodes at a graph change, so the
prediction is a handful of numpy operations per frame rather than an N x N matrix.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Container, Mapping, Optional

import numpy as np

from rtabmap_ros2.core.graph import Graph, LinkType
from rtabmap_ros2.core.params import BayesParams
from rtabmap_ros2.core.signature import Signature, aligned_words

NEW_LOCATION = -1
_EPSILON = 1e-9
# Rtabmap::adjustLikelihood's epsilon: sigma below it counts as no spread.
LIKELIHOOD_EPSILON = 1e-4
# The new location's likelihood when no score stands out (or none is above 0): RTAB-Map's 2.
NO_STANDOUT_NEW_LIKELIHOOD = 2.0
# Non-zero scores always kept for mu and sigma when the highest are trimmed (likelihood's trim).
MIN_CHANCE_SCORES = 2
# Transition weights (relative to the centre's 1) below this are dropped from neighbourhoods.
NEGLIGIBLE_TRANSITION = 1e-6
# The links of a trajectory: the hypothesis refinement walks them (not loop closures).
TRAJECTORY = (LinkType.NEIGHBOR,)
LOOP_CLOSURES = tuple(t for t in LinkType if t.is_loop_closure)
# The view alignment moves a hypothesis only to a view scoring at least this many aligned words: 7 heads in
# 7 tosses (a sign test against a view no better aligned than chance) happen less than 1 % of the time.
MIN_ALIGNED_WORDS = 7
# A column of the prior whose excess over the median is below this fraction of the largest
# excess is not spread over its neighbourhood (see BayesFilter.predict).
NEGLIGIBLE_EXCESS = 1e-3


@dataclass(frozen=True)
class Hypothesis:
    """The highest loop closure hypothesis of a frame."""

    location_id: int  # the most probable location, 0 when there is none
    probability: float  # 1 - p(S_t = -1): the value compared with T_loop
    new_location_probability: float


def likelihood(scores: dict[int, float], trim: float = 0.0) -> dict[int, float]:
    """Observation model (Eq. 3 and 4) from the raw score of every WM location.

    As RTAB-Map's ``Rtabmap::adjustLikelihood`` (the paper's Eq. 3-4 with its implementation's
    details, each of which moved precision and recall on real images, issue 32): mu and sigma
    over the non-zero scores, sigma the *sample* standard deviation (n - 1; 0 for one score);
    a location stands out when its score is strictly above mu + sigma, and its likelihood is then
    ``(s - (sigma - 1e-4)) / mu``; every other location gets 1. The new location gets
    ``mu / sigma + 1`` when sigma > 1e-4 and some location stood out, else 2 (no location shares a
    word with the image, or none stands out: a new place is then twice as likely as any).

    ``trim`` (not in RTAB-Map, ``bayes.likelihood_trim``): mu and sigma leave out this fraction of
    the highest non-zero scores (at least two are kept). They stand for the chance level of the
    scores; the highest ones are the candidates themselves (a revisited place and its graph
    neighbours), which, with an exact vocabulary search (few chance matches), make up much of the
    non-zero scores and raise mu and sigma until the right place no longer stands out.

    Args:
        scores: location id -> raw score (Eq. 1 similarity or tf-idf) for every location in WM,
            zeros included.
        trim: fraction in [0, 1) of the highest non-zero scores left out of mu and sigma.

    Returns:
        location id -> likelihood, plus :data:`NEW_LOCATION` -> likelihood of a new location.
    """
    values = np.fromiter(scores.values(), dtype=float, count=len(scores))
    non_null = values[values > 0]
    if trim > 0.0 and non_null.size > MIN_CHANCE_SCORES:
        kept = max(MIN_CHANCE_SCORES, int(round(non_null.size * (1.0 - trim))))
        non_null = np.partition(non_null, kept - 1)[:kept]
    out = dict.fromkeys(scores, 1.0)
    mu = float(non_null.mean()) if non_null.size else 0.0
    sigma = float(non_null.std(ddof=1)) if non_null.size > 1 else 0.0
    stood_out = False
    if mu > 0.0:
        # Eq. 3: only locations scoring above mu + sigma raise their likelihood above 1.
        for loc, s in scores.items():
            if s > mu + sigma:
                out[loc] = (s - (sigma - LIKELIHOOD_EPSILON)) / mu
                stood_out = True
    # Eq. 4: a new location is likely when no score stands out (sigma small relative to mu).
    out[NEW_LOCATION] = mu / sigma + 1.0 if sigma > LIKELIHOOD_EPSILON and stood_out else NO_STANDOUT_NEW_LIKELIHOOD
    return out


def discounted(like: np.ndarray, weight: float) -> np.ndarray:
    """The likelihood of a frame that repeats the previous one, counted as ``weight`` of an observation.

    Not in RTAB-Map (``bayes.discount_repeated_evidence``). Eq. 2 multiplies the belief by every
    frame's likelihood as if each were independent evidence; a camera standing still, or creeping,
    sends the same image again and again, and a weak chance match on it (an aliased texture, a
    poster) compounds frame after frame until it passes T_loop (runs of 5-10 false loop closures on
    sim/sequence.py stops, bench/bench_lcd.py --ablation). With ``weight`` = 1 - s, s the frame's
    rehearsal similarity (Eq. 1) with the previous one, only the new information of the frame
    counts: every location's likelihood becomes ``v ** weight``, and the new location's is tempered
    the same way relative to :data:`NO_STANDOUT_NEW_LIKELIHOOD`, the value of an image that favours
    no place (``2 (v / 2) ** weight``), so that a repeated frame leans towards "no information", not
    towards a loop closure.

    Args:
        like: (N + 1,) likelihood, the new location's first, then one per hypothesis (the layout of
            :meth:`BayesFilter.update`).
        weight: in [0, 1]; 1 returns ``like`` itself.
    """
    if weight >= 1.0:
        return like
    weight = max(weight, 0.0)
    out = like ** weight
    new = NO_STANDOUT_NEW_LIKELIHOOD
    out[0] = new * (like[0] / new) ** weight
    return out


class TransitionModel:
    """Cached Gaussian neighbourhoods of the transition model p(S_t = i | S_t-1 = j) (§III-C, 4)."""

    def __init__(self, params: BayesParams, graph: Graph,
                 kept: Optional[Container[int]] = None) -> None:
        """``graph``: anything with ``hops_from`` and ``neighbors`` (a Graph, or the Memory: its
        whole graph, LTM links read from the database); ``kept``: which reached nodes a cached
        neighbourhood keeps (the ones in memory: the others are not hypotheses, and the
        neighbourhoods of a small-world graph would otherwise grow with LTM)."""
        self._graph = graph
        self._kept = kept
        self._cache: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        # RTAB-Map's neighbourhoods (bayes.loop_closure_hop false): loop closures link one place.
        self._free = () if params.loop_closure_hop else LOOP_CLOSURES
        hops = np.arange(params.neighborhood + 1)
        gaussian = np.exp(-0.5 * (hops / params.sigma) ** 2)
        # Hops whose weight is negligible are not searched (with sigma 1.6: beyond 8 of the 16),
        # which matters once loop closures make the graph small-world.
        self._radius = int(np.flatnonzero(gaussian >= NEGLIGIBLE_TRANSITION)[-1])
        self._gaussian = gaussian[: self._radius + 1]

    def invalidate_around(self, *node_ids: int) -> None:
        """Forget the neighbourhoods of the nodes at a link change and of their direct neighbours.

        Nodes farther away keep their cached neighbourhood until they are recomputed, as
        RTAB-Map's filter only updates the prediction of changed ids: forgetting every node
        within reach made each loop closure recompute most of WM once the graph is small-world
        (the Bayes step took 800 ms at 1,300 locations on the revisiting sequence).
        """
        for node in node_ids:
            self._cache.pop(node, None)
            for other in self._graph.neighbors(node):
                self._cache.pop(other, None)

    def forget(self, node_ids) -> None:
        """Drop the cached neighbourhoods of nodes that left WM: in a graph made small-world by
        loop closures one holds thousands of ids, and without this every node ever in WM kept
        its own."""
        for node in node_ids:
            self._cache.pop(node, None)

    def neighbourhood(self, node_id: int) -> tuple[np.ndarray, np.ndarray]:
        """(ids, unnormalised Gaussian weights) of the nodes whose transition weight is not negligible."""
        cached = self._cache.get(node_id)
        if cached is None:
            hops = self._graph.hops_from(node_id, self._radius, free=self._free)
            if self._kept is not None:
                hops = {n: d for n, d in hops.items() if n in self._kept}
            ids = np.fromiter(hops.keys(), dtype=np.int64, count=len(hops))
            dist = np.fromiter(hops.values(), dtype=np.int64, count=len(hops))
            cached = (ids, self._gaussian[dist])
            self._cache[node_id] = cached
        return cached


class BayesFilter:
    """The recursive filter; its support follows WM as locations enter and leave it."""

    def __init__(self, params: BayesParams, graph: Graph, kept: Optional[Container[int]] = None) -> None:
        """``kept``: the nodes in memory (see :class:`TransitionModel`); the hypothesis refinement
        walks through them only."""
        self.params = params
        self.transitions = TransitionModel(params, graph, kept)
        self._graph = graph
        self._kept = kept
        self.posterior: dict[int, float] = {NEW_LOCATION: 1.0}
        # The last update's likelihood (location id -> value, NEW_LOCATION included).
        self.observation: dict[int, float] = {}

    def reset(self) -> None:
        self.posterior = {NEW_LOCATION: 1.0}

    def predict(self, wm_ids: np.ndarray) -> np.ndarray:
        """Belief (Eq. 2, right part) over ``[NEW_LOCATION, *wm_ids]`` from the previous posterior.

        Args:
            wm_ids: (N,) int64 ids of the WM locations that are hypotheses this frame, sorted.
        """
        p = self.params
        n = len(wm_ids)
        prior_new = self.posterior.get(NEW_LOCATION, 0.0)
        prior = np.array([self.posterior.get(int(i), 0.0) for i in wm_ids])
        # Locations that left WM take their belief with them; renormalise what remains.
        total = prior_new + prior.sum()
        if total <= _EPSILON:
            prior_new, prior = 1.0, np.zeros(n)
        else:
            prior_new, prior = prior_new / total, prior / total
        belief = np.zeros(n + 1)
        # Transitions from S_t-1 = -1 (§III-C, 1 and 2).
        belief[0] = p.virtual_place_prior * prior_new
        if n:
            belief[1:] = (1.0 - p.virtual_place_prior) * prior_new / n
        # Transitions from S_t-1 = j (§III-C, 3 and 4).
        belief[0] += (1.0 - p.loop_closure_prior) * prior.sum()
        if not n:
            return belief
        # Columns whose belief is negligible are not spread over their neighbourhood: their mass
        # (and every column's floor, its prior up to the median) goes uniformly over WM, the
        # limit of a Gaussian spread once loop closures make the graph small-world and a
        # neighbourhood covers most of it. Spreading every column cost O(WM x graph) per frame
        # (the Bayes step took 1.4 s at 3,200 locations); on the 3,000-image sequence this keeps
        # precision / recall (39.9 / 98.2 % vs 39.5 / 97.4 %) and recall at 100 % precision
        # (26.1 % vs 28.5 %) at 0.6 x the median pTime (bench/bench_detect.py).
        floor = np.minimum(prior, np.median(prior))
        excess = prior - floor
        spreads = excess > max(NEGLIGIBLE_EXCESS * excess.max(), _EPSILON)
        belief[1:] += p.loop_closure_prior * np.where(spreads, floor, prior).sum() / n
        active = np.flatnonzero(spreads)
        if active.size:
            hoods = [self.transitions.neighbourhood(int(wm_ids[col])) for col in active]
            ids = np.concatenate([h[0] for h in hoods])
            weights = np.concatenate([h[1] for h in hoods])
            cols = np.repeat(active, [h[0].size for h in hoods])
            # Keep the neighbours that are WM hypotheses, then normalise each column to 0.9.
            column_of = np.full(max(int(ids.max()), int(wm_ids[-1])) + 1, -1, dtype=np.int64)
            column_of[wm_ids] = np.arange(n)
            pos = column_of[ids]
            in_wm = pos >= 0
            pos, weights, cols = pos[in_wm], weights[in_wm], cols[in_wm]
            column_sums = np.bincount(cols, weights=weights, minlength=n)
            spread = p.loop_closure_prior * weights / column_sums[cols] * excess[cols]
            belief[1:] += np.bincount(pos, weights=spread, minlength=n)
        return belief

    def update(self, wm_ids: np.ndarray, observation: dict[int, float], weight: float = 1.0) -> dict[int, float]:
        """One filter step: predict, weight by the likelihood, normalise (Eq. 2).

        Args:
            wm_ids: (N,) int64 sorted ids of the WM locations that are hypotheses.
            observation: likelihood per id and for :data:`NEW_LOCATION` (see :func:`likelihood`).
            weight: how much of a new observation the frame is (see :func:`discounted`); the
                hypothesis refinement and the evidence check read ``observation`` itself.
        """
        belief = self.predict(wm_ids)
        like = np.empty(len(wm_ids) + 1)
        like[0] = observation.get(NEW_LOCATION, 1.0)
        like[1:] = [observation.get(int(i), 1.0) for i in wm_ids]
        post = belief * discounted(like, weight)
        total = post.sum()
        post = post / total if total > _EPSILON else np.eye(1, len(post)).ravel()
        self.posterior = {NEW_LOCATION: float(post[0])}
        self.posterior.update(zip(wm_ids.tolist(), post[1:].tolist()))
        self.observation = observation
        return self.posterior

    def highest(self) -> Hypothesis:
        """Hypothesis selection (§III-D): the most probable location, valued 1 - p(S_t = -1).

        The paper accepts the highest hypothesis when the new-location probability is below
        T_loop's complement; as in RTAB-Map, the value compared with T_loop is the total
        loop closure probability ``1 - p(S_t = -1)``.

        With ``refine_hops`` > 0 (not in RTAB-Map) the location is then the one along the
        trajectory near the posterior's peak where this frame's likelihood is highest (see
        :meth:`_best_observed_near`): the prediction spreads belief over a few hops only, so when a
        revisit moves faster than the first pass the posterior's peak lags behind the place the
        image shows (1-10 locations on make_sequence revisits, each a false loop closure against
        the ground truth's pairs).
        """
        best_id, best_p = 0, 0.0
        for loc, prob in self.posterior.items():
            if loc != NEW_LOCATION and prob > best_p:
                best_id, best_p = loc, prob
        p_new = self.posterior.get(NEW_LOCATION, 1.0)
        if best_id and self.params.refine_hops > 0 and self.observation:
            best_id = self._best_observed_near(best_id)
        return Hypothesis(best_id, 1.0 - p_new if best_id else 0.0, p_new)

    def _best_observed_near(self, location_id: int) -> int:
        """The hypothesis at most ``refine_hops`` neighbour links from ``location_id`` (along the
        trajectory the peak is on, not through loop closures to other visits) whose last
        likelihood, summed over the locations within ``refine_window`` neighbour links of it, is
        highest (``location_id`` itself on ties).

        The sum over a location and its neighbours on either side: consecutive images see
        overlapping parts of a place, and the likelihood of one of them alone is noisy at that
        scale (two locations a few images apart often score within 5 % of each other); the
        window locates the image along the trajectory (on single likelihoods the first false
        hypotheses of make_sequence seeds 31 and 21 were 200-300 px past the ground truth's
        window of 0.3 image widths, bench/bench_lcd.py). It assumes consecutive locations
        overlap: SLAM's nodes, a second apart, do not (``refine_window`` 0 there).
        """
        obs = self.observation

        def window(node: int) -> float:
            return sum(obs.get(n, 1.0) for n in self._graph.hops_from(node, self.params.refine_window, TRAJECTORY))

        best, best_score = location_id, window(location_id)
        for node in self._along_trajectory(location_id):
            score = window(node)
            if score > best_score:
                best, best_score = node, score
        return best

    def _along_trajectory(self, location_id: int) -> list[int]:
        """The hypotheses at most ``refine_hops`` neighbour links from ``location_id`` (itself
        first), breadth-first (nearest first), through the nodes in memory only: no LTM read."""
        return [n for n in self._graph.hops_from(location_id, self.params.refine_hops, TRAJECTORY, allowed=self._kept)
                if n in self.posterior]

    def aligned(self, hypothesis: Hypothesis, query: Signature, signatures: Mapping[int, Signature]) -> Hypothesis:
        """With ``align_radius`` > 0 (not in RTAB-Map): the hypothesis moved to the location, at
        most ``refine_hops`` neighbour links from it along its trajectory, whose image shows the
        most of ``query``'s view in place (:func:`aligned_words`; the hypothesis itself on ties,
        and the view moved to needs a score of :data:`MIN_ALIGNED_WORDS`). The likelihood counts
        shared words wherever they are: two overlapping views of a place share many, and the one
        with more texture in common wins even when the image is half a frame from it
        (make_sequence seed 44: revisit images put 200-300 px past the ground truth's window, on
        words the second view also had). The positions of the words tell which view the image is."""
        if hypothesis.location_id <= 0 or self.params.align_radius <= 0.0 or len(query.keypoints) < 2:
            return hypothesis
        radius = self.params.align_radius * float(np.ptp(query.keypoints[:, 0]))
        candidates = [n for n in self._along_trajectory(hypothesis.location_id) if n in signatures]
        # Aligned words weighted by the shared part of the frame, rounded to whole words.
        scores = [int(round(c)) for c in aligned_words(query, [signatures[n] for n in candidates], radius)]
        if not scores:
            return hypothesis
        current = scores[candidates.index(hypothesis.location_id)] if hypothesis.location_id in candidates else 0
        k = int(np.argmax(scores))  # the nearest on ties (breadth-first order)
        # A real image shares a handful of words with its neighbours, and a few of them agree on a shift by
        # chance: the view moved to needs a score of MIN_ALIGNED_WORDS.
        if scores[k] <= current or scores[k] < MIN_ALIGNED_WORDS:
            return hypothesis
        return replace(hypothesis, location_id=candidates[k])

    def supported_by_observation(self, location_id: int) -> bool:
        """Not in RTAB-Map (``bayes.min_evidence_ratio``, 0 = off): the last update's likelihood of
        the location, or of a graph neighbour, is at least ``min_evidence_ratio`` times the new
        location's. The posterior carries belief from earlier frames: after a revisit ends the
        place keeps a value over T_loop for frames, and a weak match repeated frame after frame (a
        camera stopped, its images merged by rehearsal) compounds; the current image must itself
        favour the place over a new one."""
        ratio = self.params.min_evidence_ratio
        if ratio <= 0.0:
            return True
        obs = self.observation
        best = max([obs.get(location_id, 1.0)] + [obs.get(n, 1.0) for n in self._graph.neighbors(location_id)])
        if best < ratio * obs.get(NEW_LOCATION, 1.0):
            return False
        # 1 is the likelihood of a location that did not stand out of this frame's scores (Eq. 3). When
        # neither the place nor a neighbour did but others did, the image favours other places: the
        # ratio alone (the new location's likelihood is often 2 or below) would pass it on the belief
        # carried from a revisit that just ended. An image that favours no place leaves the belief be.
        return best > 1.0 or not any(v > 1.0 for k, v in obs.items() if k != NEW_LOCATION)

    def accepted(self, hypothesis: Hypothesis, previous_value: float = 0.0) -> bool:
        """A loop closure when the hypothesis reaches T_loop and is not the only one in WM, and,
        with ``loop_ratio`` > 0 (RTAB-Map's Rtabmap/LoopRatio), when the previous frame's
        hypothesis value ``previous_value`` was not 0 and this one is at least ``loop_ratio``
        times it (Rtabmap.cpp, hypothesis validation): a lone spike is not a loop closure."""
        if not (hypothesis.location_id > 0 and len(self.posterior) > 2
                and hypothesis.probability >= self.params.loop_threshold):
            return False
        ratio = self.params.loop_ratio
        return ratio <= 0.0 or (previous_value > 0.0 and hypothesis.probability >= ratio * previous_value)
