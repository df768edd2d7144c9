"""Keypoints and descriptors: SIFT, OpenCV's full ASIFT, and the paper's modified ASIFT.

Pure compute: a grey ``uint8`` image in, a :class:`Features` set out.

The *modified ASIFT* of the reference paper runs SIFT on affine-simulated views
of an image.  A view is a pair ``(tilt t, longitude phi_deg)``: the image is
rotated by ``phi``, blurred along x with ``sigma = VIEW_BLUR_K * sqrt(t^2 - 1)``
(anti-aliasing, as in Morel & Yu's ASIFT) and squeezed along x by ``1/t``.  SIFT
runs on the view (with a mask that ignores the blank corners and a thin border)
and every keypoint is mapped back to the original image with the inverse affine
map.  ``t = 1 / cos(latitude)``.

The paper's scheme is asymmetric: SIFT on the *earlier* image, affine views of
the *later* one.  Each image is therefore detected once with the preset; its
original-view subset (:meth:`Features.original_view`) is what the next pair
uses as "SIFT on the earlier image", so no image is ever detected twice.

Presets (:data:`PRESETS`):

* ``sift``  - the original view only (plain SIFT);
* ``paper`` - latitudes 15/30/45/60 deg x longitudes 0..150 every 30 deg plus the
  original view (25 views), full resolution, unlimited keypoints;
* ``fast`` (also ``fast_sym``, its earlier name) - our real-time preset and the stereo
  estimator's keyframes: symmetric pairing (all views of both images are matched view
  against view), the original view plus tilt 2 (60 deg of latitude, where plain SIFT
  fails) at three longitudes, lower contrast and looser edge thresholds.  The symmetric
  pairing doubles the covered tilt directions (image 1 squeezed along phi = image 2
  stretched along phi); for one pair (``view_selection.detect_pair``) a low-resolution
  pass first picks the view pairs worth computing (``coarse.factor``);
* ``fast_asym`` - the same cost in the paper's asymmetric scheme: tilt 2 at four
  longitudes, views downscaled to 0.7, SIFT only on the earlier image;
* ``full``  - OpenCV's ``cv2.AffineFeature`` with its default view parameters (the
  reference; its keypoints carry ``view = -1`` since OpenCV does not report the view).

ASIFT is covered by US patent 8687920; ``cv2.AffineFeature`` is OpenCV's own
implementation and the view simulation here is written for this project.
"""

from __future__ import annotations

import logging
import math
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Literal, Mapping

import cv2
import numpy as np

from stereopath.device.core.affine_views import simulate_view, view_transform
from stereopath.device.core.config import check_range, check_ranges, from_mapping, ranged
from stereopath.device.errors import ConfigError

log = logging.getLogger(__name__)

__all__ = [
    "Features",
    "FeatureConfig",
    "SiftConfig",
    "ViewSelectionConfig",
    "AffineFeatureConfig",
    "PRESETS",
    "get_preset",
    "gray",
    "detect",
    "earlier_features",
    "earlier_subset",
    "view_transform",
    "simulate_view",
    "tilt_of_latitude",
]

ORIGINAL_VIEW = (1.0, 0.0)


def tilt_of_latitude(latitude_deg: float) -> float:
    """ASIFT tilt ``t = 1 / cos(latitude)``."""
    return 1.0 / math.cos(math.radians(latitude_deg))


# --------------------------------------------------------------------------- features


@dataclass(frozen=True, eq=False)
class Features:
    """Keypoints of one image, all in that image's pixel coordinates.

    ``view`` is the index of the simulated view a keypoint came from in the
    :class:`FeatureConfig` that produced it (0 = the original image, -1 = unknown,
    e.g. ``cv2.AffineFeature``).
    """

    xy: np.ndarray  # (N, 2) float32, pixels
    desc: np.ndarray  # (N, 128) float32
    size: np.ndarray  # (N,) float32, keypoint diameter in original pixels
    angle: np.ndarray  # (N,) float32, degrees, in original image coordinates
    response: np.ndarray  # (N,) float32
    view: np.ndarray  # (N,) int16

    def __len__(self) -> int:
        return int(self.xy.shape[0])

    @staticmethod
    def empty(dim: int = 128) -> "Features":
        z = np.zeros(0, np.float32)
        return Features(np.zeros((0, 2), np.float32), np.zeros((0, dim), np.float32), z, z.copy(), z.copy(), np.zeros(0, np.int16))

    def subset(self, index: np.ndarray) -> "Features":
        """Features selected by a boolean mask or an integer index array."""
        index = np.asarray(index)
        return Features(self.xy[index], self.desc[index], self.size[index], self.angle[index], self.response[index], self.view[index])

    def original_view(self) -> "Features":
        """The keypoints of the original (untilted) view: plain SIFT on this image."""
        return self.subset(self.view == 0)

    @staticmethod
    def concat(parts: list["Features"]) -> "Features":
        parts = [p for p in parts if len(p)]
        if not parts:
            return Features.empty()
        return Features(
            np.concatenate([p.xy for p in parts]),
            np.concatenate([p.desc for p in parts]),
            np.concatenate([p.size for p in parts]),
            np.concatenate([p.angle for p in parts]),
            np.concatenate([p.response for p in parts]),
            np.concatenate([p.view for p in parts]),
        )


# --------------------------------------------------------------------------- configuration


# SIFT's scale space as OpenCV's defaults; nobody tunes them per preset.
SIFT_SIGMA = 1.6
SIFT_OCTAVE_LAYERS = 3
SIFT_PRECISE_UPSCALE = True  # OpenCV's unbiased 2x upsampling (no 0.25 px shift)
VIEW_BLUR_K = 0.8  # anti-aliasing blur of a simulated view: sigma = VIEW_BLUR_K * sqrt(t^2 - 1)
COMPACT_VIEWS = True  # oblique views turned to the smallest canvas (SIFT is rotation invariant)


@dataclass(frozen=True)
class SiftConfig:
    """SIFT's keypoint caps and thresholds: ``nfeatures`` caps the original view and
    ``view_nfeatures`` each simulated view (0 = unlimited)."""

    nfeatures: int = ranged(0, 0, 1_000_000)
    view_nfeatures: int = ranged(0, 0, 1_000_000)
    contrast_threshold: float = ranged(0.04, 1e-4, 1.0)
    edge_threshold: float = ranged(10.0, 1.0, 100.0)

    def __post_init__(self) -> None:
        check_ranges(self, "sift.")


@dataclass(frozen=True)
class ViewSelectionConfig:
    """Pair-level view selection (Morel & Yu's two-resolution ASIFT, view_selection.py): match all
    views of the two images reduced ``factor`` times, then compute and match at full resolution
    only the view pairs with >= ``min_share`` of the best pair's matches; the reduced original
    view keeps its ``nfeatures`` strongest keypoints, a view at tilt t 1/t of that (the same
    density; 0 = as at full resolution).  ``factor`` 0 = off.  detect() on one image always
    computes every view."""

    factor: int = ranged(0, 0, 16)
    min_share: float = ranged(0.2, 0.0, 1.0)
    nfeatures: int = ranged(400, 0, 1_000_000)

    def __post_init__(self) -> None:
        check_ranges(self, "coarse.")
        if self.factor == 1:
            raise ConfigError("coarse.factor must be 0 (no view selection) or >= 2, got 1")


@dataclass(frozen=True)
class AffineFeatureConfig:
    """``cv2.AffineFeature`` parameters (backend "cv2_affine" only); OpenCV's defaults."""

    max_tilt: int = ranged(5, 1, 10)
    min_tilt: int = 0
    tilt_step: float = ranged(1.4142135623730951, 1.01, 4.0)
    rotate_step_base: float = ranged(72.0, 1.0, 180.0)

    def __post_init__(self) -> None:
        check_ranges(self, "affine.")
        check_range("affine.min_tilt", self.min_tilt, 0, self.max_tilt - 1)


@dataclass(frozen=True)
class FeatureConfig:
    """How to detect features.  Build from a mapping with ``stereopath.device.core.config.from_mapping``.

    ``views`` lists ``(tilt, longitude_deg)`` pairs; the first one must be the
    original view ``(1.0, 0.0)``.  Simulated views are computed on the image resized
    by ``view_scale``, the original view on the image resized by ``original_scale``
    (SIFT doubles it first).
    """

    views: tuple[tuple[float, float], ...] = (ORIGINAL_VIEW,)
    backend: Literal["views", "cv2_affine"] = "views"
    # How a pair (earlier, later) is matched: "asymmetric" is the paper's scheme
    # (original view of the earlier image vs all views of the later one);
    # "symmetric" matches all views of both (each image's views are computed
    # once anyway when it is the later image, so in a sequence this costs only
    # matching time).
    pairing: Literal["asymmetric", "symmetric"] = "asymmetric"
    sift: SiftConfig = SiftConfig()
    view_scale: float = ranged(1.0, 0.1, 2.0)
    original_scale: float = ranged(1.0, 0.1, 1.0)
    border_px: int = ranged(4, 0, 100)
    threads: int = ranged(1, 1, 64)  # views on a thread pool; SIFT is already parallel inside OpenCV, so 1 was fastest on 2 cores
    coarse: ViewSelectionConfig = ViewSelectionConfig()
    affine: AffineFeatureConfig = AffineFeatureConfig()

    def __post_init__(self) -> None:
        if not self.views:
            raise ConfigError("views must list at least the original view (1.0, 0.0)")
        if tuple(map(float, self.views[0])) != ORIGINAL_VIEW:
            raise ConfigError(f"views[0] must be the original view (1.0, 0.0), got {self.views[0]!r}")
        for i, v in enumerate(self.views):
            if len(v) != 2:
                raise ConfigError(f"views[{i}] must be a (tilt, longitude_deg) pair, got {v!r}")
            check_range(f"views[{i}].tilt", float(v[0]), 1.0, 16.0)
            check_range(f"views[{i}].longitude_deg", float(v[1]), -360.0, 360.0)
        check_ranges(self)

    @staticmethod
    def from_mapping(mapping: Mapping[str, object]) -> "FeatureConfig":
        return from_mapping(FeatureConfig, mapping)

    @property
    def n_views(self) -> int:
        return len(self.views)


def _paper_views() -> tuple[tuple[float, float], ...]:
    views = [ORIGINAL_VIEW]
    for lat in (15.0, 30.0, 45.0, 60.0):
        t = round(tilt_of_latitude(lat), 6)
        for phi in range(0, 180, 30):
            views.append((t, float(phi)))
    return tuple(views)


_FAST = FeatureConfig(
    views=(ORIGINAL_VIEW, (2.0, 0.0), (2.0, 60.0), (2.0, 120.0)),
    pairing="symmetric",
    sift=SiftConfig(contrast_threshold=0.015, edge_threshold=20.0),
    coarse=ViewSelectionConfig(factor=3),
)

PRESETS: dict[str, FeatureConfig] = {
    "sift": FeatureConfig(pairing="symmetric"),
    "paper": FeatureConfig(views=_paper_views()),
    # the real-time preset (and the stereo estimator's keyframes): symmetric, tilt 2 at three longitudes
    "fast": _FAST,
    "fast_sym": _FAST,  # its earlier name
    # the paper's asymmetric scheme at real-time cost (SIFT on the earlier image, four tilted views at 0.7)
    "fast_asym": FeatureConfig(
        views=(ORIGINAL_VIEW, (2.0, 0.0), (2.0, 45.0), (2.0, 90.0), (2.0, 135.0)),
        view_scale=0.7,
        sift=SiftConfig(contrast_threshold=0.02, edge_threshold=20.0),
    ),
    "full": FeatureConfig(backend="cv2_affine", pairing="symmetric"),
    # the on-board estimator's keyframes: SIFT on the image at 0.7 (its doubled first octave at 1.4x; ~half
    # the cost), two tilted views at half scale
    "onboard": FeatureConfig(
        views=(ORIGINAL_VIEW, (2.0, 0.0), (2.0, 90.0)),
        view_scale=0.5,
        original_scale=0.7,
    ),
}

PRESET_HELP: dict[str, str] = {
    "sift": "plain SIFT (original view only)",
    "paper": "the paper's modified ASIFT: latitudes 15/30/45/60 x longitudes 0..150 step 30 + original (25 views)",
    "fast": "real time, symmetric: original + tilt 2 at longitudes 0/60/120 on both images, view pairs picked at 1/3 resolution",
    "fast_sym": "the earlier name of fast",
    "fast_asym": "paper's asymmetric scheme, real time: original + tilt 2 at longitudes 0/45/90/135, views at 0.7 scale",
    "full": "OpenCV cv2.AffineFeature(SIFT) with its default view parameters (reference ASIFT)",
    "onboard": "the stereo estimator's keyframes: original at 0.7 scale + tilt 2 at longitudes 0/90 at 0.5 scale",
}


def earlier_subset(feats: Features, cfg: FeatureConfig | str) -> Features:
    """The part of an already detected image used as the *earlier* image of a pair.

    Asymmetric pairing (the paper): the original view (plain SIFT); symmetric: all.
    """
    if isinstance(cfg, str):
        cfg = get_preset(cfg)
    if cfg.backend == "views" and cfg.pairing == "asymmetric":
        return feats.original_view()
    return feats


def earlier_features(image: np.ndarray, cfg: FeatureConfig | str) -> Features:
    """Detect only what the earlier image of a pair needs (the original view when asymmetric)."""
    if isinstance(cfg, str):
        cfg = get_preset(cfg)
    if cfg.backend == "views" and cfg.pairing == "asymmetric":
        return detect(image, cfg, views=[0])
    return detect(image, cfg)


def get_preset(name: str) -> FeatureConfig:
    """The preset called ``name``; ConfigError lists the known ones otherwise."""
    try:
        return PRESETS[name]
    except KeyError:
        raise ConfigError(f"unknown feature preset {name!r}; known: {', '.join(PRESETS)}") from None


def gray(image: np.ndarray) -> np.ndarray:
    """A single-channel view of ``image``: BGR colour is converted, grey is returned as is."""
    if image.ndim == 3 and image.shape[2] == 3:
        return cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    if image.ndim == 3 and image.shape[2] == 1:
        return image[:, :, 0]
    return image


def _keypoints_to_arrays(kps, desc, view_index: int, M: np.ndarray | None, n_dim: int = 128) -> Features:
    if not kps:
        return Features.empty(n_dim)
    xy = np.array([k.pt for k in kps], np.float64)
    size = np.array([k.size for k in kps], np.float64)
    angle = np.array([k.angle for k in kps], np.float64)
    resp = np.array([k.response for k in kps], np.float32)
    if M is not None:
        Minv = cv2.invertAffineTransform(M)
        L = Minv[:, :2]
        xy = xy @ L.T + Minv[:, 2]
        size = size * math.sqrt(abs(np.linalg.det(L)))
        # Orientation: map the unit direction of each keypoint back (SIFT angles are
        # measured with y down, as on screen).
        a = np.radians(angle)
        d = np.stack([np.cos(a), np.sin(a)], axis=1) @ L.T
        angle = np.degrees(np.arctan2(d[:, 1], d[:, 0])) % 360.0
    return Features(
        xy.astype(np.float32),
        np.asarray(desc, np.float32).reshape(len(kps), -1),
        size.astype(np.float32),
        angle.astype(np.float32),
        resp,
        np.full(len(kps), view_index, np.int16),
    )


def _make_sift(cfg: FeatureConfig, view: bool) -> cv2.SIFT:
    s = cfg.sift
    n = s.view_nfeatures if view else s.nfeatures
    return cv2.SIFT_create(n, SIFT_OCTAVE_LAYERS, s.contrast_threshold, s.edge_threshold, SIFT_SIGMA,
                           enable_precise_upscale=SIFT_PRECISE_UPSCALE)


def _check_image(image: np.ndarray) -> np.ndarray:
    image = np.asarray(image)
    if image.ndim == 3 and image.shape[2] == 1:
        image = image[:, :, 0]
    if image.ndim != 2:
        raise ConfigError(f"detect() needs a single-channel image, got shape {image.shape}")
    if image.dtype != np.uint8:
        raise ConfigError(f"detect() needs a uint8 image, got {image.dtype}")
    return np.ascontiguousarray(image)


def _detect_original(image: np.ndarray, cfg: FeatureConfig) -> Features:
    """SIFT on the original view at ``cfg.original_scale``, keypoints in original pixels."""
    h, w = image.shape
    s, M = cfg.original_scale, None
    if s != 1.0:
        image = cv2.resize(image, (max(1, round(w * s)), max(1, round(h * s))), interpolation=cv2.INTER_AREA)
        sx, sy = image.shape[1] / w, image.shape[0] / h
        M = np.array([[sx, 0.0, 0.5 * sx - 0.5], [0.0, sy, 0.5 * sy - 0.5]])  # pixel centres kept
        h, w = image.shape
    b = max(1, int(round(cfg.border_px * s))) if cfg.border_px > 0 else 0
    mask = None if b == 0 else cv2.rectangle(np.zeros((h, w), np.uint8), (b, b), (w - 1 - b, h - 1 - b), 255, -1)
    kps, desc = _make_sift(cfg, view=False).detectAndCompute(image, mask)
    return _keypoints_to_arrays(kps, desc, 0, M)


def _detect_view(image: np.ndarray, small: np.ndarray, cfg: FeatureConfig, index: int, scale: float) -> Features:
    tilt, phi = map(float, cfg.views[index])
    if index == 0:
        return _detect_original(image, cfg)
    view, mask, M = simulate_view(small, tilt, phi, 1.0, VIEW_BLUR_K, max(1, int(round(cfg.border_px * scale))), COMPACT_VIEWS)
    if scale != 1.0:
        # original -> small (pixel centres: x_s = scale * x + 0.5 * scale - 0.5) -> view
        off = 0.5 * scale - 0.5
        M = np.hstack([M[:, :2] * scale, (M[:, 2] + M[:, :2].sum(axis=1) * off)[:, None]])
    sift = _make_sift(cfg, view=True)
    kps, desc = sift.detectAndCompute(view, mask)
    return _keypoints_to_arrays(kps, desc, index, M)


def detect(image: np.ndarray, cfg: FeatureConfig | str = "sift", views: list[int] | None = None) -> Features:
    """Detect and describe keypoints of a grey uint8 image with ``cfg`` (or a preset name).

    ``views`` restricts detection to those view indices (e.g. ``[0]`` for the
    plain-SIFT half of the paper's asymmetric scheme); default all.
    """
    if isinstance(cfg, str):
        cfg = get_preset(cfg)
    image = _check_image(image)
    if image.size == 0:
        return Features.empty()
    if cfg.backend == "cv2_affine":
        return _detect_cv2_affine(image, cfg)
    indices = list(range(cfg.n_views)) if views is None else list(views)
    for i in indices:
        if not 0 <= i < cfg.n_views:
            raise ConfigError(f"view index {i} out of range for a configuration with {cfg.n_views} views")
    scale = cfg.view_scale
    small = image
    if any(i > 0 for i in indices) and scale != 1.0:
        h, w = image.shape
        small = cv2.resize(image, (max(1, int(round(w * scale))), max(1, int(round(h * scale)))), interpolation=cv2.INTER_AREA)
        scale = small.shape[1] / w  # the scale actually used
    if cfg.threads > 1 and len(indices) > 1:
        # OpenCV releases the GIL, so views run in parallel.  The original view (the
        # largest) goes first so the pool stays balanced; results keep view order.
        with ThreadPoolExecutor(max_workers=cfg.threads) as pool:
            futures = {i: pool.submit(_detect_view, image, small, cfg, i, scale) for i in sorted(indices, key=lambda i: i != 0)}
            parts = [futures[i].result() for i in indices]
    else:
        parts = [_detect_view(image, small, cfg, i, scale) for i in indices]
    feats = Features.concat(parts)
    log.debug("detect: %d keypoints from %d views", len(feats), len(indices))
    return feats


def _detect_cv2_affine(image: np.ndarray, cfg: FeatureConfig) -> Features:
    sift = _make_sift(cfg, view=False)
    a = cfg.affine
    af = cv2.AffineFeature_create(sift, a.max_tilt, a.min_tilt, a.tilt_step, a.rotate_step_base)
    kps, desc = af.detectAndCompute(image, None)
    feats = _keypoints_to_arrays(kps, desc, -1, None)
    return Features(feats.xy, feats.desc, feats.size, feats.angle, feats.response, np.full(len(feats), -1, np.int16))
