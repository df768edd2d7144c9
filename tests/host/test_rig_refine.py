"""``host reprocess`` feeds its disparity offset back as ``rig_refined.yaml``: written, loaded by the
device unchanged, and the on-board triangulation with it is unbiased (issue 10)."""

from __future__ import annotations

import numpy as np
import pytest

from stereopath.device.core.geometry import make_pose
from stereopath.device.core.rig import make_camera, make_rig
from stereopath.device.core.stereo import project
from stereopath.device.estimation.stereo_measure import StereoMeasure
from stereopath.device.estimation.stereo_vo import StereoConfig
from stereopath.device.formats.rig_files import load_rig_yaml
from stereopath.host.reprocess.rig_refine import RIG_REFINED_FILE, report_entry, write_refined_rig
from tests.backend.ba_support import adjust

F, B, CX, CY = 700.0, 0.5, 600.0, 185.0
BIAS_PX = 0.3  # the right image sits 0.3 px too far right: every disparity 0.3 px too small


def _kitti_like_rig():
    K = np.array([[F, 0, CX], [0, F, CY], [0, 0, 1.0]])
    cam0 = make_camera("cam0", K, np.zeros(5), (1200, 370))
    cam1 = make_camera("cam1", K, np.zeros(5), (1200, 370))
    return make_rig(cam0, cam1, np.eye(3), [-B, 0.0, 0.0], name="synthetic")


def _scene(rng, rig, n_kf=6, n_pts=300):
    """A forward drive past points 6-40 m away; the right observations carry the disparity bias."""
    X = np.column_stack([rng.uniform(-12, 12, n_pts), rng.uniform(-2, 2, n_pts), rng.uniform(6, 40, n_pts)])
    T_wc = np.array([make_pose(np.eye(3), [0, 0, 0.8 * k]) for k in range(n_kf)])
    ids = np.arange(n_pts)
    rows = []
    for k in range(n_kf):
        Xc = X - T_wc[k][:3, 3]  # the camera only moves forward
        for cam, uv in ((0, project(rig.cam0.K, Xc)[0]), (1, project(rig.cam1.K, Xc + rig.T)[0] + [BIAS_PX, 0])):
            uv = uv + rng.normal(0, 0.05, uv.shape)
            rows.append(np.column_stack([np.full(n_pts, k), ids, np.full(n_pts, cam), uv]))
    return T_wc, dict(enumerate(X)), np.vstack(rows)


def test_the_refined_rig_round_trip_removes_the_offset(tmp_path):
    
    rng = np.random.default_rng(7)
    rig = _kitti_like_rig()
    T_wc, pts, obs = _scene(rng, rig)
    res = adjust(rig, T_wc, pts, obs, disparity_offset=True, disparity_offset_min_px=0.02)
    assert res.disparity_offset_px == pytest.approx(BIAS_PX, abs=0.02)
    entry = report_entry(rig, {"disparity_offset_px": res.disparity_offset_px})
    assert entry["file"] == RIG_REFINED_FILE
    assert entry["cam1_cx_px"]["after"] == pytest.approx(CX + res.disparity_offset_px)
    assert write_refined_rig(tmp_path, rig, entry, "sessions/s1") == [RIG_REFINED_FILE]
    text = (tmp_path / RIG_REFINED_FILE).read_text()
    assert text.startswith("# stereopath rig refined") and "sessions/s1" in text and "source.rig_file" in text
    assert f"{res.disparity_offset_px:+.4f} px" in text

    loaded = load_rig_yaml(tmp_path / RIG_REFINED_FILE)  # what the device's source.rig_file loads
    assert loaded.cam1.cx == pytest.approx(CX + res.disparity_offset_px, abs=1e-12)
    assert np.array_equal(loaded.cam0.K, rig.cam0.K) and loaded.cam1.fx == F and loaded.cam1.cy == CY
    assert np.array_equal(loaded.R, rig.R) and np.array_equal(loaded.T, rig.T)
    assert loaded.is_rectified  # rows stay aligned: not rectified again, nothing "fixed" on loading

    # the on-board estimator's triangulation: depths of the biased pair too far with the shipped rig,
    # unbiased with the refined one
    X = np.array(list(pts.values()))
    uv0, _ = project(rig.cam0.K, X)
    uv1, _ = project(rig.cam1.K, X + rig.T)
    uv1[:, 0] += BIAS_PX
    rel = {}
    for name, r in (("shipped", rig), ("refined", loaded)):
        Xc, err = StereoMeasure(r, StereoConfig()).triangulate(uv0, uv1)
        assert np.all(err < 0.1)
        rel[name] = np.median(Xc[:, 2] / X[:, 2] - 1)
    assert rel["shipped"] > 0.005  # 0.3 px at 6-40 m: 0.5-4 % too far
    assert abs(rel["refined"]) < 5e-4


def test_no_file_when_no_offset_was_applied(tmp_path):
    rig = _kitti_like_rig()
    for stats in ({"disparity_offset_px": 0.0}, {"disparity_offset_px": None}, {"skipped": "too little"}):
        assert report_entry(rig, stats) is None
    (tmp_path / RIG_REFINED_FILE).write_text("# from an earlier run\n")
    assert write_refined_rig(tmp_path, rig, None, "s") == []
    assert not (tmp_path / RIG_REFINED_FILE).exists()


def test_a_negative_offset_moves_cx_left_and_says_so(tmp_path):
    rig = _kitti_like_rig()
    entry = report_entry(rig, {"disparity_offset_px": -0.25})
    write_refined_rig(tmp_path, rig, entry, "s2")
    loaded = load_rig_yaml(tmp_path / RIG_REFINED_FILE)
    assert loaded.cam1.cx == pytest.approx(CX - 0.25)
    assert "too large" in (tmp_path / RIG_REFINED_FILE).read_text()
