"""``--map-preset auto``: the map preset chosen from the keyframes' stereo depth.

A few keyframes spread over the scan (:data:`SAMPLES`) get a survey depth map (semi-global
matching over 0.25-30 m with the room presets' cleaning); :data:`POINTS_PER_MAP` of each one's
valid pixels are kept as depths and, through the keyframe's pose, as world points.  Then
(:func:`choose_from_survey`, pure):

* ``object`` when the surfaces within the object preset's depth range (up to 2 m) are a good share
  of what the camera sees (:data:`MIN_NEAR_SHARE`) and fit in an object's volume: their extent (the
  5-95 % spread of their world points along each axis) is at most :data:`OBJECT_EXTENT_M`.  A
  table-top scan that also sees the far walls stays ``object`` (the walls lie beyond its range and
  are left out, as intended);
* otherwise the scene is what is scanned: ``room`` when :data:`COVER` of the depths lie within the
  room preset's range (6 m), else ``large_room`` (15 m).  A walk around a room sees its walls
  within 2 m all the way round: their extent, not their depth, makes it a room.

The choice, the figures it was made from and the reason go into ``map.json`` (``preset_choice``).
"""

from __future__ import annotations

import logging
from dataclasses import asdict, dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from stereopath.host.mapping.depth import DepthConfig

if TYPE_CHECKING:
    from stereopath.device.core.rig import Rig
    from stereopath.host.mapping.inputs import MapKeyframe

log = logging.getLogger(__name__)

SAMPLES = 6  # keyframes surveyed
POINTS_PER_MAP = 5000  # valid pixels kept per surveyed keyframe (evenly), so each weighs the same
COVER = 0.9  # the share of the depths the room presets' range must hold
MIN_NEAR_SHARE = 0.3  # the least share of the depths within the object range for an object scan
OBJECT_EXTENT_M = 1.6  # the largest extent of the near surfaces for an object scan
SURVEY = DepthConfig(min_depth_m=0.25, max_depth_m=30.0, block_size=7, edge_max_rel_step=0.05, erode_px=1)
ORDER = ("object", "room", "large_room")  # smallest range first


@dataclass(frozen=True)
class PresetChoice:
    preset: str
    reason: str
    keyframes_surveyed: int
    depth_quantiles_m: dict[str, float]  # p10, p50, p90 of the pooled valid depths
    near_share: float  # share of the depths within the object preset's range
    near_extent_m: list[float]  # 5-95 % spread of the near surfaces' world points per axis

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)


def choose_from_survey(depths_m: np.ndarray, world_xyz: np.ndarray, max_depths_m: dict[str, float],
                       keyframes: int = 0) -> PresetChoice:
    """The preset for the surveyed depths (N,) and their world points (N, 3) (module doc; pure).
    ``max_depths_m[name]``: each preset's depth range end.  ``object`` when nothing is valid."""
    d = np.asarray(depths_m, float).reshape(-1)
    X = np.asarray(world_xyz, float).reshape(-1, 3)
    ok = np.isfinite(d) & (d > 0) & np.all(np.isfinite(X), axis=1)
    d, X = d[ok], X[ok]
    if not len(d):
        return PresetChoice("object", "no valid stereo depth in the surveyed keyframes: the default preset",
                            keyframes, {}, 0.0, [])
    q = {f"p{p}": round(float(np.quantile(d, p / 100)), 3) for p in (10, 50, 90)}
    near = d <= max_depths_m["object"]
    share = float(np.mean(near))
    extent = (np.quantile(X[near], 0.95, axis=0) - np.quantile(X[near], 0.05, axis=0)) if near.sum() >= 10 \
        else np.zeros(3)
    ext = [round(float(e), 3) for e in extent]
    if share >= MIN_NEAR_SHARE and max(ext) <= OBJECT_EXTENT_M:
        why = (f"{share:.0%} of the stereo depth lies within the object range ({max_depths_m['object']:.1f} m), "
               f"on surfaces {max(ext):.2f} m across at most (an object: up to {OBJECT_EXTENT_M:.1f} m)")
        return PresetChoice("object", why, keyframes, q, round(share, 3), ext)
    if share < MIN_NEAR_SHARE:
        first = f"only {share:.0%} of the stereo depth lies within the object range"
    else:
        first = f"the surfaces within the object range span {max(ext):.2f} m (more than an object's {OBJECT_EXTENT_M:.1f} m)"
    cover = float(np.quantile(d, COVER))
    name = "room" if cover <= max_depths_m["room"] else "large_room"
    why = (f"{first}; {COVER:.0%} of it lies within {cover:.2f} m (median {q['p50']:.2f} m), "
           f"inside the {name} preset's {max_depths_m[name]:.1f} m")
    if name == "large_room" and cover > max_depths_m[name]:
        why = f"{first}; {COVER:.0%} of it lies within {cover:.2f} m, beyond every preset: the largest"
    return PresetChoice(name, why, keyframes, q, round(share, 3), ext)


def survey(rig: Rig, keyframes: list[MapKeyframe], samples: int = SAMPLES) -> tuple[np.ndarray, np.ndarray, int]:
    """Depths and world points of ``samples`` keyframes spread over ``keyframes`` (``MapKeyframe``:
    ``load()``, ``T_world_cam0``), and the number surveyed."""
    from stereopath.device.errors import DatasetError
    from stereopath.host.mapping.depth import StereoDepth

    if not keyframes:
        return np.zeros(0), np.zeros((0, 3)), 0
    pick = np.unique(np.round(np.linspace(0, len(keyframes) - 1, min(samples, len(keyframes)))).astype(int))
    depth = StereoDepth(rig, SURVEY)
    depths, points, n = [], [], 0
    for i in pick:
        kf = keyframes[int(i)]
        try:
            left, right = kf.load()
        except DatasetError as exc:
            log.warning("depth survey: keyframe %d unreadable (%s)", kf.index, exc)
            continue
        dm = depth.compute(left, right)
        n += 1
        ys, xs = np.nonzero(dm.depth_m > 0)
        if len(xs) > POINTS_PER_MAP:
            keep = np.linspace(0, len(xs) - 1, POINTS_PER_MAP).astype(int)
            xs, ys = xs[keep], ys[keep]
        z = dm.depth_m[ys, xs].astype(float)
        K = dm.K
        X_rect = np.column_stack([(xs - K[0, 2]) / K[0, 0] * z, (ys - K[1, 2]) / K[1, 1] * z, z])
        T = np.asarray(kf.T_world_cam0, float) @ dm.T_cam0_rect
        depths.append(z)
        points.append(X_rect @ T[:3, :3].T + T[:3, 3])
    if not depths:
        return np.zeros(0), np.zeros((0, 3)), 0
    return np.concatenate(depths), np.vstack(points), n


def choose_preset(rig: Rig, keyframes: list[MapKeyframe], max_depths_m: dict[str, float]) -> PresetChoice:
    """The map preset for these keyframes (module doc), ``max_depths_m``: each preset's depth range end; logged."""
    d, X, n = survey(rig, keyframes)
    choice = choose_from_survey(d, X, max_depths_m, n)
    log.info("map preset auto -> %s: %s", choice.preset, choice.reason)
    return choice
