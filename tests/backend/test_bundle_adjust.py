import numpy as np
import pytest

from stereopath.device.errors import EstimationError
from stereopath.device.core.stereo import project
from stereopath.device.core.geometry import invert_pose, make_pose, rotation_angle_deg, so3_exp
from stereopath.device.core.rig import paper_rig
from stereopath.host.backend import gtsam_ba
from stereopath.host.backend.ba_common import RotationPrior, interpolate_corrections, propagate_to_frames
from tests.backend.ba_support import adjust

@pytest.fixture
def ba():
    """The bundle-adjustment back end (GTSAM)."""
    return gtsam_ba


def _problem(rng, n_kf=6, n_pts=200):
    rig = paper_rig()
    pts = {i: np.array([rng.uniform(-1, 1), rng.uniform(-0.6, 0.6), rng.uniform(1.0, 2.5)]) for i in range(n_pts)}
    T_wc = [make_pose(so3_exp([0, 0.03 * k, 0]), [0.08 * k, 0, 0]) for k in range(n_kf)]
    obs = []
    for k, T in enumerate(T_wc):
        Tcw = invert_pose(T)
        for i, X in pts.items():
            Xc = Tcw[:3, :3] @ X + Tcw[:3, 3]
            uv0, _ = project(rig.cam0.K, Xc[None])
            uv1, _ = project(rig.cam1.K, (rig.R @ Xc + rig.T)[None])
            obs.append([k, i, 0, *(uv0[0] + rng.normal(0, 0.3, 2))])
            obs.append([k, i, 1, *(uv1[0] + rng.normal(0, 0.3, 2))])
    return rig, np.array(T_wc), pts, np.array(obs)


def test_bundle_adjustment_recovers_perturbed_poses(ba):
    rng = np.random.default_rng(0)
    rig, T_true, pts, obs = _problem(rng)
    T_noisy = T_true.copy()
    for k in range(1, len(T_noisy)):
        T_noisy[k] = T_noisy[k] @ make_pose(so3_exp(rng.normal(0, 0.01, 3)), rng.normal(0, 0.02, 3))
    pts_noisy = {i: X + rng.normal(0, 0.02, 3) for i, X in pts.items()}
    res = adjust(rig, T_noisy, pts_noisy, obs)
    assert res.rms_after_px < 0.5 < res.rms_before_px
    for k in range(len(T_true)):
        assert np.linalg.norm(res.T_world_cam[k][:3, 3] - T_true[k][:3, 3]) < 2e-3
        assert rotation_angle_deg(res.T_world_cam[k][:3, :3].T @ T_true[k][:3, :3]) < 0.05


def test_bundle_adjustment_rejects_too_little_data(ba):
    rng = np.random.default_rng(1)
    rig, T_true, pts, obs = _problem(rng, n_kf=2, n_pts=5)
    with pytest.raises(EstimationError):
        adjust(rig, T_true, pts, obs)
    with pytest.raises(EstimationError):
        adjust(rig, T_true[:1], pts, obs)


def test_propagation_moves_frames_with_their_keyframe():
    T_old = np.array([np.eye(4), make_pose(np.eye(3), [1, 0, 0])])
    T_new = np.array([np.eye(4), make_pose(so3_exp([0, 0, 0.1]), [1, 0.1, 0])])
    frames = np.array([np.eye(4), make_pose(np.eye(3), [1.5, 0, 0])])
    out = propagate_to_frames(frames, np.array([0, 1]), T_old, T_new)
    assert np.allclose(out[0], np.eye(4))
    assert np.allclose(out[1], T_new[1] @ make_pose(np.eye(3), [0.5, 0, 0]))


def _perturbed(rng, T_true, pts, rot=0.01, trans=0.02, pt=0.02):
    T_noisy = T_true.copy()
    for k in range(1, len(T_noisy)):
        T_noisy[k] = T_noisy[k] @ make_pose(so3_exp(rng.normal(0, rot, 3)), rng.normal(0, trans, 3))
    return T_noisy, {i: X + rng.normal(0, pt, 3) for i, X in pts.items()}


def test_disparity_offset_is_estimated_and_removes_the_scale_error(ba):
    rng = np.random.default_rng(3)
    rig, T_true, pts, obs = _problem(rng, n_kf=8, n_pts=300)
    shifted = obs.copy()
    shifted[shifted[:, 2] == 1, 3] += 0.5  # a constant disparity error of 0.5 px
    plain = adjust(rig, T_true, pts, shifted)
    fitted = adjust(rig, T_true, pts, shifted, disparity_offset=True)
    assert fitted.disparity_offset_px == pytest.approx(0.5, abs=0.05)
    assert plain.disparity_offset_px == 0.0

    def path_error(res):
        return max(np.linalg.norm(res.T_world_cam[k][:3, 3] - T_true[k][:3, 3]) for k in range(len(T_true)))

    assert path_error(fitted) < 2e-3 < path_error(plain)
    # an offset below the threshold is treated as noise and not applied
    tiny = adjust(rig, T_true, pts, obs, disparity_offset=True, disparity_offset_min_px=0.2)
    assert tiny.disparity_offset_px == 0.0


def test_an_offset_within_its_standard_error_is_not_applied(ba, monkeypatch):
    # three close keyframes and few noisy points: the offset cannot be told from the depths; its
    # estimate is noise however large the fixed threshold lets it be
    rng = np.random.default_rng(7)
    rig, T_true, pts, obs = _problem(rng, n_kf=3, n_pts=40)
    obs = obs.copy()
    obs[:, 3:5] += rng.normal(0, 0.7, (len(obs), 2))
    kept = adjust(rig, T_true, pts, obs, disparity_offset=True, disparity_offset_min_px=0.0)
    assert kept.disparity_offset_px == 0.0
    monkeypatch.setattr(ba, "OFFSET_SIGNIFICANCE", 0.0)  # without the test the noise would be applied
    noisy = adjust(rig, T_true, pts, obs, disparity_offset=True, disparity_offset_min_px=0.0)
    assert abs(noisy.disparity_offset_px) > 0.02


def test_gross_outliers_are_removed_and_weights_scale_residuals(ba):
    rng = np.random.default_rng(4)
    rig, T_true, pts, obs = _problem(rng)
    bad = rng.choice(len(obs), 100, replace=False)
    obs = obs.copy()
    obs[bad, 3:5] += rng.uniform(20, 40, (100, 2))
    T_noisy, pts_noisy = _perturbed(rng, T_true, pts)
    res = adjust(rig, T_noisy, pts_noisy, obs, outlier_px=3.0, outlier_rounds=1)
    assert res.n_obs <= len(obs) - 100
    for k in range(len(T_true)):
        assert np.linalg.norm(res.T_world_cam[k][:3, 3] - T_true[k][:3, 3]) < 2e-3
    # a 6th column scales residuals: halving every weight halves the rms
    w = np.column_stack([obs, np.full(len(obs), 0.5)])
    r_full = adjust(rig, T_true, pts, obs, max_iterations=1, outlier_rounds=0)
    r_half = adjust(rig, T_true, pts, w, max_iterations=1, outlier_rounds=0)
    assert r_half.rms_before_px == pytest.approx(0.5 * r_full.rms_before_px, rel=1e-9)
    with pytest.raises(EstimationError, match="rows"):
        adjust(rig, T_true, pts, obs[:, :4])


def test_motion_only_refinement_with_fixed_points():
    from stereopath.host.reprocess.stage_ba import refine_frame

    rng = np.random.default_rng(5)
    rig, T_true, pts, obs = _problem(rng, n_kf=5, n_pts=150)
    T_noisy, _ = _perturbed(rng, T_true, pts, 0.01, 0.03, 0.0)
    T_noisy[0] = T_true[0] @ make_pose(so3_exp([0.01, 0, 0]), [0.02, 0, 0])
    for k in range(4):
        out = refine_frame(rig, T_noisy[k], pts, obs[obs[:, 0] == k], 1.0, 0.0)
        assert np.linalg.norm(out[:3, 3] - T_true[k][:3, 3]) < 2e-3
        assert rotation_angle_deg(out[:3, :3].T @ T_true[k][:3, :3]) < 0.05
    few = obs[(obs[:, 0] == 4) & (obs[:, 1] <= 2)]  # 3 points x 2 cameras
    assert refine_frame(rig, T_noisy[4], pts, few, 1.0, 0.0, min_obs=8) is None
    # a known disparity offset (right principal point shifted) is applied to the right observations
    Tcw = invert_pose(T_true[1])
    Xc = np.array([Tcw[:3, :3] @ X + Tcw[:3, 3] for X in pts.values()])
    ids = np.array(list(pts.keys()), float)
    uv0, _ = project(rig.cam0.K, Xc)
    uv1, _ = project(rig.cam1.K, Xc @ rig.R.T + rig.T)
    shifted = np.vstack([np.column_stack([np.ones(len(ids)), ids, np.zeros(len(ids)), uv0]),
                         np.column_stack([np.ones(len(ids)), ids, np.ones(len(ids)), uv1 + [0.8, 0.0]])])
    plain = refine_frame(rig, T_noisy[1], pts, shifted, 1.0, 0.0)
    known = refine_frame(rig, T_noisy[1], pts, shifted, 1.0, 0.8)
    err = [np.linalg.norm(T[:3, 3] - T_true[1][:3, 3]) for T in (known, plain)]
    assert err[0] < 1e-5 and err[1] > 1e-4


def test_rotation_priors_pull_the_relative_rotation(ba):
    rng = np.random.default_rng(6)
    rig, T_true, pts, obs = _problem(rng, n_kf=3, n_pts=40)
    obs = obs[obs[:, 2] == 0]  # one camera only: weaker geometry
    R01_true = invert_pose(T_true[0])[:3, :3] @ invert_pose(T_true[1])[:3, :3].T
    wrong = so3_exp([0.0, 0.0, 0.02]) @ R01_true
    free = adjust(rig, T_true, pts, obs, n_fixed=1)
    pulled = adjust(rig, T_true, pts, obs, n_fixed=1,
                           priors=[RotationPrior(0, 1, wrong, 1e-5)])

    def rel(res):
        return invert_pose(res.T_world_cam[0])[:3, :3] @ invert_pose(res.T_world_cam[1])[:3, :3].T

    assert rotation_angle_deg(rel(free).T @ R01_true) < 0.05
    assert rotation_angle_deg(rel(pulled).T @ wrong) < 0.05


def test_interpolated_corrections_are_smooth_between_keyframes():
    T_old = np.array([np.eye(4), np.eye(4)])
    T_new = np.array([np.eye(4), make_pose(so3_exp([0, 0, 0.2]), [0.2, 0, 0])])
    frames = np.array([np.eye(4)] * 3)
    out = interpolate_corrections(np.array([0, 5, 10]), frames, np.array([0, 10]), T_old, T_new)
    assert np.allclose(out[0], np.eye(4))
    assert np.allclose(out[2], T_new[1])
    assert np.allclose(out[1][:3, 3], [0.1, 0, 0])
    assert rotation_angle_deg(out[1][:3, :3]) == pytest.approx(np.degrees(0.1), rel=1e-6)


def _least_squares_optimum(rig, T0, pts0, obs, huber_px=None, offset=False):
    """The optimum of the same problem by scipy.optimize.least_squares (an independent solver):
    poses (the first held), points and, with ``offset``, the right principal point's offset.

    With ``huber_px`` the robust cost of GTSAM's Huber noise model on each observation's 2D error,
    sum rho(|r|), is minimised as a least-squares problem on the residuals ``sqrt(2 rho(|r|)) r / |r|``
    (scipy's own losses act on each coordinate separately)."""
    from scipy.optimize import least_squares

    from stereopath.host.backend.ba_common import reprojection_residuals

    ids = sorted(pts0)
    K_n = len(T0)
    n_pose = 6 * (K_n - 1)

    def unpack(x):
        T = T0.copy()
        for k in range(1, K_n):
            T[k] = T0[k] @ make_pose(so3_exp(x[6 * (k - 1):6 * k - 3]), x[6 * k - 3:6 * k])
        X = x[n_pose:n_pose + 3 * len(ids)].reshape(-1, 3)
        return T, {i: X[n] for n, i in enumerate(ids)}, (x[-1] if offset else 0.0)

    def fun(x):
        T, P, d = unpack(x)
        r = reprojection_residuals(rig, T, P, obs, d)[0]
        if huber_px is None:
            return r.ravel()
        e = np.maximum(np.linalg.norm(r, axis=1), 1e-12)
        rho = np.where(e <= huber_px, 0.5 * e ** 2, huber_px * e - 0.5 * huber_px ** 2)
        return (r * (np.sqrt(2 * rho) / e)[:, None]).ravel()

    x0 = np.concatenate([np.zeros(n_pose), np.array([pts0[i] for i in ids]).ravel(), [0.0] if offset else []])
    res = least_squares(fun, x0, loss="linear", x_scale="jac", xtol=1e-12, ftol=1e-12, gtol=1e-12)
    return unpack(res.x)


def test_gtsam_reaches_the_least_squares_optimum(monkeypatch):
    """Cross-check of the back end against scipy on a small problem: plain least squares, then the
    production settings' robust loss with gross outliers and the disparity offset unknown."""
    # this problem is too small for the offset to pass the significance test: the optimum is compared
    monkeypatch.setattr(gtsam_ba, "OFFSET_SIGNIFICANCE", 0.0)
    rng = np.random.default_rng(7)
    rig, T_true, pts, obs = _problem(rng, n_kf=4, n_pts=40)
    T_noisy, pts_noisy = _perturbed(rng, T_true, pts, 0.005, 0.01, 0.01)
    a = adjust(rig, T_noisy, pts_noisy, obs, loss="linear", outlier_rounds=0, max_iterations=50,
                               relative_tol=1e-12)
    T_ref, P_ref, _ = _least_squares_optimum(rig, T_noisy, pts_noisy, obs)
    for k in range(len(T_true)):
        assert np.abs(a.T_world_cam[k] - T_ref[k]).max() < 1e-6
    assert max(np.abs(a.points[i] - P_ref[i]).max() for i in P_ref) < 1e-5
    # Huber at 1 px, 5 % gross outliers (which the robust loss must down-weight), 0.4 px disparity error
    bad = obs.copy()
    bad[bad[:, 2] == 1, 3] += 0.4
    hit = rng.random(len(bad)) < 0.05
    bad[hit, 3:5] += rng.normal(0, 8, (hit.sum(), 2))
    a = adjust(rig, T_noisy, pts_noisy, bad, robust_px=1.0, outlier_rounds=0, max_iterations=100,
                               disparity_offset=True, relative_tol=1e-12)
    T_ref, P_ref, d_ref = _least_squares_optimum(rig, T_noisy, pts_noisy, bad, huber_px=1.0, offset=True)
    assert a.disparity_offset_px == pytest.approx(d_ref, abs=1e-4)
    for k in range(len(T_true)):
        assert np.abs(a.T_world_cam[k] - T_ref[k]).max() < 1e-5
    assert max(np.abs(a.points[i] - P_ref[i]).max() for i in P_ref) < 1e-4


def test_gtsam_loop_factor_constrains_the_relative_pose():
    from stereopath.host.backend.loops import Loop

    rng = np.random.default_rng(8)
    rig, T_true, pts, obs = _problem(rng, n_kf=6, n_pts=120)
    obs = obs[obs[:, 2] == 0]  # left camera only: the path's scale is free, the loop fixes it
    rel = invert_pose(T_true[0]) @ T_true[5]
    meas = rel.copy()
    meas[:3, 3] *= 1.02  # a measured loop 2 % longer than the truth
    free = adjust(rig, T_true, pts, obs, outlier_rounds=0)
    loop = Loop(0, 5, meas, 100, 120, 1e-5, 1e-5, 0.0)
    tied = adjust(rig, T_true, pts, obs, outlier_rounds=0, loops=[loop])

    def length(res):
        return np.linalg.norm((invert_pose(res.T_world_cam[0]) @ res.T_world_cam[5])[:3, 3])

    assert length(free) == pytest.approx(np.linalg.norm(rel[:3, 3]), rel=0.01)
    assert length(tied) == pytest.approx(np.linalg.norm(meas[:3, 3]), rel=1e-3)


def test_pixel_noise_is_the_robust_spread_of_the_inlying_residuals():
    rng = np.random.default_rng(3)
    r = rng.normal(0, 0.08, (5000, 2))
    r[:400] = rng.uniform(-2.5, 2.5, (400, 2))  # mismatches: within the outlier limit, but not noise
    front = np.ones(len(r), bool)
    assert gtsam_ba.pixel_noise_px(r, front, 3.0) == pytest.approx(0.08, rel=0.15)  # the std would be 0.4
    # a fit of 2,500 unknowns to the 10,000 components leaves 3/4 of their variance in the residuals
    assert gtsam_ba.pixel_noise_px(r, front, 3.0, 2500) == pytest.approx(gtsam_ba.pixel_noise_px(r, front, 3.0) / np.sqrt(0.75), rel=0.01)
    assert gtsam_ba.pixel_noise_px(r[-4:], front[-4:], 3.0) == 1.0  # too few to say: the nominal pixel
    assert gtsam_ba.pixel_noise_px(r * 1e-3, front, 3.0) == gtsam_ba.MIN_PIXEL_SIGMA


def test_precise_observations_outweigh_a_loose_prior_once_their_noise_is_measured(ba, monkeypatch):
    """A relative-rotation prior 0.5 deg off with a 0.1 deg standard deviation, against observations with
    0.3 px noise: weighed as 1 px observations the prior pulls the rotation several times further
    than when they are weighed by the noise they have."""
    rng = np.random.default_rng(6)
    rig, T_true, pts, obs = _problem(rng, n_kf=3, n_pts=40)
    obs = obs[obs[:, 2] == 0]
    R01_true = invert_pose(T_true[0])[:3, :3] @ invert_pose(T_true[1])[:3, :3].T
    wrong = so3_exp([0.0, 0.0, np.radians(0.5)]) @ R01_true
    prior = [RotationPrior(0, 1, wrong, np.radians(0.1))]

    def pull(res) -> float:
        rel = invert_pose(res.T_world_cam[0])[:3, :3] @ invert_pose(res.T_world_cam[1])[:3, :3].T
        return rotation_angle_deg(rel.T @ R01_true)

    measured = adjust(rig, T_true, pts, obs, n_fixed=1, priors=prior)
    assert measured.pixel_sigma_px == pytest.approx(0.3, rel=0.2)
    monkeypatch.setattr(gtsam_ba, "pixel_noise_px", lambda *a: 1.0)
    nominal = adjust(rig, T_true, pts, obs, n_fixed=1, priors=prior)
    assert pull(nominal) > 3 * pull(measured)
    assert adjust(rig, T_true, pts, obs, n_fixed=1).pixel_sigma_px is None  # observations alone: unchanged


def test_frames_follow_the_adjusted_points_from_where_they_project_in_the_keyframe():
    from types import SimpleNamespace

    from stereopath.host.reprocess.stage_ba import ADJUSTED_GATE_RMS, adjusted_pixels

    rng = np.random.default_rng(7)
    rig = paper_rig()
    T_wc = make_pose(so3_exp([0.0, 0.1, 0.0]), [0.05, 0.0, 0.0])
    pts = {i: np.array([rng.uniform(-1, 1), rng.uniform(-0.6, 0.6), rng.uniform(1.0, 2.5)]) for i in range(100)}
    Tcw = invert_pose(T_wc)
    ids = np.arange(103)  # the last three have no adjusted point (dropped by the adjustment)
    true_uv, _ = project(rig.cam0.K, np.array([Tcw[:3, :3] @ pts[i] + Tcw[:3, 3] for i in range(100)]))
    detected = true_uv + rng.normal(0, 0.3, true_uv.shape)  # the detector's noise
    detected[:5] += 5.0  # five detections far off their point: not followed
    xy = np.vstack([detected, rng.uniform(0, 600, (3, 2))]).astype(np.float32)
    res = SimpleNamespace(points=pts, T_world_cam=np.array([np.eye(4), T_wc]), rms_after_px=0.4)
    got_ids, got_xy = adjusted_pixels(rig, res, 1, ids, xy)
    assert got_ids.tolist() == list(range(5, 100))
    np.testing.assert_allclose(got_xy, true_uv[5:], atol=1e-3)  # the projections, not the detections
    assert got_xy.dtype == np.float32
    # the gate scales with the adjustment's residuals
    loose = SimpleNamespace(points=pts, T_world_cam=res.T_world_cam, rms_after_px=10.0 / ADJUSTED_GATE_RMS)  # 7 px off: in
    assert len(adjusted_pixels(rig, loose, 1, ids, xy)[0]) == 100
    assert len(adjusted_pixels(rig, res, 1, ids[:0], xy[:0])[0]) == 0
    no_figure = SimpleNamespace(points=pts, T_world_cam=res.T_world_cam, rms_after_px=float("nan"))
    assert len(adjusted_pixels(rig, no_figure, 1, ids, xy)[0]) == 100  # no gate without a residual figure


def test_adjusted_points_project_into_the_raw_distorted_keyframe_image():
    import cv2
    from dataclasses import replace
    from types import SimpleNamespace

    from stereopath.host.reprocess.stage_ba import adjusted_pixels

    rng = np.random.default_rng(8)
    base = paper_rig()
    dist = np.array([-0.25, 0.08, 0.0005, -0.0003, 0.0])
    rig = replace(base, cam0=replace(base.cam0, dist=dist))
    pts = {i: np.array([rng.uniform(-1.2, 1.2), rng.uniform(-0.8, 0.8), rng.uniform(1.0, 2.0)]) for i in range(80)}
    pts[80] = np.array([0.0, 0.0, -1.0])  # behind the camera: left out
    X = np.array(list(pts.values()))
    raw = cv2.projectPoints(X[:80].reshape(-1, 1, 3), np.zeros(3), np.zeros(3), rig.cam0.K, dist)[0].reshape(-1, 2)
    pinhole, _ = project(rig.cam0.K, X[:80])
    assert np.abs(raw - pinhole).max() > 5  # the distortion moves the points by pixels
    xy = np.vstack([raw + rng.normal(0, 0.2, raw.shape), [[320.0, 240.0]]]).astype(np.float32)
    res = SimpleNamespace(points=pts, T_world_cam=np.array([np.eye(4)]), rms_after_px=0.3)
    got_ids, got_xy = adjusted_pixels(rig, res, 0, np.arange(81), xy)
    assert got_ids.tolist() == list(range(80))
    np.testing.assert_allclose(got_xy, raw, atol=1e-3)
