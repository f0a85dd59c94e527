"""``rtabmap-ros2 optimize`` on bad and on indefinite g2o files (issue 15 cases 1-2, issue 14 item 6).

Bad files: one ``error:`` line naming the problem (and the line of the file), exit 2, no output
file, no traceback. Indefinite information matrices (symmetric, not positive definite): used as
given, as gtsam's ``readG2o`` uses them, with one warning naming the edges; the optimum reached is
no worse than gtsam's own LM on the same objective (``readG2o`` of the file with its rotation
information written as on angles), and the output keeps the matrices.
"""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from rtabmap_ros2.core import transforms

TIMEOUT_S = 300
# Every INDEFINITE_EVERY-th edge gets an x-qx correlation too strong for its variances: the
# cross information INDEFINITE_CORRELATION x sqrt(I_xx I_qxqx) makes that 2x2 block's determinant
# negative (smallGrid3D: [[100, 60], [60, 25]]).
INDEFINITE_EVERY = 4
INDEFINITE_CORRELATION = 1.2
# Iterations gtsam's LM at its defaults takes on cubicle.g2o.
GTSAM_LM_CUBICLE_ITERATIONS = 39
# gtsam's LM on its own w20000.txt (bench_optimizers.py, gtsam 4.2): iterations, chi2.
GTSAM_LM_W20000 = (14, 442.444)
# Where LM stops, ours and gtsam's default: relative decrease of the error below this.
LM_RELATIVE_TOL = 1e-5


def optimize(*args) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "rtabmap_ros2", "optimize", *map(str, args)],
                          capture_output=True, text=True, timeout=TIMEOUT_S)


def _assert_error(result: subprocess.CompletedProcess, *needles: str) -> str:
    assert result.returncode == 2, result.stdout + result.stderr
    assert "Traceback" not in result.stderr, result.stderr
    lines = [line for line in result.stderr.splitlines() if line.startswith("error: ")]
    assert len(lines) == 1, result.stderr
    for needle in needles:
        assert needle in lines[0], lines[0]
    return lines[0]


SE2_CHAIN = "\n".join([f"VERTEX_SE2 {i} {i}.0 0 0" for i in range(11)]
                      + [f"EDGE_SE2 {i} {i + 1} 1 0 0 100 0 0 100 0 400" for i in range(10)]) + "\n"


def test_binary_file_is_an_error_not_a_traceback(tmp_path):
    src = tmp_path / "graph.g2o"
    src.write_bytes(bytes(range(256)) * 8)
    result = optimize(src, tmp_path / "out.g2o")
    _assert_error(result, "not a g2o text file")
    assert not (tmp_path / "out.g2o").exists()


def test_edge_to_a_missing_vertex_names_the_edge(tmp_path):
    src = tmp_path / "graph.g2o"
    src.write_text(SE2_CHAIN + "EDGE_SE2 5 99 0 0 0 100 0 0 100 0 400\n")
    result = optimize(src, tmp_path / "out.g2o")
    _assert_error(result, "graph.g2o:22", "edge 5 -> 99", "vertex 99")
    assert not (tmp_path / "out.g2o").exists()


def test_the_same_chain_without_the_dangling_edge_is_optimised(tmp_path):
    src = tmp_path / "graph.g2o"
    src.write_text(SE2_CHAIN)
    result = optimize(src, tmp_path / "out.g2o")
    assert result.returncode == 0, result.stderr
    assert "11 SE2 vertices, 10 edges" in result.stdout
    assert (tmp_path / "out.g2o").read_text().count("EDGE_SE2") == 10


def test_output_keeps_the_input_lines_but_the_vertices_and_rejected_loop_closures(tmp_path):
    """OUT = IN with the optimised vertices (written first): edge lines byte for byte (their numbers
    as the user wrote them), comments and FIX lines kept; with --robust, the loop closure it
    rejects is left out."""
    false_loop = "EDGE_SE2 2 8 0.5 0 0 100 0 0 100 0 400"
    src = tmp_path / "graph.g2o"
    lines = ["# a chain with one false loop closure", "FIX 0"] + SE2_CHAIN.splitlines()
    lines.insert(15, false_loop)
    src.write_text("\n".join(lines) + "\n")
    out = tmp_path / "out.g2o"
    result = optimize(src, out, "--robust")
    assert result.returncode == 0, result.stderr
    assert "rejected loop closures: 1" in result.stdout
    written = out.read_text().splitlines()
    assert [line.split()[1] for line in written[:11]] == [str(i) for i in range(11)]
    assert all(line.startswith("VERTEX_SE2") for line in written[:11])
    assert written[11:] == [line for line in lines if not line.startswith("VERTEX") and line != false_loop]


@pytest.mark.parametrize("bad_line, needles", [
    ("EDGE_SE2 2 3 nan 0 0 100 0 0 100 0 400", ("graph.g2o:12", "NaN or inf")),
    ("EDGE_SE2 2 3 1 0 0 100 0 0 100 0 inf", ("graph.g2o:12", "NaN or inf")),
    ("EDGE_SE2 2 3 1 0 0 -1 0 0 -1 0 -1", ("graph.g2o:12", "no positive eigenvalue")),
    ("EDGE_SE2 2 3 1 0 0 100 0 0 -100 0 400", ("graph.g2o:12", "diagonal with a negative entry")),
    ("EDGE_SE2 2 3 1 0 0 100 0 0 100", ("graph.g2o:12", "needs 11 numbers (2 id(s), 9 values), found 9")),
    ("VERTEX_SE3:QUAT 3 0 0 0 0 0 0 1", ("graph.g2o:12", "VERTEX_SE3:QUAT in a file of SE2 elements")),
    ("EDGE_SE3:QUAT 2 3 1 0 0 0 0 0 1" + " 1" * 21, ("graph.g2o:12", "EDGE_SE3:QUAT in a file of SE2")),
])
def test_malformed_or_non_finite_lines_are_named(tmp_path, bad_line, needles):
    lines = SE2_CHAIN.splitlines()
    lines.insert(11, bad_line)   # line 12
    src = tmp_path / "graph.g2o"
    src.write_text("\n".join(lines) + "\n")
    result = optimize(src, tmp_path / "out.g2o")
    message = _assert_error(result, *needles)
    assert "diverged" not in message


def test_zero_quaternion_edge_is_named(tmp_path):
    src = tmp_path / "graph.g2o"
    src.write_text("VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1\nVERTEX_SE3:QUAT 1 1 0 0 0 0 0 1\n"
                   "EDGE_SE3:QUAT 0 1 1 0 0 0 0 0 0" + " 1" * 21 + "\n")
    _assert_error(optimize(src, tmp_path / "out.g2o"), "graph.g2o:3", "quaternion")


def _indefinite_copy(graph, path):
    """``graph`` with every INDEFINITE_EVERY-th edge's information made indefinite; the edge lines."""
    out, changed, edge = [], [], 0
    for number, line in enumerate(graph.read_text().splitlines(), 1):
        f = line.split()
        if f and f[0] == "EDGE_SE3:QUAT":
            edge += 1
            if edge % INDEFINITE_EVERY == 0:
                upper = [float(v) for v in f[10:31]]
                # (x, qx): row 0, column 3 of the upper triangle; (qx, qx) is its 16th entry.
                upper[3] = INDEFINITE_CORRELATION * np.sqrt(upper[0] * upper[15])
                f = f[:10] + [f"{v:g}" for v in upper]
                changed.append((number, int(f[1]), int(f[2])))
                line = " ".join(f)
        out.append(line)
    path.write_text("\n".join(out) + "\n")
    return changed


def _edge_information(line_fields) -> np.ndarray:
    """The symmetric 6x6 information of an EDGE_SE3:QUAT line's fields, as the file gives it."""
    m = np.zeros((6, 6))
    m[np.triu_indices(6)] = [float(v) for v in line_fields[10:31]]
    return m + np.triu(m, 1).T


def _gtsam_reference_chi2(src) -> float:
    """gtsam's own reading (readG2o, information matrices as they are, rotation information on
    the angles) and LM optimum of ``src``: the objective ours minimises."""
    gtsam = pytest.importorskip("gtsam")
    graph, initial = gtsam.readG2o(str(src), True)
    first = min(initial.keys())
    graph.add(gtsam.PriorFactorPose3(first, initial.atPose3(first), gtsam.noiseModel.Isotropic.Sigma(6, 1e-6)))
    values = gtsam.LevenbergMarquardtOptimizer(graph, initial, gtsam.LevenbergMarquardtParams()).optimize()
    return 2.0 * graph.error(values)


@pytest.mark.parametrize("name, edges", [("smallGrid3D", 297), ("parking-garage", 6275)])
def test_indefinite_information_is_kept_and_matches_gtsam(shared_data, tmp_path, name, edges):
    src, out = tmp_path / "indefinite.g2o", tmp_path / "out.g2o"
    changed = _indefinite_copy(shared_data / "posegraphs" / f"{name}.g2o", src)
    assert len(changed) == edges // INDEFINITE_EVERY
    result = optimize(src, out)
    assert result.returncode == 0, result.stderr
    warnings = [line for line in result.stderr.splitlines() if "not positive definite" in line]
    assert len(warnings) == 1, result.stderr
    number, i, j = changed[0]
    assert f"{len(changed)} edge(s)" in warnings[0] and f"line {number} (edge {i} -> {j})" in warnings[0]
    chi2 = float(re.search(r"chi2 final:\s+(\S+)", result.stdout).group(1))
    reference = _gtsam_reference_chi2(src)
    print(f"indefinite {name}: chi2 ours {chi2:.6g}, gtsam {reference:.6g}")
    assert chi2 <= reference * (1 + LM_RELATIVE_TOL)
    # The optimised graph keeps the file's information matrices (to the writer's 9 digits).
    src_lines = [line.split() for line in src.read_text().splitlines() if line.startswith("EDGE")]
    out_lines = [line.split() for line in out.read_text().splitlines() if line.startswith("EDGE")]
    assert len(out_lines) == edges
    for k in range(INDEFINITE_EVERY - 1, edges, INDEFINITE_EVERY):   # the edges made indefinite
        assert np.allclose(_edge_information(out_lines[k]), _edge_information(src_lines[k]), rtol=1e-8)
        assert np.linalg.eigvalsh(_edge_information(out_lines[k]))[0] < 0
    from rtabmap_ros2.io.g2o import read_g2o

    poses, _, planar = read_g2o(out)
    assert not planar and transforms.is_rigid(poses[min(poses)])


def test_cubicle_is_optimised_to_its_optimum_within_the_iteration_budget(shared_data, tmp_path):
    """cubicle.g2o (real, 5,750 poses, 5,021 indefinite edges): the default solver converges in
    fewer iterations than gtsam's default LM (39), to gtsam's chi2 or lower (issue 50), and a second
    run from its output finds nothing more to gain."""
    src = shared_data / "posegraphs" / "cubicle.g2o"
    if not src.exists():
        pytest.skip(f"{src} not found")
    first = optimize(src, tmp_path / "once.g2o")
    assert first.returncode == 0, first.stderr
    iterations = int(re.search(r"iterations:\s+(\d+)", first.stdout).group(1))
    chi2 = float(re.search(r"chi2 final:\s+(\S+)", first.stdout).group(1))
    again = optimize(tmp_path / "once.g2o", tmp_path / "twice.g2o")
    assert again.returncode == 0, again.stderr
    chi2_again = float(re.search(r"chi2 final:\s+(\S+)", again.stdout).group(1))
    reference = _gtsam_reference_chi2(src)
    print(f"cubicle: chi2 {chi2:.6g} in {iterations} iterations; again from there {chi2_again:.6g}; "
          f"gtsam LM {reference:.6g}")
    assert iterations < GTSAM_LM_CUBICLE_ITERATIONS
    assert chi2 <= reference * (1 + LM_RELATIVE_TOL)
    assert chi2_again >= (1 - 1e-3) * chi2


def test_a_toro_graph_from_gtsams_examples_is_optimised_in_lms_iterations(tmp_path):
    """w20000.txt (gtsam's example data, not in the repository: 20,061 poses, EDGE2 lines only):
    read, chained, optimised to GTSAM's LM optimum in no more than its 14 iterations. LM fails one
    damping an iteration at 1e-10 there; the default solver handed it to dogleg, which took 27
    iterations and 2.5x the time (bench_optimizers.py), before it told that from cubicle's stall."""
    gtsam = pytest.importorskip("gtsam")
    src = Path(gtsam.__file__).parent / "Data" / "w20000.txt"
    if not src.exists():
        pytest.skip(f"{src} not found")
    done = optimize(src, tmp_path / "out.g2o")
    assert done.returncode == 0, done.stderr
    assert "EDGE2 information read in g2o's" in done.stderr
    iterations = int(re.search(r"iterations:\s+(\d+)", done.stdout).group(1))
    chi2 = float(re.search(r"chi2 final:\s+(\S+)", done.stdout).group(1))
    assert iterations <= GTSAM_LM_W20000[0] and chi2 <= GTSAM_LM_W20000[1] * (1 + LM_RELATIVE_TOL), done.stdout
    from rtabmap_ros2.io.g2o import read_g2o

    poses, links, planar = read_g2o(tmp_path / "out.g2o")   # written as g2o's own elements
    assert planar and len(poses) == 20061 and len(links) == sum(1 for _ in src.open())


def test_non_symmetric_or_nan_information_stays_an_error():
    from rtabmap_ros2.core.graph import Link, LinkType
    from rtabmap_ros2.core.optimizer import optimize as optimize_graph
    from rtabmap_ros2.core.params import GraphParams
    from rtabmap_ros2.errors import OptimizationError

    step = transforms.from_xy_yaw(1.0, 0.0, 0.0)
    poses = {1: transforms.identity(), 2: step}
    skew = np.eye(6)
    skew[0, 1] = 0.5
    nan = np.eye(6)
    nan[2, 2] = np.nan
    for info, needle in ((skew, "not symmetric"), (nan, "NaN")):
        with pytest.raises(OptimizationError, match=f"link 1 -> 2: .*{needle}"):
            optimize_graph(poses, [Link(1, 2, LinkType.NEIGHBOR, step, info)], 1, GraphParams(robust=False), True)
    nan_step = step.copy()
    nan_step[0, 3] = np.nan
    with pytest.raises(OptimizationError, match="link 1 -> 2: transform has NaN"):
        optimize_graph(poses, [Link(1, 2, LinkType.NEIGHBOR, nan_step, np.eye(6))], 1, GraphParams(robust=False), True)
