"""The on-board estimator by name: ``make_estimator("stereo", rig, ...)``.

The research baselines (``paper``, ``sfm``) are host-side: ``stereopath.host.evaluation.baselines``.
"""

from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING, Mapping

from stereopath.device.core.stereo_config import StereoConfig
from stereopath.device.errors import ConfigError
from stereopath.device.core.rig import Rig

if TYPE_CHECKING:
    from stereopath.device.estimation.stereo_vo import StereoEstimator

ESTIMATORS = ("stereo",)

def make_estimator(name: str, rig: Rig, preset: str | None = None,
                   options: StereoConfig | Mapping[str, object] | None = None) -> StereoEstimator:
    """Build the on-board estimator.  ``preset`` names the feature preset (``asift.feature_preset``);
    ``options`` is a :class:`StereoConfig` or a mapping of its sections (nested tables, as in
    ``[estimator.stereo.*]``: ``{"klt": {"klt_window": 21}}``)."""
    from stereopath.device.core.config import from_mapping

    if name != "stereo":
        raise ConfigError(f"unknown on-board estimator {name!r}; known: {', '.join(ESTIMATORS)} "
                          "(the paper and sfm baselines run on the host: stereopath odometry --estimator)")
    from stereopath.device.estimation.stereo_vo import StereoEstimator

    cfg = options if isinstance(options, StereoConfig) else from_mapping(StereoConfig, options or {}, prefix="stereo")
    if preset is not None:
        cfg = dataclasses.replace(cfg, asift=from_mapping(
            type(cfg.asift), {**_fields(cfg.asift), "feature_preset": preset}, prefix="stereo.asift"))
    return StereoEstimator(rig, cfg)


def _fields(section: object) -> dict[str, object]:
    return {f.name: getattr(section, f.name) for f in dataclasses.fields(section)}
