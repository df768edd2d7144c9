"""The on-board estimator by name: ``make_estimator("stereo", rig, ...)``.

The research baselines (``paper``, ``sfm``) are host-side: ``stereopath.host.evaluation.baselines``.
"""

from __future__ import annotations

from typing import Any

from stereopath.device.errors import ConfigError
from stereopath.device.core.rig import Rig

ESTIMATORS = ("stereo",)


def make_estimator(name: str, rig: Rig, preset: str | None = None, options: dict[str, Any] | None = None):
    """Build the on-board estimator.  ``preset`` names the feature preset; ``options`` are config keys."""
    from stereopath.device.core.config import from_mapping

    opts = dict(options or {})
    if preset is not None:
        opts["feature_preset"] = preset
    if name == "stereo":
        from stereopath.device.estimation.stereo_vo import StereoConfig, StereoEstimator

        return StereoEstimator(rig, from_mapping(StereoConfig, opts, prefix="stereo"))
    raise ConfigError(f"unknown on-board estimator {name!r}; known: {', '.join(ESTIMATORS)} "
                      "(the paper and sfm baselines run on the host: stereopath odometry --estimator)")
