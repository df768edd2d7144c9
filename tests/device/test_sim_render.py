"""Simulator rendering: exact pinhole geometry, depth, mip levels, near-plane clipping, stereo consistency."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from stereopath.device.core.geometry import euler_xyz_to_matrix, invert_pose, make_pose
from stereopath.device.core.rig import paper_rig
from stereopath.device.sim.render import Renderer
from stereopath.device.sim.scene import Quad, Scene, point_to_scene_distance

# ---------------------------------------------------------------------------------------------
# a single textured quad carrying Gaussian dots at known texels

TEX_H, TEX_W = 256, 384
QUAD_O = np.array([-0.3, -0.2, 1.5])
QUAD_U = np.array([0.6, 0.0, 0.0])
QUAD_V = np.array([0.0, 0.4, 0.0])
DOTS = [(60.0, 50.0), (300.0, 70.0), (190.0, 128.0), (80.0, 200.0), (330.0, 210.0)]  # (s, t) texel centres
K = np.array([[500.0, 0, 319.5], [0, 500.0, 239.5], [0, 0, 1]])
SIZE = (640, 480)


def _dot_scene(sigma: float = 5.0) -> Scene:
    yy, xx = np.mgrid[0:TEX_H, 0:TEX_W].astype(np.float64)
    tex = np.full((TEX_H, TEX_W), 30.0)
    for s, t in DOTS:
        tex += 200.0 * np.exp(-((xx - s) ** 2 + (yy - t) ** 2) / (2 * sigma**2))
    quad = Quad(QUAD_O, QUAD_U, QUAD_V, 0, 0.6 / TEX_W, "dots")
    return Scene([quad], [np.clip(tex + 0.5, 0, 255).astype(np.uint8)])


def _dot_world(s: float, t: float) -> np.ndarray:
    return QUAD_O + (s + 0.5) / TEX_W * QUAD_U + (t + 0.5) / TEX_H * QUAD_V


def _project(T_world_cam: np.ndarray, X: np.ndarray) -> np.ndarray:
    Xc = invert_pose(T_world_cam) @ np.append(X, 1.0)
    p = K @ Xc[:3]
    return p[:2] / p[2]


def _centroid(img: np.ndarray, guess: np.ndarray, half: int) -> np.ndarray:
    x0, y0 = int(round(guess[0])), int(round(guess[1]))
    win = img[y0 - half:y0 + half + 1, x0 - half:x0 + half + 1].astype(np.float64) - 30.0
    win = np.clip(win, 0, None)
    ys, xs = np.mgrid[y0 - half:y0 + half + 1, x0 - half:x0 + half + 1]
    return np.array([(win * xs).sum() / win.sum(), (win * ys).sum() / win.sum()])


@pytest.fixture(scope="module")
def dot_renderer() -> Renderer:
    return Renderer(_dot_scene(), paper_rig(), noise_sigma=0.0)


POSES = [
    make_pose(np.eye(3), [0.0, 0.0, 0.0]),
    make_pose(euler_xyz_to_matrix(np.radians([12.0, -18.0, 25.0])), [0.25, -0.15, 0.35]),
    make_pose(euler_xyz_to_matrix(np.radians([-8.0, 12.0, -10.0])), [-0.3, 0.2, 0.1]),
    make_pose(euler_xyz_to_matrix(np.radians([3.0, -4.0, 40.0])), [0.05, 0.0, -3.0]),  # far: coarse mip level
]


@pytest.mark.parametrize("pose_index", range(len(POSES)))
def test_textured_dots_land_where_the_pinhole_model_says(dot_renderer, pose_index):
    T = POSES[pose_index]
    img, depth = dot_renderer.render_view(K, SIZE, T)
    errors = []
    for s, t in DOTS:
        p = _project(T, _dot_world(s, t))
        assert 10 < p[0] < SIZE[0] - 10 and 10 < p[1] < SIZE[1] - 10
        z = float(depth[int(round(p[1])), int(round(p[0]))])
        sigma_px = 5.0 * (0.6 / TEX_W) * K[0, 0] / z
        c = _centroid(img, p, int(np.ceil(3.5 * sigma_px)) + 2)
        errors.append(np.linalg.norm(c - p))
    assert max(errors) < 0.25, errors
    if pose_index == 3:
        assert dot_renderer.lod_levels(K, T).max() >= 2  # the far view samples a coarse mip level


def test_depth_is_the_exact_ray_plane_intersection(dot_renderer):
    T = POSES[1]
    _, depth = dot_renderer.render_view(K, SIZE, T)
    T_cw = invert_pose(T)
    n_c = T_cw[:3, :3] @ np.array([0.0, 0.0, -1.0])
    d_c = n_c @ (T_cw[:3, :3] @ QUAD_O + T_cw[:3, 3])
    ys, xs = np.nonzero(depth > 0)
    rays = np.linalg.inv(K) @ np.stack([xs, ys, np.ones_like(xs)]).astype(float)
    z_true = d_c / (n_c @ rays)
    assert len(xs) > 20000
    assert np.max(np.abs(depth[ys, xs] - z_true) / z_true) < 1e-5
    # the covered region is exactly the projected rectangle (pixel centres inside it)
    X = (T[:3, :3] @ (rays * z_true) + T[:3, 3][:, None]).T
    a = (X - QUAD_O) @ QUAD_U / (QUAD_U @ QUAD_U)
    b = (X - QUAD_O) @ QUAD_V / (QUAD_V @ QUAD_V)
    tol = 0.05 / TEX_W * 4  # ~0.2 texel
    assert np.all((a > -tol) & (a < 1 + tol) & (b > -tol) & (b < 1 + tol))
    corners_px = np.array([_project(T, c) for c in (QUAD_O, QUAD_O + QUAD_U, QUAD_O + QUAD_U + QUAD_V, QUAD_O + QUAD_V)])
    inside = np.zeros((SIZE[1], SIZE[0]), np.uint8)
    cv2.fillConvexPoly(inside, np.round(corners_px * 16).astype(np.int32), 1, cv2.LINE_8, 4)
    assert abs(int((depth > 0).sum()) - int(inside.sum())) < 0.01 * inside.sum()


def test_distorted_camera_renders_through_its_distortion_model(dot_renderer):
    dist = np.array([-0.25, 0.08, 0.001, -0.0005, 0.0])
    T = POSES[1]
    img, depth = dot_renderer.render_view(K, SIZE, T, dist=dist)
    assert img.shape == (SIZE[1], SIZE[0]) and depth.shape == img.shape
    for s, t in DOTS:
        X = (invert_pose(T) @ np.append(_dot_world(s, t), 1.0))[:3]
        p = cv2.projectPoints(X.reshape(1, 3), np.zeros(3), np.zeros(3), K, dist)[0].reshape(2)
        c = _centroid(img, p, 12)
        assert np.linalg.norm(c - p) < 0.5


def test_quad_crossing_the_near_plane_is_clipped_correctly():
    # a large floor under a low camera, extending far behind it
    floor_tex = (np.random.default_rng(0).random((512, 512)) * 200 + 20).astype(np.uint8)
    quad = Quad(np.array([-10.0, 10.0, 0.0]), np.array([20.0, 0.0, 0.0]), np.array([0.0, -20.0, 0.0]), 0, 20 / 512, "floor")
    scene = Scene([quad], [floor_tex])
    r = Renderer(scene, paper_rig(), noise_sigma=0.0)
    # camera 0.3 m above the floor looking along world +y, tilted 10 deg down
    R_wc = np.array([[1.0, 0, 0], [0, 0, 1.0], [0, -1.0, 0]]) @ euler_xyz_to_matrix(np.radians([-10.0, 0, 0]))
    T = make_pose(R_wc, [0.0, 0.0, 0.3])
    _, depth = r.render_view(K, SIZE, T)
    ys, xs = np.mgrid[0:SIZE[1], 0:SIZE[0]]
    rays_w = R_wc @ (np.linalg.inv(K) @ np.stack([xs.ravel(), ys.ravel(), np.ones(xs.size)]))
    s = -0.3 / rays_w[2]  # ray parameter where z_world = 0 (the ray's camera-z component is 1)
    hit = (rays_w[2] < 0) & (np.abs(s * rays_w[0]) < 10) & (np.abs(s * rays_w[1]) < 10)
    z_true = np.where(hit, s, 0.0).reshape(SIZE[1], SIZE[0])
    got = depth > 0
    assert np.mean(got == hit.reshape(got.shape)) > 0.999
    both = got & hit.reshape(got.shape)
    assert np.max(np.abs(depth[both] - z_true[both]) / z_true[both]) < 1e-4


# ---------------------------------------------------------------------------------------------
# the table-top scene through the session


@pytest.fixture(scope="module")
def session():
    from stereopath.device.sim import open_sim

    return open_sim(frames=400, with_depth=True)


def test_table_top_depth_back_projects_onto_the_scene_without_holes(session):
    K0 = session.rig.cam0.K
    for i in (30, 260):
        f = session.render(i)
        d = f.meta["depth0"]
        assert d.dtype == np.float32 and d.shape == (480, 640)
        assert np.all(d > 0)  # closed room: every pixel sees a surface
        assert 0.3 < np.percentile(d, 2) and np.percentile(d, 98) < 4.5
        ys, xs = np.mgrid[0:480, 0:640]
        rays = np.linalg.inv(K0) @ np.stack([xs.ravel(), ys.ravel(), np.ones(xs.size)])
        T = f.meta["T_world_cam0"]
        Xw = (T[:3, :3] @ (rays * d.ravel()) + T[:3, 3][:, None]).T
        dist = point_to_scene_distance(session.scene, Xw[::7])
        assert np.median(dist) < 1e-5 and np.percentile(dist, 99.5) < 1e-4


def _gt_disparity_rectified(rig, rect, depth0):
    mx, my = rect.maps0
    z = cv2.remap(depth0, mx, my, cv2.INTER_NEAREST)
    p = np.stack([mx, my, np.ones_like(mx)], -1).reshape(-1, 3).T
    X0 = (np.linalg.inv(rig.cam0.K) @ p) * z.reshape(-1)
    Zr = (rect.R0 @ X0)[2].reshape(z.shape)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(Zr > 0, rect.f * rect.baseline_m / Zr, np.nan)


def test_rendered_stereo_disparity_matches_ground_truth_depth(session):
    rig = session.rig
    rect = rig.rectification()
    sgbm = cv2.StereoSGBM_create(minDisparity=0, numDisparities=64, blockSize=5, P1=8 * 25, P2=32 * 25,
                                 uniquenessRatio=10, speckleWindowSize=50, speckleRange=2)
    for i in (60, 330):
        f = session.render(i)
        l, r = rect.rectify(f.left, f.right)
        disp = sgbm.compute(l, r).astype(np.float32) / 16.0
        gt = _gt_disparity_rectified(rig, rect, f.meta["depth0"])
        valid = (disp > 0) & np.isfinite(gt)
        assert valid.mean() > 0.6
        err = np.abs(disp[valid] - gt[valid])
        assert np.median(err) < 0.5
        assert np.mean(err < 1.0) > 0.85


def _warp_right_to_left(right, depth0, K0, K1, T_cam1_cam0):
    h, w = depth0.shape
    ys, xs = np.mgrid[0:h, 0:w]
    X0 = (np.linalg.inv(K0) @ np.stack([xs.ravel(), ys.ravel(), np.ones(xs.size)])) * depth0.ravel()
    X1 = T_cam1_cam0[:3, :3] @ X0 + T_cam1_cam0[:3, 3][:, None]
    p = K1 @ X1
    mx = (p[0] / p[2]).reshape(h, w).astype(np.float32)
    my = (p[1] / p[2]).reshape(h, w).astype(np.float32)
    warped = cv2.remap(right, mx, my, cv2.INTER_LINEAR, borderValue=0)
    inside = (mx > 1) & (mx < w - 2) & (my > 1) & (my < h - 2)
    return warped, inside


def test_paper_rig_right_image_is_the_left_seen_through_the_extrinsics():
    from stereopath.device.sim import open_sim

    sess = open_sim(frames=400, noise_sigma=0.0, with_depth=True)
    rig = sess.rig
    f = sess.render(180)
    d = f.meta["depth0"]
    warped, inside = _warp_right_to_left(f.right, d, rig.cam0.K, rig.cam1.K, rig.T_cam1_cam0)
    diff = np.abs(warped.astype(float) - f.left.astype(float))[inside]
    assert inside.mean() > 0.8
    assert np.median(diff) < 2.0
    # the check has teeth: dropping the rotation of the extrinsics makes it clearly worse
    wrong = rig.T_cam1_cam0.copy()
    wrong[:3, :3] = np.eye(3)
    warped_bad, inside_bad = _warp_right_to_left(f.right, d, rig.cam0.K, rig.cam1.K, wrong)
    bad = np.abs(warped_bad.astype(float) - f.left.astype(float))[inside_bad]
    assert np.median(bad) > 3 * max(np.median(diff), 1.0)


def test_rendered_frames_are_rich_in_sift_keypoints(session):
    f = session.render(120)
    kps = cv2.SIFT_create().detect(f.left, None)
    assert len(kps) > 1000
