"""Dense mapping pipeline and `stereopath host map`: sessions, stored keyframes, bad input."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from stereopath.device.errors import CalibrationError, ConfigError, DatasetError, StereopathError
from stereopath.device.formats.tum import Trajectory
from stereopath.host.cli import main as cli_main
from stereopath.host.mapping.inputs import KeyframeSelection, associate_poses, keyframes_input, select_keyframes
from stereopath.host.mapping.mapper import MAP_FILES, build_map, map_path, map_preset, write_map

FAST = dict(max_keyframes=6)


def _pose(x: float, yaw_deg: float = 0.0) -> np.ndarray:
    from stereopath.device.core.geometry import rot_z

    T = np.eye(4)
    T[:3, :3] = rot_z(np.radians(yaw_deg))
    T[0, 3] = x
    return T


@pytest.fixture(scope="module")
def session(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("sess") / "s"
    assert cli_main(["-q", "sim", "--out", str(d), "--frames", "60"]) == 0
    return d


def _fast_config(**kf):
    return map_preset("object", voxel_mm=6.0, **{**FAST, **kf})


def _no_leftovers(parent: Path, name: str) -> None:
    assert not (parent / name).exists()
    assert not [p for p in parent.iterdir() if p.name.startswith(f".{name}.")]


# ---------------------------------------------------------------------------------------------
# pure parts


def test_select_keyframes_by_stride_motion_and_cap():
    poses = np.array([_pose(0.01 * i) for i in range(50)])  # 1 cm steps
    assert select_keyframes(poses, KeyframeSelection(stride=10)).tolist() == [0, 10, 20, 30, 40]
    by_motion = select_keyframes(poses, KeyframeSelection(min_translation_m=0.045, min_rotation_deg=90))
    assert by_motion.tolist() == [0, 5, 10, 15, 20, 25, 30, 35, 40, 45]
    turning = np.array([_pose(0.0, 2.0 * i) for i in range(10)])  # rotation only, 2 deg steps
    assert select_keyframes(turning, KeyframeSelection(min_translation_m=1.0, min_rotation_deg=5.0,
                                                       min_keyframes=0)).tolist() == [0, 3, 6, 9]
    # a short or nearly still recording: filled up to min_keyframes (default 8) in its longest gaps, the moves kept
    assert select_keyframes(turning, KeyframeSelection(min_translation_m=1.0, min_rotation_deg=5.0)).tolist() == \
        [0, 1, 2, 3, 4, 6, 7, 9]
    still = np.array([_pose(0.0) for _ in range(30)])
    assert select_keyframes(still, KeyframeSelection()).tolist() == [0, 3, 7, 10, 14, 21, 25, 29]
    assert select_keyframes(still[:5], KeyframeSelection()).tolist() == [0, 1, 2, 3, 4]
    assert select_keyframes(still, KeyframeSelection(min_keyframes=0)).tolist() == [0]
    # seven keyframes by motion get one more, not eight
    seven = select_keyframes(poses[:31], KeyframeSelection(min_translation_m=0.045, min_rotation_deg=90,
                                                           min_keyframes=0))
    assert seven.tolist() == [0, 5, 10, 15, 20, 25, 30]
    assert select_keyframes(poses[:31], KeyframeSelection(min_translation_m=0.045,
                                                          min_rotation_deg=90)).tolist() == [0, 2, 5, 10, 15, 20, 25, 30]
    capped = select_keyframes(poses, KeyframeSelection(stride=1, max_keyframes=4))
    assert capped.tolist() == [0, 16, 33, 49]
    assert len(select_keyframes(np.zeros((0, 4, 4)), KeyframeSelection())) == 0


def test_associate_poses_nearest_within_tolerance():
    traj = Trajectory(np.array([100, 200, 300], np.int64), np.array([_pose(1.0), _pose(2.0), _pose(3.0)]))
    idx, poses = associate_poses(np.array([98, 160, 290, 500]), traj, max_dt_ns=30)
    assert idx.tolist() == [0, 2]
    assert poses[:, 0, 3].tolist() == [1.0, 3.0]


def test_presets_and_overrides():
    cfg = map_preset("room", voxel_mm=25.0, stride=3)
    assert cfg.fusion.voxel_m == pytest.approx(0.025) and cfg.keyframes.stride == 3
    assert map_preset("object").fusion.voxel_m == pytest.approx(0.004)
    with pytest.raises(ConfigError, match="unknown map preset"):
        map_preset("castle")
    with pytest.raises(ConfigError, match="voxel_mm"):
        map_preset("object", voxel_mm=0.0)


# ---------------------------------------------------------------------------------------------
# from a session


@pytest.mark.slow
def test_map_command_on_a_session(session, tmp_path, capsys):
    out = tmp_path / "model"
    rc = cli_main(["-q", "host", "map", str(session), "--out", str(out), "--poses",
                   str(session / "groundtruth.tum"), "--voxel-mm", "6", "--max-keyframes", "6", "--no-progress"])
    assert rc == 0
    assert "6 keyframes (60 frames)" in capsys.readouterr().out
    assert sorted(p.name for p in out.iterdir()) == sorted(MAP_FILES)
    stats = json.loads((out / "map.json").read_text())
    assert stats["keyframes"] == 6 and stats["frames_total"] == 60 and stats["voxel_mm"] == pytest.approx(6.0)
    assert stats["mesh_vertices"] > 1000 and stats["cloud_points"] > 1000
    assert set(stats["timings_s"]) >= {"depth", "fusion", "extract", "preview", "total"}
    import open3d as o3d

    mesh = o3d.io.read_triangle_mesh(str(out / "mesh.ply"))
    assert len(mesh.triangles) == stats["mesh_triangles"]
    cloud = o3d.io.read_point_cloud(str(out / "cloud.ply"))
    assert len(cloud.points) == stats["cloud_points"]
    png = cv2.imread(str(out / "model.png"))
    assert png.shape == (720, 960, 3)
    assert (png < 250).any(axis=2).mean() > 0.05  # something was drawn on the white background
    # the model sits on the simulated scene's surfaces
    from stereopath.device.sim.scene import point_to_scene_distance, table_top_scene

    d = point_to_scene_distance(table_top_scene(0), np.asarray(mesh.vertices))
    assert np.median(d) < 0.01


def test_session_without_estimated_path_writes_nothing(session, tmp_path, capsys):
    rc = cli_main(["-q", "host", "map", str(session), "--out", str(tmp_path / "m"), "--no-progress"])
    assert rc == 2
    assert "trajectory.tum" in capsys.readouterr().err
    _no_leftovers(tmp_path, "m")
    with pytest.raises(DatasetError, match="no estimated path"):
        map_path(session, tmp_path / "m", _fast_config(), progress=False)
    _no_leftovers(tmp_path, "m")


def test_empty_session_raises_and_writes_nothing(session, tmp_path):
    s = tmp_path / "empty"
    shutil.copytree(session, s)
    for cam in ("cam0", "cam1"):
        for f in (s / "mav0" / cam / "data").iterdir():
            f.unlink()
    with pytest.raises(DatasetError, match="no stereo pairs"):
        map_path(s, tmp_path / "out", _fast_config(), poses=s / "groundtruth.tum", progress=False)
    _no_leftovers(tmp_path, "out")


def test_all_invalid_depth_raises_and_writes_nothing(session, tmp_path):
    s = tmp_path / "blank"
    shutil.copytree(session, s)
    for cam in ("cam0", "cam1"):
        for f in (s / "mav0" / cam / "data").glob("*.png"):
            cv2.imwrite(str(f), np.full((480, 640), 128, np.uint8))
    out = tmp_path / "out"
    out.mkdir()
    (out / "keep.txt").write_text("mine")
    with pytest.raises(StereopathError, match="no valid depth in any of the 6 keyframes"):
        map_path(s, out, _fast_config(), poses=s / "groundtruth.tum", progress=False)
    assert [p.name for p in out.iterdir()] == ["keep.txt"]
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".out.")]


def test_not_a_session_or_keyframes(tmp_path):
    (tmp_path / "junk").mkdir()
    with pytest.raises(DatasetError, match="neither a session"):
        map_path(tmp_path / "junk", tmp_path / "out", _fast_config(), progress=False)
    with pytest.raises(DatasetError, match="not found"):
        map_path(tmp_path / "nothing", tmp_path / "out", _fast_config(), progress=False)
    _no_leftovers(tmp_path, "out")


# ---------------------------------------------------------------------------------------------
# from stored keyframes


@pytest.fixture(scope="module")
def keyframe_dir(session, tmp_path_factory) -> Path:
    from stereopath.device.formats import open_source
    from stereopath.device.wire.protocol import encode_keyframe, make_keyframe, rig_reference
    from stereopath.host.live.store import SessionKeyframes

    seq = open_source(f"session:{session}")
    gt = seq.groundtruth
    root = tmp_path_factory.mktemp("live") / "20260101T000000Z-abcdef"
    store = SessionKeyframes(root, fsync=False)
    ref = rig_reference(seq.rig)
    for k, i in enumerate(range(20, 60, 8)):
        fr = seq.frame(i)
        kf = make_keyframe(root.name, k, i, int(seq.t_ns[i]), gt.T_world_cam[i], (fr.left, fr.right), ref, encoding="png")
        store.put(kf, encode_keyframe(kf))
    store.close()
    return root


def test_keyframes_without_calibration_raise(keyframe_dir, tmp_path):
    with pytest.raises(CalibrationError, match="keyframes without calibration"):
        map_path(keyframe_dir, tmp_path / "out", _fast_config(), progress=False)
    _no_leftovers(tmp_path, "out")


def test_keyframes_with_the_wrong_rig_raise(keyframe_dir, tmp_path):
    from stereopath.device.core.rig import paper_rig
    from stereopath.device.formats.rig_files import save_rig_yaml

    other = tmp_path / "other.yaml"
    save_rig_yaml(paper_rig(), other)  # no T_body_cam0: a different calibration hash
    with pytest.raises(CalibrationError, match="does not match"):
        keyframes_input(keyframe_dir, rig=other)


def test_map_from_stored_keyframes(keyframe_dir, session, tmp_path):
    rig_yaml = session / "mav0" / "rig.yaml"
    inp = keyframes_input(keyframe_dir / "keyframes", rig=rig_yaml)
    assert inp.kind == "keyframes" and len(inp.keyframes) == 5
    shutil.copy(rig_yaml, keyframe_dir / "rig.yaml")
    try:
        out = tmp_path / "kmodel"
        result = map_path(keyframe_dir, out, _fast_config(), progress=False)
    finally:
        (keyframe_dir / "rig.yaml").unlink()
    assert result.stats["input_kind"] == "keyframes" and result.stats["keyframes"] == 5
    assert sorted(p.name for p in out.iterdir()) == sorted(MAP_FILES)


# ---------------------------------------------------------------------------------------------
# writing


def test_write_map_replaces_model_files_only(session, tmp_path):
    from stereopath.device.formats import open_source
    from stereopath.host.mapping.inputs import keyframes_from_sequence

    seq = open_source(f"session:{session}")
    inp = keyframes_from_sequence(seq, seq.groundtruth, KeyframeSelection(stride=8, max_keyframes=6))
    result = build_map(inp, _fast_config(), progress=False)
    out = tmp_path / "out"
    out.mkdir()
    (out / "report.json").write_text("{}")
    (out / "mesh.ply").write_text("old")
    paths = write_map(result, out)
    assert sorted(p.name for p in out.iterdir()) == sorted([*MAP_FILES, "report.json"])
    assert paths["mesh.ply"].stat().st_size > 1000
    (tmp_path / "file").write_text("x")
    with pytest.raises(StereopathError, match="not a folder"):
        write_map(result, tmp_path / "file")


def test_dense_mapper_is_incremental(session):
    from stereopath.device.formats import open_source
    from stereopath.host.mapping.mapper import DenseMapper

    seq = open_source(f"session:{session}")
    mapper = DenseMapper(seq.rig, _fast_config(), source="live")
    with pytest.raises(DatasetError, match="no keyframes"):
        mapper.finish()
    sizes = []
    for i in (24, 32, 40, 48, 56):
        fr = seq.frame(i)
        dm = mapper.add(fr.left, fr.right, seq.groundtruth.T_world_cam[i], index=i)
        assert dm.valid_fraction > 0.1
        sizes.append(len(mapper.mesh().vertices))
    assert sizes[0] == 0 and sizes[-1] > sizes[-2] > 0, sizes  # a voxel needs 3 observations to show
    result = mapper.finish({"session": "abc"})
    assert result.stats["keyframes"] == 5 and result.stats["keyframe_indices"] == [24, 32, 40, 48, 56]
    assert result.stats["session"] == "abc" and result.preview.shape == (720, 960, 3)


def test_preview_renderer_orientation(tmp_path):
    """look_at puts the target on the optical axis with world-up at the top of the image."""
    from stereopath.host.mapping.preview import look_at, preview_camera, render_mesh, write_png

    T = look_at(np.array([2.0, 0.0, 0.0]), np.zeros(3), np.array([0.0, 0.0, 1.0]))
    p = np.linalg.inv(T) @ np.array([0.0, 0.0, 0.0, 1.0])
    np.testing.assert_allclose(p[:3], [0.0, 0.0, 2.0], atol=1e-12)
    assert np.linalg.det(T[:3, :3]) == pytest.approx(1.0)
    assert (np.linalg.inv(T) @ np.array([0.0, 0.0, 1.0, 1.0]))[1] < 0  # world up -> image up (y < 0)
    assert (np.linalg.inv(T) @ np.array([0.0, 1.0, 0.0, 1.0]))[0] > 0  # facing -x, +y is on the right (no mirror)
    # two squares facing +x: red above z = 0, blue below
    v = np.array([[0, -1, 0], [0, 1, 0], [0, 1, 1], [0, -1, 1], [0, -1, -1], [0, 1, -1], [0, 1, 0], [0, -1, 0]], float)
    t = np.array([[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 7]])
    c = np.array([[1, 0, 0]] * 4 + [[0, 0, 1]] * 4, float)
    K, T = preview_camera(v, size=(160, 120), view_dir=np.array([-1.0, 0, 0]), up=np.array([0, 0, 1.0]))
    img = render_mesh(v, t, K, T, size=(160, 120), vertex_colors=c)
    red = (img[:, :, 0] > 150) & (img[:, :, 2] < 100)
    blue = (img[:, :, 2] > 150) & (img[:, :, 0] < 100)
    assert red.sum() > 500 and blue.sum() > 500
    assert np.nonzero(red)[0].mean() < 60 < np.nonzero(blue)[0].mean()
    write_png(img, tmp_path / "p.png")
    assert cv2.imread(str(tmp_path / "p.png")).shape == (120, 160, 3)


def test_the_map_stage_key_hashes_every_depth_setting():
    """The reprocess map stage's key covers the fixed SGBM settings too (as recorded in map.json), so a
    stored model is reused only when the depth it was made with is the same."""
    from stereopath.host.mapping.mapper import map_preset
    from stereopath.host.reprocess import stage_map

    config = map_preset("object")
    recorded = stage_map.settings(config)["depth"]
    assert recorded == config.depth.record()
    assert {"uniqueness_ratio", "pre_filter_cap", "speckle_window_px", "edge_dilate_px"} <= set(recorded)
    assert stage_map.settings("auto") == {"preset": "auto"}


def test_the_volume_table_is_counted_as_open3d_allocates_it():
    """The hash table of the model's voxel blocks doubles when it fills: what it holds is the next
    doubling of the initial size at or above the blocks in use (as Open3D's VoxelBlockGrid grows)."""
    import open3d as o3d

    from stereopath.host.reprocess.stage_map import table_blocks

    assert table_blocks(19000, 20000) == 20000 and table_blocks(20128, 20000) == 40000
    assert table_blocks(60226, 20000) == 80000 and table_blocks(0, 20000) == 20000
    f32 = o3d.core.float32
    grid = o3d.t.geometry.VoxelBlockGrid(("tsdf", "weight"), (f32, f32), (1, 1), 0.01, 8, 64, o3d.core.Device("CPU:0"))
    keys = np.stack(np.meshgrid(np.arange(10), np.arange(10), np.arange(2), indexing="ij"), -1).reshape(-1, 3)
    for part in np.array_split(keys.astype(np.int32), 20):  # a few blocks at a time, as keyframes add them
        grid.hashmap().activate(o3d.core.Tensor(part))
    assert grid.hashmap().size() == 200 and grid.hashmap().capacity() == table_blocks(200, 64) == 256


def test_an_interrupted_map_build_goes_on_from_its_last_stored_volume(session, tmp_path, monkeypatch):
    """With the volume stored every 4 keyframes (batches of 2 here), a build stopped at its 7th keyframe
    resumes after the 4th with the stored volume (no copy of it is made) and gives the model of an
    uninterrupted build: the same blocks, the same surface."""
    from stereopath.device.formats import open_source
    from stereopath.host.mapping import mapper as mapper_mod
    from stereopath.host.mapping.inputs import keyframes_from_sequence
    from stereopath.host.mapping.map_progress import MapCheckpoint

    monkeypatch.setattr(mapper_mod, "DEPTH_BATCH", 2)
    seq = open_source(f"session:{session}")
    sel = KeyframeSelection(stride=6, max_keyframes=10)
    cfg = _fast_config(max_keyframes=10)
    whole = build_map(keyframes_from_sequence(seq, seq.groundtruth, sel), cfg, progress=False)
    n = whole.stats["keyframes"]
    assert n >= 9
    fused: list[int] = []

    def stop_at_7(k, _dm):
        fused.append(k)
        if len(fused) == 7:
            raise KeyboardInterrupt

    ckpt = MapCheckpoint(tmp_path / "parts", every=4)
    with pytest.raises(KeyboardInterrupt):
        build_map(keyframes_from_sequence(seq, seq.groundtruth, sel), cfg, progress=False, on_keyframe=stop_at_7,
                  checkpoint=ckpt)
    assert [p.name for p in (tmp_path / "parts").iterdir()] == ["chunk-000004"]
    fused.clear()
    again = build_map(keyframes_from_sequence(seq, seq.groundtruth, sel), cfg, progress=False,
                      on_keyframe=lambda k, _dm: fused.append(k), checkpoint=ckpt)
    assert fused == list(range(4, n))  # the first four came from the stored volume
    for key in ("keyframes", "blocks", "keyframe_indices", "mesh_vertices", "mesh_triangles", "cloud_points"):
        assert again.stats[key] == whole.stats[key], key
    a, b = (np.asarray(r.mesh.vertices) for r in (whole, again))
    assert np.array_equal(a[np.lexsort(a.T)], b[np.lexsort(b.T)])
    ca, cb = (np.asarray(r.mesh.vertex_colors) for r in (whole, again))
    assert np.array_equal(ca[np.lexsort(a.T)], cb[np.lexsort(b.T)])
    # a chunk written with another voxel size is not used: the build starts from the first keyframe
    fused.clear()
    shutil.rmtree(tmp_path / "parts")  # the finished build's last chunk (the stage removes it)
    with pytest.raises(KeyboardInterrupt):
        build_map(keyframes_from_sequence(seq, seq.groundtruth, sel), cfg, progress=False, on_keyframe=stop_at_7,
                  checkpoint=ckpt)
    fused.clear()
    other = map_preset("object", voxel_mm=5.0, **{**FAST, "max_keyframes": 10})
    build_map(keyframes_from_sequence(seq, seq.groundtruth, sel), other, progress=False,
              on_keyframe=lambda k, _dm: fused.append(k), checkpoint=MapCheckpoint(tmp_path / "parts", every=100))
    assert fused == list(range(n))
    # nor a damaged one (a file cut short)
    fused.clear()
    shutil.rmtree(tmp_path / "parts")
    with pytest.raises(KeyboardInterrupt):
        build_map(keyframes_from_sequence(seq, seq.groundtruth, sel), cfg, progress=False, on_keyframe=stop_at_7,
                  checkpoint=ckpt)
    tsdf = tmp_path / "parts" / "chunk-000004" / "tsdf.npy"
    tsdf.write_bytes(tsdf.read_bytes()[:-100])
    fused.clear()
    build_map(keyframes_from_sequence(seq, seq.groundtruth, sel), cfg, progress=False,
              on_keyframe=lambda k, _dm: fused.append(k), checkpoint=ckpt)
    assert fused == list(range(n))


def test_depth_maps_side_by_side_give_the_model_of_one_at_a_time(session):
    """The one-process spreader of the map stage (two keyframes' depth at once, a matcher per thread,
    OpenCV at one thread meanwhile): the same depth maps in the same order, so the same model."""
    import cv2

    from stereopath.device.formats import open_source
    from stereopath.host.backend.parallel import ThreadSpreader, spread_with
    from stereopath.host.mapping.inputs import keyframes_from_sequence

    seq = open_source(f"session:{session}")
    sel = KeyframeSelection(stride=6, max_keyframes=8)
    cfg = _fast_config(max_keyframes=8)
    seen: dict[str, list[np.ndarray]] = {"line": [], "side": []}
    line = build_map(keyframes_from_sequence(seq, seq.groundtruth, sel), cfg, progress=False,
                     on_keyframe=lambda k, dm: seen["line"].append(np.nan_to_num(dm.disparity_px, nan=-1.0)))
    before = cv2.getNumThreads()
    with spread_with(ThreadSpreader(2)):
        side = build_map(keyframes_from_sequence(seq, seq.groundtruth, sel), cfg, progress=False,
                         on_keyframe=lambda k, dm: seen["side"].append(np.nan_to_num(dm.disparity_px, nan=-1.0)))
    assert cv2.getNumThreads() == before
    assert len(seen["line"]) == len(seen["side"]) >= 6
    assert all(np.array_equal(a, b) for a, b in zip(seen["line"], seen["side"]))
    for key in ("keyframes", "blocks", "mesh_vertices", "mesh_triangles"):
        assert side.stats[key] == line.stats[key], key


def test_each_thread_computes_depth_with_a_matcher_of_its_own(session):
    """An OpenCV matcher keeps its work buffers between calls: two threads never share one."""
    import threading

    from stereopath.device.formats import open_source
    from stereopath.host.mapping.depth import StereoDepth

    depth = StereoDepth(open_source(f"session:{session}").rig)
    here = depth._matcher(1)
    there: list = []
    t = threading.Thread(target=lambda: there.append(depth._matcher(1)))
    t.start()
    t.join()
    assert depth._matcher(1) is here and there[0] is not here
