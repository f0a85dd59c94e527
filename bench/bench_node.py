"""ROS 2 node benchmarks: message conversion cost, and end-to-end latency through the node.

``python bench/bench_node.py [--quick] [--skip-latency]``

1. Conversion of a 640x480 RGB + depth pair from messages (``image_from_msg`` + ``depth_from_msg``,
   rgb8 / bgr8 with 16UC1 / 32FC1), median and p95; target < 2 ms. Baseline measured in the same
   run: the naive ``np.array(list(msg.data))`` read LIBRARIES.md warns against.
2. Latency from the last message of a synchronised set to ``mapPath`` at the node's detection rate
   (1 Hz), with a simulated session written to a bag and played in real time by ``play`` in a
   subprocess, once with the default ``qos:=sensor_data`` (best effort) and once with
   ``qos:=reliable``. Frames processed out of those in the bag (target: all), and where the others
   went: messages lost in transport (DDS ``message_lost`` events, per topic), sets the synchroniser
   dropped, frames pushed out of the node's frame queue (``frames_dropped_queue``, target 0).
   The 1-minute load average before and after each run is recorded: the loss with best effort
   grows with the CPU load of the machine. Needs the core and the simulator; skipped with a
   message otherwise.

Prints a table and writes ``bench/results/node.json``.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
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
    return out


def bench_latency(quick: bool, qos: str) -> dict | None:
    """Node in this process, a simulated session played in real time by ``play`` in a subprocess."""
    import os
    import random
    import subprocess
    import tempfile
    import threading

    try:
        import rclpy
        from rclpy.executors import MultiThreadedExecutor
        from rclpy.parameter import Parameter

        from rtabmap_ros2 import sim
        from rtabmap_ros2.io.bag import write_bag
        from rtabmap_ros2.ros.node import RtabmapNode
    except ImportError as exc:
        print(f"latency: skipped ({exc})")
        return None

    n_frames = 15 if quick else None
    domain = random.randint(150, 230)
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    os.environ.update(env)
    world = sim.build_world(seed=0)
    session = sim.make_sessions(world, small=True, sessions=1)[0]
    count = len(session) if n_frames is None else min(n_frames, len(session))
    with tempfile.TemporaryDirectory() as tmp:
        bag = write_bag(Path(tmp) / "session", (sim.render_frame(world, session, i) for i in range(count)))
        ctx = rclpy.Context()
        rclpy.init(context=ctx, domain_id=domain)
        node = RtabmapNode(context=ctx, parameter_overrides=[
            Parameter("database_path", value=str(Path(tmp) / "bench.db")),
            Parameter("export_dir", value=str(Path(tmp) / "exports")), Parameter("qos", value=qos)])
        executor = MultiThreadedExecutor(num_threads=2, context=ctx)
        executor.add_node(node)
        thread = threading.Thread(target=executor.spin, daemon=True)
        thread.start()
        load_before = os.getloadavg()[0]
        t0 = time.monotonic()
        play = subprocess.run([sys.executable, "-m", "rtabmap_ros2.cli.cli", "play", str(bag), "--delay", "2"],
                              env=env, capture_output=True, text=True, timeout=600)
        # play returns once reliable subscribers acknowledged everything; then let the queue drain.
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline and node.frames_processed + node.frames_dropped < node._sync.emitted:
            time.sleep(0.1)
        wall = time.monotonic() - t0
        latencies = np.array(node.latencies_s) * 1e3
        result = {
            "frames_in_bag": count, "sets_synchronised": node._sync.emitted,
            "frames_processed": node.frames_processed,
            "frames_dropped_queue": node.frames_dropped,
            "messages_lost_in_transport": dict(node.messages_lost),
            "sync_dropped": dict(node._sync.dropped),
            "bad_messages": {f"{t} ({k})": n for (t, k), n in node.bad_messages.items()},
            "latency_median_ms": float(np.median(latencies)) if latencies.size else None,
            "latency_p95_ms": float(np.percentile(latencies, 95)) if latencies.size else None,
            "wall_s": wall, "play_returncode": play.returncode,
            "play_all_acknowledged": "did not acknowledge" not in play.stderr,
            "load_average_1min": [load_before, os.getloadavg()[0]],
        }
        executor.shutdown()
        thread.join(timeout=10)
        node.destroy_node()
        rclpy.try_shutdown(context=ctx)
    print(f"latency last message of a set -> mapPath at 1 Hz ({count} frames played in real time, qos {qos}):")
    for key, value in result.items():
        print(f"  {key:28s} {value}")
    return result


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="fewer repeats, shorter session")
    parser.add_argument("--skip-latency", action="store_true", help="conversion only")
    args = parser.parse_args(argv)

    results: dict = {"conversion": bench_conversion(30 if args.quick else 200)}
    print(f"{'conversion (640x480)':40s} {'median ms':>10s} {'p95 ms':>10s}")
    for name, r in results["conversion"].items():
        print(f"{name:40s} {r['median_ms']:10.3f} {r['p95_ms']:10.3f}")
    if not args.skip_latency:
        for qos in ("sensor_data", "reliable"):
            latency = bench_latency(args.quick, qos)
            if latency is not None:
                results[f"latency_{qos}"] = latency
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    RESULTS.write_text(json.dumps(results, indent=2))
    print(f"wrote {RESULTS}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
