"""Simulator speed: rendering per frame and the whole default multi-session simulation.

Measured in one run:

* world: ``build_world`` (textures from the scikit-image photos), one call;
* render: ``render_rgbd`` (640x480 colour + depth) and ``render_scan`` (481 beams) per frame,
  median over frames of session 1; baseline: a bare ``np.empty((480, 640, 3))`` + one
  ``rng.standard_normal((480, 640))`` (the cost floor of producing a noisy image);
* frame: ``render_frame`` (RGB-D + scan + odometry in a SensorFrame), median;
* simulate: the full ``simulate()`` (bags with JPEG/PNG images, ground truth, loops.csv, plots),
  total seconds with the default 2 worker processes; ``--quick`` runs the ``--small`` set instead.

The machine's 2 cores are shared: times vary with the load (reported in the JSON).

Usage: ``python bench/bench_sim.py [--quick]``. Writes ``bench/results/sim.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np

from rtabmap_ros2.sim import build_world, make_sessions, render_frame, render_rgbd, render_scan, simulate

RESULTS = Path(__file__).resolve().parent / "results" / "sim.json"
FRAMES = 40
QUICK_FRAMES = 10


def _median_ms(fn, items) -> float:
    times = []
    for item in items:
        t = time.perf_counter()
        fn(item)
        times.append((time.perf_counter() - t) * 1000)
    return statistics.median(times)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="fewer frames; simulate the --small set")
    args = parser.parse_args()
    n = QUICK_FRAMES if args.quick else FRAMES

    t = time.perf_counter()
    world = build_world(seed=0)
    world_s = time.perf_counter() - t
    session = make_sessions(world, sessions=1)[0]
    idx = np.linspace(0, len(session) - 1, n).astype(int)
    rng = np.random.default_rng(0)
    rows = {
        "baseline_noise_image_ms": _median_ms(
            lambda _: (np.empty((480, 640, 3), np.float32), rng.standard_normal((480, 640), dtype=np.float32)), idx),
        "render_rgbd_ms": _median_ms(lambda i: render_rgbd(world, session.T_world_base[i], rng), idx),
        "render_scan_ms": _median_ms(lambda i: render_scan(world, session.T_world_base[i], rng), idx),
        "render_frame_ms": _median_ms(lambda i: render_frame(world, session, i), idx),
    }
    with tempfile.TemporaryDirectory() as tmp:
        t = time.perf_counter()
        summary = simulate(Path(tmp) / "sim", seed=0, small=args.quick)
        sim_s = time.perf_counter() - t
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")

    print(f"{'measure':<28}{'value':>12}")
    print(f"{'build_world (s)':<28}{world_s:>12.2f}")
    for k, v in rows.items():
        print(f"{k:<28}{v:>12.1f}")
    label = "simulate --small (s)" if args.quick else "simulate default (s)"
    print(f"{label:<28}{sim_s:>12.1f}")
    print(f"{'frames / length (m)':<28}{summary.total_frames:>6d} / {summary.total_length_m:.0f}")
    print(f"{'ms per simulated frame':<28}{1000 * sim_s / summary.total_frames:>12.1f}")
    print(f"{'load average (1 min)':<28}{load:>12.2f}")

    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    RESULTS.write_text(json.dumps({
        "quick": args.quick, "frames_timed": int(n), "build_world_s": world_s, **rows,
        "simulate_s": sim_s, "simulate_small": args.quick, "simulate_frames": summary.total_frames,
        "simulate_length_m": summary.total_length_m, "ms_per_simulated_frame": 1000 * sim_s / summary.total_frames,
        "load_average_1min": load, "cpus": os.cpu_count(), "python": platform.python_version(),
    }, indent=2))
    print(f"wrote {RESULTS}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
