"""``rtabmap-ros2 export map.db --out DIR``: the global map, optimised offline with all constraints.

Opens the database read-only, optimises every node and link (WM and LTM, 2014 §II-C) and writes
``poses.txt``, ``nodes.csv``, ``links.csv``, ``graph.g2o``, ``map.pgm`` + ``map.yaml``, ``map.png``,
``cloud.ply`` and ``summary.json`` (see :mod:`rtabmap_ros2.io.export`).
"""

from __future__ import annotations

import argparse

from rtabmap_ros2.cli.common_args import add_param_arguments


def add_parser(subparsers) -> None:
    parser = subparsers.add_parser(
        "export", help="optimise a map database's global graph and export poses, graph, grid and cloud",
        description=__doc__.splitlines()[0])
    parser.add_argument("database", metavar="DB", help="map database written by 'map' or the node")
    parser.add_argument("--out", required=True, metavar="DIR", help="output folder (created)")
    add_param_arguments(parser, default_config="rtabmap.yaml")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from rtabmap_ros2.cli.common_args import params_from_args
    from rtabmap_ros2.io.export import export_global_map

    params = params_from_args(args)
    summary = export_global_map(args.database, args.out, params)
    links = ", ".join(f"{k} {v}" for k, v in summary["links_by_type"].items())
    opt = summary["optimization"]
    print(f"nodes: {summary['nodes']} ({summary['nodes_in_wm']} in WM), sessions: {len(summary['sessions'])}")
    print(f"links: {summary['links']} ({links}); rejected by the robust optimisation: "
          f"{len(summary['rejected_loop_closures'])}")
    print(f"connected components: {summary['components']} (sizes {summary['component_sizes'][:10]})")
    print(f"optimisation: chi2 {opt['chi2_initial']:.6g} -> {opt['chi2_final']:.6g}, {opt['iterations']} "
          f"iterations, {opt['time_s']:.3f} s ({'3 DoF' if summary['planar'] else '6 DoF'})")
    print(f"grid: {summary['grid']['width']}x{summary['grid']['height']} cells at {summary['grid']['resolution']} m, "
          f"cloud: {summary['cloud_points']} points")
    print(f"wrote {args.out} in {summary['time_s']['total']:.1f} s")
    return 0
