"""Which simulated views of an image pair to compute: Morel & Yu's two-resolution ASIFT.

Pure compute, grey ``uint8`` images in.  Matching every view of one image against
every view of the other costs ``n_views^2`` view pairs, yet on a real viewpoint
change only the few view pairs whose simulated tilts undo it give many matches.
ASIFT's own acceleration (Morel & Yu, "ASIFT: A New Framework for Fully Affine
Invariant Image Comparison", SIAM J. Imaging Sciences 2009, section 4) finds them at
low resolution: both images reduced ``K`` times (``K = 3``, area averaging, so 1/9 of
the pixels), all views simulated and matched there, and only the view pairs that
matched well are then computed and matched at full resolution.

Here a view pair is kept when its low-resolution matches reach ``coarse.min_share`` of
the best pair's (and at least :data:`MIN_MATCHES`).  Each pair is counted on its own
(ratio test, mutual check, one match per location inside the pair), so a view pair
that finds the same places as another still counts: the full-resolution collapse
picks the better one later.  When no pair reaches the minimum (too little texture at
low resolution to tell) every pair is kept, as without selection.
"""

from __future__ import annotations

import dataclasses
from typing import Iterable

import cv2
import numpy as np

from stereopath.device.core.features import FeatureConfig, Features, detect, earlier_features, get_preset
from stereopath.device.core.matching import MatchConfig, Matches, collapse_duplicates, match, match_candidates

__all__ = ["MIN_MATCHES", "candidate_pairs", "coarse_config", "coarse_pair_counts", "select_view_pairs", "views_of", "detect_pair", "match_pair"]

MIN_MATCHES = 3  # a view pair with fewer low-resolution matches than this is noise


def candidate_pairs(cfg: FeatureConfig) -> list[tuple[int, int]]:
    """All view pairs a preset matches: every view against every view when symmetric,
    the earlier image's original view against each view of the later one when asymmetric."""
    n = cfg.n_views
    if cfg.pairing == "asymmetric":
        return [(0, b) for b in range(n)]
    return [(a, b) for a in range(n) for b in range(n)]


def views_of(pairs: Iterable[tuple[int, int]], side: int) -> list[int]:
    """The views of image ``side`` (0 = first, 1 = second) that ``pairs`` use, sorted."""
    return sorted({int(p[side]) for p in pairs})


def _reduce(image: np.ndarray, k: int) -> np.ndarray:
    h, w = image.shape[:2]
    return cv2.resize(image, (max(1, round(w / k)), max(1, round(h / k))), interpolation=cv2.INTER_AREA)


def coarse_config(cfg: FeatureConfig) -> FeatureConfig:
    """The preset as used on the reduced images: border scaled, keypoints capped at the same
    density in every view (a view at tilt ``t`` has ``1/t`` of the image's area; the mean tilt
    of the views when they differ)."""
    k = max(2, cfg.coarse.factor)
    cap = cfg.coarse.nfeatures
    tilt = float(np.exp(np.mean([np.log(t) for t, _ in cfg.views[1:]]))) if cfg.n_views > 1 else 1.0
    sift = dataclasses.replace(cfg.sift, nfeatures=cap or cfg.sift.nfeatures,
                               view_nfeatures=max(1, round(cap / tilt)) if cap else cfg.sift.view_nfeatures)
    return dataclasses.replace(cfg, coarse=dataclasses.replace(cfg.coarse, factor=0), sift=sift,
                               border_px=max(1, round(cfg.border_px / k)) if cfg.border_px else 0)


def coarse_pair_counts(img1: np.ndarray, img2: np.ndarray, cfg: FeatureConfig, match_cfg: MatchConfig = MatchConfig()) -> dict[tuple[int, int], int]:
    """Matches of every candidate view pair on the two images reduced ``cfg.coarse.factor`` times.

    Each pair is counted on its own: candidates that pass the ratio test and the mutual
    check, made one-to-one per location inside the pair.  The reduced original view keeps its
    ``cfg.coarse.nfeatures`` strongest keypoints (SIFT's own response ranking) and a view at tilt
    ``t`` (``1/t`` of the area) ``1/t`` of that, the same density everywhere, so that no view's
    counts are favoured by its size: the most repeatable keypoints are enough to rank the pairs,
    and descriptors are most of SIFT's cost.
    """
    k = max(2, cfg.coarse.factor)
    pairs = candidate_pairs(cfg)
    small = coarse_config(cfg)
    f1 = detect(_reduce(img1, k), small, views=views_of(pairs, 0))
    f2 = detect(_reduce(img2, k), small, views=views_of(pairs, 1))
    i, j, d, r = match_candidates(f1, f2, match_cfg, pairs)
    score = r if match_cfg.rank_by == "ratio" else d
    counts = {p: 0 for p in pairs}
    v1, v2 = f1.view[i], f2.view[j]
    for a, b in pairs:
        sel = np.nonzero((v1 == a) & (v2 == b))[0]
        if len(sel) > 1:
            keep = collapse_duplicates(f1.xy[i[sel]], f2.xy[j[sel]], score[sel], match_cfg.distinct_px)
            counts[(a, b)] = int(keep.sum())
        else:
            counts[(a, b)] = len(sel)
    return counts


def select_view_pairs(img1: np.ndarray, img2: np.ndarray, cfg: FeatureConfig | str, match_cfg: MatchConfig = MatchConfig()) -> list[tuple[int, int]] | None:
    """The view pairs worth computing at full resolution, or ``None`` when ``cfg`` selects none
    (``coarse.factor`` 0, a single view, or OpenCV's ``AffineFeature``): then all are used."""
    if isinstance(cfg, str):
        cfg = get_preset(cfg)
    if cfg.coarse.factor < 2 or cfg.backend != "views" or cfg.n_views == 1:
        return None
    counts = coarse_pair_counts(img1, img2, cfg, match_cfg)
    best = max(counts.values(), default=0)
    if best < MIN_MATCHES:
        return candidate_pairs(cfg)
    floor = max(MIN_MATCHES, cfg.coarse.min_share * best)
    return [p for p in candidate_pairs(cfg) if counts[p] >= floor]


def detect_pair(img1: np.ndarray, img2: np.ndarray, cfg: FeatureConfig | str, match_cfg: MatchConfig = MatchConfig()) -> tuple[Features, Features, list[tuple[int, int]] | None]:
    """Features of both images of a pair, computing only the views the pair needs.

    Returns ``(f1, f2, pairs)``; match them with ``match(f1, f2, match_cfg, only_pairs=pairs)``
    (see :func:`match_pair`).  Without view selection ``pairs`` is ``None`` and the images get
    what the preset gives them (the earlier one only its original view when asymmetric).
    """
    if isinstance(cfg, str):
        cfg = get_preset(cfg)
    pairs = select_view_pairs(img1, img2, cfg, match_cfg)
    if pairs is None:
        return earlier_features(img1, cfg), detect(img2, cfg), None
    return detect(img1, cfg, views=views_of(pairs, 0)), detect(img2, cfg, views=views_of(pairs, 1)), pairs


def match_pair(img1: np.ndarray, img2: np.ndarray, cfg: FeatureConfig | str, match_cfg: MatchConfig = MatchConfig()) -> tuple[Features, Features, Matches]:
    """:func:`detect_pair` then :func:`~stereopath.device.core.matching.match` on the chosen view pairs."""
    f1, f2, pairs = detect_pair(img1, img2, cfg, match_cfg)
    return f1, f2, match(f1, f2, match_cfg, only_pairs=pairs)
