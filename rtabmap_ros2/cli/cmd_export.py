"""``rtabmap-ros2 export map.db --out DIR``: the global map, optimised offline with all constraints.

Opens the database read-only, optimises every node and link (WM and LTM, 2014 §II-C) and writes
``poses.txt``, ``nodes.csv``, ``links.csv``, ``graph.g2o``, ``map.pgm`` + ``map.yaml``, ``map.png``,
``cloud.ply`` and ``summary.json`` (see :mod:`rtabmap_ros2.io.export`).

Parameters: those stored with the database (the ones ``map`` or the node mapped with: a 6-DoF
map is exported in 6 DoF, its grid from the sensor it was mapped with), then ``--config FILE`` and
``--set NAME=VALUE`` over them; the shipped ``config/rtabmap.yaml`` only when the database holds
none (written by another tool). The command says which it used.
"""

from __future__ import annotations

import argparse

from rtabmap_ros2.cli.common_args import add_param_arguments


def add_parser(subparsers) -> None:
    parser = subparsers.add_parser(
        "export", help="optimise a map database's global graph and export poses, graph, grid and cloud",
        description=__doc__.split("\n\n", 1)[0] + " Parameters: the database's (those it was mapped with), then "
                    "--config and --set over them.")
    parser.add_argument("database", metavar="DB", help="map database written by 'map' or the node")
    parser.add_argument("--out", required=True, metavar="DIR", help="output folder (created)")
    add_param_arguments(parser, default_config="rtabmap.yaml", base="the parameters stored with the database")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from rtabmap_ros2.cli.common_args import params_for_database
    from rtabmap_ros2.io.export import export_global_map

    params, origin = params_for_database(args, args.database)
    print(f"parameters: {origin}")
    summary = export_global_map(args.database, args.out, params)
    links = ", ".join(f"{k} {v}" for k, v in summary["links_by_type"].items())
    opt = summary["optimization"]
    grid = summary["grid"]
    print(f"nodes: {summary['nodes']} ({summary['nodes_in_wm']} in WM), sessions: {len(summary['sessions'])}")
    print(f"links: {summary['links']} ({links}); loop closures rejected by the global optimisation: "
          f"{len(summary['loop_closures_rejected_by_global_optimization'])}")
    print(f"connected components: {summary['components']} (sizes {summary['component_sizes'][:10]})")
    mode = ("3 DoF: x, y, yaw (registration.planar true)" if summary["planar"]
            else "6 DoF (registration.planar false)")
    print(f"optimisation: chi2 {opt['chi2_initial']:.6g} -> {opt['chi2_final']:.6g}, {opt['iterations']} "
          f"iterations, {opt['time_s']:.3f} s, {mode}")
    if grid["empty_reason"]:
        print(f"grid: EMPTY ({grid['width']}x{grid['height']} unknown cell): {grid['empty_reason']}")
    else:
        print(f"grid: {grid['width']}x{grid['height']} cells at {grid['resolution']} m from {grid['source']}")
    print(f"cloud: {summary['cloud_points']} points")
    print(f"wrote {args.out} in {summary['time_s']['total']:.1f} s")
    return 0
