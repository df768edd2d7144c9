"""Calibration math: stereo rig from chessboard views, IMU bias and gravity from a still period.

Pure functions on arrays (no file I/O); the command-line tools in
``device/commands/calibrate_*.py`` read images and samples and write the results.

Stereo: chessboard inner corners (``cols x rows``) are detected and refined per image;
each camera is calibrated alone (``cv2.calibrateCamera``), then the pair with the
intrinsics as the initial guess (``cv2.stereoCalibrate`` with
``CALIB_USE_INTRINSIC_GUESS``), giving ``R``, ``T`` = ``T_cam1_cam0`` (OpenCV convention,
metres when the square size is given in metres).

IMU: in a still window the gyro measures only its bias (plus the Earth's rotation,
7.3e-5 rad/s, below the MPU-6050's resolution) and the accelerometer the specific force
``+g`` pointing up.  :func:`imu_still_calibration` returns the gyro bias, the mean
specific force, its norm and the rotation ``R_world_imu`` that makes the measured
gravity vertical (world z up, yaw arbitrary: set to zero).  :func:`detect_still_window`
finds the longest still stretch; :func:`implied_gyro_bias` gives the bias implied by a
ground-truth rotation over the same window (mean gyro minus true mean rate).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from stereopath.device.errors import CalibrationError
from stereopath.device.core.frames import ImuSamples
from stereopath.device.core.geometry import so3_exp, so3_log
from stereopath.device.core.rig import Rig, make_camera, make_rig

STANDARD_GRAVITY = 9.80665


# -------------------------------------------------------------------------------------------
# stereo


def parse_board(text: str) -> tuple[int, int]:
    """``"9x6"`` -> (9, 6) inner corners (columns, rows)."""
    try:
        cols, rows = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise CalibrationError(f"board {text!r}: expected COLSxROWS inner corners, e.g. 9x6") from None
    if cols < 2 or rows < 2:
        raise CalibrationError(f"board {text!r}: need at least 2x2 inner corners")
    return cols, rows


def board_points(board: tuple[int, int], square_m: float) -> np.ndarray:
    """(N, 3) float32 corner coordinates on the board plane (z = 0), row by row."""
    if square_m <= 0:
        raise CalibrationError(f"square size must be positive, got {square_m}")
    cols, rows = board
    grid = np.zeros((rows * cols, 3), np.float32)
    grid[:, :2] = np.mgrid[0:cols, 0:rows].T.reshape(-1, 2) * square_m
    return grid


def find_corners(gray: np.ndarray, board: tuple[int, int]) -> np.ndarray | None:
    """Sub-pixel inner corners (N, 1, 2) float32, or None when the board is not found."""
    if gray.ndim == 3:
        gray = cv2.cvtColor(gray, cv2.COLOR_BGR2GRAY)
    flags = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
    ok, corners = cv2.findChessboardCorners(gray, board, flags=flags)
    if not ok:
        return None
    criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 50, 1e-3)
    return cv2.cornerSubPix(gray, corners.astype(np.float32), (11, 11), (-1, -1), criteria)


@dataclass
class StereoCalibration:
    rig: Rig
    rms_px: float            # stereo RMS reprojection error (both cameras)
    rms_left_px: float       # single-camera RMS errors
    rms_right_px: float
    pairs_used: int
    per_view_px: np.ndarray  # (pairs, 2) RMS per view and camera

    @property
    def baseline_m(self) -> float:
        return self.rig.baseline_m


def calibrate_stereo(corners_left: list[np.ndarray], corners_right: list[np.ndarray], image_size: tuple[int, int],
                     board: tuple[int, int], square_m: float, name: str = "calibrated") -> StereoCalibration:
    """Rig from matched chessboard detections (lists of (N, 1, 2) corners, same order)."""
    if len(corners_left) != len(corners_right):
        raise CalibrationError("calibrate_stereo: left and right detection lists differ in length")
    if len(corners_left) < 3:
        raise CalibrationError(f"calibrate_stereo: need at least 3 pairs with the board found in both "
                               f"images, got {len(corners_left)}")
    obj = board_points(board, square_m)
    objs = [obj] * len(corners_left)
    size = (int(image_size[0]), int(image_size[1]))
    rms_l, K0, d0, _, _ = cv2.calibrateCamera(objs, corners_left, size, None, None)
    rms_r, K1, d1, _, _ = cv2.calibrateCamera(objs, corners_right, size, None, None)
    criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 100, 1e-6)
    out = cv2.stereoCalibrateExtended(objs, corners_left, corners_right, K0, d0, K1, d1, size, None, None,
                                      flags=cv2.CALIB_USE_INTRINSIC_GUESS, criteria=criteria)
    rms, K0, d0, K1, d1, R, T = out[:7]
    per_view = out[11]
    if not np.isfinite(rms):
        raise CalibrationError("calibrate_stereo: optimisation diverged")
    cam0 = make_camera("cam0", K0, d0.reshape(-1), size)
    cam1 = make_camera("cam1", K1, d1.reshape(-1), size)
    rig = make_rig(cam0, cam1, R, np.asarray(T).reshape(3), name=name)
    return StereoCalibration(rig, float(rms), float(rms_l), float(rms_r), len(objs),
                             np.asarray(per_view, float).reshape(len(objs), -1))


# -------------------------------------------------------------------------------------------
# IMU


@dataclass
class ImuStillCalibration:
    gyro_bias_rad_s: np.ndarray     # (3,) mean angular rate while still
    gyro_std_rad_s: np.ndarray      # (3,) spread (noise + residual motion)
    accel_mean_m_s2: np.ndarray     # (3,) mean specific force (gravity reaction, points up)
    accel_std_m_s2: np.ndarray
    gravity_m_s2: float             # |accel_mean|
    R_world_imu: np.ndarray         # rotation making accel_mean point along world +z (yaw = 0)
    t0_ns: int
    t1_ns: int
    samples: int

    @property
    def duration_s(self) -> float:
        return (self.t1_ns - self.t0_ns) / 1e9

    @property
    def gravity_error_m_s2(self) -> float:
        return self.gravity_m_s2 - STANDARD_GRAVITY

    def as_dict(self) -> dict[str, object]:
        return {
            "gyro_bias_rad_s": [float(v) for v in self.gyro_bias_rad_s],
            "gyro_std_rad_s": [float(v) for v in self.gyro_std_rad_s],
            "accel_mean_m_s2": [float(v) for v in self.accel_mean_m_s2],
            "accel_std_m_s2": [float(v) for v in self.accel_std_m_s2],
            "gravity_m_s2": float(self.gravity_m_s2),
            "R_world_imu": [[float(v) for v in row] for row in self.R_world_imu],
            "window_ns": [int(self.t0_ns), int(self.t1_ns)],
            "samples": int(self.samples),
        }


def gravity_alignment(accel_mean: np.ndarray) -> np.ndarray:
    """Smallest rotation ``R_world_imu`` with ``R @ accel_mean`` along +z (world z up)."""
    a = np.asarray(accel_mean, float)
    n = np.linalg.norm(a)
    if n < 1e-6:
        raise CalibrationError("gravity alignment: mean acceleration is zero (accelerometer not working?)")
    u = a / n
    z = np.array([0.0, 0.0, 1.0])
    axis = np.cross(u, z)
    s, c = np.linalg.norm(axis), float(np.dot(u, z))
    if s < 1e-12:
        return np.eye(3) if c > 0 else np.diag([1.0, -1.0, -1.0])
    return so3_exp(axis / s * np.arctan2(s, c))


def imu_still_calibration(samples: ImuSamples) -> ImuStillCalibration:
    """Gyro bias and gravity from samples taken while the unit was still."""
    if len(samples) < 10:
        raise CalibrationError(f"IMU calibration: need at least 10 still samples, got {len(samples)}")
    g, a = samples.gyro_rad_s, samples.accel_m_s2
    am = a.mean(axis=0)
    return ImuStillCalibration(
        gyro_bias_rad_s=g.mean(axis=0), gyro_std_rad_s=g.std(axis=0),
        accel_mean_m_s2=am, accel_std_m_s2=a.std(axis=0), gravity_m_s2=float(np.linalg.norm(am)),
        R_world_imu=gravity_alignment(am), t0_ns=int(samples.t_ns[0]), t1_ns=int(samples.t_ns[-1]),
        samples=len(samples))


# what "still" means for the IMU calibration (per block of STILL_BLOCK_S): the block means of the gyro (rad/s)
# and the accelerometer (m/s^2) within these steps of each other, and each block's spread below these
STILL_BLOCK_S, STILL_GYRO_STEP, STILL_ACCEL_STEP, STILL_GYRO_STD, STILL_ACCEL_STD = 0.5, 0.01, 0.3, 0.2, 2.5


def _block_index(t_ns: np.ndarray, block_s: float) -> np.ndarray:
    """Sample indexes where consecutive ``block_s`` blocks from the first sample start (the samples after
    the last whole block's start are its own, shorter block's: callers drop it or merge it)."""
    edges = np.arange(t_ns[0], t_ns[-1] + 1, max(1, int(block_s * 1e9)))
    return np.searchsorted(t_ns, edges)


def check_still(samples: ImuSamples, what: str, block_s: float = STILL_BLOCK_S) -> None:
    """:class:`CalibrationError` when ``samples`` were not taken at rest, by the criteria of
    :func:`detect_still_window`: the means of ``block_s`` blocks within ``STILL_GYRO_STEP`` /
    ``STILL_ACCEL_STEP`` of the window's mean, each block's spread below ``STILL_GYRO_STD`` /
    ``STILL_ACCEL_STD``.  A window shorter than four blocks is cut into four, and a block mean may differ
    by four times its own noise where that is more (short blocks, a vibrating unit); the samples after the
    last whole block join it.  ``what`` names the window in the message."""
    t = samples.t_ns
    if len(t) < 20:
        raise CalibrationError(f"{what}: {len(t)} IMU samples are too few to tell whether the unit was still "
                               f"(at least 20)")
    block_s = min(block_s, (t[-1] - t[0]) / 4e9)
    idx = _block_index(t, block_s)
    bounds = list(zip(idx[:-1], idx[1:]))
    bounds[-1] = (bounds[-1][0], len(t))  # the tail joins the last block
    if min(i1 - i0 for i0, i1 in bounds) < 5:
        raise CalibrationError(f"{what}: {len(t)} IMU samples are too few to tell whether the unit was still")

    def test(x: np.ndarray, step_max: float, std_max: float) -> tuple[bool, float, float, float]:
        means = np.array([x[i0:i1].mean(axis=0) for i0, i1 in bounds])
        stds = np.array([x[i0:i1].std(axis=0).max() for i0, i1 in bounds])
        allowed = max(step_max, 4.0 * float(np.median(stds)) / np.sqrt(min(i1 - i0 for i0, i1 in bounds)))
        step = float(np.abs(means - means.mean(axis=0)).max())
        return step <= allowed and float(stds.max()) <= std_max, step, allowed, float(stds.max())

    g_ok, g_step, g_allowed, g_std = test(samples.gyro_rad_s, STILL_GYRO_STEP, STILL_GYRO_STD)
    a_ok, a_step, a_allowed, a_std = test(samples.accel_m_s2, STILL_ACCEL_STEP, STILL_ACCEL_STD)
    if not (g_ok and a_ok):
        raise CalibrationError(
            f"{what}: the unit was not still (its {block_s:.2g} s means of the gyro differ by up to {g_step:.4f} rad/s, "
            f"of the accelerometer by {a_step:.3f} m/s^2; at rest they stay within {g_allowed:.4f} and "
            f"{a_allowed:.3f}; spread up to {g_std:.3f} rad/s and {a_std:.2f} m/s^2): the bias and gravity "
            f"would be wrong")


def detect_still_window(samples: ImuSamples, min_duration_s: float = 2.0, block_s: float = STILL_BLOCK_S,
                        gyro_step_max: float = STILL_GYRO_STEP, accel_step_max: float = STILL_ACCEL_STEP,
                        gyro_std_max: float = STILL_GYRO_STD, accel_std_max: float = STILL_ACCEL_STD) -> tuple[int, int]:
    """Longest still stretch of ``block_s`` blocks: (t0_ns, t1_ns).

    Stillness is judged on block *means*, so that vibration (motors, a hand) does not
    hide a still unit: a run of blocks continues while each block's mean gyro stays within
    ``gyro_step_max`` (rad/s) and its mean acceleration within ``accel_step_max`` (m/s^2) of
    the run's mean so far (a turn changes the mean rate, a tilt the mean acceleration); a
    block whose spread exceeds ``gyro_std_max`` / ``accel_std_max`` (shaking) ends the run.
    Raises :class:`CalibrationError` when no run lasts ``min_duration_s``.
    """
    t = samples.t_ns
    if len(t) < 10:
        raise CalibrationError("still-window detection: too few samples")
    idx = _block_index(t, block_s)
    best = (0, 0)
    run: list[int] = []   # block numbers of the current run
    g_sum = np.zeros(3)
    a_sum = np.zeros(3)
    for b in range(len(idx) - 1):
        i0, i1 = idx[b], idx[b + 1]
        ok = i1 - i0 >= 5
        if ok:
            g = samples.gyro_rad_s[i0:i1]
            a = samples.accel_m_s2[i0:i1]
            gm, am = g.mean(axis=0), a.mean(axis=0)
            ok = bool(np.all(g.std(axis=0) < gyro_std_max) and np.all(a.std(axis=0) < accel_std_max))
        if ok and run:
            ok = bool(np.max(np.abs(gm - g_sum / len(run))) <= gyro_step_max
                      and np.max(np.abs(am - a_sum / len(run))) <= accel_step_max)
            if not ok:  # this block may start the next run
                run, g_sum, a_sum = [], np.zeros(3), np.zeros(3)
                ok = True
        if ok and i1 - i0 >= 5:
            run.append(b)
            g_sum += gm
            a_sum += am
            if len(run) > best[1] - best[0]:
                best = (run[0], run[-1] + 1)
        else:
            run, g_sum, a_sum = [], np.zeros(3), np.zeros(3)
    if best[1] == best[0]:
        raise CalibrationError(f"no still period of at least {min_duration_s:.1f} s found")
    t0, t1 = int(t[idx[best[0]]]), int(t[idx[best[1]] - 1])
    if (t1 - t0) / 1e9 < min_duration_s:
        raise CalibrationError(f"no still period of at least {min_duration_s:.1f} s found "
                               f"(longest {(t1 - t0) / 1e9:.1f} s)")
    return t0, t1


def implied_gyro_bias(samples: ImuSamples, R_world_body0: np.ndarray, R_world_body1: np.ndarray,
                      dt_s: float) -> np.ndarray:
    """Gyro bias implied by a true rotation over a window: mean gyro minus the true mean rate.

    The true mean body rate over ``dt_s`` is ``log(R0^T R1) / dt`` (exact for a constant
    rate, first order otherwise, which suffices for nearly still windows).
    """
    if dt_s <= 0:
        raise CalibrationError("implied_gyro_bias: window duration must be positive")
    w_true = so3_log(np.asarray(R_world_body0).T @ np.asarray(R_world_body1)) / dt_s
    return samples.gyro_rad_s.mean(axis=0) - w_true
