"""g2o files: reading (bulk, with the bad line named), writing, round trips, information kept as given."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from rtabmap_ros2.core import transforms
from rtabmap_ros2.core.graph import Link, LinkType
from rtabmap_ros2.errors import OptimizationError
from rtabmap_ros2.io.g2o import read_g2o, write_g2o


def test_g2o_round_trip_se2_and_se3(tmp_path, random_se3, rng):
    for planar in (True, False):
        poses = {i: (transforms.project_planar(random_se3()) if planar else random_se3()) for i in range(4)}
        links = []
        for a, b in [(0, 1), (1, 2), (2, 3), (0, 3)]:
            A = rng.normal(size=(6, 6))
            info = A @ A.T + 6 * np.eye(6)
            if planar:
                keep = np.zeros((6, 6))
                keep[np.ix_([0, 1, 5], [0, 1, 5])] = info[np.ix_([0, 1, 5], [0, 1, 5])]
                info = keep + np.diag([0, 0, 1, 1, 1, 0]) * keep[0, 0]
            links.append(Link(a, b, LinkType.NEIGHBOR if b == a + 1 else LinkType.LOOP_INTRA,
                              transforms.relative(poses[a], poses[b]), info))
        path = tmp_path / f"graph_{planar}.g2o"
        write_g2o(path, poses, links, planar)
        poses2, links2, planar2 = read_g2o(path)
        assert planar2 == planar and poses2.keys() == poses.keys()
        for k in poses:
            assert np.allclose(poses2[k], poses[k], atol=1e-6)
        for l1, l2 in zip(links, links2):
            assert (l1.from_id, l1.to_id, l1.type) == (l2.from_id, l2.to_id, l2.type)
            assert np.allclose(l1.T_from_to, l2.T_from_to, atol=1e-6)
            assert np.allclose(l1.information, l2.information, rtol=1e-6)


def test_edges_only_file_is_chained(tmp_path):
    path = tmp_path / "edges.g2o"
    path.write_text("EDGE_SE2 0 1 1 0 0 1 0 0 1 0 1\nEDGE_SE2 1 2 1 0 1.5707963 1 0 0 1 0 1\n"
                    "EDGE_SE2 2 3 1 0 0 1 0 0 1 0 1\n")
    poses, links, planar = read_g2o(path)
    assert planar and len(links) == 3
    assert np.allclose(poses[3][:2, 3], [2.0, 1.0], atol=1e-6)


def test_many_at_once_conversions_match_one_at_a_time(rng, random_se3):
    """The vectorised transforms read_g2o / write_g2o use agree with the one-pose functions,
    including rotations near 180 degrees (each quaternion branch)."""
    T = np.stack([random_se3() for _ in range(200)]
                 + [transforms.from_xyz_quat_xyzw([0, 0, 0], q) for q in np.eye(4)]
                 + [transforms.from_xyz_quat_xyzw([1, 2, 3], [1, 1e-9, 0, 1e-9])])
    q = transforms.quats_xyzw(T)
    assert np.allclose(q, [transforms.quat_xyzw(t) for t in T], atol=1e-12)
    assert np.allclose(transforms.from_xyz_quats_xyzw(T[:, :3, 3], q), T, atol=1e-12)
    xy_yaw = rng.uniform(-4, 4, (50, 3))
    assert np.allclose(transforms.from_xy_yaws(xy_yaw), [transforms.from_xy_yaw(*v) for v in xy_yaw])
    with pytest.raises(ValueError, match="quaternion 1 .* is not a rotation"):
        transforms.from_xyz_quats_xyzw(np.zeros((2, 3)), [[0, 0, 0, 1], [0, 0, 0, 0]])


SE3_CHAIN = "".join(f"VERTEX_SE3:QUAT {i} {i}.0 0 0 0 0 0 1\n" for i in range(6))
SE3_INFO = [100, 0, 0, 0, 0, 0, 100, 0, 0, 0, 0, 100, 0, 0, 0, 400, 0, 0, 400, 0, 400]


def _se3_edge(i, j, upper) -> str:
    return f"EDGE_SE3:QUAT {i} {j} 1 0 0 0 0 0 1 " + " ".join(f"{v:g}" for v in upper) + "\n"


def test_indefinite_information_is_kept_as_given_with_one_warning(tmp_path, caplog):
    """Edges whose information is not positive definite keep the file's matrix (as on our
    angles, as gtsam reads it), one warning counts and names them; writing them back gives the file's numbers."""
    indefinite = list(SE3_INFO)
    indefinite[3] = 1.2 * np.sqrt(100 * 400)   # (x, qx): determinant of that block < 0
    text = SE3_CHAIN + "".join(_se3_edge(i, i + 1, indefinite if i % 2 else SE3_INFO) for i in range(5))
    path = tmp_path / "graph.g2o"
    path.write_text(text)
    with caplog.at_level(logging.WARNING):
        poses, links, planar = read_g2o(path)
    warnings = [r.getMessage() for r in caplog.records if "not positive definite" in r.getMessage()]
    assert len(warnings) == 1 and "2 edge(s)" in warnings[0]
    assert "line 8 (edge 1 -> 2)" in warnings[0] and "line 10 (edge 3 -> 4)" in warnings[0]
    file_matrix = np.zeros((6, 6))
    file_matrix[np.triu_indices(6)] = indefinite
    file_matrix = file_matrix + np.triu(file_matrix, 1).T
    assert np.array_equal(links[1].information, file_matrix)
    assert np.linalg.eigvalsh(links[1].information)[0] < 0
    out = tmp_path / "out.g2o"
    write_g2o(out, poses, links, planar)
    assert [line.split()[10:] for line in out.read_text().splitlines()[6:]] == \
        [line.split()[10:] for line in _reformatted(text).splitlines()[6:]]


def _reformatted(text: str) -> str:
    """``text`` with every number of its edge lines as the writer formats it (%.9g)."""
    out = []
    for line in text.splitlines():
        f = line.split()
        if f[0].startswith("EDGE"):
            f = f[:3] + [f"{float(v):.9g}" for v in f[3:]]
        out.append(" ".join(f))
    return "\n".join(out) + "\n"


@pytest.mark.parametrize("upper, needle", [
    ([-v for v in SE3_INFO], "no positive eigenvalue"),
    ([100, 0, 0, 0, 0, 0, -100, 0, 0, 0, 0, 100, 0, 0, 0, 400, 0, 0, 400, 0, 400], "diagonal with a negative entry"),
])
def test_information_gtsam_cannot_use_names_the_line(tmp_path, upper, needle):
    path = tmp_path / "graph.g2o"
    path.write_text(SE3_CHAIN + _se3_edge(0, 1, SE3_INFO) + _se3_edge(1, 2, upper))
    with pytest.raises(OptimizationError, match=f"graph.g2o:8: .*{needle}"):
        read_g2o(path)


def test_field_counts_are_checked_per_line_not_in_total(tmp_path):
    """One line a number short and the next one a number long hold the right total: the short one
    is still named (numbers are converted in bulk, counted per line)."""
    lines = [f"VERTEX_SE2 {i} {i}.0 0 0" for i in range(4)]
    lines += ["EDGE_SE2 0 1 1 0 0 100 0 0 100 0 400", "EDGE_SE2 1 2 1 0 0 100 0 0 100 0",
              "EDGE_SE2 2 3 1 0 0 100 0 0 100 0 400 7"]
    path = tmp_path / "graph.g2o"
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(OptimizationError, match="graph.g2o:6: .*needs 11 numbers .* found 10"):
        read_g2o(path)


def test_numbers_only_python_reads_are_read_line_by_line(tmp_path):
    """What numpy's bulk conversion refuses but Python's float accepts (digit separators) is read
    by the line-by-line path, not turned into an error."""
    path = tmp_path / "graph.g2o"
    path.write_text("VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 1_0.0 0 0\nEDGE_SE2 0 1 10 0 0 100 0 0 100 0 400\n")
    poses, links, planar = read_g2o(path)
    assert planar and poses[1][0, 3] == 10.0 and len(links) == 1


# -- TORO's elements -------------------------------------------------------------------------------

def _toro_graph(path, order: str) -> None:
    """A triangle of VERTEX2 / EDGE2 with the information xx 10, xy 1, xt 2, yy 20, yt 3, tt 30
    written in g2o's or TORO's order."""
    info = "10 1 2 20 3 30" if order == "g2o" else "10 1 20 30 2 3"
    path.write_text("VERTEX2 0 0 0 0\nVERTEX2 1 1 0 0.1\nVERTEX2 2 1 1 1.6\n"
                    f"EDGE2 0 1 1 0 0.1 {info}\nEDGE2 1 2 0 1 1.5 {info}\nEDGE2 2 0 -1 1 -1.6 {info}\n")


def test_toro_2d_information_order_is_told_from_the_numbers(tmp_path, caplog):
    """EDGE2's six numbers in g2o's or TORO's order give the same links: the order is the one whose
    matrices are positive definite (both have non-zero diagonals here), named in the log."""
    links = {}
    for order in ("g2o", "toro"):
        path = tmp_path / f"{order}.txt"
        _toro_graph(path, order)
        with caplog.at_level(logging.INFO, logger="rtabmap_ros2.io.g2o"):
            poses, links[order], planar = read_g2o(path)
        assert planar and len(poses) == 3
        assert ("TORO's" if order == "toro" else "g2o's") in caplog.text
        caplog.clear()
    expected = np.array([[10, 1, 2], [1, 20, 3], [2, 3, 30]], dtype=float)
    for a, b in zip(links["g2o"], links["toro"]):
        assert np.array_equal(a.information, b.information) and np.array_equal(a.T_from_to, b.T_from_to)
        assert np.array_equal(a.information[np.ix_([0, 1, 5], [0, 1, 5])], expected)


def test_toro_2d_unit_information_of_a_graph_file(tmp_path):
    """TORO's '1 0 1 1 0 0' (w10000.graph) is the identity; in g2o's order it has a zero diagonal."""
    path = tmp_path / "w.graph"
    path.write_text("VERTEX2 0 0 0 0\nVERTEX2 1 1 0 0\nEDGE2 1 0 -1 0 0 1 0 1 1 0 0\nEQUIV 1 0\n")
    _, links, _ = read_g2o(path)
    assert np.array_equal(links[0].information[np.ix_([0, 1, 5], [0, 1, 5])], np.eye(3))


def test_toro_2d_orders_mixed_in_one_file_is_an_error(tmp_path):
    path = tmp_path / "mixed.g2o"
    path.write_text("EDGE2 0 1 1 0 0 1 0 0 1 0 1\nEDGE2 1 2 1 0 0 1 0 1 1 0 0\n")
    with pytest.raises(OptimizationError, match=r"mixed.g2o:1: .*only g2o's order.*line 2 fits only TORO's"):
        read_g2o(path)


def test_toro_3d_elements(tmp_path):
    """VERTEX3 / EDGE3 are x y z roll pitch yaw (R = Rz Ry Rx); an EDGE3 without information gets the identity."""
    upper = " ".join(str(v) for v in (np.eye(6) * np.arange(1, 7))[np.triu_indices(6)])
    path = tmp_path / "s.graph"
    path.write_text("VERTEX3 0 0 0 0 0 0 0\nVERTEX3 1 1 2 3 0.1 -0.2 0.3\n"
                    f"EDGE3 0 1 1 2 3 0.1 -0.2 0.3 {upper}\nEDGE3 1 0 -1 0 0 0 0 0\n")
    poses, links, planar = read_g2o(path)
    assert not planar
    assert np.allclose(poses[1], transforms.from_xyz_rpy([1, 2, 3, 0.1, -0.2, 0.3]))
    assert np.allclose(links[0].T_from_to, poses[1])
    assert np.array_equal(links[0].information, np.diag(np.arange(1.0, 7.0)))
    assert np.array_equal(links[1].information, np.eye(6))


def test_equivalent_vertices_are_not_constraints_and_the_log_says_which_no_edge_joins(tmp_path, caplog):
    path = tmp_path / "e.graph"
    path.write_text("VERTEX2 0 0 0 0\nVERTEX2 1 1 0 0\nVERTEX2 2 2 0 0\n"
                    "EDGE2 0 1 1 0 0 1 0 1 1 0 0\nEDGE2 1 2 1 0 0 1 0 1 1 0 0\nEQUIV 1 0\nEQUIV 2 0\n")
    with caplog.at_level(logging.WARNING, logger="rtabmap_ros2.io.g2o"):
        _, links, _ = read_g2o(path)
    assert len(links) == 2
    assert "2 EQUIV line(s)" in caplog.text and "1 join vertices no edge joins, e.g. 2 and 0" in caplog.text


def test_a_toro_file_is_written_back_as_g2o(tmp_path):
    from rtabmap_ros2.io.g2o import write_optimised

    src = tmp_path / "t.graph"
    _toro_graph(src, "toro")
    poses, links, planar = read_g2o(src)
    out = tmp_path / "out.g2o"
    write_optimised(src, out, poses, planar, links, [True, False, True])
    text = out.read_text()
    assert "EDGE2" not in text and text.count("EDGE_SE2") == 2 and text.count("VERTEX_SE2") == 3
    _, written, _ = read_g2o(out)
    for a, b in zip(written, [links[0], links[2]]):
        assert (a.from_id, a.to_id) == (b.from_id, b.to_id)
        assert np.allclose(a.information, b.information) and np.allclose(a.T_from_to, b.T_from_to, atol=1e-8)


@pytest.mark.parametrize("line", ["EQUIV 1", "EQUIV 1 x", "EQUIV", "EQUIV 1 2 3"])
def test_a_malformed_equiv_line_is_named(tmp_path, line):
    path = tmp_path / "bad.graph"
    path.write_text(f"VERTEX2 0 0 0 0\nVERTEX2 1 1 0 0\nEDGE2 0 1 1 0 0 1 0 1 1 0 0\n{line}\n")
    with pytest.raises(OptimizationError, match=r"bad.graph:4: .*EQUIV needs two vertex ids"):
        read_g2o(path)
