"""Simulated multi-session recordings of a lab building (Labbé & Michaud 2014 §III imitation).

* :mod:`~rtabmap_ros2.sim.world`: the floor plan and wall textures (real scikit-image photos);
* :mod:`~rtabmap_ros2.sim.robot`: routes, driving, wheel odometry;
* :mod:`~rtabmap_ros2.sim.render`: the 2D laser and the Kinect-like RGB-D camera;
* :mod:`~rtabmap_ros2.sim.simulate`: sessions, bags, ground truth, revisits (``loops.csv``).

Quick use in tests (no bag)::

    from rtabmap_ros2.sim import build_world, make_sessions, session_frames, find_revisits
    world = build_world(seed=0)
    sessions = make_sessions(world, small=True)      # or make_sessions(world) for the 5 sessions
    frames = list(session_frames(world, sessions[0]))
    sessions[0].T_world_base                          # (N,4,4) ground truth of those frames
"""

from rtabmap_ros2.sim.render import SensorRig, kinect_camera, render_rgbd, render_scan
from rtabmap_ros2.sim.simulate import (
    SessionDataset, SessionTruth, SimulationSummary, find_revisits, make_sessions, render_frame,
    session_frames, simulate,
)
from rtabmap_ros2.sim.world import World, build_world

__all__ = [
    "World", "build_world", "SensorRig", "kinect_camera", "render_rgbd", "render_scan", "SessionTruth",
    "SessionDataset", "SimulationSummary", "make_sessions", "render_frame", "session_frames",
    "find_revisits", "simulate",
]
