import logging

import numpy as np
import pytest

from stereopath.device.errors import CalibrationError
from stereopath.device.core.rig import paper_rig, rig_from_dict, rig_to_dict
from stereopath.device.formats.rig_files import load_euroc_rig, load_kitti_calib, load_rig_yaml, save_rig_yaml


def test_paper_yaml_equals_builtin_rig(repo_root, caplog):
    with caplog.at_level(logging.INFO):
        y = load_rig_yaml(repo_root / "firmware_cfg" / "rig_paper.yaml")
    notes = [r for r in caplog.records if "orthonormal" in r.getMessage()]
    # Table 1's R is rounded (4 decimals): projected once, said at info level (nothing for a user to do)
    assert len(notes) == 1 and notes[0].levelno == logging.INFO
    assert notes[0].getMessage().startswith(f"rig {y.name!r}: R is not exactly orthonormal")
    r = paper_rig()
    assert np.allclose(y.R, r.R) and np.allclose(y.T, r.T) and np.allclose(y.cam0.K, r.cam0.K)
    assert np.allclose(y.T, [-0.047917, -0.000142, -0.013373])  # mm -> m
    assert np.allclose(y.R.T @ y.R, np.eye(3), atol=1e-12)


def test_a_rotation_further_from_orthonormal_than_rounding_is_a_warning(caplog):
    d = rig_to_dict(paper_rig())
    R = np.asarray(d["R_cam1_cam0"], float)
    d["R_cam1_cam0"] = (R + np.array([[0.0, 3e-3, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]])).tolist()
    with caplog.at_level(logging.INFO):
        rig = rig_from_dict(d)
    notes = [r for r in caplog.records if "orthonormal" in r.getMessage()]
    assert len(notes) == 1 and notes[0].levelno == logging.WARNING
    assert np.allclose(rig.R.T @ rig.R, np.eye(3), atol=1e-12)


def test_rectification_of_paper_rig():
    rect = paper_rig().rectification()
    assert rect.baseline_m == pytest.approx(np.linalg.norm([0.047917, 0.000142, 0.013373]), rel=1e-6)
    # a point in front of the rig lands on the same rectified row in both cameras
    import cv2
    rig = paper_rig()
    X = np.array([[0.1, -0.05, 1.2]])
    p0 = cv2.projectPoints(X, np.zeros(3), np.zeros(3), rig.cam0.K, rig.cam0.dist)[0].reshape(-1, 2)
    p1 = cv2.projectPoints(X @ rig.R.T + rig.T, np.zeros(3), np.zeros(3), rig.cam1.K, rig.cam1.dist)[0].reshape(-1, 2)
    r0 = cv2.undistortPoints(p0.reshape(-1, 1, 2), rig.cam0.K, rig.cam0.dist, R=rect.R0, P=rect.P0).reshape(2)
    r1 = cv2.undistortPoints(p1.reshape(-1, 1, 2), rig.cam1.K, rig.cam1.dist, R=rect.R1, P=rect.P1).reshape(2)
    assert abs(r0[1] - r1[1]) < 1e-6
    Z_rect = rect.f * rect.baseline_m / (r0[0] - r1[0])
    assert Z_rect > 0


def test_yaml_round_trip(tmp_path):
    r = paper_rig(T_body_cam0=np.eye(4))
    save_rig_yaml(r, tmp_path / "rig.yaml", comment="test")
    r2 = load_rig_yaml(tmp_path / "rig.yaml")
    assert np.allclose(r2.R, r.R) and np.allclose(r2.T, r.T) and np.allclose(r2.T_body_cam0, np.eye(4))


@pytest.mark.parametrize(
    "mutate, field",
    [
        (lambda d: d.__setitem__("R_cam1_cam0", [[1, 0.5, 0], [0, 1, 0], [0, 0, 1]]), "R"),
        (lambda d: d.__setitem__("R_cam1_cam0", [[-1, 0, 0], [0, 1, 0], [0, 0, 1]]), "det"),
        (lambda d: d["cam0"].__setitem__("intrinsics", [-500, 500, 320, 240]), "focal length"),
        (lambda d: d["cam1"].__setitem__("intrinsics", [500, 0, 320, 240]), "focal length"),
        (lambda d: d.__setitem__("T_cam1_cam0_m", [0, 0, 0]), "zero baseline"),
        (lambda d: d.__setitem__("T_cam1_cam0_m", [0.1, 0]), "T"),
        (lambda d: d.__setitem__("R_cam1_cam0", [[1, 0], [0, 1]]), "R"),
        (lambda d: d["cam0"].__setitem__("distortion", [0, 0, 0]), "cam0.distortion"),
        (lambda d: d.pop("cam1"), "cam1"),
        (lambda d: d.__setitem__("baseline", 1), "unknown"),
    ],
)
def test_validation_names_the_field(mutate, field):
    d = rig_to_dict(paper_rig())
    mutate(d)
    with pytest.raises(CalibrationError, match=field):
        rig_from_dict(d)


@pytest.mark.parametrize("size", [[float("inf"), 480], [640, float("nan")], [640.7, 480], [True, 480],
                                  [480, 1.5], ["wide", 480]])
def test_image_size_must_be_whole_pixels(size):
    d = rig_to_dict(paper_rig())
    d["cam1"]["image_size"] = size
    with pytest.raises(CalibrationError, match=r"cam1\.image_size: expected \[width, height\] in whole pixels"):
        rig_from_dict(d)


def test_image_size_accepts_whole_floats_and_numpy_ints():
    d = rig_to_dict(paper_rig())
    d["cam0"]["image_size"] = [640.0, np.int64(480)]
    d["cam1"]["image_size"] = ["640", 480]
    rig = rig_from_dict(d)
    assert rig.cam0.size == (640, 480) and rig.cam1.size == (640, 480)
    assert all(type(v) is int for v in rig.cam0.size)


def test_yaml_image_size_inf_is_a_calibration_error(tmp_path):
    save_rig_yaml(paper_rig(), tmp_path / "rig.yaml")
    text = (tmp_path / "rig.yaml").read_text()
    assert "image_size: [640, 480]" in text
    (tmp_path / "rig.yaml").write_text(text.replace("image_size: [640, 480]", "image_size: [.inf, 480]", 1))
    with pytest.raises(CalibrationError, match="image_size"):
        load_rig_yaml(tmp_path / "rig.yaml")


def test_missing_and_broken_files(tmp_path):
    with pytest.raises(CalibrationError, match="not found"):
        load_rig_yaml(tmp_path / "nope.yaml")
    (tmp_path / "bad.yaml").write_text("cam0: [unclosed\n")
    with pytest.raises(CalibrationError, match="invalid YAML"):
        load_rig_yaml(tmp_path / "bad.yaml")
    (tmp_path / "calib.txt").write_text("P0: 1 2 3\n")
    with pytest.raises(CalibrationError, match="P0"):
        load_kitti_calib(tmp_path / "calib.txt", (100, 100))


def test_kitti_calib(data_dir):
    rig = load_kitti_calib(data_dir / "kitti_odometry/sequences/06/calib.txt", (1226, 370))
    assert rig.cam0.fx == pytest.approx(707.0912)
    assert rig.baseline_m == pytest.approx(0.537, abs=1e-3)
    assert rig.is_rectified


def test_euroc_rig(data_dir):
    rig = load_euroc_rig(data_dir / "euroc_v1_01_head/mav0")
    assert rig.cam0.size == (752, 480)
    assert rig.baseline_m == pytest.approx(0.110, abs=2e-3)  # EuRoC's stereo baseline is about 11 cm
    assert rig.T[0] < 0  # right camera to the right: x_cam1 = R x_cam0 + T has T_x < 0
    assert rig.T_body_cam0 is not None and rig.cam0.dist.size == 4
