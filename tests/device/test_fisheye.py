"""Fisheye (equidistant) ASL data: EuRoC-style sensor.yaml and Kalibr camchains read, the images seen
through pinhole views, TUM VI's motion-capture ground truth, and the estimator on a fisheye rig.

The fisheye sessions are the simulator's frames, rendered with a TUM VI-like pinhole rig (512 x 512,
f = 190 px, 10 cm baseline), warped into equidistant images with OpenCV's own ``cv2.fisheye`` model
(the same K, TUM VI's lens coefficients) and written in the ASL layout with the calibration files a
fisheye dataset ships."""

import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from stereopath.device.core.fisheye import make_fisheye_camera, pinhole_view
from stereopath.device.errors import CalibrationError
from stereopath.device.estimation.base import run_estimator
from stereopath.device.estimation.registry import make_estimator
from stereopath.device.formats.asl import open_asl
from stereopath.device.formats.rig_files import load_euroc_calibration, load_euroc_rig
from stereopath.device.formats.source import open_source
from stereopath.host.evaluation.evaluate import evaluate

D_FISH = [0.03, -0.02, 0.01, -0.002]  # k1..k4 of a mild wide-angle lens
D_TUMVI = [0.0034823894022493434, 0.0007150348452162257, -0.0020532361418706202, 0.00020293673591811182]


def _tumvi_like(session):
    """The simulator with a TUM VI-like pinhole rig instead of its own (same IMU and body frame)."""
    from stereopath.device.core.rig import make_camera, make_rig

    K = np.array([[190.0, 0, 255.5], [0, 190.0, 255.5], [0, 0, 1]])
    cams = [make_camera(n, K, np.zeros(5), (512, 512)) for n in ("cam0", "cam1")]
    session.rig = make_rig(*cams, np.eye(3), [-0.10, 0, 0], name="tumvi-like", T_body_cam0=session.rig.T_body_cam0)
    return session


def _to_fisheye(img: np.ndarray, K: np.ndarray, D) -> np.ndarray:
    """The pinhole image ``img`` (camera ``K``, no distortion) as the equidistant camera (K, D) sees it."""
    h, w = img.shape
    u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    pts = np.stack([u.ravel(), v.ravel()], 1).reshape(-1, 1, 2)
    rays = cv2.fisheye.undistortPoints(pts, K, np.asarray(D, float)).reshape(-1, 2)
    src = rays @ K[:2, :2].T + K[:2, 2]
    mx = src[:, 0].reshape(h, w).astype(np.float32)
    my = src[:, 1].reshape(h, w).astype(np.float32)
    return cv2.remap(img, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)


def _sensor_yaml(K, D, T_BS, size) -> str:
    rows = ", ".join(repr(float(v)) for v in np.asarray(T_BS).ravel())
    return ("%YAML:1.0\nsensor_type: camera\nT_BS:\n  cols: 4\n  rows: 4\n  data: [" + rows + "]\n"
            f"rate_hz: 20\nresolution: [{size[0]}, {size[1]}]\ncamera_model: pinhole\n"
            f"intrinsics: [{K[0, 0]}, {K[1, 1]}, {K[0, 2]}, {K[1, 2]}]\n"
            "distortion_model: equidistant\n"
            f"distortion_coefficients: {list(map(float, D))}\n")


@pytest.fixture(scope="module")
def fisheye_session(tmp_path_factory):
    """A 100-frame simulated session (TUM VI-like rig) recorded, then turned into a fisheye dataset:
    images warped, ``sensor.yaml`` equidistant, our ``rig.yaml`` removed (the third-party layout)."""
    from stereopath.device.formats.recorder import record_sequence
    from stereopath.device.sim.session import SimConfig, open_sim

    root = tmp_path_factory.mktemp("fisheye")
    pin = root / "pinhole"
    record_sequence(_tumvi_like(open_sim(SimConfig(frames=100, seed=2))), pin, config_dict={"source": "sim"})
    fish = root / "fisheye"
    shutil.copytree(pin, fish)
    seq = open_asl(pin / "mav0")
    rig = seq.rig
    (fish / "mav0" / "rig.yaml").unlink()
    T_b_c1 = rig.T_body_cam0 @ rig.T_cam0_cam1
    for cam, name, T_BS in ((rig.cam0, "cam0", rig.T_body_cam0), (rig.cam1, "cam1", T_b_c1)):
        (fish / "mav0" / name / "sensor.yaml").write_text(_sensor_yaml(cam.K, D_TUMVI, T_BS, cam.size))
        for png in sorted((fish / "mav0" / name / "data").glob("*.png")):
            cv2.imwrite(str(png), _to_fisheye(cv2.imread(str(png), cv2.IMREAD_GRAYSCALE), cam.K, D_TUMVI))
    return pin, fish


def test_pinhole_view_undoes_the_lens():
    K = np.array([[500.0, 0, 319.5], [0, 500.0, 239.5], [0, 0, 1]])
    cam = make_fisheye_camera("cam0", K, D_FISH, (640, 480))
    view = pinhole_view(cam, "cam0")
    assert np.allclose(view.camera.K, K) and not np.any(view.camera.dist)
    # a ray lands in the fisheye image where the view's map says its pinhole pixel comes from
    X = np.array([[0.3, -0.2, 1.0], [-0.5, 0.35, 1.0], [0.0, 0.0, 1.0]])
    uv_pin = X[:, :2] / X[:, 2:] @ K[:2, :2].T + K[:2, 2]
    uv_fish = cv2.fisheye.projectPoints(X.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), K,
                                        np.array(D_FISH))[0].reshape(-1, 2)
    for (u, v), (uf, vf) in zip(uv_pin, uv_fish):
        assert view.map_x[int(round(v)), int(round(u))] == pytest.approx(uf, abs=0.6)
        assert view.map_y[int(round(v)), int(round(u))] == pytest.approx(vf, abs=0.6)
    # and a textured image survives the round trip to within interpolation
    rng = np.random.default_rng(0)
    img = cv2.GaussianBlur(rng.uniform(0, 255, (480, 640)).astype(np.float32), (0, 0), 2.5)
    img = cv2.normalize(img, None, 20, 230, cv2.NORM_MINMAX).astype(np.uint8)
    back = view.apply(_to_fisheye(img, K, D_FISH)).astype(int)
    assert np.median(np.abs(back[10:-10, 10:-10] - img[10:-10, 10:-10])) <= 2


def test_a_fisheye_model_that_folds_back_is_refused():
    K = np.array([[500.0, 0, 319.5], [0, 500.0, 239.5], [0, 0, 1]])
    with pytest.raises(CalibrationError, match="outside"):
        pinhole_view(make_fisheye_camera("cam1", K, [3.0, 2.0, 1.0, 1.0], (640, 480)), "cam1")
    with pytest.raises(CalibrationError, match="cam0.distortion"):
        make_fisheye_camera("cam0", K, [0.1, 0.2, 0.3], (640, 480))


@pytest.mark.slow
def test_fisheye_dataset_reads_as_the_pinhole_rig_it_was_made_from(fisheye_session):
    pin, fish = fisheye_session
    a, b = open_asl(pin / "mav0"), open_asl(fish / "mav0")
    assert b.views[0] is not None and b.views[1] is not None
    assert np.allclose(b.rig.cam0.K, a.rig.cam0.K) and not np.any(b.rig.cam0.dist)
    assert np.allclose(b.rig.T, a.rig.T, atol=1e-9) and np.allclose(b.rig.R, a.rig.R, atol=1e-9)
    assert np.allclose(b.rig.T_body_cam0, a.rig.T_body_cam0)
    fa, fb = a.frame(10), b.frame(10)
    assert fb.left.shape == fa.left.shape
    diff = np.abs(fb.left.astype(int) - fa.left.astype(int))[8:-8, 8:-8]
    assert np.median(diff) <= 2 and np.mean(diff) < 4
    # the same images without their lens model are a different picture
    raw = cv2.imread(str(b.image_paths(10)[0]), cv2.IMREAD_GRAYSCALE).astype(int)
    assert np.mean(np.abs(raw - fa.left.astype(int))[8:-8, 8:-8]) > 3 * np.mean(diff)
    with pytest.raises(CalibrationError, match="pinhole views"):
        load_euroc_rig(fish / "mav0")  # the rig alone would be read with the fisheye images


@pytest.mark.slow
def test_estimator_tracks_the_fisheye_rig_as_the_pinhole_one(fisheye_session):
    pin, fish = fisheye_session
    out = []
    for d in (pin, fish):
        seq = open_source(f"session:{d}")
        est = make_estimator("stereo", seq.rig)
        run = run_estimator(est, seq.frames(), seq.imu)
        out.append((run, evaluate(seq.groundtruth, run.trajectory)))
    (run_p, m_p), (run_f, m_f) = out
    assert run_f.frames_tracked == run_p.frames_tracked == 100
    assert m_f["ate_rmse_m"] < 1.5 * m_p["ate_rmse_m"] + 3e-4


def _camchain(rig, T_cam0_imu, D, chain=True) -> str:
    def mat(T):
        return "\n".join(f"  - [{', '.join(repr(float(v)) for v in row)}]" for row in T)

    def cam(c, name, T_cam_imu, extra=""):
        return (f"{name}:\n  T_cam_imu:\n{mat(T_cam_imu)}\n{extra}  cam_overlaps: [1]\n  camera_model: pinhole\n"
                f"  distortion_coeffs: {list(map(float, D))}\n  distortion_model: equidistant\n"
                f"  intrinsics: [{c.fx}, {c.fy}, {c.cx}, {c.cy}]\n  resolution: [{c.size[0]}, {c.size[1]}]\n"
                f"  rostopic: /{name}/image_raw\n")

    T_c1_c0 = rig.T_cam1_cam0
    extra = "  T_cn_cnm1:\n" + mat(T_c1_c0).replace("  -", "    -") + "\n" if chain else ""
    return cam(rig.cam0, "cam0", T_cam0_imu) + cam(rig.cam1, "cam1", T_c1_c0 @ T_cam0_imu, extra)


def test_kalibr_camchain_and_mocap_ground_truth_of_the_tum_vi_layout(fisheye_session, tmp_path):
    """TUM VI ships its calibration as a Kalibr camchain in ``dso/`` and its ground truth as the
    motion capture's IMU poses in ``mav0/mocap0/data.csv``."""
    from stereopath.device.core.geometry import invert_pose

    _, fish = fisheye_session
    ref = open_asl(fish / "mav0")
    d = tmp_path / "dataset-room1_512_16"
    shutil.copytree(fish / "mav0", d / "mav0")
    for name in ("cam0", "cam1"):  # sensor files without a calibration
        (d / "mav0" / name / "sensor.yaml").write_text("sensor_type: camera\nrate_hz: 20\n")
    with pytest.raises(CalibrationError, match="camchain"):
        open_asl(d / "mav0")
    (d / "dso").mkdir()
    (d / "dso" / "camchain.yaml").write_text(_camchain(ref.rig, invert_pose(ref.rig.T_body_cam0), D_TUMVI))
    # the body (IMU) poses of the ground truth, as TUM VI's mocap0 gives them
    gt = ref.groundtruth
    body = gt.T_world_cam @ invert_pose(ref.rig.T_body_cam0)
    (d / "mav0" / "mocap0").mkdir()
    rows = ["#timestamp [ns],p_RS_R_x [m],p_RS_R_y [m],p_RS_R_z [m],q_RS_w [],q_RS_x [],q_RS_y [],q_RS_z []"]
    from scipy.spatial.transform import Rotation

    for t, T in zip(gt.t_ns, body):
        x, y, z, w = Rotation.from_matrix(T[:3, :3]).as_quat()
        rows.append(",".join([str(int(t))] + [repr(float(v)) for v in (*T[:3, 3], w, x, y, z)]))
    (d / "mav0" / "mocap0" / "data.csv").write_text("\n".join(rows) + "\n")
    seq = open_asl(d)
    calib = load_euroc_calibration(d / "mav0")
    assert calib.source.endswith("camchain.yaml")
    assert np.allclose(seq.rig.T, ref.rig.T, atol=1e-9) and np.allclose(seq.rig.T_body_cam0, ref.rig.T_body_cam0, atol=1e-9)
    assert seq.views[0] is not None
    assert np.array_equal(seq.frame(5).left, ref.frame(5).left)
    g = seq.groundtruth
    assert g is not None and len(g.t_ns) == len(gt.t_ns)
    assert np.allclose(g.T_world_cam, gt.T_world_cam, atol=1e-6)


def test_camchain_without_t_cn_cnm1_and_broken_camchains(fisheye_session, tmp_path):
    """The stereo extrinsics from the two T_cam_imu when T_cn_cnm1 is absent; a broken camchain is
    refused with the file and the field named."""
    from stereopath.device.core.geometry import invert_pose

    _, fish = fisheye_session
    ref = open_asl(fish / "mav0")
    m = tmp_path / "mav0"
    shutil.copytree(fish / "mav0", m)
    for name in ("cam0", "cam1"):
        (m / name / "sensor.yaml").unlink()
    good = _camchain(ref.rig, invert_pose(ref.rig.T_body_cam0), D_TUMVI, chain=False)
    chain = tmp_path / "camchain-imucam-room1.yaml"
    chain.write_text(good)
    (tmp_path / "camchain-room1.yaml").write_text("cam0: [1, 2]\n")  # a camera-only one: the imucam wins
    seq = open_asl(m)
    assert np.allclose(seq.rig.R, ref.rig.R, atol=1e-9) and np.allclose(seq.rig.T, ref.rig.T, atol=1e-9)
    assert np.allclose(seq.rig.T_body_cam0, ref.rig.T_body_cam0, atol=1e-9)
    T_bad = invert_pose(ref.rig.T_body_cam0)
    T_bad[:3, :3] *= 1.5  # not a rotation
    i1 = good.index("cam1:")
    broken = {
        "cam1.distortion: not numeric": good[:i1] + good[i1:].replace("distortion_coeffs: [0.00", "distortion_coeffs: [a"),
        "cam0.distortion: expected shape": good.replace(f"distortion_coeffs: [{D_TUMVI[0]!r}, ", "distortion_coeffs: [", 1),
        "cam0.intrinsics must be": good.replace("intrinsics: [", "intrinsics: [1, ", 1),
        "cam0.distortion_model 'omni'": good.replace("distortion_model: equidistant", "distortion_model: omni", 1),
        "cam0.T_cam_imu rotation: not a rotation": _camchain(ref.rig, T_bad, D_TUMVI, chain=False),
        "missing cam1": good[:i1],
    }
    for what, text in broken.items():
        chain.write_text(text)
        with pytest.raises(CalibrationError, match=what.replace("(", r"\(")) as info:
            open_asl(m)
        assert str(chain) in str(info.value)


# ---------------------------------------------------------------------------------------------
# the device: a Kalibr camchain as source.rig_file (a fisheye rig calibrated with Kalibr)


def test_rig_file_is_our_yaml_or_a_kalibr_camchain(fisheye_session, tmp_path):
    from stereopath.device.core.geometry import invert_pose
    from stereopath.device.formats.rig_files import load_rig_file, load_rig_yaml

    ours = Path(__file__).resolve().parents[2] / "firmware_cfg" / "rig_paper.yaml"
    calib = load_rig_file(ours)
    assert not calib.has_views and np.allclose(calib.rig.T, load_rig_yaml(ours).T)
    ref = open_asl(fisheye_session[1] / "mav0")
    chain = tmp_path / "camchain-imucam-box.yaml"
    chain.write_text(_camchain(ref.rig, invert_pose(ref.rig.T_body_cam0), D_TUMVI))
    calib = load_rig_file(chain)
    assert calib.has_views and np.allclose(calib.rig.T, ref.rig.T, atol=1e-9)
    assert np.allclose(calib.rig.T_body_cam0, ref.rig.T_body_cam0, atol=1e-9)
    radtan = tmp_path / "camchain-radtan.yaml"
    radtan.write_text(chain.read_text().replace("distortion_model: equidistant", "distortion_model: radtan"))
    calib = load_rig_file(radtan)
    assert not calib.has_views and np.allclose(calib.rig.cam0.dist, D_TUMVI)
    with pytest.raises(CalibrationError, match="not found"):
        load_rig_file(tmp_path / "nope.yaml")


def test_replay_refuses_a_fisheye_rig_file(fisheye_session, tmp_path):
    """Recorded images are either pinhole already (a session: the box recorded them through its views)
    or read through their own lens model (a fisheye dataset): a fisheye rig file over them would
    resample them twice, so replay refuses it (a configuration error of the service)."""
    from stereopath.device.capture.sources import create_source
    from stereopath.device.core.config import from_mapping
    from stereopath.device.core.geometry import invert_pose
    from stereopath.device.settings import SourceSettings

    pin, fish = fisheye_session
    ref = open_asl(fish / "mav0")
    chain = tmp_path / "camchain-imucam-box.yaml"
    chain.write_text(_camchain(ref.rig, invert_pose(ref.rig.T_body_cam0), D_TUMVI))
    settings = from_mapping(SourceSettings, {"backend": "replay", "rig_file": str(chain), "replay": {"count": 2}})
    for spec in (f"session:{pin}", f"euroc:{fish}"):
        src = create_source(settings, sequence=open_source(spec))
        with pytest.raises(CalibrationError, match="cannot be replayed over recorded images"):
            src.open()
    # a pinhole rig file (our YAML) over the same data is taken as before
    ok = from_mapping(SourceSettings, {"backend": "replay", "rig_file": str(pin / "mav0" / "rig.yaml"),
                                       "replay": {"count": 2}})
    with create_source(ok, sequence=open_source(f"session:{pin}")) as src:
        assert len(list(src)) == 2 and np.allclose(src.rig.cam0.K, ref.rig.cam0.K)


def test_a_rig_of_pinhole_views_says_so_in_its_file_and_in_the_refined_rig(tmp_path):
    """A fisheye rig's pinhole rig carries the calibration it is a view of through rig.yaml (what the
    recorder writes), and the refined rig of its sessions is advised for the host only."""
    from stereopath.device.core.rig import make_camera, make_rig
    from stereopath.device.formats.rig_files import load_rig_file, load_rig_yaml, save_rig_yaml
    from stereopath.host.reprocess.rig_refine import comment, report_entry

    K = np.array([[190.0, 0, 255.5], [0, 190.0, 255.5], [0, 0, 1]])
    cams = [make_camera(n, K, np.zeros(5), (512, 512)) for n in ("cam0", "cam1")]
    chain = tmp_path / "camchain.yaml"
    chain.write_text(_camchain(make_rig(*cams, np.eye(3), [-0.1, 0, 0]), np.eye(4), D_TUMVI))
    rig = load_rig_file(chain).rig
    assert rig.views_of == str(chain)
    save_rig_yaml(rig, tmp_path / "rig.yaml")
    back = load_rig_yaml(tmp_path / "rig.yaml")
    assert back.views_of == str(chain) and np.allclose(back.cam0.K, K)
    entry = report_entry(back, {"disparity_offset_px": 0.2})
    assert "not the device's source.rig_file" in entry["use"] and str(chain) in entry["use"]
    assert "not the device's source.rig_file" in comment(back, 0.2, "s1")
    plain = make_rig(*cams, np.eye(3), [-0.1, 0, 0])
    assert plain.views_of == "" and "device configuration source.rig_file" in report_entry(
        plain, {"disparity_offset_px": 0.2})["use"]


def test_our_rig_yaml_is_never_taken_for_a_camchain(tmp_path):
    import yaml

    from stereopath.device.formats.rig_files import is_kalibr_camchain

    ours = yaml.safe_load((Path(__file__).resolve().parents[2] / "firmware_cfg" / "rig_paper.yaml").read_text())
    ours["cam0"]["camera_model"] = "pinhole"  # a note a user might add
    ours["cam0"]["distortion_coeffs"] = [0, 0, 0, 0]
    ours["cam0"]["resolution"] = [640, 480]
    assert not is_kalibr_camchain(ours)


def test_picamera2_frames_go_through_the_fisheye_views_of_the_rig_file(tmp_path):
    """The live path: a picamera2 pair (the fake, showing one textured pair) with a Kalibr fisheye
    camchain as source.rig_file delivers every exposure through the views; without it, as captured."""
    from stereopath.device.capture.sources import create_source
    from stereopath.device.core.rig import make_camera, make_rig
    from stereopath.device.formats.rig_files import load_rig_file
    from tests.fakes.fake_picamera2 import FakeCameraWorld
    from tests.fakes.standins import source_settings, take

    K = np.array([[40.0, 0, 31.5], [0, 40.0, 23.5], [0, 0, 1]])
    cams = [make_camera(n, K, np.zeros(5), (64, 48)) for n in ("cam0", "cam1")]
    rig = make_rig(*cams, np.eye(3), [-0.06, 0, 0])
    chain = tmp_path / "camchain.yaml"
    chain.write_text(_camchain(rig, np.eye(4), D_FISH))
    views = load_rig_file(chain).views
    rng = np.random.default_rng(4)
    pair = tuple(cv2.GaussianBlur(rng.uniform(0, 255, (48, 64)).astype(np.float32), (0, 0), 1.5).astype(np.uint8)
                 for _ in range(2))
    out = {}
    for name, kw in (("raw", {}), ("views", {"rig_file": str(chain)})):
        src = create_source(source_settings("picamera2", [64, 48], 500, **kw), api=FakeCameraWorld(images=[pair]).api())
        with src:
            out[name] = take(src, 4)
            if name == "views":
                assert np.allclose(src.rig.cam0.K, K) and not np.any(src.rig.cam0.dist)
    raw = out["raw"][0]
    assert {raw.left.tobytes(), raw.right.tobytes()} == {pair[0].tobytes(), pair[1].tobytes()}
    for seen in out["views"]:
        assert np.array_equal(seen.left, views[0].apply(raw.left))
        assert np.array_equal(seen.right, views[1].apply(raw.right))
        assert not np.array_equal(seen.left, raw.left)


def test_picamera2_refuses_a_fisheye_rig_file_for_another_image_size(tmp_path):
    from stereopath.device.capture.sources import create_source
    from stereopath.device.core.rig import make_camera, make_rig
    from tests.fakes.fake_picamera2 import FakeCameraWorld
    from tests.fakes.standins import source_settings

    K = np.array([[40.0, 0, 31.5], [0, 40.0, 23.5], [0, 0, 1]])
    cams = [make_camera(n, K, np.zeros(5), (64, 48)) for n in ("cam0", "cam1")]
    chain = tmp_path / "camchain.yaml"
    chain.write_text(_camchain(make_rig(*cams, np.eye(3), [-0.06, 0, 0]), np.eye(4), D_FISH))
    world = FakeCameraWorld()
    src = create_source(source_settings("picamera2", [48, 48], 500, rig_file=str(chain)), api=world.api())
    with pytest.raises(CalibrationError, match="calibrated at 64x48 but the picamera2 source delivers 48x48"):
        src.open()
    assert all(cam._thread is None or not cam._thread.is_alive() for cam in world.instances)  # cameras stopped


def test_picamera2_refuses_a_pinhole_rig_file_for_another_image_size(tmp_path):
    """A pinhole rig YAML's image_size must be the size the cameras deliver, as a fisheye camera's is."""
    from stereopath.device.capture.sources import create_source
    from stereopath.device.core.rig import make_camera, make_rig
    from stereopath.device.formats.rig_files import save_rig_yaml
    from tests.fakes.fake_picamera2 import FakeCameraWorld
    from tests.fakes.standins import source_settings

    K = np.array([[40.0, 0, 31.5], [0, 40.0, 23.5], [0, 0, 1]])
    cams = [make_camera(n, K, np.zeros(5), (128, 96)) for n in ("cam0", "cam1")]
    path = tmp_path / "rig.yaml"
    save_rig_yaml(make_rig(*cams, np.eye(3), [-0.06, 0, 0]), path)
    world = FakeCameraWorld()
    src = create_source(source_settings("picamera2", [64, 48], 500, rig_file=str(path)), api=world.api())
    with pytest.raises(CalibrationError, match="cam0 is calibrated at 128x96 but the picamera2 source delivers 64x48"):
        src.open()
    assert all(cam._thread is None or not cam._thread.is_alive() for cam in world.instances)  # cameras stopped
