"""The simulated robot: routes on the building's waypoint graph, driving, wheel odometry.

Driving: a pure-pursuit controller follows the route (shortest paths between the plan's goals)
at :data:`CONTROL_DT_S`; it slows down and turns in place when the heading error is large (door
entries, U-turns), which gives smooth turns. The robot stops for a few seconds in rooms and some
open areas (repeated images there: weights grow by rehearsal, 2013 §III-C). Poses are sampled at
1 Hz, as in 2014 §III (R = 1 s), or at another frame rate (``frame_period_s``: a driver publishing
faster than the detection rate).

Wheel odometry (:func:`wheel_odometry`): the ground-truth motion between consecutive 1 Hz
frames ``(dx, dy, dyaw)`` (previous base frame) is corrupted and integrated from identity:

* translation scaled by ``1 + n``, ``n ~ N(0, 2 %)``, plus lateral noise ``N(0, 0.5 % of d)``;
* yaw: ``dyaw * (1 + N(0, 2 %)) + N(0, (0.25 deg/m * d)) + bias * d``, with one yaw bias per
  session ``bias ~ N(0, 0.1 deg/m)`` (a slightly wrong wheel base): a decent indoor wheel
  odometry (a few degrees of heading error per 100 m). The first version used 1 deg/m and
  0.2 deg/m, several times worse than real wheel odometry;
* reset to identity at each session start (odom frame = pose of the first frame);
  :func:`reset_odometry` resets it anywhere else (a wheel driver restarted mid-session).

The covariance written in the odometry is *fixed per step*: the variance of one 1 s increment at
nominal speed (:func:`step_covariance`), since rtabmap_ros uses the odometry covariance as the
variance of the neighbour link between consecutive nodes.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import dijkstra

from rtabmap_ros2.core import transforms
from rtabmap_ros2.errors import RtabmapError
from rtabmap_ros2.sim.world import World

CONTROL_DT_S = 0.05
FRAME_PERIOD_S = 1.0
ROUTE_SPACING_M = 0.05
LOOKAHEAD_M = 0.7
HEADING_GAIN = 2.0           # rad/s per rad of heading error
MAX_YAW_RATE = 0.6           # rad/s
MAX_ACCELERATION = 0.5       # m/s^2
TURN_IN_PLACE_RAD = np.deg2rad(60.0)  # heading error above which the robot stops to turn
SPEED_RANGE_MPS = (0.45, 0.55)        # nominal speed drawn per session
STOP_DURATION_RANGE_S = (3.0, 7.0)
PROGRESS_WINDOW_M = 2.0
GOAL_TOLERANCE_M = 0.05
MAX_DRIVE_TIME_S = 3600.0

ODOM_TRANSLATION_SIGMA = 0.02          # relative
ODOM_LATERAL_SIGMA = 0.005             # relative to the distance
ODOM_ROTATION_SIGMA = 0.02             # relative to the turn
ODOM_YAW_PER_METRE_SIGMA = np.deg2rad(0.25)  # rad per metre travelled
ODOM_YAW_BIAS_SIGMA = np.deg2rad(0.1)        # rad per metre, drawn per session
ODOM_PLANAR_SIGMA = 1e-3                      # z, roll, pitch (m, rad): the robot is planar

# Session plans: goal waypoints in order (route = shortest paths between them). Names are
# World.nodes; stops happen at the goals listed in STOP_NODES. Each session starts elsewhere and
# revisits parts of earlier ones in the same and the opposite direction (2014 §III).
SESSION_PLANS = (
    ("SW", "SM", "NM", "NW", "SW", "r1", "r2", "r6"),
    ("SE", "NE", "N45", "cAn", "A_c", "cA", "NM", "c3", "r3", "NM", "SM", "r7", "SE", "r5", "c5"),
    ("L_w", "L_n", "L_c", "cL", "NW", "r8", "c4n", "r4", "c4w", "SW", "c1", "r6", "SM", "r7"),
    ("T_nw", "T_ne", "T_e", "T_m2", "T_m", "T_w", "T_sw", "T_s", "N45", "NM", "r9", "c3", "NW",
     "cL", "L_c", "L_s", "L_w", "L_n", "L_c", "cL"),
    ("r2", "SM", "cA", "A_c", "A_e", "A_n", "N45", "NE", "SE", "c7", "SM", "SW", "cL", "L_c"),
)
SMALL_SESSION_PLANS = (
    ("cL", "SW", "c2"),
    ("r1", "c1", "c2", "r2"),
)
STOP_NODES = frozenset({"r1", "r2", "r3", "r4", "r5", "r6", "r7", "r8", "r9", "L_c", "T_m", "A_c"})


@dataclass(frozen=True)
class Trajectory:
    """Ground truth of one drive, sampled at 1 Hz.

    Attributes:
        times_s: (N,) seconds since the session start.
        xy_yaw: (N,3) planar poses in the world frame (m, m, rad).
        route_xy: (M,2) the route followed (m).
        speed_mps: nominal speed.
    """

    times_s: np.ndarray
    xy_yaw: np.ndarray
    route_xy: np.ndarray
    speed_mps: float

    @property
    def poses(self) -> np.ndarray:
        """(N,4,4) ``T_world_base``."""
        return np.stack([transforms.from_xy_yaw(*p) for p in self.xy_yaw])

    @property
    def length_m(self) -> float:
        """Distance travelled (m)."""
        return float(np.linalg.norm(np.diff(self.xy_yaw[:, :2], axis=0), axis=1).sum())


def plan_route(world: World, goals: tuple[str, ...]) -> tuple[np.ndarray, list[int]]:
    """Shortest-path polyline through ``goals`` (node names): ((K,2) m, indices of the goals in it)."""
    names = list(world.nodes)
    index = {n: i for i, n in enumerate(names)}
    for g in goals:
        if g not in index:
            raise RtabmapError(f"unknown waypoint {g!r} in a session plan: use one of World.nodes")
    xy = np.array([world.nodes[n] for n in names])
    i, j = np.array([[index[a], index[b]] for a, b in world.edges]).T
    w = np.linalg.norm(xy[i] - xy[j], axis=1)
    graph = csr_matrix((np.concatenate([w, w]), (np.concatenate([i, j]), np.concatenate([j, i]))),
                       shape=(len(names), len(names)))
    path = [index[goals[0]]]
    goal_positions = [0]
    for a, b in zip(goals[:-1], goals[1:]):
        _, pred = dijkstra(graph, indices=index[a], return_predecessors=True)
        leg = [index[b]]
        while leg[-1] != index[a]:
            if pred[leg[-1]] < 0:
                raise RtabmapError(f"no route from {a!r} to {b!r} in the waypoint graph")
            leg.append(int(pred[leg[-1]]))
        path.extend(reversed(leg[:-1]))
        goal_positions.append(len(path) - 1)
    return xy[path], goal_positions


def _densify(polyline: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Resample a polyline (K,2) every ROUTE_SPACING_M: points (M,2) and the vertex -> point index."""
    pts, vertex_index = [polyline[0]], [0]
    for a, b in zip(polyline[:-1], polyline[1:]):
        n = max(1, int(np.ceil(np.linalg.norm(b - a) / ROUTE_SPACING_M)))
        t = np.linspace(0.0, 1.0, n + 1)[1:, None]
        pts.extend(a + t * (b - a))
        vertex_index.append(len(pts) - 1)
    return np.asarray(pts), np.asarray(vertex_index)


def drive(route_xy: np.ndarray, stops: dict[int, float], rng: np.random.Generator,
          speed_mps: float | None = None, frame_period_s: float = FRAME_PERIOD_S) -> Trajectory:
    """Follow a route with pure pursuit; return the ground truth sampled every ``frame_period_s``.

    Args:
        route_xy: (K,2) route vertices (m, world frame).
        stops: route vertex index -> stop duration (s) when the robot reaches it.
        rng: draws the nominal speed when ``speed_mps`` is None.
        frame_period_s: time between frames (s; 1 Hz by default), a multiple of :data:`CONTROL_DT_S`.
    """
    if speed_mps is None:
        speed_mps = float(rng.uniform(*SPEED_RANGE_MPS))
    pts, vertex_index = _densify(route_xy)
    stop_at = {int(vertex_index[k]): d for k, d in stops.items()}
    lookahead = int(round(LOOKAHEAD_M / ROUTE_SPACING_M))
    window = int(round(PROGRESS_WINDOW_M / ROUTE_SPACING_M))
    first = pts[min(lookahead, len(pts) - 1)] - pts[0]
    x, y, yaw = float(pts[0, 0]), float(pts[0, 1]), float(np.arctan2(first[1], first[0]))
    v = 0.0
    progress = 0
    stopped_until = -1.0
    done_stops: set[int] = set()
    steps_per_frame = int(round(frame_period_s / CONTROL_DT_S))
    if steps_per_frame < 1 or abs(steps_per_frame * CONTROL_DT_S - frame_period_s) > 1e-6:
        raise RtabmapError(f"frame period {frame_period_s} s is not a multiple of the control step {CONTROL_DT_S} s")
    samples, times = [], []
    step = 0
    while True:
        t = step * CONTROL_DT_S
        if step % steps_per_frame == 0:
            samples.append((x, y, yaw))
            times.append(t)
        if t > MAX_DRIVE_TIME_S:
            raise RtabmapError("the simulated robot did not reach the end of its route in an hour")
        # Progress along the route: nearest route point in a window ahead.
        lo, hi = progress, min(len(pts), progress + window)
        progress = lo + int(np.argmin(np.hypot(pts[lo:hi, 0] - x, pts[lo:hi, 1] - y)))
        for idx in stop_at:
            if idx not in done_stops and progress >= idx:
                done_stops.add(idx)
                stopped_until = t + stop_at[idx]
                v = 0.0
        at_end = progress >= len(pts) - 1 and np.hypot(pts[-1, 0] - x, pts[-1, 1] - y) < GOAL_TOLERANCE_M
        if at_end and t >= stopped_until:
            if step % steps_per_frame == 0:
                break
            step += 1
            continue
        if t < stopped_until or at_end:
            step += 1
            continue
        target = pts[min(progress + lookahead, len(pts) - 1)]
        dist_to_end = np.hypot(pts[-1, 0] - x, pts[-1, 1] - y) if progress + lookahead >= len(pts) - 1 else np.inf
        err = transforms.wrap_angle(np.arctan2(target[1] - y, target[0] - x) - yaw)
        w = float(np.clip(HEADING_GAIN * err, -MAX_YAW_RATE, MAX_YAW_RATE))
        v_target = 0.0 if abs(err) > TURN_IN_PLACE_RAD else speed_mps * np.cos(err) ** 2
        v_target = min(v_target, np.sqrt(2 * MAX_ACCELERATION * dist_to_end) if np.isfinite(dist_to_end) else v_target)
        v = float(np.clip(v_target, v - MAX_ACCELERATION * CONTROL_DT_S, v + MAX_ACCELERATION * CONTROL_DT_S))
        if np.isfinite(dist_to_end) and dist_to_end < GOAL_TOLERANCE_M:
            v = 0.0
            x, y = float(pts[-1, 0]), float(pts[-1, 1])
            progress = len(pts) - 1
        x += v * np.cos(yaw) * CONTROL_DT_S
        y += v * np.sin(yaw) * CONTROL_DT_S
        yaw = transforms.wrap_angle(yaw + w * CONTROL_DT_S)
        step += 1
    return Trajectory(times_s=np.asarray(times), xy_yaw=np.asarray(samples), route_xy=np.asarray(route_xy),
                      speed_mps=speed_mps)


def plan_trajectory(world: World, goals: tuple[str, ...], rng: np.random.Generator,
                    frame_period_s: float = FRAME_PERIOD_S) -> Trajectory:
    """Route through ``goals``, stops of a few seconds at the goals in STOP_NODES, then drive
    (frames every ``frame_period_s``)."""
    route, goal_positions = plan_route(world, goals)
    stops = {pos: float(rng.uniform(*STOP_DURATION_RANGE_S))
             for g, pos in zip(goals, goal_positions) if g in STOP_NODES}
    return drive(route, stops, rng, frame_period_s=frame_period_s)


def step_covariance(speed_mps: float) -> np.ndarray:
    """6x6 covariance (x y z roll pitch yaw) of one 1 s odometry increment at ``speed_mps`` (the
    neighbour link between two nodes a detection period apart, whatever the frame rate)."""
    d = speed_mps * FRAME_PERIOD_S
    var_xy = (ODOM_TRANSLATION_SIGMA * d) ** 2 + (ODOM_LATERAL_SIGMA * d) ** 2
    var_yaw = (ODOM_YAW_PER_METRE_SIGMA * d) ** 2 + (ODOM_YAW_BIAS_SIGMA * d) ** 2
    return np.diag([var_xy, var_xy, ODOM_PLANAR_SIGMA ** 2, ODOM_PLANAR_SIGMA ** 2, ODOM_PLANAR_SIGMA ** 2, var_yaw])


def wheel_odometry(xy_yaw: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Noisy odometry (N,4,4) ``T_odom_base`` from ground-truth planar poses (N,3), identity first."""
    bias = rng.normal(0.0, ODOM_YAW_BIAS_SIGMA)
    out = np.empty((len(xy_yaw), 4, 4))
    out[0] = np.eye(4)
    x = y = yaw = 0.0
    for k in range(1, len(xy_yaw)):
        x0, y0, a0 = xy_yaw[k - 1]
        x1, y1, a1 = xy_yaw[k]
        c, s = np.cos(a0), np.sin(a0)
        dx = c * (x1 - x0) + s * (y1 - y0)      # motion in the previous base frame
        dy = -s * (x1 - x0) + c * (y1 - y0)
        dyaw = transforms.wrap_angle(a1 - a0)
        d = float(np.hypot(dx, dy))
        scale = 1.0 + rng.normal(0.0, ODOM_TRANSLATION_SIGMA)
        odx = dx * scale
        ody = dy * scale + rng.normal(0.0, ODOM_LATERAL_SIGMA * d) if d > 0 else 0.0
        odyaw = (dyaw * (1.0 + rng.normal(0.0, ODOM_ROTATION_SIGMA))
                 + rng.normal(0.0, ODOM_YAW_PER_METRE_SIGMA * d) + bias * d) if (d > 0 or dyaw != 0) else 0.0
        c, s = np.cos(yaw), np.sin(yaw)
        x += c * odx - s * ody
        y += s * odx + c * ody
        yaw = transforms.wrap_angle(yaw + odyaw)
        out[k] = transforms.from_xy_yaw(x, y, yaw)
    return out


def reset_odometry(T_odom_base: np.ndarray, at: int) -> np.ndarray:
    """Odometry (N,4,4) reset to identity at frame ``at``: frames from ``at`` on are expressed in
    a new odometry frame, the pose of frame ``at`` (as a driver restarted there would report)."""
    if not 0 <= at < len(T_odom_base):
        raise RtabmapError(f"odometry reset at frame {at} is outside the {len(T_odom_base)} frames")
    out = np.array(T_odom_base, dtype=np.float64, copy=True)
    out[at:] = transforms.inverse(out[at]) @ out[at:]
    out[at] = np.eye(4)
    return out
