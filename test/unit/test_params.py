"""Typed parameters: defaults, RTAB-Map aliases, YAML (plain and ROS), --set, errors."""

from __future__ import annotations

from pathlib import Path

import pytest

from rtabmap_ros2.core.params import Params, default_config_path
from rtabmap_ros2.errors import ParameterError


def test_defaults_are_the_papers_table_i():
    """Table I, except where measurements chose RTAB-Map's values (see the fields' docs)."""
    p = Params()
    assert p.memory.stm_size == 30
    assert p.memory.rehearsal_similarity == pytest.approx(0.6)  # paper 0.20; RTAB-Map 0.6 (see its doc)
    assert p.memory.recent_wm_ratio == pytest.approx(0.20)
    assert p.memory.bad_signature_ratio == pytest.approx(0.5)  # paper 0.25; RTAB-Map's Kp/BadSignRatio
    assert p.memory.time_threshold_ms == pytest.approx(700.0)
    assert p.memory.max_retrieved == 2
    assert p.vocabulary.nndr == pytest.approx(0.8)
    assert p.features.max_features == 400
    assert p.bayes.sigma == pytest.approx(1.6) and p.bayes.neighborhood == 16
    # Hypothesis selection and validation as RTAB-Map's defaults (issues 32 and 48: its epipolar check
    # off, its virtual place prior, its likelihood, its rehearsal, its approximate word search and its
    # features).
    assert p.bayes.loop_ratio == 0.0 and not p.bayes.epipolar_verification
    assert p.bayes.virtual_place_prior == pytest.approx(0.9) and p.bayes.epipolar_min_matches == 8
    assert p.bayes.likelihood == "tf_idf" and p.memory.rehearsal_similarity == pytest.approx(0.6)
    assert p.vocabulary.index == "kdtree"
    assert p.features.detector == "gftt_orb" and p.features.gftt_min_distance_px == pytest.approx(7.0)


def test_defaults_are_rtabmaps_detection():
    """Issue 48's rule left none of the defaults' additions: detect's defaults are the conformance
    setting (config/rtabmap_reference.yaml, RTAB-Map's own values) in every detection section."""
    reference = Params.from_yaml(Path(__file__).resolve().parents[2] / "config" / "rtabmap_reference.yaml")
    defaults = Params()
    for section in ("features", "vocabulary", "memory", "bayes"):
        assert getattr(defaults, section) == getattr(reference, section), section


def test_one_detector_for_detect_map_and_the_node():
    """config/rtabmap.yaml (map, demo, the node) keeps detect's loop closure detection (issue 32) but for
    the values bench_slam.py measured for SLAM (the raw score, RTAB-Map's choice of the posterior's peak,
    the new words' comparison, the kd-trees' later rebuild swap)."""
    from dataclasses import replace

    from rtabmap_ros2.core.params import default_config_path

    slam, defaults = Params.from_yaml(default_config_path()), Params()
    assert slam.bayes == replace(defaults.bayes, likelihood="eq1")
    assert slam.vocabulary == replace(defaults.vocabulary, new_words_compared_together=False, rebuild_swap_frames=300)
    assert slam.features == defaults.features


@pytest.mark.parametrize("alias, value, section, field, expected", [
    ("Mem/STMSize", "15", "memory", "stm_size", 15),
    ("RGBD/LinearUpdate", "0.05", "graph", "linear_update", 0.05),
    ("RGBD/AngularUpdate", "0.1", "graph", "angular_update", 0.1),
    ("Mem/RehearsalSimilarity", "0.45", "memory", "rehearsal_similarity", 0.45),
    ("Kp/TfIdfLikelihoodUsed", "false", "bayes", "likelihood", "eq1"),
    ("GFTT/MinDistance", "7", "features", "gftt_min_distance_px", 7.0),
    ("Kp/TfIdfLikelihoodUsed", "true", "bayes", "likelihood", "tf_idf"),
    ("Kp/NewWordsComparedTogether", "false", "vocabulary", "new_words_compared_together", False),
    ("Rtabmap/LoopRatio", "0.5", "bayes", "loop_ratio", 0.5),
    ("VhEp/Enabled", "false", "bayes", "epipolar_verification", False),
    ("VhEp/MatchCountMin", "12", "bayes", "epipolar_min_matches", 12),
    ("VhEp/RansacParam1", "2", "bayes", "epipolar_max_distance", 2.0),
    ("VhEp/RansacParam2", "0.95", "bayes", "epipolar_confidence", 0.95),
    ("Bayes/VirtualPlacePriorThr", "0.8", "bayes", "virtual_place_prior", 0.8),
    ("Mem/RehearsalWeightIgnoredWhileMoving", "true", "memory", "rehearsal_weight_ignored_while_moving", True),
    ("Mem/RehearsalIdUpdatedToNewOne", "true", "memory", "rehearsal_id_updated_to_new_one", True),
    ("Mem/RehearsalMaxDistance", "0.1", "memory", "rehearsal_max_distance", 0.1),
    ("Mem/RehearsalMaxAngle", "0.2", "memory", "rehearsal_max_angle", 0.2),
    ("Mem/RecentWmRatio", 0.3, "memory", "recent_wm_ratio", 0.3),
    ("Rtabmap/LoopThr", "0.2", "bayes", "loop_threshold", 0.2),
    ("Rtabmap/TimeThr", "500", "memory", "time_threshold_ms", 500.0),
    ("Rtabmap/MaxRetrieved", 3, "memory", "max_retrieved", 3),
    ("Rtabmap/MemoryThr", "500", "memory", "max_wm_size", 500),
    ("Kp/NndrRatio", "0.7", "vocabulary", "nndr", 0.7),
    ("Kp/MaxFeatures", "200", "features", "max_features", 200),
    ("Kp/BadSignRatio", "0.5", "memory", "bad_signature_ratio", 0.5),
    ("Kp/DetectorStrategy", "2", "features", "detector", "orb"),
    ("Reg/Force3DoF", "false", "registration", "planar", False),
    ("Grid/Sensor", "0", "grid", "sensor", "laser"),
    ("Grid/Sensor", 1, "grid", "sensor", "depth"),
    ("Grid/Sensor", "2", "grid", "sensor", "both"),
    ("Grid/FromDepth", "true", "grid", "sensor", "depth"),
    ("Grid/FromDepth", "false", "grid", "sensor", "laser"),
    ("Grid/DepthDecimation", "2", "grid", "depth_decimation", 2),
    ("Grid/MaxObstacleHeight", "1.5", "grid", "max_obstacle_height", 1.5),
    ("Grid/MaxGroundHeight", "0.1", "grid", "max_ground_height", 0.1),
    ("Grid/MinGroundHeight", "-0.5", "grid", "min_ground_height", -0.5),
    ("Grid/RangeMin", "0.3", "grid", "range_min", 0.3),
    ("Mem/DepthAsMask", "true", "features", "depth_as_mask", True),
    ("Kp/MinDepth", "0.4", "features", "min_depth", 0.4),
    ("Kp/MaxDepth", "4", "features", "max_depth", 4.0),
    ("Vis/MinDepth", "0.3", "registration", "min_depth", 0.3),
    ("Vis/MaxDepth", "4.0", "registration", "max_depth", 4.0),
    ("RGBD/ProximityBySpace", "true", "graph", "proximity_by_space", True),
    ("RGBD/ProximityMaxGraphDepth", "20", "graph", "proximity_max_graph_depth", 20),
    ("RGBD/ProximityMaxPaths", "1", "graph", "proximity_max_paths", 1),
    ("RGBD/ProximityPathFilteringRadius", "0.5", "graph", "proximity_filtering_radius", 0.5),
    ("RGBD/ProximityAngle", "30", "graph", "proximity_angle", 30.0),
    ("queue_size", "20", "sync", "queue_size", 20),
    ("sync_queue_size", 15, "sync", "queue_size", 15),
])
def test_rtabmap_aliases_map_to_typed_fields(alias, value, section, field, expected):
    p = Params().with_value(alias, value)
    assert getattr(getattr(p, section), field) == expected
    assert type(getattr(getattr(p, section), field)) is type(expected)


def test_set_overrides_accept_dotted_and_rtabmap_names_in_order():
    p = Params().with_overrides(["Mem/STMSize=12", "memory.rehearsal_similarity=0.3", "memory.stm_size=7"])
    assert p.memory.stm_size == 7
    assert p.memory.rehearsal_similarity == pytest.approx(0.3)
    assert Params().memory.stm_size == 30  # frozen: the original is unchanged


@pytest.mark.parametrize("assignment", ["memory.stm_size", "nosuch.key=1", "memory.nosuch=1", "Mem/Nosuch=2",
                                        "memory.stm_size=0", "memory.stm_size=abc", "memory.stm_size=2.5",
                                        "bayes.loop_threshold=1.5", "vocabulary.nndr=0", "VhEp/MatchCountMin=7",
                                        "features.detector=surf", "memory.keep_one_node_per_session=maybe",
                                        "Grid/Sensor=3", "grid.sensor=lidar", "Grid/MaxObstacleHeight=0.02",
                                        "Grid/MinGroundHeight=0.2"])
def test_bad_set_assignments_raise_parameter_error(assignment):
    with pytest.raises(ParameterError):
        Params().with_overrides([assignment])


def test_parameter_error_names_the_bad_value():
    with pytest.raises(ParameterError, match="stm_size.*-3"):
        Params().with_value("memory.stm_size", -3)
    with pytest.raises(ParameterError, match="unknown parameter 'memory.stmsize'"):
        Params().with_value("memory.stmsize", 3)


def test_plain_yaml(tmp_path):
    path = tmp_path / "p.yaml"
    path.write_text("memory:\n  stm_size: 12\n  time_threshold_ms: 300\nbayes:\n  loop_threshold: 0.2\n"
                    "Kp/MaxFeatures: 250\n")
    p = Params.from_yaml(path)
    assert (p.memory.stm_size, p.memory.time_threshold_ms, p.bayes.loop_threshold) == (12, 300.0, 0.2)
    assert p.features.max_features == 250


def test_ros_parameter_file_yaml(tmp_path):
    path = tmp_path / "ros.yaml"
    path.write_text("/**:\n  ros__parameters:\n    frame_id: base_footprint\n    detection_rate: 2.0\n"
                    "    memory:\n      stm_size: 9\n    Mem/RehearsalSimilarity: 0.45\n")
    p = Params.from_yaml(path)
    assert p.node.frame_id == "base_footprint"
    assert p.sync.rate_hz == 2.0
    assert p.memory.stm_size == 9 and p.memory.rehearsal_similarity == 0.45


def test_an_rtabmap_ros_parameter_file_works_as_it_is(tmp_path, caplog):
    # A launch's file names rtabmap_ros settings with no equivalent here: left out with one warning
    # naming them (the node does the same), the rest applied; a typo of a dotted name still fails.
    path = tmp_path / "rtabmap_ros.yaml"
    path.write_text("rtabmap:\n  ros__parameters:\n    frame_id: base_footprint\n    subscribe_rgbd: false\n"
                    "    RGBD/ProximityBySpace: 'true'\n    Reg/Strategy: '1'\n    RGBD/LinearUpdate: '0.05'\n"
                    "    Mem/STMSize: '12'\n")
    with caplog.at_level("WARNING"):
        p = Params.from_yaml(path)
    assert p.node.frame_id == "base_footprint" and p.memory.stm_size == 12 and p.graph.linear_update == 0.05
    assert p.graph.proximity_by_space
    assert "Reg/Strategy, subscribe_rgbd ignored" in caplog.text
    path.write_text("rtabmap:\n  ros__parameters:\n    memory.stm_sise: 3\n")
    with pytest.raises(ParameterError, match="stm_sise"):
        Params.from_yaml(path)


def test_yaml_errors(tmp_path):
    unknown = tmp_path / "u.yaml"
    unknown.write_text("memory:\n  stm_sise: 3\n")
    with pytest.raises(ParameterError, match="stm_sise"):
        Params.from_yaml(unknown)
    broken = tmp_path / "b.yaml"
    broken.write_text("memory: [1, 2\n")
    with pytest.raises(ParameterError):
        Params.from_yaml(broken)
    with pytest.raises(ParameterError):
        Params.from_yaml(tmp_path / "missing.yaml")
    scalar = tmp_path / "s.yaml"
    scalar.write_text("3\n")
    with pytest.raises(ParameterError):
        Params.from_yaml(scalar)


def test_yaml_uses_safe_load(tmp_path):
    path = tmp_path / "evil.yaml"
    path.write_text("memory:\n  stm_size: !!python/object/apply:os.system ['true']\n")
    with pytest.raises(ParameterError):
        Params.from_yaml(path)


def test_shipped_config_loads_with_the_2014_values():
    path = default_config_path("rtabmap.yaml")
    assert path is not None and path.is_file()
    p = Params.from_yaml(path)
    assert p.memory.stm_size == 10
    assert p.memory.rehearsal_similarity == pytest.approx(0.45)
    assert p.memory.time_threshold_ms == pytest.approx(700.0)
    # Planar for the wheeled robot it describes; RTAB-Map's (and the code's) default is 6 DoF.
    assert p.registration.planar and not Params().registration.planar
    assert p.grid.sensor == "auto"


def test_round_trip_through_yaml(tmp_path):
    p = Params().with_overrides(["memory.stm_size=11", "features.roi_ratios=0 0 0.1 0.4"])
    p.to_yaml(tmp_path / "out.yaml")
    again = Params.from_yaml(tmp_path / "out.yaml")
    assert again == p


def test_the_removed_ivf_parameters_say_what_replaced_them():
    """Issue 50: config files written for the IVF word search get a ParameterError naming the change."""
    with pytest.raises(ParameterError, match="renamed vocabulary.rebuild_swap_frames"):
        Params().with_value("vocabulary.ivf_swap_frames", 300)
    with pytest.raises(ParameterError, match="IVF word search was removed"):
        Params().with_overrides(["vocabulary.ivf_nprobe=32"])
    with pytest.raises(ParameterError, match="auto and ivf were removed"):
        Params().with_value("vocabulary.index", "auto")
    assert Params().with_value("vocabulary.rebuild_swap_frames", 50).vocabulary.rebuild_swap_frames == 50


def test_a_database_made_with_a_removed_parameter_still_loads(caplog):
    """Issue 48 removed bayes.likelihood_trim and the other additions: a map made before still
    exports (its stored parameters load, the removed one left out with a warning), while a config
    file naming it gets an error saying what happened."""
    stored = {"bayes": {"likelihood_trim": 0.5, "loop_threshold": 0.2, "hypothesis_hops": 1},
              "features": {"roll_normalization": True}, "memory": {"stm_size": 12}}
    with caplog.at_level("WARNING"):
        params = Params.from_stored(stored)
    assert params.bayes.loop_threshold == pytest.approx(0.2) and params.memory.stm_size == 12
    for name in ("bayes.likelihood_trim", "bayes.hypothesis_hops", "features.roll_normalization"):
        assert name in caplog.text
        with pytest.raises(ParameterError, match="removed in issue 48"):
            Params().with_value(name, 1)
    with pytest.raises(ParameterError, match="removed in issue 48"):
        Params.from_mapping(stored)


def test_a_config_switching_a_removed_addition_off_still_loads(caplog):
    """A config written for the version before issue 48's removal, as config/rtabmap_reference.yaml was,
    sets the additions off: that is what the code now always does, so it loads with a warning."""
    with caplog.at_level("WARNING"):
        params = Params.from_mapping({"features": {"roll_normalization": False, "max_features": 300},
                                      "bayes": {"hypothesis_hops": 0}})
    assert params.features.max_features == 300 and params.bayes == Params().bayes
    assert "features.roll_normalization" in caplog.text and "bayes.hypothesis_hops" in caplog.text
    assert Params().with_overrides(["features.roll_normalization=false"]) == Params()


def test_a_config_given_to_map_applies_over_the_shipped_one(tmp_path):
    # As the node's --params-file: the user's file changes what it names, the shipped SLAM settings
    # stay (they were all replaced by the dataclass defaults before).
    import argparse

    from rtabmap_ros2.cli.common_args import add_param_arguments, params_from_args

    path = tmp_path / "mine.yaml"
    path.write_text("rtabmap:\n  ros__parameters:\n    Mem/STMSize: '12'\n")
    parser = argparse.ArgumentParser()
    add_param_arguments(parser, default_config="rtabmap.yaml")
    shipped = Params.from_yaml(default_config_path())
    params = params_from_args(parser.parse_args(["--config", str(path), "--set", "Rtabmap/LoopThr=0.2"]))
    assert params.memory.stm_size == 12 and params.bayes.loop_threshold == 0.2
    assert params.registration == shipped.registration and params.vocabulary == shipped.vocabulary
    assert shipped.bayes.likelihood != Params().bayes.likelihood and params.bayes.likelihood == shipped.bayes.likelihood
    # Without a shipped config (detect), the file applies over the defaults.
    parser = argparse.ArgumentParser()
    add_param_arguments(parser)
    assert params_from_args(parser.parse_args(["--config", str(path)])) == Params().with_value("memory.stm_size", 12)
