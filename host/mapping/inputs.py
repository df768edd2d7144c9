"""Dense mapping inputs: a recorded session or stored keyframes, with poses, and the keyframe choice.

:func:`open_map_input` reads a recorded session (``SESSION/mav0`` ..., poses from ``trajectory.tum``
or a ``poses`` file, keyframes chosen by :func:`select_keyframes`) or a folder of keyframes stored
by ``host live`` (:mod:`stereopath.host.live.store`; the rig comes from the ``rig.yaml`` ``host live``
stored beside them from the device, or an explicit rig, and must match the keyframes' rig hash).
"""

from __future__ import annotations

import logging
from collections.abc import Callable
import dataclasses
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from stereopath.device.core.config import check_ranges, ranged
from stereopath.device.core.geometry import rotation_angle_deg
from stereopath.device.core.rig import Rig
from stereopath.device.errors import CalibrationError, ConfigError, DatasetError
from stereopath.device.formats.sequence import SequenceBase
from stereopath.device.formats.tum import Trajectory

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class KeyframeSelection:
    """Which frames become keyframes: every ``stride``-th frame with a pose (``stride > 0``), or
    (``stride = 0``) a new keyframe whenever the camera moved ``min_translation_m`` or turned
    ``min_rotation_deg`` since the last one, filled up to ``min_keyframes`` (the last frame, then the
    middle of the longest gap, again) when the camera moved less than that (a short or nearly still
    recording: the fusion keeps only surfaces several keyframes saw).  ``max_keyframes > 0`` thins the
    result evenly."""

    stride: int = ranged(0, 0, 1_000_000)
    min_translation_m: float = ranged(0.04, 0.0, 100.0)
    min_rotation_deg: float = ranged(5.0, 0.0, 180.0)
    max_keyframes: int = ranged(0, 0, 1_000_000)
    min_keyframes: int = ranged(8, 0, 1_000_000)

    def __post_init__(self) -> None:
        check_ranges(self)


@dataclass(frozen=True, eq=False)
class MapKeyframe:
    """One keyframe to fuse: its time, its camera-0 pose and a loader of its (left, right) images."""

    index: int
    t_ns: int
    T_world_cam0: np.ndarray
    load: Callable[[], tuple[np.ndarray, np.ndarray]]


@dataclass(eq=False)
class MapInput:
    """What :func:`build_map` consumes: a rig and the keyframes with poses."""

    rig: Rig
    keyframes: list[MapKeyframe]
    kind: str  # "session", "keyframes" or "sequence"
    source: str
    frames_total: int
    poses_source: str
    skipped: list[str] = field(default_factory=list)  # unreadable inputs left out (see build_map's strict)


def select_keyframes(T_world_cam: np.ndarray, selection: KeyframeSelection) -> np.ndarray:
    """Indices into ``T_world_cam`` (N, 4, 4) of the keyframes (pure; always includes the first)."""
    T = np.asarray(T_world_cam, float).reshape(-1, 4, 4)
    n = len(T)
    if n == 0:
        return np.zeros(0, dtype=np.int64)
    if selection.stride > 0:
        idx = np.arange(0, n, selection.stride)
    else:
        keep = [0]
        last = T[0]
        for i in range(1, n):
            dt = float(np.linalg.norm(T[i, :3, 3] - last[:3, 3]))
            dr = rotation_angle_deg(last[:3, :3].T @ T[i, :3, :3])
            if dt >= selection.min_translation_m or dr >= selection.min_rotation_deg:
                keep.append(i)
                last = T[i]
        if len(keep) < selection.min_keyframes:  # fill the longest gaps (and take the last frame) up to the minimum
            keep = sorted(set(keep) | {n - 1})
            while len(keep) < min(n, selection.min_keyframes):
                g = int(np.argmax(np.diff(keep)))
                keep.insert(g + 1, keep[g] + (keep[g + 1] - keep[g]) // 2)
        idx = np.array(keep)
    if selection.max_keyframes and len(idx) > selection.max_keyframes:
        pick = np.unique(np.round(np.linspace(0, len(idx) - 1, selection.max_keyframes)).astype(int))
        idx = idx[pick]
    return idx.astype(np.int64)


def associate_poses(frame_t_ns: np.ndarray, traj: Trajectory, max_dt_ns: int) -> tuple[np.ndarray, np.ndarray]:
    """``(frame indices, poses)`` for the frames with a trajectory pose within ``max_dt_ns`` (nearest)."""
    ft = np.asarray(frame_t_ns, np.int64)
    tt = np.asarray(traj.t_ns, np.int64)
    if len(ft) == 0 or len(tt) == 0:
        return np.zeros(0, np.int64), np.zeros((0, 4, 4))
    order = np.argsort(tt, kind="stable")
    tt_s = tt[order]
    j = np.clip(np.searchsorted(tt_s, ft), 1, len(tt_s) - 1) if len(tt_s) > 1 else np.zeros(len(ft), int)
    if len(tt_s) > 1:
        left_closer = np.abs(ft - tt_s[j - 1]) <= np.abs(tt_s[j] - ft)
        j = np.where(left_closer, j - 1, j)
    dt = np.abs(tt_s[j] - ft)
    ok = dt <= max_dt_ns
    poses = np.asarray(traj.T_world_cam)[order][j[ok]]
    finite = np.all(np.isfinite(poses), axis=(1, 2))  # (0, 4, 4) when no pose is near a frame
    idx = np.nonzero(ok)[0][finite]
    return idx.astype(np.int64), poses[finite]


def _frame_tolerance_ns(t_ns: np.ndarray) -> int:
    if len(t_ns) < 2:
        return 1_000_000
    return max(1_000_000, int(np.median(np.diff(np.asarray(t_ns, np.int64)))) // 2)


def keyframes_from_sequence(seq: SequenceBase, trajectory: Trajectory, selection: KeyframeSelection,
                            kind: str = "sequence", source: str = "", poses_source: str = "trajectory") -> MapInput:
    """Keyframes of any sequence (``rig``, ``t_ns``, ``frame(i)``) posed by ``trajectory``."""
    t_ns = np.asarray(seq.t_ns, np.int64)
    if len(t_ns) == 0:
        raise DatasetError(f"{source or seq}: no frames")
    idx, poses = associate_poses(t_ns, trajectory, _frame_tolerance_ns(t_ns))
    if len(idx) == 0:
        raise DatasetError(f"{source or seq}: none of the {len(t_ns)} frames has a pose in {poses_source} "
                           f"(timestamps do not match)")
    sel = select_keyframes(poses, selection)

    def loader(i: int) -> Callable[[], tuple[np.ndarray, np.ndarray]]:
        def load() -> tuple[np.ndarray, np.ndarray]:
            fr = seq.frame(i)
            return fr.left, fr.right
        return load

    kfs = [MapKeyframe(int(idx[k]), int(t_ns[idx[k]]), poses[k], loader(int(idx[k]))) for k in sel]
    log.info("%s: %d frames, %d with poses, %d keyframes", source or "sequence", len(t_ns), len(idx), len(kfs))
    return MapInput(rig=seq.rig, keyframes=kfs, kind=kind, source=source or str(getattr(seq, "spec", "")),
                    frames_total=len(t_ns), poses_source=poses_source)


def session_input(session_dir: str | Path, selection: KeyframeSelection, poses: str | Path | None = None) -> MapInput:
    """A recorded session: poses from ``poses`` (TUM or KITTI file) or the session's ``trajectory.tum``."""
    from stereopath.device.formats import open_source
    from stereopath.device.formats.tum import read_trajectory

    d = Path(session_dir)
    seq = open_source(f"session:{d}")
    if poses is not None:
        traj = read_trajectory(poses)
        poses_source = str(poses)
    else:
        traj = seq.trajectory
        poses_source = str(d / "trajectory.tum")
        if traj is None:
            raise DatasetError(f"{d}: no estimated path (trajectory.tum missing or empty); "
                               f"run odometry first or pass --poses FILE")
    return keyframes_from_sequence(seq, traj, selection, kind="session", source=str(d), poses_source=poses_source)


def keyframe_folder(path: Path) -> Path | None:
    """The ``keyframes`` folder for ``path`` (itself, or its ``keyframes`` child), or None."""
    for cand in (path, path / "keyframes"):
        if cand.is_dir() and ((cand / "index.csv").is_file() or any(cand.glob("kf_*.msgpack"))):
            return cand
    return None


def keyframes_input(path: str | Path, selection: KeyframeSelection | None = None,
                    rig: Rig | str | Path | None = None, strict: bool = False) -> MapInput:
    """Keyframes stored by ``host live`` (see :mod:`stereopath.host.live.store`).

    The calibration is ``rig`` (a Rig or a rig YAML path) or a ``rig.yaml`` in the keyframes
    folder or its parent; its hash must match the keyframes' rig reference.
    """
    from stereopath.device.wire.protocol import Keyframe, decode_image, rig_reference
    from stereopath.device.formats.rig_files import load_rig_yaml
    from stereopath.host.live.store import load_keyframe

    p = Path(path)
    kdir = keyframe_folder(p)
    if kdir is None:
        raise DatasetError(f"{p}: no stored keyframes (expected index.csv or kf_*.msgpack files)")
    files = sorted(kdir.glob("kf_*.msgpack"))
    if not files:
        raise DatasetError(f"{kdir}: the keyframe folder is empty")
    kfs, skipped = [], []
    for f in files:
        try:
            kfs.append(load_keyframe(f))
        except DatasetError as exc:
            if strict:
                raise
            log.warning("skipping unreadable keyframe: %s", exc)
            skipped.append(f.name)
    if not kfs:
        raise DatasetError(f"{kdir}: none of the {len(files)} keyframe files is readable")
    kfs.sort(key=lambda k: k.seq)
    refs = {(k.rig_name, k.rig_hash) for k in kfs}
    if len(refs) != 1:
        raise CalibrationError(f"{kdir}: keyframes refer to {len(refs)} different rigs: {sorted(refs)}")
    (rig_name, rig_hash), = refs
    if isinstance(rig, Rig):
        the_rig, rig_src = rig, "given rig"
    else:
        cands = [Path(rig)] if rig is not None else [kdir / "rig.yaml", kdir.parent / "rig.yaml"]
        found = [c for c in cands if c.is_file()]
        if not found:
            raise CalibrationError(f"{kdir}: keyframes without calibration: no rig.yaml for rig {rig_name!r} "
                                   f"(hash {rig_hash}) in {', '.join(str(c) for c in cands)}; pass --rig RIG.yaml")
        the_rig, rig_src = load_rig_yaml(found[0]), str(found[0])
    got = rig_reference(the_rig)
    if got[1] != rig_hash:
        stored = [c for c in (kdir / "rig.yaml", kdir.parent / "rig.yaml") if c.is_file() and c != Path(rig_src)]
        hint = (f"; the device's rig of these keyframes is stored in {stored[0]}: drop --rig to map with it"
                if rig is not None and stored else "")
        raise CalibrationError(f"{rig_src}: rig hash {got[1]} ({got[0]}) does not match the keyframes' rig "
                               f"{rig_name!r} (hash {rig_hash}){hint}")
    poses = np.array([k.T_world_cam for k in kfs])
    sel = select_keyframes(poses, selection or KeyframeSelection(stride=1))

    def loader(kf: Keyframe) -> Callable[[], tuple[np.ndarray, np.ndarray]]:
        def load() -> tuple[np.ndarray, np.ndarray]:
            return decode_image(kf.left), decode_image(kf.right)
        return load

    out = [MapKeyframe(int(kfs[i].seq), int(kfs[i].t_ns), poses[i], loader(kfs[i])) for i in sel]
    return MapInput(rig=the_rig, keyframes=out, kind="keyframes", source=str(kdir), frames_total=len(kfs),
                    poses_source="keyframe poses", skipped=skipped)


def open_map_input(path: str | Path, selection: KeyframeSelection, poses: str | Path | None = None,
                   rig: str | Path | None = None, strict: bool = False) -> MapInput:
    """A session folder (``mav0`` inside) or a stored-keyframes folder, whichever ``path`` is."""
    p = Path(path)
    if not p.exists():
        raise DatasetError(f"input not found: {p}")
    if not p.is_dir():
        raise DatasetError(f"{p} is not a folder (expected a session or a keyframes folder)")
    if (p / "mav0").is_dir():
        return session_input(p, selection, poses)
    if keyframe_folder(p) is not None:
        if poses is not None:
            raise ConfigError("--poses applies to sessions; stored keyframes carry their own poses")
        # stored keyframes are already spaced by the device: every one by default, max_keyframes still applies
        return keyframes_input(p, selection if selection.stride else dataclasses.replace(selection, stride=1), rig,
                               strict=strict)
    raise DatasetError(f"{p}: neither a session (no mav0/) nor a keyframes folder (no index.csv, kf_*.msgpack)")
