"""Baseline of ``bench_optimizers.py``: a bare GTSAM Levenberg-Marquardt run on a g2o file.

``python bench/gtsam_lm.py IN.g2o OUT.g2o``: ``gtsam.readG2o`` (information matrices as they are
in the file), the first vertex held by a prior (sigma 1e-6, as ``rtabmap-ros2 optimize`` holds
its root), ``LevenbergMarquardtOptimizer`` at GTSAM's default parameters (100 iterations,
relative and absolute error tolerance 1e-5: the same as ours), ``gtsam.writeG2o``. Prints the
iterations, GTSAM's own chi2 (2 x graph error) and the time of the optimisation alone (the
in-process figure next to the whole process's). Nothing of rtabmap_ros2 is imported: this is what
a user would write with GTSAM alone.
"""

import sys
import time

import gtsam

ROOT_PRIOR_SIGMA = 1e-6


def main(src: str, dst: str) -> None:
    with open(src) as f:
        is_3d = any(line.startswith(("VERTEX_SE3", "EDGE_SE3")) for line in f)
    graph, initial = gtsam.readG2o(src, is_3d)
    first = min(initial.keys())
    if is_3d:
        graph.add(gtsam.PriorFactorPose3(first, initial.atPose3(first),
                                         gtsam.noiseModel.Isotropic.Sigma(6, ROOT_PRIOR_SIGMA)))
    else:
        graph.add(gtsam.PriorFactorPose2(first, initial.atPose2(first),
                                         gtsam.noiseModel.Isotropic.Sigma(3, ROOT_PRIOR_SIGMA)))
    start = time.perf_counter()
    optimizer = gtsam.LevenbergMarquardtOptimizer(graph, initial, gtsam.LevenbergMarquardtParams())
    values = optimizer.optimize()
    elapsed = time.perf_counter() - start
    gtsam.writeG2o(graph, values, dst)
    print(f"iterations: {optimizer.iterations()}")
    print(f"chi2 final: {2.0 * graph.error(values):.9g}")
    print(f"time: {elapsed:.3f} s")


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2])
