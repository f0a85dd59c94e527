"""``rtabmap-ros2 demo [--out DIR]``: simulate, map, export and report in one command.

The 2014 paper's second experiment on the simulated building: the sessions are mapped one after
the other into one database with the memory kept between them (T_time = 0.7 s, the shipped
``config/rtabmap.yaml``), then the global map is optimised offline and exported, and the report's
figures are drawn. Writes in ``DIR`` (default ``./rtabmap_demo``):

* ``sim/``: the simulated bags, ``ground_truth.txt``, ``loops.csv``, ``world.png`` (reused when
  its ``world.json`` matches ``--sessions``, ``--seed`` and ``--small``);
* ``map.db`` and ``params.yaml`` (the parameters used);
* ``export/``: poses, graph, ``map.png``, ``map.pgm`` + ``map.yaml``, ``cloud.ply``;
* ``report/``: the figures and ``index.html``.

Prints a short summary: sessions, nodes, WM size, intra / inter-session loop closures, connected
components, ATE against the ground truth (one rigid alignment), max pTime.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from rtabmap_ros2.cli.common_args import add_param_arguments

DEFAULT_OUT = "rtabmap_demo"
DEFAULT_SESSIONS, DEFAULT_SMALL_SESSIONS = 5, 2


def add_parser(subparsers) -> None:
    parser = subparsers.add_parser(
        "demo", help="simulate a 5-session building, map it (multi-session), export and draw the report",
        description=__doc__.splitlines()[0])
    parser.add_argument("--out", default=DEFAULT_OUT, metavar="DIR", help=f"output folder (default ./{DEFAULT_OUT})")
    parser.add_argument("--sessions", type=int, default=None,
                        help=f"simulated sessions (default {DEFAULT_SESSIONS}, or {DEFAULT_SMALL_SESSIONS} with --small)")
    parser.add_argument("--seed", type=int, default=0, help="simulation seed")
    parser.add_argument("--small", action="store_true", help="2 short sessions (~50 frames each): under a minute")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    add_param_arguments(parser, default_config="rtabmap.yaml")
    parser.set_defaults(func=run)


def _simulation_matches(sim_dir: Path, sessions: int, seed: int, small: bool) -> bool:
    """True when ``sim_dir`` holds a complete simulation of these settings."""
    info_path = sim_dir / "world.json"
    if not info_path.is_file():
        return False
    try:
        info = json.loads(info_path.read_text())
    except (OSError, ValueError):
        return False
    bags = [s.get("bag") for s in info.get("sessions", [])]
    return (info.get("seed") == seed and bool(info.get("small")) == small and len(bags) == sessions
            and all(b and (sim_dir / b).is_dir() for b in bags)
            and (sim_dir / "ground_truth.txt").is_file() and (sim_dir / "loops.csv").is_file())


def _prepare_simulation(sim_dir: Path, sessions: int, seed: int, small: bool) -> tuple[list[Path], bool]:
    """The session bags: reused if they match, else simulated. Returns (bags, reused)."""
    import shutil

    from rtabmap_ros2.errors import RtabmapError
    from rtabmap_ros2.sim.simulate import simulate

    reused = _simulation_matches(sim_dir, sessions, seed, small)
    if not reused:
        if sim_dir.exists():
            if not (sim_dir / "world.json").is_file() and any(sim_dir.iterdir()):
                raise RtabmapError(f"{sim_dir} exists and is not a simulation written by demo: remove it or "
                                   f"choose another --out")
            shutil.rmtree(sim_dir)  # an older simulation with other settings
        simulate(sim_dir, sessions=sessions, seed=seed, small=small)
    info = json.loads((sim_dir / "world.json").read_text())
    return [sim_dir / s["bag"] for s in info["sessions"]], reused


def run(args: argparse.Namespace) -> int:
    from rtabmap_ros2.core.rtabmap import Rtabmap
    from rtabmap_ros2.io.bag import BagDataset
    from rtabmap_ros2.cli.cmd_map import map_datasets
    from rtabmap_ros2.cli.common_args import params_from_args
    from rtabmap_ros2.io.export import export_global_map
    from rtabmap_ros2.io.report import ReportInputs, write_report

    params = params_from_args(args)
    out = Path(args.out).expanduser()
    out.mkdir(parents=True, exist_ok=True)
    sessions = args.sessions if args.sessions is not None else (DEFAULT_SMALL_SESSIONS if args.small else DEFAULT_SESSIONS)
    times = {}

    t0 = time.perf_counter()
    sim_dir = out / "sim"
    bags, reused = _prepare_simulation(sim_dir, sessions, args.seed, args.small)
    times["simulation"] = time.perf_counter() - t0
    print(f"simulation: {len(bags)} sessions in {sim_dir} ({'reused' if reused else 'generated'}, "
          f"{times['simulation']:.0f} s)")

    # Mapping (2014 experiment 2): one Rtabmap, memory kept, one session per bag.
    t0 = time.perf_counter()
    db_path = out / "map.db"
    datasets = [(bag.name, BagDataset(bag, sync=params.sync)) for bag in bags]
    with Rtabmap(params, db_path, delete_existing=True) as rtabmap:
        map_datasets(rtabmap, datasets, progress=not args.no_progress)
        rtabmap.flush()
    params.to_yaml(out / "params.yaml")
    times["mapping"] = time.perf_counter() - t0
    frames = sum(len(d) for _, d in datasets)
    print(f"mapping: {frames} frames in {times['mapping']:.0f} s ({frames / max(times['mapping'], 1e-9):.1f} frames/s)")

    t0 = time.perf_counter()
    export = export_global_map(db_path, out / "export", params)
    times["export"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    inputs = ReportInputs(database=db_path, ground_truth=sim_dir / "ground_truth.txt", loops=sim_dir / "loops.csv",
                          export_dir=out / "export")
    report = write_report(inputs, out / "report", params)
    times["report"] = time.perf_counter() - t0

    s = report.summary
    print()
    print(f"sessions:             {s['sessions']}")
    print(f"nodes:                {s['nodes']} (WM at the end: {s['wm_size']}, last local map: {s['local_map_nodes']})")
    print(f"loop closures:        intra-session {s['loop_closures_intra']}, inter-session {s['loop_closures_inter']}")
    print(f"connected components: {s['components']}")
    if s.get("ate"):
        print(f"ATE (rigid alignment): RMSE {s['ate']['rmse_m']:.3f} m, max {s['ate']['max_m']:.3f} m "
              f"over {s['ate']['matched']} nodes")
    if s.get("recall_at_100_precision") is not None:
        print(f"recall at 100 % precision: {100 * s['recall_at_100_precision']:.1f} %")
    print(f"max pTime:            {s['max_process_time_ms']:.0f} ms (T_time {s['time_threshold_ms']:.0f} ms, "
          f"{s['frames_over_time_threshold']} of {s['frames']} frames over)")
    print("time:                 " + ", ".join(f"{k} {v:.0f} s" for k, v in times.items())
          + f", total {sum(times.values()):.0f} s")
    print(f"map:                  {out / 'export' / 'map.png'}")
    print(f"report:               {report.index_html}")
    (out / "demo_summary.json").write_text(json.dumps({**s, "time_s": times, "export": export}, indent=2) + "\n")
    return 0
