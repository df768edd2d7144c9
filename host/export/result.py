"""What an export reads: a ``host reprocess`` output, a recorded session or a ``host live`` store.

:func:`open_result` tells them apart and returns an :class:`ExportSource`: the rig, every frame's
time and pose, the keyframes (with lazily loaded images), the IMU and, for a reprocessed output,
the bundle-adjusted points and their observations.

* reprocessed (``RESULT/stages/manifest.json``): the refined path (``ba.npz: T_frames``), the
  adjusted keyframes (``T_kf``) and points (``point_ids``, ``point_xyz``), the tracks' observation
  rows (``tracks.npz``) of those points that the adjustment kept (within its ``ba_outlier_px``),
  and the session it was made from (``report.json: source``, or ``session=``), whose images and
  IMU are read.  The right camera's principal point carries the adjusted disparity offset, as in
  the adjustment.
* a recorded session (``RESULT/mav0``): its on-board path (``trajectory.tum``) at every frame; the
  keyframes are chosen by camera motion as ``host map`` chooses them (4 cm or 5 degrees); no points.
* a ``host live`` store (a folder of ``kf_*.msgpack`` with ``index.csv``, or the ``host live``
  output holding one session): the keyframes as received, their poses and the rig the device sent.
"""

from __future__ import annotations

import dataclasses
import json
import logging
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from stereopath.device.core.frames import ImuSamples
from stereopath.device.core.rig import Rig
from stereopath.device.errors import DatasetError
from stereopath.device.formats.sequence import SequenceBase

log = logging.getLogger(__name__)


@dataclass(frozen=True, eq=False)
class ExportKeyframe:
    """One keyframe: its index among the keyframes, frame index, time, camera-0 pose and image loader."""

    k: int
    frame: int
    t_ns: int
    T_world_cam0: np.ndarray
    load: Callable[[], tuple[np.ndarray, np.ndarray]]  # (left, right) as recorded (grey or BGR)


@dataclass(eq=False)
class ExportSource:
    kind: str  # "reprocessed", "session" or "live"
    path: Path
    rig: Rig  # with the adjusted disparity offset on camera 1's principal point (reprocessed)
    t_ns: np.ndarray  # every frame with a pose
    T_world_cam0: np.ndarray  # (N, 4, 4)
    keyframes: list[ExportKeyframe]
    imu: ImuSamples | None = None
    point_ids: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    point_xyz: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    observations: np.ndarray = field(default_factory=lambda: np.zeros((0, 6)))  # (keyframe, point id, cam, u, v, w)
    ba_stats: dict[str, Any] = field(default_factory=dict)
    world_frame: str = "first_camera"
    frame_images: Callable[[int], tuple[bytes, bytes, str]] | None = None  # pose index -> stored image files' bytes
    frame_loader: Callable[[int], tuple[np.ndarray, np.ndarray]] | None = None  # pose index -> (left, right)

    @property
    def has_points(self) -> bool:
        return len(self.point_ids) > 0


def open_result(path: str | Path, session: str | Path | None = None) -> ExportSource:
    """The export input at ``path`` (see the module doc); DatasetError when it is none of the three."""
    p = Path(path)
    if not p.exists():
        raise DatasetError(f"RESULT {p}: not found")
    if not p.is_dir():
        raise DatasetError(f"RESULT {p}: not a folder (give a `host reprocess` output, a session or a `host live` store)")
    if (p / "stages" / "manifest.json").is_file():
        return _reprocessed(p, session)
    if (p / "mav0").is_dir():
        return _session(p)
    live = _live_folder(p)
    if live is not None:
        return _live(live)
    raise DatasetError(f"RESULT {p}: neither a `host reprocess` output (stages/manifest.json), a recorded session "
                       f"(mav0/) nor a `host live` store (kf_*.msgpack with index.csv)")


def _npz(path: Path) -> dict[str, np.ndarray]:
    from stereopath.host.reprocess.store import load_npz

    if not path.is_file():
        raise DatasetError(f"{path}: missing (the reprocessing did not finish this stage; run it again)")
    arrs = load_npz(path)
    if arrs is None:
        raise DatasetError(f"{path}: unreadable (run `host reprocess` again to recompute it)")
    return arrs


def _file_images(seq: SequenceBase) -> Callable[[int], tuple[bytes, bytes, str]] | None:
    """Frame -> the recorded PNG files' bytes, when the images are read as stored (no pinhole view)."""
    views = getattr(seq, "views", None)
    if not hasattr(seq, "image_paths") or (views is not None and any(v is not None for v in views)):
        return None

    def read(i: int) -> tuple[bytes, bytes, str]:
        a, b = seq.image_paths(i)
        fmt = Path(a).suffix.lstrip(".").lower() or "png"
        try:
            return Path(a).read_bytes(), Path(b).read_bytes(), fmt
        except OSError as exc:
            raise DatasetError(f"cannot read frame {i}'s images: {exc}") from None

    return read


def _loader(seq: SequenceBase, i: int) -> Callable[[], tuple[np.ndarray, np.ndarray]]:
    def load() -> tuple[np.ndarray, np.ndarray]:
        fr = seq.frame(i)
        return fr.left, fr.right

    return load


def ba_observations(rig: Rig, T_kf: np.ndarray, point_ids: np.ndarray, point_xyz: np.ndarray, obs: np.ndarray,
                    offset_px: float, outlier_px: float) -> np.ndarray:
    """The observation rows of the adjusted points that the adjustment keeps: in front of their camera,
    within ``outlier_px`` of the adjusted projection, and of points still seen from two keyframes."""
    from stereopath.host.backend.ba_common import reprojection_residuals, select_observations

    points = {int(i): x for i, x in zip(point_ids, point_xyz)}
    obs = select_observations(obs, points, 1)
    if not len(obs):
        return np.zeros((0, 6))
    r, front = reprojection_residuals(rig, T_kf, points, obs, offset_px)
    w = obs[:, 5] if obs.shape[1] > 5 else np.ones(len(obs))
    good = front & (np.linalg.norm(r / w[:, None], axis=1) <= outlier_px)
    return select_observations(obs[good], points, 2)


def _reprocessed(p: Path, session: str | Path | None) -> ExportSource:
    from stereopath.host.reprocess.pipeline import open_session_checked
    from stereopath.host.reprocess.store import meta

    man = json.loads((p / "stages" / "manifest.json").read_text())
    est, trk, ba = (_npz(p / "stages" / f"{n}.npz") for n in ("estimate", "tracks", "ba"))
    if session is None:
        try:
            session = json.loads((p / "report.json").read_text())["source"]
        except (OSError, ValueError, KeyError):
            raise DatasetError(f"RESULT {p}: no report.json naming the session it was made from; give --session") from None
    if not Path(session).is_dir():
        raise DatasetError(f"RESULT {p} was made from {session}, which is not there any more; give --session")
    seq = open_session_checked(session)
    frames_used = np.asarray(est["seq"], np.int64)
    if len(frames_used) and (int(np.max(frames_used)) >= len(seq)
                             or not np.array_equal(np.asarray(seq.t_ns, np.int64)[frames_used], est["t_ns"])):
        raise DatasetError(f"{session}: not the recording RESULT {p} was made from (its frame times differ)")
    stats = meta(ba, "stats")
    if stats.get("skipped"):
        raise DatasetError(f"RESULT {p}: its bundle adjustment was skipped ({stats['skipped']}); nothing to export")
    rig = seq.rig
    offset = float(stats.get("disparity_offset_px") or 0.0)
    if offset:
        K1 = rig.cam1.K.copy()
        K1[0, 2] += offset
        rig = dataclasses.replace(rig, cam1=dataclasses.replace(rig.cam1, K=K1))
    outlier_px = float(man.get("stages", {}).get("ba", {}).get("settings", {}).get("ba_outlier_px", 3.0))
    kf = np.asarray(trk["kf_index"], np.int64)
    T_kf = np.asarray(ba["T_kf"], float)
    obs = ba_observations(seq.rig, T_kf, ba["point_ids"], ba["point_xyz"], trk["observations"], offset, outlier_px)
    frames = np.asarray(est["seq"], np.int64)
    kfs = [ExportKeyframe(k, int(frames[i]), int(est["t_ns"][i]), T_kf[k], _loader(seq, int(frames[i])))
           for k, i in enumerate(kf)]
    keep = np.isin(ba["point_ids"], np.unique(obs[:, 1]).astype(np.int64))
    return ExportSource("reprocessed", p, rig, np.asarray(est["t_ns"], np.int64), np.asarray(ba["T_frames"], float),
                        kfs, imu=seq.imu, point_ids=np.asarray(ba["point_ids"], np.int64)[keep],
                        point_xyz=np.asarray(ba["point_xyz"], float)[keep], observations=obs,
                        ba_stats={**stats, "outlier_px": outlier_px},
                        world_frame=stats.get("world_frame") or "first_camera",
                        frame_images=_indexed(_file_images(seq), frames),
                        frame_loader=lambda i: _loader(seq, int(frames[i]))())


def _indexed(read: Callable[[int], Any] | None, frames: np.ndarray) -> Callable[[int], Any] | None:
    """``read`` of the sequence frame behind each pose index."""
    if read is None:
        return None
    return lambda i: read(int(frames[i]))


def _session(p: Path) -> ExportSource:
    from stereopath.host.mapping.inputs import KeyframeSelection, associate_poses, select_keyframes
    from stereopath.host.reprocess.pipeline import open_session_checked

    seq = open_session_checked(p)
    traj = seq.trajectory
    if traj is None or not len(traj):
        raise DatasetError(f"RESULT {p}: the session holds no on-board path (trajectory.tum); "
                           f"run `stereopath host reprocess` on it and export that output")
    t = np.asarray(seq.t_ns, np.int64)
    tol = int(np.median(np.diff(t)) // 2) if len(t) > 1 else 1_000_000
    idx, poses = associate_poses(t, traj, tol)
    if not len(idx):
        raise DatasetError(f"RESULT {p}: no frame has a pose in trajectory.tum")
    chosen = select_keyframes(poses, KeyframeSelection())
    kfs = [ExportKeyframe(k, int(idx[j]), int(t[idx[j]]), poses[j], _loader(seq, int(idx[j])))
           for k, j in enumerate(chosen)]
    world = (getattr(seq, "manifest", None) or {}).get("world_frame", "first_camera")
    return ExportSource("session", p, seq.rig, t[idx], poses, kfs, imu=seq.imu, world_frame=str(world),
                        frame_images=_indexed(_file_images(seq), idx),
                        frame_loader=lambda i: _loader(seq, int(idx[i]))())


def _live_folder(p: Path) -> Path | None:
    """The keyframes folder of a ``host live`` store at ``p`` (the folder itself, ``p/keyframes`` or the
    one session's ``p/<session>/keyframes``); None when there is none, DatasetError when several."""
    from stereopath.host.mapping.inputs import keyframe_folder

    found = keyframe_folder(p)
    if found is not None:
        return found
    subs = [d / "keyframes" for d in sorted(p.iterdir()) if d.is_dir() and (d / "keyframes").is_dir()]
    if len(subs) > 1:
        raise DatasetError(f"RESULT {p}: a `host live` store with {len(subs)} sessions; give one of "
                           + ", ".join(str(s.parent) for s in subs[:5]))
    return subs[0] if subs else None


def _live(folder: Path) -> ExportSource:
    from stereopath.host.mapping.inputs import KeyframeSelection, keyframes_input

    inp = keyframes_input(folder, KeyframeSelection(stride=1))
    kfs = [ExportKeyframe(k, int(m.index), int(m.t_ns), np.asarray(m.T_world_cam0, float), m.load)
           for k, m in enumerate(inp.keyframes)]
    if not kfs:
        raise DatasetError(f"RESULT {folder}: no stored keyframe")
    return ExportSource("live", folder, inp.rig, np.array([k.t_ns for k in kfs], np.int64),
                        np.array([k.T_world_cam0 for k in kfs]), kfs, frame_loader=lambda i: kfs[i].load())


def iter_keyframes(src: ExportSource) -> Iterator[tuple[ExportKeyframe, np.ndarray, np.ndarray]]:
    """Each keyframe with its images, loaded one at a time (bounded memory)."""
    for kf in src.keyframes:
        left, right = kf.load()
        yield kf, left, right
