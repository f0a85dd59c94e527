"""``rtabmap-ros2 report DATABASE_OR_RUN_DIR --out DIR``: figures and an HTML page of a run.

Accepts a map database, or a run folder written by ``demo`` (``map.db``, ``sim/ground_truth.txt``,
``sim/loops.csv``, ``export/``). Writes PNG figures like the papers' (process time, memory, global
map with coloured links, y over time per session, local vs global map; with ground truth the
trajectories and precision-recall), ``summary.json`` and ``index.html``
(see :mod:`rtabmap_ros2.io.report`).
"""

from __future__ import annotations

import argparse


def add_parser(subparsers) -> None:
    parser = subparsers.add_parser(
        "report", help="PNG figures and an HTML page of a mapping run (database or demo folder)",
        description=__doc__.splitlines()[0])
    parser.add_argument("path", metavar="DATABASE_OR_RUN_DIR", help="map database, or a folder written by 'demo'")
    parser.add_argument("--out", required=True, help="report folder (created)")
    parser.add_argument("--ground-truth", metavar="FILE", default=None,
                        help="TUM file of the true base poses (default in a run folder: sim/ground_truth.txt)")
    parser.add_argument("--loops", metavar="FILE", default=None,
                        help="simulator's loops.csv, for precision-recall (default in a run folder: sim/loops.csv)")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from rtabmap_ros2.io.report import find_inputs, write_report

    report = write_report(find_inputs(args.path, args.ground_truth, args.loops), args.out)
    for name in report.figures:
        print(f"wrote {report.figures[name]}")
    for name, reason in report.skipped.items():
        print(f"skipped {name}: {reason}")
    print(f"report: {report.index_html}")
    return 0
