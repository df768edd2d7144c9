"""The ``"handheld"`` trajectory: real recorded motion, rescaled to a hand-held table-top scan.

A stand-in for hand-held recordings, whose motion the analytic trajectories do not have: it
replays a real flight (the EuRoC ``V1_01`` motion-capture ground truth, a TUM file
``trajectories/V101_gt.txt`` of the shared data, 20 Hz) from :data:`WINDOW_START_S` seconds into
it, when the vehicle is already moving:

* **switched on in motion**: there is no still block; the rig moves from the first IMU sample on,
  as when the box is switched on while carried;
* **positions** are the flight's, relative to its pose at the window start, turned about the
  vertical and scaled so that the session's frames travel :data:`SCAN_LENGTH_M` (a 1-2 m scan),
  starting at the arc's start point (0.9-1.2 m from the table objects);
* **orientations** are the flight's, at their real angular speed (the motion blur comes from
  them), expressed in a level frame of the vehicle's heading at the window start and turned so
  that the camera looks at the table objects at the start, tilted down :data:`TILT_DEG`.

The recorded samples are fitted by least squares with Gaussian radial basis functions (one every
:data:`BASIS_SPACING_S`, width the same), which give smooth positions and Euler angles with
closed-form first and second derivatives: the IMU truth built on them is exact for this smooth
motion, as for the analytic trajectories.

The motion file is not part of the package: it is found at ``$STEREOPATH_MOTION_FILE``, else under
``$STEREOPATH_DATA/trajectories/``, else in the ``shared/data/trajectories/`` folder beside the
source tree (or one level further up, for a work tree).
"""

from __future__ import annotations

import functools
import os
from pathlib import Path

import numpy as np

from stereopath.device.errors import ConfigError
from stereopath.device.sim.scene import TARGET_WORLD
from stereopath.device.sim.motion import FIRST_FRAME_S, MotionState, rotation_chain

MOTION_FILE_NAME = "V101_gt.txt"
WINDOW_START_S = 40.0      # seconds into the flight: airborne and moving
SCAN_LENGTH_M = 1.5        # path travelled by the default session's frames (400 at 20 Hz)
SCAN_FRAMES = 400
SCAN_RATE_HZ = 20.0
TILT_DEG = 25.0            # camera pitched down from the vehicle's level heading
BASIS_SPACING_S = 0.1      # Gaussian basis: one centre every 0.1 s, sigma 0.1 s
RIDGE = 1e-6
START_RADIUS_M, START_HEIGHT_M, START_PHI_DEG = 1.05, 1.30, -115.0  # the arc's start point

# the camera in the level vehicle frame (x forward, y left, z up): z forward, x right, y down
_R_BODY_CAM = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def motion_file() -> Path:
    """The recorded flight (module doc); :class:`ConfigError` when it cannot be found."""
    env = os.environ.get("STEREOPATH_MOTION_FILE")
    cands = [Path(env)] if env else []
    if os.environ.get("STEREOPATH_DATA"):
        cands.append(Path(os.environ["STEREOPATH_DATA"]) / "trajectories" / MOTION_FILE_NAME)
    root = Path(__file__).resolve().parents[2]
    cands += [root.parent / "shared" / "data" / "trajectories" / MOTION_FILE_NAME,
              root.parent.parent / "shared" / "data" / "trajectories" / MOTION_FILE_NAME]
    for c in cands:
        if c.is_file():
            return c
    raise ConfigError(f"trajectory = 'handheld' replays {MOTION_FILE_NAME} (a TUM file of a real flight), not found "
                      f"at {', '.join(map(str, cands))}; set STEREOPATH_MOTION_FILE or STEREOPATH_DATA")


@functools.lru_cache(maxsize=2)
def _load_tum(path: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(t_s, positions (N, 3), rotations (N, 3, 3)) of a TUM file."""
    from stereopath.device.core.geometry import quat_xyzw_to_matrix

    rows = np.loadtxt(path, comments="#", ndmin=2)
    if rows.shape[1] != 8 or len(rows) < 10:
        raise ConfigError(f"{path}: expected TUM rows 'time tx ty tz qx qy qz qw'")
    R = np.array([quat_xyzw_to_matrix(q) for q in rows[:, 4:8]])
    return rows[:, 0] - rows[0, 0], rows[:, 1:4], R


class _GaussianBasis:
    """``f(t) = sum_k c_k exp(-(t - t_k)^2 / (2 s^2))`` fitted by ridge least squares, with exact derivatives."""

    def __init__(self, t: np.ndarray, values: np.ndarray, t0: float, t1: float, spacing: float) -> None:
        self.centres = np.arange(t0 - 2 * spacing, t1 + 2 * spacing + 1e-9, spacing)
        self.s = float(spacing)
        A = self._phi(t)[0]
        lhs = A.T @ A + RIDGE * len(t) * np.eye(len(self.centres))
        self.c = np.linalg.solve(lhs, A.T @ values)

    def _phi(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        d = np.asarray(t, float)[:, None] - self.centres[None, :]
        s2 = self.s**2
        phi = np.exp(-0.5 * d**2 / s2)
        return phi, -d / s2 * phi, (d**2 / s2**2 - 1.0 / s2) * phi

    def __call__(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        phi, dphi, ddphi = self._phi(t)
        return phi @ self.c, dphi @ self.c, ddphi @ self.c


def _euler_zyx(R: np.ndarray) -> np.ndarray:
    """(N, 3) yaw (unwrapped), pitch, roll with ``R = Rz(yaw) Ry(pitch) Rx(roll)``."""
    yaw = np.unwrap(np.arctan2(R[:, 1, 0], R[:, 0, 0]))
    pitch = -np.arcsin(np.clip(R[:, 2, 0], -1.0, 1.0))
    roll = np.arctan2(R[:, 2, 1], R[:, 2, 2])
    return np.stack([yaw, pitch, roll], 1)


def _rot_z(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _rot_y(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


class HandheldTrajectory:
    """The recorded motion as a trajectory (the interface of
    :class:`stereopath.device.sim.trajectories.AnalyticTrajectory`); see the module doc."""

    name = "handheld"
    hand_held = True  # the session renders it with auto-exposure changes and motion blur

    def __init__(self, duration_s: float, path: Path | None = None, scan_length_m: float = SCAN_LENGTH_M) -> None:
        self.duration_s = float(duration_s)
        t, p, R = _load_tum(str(path or motion_file()))
        t0, t1 = WINDOW_START_S, WINDOW_START_S + self.duration_s
        if t1 + 1.0 > t[-1]:
            raise ConfigError(f"trajectory = 'handheld': the recorded flight lasts {t[-1]:.1f} s, a session of "
                              f"{self.duration_s:.1f} s from {WINDOW_START_S:.0f} s into it does not fit")
        keep = (t >= t0 - 1.0) & (t <= t1 + 1.0)
        t, p, R = t[keep] - t0, p[keep], R[keep]
        i0 = int(np.argmin(np.abs(t)))
        # a level frame with the vehicle's heading at the window start
        fwd = R[i0][:, 0] - R[i0][2, 0] * np.array([0.0, 0.0, 1.0])
        heading = float(np.arctan2(fwd[1], fwd[0]))
        R_level0 = _rot_z(heading)
        R_v = np.einsum("ij,njk->nik", R_level0.T, R) @ (R[i0].T @ R_level0)  # level at the start, real motion after
        # turn the heading at the start so that the camera looks at the table objects from the arc's start point
        phi = np.radians(START_PHI_DEG)
        start = np.array([START_RADIUS_M * np.cos(phi), START_RADIUS_M * np.sin(phi), START_HEIGHT_M])
        to_target = TARGET_WORLD - start
        self._yaw0 = float(np.arctan2(to_target[1], to_target[0]))
        turn = _rot_z(self._yaw0) @ R_level0.T
        rel = (p - p[i0]) @ turn.T
        frame_t = FIRST_FRAME_S + np.arange(SCAN_FRAMES) / SCAN_RATE_HZ
        self._pos = _GaussianBasis(t, rel, -1.0, self.duration_s + 1.0, BASIS_SPACING_S)
        travelled = float(np.sum(np.linalg.norm(np.diff(self._pos(frame_t)[0], axis=0), axis=1)))
        self.scale = scan_length_m / travelled
        self.start = start
        self._ang = _GaussianBasis(t, _euler_zyx(R_v), -1.0, self.duration_s + 1.0, BASIS_SPACING_S)
        self._cam = _rot_y(np.radians(TILT_DEG)) @ _R_BODY_CAM

    def state(self, t_s) -> MotionState:
        t = np.atleast_1d(np.asarray(t_s, float))
        P, dP, ddP = self._pos(t)
        A, dA, ddA = self._ang(t)
        factors = [("z", A[:, 0] + self._yaw0, dA[:, 0], ddA[:, 0]), ("y", A[:, 1], dA[:, 1], ddA[:, 1]),
                   ("x", A[:, 2], dA[:, 2], ddA[:, 2]), ("const", self._cam)]
        R, w, al = rotation_chain(factors, len(t))
        return MotionState(t, R, self.start + self.scale * P, self.scale * dP, self.scale * ddP, w, al)

    def pose(self, t_s) -> np.ndarray:
        """``T_world_cam0`` (4, 4) for a scalar time, (N, 4, 4) for an array."""
        T = self.state(t_s).T_world_cam
        return T[0] if np.ndim(t_s) == 0 else T

    def path_length_m(self, t_s: np.ndarray) -> float:
        p = self.state(np.asarray(t_s, float)).p_world_cam
        return float(np.sum(np.linalg.norm(np.diff(p, axis=0), axis=1)))

