"""Stage ``tracks``: modified-ASIFT keypoints with stereo 3D points at every keyframe of the
estimate, matched between keyframes up to ``window`` apart (guided by the estimated poses) and
joined into tracks (:mod:`stereopath.host.backend.tracks`), and loops between keyframes far
apart in the sequence found and verified on the same keypoints (:mod:`stereopath.host.backend.loops`).

These fresh detections replace the estimator's chained KLT tracks, whose drift grows with track
age and would bend the path in bundle adjustment.  Outputs (``tracks.npz``): the keyframes'
frame indices ``kf_index`` and poses ``T_kf``, ``observations`` rows (compact: int32 ids, float32
pixels; :data:`~stereopath.host.backend.ba_common.OBSERVATION_DTYPE`), the tracks' first 3D
points (``point_ids``, ``point_xyz``) and every keyframe's keypoints (``kf_offsets``,
``kf_ids``, ``kf_xy``) for the frame refinement, ``loops`` (rows of
:func:`~stereopath.host.backend.loops.loops_to_array`), plus ``stats``.
"""

from __future__ import annotations

import dataclasses
import functools
import logging

import numpy as np

from stereopath.device.estimation.base import TrackStatus
from stereopath.host.reprocess.config import ReprocessPreset, StageInputs
from stereopath.host.backend.observations import OBSERVATION_DTYPE
from stereopath.host.backend.loops import detect_loops, loops_to_array
from stereopath.host.backend.parallel import parallel_map, spare_cores, spreading
from stereopath.host.progress import Bar
from stereopath.host.reprocess.keyframe_store import KeyframeFeatureStore
from stereopath.host.reprocess.memory import nbytes
from stereopath.host.reprocess.store import json_array

log = logging.getLogger(__name__)

NAME = "tracks"
KEYFRAME_BATCH = 16  # the estimator's keyframes whose keypoints are computed together (spread by a fleet task)


def settings(config: ReprocessPreset) -> dict:
    return {"tracks": config.tracks, "loops": config.loops,
            "exposure": (config.match_exposure, config.exposure_tolerance)}


def choose_keyframes(est: dict[str, np.ndarray]) -> np.ndarray:
    """The estimator's keyframes that were tracked, plus the first and last tracked frames."""
    ok = np.flatnonzero(est["status"] == TrackStatus.OK.code)
    kf = np.flatnonzero(est["keyframe"] & (est["status"] == TrackStatus.OK.code))
    return np.unique(np.concatenate([ok[:1], kf, ok[-1:]])).astype(np.int64)


def next_keyframe(rig, est: dict[str, np.ndarray], k: int, points, cfg) -> int:
    """The keyframe after keyframe ``k`` (frame index): the last tracked frame that sees ``points`` (frame
    ``k``'s stereo points) within ``cfg.keyframe_parallax_deg`` and ``cfg.keyframe_motion_px``
    (:func:`tracks.view_change`), at least the next tracked frame."""
    from stereopath.host.backend.tracks import view_change

    ok, T = np.flatnonzero(est["status"] == TrackStatus.OK.code), est["T_world_cam"]
    later = ok[ok > k]
    nxt = int(later[0])
    for j in later[1:]:
        angle, motion = view_change(rig, points, T[k], T[j], cfg.stereo.min_depth_m)
        if angle > cfg.keyframe_parallax_deg or motion > cfg.keyframe_motion_px:
            break
        nxt = int(j)
    return nxt


def keyframes_by_view_change(rig, est: dict[str, np.ndarray], features_of, cfg, progress=None,
                             into: KeyframeFeatureStore | None = None) -> tuple[np.ndarray, list | KeyframeFeatureStore]:
    """Offline keyframes (frame indices) and their features: from the first tracked frame, the next
    keyframe is :func:`next_keyframe` from the previous keyframe's features; the last tracked frame
    ends the list.  ``features_of(i)`` computes frame ``i``'s features.  Rotation alone changes no
    viewpoint: a scan that mostly turns gets few keyframes, driving towards the scene one every frame or two.
    ``into``: a store the features go to as they are found (returned instead of a list); ``progress(n)``
    counts frames passed."""
    ok = np.flatnonzero(est["status"] == TrackStatus.OK.code)
    feats: list = []
    kf = [int(ok[0])]
    last = features_of(kf[0])
    feats.append(last) if into is None else into.append(kf[0], last)
    while kf[-1] < ok[-1]:
        kf.append(next_keyframe(rig, est, kf[-1], last, cfg))
        last = features_of(kf[-1])
        feats.append(last) if into is None else into.append(kf[-1], last)
        if progress is not None:
            progress(int(np.count_nonzero((ok > kf[-2]) & (ok <= kf[-1]))))
    return np.array(kf, np.int64), feats if into is None else into


def guessed_keyframe_count(rig, est: dict[str, np.ndarray], images_of, cfg) -> int:
    """How many offline keyframes this stage will choose, guessed the way :func:`keyframes_ahead`
    guesses ahead: the rule of :func:`next_keyframe` on cheap corners (:func:`view_points`) from the
    first tracked frame to the last (a small fraction of the keypoints' cost).  What a
    session's tracks and bundle adjustment will cost, for a scheduler; never used for results."""
    if not np.any(est["status"] == TrackStatus.OK.code):
        return 0
    if cfg.keyframe_parallax_deg <= 0:  # the estimator's keyframes
        return len(choose_keyframes(est))
    return len(keyframes_by_view_change(rig, est, lambda i: view_points(rig, *images_of(i), cfg), cfg)[0])


def keyframes_ahead(rig, est: dict[str, np.ndarray], images_of, cfg, progress=None,
                    into: KeyframeFeatureStore | None = None) -> tuple[np.ndarray, list | KeyframeFeatureStore]:
    """The keyframes and keypoints of :func:`keyframes_by_view_change` (the same ones), with the keypoints
    computed in batches of independent pieces (:func:`parallel_map`) instead of one after another.

    Each keyframe is chosen from the previous one's keypoints, so the chain is guessed ahead from
    cheap corners (:func:`view_points`, the same rule on other points of the same scene), the keypoints
    of the guessed keyframes are computed together, and the chain is then followed with the rule on
    the keypoints as far as the guesses were right.  At a wrong guess the next batch starts from the
    right keyframe; a batch grows while the guesses hold (twice the last one's size) and starts again
    at two after a wrong one, so little work is thrown away where the guesses are poor.  While the
    spreader has no idle processor (:func:`spare_cores`: other sessions keep every core busy) the
    next keyframe is found exactly as one after another, and nothing is guessed.  ``into``: a store the
    keyframes' features go to as the chain passes them (returned instead of a list; only the batch
    ahead is then held); ``progress(n)`` counts keyframes."""
    ok = np.flatnonzero(est["status"] == TrackStatus.OK.code)
    feats: dict[int, object] = {}
    corners: dict[int, object] = {}
    kf, size = [int(ok[0])], 2

    def compute(todo: list[int]) -> None:
        if into is not None:  # stored by an interrupted run: read back, not computed again
            for g in todo:
                got = into.stored(g)
                if got is not None:
                    feats[g] = got
            todo = [g for g in todo if g not in feats]
        feats.update(zip(todo, parallel_map(_keyframe_features, (rig, cfg), [images_of(g) for g in todo])))
        if into is not None:
            for g in todo:
                into.features(g, lambda _g: feats[_g])

    def pass_on() -> None:  # keyframes the chain has passed go to the store; guesses behind it are dropped
        if into is None:
            return
        for k in kf[len(into):-1]:
            into.append(k, feats[k])
        for g in [g for g in feats if g < kf[-1]]:
            del feats[g]
        for g in [g for g in corners if g < kf[-1]]:
            del corners[g]

    while True:
        if not spare_cores():
            if kf[-1] not in feats:
                compute([kf[-1]])
            if kf[-1] >= ok[-1]:
                break
            kf.append(next_keyframe(rig, est, kf[-1], feats[kf[-1]], cfg))
            if progress is not None:
                progress(1)
            size = 2
            pass_on()
            continue
        guess = [kf[-1]]  # kf[-1] is a keyframe whose keypoints are still to compute
        while len(guess) < size and guess[-1] < ok[-1]:
            g = guess[-1]
            if g not in corners:
                corners[g] = view_points(rig, *images_of(g), cfg)
            guess.append(next_keyframe(rig, est, g, corners[g], cfg))
        compute([g for g in guess if g not in feats])
        start = len(kf)
        while kf[-1] < ok[-1] and kf[-1] in feats:
            kf.append(next_keyframe(rig, est, kf[-1], feats[kf[-1]], cfg))
        if progress is not None:
            progress(len(kf) - start)
        if kf[-1] in feats:  # the last tracked frame, with its keypoints
            break
        size = 2 * size if len(kf) - start >= len(guess) - 1 else 2
        pass_on()
    log.info("offline keyframes guessed ahead: %d keyframes, keypoints of %d frames", len(kf), len(feats))
    if into is None:
        return np.array(kf, np.int64), [feats[k] for k in kf]
    for k in kf[len(into):]:
        into.append(k, feats[k])
    return np.array(kf, np.int64), into


# the points that guess the offline keyframes ahead: Shi-Tomasi corners spread over the image (as the keypoints are)
VIEW_CORNERS = 500
VIEW_CORNER_QUALITY = 0.01
VIEW_CORNER_SPACING_PX = 12


def view_points(rig, left: np.ndarray, right: np.ndarray, cfg):
    """A frame's points for guessing the next keyframe ahead (:func:`keyframes_ahead`): corners of the
    left image with a stereo 3D point, found and triangulated as the keypoints are
    (:func:`tracks.stereo_points`).  They sample the same scene as the keypoints (the viewpoint change
    is a median over them) at a small part of their cost.  Returned as keypoints without descriptors."""
    import cv2

    from stereopath.device.core.features import Features, gray
    from stereopath.host.backend.tracks import KeyframeFeatures, stereo_points

    left, right = gray(left), gray(right)
    c = cv2.goodFeaturesToTrack(left, maxCorners=VIEW_CORNERS, qualityLevel=VIEW_CORNER_QUALITY,
                                minDistance=VIEW_CORNER_SPACING_PX)
    xy = np.zeros((0, 2), np.float32) if c is None else c.reshape(-1, 2).astype(np.float32)
    # a guess needs their depth roughly: the KLT match without the slanted refinement
    no_slant = dataclasses.replace(cfg, stereo=dataclasses.replace(cfg.stereo, slanted_window=0))
    uv0, uv1, X, ok = stereo_points(rig, left, right, xy, no_slant)
    n = int(ok.sum())
    z = np.zeros(n, np.float32)
    feats = Features(xy[ok], np.zeros((n, 0), np.float32), z, z.copy(), z.copy(), np.zeros(n, np.int16))
    return KeyframeFeatures(feats, uv0[ok], uv1[ok], X[ok])


def _empty(est: dict[str, np.ndarray], kf: np.ndarray, reason: str) -> dict[str, np.ndarray]:
    log.warning("no tracks: %s", reason)
    return {"kf_index": kf, "T_kf": est["T_world_cam"][kf], "observations": np.zeros(0, OBSERVATION_DTYPE),
            "point_ids": np.zeros(0, np.int64), "point_xyz": np.zeros((0, 3)),
            "kf_offsets": np.zeros(len(kf) + 1, np.int64), "kf_ids": np.zeros(0, np.int32),
            "kf_xy": np.zeros((0, 2), np.float32), "loops": loops_to_array([]),
            "stats": json_array({"skipped": reason, "keyframes": len(kf)})}


def _keyframe_features(shared: tuple, images: tuple[np.ndarray, np.ndarray]):
    """One keyframe's stereo keypoints (a piece of :func:`parallel_map`; ``shared`` = rig, track config),
    on as many threads as OpenCV may use here (one in a fleet's piece, the task's CPUs in its task)."""
    import cv2

    from stereopath.host.backend.tracks import stereo_features

    rig, cfg = shared
    return stereo_features(rig, images[0], images[1], cfg, workers=max(1, cv2.getNumThreads()))


def run(config: ReprocessPreset, inputs: StageInputs) -> dict[str, np.ndarray]:
    from stereopath.host.backend import tracks as tracks_mod

    seq, est = inputs.seq, inputs.results["estimate"]
    cfg = config.tracks
    if not np.any(est["status"] == TrackStatus.OK.code):
        return _empty(est, np.zeros(0, np.int64), "no tracked frame in the re-estimate")

    def images_of(i: int) -> tuple[np.ndarray, np.ndarray]:
        fr = seq.frame(int(est["seq"][i]))
        return fr.left, fr.right

    # every keyframe's keypoints go to a file of the stage store as they are computed (read back by the
    # matching a batch at a time): held all at once they would grow with the scan, and an interrupted
    # stage starts again from the last keyframe stored
    store = KeyframeFeatureStore(inputs.parts)

    def features_of(i: int):
        return store.features(i, lambda j: _keyframe_features((seq.rig, cfg), images_of(j)))

    with inputs.memory.timed("keyframe_features"):
        if cfg.keyframe_parallax_deg > 0:
            if spreading():  # keypoints of guessed keyframes ahead, in parallel (the same keyframes)
                with Bar(None, "keyframe features", inputs.progress, "kf") as tick:
                    kf, feats = keyframes_ahead(seq.rig, est, images_of, cfg, tick, into=store)
            else:  # one after another: nothing is computed that is not used
                n_ok = int(np.count_nonzero(est["status"] == TrackStatus.OK.code))
                with Bar(n_ok, "keyframe features", inputs.progress, "frame") as tick:
                    kf, feats = keyframes_by_view_change(seq.rig, est, features_of, cfg, tick, into=store)
        else:
            kf = choose_keyframes(est)
            with Bar(len(kf), "keyframe features", inputs.progress, "kf") as tick:
                # independent per keyframe: a fleet task spreads them over idle cores (same results, same order),
                # a batch at a time
                for s in range(0, len(kf), KEYFRAME_BATCH):
                    part = [int(i) for i in kf[s:s + KEYFRAME_BATCH]]
                    for i, f in zip(part, parallel_map(_keyframe_features, (seq.rig, cfg), [images_of(i) for i in part])):
                        store.append(i, store.features(i, lambda _j, f=f: f))
                    tick(len(part))
            feats = store
    inputs.memory.note("keypoints_descriptors", store.held_bytes())
    if len(kf) < 2:
        return _empty(est, kf, f"{len(kf)} tracked keyframe(s) in the re-estimate; bundle adjustment needs two")
    T_kf = est["T_world_cam"][kf]
    align = None
    if cfg.align_window:  # every track's observations moved onto its reference view's surface point
        from stereopath.host.backend.track_alignment import align_tracks

        images = [images_of(i) for i in kf]
        inputs.memory.note("images", nbytes(images))
        align = functools.partial(align_tracks, seq.rig, [a for a, _ in images], [b for _, b in images], T_kf, cfg)
    with Bar(len(kf), "track matching", inputs.progress, "kf") as tick, inputs.memory.timed("track_matching"):
        tr = tracks_mod.build_tracks(seq.rig, feats, T_kf, cfg, progress=tick, align=align, sizes=store.sizes)
    inputs.memory.note("keypoints_descriptors", store.held_bytes())
    inputs.memory.note("observations", tr.observations.nbytes)
    inputs.memory.note("tracks", nbytes(tr.points) + nbytes(tr.kf_ids) + nbytes(tr.kf_xy))
    with inputs.memory.timed("loops"):
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
        "kf_ids": np.concatenate(tr.kf_ids) if tr.kf_ids else np.zeros(0, np.int32),
        "kf_xy": np.concatenate(tr.kf_xy) if tr.kf_xy else np.zeros((0, 2), np.float32),
        "loops": loops_to_array(loops),
        "stats": json_array({**tr.stats, "loops": len(loops), **exposure_stats(seq, est["seq"][kf])}),
    }


def exposure_stats(seq, frames: np.ndarray) -> dict:
    """The right camera's grey-level relation at the keyframes (``frames``: their sequence indices) when
    the stage read an exposure-matched sequence, else nothing."""
    from stereopath.host.reprocess.exposure import ExposureMatchedSequence

    return {"exposure": seq.summary(frames)} if isinstance(seq, ExposureMatchedSequence) else {}
