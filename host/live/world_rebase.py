"""One world per session on the host: the device's world rebases applied to what the receiver holds.

A device whose estimator started in motion redefines its world once, when gravity becomes known
(:class:`~stereopath.device.wire.messages.WorldRebase`): the poses and keyframes it sent before
``from_t_ns`` are in the earlier world, ``T_new_old`` maps them.  :class:`SessionRebases` keeps each
session's rebases (in the order received; the device repeats its message with every status, so a
repeated one is recognised and applied once), maps a live pose timed before them as it arrives, and
rewrites the poses the host stored.  Each applied rebase is recorded in the session folder's
``world_rebase.json`` (``{"rebases": [{"from_t_ns", "T_new_old"}...]}``, oldest first): the
keyframes on disk keep the poses they were sent with, and that file maps those timed before each.
"""

from __future__ import annotations

import dataclasses
import json
import os
from pathlib import Path

import numpy as np

from stereopath.device.errors import DatasetError
from stereopath.device.formats.fileio import write_json_atomic
from stereopath.device.wire.messages import Keyframe, Pose, WorldRebase, pose_from_matrix

REBASE_JSON = "world_rebase.json"
MAX_REBASES = 16  # per session: a device rebases once; more are refused (a flood cannot grow the host's state)


@dataclasses.dataclass(frozen=True, eq=False)
class Rebase:
    """One applied rebase: the poses timed before ``from_t_ns`` map by ``T_new_old``."""

    from_t_ns: int
    T_new_old: np.ndarray

    def map(self, pose: Pose) -> Pose:
        """``pose`` (given in the world before this rebase) in the one after it, when timed before it."""
        if pose.t_ns >= self.from_t_ns:
            return pose
        return pose_from_matrix(pose.session_id, pose.seq, pose.t_ns, self.T_new_old @ pose.T_world_cam,
                                pose.tracking, pose.inliers, pose.keyframe)

    def same(self, other: Rebase) -> bool:
        return self.from_t_ns == other.from_t_ns and bool(np.allclose(self.T_new_old, other.T_new_old, atol=1e-6))


class SessionRebases:
    """Each session's rebases (see the module doc); thread-compatible: the receiver calls it under its lock."""

    def __init__(self) -> None:
        self._by_session: dict[str, list[Rebase]] = {}

    def of(self, session_id: str) -> list[Rebase]:
        return list(self._by_session.get(session_id, ()))

    def load(self, session_id: str, rebases: list[Rebase]) -> None:
        """Rebases applied before (read back from the session folder)."""
        self._by_session[session_id] = list(rebases)[:MAX_REBASES]

    def add(self, msg: WorldRebase) -> Rebase | None:
        """The rebase to apply now, or None when it was applied already (the device repeats it) or the
        session has had :data:`MAX_REBASES`."""
        new = Rebase(int(msg.from_t_ns), msg.T_new_old)
        held = self._by_session.setdefault(msg.session_id, [])
        if any(r.same(new) for r in held) or len(held) >= MAX_REBASES:
            return None
        held.append(new)
        return new

    def map_matrix(self, session_id: str, t_ns: int, T_world_cam: np.ndarray) -> np.ndarray:
        """A pose of the session timed ``t_ns``, as sent, in the session's current world."""
        for r in self._by_session.get(session_id, ()):
            if t_ns < r.from_t_ns:
                T_world_cam = r.T_new_old @ T_world_cam
        return T_world_cam

    def map_keyframe(self, kf: Keyframe) -> Keyframe:
        """A keyframe's pose in its session's current world (the images and the stored bytes are as sent)."""
        T0 = kf.T_world_cam
        T = self.map_matrix(kf.session_id, kf.t_ns, T0)
        if T is T0:  # none applies
            return kf
        moved = pose_from_matrix(kf.session_id, 0, kf.t_ns, T)
        return dataclasses.replace(kf, position_m=moved.position_m, quat_xyzw=moved.quat_xyzw)

    def map_pose(self, pose: Pose) -> Pose:
        """A live pose in its session's current world (one timed before a rebase was sent in the earlier one)."""
        for r in self._by_session.get(pose.session_id, ()):
            pose = r.map(pose)
        return pose


def rewrite_tum(path: Path, rebase: Rebase) -> int:
    """Map the poses of the TUM file ``path`` timed before the rebase (atomically); returns how many."""
    from stereopath.device.core.geometry import make_pose, matrix_to_quat_xyzw, quat_xyzw_to_matrix

    if not path.is_file():
        return 0
    out, n = [], 0
    for line in path.read_text().splitlines(keepends=True):
        parts = line.split()
        if len(parts) != 8 or line.startswith("#"):
            out.append(line)
            continue
        stamp = parts[0]
        sec, _, frac = stamp.partition(".")
        t_ns = int(sec) * 1_000_000_000 + int((frac + "000000000")[:9])
        if t_ns >= rebase.from_t_ns:
            out.append(line)
            continue
        v = [float(x) for x in parts[1:]]
        T = rebase.T_new_old @ make_pose(quat_xyzw_to_matrix(np.array(v[3:])), np.array(v[:3]))
        p, q = T[:3, 3], matrix_to_quat_xyzw(T[:3, :3])
        out.append(f"{stamp} {p[0]:.6f} {p[1]:.6f} {p[2]:.6f} {q[0]:.7f} {q[1]:.7f} {q[2]:.7f} {q[3]:.7f}\n")
        n += 1
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text("".join(out))
    os.replace(tmp, path)
    return n


def record(session_dir: Path, rebases: list[Rebase]) -> None:
    """``world_rebase.json`` of a session folder: its rebases, oldest first."""
    session_dir.mkdir(parents=True, exist_ok=True)
    write_json_atomic(session_dir / REBASE_JSON, {"rebases": [
        {"from_t_ns": r.from_t_ns, "T_new_old": [[float(v) for v in row] for row in r.T_new_old]} for r in rebases]},
        indent=1, fsync=False)


def read_rebases(session_dir: Path) -> list[Rebase]:
    """The rebases recorded in a session folder (none when it has no ``world_rebase.json``)."""
    p = Path(session_dir) / REBASE_JSON
    if not p.is_file():
        return []
    try:
        rows = json.loads(p.read_text())["rebases"]
        out = [Rebase(int(r["from_t_ns"]), np.asarray(r["T_new_old"], float)) for r in rows]
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise DatasetError(f"{p}: unreadable world rebase ({exc})") from None
    for r in out:
        if r.T_new_old.shape != (4, 4) or not np.isfinite(r.T_new_old).all():
            raise DatasetError(f"{p}: T_new_old is not a finite 4x4 matrix")
    return out
