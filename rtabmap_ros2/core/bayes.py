"""Discrete Bayes filter over loop closure hypotheses (2013 §III-C) and hypothesis selection (§III-D).

States: ``S_t = -1`` (:data:`NEW_LOCATION`, the current location is new) and ``S_t = j`` for every
location j in WM. Eq. 2: ``p(S_t | L^t) = η p(L_t | S_t) Σ_i p(S_t | S_t-1 = i) p(S_t-1 = i | L^t-1)``.

The transition model spreads the belief of a location j over its graph neighbourhood (neighbour
and loop closure links, hops counted through nodes that are not in WM too; a loop closure link
crossed without a hop, as RTAB-Map's Memory::getNeighborsId: a place and the ones it closed a loop
with are one place) with a discretised
Gaussian of hop distance, restricted to WM and normalised to ``loop_closure_prior`` (0.9).
Neighbourhoods are cached per location and recomputed for the nodes at a graph change, so the
prediction is a handful of numpy operations per frame rather than an N x N matrix.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Container, Optional

import numpy as np

from rtabmap_ros2.core.graph import Graph, LinkType
from rtabmap_ros2.core.params import BayesParams

NEW_LOCATION = -1
_EPSILON = 1e-9
# Rtabmap::adjustLikelihood's epsilon: sigma below it counts as no spread.
LIKELIHOOD_EPSILON = 1e-4
# The new location's likelihood when no score stands out (or none is above 0): RTAB-Map's 2.
NO_STANDOUT_NEW_LIKELIHOOD = 2.0
# Transition weights (relative to the centre's 1) below this are dropped from neighbourhoods.
NEGLIGIBLE_TRANSITION = 1e-6
LOOP_CLOSURES = tuple(t for t in LinkType if t.is_loop_closure)
# A column of the prior whose excess over the median is below this fraction of the largest
# excess is not spread over its neighbourhood (see BayesFilter.predict).
NEGLIGIBLE_EXCESS = 1e-3


@dataclass(frozen=True)
class Hypothesis:
    """The highest loop closure hypothesis of a frame."""

    location_id: int  # the most probable location, 0 when there is none
    probability: float  # 1 - p(S_t = -1): the value compared with T_loop
    new_location_probability: float


def likelihood(scores: dict[int, float]) -> dict[int, float]:
    """Observation model (Eq. 3 and 4) from the raw score of every WM location.

    As RTAB-Map's ``Rtabmap::adjustLikelihood`` (the paper's Eq. 3-4 with its implementation's
    details, each of which moved precision and recall on real images, issue 32): mu and sigma
    over the non-zero scores, sigma the *sample* standard deviation (n - 1; 0 for one score);
    a location stands out when its score is strictly above mu + sigma, and its likelihood is then
    ``(s - (sigma - 1e-4)) / mu``; every other location gets 1. The new location gets
    ``mu / sigma + 1`` when sigma > 1e-4 and some location stood out, else 2 (no location shares a
    word with the image, or none stands out: a new place is then twice as likely as any).

    Args:
        scores: location id -> raw score (Eq. 1 similarity or tf-idf) for every location in WM,
            zeros included.

    Returns:
        location id -> likelihood, plus :data:`NEW_LOCATION` -> likelihood of a new location.
    """
    values = np.fromiter(scores.values(), dtype=float, count=len(scores))
    non_null = values[values > 0]
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
        # RTAB-Map's neighbourhoods: a loop closure link is crossed without a hop.
        self._free = LOOP_CLOSURES
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
        """``kept``: the nodes in memory (see :class:`TransitionModel`)."""
        self.params = params
        self._graph = graph
        self._kept = kept
        self.transitions = TransitionModel(params, graph, kept)
        self.posterior: dict[int, float] = {NEW_LOCATION: 1.0}
        # The last frame's likelihood (bench/bench_transition.py reads it).
        self.observation: dict[int, float] = {}

    def reset(self) -> None:
        self.posterior = {NEW_LOCATION: 1.0}
        self.observation = {}

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

    def update(self, wm_ids: np.ndarray, observation: dict[int, float]) -> dict[int, float]:
        """One filter step: predict, weight by the likelihood, normalise (Eq. 2).

        Args:
            wm_ids: (N,) int64 sorted ids of the WM locations that are hypotheses.
            observation: likelihood per id and for :data:`NEW_LOCATION` (see :func:`likelihood`).
        """
        belief = self.predict(wm_ids)
        like = np.empty(len(wm_ids) + 1)
        like[0] = observation.get(NEW_LOCATION, 1.0)
        like[1:] = [observation.get(int(i), 1.0) for i in wm_ids]
        post = belief * like
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
        loop closure probability ``1 - p(S_t = -1)``. On an exact tie the newest location wins, as
        in RTAB-Map (Rtabmap.cpp walks the posterior from the highest id with a strict ``>``).
        """
        best_id, best_p = 0, 0.0
        for loc, prob in self.posterior.items():
            if loc != NEW_LOCATION and (prob > best_p or (prob == best_p and prob > 0.0 and loc > best_id)):
                best_id, best_p = loc, prob
        p_new = self.posterior.get(NEW_LOCATION, 1.0)
        return Hypothesis(best_id, 1.0 - p_new if best_id else 0.0, p_new)

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
