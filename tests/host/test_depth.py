"""Stereo depth: pure helpers, a synthetic plane, the simulator's ground truth, Middlebury."""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import pytest

from stereopath.device.errors import ConfigError, StereopathError
from stereopath.device.core.rig import make_camera, make_rig
from stereopath.host.mapping.depth import (
    DEPTH_PRESETS,
    DepthConfig,
    StereoDepth,
    compute_disparity,
    depth_edge_mask,
    depth_preset,
    disparity_search_range,
    fill_holes_background,
    left_right_check,
)


def _texture(h: int, w: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    noise = rng.uniform(0, 255, (h // 4 + 1, w // 4 + 1)).astype(np.float32)
    img = cv2.resize(noise, (w, h), interpolation=cv2.INTER_CUBIC)
    return np.clip(img, 0, 255).astype(np.uint8)


# ---------------------------------------------------------------------------------------------
# configuration and pure helpers


def test_config_rejects_bad_values():
    with pytest.raises(ConfigError, match="block_size"):
        DepthConfig(block_size=4)
    with pytest.raises(ConfigError, match="max_depth_m"):
        DepthConfig(min_depth_m=2.0, max_depth_m=1.0)
    with pytest.raises(ConfigError, match="p2_per_pixel"):
        DepthConfig(p1_per_pixel=10.0, p2_per_pixel=5.0)
    with pytest.raises(ConfigError, match="mode"):
        DepthConfig(mode="fast")  # type: ignore[arg-type]
    with pytest.raises(ConfigError, match="unknown depth preset 'x'"):
        depth_preset("x")
    assert depth_preset("object").max_depth_m < depth_preset("room").max_depth_m


def test_disparity_search_range_covers_min_depth():
    cfg = DepthConfig(min_depth_m=0.25)
    n = disparity_search_range(cfg, 500.0, 0.05)  # f*B/zmin = 100 px
    assert n % 16 == 0 and n >= 100 and n < 100 + 32
    assert disparity_search_range(dataclasses.replace(cfg, max_disparity_px=40), 500.0, 0.05) == 48


def test_left_right_check_keeps_consistent_pixels_only():
    dl = np.full((2, 20), 3.0, np.float32)
    dr = np.full((2, 20), 3.0, np.float32)
    dr[0, 7] = 9.0  # right pixel 7 disagrees: left pixel 10 (10 - 3 = 7) must go
    dl[1, 1] = 3.0  # 1 - 3 < 0: matches outside the right image
    ok = left_right_check(dl, dr, 1.0)
    assert not ok[0, 10] and ok[0, 11] and ok[0, 9]
    assert not ok[1, 1] and not ok[1, 2] and ok[1, 3]
    dl[0, 5] = np.nan
    assert not left_right_check(dl, dr, 1.0)[0, 5]


def test_depth_edge_mask_marks_both_sides_of_a_step():
    z = np.ones((10, 10), np.float32)
    z[:, 5:] = 2.0
    e = depth_edge_mask(z, 0.1, dilate_px=0)
    assert e[:, 4].all() and e[:, 5].all() and not e[:, :4].any() and not e[:, 6:].any()
    assert not depth_edge_mask(np.ones((5, 5), np.float32), 0.1).any()


def test_fill_holes_uses_the_farther_neighbour():
    d = np.array([[5.0, np.nan, np.nan, 2.0, np.nan]], np.float32)
    f = fill_holes_background(d)
    np.testing.assert_allclose(f, [[5.0, 2.0, 2.0, 2.0, 2.0]])


# ---------------------------------------------------------------------------------------------
# synthetic rectified pair


def test_fronto_parallel_plane_disparity():
    h, w, d_true = 120, 200, 12.0
    right = _texture(h, w + 40, seed=3)
    # the left image sees the same texture shifted by d (x_right = x_left - d)
    M = np.float32([[1, 0, d_true], [0, 1, 0]])  # left(x) = right(x - d)
    left = cv2.warpAffine(right, M, (w + 40, h), flags=cv2.INTER_LINEAR)
    left, right = left[:, 20:20 + w], right[:, 20:20 + w]
    cfg = DepthConfig(max_disparity_px=31, block_size=5, edge_max_rel_step=0.0)
    disp = compute_disparity(left, right, cfg, 32)
    core = disp[10:-10, 40:-10]
    assert np.mean(np.isfinite(core)) > 0.9
    assert abs(float(np.nanmedian(core)) - d_true) < 0.1


def test_compute_rejects_size_mismatch():
    K = np.array([[300.0, 0, 79.5], [0, 300.0, 59.5], [0, 0, 1]])
    cam = make_camera("c", K, np.zeros(5), (160, 120))
    rig = make_rig(cam, cam, np.eye(3), [-0.1, 0.0, 0.0])
    sd = StereoDepth(rig, DepthConfig(edge_max_rel_step=0.0))
    img = np.zeros((120, 160), np.uint8)
    with pytest.raises(StereopathError, match="right image is 100x120"):
        sd.compute(img, np.zeros((120, 100), np.uint8))
    with pytest.raises(StereopathError, match="left image is 100x120"):
        sd.compute(np.zeros((120, 100), np.uint8), img)
    dm = sd.compute(img, img)  # no texture at all: no depth, but no crash
    assert dm.valid_fraction == 0.0 and dm.depth_m.dtype == np.float32


# ---------------------------------------------------------------------------------------------
# simulator ground truth


@pytest.fixture(scope="module")
def sim_frames():
    from stereopath.device.sim.session import SimConfig, open_sim

    sess = open_sim(SimConfig(frames=400, with_depth=True))
    return sess, [sess.frame(i) for i in (150, 230)]


def _gt_in_rect(depth0: np.ndarray, K0: np.ndarray, R0: np.ndarray, Kr: np.ndarray) -> np.ndarray:
    """Camera-0 ground-truth depth forward-projected into the rectified camera (nearest pixel, z-buffer)."""
    h, w = depth0.shape
    v, u = np.nonzero(depth0 > 0)
    z = depth0[v, u].astype(float)
    P = np.stack([(u - K0[0, 2]) * z / K0[0, 0], (v - K0[1, 2]) * z / K0[1, 1], z], axis=1) @ R0.T
    ur = np.rint(Kr[0, 0] * P[:, 0] / P[:, 2] + Kr[0, 2]).astype(int)
    vr = np.rint(Kr[1, 1] * P[:, 1] / P[:, 2] + Kr[1, 2]).astype(int)
    ok = (ur >= 0) & (ur < w) & (vr >= 0) & (vr < h)
    out = np.full((h, w), np.inf, np.float32)
    np.minimum.at(out, (vr[ok], ur[ok]), P[ok, 2].astype(np.float32))
    out[~np.isfinite(out)] = 0.0
    return out


def test_depth_matches_simulator_ground_truth(sim_frames):
    sess, frames = sim_frames
    sd = StereoDepth(sess.rig, DEPTH_PRESETS["object"])
    for fr in frames:
        dm = sd.compute(fr.left, fr.right)
        assert dm.depth_m.shape == fr.left.shape and dm.valid_fraction > 0.2
        gt = _gt_in_rect(fr.meta["depth0"], sess.rig.cam0.K, dm.R_rect_cam0, dm.K)
        lo = cv2.erode(np.where(gt > 0, gt, 1e9).astype(np.float32), np.ones((3, 3), np.uint8))
        hi = cv2.dilate(gt, np.ones((3, 3), np.uint8))
        m = dm.valid & (gt > 0) & ((hi - lo) < 0.02 * gt)
        assert m.sum() > 20000
        rel = np.abs(dm.depth_m[m] - gt[m]) / gt[m]
        assert np.median(rel) < 0.01
        assert np.mean(rel > 0.05) < 0.05


def test_rectified_pose_composes_with_cam0_pose(sim_frames):
    """Points of the depth map, moved to the world with pose_world_rect, land on the scene."""
    from stereopath.device.sim.scene import point_to_scene_distance

    sess, frames = sim_frames
    sd = StereoDepth(sess.rig, DEPTH_PRESETS["object"])
    fr = frames[0]
    dm = sd.compute(fr.left, fr.right)
    T = dm.pose_world_rect(fr.meta["T_world_cam0"])
    np.testing.assert_allclose(T[:3, 3], fr.meta["T_world_cam0"][:3, 3])
    p = dm.points_rect(stride=4)
    pw = p @ T[:3, :3].T + T[:3, 3]
    d = point_to_scene_distance(sess.scene, pw)
    assert np.median(d) < 0.005
    # the same points without the rectifying rotation are far off (the rotation matters)
    T_wrong = fr.meta["T_world_cam0"]
    d_wrong = point_to_scene_distance(sess.scene, p @ T_wrong[:3, :3].T + T_wrong[:3, 3])
    assert np.median(d_wrong) > 0.05


# ---------------------------------------------------------------------------------------------
# Middlebury (real data)


@pytest.mark.realdata
@pytest.mark.parametrize("scene", ["cones", "teddy"])
def test_middlebury_bad_pixel_rate(data_dir, scene):
    from stereopath.host.evaluation.middlebury import read_scene

    sc = read_scene(data_dir / "middlebury" / scene)
    assert sc.num_disparities == 64  # cones / teddy: disparities up to 55 / 52.75 px (x4 in disp2.png)
    cfg = DepthConfig(max_disparity_px=sc.num_disparities - 1, block_size=3, edge_max_rel_step=0.0)
    disp = compute_disparity(sc.left, sc.right, cfg, sc.num_disparities)
    gt = sc.gt
    known = np.isfinite(gt)
    matched = np.isfinite(disp)
    assert np.mean(matched[known]) > 0.8
    bad_matched = np.mean(np.abs(disp[known & matched] - gt[known & matched]) > 2.0)
    bad_all = np.mean(np.abs(fill_holes_background(disp)[known] - gt[known]) > 2.0)
    assert bad_matched < 0.06
    assert bad_all <= 0.15


@pytest.mark.realdata
def test_middlebury_layouts_read_the_same_scene(data_dir, tmp_path):
    """The 2014 layout (im0/im1, PFM disparity with infinity unknown, calib.txt's ndisp) and the
    2003 layout's scale factors from datasets.xml give the same ground truth; a scene without a
    scale factor, or a folder that is no scene, is refused by name."""
    from stereopath.device.errors import DatasetError
    from stereopath.host.evaluation.middlebury import find_scenes, read_scene

    ref = read_scene(data_dir / "middlebury" / "cones")
    raw = cv2.imread(str(data_dir / "middlebury" / "cones" / "disp2.png"), cv2.IMREAD_GRAYSCALE)
    assert np.array_equal(np.isnan(ref.gt), raw == 0)
    assert np.allclose(ref.gt[raw > 0], raw[raw > 0] / 4.0)
    d = tmp_path / "cones2014"
    d.mkdir()
    cv2.imwrite(str(d / "im0.png"), ref.left)
    cv2.imwrite(str(d / "im1.png"), ref.right)
    cv2.imwrite(str(d / "disp0GT.pfm"), np.where(np.isnan(ref.gt), np.inf, ref.gt).astype(np.float32))
    (d / "calib.txt").write_text("cam0=[450 0 225; 0 450 187; 0 0 1]\ndoffs=0\nbaseline=100\nndisp=100\n")
    sc = read_scene(d)
    assert np.array_equal(np.isnan(sc.gt), np.isnan(ref.gt)) and np.allclose(sc.gt[~np.isnan(sc.gt)], ref.gt[~np.isnan(ref.gt)])
    assert sc.num_disparities == 112  # calib.txt's ndisp=100 rounded up to 16
    # a 2003 scene the datasets.xml does not list, with its own file
    e = tmp_path / "newscene"
    e.mkdir()
    for f in ("im2.png", "im6.png", "disp2.png"):
        (e / f).write_bytes((data_dir / "middlebury" / "cones" / f).read_bytes())
    with pytest.raises(DatasetError, match="no disparity scale factor for 'newscene'"):
        read_scene(e)
    (tmp_path / "datasets.xml").write_text('<opencv_storage><datasets>\n\tnewscene "8" "0"\n</datasets></opencv_storage>\n')
    half = read_scene(e)
    assert np.allclose(half.gt[raw > 0], raw[raw > 0] / 8.0) and half.num_disparities == 32
    assert [p.name for p in find_scenes(tmp_path)] == ["cones2014", "newscene"]
    with pytest.raises(DatasetError, match="not a Middlebury scene"):
        read_scene(tmp_path)
