"""Dense stereo depth on rectified keyframes: semi-global matching with a left-right check.

:meth:`StereoDepth.compute`: rectify; OpenCV ``StereoSGBM`` on the pair and again on the pair turned by
180 degrees (``rot180(right)`` as reference: the right image's disparity), both padded so the first
columns are matched; keep a pixel when both agree within :data:`LR_MAX_DIFF_PX` and take their mean
(SGBM's fast mode aggregates top to bottom only, which makes slanted surfaces lag by about 0.1 px; the
turned pass lags the other way, so the mean cancels it); drop speckles, the black border of the rectified
image, optionally depth edges, and erode each region by ``erode_px``; ``depth = f * B / d`` within
``[min_depth_m, max_depth_m]``.  Depth is in the **rectified left camera frame**
(``T_world_rect = T_world_cam0 @ [R0^T | 0]``, :meth:`DepthMap.pose_world_rect`); disparities are float32
px with NaN where invalid, depths float32 metres with 0 where invalid (Open3D's convention).
"""

from __future__ import annotations

import dataclasses
import logging
import threading
from dataclasses import dataclass
from typing import Literal

import cv2
import numpy as np

from stereopath.device.core.config import check_ranges, ranged
from stereopath.device.errors import ConfigError, StereopathError
from stereopath.device.core.rig import Rectification, Rig

log = logging.getLogger(__name__)

SgbmMode = Literal["sgbm", "3way", "hh", "hh4"]
_MODES = {
    "sgbm": cv2.STEREO_SGBM_MODE_SGBM,
    "3way": cv2.STEREO_SGBM_MODE_SGBM_3WAY,
    "hh": cv2.STEREO_SGBM_MODE_HH,
    "hh4": cv2.STEREO_SGBM_MODE_HH4,
}
MAX_DISPARITY_PX = 512
UNIQUENESS_RATIO = 10  # SGBM: percent margin of the best cost over the second best
PRE_FILTER_CAP = 63  # SGBM: clip of the prefiltered image derivative
LR_MAX_DIFF_PX = 1.0  # left-right consistency tolerance (the mean of both disparities is kept)
SPECKLE_WINDOW_PX = 100  # blobs smaller than this are dropped
SPECKLE_RANGE_PX = 2.0  # disparity step that separates blobs
EDGE_DILATE_PX = 1  # how far the depth-edge mask is grown


@dataclass(frozen=True)
class DepthConfig:
    """Settings of :class:`StereoDepth` (see :data:`DEPTH_PRESETS` for object scans and rooms).

    ``max_disparity_px = 0`` derives the search range from ``min_depth_m``
    (``f * B / min_depth_m``, rounded up to a multiple of 16).
    """

    min_depth_m: float = ranged(0.25, 1e-3, 1e3)
    max_depth_m: float = ranged(2.0, 1e-3, 1e4)  # and above min_depth_m
    max_disparity_px: int = ranged(0, 0, MAX_DISPARITY_PX)
    block_size: int = ranged(3, 1, 15)  # odd
    mode: SgbmMode = "3way"
    p1_per_pixel: float = ranged(8.0, 0.0, 1e4)  # SGBM P1 = p1_per_pixel * channels * block_size^2
    p2_per_pixel: float = ranged(32.0, 0.0, 1e5)  # SGBM P2, the same way (P2 > P1)
    edge_max_rel_step: float = ranged(0.0, 0.0, 10.0)  # drop pixels next to a relative depth step above this; 0 = off
    erode_px: int = ranged(0, 0, 20)  # finally shrink every valid region by this many pixels (drops unreliable rims)

    def __post_init__(self) -> None:
        check_ranges(self)
        if self.max_depth_m <= self.min_depth_m:
            raise ConfigError(f"max_depth_m = {self.max_depth_m} must exceed min_depth_m = {self.min_depth_m}")
        if self.block_size % 2 == 0:
            raise ConfigError(f"block_size = {self.block_size} must be odd")
        if self.mode not in _MODES:
            raise ConfigError(f"mode = {self.mode!r} must be one of {sorted(_MODES)}")
        if self.p2_per_pixel <= self.p1_per_pixel:
            raise ConfigError(f"p2_per_pixel = {self.p2_per_pixel} must exceed p1_per_pixel = {self.p1_per_pixel}")

    def record(self) -> dict[str, float | int | str | bool]:
        """Every setting the depth uses, with the fixed ones (``map.json``'s ``config.depth``)."""
        return {"min_depth_m": self.min_depth_m, "max_depth_m": self.max_depth_m,
                "max_disparity_px": self.max_disparity_px, "block_size": self.block_size, "mode": self.mode,
                "p1_per_pixel": self.p1_per_pixel, "p2_per_pixel": self.p2_per_pixel,
                "uniqueness_ratio": UNIQUENESS_RATIO, "pre_filter_cap": PRE_FILTER_CAP,
                "lr_max_diff_px": LR_MAX_DIFF_PX, "lr_average": True, "speckle_window_px": SPECKLE_WINDOW_PX,
                "speckle_range_px": SPECKLE_RANGE_PX, "pad_left": True, "edge_max_rel_step": self.edge_max_rel_step,
                "edge_dilate_px": EDGE_DILATE_PX, "erode_px": self.erode_px}


DEPTH_PRESETS: dict[str, DepthConfig] = {
    # hand-held object scans: 0.25-2 m; depth edges and the rims of valid regions (where SGBM
    # smears foreground over background) are dropped
    "object": DepthConfig(min_depth_m=0.25, max_depth_m=2.0, block_size=5, edge_max_rel_step=0.03, erode_px=1),
    # rooms: 0.4-6 m; far points have coarse depth, so a larger block and less cleaning
    "room": DepthConfig(min_depth_m=0.4, max_depth_m=6.0, block_size=7, edge_max_rel_step=0.05, erode_px=1),
    # halls and large rooms: 0.5-15 m (stereo depth error grows with the square of the depth)
    "large_room": DepthConfig(min_depth_m=0.5, max_depth_m=15.0, block_size=7, edge_max_rel_step=0.05, erode_px=1),
}


def depth_preset(name: str) -> DepthConfig:
    """The named :data:`DEPTH_PRESETS` entry (ConfigError naming the choices otherwise)."""
    if name not in DEPTH_PRESETS:
        raise ConfigError(f"unknown depth preset {name!r}; known: {', '.join(sorted(DEPTH_PRESETS))}")
    return DEPTH_PRESETS[name]


@dataclass(frozen=True, eq=False)
class DepthMap:
    """Depth of one keyframe in the rectified left camera frame.

    ``depth_m`` (H, W) float32 metres along the rectified camera's z, 0 = invalid;
    ``disparity_px`` (H, W) float32, NaN = invalid; ``K`` 3x3 intrinsics of the rectified left
    camera; ``R_rect_cam0`` the rectifying rotation (rectified <- cam0); ``color`` (H, W, 3)
    uint8 RGB of the rectified left image when the source had colour, else None; ``gray`` the
    rectified left image (H, W) uint8.
    """

    depth_m: np.ndarray
    disparity_px: np.ndarray
    K: np.ndarray
    R_rect_cam0: np.ndarray
    gray: np.ndarray
    color: np.ndarray | None = None

    @property
    def valid(self) -> np.ndarray:
        return self.depth_m > 0

    @property
    def valid_fraction(self) -> float:
        return float(np.count_nonzero(self.depth_m > 0)) / max(1, self.depth_m.size)

    @property
    def size(self) -> tuple[int, int]:
        """(width, height)."""
        return int(self.depth_m.shape[1]), int(self.depth_m.shape[0])

    @property
    def T_cam0_rect(self) -> np.ndarray:
        """4x4 pose of the rectified camera in camera 0's frame (a pure rotation, ``R0^T``)."""
        T = np.eye(4)
        T[:3, :3] = self.R_rect_cam0.T
        return T

    def pose_world_rect(self, T_world_cam0: np.ndarray) -> np.ndarray:
        """``T_world_rect = T_world_cam0 @ T_cam0_rect``."""
        return np.asarray(T_world_cam0, float) @ self.T_cam0_rect

    def points_rect(self, stride: int = 1) -> np.ndarray:
        """(N, 3) valid points in the rectified camera frame (every ``stride``-th row and column)."""
        d = self.depth_m[::stride, ::stride]
        v, u = np.nonzero(d > 0)
        z = d[v, u].astype(float)
        u = u * stride
        v = v * stride
        K = self.K
        x = (u - K[0, 2]) * z / K[0, 0]
        y = (v - K[1, 2]) * z / K[1, 1]
        return np.stack([x, y, z], axis=1)

    def colors_rgb(self) -> np.ndarray:
        """(H, W, 3) uint8 RGB: the colour image, or the grey image replicated."""
        if self.color is not None:
            return self.color
        return np.repeat(self.gray[:, :, None], 3, axis=2)


# ---------------------------------------------------------------------------------------------
# pure disparity helpers (arrays in, arrays out)


def disparity_search_range(config: DepthConfig, f_px: float, baseline_m: float) -> int:
    """Number of disparities searched (a multiple of 16) for ``config`` on a rig with ``f * B``."""
    if config.max_disparity_px > 0:
        d = config.max_disparity_px
    else:
        d = f_px * baseline_m / config.min_depth_m
    n = int(np.ceil((d + 1) / 16.0)) * 16
    return int(min(max(n, 16), MAX_DISPARITY_PX))


def _as_gray(img: np.ndarray) -> np.ndarray:
    if img.ndim == 2:
        return img
    if img.ndim == 3 and img.shape[2] == 3:
        return cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    if img.ndim == 3 and img.shape[2] == 1:
        return img[:, :, 0]
    raise StereopathError(f"unsupported image shape {img.shape} (expected HxW grey or HxWx3 BGR)")


def make_matcher(config: DepthConfig, num_disparities: int, channels: int = 1) -> cv2.StereoSGBM:
    """An OpenCV SGBM matcher for ``config`` (its own speckle filter and LR check are off: we do both)."""
    bs = config.block_size
    return cv2.StereoSGBM_create(
        minDisparity=0,
        numDisparities=int(num_disparities),
        blockSize=bs,
        P1=int(round(config.p1_per_pixel * channels * bs * bs)),
        P2=int(round(config.p2_per_pixel * channels * bs * bs)),
        disp12MaxDiff=-1,
        uniquenessRatio=UNIQUENESS_RATIO,
        speckleWindowSize=0,
        speckleRange=0,
        preFilterCap=PRE_FILTER_CAP,
        mode=_MODES[config.mode],
    )


def _match(matcher: cv2.StereoSGBM, ref: np.ndarray, other: np.ndarray, pad: int) -> np.ndarray:
    """Float disparity of ``ref`` against ``other`` (NaN where SGBM gives none)."""
    if pad:
        ref = cv2.copyMakeBorder(ref, 0, 0, pad, 0, cv2.BORDER_REPLICATE)
        other = cv2.copyMakeBorder(other, 0, 0, pad, 0, cv2.BORDER_REPLICATE)
    raw = matcher.compute(ref, other)
    if pad:
        raw = raw[:, pad:]
    d = raw.astype(np.float32) * (1.0 / cv2.StereoMatcher_DISP_SCALE)
    d[raw < 0] = np.nan
    return d


def left_right_check(disp_left: np.ndarray, disp_right: np.ndarray, max_diff_px: float) -> np.ndarray:
    """Boolean mask of left pixels whose disparity the right image confirms.

    ``disp_right[y, x_r]`` is the disparity of right pixel ``x_r`` (its match is at ``x_r + d``
    in the left image).  A left pixel ``x`` with disparity ``d`` is consistent when
    ``|disp_left[y, x] - disp_right[y, round(x - d)]| <= max_diff_px``.
    """
    h, w = disp_left.shape
    finite = np.isfinite(disp_left)
    xr = np.rint(np.arange(w, dtype=np.float32)[None, :] - np.where(finite, disp_left, 0.0)).astype(np.int64)
    inside = finite & (xr >= 0) & (xr < w)
    dr = np.take_along_axis(disp_right, np.clip(xr, 0, w - 1), axis=1)
    with np.errstate(invalid="ignore"):
        agree = np.abs(dr - disp_left) <= max_diff_px
    return inside & agree


def filter_speckles(disp: np.ndarray, window_px: int, range_px: float) -> np.ndarray:
    """Drop connected blobs smaller than ``window_px`` (neighbours within ``range_px``); NaN = invalid."""
    if window_px <= 0:
        return disp
    fixed = np.where(np.isfinite(disp), np.rint(disp * 16.0), -16).astype(np.int16)
    cv2.filterSpeckles(fixed, -16, int(window_px), max(1, int(round(range_px * 16.0))))
    out = disp.copy()
    out[fixed < 0] = np.nan
    return out


def depth_edge_mask(depth: np.ndarray, max_rel_step: float, dilate_px: int = 1) -> np.ndarray:
    """Pixels next to a depth discontinuity (relative step to a 4-neighbour above ``max_rel_step``)."""
    z = depth.astype(np.float32)
    valid = z > 0
    edge = np.zeros(z.shape, bool)
    for axis in (0, 1):
        a = np.swapaxes(z, 0, axis)
        va = np.swapaxes(valid, 0, axis)
        both = va[1:] & va[:-1]
        with np.errstate(divide="ignore", invalid="ignore"):
            step = np.abs(a[1:] - a[:-1]) / np.minimum(a[1:], a[:-1])
        jump = both & (step > max_rel_step)
        e = np.swapaxes(edge, 0, axis)
        e[1:] |= jump
        e[:-1] |= jump
    if dilate_px > 0 and edge.any():
        k = np.ones((2 * dilate_px + 1, 2 * dilate_px + 1), np.uint8)
        edge = cv2.dilate(edge.astype(np.uint8), k).astype(bool)
    return edge


def fill_holes_background(disp: np.ndarray) -> np.ndarray:
    """Dense copy of ``disp``: every NaN takes the smaller (farther) of the nearest valid disparities
    to its left and right on the same row; rows without any stay 0.  For evaluations that need a
    dense map (Middlebury's convention); never used for fusion."""
    h, w = disp.shape
    valid = np.isfinite(disp)
    cols = np.arange(w)[None, :]
    left = np.maximum.accumulate(np.where(valid, cols, -1), axis=1)
    right = np.minimum.accumulate(np.where(valid, cols, w)[:, ::-1], axis=1)[:, ::-1]
    rows = np.arange(h)[:, None]
    lv = np.where(left >= 0, disp[rows, np.clip(left, 0, w - 1)], np.inf)
    rv = np.where(right < w, disp[rows, np.clip(right, 0, w - 1)], np.inf)
    fill = np.minimum(lv, rv)
    fill[~np.isfinite(fill)] = 0.0
    return np.where(valid, disp, fill).astype(np.float32)


def compute_disparity(left: np.ndarray, right: np.ndarray, config: DepthConfig, num_disparities: int,
                      matcher: cv2.StereoSGBM | None = None) -> np.ndarray:
    """Disparity (float32 px, NaN = invalid) of an already rectified pair, with LR check and speckles.

    ``left``/``right`` are HxW grey or HxWx3 images of the same size.
    """
    if left.shape != right.shape:
        raise StereopathError(f"left image is {left.shape} but right image is {right.shape}")
    if left.ndim not in (2, 3) or left.shape[0] < 8 or left.shape[1] < 8:
        raise StereopathError(f"unsupported image shape {left.shape}")
    channels = 1 if left.ndim == 2 else left.shape[2]
    m = matcher if matcher is not None else make_matcher(config, num_disparities, channels)
    pad = num_disparities  # so the left columns are matched too
    dl = _match(m, left, right, pad)
    # the right image's disparity from the pair turned by 180 degrees: mirrored like the plain
    # left-right trick, and also upside down, so SGM's top-to-bottom path runs the other way and its
    # lag on slanted surfaces has the opposite sign in the two maps; the mean of both cancels it
    dr = _match(m, np.ascontiguousarray(right[::-1, ::-1]), np.ascontiguousarray(left[::-1, ::-1]), pad)[::-1, ::-1]
    ok = left_right_check(dl, dr, LR_MAX_DIFF_PX)
    dl = 0.5 * (dl + sample_row_linear(dr, dl))
    dl[~ok] = np.nan
    return filter_speckles(dl, SPECKLE_WINDOW_PX, SPECKLE_RANGE_PX)


def sample_row_linear(disp_right: np.ndarray, disp_left: np.ndarray) -> np.ndarray:
    """``disp_right`` at ``x - disp_left`` on each row, linearly interpolated (nearest where a
    neighbour is missing; NaN outside the image or where ``disp_left`` is NaN)."""
    h, w = disp_left.shape
    xr = np.arange(w, dtype=np.float32)[None, :] - disp_left
    finite = np.isfinite(xr)
    xs = np.where(finite, xr, -1.0)
    x0 = np.floor(xs).astype(np.int64)
    f = (xs - x0).astype(np.float32)
    a = np.take_along_axis(disp_right, np.clip(x0, 0, w - 1), axis=1)
    b = np.take_along_axis(disp_right, np.clip(x0 + 1, 0, w - 1), axis=1)
    out = a * (1 - f) + b * f
    out = np.where(np.isfinite(out), out, np.where(f < 0.5, a, b))
    out[~finite | (xs < 0) | (xs > w - 1)] = np.nan
    return out.astype(np.float32)


def _valid_area(rect_map: tuple[np.ndarray, np.ndarray], size: tuple[int, int], margin: float = 1.0) -> np.ndarray:
    """Pixels of a rectified image that sample inside the source image."""
    mx, my = rect_map
    w, h = size
    return (mx >= margin) & (mx <= w - 1 - margin) & (my >= margin) & (my <= h - 1 - margin)


class StereoDepth:
    """Dense depth for one rig: rectification, matcher and masks are set up once and reused."""

    def __init__(self, rig: Rig, config: DepthConfig | None = None) -> None:
        self.rig = rig
        self.config = config or DepthConfig()
        self.rect: Rectification = rig.rectification()
        f, B = self.rect.f, self.rect.baseline_m
        if not (np.isfinite(f) and f > 0 and np.isfinite(B) and B > 0):
            raise StereopathError(f"rig {rig.name!r}: rectified focal {f} px / baseline {B} m unusable for depth")
        self.f_px, self.baseline_m = f, B
        self.num_disparities = disparity_search_range(self.config, f, B)
        self.valid_left = _valid_area(self.rect.maps0, rig.cam0.size)
        self.valid_right = _valid_area(self.rect.maps1, rig.cam1.size)
        self._matchers: dict[tuple[int, int], cv2.StereoSGBM] = {}
        log.debug("stereo depth: f=%.1f px, B=%.4f m, %d disparities (%.2f-%.2f m)", f, B, self.num_disparities,
                  self.config.min_depth_m, self.config.max_depth_m)

    def __getstate__(self) -> dict:
        """Picklable (a fleet task sends it to the processes computing its keyframes' depth): the
        OpenCV matchers are made again where they are used."""
        return {**self.__dict__, "_matchers": {}}

    @property
    def K(self) -> np.ndarray:
        return self.rect.K

    def _matcher(self, channels: int) -> cv2.StereoSGBM:
        # one per thread: a matcher keeps its work buffers between calls, so two keyframes computed side
        # by side (a thread spreader's pieces) each need their own
        key = (threading.get_ident(), channels)
        if key not in self._matchers:
            self._matchers[key] = make_matcher(self.config, self.num_disparities, channels)
        return self._matchers[key]

    def disparity_rectified(self, left_rect: np.ndarray, right_rect: np.ndarray) -> np.ndarray:
        """Disparity of a rectified pair, masked to the area both rectified images cover."""
        gl, gr = _as_gray(left_rect), _as_gray(right_rect)
        disp = compute_disparity(gl, gr, self.config, self.num_disparities, self._matcher(1))
        if disp.shape != self.valid_left.shape:
            raise StereopathError(f"image is {disp.shape[1]}x{disp.shape[0]} but the rig expects "
                                  f"{self.valid_left.shape[1]}x{self.valid_left.shape[0]}")
        disp[~self.valid_left] = np.nan
        h, w = disp.shape
        finite = np.isfinite(disp)
        xr = np.rint(np.arange(w)[None, :] - np.where(finite, disp, 0.0)).astype(np.int64)
        ok_r = np.take_along_axis(self.valid_right, np.clip(xr, 0, w - 1), axis=1) & (xr >= 0)
        disp[finite & ~ok_r] = np.nan
        return disp

    def depth_from_disparity(self, disp: np.ndarray) -> np.ndarray:
        """float32 depth (0 = invalid) from a disparity map, range-limited and edge-cleaned."""
        fB = self.f_px * self.baseline_m
        with np.errstate(divide="ignore", invalid="ignore"):
            z = np.where(np.isfinite(disp) & (disp > 0), fB / disp, 0.0).astype(np.float32)
        z[(z < self.config.min_depth_m) | (z > self.config.max_depth_m)] = 0.0
        if self.config.edge_max_rel_step > 0:
            z[depth_edge_mask(z, self.config.edge_max_rel_step, EDGE_DILATE_PX)] = 0.0
        if self.config.erode_px > 0:
            k = np.ones((2 * self.config.erode_px + 1,) * 2, np.uint8)
            z[cv2.erode((z > 0).astype(np.uint8), k, borderType=cv2.BORDER_CONSTANT, borderValue=0) == 0] = 0.0
        return z

    def compute(self, left: np.ndarray, right: np.ndarray) -> DepthMap:
        """Depth of a raw (unrectified) stereo pair: grey images, or BGR (then ``color`` is kept)."""
        if left.shape[:2] != (self.rig.cam0.size[1], self.rig.cam0.size[0]):
            raise StereopathError(f"left image is {left.shape[1]}x{left.shape[0]} but the rig's camera 0 is "
                                  f"{self.rig.cam0.size[0]}x{self.rig.cam0.size[1]}")
        if right.shape[:2] != (self.rig.cam1.size[1], self.rig.cam1.size[0]):
            raise StereopathError(f"right image is {right.shape[1]}x{right.shape[0]} but the rig's camera 1 is "
                                  f"{self.rig.cam1.size[0]}x{self.rig.cam1.size[1]}")
        lr, rr = self.rect.rectify(left, right)
        gray = _as_gray(lr)
        color = cv2.cvtColor(lr, cv2.COLOR_BGR2RGB) if lr.ndim == 3 and lr.shape[2] == 3 else None
        disp = self.disparity_rectified(gray, _as_gray(rr))
        depth = self.depth_from_disparity(disp)
        disp[depth <= 0] = np.nan
        return DepthMap(depth_m=depth, disparity_px=disp, K=self.rect.K.copy(),
                        R_rect_cam0=np.asarray(self.rect.R0, float).copy(), gray=gray, color=color)

    def compute_frame(self, frame) -> DepthMap:
        """:meth:`compute` on a :class:`stereopath.device.core.frames.StereoFrame`."""
        return self.compute(frame.left, frame.right)


def with_range(config: DepthConfig, min_depth_m: float | None = None, max_depth_m: float | None = None) -> DepthConfig:
    """``config`` with a different depth range (validated)."""
    changes = {}
    if min_depth_m is not None:
        changes["min_depth_m"] = float(min_depth_m)
    if max_depth_m is not None:
        changes["max_depth_m"] = float(max_depth_m)
    return dataclasses.replace(config, **changes)
