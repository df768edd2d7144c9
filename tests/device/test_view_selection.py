"""Two-resolution view selection (Morel & Yu's ASIFT acceleration) and matching on chosen view pairs."""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import pytest

from stereopath.device.core.features import FeatureConfig, ViewSelectionConfig, detect, get_preset
from stereopath.device.core.matching import MatchConfig, match
from stereopath.device.core.view_selection import candidate_pairs, coarse_config, coarse_pair_counts, detect_pair, match_pair, select_view_pairs, views_of
from stereopath.device.errors import ConfigError
from stereopath.host.evaluation.features import correct_mask


def tilted_plane_homography(w: int, h: int, deg: float, axis_deg: float) -> np.ndarray:
    """Homography of a fronto-parallel plane seen by a camera turned ``deg`` about an in-plane
    axis at ``axis_deg`` through the plane's centre, scaled so the warped image fills the frame."""
    f = float(w)
    K = np.array([[f, 0, w / 2], [0, f, h / 2], [0, 0, 1]])
    a = np.radians(axis_deg)
    R = cv2.Rodrigues(np.array([np.cos(a), np.sin(a), 0.0]) * np.radians(deg))[0]
    d = 2.0
    C = np.array([0.0, 0.0, d])
    H = K @ (R + np.outer(C - R @ C, [0.0, 0.0, 1.0]) / d) @ np.linalg.inv(K)
    c = cv2.perspectiveTransform(np.float32([[0, 0], [w, 0], [0, h], [w, h]]).reshape(-1, 1, 2), H).reshape(-1, 2)
    s = min(w / np.ptp(c[:, 0]), h / np.ptp(c[:, 1]))
    return np.array([[s, 0, -s * c[:, 0].min()], [0, s, -s * c[:, 1].min()], [0, 0, 1]]) @ H


@pytest.fixture(scope="module")
def cones(data_dir):
    p = data_dir / "middlebury" / "cones" / "im2.png"
    if not p.is_file():
        pytest.skip("Middlebury cones not found")
    return cv2.imread(str(p), cv2.IMREAD_GRAYSCALE)


def _correct(img1, img2, H, cfg, pairs) -> tuple[int, int]:
    f1 = detect(img1, cfg, views=None if pairs is None else views_of(pairs, 0))
    f2 = detect(img2, cfg, views=None if pairs is None else views_of(pairs, 1))
    m = match(f1, f2, MatchConfig(), only_pairs=pairs)
    p1, p2 = m.points(f1, f2)
    return int(correct_mask(p1, p2, H).sum()), len(f1) + len(f2)


@pytest.mark.slow
@pytest.mark.realdata
@pytest.mark.parametrize("deg, axis_deg", [(50.0, 90.0), (65.0, 30.0)])
def test_selection_keeps_the_correct_matches_of_all_view_pairs_on_a_tilted_plane(cones, deg, axis_deg):
    h, w = cones.shape
    H = tilted_plane_homography(w, h, deg, axis_deg)
    tilted = cv2.warpPerspective(cones, H, (w, h), flags=cv2.INTER_AREA)
    cfg = get_preset("fast")
    pairs = select_view_pairs(cones, tilted, cfg)
    assert pairs is not None and 0 < len(pairs) < len(candidate_pairs(cfg))
    selected, n_selected = _correct(cones, tilted, H, cfg, pairs)
    everything, n_all = _correct(cones, tilted, H, dataclasses.replace(cfg, coarse=ViewSelectionConfig(factor=0)), None)
    assert everything > 150
    assert selected >= 0.95 * everything  # the dropped view pairs held (almost) nothing of their own
    assert n_selected <= n_all


def test_a_squeezed_image_selects_the_view_pair_that_undoes_the_squeeze():
    rng = np.random.default_rng(3)
    img = np.zeros((300, 400), np.float32)
    for sigma in (1.5, 3.0, 6.0):
        img += cv2.GaussianBlur(rng.standard_normal(img.shape).astype(np.float32), (0, 0), sigma) * sigma
    img = cv2.normalize(img, None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)
    # the second image: the first seen at tilt 2.5 along x (squeezed to 0.4 of its width)
    squeezed = cv2.resize(cv2.GaussianBlur(img, (0, 0), sigmaX=1.6, sigmaY=0.01), (160, 300), interpolation=cv2.INTER_AREA)
    cfg = dataclasses.replace(get_preset("fast"), views=((1.0, 0.0), (2.0, 0.0), (2.0, 90.0)))
    counts = coarse_pair_counts(img, squeezed, cfg)
    assert max(counts, key=counts.get) == (1, 0)  # the first image squeezed along x vs the second as it is
    pairs = select_view_pairs(img, squeezed, cfg)
    # the second image squeezed across (along y) is the first up to scale: that pair undoes it too;
    # the first squeezed along y against the second (tilt 5 apart) does not
    assert (1, 0) in pairs and (0, 2) in pairs and (2, 0) not in pairs and len(pairs) < 9
    f1, f2, m = match_pair(img, squeezed, cfg)
    assert set(np.unique(f1.view)) == set(views_of(pairs, 0)) and set(np.unique(f2.view)) == set(views_of(pairs, 1))
    used = set(zip(f1.view[m.idx[:, 0]].tolist(), f2.view[m.idx[:, 1]].tolist()))
    assert used <= set(pairs) and len(m) > 50


def test_without_selection_every_view_is_computed(cones):
    small = cones[::2, ::2].copy()
    f1, f2, pairs = detect_pair(small, small, "sift")
    assert pairs is None and set(np.unique(f2.view)) == {0}
    f1, f2, pairs = detect_pair(small, small, dataclasses.replace(get_preset("fast"), coarse=ViewSelectionConfig(factor=0)))
    assert pairs is None and set(np.unique(f1.view)) == set(np.unique(f2.view)) == {0, 1, 2, 3}
    f1, f2, pairs = detect_pair(small, small, "fast_asym")  # asymmetric: the earlier image's original view only
    assert pairs is None and set(np.unique(f1.view)) == {0}
    assert candidate_pairs(get_preset("fast_asym")) == [(0, b) for b in range(5)]
    # a blank pair has no coarse matches at all: every view pair is kept rather than none
    blank = np.full((120, 160), 128, np.uint8)
    assert select_view_pairs(blank, blank, "fast") == candidate_pairs(get_preset("fast"))


def test_only_pairs_restricts_per_view_matching_and_is_ignored_without_view_labels():
    rng = np.random.default_rng(0)
    desc = rng.random((40, 128)).astype(np.float32)
    xy = rng.random((40, 2)).astype(np.float32) * 300
    from stereopath.device.core.features import Features

    view = np.repeat(np.arange(4, dtype=np.int16), 10)
    z = np.zeros(40, np.float32)
    f = Features(xy, desc, z + 5, z, z + 1, view)
    m = match(f, f, MatchConfig(), only_pairs=[(1, 1), (2, 2)])
    assert len(m) == 20 and set(f.view[m.idx[:, 0]].tolist()) == {1, 2}
    assert len(match(f, f, MatchConfig())) == 40
    assert len(match(f, f, MatchConfig(per_view=False), only_pairs=[(1, 1)])) == 40


def test_coarse_config_is_validated():
    assert FeatureConfig.from_mapping({"coarse": {"factor": 3, "min_share": 0.3, "nfeatures": 200}}).coarse.factor == 3
    with pytest.raises(ConfigError, match=r"coarse\.factor"):
        FeatureConfig(coarse=ViewSelectionConfig(factor=1))
    with pytest.raises(ConfigError, match=r"coarse\.min_share"):
        FeatureConfig.from_mapping({"coarse": {"min_share": 1.5}})
    assert get_preset("fast").coarse.factor == 3 and get_preset("fast_asym").coarse.factor == 0


def test_coarse_pass_caps_every_view_at_the_same_keypoint_density():
    fast = get_preset("fast")  # tilt-2 views: half the image's area, half the keypoints
    small = coarse_config(fast)
    assert small.coarse.factor == 0 and small.sift.nfeatures == fast.coarse.nfeatures
    assert small.sift.view_nfeatures == round(fast.coarse.nfeatures / 2)
    assert small.border_px == max(1, round(fast.border_px / fast.coarse.factor))
    paper = dataclasses.replace(get_preset("paper"), coarse=ViewSelectionConfig(factor=3, nfeatures=400))
    tilts = np.array([t for t, _ in paper.views[1:]])
    assert coarse_config(paper).sift.view_nfeatures == round(400 / np.exp(np.log(tilts).mean()))
    uncapped = coarse_config(dataclasses.replace(fast, coarse=dataclasses.replace(fast.coarse, nfeatures=0)))
    assert uncapped.sift.nfeatures == fast.sift.nfeatures and uncapped.sift.view_nfeatures == fast.sift.view_nfeatures
