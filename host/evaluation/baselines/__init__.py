"""Research baselines the on-board estimator is compared with (``odometry --estimator paper|sfm``, ``--compare``).

``paper`` is the reference paper's steps as written; ``sfm`` is monocular structure from motion whose step
length comes from ground truth (oracle scale), which no device has.  Neither ships on the device.
"""

from __future__ import annotations

from typing import Any

from stereopath.device.core.rig import Rig
from stereopath.device.errors import ConfigError
from stereopath.device.estimation import registry
from stereopath.device.formats.tum import Trajectory

ESTIMATORS = (*registry.ESTIMATORS, "paper", "sfm")


def make_estimator(name: str, rig: Rig, preset: str | None = None, groundtruth: Trajectory | None = None,
                   options: dict[str, Any] | None = None):
    """The on-board estimator or a baseline, by name."""
    from stereopath.device.core.config import from_mapping

    if name in registry.ESTIMATORS:
        return registry.make_estimator(name, rig, preset=preset, options=options)
    opts = dict(options or {})
    if preset is not None:
        opts["feature_preset"] = preset
    if name == "paper":
        from stereopath.host.evaluation.baselines.paper import PaperConfig, PaperEstimator

        return PaperEstimator(rig, from_mapping(PaperConfig, opts, prefix="paper"))
    if name == "sfm":
        from stereopath.host.evaluation.baselines.sfm import SfmConfig, SfmEstimator

        if groundtruth is None:
            raise ConfigError("the sfm baseline takes its step length from ground truth (oracle scale); "
                              "this source has none")
        return SfmEstimator(rig, groundtruth, from_mapping(SfmConfig, opts, prefix="sfm"))
    raise ConfigError(f"unknown estimator {name!r}; known: {', '.join(ESTIMATORS)}")
