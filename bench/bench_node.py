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


def bench_replay(bag: Path, qos: str, rate: float) -> dict | None:
    """Node in this process (default parameters but ``qos``), ``bag`` played by ``play`` in a subprocess."""
    import os
    import random
    import subprocess
    import tempfile
    import threading

    try:
        import rclpy
        from rclpy.executors import MultiThreadedExecutor
        from rclpy.parameter import Parameter

        from rtabmap_ros2.ros.node import RtabmapNode
    except ImportError as exc:
        print(f"replay: skipped ({exc})")
        return None

    domain = random.randint(150, 230)
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    os.environ.update(env)
    with tempfile.TemporaryDirectory() as tmp:
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
        play = subprocess.run([sys.executable, "-m", "rtabmap_ros2.cli.cli", "play", str(bag), "--delay", "2",
                               "--rate", str(rate)], env=env, capture_output=True, text=True, timeout=900)
        # play returns once reliable subscribers acknowledged everything; then let the queue drain.
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline and node.frames_processed + node.frames_dropped < node._sync.emitted:
            time.sleep(0.1)
        wall = time.monotonic() - t0
        latencies = np.array(node.latencies_s) * 1e3
        played = [int(line.rsplit(":", 2)[-1].split()[0]) for line in play.stderr.splitlines()
                  if "/rgb/image" in line and "messages" in line]
        result = {
            "frames_played": played[0] if played else None,
            "sets_synchronised": node._sync.emitted,
            "frames_processed": node.frames_processed,
            "subscribed": {s: f"{c.topic} ({'reliable' if r == 1 else 'best effort'})"
                           for s, (c, r) in node.subscriptions_.current.items()},
            "frames_dropped_queue": node.frames_dropped,
            "messages_lost_in_transport": dict(node.messages_lost),
            "sync_dropped": dict(node._sync.dropped),
            "bad_messages": {f"{t} ({k})": n for (t, k), n in node.bad_messages.items()},
            "frame_errors": dict(node.frame_errors),
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
    ratio = result["frames_processed"] / result["frames_played"] if result["frames_played"] else 0.0
    result["processed_ratio"] = ratio
    print(f"replay {bag.parent.name} qos {qos} (rate {rate:g}): played {result['frames_played']}, "
          f"synchronised {result['sets_synchronised']}, processed {result['frames_processed']} ({ratio:.0%})")
    for key, value in result.items():
        print(f"  {key:28s} {value}")
    return result


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
    args = parser.parse_args(argv)

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
    RESULTS.write_text(json.dumps(results, indent=2))
    print(f"wrote {RESULTS}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
