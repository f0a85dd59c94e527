"""``rtabmap-ros2 optimize IN.g2o OUT.g2o``: optimise a g2o pose graph with the package's optimiser.

The root (held fixed) is the first vertex of the file (the lowest id), as is standard for g2o
benchmarks; files with edges only are initialised by chaining the edges. The default solver,
``auto``, is GTSAM's Levenberg-Marquardt while its damping works and Powell's dogleg (one
factorisation per iteration, failed steps retried along it) once a damping has failed in two
iterations running: on cubicle.g2o LM alone takes 39 iterations, each failed damping costing a
factorisation, ``auto`` reaches the same optimum in 2 + 9 (``bench/bench_optimizers.py``). 3D files
are read as GTSAM's ``readG2o`` reads them (:mod:`rtabmap_ros2.io.g2o`), so the chi2 is GTSAM's.
Prints the initial and final chi2 (sum of whitened squared errors), the iterations and the time.
OUT is IN with the optimised vertices: the vertex lines first, then IN's other lines as they are
(g2o's edges byte for byte, TORO's written as g2o's; with ``--robust``, the rejected loop closures
left out).
"""

from __future__ import annotations

import argparse


def add_parser(subparsers) -> None:
    parser = subparsers.add_parser(
        "optimize", help="optimise a g2o pose graph (gtsam), root = first vertex",
        description=__doc__.splitlines()[0],
        epilog="The root, held fixed at its pose in the file, is the vertex with the lowest id.")
    parser.add_argument("input", help="pose graph: g2o (VERTEX_SE2/EDGE_SE2 or VERTEX_SE3:QUAT/EDGE_SE3:QUAT) or "
                                      "TORO (VERTEX2/EDGE2 or VERTEX3/EDGE3, e.g. a .graph file)")
    parser.add_argument("output", help="g2o file written with the optimised vertices and the kept edges")
    parser.add_argument("--optimizer", choices=["auto", "lm", "gn", "dogleg"], default="auto",
                        help="auto (default): Levenberg-Marquardt at GTSAM's defaults (what the graph SLAM uses), "
                             "Powell's dogleg from where LM's damping fails in two iterations running; lm, gn, "
                             "dogleg: one solver throughout")
    parser.add_argument("--iterations", type=int, default=100, metavar="N", help="maximum iterations (default 100)")
    parser.add_argument("--robust", action="store_true",
                        help="dynamic covariance scaling on loop closures (edges between non-consecutive ids); "
                             "drop those it rejects and re-optimise")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from rtabmap_ros2.core.optimizer import optimize
    from rtabmap_ros2.core.params import GraphParams
    from rtabmap_ros2.errors import ParameterError
    from rtabmap_ros2.io.g2o import read_g2o, write_optimised

    if args.iterations < 1:
        raise ParameterError(f"--iterations {args.iterations}: expected >= 1")
    poses, links, planar = read_g2o(args.input)
    root = min(poses)
    params = GraphParams(optimizer=args.optimizer, iterations=args.iterations, robust=args.robust)
    result = optimize(poses, links, root, params, planar, cache=False)
    rejected = {id(link) for link in result.rejected}  # the same Link objects as in ``links``
    write_optimised(args.input, args.output, result.poses, planar, links,
                    [id(link) not in rejected for link in links])
    print(f"graph: {len(poses)} {'SE2' if planar else 'SE3'} vertices, {len(links)} edges, root {root}")
    print(f"optimizer: {args.optimizer}{' + DCS' if args.robust else ''}")
    print(f"chi2 initial: {result.chi2_initial:.6g}")
    print(f"chi2 final:   {result.chi2_final:.6g}")
    print(f"iterations:   {result.iterations}")
    print(f"time:         {result.time_s:.3f} s")
    if args.robust:
        print(f"rejected loop closures: {len(result.rejected)}")
    print(f"wrote {args.output}")
    return 0
