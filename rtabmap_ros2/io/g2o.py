"""g2o pose graph files: VERTEX_SE2 / EDGE_SE2 and VERTEX_SE3:QUAT / EDGE_SE3:QUAT, read and written.

Conventions of the format (g2o's ``types_slam2d`` / ``types_slam3d``): ``VERTEX_SE2 id x y theta``,
``EDGE_SE2 i j dx dy dtheta`` + the upper triangle of the 3x3 information over (x, y, theta);
``VERTEX_SE3:QUAT id x y z qx qy qz qw``, ``EDGE_SE3:QUAT i j dx dy dz qx qy qz qw`` + the upper
triangle of the 6x6 information, read as information on (x, y, z) and the rotation's angles
(our links' (x, y, z, roll, pitch, yaw) information, written back as it is), as gtsam's
``readG2o`` reads it. (g2o itself puts the rotation error on the quaternion's vector part, about
half the angle: 1/4 of this weight on rotations. Issue 50 measures ``optimize`` by GTSAM's chi2,
so a file means here what it means to GTSAM, and the optimum is GTSAM's.)

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
# Numbers after the tag of each g2o element: (ids, floats).
G2O_FIELDS = {"VERTEX_SE2": (1, 3), "EDGE_SE2": (2, 3 + 6),
              "VERTEX_SE3:QUAT": (1, 7), "EDGE_SE3:QUAT": (2, 7 + 21)}
# g2o elements read and ignored (the root is the lowest id, not a FIX line).
G2O_IGNORED = ("FIX", "PARAMS_SE3OFFSET")
# Largest id read through float64 exactly (2^53).
LARGEST_EXACT_ID = 2 ** 53
# Digits of every number written (a float64 round-trips at 17; 9 keep 1e-9 relative).
G2O_DIGITS = 9


def read_g2o(path) -> tuple[dict[int, np.ndarray], list[Link], bool]:
    """Read a g2o pose graph (VERTEX_SE2/EDGE_SE2 or VERTEX_SE3:QUAT/EDGE_SE3:QUAT).

    Information matrices are kept as given (g2o stores the upper triangle); those that are not
    positive definite are named in one warning (the optimiser uses them as gtsam's ``readG2o``
    does, see :func:`rtabmap_ros2.core.optimizer.information_check`).

    Returns:
        ``(poses, links, planar)``: vertex poses (4x4); links with their 6x6 information over
        (x, y, z, roll, pitch, yaw) (planar files: z, roll, pitch get the x information's value,
        unused by Pose2); ``planar`` True for SE2 files. A file with edges only (CSAIL.g2o) gets
        poses chained from the first edge's from vertex. Edges are typed NEIGHBOR when they join
        consecutive ids, LOOP_INTRA otherwise.

    Raises:
        OptimizationError: unreadable or binary file; unknown, malformed or non-finite lines, an
            information matrix gtsam cannot use (no positive eigenvalue; diagonal with a negative
            entry), each naming the line; an edge to a vertex the file does not define (naming the edge).
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
    for number, line in enumerate(lines, 1):
        head = line.split(None, 1)
        if not head or head[0].startswith("#") or head[0] in G2O_IGNORED:
            continue
        tag = head[0]
        group = groups.get(tag)
        if group is None:
            raise _line_error(path, lines, number, f"unsupported element {tag}")
        element_planar = tag.endswith("SE2")
        if planar is not None and element_planar != planar:
            raise _line_error(path, lines, number, f"{tag} in a file of {'SE2' if planar else 'SE3:QUAT'} elements")
        planar = element_planar
        group[0].append(number)
        group[1].append(head[1] if len(head) > 1 else "")
    if planar is None:
        raise OptimizationError(f"{path} holds no vertex or edge")
    vertex_tag, edge_tag = ("VERTEX_SE2", "EDGE_SE2") if planar else ("VERTEX_SE3:QUAT", "EDGE_SE3:QUAT")
    numbers, texts = groups[vertex_tag]
    vertex_ids, v = _block(path, lines, vertex_tag, numbers, texts)
    poses: dict[int, np.ndarray] = {}
    if len(texts):
        if planar:
            vertex_poses = transforms.from_xy_yaws(v)
        else:
            vertex_poses = _transforms(path, lines, numbers, v[:, :3], v[:, 3:7])
        poses = dict(zip(vertex_ids[:, 0].tolist(), vertex_poses))
    edge_numbers, texts = groups[edge_tag]
    ids, v = _block(path, lines, edge_tag, edge_numbers, texts)
    if planar:
        steps = transforms.from_xy_yaws(v[:, :3])
        upper = v[:, 3:]
    else:
        steps = _transforms(path, lines, edge_numbers, v[:, :3], v[:, 3:7])
        upper = v[:, 7:]
    info, indefinite = _information(path, lines, edge_numbers, upper, 3 if planar else 6)
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
    if indefinite:
        named = ", ".join(f"line {edge_numbers[k]} (edge {links[k].from_id} -> {links[k].to_id})"
                          for k in indefinite[:G2O_EDGES_NAMED])
        more = f" and {len(indefinite) - G2O_EDGES_NAMED} more" if len(indefinite) > G2O_EDGES_NAMED else ""
        logger.warning(
            "%s: %d edge(s) have an information matrix that is not positive definite, used as given, as gtsam's "
            "readG2o does (its Cholesky factor stops at the first pivot that is not positive and keeps the "
            "matrix's own entries from there on): %s%s", path, len(indefinite), named, more)
    return poses, links, planar


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
    info = np.zeros((len(upper), dim, dim))
    rows, cols = np.triu_indices(dim)
    info[:, rows, cols] = upper
    info[:, cols, rows] = upper
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


def write_optimised(src, path, poses: dict[int, np.ndarray], planar: bool,
                    kept: list[bool] | None = None) -> None:
    """Write the g2o file ``src`` (as :func:`read_g2o` read it) with its vertices at ``poses``.

    The vertex lines come first (every pose, lowest id first, as :func:`write_g2o` writes them),
    then the file's other lines as they are: edges byte for byte (no number the optimiser did not
    change is rounded; formatting them again was most of the writing time), comments and FIX lines
    kept. ``kept``: one flag per edge line, in the file's order (the order of ``read_g2o``'s links);
    an edge whose flag is False is left out (a loop closure the robust mode rejected).
    """
    src = Path(src)
    try:
        lines = src.read_bytes().decode("utf-8").splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise OptimizationError(f"cannot read g2o file {src} again to write {path}: {exc}") from exc
    edge_tag = "EDGE_SE2" if planar else "EDGE_SE3:QUAT"
    out = _vertex_lines(poses, planar)
    edge = 0
    for line in lines:
        head = line.split(None, 1)
        tag = head[0] if head else ""
        if tag in G2O_FIELDS and tag != edge_tag:   # a vertex line: written above, at its optimised pose
            continue
        if tag == edge_tag:
            edge += 1
            if kept is not None and not (edge <= len(kept) and kept[edge - 1]):
                continue
        out.append(line)
    if kept is not None and edge != len(kept):
        raise OptimizationError(f"{src} has {edge} edges, not the {len(kept)} it had when read: "
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
