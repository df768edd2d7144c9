"""Slanted-window stereo refinement (stereopath.host.backend.slanted_stereo)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from stereopath.host.backend.slanted_stereo import SlantedFit, refine_slanted


def plane_wave_texture(x: np.ndarray, y: np.ndarray, seed: int) -> np.ndarray:
    """A sum of random plane waves (wavelengths 4-40 px), evaluated exactly at ``(x, y)``, 10-240."""
    rng = np.random.default_rng(seed)
    f = np.zeros(np.broadcast(x, y).shape)
    for _ in range(60):
        k = 2 * np.pi / rng.uniform(4.0, 40.0)
        a = rng.uniform(0, 2 * np.pi)
        f += np.sin(k * (np.cos(a) * x + np.sin(a) * y) + rng.uniform(0, 2 * np.pi))
    return (125.0 + 115.0 * f / np.abs(f).max()).astype(np.float32)


def _slanted_pair(d0: float, ax: float, by: float, gain: float = 1.0, offset: float = 0.0, seed: int = 3):
    """Left image of a texture and a right image that sees it with the disparity ``d0 + ax x + by y``
    (x, y from the image centre), both rendered exactly (no resampling) with mild noise; and the
    true right pixel of a left pixel."""
    h, w = 240, 320
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float64)
    cx, cy = w / 2, h / 2
    # right pixel (u, y) shows left x with u = x - d0 - ax (x - cx) - by (y - cy)
    x_src = (xs + d0 - ax * cx + by * (ys - cy)) / (1.0 - ax)
    rng = np.random.default_rng(seed + 1)
    left = plane_wave_texture(xs, ys, seed) + rng.normal(0, 1.0, (h, w)).astype(np.float32)
    right = gain * plane_wave_texture(x_src, ys, seed) + offset + rng.normal(0, 1.0, (h, w)).astype(np.float32)

    def true_right(xy):
        d = d0 + ax * (xy[:, 0] - cx) + by * (xy[:, 1] - cy)
        return np.column_stack([xy[:, 0] - d, xy[:, 1]])

    return left, right, true_right


def _points(n: int, seed: int = 5) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.column_stack([rng.uniform(60, 260, n), rng.uniform(30, 210, n)])


def _translational(left, right, xy, guess) -> tuple[np.ndarray, np.ndarray]:
    """OpenCV's KLT (one level, 21 px window) from ``guess``: right pixels and the converged mask."""
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-4)
    p1, st, _ = cv2.calcOpticalFlowPyrLK(left.astype(np.uint8), right.clip(0, 255).astype(np.uint8),
                                         xy.astype(np.float32).reshape(-1, 1, 2),
                                         guess.astype(np.float32).reshape(-1, 1, 2), winSize=(21, 21),
                                         maxLevel=0, criteria=crit, flags=cv2.OPTFLOW_USE_INITIAL_FLOW)
    return p1.reshape(-1, 2).astype(np.float64), st.ravel() == 1


def test_a_slanted_surface_is_matched_at_the_window_centre_where_a_translational_window_is_not():
    # disparity growing 0.15 px per px to the right and 0.1 px per px downwards: the translational window
    # measures the disparity at its gradient-energy centroid, off the centre by a random ~pixel
    left, right, truth = _slanted_pair(d0=12.0, ax=0.15, by=0.1)
    xy = _points(300)
    true = truth(xy)
    klt, st = _translational(left, right, xy, true + 0.3)
    assert st.all()
    ref, ok = refine_slanted(left, right, xy, klt, SlantedFit(half=10))  # the offline tracks' 21 px window
    assert ok.mean() > 0.95
    err_klt = np.abs(klt[:, 0] - true[:, 0])
    err = np.abs(ref[ok, 0] - true[ok, 0])
    assert np.median(err_klt) > 0.05  # the translational window is off on a slant ...
    assert np.median(err) < 0.02 and np.percentile(err, 90) < 0.06  # ... the slanted one is not
    assert np.median(np.abs(ref[ok, 1] - true[ok, 1])) < 0.02


def test_a_fronto_parallel_surface_stays_where_it_was_matched_and_brightness_changes_do_not_matter():
    left, right, truth = _slanted_pair(d0=7.3, ax=0.0, by=0.0, gain=1.25, offset=-15.0, seed=8)
    xy = _points(200, seed=9)
    true = truth(xy)
    ref, ok = refine_slanted(left, right, xy, true + np.array([0.4, -0.3]))
    assert ok.mean() > 0.95
    err = np.hypot(*(ref[ok] - true[ok]).T)
    assert np.median(err) < 0.02 and err.max() < 0.1


def test_points_that_cannot_be_refined_are_flagged_and_left_as_given():
    left, right, truth = _slanted_pair(d0=10.0, ax=0.1, by=0.0)
    left[:, :] = 128.0  # no texture at all in the left image: nothing to fit
    xy = _points(20)
    guess = truth(xy)
    ref, ok = refine_slanted(left, right, xy, guess)
    assert not ok.any()
    assert np.array_equal(ref, guess)
    empty, ok0 = refine_slanted(left, right, np.zeros((0, 2)), np.zeros((0, 2)))
    assert empty.shape == (0, 2) and ok0.shape == (0,)


def test_blocks_and_threads_give_the_same_result_as_one_pass(monkeypatch):
    import stereopath.host.backend.slanted_stereo as mod

    left, right, truth = _slanted_pair(d0=9.0, ax=0.05, by=-0.05, seed=11)
    xy = _points(700, seed=12)
    guess = truth(xy) + 0.2
    monkeypatch.setattr(mod, "BLOCK", 100_000)
    one, ok_one = refine_slanted(left, right, xy, guess)
    monkeypatch.setattr(mod, "BLOCK", 128)  # 6 blocks
    threads = cv2.getNumThreads()
    try:
        cv2.setNumThreads(3)
        many, ok_many = refine_slanted(left, right, xy, guess)
        cv2.setNumThreads(1)
        serial, ok_serial = refine_slanted(left, right, xy, guess)
    finally:
        cv2.setNumThreads(threads)
    assert ok_one.mean() > 0.95
    assert np.array_equal(one, many) and np.array_equal(ok_one, ok_many)
    assert np.array_equal(one, serial) and np.array_equal(ok_one, ok_serial)


def _middlebury_points(data_dir, scene: str):
    """Left image, right image, SIFT keypoints on smooth true disparity and their true disparity
    (Middlebury 2003, disparity x4 in disp2.png), and the KLT match started 0.4 px off the truth."""
    d = data_dir / "middlebury" / scene
    L = cv2.imread(str(d / "im2.png"), cv2.IMREAD_GRAYSCALE)
    R = cv2.imread(str(d / "im6.png"), cv2.IMREAD_GRAYSCALE)
    D = cv2.imread(str(d / "disp2.png"), cv2.IMREAD_GRAYSCALE).astype(np.float64) / 4.0
    xy = np.array([k.pt for k in cv2.SIFT_create(nfeatures=3000).detect(L, None)], np.float64)
    h, w = L.shape
    xi = np.clip(np.round(xy[:, 0]).astype(int), 2, w - 3)
    yi = np.clip(np.round(xy[:, 1]).astype(int), 2, h - 3)
    nb = np.stack([D[yi + a, xi + b] for a in range(-2, 3) for b in range(-2, 3)], 1)
    x0 = np.clip(np.floor(xy[:, 0]).astype(int), 0, w - 2)
    y0 = np.clip(np.floor(xy[:, 1]).astype(int), 0, h - 2)
    fx, fy = xy[:, 0] - x0, xy[:, 1] - y0
    gt = (D[y0, x0] * (1 - fx) * (1 - fy) + D[y0, x0 + 1] * fx * (1 - fy) + D[y0 + 1, x0] * (1 - fx) * fy
          + D[y0 + 1, x0 + 1] * fx * fy)
    keep = (nb.min(1) > 0) & (np.ptp(nb, 1) <= 3.0) & (xy[:, 0] - gt > 10)
    xy, gt = xy[keep], gt[keep]
    guess = np.column_stack([xy[:, 0] - gt + 0.4, xy[:, 1]])
    klt, st = _translational(L.astype(np.float32), R.astype(np.float32), xy, guess)
    good = st & (np.abs(klt[:, 1] - xy[:, 1]) < 1) & (np.abs(xy[:, 0] - klt[:, 0] - gt) < 1.5)
    return L, R, xy[good], gt[good], klt[good]


@pytest.mark.realdata
@pytest.mark.parametrize("scene", ["cones", "teddy"])
def test_real_stereo_pairs_are_matched_closer_to_the_true_disparity(data_dir, scene):
    L, R, xy, gt, klt = _middlebury_points(data_dir, scene)
    assert len(xy) > 300
    ref, ok = refine_slanted(L, R, xy, klt)
    assert ok.mean() > 0.85
    err_klt = xy[:, 0] - klt[:, 0] - gt
    err = xy[:, 0] - ref[:, 0] - gt
    rms = lambda e: float(np.sqrt(np.mean(e ** 2)))  # noqa: E731
    # the true disparity is in quarter pixels: both errors carry its +-0.125 px rounding
    assert rms(err[ok]) < 0.95 * rms(err_klt[ok])  # cones 0.341 -> 0.285 px, teddy 0.327 -> 0.293 px
    assert rms(err_klt[~ok]) > rms(err_klt[ok])  # the points it cannot refine are the badly matched ones


def test_the_track_setting_takes_off_or_a_window_size_and_rejects_others():
    from stereopath.device.errors import ConfigError
    from stereopath.host.backend.tracks import StereoMatch, TrackConfig

    assert TrackConfig().stereo.slanted_window == TrackConfig().stereo.klt_window  # by default the KLT's own window
    assert TrackConfig(stereo=StereoMatch(slanted_window=0)).stereo.slanted_window == 0
    for bad in (3, 43, -1):
        with pytest.raises(ConfigError, match="slanted_window"):
            TrackConfig(stereo=StereoMatch(slanted_window=bad))
