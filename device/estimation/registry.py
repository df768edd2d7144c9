"""Estimators by name: ``make_estimator("stereo" | "paper" | "sfm", rig, ...)``."""

from __future__ import annotations

from typing import Any

from stereopath.device.errors import ConfigError
from stereopath.device.core.rig import Rig
from stereopath.device.formats.tum import Trajectory

ESTIMATORS = ("stereo", "paper", "sfm")


def make_estimator(name: str, rig: Rig, preset: str | None = None, groundtruth: Trajectory | None = None,
                   options: dict[str, Any] | None = None):
    """Build an estimator.  ``preset`` names the feature preset; ``options`` are config keys."""
    from stereopath.device.core.config import from_mapping

    opts = dict(options or {})
    if preset is not None:
        opts["feature_preset"] = preset
    if name == "stereo":
        from stereopath.device.estimation.stereo_vo import StereoConfig, StereoEstimator

        return StereoEstimator(rig, from_mapping(StereoConfig, opts, prefix="stereo"))
    if name == "paper":
        from stereopath.device.estimation.paper import PaperConfig, PaperEstimator

        return PaperEstimator(rig, from_mapping(PaperConfig, opts, prefix="paper"))
    if name == "sfm":
        from stereopath.device.estimation.sfm import SfmConfig, SfmEstimator

        if groundtruth is None:
            raise ConfigError("the sfm baseline takes its step length from ground truth (oracle scale); "
                              "this source has none")
        return SfmEstimator(rig, groundtruth, from_mapping(SfmConfig, opts, prefix="sfm"))
    raise ConfigError(f"unknown estimator {name!r}; known: {', '.join(ESTIMATORS)}")
