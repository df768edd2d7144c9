"""Dense mapping: keyframes with poses -> stereo depth -> TSDF fusion -> mesh, cloud, preview.

Stages, each a plain function:

* inputs (:mod:`stereopath.host.mapping.inputs`): a recorded session or a folder of keyframes
  stored by ``host live``, with poses, keyframes chosen by camera motion;
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
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from stereopath.device.core.config import check_range, check_ranges, ranged
from stereopath.device.errors import ConfigError, DatasetError, StereopathError
from stereopath.device.core.rig import Rig
from stereopath.device.formats.tum import Trajectory
from stereopath.device.formats.sequence import SequenceBase
from stereopath.host.mapping.depth import DEPTH_PRESETS, DepthConfig, DepthMap, StereoDepth
from stereopath.host.mapping.fusion import FUSION_PRESETS, FusionConfig, TsdfVolume
from stereopath.host.mapping.inputs import KeyframeSelection, MapInput, keyframes_from_sequence, open_map_input
from stereopath.host.backend.parallel import parallel_map
from stereopath.host.progress import progress_bar

if TYPE_CHECKING:
    import open3d as o3d

    from stereopath.host.mapping.inputs import MapKeyframe
    from stereopath.host.mapping.map_progress import MapCheckpoint

log = logging.getLogger(__name__)

MAP_FILES = ("mesh.ply", "cloud.ply", "model.png", "map.json")
MAP_TEMP_PREFIX = ".map-writing."  # the hidden folder write_map writes into, inside the model folder
STALE_TEMP_S = 3600.0  # such a folder this old was left by a writer that was killed


@dataclass(frozen=True)
class MapConfig:
    """Depth, fusion and keyframe settings of one mapping run, plus the preview size."""

    depth: DepthConfig = field(default_factory=DepthConfig)
    fusion: FusionConfig = field(default_factory=FusionConfig)
    keyframes: KeyframeSelection = field(default_factory=KeyframeSelection)
    preview_size: tuple[int, int] = ranged((960, 720), 16, 8192)
    preset: str = "custom"

    def __post_init__(self) -> None:
        check_ranges(self)


MAP_PRESETS: dict[str, MapConfig] = {
    "object": MapConfig(depth=DEPTH_PRESETS["object"], fusion=FUSION_PRESETS["object"],
                        keyframes=KeyframeSelection(min_translation_m=0.04, min_rotation_deg=5.0), preset="object"),
    "room": MapConfig(depth=DEPTH_PRESETS["room"], fusion=FUSION_PRESETS["room"],
                      keyframes=KeyframeSelection(min_translation_m=0.15, min_rotation_deg=10.0), preset="room"),
    "large_room": MapConfig(depth=DEPTH_PRESETS["large_room"], fusion=FUSION_PRESETS["large_room"],
                            keyframes=KeyframeSelection(min_translation_m=0.3, min_rotation_deg=10.0),
                            preset="large_room"),
}
AUTO = "auto"  # the preset chosen from the keyframes' stereo depth (stereopath.host.mapping.auto_preset)
PRESET_CHOICES = (AUTO, *MAP_PRESETS)


def map_preset(name: str, voxel_mm: float | None = None, **keyframe_changes: float) -> MapConfig:
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
# building


@dataclass(eq=False)
class MapResult:
    """The model in memory: legacy Open3D mesh and cloud, preview image (RGB) and statistics."""

    mesh: o3d.geometry.TriangleMesh
    cloud: o3d.geometry.PointCloud
    preview: np.ndarray
    stats: dict[str, Any]


class DenseMapper:
    """Incremental dense mapping for one rig: ``add`` keyframes, ``mesh()`` any time, ``finish()``.

    ``build_map`` drives it for a whole input; a live view can call ``add`` as keyframes arrive
    and ``mesh()`` every few keyframes (extraction costs about 0.1-0.5 s for a table-top scan).
    """

    def __init__(self, rig: Rig, config: MapConfig, source: str = "", keep_depth: bool = False) -> None:
        self.rig = rig
        # keep_depth: every keyframe's depth map stays in memory (about 1.2 MB at 640x480) so that
        # :meth:`repose` can fuse them again at new poses
        self.config = config
        self.source = source or rig.name
        self.depth = StereoDepth(rig, config.depth)
        self.volume = TsdfVolume(config.fusion)
        self.poses: list[np.ndarray] = []
        self.indices: list[int] = []
        self.valid_fractions: list[float] = []
        self.depth_maps: list[DepthMap] | None = [] if keep_depth else None
        self.reposed = 0
        self.timings = {"load": 0.0, "depth": 0.0, "fusion": 0.0}
        log.info("dense mapping (%s preset): depth %.2f-%.2f m, voxel %.1f mm", config.preset, config.depth.min_depth_m,
                 config.depth.max_depth_m, config.fusion.voxel_m * 1e3)
        log.debug("dense mapping settings: depth %s; fusion %s", config.depth, config.fusion)

    @property
    def keyframes(self) -> int:
        return len(self.poses)

    def progress(self) -> dict[str, Any]:
        """The keyframes fused so far, as JSON values (what :meth:`resume` restores besides the volume)."""
        return {"poses": np.asarray(self.poses).tolist(), "indices": list(self.indices),
                "valid_fractions": list(self.valid_fractions), "timings": dict(self.timings)}

    def resume(self, volume_folder: Path, state: dict[str, Any]) -> None:
        """Continue from a stored build: the volume in ``volume_folder``, the rest from :meth:`progress`."""
        poses = [np.asarray(T, float).reshape(4, 4) for T in state["poses"]]
        indices, fractions = [int(i) for i in state["indices"]], [float(f) for f in state["valid_fractions"]]
        if not len(poses) == len(indices) == len(fractions):
            raise StereopathError("stored progress: poses, indices and depth fractions differ in number")
        self.volume.restore(volume_folder)
        self.poses, self.indices, self.valid_fractions = poses, indices, fractions
        self.timings.update({k: float(v) for k, v in state["timings"].items() if k in self.timings})

    def reset(self) -> None:
        """Back to an empty volume and no keyframe fused."""
        self.volume = TsdfVolume(self.config.fusion)
        self.poses, self.indices, self.valid_fractions = [], [], []
        self.depth_maps = [] if self.depth_maps is not None else None
        self.timings = {"load": 0.0, "depth": 0.0, "fusion": 0.0}

    def add(self, left: np.ndarray, right: np.ndarray, T_world_cam0: np.ndarray,
            index: int | None = None) -> DepthMap:
        """Depth of one raw stereo pair, fused at the camera-0 pose; returns the :class:`stereopath.host.mapping.depth.DepthMap`."""
        t0 = time.perf_counter()
        dm = self.depth.compute(left, right)
        self.timings["depth"] += time.perf_counter() - t0
        return self.fuse(dm, T_world_cam0, index)

    def fuse(self, dm: DepthMap, T_world_cam0: np.ndarray, index: int | None = None) -> DepthMap:
        """Fuse a depth map computed by ``self.depth`` at the camera-0 pose; returns ``dm``."""
        t0 = time.perf_counter()
        self.volume.integrate_depth_map(dm, T_world_cam0)
        self.timings["fusion"] += time.perf_counter() - t0
        self.poses.append(np.asarray(T_world_cam0, float))
        self.indices.append(len(self.indices) if index is None else int(index))
        self.valid_fractions.append(dm.valid_fraction)
        if self.depth_maps is not None:
            self.depth_maps.append(dm)
        return dm

    def repose(self, T_world_cam0: np.ndarray) -> None:
        """Move the fused keyframes to new poses (K, 4, 4): the TSDF is rebuilt by integrating every
        kept depth map again at its new pose (re-integration, not a deformation of the old volume:
        exact, and about the fusion time of the keyframes so far, ~0.05 s each)."""
        if self.depth_maps is None:
            raise StereopathError(f"{self.source}: repose needs the depth maps (DenseMapper(keep_depth=True))")
        T = np.asarray(T_world_cam0, float)
        if T.shape != (len(self.poses), 4, 4):
            raise StereopathError(f"{self.source}: repose got {T.shape[0] if T.ndim == 3 else '?'} poses for "
                                  f"{len(self.poses)} fused keyframes")
        t0 = time.perf_counter()
        self.volume = TsdfVolume(self.config.fusion)
        for dm, Tk in zip(self.depth_maps, T):
            self.volume.integrate_depth_map(dm, Tk)
        self.poses = [Tk.copy() for Tk in T]
        self.reposed += 1
        self.timings["fusion"] += time.perf_counter() - t0

    def mesh(self) -> o3d.geometry.TriangleMesh:
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
                "depth": config.depth.record(),
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


DEPTH_BATCH = 8  # keyframes loaded and their depth computed together before they are fused in order


def _depth_map(depth: StereoDepth, images: tuple[np.ndarray, np.ndarray]) -> DepthMap:
    """One keyframe's depth map (a piece of :func:`~stereopath.host.backend.parallel.parallel_map`)."""
    return depth.compute(images[0], images[1])


def build_map(inp: MapInput, config: MapConfig, progress: bool | None = None,
              on_keyframe: Callable[[int, Any], None] | None = None, strict: bool = False,
              checkpoint: MapCheckpoint | None = None) -> MapResult:
    """Depth and fusion of every keyframe of ``inp``, then mesh, cloud and preview (no file I/O but
    the ``checkpoint``'s).

    ``progress``: tqdm bar on stderr (None = only when stderr is a terminal).  ``on_keyframe(k,
    depth_map)`` is called after each keyframe is fused (for live views).  A keyframe whose
    images cannot be read is skipped and counted (``stats["keyframes_skipped"]``) unless ``strict``.
    ``checkpoint``: the volume is stored there every so many keyframes, and a build finding one
    stored goes on after it.
    """
    if not inp.keyframes:
        raise DatasetError(f"{inp.source}: no keyframes to map")
    t_start = time.perf_counter()
    mapper = DenseMapper(inp.rig, config, source=inp.source)
    first = 0
    resumed = checkpoint.load(mapper) if checkpoint is not None else None
    if resumed is not None:
        first, inp.skipped[:] = resumed
    bar = progress_bar(len(inp.keyframes), "depth + fusion", progress, unit="kf", initial=first)
    try:
        for start in range(first, len(inp.keyframes), DEPTH_BATCH):
            loaded = []
            for k in range(start, min(start + DEPTH_BATCH, len(inp.keyframes))):
                kf, t0 = inp.keyframes[k], time.perf_counter()
                try:
                    loaded.append((k, kf, kf.load()))
                except DatasetError as exc:
                    if strict:
                        raise
                    log.warning("skipping keyframe %d: %s", kf.index, exc)
                    inp.skipped.append(str(kf.index))
                mapper.timings["load"] += time.perf_counter() - t0
            # the batch's depth maps are independent (a fleet task spreads them over idle cores); fused in order
            t0 = time.perf_counter()
            depths = parallel_map(_depth_map, mapper.depth, [images for _, _, images in loaded])
            mapper.timings["depth"] += time.perf_counter() - t0
            for (k, kf, _), dm in zip(loaded, depths):
                mapper.fuse(dm, kf.T_world_cam0, index=kf.index)
                if on_keyframe is not None:
                    on_keyframe(k, dm)
                if bar is not None:
                    bar.update(1)
            done = min(start + DEPTH_BATCH, len(inp.keyframes))
            if checkpoint is not None and done < len(inp.keyframes) and done // checkpoint.every > start // checkpoint.every:
                checkpoint.save(mapper, done, inp.skipped)
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

    Everything is written into a hidden temporary folder inside ``out_dir`` first (the same file
    system, whether or not ``out_dir`` is a mount point, and nothing written beside it); only when
    all four files exist are they moved in, each by an atomic rename, ``map.json`` last.
    ``out_dir`` may already exist (other files in it are left alone).  A temporary folder left by
    a writer that was killed is removed by a later write (once an hour old: another writer may be
    using a newer one).
    """
    from stereopath.host.mapping.fusion import write_cloud, write_mesh
    from stereopath.host.mapping.preview import write_png

    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise StereopathError(f"output {out} exists and is not a folder")
    out.mkdir(parents=True, exist_ok=True)
    for stale in out.glob(f"{MAP_TEMP_PREFIX}*.tmp"):  # left by a killed writer (not one writing now)
        try:
            if time.time() - stale.stat().st_mtime > STALE_TEMP_S:
                shutil.rmtree(stale, ignore_errors=True)
        except OSError:
            pass
    tmp = Path(tempfile.mkdtemp(prefix=MAP_TEMP_PREFIX, suffix=".tmp", dir=out))
    try:
        write_mesh(result.mesh, tmp / "mesh.ply")
        write_cloud(result.cloud, tmp / "cloud.ply")
        write_png(result.preview, tmp / "model.png")
        (tmp / "map.json").write_text(json.dumps(result.stats, indent=2, sort_keys=False) + "\n")
        for name in MAP_FILES:  # map.json, the last, says the model is complete
            os.replace(tmp / name, out / name)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return {name: out / name for name in MAP_FILES}


def auto_config(rig: Rig, keyframes_for: Callable[[KeyframeSelection], list[MapKeyframe]],
                voxel_mm: float | None = None, **keyframe_changes: float) -> tuple[MapConfig, dict[str, Any]]:
    """The preset :mod:`stereopath.host.mapping.auto_preset` chooses for the keyframes
    ``keyframes_for(selection)`` gives (surveyed with the object preset's finer keyframe spacing), with
    ``voxel_mm`` and the keyframe changes applied; and the ``preset_choice`` entry of map.json."""
    from stereopath.host.mapping.auto_preset import ORDER, choose_preset

    survey_cfg = map_preset("object", **keyframe_changes)
    choice = choose_preset(rig, keyframes_for(survey_cfg.keyframes), {k: MAP_PRESETS[k].depth.max_depth_m for k in ORDER})
    return map_preset(choice.preset, voxel_mm=voxel_mm, **keyframe_changes), {"asked": AUTO, **choice.as_dict()}


def asked_choice(config: MapConfig) -> dict[str, Any]:
    """The ``preset_choice`` entry of map.json for a preset given by name."""
    return {"asked": config.preset, "preset": config.preset, "reason": "given (--map-preset)"}


def map_sequence(seq: SequenceBase, trajectory: Trajectory, out_dir: str | Path | None, config: MapConfig | str,
                 progress: bool | None = None, source: str = "", checkpoint: MapCheckpoint | None = None) -> MapResult:
    """Map any sequence (``rig``, ``t_ns``, ``frame(i)``) with the poses of ``trajectory``; write the
    model into ``out_dir`` when given.  (For reprocessing and the demo.)  ``config`` may be
    :data:`AUTO`: the preset is chosen from the keyframes' stereo depth.  ``checkpoint``: see
    :func:`build_map`."""
    source = source or str(getattr(seq, "spec", ""))
    if isinstance(config, str) and config == AUTO:
        config, choice = auto_config(seq.rig, lambda sel: keyframes_from_sequence(seq, trajectory, sel,
                                                                                  source=source).keyframes)
    else:
        config = map_preset(config) if isinstance(config, str) else config
        choice = asked_choice(config)
    inp = keyframes_from_sequence(seq, trajectory, config.keyframes, source=source)
    result = build_map(inp, config, progress=progress, checkpoint=checkpoint)
    result.stats["preset_choice"] = choice
    if out_dir is not None:
        write_map(result, out_dir)
    return result


def map_path(path: str | Path, out_dir: str | Path, config: MapConfig | str, poses: str | Path | None = None,
             rig: str | Path | None = None, progress: bool | None = None, strict: bool = False,
             voxel_mm: float | None = None, **keyframe_changes: float) -> MapResult:
    """``stereopath host map``: open a session or keyframes folder, build the model, write it.

    ``config``: a MapConfig, or a preset name (with ``voxel_mm`` and ``keyframe_changes`` applied),
    :data:`AUTO` choosing it from the keyframes' stereo depth.  Unreadable keyframes or frames are
    skipped and counted unless ``strict``."""
    if isinstance(config, str) and config == AUTO:
        survey_sel = map_preset("object", **keyframe_changes).keyframes
        first = open_map_input(path, survey_sel, poses=poses, rig=rig, strict=strict)
        config, choice = auto_config(first.rig, lambda sel: first.keyframes, voxel_mm, **keyframe_changes)
        inp = first if config.keyframes == survey_sel else open_map_input(path, config.keyframes, poses=poses,
                                                                          rig=rig, strict=strict)
    else:
        if isinstance(config, str):
            config = map_preset(config, voxel_mm=voxel_mm, **keyframe_changes)
        choice = asked_choice(config)
        inp = open_map_input(path, config.keyframes, poses=poses, rig=rig, strict=strict)
    result = build_map(inp, config, progress=progress, strict=strict)
    result.stats["preset_choice"] = choice
    write_map(result, out_dir)
    return result
