"""Typed parameters: one frozen dataclass per module, nested in :class:`Params`.

Defaults are the papers' values (Labbé & Michaud 2013, Table I; 2014, §III) unless the field's doc
says why not. Every field has ``metadata={"doc": ..., "unit": ...}``; the ROS node declares one
parameter per field from that metadata, and the command line accepts the same names.

Names accepted when loading (``Params.from_mapping``, ``Params.with_overrides``):

* dotted names, ``memory.stm_size``;
* RTAB-Map's own names through :data:`RTABMAP_ALIASES` (``Mem/STMSize``, ``Rtabmap/TimeThr``...);
* the node's plain names (``database_path``, ``frame_id``...) for the fields of :class:`NodeParams`,
  and ``detection_rate``, ``approx_sync``, ``sync_queue_size`` for the synchroniser.

Unknown names raise :class:`~rtabmap_ros2.errors.ParameterError`; YAML is read with ``safe_load``.
"""

from __future__ import annotations

import logging
import math
import os
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import Any, Iterator, Mapping

from rtabmap_ros2.errors import ParameterError


HALF_PI = math.pi / 2
NODE_QOS = ("auto", "reliable", "sensor_data")
NODE_IMAGE_TRANSPORTS = ("auto", "raw", "compressed")
GRID_SENSORS = ("auto", "laser", "depth", "both")


def _p(default: Any, doc: str, unit: str = "") -> Any:
    """A dataclass field with its doc and unit in the metadata."""
    return field(default=default, metadata={"doc": doc, "unit": unit})


def _check(condition: bool, name: str, value: Any, expected: str) -> None:
    if not condition:
        raise ParameterError(f"{name}={value!r} is invalid: expected {expected}")


@dataclass(frozen=True)
class FeatureParams:
    """Location creation (2013 §III-A, Alg. 2): keypoints and descriptors of an image."""

    detector: str = _p(
        "gftt_orb",
        "Detector/descriptor: gftt_orb (GFTT corners + ORB descriptors, RTAB-Map's default "
        "Kp/DetectorStrategy=8), orb, sift. SURF (the paper's) is patented and absent from OpenCV "
        "wheels; sift is 15x slower (bench/bench_features.py). orb gave 13 % more correct matches "
        "on the TUM pairs, fewer false loop closures at T_loop 0.11 but lower recall above 0.3 on "
        "the revisiting sequence than gftt_orb: no clear winner, RTAB-Map's default is kept.",
    )
    max_features: int = _p(400, "T_maxFeatures: keep at most this many strongest features (0 = all)")
    response_threshold: float = _p(
        0.0, "T_response: minimum detector response of a feature (detector-specific scale)"
    )
    gftt_min_distance_px: float = _p(
        7.0, "gftt_orb: GFTT/MinDistance, the least distance between two corners (RTAB-Map's 7). 5 px lifted "
        "Lip6Outdoor (240x192: 400 corners instead of ~300) but cost precision where a photo recurs and lost "
        "make_sequence sets nobody had tuned on; issue 48's rule keeps RTAB-Map's value (docs/benchmarks.md)", "px")
    depth_as_mask: bool = _p(
        False, "With a depth image (SLAM): detect features only where its depth is valid and within "
        "min_depth..max_depth (RTAB-Map's Mem/DepthAsMask, true in RTAB-Map). Not the default here: on the "
        "simulator's seed 4242 it made session 2 merge onto a look-alike place 27.7 m away (7 wrong loop "
        "closures kept, ATE 13.3 m against 0.019 m); on the real fr1 loop pairs 11 -> 14 accepted, 5 -> 11 "
        "off by more than 3 cm / 1.5 deg; on the real fr1 recording the same yardstick either way "
        "(bench/bench_slam.py, bench/bench_registration.py; docs/benchmarks.md)")
    min_depth: float = _p(0.0, "Features only where the depth is above this (RTAB-Map's Kp/MinDepth; 0 = none; "
                          "through depth_as_mask, else the features found are filtered)", "m")
    max_depth: float = _p(0.0, "Features only where the depth is below this (RTAB-Map's Kp/MaxDepth; 0 = no "
                          "limit; through depth_as_mask, else the features found are filtered)", "m")
    roi_ratios: tuple[float, float, float, float] = _p(
        (0.0, 0.0, 0.0, 0.0),
        "Region of interest as ratios of the image cut off at left, right, top, bottom "
        "(the 2013 NFSMW experiment used 0 0 0.1 0.4)",
        "ratio",
    )

    def __post_init__(self) -> None:
        _check(self.detector in ("gftt_orb", "orb", "sift"), "features.detector", self.detector,
               "one of gftt_orb, orb, sift")
        _check(self.max_features >= 0, "features.max_features", self.max_features, ">= 0")
        _check(self.gftt_min_distance_px >= 0.0, "features.gftt_min_distance_px", self.gftt_min_distance_px, ">= 0")
        _check(self.min_depth >= 0.0, "features.min_depth", self.min_depth, ">= 0")
        _check(self.max_depth == 0.0 or self.max_depth > self.min_depth, "features.max_depth", self.max_depth,
               f"0 (no limit) or above features.min_depth ({self.min_depth})")
        _check(len(self.roi_ratios) == 4 and all(0.0 <= r < 1.0 for r in self.roi_ratios)
               and self.roi_ratios[0] + self.roi_ratios[1] < 1.0
               and self.roi_ratios[2] + self.roi_ratios[3] < 1.0,
               "features.roi_ratios", self.roi_ratios, "4 ratios in [0, 1) leaving part of the image")


@dataclass(frozen=True)
class VocabularyParams:
    """Incremental visual vocabulary (2013 §III-A): 2-NN quantisation with the NNDR test."""

    nndr: float = _p(0.8, "T_NNDR: a descriptor matches its nearest word if d1 <= T_NNDR * d2", "ratio")
    new_words_compared_together: bool = _p(
        True, "Compare a frame's new words with each other too, in order (RTAB-Map's "
        "Kp/NewWordsComparedTogether): a feature repeated in one image gives one word (config/rtabmap.yaml: false "
        "for SLAM, with bayes.likelihood eq1, measured with bench/bench_slam.py)")
    index: str = _p(
        "kdtree",
        "Word search: kdtree (RTAB-Map's Kp/NNStrategy 1: FLANN randomized kd-trees over binary descriptors' "
        "bits, 32 checks, approximate; float descriptors (features.detector sift) use flat) or flat (exact brute "
        "force, faiss). Issue 48: the exact search needed a likelihood trim that broke real images",
    )
    kdtree_seed: int = _p(
        0, "kdtree: seed of the trees' random choices (FLANN draws its own on every run, so RTAB-Map itself "
        "is not repeatable: bench/bench_lcd.py --ours-runs compares several seeds with several of its runs)")
    kdtree_search_threads: int = _p(
        2,
        "kdtree: threads searching a frame's descriptors, in chunks of 50 claimed in turn (the frame's thread "
        "never waits for a helper that has not started; the words found are the same for any number). "
        "RTAB-Map's FLANN search uses one. 2 halve a search on an idle core (400 queries, 200k words: 20.9 -> 10.0 "
        "ms); in `map`, where the image reader and database writer share the second core, quantisation's median "
        "fell 2.4-3.6 ms a frame on simulator seeds 5, 9, 4242, 17 (bench/bench_slam.py; bench/bench_vocabulary.py "
        "compares 1 and 2). The exact search (flat) stays on one thread", "threads")
    rebuild_swap_frames: int = _p(
        1,
        "kdtree: the trees are rebuilt when they have doubled (Kp/FlannRebalancingFactor 2), in a background "
        "thread; the rebuild is swapped in this many frames (searches) after it started, and, past 20,000 words "
        "(core/kdtree.py IN_TIME_REBUILD_WORDS), at least one frame per 1,000 words it holds "
        "(SWAP_WORDS_PER_SEARCH: a 1M-word rebuild takes ~8 s of CPU), "
        "waiting for it then if needed: the same images give the same words whatever the load. RTAB-Map rebuilds "
        "in the frame; with 300 (before) every new word went into deepened old trees for 300 frames or more, and "
        "sets under 300 images never saw a rebuild: our port of RTAB-Map's setting lost to it on 7 sets of 11, "
        "with 1 on 2, Lip6Outdoor recall at 100 % precision 0.861 -> 0.881 (issue 48, bench/bench_lcd.py)", "frames")

    def __post_init__(self) -> None:
        _check(0.0 < self.nndr <= 1.0, "vocabulary.nndr", self.nndr, "in (0, 1]")
        _check(self.index in ("flat", "kdtree"), "vocabulary.index", self.index,
               "kdtree or flat (auto and ivf were removed with the IVF word search, issue 50: flat is the exact search)")
        _check(self.rebuild_swap_frames >= 1, "vocabulary.rebuild_swap_frames", self.rebuild_swap_frames, ">= 1")
        _check(self.kdtree_search_threads >= 1, "vocabulary.kdtree_search_threads", self.kdtree_search_threads,
               ">= 1")


@dataclass(frozen=True)
class MemoryParams:
    """STM / WM / LTM management (2013 §III-B, E, F; 2014 §II-C)."""

    stm_size: int = _p(30, "T_STM: number of locations in Short-Term Memory", "locations")
    rehearsal_similarity: float = _p(
        0.6, "T_similarity: merge the new location into the previous one if Eq. 1 is above this. RTAB-Map's "
        "Mem/RehearsalSimilarity 0.6 (the paper's 0.20 merged a moving camera's overlapping views). 0.7, chosen "
        "with the exact word search, made no set better with the kd-trees: bench/bench_lcd.py's ablation row "
        "'rehearsal similarity 0.7' (issue 48)", "ratio"
    )
    rehearsal_max_distance: float = _p(
        0.05, "SLAM mode: the camera moved when its neighbour link is longer than this along an axis; "
        "a moving camera's locations are not merged by rehearsal (RTAB-Map's Mem/RehearsalMaxDistance)", "m")
    rehearsal_max_angle: float = _p(
        0.1, "SLAM mode: the camera moved when its neighbour link turns more than this "
        "(RTAB-Map's Mem/RehearsalMaxAngle)", "rad")
    rehearsal_id_updated_to_new_one: bool = _p(
        False, "Rehearsal merges the new location into the previous one, which keeps its id, words and pose "
        "(False, RTAB-Map's default), or the previous one into the new one, which keeps its id, pose, scan and "
        "stamp, takes the older image's words and the older location's links (True; RTAB-Map's "
        "Mem/RehearsalIdUpdatedToNewOne). Detection: False, a loop closure then names the image that holds "
        "the words (issue 32). SLAM (rehearsal merges only while the robot stands still) keeps False too: on "
        "the simulated building (bench/bench_slam.py --seeds 0,5,9,4242,17) ATE 0.016 / 0.017 / 0.015 / "
        "0.018 / 0.016 m with False, 0.016 / 0.014 / 0.014 / 0.020 / 0.018 m with True: better on three seeds, "
        "worse on two, the same summed (1 component, no wrong loop closure kept either way)")
    rehearsal_weight_ignored_while_moving: bool = _p(
        False, "SLAM mode, camera moving: similar consecutive locations are both kept and the older one's "
        "weight goes to the newer (False), or nothing happens (True; RTAB-Map's "
        "Mem/RehearsalWeightIgnoredWhileMoving)")
    recent_wm_ratio: float = _p(
        0.20, "T_recent: part of WM after the last loop closure that is protected from transfer", "ratio"
    )
    bad_signature_ratio: float = _p(
        0.5, "T_bad (RTAB-Map's Kp/BadSignRatio; the 2013 paper's 0.25): an image with fewer features than "
        "T_bad x the mean words of the locations in WM and STM is a bad signature (kept without words)", "ratio"
    )
    time_threshold_ms: float = _p(
        700.0, "T_time: transfer WM -> LTM when the processing time exceeds it (0 = no limit)", "ms"
    )
    max_retrieved: int = _p(2, "Locations retrieved from LTM per frame (Alg. 3)", "locations")
    max_local_retrieved: int = _p(
        2, "SLAM mode: locations retrieved per frame from LTM because they are linked to the local map's "
        "nodes near the robot (RTAB-Map's RGBD/MaxLocalRetrieved)", "locations")
    max_wm_size: int = _p(
        0, "Most locations in WM: over it, the lowest-weighted go to LTM every frame (0 = no limit; "
        "RTAB-Map's Rtabmap/MemoryThr)", "locations")
    time_target_ratio: float = _p(
        0.8, "SLAM mode: after a frame over T_time, WM is capped at the size it would have taken this part of "
        "T_time at (core/wm_budget.py)", "ratio")
    wm_cap_growth: float = _p(
        0.3, "SLAM mode: how much that cap rises per frame faster than time_target_ratio x T_time, up to "
        "the largest WM a frame went over T_time at "
        "(core/wm_budget.py)", "locations/frame")
    keep_one_node_per_session: bool = _p(
        True, "Never transfer the last WM node of a session, so no map is orphaned (2014 §IV)"
    )
    local_immunization_ratio: float = _p(
        0.25, "SLAM mode: at most this part of WM, the local map's nodes nearest the robot within "
        "memory.local_radius, is protected from transfer (RTAB-Map's RGBD/LocalImmunizationRatio)", "ratio")
    local_radius: float = _p(
        10.0, "SLAM mode: radius around the robot of the nodes protected by "
        "memory.local_immunization_ratio (RTAB-Map's RGBD/LocalRadius)", "m")

    def __post_init__(self) -> None:
        _check(self.stm_size >= 1, "memory.stm_size", self.stm_size, ">= 1")
        _check(0.0 <= self.rehearsal_similarity <= 1.0, "memory.rehearsal_similarity",
               self.rehearsal_similarity, "in [0, 1]")
        _check(self.rehearsal_max_distance >= 0.0, "memory.rehearsal_max_distance", self.rehearsal_max_distance,
               ">= 0")
        _check(self.rehearsal_max_angle >= 0.0, "memory.rehearsal_max_angle", self.rehearsal_max_angle, ">= 0")
        _check(0.0 <= self.recent_wm_ratio <= 1.0, "memory.recent_wm_ratio", self.recent_wm_ratio, "in [0, 1]")
        _check(0.0 <= self.bad_signature_ratio <= 1.0, "memory.bad_signature_ratio",
               self.bad_signature_ratio, "in [0, 1]")
        _check(self.time_threshold_ms >= 0.0, "memory.time_threshold_ms", self.time_threshold_ms, ">= 0")
        _check(self.max_retrieved >= 0, "memory.max_retrieved", self.max_retrieved, ">= 0")
        _check(self.max_local_retrieved >= 0, "memory.max_local_retrieved", self.max_local_retrieved, ">= 0")
        _check(self.max_wm_size >= 0, "memory.max_wm_size", self.max_wm_size, ">= 0")
        _check(0.0 < self.time_target_ratio <= 1.0, "memory.time_target_ratio", self.time_target_ratio, "in (0, 1]")
        _check(self.wm_cap_growth >= 0.0, "memory.wm_cap_growth", self.wm_cap_growth, ">= 0")
        _check(0.0 <= self.local_immunization_ratio <= 1.0, "memory.local_immunization_ratio",
               self.local_immunization_ratio, "in [0, 1]")
        _check(self.local_radius >= 0.0, "memory.local_radius", self.local_radius, ">= 0")


@dataclass(frozen=True)
class BayesParams:
    """Discrete Bayes filter and hypothesis selection (2013 §III-C, D)."""

    loop_threshold: float = _p(
        0.11, "T_loop: accept the highest loop closure hypothesis when its posterior is at least "
        "this (RTAB-Map's implementation of §III-D; 2014: H = 0.11)", "probability")
    sigma: float = _p(1.6, "Std. deviation of the discretised Gaussian of the transition model", "locations")
    neighborhood: int = _p(16, "Neighbours (graph hops) reached by the transition model", "locations")
    virtual_place_prior: float = _p(
        0.9, "p(S_t=-1 | S_t-1=-1), the new-location persistence (RTAB-Map's Bayes/VirtualPlacePriorThr; "
        "paper and RTAB-Map: 0.9). 0.95 (the default before issue 32, chosen on sim/sequence.py) kept "
        "the value of true revisits under T_loop on real images (bench/bench_lcd.py --ablation)", "probability")
    loop_closure_prior: float = _p(0.9, "Sum of p(S_t>=0 | S_t-1=j) over the neighbourhood of j", "probability")
    likelihood: str = _p(
        "tf_idf", "Raw score of a WM location before Eq. 3-4: tf_idf (RTAB-Map's Kp/TfIdfLikelihoodUsed: "
        "sum over the frame's words of n_wj log10(N / n_w) / n_j, over the inverted index) or eq1 "
        "(the paper's Eq. 1 similarity; config/rtabmap.yaml's for SLAM, where it kept the simulated building's ATE "
        "at 0.015-0.017 m against 0.016-0.046 m with tf_idf, bench/bench_slam.py, issue 32)")
    loop_ratio: float = _p(
        0.0, "RTAB-Map's Rtabmap/LoopRatio: reject a hypothesis below this ratio of the previous "
        "frame's hypothesis value, or when the previous value was 0 (0 = off, RTAB-Map's default, as here: "
        "0.9, its 2013 value, rejected every frame of a revisit whose value fell by 10 %, and the missed "
        "loop closures left the visits unlinked so the value fell further: recall 0.59 instead of 0.67 on "
        "seed 11; the stale hypotheses it was rejecting are left to epipolar_verification, "
        "bench/bench_detect.py --ablation)", "ratio")
    epipolar_verification: bool = _p(
        False, "RTAB-Map's VhEp/Enabled (off, as RTAB-Map): a hypothesis reaching T_loop is accepted only when the "
        "words found once in both images fit a fundamental matrix (RANSAC) with epipolar_min_matches inliers. "
        "On RTAB-Map's own real images true revisits share 0-9 such words with the hypothesis (its belief "
        "comes from the neighbouring frames): on, 35 of 44 loop images are accepted instead of 44 "
        "(bench/bench_lcd.py --ablation)")
    epipolar_min_matches: int = _p(
        8, "RTAB-Map's VhEp/MatchCountMin: word pairs, then RANSAC inliers, needed by the epipolar "
        "verification", "pairs")
    epipolar_max_distance: float = _p(
        3.0, "RTAB-Map's VhEp/RansacParam1: largest distance of an inlier from its epipolar line", "px")
    epipolar_confidence: float = _p(
        0.99, "RTAB-Map's VhEp/RansacParam2: RANSAC confidence of the fundamental matrix", "probability")
    epipolar_min_coverage: float = _p(
        0.1, "Not in RTAB-Map: the epipolar verification's inliers must also cover this fraction of "
        "the image (area of their convex hull over that of all the image's keypoints, in the image "
        "where it is smaller; 0 = off). A poster or sign seen again elsewhere fits a fundamental "
        "matrix on its own words, in a corner of the image; a revisited place matches across it "
        "(bench/bench_detect.py --ablation)", "ratio")

    def __post_init__(self) -> None:
        _check(0.0 <= self.loop_threshold <= 1.0, "bayes.loop_threshold", self.loop_threshold, "in [0, 1]")
        _check(self.sigma > 0.0, "bayes.sigma", self.sigma, "> 0")
        _check(self.neighborhood >= 0, "bayes.neighborhood", self.neighborhood, ">= 0")
        _check(0.0 < self.virtual_place_prior < 1.0, "bayes.virtual_place_prior", self.virtual_place_prior,
               "in (0, 1)")
        _check(0.0 < self.loop_closure_prior < 1.0, "bayes.loop_closure_prior", self.loop_closure_prior,
               "in (0, 1)")
        _check(self.likelihood in ("tf_idf", "eq1"), "bayes.likelihood", self.likelihood, "tf_idf or eq1")
        _check(0.0 <= self.loop_ratio <= 1.0, "bayes.loop_ratio", self.loop_ratio, "in [0, 1]")
        _check(self.epipolar_min_matches >= 8, "bayes.epipolar_min_matches", self.epipolar_min_matches,
               ">= 8 (a fundamental matrix needs 8 pairs)")
        _check(self.epipolar_max_distance > 0.0, "bayes.epipolar_max_distance", self.epipolar_max_distance, "> 0")
        _check(0.0 < self.epipolar_confidence < 1.0, "bayes.epipolar_confidence", self.epipolar_confidence,
               "in (0, 1)")
        _check(0.0 <= self.epipolar_min_coverage < 1.0, "bayes.epipolar_min_coverage", self.epipolar_min_coverage,
               "in [0, 1)")


@dataclass(frozen=True)
class RegistrationParams:
    """Loop closure verification (2014 §II-A): PnP (or RANSAC on 3D words), 2D ICP refinement."""

    min_inliers: int = _p(20, "I: minimum RANSAC inliers to accept a loop closure (paper: 5; "
                          "20 measured in bench/bench_registration.py to reject perceptual aliasing; RTAB-Map's "
                          "Vis/MinInliers)")
    estimation: str = _p(
        "auto", "Loop closure transform (RTAB-Map's Vis/EstimationType): pnp (1: the 3D words of one node, "
        "from its depth, against the 2D keypoints of the other, RANSAC on the reprojection error in pixels, "
        "then refined on both nodes' words), 3d (0: RANSAC on 3D-3D word pairs, the 2014 paper's; "
        "inlier_distance) or auto: pnp in 6 DoF, 3d when planar with laser scans, where 2D ICP then decides x, "
        "y and yaw (the 2014 paper's pipeline; PnP there took the simulated building's seed 0 ATE from 0.0161 "
        "to 0.0177 m and accepted 2 look-alike loop closures, bench/bench_slam.py). On the 24 real TUM loop "
        "pairs: bench/bench_registration.py")
    inlier_distance: float = _p(0.1, "3d estimation: RANSAC inlier threshold on 3D word positions", "m")
    ransac_iterations: int = _p(500, "RANSAC hypotheses (both estimations)", "iterations")
    pnp_reprojection_error: float = _p(
        2.0, "pnp: a word pair is an inlier when it reprojects within this distance (RTAB-Map's "
        "Vis/PnPReprojError)", "px")
    pnp_refine_iterations: int = _p(
        5, "pnp: refinements of the RANSAC estimate, each re-selecting the inliers at the current estimate "
        "and minimising their reprojection errors (RTAB-Map's Vis/PnPRefineIterations; 0 = RANSAC's answer)",
        "iterations")
    bundle_adjustment: bool = _p(
        True, "pnp: refine on the reprojection errors in both images (the from node's words, from its depth, "
        "in the to image and the to node's in the from image: a two-view bundle adjustment of the pose with "
        "the words held at their depth), not in the to image only (RTAB-Map's Vis/BundleAdjustment)")
    pnp_max_variance: float = _p(
        0.0025, "pnp: reject a loop closure whose translation variance (from the inliers' 3D residuals, as "
        "its information matrix) is above this (RTAB-Map's Vis/PnPMaxVariance, there 0 = off). 0.0025 m^2 "
        "(5 cm standard deviation): on the 24 real TUM loop pairs it rejects the 3 PnP estimates whose words "
        "disagree that much (7.2, 6.7 and 2.7 cm, 2.2 to 3.3 deg off the motion capture; the graph check "
        "cannot catch them, their covariance is as loose) and none within 3 cm / 1.5 deg; the accepted "
        "ones on fr1_xyz have 1.0-1.3 cm (bench/bench_registration.py). 0 = off", "m^2")
    guided_window: float = _p(
        10.0, "pnp: after a first estimate from the shared words (8 inliers or more), match every keypoint "
        "with depth to the keypoints of the other image within this distance of where the estimate projects "
        "it (descriptor distance, nearest neighbour ratio), then refine again on these matches (RTAB-Map's "
        "Vis/CorGuessWinSize, here with the first estimate as the guess; 0 = the shared words only, as "
        "RTAB-Map's loop closures). On the 24 real TUM loop pairs 16 accepted instead of 9, as near the "
        "images' own optimum (bench/bench_registration.py)", "px")
    min_depth: float = _p(
        0.0, "Loop closure transforms from the words whose depth (along the camera's axis) is above this only, "
        "on both nodes (RTAB-Map's Vis/MinDepth; 0 = none)", "m")
    max_depth: float = _p(
        0.0, "Loop closure transforms from the words whose depth is below this only, on both nodes: a far "
        "point's depth is noisier (RTAB-Map's Vis/MaxDepth; 0 = no limit; with either limit, words without "
        "depth are left out too, as RTAB-Map's)", "m")
    planar: bool = _p(
        False, "Robot moves on a plane: registration and optimisation keep x, y and yaw only (RTAB-Map's "
        "Reg/Force3DoF, false by default as there: 6 DoF; config/rtabmap.yaml sets it for its wheeled robot "
        "with a laser). Applied as given whatever the sensors; when the odometry leaves the plane (0.1 m, 5 deg "
        "from the session's first pose) a warning says so: a hand-held camera needs false")
    icp_refine: bool = _p(True, "Refine visual loop closures with 2D ICP on the laser scans")
    neighbor_link_refining: bool = _p(
        False, "Refine each neighbour link with 2D ICP of the new scan against the previous nodes' "
        "scans, started from the odometry, which fills in only what the scans leave free (RTAB-Map's "
        "RGBD/NeighborLinkRefining; planar mode with a laser)")
    neighbor_scan_map_nodes: int = _p(
        10, "Neighbour link refining matches the new scan against the scans of this many previous "
        "nodes of the session, assembled at their linked poses (1 = the previous scan only)", "nodes")
    scan_map_voxel_size: float = _p(
        0.05, "Voxel edge of the assembled scans of neighbour link refining (one centroid per voxel: "
        "denoised, even density; RTAB-Map's Icp/VoxelSize)", "m")
    icp_max_correspondence_distance: float = _p(0.3, "ICP: maximum point-to-line correspondence distance", "m")
    icp_iterations: int = _p(30, "ICP: maximum iterations", "iterations")
    icp_min_overlap: float = _p(0.5, "ICP: minimum ratio of scan points with a correspondence", "ratio")
    icp_max_translation: float = _p(
        0.5, "ICP: reject a refinement that moves the visual estimate by more than this", "m")

    def __post_init__(self) -> None:
        _check(self.min_inliers >= 3, "registration.min_inliers", self.min_inliers, ">= 3")
        _check(self.inlier_distance > 0, "registration.inlier_distance", self.inlier_distance, "> 0")
        _check(self.ransac_iterations >= 1, "registration.ransac_iterations", self.ransac_iterations, ">= 1")
        _check(self.estimation in ("auto", "pnp", "3d"), "registration.estimation", self.estimation,
               "auto, pnp or 3d")
        _check(self.pnp_reprojection_error > 0, "registration.pnp_reprojection_error", self.pnp_reprojection_error,
               "> 0")
        _check(self.pnp_refine_iterations >= 0, "registration.pnp_refine_iterations", self.pnp_refine_iterations,
               ">= 0")
        _check(self.pnp_max_variance >= 0, "registration.pnp_max_variance", self.pnp_max_variance, ">= 0")
        _check(self.guided_window >= 0, "registration.guided_window", self.guided_window, ">= 0")
        _check(self.min_depth >= 0, "registration.min_depth", self.min_depth, ">= 0")
        _check(self.max_depth == 0 or self.max_depth > self.min_depth, "registration.max_depth", self.max_depth,
               f"0 (no limit) or above registration.min_depth ({self.min_depth})")
        _check(self.icp_max_correspondence_distance > 0, "registration.icp_max_correspondence_distance",
               self.icp_max_correspondence_distance, "> 0")
        _check(self.icp_iterations >= 1, "registration.icp_iterations", self.icp_iterations, ">= 1")
        _check(self.neighbor_scan_map_nodes >= 1, "registration.neighbor_scan_map_nodes",
               self.neighbor_scan_map_nodes, ">= 1")
        _check(self.scan_map_voxel_size > 0, "registration.scan_map_voxel_size", self.scan_map_voxel_size, "> 0")
        _check(0.0 <= self.icp_min_overlap <= 1.0, "registration.icp_min_overlap", self.icp_min_overlap,
               "in [0, 1]")
        _check(self.icp_max_translation > 0, "registration.icp_max_translation", self.icp_max_translation,
               "> 0")


@dataclass(frozen=True)
class GraphParams:
    """Graph SLAM (2014 §II-B, C): optimisation and sessions."""

    optimizer: str = _p("lm", "Pose graph solver (gtsam): lm (Levenberg-Marquardt), gn (Gauss-Newton), "
                        "dogleg (Powell's, from a wide trust region; LM where the Gauss-Newton system is singular), "
                        "auto (LM, dogleg once LM's damping, raised above its initial value, fails in two "
                        "iterations running: the default of rtabmap-ros2 optimize)")
    iterations: int = _p(100, "Maximum optimiser iterations", "iterations")
    robust: bool = _p(True, "Dynamic covariance scaling on loop closures; drop those it rejects")
    incremental: bool = _p(True, "Local map: continue the last solution with gtsam's iSAM2 (the frame's nodes and links "
                           "added to it) instead of solving the whole local map again at a loop closure; a batch "
                           "solve (the optimizer above) whenever it cannot continue: nodes left the local map, "
                           "a map merged, loop closures undone")
    robust_reject_scale: float = _p(
        0.1, "Robust: a loop closure whose DCS scale ends below this is dropped as inconsistent", "ratio")
    optimize_max_error: float = _p(
        3.0, "Reject the frame's new loop closures when, after optimising with them, a link's error "
        "exceeds this many standard deviations (RTAB-Map's RGBD/OptimizeMaxError; 0 = no check): "
        "a wrong loop closure (perceptual aliasing) bends the odometry chain. A link already off "
        "before them counts only if its error grew, by how far it moved", "std dev")
    merge_min_separation: float = _p(
        5.0, "A loop closure joining two maps that are not connected yet (an inter-session merge) "
        "is held until a second one, between places at least this far from the first on both maps, "
        "agrees on the maps' alignment: perceptual aliasing (look-alike posters, symmetric corridors) "
        "repeats over a few metres, a true overlap does not end there (0 = merge on the first). Once "
        "joined, an inter-session loop closure putting the old node farther than this from its kept pose "
        "is rejected as a look-alike, and so is a loop closure within the session putting the old node "
        "farther than this from its pose in the local map (the local map's drift over a loop must stay "
        "under it)", "m")
    merge_min_loop_closures: int = _p(
        3, "A merge also needs this many loop closures agreeing on the alignment (the new one and held ones): "
        "on the simulated sessions with a small WM, pairs of look-alike loop closures shifted alike along "
        "parallel corridors agreed (18-43 m off), no true merge came with fewer than 3", "loop closures")
    merge_max_conflict: float = _p(
        0.15, "A merge that merge_min_separation confirms is still refused when, around its loop closures, "
        "this fraction of the cells one map's laser hits (walls) lies where the other map's laser saw free "
        "space, after aligning the two by ICP (Birk and Carpin's acceptance index for map merging): look-alike "
        "places a fixed distance apart (a poster repeated along two corridors) agree with each other on a wrong "
        "alignment, the walls do not. Measured on the simulated sessions: true merges 0.00-0.07, wrong ones "
        "0.29-0.40 (1 = no check)", "ratio")
    odom_reset_jump: float = _p(
        1.0, "Odometry reset detection: a new map starts when odometry moves between two frames by more "
        "than this plus a plausible speed x the time between them (the first frames after a reset were "
        "lost, so the first one received is already away from the origin), or by more than this across "
        "a silence longer than odom_reset_max_gap. RTAB-Map's RGBD/NewMapOdomChangeDistance, which has "
        "no speed term; 0 = off (a reset is then seen only by an identity pose or a covariance of 9999, "
        "as in RTAB-Map by default)", "m")
    odom_reset_speed: float = _p(
        1.0, "Odometry reset detection: speed the robot is assumed able to reach however slowly it moved so "
        "far. The plausible speed across a gap is the larger of this and twice the fastest speed seen "
        "over the last 20 frames, so a fast robot is judged by its own speed (raise it when the robot "
        "can speed up much while frames are lost)", "m/s")
    odom_reset_max_gap: float = _p(
        60.0, "Odometry reset detection: across a silence longer than this (no frame; or a stamp going "
        "back, a bag replayed) odometry is not trusted to bridge more than odom_reset_jump: a robot "
        "that moved meanwhile starts a new map, joined again by loop closures", "s")
    linear_update: float = _p(
        0.0, "Minimum displacement to add a node (RTAB-Map's RGBD/LinearUpdate): a frame whose odometry moved "
        "less than this along each of x, y and z since the session's last node, and less than angular_update "
        "about each axis, does not become a node (nothing stored, no loop closure detection: the map stays as "
        "it is while the robot stands still). 0 = translation not checked; with both 0, every frame becomes a "
        "node. RTAB-Map's default is 0.1 m; ours is 0: every synchronised frame is a node and a robot standing still "
        "is folded by rehearsal (memory.rehearsal_similarity) instead; 0.1 / 0.1 gives RTAB-Map's behaviour", "m")
    angular_update: float = _p(
        0.0, "Minimum rotation to add a node (RTAB-Map's RGBD/AngularUpdate): see linear_update; 0 = rotation "
        "not checked. RTAB-Map's default is 0.1 rad", "rad")
    proximity_by_space: bool = _p(
        False, "Proximity detection by space (RTAB-Map's RGBD/ProximityBySpace, visual; core/proximity.py): each frame "
        "also registers the new node with WM nodes the local map puts near it (within memory.local_radius and "
        "proximity_max_graph_depth links, one per path of neighbour links, at most proximity_max_paths, the "
        "nearest within proximity_filtering_radius and proximity_angle), for revisits the Bayes filter does not "
        "single out; the loop closures found are judged with the frame's others (optimize_max_error). RTAB-Map's "
        "default is true; ours is false: the simulated building's map got worse with it (ATE 0.013 -> 0.015 m, "
        "0.022 -> 0.024), the real hand-held recording's better (0.017 -> 0.009 m every frame; docs/benchmarks.md)")
    proximity_max_graph_depth: int = _p(
        50, "Proximity detection: candidates within this many links of the new node "
        "(RTAB-Map's RGBD/ProximityMaxGraphDepth; 0 = any)", "links")
    proximity_max_paths: int = _p(
        3, "Proximity detection: paths whose candidate is registered a frame, highest likelihood then most "
        "recent first (RTAB-Map's RGBD/ProximityMaxPaths; 0 = all)", "paths")
    proximity_filtering_radius: float = _p(
        1.0, "Proximity detection: a path's candidate must be this near the robot, and the registered transform "
        "this short (RTAB-Map's RGBD/ProximityPathFilteringRadius)", "m")
    proximity_angle: float = _p(
        45.0, "Proximity detection: a candidate's forward axis within this angle of the robot's "
        "(RTAB-Map's RGBD/ProximityAngle; 0 = any)", "deg")
    odom_default_variance: float = _p(
        1e-3, "Variance of neighbour links when odometry has no covariance", "m^2, rad^2")
    loop_closure_variance: float = _p(1e-3, "Variance of loop closure links (before robust scaling)",
                                      "m^2, rad^2")

    def __post_init__(self) -> None:
        _check(self.optimizer in ("lm", "gn", "dogleg", "auto"), "graph.optimizer", self.optimizer,
               "lm, gn, dogleg or auto")
        _check(self.iterations >= 1, "graph.iterations", self.iterations, ">= 1")
        _check(0.0 < self.robust_reject_scale < 1.0, "graph.robust_reject_scale", self.robust_reject_scale,
               "in (0, 1)")
        _check(self.optimize_max_error >= 0, "graph.optimize_max_error", self.optimize_max_error, ">= 0")
        _check(self.merge_min_separation >= 0, "graph.merge_min_separation", self.merge_min_separation, ">= 0")
        _check(self.merge_min_loop_closures >= 2, "graph.merge_min_loop_closures", self.merge_min_loop_closures, ">= 2")
        _check(0.0 <= self.merge_max_conflict <= 1.0, "graph.merge_max_conflict", self.merge_max_conflict, "in [0, 1]")
        _check(self.odom_reset_jump >= 0, "graph.odom_reset_jump", self.odom_reset_jump, ">= 0")
        _check(self.odom_reset_speed >= 0, "graph.odom_reset_speed", self.odom_reset_speed, ">= 0")
        _check(self.odom_reset_max_gap > 0, "graph.odom_reset_max_gap", self.odom_reset_max_gap, "> 0")
        _check(self.linear_update >= 0, "graph.linear_update", self.linear_update, ">= 0")
        _check(self.angular_update >= 0, "graph.angular_update", self.angular_update, ">= 0")
        _check(self.proximity_max_graph_depth >= 0, "graph.proximity_max_graph_depth", self.proximity_max_graph_depth,
               ">= 0")
        _check(self.proximity_max_paths >= 0, "graph.proximity_max_paths", self.proximity_max_paths, ">= 0")
        _check(self.proximity_filtering_radius > 0, "graph.proximity_filtering_radius",
               self.proximity_filtering_radius, "> 0")
        _check(0.0 <= self.proximity_angle <= 180.0, "graph.proximity_angle", self.proximity_angle, "in [0, 180]")
        _check(self.odom_default_variance > 0, "graph.odom_default_variance", self.odom_default_variance, "> 0")
        _check(self.loop_closure_variance > 0, "graph.loop_closure_variance", self.loop_closure_variance, "> 0")


@dataclass(frozen=True)
class GridParams:
    """Occupancy grid (nav_msgs conventions) and assembled point cloud."""

    resolution: float = _p(0.05, "Cell size of the occupancy grid", "m")
    range_max: float = _p(
        5.0, "Use laser returns up to this range, and clear free space up to it along beams with no "
        "return (0 = the scan's range_max; RTAB-Map's Grid/RangeMax default: farther returns are "
        "noisier and cost ray casting time); depth grid: depth points up to this depth (RTAB-Map's Grid/RangeMax, "
        "for both)", "m")
    range_min: float = _p(
        0.0, "Ignore laser returns and depth points nearer than this: the robot's own body in view (RTAB-Map's "
        "Grid/RangeMin; 0 = the scan's range_min only)", "m")
    cloud_voxel_size: float = _p(0.05, "Voxel size of the assembled RGB-D point cloud", "m")
    cloud_decimation: int = _p(4, "Use every n-th depth pixel in each direction for the point cloud", "px")
    sensor: str = _p(
        "auto", "What the occupancy grid is made from (RTAB-Map's Grid/Sensor: 0 laser, 1 depth, 2 both; "
        "Grid/FromDepth): laser (the nodes' laser scans), depth (the points of their depth images), both, or "
        "auto (each node's laser scan when it has one, else its depth image: a laser robot's map is its "
        "laser's, a camera-only map its depth images'; RTAB-Map's own default is depth)")
    depth_decimation: int = _p(
        4, "Depth grid: use every n-th depth pixel in each direction (RTAB-Map's Grid/DepthDecimation)", "px")
    max_ground_height: float = _p(
        0.0, "Depth grid: points at or below this height (z in the map frame) are ground, free cells; above "
        "it, obstacles (RTAB-Map's Grid/MaxGroundHeight; 0 = grid.resolution, as RTAB-Map without its normals "
        "segmentation, which this grid does not do). Heights are map-frame z (RTAB-Map's "
        "Grid/MapFrameProjection): the map frame is the root node's odometry frame, whose origin a wheeled "
        "robot's base starts on the floor at, and a recording with odometry in a room frame (motion capture, "
        "tum2bag) has its floor at 0", "m")
    min_ground_height: float = _p(
        0.0, "Depth grid: points below this height are dropped (noise under the floor; RTAB-Map's "
        "Grid/MinGroundHeight; 0 = no limit)", "m")
    max_obstacle_height: float = _p(
        0.0, "Depth grid: points above this height are dropped (a ceiling, a table top the robot passes under; "
        "RTAB-Map's Grid/MaxObstacleHeight; 0 = no limit)", "m")

    def __post_init__(self) -> None:
        _check(self.resolution > 0, "grid.resolution", self.resolution, "> 0")
        _check(self.range_max >= 0, "grid.range_max", self.range_max, ">= 0")
        _check(self.range_min >= 0 and (self.range_max == 0 or self.range_min < self.range_max), "grid.range_min",
               self.range_min, f">= 0 and below grid.range_max ({self.range_max})")
        _check(self.sensor in GRID_SENSORS, "grid.sensor", self.sensor, " or ".join(GRID_SENSORS))
        _check(self.depth_decimation >= 1, "grid.depth_decimation", self.depth_decimation, ">= 1")
        _check(self.max_ground_height >= 0, "grid.max_ground_height", self.max_ground_height, ">= 0")
        _check(self.max_obstacle_height == 0 or self.max_obstacle_height > self.ground_height,
               "grid.max_obstacle_height", self.max_obstacle_height,
               f"0 (no limit) or above the ground height {self.ground_height} m")
        _check(self.min_ground_height == 0 or self.min_ground_height < self.ground_height,
               "grid.min_ground_height", self.min_ground_height,
               f"0 (no limit) or below the ground height {self.ground_height} m")
        _check(self.cloud_voxel_size > 0, "grid.cloud_voxel_size", self.cloud_voxel_size, "> 0")
        _check(self.cloud_decimation >= 1, "grid.cloud_decimation", self.cloud_decimation, ">= 1")

    @property
    def ground_height(self) -> float:
        """Height (m, map-frame z) up to which depth points are ground: max_ground_height, or the
        cell size when it is 0 (RTAB-Map's passthrough segmentation)."""
        return self.max_ground_height if self.max_ground_height > 0 else self.resolution


@dataclass(frozen=True)
class SyncParams:
    """The one synchroniser shared by the bag reader and the node."""

    rate_hz: float = _p(1.0, "Detection rate: at most one frame per period (0 = every set)", "Hz")
    approx_sync: bool = _p(True, "Approximate time: nearest stamps within the tolerance (else equal stamps)")
    tolerance_s: float = _p(0.1, "Largest stamp difference between the messages of one frame", "s")
    queue_size: int = _p(10, "Messages buffered per topic while waiting for the others", "messages")
    min_valid_depth_ratio: float = _p(
        0.01, "A frame whose depth image has fewer valid pixels (finite, > 0) than this fraction is dropped "
        "as bad input (an all-NaN or all-zero depth would give a location with no 3D word)", "ratio")
    min_valid_scan_ratio: float = _p(
        0.01, "A frame whose laser scan has fewer valid returns (finite, in [range_min, range_max)) than "
        "this fraction of its beams is dropped as bad input (at least one return is always required)", "ratio")

    def __post_init__(self) -> None:
        _check(self.rate_hz >= 0, "sync.rate_hz", self.rate_hz, ">= 0")
        _check(self.tolerance_s >= 0, "sync.tolerance_s", self.tolerance_s, ">= 0")
        _check(self.queue_size >= 1, "sync.queue_size", self.queue_size, ">= 1")
        _check(0 <= self.min_valid_depth_ratio <= 1, "sync.min_valid_depth_ratio", self.min_valid_depth_ratio,
               "in [0, 1]")
        _check(0 <= self.min_valid_scan_ratio <= 1, "sync.min_valid_scan_ratio", self.min_valid_scan_ratio,
               "in [0, 1]")


@dataclass(frozen=True)
class NodeParams:
    """The ROS 2 node's own parameters (declared under their plain names, e.g. ``frame_id``)."""

    database_path: str = _p("~/.ros/rtabmap_ros2.db", "Long-term memory database (reopened if it exists)")
    delete_db_on_start: bool = _p(False, "Delete the database at start instead of continuing it")
    frame_id: str = _p("base_link", "Robot base frame")
    map_frame_id: str = _p("map", "Map frame of the published map")
    odom_frame_id: str = _p("odom", "Odometry frame")
    export_dir: str = _p("~/.ros/rtabmap_ros2_exports", "Folder of export_global_map's time-stamped exports")
    subscribe_rgb: bool = _p(True, "Subscribe to rgb/image and rgb/camera_info")
    subscribe_depth: bool = _p(True, "Subscribe to depth/image")
    subscribe_scan: bool = _p(True, "Subscribe to scan")
    qos: str = _p("auto", "QoS of the subscriptions: auto (per topic, reliable when every publisher is reliable, "
                          "else best effort; re-checked when publishers appear), reliable or sensor_data "
                          "(best effort)")
    image_transport: str = _p("auto", "Images: auto (whichever of rgb/image or rgb/image/compressed, depth/image "
                                      "or depth/image/compressedDepth is published), raw or compressed")
    topic_timeout_s: float = _p(5.0, "Warn once when an expected topic has been silent this long", "s")
    base_to_laser: tuple = _p((0.0, 0.0, 0.0, 0.0, 0.0, 0.0),
                              "Laser mount [x, y, z, roll, pitch, yaw] in frame_id, used without tf2 (pip "
                              "install) or when set", "m, rad")
    base_to_camera: tuple = _p((0.0, 0.0, 0.0, -HALF_PI, 0.0, -HALF_PI),
                               "Mount of the RGB image's optical frame [x, y, z, roll, pitch, yaw] in frame_id "
                               "(default: at the base origin, optical z forward), used without tf2 or when set",
                               "m, rad")
    wait_for_transform: float = _p(0.2, "With tf2: longest wait for frame_id -> a message's header.frame_id", "s")
    publish_tf: bool = _p(True, "With tf2: broadcast map_frame_id -> odom_frame_id")
    tf_publish_rate: float = _p(20.0, "Rate of the map -> odom broadcast (also while paused)", "Hz")
    tf_delay: float = _p(0.05, "The map -> odom transform is stamped now + tf_delay", "s")
    localization: bool = _p(False, "Start in localization mode (RTAB-Map: Mem/IncrementalMemory false)")
    service_timeout_s: float = _p(10.0, "Longest wait of a service for the worker (busy with a frame or a "
                                        "command) before it answers with an error", "s")

    def __post_init__(self) -> None:
        _check(self.qos in NODE_QOS, "qos", self.qos, " or ".join(NODE_QOS))
        _check(self.image_transport in NODE_IMAGE_TRANSPORTS, "image_transport", self.image_transport,
               " or ".join(NODE_IMAGE_TRANSPORTS))
        _check(self.topic_timeout_s > 0, "topic_timeout_s", self.topic_timeout_s, "> 0")
        for name in ("base_to_laser", "base_to_camera"):
            value = getattr(self, name)
            _check(len(value) == 6 and all(math.isfinite(v) for v in value), name, value,
                   "6 finite numbers [x, y, z, roll, pitch, yaw]")
        _check(self.wait_for_transform >= 0, "wait_for_transform", self.wait_for_transform, ">= 0")
        _check(self.tf_publish_rate > 0, "tf_publish_rate", self.tf_publish_rate, "> 0 (publish_tf turns it off)")
        _check(self.service_timeout_s > 0, "service_timeout_s", self.service_timeout_s, "> 0")


@dataclass(frozen=True)
class Params:
    """All parameters, one section per module."""

    features: FeatureParams = field(default_factory=FeatureParams)
    vocabulary: VocabularyParams = field(default_factory=VocabularyParams)
    memory: MemoryParams = field(default_factory=MemoryParams)
    bayes: BayesParams = field(default_factory=BayesParams)
    registration: RegistrationParams = field(default_factory=RegistrationParams)
    graph: GraphParams = field(default_factory=GraphParams)
    grid: GridParams = field(default_factory=GridParams)
    sync: SyncParams = field(default_factory=SyncParams)
    node: NodeParams = field(default_factory=NodeParams)

    # -- reading -------------------------------------------------------------------------------
    @classmethod
    def from_mapping(cls, values: Mapping[str, Any], base: "Params | None" = None) -> "Params":
        """Parameters from a (possibly nested, possibly ROS ``ros__parameters``) mapping.

        A ROS 2 parameter file is read as the node reads it: an rtabmap_ros parameter with no
        equivalent here (``Reg/Strategy``, ``subscribe_rgbd``, ...) is left out with one
        warning naming them all, so an rtabmap_ros launch's file works as it is; an unknown dotted
        name (a typo of ours) is an error in any file."""
        params = base if base is not None else cls()
        unwrapped = _unwrap_ros(values)
        ignored = []
        for name, value in flatten(unwrapped).items():
            if unwrapped is not values and "." not in name and not known_name(name):
                ignored.append(name)
                continue
            params = params.with_value(name, value)
        if ignored:
            logging.getLogger(__name__).warning(
                "ROS parameter file: %s ignored (rtabmap_ros parameters with no equivalent here; "
                "rtabmap-ros2 params lists every parameter with its RTAB-Map name)", ", ".join(sorted(ignored)))
        return params

    @classmethod
    def from_stored(cls, values: Mapping[str, Any]) -> "Params":
        """The parameters a database was made with: as :meth:`from_mapping`, but a parameter removed
        since (:data:`REMOVED_PARAMETERS`) is left out with a warning, so that an older map still
        exports, reports and merges."""
        flat = flatten(_unwrap_ros(values))
        removed = sorted(name for name in flat if name in REMOVED_PARAMETERS)
        if removed:
            logging.getLogger(__name__).warning(
                "the database's parameters %s no longer exist (made by an older version): left out", ", ".join(removed))
        return cls.from_mapping({k: v for k, v in flat.items() if k not in REMOVED_PARAMETERS})

    @classmethod
    def from_yaml(cls, path: str | os.PathLike, base: "Params | None" = None) -> "Params":
        """Parameters from a YAML file (plain nested keys, or a ROS 2 parameter file)."""
        import yaml   # here, not at import: 10 ms of every command that reads no YAML (optimize)

        path = Path(path).expanduser()
        try:
            text = path.read_text()
        except OSError as exc:
            raise ParameterError(f"cannot read parameter file {path}: {exc.strerror}") from exc
        try:
            data = yaml.safe_load(text) or {}
        except yaml.YAMLError as exc:
            raise ParameterError(f"parameter file {path} is not valid YAML: {exc}") from exc
        if not isinstance(data, Mapping):
            raise ParameterError(f"parameter file {path} must hold a mapping, not {type(data).__name__}")
        return cls.from_mapping(data, base)

    def with_overrides(self, assignments: list[str] | tuple[str, ...]) -> "Params":
        """Apply ``NAME=VALUE`` strings (``--set`` on the command line); values are parsed as YAML."""
        import yaml

        params = self
        for text in assignments:
            if "=" not in text:
                raise ParameterError(f"--set {text!r}: expected NAME=VALUE, e.g. Mem/STMSize=30")
            name, raw = text.split("=", 1)
            try:
                value = yaml.safe_load(raw) if raw.strip() else ""
            except yaml.YAMLError:
                value = raw
            params = params.with_value(name.strip(), value)
        return params

    def with_value(self, name: str, value: Any) -> "Params":
        """A copy with one parameter changed; ``name`` may be dotted, an RTAB-Map name or a node name."""
        if name in REMOVED_AS_DEFAULT and value == REMOVED_AS_DEFAULT[name] and not isinstance(value, str):
            logging.getLogger(__name__).warning("parameter %s no longer exists; %r is what the code always does now: "
                                                "ignored (%s)", name, value, REMOVED_PARAMETERS[name])
            return self
        dotted, value = resolve_name(name, value)
        section_name, field_name = dotted.split(".", 1)
        section = getattr(self, section_name)
        coerced = _coerce(dotted, getattr(section, field_name), value)
        try:
            new_section = replace(section, **{field_name: coerced})
        except TypeError as exc:  # pragma: no cover - replace only fails on programming errors
            raise ParameterError(f"{name}: {exc}") from exc
        return replace(self, **{section_name: new_section})

    # -- writing -------------------------------------------------------------------------------
    def to_dict(self) -> dict[str, dict[str, Any]]:
        """Nested plain dict (tuples as lists), suitable for YAML."""
        out: dict[str, dict[str, Any]] = {}
        for sec in fields(self):
            section = getattr(self, sec.name)
            out[sec.name] = {f.name: _plain(getattr(section, f.name)) for f in fields(section)}
        return out

    def to_yaml(self, path: str | os.PathLike) -> None:
        """Write the parameters actually used (tools write them next to their results)."""
        import yaml

        Path(path).write_text(yaml.safe_dump(self.to_dict(), sort_keys=False))

    def public_items(self) -> Iterator[tuple[str, Any, str, str]]:
        """(public name, value, doc, unit) per field: ``section.field``, or ``field`` for the node."""
        for sec in fields(self):
            section = getattr(self, sec.name)
            for f in fields(section):
                public = f.name if sec.name == "node" else f"{sec.name}.{f.name}"
                yield public, _plain(getattr(section, f.name)), f.metadata.get("doc", ""), f.metadata.get("unit", "")


# RTAB-Map's parameter names -> (dotted name, conversion from RTAB-Map's unit to ours).
RTABMAP_ALIASES: dict[str, tuple[str, Any]] = {
    "Mem/IncrementalMemory": ("node.localization", lambda v: not _to_bool("Mem/IncrementalMemory", v)),
    "Mem/STMSize": ("memory.stm_size", int),
    "Mem/RehearsalSimilarity": ("memory.rehearsal_similarity", float),
    "Mem/RecentWmRatio": ("memory.recent_wm_ratio", float),
    "Mem/RehearsalMaxDistance": ("memory.rehearsal_max_distance", float),
    "Mem/RehearsalMaxAngle": ("memory.rehearsal_max_angle", float),
    "Mem/RehearsalIdUpdatedToNewOne": ("memory.rehearsal_id_updated_to_new_one",
                                       lambda v: _to_bool("Mem/RehearsalIdUpdatedToNewOne", v)),
    "Mem/RehearsalWeightIgnoredWhileMoving": ("memory.rehearsal_weight_ignored_while_moving",
                                              lambda v: _to_bool("Mem/RehearsalWeightIgnoredWhileMoving", v)),
    "Kp/BadSignRatio": ("memory.bad_signature_ratio", float),
    "Rtabmap/TimeThr": ("memory.time_threshold_ms", float),
    "Rtabmap/MaxRetrieved": ("memory.max_retrieved", int),
    "Rtabmap/MemoryThr": ("memory.max_wm_size", int),
    "RGBD/MaxLocalRetrieved": ("memory.max_local_retrieved", int),
    "RGBD/LocalImmunizationRatio": ("memory.local_immunization_ratio", float),
    "RGBD/LocalRadius": ("memory.local_radius", float),
    "Rtabmap/LoopThr": ("bayes.loop_threshold", float),
    "Bayes/VirtualPlacePriorThr": ("bayes.virtual_place_prior", float),
    "Kp/NndrRatio": ("vocabulary.nndr", float),
    "Kp/MinDepth": ("features.min_depth", float),
    "Kp/MaxDepth": ("features.max_depth", float),
    "Mem/DepthAsMask": ("features.depth_as_mask", lambda v: _to_bool("Mem/DepthAsMask", v)),
    "Kp/NNStrategy": ("vocabulary.index", lambda v: _NN_STRATEGIES.get(int(v), f"Kp/NNStrategy {v}")),
    "Kp/NewWordsComparedTogether": ("vocabulary.new_words_compared_together",
                                    lambda v: _to_bool("Kp/NewWordsComparedTogether", v)),
    "Kp/TfIdfLikelihoodUsed": ("bayes.likelihood",
                               lambda v: "tf_idf" if _to_bool("Kp/TfIdfLikelihoodUsed", v) else "eq1"),
    "Rtabmap/LoopRatio": ("bayes.loop_ratio", float),
    "VhEp/Enabled": ("bayes.epipolar_verification", lambda v: _to_bool("VhEp/Enabled", v)),
    "VhEp/MatchCountMin": ("bayes.epipolar_min_matches", int),
    "VhEp/RansacParam1": ("bayes.epipolar_max_distance", float),
    "VhEp/RansacParam2": ("bayes.epipolar_confidence", float),
    "Kp/MaxFeatures": ("features.max_features", int),
    "Kp/DetectorStrategy": ("features.detector", lambda v: _DETECTOR_STRATEGIES.get(int(v), str(v))),
    "GFTT/MinDistance": ("features.gftt_min_distance_px", float),
    "Kp/RoiRatios": ("features.roi_ratios", lambda v: tuple(float(x) for x in str(v).split())),
    "SURF/HessianThreshold": ("features.response_threshold", float),
    "Vis/MinInliers": ("registration.min_inliers", int),
    "Vis/InlierDistance": ("registration.inlier_distance", float),
    "Vis/Iterations": ("registration.ransac_iterations", int),
    "Vis/EstimationType": ("registration.estimation",
                           lambda v: _ESTIMATION_TYPES.get(int(v), f"Vis/EstimationType {v}")),
    "Vis/PnPReprojError": ("registration.pnp_reprojection_error", float),
    "Vis/PnPRefineIterations": ("registration.pnp_refine_iterations", int),
    "Vis/PnPMaxVariance": ("registration.pnp_max_variance", float),
    "Vis/BundleAdjustment": ("registration.bundle_adjustment", lambda v: int(v) > 0),
    "Vis/CorGuessWinSize": ("registration.guided_window", float),
    "Vis/MinDepth": ("registration.min_depth", float),
    "Vis/MaxDepth": ("registration.max_depth", float),
    "Reg/Force3DoF": ("registration.planar", lambda v: _to_bool("Reg/Force3DoF", v)),
    "RGBD/NeighborLinkRefining": ("registration.neighbor_link_refining",
                                  lambda v: _to_bool("RGBD/NeighborLinkRefining", v)),
    "Icp/MaxCorrespondenceDistance": ("registration.icp_max_correspondence_distance", float),
    "Icp/Iterations": ("registration.icp_iterations", int),
    "Optimizer/Iterations": ("graph.iterations", int),
    "Optimizer/Robust": ("graph.robust", lambda v: _to_bool("Optimizer/Robust", v)),
    "RGBD/OptimizeMaxError": ("graph.optimize_max_error", float),
    "RGBD/ProximityBySpace": ("graph.proximity_by_space", lambda v: _to_bool("RGBD/ProximityBySpace", v)),
    "RGBD/ProximityMaxGraphDepth": ("graph.proximity_max_graph_depth", int),
    "RGBD/ProximityMaxPaths": ("graph.proximity_max_paths", int),
    "RGBD/ProximityPathFilteringRadius": ("graph.proximity_filtering_radius", float),
    "RGBD/ProximityAngle": ("graph.proximity_angle", float),
    "RGBD/NewMapOdomChangeDistance": ("graph.odom_reset_jump", float),
    "RGBD/LinearUpdate": ("graph.linear_update", float),
    "RGBD/AngularUpdate": ("graph.angular_update", float),
    "Grid/CellSize": ("grid.resolution", float),
    "Grid/RangeMax": ("grid.range_max", float),
    "Grid/RangeMin": ("grid.range_min", float),
    "Grid/Sensor": ("grid.sensor", lambda v: _GRID_SENSORS.get(int(v), f"Grid/Sensor {v}")),
    "Grid/FromDepth": ("grid.sensor", lambda v: "depth" if _to_bool("Grid/FromDepth", v) else "laser"),
    "Grid/DepthDecimation": ("grid.depth_decimation", int),
    "Grid/MaxGroundHeight": ("grid.max_ground_height", float),
    "Grid/MinGroundHeight": ("grid.min_ground_height", float),
    "Grid/MaxObstacleHeight": ("grid.max_obstacle_height", float),
    "Rtabmap/DetectionRate": ("sync.rate_hz", float),
    # The node's historical names for synchroniser settings (rtabmap_ros uses these).
    "detection_rate": ("sync.rate_hz", float),
    "approx_sync": ("sync.approx_sync", lambda v: _to_bool("approx_sync", v)),
    "sync_queue_size": ("sync.queue_size", int),
    "queue_size": ("sync.queue_size", int),   # rtabmap_ros' name before sync_queue_size (deprecated there)
    "approx_sync_max_interval": ("sync.tolerance_s", float),
}

# Kp/NNStrategy values with an equivalent here (RTAB-Map: 0 linear FLANN and 3-4 brute force, exact;
# 1 FLANN kd-trees; 2 LSH, not available).
_NN_STRATEGIES = {0: "flat", 1: "kdtree", 3: "flat", 4: "flat"}
# Vis/EstimationType values with an equivalent here (RTAB-Map: 0 3D->3D, 1 3D->2D PnP, 2 2D->2D epipolar, absent).
_ESTIMATION_TYPES = {0: "3d", 1: "pnp"}
# Grid/Sensor values (RTAB-Map: 0 laser scan, 1 depth images, 2 both).
_GRID_SENSORS = {0: "laser", 1: "depth", 2: "both"}
# Kp/DetectorStrategy values with an equivalent here (RTAB-Map: 2=ORB, 1=SIFT, 8=GFTT/ORB).
_DETECTOR_STRATEGIES = {2: "orb", 1: "sift", 8: "gftt_orb"}


# Parameters that were removed, with what to do instead: a config file written for an older version
# gets this rather than "unknown parameter".
_IVF_REMOVED = "the IVF word search was removed (issue 50): vocabulary.index is kdtree (RTAB-Map's) or flat (exact)"
REMOVED_PARAMETERS: dict[str, str] = {
    "vocabulary.ivf_min_words": _IVF_REMOVED + "; delete this key",
    "vocabulary.ivf_nprobe": _IVF_REMOVED + "; delete this key",
    "vocabulary.ivf_retrain_growth": _IVF_REMOVED + "; delete this key",
    "vocabulary.ivf_swap_frames": "renamed vocabulary.rebuild_swap_frames (the kd-trees' background rebuild; "
                                  "the IVF word search was removed, issue 50)",
    **{f"bayes.{name}": f"not in RTAB-Map, removed in issue 48 ({what} lost against RTAB-Map on real images, "
                        "docs/benchmarks.md); delete this key"
       for name, what in (("likelihood_trim", "the trimmed Eq. 3-4"), ("min_evidence_ratio", "the evidence check"),
                          ("refine_hops", "the hypothesis refinement"), ("refine_window", "the hypothesis refinement"),
                          ("align_radius", "the view alignment"),
                          ("discount_repeated_evidence", "the repeated evidence discount"),
                          ("loop_closure_hop", "the loop closure hop; RTAB-Map's neighbourhoods are kept"))},
    "features.roll_normalization": "not in RTAB-Map, removed in issue 48 (it lifted Lip6Outdoor but lost where a "
                                   "rolled photo recurs, make_sequence with Lip6's photos, docs/benchmarks.md); "
                                   "delete this key",
    "bayes.hypothesis_hops": "not in RTAB-Map, removed in issue 48 (no row of the generalisation table on RTAB-Map's "
                             "detection shows it does not lose; the posterior's peak names the loop closure, as in "
                             "RTAB-Map): delete this key",
    "features.describable_corners_only": "not in RTAB-Map, removed in issue 48 (with GFTT/MinDistance 5 it gave false "
                                         "loop closures on RTAB-Map's 84 images, docs/benchmarks.md); GFTT keeps the "
                                         "strongest corners of the whole image as RTAB-Map's does: delete this key",
}


# Removed parameters whose value here is what the code now always does: a config file written for an older
# version that sets one of them so (RTAB-Map's behaviour) still loads, with a warning.
REMOVED_AS_DEFAULT: dict[str, Any] = {"features.roll_normalization": False, "bayes.hypothesis_hops": 0}


def known_name(name: str) -> bool:
    """Whether ``name`` is a parameter here under any accepted spelling (removed ones included:
    they get their own message)."""
    return name in REMOVED_PARAMETERS or name in RTABMAP_ALIASES or _field_name(name) is not None


def _field_name(name: str) -> str | None:
    """The dotted name of a node parameter's plain name or of a dotted name; None if neither."""
    if "." not in name and name in {f.name for f in fields(NodeParams)}:
        return f"node.{name}"
    section_name, _, field_name = name.partition(".")
    sections = {f.name: f for f in fields(Params)}
    if section_name in sections and field_name:
        section_type = sections[section_name].default_factory  # type: ignore[misc]
        if field_name in {f.name for f in fields(section_type)}:
            return name
    return None


def resolve_name(name: str, value: Any) -> tuple[str, Any]:
    """Map any accepted spelling of a parameter to its dotted name, converting the value's unit."""
    if name in REMOVED_PARAMETERS:
        raise ParameterError(f"parameter {name!r} no longer exists: {REMOVED_PARAMETERS[name]}")
    if name in RTABMAP_ALIASES:
        dotted, convert = RTABMAP_ALIASES[name]
        try:
            return dotted, convert(value)
        except (TypeError, ValueError) as exc:
            raise ParameterError(f"{name}={value!r} cannot be converted for {dotted}: {exc}") from exc
    dotted = _field_name(name)
    if dotted is not None:
        return dotted, value
    raise ParameterError(
        f"unknown parameter {name!r}: use a dotted name such as memory.stm_size, an RTAB-Map name "
        f"such as Mem/STMSize, or a node parameter such as database_path"
    )


def _coerce(name: str, current: Any, value: Any) -> Any:
    """Convert ``value`` to the type of the field's current value, with a clear error."""
    try:
        if isinstance(current, bool):
            return _to_bool(name, value)
        if isinstance(current, int):
            if isinstance(value, float) and not value.is_integer():
                raise ValueError("not an integer")
            return int(value)
        if isinstance(current, float):
            return float(value)
        if isinstance(current, tuple):
            items = value.split() if isinstance(value, str) else list(value)
            if len(items) != len(current):
                raise ValueError(f"expected {len(current)} values")
            return tuple(type(c)(v) for c, v in zip(current, items))
        if isinstance(current, str):
            return str(value)
    except (TypeError, ValueError) as exc:
        raise ParameterError(f"{name}={value!r} is invalid: {exc}") from exc
    return value


def _to_bool(name: str, value: Any) -> bool:
    if isinstance(value, bool):
        return value
    text = str(value).strip().lower()
    if text in ("true", "1", "yes", "on"):
        return True
    if text in ("false", "0", "no", "off"):
        return False
    raise ParameterError(f"{name}={value!r} is not a boolean (true/false)")


def _plain(value: Any) -> Any:
    return list(value) if isinstance(value, tuple) else value


def _unwrap_ros(values: Mapping[str, Any]) -> Mapping[str, Any]:
    """Accept a ROS 2 parameter file: ``node_name: {ros__parameters: {...}}``."""
    for value in values.values():
        if isinstance(value, Mapping) and "ros__parameters" in value:
            return value["ros__parameters"] or {}
    if "ros__parameters" in values:
        return values["ros__parameters"] or {}
    return values


def flatten(values: Mapping[str, Any], separator: str = ".", prefix: str = "") -> dict[str, Any]:
    """Nested mappings to flat names joined by ``separator`` (lists kept as values).

    With ".", RTAB-Map names (with '/') are kept whole: ``{"Mem": {"STMSize": 30}}`` gives
    ``Mem.STMSize`` but ``{"Mem/STMSize": 30}`` stays ``Mem/STMSize``.
    """
    out: dict[str, Any] = {}
    for key, value in values.items():
        name = f"{prefix}{key}"
        if isinstance(value, Mapping):
            out.update(flatten(value, separator, f"{name}{separator}"))
        else:
            out[name] = value
    return out


def default_config_path(name: str = "rtabmap.yaml") -> Path | None:
    """Locate a shipped config file: ament share dir, the source tree, or the pip data prefix."""
    import sys

    candidates = [Path(__file__).resolve().parents[2] / "config" / name,
                  Path(sys.prefix) / "share" / "rtabmap_ros2" / "config" / name]
    try:  # in a ROS 2 workspace
        from ament_index_python.packages import get_package_share_directory

        candidates.insert(0, Path(get_package_share_directory("rtabmap_ros2")) / "config" / name)
    except Exception:  # noqa: BLE001 - ament not installed or package not in the index
        pass
    for path in candidates:
        if path.is_file():
            return path
    return None


__all__ = [
    "BayesParams", "FeatureParams", "GraphParams", "GridParams", "MemoryParams", "NodeParams", "Params",
    "RTABMAP_ALIASES", "RegistrationParams", "SyncParams", "VocabularyParams", "default_config_path", "flatten",
    "resolve_name",
]
