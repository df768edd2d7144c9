"""Rigid-body geometry: rotations, quaternions, poses.  Pure NumPy, no I/O.

Conventions used everywhere in stereopath:

* A pose ``T_a_b`` is a 4x4 homogeneous matrix that maps points expressed in
  frame ``b`` into frame ``a``: ``p_a = T_a_b @ p_b``.  Trajectories store
  ``T_world_cam`` (camera-to-world), so the camera centre in the world is
  ``T_world_cam[:3, 3]``.
* Cameras: x right, y down, z forward (OpenCV).  Units are metres and radians
  unless a name says otherwise (``_deg``, ``_mm``, ``_ns``).
* Quaternions are stored ``(x, y, z, w)`` as in the TUM trajectory format.
* Euler angles for reports follow the reference paper's Eq. 1:
  ``R = Rx(a) @ Ry(b) @ Rz(c)``.
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "skew",
    "so3_exp",
    "so3_log",
    "rot_x",
    "rot_y",
    "rot_z",
    "euler_xyz_to_matrix",
    "matrix_to_euler_xyz",
    "project_to_so3",
    "chordal_mean",
    "rotation_angle_deg",
    "quat_xyzw_to_matrix",
    "matrix_to_quat_xyzw",
    "make_pose",
    "invert_pose",
]


def skew(v: np.ndarray) -> np.ndarray:
    """Cross-product matrix ``[v]_x`` so that ``skew(a) @ b == cross(a, b)``."""
    x, y, z = np.asarray(v, dtype=float).reshape(3)
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def so3_exp(rotvec: np.ndarray) -> np.ndarray:
    """Rotation matrix of a rotation vector (axis * angle, radians), Rodrigues' formula."""
    w = np.asarray(rotvec, dtype=float).reshape(3)
    theta = float(np.linalg.norm(w))
    K = skew(w)
    if theta < 1e-8:
        return np.eye(3) + K + 0.5 * K @ K
    return np.eye(3) + np.sin(theta) / theta * K + (1.0 - np.cos(theta)) / theta**2 * K @ K


def so3_log(R: np.ndarray) -> np.ndarray:
    """Rotation vector of a rotation matrix (inverse of :func:`so3_exp`)."""
    R = np.asarray(R, dtype=float)
    cos_t = np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0)
    theta = float(np.arccos(cos_t))
    v = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    if theta < 1e-8:
        return 0.5 * v
    if np.pi - theta < 1e-4:
        # Near pi the antisymmetric part vanishes; take the axis from R + I.
        M = (R + np.eye(3)) / 2.0
        axis = M[int(np.argmax(np.diag(M)))]
        axis = axis / np.linalg.norm(axis)
        if np.dot(axis, v) < 0:
            axis = -axis
        return axis * theta
    return theta / (2.0 * np.sin(theta)) * v


def rot_x(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def rot_y(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def rot_z(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def euler_xyz_to_matrix(angles_rad: np.ndarray) -> np.ndarray:
    """``R = Rx(a) Ry(b) Rz(c)`` (the paper's Eq. 1)."""
    a, b, c = np.asarray(angles_rad, dtype=float).reshape(3)
    return rot_x(a) @ rot_y(b) @ rot_z(c)


def matrix_to_euler_xyz(R: np.ndarray) -> np.ndarray:
    """Angles ``(a, b, c)`` in radians with ``R = Rx(a) Ry(b) Rz(c)``.

    For this order ``R[0, 2] = sin(b)``, ``R[1, 2] = -sin(a) cos(b)``,
    ``R[2, 2] = cos(a) cos(b)``, ``R[0, 1] = -cos(b) sin(c)``, ``R[0, 0] = cos(b) cos(c)``.
    At gimbal lock (|b| = 90 deg) ``c`` is set to zero.
    """
    R = np.asarray(R, dtype=float)
    sb = float(np.clip(R[0, 2], -1.0, 1.0))
    b = np.arcsin(sb)
    if abs(sb) < 1.0 - 1e-10:
        a = np.arctan2(-R[1, 2], R[2, 2])
        c = np.arctan2(-R[0, 1], R[0, 0])
    else:
        a = np.arctan2(R[2, 1], R[1, 1])
        c = 0.0
    return np.array([a, b, c])


def project_to_so3(M: np.ndarray) -> np.ndarray:
    """Nearest rotation matrix in the Frobenius sense (SVD, determinant forced to +1)."""
    U, _, Vt = np.linalg.svd(np.asarray(M, dtype=float))
    D = np.eye(3)
    D[2, 2] = np.sign(np.linalg.det(U @ Vt)) or 1.0
    return U @ D @ Vt


def project_to_se3(T: np.ndarray) -> np.ndarray:
    """``T`` (4x4) with its rotation block projected onto SO(3): products of corrections stay rigid."""
    out = np.array(T, dtype=float)
    out[:3, :3] = project_to_so3(out[:3, :3])
    return out


def chordal_mean(rotations: list[np.ndarray] | np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
    """Chordal L2 mean of rotations: the element-wise (weighted) mean projected onto SO(3).

    This is the proper reading of the paper's Eq. 3 ``(R1 + R2) / 2``, whose
    raw result is not a rotation.
    """
    Rs = np.asarray(rotations, dtype=float).reshape(-1, 3, 3)
    if len(Rs) == 0:
        raise ValueError("chordal_mean needs at least one rotation")
    w = np.ones(len(Rs)) if weights is None else np.asarray(weights, dtype=float).reshape(-1)
    M = np.tensordot(w / w.sum(), Rs, axes=1)
    return project_to_so3(M)


def rotation_angle_deg(R: np.ndarray) -> float:
    """Angle of a rotation matrix in degrees."""
    return float(np.degrees(np.linalg.norm(so3_log(R))))


def quat_xyzw_to_matrix(q: np.ndarray) -> np.ndarray:
    """Rotation matrix of a unit quaternion ``(x, y, z, w)`` (normalised first)."""
    x, y, z, w = np.asarray(q, dtype=float).reshape(4) / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def matrix_to_quat_xyzw(R: np.ndarray) -> np.ndarray:
    """Unit quaternion ``(x, y, z, w)`` with ``w >= 0`` of a rotation matrix."""
    R = np.asarray(R, dtype=float)
    tr = np.trace(R)
    if tr > 0:
        s = 2.0 * np.sqrt(tr + 1.0)
        q = np.array([(R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s, 0.25 * s])
    elif R[0, 0] > R[1, 1] and R[0, 0] > R[2, 2]:
        s = 2.0 * np.sqrt(1.0 + R[0, 0] - R[1, 1] - R[2, 2])
        q = np.array([0.25 * s, (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s, (R[2, 1] - R[1, 2]) / s])
    elif R[1, 1] > R[2, 2]:
        s = 2.0 * np.sqrt(1.0 + R[1, 1] - R[0, 0] - R[2, 2])
        q = np.array([(R[0, 1] + R[1, 0]) / s, 0.25 * s, (R[1, 2] + R[2, 1]) / s, (R[0, 2] - R[2, 0]) / s])
    else:
        s = 2.0 * np.sqrt(1.0 + R[2, 2] - R[0, 0] - R[1, 1])
        q = np.array([(R[0, 2] + R[2, 0]) / s, (R[1, 2] + R[2, 1]) / s, 0.25 * s, (R[1, 0] - R[0, 1]) / s])
    q /= np.linalg.norm(q)
    return -q if q[3] < 0 else q


def make_pose(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """4x4 pose from a rotation matrix and a translation vector."""
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = np.asarray(t, dtype=float).reshape(3)
    return T


def invert_pose(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid 4x4 pose (``T_b_a`` from ``T_a_b``)."""
    R = T[:3, :3]
    Ti = np.eye(4)
    Ti[:3, :3] = R.T
    Ti[:3, 3] = -R.T @ T[:3, 3]
    return Ti
