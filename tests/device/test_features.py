"""Feature detection: configuration, presets, affine view simulation and keypoint back-mapping."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from stereopath.device.core.config import from_mapping
from stereopath.device.errors import ConfigError
from stereopath.device.core.features import (
    PRESETS,
    AffineFeatureConfig,
    FeatureConfig,
    Features,
    detect,
    earlier_features,
    earlier_subset,
    get_preset,
    simulate_view,
    tilt_of_latitude,
    view_transform,
)


def texture(w: int = 320, h: int = 240, seed: int = 0) -> np.ndarray:
    """Deterministic blob texture with structure at several scales."""
    rng = np.random.default_rng(seed)
    img = np.zeros((h, w), np.float32)
    for sigma in (1.5, 3.0, 6.0):
        noise = rng.standard_normal((h, w)).astype(np.float32)
        img += cv2.GaussianBlur(noise, (0, 0), sigma) * sigma
    img = (img - img.min()) / (img.max() - img.min()) * 255.0
    return img.astype(np.uint8)


# --------------------------------------------------------------------------- configuration


def test_paper_preset_has_25_views_with_the_papers_tilts_and_longitudes():
    cfg = PRESETS["paper"]
    assert cfg.n_views == 25
    assert cfg.views[0] == (1.0, 0.0)
    tilts = sorted({t for t, _ in cfg.views[1:]})
    assert tilts == pytest.approx([1.0 / math.cos(math.radians(a)) for a in (15, 30, 45, 60)], abs=1e-5)
    assert tilts == pytest.approx([1.035, 1.155, 1.414, 2.0], abs=1e-3)
    for t in tilts:
        assert sorted(p for tt, p in cfg.views if tt == t) == [0.0, 30.0, 60.0, 90.0, 120.0, 150.0]
    assert cfg.pairing == "asymmetric"


def test_presets_are_listed_and_valid():
    assert {"sift", "paper", "fast", "fast_sym", "fast_asym", "full"} <= set(PRESETS)
    assert PRESETS["sift"].n_views == 1
    assert PRESETS["full"].backend == "cv2_affine"
    assert PRESETS["fast"].pairing == "symmetric" and PRESETS["fast_sym"] is PRESETS["fast"]
    assert PRESETS["fast_asym"].pairing == "asymmetric"
    with pytest.raises(ConfigError, match="unknown feature preset 'nope'"):
        get_preset("nope")


def test_config_from_mapping_and_validation():
    cfg = from_mapping(FeatureConfig, {"views": [[1.0, 0.0], [2.0, 45]], "view_scale": 0.5, "threads": 2})
    assert cfg.views == ((1.0, 0.0), (2.0, 45.0))
    assert cfg.view_scale == 0.5
    with pytest.raises(ConfigError, match="bogus"):
        from_mapping(FeatureConfig, {"bogus": 1})
    with pytest.raises(ConfigError, match=r"views\[0\] must be the original view"):
        FeatureConfig(views=((2.0, 0.0),))
    with pytest.raises(ConfigError, match=r"views\[1\].tilt"):
        FeatureConfig(views=((1.0, 0.0), (0.5, 0.0)))
    with pytest.raises(ConfigError, match="view_scale"):
        FeatureConfig(view_scale=0.0)
    with pytest.raises(ConfigError, match="pairing"):
        from_mapping(FeatureConfig, {"pairing": "both"})


def test_tilt_of_latitude():
    assert tilt_of_latitude(60.0) == pytest.approx(2.0)
    assert tilt_of_latitude(0.0) == pytest.approx(1.0)


# --------------------------------------------------------------------------- view simulation


@pytest.mark.parametrize("tilt,phi", [(2.0, 0.0), (2.0, 45.0), (1.414, 90.0), (1.155, 150.0)])
def test_view_transform_squeezes_by_tilt_and_maps_corners_inside(tilt, phi):
    w, h = 320, 240
    M, (vw, vh) = view_transform((w, h), tilt, phi)
    L = M[:, :2]
    sv = np.linalg.svd(L, compute_uv=False)
    assert sv[0] / sv[1] == pytest.approx(tilt, rel=1e-9)  # a tilt, nothing else
    assert abs(np.linalg.det(L)) == pytest.approx(1.0 / tilt, rel=1e-9)
    corners = np.array([[0, 0], [w - 1, 0], [0, h - 1], [w - 1, h - 1]], float) @ L.T + M[:, 2]
    assert corners.min() >= -1e-9
    assert (corners[:, 0] <= vw - 1 + 1e-9).all() and (corners[:, 1] <= vh - 1 + 1e-9).all()


def test_simulated_view_maps_pixels_back_exactly():
    """A bright dot lands where the returned affine map says it does."""
    img = np.zeros((240, 320), np.uint8)
    cv2.circle(img, (200, 80), 4, 255, -1)
    view, mask, M = simulate_view(img, 2.0, 30.0, blur_k=0.8, border_px=4)
    assert view.shape == mask.shape
    expected = M[:, :2] @ np.array([200.0, 80.0]) + M[:, 2]
    ys, xs = np.nonzero(view > 40)
    w = view[ys, xs].astype(float)
    centroid = np.array([np.sum(xs * w), np.sum(ys * w)]) / w.sum()
    assert np.linalg.norm(centroid - expected) < 0.3
    assert mask[int(round(expected[1])), int(round(expected[0]))] == 255
    assert mask[0, 0] == 0  # blank canvas corner is masked out


def test_view_keypoints_map_back_to_original_keypoints():
    img = texture()
    cfg = FeatureConfig(views=((1.0, 0.0), (1.414, 0.0), (1.414, 60.0), (2.0, 120.0)), threads=2)
    f = detect(img, cfg)
    f0 = f.original_view()
    assert len(f0) > 100
    assert set(np.unique(f.view)) == {0, 1, 2, 3}
    bf = cv2.BFMatcher(cv2.NORM_L2)
    for v in (1, 2, 3):
        fv = f.subset(f.view == v)
        ms = bf.match(fv.desc, f0.desc)
        d = np.array([f0.xy[m.trainIdx] - fv.xy[m.queryIdx] for m in ms])
        close = np.linalg.norm(d, axis=1) < 3.0
        assert close.sum() > 0.1 * len(fv)
        assert np.abs(np.median(d[close], axis=0)).max() < 0.35  # no systematic offset
        assert np.median(np.linalg.norm(d[close], axis=1)) < 1.5


def test_downscaled_views_map_back_too():
    img = texture(seed=3)
    cfg = FeatureConfig(views=((1.0, 0.0), (1.414, 45.0)), view_scale=0.7)
    f = detect(img, cfg)
    f0, f1 = f.original_view(), f.subset(f.view == 1)
    ms = cv2.BFMatcher(cv2.NORM_L2).match(f1.desc, f0.desc)
    d = np.array([f0.xy[m.trainIdx] - f1.xy[m.queryIdx] for m in ms])
    close = np.linalg.norm(d, axis=1) < 3.0
    assert close.sum() > 20
    assert np.abs(np.median(d[close], axis=0)).max() < 0.5


# --------------------------------------------------------------------------- detect


def test_original_view_at_a_reduced_scale_maps_back_to_full_resolution_keypoints():
    img = texture(w=480, h=360, seed=4)
    full = detect(img, FeatureConfig())
    half = detect(img, FeatureConfig(original_scale=0.5))
    assert 20 < len(half) < len(full)
    assert (half.view == 0).all()
    ms = cv2.BFMatcher(cv2.NORM_L2).match(half.desc, full.desc)
    d = np.array([full.xy[m.trainIdx] - half.xy[m.queryIdx] for m in ms])
    close = np.linalg.norm(d, axis=1) < 3.0
    assert close.sum() > 0.3 * len(half)
    assert np.abs(np.median(d[close], axis=0)).max() < 0.3  # pixel centres kept: no half-pixel shift
    # sizes in original pixels: the matched keypoints' sizes agree
    ratio = np.array([full.size[m.trainIdx] / half.size[m.queryIdx] for m in ms])[close]
    assert 0.8 < np.median(ratio) < 1.25
    with pytest.raises(ConfigError):
        FeatureConfig(original_scale=1.5)


def test_detect_returns_consistent_arrays():
    f = detect(texture(), "fast")
    n = len(f)
    assert n > 100
    assert f.xy.shape == (n, 2) and f.xy.dtype == np.float32
    assert f.desc.shape == (n, 128) and f.desc.dtype == np.float32
    for a in (f.size, f.angle, f.response):
        assert a.shape == (n,)
    assert f.view.dtype == np.int16
    assert (f.xy[:, 0] >= 0).all() and (f.xy[:, 0] <= 319).all()
    assert (f.xy[:, 1] >= 0).all() and (f.xy[:, 1] <= 239).all()
    assert ((f.angle >= 0) & (f.angle < 360)).all()
    assert set(np.unique(f.view)) <= set(range(PRESETS["fast"].n_views))


def test_sift_preset_equals_original_view_of_fast():
    img = texture(seed=1)
    a = detect(img, FeatureConfig())
    b = detect(img, FeatureConfig(views=((1.0, 0.0), (2.0, 0.0)))).original_view()
    assert len(a) == len(b)
    np.testing.assert_allclose(a.xy, b.xy)


def test_earlier_image_gets_original_view_only_when_asymmetric():
    img = texture(seed=2)
    cfg = get_preset("fast_asym")
    full = detect(img, cfg)
    early = earlier_features(img, cfg)
    assert (early.view == 0).all()
    assert len(earlier_subset(full, cfg)) == len(early)
    sym = get_preset("fast_sym")
    assert len(earlier_subset(full, sym)) == len(full)


def test_blank_and_tiny_images_give_empty_features():
    for img in (np.zeros((240, 320), np.uint8), np.full((240, 320), 255, np.uint8), np.zeros((8, 8), np.uint8), np.zeros((0, 0), np.uint8)):
        f = detect(img, "fast")
        assert len(f) == 0
        assert f.desc.shape == (0, 128)
        assert len(f.original_view()) == 0


def test_detect_rejects_bad_images():
    with pytest.raises(ConfigError, match="single-channel"):
        detect(np.zeros((10, 10, 3), np.uint8), "sift")
    with pytest.raises(ConfigError, match="uint8"):
        detect(np.zeros((10, 10), np.float32), "sift")
    with pytest.raises(ConfigError, match="view index 7"):
        detect(texture(), "fast", views=[7])


def test_features_concat_and_subset():
    f = detect(texture(), "sift")
    a, b = f.subset(np.arange(10)), f.subset(np.arange(10, 25))
    c = Features.concat([a, Features.empty(), b])
    assert len(c) == 25
    np.testing.assert_array_equal(c.xy, f.xy[:25])
    assert len(Features.concat([])) == 0


def test_cv2_affine_backend_labels_unknown_view():
    cfg = FeatureConfig(backend="cv2_affine", affine=AffineFeatureConfig(max_tilt=2), pairing="symmetric")
    f = detect(texture(160, 120), cfg)
    assert len(f) > 0
    assert (f.view == -1).all()
