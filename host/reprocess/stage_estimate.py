"""Stage ``estimate``: the ``stereo`` estimator over every frame with the preset's settings.

Outputs (``estimate.npz``): per-frame ``t_ns``, ``seq``, ``T_world_cam``, ``status``
(:attr:`TrackStatus.code`), ``keyframe``, ``frame_ms`` and ``meta`` (world frame, estimator, its stats).
Every :data:`CHUNK_FRAMES` frames the estimator and its results are stored in the stage's parts folder
(:mod:`~stereopath.host.reprocess.estimate_progress`); an interrupted stage continues from there.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from stereopath.device.core.config import as_dict
from stereopath.device.estimation.base import EstimateProgress
from stereopath.host.reprocess.config import ReprocessPreset, StageInputs
from stereopath.host.progress import Bar
from stereopath.host.reprocess.estimate_progress import EstimateCheckpoint
from stereopath.host.reprocess.store import json_array

NAME = "estimate"
CHUNK_FRAMES = 500  # frames between two stored progress records (a few seconds of work each)


def settings(config: ReprocessPreset) -> dict[str, Any]:
    """The settings that make up this stage's key."""
    return {"preset": config.estimator_preset, "options": as_dict(config.estimator_options)}


def run(config: ReprocessPreset, inputs: StageInputs) -> dict[str, np.ndarray]:
    from stereopath.device.estimation.base import Chunks, run_estimator
    from stereopath.device.estimation.registry import make_estimator

    seq = inputs.seq
    # the estimator and its results are stored every CHUNK_FRAMES frames: an interrupted stage goes on from there
    store = EstimateCheckpoint(inputs.parts) if inputs.parts is not None else None
    stored = store.load() if store is not None else None
    skipped = getattr(seq, "skipped_frames", None)  # the unreadable frames the source has met (the report's)
    if stored is not None:
        est, done = stored
        if skipped is not None:
            skipped.extend(i for i in done.skipped_frames if i not in skipped)
    else:
        est = make_estimator("stereo", seq.rig, preset=config.estimator_preset, options=config.estimator_options)
        done = EstimateProgress()

    def save(progress: EstimateProgress) -> None:
        progress.skipped_frames = list(skipped or [])
        store.save(est, progress)

    chunks = None if store is None else Chunks(CHUNK_FRAMES, save)
    try:
        with Bar(len(seq), "re-estimate", inputs.progress, "frame", initial=done.next_seq) as tick:
            res = run_estimator(est, seq.frames(start=done.next_seq), getattr(seq, "imu", None), progress=tick,
                                resume=done, chunks=chunks)
    finally:
        if hasattr(est, "close"):
            est.close()
    return {
        "t_ns": np.array([e.t_ns for e in res.estimates], np.int64),
        "seq": np.array([e.seq for e in res.estimates], np.int64),
        "T_world_cam": np.array([e.T_world_cam for e in res.estimates]),
        "status": np.array([e.status.code for e in res.estimates], np.int8),
        "keyframe": np.array([e.keyframe for e in res.estimates], bool),
        "frame_ms": np.array(res.frame_ms, float),
        "meta": json_array({"world_frame": res.world_frame, "estimator": res.estimator, "stats": res.extra}),
    }
