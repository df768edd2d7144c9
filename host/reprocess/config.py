"""Settings of ``host reprocess`` (:class:`ReprocessPreset`, the named presets) and what a stage gets.

Each stage module (``stage_estimate``, ``stage_tracks``, ``stage_ba``, ``stage_map``) has
``run(config, inputs) -> outputs``: ``config`` a :class:`ReprocessPreset`, ``inputs`` a
:class:`StageInputs` (the sequence and the arrays of the stages it depends on).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from stereopath.device.core.stereo_config import DisparityOffsetConfig, KeyframePolicy, StereoConfig
from stereopath.host.backend.ba_common import BAConfig
from stereopath.host.backend.loops import LoopConfig
from stereopath.host.reprocess.memory import MemoryLedger
from stereopath.host.reprocess.preset_names import DEFAULT_PRESET, PRESET_ABOUT
from stereopath.host.backend.tracks import TrackConfig


def offline_stereo() -> StereoConfig:
    """The stereo estimator as reprocessing runs it.

    Offline there is no frame deadline: each keyframe's ASIFT work is joined at its keyframe (on board
    it runs on a worker thread whose result arrives when it is ready), so a rerun (or a resumed run, or
    a fleet worker) gives the same path to the last bit.  The disparity offset is not refined on line:
    the bundle adjustment estimates it from every keyframe at once, and an on-line value that changes
    part-way through (the points re-triangulated each time) only hands it a start whose scale drifts."""
    return StereoConfig(keyframes=KeyframePolicy(background=False),
                        disparity_offset=DisparityOffsetConfig(estimate=False))


@dataclass(frozen=True)
class ReprocessPreset:
    """Settings of one reprocessing run (see :data:`REPROCESS_PRESETS`)."""

    description: str
    estimator_preset: str | None = None  # feature preset of the stereo estimator (None: its on-board default)
    # the stereo estimator's settings by stage (its feature preset is estimator_preset); a preset overrides
    # a section with a typed value: dataclasses.replace(offline_stereo(), klt=KltConfig(...))
    estimator_options: StereoConfig = field(default_factory=offline_stereo)
    tracks: TrackConfig = field(default_factory=TrackConfig)
    loops: LoopConfig = field(default_factory=LoopConfig)  # loop closure between keyframes (tracks stage)
    # the keyframe bundle adjustment; with ba.imu, IMU preintegration between keyframes (GTSAM back end):
    # CombinedImuFactors with the recorded noise, velocity and bias unknowns, gravity direction estimated
    # jointly (started from the still start, else from the path); left out (with a warning) when the session
    # has no IMU or no T_body_cam0, or when its readings do not fit the path
    ba: BAConfig = field(default_factory=BAConfig)
    refine_frames: bool = True  # motion-only refinement of the frames between keyframes
    frame_points: int = 600  # keypoints per neighbouring keyframe followed into each frame's left image
    imu_rotation_priors: bool = False  # gyro-integrated relative rotations between keyframes as BA terms
    gyro_sigma_rad_per_sqrt_s: float = 0.002
    # the right images in the left camera's grey levels for the tracks, ba and map stages where the two
    # cameras differ by more than exposure_tolerance grey levels (host/reprocess/exposure.py); the estimate
    # stage runs the on-board estimator, which measures and corrects them itself
    match_exposure: bool = True
    exposure_tolerance: float = 4.0


_TRACK_GAPS = (1, 2, 3, 5, 8, 12, 16, 20)

REPROCESS_PRESETS: dict[str, ReprocessPreset] = {
    "standard": ReprocessPreset(
        PRESET_ABOUT["standard"],
        tracks=TrackConfig(feature_preset="fast_asym", max_features=0, window=20, gaps=_TRACK_GAPS),
    ),
    "aligned": ReprocessPreset(
        PRESET_ABOUT["aligned"],
        tracks=TrackConfig(feature_preset="fast_asym", max_features=0, window=20, gaps=_TRACK_GAPS, align_window=21),
    ),
    "quick": ReprocessPreset(
        PRESET_ABOUT["quick"],
        tracks=TrackConfig(feature_preset="fast_asym", original_view_only=True, max_features=0, window=20,
                           gaps=_TRACK_GAPS),
    ),
    "paper": ReprocessPreset(
        PRESET_ABOUT["paper"],
        estimator_preset="paper",
        tracks=TrackConfig(feature_preset="paper", max_features=0, window=20, gaps=_TRACK_GAPS),
    ),
    "full": ReprocessPreset(
        PRESET_ABOUT["full"],
        estimator_preset="full",
        tracks=TrackConfig(feature_preset="full", max_features=0, window=20, gaps=_TRACK_GAPS),
    ),
}


def resolve_preset(preset: "str | ReprocessPreset") -> tuple[str, ReprocessPreset]:
    """``(name, settings)`` of a preset name or a :class:`ReprocessPreset` ("custom")."""
    if not isinstance(preset, str):
        return "custom", preset
    if preset not in REPROCESS_PRESETS:
        from stereopath.device.errors import ConfigError

        raise ConfigError(f"unknown reprocess preset {preset!r}; known: {', '.join(REPROCESS_PRESETS)}")
    return preset, REPROCESS_PRESETS[preset]


@dataclass
class StageInputs:
    """What a stage's ``run`` gets: the sequence, progress-bar setting and earlier stages' arrays."""

    seq: Any
    progress: bool | None = None
    results: dict[str, dict[str, np.ndarray]] = field(default_factory=dict)
    extra: dict[str, Any] = field(default_factory=dict)  # e.g. the map stage's folder and settings
    memory: MemoryLedger = field(default_factory=MemoryLedger)  # sizes of what the stage holds
    # the stage's folder of partial results (kept until the stage is stored: an interrupted stage
    # resumes from them); None: held in memory
    parts: Path | None = None
