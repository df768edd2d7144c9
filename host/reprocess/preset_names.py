"""The reprocessing presets' names and what each does, without their settings (the command line reads
these without importing the pipeline; :data:`stereopath.host.reprocess.config.REPROCESS_PRESETS` holds
the settings)."""

from __future__ import annotations

DEFAULT_PRESET = "standard"

PRESET_ABOUT: dict[str, str] = {
    "standard": "the on-board estimator again, then modified-ASIFT (preset 'fast_asym': original view + 4 tilted "
                "views) at every keyframe, tracks over 20 keyframes, bundle adjustment, frame refinement",
    "aligned": "standard, with every track's observations aligned on one reference view (an affine window fit): "
               "each keyframe then sees the same surface point, far more precisely than a detector; for a rig "
               "whose stereo calibration is good (see docs/architecture.md: on KITTI's rectified pair it is worse); ~10 s more",
    "quick": "plain SIFT tracks (no affine views) over 20 keyframes: about half the time, less accurate",
    "paper": "the paper's modified ASIFT (25 views) in the estimator and at every keyframe: slow",
    "full": "OpenCV's reference ASIFT (cv2.AffineFeature) in the estimator and at every keyframe: slowest",
}
