"""Trajectory files: TUM (``t tx ty tz qx qy qz qw``, seconds) and KITTI (3x4 row-major poses).

A :class:`~stereopath.device.core.trajectory.Trajectory` holds ``t_ns`` (N,) int64 and ``T_world_cam`` (N, 4, 4).
Malformed files raise :class:`DatasetError` with the line number.
"""

from __future__ import annotations

import io
from decimal import Decimal, InvalidOperation
from pathlib import Path

import numpy as np

from stereopath.device.errors import DatasetError
from stereopath.device.formats.csvrows import INT64_MAX, INT64_MIN, read_lines
from stereopath.device.formats.fileio import write_text_atomic
from stereopath.device.core.geometry import matrix_to_quat_xyzw, project_to_so3
from stereopath.device.core.trajectory import Trajectory


_SECONDS_BOUND = Decimal(10) ** 10  # past int64 nanoseconds (about 9.2e9 s, 292 years either side of 1970)

# Physical sanity of a pose read from a file.  A hand-held scan, a drone or a car stays within 1,000 km of
# where its path starts, and a value beyond that (1e308 fits a float) would overflow the alignment's sums
# of squares.  A quaternion written with two decimals is within 1 % of unit length: 5 % is a typo or a
# column in the wrong place.  A rotation matrix written with six digits is orthonormal within 1e-5.
POSITION_BOUND_M = 1e6
QUAT_NORM_TOL = 0.05
ROTATION_TOL = 1e-2  # max |R^T R - I|, as for a rig's rotation


def check_position(path: Path, line: int, p_m: np.ndarray) -> None:
    """Refuse a non-finite position or one farther than :data:`POSITION_BOUND_M` from the origin."""
    if not np.all(np.isfinite(p_m)):
        raise DatasetError(f"{path}:{line}: non-finite position")
    if float(np.max(np.abs(p_m))) > POSITION_BOUND_M:
        raise DatasetError(f"{path}:{line}: position {np.max(np.abs(p_m)):.3g} m from the origin is beyond the "
                           f"{POSITION_BOUND_M:.0e} m a trajectory may reach (a wrong unit or a damaged value?)")


def check_quaternion(path: Path, line: int, q: np.ndarray) -> None:
    """Refuse a quaternion that is not finite or not within :data:`QUAT_NORM_TOL` of unit length."""
    if not np.all(np.isfinite(q)):
        raise DatasetError(f"{path}:{line}: non-finite quaternion")
    big = float(np.max(np.abs(q)))
    n = big if big > 2.0 else float(np.linalg.norm(q))  # (1e308)^2 overflows; its largest element says enough
    if n < 1e-9:
        raise DatasetError(f"{path}:{line}: zero quaternion")
    if abs(n - 1.0) > QUAT_NORM_TOL:
        raise DatasetError(f"{path}:{line}: quaternion of length {n:.4g}, not a rotation (a unit quaternion is "
                           f"1 +- {QUAT_NORM_TOL})")


def checked_rotation(path: Path, line: int, R: np.ndarray) -> np.ndarray:
    """``R`` when it is (nearly) a rotation: |R^T R - I| within :data:`ROTATION_TOL`, det > 0; a rotation
    written with rounded elements beyond what the evaluation takes as a rotation (1e-6) is projected onto SO(3)."""
    if not np.all(np.isfinite(R)) or float(np.max(np.abs(R))) > 1.0 + ROTATION_TOL:
        raise DatasetError(f"{path}:{line}: rotation has an element beyond +-1: not a rotation matrix")
    err = float(np.max(np.abs(R.T @ R - np.eye(3))))
    if err > ROTATION_TOL or np.linalg.det(R) <= 0:
        raise DatasetError(f"{path}:{line}: not a rotation matrix (max |R^T R - I| = {err:.3g}, "
                           f"det = {np.linalg.det(R):.3g})")
    if np.allclose(R.T @ R, np.eye(3), atol=1e-6) and abs(np.linalg.det(R) - 1.0) <= 1e-6:
        return R  # as written: what the evaluation (evo's is_so3) takes as a rotation is not changed
    return project_to_so3(R)


def seconds_to_ns(text: str) -> int:
    """Exact conversion of a decimal seconds string to integer nanoseconds.

    Raises ``decimal.InvalidOperation`` for text that is not a number and ``ValueError`` for a
    time that is not finite or does not fit int64 nanoseconds.
    """
    d = Decimal(text)
    if not d.is_finite() or d.copy_abs() > _SECONDS_BOUND:  # before any arithmetic: 1e999999999 overflows it
        raise ValueError(f"time {text!r} s is not finite or outside the int64 nanosecond range")
    ns = int((d * 1_000_000_000).to_integral_value())
    if not INT64_MIN <= ns <= INT64_MAX:
        raise ValueError(f"time {text!r} s is outside the int64 nanosecond range")
    return ns


def ns_to_seconds_str(t_ns: int) -> str:
    t = int(t_ns)
    sign = "-" if t < 0 else ""
    t = abs(t)
    return f"{sign}{t // 1_000_000_000}.{t % 1_000_000_000:09d}"


def format_tum_line(t_ns: int, T: np.ndarray) -> str:
    q = matrix_to_quat_xyzw(T[:3, :3])
    p = T[:3, 3]
    return (f"{ns_to_seconds_str(t_ns)} {p[0]:.9f} {p[1]:.9f} {p[2]:.9f} "
            f"{q[0]:.9f} {q[1]:.9f} {q[2]:.9f} {q[3]:.9f}\n")


def write_tum(path: str | Path, traj: Trajectory) -> None:
    """Write a TUM file atomically (temp file + rename)."""
    p = Path(path)
    buf = io.StringIO()
    buf.write("# timestamp tx ty tz qx qy qz qw (T_world_cam, metres, seconds)\n")
    for t, T in zip(traj.t_ns, traj.T_world_cam):
        buf.write(format_tum_line(int(t), T))
    write_text_atomic(p, buf.getvalue(), fsync=False)


def read_tum_poses(path: str | Path, torn_tail_ok: bool = False) -> Trajectory | None:
    """Every pose of a TUM file, None when it has none (commas are accepted as separators).

    With ``torn_tail_ok`` a final line without its newline (a file cut by a crash while being
    appended to, e.g. a session's ``trajectory.tum``) is logged and ignored.
    """
    p = Path(path)
    ts, rows = [], []
    for i, s in read_lines(p, torn_tail_ok=torn_tail_ok):
        parts = s.replace(",", " ").split()
        if len(parts) != 8:
            raise DatasetError(f"{p}:{i}: expected 8 values (t tx ty tz qx qy qz qw), got {len(parts)}")
        try:
            t = seconds_to_ns(parts[0])
        except InvalidOperation:
            raise DatasetError(f"{p}:{i}: non-numeric value (timestamp {parts[0]!r})") from None
        except ValueError as exc:
            raise DatasetError(f"{p}:{i}: {exc}") from None
        try:
            v = np.array([float(x) for x in parts[1:]])
        except ValueError:
            raise DatasetError(f"{p}:{i}: non-numeric value") from None
        check_position(p, i, v[:3])
        check_quaternion(p, i, v[3:])
        ts.append(t)
        rows.append(v)
    return Trajectory.from_pose_rows(ts, rows) if ts else None


def read_tum(path: str | Path) -> Trajectory:
    """A complete TUM trajectory file (at least one pose)."""
    traj = read_tum_poses(path)
    if traj is None:
        raise DatasetError(f"{path}: no poses")
    return traj


def read_kitti_poses(path: str | Path, t_ns: np.ndarray | None = None) -> Trajectory:
    """KITTI pose file (12 values a row).  Without ``t_ns`` the rows get 0.1 s steps."""
    p = Path(path)
    Ts = []
    for i, line in read_lines(p, torn_tail_ok=False):  # DatasetError: missing, a folder, not text
        try:
            v = np.array([float(x) for x in line.split()])
        except ValueError:
            raise DatasetError(f"{p}:{i}: non-numeric value") from None
        if v.size != 12:
            raise DatasetError(f"{p}:{i}: expected 12 values, got {v.size}")
        if not np.all(np.isfinite(v)):
            raise DatasetError(f"{p}:{i}: non-finite value")
        T = np.eye(4)
        T[:3, :] = v.reshape(3, 4)
        T[:3, :3] = checked_rotation(p, i, T[:3, :3])
        check_position(p, i, T[:3, 3])
        Ts.append(T)
    if not Ts:
        raise DatasetError(f"{p}: no poses")
    if t_ns is None:
        t_ns = np.arange(len(Ts), dtype=np.int64) * 100_000_000
    if len(t_ns) != len(Ts):
        raise DatasetError(f"{p}: {len(Ts)} poses but {len(t_ns)} timestamps")
    return Trajectory(np.asarray(t_ns), np.array(Ts))


def pose_file_columns(path: str | Path) -> int:
    """Values on the first data line of a pose file (12: KITTI, 8: TUM).

    A missing file, a folder, a file that is not text or has no data line raise DatasetError.
    """
    p = Path(path)
    lines = read_lines(p, torn_tail_ok=False)
    if not lines:
        raise DatasetError(f"{p}: no poses")
    return len(lines[0][1].replace(",", " ").split())


def read_trajectory(path: str | Path) -> Trajectory:
    """TUM or KITTI, decided by the number of columns of the first data line."""
    p = Path(path)
    if pose_file_columns(p) == 12:
        return read_kitti_poses(p)
    return read_tum(p)
