"""`stereopath host export`: COLMAP, nerfstudio and MCAP round trips through their real readers."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from stereopath.device.errors import ConfigError, DatasetError

FRAMES = 24


@pytest.fixture(scope="module")
def session(tmp_path_factory) -> Path:
    from stereopath.device.formats.recorder import record_sequence
    from stereopath.device.sim.session import SimConfig, open_sim

    d = tmp_path_factory.mktemp("export") / "session"
    record_sequence(open_sim(SimConfig(frames=FRAMES)), d, config_dict={"source": "sim"})
    return d


@pytest.fixture(scope="module")
def reprocessed(session, tmp_path_factory) -> Path:
    """The session reprocessed once (no dense model: the exports read the path, points and tracks)."""
    from stereopath.host.reprocess.pipeline import RunChoices, reprocess_session

    out = tmp_path_factory.mktemp("export") / "reprocessed"
    reprocess_session(session, out, preset="quick", run=RunChoices(do_map=False, progress=False))
    return out


@pytest.fixture(scope="module")
def source(reprocessed):
    from stereopath.host.export.result import open_result

    return open_result(reprocessed)


@pytest.fixture(scope="module")
def colmap_out(reprocessed, tmp_path_factory) -> Path:
    from stereopath.host.export.run import export_result

    out = tmp_path_factory.mktemp("export") / "colmap"
    export_result(reprocessed, out, "colmap", progress=False)
    return out


def _colmap_residuals(rec) -> np.ndarray:
    """pycolmap's own projection of every point into every image of its track, minus the stored pixel."""
    res = []
    for p in rec.points3D.values():
        for el in p.track.elements:
            im = rec.images[el.image_id]
            res.append(im.project_point(p.xyz) - im.points2D[el.point2D_idx].xy)
    return np.array(res)


@pytest.mark.slow
def test_colmap_model_reads_back_with_our_rig_poses_and_errors(colmap_out, source):
    import pycolmap

    from stereopath.device.core.geometry import invert_pose
    from stereopath.host.export.conventions import T_cam1_cam0

    rec = pycolmap.Reconstruction(str(colmap_out / "sparse" / "0"))
    n_kf = len(source.keyframes)
    assert n_kf >= 3
    assert len(rec.rigs) == 1 and len(rec.cameras) == 2 and len(rec.frames) == n_kf and rec.num_reg_images() == 2 * n_kf
    assert rec.num_points3D() == len(source.point_ids) > 1000
    rig = rec.rigs[1]
    T10 = rig.sensor_from_rig(pycolmap.sensor_t(type=pycolmap.SensorType.CAMERA, id=2)).matrix()
    assert np.allclose(T10, T_cam1_cam0(source.rig.R, source.rig.T)[:3], atol=1e-9)
    for kf in source.keyframes:
        left = rec.images[2 * kf.k + 1]
        assert np.allclose(left.cam_from_world().matrix(), invert_pose(kf.T_world_cam0)[:3], atol=1e-9)
        assert (colmap_out / "images" / left.name).is_file()
    r = _colmap_residuals(rec)
    assert len(r) == len(source.observations)
    rms_colmap = float(np.sqrt(np.mean(np.sum(r ** 2, axis=1) / 2)))
    assert abs(rms_colmap - source.ba_stats["rms_after_px"]) < 0.05
    colours = np.array([p.color for p in rec.points3D.values()])
    assert colours.std() > 5  # read from the images, not a constant
    summary = json.loads((colmap_out / "export.json").read_text())
    assert summary["mean_reprojection_error_px"] == pytest.approx(rec.compute_mean_reprojection_error(), abs=1e-9)


def test_pycolmap_bundle_adjustment_from_our_model_moves_the_poses_less_than_their_error(colmap_out, reprocessed):
    """COLMAP's own bundle adjustment (calibration and rig held, as ours holds them) starting from the
    exported model: the cameras move by much less than the adjusted path's error against the ground truth."""
    import pycolmap

    rec = pycolmap.Reconstruction(str(colmap_out / "sparse" / "0"))
    before = {i: im.projection_center().copy() for i, im in rec.images.items()}
    options = pycolmap.BundleAdjustmentOptions()
    options.refine_focal_length = options.refine_principal_point = options.refine_extra_params = False
    options.refine_sensor_from_rig = False
    options.print_summary = False
    pycolmap.bundle_adjustment(rec, options)
    moved = max(float(np.linalg.norm(im.projection_center() - before[i])) for i, im in rec.images.items())
    ate = json.loads((reprocessed / "report.json").read_text())["ate_rmse_m"]
    assert 0 < moved < 0.5 * ate, (moved, ate)


def test_colmap_text_model(reprocessed, tmp_path):
    import pycolmap

    from stereopath.host.export.run import export_result

    export_result(reprocessed, tmp_path / "t", "colmap", progress=False, text=True)
    assert (tmp_path / "t" / "sparse" / "0" / "points3D.txt").is_file()
    assert pycolmap.Reconstruction(str(tmp_path / "t" / "sparse" / "0")).num_points3D() > 1000


@pytest.fixture(scope="module")
def nerfstudio_out(reprocessed, tmp_path_factory) -> Path:
    from stereopath.host.export.run import export_result

    out = tmp_path_factory.mktemp("export") / "nerfstudio"
    export_result(reprocessed, out, "nerfstudio", progress=False)
    return out


def test_every_point_projects_through_transforms_json_onto_its_observation(nerfstudio_out, source):
    """Read transforms.json as nerfstudio's dataparser does (per-frame fl_x/fl_y/cx/cy, OpenGL camera to
    world) and project every bundle-adjusted point into every image that observed it."""
    from stereopath.host.export.conventions import project_opengl
    from stereopath.host.backend.ba_common import reprojection_residuals

    T_kf = np.array([kf.T_world_cam0 for kf in source.keyframes])
    meta = json.loads((nerfstudio_out / "transforms.json").read_text())
    assert meta["camera_model"] == "OPENCV" and meta["ply_file_path"] == "sparse_pc.ply"
    assert np.allclose(meta["applied_transform"], np.eye(4)[:3])
    frames = {(f["keyframe"], int(f["camera"][-1])): f for f in meta["frames"]}
    assert len(frames) == len(meta["frames"]) == 2 * len(source.keyframes)
    pts = dict(zip(source.point_ids.tolist(), source.point_xyz))
    errors = []
    for (k, cam), f in frames.items():
        assert (nerfstudio_out / f["file_path"]).is_file()
        assert (f["w"], f["h"]) == tuple(source.rig.cam0.size)
        rows = source.observations[(source.observations[:, 0] == k) & (source.observations[:, 2] == cam)]
        X = np.array([pts[int(i)] for i in rows[:, 1]])
        uv, front = project_opengl((f["fl_x"], f["fl_y"]), (f["cx"], f["cy"]), np.array(f["transform_matrix"]), X)
        assert front.all()
        errors.append(np.linalg.norm(uv - rows[:, 3:5], axis=1))
        # the same residuals as the bundle adjustment's own projection (its disparity offset included)
        r, _ = reprojection_residuals(source.rig, T_kf, pts, rows[:, :5])
        assert np.allclose(errors[-1], np.linalg.norm(r, axis=1), atol=1e-6)
    e = np.concatenate(errors)
    assert len(e) == len(source.observations)
    # the adjusted points' residuals as the bundle adjustment left them: sub-pixel but for a few of the
    # observations it kept (within its 3 px outlier gate)
    assert np.sqrt(np.mean(e ** 2 / 2)) < 0.5 and np.mean(e < 1.0) > 0.99, (np.sqrt(np.mean(e ** 2 / 2)), e.max())


def test_transforms_json_matches_nerfstudio_colmap_conversion_of_our_colmap_model(nerfstudio_out, colmap_out):
    """nerfstudio's colmap_to_json (keep_original_world_coordinate): c2w = inv(w2c), columns 1 and 2
    negated; applied to our COLMAP export it gives our transforms.json, image for image."""
    import pycolmap

    rec = pycolmap.Reconstruction(str(colmap_out / "sparse" / "0"))
    meta = json.loads((nerfstudio_out / "transforms.json").read_text())
    ours = {f["file_path"]: np.array(f["transform_matrix"]) for f in meta["frames"]}
    for im in rec.images.values():
        w2c = np.vstack([im.cam_from_world().matrix(), [0, 0, 0, 1]])
        c2w = np.linalg.inv(w2c)
        c2w[0:3, 1:3] *= -1
        assert np.allclose(ours[f"images/{im.name}"], c2w, atol=1e-9)
        cam = rec.cameras[im.camera_id]
        f = next(fr for fr in meta["frames"] if fr["file_path"] == f"images/{im.name}")
        assert np.allclose([f["fl_x"], f["fl_y"], f["cx"], f["cy"]], cam.params)


def test_sparse_pc_ply_reads_back_with_open3d(nerfstudio_out, source):
    import open3d as o3d

    pc = o3d.io.read_point_cloud(str(nerfstudio_out / "sparse_pc.ply"))
    assert np.allclose(np.asarray(pc.points), source.point_xyz, atol=1e-5)  # float32
    assert pc.has_colors() and np.asarray(pc.colors).std() > 0.02


def _read_mcap(path: Path) -> dict[str, list]:
    from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
    from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
    from foxglove_schemas_protobuf.PointCloud_pb2 import PointCloud
    from foxglove_schemas_protobuf.PoseInFrame_pb2 import PoseInFrame
    from mcap.reader import make_reader

    classes = {"foxglove.FrameTransform": FrameTransform, "foxglove.PoseInFrame": PoseInFrame,
               "foxglove.CompressedImage": CompressedImage, "foxglove.PointCloud": PointCloud}
    out: dict[str, list] = {}
    with open(path, "rb") as fh:
        reader = make_reader(fh)
        for schema, channel, message in reader.iter_messages():
            if channel.message_encoding == "json":
                msg = json.loads(message.data)
            else:
                assert channel.message_encoding == "protobuf" and schema.encoding == "protobuf"
                msg = classes[schema.name].FromString(message.data)
            out.setdefault(channel.topic, []).append((message.log_time, msg))
    return out


def _pose(msg) -> np.ndarray:
    from stereopath.device.core.geometry import quat_xyzw_to_matrix

    p, q = msg.pose.position, msg.pose.orientation
    T = np.eye(4)
    T[:3, :3] = quat_xyzw_to_matrix(np.array([q.x, q.y, q.z, q.w]))
    T[:3, 3] = [p.x, p.y, p.z]
    return T


def test_mcap_round_trip_gives_back_counts_times_and_poses(reprocessed, source, session, tmp_path):
    from stereopath.host.export.run import export_result

    export_result(reprocessed, tmp_path / "m", "mcap", progress=False)
    got = _read_mcap(tmp_path / "m" / "scan.mcap")
    t = source.t_ns
    assert [m[0] for m in got["/pose"]] == t.tolist()
    assert np.allclose([_pose(m) for _, m in got["/pose"]], source.T_world_cam0, atol=1e-9)
    tf = [m for _, m in got["/tf"]]
    assert len(tf) == len(t) + 1 and (tf[0].parent_frame_id, tf[0].child_frame_id) == ("cam0", "cam1")
    assert all((m.parent_frame_id, m.child_frame_id) == ("world", "cam0") for m in tf[1:])
    for cam in ("cam0", "cam1"):
        imgs = got[f"/{cam}/image"]
        assert [m[0] for m in imgs] == t.tolist() and all(m.format == "png" for _, m in imgs)
    first = got["/cam0/image"][0][1].data
    assert first == (session / "mav0" / "cam0" / "data" / f"{t[0]}.png").read_bytes()
    within = np.flatnonzero((source.imu.t_ns >= t[0]) & (source.imu.t_ns <= t[-1]))
    assert [m[0] for m in got["/imu"]] == source.imu.t_ns[within].tolist()
    assert got["/imu"][5][1]["angular_velocity"]["x"] == pytest.approx(source.imu.gyro_rad_s[within[5], 0])
    (_, cloud), = got["/map"]
    assert len(cloud.data) == cloud.point_stride * len(source.point_ids)
    xyz = np.frombuffer(cloud.data, np.dtype([("p", "<f4", 3), ("c", "u1", 4)]))["p"]
    assert np.allclose(xyz, source.point_xyz, atol=1e-5)


def test_mcap_of_a_recorded_session_and_of_a_live_store(session, tmp_path):
    from stereopath.device.formats.rig_files import save_rig_yaml
    from stereopath.device.formats.source import open_source
    from stereopath.device.formats.tum import write_tum
    from stereopath.device.wire.protocol import encode_keyframe, make_keyframe, rig_reference
    from stereopath.host.export.run import export_result
    from stereopath.host.live.store import KeyframeStore

    with pytest.raises(DatasetError, match="no on-board path"):
        export_result(session, tmp_path / "none", "mcap", progress=False)
    assert not (tmp_path / "none").exists()
    rec = tmp_path / "recorded"
    shutil.copytree(session, rec)
    seq = open_source(f"session:{rec}")
    write_tum(rec / "trajectory.tum", seq.groundtruth)  # stands in for the on-board path
    export_result(rec, tmp_path / "s", "mcap", progress=False)
    got = _read_mcap(tmp_path / "s" / "scan.mcap")
    assert len(got["/pose"]) == len(got["/cam1/image"]) == len(seq) and "/map" not in got
    assert np.allclose([_pose(m) for _, m in got["/pose"]], seq.groundtruth.T_world_cam, atol=1e-6)

    store = KeyframeStore(tmp_path / "live", fsync=False)
    for k in range(4):
        fr = seq.frame(3 * k)
        kf = make_keyframe("sessX", k, 3 * k, int(seq.t_ns[3 * k]), seq.groundtruth.T_world_cam[3 * k],
                           (fr.left, fr.right), rig_reference(seq.rig), "png")
        store.put(kf, encode_keyframe(kf))
    store.close()
    save_rig_yaml(seq.rig, tmp_path / "live" / "sessX" / "keyframes" / "rig.yaml")
    export_result(tmp_path / "live", tmp_path / "l", "mcap", progress=False)
    got = _read_mcap(tmp_path / "l" / "scan.mcap")
    assert [m[0] for m in got["/pose"]] == [int(seq.t_ns[3 * k]) for k in range(4)]
    assert len(got["/cam0/image"]) == 4


def test_out_folder_refused_unless_force_and_left_alone_on_failure(reprocessed, tmp_path, monkeypatch):
    from stereopath.host.export import nerfstudio
    from stereopath.host.export.run import export_result

    out = tmp_path / "out"
    out.mkdir()
    (out / "keep.txt").write_text("mine")
    with pytest.raises(ConfigError, match="not empty"):
        export_result(reprocessed, out, "nerfstudio", progress=False)
    with pytest.raises(ConfigError, match="known formats"):
        export_result(reprocessed, tmp_path / "x", "ply", progress=False)

    def broken(*a, **k):
        raise DatasetError("disk trouble")

    monkeypatch.setattr(nerfstudio, "export_nerfstudio", broken)
    with pytest.raises(DatasetError):
        export_result(reprocessed, out, "nerfstudio", force=True, progress=False)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"] and (out / "keep.txt").read_text() == "mine"
    monkeypatch.undo()
    export_result(reprocessed, out, "nerfstudio", force=True, progress=False)
    assert not (out / "keep.txt").exists() and (out / "transforms.json").is_file()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]


def test_cli_export_and_its_errors(reprocessed, tmp_path, capsys):
    from stereopath.host.cli import main
    from stereopath.host.commands import export as cmd
    from stereopath.host.export.run import FORMATS

    assert cmd.FORMATS == FORMATS
    assert main(["host", "export", str(reprocessed), "--format", "colmap", "--out", str(tmp_path / "c"),
                 "--no-progress"]) == 0
    assert "points, COLMAP mean reprojection error" in capsys.readouterr().out
    assert main(["host", "export", str(tmp_path), "--format", "mcap", "--out", str(tmp_path / "m")]) == 2
    assert "neither a `host reprocess` output" in capsys.readouterr().err
    assert main(["host", "export", str(reprocessed), "--format", "colmap", "--out", str(tmp_path / "c")]) == 2
    assert "not empty" in capsys.readouterr().err


def test_live_mcap_sink_records_poses_and_keyframes_as_they_arrive(session, tmp_path):
    """`host live --mcap`: poses from one thread and keyframes from another, read back equal."""
    import threading

    from stereopath.device.core.geometry import matrix_to_quat_xyzw
    from stereopath.device.formats.source import open_source
    from stereopath.device.wire.messages import Pose
    from stereopath.device.wire.protocol import make_keyframe, rig_reference
    from stereopath.host.live.mcap_sink import McapSink

    seq = open_source(f"session:{session}")
    gt = seq.groundtruth
    sink = McapSink(tmp_path / "live.mcap", rig_for=lambda sid: seq.rig)
    poses = [Pose("sessM", i, int(gt.t_ns[i]), tuple(gt.T_world_cam[i][:3, 3]),
                  tuple(matrix_to_quat_xyzw(gt.T_world_cam[i][:3, :3]))) for i in range(len(gt))]
    kfs = [make_keyframe("sessM", k, 4 * k, int(gt.t_ns[4 * k]), gt.T_world_cam[4 * k],
                         (seq.frame(4 * k).left, seq.frame(4 * k).right), rig_reference(seq.rig), enc) for k, enc in enumerate(["jpg", "png", "png"])]
    th = threading.Thread(target=lambda: [sink.on_pose(p) for p in poses])
    th.start()
    for kf in kfs:
        sink.on_keyframe(kf, True)
    sink.on_keyframe(kfs[0], False)  # a duplicate is not recorded again
    th.join()
    counts = sink.close()
    got = _read_mcap(tmp_path / "live.mcap")
    assert counts["pose"] == len(got["/pose"]) == len(gt) and counts["cam0"] == len(got["/cam1/image"]) == 3
    assert [t for t, _ in got["/pose"]] == gt.t_ns.tolist()
    assert np.allclose([_pose(m) for _, m in got["/pose"]], gt.T_world_cam, atol=1e-6)
    assert [m.format for _, m in got["/cam0/image"]] == ["jpeg", "png", "png"]
    assert got["/cam1/image"][2][1].data == kfs[2].right.data
    assert sum(1 for _, m in got["/tf"] if m.child_frame_id == "cam1") == 1


def test_live_mcap_sink_records_a_world_rebase_as_metadata(tmp_path):
    """A start in motion levelled on board: the poses written before it stay as written, and the file
    records the rebase (session, first pose in the new world, the map of the earlier poses)."""
    import json

    from mcap.reader import make_reader

    from stereopath.device.core.geometry import make_pose, matrix_to_quat_xyzw, rot_z
    from stereopath.device.wire.messages import Pose, WorldRebase
    from stereopath.host.live.mcap_sink import McapSink

    sink = McapSink(tmp_path / "live.mcap")
    G = make_pose(rot_z(0.3), np.zeros(3))
    sink.on_pose(Pose("sessR", 0, 1_000, (0.1, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0)))
    sink.on_rebase(WorldRebase("sessR", 2_000, (0.0, 0.0, 0.0), tuple(matrix_to_quat_xyzw(G[:3, :3]))))
    sink.on_pose(Pose("sessR", 1, 2_000, (0.2, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0)))
    assert sink.close()["pose"] == 2
    with open(tmp_path / "live.mcap", "rb") as fh:
        meta = {m.name: m.metadata for m in make_reader(fh).iter_metadata()}
    got = meta["world rebase 1"]
    assert got["session_id"] == "sessR" and int(got["from_t_ns"]) == 2_000
    assert np.allclose(np.array(json.loads(got["T_new_old"])), G, atol=1e-9)
    assert _read_mcap(tmp_path / "live.mcap")["/pose"][0][1].pose.position.x == pytest.approx(0.1)  # as written


def test_ros2_bag_decodes_with_the_mcap_ros2_decoder(reprocessed, source, tmp_path):
    """--ros2: read back by a second implementation (mcap-ros2-support decodes the CDR with the message
    definitions stored in the file): counts, times, poses and images equal the source."""
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    from stereopath.device.core.geometry import quat_xyzw_to_matrix
    from stereopath.host.export.run import export_result

    with pytest.raises(ConfigError, match="--ros2 goes with --format mcap"):
        export_result(reprocessed, tmp_path / "x", "colmap", progress=False, ros2=True)
    export_result(reprocessed, tmp_path / "r", "mcap", progress=False, ros2=True)
    bag = tmp_path / "r" / "rosbag2"
    assert (bag / "metadata.yaml").is_file()
    (path,) = bag.glob("*.mcap")
    got: dict[str, list] = {}
    with open(path, "rb") as fh:
        for schema, channel, message, msg in make_reader(fh, decoder_factories=[DecoderFactory()]).iter_decoded_messages():
            got.setdefault(channel.topic, []).append((message.log_time, schema.name, msg))
    t = source.t_ns.tolist()
    assert [x[0] for x in got["/odom"]] == [x[0] for x in got["/cam1/image"]] == t
    assert {x[1] for x in got["/odom"]} == {"nav_msgs/msg/Odometry"} and got["/tf"][0][1] == "tf2_msgs/msg/TFMessage"
    for (_, _, odom), T in zip(got["/odom"], source.T_world_cam0):
        p, q = odom.pose.pose.position, odom.pose.pose.orientation
        assert np.allclose([p.x, p.y, p.z], T[:3, 3]) and np.allclose(quat_xyzw_to_matrix([q.x, q.y, q.z, q.w]), T[:3, :3])
    img = got["/cam0/image"][0][2]
    left, _ = source.frame_loader(0)
    assert (img.height, img.width, img.encoding) == (left.shape[0], left.shape[1], "mono8")
    assert bytes(img.data) == left.tobytes()
    within = (source.imu.t_ns >= t[0]) & (source.imu.t_ns <= t[-1])
    assert len(got["/imu0"]) == int(within.sum()) and got["/imu0"][0][2].orientation_covariance[0] == -1
    (_, _, static), = got["/tf_static"]
    assert static.transforms[0].child_frame_id == "cam1"


@pytest.mark.realdata
def test_euroc_frames_with_their_lens_round_trip(data_dir, tmp_path):
    """EuRoC's radial-tangential cameras: the keyframe images are written undistorted onto K, so a point's
    pinhole projection (what the observations are) lands where the lens put it in the original image, and
    pycolmap and transforms.json give back the projections."""
    import cv2
    import pycolmap

    from stereopath.device.core.geometry import invert_pose
    from stereopath.device.formats.source import open_source
    from stereopath.host.export.colmap import export_colmap
    from stereopath.host.export.conventions import T_world_cam1, project_opengl, project_pinhole
    from stereopath.host.export.nerfstudio import export_nerfstudio
    from stereopath.host.export.result import ExportKeyframe, ExportSource

    seq = open_source(f"euroc:{data_dir / 'euroc_v1_01_head' / 'mav0'}")
    rig, gt = seq.rig, seq.groundtruth
    assert np.any(rig.cam0.dist != 0)
    frames = [0, 40, 80]
    t_gt = np.asarray(gt.t_ns)
    T = [gt.T_world_cam[int(np.argmin(np.abs(t_gt - seq.t_ns[i])))] for i in frames]
    kfs = [ExportKeyframe(k, i, int(seq.t_ns[i]), T[k], (lambda i=i: (seq.frame(i).left, seq.frame(i).right)))
           for k, i in enumerate(frames)]
    rng = np.random.default_rng(1)
    X_cam = np.column_stack([rng.uniform(-0.8, 0.8, 300), rng.uniform(-0.5, 0.5, 300), rng.uniform(2.0, 3.0, 300)])
    X = X_cam @ T[0][:3, :3].T + T[0][:3, 3]
    rows = []
    for k, Tk in enumerate(T):
        for cam, Tc, K in ((0, Tk, rig.cam0.K), (1, T_world_cam1(Tk, rig.R, rig.T), rig.cam1.K)):
            uv, front = project_pinhole(K, Tc, X)
            inside = front & (uv[:, 0] > 20) & (uv[:, 0] < 730) & (uv[:, 1] > 20) & (uv[:, 1] < 460)
            ids = np.flatnonzero(inside)
            rows.append(np.column_stack([np.full(len(ids), k), ids, np.full(len(ids), cam), uv[ids], np.ones(len(ids))]))
    obs = np.vstack(rows)
    src = ExportSource("reprocessed", data_dir, rig, np.array([k.t_ns for k in kfs]), np.array(T), kfs,
                       point_ids=np.arange(len(X)), point_xyz=X, observations=obs)
    (tmp_path / "c").mkdir()
    export_colmap(src, tmp_path / "c", progress=False)
    rec = pycolmap.Reconstruction(str(tmp_path / "c" / "sparse" / "0"))
    assert np.abs(_colmap_residuals(rec)).max() < 1e-6
    (tmp_path / "n").mkdir()
    export_nerfstudio(src, tmp_path / "n", progress=False)
    meta = json.loads((tmp_path / "n" / "transforms.json").read_text())
    for f in meta["frames"]:
        k, cam = f["keyframe"], int(f["camera"][-1])
        sel = (obs[:, 0] == k) & (obs[:, 2] == cam)
        uv, _ = project_opengl((f["fl_x"], f["fl_y"]), (f["cx"], f["cy"]), np.array(f["transform_matrix"]),
                               X[obs[sel, 1].astype(int)])
        assert np.abs(uv - obs[sel, 3:5]).max() < 1e-6
    # the undistorted image at a point's pinhole pixel shows what the original shows at its lens pixel
    written = cv2.imread(str(tmp_path / "c" / "images" / "cam0" / f"{kfs[1].t_ns}.png"), cv2.IMREAD_GRAYSCALE)
    original = seq.frame(frames[1]).left
    Xc = X @ invert_pose(T[1])[:3, :3].T + invert_pose(T[1])[:3, 3]
    Xc = Xc[Xc[:, 2] > 0]
    lens, _ = cv2.projectPoints(Xc, np.zeros(3), np.zeros(3), rig.cam0.K, rig.cam0.dist)
    pin, _ = project_pinhole(rig.cam0.K, np.eye(4), Xc)
    lens = lens.reshape(-1, 2)
    ok = (pin[:, 0] > 5) & (pin[:, 0] < 745) & (pin[:, 1] > 5) & (pin[:, 1] < 475) & \
         (lens[:, 0] > 5) & (lens[:, 0] < 745) & (lens[:, 1] > 5) & (lens[:, 1] < 475)
    a = cv2.remap(written, pin[ok, 0].astype(np.float32).reshape(-1, 1), pin[ok, 1].astype(np.float32).reshape(-1, 1),
                  cv2.INTER_LINEAR).astype(float).ravel()
    b = cv2.remap(original, lens[ok, 0].astype(np.float32).reshape(-1, 1), lens[ok, 1].astype(np.float32).reshape(-1, 1),
                  cv2.INTER_LINEAR).astype(float).ravel()
    assert ok.sum() > 100 and np.mean(np.abs(a - b)) < 3.0 < np.mean(np.abs(a - np.roll(b, 7)))


def test_nerfstudio_of_a_recorded_session_takes_keyframes_by_motion(session, tmp_path):
    from stereopath.device.formats.source import open_source
    from stereopath.device.formats.tum import write_tum
    from stereopath.host.export.run import export_result

    rec = tmp_path / "recorded"
    shutil.copytree(session, rec)
    seq = open_source(f"session:{rec}")
    write_tum(rec / "trajectory.tum", seq.groundtruth)
    s = export_result(rec, tmp_path / "n", "nerfstudio", progress=False)
    meta = json.loads((tmp_path / "n" / "transforms.json").read_text())
    assert 2 <= s["keyframes"] < len(seq) and len(meta["frames"]) == 2 * s["keyframes"]
    assert "ply_file_path" not in meta and not (tmp_path / "n" / "sparse_pc.ply").exists()  # no points: random init
    with pytest.raises(DatasetError, match="no bundle-adjusted points"):
        export_result(rec, tmp_path / "c", "colmap", progress=False)
    assert not (tmp_path / "c").exists()


@pytest.mark.realdata
def test_euroc_recording_to_mcap_round_trip(data_dir, tmp_path):
    """The shared EuRoC frames as a recorded session (its mav0 linked, the ground truth standing in for an
    on-board path): the MCAP holds every frame's original image bytes, the IMU and the poses."""
    from stereopath.device.formats.source import open_source
    from stereopath.device.formats.tum import write_tum
    from stereopath.host.export.run import export_result
    from stereopath.host.mapping.inputs import associate_poses

    rec = tmp_path / "euroc"
    rec.mkdir()
    (rec / "mav0").symlink_to(data_dir / "euroc_v1_01_head" / "mav0")
    gt = open_source(f"euroc:{data_dir / 'euroc_v1_01_head' / 'mav0'}").groundtruth
    write_tum(rec / "trajectory.tum", gt)
    seq = open_source(f"session:{rec}")
    export_result(rec, tmp_path / "m", "mcap", progress=False)
    got = _read_mcap(tmp_path / "m" / "scan.mcap")
    idx, poses = associate_poses(seq.t_ns, gt, 25_000_000)
    assert len(idx) == len(seq) and [t for t, _ in got["/pose"]] == seq.t_ns.tolist()
    assert np.allclose([_pose(m) for _, m in got["/pose"]], poses, atol=1e-6)
    a, b = seq.image_paths(10)
    assert got["/cam0/image"][10][1].data == a.read_bytes() and got["/cam1/image"][10][1].data == b.read_bytes()
    t = seq.t_ns
    assert len(got["/imu"]) == int(np.sum((seq.imu.t_ns >= t[0]) & (seq.imu.t_ns <= t[-1]))) > 100


def test_live_mcap_never_overwrites_an_earlier_recording(tmp_path, capsys):
    from stereopath.host.cli import main

    old = tmp_path / "earlier.mcap"
    old.write_bytes(b"an earlier recording")
    assert main(["host", "live", "--device", "127.0.0.1:5555", "--out", str(tmp_path / "out"), "--insecure",
                 "--mcap", str(old)]) == 2
    assert "exists; give a new file name" in capsys.readouterr().err and old.read_bytes() == b"an earlier recording"


def test_reprocessed_result_read_with_another_session_is_refused(reprocessed, tmp_path):
    from stereopath.device.formats.recorder import record_sequence
    from stereopath.device.sim.session import SimConfig, open_sim
    from stereopath.host.export.run import export_result

    other = tmp_path / "other"
    record_sequence(open_sim(SimConfig(frames=6, seed=3)), other, config_dict={"source": "sim"})
    with pytest.raises(DatasetError, match="not the recording"):
        export_result(reprocessed, tmp_path / "o", "nerfstudio", progress=False, session=other)
    with pytest.raises(DatasetError, match="give --session"):
        export_result(reprocessed, tmp_path / "o", "nerfstudio", progress=False, session=tmp_path / "gone")
