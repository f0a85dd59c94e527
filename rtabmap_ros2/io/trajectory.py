"""Trajectories in TUM format, rigid alignment and absolute trajectory error (ATE).

TUM format (Sturm et al. 2012): one pose per line, ``stamp x y z qx qy qz qw`` with the stamp in
seconds, ``#`` comments. Evaluation follows the TUM benchmark's ``evaluate_ate.py`` and evo:
poses are matched by stamp, one rigid transform (Umeyama / Horn without scale) aligns the
estimate to the ground truth, and the ATE is the RMSE of the remaining position differences.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from rtabmap_ros2.core import files, transforms
from rtabmap_ros2.errors import DatasetError

NS_PER_S = 1_000_000_000
# Default largest stamp difference when matching two trajectories (s): TUM's evaluate_ate default.
DEFAULT_MAX_DIFFERENCE_S = 0.02


@dataclass
class Trajectory:
    """Stamped poses.

    Attributes:
        stamps_ns: (N,) int64 stamps (ns).
        poses: (N,4,4) float64 poses (e.g. ``T_map_base``).
    """

    stamps_ns: np.ndarray
    poses: np.ndarray

    def __len__(self) -> int:
        return len(self.stamps_ns)

    @property
    def positions(self) -> np.ndarray:
        """(N,3) translations (m)."""
        return self.poses[:, :3, 3]


def stamp_text(stamp_ns: int) -> str:
    """Seconds with 9 decimals of an int ns stamp, exactly (integer arithmetic, no float division:
    ``1305031229528748000`` -> ``1305031229.528748000``); inverse of :func:`seconds_to_ns`."""
    stamp_ns = int(stamp_ns)
    sign = "-" if stamp_ns < 0 else ""
    seconds, ns = divmod(abs(stamp_ns), NS_PER_S)
    return f"{sign}{seconds}.{ns:09d}"


def tum_line(stamp_ns: int, T: np.ndarray) -> str:
    """One TUM line ``stamp x y z qx qy qz qw`` (stamp in seconds, 9 decimals)."""
    q = transforms.quat_xyzw(T)
    t = T[:3, 3]
    return (f"{stamp_text(stamp_ns)} {t[0]:.6f} {t[1]:.6f} {t[2]:.6f} "
            f"{q[0]:.9f} {q[1]:.9f} {q[2]:.9f} {q[3]:.9f}")


def write_tum(path: str | os.PathLike, stamps_ns, poses, header: str | None = None) -> None:
    """Write a TUM file.

    Args:
        path: output file.
        stamps_ns: (N,) int stamps (ns).
        poses: (N,4,4) poses.
        header: optional comment line (without ``#``).
    """
    lines = [f"# {header}"] if header else []
    lines += [tum_line(int(s), np.asarray(T, dtype=float)) for s, T in zip(stamps_ns, poses)]
    files.write_text(path, "\n".join(lines) + "\n")


def read_tum(path: str | os.PathLike) -> Trajectory:
    """Read a TUM file (stamps in seconds -> ns); raises DatasetError naming the bad line."""
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as exc:
        raise DatasetError(f"cannot read trajectory {path}: {exc.strerror}") from exc
    stamps, poses = [], []
    for number, line in enumerate(text.splitlines(), 1):
        fields = line.replace(",", " ").split()
        if not fields or fields[0].startswith("#"):
            continue
        if len(fields) != 8:
            raise DatasetError(f"{path}:{number}: expected 8 values 'stamp x y z qx qy qz qw', got {len(fields)}")
        try:
            values = [float(v) for v in fields[1:]]
            stamps.append(seconds_to_ns(fields[0]))
        except ValueError as exc:
            raise DatasetError(f"{path}:{number}: not a number in {line.strip()!r}") from exc
        poses.append(transforms.from_xyz_quat_xyzw(values[:3], values[3:]))
    if not stamps:
        return Trajectory(np.zeros(0, np.int64), np.zeros((0, 4, 4)))
    return Trajectory(np.asarray(stamps, dtype=np.int64), np.stack(poses))


def seconds_to_ns(text: str) -> int:
    """Exact ns from a decimal seconds string (no float rounding for 9-decimal stamps)."""
    whole, _, frac = text.strip().partition(".")
    if not frac:
        return int(round(float(text) * NS_PER_S))
    sign = -1 if whole.startswith("-") else 1
    return int(whole) * NS_PER_S + sign * int((frac + "0" * 9)[:9])


def associate(stamps_a_ns: np.ndarray, stamps_b_ns: np.ndarray,
              max_difference_s: float = DEFAULT_MAX_DIFFERENCE_S) -> tuple[np.ndarray, np.ndarray]:
    """Index pairs (ia, ib) matching each stamp of ``a`` to the nearest of ``b`` within the tolerance.

    Each ``b`` stamp is used at most once (the closest ``a`` wins).
    """
    a = np.asarray(stamps_a_ns, dtype=np.int64)
    b = np.asarray(stamps_b_ns, dtype=np.int64)
    if len(a) == 0 or len(b) == 0:
        return np.zeros(0, int), np.zeros(0, int)
    order = np.argsort(b)
    b_sorted = b[order]
    pos = np.clip(np.searchsorted(b_sorted, a), 1, len(b_sorted) - 1) if len(b_sorted) > 1 else np.zeros(len(a), int)
    left = np.clip(pos - 1, 0, len(b_sorted) - 1)
    pick = np.where(np.abs(b_sorted[left] - a) <= np.abs(b_sorted[pos] - a), left, pos)
    diff = np.abs(b_sorted[pick] - a)
    ok = diff <= max_difference_s * NS_PER_S
    ia = np.flatnonzero(ok)
    ib = order[pick[ok]]
    # One-to-one: keep the closest a for each b.
    best: dict[int, int] = {}
    for i, j in zip(ia.tolist(), ib.tolist()):
        if j not in best or diff[i] < diff[best[j]]:
            best[j] = i
    ib_kept = np.array(sorted(best, key=lambda j: best[j]), dtype=int)
    ia_kept = np.array([best[j] for j in ib_kept], dtype=int)
    return ia_kept, ib_kept


def align_rigid(source: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Rigid transform (4x4, no scale) minimising ``sum |target - (R source + t)|^2`` (Umeyama 1991).

    Args:
        source: (N,3) points (m), N >= 3 (N >= 2 for points on a line, with an arbitrary roll).
        target: (N,3) corresponding points (m).
    """
    source = np.asarray(source, dtype=float)
    target = np.asarray(target, dtype=float)
    if source.shape != target.shape or source.ndim != 2 or source.shape[1] != 3 or len(source) < 2:
        raise DatasetError(f"alignment needs two (N,3) arrays with N >= 2, got {source.shape} and {target.shape}")
    mu_s, mu_t = source.mean(axis=0), target.mean(axis=0)
    cov = (target - mu_t).T @ (source - mu_s) / len(source)
    U, _, Vt = np.linalg.svd(cov)
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2, 2] = -1.0
    R = U @ S @ Vt
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = mu_t - R @ mu_s
    return T


@dataclass
class AteResult:
    """Absolute trajectory error after one rigid alignment.

    Attributes:
        rmse_m, mean_m, median_m, max_m: statistics of the position errors (m).
        matched: number of stamp-matched poses.
        T_gt_est: (4x4) alignment applied to the estimate.
        errors_m: (matched,) position error per matched pose (m).
        index_est, index_gt: (matched,) indices of the matched poses in each trajectory.
    """

    rmse_m: float
    mean_m: float
    median_m: float
    max_m: float
    matched: int
    T_gt_est: np.ndarray
    errors_m: np.ndarray
    index_est: np.ndarray
    index_gt: np.ndarray

    def to_dict(self) -> dict:
        return {"rmse_m": self.rmse_m, "mean_m": self.mean_m, "median_m": self.median_m, "max_m": self.max_m,
                "matched": self.matched}


def ate(estimate: Trajectory, ground_truth: Trajectory,
        max_difference_s: float = DEFAULT_MAX_DIFFERENCE_S) -> AteResult:
    """ATE of ``estimate`` against ``ground_truth``: match by stamp, ONE rigid alignment, RMSE.

    Raises:
        DatasetError: fewer than 3 poses matched.
    """
    ie, ig = associate(estimate.stamps_ns, ground_truth.stamps_ns, max_difference_s)
    if len(ie) < 3:
        raise DatasetError(
            f"only {len(ie)} poses of the estimate ({len(estimate)}) match a ground-truth stamp within "
            f"{max_difference_s} s: are both trajectories of the same run?")
    est = estimate.positions[ie]
    gt = ground_truth.positions[ig]
    T = align_rigid(est, gt)
    aligned = est @ T[:3, :3].T + T[:3, 3]
    errors = np.linalg.norm(aligned - gt, axis=1)
    return AteResult(float(np.sqrt(np.mean(errors ** 2))), float(errors.mean()), float(np.median(errors)),
                     float(errors.max()), int(len(ie)), T, errors, ie, ig)


def ate_sessions(estimates: dict[int, Trajectory], ground_truths: dict[int, Trajectory],
                 max_difference_s: float = DEFAULT_MAX_DIFFERENCE_S) -> AteResult:
    """ATE of a multi-session estimate whose sessions may share stamps (robots mapping at the same
    time): each session matched by stamp with its own ground truth, ONE rigid alignment for all.

    Args:
        estimates, ground_truths: session id -> trajectory; every estimated session needs its truth.

    Returns:
        :class:`AteResult`; ``index_est`` / ``index_gt`` index the sessions' trajectories
        concatenated in increasing session id.

    Raises:
        DatasetError: a session without ground truth, or fewer than 3 poses matched in all.
    """
    missing = sorted(set(estimates) - set(ground_truths))
    if missing:
        raise DatasetError(f"sessions {missing} of the estimate have no ground truth")
    est, gt, index_est, index_gt = [], [], [], []
    offset_est = offset_gt = 0
    for session in sorted(estimates):
        e, g = estimates[session], ground_truths[session]
        ie, ig = associate(e.stamps_ns, g.stamps_ns, max_difference_s)
        est.append(e.positions[ie])
        gt.append(g.positions[ig])
        index_est.append(ie + offset_est)
        index_gt.append(ig + offset_gt)
        offset_est += len(e)
        offset_gt += len(g)
    est_xyz, gt_xyz = np.concatenate(est), np.concatenate(gt)
    if len(est_xyz) < 3:
        raise DatasetError(f"only {len(est_xyz)} poses of the estimate match a ground-truth stamp of their session "
                           f"within {max_difference_s} s")
    T = align_rigid(est_xyz, gt_xyz)
    errors = np.linalg.norm(est_xyz @ T[:3, :3].T + T[:3, 3] - gt_xyz, axis=1)
    return AteResult(float(np.sqrt(np.mean(errors ** 2))), float(errors.mean()), float(np.median(errors)),
                     float(errors.max()), int(len(errors)), T, errors, np.concatenate(index_est),
                     np.concatenate(index_gt))


__all__ = ["AteResult", "Trajectory", "align_rigid", "associate", "ate", "ate_sessions", "read_tum", "seconds_to_ns",
           "stamp_text", "tum_line", "write_tum"]
