"""Offline reprocessing of a recorded session: re-estimate, bundle adjust, map, report.

Stages (each writes its result atomically into ``OUT/stages/`` and is recorded in
``OUT/stages/manifest.json`` with a key: a hash of its inputs and settings; a rerun reuses every
stage whose key and files are still there and recomputes the rest):

1. ``estimate`` (``estimate.npz``): the ``stereo`` estimator over every frame with the preset's
   settings (per-frame poses, status, keyframes, frame times);
2. ``tracks`` (``tracks.npz``): at every keyframe of the estimate, modified-ASIFT keypoints of
   the preset (:mod:`stereopath.device.core.features`) with stereo 3D points, matched between keyframes up to
   ``window`` apart, guided by the estimated poses, and joined into tracks (:mod:`stereopath.host.reprocess.tracks`).
   These fresh detections replace the estimator's chained KLT tracks, whose drift grows with
   track age and would bend the path in bundle adjustment;
3. ``ba`` (``ba.npz``): bundle adjustment of keyframe poses and track points
   (:mod:`stereopath.host.reprocess.bundle_adjust`: Levenberg-Marquardt on the reprojection error in both cameras,
   Huber loss, Schur complement; the rig's constant disparity error is estimated too and applied
   when it exceeds 0.02 px; optional gyro rotation priors), outlier removal and a second solve;
   then every other frame: the keyframe corrections interpolated, followed by a
   motion-only refinement on the adjusted points (each frame observes its neighbouring
   keyframes' tracked keypoints by one KLT step each);
4. ``map`` (``map/``): the dense model with the refined path (:func:`stereopath.host.mapping.mapper.map_sequence`).

Then the outputs (always rewritten, each atomically): ``trajectory.tum``, ``report.json`` (the
schema of :mod:`stereopath.host.evaluation.report` plus ``extra.before_after``: the session's on-board path when it has
one, the re-estimate and the adjusted path, with errors when there is ground truth),
``path.png``, ``errors.png`` (with ground truth), the model files and ``report.html``.

Ctrl-C between or inside stages leaves only finished stages behind (each stage's files appear by
rename only when complete, and the manifest is updated after them).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import os
import shutil
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from stereopath.device.errors import DatasetError, EstimationError, StereopathError
from stereopath.device.formats.tum import Trajectory
from stereopath.host.reprocess.tracks import TrackConfig

log = logging.getLogger(__name__)

STAGES = ("estimate", "tracks", "ba", "map")
MANIFEST = "manifest.json"
PIPELINE_VERSION = 1  # bump when a stage's computation changes (invalidates stored stages)
MODEL_FILES = ("mesh.ply", "cloud.ply", "model.png", "map.json")
_STATUS = ("ok", "imu_only", "lost")


@dataclass(frozen=True)
class ReprocessPreset:
    """Settings of one reprocessing run (see :data:`REPROCESS_PRESETS`)."""

    description: str
    estimator_preset: str | None = None  # feature preset of the stereo estimator (None: its on-board default)
    estimator_options: tuple[tuple[str, Any], ...] = ()
    tracks: TrackConfig = field(default_factory=TrackConfig)
    ba_loss: str = "huber"
    ba_robust_px: float = 1.0
    ba_max_iterations: int = 30
    ba_outlier_px: float = 3.0
    ba_outlier_rounds: int = 1
    ba_disparity_offset: bool = True  # estimate a constant disparity error (right principal point) in BA
    ba_disparity_offset_min_px: float = 0.02  # smaller estimates are noise: not applied
    refine_frames: bool = True  # motion-only refinement of the frames between keyframes
    frame_points: int = 300  # keypoints per neighbouring keyframe followed into each frame
    imu_rotation_priors: bool = False  # gyro-integrated relative rotations between keyframes as BA terms
    gyro_sigma_rad_per_sqrt_s: float = 0.002


_TRACK_GAPS = (1, 2, 3, 5, 8, 12, 16, 20)

REPROCESS_PRESETS: dict[str, ReprocessPreset] = {
    "standard": ReprocessPreset(
        "the on-board estimator again, then modified-ASIFT (preset 'fast': original view + 4 tilted "
        "views) at every keyframe, tracks over 20 keyframes, bundle adjustment, frame refinement",
        tracks=TrackConfig(feature_preset="fast", max_features=0, window=20, gaps=_TRACK_GAPS),
    ),
    "quick": ReprocessPreset(
        "plain SIFT tracks (no affine views) over 20 keyframes: about half the time, less accurate",
        tracks=TrackConfig(feature_preset="fast", original_view_only=True, max_features=0, window=20,
                           gaps=_TRACK_GAPS),
    ),
    "paper": ReprocessPreset(
        "the paper's modified ASIFT (25 views) in the estimator and at every keyframe: slow",
        estimator_preset="paper",
        tracks=TrackConfig(feature_preset="paper", max_features=0, window=20, gaps=_TRACK_GAPS),
    ),
    "full": ReprocessPreset(
        "OpenCV's reference ASIFT (cv2.AffineFeature) in the estimator and at every keyframe: slowest",
        estimator_preset="full",
        tracks=TrackConfig(feature_preset="full", max_features=0, window=20, gaps=_TRACK_GAPS),
    ),
}
DEFAULT_PRESET = "standard"


@dataclass
class ReprocessResult:
    out_dir: Path
    report: dict[str, Any]
    trajectory: Trajectory
    stages: dict[str, str]  # stage -> "computed" | "reused" | "skipped"
    seconds: dict[str, float]
    files: list[str]


# ---------------------------------------------------------------------------------------------
# helpers


def _progress_bar(total: int, desc: str, enabled: bool | None, unit: str = "it"):
    if enabled is None:
        enabled = sys.stderr.isatty()
    if not enabled:
        return None
    from tqdm import tqdm

    return tqdm(total=total, desc=desc, unit=unit, leave=False, file=sys.stderr)


class _Bar:
    """A tqdm bar or nothing, usable as ``with _Bar(...) as tick: tick(1)``."""

    def __init__(self, total: int, desc: str, enabled: bool | None, unit: str = "it") -> None:
        self.bar = _progress_bar(total, desc, enabled, unit)

    def __enter__(self) -> Callable[[int], None]:
        return (lambda n=1: None) if self.bar is None else self.bar.update

    def __exit__(self, *exc: Any) -> None:
        if self.bar is not None:
            self.bar.close()


def _plain(v: Any) -> Any:
    if dataclasses.is_dataclass(v) and not isinstance(v, type):
        return _plain(dataclasses.asdict(v))
    if isinstance(v, dict):
        return {str(k): _plain(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_plain(x) for x in v]
    if isinstance(v, np.ndarray):
        return v.tolist()
    if isinstance(v, np.generic):
        return v.item()
    return v


def _key(*parts: Any) -> str:
    text = json.dumps(_plain(list(parts)), sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def _atomic_write_text(path: Path, text: str) -> None:
    tmp = path.with_name("." + path.name + ".tmp")
    tmp.write_text(text)
    os.replace(tmp, path)


def _save_npz(path: Path, **arrays: Any) -> None:
    """``np.savez`` into a temporary file, then rename (a reader never sees half a file)."""
    tmp = path.with_name("." + path.name + ".tmp.npz")
    np.savez(tmp, **arrays)
    os.replace(tmp, path)


def _json_array(obj: Any) -> np.ndarray:
    return np.array(json.dumps(_plain(obj)))


def _copy_atomic(src: Path, dst: Path) -> None:
    """``dst`` becomes a copy of ``src`` (a hard link when the file system allows) by rename."""
    if dst.exists() and os.path.samefile(src, dst):
        return  # already that file (rename would be a no-op and leave the temporary link behind)
    tmp = dst.with_name("." + dst.name + ".tmp")
    if tmp.exists():
        tmp.unlink()
    try:
        os.link(src, tmp)
    except OSError:
        shutil.copyfile(src, tmp)
    os.replace(tmp, dst)


def sequence_fingerprint(seq: Any) -> dict[str, Any]:
    """What identifies a sequence's input data cheaply: spec, frame times, rig, IMU extent."""
    from stereopath.device.core.rig import rig_to_dict

    t = np.asarray(seq.t_ns, np.int64)
    imu = getattr(seq, "imu", None)
    return {
        "spec": str(getattr(seq, "spec", "")),
        "frames": int(len(t)),
        "t_ns_sha": hashlib.sha256(t.tobytes()).hexdigest()[:16],
        "rig": _key(rig_to_dict(seq.rig)),
        "imu": None if imu is None or not len(imu) else [int(len(imu)), int(imu.t_ns[0]), int(imu.t_ns[-1])],
    }


# ---------------------------------------------------------------------------------------------
# the stage store


class StageStore:
    """``OUT/stages/``: stage files plus a manifest of finished stages and their keys."""

    def __init__(self, root: Path) -> None:
        self.root = root
        self.path = root / MANIFEST
        self.data: dict[str, Any] = {"format": "stereopath-reprocess", "version": PIPELINE_VERSION, "stages": {}}
        if self.path.is_file():
            try:
                d = json.loads(self.path.read_text())
                if isinstance(d, dict) and isinstance(d.get("stages"), dict):
                    self.data = d
            except (json.JSONDecodeError, UnicodeDecodeError):
                log.warning("%s is unreadable; all stages will be recomputed", self.path)

    def done(self, name: str, key: str) -> bool:
        ent = self.data["stages"].get(name)
        if not ent or ent.get("key") != key:
            return False
        return all((self.root / f).exists() for f in ent.get("files", []))

    def finish(self, name: str, key: str, files: list[str], seconds: float, settings: Any) -> None:
        self.data["stages"][name] = {
            "key": key, "files": files, "seconds": round(seconds, 3), "settings": _plain(settings),
            "finished_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        }
        self.root.mkdir(parents=True, exist_ok=True)
        _atomic_write_text(self.path, json.dumps(self.data, indent=2) + "\n")

    def forget(self, name: str) -> None:
        if self.data["stages"].pop(name, None) is not None:
            _atomic_write_text(self.path, json.dumps(self.data, indent=2) + "\n")

    def seconds(self, name: str) -> float:
        return float(self.data["stages"].get(name, {}).get("seconds", 0.0))


# ---------------------------------------------------------------------------------------------
# stages


def _run_estimate(seq: Any, preset: ReprocessPreset, progress: bool | None) -> dict[str, np.ndarray]:
    from stereopath.device.estimation.base import run_estimator
    from stereopath.device.estimation.registry import make_estimator

    est = make_estimator("stereo", seq.rig, preset=preset.estimator_preset, options=dict(preset.estimator_options))
    if hasattr(est, "record_observations"):
        est.record_observations = False  # offline tracks replace the on-board observation log
    try:
        with _Bar(len(seq), "re-estimate", progress, "frame") as tick:
            run = run_estimator(est, seq.frames(), getattr(seq, "imu", None), progress=tick)
    finally:
        if hasattr(est, "close"):
            est.close()
    return {
        "t_ns": np.array([e.t_ns for e in run.estimates], np.int64),
        "seq": np.array([e.seq for e in run.estimates], np.int64),
        "T_world_cam": np.array([e.T_world_cam for e in run.estimates]),
        "status": np.array([_STATUS.index(e.status) if e.status in _STATUS else 2 for e in run.estimates], np.int8),
        "keyframe": np.array([e.keyframe for e in run.estimates], bool),
        "frame_ms": np.array(run.frame_ms, float),
        "meta": _json_array({"world_frame": run.world_frame, "estimator": run.estimator, "stats": run.extra}),
    }


def _choose_keyframes(est: dict[str, np.ndarray]) -> np.ndarray:
    """Frame indices used as bundle-adjustment keyframes: the estimator's keyframes that were
    tracked, plus the first and last tracked frames."""
    ok = np.flatnonzero(est["status"] == 0)
    kf = np.flatnonzero(est["keyframe"] & (est["status"] == 0))
    return np.unique(np.concatenate([ok[:1], kf, ok[-1:]])).astype(np.int64)


def _run_tracks(seq: Any, est: dict[str, np.ndarray], preset: ReprocessPreset,
                progress: bool | None) -> dict[str, np.ndarray]:
    from stereopath.host.reprocess.tracks import build_tracks, stereo_features

    kf = _choose_keyframes(est) if np.any(est["status"] == 0) else np.zeros(0, np.int64)
    if len(kf) < 2:
        reason = f"{len(kf)} tracked keyframe(s) in the re-estimate; bundle adjustment needs two"
        log.warning("no tracks: %s", reason)
        return {"kf_index": kf, "T_kf": est["T_world_cam"][kf], "observations": np.zeros((0, 6)),
                "point_ids": np.zeros(0, np.int64), "point_xyz": np.zeros((0, 3)),
                "kf_offsets": np.zeros(len(kf) + 1, np.int64), "kf_ids": np.zeros(0, np.int64),
                "kf_xy": np.zeros((0, 2), np.float32), "stats": _json_array({"skipped": reason, "keyframes": len(kf)})}
    T_kf = est["T_world_cam"][kf]
    feats = []
    with _Bar(len(kf), "keyframe features", progress, "kf") as tick:
        for i in kf:
            fr = seq.frame(int(est["seq"][i]))
            feats.append(stereo_features(seq.rig, fr.left, fr.right, preset.tracks))
            tick(1)
    cfg = preset.tracks
    n_gaps = len([g for g in (cfg.gaps or range(1, cfg.window + 1)) if 1 <= g <= cfg.window])
    with _Bar(n_gaps, "track matching", progress, "gap") as tick:
        tr = build_tracks(seq.rig, feats, T_kf, cfg, progress=tick)
    ids = np.fromiter(tr.points.keys(), np.int64, len(tr.points))
    xyz = np.array([tr.points[int(i)] for i in ids]).reshape(-1, 3)
    return {
        "kf_index": kf,
        "T_kf": T_kf,
        "observations": tr.observations,
        "point_ids": ids,
        "point_xyz": xyz,
        "kf_offsets": np.concatenate([[0], np.cumsum([len(a) for a in tr.kf_ids])]).astype(np.int64),
        "kf_ids": np.concatenate(tr.kf_ids) if tr.kf_ids else np.zeros(0, np.int64),
        "kf_xy": np.concatenate(tr.kf_xy) if tr.kf_xy else np.zeros((0, 2), np.float32),
        "stats": _json_array(tr.stats),
    }


def gyro_rotation_priors(seq: Any, t_kf: np.ndarray, sigma_rad_per_sqrt_s: float) -> list:
    """Relative rotations between consecutive keyframes from the gyro (bias from the still start)."""
    from stereopath.device.estimation.inertial import GyroIntegrator, estimate_still
    from stereopath.host.reprocess.bundle_adjust import RotationPrior

    imu = getattr(seq, "imu", None)
    rig = seq.rig
    if imu is None or not len(imu) or rig.T_body_cam0 is None:
        return []
    still = estimate_still(imu.between(int(imu.t_ns[0]) - 1, int(seq.t_ns[0])))
    bias = None if still is None else still.gyro_bias_rad_s
    Rbc = np.asarray(rig.T_body_cam0)[:3, :3]
    out = []
    for i in range(len(t_kf) - 1):
        g = GyroIntegrator(bias)
        blk = imu.between(int(t_kf[i]) - 50_000_000, int(t_kf[i + 1]) + 50_000_000)
        Rb = g.feed_and_integrate(blk, int(t_kf[i]), int(t_kf[i + 1]))
        if Rb is None:
            continue
        dt = (int(t_kf[i + 1]) - int(t_kf[i])) * 1e-9
        out.append(RotationPrior(i, i + 1, Rbc.T @ Rb @ Rbc, max(sigma_rad_per_sqrt_s * np.sqrt(dt), 1e-6)))
    return out


def _run_ba(seq: Any, est: dict[str, np.ndarray], trk: dict[str, np.ndarray], preset: ReprocessPreset,
            progress: bool | None) -> dict[str, np.ndarray]:
    from stereopath.host.reprocess.bundle_adjust import bundle_adjust, interpolate_corrections, refine_poses_fixed_points
    from stereopath.host.reprocess.tracks import frame_observations

    kf = trk["kf_index"]
    T_kf = trk["T_kf"]
    points = {int(i): x for i, x in zip(trk["point_ids"], trk["point_xyz"])}
    priors = []
    if preset.imu_rotation_priors:
        priors = gyro_rotation_priors(seq, est["t_ns"][kf], preset.gyro_sigma_rad_per_sqrt_s)
    t0 = time.perf_counter()
    bar = _progress_bar(preset.ba_max_iterations * (1 + preset.ba_outlier_rounds), "bundle adjustment",
                        progress, "iteration")
    try:
        res = bundle_adjust(seq.rig, T_kf, points, trk["observations"], huber_px=preset.ba_robust_px,
                            loss=preset.ba_loss, max_iterations=preset.ba_max_iterations,
                            outlier_px=preset.ba_outlier_px, outlier_rounds=preset.ba_outlier_rounds,
                            rotation_priors=priors, estimate_disparity_offset=preset.ba_disparity_offset,
                            disparity_offset_min_px=preset.ba_disparity_offset_min_px,
                            on_iteration=None if bar is None else bar.update)
    except EstimationError as exc:
        # too little structure to adjust (e.g. a very short or featureless session): keep the re-estimate
        log.warning("bundle adjustment not possible (%s): the re-estimated path is kept", exc)
        return {"T_kf": T_kf, "T_frames": est["T_world_cam"].copy(), "point_ids": np.zeros(0, np.int64),
                "point_xyz": np.zeros((0, 3)), "stats": _json_array({"skipped": str(exc), "poses": len(kf)})}
    finally:
        if bar is not None:
            bar.close()
    t_ba = time.perf_counter() - t0
    T_all = est["T_world_cam"]
    T_frames = interpolate_corrections(est["t_ns"], T_all, est["t_ns"][kf], T_kf, res.T_world_cam)
    T_frames[kf] = res.T_world_cam
    n_refined = 0
    t1 = time.perf_counter()
    if preset.refine_frames:
        is_kf = np.zeros(len(T_all), bool)
        is_kf[kf] = True
        offs = trk["kf_offsets"]
        kf_img: dict[int, np.ndarray] = {}
        rows = []
        todo = np.flatnonzero(~is_kf)
        with _Bar(len(todo), "frame refinement", progress, "frame") as tick:
            for i in todo:
                j = int(np.searchsorted(kf, i))
                fr = seq.frame(int(est["seq"][i]))
                for k in (j - 1, j):
                    if not 0 <= k < len(kf):
                        continue
                    if k not in kf_img:
                        kf_img = {kk: v for kk, v in kf_img.items() if kk >= k - 1}  # keep the cache small
                        kf_img[k] = seq.frame(int(est["seq"][kf[k]])).left
                    ids = trk["kf_ids"][offs[k]:offs[k + 1]]
                    xy = trk["kf_xy"][offs[k]:offs[k + 1]]
                    if len(ids) > preset.frame_points:
                        pick = np.linspace(0, len(ids) - 1, preset.frame_points).astype(int)
                        ids, xy = ids[pick], xy[pick]
                    o = frame_observations(seq.rig, kf_img[k], xy, ids, res.points, fr.left, fr.right,
                                           T_frames[i], preset.tracks)
                    o[:, 0] = i
                    rows.append(o)
                tick(1)
        if rows:
            obs = np.vstack(rows)
            T_ref, ok = refine_poses_fixed_points(seq.rig, T_frames, res.points, obs, huber_px=preset.ba_robust_px,
                                                  disparity_offset_px=res.disparity_offset_px)
            ok &= ~is_kf
            T_frames[ok] = T_ref[ok]
            n_refined = int(ok.sum())
    stats = {"poses": len(kf), "points": res.n_points, "observations": res.n_obs,
             "rms_before_px": res.rms_before_px, "rms_after_px": res.rms_after_px, "iterations": res.iterations,
             "inlier_fraction": res.inlier_fraction, "rotation_priors": len(priors),
             "disparity_offset_px": res.disparity_offset_px if preset.ba_disparity_offset else None,
             "frames_refined": n_refined, "ba_seconds": round(t_ba, 3),
             "frame_refinement_seconds": round(time.perf_counter() - t1, 3)}
    ids = np.fromiter(res.points.keys(), np.int64, len(res.points))
    return {
        "T_kf": res.T_world_cam,
        "T_frames": T_frames,
        "point_ids": ids,
        "point_xyz": np.array([res.points[int(i)] for i in ids]).reshape(-1, 3),
        "stats": _json_array(stats),
    }


def _meta(arrs: dict[str, np.ndarray], key: str) -> Any:
    return json.loads(str(arrs[key]))


def _load_npz(path: Path) -> dict[str, np.ndarray] | None:
    try:
        with np.load(path, allow_pickle=False) as z:
            return {k: z[k] for k in z.files}
    except (OSError, ValueError, EOFError, KeyError) as exc:
        log.warning("%s unreadable (%s): recomputing", path, exc)
        return None


# ---------------------------------------------------------------------------------------------
# the pipeline


def open_session_checked(session_dir: str | Path) -> Any:
    """Open a recorded session for reprocessing; :class:`StereopathError` subclasses on bad input."""
    from stereopath.device.formats import open_source

    d = Path(session_dir)
    if not d.exists():
        raise DatasetError(f"session folder not found: {d}")
    if d.is_dir() and not any(d.iterdir()):
        raise DatasetError(f"{d}: the session folder is empty")
    seq = open_source(f"session:{d}")
    if len(seq) < 2:
        raise DatasetError(f"{d}: {len(seq)} stereo frame(s); reprocessing needs at least two")
    return seq


def _metrics(gt: Trajectory | None, traj: Trajectory | None) -> dict[str, Any] | None:
    from stereopath.host.evaluation.evaluate import evaluate
    from stereopath.host.evaluation.report import METRIC_KEYS

    if traj is None or len(traj) == 0:
        return None
    out: dict[str, Any] = {"frames": int(len(traj))}
    if gt is not None and len(gt) >= 3:
        from evo.core.geometry import GeometryException

        try:
            m = evaluate(gt, traj)
        except (StereopathError, GeometryException) as exc:  # e.g. too little motion to align
            log.warning("evaluation against the ground truth failed: %s", exc)
            m = None
        if m is not None:
            out.update({k: m.get(k) for k in METRIC_KEYS})
            out["n_associated"] = m.get("n_associated")
    return out


def reprocess_sequence(seq: Any, out_dir: str | Path, preset: str | ReprocessPreset = DEFAULT_PRESET,
                       do_map: bool = True, map_preset: str = "object", force: bool = False,
                       progress: bool | None = None, onboard: Trajectory | None = None,
                       source_label: str | None = None, imu_priors: bool = False,
                       after_stage: Callable[[str], None] | None = None) -> ReprocessResult:
    """Run the stages on any sequence (``rig``, ``t_ns``, ``frame(i)``, ``frames()``, ``imu``,
    ``groundtruth``) and write the outputs into ``out_dir`` (see the module doc).

    ``onboard``: the path estimated on the device (for the before/after figures).  ``force``
    recomputes every stage.  ``imu_priors`` adds gyro rotation priors between consecutive
    keyframes to the bundle adjustment (sequences with an IMU and ``rig.T_body_cam0``).  ``after_stage(name)`` is called after each stage is stored (a hook
    for tests and progress reporting).
    """
    if isinstance(preset, str):
        if preset not in REPROCESS_PRESETS:
            from stereopath.device.errors import ConfigError

            raise ConfigError(f"unknown reprocess preset {preset!r}; known: {', '.join(REPROCESS_PRESETS)}")
        preset_name, P = preset, REPROCESS_PRESETS[preset]
    else:
        preset_name, P = "custom", preset
    if imu_priors:
        P = dataclasses.replace(P, imu_rotation_priors=True)
        preset_name += "+imu"
    if do_map:
        from stereopath.host.mapping.mapper import map_preset as _mp

        map_cfg = _mp(map_preset)
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise StereopathError(f"output {out} exists and is not a folder")
    stages_dir = out / "stages"
    stages_dir.mkdir(parents=True, exist_ok=True)
    store = StageStore(stages_dir)
    status: dict[str, str] = {}
    fp = sequence_fingerprint(seq)
    label = source_label or fp["spec"] or "sequence"

    est_settings = {"preset": P.estimator_preset, "options": dict(P.estimator_options)}
    ba_settings = {k: v for k, v in dataclasses.asdict(P).items()
                   if k not in ("description", "tracks", "estimator_preset", "estimator_options")}
    keys: dict[str, str] = {}
    keys["estimate"] = _key("estimate", PIPELINE_VERSION, fp, est_settings)
    keys["tracks"] = _key("tracks", PIPELINE_VERSION, keys["estimate"], P.tracks)
    keys["ba"] = _key("ba", PIPELINE_VERSION, keys["tracks"], ba_settings)
    settings = {"estimate": est_settings, "tracks": P.tracks, "ba": ba_settings}
    cache: dict[str, dict[str, np.ndarray]] = {}

    def compute_estimate() -> dict[str, np.ndarray]:
        return _run_estimate(seq, P, progress)

    def compute_tracks() -> dict[str, np.ndarray]:
        return _run_tracks(seq, get("estimate"), P, progress)

    def compute_ba() -> dict[str, np.ndarray]:
        return _run_ba(seq, get("estimate"), get("tracks"), P, progress)

    computers = {"estimate": compute_estimate, "tracks": compute_tracks, "ba": compute_ba}

    def run_stage(name: str, files: list[str], compute: Callable[[], Any]) -> Any:
        store.forget(name)
        t0 = time.perf_counter()
        result = compute()
        store.finish(name, keys[name], files, time.perf_counter() - t0, settings.get(name))
        status[name] = "computed"
        log.info("stage %s: computed in %.1f s", name, time.perf_counter() - t0)
        if after_stage is not None:
            after_stage(name)
        return result

    def get(name: str, need_data: bool = True) -> dict[str, np.ndarray]:
        """The stage's arrays: stored ones when finished with the same key, else computed now."""
        if name in cache:
            return cache[name]
        path = stages_dir / f"{name}.npz"
        if not force and store.done(name, keys[name]) and status.get(name) != "computed":
            if not need_data:
                status.setdefault(name, "reused")
                return {}
            data = _load_npz(path)
            if data is not None:
                status[name] = "reused"
                cache[name] = data
                return data

        def compute() -> dict[str, np.ndarray]:
            data = computers[name]()
            _save_npz(path, **data)
            return data

        cache[name] = run_stage(name, [path.name], compute)
        return cache[name]

    est = get("estimate")
    get("tracks", need_data=False)
    ba = get("ba")
    trk_stats = _meta(cache["tracks"], "stats") if "tracks" in cache else _stage_stats(stages_dir, "tracks.npz")

    t_ns = est["t_ns"]
    final = Trajectory(t_ns, ba["T_frames"])
    reest = Trajectory(t_ns, est["T_world_cam"])

    # 4. map
    map_stats: dict[str, Any] | None = None
    if do_map:
        keys["map"] = _key("map", PIPELINE_VERSION, keys["ba"], dataclasses.asdict(map_cfg))
        settings["map"] = dataclasses.asdict(map_cfg)
        map_files = [f"map/{f}" for f in MODEL_FILES]

        def compute_map() -> None:
            from stereopath.host.mapping.mapper import map_sequence

            dst = stages_dir / "map"
            if dst.exists():
                shutil.rmtree(dst)
            map_sequence(seq, final, dst, map_cfg, progress=progress, source=label)

        if not force and store.done("map", keys["map"]):
            status["map"] = "reused"
        else:
            try:
                run_stage("map", map_files, compute_map)
            except StereopathError as exc:  # e.g. no valid depth with this map preset: keep the path outputs
                log.warning("dense model failed: %s", exc)
                status["map"] = "failed"
                map_stats = {"error": str(exc)}
        if status["map"] != "failed":
            try:
                map_stats = json.loads((stages_dir / "map" / "map.json").read_text())
            except (OSError, json.JSONDecodeError):
                map_stats = None
    else:
        status["map"] = "skipped"

    # outputs
    files = _write_outputs(out, seq, est, trk_stats=trk_stats,
                           ba=ba, reest=reest, final=final, onboard=onboard, label=label,
                           preset_name=preset_name, preset=P, status=status, store=store,
                           map_stats=map_stats, do_map=do_map)
    report = json.loads((out / "report.json").read_text())
    seconds = {s: store.seconds(s) for s in STAGES}
    return ReprocessResult(out, report, final, status, seconds, files)


def _stage_stats(stages_dir: Path, fname: str) -> dict[str, Any]:
    try:
        with np.load(stages_dir / fname, allow_pickle=False) as z:
            return json.loads(str(z["stats"]))
    except (OSError, ValueError, KeyError):
        return {}


def _write_outputs(out: Path, seq: Any, est: dict[str, np.ndarray], trk_stats: dict, ba: dict[str, np.ndarray],
                   reest: Trajectory, final: Trajectory, onboard: Trajectory | None, label: str, preset_name: str,
                   preset: ReprocessPreset, status: dict[str, str], store: StageStore,
                   map_stats: dict | None, do_map: bool) -> list[str]:
    from stereopath.device.formats.tum import write_tum
    from stereopath.host.evaluation.plots import plot_path
    from stereopath.host.evaluation.report import make_report, write_report
    from stereopath.host.reprocess.report_html import plot_errors, write_html_report

    try:
        gt = getattr(seq, "groundtruth", None)
    except StereopathError as exc:  # the ground truth is optional: keep the finished work
        log.warning("ground truth unusable, results written without errors against it: %s", exc)
        gt, gt_error = None, str(exc)
    else:
        gt_error = None
    meta = _meta(est, "meta")
    m_final = _metrics(gt, final)
    m_reest = _metrics(gt, reest)
    m_onboard = _metrics(gt, onboard) if onboard is not None and len(onboard) else None

    def ratio(a: dict | None, b: dict | None) -> float | None:
        if not a or not b or a.get("ate_rmse_m") is None or not b.get("ate_rmse_m"):
            return None
        return float(a["ate_rmse_m"]) / float(b["ate_rmse_m"])

    before_after = {
        "onboard": m_onboard,
        "reestimated": m_reest,
        "bundle_adjusted": m_final,
        "ate_ratio_vs_onboard": ratio(m_final, m_onboard),
        "ate_ratio_vs_reestimated": ratio(m_final, m_reest),
    }
    frames_tracked = int(np.sum(est["status"] == 0))
    extra = {
        "before_after": before_after,
        "preset": {"name": preset_name, **_plain(dataclasses.asdict(preset))},
        "estimate": {"estimator": meta.get("estimator"), "stats": meta.get("stats"),
                     "keyframes": int(np.sum(est["keyframe"]))},
        "tracks": trk_stats,
        "bundle_adjustment": _meta(ba, "stats"),
        "stages": {s: {"status": status.get(s, "skipped"), "seconds": store.seconds(s)} for s in STAGES},
        "map": map_stats,
    }
    if gt_error is not None:
        extra["groundtruth_error"] = gt_error
    skipped = list(getattr(seq, "skipped_frames", None) or [])
    extra["frames_skipped"] = len(skipped)
    if skipped:
        extra["skipped_frame_indexes"] = skipped[:1000]
    report = make_report(source=label, estimator="stereo+ba", frames=len(final), frames_tracked=frames_tracked,
                         metrics=m_final if m_final and m_final.get("ate_rmse_m") is not None else None,
                         frame_ms=est["frame_ms"], world_frame=meta.get("world_frame", "first_camera"), extra=extra)
    out.mkdir(parents=True, exist_ok=True)
    write_tum(out / "trajectory.tum", final)
    write_report(out / "report.json", report)
    gt_usable = gt is not None and m_final is not None and m_final.get("ate_rmse_m") is not None
    plot_path(out / "path.png", gt if gt_usable else None, final, world_frame=meta.get("world_frame"),
              title="reprocessed path (bundle adjusted)")
    files = ["trajectory.tum", "report.json", "path.png"]
    curves = {"re-estimated": reest, "bundle adjusted": final}
    if m_onboard and m_onboard.get("ate_rmse_m") is not None:
        curves = {"on-board": onboard, **curves}
    if gt_usable and plot_errors(out / "errors.png", gt, curves):
        files.append("errors.png")
    elif (out / "errors.png").exists():
        (out / "errors.png").unlink()  # from an earlier run with other inputs
    if do_map and status.get("map") != "failed" and (out / "stages" / "map").is_dir():
        for f in MODEL_FILES:
            src = out / "stages" / "map" / f
            if src.is_file():
                _copy_atomic(src, out / f)
                files.append(f)
    write_html_report(out / "report.html", report, [f for f in ("path.png", "errors.png", "model.png") if f in files])
    files.append("report.html")
    return files


def reprocess_session(session_dir: str | Path, out_dir: str | Path, preset: str | ReprocessPreset = DEFAULT_PRESET,
                      do_map: bool = True, map_preset: str = "object", force: bool = False,
                      progress: bool | None = None, imu_priors: bool = False,
                      after_stage: Callable[[str], None] | None = None, strict: bool = False) -> ReprocessResult:
    """``stereopath host reprocess``: a recorded session folder -> ``out_dir`` (see the module doc).

    The input is checked before anything is written: a missing or empty folder, a folder that is
    not a session, missing calibration or fewer than two frames raise a
    :class:`stereopath.device.errors.StereopathError` and leave ``out_dir`` untouched.
    """
    seq = open_session_checked(session_dir)
    from stereopath.device.core.stereo_order import check_sequence_order

    check_sequence_order(seq)  # exchanged left/right images: say so before any stage runs
    seq.strict = strict  # False: unreadable frames are skipped and counted (report extra.frames_skipped)
    onboard = getattr(seq, "trajectory", None)
    return reprocess_sequence(seq, out_dir, preset=preset, do_map=do_map, map_preset=map_preset, force=force,
                              progress=progress, onboard=onboard, source_label=str(session_dir),
                              imu_priors=imu_priors, after_stage=after_stage)
