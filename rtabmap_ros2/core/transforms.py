"""SE(3) / SE(2) helpers on 4x4 homogeneous matrices.

Conventions: ``T_a_b`` maps points from frame b into frame a (``p_a = T_a_b @ p_b``); a pose of the
robot in the map is ``T_map_base``. Quaternions are named by their order: ``quat_xyzw`` (ROS, TUM)
or ``quat_wxyz``.
"""

from __future__ import annotations

import numpy as np


def identity() -> np.ndarray:
    """The 4x4 identity transform (float64)."""
    return np.eye(4)


def inverse(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid 4x4 transform."""
    R = T[:3, :3]
    out = np.eye(4)
    out[:3, :3] = R.T
    out[:3, 3] = -R.T @ T[:3, 3]
    return out


def inverse_many(T: np.ndarray) -> np.ndarray:
    """Inverses of (N,4,4) rigid transforms."""
    R_t = np.transpose(T[:, :3, :3], (0, 2, 1))
    out = np.zeros_like(T, dtype=float)
    out[:, :3, :3] = R_t
    out[:, :3, 3] = -np.einsum("nij,nj->ni", R_t, T[:, :3, 3])
    out[:, 3, 3] = 1.0
    return out


def relative(T_w_a: np.ndarray, T_w_b: np.ndarray) -> np.ndarray:
    """``T_a_b = inv(T_w_a) @ T_w_b``: the motion from pose a to pose b."""
    return inverse(T_w_a) @ T_w_b


def from_xyz_quat_xyzw(xyz, quat_xyzw) -> np.ndarray:
    """4x4 transform from a translation (m) and a unit quaternion (x, y, z, w)."""
    x, y, z, w = (float(v) for v in quat_xyzw)
    n = np.sqrt(x * x + y * y + z * z + w * w)
    if not np.isfinite(n) or n < 1e-9:
        raise ValueError(f"quaternion {quat_xyzw} is not a rotation (norm {n})")
    x, y, z, w = x / n, y / n, z / n, w / n
    T = np.eye(4)
    T[:3, :3] = [
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ]
    T[:3, 3] = np.asarray(xyz, dtype=float)
    return T


def unusable_quaternions(quats_xyzw: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """((n,) bool, (n,) norms): which of (n, 4) quaternions are no rotation (norm < 1e-9 or not finite)."""
    n = np.linalg.norm(np.asarray(quats_xyzw, dtype=np.float64).reshape(-1, 4), axis=1)
    return ~(np.isfinite(n) & (n >= 1e-9)), n


def from_xyz_quats_xyzw(xyz: np.ndarray, quats_xyzw: np.ndarray) -> np.ndarray:
    """(n, 4, 4) transforms from (n, 3) translations (m) and (n, 4) quaternions (x, y, z, w),
    each normalised: :func:`from_xyz_quat_xyzw` on many at once.

    Raises:
        ValueError: naming the index of the first quaternion that is not a rotation
            (:func:`unusable_quaternions`).
    """
    q = np.asarray(quats_xyzw, dtype=np.float64).reshape(-1, 4)
    bad, n = unusable_quaternions(q)
    if bad.any():
        i = int(np.argmax(bad))
        raise ValueError(f"quaternion {i} {q[i].tolist()} is not a rotation (norm {n[i]})")
    x, y, z, w = (q / n[:, None]).T
    T = np.zeros((len(q), 4, 4))
    T[:, 0, 0], T[:, 0, 1], T[:, 0, 2] = 1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)
    T[:, 1, 0], T[:, 1, 1], T[:, 1, 2] = 2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)
    T[:, 2, 0], T[:, 2, 1], T[:, 2, 2] = 2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)
    T[:, :3, 3] = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
    T[:, 3, 3] = 1.0
    return T


def from_xy_yaws(xy_yaw: np.ndarray) -> np.ndarray:
    """(n, 4, 4) planar transforms of (n, 3) ``(x, y, yaw)`` rows (m, m, rad): :func:`from_xy_yaw`
    on many at once."""
    v = np.asarray(xy_yaw, dtype=np.float64).reshape(-1, 3)
    c, s = np.cos(v[:, 2]), np.sin(v[:, 2])
    T = np.zeros((len(v), 4, 4))
    T[:, 0, 0], T[:, 0, 1], T[:, 1, 0], T[:, 1, 1] = c, -s, s, c
    T[:, 2, 2] = T[:, 3, 3] = 1.0
    T[:, :2, 3] = v[:, :2]
    return T


def from_xyz_rpy(xyz_rpy) -> np.ndarray:
    """4x4 transform of ``[x, y, z, roll, pitch, yaw]`` (m, rad), ROS's convention (tf2, URDF):
    R = Rz(yaw) Ry(pitch) Rx(roll), i.e. roll about x, then pitch about y, then yaw about z (fixed axes).

    Raises:
        ValueError: not 6 finite numbers.
    """
    values = np.asarray(xyz_rpy, dtype=np.float64).reshape(-1)
    if values.size != 6 or not np.all(np.isfinite(values)):
        raise ValueError(f"expected 6 finite numbers [x, y, z, roll, pitch, yaw], got {list(values)}")
    return from_xyz_rpys(values)[0]


def from_xyz_rpys(xyz_rpy: np.ndarray) -> np.ndarray:
    """(n, 4, 4) transforms of (n, 6) ``[x, y, z, roll, pitch, yaw]`` rows: :func:`from_xyz_rpy`
    on many at once (no check)."""
    v = np.asarray(xyz_rpy, dtype=np.float64).reshape(-1, 6)
    cr, sr = np.cos(v[:, 3]), np.sin(v[:, 3])
    cp, sp = np.cos(v[:, 4]), np.sin(v[:, 4])
    cy, sy = np.cos(v[:, 5]), np.sin(v[:, 5])
    T = np.zeros((len(v), 4, 4))
    T[:, 0, 0], T[:, 0, 1], T[:, 0, 2] = cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr
    T[:, 1, 0], T[:, 1, 1], T[:, 1, 2] = sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr
    T[:, 2, 0], T[:, 2, 1], T[:, 2, 2] = -sp, cp * sr, cp * cr
    T[:, :3, 3] = v[:, :3]
    T[:, 3, 3] = 1.0
    return T


def to_xyz_rpy(T: np.ndarray) -> np.ndarray:
    """``[x, y, z, roll, pitch, yaw]`` of a 4x4 transform (inverse of :func:`from_xyz_rpy`)."""
    R = T[:3, :3]
    pitch = np.arctan2(-R[2, 0], np.hypot(R[0, 0], R[1, 0]))
    roll = np.arctan2(R[2, 1], R[2, 2])
    yaw = np.arctan2(R[1, 0], R[0, 0])
    return np.array([T[0, 3], T[1, 3], T[2, 3], roll, pitch, yaw])


def quat_xyzw(T: np.ndarray) -> np.ndarray:
    """Unit quaternion (x, y, z, w) of the rotation of a 4x4 transform, with w >= 0
    (:func:`quats_xyzw` of one matrix: one conversion, so a pose and a path of it agree)."""
    return quats_xyzw(np.asarray(T)[None])[0]


def quats_xyzw(T: np.ndarray) -> np.ndarray:
    """(n, 4) unit quaternions (x, y, z, w), ``w >= 0``, of (n, 4, 4) transforms (or (n, 3, 3)
    rotations): :func:`quat_xyzw` on many at once (the same branch per matrix, by its largest
    diagonal term)."""
    R = np.asarray(T, dtype=np.float64)[:, :3, :3]
    r00, r11, r22 = R[:, 0, 0], R[:, 1, 1], R[:, 2, 2]
    tr = r00 + r11 + r22
    q = np.empty((len(R), 4))
    case_w = tr > 0
    case_x = ~case_w & (r00 > r11) & (r00 > r22)
    case_y = ~case_w & ~case_x & (r11 > r22)
    case_z = ~(case_w | case_x | case_y)
    with np.errstate(invalid="ignore", divide="ignore"):
        s = np.sqrt(tr + 1.0) * 2
        q_w = np.stack([(R[:, 2, 1] - R[:, 1, 2]) / s, (R[:, 0, 2] - R[:, 2, 0]) / s,
                        (R[:, 1, 0] - R[:, 0, 1]) / s, 0.25 * s], axis=1)
        s = np.sqrt(1.0 + r00 - r11 - r22) * 2
        q_x = np.stack([0.25 * s, (R[:, 0, 1] + R[:, 1, 0]) / s, (R[:, 0, 2] + R[:, 2, 0]) / s,
                        (R[:, 2, 1] - R[:, 1, 2]) / s], axis=1)
        s = np.sqrt(1.0 + r11 - r00 - r22) * 2
        q_y = np.stack([(R[:, 0, 1] + R[:, 1, 0]) / s, 0.25 * s, (R[:, 1, 2] + R[:, 2, 1]) / s,
                        (R[:, 0, 2] - R[:, 2, 0]) / s], axis=1)
        s = np.sqrt(1.0 + r22 - r00 - r11) * 2
        q_z = np.stack([(R[:, 0, 2] + R[:, 2, 0]) / s, (R[:, 1, 2] + R[:, 2, 1]) / s, 0.25 * s,
                        (R[:, 1, 0] - R[:, 0, 1]) / s], axis=1)
    for case, value in ((case_w, q_w), (case_x, q_x), (case_y, q_y), (case_z, q_z)):
        q[case] = value[case]
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    q[q[:, 3] < 0] *= -1.0
    return q


def from_xy_yaw(x: float, y: float, yaw: float, z: float = 0.0) -> np.ndarray:
    """4x4 transform of a planar pose (m, m, rad)."""
    c, s = np.cos(yaw), np.sin(yaw)
    T = np.eye(4)
    T[:2, :2] = [[c, -s], [s, c]]
    T[:3, 3] = [x, y, z]
    return T


def to_xy_yaw(T: np.ndarray) -> tuple[float, float, float]:
    """Planar part (x, y, yaw) of a 4x4 transform."""
    return float(T[0, 3]), float(T[1, 3]), float(np.arctan2(T[1, 0], T[0, 0]))


def to_xy_yaws(T: np.ndarray) -> np.ndarray:
    """(n, 3) planar parts (x, y, yaw) of (n, 4, 4) transforms (m, m, rad): :func:`to_xy_yaw` on
    many at once."""
    T = np.asarray(T, dtype=np.float64).reshape(-1, 4, 4)
    return np.column_stack([T[:, 0, 3], T[:, 1, 3], np.arctan2(T[:, 1, 0], T[:, 0, 0])])


def wrap_angle(angle: float) -> float:
    """``angle`` (rad) wrapped to [-pi, pi)."""
    return float((angle + np.pi) % (2 * np.pi) - np.pi)


def yaw_of(T: np.ndarray) -> float:
    """Rotation about z (rad) of a 4x4 transform."""
    return float(np.arctan2(T[1, 0], T[0, 0]))


def project_planar(T: np.ndarray) -> np.ndarray:
    """Keep x, y, yaw of a transform (3 DoF), dropping z, roll and pitch."""
    x, y, yaw = to_xy_yaw(T)
    return from_xy_yaw(x, y, yaw)


def rotation_angle(T: np.ndarray) -> float:
    """Angle (rad) of the rotation part of a 4x4 transform."""
    c = (np.trace(T[:3, :3]) - 1.0) / 2.0
    return float(np.arccos(np.clip(c, -1.0, 1.0)))


def is_rigid(T: np.ndarray, tol: float = 1e-4) -> bool:
    """True when T is a finite 4x4 rigid transform."""
    T = np.asarray(T)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        return False
    R = T[:3, :3]
    return bool(np.allclose(R @ R.T, np.eye(3), atol=tol) and abs(np.linalg.det(R) - 1) < tol
                and np.allclose(T[3], [0, 0, 0, 1]))
