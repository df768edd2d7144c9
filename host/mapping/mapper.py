"""Dense mapping: keyframes with poses -> stereo depth -> TSDF fusion -> mesh, cloud, preview.

Stages, each a plain function:

* inputs (:func:`open_map_input`): a recorded session (``SESSION/mav0`` ..., poses from
  ``trajectory.tum`` or a ``poses`` file, keyframes chosen by :func:`select_keyframes`) or a
  folder of keyframes stored by ``host live`` (:mod:`stereopath.host.live.store`: one file per keyframe
  with its pose, plus ``index.csv``; the rig calibration comes from a ``rig.yaml`` beside them or
  an explicit rig and must match the keyframes' rig hash);
* :func:`build_map` (driving a :class:`DenseMapper`, which live views can feed keyframe by
  keyframe): depth per keyframe (:mod:`stereopath.host.mapping.depth`), fusion (:mod:`stereopath.host.mapping.fusion`), mesh and cloud
  extraction, preview (:mod:`stereopath.host.mapping.preview`), statistics -- all in memory;
* :func:`write_map`: ``mesh.ply``, ``cloud.ply``, ``model.png``, ``map.json`` written into a
  temporary folder and moved into place only when all four exist, so a failure leaves nothing
  partial behind.

Poses are ``T_world_cam0``.  Depth lives in the rectified left camera, whose pose is
``T_world_cam0 @ [R0^T | 0]`` (see :mod:`stereopath.host.mapping.depth`).
"""

from __future__ import annotations

import dataclasses
import json
import logging
import os
import shutil
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from stereopath.device.core.config import check_range
from stereopath.device.errors import CalibrationError, ConfigError, DatasetError, StereopathError
from stereopath.device.core.geometry import rotation_angle_deg
from stereopath.device.core.rig import Rig
from stereopath.device.formats.tum import Trajectory
from stereopath.host.mapping.depth import DEPTH_PRESETS, DepthConfig, StereoDepth
from stereopath.host.mapping.fusion import FUSION_PRESETS, FusionConfig, TsdfVolume

log = logging.getLogger(__name__)

MAP_FILES = ("mesh.ply", "cloud.ply", "model.png", "map.json")


@dataclass(frozen=True)
class KeyframeSelection:
    """Which frames become keyframes: every ``stride``-th frame with a pose (``stride > 0``), or
    (``stride = 0``) a new keyframe whenever the camera moved ``min_translation_m`` or turned
    ``min_rotation_deg`` since the last one.  ``max_keyframes > 0`` thins the result evenly."""

    stride: int = 0
    min_translation_m: float = 0.04
    min_rotation_deg: float = 5.0
    max_keyframes: int = 0

    def __post_init__(self) -> None:
        check_range("stride", self.stride, 0, 1_000_000)
        check_range("min_translation_m", self.min_translation_m, 0.0, 100.0)
        check_range("min_rotation_deg", self.min_rotation_deg, 0.0, 180.0)
        check_range("max_keyframes", self.max_keyframes, 0, 1_000_000)


@dataclass(frozen=True)
class MapConfig:
    """Depth, fusion and keyframe settings of one mapping run, plus the preview size."""

    depth: DepthConfig = field(default_factory=DepthConfig)
    fusion: FusionConfig = field(default_factory=FusionConfig)
    keyframes: KeyframeSelection = field(default_factory=KeyframeSelection)
    preview_size: tuple[int, int] = (960, 720)
    preset: str = "custom"

    def __post_init__(self) -> None:
        check_range("preview_size[0]", self.preview_size[0], 16, 8192)
        check_range("preview_size[1]", self.preview_size[1], 16, 8192)


MAP_PRESETS: dict[str, MapConfig] = {
    "object": MapConfig(depth=DEPTH_PRESETS["object"], fusion=FUSION_PRESETS["object"],
                        keyframes=KeyframeSelection(min_translation_m=0.04, min_rotation_deg=5.0), preset="object"),
    "room": MapConfig(depth=DEPTH_PRESETS["room"], fusion=FUSION_PRESETS["room"],
                      keyframes=KeyframeSelection(min_translation_m=0.15, min_rotation_deg=10.0), preset="room"),
}


def map_preset(name: str, voxel_mm: float | None = None, **keyframe_changes: Any) -> MapConfig:
    """The named preset, optionally with another voxel size (truncation scales with it)."""
    if name not in MAP_PRESETS:
        raise ConfigError(f"unknown map preset {name!r}; known: {', '.join(sorted(MAP_PRESETS))}")
    cfg = MAP_PRESETS[name]
    if voxel_mm is not None:
        check_range("voxel_mm", voxel_mm, 0.1, 1000.0)
        cfg = dataclasses.replace(cfg, fusion=dataclasses.replace(cfg.fusion, voxel_m=float(voxel_mm) / 1000.0))
    if keyframe_changes:
        cfg = dataclasses.replace(cfg, keyframes=dataclasses.replace(cfg.keyframes, **keyframe_changes))
    return cfg


# ---------------------------------------------------------------------------------------------
# inputs


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
    finite = np.all(np.isfinite(poses.reshape(len(poses), -1)), axis=1)
    idx = np.nonzero(ok)[0][finite]
    return idx.astype(np.int64), poses[finite]


def _frame_tolerance_ns(t_ns: np.ndarray) -> int:
    if len(t_ns) < 2:
        return 1_000_000
    return max(1_000_000, int(np.median(np.diff(np.asarray(t_ns, np.int64)))) // 2)


def keyframes_from_sequence(seq: Any, trajectory: Trajectory, selection: KeyframeSelection,
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


def _keyframe_folder(path: Path) -> Path | None:
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
    from stereopath.device.wire.protocol import decode_image, rig_reference
    from stereopath.device.core.rig import load_rig_yaml
    from stereopath.host.live.store import load_keyframe

    p = Path(path)
    kdir = _keyframe_folder(p)
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
        raise CalibrationError(f"{rig_src}: rig hash {got[1]} ({got[0]}) does not match the keyframes' rig "
                               f"{rig_name!r} (hash {rig_hash})")
    poses = np.array([k.T_world_cam for k in kfs])
    sel = select_keyframes(poses, selection or KeyframeSelection(stride=1))

    def loader(kf: Any) -> Callable[[], tuple[np.ndarray, np.ndarray]]:
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
    if _keyframe_folder(p) is not None:
        if poses is not None:
            raise ConfigError("--poses applies to sessions; stored keyframes carry their own poses")
        # stored keyframes are already spaced by the device: every one by default, max_keyframes still applies
        return keyframes_input(p, selection if selection.stride else dataclasses.replace(selection, stride=1), rig,
                               strict=strict)
    raise DatasetError(f"{p}: neither a session (no mav0/) nor a keyframes folder (no index.csv, kf_*.msgpack)")


# ---------------------------------------------------------------------------------------------
# building


@dataclass(eq=False)
class MapResult:
    """The model in memory: legacy Open3D mesh and cloud, preview image (RGB) and statistics."""

    mesh: Any
    cloud: Any
    preview: np.ndarray
    stats: dict[str, Any]


def _progress(total: int, desc: str, enabled: bool | None):
    if enabled is None:
        enabled = sys.stderr.isatty()
    if not enabled:
        return None
    from tqdm import tqdm

    return tqdm(total=total, desc=desc, unit="kf", leave=False, file=sys.stderr)


class DenseMapper:
    """Incremental dense mapping for one rig: ``add`` keyframes, ``mesh()`` any time, ``finish()``.

    ``build_map`` drives it for a whole input; a live view can call ``add`` as keyframes arrive
    and ``mesh()`` every few keyframes (extraction costs about 0.1-0.5 s for a table-top scan).
    """

    def __init__(self, rig: Rig, config: MapConfig, source: str = "") -> None:
        self.rig = rig
        self.config = config
        self.source = source or rig.name
        self.depth = StereoDepth(rig, config.depth)
        self.volume = TsdfVolume(config.fusion)
        self.poses: list[np.ndarray] = []
        self.indices: list[int] = []
        self.valid_fractions: list[float] = []
        self.timings = {"load": 0.0, "depth": 0.0, "fusion": 0.0}
        log.info("dense mapping (%s): depth %s; fusion %s", config.preset, config.depth, config.fusion)

    @property
    def keyframes(self) -> int:
        return len(self.poses)

    def add(self, left: np.ndarray, right: np.ndarray, T_world_cam0: np.ndarray, index: int | None = None) -> Any:
        """Depth of one raw stereo pair, fused at the camera-0 pose; returns the :class:`stereopath.host.mapping.depth.DepthMap`."""
        t0 = time.perf_counter()
        dm = self.depth.compute(left, right)
        t1 = time.perf_counter()
        self.volume.integrate_depth_map(dm, T_world_cam0)
        self.timings["depth"] += t1 - t0
        self.timings["fusion"] += time.perf_counter() - t1
        self.poses.append(np.asarray(T_world_cam0, float))
        self.indices.append(len(self.indices) if index is None else int(index))
        self.valid_fractions.append(dm.valid_fraction)
        return dm

    def mesh(self) -> Any:
        """The current legacy Open3D mesh (may be empty)."""
        return self.volume.extract_mesh()

    def finish(self, extra_stats: dict[str, Any] | None = None) -> MapResult:
        """Mesh, cloud, preview and statistics; StereopathError when there is nothing to show."""
        from stereopath.host.mapping.preview import render_mesh_preview

        config, n_kf = self.config, len(self.poses)
        if n_kf == 0:
            raise DatasetError(f"{self.source}: no keyframes to map")
        used = int(sum(f > 0 for f in self.valid_fractions))
        if self.volume.pixels_integrated == 0:
            raise StereopathError(f"{self.source}: no valid depth in any of the {n_kf} keyframes "
                                  f"(range {config.depth.min_depth_m}-{config.depth.max_depth_m} m); nothing to fuse")
        t0 = time.perf_counter()
        mesh = self.volume.extract_mesh()
        cloud = self.volume.extract_cloud()
        t_mesh = time.perf_counter() - t0
        if len(mesh.vertices) == 0 or len(mesh.triangles) == 0:
            raise StereopathError(f"{self.source}: the fused volume holds no surface (too few observations per "
                                  f"voxel; {used} of {n_kf} keyframes had depth)")
        t0 = time.perf_counter()
        poses = np.array(self.poses)
        view_dir = poses[:, :3, 2].mean(axis=0)
        up = -poses[:, :3, 1].mean(axis=0)
        preview = render_mesh_preview(mesh, size=config.preview_size,
                                      view_dir=view_dir if np.linalg.norm(view_dir) > 1e-6 else None,
                                      up=up if np.linalg.norm(up) > 1e-6 else None, elevation_deg=20.0)
        t_preview = time.perf_counter() - t0
        v = np.asarray(mesh.vertices)
        t = self.timings
        stats: dict[str, Any] = {
            "format": "stereopath-map",
            "version": 1,
            "source": self.source,
            "rig": self.rig.name,
            "preset": config.preset,
            "keyframes": n_kf,
            "keyframes_with_depth": used,
            "keyframe_indices": list(self.indices),
            "depth_valid_fraction_mean": float(np.mean(self.valid_fractions)),
            "voxel_m": config.fusion.voxel_m,
            "voxel_mm": config.fusion.voxel_m * 1000.0,
            "trunc_m": config.fusion.trunc_m,
            "blocks": self.volume.block_count,
            "mesh_vertices": int(len(mesh.vertices)),
            "mesh_triangles": int(len(mesh.triangles)),
            "cloud_points": int(len(cloud.points)),
            "bounds_min_m": v.min(axis=0).tolist(),
            "bounds_max_m": v.max(axis=0).tolist(),
            "config": {
                "depth": dataclasses.asdict(config.depth),
                "fusion": dataclasses.asdict(config.fusion),
                "keyframes": dataclasses.asdict(config.keyframes),
            },
            "timings_s": {
                "load": round(t["load"], 4),
                "depth": round(t["depth"], 4),
                "fusion": round(t["fusion"], 4),
                "extract": round(t_mesh, 4),
                "preview": round(t_preview, 4),
            },
            "depth_ms_per_keyframe": round(1000.0 * t["depth"] / n_kf, 2),
            "fusion_keyframes_per_s": round(n_kf / t["fusion"], 2) if t["fusion"] > 0 else None,
        }
        stats.update(extra_stats or {})
        return MapResult(mesh=mesh, cloud=cloud, preview=preview, stats=stats)


def build_map(inp: MapInput, config: MapConfig, progress: bool | None = None,
              on_keyframe: Callable[[int, Any], None] | None = None, strict: bool = False) -> MapResult:
    """Depth and fusion of every keyframe of ``inp``, then mesh, cloud and preview (no file I/O).

    ``progress``: tqdm bar on stderr (None = only when stderr is a terminal).  ``on_keyframe(k,
    depth_map)`` is called after each keyframe is fused (for live views).  A keyframe whose
    images cannot be read is skipped and counted (``stats["keyframes_skipped"]``) unless ``strict``.
    """
    if not inp.keyframes:
        raise DatasetError(f"{inp.source}: no keyframes to map")
    t_start = time.perf_counter()
    mapper = DenseMapper(inp.rig, config, source=inp.source)
    bar = _progress(len(inp.keyframes), "depth + fusion", progress)
    try:
        for k, kf in enumerate(inp.keyframes):
            t0 = time.perf_counter()
            try:
                left, right = kf.load()
            except DatasetError as exc:
                if strict:
                    raise
                log.warning("skipping keyframe %d: %s", kf.index, exc)
                inp.skipped.append(str(kf.index))
                continue
            mapper.timings["load"] += time.perf_counter() - t0
            dm = mapper.add(left, right, kf.T_world_cam0, index=kf.index)
            if on_keyframe is not None:
                on_keyframe(k, dm)
            if bar is not None:
                bar.update(1)
    finally:
        if bar is not None:
            bar.close()
    result = mapper.finish({"input_kind": inp.kind, "poses": inp.poses_source, "frames_total": inp.frames_total,
                            "keyframes_skipped": len(inp.skipped), "skipped": inp.skipped[:1000]})
    result.stats["timings_s"]["total"] = round(time.perf_counter() - t_start, 4)
    return result


# ---------------------------------------------------------------------------------------------
# writing


def write_map(result: MapResult, out_dir: str | Path) -> dict[str, Path]:
    """Write ``mesh.ply``, ``cloud.ply``, ``model.png``, ``map.json`` into ``out_dir``.

    Everything is written into a temporary folder beside ``out_dir`` first; only when all four
    files exist are they moved in (each move is an atomic rename).  ``out_dir`` may already exist
    (other files in it are left alone).
    """
    from stereopath.host.mapping.fusion import write_cloud, write_mesh
    from stereopath.host.mapping.preview import write_png

    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise StereopathError(f"output {out} exists and is not a folder")
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.", suffix=".tmp", dir=out.parent))
    from stereopath.device.formats.fileio import process_umask

    tmp.chmod(0o777 & ~process_umask())  # mkdtemp makes 0700; the model folder gets what mkdir would give
    try:
        write_mesh(result.mesh, tmp / "mesh.ply")
        write_cloud(result.cloud, tmp / "cloud.ply")
        write_png(result.preview, tmp / "model.png")
        (tmp / "map.json").write_text(json.dumps(result.stats, indent=2, sort_keys=False) + "\n")
        if not out.exists():
            os.replace(tmp, out)
        else:
            for name in MAP_FILES:
                os.replace(tmp / name, out / name)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)
    return {name: out / name for name in MAP_FILES}


def map_sequence(seq: Any, trajectory: Trajectory, out_dir: str | Path | None, config: MapConfig,
                 progress: bool | None = None, source: str = "") -> MapResult:
    """Map any sequence (``rig``, ``t_ns``, ``frame(i)``) with the poses of ``trajectory``; write the
    model into ``out_dir`` when given.  (For reprocessing and the demo.)"""
    inp = keyframes_from_sequence(seq, trajectory, config.keyframes, source=source or str(getattr(seq, "spec", "")))
    result = build_map(inp, config, progress=progress)
    if out_dir is not None:
        write_map(result, out_dir)
    return result


def map_path(path: str | Path, out_dir: str | Path, config: MapConfig, poses: str | Path | None = None,
             rig: str | Path | None = None, progress: bool | None = None, strict: bool = False) -> MapResult:
    """``stereopath host map``: open a session or keyframes folder, build the model, write it.

    Unreadable keyframes or frames are skipped and counted unless ``strict``."""
    inp = open_map_input(path, config.keyframes, poses=poses, rig=rig, strict=strict)
    result = build_map(inp, config, progress=progress, strict=strict)
    write_map(result, out_dir)
    return result
