"""Trajectory samples and rotation chains with exact derivatives, shared by the simulator's trajectories.

``FIRST_FRAME_S``: the first camera frame's time in every simulated session (one second after the
first IMU sample).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

FIRST_FRAME_S = 1.0


@dataclass
class MotionState:
    """Trajectory samples (N = len(t_s)); ``omega_cam``/``alpha_cam`` in the camera frame."""

    t_s: np.ndarray
    R_world_cam: np.ndarray   # (N, 3, 3)
    p_world_cam: np.ndarray   # (N, 3) camera centre
    v_world: np.ndarray       # (N, 3) m/s
    a_world: np.ndarray       # (N, 3) m/s^2 (kinematic, gravity not included)
    omega_cam: np.ndarray     # (N, 3) rad/s, body angular velocity: R^T dR/dt = [omega]x
    alpha_cam: np.ndarray     # (N, 3) rad/s^2, d(omega_cam)/dt

    @property
    def T_world_cam(self) -> np.ndarray:
        n = len(self.t_s)
        T = np.tile(np.eye(4), (n, 1, 1))
        T[:, :3, :3] = self.R_world_cam
        T[:, :3, 3] = self.p_world_cam
        return T


_AXES = {"x": 0, "y": 1, "z": 2}


def _elementary(axis: str, th: np.ndarray) -> np.ndarray:
    c, s = np.cos(th), np.sin(th)
    n = len(th)
    R = np.zeros((n, 3, 3))
    i = _AXES[axis]
    j, k = (i + 1) % 3, (i + 2) % 3
    R[:, i, i] = 1.0
    R[:, j, j] = c
    R[:, k, k] = c
    R[:, k, j] = s
    R[:, j, k] = -s
    return R


Factor = tuple  # ("x"|"y"|"z", theta, dtheta, ddtheta) or ("const", R)


def rotation_chain(factors: list[Factor], n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``R = F1 F2 ... Fk`` with its body angular velocity and acceleration (time derivatives given)."""
    M = np.tile(np.eye(3), (n, 1, 1))
    w = np.zeros((n, 3))
    a = np.zeros((n, 3))
    for f in reversed(factors):
        if f[0] == "const":
            M = np.einsum("ij,njk->nik", f[1], M)
            continue
        axis, th, dth, ddth = f
        e = _AXES[axis]
        col = M[:, e, :]  # M^T e_k = row e of M
        v = col * dth[:, None]
        a = col * ddth[:, None] - np.cross(w, v) + a
        w = v + w
        M = np.einsum("nij,njk->nik", _elementary(axis, th), M)
    return M, w, a
