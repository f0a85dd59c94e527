"""g2o pose graph files: VERTEX_SE2 / EDGE_SE2 and VERTEX_SE3:QUAT / EDGE_SE3:QUAT, read and written;
TORO's VERTEX2 / EDGE2 and VERTEX3 / EDGE3 read too.

Conventions of the format (g2o's ``types_slam2d`` / ``types_slam3d``): ``VERTEX_SE2 id x y theta``,
``EDGE_SE2 i j dx dy dtheta`` + the upper triangle of the 3x3 information over (x, y, theta);
``VERTEX_SE3:QUAT id x y z qx qy qz qw``, ``EDGE_SE3:QUAT i j dx dy dz qx qy qz qw`` + the upper
triangle of the 6x6 information, read as information on (x, y, z) and the rotation's angles
(our links' (x, y, z, roll, pitch, yaw) information, written back as it is), as gtsam's
``readG2o`` reads it. (g2o itself puts the rotation error on the quaternion's vector part, about
half the angle: 1/4 of this weight on rotations. Issue 50 measures ``optimize`` by GTSAM's chi2,
so a file means here what it means to GTSAM, and the optimum is GTSAM's.)

TORO's elements (openslam.org's TORO, the classic 2D benchmarks' ``.graph`` files, gtsam's examples):
``VERTEX2 id x y theta`` and ``EDGE2 i j dx dy dtheta`` + six information entries, which files write
in g2o's order (xx xy xt yy yt tt) or in TORO's (xx xy yy tt xt yt): the order is chosen per file,
the one whose diagonal entries are all non-zero (as gtsam's ``load2D`` checks them), when both are,
the one that makes every matrix positive definite, and when still both, TORO's for a ``.graph``
file and g2o's otherwise; ``VERTEX3 id x y z roll pitch yaw`` (R = Rz(yaw) Ry(pitch) Rx(roll), as
gtsam's ``load3D``) and ``EDGE3 i j dx dy dz roll pitch yaw`` + the upper triangle of the 6x6
information over (x, y, z, roll, pitch, yaw), or nothing (identity, as TORO's 3D files have it).
Written back as g2o's own elements.

Information matrices are kept as the file gives them, positive definite or not (the optimiser
uses them as gtsam does: :func:`rtabmap_ros2.core.optimizer.information_check`); the reader warns
once, naming the edges that are not positive definite.

Reading is done per element at once: the lines are grouped by tag, each group converted by numpy
in one call; only when that fails is the group read again line by line, to name the bad line.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from rtabmap_ros2.core import files, transforms
from rtabmap_ros2.core.graph import Link, LinkType, chain_poses
from rtabmap_ros2.core.optimizer import POSE2_FROM_OURS, information_check
from rtabmap_ros2.errors import OptimizationError

logger = logging.getLogger(__name__)

# Edges that are not positive definite named in the reader's warning (the rest are counted).
G2O_EDGES_NAMED = 10
# Numbers after the tag of each element read: (ids, floats). g2o's own, then TORO's (module doc).
G2O_FIELDS = {"VERTEX_SE2": (1, 3), "EDGE_SE2": (2, 3 + 6),
              "VERTEX_SE3:QUAT": (1, 7), "EDGE_SE3:QUAT": (2, 7 + 21),
              "VERTEX2": (1, 3), "EDGE2": (2, 3 + 6), "VERTEX3": (1, 6), "EDGE3": (2, 6 + 21)}
PLANAR_TAGS = ("VERTEX_SE2", "EDGE_SE2", "VERTEX2", "EDGE2")
EDGE_TAGS = ("EDGE_SE2", "EDGE_SE3:QUAT", "EDGE2", "EDGE3")
# An EDGE3 line without information gets the identity's upper triangle.
IDENTITY_UPPER_6 = " " + " ".join("1" if i == j else "0" for i in range(6) for j in range(i, 6))
# EDGE2's information in TORO's order (xx xy yy tt xt yt), as indices into g2o's (xx xy xt yy yt tt).
TORO_TO_G2O_SE2 = [0, 1, 4, 2, 5, 3]
# g2o elements read and ignored (the root is the lowest id, not a FIX line).
G2O_IGNORED = ("FIX", "PARAMS_SE3OFFSET")
# TORO's "EQUIV i j" (vertices i and j are one place): not a constraint here, as gtsam's readers skip
# it; the reader warns about those whose vertices no edge joins. (w10000.graph, gtsam's example data:
# 5,875, every one beside an edge of the same two vertices, which the optimum puts 2 cm apart.)
TORO_EQUIV = "EQUIV"
# Largest id read through float64 exactly (2^53).
LARGEST_EXACT_ID = 2 ** 53
# Digits of every number written (a float64 round-trips at 17; 9 keep 1e-9 relative).
G2O_DIGITS = 9


def read_g2o(path) -> tuple[dict[int, np.ndarray], list[Link], bool]:
    """Read a pose graph: g2o's VERTEX_SE2/EDGE_SE2 or VERTEX_SE3:QUAT/EDGE_SE3:QUAT, or TORO's
    VERTEX2/EDGE2 or VERTEX3/EDGE3 (module doc), 2D or 3D elements, not both.

    Information matrices are kept as given (g2o stores the upper triangle); those that are not
    positive definite are named in one warning (the optimiser uses them as gtsam's ``readG2o``
    does, see :func:`rtabmap_ros2.core.optimizer.information_check`).

    Returns:
        ``(poses, links, planar)``: vertex poses (4x4); links with their 6x6 information over
        (x, y, z, roll, pitch, yaw) (planar files: z, roll, pitch get the x information's value,
        unused by Pose2), in the order of the file's edge lines; ``planar`` True for 2D files. A
        file with edges only (CSAIL.g2o) gets poses chained from the first edge's from vertex.
        Edges are typed NEIGHBOR when they join consecutive ids, LOOP_INTRA otherwise.

    Raises:
        OptimizationError: unreadable or binary file; unknown, malformed or non-finite lines, an
            information matrix gtsam cannot use (no positive eigenvalue; diagonal with a negative
            entry), EDGE2 lines whose information fits neither order, each naming the line; an edge
            to a vertex the file does not define (naming the edge).
    """
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise OptimizationError(f"cannot read g2o file {path}: {exc.strerror}") from exc
    try:
        lines = data.decode("utf-8").splitlines()
    except UnicodeDecodeError as exc:
        raise OptimizationError(
            f"{path} is not a g2o text file (byte {exc.start} is not text): expected lines such as "
            "'VERTEX_SE2 id x y theta' and 'EDGE_SE2 i j dx dy dtheta I11 I12 I13 I22 I23 I33'") from exc
    # Lines grouped by element, numbers after the tag kept as text (line numbers for the messages).
    groups: dict[str, tuple[list[int], list[str]]] = {tag: ([], []) for tag in G2O_FIELDS}
    planar: bool | None = None
    equivalent: list[tuple[int, int]] = []
    for number, line in enumerate(lines, 1):
        head = line.split(None, 1)
        if not head or head[0].startswith("#") or head[0] in G2O_IGNORED:
            continue
        tag = head[0]
        if tag == TORO_EQUIV:
            try:
                first, second = map(int, head[1].split()) if len(head) > 1 else ()
            except ValueError:
                raise _line_error(path, lines, number, "EQUIV needs two vertex ids") from None
            equivalent.append((first, second))
            continue
        group = groups.get(tag)
        if group is None:
            raise _line_error(path, lines, number, f"unsupported element {tag} (pose graph elements read: "
                                                   f"{', '.join(G2O_FIELDS)})")
        element_planar = tag in PLANAR_TAGS
        if planar is not None and element_planar != planar:
            raise _line_error(path, lines, number, f"{tag} in a file of {'SE2' if planar else 'SE3:QUAT'} elements")
        planar = element_planar
        text = head[1] if len(head) > 1 else ""
        if tag == "EDGE3" and len(text.split()) == 2 + 6:
            text += IDENTITY_UPPER_6
        group[0].append(number)
        group[1].append(text)
    if planar is None:
        raise OptimizationError(f"{path} holds no vertex or edge")
    poses: dict[int, np.ndarray] = {}
    edges = []   # per edge element: (line numbers, ids, steps, information's upper triangle in g2o's order)
    for tag, (numbers, texts) in groups.items():
        if not texts:
            continue
        ids, v = _block(path, lines, tag, numbers, texts)
        if tag in ("VERTEX_SE2", "VERTEX2"):
            poses.update(zip(ids[:, 0].tolist(), transforms.from_xy_yaws(v)))
        elif tag == "VERTEX_SE3:QUAT":
            poses.update(zip(ids[:, 0].tolist(), _transforms(path, lines, numbers, v[:, :3], v[:, 3:7])))
        elif tag == "VERTEX3":
            poses.update(zip(ids[:, 0].tolist(), transforms.from_xyz_rpys(v)))
        elif tag == "EDGE_SE2":
            edges.append((numbers, ids, transforms.from_xy_yaws(v[:, :3]), v[:, 3:]))
        elif tag == "EDGE2":
            upper = v[:, 3:]
            if _toro_order(path, lines, numbers, upper):
                upper = upper[:, TORO_TO_G2O_SE2]
            edges.append((numbers, ids, transforms.from_xy_yaws(v[:, :3]), upper))
        elif tag == "EDGE_SE3:QUAT":
            edges.append((numbers, ids, _transforms(path, lines, numbers, v[:, :3], v[:, 3:7]), v[:, 7:]))
        else:   # EDGE3
            edges.append((numbers, ids, transforms.from_xyz_rpys(v[:, :6]), v[:, 6:]))
    dim = 3 if planar else 6
    if edges:
        all_numbers = np.concatenate([e[0] for e in edges])
        order = np.argsort(all_numbers, kind="stable")   # the file's order
        edge_numbers = all_numbers[order].tolist()
        ids = np.concatenate([e[1] for e in edges])[order]
        steps = np.concatenate([e[2] for e in edges])[order]
        upper = np.concatenate([e[3] for e in edges])[order]
    else:
        edge_numbers, ids = [], np.zeros((0, 2), dtype=np.int64)
        steps, upper = np.zeros((0, 4, 4)), np.zeros((0, dim * (dim + 1) // 2))
    info, indefinite = _information(path, lines, edge_numbers, upper, dim)
    if planar:
        # Pose2 uses x, y, yaw; z, roll, pitch get the x information (unused).
        information = np.eye(6) * info[:, :1, :1]
        rows, cols = np.ix_(POSE2_FROM_OURS, POSE2_FROM_OURS)
        information[:, rows, cols] = info
    else:
        information = info
    pairs = ids.tolist()
    kinds = np.where(np.abs(ids[:, 0] - ids[:, 1]) == 1, 0, 1).tolist()
    link_types = (LinkType.NEIGHBOR, LinkType.LOOP_INTRA)
    links = [Link(i, j, link_types[kind], T, I) for (i, j), kind, T, I in zip(pairs, kinds, steps, information)]
    if poses:
        known = np.array(sorted(poses), dtype=np.int64)
        missing = ~np.isin(ids, known)
        if missing.any():
            k = int(np.argmax(missing.any(axis=1)))
            link = links[k]
            vertex = link.from_id if missing[k, 0] else link.to_id
            raise OptimizationError(
                f"{path}:{edge_numbers[k]}: edge {link.from_id} -> {link.to_id} refers to vertex {vertex}, "
                "which the file does not define (no VERTEX line): fix or remove the edge")
    elif links:
        # Edges only (CSAIL.g2o): initial guess by chaining the edges from the first vertex.
        first = int(ids.min())
        poses = chain_poses(first, transforms.identity(), links)
    if equivalent:
        joined = {(link.from_id, link.to_id) for link in links}
        apart = [pair for pair in equivalent if pair not in joined and pair[::-1] not in joined]
        logger.warning("%s: %d EQUIV line(s) (TORO: two vertices at one place) not used as constraints, as gtsam "
                       "reads them; %s", path, len(equivalent),
                       f"{len(apart)} join vertices no edge joins, e.g. {apart[0][0]} and {apart[0][1]}: add an "
                       "edge for each if they are constraints" if apart else "an edge joins the vertices of each")
    if indefinite:
        named = ", ".join(f"line {edge_numbers[k]} (edge {links[k].from_id} -> {links[k].to_id})"
                          for k in indefinite[:G2O_EDGES_NAMED])
        more = f" and {len(indefinite) - G2O_EDGES_NAMED} more" if len(indefinite) > G2O_EDGES_NAMED else ""
        logger.warning(
            "%s: %d edge(s) have an information matrix that is not positive definite, used as given, as gtsam's "
            "readG2o does (its Cholesky factor stops at the first pivot that is not positive and keeps the "
            "matrix's own entries from there on): %s%s", path, len(indefinite), named, more)
    return poses, links, planar


def _toro_order(path: Path, lines: list[str], numbers: list[int], upper: np.ndarray) -> bool:
    """Whether the EDGE2 lines' six information entries (``upper``, one row a line) are in TORO's
    order (xx xy yy tt xt yt) rather than g2o's (xx xy xt yy yt tt): module doc."""
    fits_g2o = (upper[:, [0, 3, 5]] != 0).all(axis=1)
    fits_toro = (upper[:, [0, 2, 3]] != 0).all(axis=1)
    if not (fits_g2o | fits_toro).all():
        k = int(np.argmin(fits_g2o | fits_toro))
        raise _line_error(path, lines, numbers[k], "the information has a zero diagonal entry in g2o's order "
                                                   "(xx xy xt yy yt tt) and in TORO's (xx xy yy tt xt yt)")
    if not fits_g2o.all() and not fits_toro.all():
        raise _line_error(path, lines, numbers[int(np.argmin(fits_toro))],
                          f"the information fits only g2o's order (xx xy xt yy yt tt), while line "
                          f"{numbers[int(np.argmin(fits_g2o))]} fits only TORO's (xx xy yy tt xt yt): one order a file")
    if fits_g2o.all() and fits_toro.all():
        positive = [information_check(_symmetric(rows, 3)).positive_definite.all()
                    for rows in (upper, upper[:, TORO_TO_G2O_SE2])]
        toro = positive[1] and not positive[0] or positive[0] == positive[1] and path.suffix == ".graph"
    else:
        toro = fits_toro.all()
    logger.info("%s: EDGE2 information read in %s order", path, "TORO's (xx xy yy tt xt yt)" if toro
                else "g2o's (xx xy xt yy yt tt)")
    return bool(toro)


def _symmetric(upper: np.ndarray, dim: int) -> np.ndarray:
    """(n, dim, dim) symmetric matrices of their upper triangles (n, dim (dim + 1) / 2), row by row."""
    out = np.zeros((len(upper), dim, dim))
    rows, cols = np.triu_indices(dim)
    out[:, rows, cols] = upper
    out[:, cols, rows] = upper
    return out


def _numbers(text: str, tag: str) -> tuple[list[int], list[float]]:
    """The ids and the finite values of the numbers after a g2o line's tag (ValueError naming what
    is wrong)."""
    f = text.split()
    n_ids, n_values = G2O_FIELDS[tag]
    if len(f) != n_ids + n_values:
        raise ValueError(f"{tag} needs {n_ids + n_values} numbers ({n_ids} id(s), {n_values} values), "
                         f"found {len(f)}")
    ids = [int(x) for x in f[:n_ids]]
    if any(abs(i) >= LARGEST_EXACT_ID for i in ids):
        raise ValueError(f"an id beyond 2^53 ({ids})")
    values = [float(x) for x in f[n_ids:]]
    if not np.all(np.isfinite(values)):
        raise ValueError("NaN or inf value")
    return ids, values


def _line_error(path: Path, lines: list[str], number: int, reason: str) -> OptimizationError:
    return OptimizationError(f"{path}:{number}: cannot read {lines[number - 1].strip()[:60]!r}: {reason}")


def _block(path: Path, lines: list[str], tag: str, numbers: list[int],
           texts: list[str]) -> tuple[np.ndarray, np.ndarray]:
    """Ids ((n, ids) int64) and values ((n, values) float64) of every line of one element, ``texts``
    the text after each line's tag, converted by one ``np.loadtxt``. When that fails the lines are
    read one by one (:func:`_numbers`), which names the bad line (or reads what only Python's
    ``int`` / ``float`` accept)."""
    n_ids, n_values = G2O_FIELDS[tag]
    if not texts:
        return np.zeros((0, n_ids), dtype=np.int64), np.zeros((0, n_values))
    try:
        # comments=None: a '#' inside a line is an error, as it was line by line.
        table = np.loadtxt(texts, dtype=np.float64, comments=None, ndmin=2)
        if table.shape != (len(texts), n_ids + n_values):   # blank rows are skipped by loadtxt
            raise ValueError("field count")
        ids = table[:, :n_ids]
        if not (np.all(ids == np.round(ids)) and np.all(np.abs(ids) < LARGEST_EXACT_ID)):
            raise ValueError("ids")
        values = table[:, n_ids:]
        if not np.isfinite(values).all():
            raise ValueError("not finite")
    except (ValueError, OverflowError):
        parsed = []
        for number, text in zip(numbers, texts):
            try:
                parsed.append(_numbers(text, tag))
            except (ValueError, OverflowError) as exc:
                raise _line_error(path, lines, number, str(exc)) from exc
        return (np.array([i for i, _ in parsed], dtype=np.int64),
                np.array([v for _, v in parsed], dtype=np.float64))
    return ids.astype(np.int64), np.ascontiguousarray(values)


def _transforms(path: Path, lines: list[str], numbers: list[int], xyz: np.ndarray,
                quat_xyzw: np.ndarray) -> np.ndarray:
    """(n, 4, 4) transforms of g2o SE3 lines; the line of a quaternion that is no rotation named."""
    bad, norms = transforms.unusable_quaternions(quat_xyzw)
    if bad.any():
        k = int(np.argmax(bad))
        raise _line_error(path, lines, numbers[k],
                          f"quaternion {quat_xyzw[k].tolist()} is not a rotation (norm {norms[k]})")
    return transforms.from_xyz_quats_xyzw(xyz, quat_xyzw)


def _information(path: Path, lines: list[str], numbers: list[int], upper: np.ndarray,
                 dim: int) -> tuple[np.ndarray, list[int]]:
    """(n, dim, dim) symmetric information of g2o edges from their upper triangles, and the
    indices of those that are not positive definite; the line of one gtsam cannot use named."""
    info = _symmetric(upper, dim)
    if not len(info):
        return info, []
    check = information_check(info)
    if check.unusable is not None:
        raise _line_error(path, lines, numbers[check.unusable], check.reason)
    return info, np.flatnonzero(~check.positive_definite).tolist()


def write_g2o(path, poses: dict[int, np.ndarray], links: list[Link], planar: bool) -> None:
    """Write a g2o pose graph (SE2 when ``planar``, else SE3:QUAT); inverse of :func:`read_g2o`.
    Every number with :data:`G2O_DIGITS` significant digits."""
    _write_lines(path, _vertex_lines(poses, planar) + _edge_lines(links, planar))


def write_optimised(src, path, poses: dict[int, np.ndarray], planar: bool, links: list[Link],
                    kept: list[bool] | None = None) -> None:
    """Write the g2o file ``src`` (as :func:`read_g2o` read it, ``links`` its links) with its
    vertices at ``poses``.

    The vertex lines come first (every pose, lowest id first, as :func:`write_g2o` writes them),
    then the file's other lines as they are: g2o's own edges byte for byte (no number the optimiser
    did not change is rounded; formatting them again was most of the writing time), TORO's written
    as g2o's from their link (EDGE2's information order is not in the line: a file of g2o's
    elements means the same to any reader), comments and FIX lines kept. ``kept``: one flag per
    edge line, in the file's order (the order of ``read_g2o``'s links); an edge whose flag is False
    is left out (a loop closure the robust mode rejected).
    """
    src = Path(src)
    try:
        lines = src.read_bytes().decode("utf-8").splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise OptimizationError(f"cannot read g2o file {src} again to write {path}: {exc}") from exc
    own_edge_tag = "EDGE_SE2" if planar else "EDGE_SE3:QUAT"
    as_g2o = None   # every link as g2o's line, made at the first TORO edge (one at a time: 6 s on 64,311 edges)
    out = _vertex_lines(poses, planar)
    edge = 0
    for line in lines:
        head = line.split(None, 1)
        tag = head[0] if head else ""
        if tag in G2O_FIELDS and tag not in EDGE_TAGS:   # a vertex line: written above, at its optimised pose
            continue
        if tag in EDGE_TAGS:
            edge += 1
            if edge > len(links) or kept is not None and not (edge <= len(kept) and kept[edge - 1]):
                continue
            if tag != own_edge_tag:
                as_g2o = _edge_lines(links, planar) if as_g2o is None else as_g2o
                line = as_g2o[edge - 1]
        out.append(line)
    if edge != len(links) or kept is not None and edge != len(kept):
        raise OptimizationError(f"{src} has {edge} edges, not the {len(links)} it had when read: "
                                "was it changed meanwhile?")
    _write_lines(path, out)


def _vertex_lines(poses: dict[int, np.ndarray], planar: bool) -> list[str]:
    ids = sorted(poses)
    T = np.stack([poses[i] for i in ids]) if ids else np.zeros((0, 4, 4))
    if planar:
        tag, values = "VERTEX_SE2", transforms.to_xy_yaws(T)
    else:
        tag = "VERTEX_SE3:QUAT"
        values = np.column_stack([T[:, :3, 3], transforms.quats_xyzw(T)]) if ids else np.zeros((0, 7))
    line = tag + " %d" + f" %.{G2O_DIGITS}g" * values.shape[1]
    return [line % (i, *row) for i, row in zip(ids, values.tolist())]


def _edge_lines(links: list[Link], planar: bool) -> list[str]:
    steps = np.stack([link.T_from_to for link in links]) if links else np.zeros((0, 4, 4))
    info = np.stack([np.asarray(link.information, dtype=np.float64) for link in links]) if links \
        else np.zeros((0, 6, 6))
    if planar:
        order = POSE2_FROM_OURS
        values = transforms.to_xy_yaws(steps)
    else:
        order = list(range(6))
        values = np.column_stack([steps[:, :3, 3], transforms.quats_xyzw(steps)]) if links else np.zeros((0, 7))
    rows, cols = np.triu_indices(len(order))
    upper = info[:, np.asarray(order)[rows], np.asarray(order)[cols]]
    tag = "EDGE_SE2" if planar else "EDGE_SE3:QUAT"
    line = tag + " %d %d" + f" %.{G2O_DIGITS}g" * (values.shape[1] + upper.shape[1])
    return [line % (link.from_id, link.to_id, *row)
            for link, row in zip(links, np.column_stack([values, upper]).tolist())]


def _write_lines(path, lines: list[str]) -> None:
    try:
        files.write_text(path, "\n".join(lines) + "\n")
    except OSError as exc:
        raise OptimizationError(f"cannot write g2o file {path}: {exc.strerror}") from exc


__all__ = ["read_g2o", "write_g2o", "write_optimised"]
