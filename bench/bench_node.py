"""ROS 2 node benchmarks: message conversion cost, and end-to-end latency through the node.

``python bench/bench_node.py [--quick] [--skip-latency] [--rate R]``

1. Conversion of a 640x480 RGB + depth pair from messages (``image_from_msg`` + ``depth_from_msg``,
   rgb8 / bgr8 with 16UC1 / 32FC1), median and p95; target < 2 ms. Baseline measured in the same
   run: the naive ``np.array(list(msg.data))`` read LIBRARIES.md warns against.
2. Replay into the node at its default parameters (issue 13): the project's own simulated session
   (``rtabmap-ros2 simulate --sessions 1 --small``: compressed ``rgb/image/compressed`` +
   ``depth/image/compressedDepth``) and the same with ``--raw-images``, each played in real time by
   ``rtabmap-ros2 play`` in a subprocess, once per ``qos`` (``auto``, the default; ``reliable``;
   ``sensor_data``). Reported: frames played (RGB messages the player published), sets synchronised,
   frames processed (target >= 95 % of those played at the defaults), where the others went
   (messages lost in transport per topic, the synchroniser's drops, frames pushed out of the node's
   queue), the latency from the last message of a set to ``mapPath`` (median, p95) and the 1-minute
   load average before and after (best-effort loss grows with the CPU load). Needs the core and the
   simulator; skipped with a message otherwise.

3. Two sessions into the node (issue 33): ``rtabmap-ros2 simulate --sessions 2 --small --raw-images
   --seed 7 --no-tf-static`` with the sensors mounted off the base (mounts given as the node's
   ``base_to_laser`` / ``base_to_camera`` parameters), session 1 then session 2 (its odometry
   restarts at identity: a new map) each played by ``rtabmap-ros2 play --rate R`` into one node at
   its defaults, at R = 1, 2 and 4. Reported: frames played / synchronised / processed / dropped
   (frame queue), latency from the last message of a set to ``mapPath`` (p50 / p95 / max), the
   worker's time per frame by part as published on ``info`` (``node_time_ms/<part>``: median, p95,
   max per session), the nodes of the map, the frames merged into the previous node by rehearsal
   (``merged_id`` on ``info``), and the map's connected components. ``--two-sessions-only`` runs
   this section alone; ``--rates`` chooses the rates; ``--full-sessions`` plays the two full
   sessions (~300 and ~400 frames, maps of ~700 nodes) instead of the small ones (-> ``two_sessions_full``).

4. Issue 50's input (``--recording``): a recording like the independent one issue 50 replayed, built
   with our simulator: ``rtabmap-ros2 simulate --sessions 2 --seed 7 --raw-images --frame-rate 2
   --laser-mount ... --camera-mount ... --no-tf-static`` (two full sessions, 640x480 rgb8 + 16UC1
   depth, LaserScan and odometry at 2 Hz, the second session's odometry restarting at identity,
   sensors off the base given as the node's ``base_to_laser`` / ``base_to_camera``), played by
   ``rtabmap-ros2 play --rate R`` into one node at its defaults, at R = 1, 2 and 4 (``--rates``;
   ``--recording-seed`` another building and drive). Reported per rate: frames played (RGB
   messages), sets synchronised at the detection rate (1 Hz of bag time), the frames ``map`` makes of the same bags at the same rate (the "1 Hz frames"), frames
   processed, dropped from the worker's queue, became nodes (and rehearsal merges), the worker's
   time per frame by part (``FrameTimes``: median / p95 / max; ``total`` is the worker's critical
   path, the other threads' parts beside it) against the period of the 1 Hz frames at that rate,
   latency to ``mapPath``, the exported map's ATE against ``ground_truth.txt`` (one alignment) and
   its connected components, the load average before and after. ``--recording-dir DIR`` keeps the
   2 GB of bags between runs (simulated there when missing).

Prints a table and writes ``bench/results/node.json`` (sections not run keep their last results).
"""

from __future__ import annotations

import argparse
import importlib
import json
import sys
import time
from contextlib import contextmanager
from pathlib import Path

import numpy as np

RESULTS = Path(__file__).resolve().parent / "results" / "node.json"
WIDTH, HEIGHT = 640, 480


def _timed(fn, repeats: int) -> dict[str, float]:
    fn()  # warm-up
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append((time.perf_counter() - t0) * 1e3)
    return {"median_ms": float(np.median(times)), "p95_ms": float(np.percentile(times, 95)), "n": repeats}


def bench_conversion(repeats: int) -> dict[str, dict[str, float]]:
    from rtabmap_ros2.ros import conversions as conv

    rng = np.random.default_rng(0)
    rgb = rng.integers(0, 256, (HEIGHT, WIDTH, 3), dtype=np.uint8)
    depth = rng.uniform(0.5, 5.0, (HEIGHT, WIDTH)).astype(np.float32)
    depth[rng.random((HEIGHT, WIDTH)) < 0.1] = np.nan
    out = {}
    for color_enc in ("rgb8", "bgr8"):
        for depth_enc in ("16UC1", "32FC1"):
            rgb_msg = conv.image_to_msg(rgb, 0, "camera", color_enc)
            depth_msg = conv.depth_to_msg(depth, 0, "camera", depth_enc)
            out[f"from_msg {color_enc}+{depth_enc}"] = _timed(
                lambda: (conv.image_from_msg(rgb_msg), conv.depth_from_msg(depth_msg)), repeats)
    out["to_msg rgb8+16UC1"] = _timed(
        lambda: (conv.image_to_msg(rgb, 0, "c"), conv.depth_to_msg(depth, 0, "c")), repeats)
    rgb_msg = conv.image_to_msg(rgb, 0, "camera")
    out["baseline np.array(list(data)) rgb8"] = _timed(
        lambda: np.array(list(rgb_msg.data), dtype=np.uint8).reshape(HEIGHT, WIDTH, 3), max(3, repeats // 20))
    out.update(_bench_map_messages(rng, max(3, repeats // 20)))
    return out


def _bench_map_messages(rng, repeats: int, nodes: int = 1700, loop_closures: int = 350) -> dict:
    """mapPath and mapGraph of a local map the size of the simulator's five sessions (1,700 nodes,
    ~2,000 links), against the path made one pose at a time (pose_to_msg per node, as before)."""
    from geometry_msgs.msg import PoseStamped
    from nav_msgs.msg import Path as PathMsg

    from rtabmap_ros2.core import transforms
    from rtabmap_ros2.core.graph import Link, LinkType
    from rtabmap_ros2.ros import conversions as conv

    poses = {i: transforms.from_xyz_rpy([*rng.normal(0, 10, 2), 0.0, 0.0, 0.0, rng.uniform(-np.pi, np.pi)])
             for i in range(1, nodes + 1)}
    links = [Link(i, i + 1, LinkType.NEIGHBOR) for i in range(1, nodes)]
    links += [Link(int(a), int(b), LinkType.LOOP_INTER) for a, b in rng.integers(1, nodes + 1, (loop_closures, 2))]

    def one_pose_at_a_time():
        hdr = conv.header(0, "map")
        msg = PathMsg(header=hdr)
        msg.poses = [PoseStamped(header=hdr, pose=conv.pose_to_msg(poses[i])) for i in sorted(poses)]
        return msg

    return {f"to_msg mapPath {nodes} poses": _timed(lambda: conv.path_to_msg(poses, 0, "map"), repeats),
            "baseline mapPath one pose at a time": _timed(one_pose_at_a_time, repeats),
            f"to_msg mapGraph {nodes} nodes {len(links)} links": _timed(
                lambda: conv.graph_to_markers(poses, links, 0, "map"), repeats)}


@contextmanager
def _node_in_process(tmp: str, parameters: dict, extra_nodes=lambda ctx: []):
    """An ``rtabmap`` node (database and exports in ``tmp``, ``parameters`` besides) spinning in
    this process on its own ROS domain, with the nodes ``extra_nodes(ctx)`` makes; yields
    ``(node, env)``, env being what a ``play`` subprocess needs to reach it. Shut down after."""
    import os
    import random
    import threading

    import rclpy
    from rclpy.parameter import Parameter

    from rtabmap_ros2.ros.executor import NodeExecutor
    from rtabmap_ros2.ros.node import RtabmapNode

    domain = random.randint(150, 230)
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    os.environ.update(env)
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=domain)
    overrides = {"database_path": str(Path(tmp) / "bench.db"), "export_dir": str(Path(tmp) / "exports"),
                 **parameters}
    node = RtabmapNode(context=ctx, parameter_overrides=[Parameter(k, value=v) for k, v in overrides.items()])
    others = extra_nodes(ctx)
    executor = NodeExecutor(num_threads=2 + len(others), context=ctx)
    for n in (node, *others):
        executor.add_node(n)
    thread = threading.Thread(target=executor.spin, daemon=True)
    thread.start()
    try:
        yield node, env
    finally:
        executor.shutdown()
        thread.join(timeout=10)
        for n in (node, *others):
            n.destroy_node()
        rclpy.try_shutdown(context=ctx)


def _play(bag: Path, rate: float, env: dict, timeout_s: float):
    """``rtabmap-ros2 play`` of ``bag`` in a subprocess: the RGB messages it published (a
    one-element list, empty when it did not say) and the finished process."""
    import subprocess

    play = subprocess.run([sys.executable, "-m", "rtabmap_ros2.cli.cli", "play", str(bag), "--delay", "2",
                           "--rate", str(rate)], env=env, capture_output=True, text=True, timeout=timeout_s)
    return [int(line.rsplit(":", 2)[-1].split()[0]) for line in play.stderr.splitlines()
            if "/rgb/image" in line and "messages" in line][:1], play


def _drain(node, timeout_s: float, also=lambda: False) -> None:
    """Wait until every synchronised set is processed or dropped (and while ``also()``)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline and (node.frames_processed + node.frames_dropped < node._sync.emitted
                                           or also()):
        time.sleep(0.1)


def _counters(node) -> dict:
    """The node's frame and message counters."""
    return {"sets_synchronised": node._sync.emitted, "frames_processed": node.frames_processed,
            "frames_dropped_queue": node.frames_dropped, "sync_dropped": dict(node._sync.dropped),
            "messages_lost_in_transport": dict(node.messages_lost),
            "bad_messages": {f"{t} ({k})": n for (t, k), n in node.bad_messages.items()},
            "frame_errors": dict(node.frame_errors)}


def bench_replay(bag: Path, qos: str, rate: float) -> dict | None:
    """Node in this process (default parameters but ``qos``), ``bag`` played by ``play`` in a subprocess."""
    import os
    import tempfile

    try:
        importlib.import_module("rtabmap_ros2.ros.node")   # rclpy and the messages
    except ImportError as exc:
        print(f"replay: skipped ({exc})")
        return None

    with tempfile.TemporaryDirectory() as tmp, _node_in_process(tmp, {"qos": qos}) as (node, env):
        load_before = os.getloadavg()[0]
        t0 = time.monotonic()
        # play returns once reliable subscribers acknowledged everything; then let the queue drain.
        played, play = _play(bag, rate, env, timeout_s=900)
        _drain(node, 30)
        wall = time.monotonic() - t0
        latencies = np.array(node.latencies_s) * 1e3
        result = {
            "frames_played": played[0] if played else None,
            **_counters(node),
            "subscribed": {s: f"{c.topic} ({'reliable' if r == 1 else 'best effort'})"
                           for s, (c, r) in node.subscriptions_.current.items()},
            "latency_median_ms": float(np.median(latencies)) if latencies.size else None,
            "latency_p95_ms": float(np.percentile(latencies, 95)) if latencies.size else None,
            "wall_s": wall, "play_returncode": play.returncode,
            "play_all_acknowledged": "did not acknowledge" not in play.stderr,
            "load_average_1min": [load_before, os.getloadavg()[0]],
        }
    ratio = result["frames_processed"] / result["frames_played"] if result["frames_played"] else 0.0
    result["processed_ratio"] = ratio
    print(f"replay {bag.parent.name} qos {qos} (rate {rate:g}): played {result['frames_played']}, "
          f"synchronised {result['sets_synchronised']}, processed {result['frames_processed']} ({ratio:.0%})")
    for key, value in result.items():
        print(f"  {key:28s} {value}")
    return result


# Section 3: a seed other than the demo's (0), sensors off the base (as in test_node_mounts.py).
TWO_SESSION_SEED = 7
LASER_MOUNT = [0.25, 0.1, 0.3, 0.0, 0.0, 0.3]
CAMERA_MOUNT = [0.15, -0.05, 0.5, -1.5708, 0.0, -1.3]
TWO_SESSION_RATES = [1.0, 2.0, 4.0]
# After the last play, how long the node may take to empty its queue (s).
DRAIN_TIMEOUT_S = 60.0


def two_session_replay(bags: list[Path], rate: float) -> dict | None:
    """``bags`` played one after the other into one node (defaults + mounts) at ``rate``; the
    node's counters, latencies and the per-part times it published on ``info``."""
    import os
    import tempfile

    try:
        from diagnostic_msgs.msg import DiagnosticArray
        from rclpy.node import Node

        from rtabmap_ros2.core.global_map import load_global_map
        from rtabmap_ros2.ros.conversions import statistics_from_msg
        from rtabmap_ros2.ros.frame_times import INFO_KEY_PREFIX
    except ImportError as exc:
        print(f"two-session replay: skipped ({exc})")
        return None

    infos: list[dict[str, str]] = []

    def listener(ctx) -> list:
        node = Node("bench_info", context=ctx)
        node.create_subscription(DiagnosticArray, "info", lambda m: infos.append(statistics_from_msg(m)), 100)
        return [node]

    mounts = {"base_to_laser": LASER_MOUNT, "base_to_camera": CAMERA_MOUNT}
    with tempfile.TemporaryDirectory() as tmp:
        with _node_in_process(tmp, mounts, listener) as (node, env):
            load_before = os.getloadavg()[0]
            played, sessions_first_info = [], []
            t0 = time.monotonic()
            for bag in bags:
                sessions_first_info.append(len(infos))
                played += _play(bag, rate, env, timeout_s=1800)[0]
            _drain(node, DRAIN_TIMEOUT_S, also=lambda: len(infos) < node.frames_processed)
            wall = time.monotonic() - t0
            latencies = np.array(node.latencies_s) * 1e3
            result = {
                "rate": rate, "frames_played": sum(played), "frames_played_per_session": played,
                **_counters(node),
                "latency_p50_ms": float(np.median(latencies)) if latencies.size else None,
                "latency_p95_ms": float(np.percentile(latencies, 95)) if latencies.size else None,
                "latency_max_ms": float(latencies.max()) if latencies.size else None,
                "rehearsal_merges": sum(1 for info in infos if int(info.get("merged_id", "0") or 0)),
                "wall_s": wall, "load_average_1min": [load_before, os.getloadavg()[0]],
            }
            # Per-part times by session, from info (each message carries the previous frame's).
            bounds = sessions_first_info + [len(infos)]
            result["time_ms_by_session"] = []
            for first, last in zip(bounds, bounds[1:]):
                rows = infos[first:last]
                parts = sorted({k for info in rows for k in info if k.startswith(INFO_KEY_PREFIX + "/")})
                summary = {key.split("/", 1)[1]: _spread([float(info[key]) for info in rows if key in info])
                           for key in parts}
                core = [float(info["total_time_ms"]) for info in rows if "total_time_ms" in info]
                if core:
                    summary["core total_time_ms"] = _spread(core)
                result["time_ms_by_session"].append(summary)

        global_map = load_global_map(Path(tmp) / "bench.db", node_params())
        result["map_nodes"] = len(global_map.poses)
        result["map_sessions"] = len(set(global_map.map_ids.values()))
        result["components"] = len(global_map.components)
    result["nodes_plus_merges"] = result["map_nodes"] + result["rehearsal_merges"]
    return result


# Section 4 (issue 50): the recording's parameters.
RECORDING_SEED = 7
RECORDING_FRAME_RATE_HZ = 2.0


def node_params():
    """The parameters the node runs at by default (config/rtabmap.yaml when found: planar; Params()'s
    own default is 6 DoF since issue 49), for the export and the 1 Hz frames."""
    from rtabmap_ros2.ros.params import defaults

    return defaults()


def make_recording(out: Path, seed: int = RECORDING_SEED) -> list[Path]:
    """Issue 50's input in ``out`` (simulated with ``seed`` when ``out`` has no ground truth yet): the bags."""
    from rtabmap_ros2.sim.simulate import simulate

    if not (out / "ground_truth.txt").is_file():
        print(f"simulating issue 50's recording in {out} (2 sessions, raw images, 2 Hz, seed {seed})", flush=True)
        simulate(out, sessions=2, seed=seed, raw_images=True, frame_rate_hz=RECORDING_FRAME_RATE_HZ,
                 laser_mount=LASER_MOUNT, camera_mount=CAMERA_MOUNT, tf_static=False)
    return [out / "session_1", out / "session_2"]


def frames_at_detection_rate(bags: list[Path]) -> list[int]:
    """The frames ``map`` makes of each bag at the node's default detection rate (the 1 Hz frames)."""
    from rtabmap_ros2.io.bag import BagDataset

    sync = node_params().sync
    counts = []
    for bag in bags:
        dataset = BagDataset(bag, sync=sync)
        for _ in dataset:
            pass
        counts.append(dataset.last_read.frames)
    return counts


def thread_cpu_s() -> dict[str, float]:
    """CPU seconds of this process's threads by name (Python threads; the others, DDS's and the
    executor's, summed as ``other``), from /proc."""
    import os
    import threading

    ticks = os.sysconf("SC_CLK_TCK")
    names = {t.native_id: t.name for t in threading.enumerate()}
    out: dict[str, float] = {}
    for tid in os.listdir("/proc/self/task"):
        try:
            with open(f"/proc/self/task/{tid}/stat") as f:
                fields = f.read().rsplit(")", 1)[1].split()
        except OSError:
            continue
        name = names.get(int(tid), "other")
        out[name] = out.get(name, 0.0) + (int(fields[11]) + int(fields[12])) / ticks
    return out


def recording_replay(bags: list[Path], rate: float, ground_truth: Path, one_hz_frames: int) -> dict | None:
    """``bags`` played one after the other into one node (defaults + mounts) at ``rate``: counters,
    the worker's parts, the exported map's ATE and components."""
    import os
    import tempfile

    try:
        from rtabmap_ros2.core.global_map import load_global_map
        from rtabmap_ros2.io.export import export_global_map
        from rtabmap_ros2.io.trajectory import ate, read_tum
    except ImportError as exc:
        print(f"recording replay: skipped ({exc})")
        return None

    mounts = {"base_to_laser": LASER_MOUNT, "base_to_camera": CAMERA_MOUNT}
    with tempfile.TemporaryDirectory() as tmp:
        with _node_in_process(tmp, mounts) as (node, env):
            core_steps: list[dict] = []   # the core's own step times (Statistics.timings_ms) per frame
            process = node._core.process

            def timed_process(frame, **kwargs):
                stats = process(frame, **kwargs)
                core_steps.append({**stats.timings_ms, "pTime": stats.process_time_ms})
                return stats

            node._core.process = timed_process
            load_before = os.getloadavg()[0]
            cpu_before = thread_cpu_s()
            played, t0 = [], time.monotonic()
            for bag in bags:
                played += _play(bag, rate, env, timeout_s=3600)[0]
            _drain(node, DRAIN_TIMEOUT_S)
            wall = time.monotonic() - t0
            cpu = {name: round(s - cpu_before.get(name, 0.0), 1) for name, s in thread_cpu_s().items()}
            latencies = np.array(node.latencies_s) * 1e3
            parts = node.frame_times.spread()
            parts["core steps (inside process)"] = {
                k: _spread([row[k] for row in core_steps if k in row]) for k in core_steps[0]} if core_steps else {}
            result = {
                "rate": rate, "frames_played": sum(played), "frames_played_per_session": played,
                "one_hz_frames": one_hz_frames, **_counters(node),
                "latency_p50_ms": float(np.median(latencies)) if latencies.size else None,
                "latency_p95_ms": float(np.percentile(latencies, 95)) if latencies.size else None,
                "latency_max_ms": float(latencies.max()) if latencies.size else None,
                "rehearsal_merges": node.rehearsal_merges,
                "period_of_1hz_frames_ms": 1000.0 / rate, "time_ms": parts,
                "cpu_s_by_thread": dict(sorted(cpu.items(), key=lambda kv: -kv[1])),
                "wall_s": wall, "load_average_1min": [load_before, os.getloadavg()[0]],
            }
        params = node_params()
        global_map = load_global_map(Path(tmp) / "bench.db", params)
        result["map_nodes"] = len(global_map.poses)
        result["map_sessions"] = len(set(global_map.map_ids.values()))
        summary = export_global_map(Path(tmp) / "bench.db", Path(tmp) / "export", params)
        result["components"] = summary["components"]
        result["ate"] = ate(read_tum(Path(tmp) / "export" / "poses.txt"), read_tum(ground_truth)).to_dict()
    result["nodes_ratio"] = result["map_nodes"] / one_hz_frames if one_hz_frames else 0.0
    result["nodes_plus_merges_ratio"] = (result["map_nodes"] + result["rehearsal_merges"]) / one_hz_frames \
        if one_hz_frames else 0.0
    return result


def _print_recording(r: dict) -> None:
    print(f"rate {r['rate']:g}x: played {r['frames_played']} ({r['frames_played_per_session']}), synchronised "
          f"{r['sets_synchronised']} (1 Hz frames of the bags: {r['one_hz_frames']}), processed "
          f"{r['frames_processed']}, dropped {r['frames_dropped_queue']} (sync {r['sync_dropped']}); nodes "
          f"{r['map_nodes']} ({r['nodes_ratio']:.1%}) + {r['rehearsal_merges']} rehearsal merges "
          f"({r['nodes_plus_merges_ratio']:.1%}), {r['map_sessions']} sessions, {r['components']} component(s), "
          f"ATE {r['ate']['rmse_m'] * 100:.2f} cm; latency p50 {r['latency_p50_ms']:.0f} / p95 "
          f"{r['latency_p95_ms']:.0f} / max {r['latency_max_ms']:.0f} ms; load {r['load_average_1min']}")
    print(f"  CPU s by thread over {r['wall_s']:.0f} s: {r['cpu_s_by_thread']}")
    print(f"  time per frame (ms) median/p95/max against a period of {r['period_of_1hz_frames_ms']:.0f} ms:")
    for thread, parts in r["time_ms"].items():
        text = ", ".join(f"{name} {v['median']:.1f}/{v['p95']:.1f}/{v['max']:.0f}" for name, v in parts.items())
        print(f"    {thread}: {text}")


def _spread(values: list[float]) -> dict[str, float]:
    """Median, p95 and max of a non-empty list."""
    v = np.asarray(values)
    return {"median": float(np.median(v)), "p95": float(np.percentile(v, 95)), "max": float(v.max())}


def _print_two_sessions(r: dict) -> None:
    print(f"rate {r['rate']:g}x: played {r['frames_played']} ({r['frames_played_per_session']}), synchronised "
          f"{r['sets_synchronised']}, processed {r['frames_processed']}, dropped {r['frames_dropped_queue']} "
          f"(sync {r['sync_dropped']}); latency p50 {r['latency_p50_ms']:.0f} / p95 {r['latency_p95_ms']:.0f} / "
          f"max {r['latency_max_ms']:.0f} ms; map {r['map_nodes']} nodes + {r['rehearsal_merges']} rehearsal "
          f"merges = {r['nodes_plus_merges']}, {r['map_sessions']} sessions, {r['components']} component(s)")
    for k, parts in enumerate(r["time_ms_by_session"], 1):
        text = ", ".join(f"{name} {v['median']:.1f}/{v['p95']:.1f}/{v['max']:.0f}" for name, v in parts.items())
        print(f"  session {k} ms median/p95/max: {text}")


def simulated_bags(out: Path) -> dict[str, Path]:
    """The default (compressed) and --raw-images small session 1, as ``rtabmap-ros2 simulate`` writes them."""
    from rtabmap_ros2.sim.simulate import simulate

    bags = {}
    for kind, raw in (("compressed", False), ("raw", True)):
        simulate(out / kind, sessions=1, small=True, raw_images=raw)
        bags[kind] = out / kind / "session_1"
    return bags


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="fewer conversion repeats")
    parser.add_argument("--skip-latency", action="store_true", help="conversion only")
    parser.add_argument("--rate", type=float, default=1.0, help="playback speed of the replays (1 = real time)")
    parser.add_argument("--two-sessions-only", action="store_true", help="section 3 only")
    parser.add_argument("--rates", type=float, nargs="+", default=TWO_SESSION_RATES,
                        help="playback speeds of section 3")
    parser.add_argument("--full-sessions", action="store_true",
                        help="section 3 on the two full simulated sessions instead of the small ones")
    parser.add_argument("--recording", action="store_true", help="section 4 only (issue 50's input)")
    parser.add_argument("--recording-dir", type=Path, default=None,
                        help="section 4's bags (simulated there when missing; default: a temporary folder)")
    parser.add_argument("--recording-seed", type=int, default=RECORDING_SEED,
                        help=f"section 4's building and drive (default {RECORDING_SEED}; another seed: a recording "
                             "the node was never run on, written under its own key)")
    args = parser.parse_args(argv)

    old = json.loads(RESULTS.read_text()) if RESULTS.exists() else {}
    if args.recording:
        import tempfile

        runs = []
        with tempfile.TemporaryDirectory() as tmp:
            folder = args.recording_dir or Path(tmp)
            bags = make_recording(folder, args.recording_seed)
            key = "recording_2hz_raw" + ("" if args.recording_seed == RECORDING_SEED
                                         else f"_seed{args.recording_seed}")
            one_hz = frames_at_detection_rate(bags)
            print(f"1 Hz frames of the bags (what map makes of them): {one_hz}", flush=True)
            for rate in args.rates:
                r = recording_replay(bags, rate, folder / "ground_truth.txt", sum(one_hz))
                if r is not None:
                    runs.append(r)
                    _print_recording(r)
                    RESULTS.write_text(json.dumps({**old, key: runs}, indent=2))
        print(f"wrote {RESULTS}")
        return 0
    if args.two_sessions_only:
        import tempfile

        from rtabmap_ros2.sim.simulate import simulate

        runs = []
        with tempfile.TemporaryDirectory() as tmp:
            simulate(Path(tmp), sessions=2, small=not args.full_sessions, seed=TWO_SESSION_SEED, raw_images=True,
                     laser_mount=LASER_MOUNT, camera_mount=CAMERA_MOUNT, tf_static=False)
            bags = [Path(tmp) / "session_1", Path(tmp) / "session_2"]
            for rate in args.rates:
                r = two_session_replay(bags, rate)
                if r is not None:
                    runs.append(r)
                    _print_two_sessions(r)
        key = "two_sessions_full" if args.full_sessions else "two_sessions"
        RESULTS.write_text(json.dumps({**old, key: runs}, indent=2))
        print(f"wrote {RESULTS}")
        return 0
    results: dict = {"conversion": bench_conversion(30 if args.quick else 200)}
    print(f"{'conversion (640x480)':40s} {'median ms':>10s} {'p95 ms':>10s}")
    for name, r in results["conversion"].items():
        print(f"{name:40s} {r['median_ms']:10.3f} {r['p95_ms']:10.3f}")
    if not args.skip_latency:
        import tempfile

        try:
            import rtabmap_ros2.sim  # noqa: F401
        except ImportError as exc:
            print(f"replay: skipped ({exc})")
        else:
            with tempfile.TemporaryDirectory() as tmp:
                for kind, bag in simulated_bags(Path(tmp)).items():
                    for qos in ("auto", "reliable", "sensor_data"):
                        replay = bench_replay(bag, qos, rate=args.rate)
                        if replay is not None:
                            results[f"replay_{kind}_{qos}"] = replay
            print(f"{'bag':12s} {'qos':12s} {'played':>7s} {'synced':>7s} {'processed':>9s} {'ratio':>6s}")
            for key, r in results.items():
                if key.startswith("replay_"):
                    kind, qos = key[len("replay_"):].split("_", 1)
                    print(f"{kind:12s} {qos:12s} {r['frames_played']!s:>7s} {r['sets_synchronised']:7d} "
                          f"{r['frames_processed']:9d} {r['processed_ratio']:6.0%}")
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    RESULTS.write_text(json.dumps({**old, **results}, indent=2))
    print(f"wrote {RESULTS}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
