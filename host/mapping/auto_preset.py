"""``--map-preset auto``: the map preset chosen from the keyframes' stereo depth.

A few keyframes spread over the scan (:data:`SAMPLES`) get a survey depth map (semi-global
matching over 0.25-30 m, the room presets' cleaning); the depths of all their valid pixels are
pooled and the preset is the smallest whose depth range holds :data:`COVER` of them:
``object`` (up to 2 m), ``room`` (up to 6 m), else ``large_room`` (up to 15 m).  A scan of a
table top whose camera also sees the far wall now and then stays ``object``; a walk through a room
that sees its walls at 2-4 m gets ``room``.  The choice, the figures it was made from and the
reason are recorded in ``map.json`` (``preset_choice``).
"""

from __future__ import annotations

import logging
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from stereopath.host.mapping.depth import DepthConfig

log = logging.getLogger(__name__)

SAMPLES = 6  # keyframes surveyed
COVER = 0.9  # the share of the valid depths the chosen preset's range must hold
SURVEY = DepthConfig(min_depth_m=0.25, max_depth_m=30.0, block_size=7, edge_max_rel_step=0.05, erode_px=1)
ORDER = ("object", "room", "large_room")  # smallest range first
PIXELS_PER_MAP = 20000  # valid depths kept per surveyed keyframe (evenly), so each weighs the same


@dataclass(frozen=True)
class PresetChoice:
    preset: str
    reason: str
    keyframes_surveyed: int
    valid_fraction: float
    depth_quantiles_m: dict[str, float]  # p10, p50, p90 of the pooled valid depths

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)


def choose_from_depths(depths_m: np.ndarray, max_depths_m: dict[str, float], keyframes: int = 0,
                       valid_fraction: float = 0.0) -> PresetChoice:
    """The preset for pooled valid depths ``depths_m`` (pure): the first of :data:`ORDER` whose
    ``max_depths_m[name]`` is at least the :data:`COVER` quantile; ``object`` when no depth is valid."""
    d = np.asarray(depths_m, float)
    d = d[np.isfinite(d) & (d > 0)]
    if not len(d):
        return PresetChoice("object", "no valid stereo depth in the surveyed keyframes: the default preset",
                            keyframes, valid_fraction, {})
    q = {f"p{int(p)}": round(float(np.quantile(d, p / 100)), 3) for p in (10, 50, 90)}
    cover = float(np.quantile(d, COVER))
    for name in ORDER:
        if cover <= max_depths_m[name] or name == ORDER[-1]:
            held = float(np.mean(d <= max_depths_m[name]))
            why = (f"{COVER:.0%} of the stereo depth lies within {cover:.2f} m "
                   f"(median {q['p50']:.2f} m); the {name} preset reaches {max_depths_m[name]:.1f} m "
                   f"and holds {held:.0%} of it")
            return PresetChoice(name, why, keyframes, valid_fraction, q)
    raise AssertionError("unreachable")  # pragma: no cover


def survey(rig: Any, keyframes: list[Any], samples: int = SAMPLES) -> tuple[np.ndarray, int, float]:
    """Pooled valid depths of ``samples`` keyframes spread over ``keyframes`` (``MapKeyframe``: ``load()``),
    the number surveyed and their mean valid fraction."""
    from stereopath.device.errors import DatasetError
    from stereopath.host.mapping.depth import StereoDepth

    if not keyframes:
        return np.zeros(0), 0, 0.0
    pick = np.unique(np.round(np.linspace(0, len(keyframes) - 1, min(samples, len(keyframes)))).astype(int))
    depth = StereoDepth(rig, SURVEY)
    pooled, fractions = [], []
    for i in pick:
        try:
            left, right = keyframes[int(i)].load()
        except DatasetError as exc:
            log.warning("depth survey: keyframe %d unreadable (%s)", i, exc)
            continue
        dm = depth.compute(left, right)
        v = dm.depth_m[dm.depth_m > 0]
        fractions.append(dm.valid_fraction)
        if len(v) > PIXELS_PER_MAP:
            v = v[np.linspace(0, len(v) - 1, PIXELS_PER_MAP).astype(int)]
        pooled.append(v)
    d = np.concatenate(pooled) if pooled else np.zeros(0)
    return d, len(fractions), float(np.mean(fractions)) if fractions else 0.0


def choose_preset(rig: Any, keyframes: list[Any], max_depths_m: dict[str, float]) -> PresetChoice:
    """The map preset for these keyframes (module doc), ``max_depths_m``: each preset's depth range end; logged."""
    d, n, frac = survey(rig, keyframes)
    choice = choose_from_depths(d, max_depths_m, n, frac)
    log.info("map preset auto -> %s: %s", choice.preset, choice.reason)
    return choice
