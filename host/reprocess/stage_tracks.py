"""Stage ``tracks``: modified-ASIFT keypoints with stereo 3D points at every keyframe of the
estimate, matched between keyframes up to ``window`` apart (guided by the estimated poses) and
joined into tracks (:mod:`stereopath.host.reprocess.tracks`), and loops between keyframes far
apart in the sequence found and verified on the same keypoints (:mod:`stereopath.host.reprocess.loops`).

These fresh detections replace the estimator's chained KLT tracks, whose drift grows with track
age and would bend the path in bundle adjustment.  Outputs (``tracks.npz``): the keyframes'
frame indices ``kf_index`` and poses ``T_kf``, ``observations`` rows, the tracks' first 3D
points (``point_ids``, ``point_xyz``) and every keyframe's keypoints (``kf_offsets``,
``kf_ids``, ``kf_xy``) for the frame refinement, ``loops`` (rows of
:func:`~stereopath.host.reprocess.loops.loops_to_array`), plus ``stats``.
"""

from __future__ import annotations

import logging

import numpy as np

from stereopath.host.reprocess.config import ReprocessPreset, StageInputs
from stereopath.host.reprocess.loops import detect_loops, loops_to_array
from stereopath.host.reprocess.parallel import parallel_map
from stereopath.host.progress import Bar
from stereopath.host.reprocess.store import json_array

log = logging.getLogger(__name__)

NAME = "tracks"


def settings(config: ReprocessPreset) -> dict:
    return {"tracks": config.tracks, "loops": config.loops}


def choose_keyframes(est: dict[str, np.ndarray]) -> np.ndarray:
    """The estimator's keyframes that were tracked, plus the first and last tracked frames."""
    ok = np.flatnonzero(est["status"] == 0)
    kf = np.flatnonzero(est["keyframe"] & (est["status"] == 0))
    return np.unique(np.concatenate([ok[:1], kf, ok[-1:]])).astype(np.int64)


def keyframes_by_view_change(rig, est: dict[str, np.ndarray], features_of, cfg, progress=None
                             ) -> tuple[np.ndarray, list]:
    """Offline keyframes (frame indices) and their features: from the first tracked frame, the next
    keyframe is the last tracked frame that sees the previous keyframe's points within
    ``cfg.keyframe_parallax_deg`` and ``cfg.keyframe_motion_px`` (:func:`tracks.view_change`), at least
    the next tracked frame; the last tracked frame ends the list.  ``features_of(i)`` computes
    frame ``i``'s features.  Rotation alone changes no viewpoint: a scan that mostly turns gets few
    keyframes, driving towards the scene one every frame or two."""
    from stereopath.host.reprocess.tracks import view_change

    ok = np.flatnonzero(est["status"] == 0)
    T = est["T_world_cam"]
    kf, feats = [int(ok[0])], [features_of(int(ok[0]))]
    while kf[-1] < ok[-1]:
        later = ok[ok > kf[-1]]
        nxt = int(later[0])
        for j in later[1:]:
            angle, motion = view_change(rig, feats[-1], T[kf[-1]], T[j], cfg.min_depth_m)
            if angle > cfg.keyframe_parallax_deg or motion > cfg.keyframe_motion_px:
                break
            nxt = int(j)
        kf.append(nxt)
        feats.append(features_of(nxt))
        if progress is not None:
            progress(1)
    return np.array(kf, np.int64), feats


# the points that choose the offline keyframes: Shi-Tomasi corners spread over the image (as the keypoints are)
VIEW_CORNERS = 500
VIEW_CORNER_QUALITY = 0.01
VIEW_CORNER_SPACING_PX = 12


def view_points(rig, left: np.ndarray, right: np.ndarray, cfg):
    """A keyframe's points for choosing the next one (:func:`keyframes_by_view_change`): corners of the
    left image with a stereo 3D point, found and triangulated as the keyframe's keypoints are
    (:func:`tracks.stereo_points`).  They sample the same scene as the keypoints (the viewpoint change
    is a median over them) at a small part of their cost, so the keypoints of every keyframe can be
    computed afterwards, independently (:func:`parallel_map`).  Returned as keypoints without descriptors."""
    import cv2

    from stereopath.device.core.features import Features, gray
    from stereopath.host.reprocess.tracks import KeyframeFeatures, stereo_points

    left, right = gray(left), gray(right)
    c = cv2.goodFeaturesToTrack(left, maxCorners=VIEW_CORNERS, qualityLevel=VIEW_CORNER_QUALITY,
                                minDistance=VIEW_CORNER_SPACING_PX)
    xy = np.zeros((0, 2), np.float32) if c is None else c.reshape(-1, 2).astype(np.float32)
    uv0, uv1, X, ok = stereo_points(rig, left, right, xy, cfg)
    n = int(ok.sum())
    z = np.zeros(n, np.float32)
    feats = Features(xy[ok], np.zeros((n, 0), np.float32), z, z.copy(), z.copy(), np.zeros(n, np.int16))
    return KeyframeFeatures(feats, uv0[ok], uv1[ok], X[ok])


def _empty(est: dict[str, np.ndarray], kf: np.ndarray, reason: str) -> dict[str, np.ndarray]:
    log.warning("no tracks: %s", reason)
    return {"kf_index": kf, "T_kf": est["T_world_cam"][kf], "observations": np.zeros((0, 6)),
            "point_ids": np.zeros(0, np.int64), "point_xyz": np.zeros((0, 3)),
            "kf_offsets": np.zeros(len(kf) + 1, np.int64), "kf_ids": np.zeros(0, np.int64),
            "kf_xy": np.zeros((0, 2), np.float32), "loops": loops_to_array([]),
            "stats": json_array({"skipped": reason, "keyframes": len(kf)})}


def _keyframe_features(shared: tuple, images: tuple[np.ndarray, np.ndarray]):
    """One keyframe's stereo keypoints (a piece of :func:`parallel_map`; ``shared`` = rig, track config)."""
    from stereopath.host.reprocess.tracks import stereo_features

    rig, cfg = shared
    return stereo_features(rig, images[0], images[1], cfg)


def run(config: ReprocessPreset, inputs: StageInputs) -> dict[str, np.ndarray]:
    from stereopath.host.reprocess import tracks as tracks_mod

    seq, est = inputs.seq, inputs.results["estimate"]
    cfg = config.tracks
    if not np.any(est["status"] == 0):
        return _empty(est, np.zeros(0, np.int64), "no tracked frame in the re-estimate")

    def images_of(i: int) -> tuple[np.ndarray, np.ndarray]:
        fr = seq.frame(int(est["seq"][i]))
        return fr.left, fr.right

    images: dict[int, tuple[np.ndarray, np.ndarray]] = {}

    def points_of(i: int):
        images[i] = images_of(i)
        return view_points(seq.rig, *images[i], cfg)

    if cfg.keyframe_parallax_deg > 0:
        with Bar(None, "keyframes", inputs.progress, "kf") as tick:
            kf, _ = keyframes_by_view_change(seq.rig, est, points_of, cfg, tick)
    else:
        kf = choose_keyframes(est)
    with Bar(len(kf), "keyframe features", inputs.progress, "kf") as tick:
        pairs = [images.pop(int(i), None) or images_of(i) for i in kf]
        # independent per keyframe: a fleet task spreads them over idle cores (same results, same order)
        feats = parallel_map(_keyframe_features, (seq.rig, cfg), pairs)
        tick(len(kf))
    if len(kf) < 2:
        return _empty(est, kf, f"{len(kf)} tracked keyframe(s) in the re-estimate; bundle adjustment needs two")
    T_kf = est["T_world_cam"][kf]
    n_gaps = len([g for g in (cfg.gaps or range(1, cfg.window + 1)) if 1 <= g <= cfg.window])
    with Bar(n_gaps, "track matching", inputs.progress, "gap") as tick:
        tr = tracks_mod.build_tracks(seq.rig, feats, T_kf, cfg, progress=tick)
    loops = detect_loops(seq.rig, feats, T_kf, config.loops)
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
        "loops": loops_to_array(loops),
        "stats": json_array({**tr.stats, "loops": len(loops)}),
    }
