"""Feature tracks over keyframes for offline bundle adjustment (drift-free observations).

Chained on-board KLT drifts smoothly in time, and bundle adjustment on such observations bends the path.
Here every keyframe gets fresh detections: :func:`stereo_features` (a feature preset's keypoints of the
left image, located in the right image by KLT seeded by a depth guess, checked forward-backward and on
the rectified rows, triangulated) and :func:`build_tracks` (each keyframe matched with the next
``window`` keyframes, guided by the estimated poses within ``radius_px``, joined by union-find; tracks
holding two keypoints of one keyframe dropped).  Each observation is an independent detection, so its
error does not grow with the track's age.  Pure computation apart from the images handed in.
See docs/architecture.md, "Reprocessing".
"""

from __future__ import annotations

import array
import dataclasses
import logging
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Protocol

import cv2
import numpy as np

from stereopath.device.core.config import check_range, check_ranges, ranged
from stereopath.device.core.features import gray
from stereopath.device.core.stereo import stereo_right, triangulate, undistort_px
from stereopath.device.core.scaled_klt import forward_backward
from stereopath.device.core.geometry import invert_pose
from stereopath.device.core.rig import Rig
from stereopath.device.errors import ConfigError
from stereopath.host.backend.observations import OBSERVATION_DTYPE, compact_observations
from stereopath.host.backend.parallel import ThreadSpreader, opencv_threads, parallel_map
from stereopath.host.backend.slanted_stereo import SlantedFit, refine_slanted

if TYPE_CHECKING:
    from stereopath.device.core.matching import MatchConfig

log = logging.getLogger(__name__)


MIN_TRACK_LENGTH = 2  # keyframes a track must span to be kept
SIZE_WEIGHTING_PX = 10.0  # keypoints larger than this get weight SIZE_WEIGHTING_PX / size
ALIGN_MAX_MOVE_PX = 1.5  # an aligned observation moved further than this is dropped (track_alignment)


@dataclass(frozen=True)
class StereoMatch:
    """How a left-image keypoint is found in the right image and triangulated (the KLT search
    :func:`stereopath.device.core.stereo.stereo_right` reads ``klt_window``, ``klt_levels``,
    ``fb_max_px`` and ``epipolar_max_dy_px``)."""

    klt_window: int = ranged(21, 3, 101)
    klt_levels: int = ranged(3, 0, 8)
    # pyramid levels above the image for KLT seeded from a known 3D point (frame refinement): the
    # seed is within a pixel or two, so the coarse levels only cost time
    seeded_klt_levels: int = ranged(1, 0, 8)
    fb_max_px: float = ranged(0.5, 0.0, 100.0)
    epipolar_max_dy_px: float = ranged(1.0, 0.0, 100.0)
    triangulation_max_px: float = ranged(1.0, 0.0, 100.0)
    min_depth_m: float = 0.1
    max_depth_m: float = 40.0
    guess_disparity_px: float = ranged(20.0, 0.1, 10_000.0)  # the right-image search starts here without a depth guess
    # the right-image match refined with a slanted window of this side (pixels; 0 = the KLT match as
    # is; by default the KLT window): unbiased on surfaces seen at a slant (slanted_stereo)
    slanted_window: int = 21

    def __post_init__(self) -> None:
        check_ranges(self, "tracks.stereo.")
        check_range("tracks.stereo.min_depth_m", self.min_depth_m, 1e-3, self.max_depth_m)
        if self.slanted_window and not 5 <= self.slanted_window <= 41:
            raise ConfigError(f"slanted_window must be 0 (off) or 5-41 pixels, got {self.slanted_window}")


@dataclass(frozen=True)
class PairMatch:
    """How the keypoints of two keyframes are matched and checked against their relative pose."""

    radius_px: float = ranged(16.0, 0.5, 500.0)  # guided matching: search radius around the predicted position
    ratio: float = ranged(0.8, 0.1, 1.0)
    prefilter_px: float = 3.0  # matches used to refine the pair's relative pose (deviation after the median offset)
    verify_px: float = 0.7  # accepted deviation from the position predicted with the refined pose ...
    # ... where the prediction is the segment swept by the point's depth over this many standard
    # deviations of the stereo disparity (moving towards a point turns its depth error into an image
    # shift along the epipolar line, which grows with the motion; 0 = the depth as measured).  The
    # standard deviation is the pair's own: the spread (MAD) of the matches' disparity disagreement
    verify_depth_sigmas: float = ranged(3.0, 0.0, 20.0)
    verify_disparity_px: float = 1.5  # accepted stereo disparity disagreement

    def __post_init__(self) -> None:
        check_ranges(self, "tracks.match.")


@dataclass(frozen=True)
class TrackConfig:
    feature_preset: str = "sift"  # stereopath.device.core.features preset of the keyframe detections
    original_view_only: bool = False  # only the preset's original view (its SIFT thresholds, no affine views)
    max_features: int = ranged(2000, 0, 1_000_000)  # strongest keypoints kept per keyframe (0 = all)
    window: int = ranged(20, 1, 1000)  # each keyframe is matched with later keyframes up to this far ...
    gaps: tuple[int, ...] = ()  # ... at these distances only (empty = every distance 1..window)
    # each track's observations aligned on its middle keyframe's window of this side (pixels; 0 = the
    # keypoints as detected; 21 = the KLT window in the 'aligned' preset) and dropped where that moves
    # them further than ALIGN_MAX_MOVE_PX (track_alignment)
    align_window: int = 0
    # offline keyframes (independent of the on-board estimator's real-time choice): the next keyframe
    # is the last frame from which the previous keyframe's stereo points are seen under a viewpoint
    # change (median parallax angle between the two camera centres) of at most keyframe_parallax_deg
    # and moved by at most keyframe_motion_px in the image (median), at least the next frame
    # (keyframe_parallax_deg = 0: the estimator's keyframes)
    keyframe_parallax_deg: float = ranged(2.5, 0.0, 90.0)
    keyframe_motion_px: float = ranged(100.0, 1.0, 100_000.0)
    stereo: StereoMatch = field(default_factory=StereoMatch)
    match: PairMatch = field(default_factory=PairMatch)

    def __post_init__(self) -> None:
        check_ranges(self, "tracks.")
        if self.align_window and not 5 <= self.align_window <= 41:
            raise ConfigError(f"align_window must be 0 (off) or 5-41 pixels, got {self.align_window}")


@dataclass
class KeyframeFeatures:
    """Stereo keypoints of one keyframe: left pixels (raw and undistorted), right (undistorted),
    3D point in the left camera, descriptors (as :class:`stereopath.device.core.features.Features`)."""

    feats: object  # stereopath.device.core.features.Features, the stereo subset
    uv0: np.ndarray  # (N, 2) undistorted left pixels
    uv1: np.ndarray  # (N, 2) undistorted right pixels
    X_cam: np.ndarray  # (N, 3) in the left camera

    def __len__(self) -> int:
        return len(self.uv0)

    def to_arrays(self) -> dict[str, np.ndarray]:
        f = self.feats
        return {"xy": f.xy, "desc": f.desc, "size": f.size, "angle": f.angle, "response": f.response,
                "view": f.view, "uv0": self.uv0, "uv1": self.uv1, "X_cam": self.X_cam}

    @staticmethod
    def from_arrays(a: dict[str, np.ndarray]) -> "KeyframeFeatures":
        from stereopath.device.core.features import Features

        f = Features(a["xy"], a["desc"], a["size"], a["angle"], a["response"], a["view"])
        return KeyframeFeatures(f, a["uv0"], a["uv1"], a["X_cam"])


def stereo_features(rig: Rig, left: np.ndarray, right: np.ndarray, cfg: TrackConfig,
                    depth_guess_m: float | None = None, workers: int = 1) -> KeyframeFeatures:
    """Keypoints of the left image with a stereo 3D point (see the module doc).

    ``workers > 1``: the affine views and then parts of the keypoints run side by side on that many
    threads, OpenCV's own pool at one thread meanwhile.  The same keypoints and points (each view and
    each point is computed on its own); measured on a keyframe of the simulated scan on two cores,
    less CPU and less time than one view at a time with OpenCV splitting each call."""
    from stereopath.device.core.features import detect, get_preset

    left, right = gray(left), gray(right)
    fc = get_preset(cfg.feature_preset)
    views = [0] if cfg.original_view_only else None
    if workers > 1:
        with opencv_threads(1):
            feats = detect(left, dataclasses.replace(fc, threads=workers), views=views)
    else:
        feats = detect(left, fc, views=views)
    feats = _strongest(feats, cfg.max_features)
    parts = np.array_split(np.arange(len(feats)), max(1, workers))
    got = ThreadSpreader(workers)(_stereo_part, (rig, left, right, feats.xy, cfg, depth_guess_m), parts)
    uv0, uv1, X, ok = (np.concatenate([g[i] for g in got]) for i in range(4))
    return KeyframeFeatures(feats.subset(ok), uv0[ok], uv1[ok], X[ok])


def _stereo_part(shared: tuple, idx: np.ndarray):
    """:func:`stereo_points` of the keypoints ``idx`` (a piece; ``shared`` = rig, images, pixels, config, depth)."""
    rig, left, right, xy, cfg, depth_guess_m = shared
    return stereo_points(rig, left, right, xy[idx], cfg, depth_guess_m)


def _strongest(feats, max_features: int):
    """The ``max_features`` keypoints of strongest response (0: all)."""
    if max_features and len(feats) > max_features:
        return feats.subset(np.argsort(-feats.response, kind="stable")[:max_features])
    return feats


def right_guess_at_depth(rig: Rig, uv0: np.ndarray, cfg: TrackConfig, depth_guess_m: float | None = None) -> np.ndarray:
    """Raw right pixels of undistorted left pixels ``uv0`` put at ``depth_guess_m`` (default: the depth of
    ``cfg.stereo.guess_disparity_px``): where a right-image search without a better guess starts."""
    K0, K1, d1 = rig.cam0.K, rig.cam1.K, rig.cam1.dist
    z0 = depth_guess_m or rig.rectification().f * rig.rectification().baseline_m / cfg.stereo.guess_disparity_px
    rays = np.column_stack([(uv0[:, 0] - K0[0, 2]) / K0[0, 0], (uv0[:, 1] - K0[1, 2]) / K0[1, 1], np.ones(len(uv0))])
    Xr = (rays * z0) @ rig.R.T + rig.T
    Xr[:, 2] = np.maximum(Xr[:, 2], 1e-3)
    return cv2.projectPoints(Xr.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), K1, d1)[0].reshape(-1, 2)


def stereo_points(rig: Rig, left: np.ndarray, right: np.ndarray, xy: np.ndarray, cfg: TrackConfig,
                  depth_guess_m: float | None = None, guess_right: np.ndarray | None = None
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Left pixels ``xy`` of grey images located in the right image and triangulated: undistorted
    left and right pixels, 3D points in the left camera, and the mask of the good ones.  The
    right-image search starts at ``depth_guess_m``, or at ``guess_right`` (raw right pixels of a
    match known within a pixel: the slanted window refines it directly, else KLT without its
    coarse levels)."""
    K0, d0, K1, d1 = rig.cam0.K, rig.cam0.dist, rig.cam1.K, rig.cam1.dist
    if len(xy) == 0:  # a blank image: no keypoint
        return np.zeros((0, 2)), np.zeros((0, 2)), np.zeros((0, 3)), np.zeros(0, bool)
    uv0 = undistort_px(xy, K0, d0)
    if guess_right is not None and cfg.stereo.slanted_window:
        xr, ok = np.asarray(guess_right, np.float64).reshape(-1, 2), np.ones(len(uv0), bool)
    elif guess_right is not None:
        xr, ok = stereo_right(rig, left, right, xy, guess_right, cfg.stereo, levels=cfg.stereo.seeded_klt_levels)
    else:
        xr, ok = stereo_right(rig, left, right, xy, right_guess_at_depth(rig, uv0, cfg, depth_guess_m), cfg.stereo)
    if cfg.stereo.slanted_window:
        idx = np.flatnonzero(ok)
        xr_ok, refined = refine_slanted(left, right, np.asarray(xy)[idx], xr[idx], 
                                         SlantedFit(half=cfg.stereo.slanted_window // 2))
        xr = xr.astype(np.float64)
        xr[idx] = xr_ok
        ok[idx] = refined
    uv1 = undistort_px(xr, K1, d1)
    X, err = triangulate(rig, uv0, uv1)
    ok &= (err < cfg.stereo.triangulation_max_px) & (X[:, 2] > cfg.stereo.min_depth_m) & (X[:, 2] < cfg.stereo.max_depth_m)
    return uv0, uv1, X, ok


class _Tracks:
    """Union-find over keypoints that never joins two keypoints of one keyframe into a track."""

    def __init__(self, kf_of: np.ndarray) -> None:
        # int32 arrays, not lists: 4 bytes a keypoint instead of a Python int object and a pointer (the
        # union-find over a long scan's millions of matched keypoints was the tracks stage's largest part)
        self.parent = array.array("i", np.arange(len(kf_of), dtype=np.int32).tobytes())
        self.kf_of = array.array("i", np.asarray(kf_of, dtype=np.int32).tobytes())
        self.kfs: dict[int, set[int]] = {}
        self.conflicts = 0

    def find(self, a: int) -> int:
        p = self.parent
        root = a
        while p[root] != root:
            root = p[root]
        while p[a] != root:
            p[a], a = root, p[a]
        return root

    def union_many(self, qa: list[int], qb: list[int]) -> None:
        find, parent, kfs, kf_of = self.find, self.parent, self.kfs, self.kf_of
        for a, b in zip(qa, qb):
            ra, rb = find(a), find(b)
            if ra == rb:
                continue
            sa = kfs.get(ra)
            if sa is None:
                sa = {kf_of[ra]}
            sb = kfs.get(rb)
            if sb is None:
                sb = {kf_of[rb]}
            if not sa.isdisjoint(sb):
                self.conflicts += 1
                continue
            if len(sa) < len(sb):
                ra, rb, sa, sb = rb, ra, sb, sa
            parent[rb] = ra
            sa |= sb
            kfs[ra] = sa
            kfs.pop(rb, None)


def _project(rig: Rig, X_cam: np.ndarray, min_depth: float) -> np.ndarray:
    """Left-camera pixels (with distortion) of camera points; NaN behind ``min_depth``."""
    K0 = rig.cam0.K
    pred = np.full((len(X_cam), 2), np.nan)
    front = X_cam[:, 2] > min_depth
    if not front.any():
        return pred
    if np.any(rig.cam0.dist):
        pred[front] = cv2.projectPoints(X_cam[front].reshape(-1, 1, 3), np.zeros(3), np.zeros(3), K0,
                                        rig.cam0.dist)[0].reshape(-1, 2)
    else:
        pred[front] = X_cam[front, :2] / X_cam[front, 2:] * [K0[0, 0], K0[1, 1]] + K0[:2, 2]
    return pred


def view_change(rig: Rig, kf: KeyframeFeatures, T_world_kf: np.ndarray, T_world_cam: np.ndarray,
                min_depth_m: float) -> tuple[float, float]:
    """How far a camera at ``T_world_cam`` sees a keyframe's stereo points from the keyframe's view:
    the median parallax angle (deg) between the rays from the two camera centres, and the median
    image motion (px; inf for points that end up behind the camera)."""
    if len(kf) == 0:
        return float("inf"), float("inf")
    T = invert_pose(T_world_cam) @ T_world_kf
    pred = _project(rig, kf.X_cam @ T[:3, :3].T + T[:3, 3], min_depth_m)
    d = np.linalg.norm(pred - kf.feats.xy, axis=1)
    X, c = kf.X_cam, invert_pose(T)[:3, 3]  # the camera's centre in the keyframe
    cos = np.einsum("ij,ij->i", X, X - c) / np.maximum(np.linalg.norm(X, axis=1) * np.linalg.norm(X - c, axis=1), 1e-12)
    angle = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
    return float(np.median(angle)), float(np.median(np.where(np.isfinite(d), d, np.inf)))


def _refine_relative_pose(rig: Rig, X_a: np.ndarray, xy_b: np.ndarray, T_b_a: np.ndarray) -> np.ndarray:
    """``T_b_a`` refined (LM from the guess) on matches of a's stereo points with b's pixels."""
    from stereopath.device.core.stereo import pose_to_rvec_tvec, rvec_tvec_to_pose

    if len(X_a) < 12:
        return T_b_a
    rvec, tvec = pose_to_rvec_tvec(T_b_a)
    rvec, tvec = cv2.solvePnPRefineLM(X_a.reshape(-1, 1, 3).astype(np.float64),
                                      xy_b.reshape(-1, 1, 2).astype(np.float64), rig.cam0.K, rig.cam0.dist,
                                      rvec, tvec)
    T = rvec_tvec_to_pose(rvec, tvec)
    return T if np.all(np.isfinite(T)) else T_b_a


def match_projected(rig: Rig, a: KeyframeFeatures, b: KeyframeFeatures, T_b_a: np.ndarray, radius_px: float,
                    mcfg: MatchConfig, min_depth_m: float) -> tuple[np.ndarray, np.ndarray]:
    """(M, 2) index pairs of keypoints of ``a`` and ``b`` matched by ``mcfg`` within ``radius_px`` of where a's stereo points
    fall in b with the relative pose ``T_b_a`` (points nearer than ``min_depth_m`` not searched for), and
    those predicted pixels (N, 2; NaN where not searched for)."""
    from stereopath.device.core.matching import match_guided

    pred = _project(rig, a.X_cam @ T_b_a[:3, :3].T + T_b_a[:3, 3], min_depth_m)
    return np.asarray(match_guided(a.feats, b.feats, pred, radius_px, mcfg).idx, np.int64).reshape(-1, 2), pred


def match_keyframes(rig: Rig, a: KeyframeFeatures, b: KeyframeFeatures, T_world_a: np.ndarray,
                    T_world_b: np.ndarray, cfg: TrackConfig) -> np.ndarray:
    """(M, 2) index pairs of keypoints of ``a`` and ``b`` that match near their predicted positions.

    a's stereo points are projected into b with the estimated relative pose and matched within
    ``radius_px``.  The relative pose is then refined on the matches that agree with the
    prediction within ``prefilter_px`` after removing their median offset, and a match is kept
    when it lies within ``verify_px`` of its position predicted with the refined pose and its
    stereo disparity agrees within ``verify_disparity_px``.
    """
    from stereopath.device.core.matching import MatchConfig

    if len(a) == 0 or len(b) == 0:
        return np.zeros((0, 2), np.int64)
    mcfg = MatchConfig(ratio=cfg.match.ratio, per_view=False)
    T_b_a = invert_pose(T_world_b) @ T_world_a
    idx, pred = match_projected(rig, a, b, T_b_a, cfg.match.radius_px, mcfg, cfg.stereo.min_depth_m)
    if len(idx) == 0:
        return idx
    xy_b = b.feats.xy[idx[:, 1]].astype(np.float64)
    res = xy_b - pred[idx[:, 0]]
    pre = np.linalg.norm(res - np.median(res, axis=0), axis=1) <= cfg.match.prefilter_px
    if pre.sum() >= 12:
        T_b_a = _refine_relative_pose(rig, a.X_cam[idx[pre, 0]], xy_b[pre], T_b_a)
    Xa = a.X_cam[idx[:, 0]]
    Xb = Xa @ T_b_a[:3, :3].T + T_b_a[:3, 3]
    pred = _project(rig, Xb, cfg.stereo.min_depth_m)
    res = xy_b - pred
    res = res - np.nanmedian(res, axis=0)
    disp_err = _disparity(rig, Xb) - _disparity(rig, b.X_cam[idx[:, 1]])
    if cfg.match.verify_depth_sigmas > 0 and pre.sum() >= 12:
        # a's and b's disparities are equally noisy: their difference has sqrt(2) sigma
        e = disp_err[pre]
        sigma = 1.4826 * np.median(np.abs(e - np.median(e))) / np.sqrt(2.0)
        res = _off_depth_segment(rig, Xa, T_b_a, pred, res, cfg.match.verify_depth_sigmas * sigma, cfg.stereo.min_depth_m)
    ok = np.linalg.norm(res, axis=1) <= cfg.match.verify_px
    ok &= np.abs(disp_err) <= cfg.match.verify_disparity_px
    return idx[ok]


def _off_depth_segment(rig: Rig, Xa: np.ndarray, T_b_a: np.ndarray, pred: np.ndarray, res: np.ndarray,
                       delta: float, min_depth_m: float) -> np.ndarray:
    """``res`` (b's pixel minus ``pred``) less its part explained by a's stereo depth uncertainty.

    a's point moves along a's viewing ray when its disparity changes by +-``delta`` px
    (the point scaled by d / (d -+ delta)); its image in b sweeps a short segment of the epipolar line
    around ``pred``.  Returned: the offset of b's pixel from that segment (zero along it inside)."""
    d = np.maximum(_disparity(rig, Xa), 1e-3)
    ends = []
    for dd in (-delta, delta):
        s = (d / np.maximum(d + dd, 1e-3))[:, None]  # nearer (+delta) or farther (-delta), far end capped
        s = np.where((d + dd)[:, None] > 1e-3, s, 1e3)
        ends.append(_project(rig, (Xa * s) @ T_b_a[:3, :3].T + T_b_a[:3, 3], min_depth_m) - pred)
    seg = ends[1] - ends[0]  # from the far end to the near end
    L2 = np.einsum("ij,ij->i", seg, seg)
    ok = np.isfinite(L2) & (L2 > 1e-12)
    tpar = np.zeros(len(res))
    tpar[ok] = np.einsum("ij,ij->i", res[ok] - ends[0][ok], seg[ok]) / L2[ok]
    tpar = np.clip(tpar, 0.0, 1.0)
    closest = np.where(ok[:, None], ends[0] + tpar[:, None] * seg, 0.0)
    return res - closest


def _disparity(rig: Rig, X_cam: np.ndarray) -> np.ndarray:
    """Horizontal disparity (px) of left-camera points: left u minus right u."""
    K0, K1 = rig.cam0.K, rig.cam1.K
    Xr = X_cam @ rig.R.T + rig.T
    ul = K0[0, 0] * X_cam[:, 0] / X_cam[:, 2] + K0[0, 2]
    ur = K1[0, 0] * Xr[:, 0] / Xr[:, 2] + K1[0, 2]
    return ul - ur


def _match_gap(shared: tuple, gap: int) -> list[np.ndarray]:
    """:func:`match_keyframes` of keyframe ``i`` with ``i + gap`` for the first ``first`` keyframes ``i`` of a
    batch (``shared``: rig, the batch's keyframes and the ``gap`` after them, their poses, config, first)."""
    rig, kfs, T, cfg, first = shared
    return [match_keyframes(rig, kfs[i], kfs[i + gap], T[i], T[i + gap], cfg)
            for i in range(min(first, len(kfs) - gap))]


# keyframes whose matches with the later keyframes are computed together: with the window after them,
# what the matching holds in memory at a time
MATCH_BATCH = 24


def match_all(rig: Rig, kfs: "KeyframeList", T_world_cam: np.ndarray, cfg: TrackConfig, gaps: list[int],
              progress=None) -> list[list[np.ndarray]]:
    """For each gap of ``gaps``, the matches (:func:`match_keyframes`) of every keyframe ``i`` with ``i + gap``.

    The keyframes are taken in batches of :data:`MATCH_BATCH` with the ``max(gaps)`` after them, so only
    those are held at a time (``kfs`` may load them on demand); within a batch the gaps' matchings are
    independent (:func:`parallel_map` may spread them).  ``progress(n)`` after each batch of ``n`` keyframes."""
    per_gap: list[list[np.ndarray]] = [[] for _ in gaps]
    n, reach = len(kfs), max(gaps, default=0)
    for s in range(0, n, MATCH_BATCH):
        e = min(n, s + MATCH_BATCH + reach)
        first = min(MATCH_BATCH, n - s)
        part = [kfs[k] for k in range(s, e)]
        for out, got in zip(per_gap, parallel_map(_match_gap, (rig, part, T_world_cam[s:e], cfg, first), gaps)):
            out.extend(got)
        if progress is not None:
            progress(first)
    return per_gap


class KeyframeList(Protocol):
    """Keyframes' stereo keypoints by index: a list, or a store that loads them on demand."""

    def __len__(self) -> int: ...

    def __getitem__(self, k: int) -> KeyframeFeatures: ...


@dataclass
class Tracks:
    """Feature tracks over keyframes (see :func:`build_tracks`)."""

    observations: np.ndarray  # compact rows (keyframe, point id, cam, u, v, weight), undistorted pixels (ba_common)
    points: dict[int, np.ndarray]  # point id -> world XYZ (mean of its stereo points)
    kf_ids: list[np.ndarray]  # per keyframe: point ids of its keypoints in tracks
    kf_xy: list[np.ndarray]  # per keyframe: their raw (distorted) left pixel positions
    stats: dict


def build_tracks(rig: Rig, kfs: KeyframeList, T_world_cam: np.ndarray, cfg: TrackConfig,
                 progress=None, align=None, sizes: list[int] | None = None) -> Tracks:
    """Join the keyframes' stereo keypoints into tracks (see the module doc).

    Observation rows are ``(keyframe, point id, cam, u, v, weight)`` in undistorted pixels, held
    compact (:func:`~stereopath.host.backend.ba_common.compact_observations`), one left and one right
    row per keypoint in a track; ``weight`` scales the residual (large
    keypoints are located less precisely).  ``progress(n)`` is called after each batch of ``n``
    keyframes matched (:func:`match_all`).  ``sizes``: the keyframes' keypoint counts when known
    (``kfs`` is then read in order, a batch at a time).
    """
    T_world_cam = np.asarray(T_world_cam, dtype=float).reshape(-1, 4, 4)
    sizes = [len(k) for k in kfs] if sizes is None else sizes
    offsets = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
    kf_of = np.repeat(np.arange(len(kfs), dtype=np.int32), np.diff(offsets))
    # nearer keyframe pairs first: their matches are the most reliable, later conflicting ones lose
    gaps = sorted(g for g in (cfg.gaps or range(1, cfg.window + 1)) if 1 <= g <= cfg.window)
    # matched a batch of keyframes at a time; joined below gap by gap, in order
    matched = match_all(rig, kfs, T_world_cam, cfg, gaps, progress)
    pairs = [(idx[:, 0] + offsets[i], idx[:, 1] + offsets[i + gap])
             for gap, per_i in zip(gaps, matched) for i, idx in enumerate(per_i)]
    del matched
    n_matches = sum(len(a) for a, _ in pairs)
    # the union-find runs over the keypoints in a match only (numbered in order), the rest stay alone
    used = np.unique(np.concatenate([np.concatenate(p) for p in pairs])) if pairs else np.zeros(0, np.int64)
    uf = _Tracks(kf_of[used])
    for a, b in pairs:
        uf.union_many(np.searchsorted(used, a).tolist(), np.searchsorted(used, b).tolist())
    del pairs
    n = int(offsets[-1])
    empty = [np.zeros(0, np.int32) for _ in range(len(kfs))]
    if n == 0:
        return Tracks(np.zeros(0, OBSERVATION_DTYPE), {}, empty, [np.zeros((0, 2), np.float32) for _ in range(len(kfs))],
                      {"keypoints": 0, "matches": 0, "tracks": 0, "observations": 0})
    find = uf.find
    roots = np.arange(n, dtype=np.int64)
    roots[used] = used[np.fromiter((find(i) for i in range(len(used))), dtype=np.int64, count=len(used))]
    conflicts = uf.conflicts
    del uf, find
    uniq_roots, inv, counts = np.unique(roots, return_inverse=True, return_counts=True)
    good = counts >= MIN_TRACK_LENGTH
    sel = good[inv]
    if align is not None:
        kfs, kept = align(kfs, kf_of, np.where(sel, inv, -1))
        sel &= kept
        counts = np.bincount(inv[sel], minlength=len(uniq_roots))
        good = counts >= MIN_TRACK_LENGTH
        sel &= good[inv]
    tid = np.cumsum(good) - 1  # track id of each good root
    rows: list[np.ndarray] = []
    kf_ids, kf_xy = [], []
    Xw_sum = np.zeros((int(good.sum()), 3))
    for k in range(len(kfs)):
        kf = kfs[k]
        s = slice(offsets[k], offsets[k + 1])
        m = sel[s]
        ids = tid[inv[s][m]]
        kf_ids.append(ids.astype(np.int32))
        kf_xy.append(kf.feats.xy[m].astype(np.float32))
        if not m.any():
            continue
        w = np.ones(len(ids))
        if SIZE_WEIGHTING_PX > 0:
            w = np.minimum(1.0, SIZE_WEIGHTING_PX / np.maximum(kf.feats.size[m].astype(float), 1e-3))
        kk = np.full(len(ids), k)
        rows.append(compact_observations(kk, ids, np.zeros(len(ids), np.uint8), kf.uv0[m], w))
        rows.append(compact_observations(kk, ids, np.ones(len(ids), np.uint8), kf.uv1[m], w))
        T = T_world_cam[k]
        np.add.at(Xw_sum, ids, kf.X_cam[m] @ T[:3, :3].T + T[:3, 3])
    obs = np.concatenate(rows) if rows else np.zeros(0, OBSERVATION_DTYPE)
    del rows
    n_per = np.bincount(tid[inv[sel]], minlength=len(Xw_sum))
    points = {int(i): Xw_sum[i] / n_per[i] for i in range(len(Xw_sum)) if n_per[i]}
    lengths = counts[good]
    stats = {"keyframes": len(kfs), "keypoints": n, "matches": n_matches, "tracks": int(good.sum()),
             "observations": int(len(obs)), "conflicting_matches": conflicts,
             "mean_track_length": float(lengths.mean()) if len(lengths) else 0.0,
             "max_track_length": int(lengths.max()) if len(lengths) else 0}
    log.info("tracks: %d keypoints, %d matches, %d tracks (mean length %.1f keyframes), %d observations",
             n, n_matches, stats["tracks"], stats["mean_track_length"], len(obs))
    return Tracks(obs, points, kf_ids, kf_xy, stats)


@dataclass(frozen=True)
class TrackedKeypoints:
    """A keyframe's left image, the raw (distorted) pixels its tracked points are followed from (their
    detections, or where their adjusted points project) and the points' ids."""

    left: np.ndarray
    xy: np.ndarray
    ids: np.ndarray


def frame_observations(rig: Rig, kf: TrackedKeypoints, points: dict[int, np.ndarray],
                       frame: tuple[np.ndarray, np.ndarray], T_world_cam_guess: np.ndarray,
                       cfg: TrackConfig, right_image: bool = True) -> np.ndarray:
    """Observations of a keyframe's tracked points in another (nearby) frame (its ``(left, right)``
    images), for motion-only refinement.

    Each keypoint is followed by one KLT step from the keyframe image straight into ``left``
    (seeded by projecting its point with ``T_world_cam_guess``; no chaining, so no drift) and, with
    ``right_image``, located in ``right`` the same way as at keyframes (without, ``right`` is not
    read).  Rows ``(0, point id, cam, u, v, 1)`` in undistorted pixels (the caller sets the pose index).
    """
    kf_left, kf_xy, kf_ids = gray(kf.left), kf.xy, kf.ids
    left = gray(frame[0])
    known = np.array([int(i) in points for i in kf_ids], dtype=bool) if len(kf_ids) else np.zeros(0, bool)
    if not known.any():
        return np.zeros((0, 6))
    ids = np.asarray(kf_ids)[known]
    xy = np.asarray(kf_xy, np.float32)[known]
    X = np.array([points[int(i)] for i in ids])
    T_cw = invert_pose(T_world_cam_guess)
    Xc = X @ T_cw[:3, :3].T + T_cw[:3, 3]
    front = Xc[:, 2] > cfg.stereo.min_depth_m
    ids, xy, Xc = ids[front], xy[front], Xc[front]
    if len(ids) == 0:
        return np.zeros((0, 6))
    K0, d0, K1, d1 = rig.cam0.K, rig.cam0.dist, rig.cam1.K, rig.cam1.dist
    guess = cv2.projectPoints(Xc.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), K0, d0)[0].reshape(-1, 2)
    lk = dict(winSize=(cfg.stereo.klt_window, cfg.stereo.klt_window), maxLevel=cfg.stereo.seeded_klt_levels,
              criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 40, 0.005))
    p1, both, fb = forward_backward(kf_left, left, xy, guess, lk, cfg.stereo.seeded_klt_levels)
    w, h = rig.cam0.size
    ok = both & (fb < cfg.stereo.fb_max_px)
    ok &= (p1[:, 0] >= 0) & (p1[:, 0] < w - 1) & (p1[:, 1] >= 0) & (p1[:, 1] < h - 1)
    ids, p1, Xc = ids[ok], p1[ok], Xc[ok]
    if len(ids) == 0:
        return np.zeros((0, 6))
    ul = undistort_px(p1, K0, d0)
    if not right_image:
        return np.column_stack([np.zeros(len(ids)), ids, np.zeros(len(ids)), ul, np.ones(len(ids))])
    right = gray(frame[1])
    Xr = Xc @ rig.R.T + rig.T
    Xr[:, 2] = np.maximum(Xr[:, 2], 1e-3)
    gr = cv2.projectPoints(Xr.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), K1, d1)[0].reshape(-1, 2)
    pr, okr = stereo_right(rig, left, right, p1, gr, cfg.stereo, levels=cfg.stereo.seeded_klt_levels)
    ur = undistort_px(pr[okr], K1, d1)
    rows = [np.column_stack([np.zeros(len(ids)), ids, np.zeros(len(ids)), ul, np.ones(len(ids))])]
    if okr.any():
        rows.append(np.column_stack([np.zeros(okr.sum()), ids[okr], np.ones(okr.sum()), ur, np.ones(okr.sum())]))
    return np.vstack(rows)
