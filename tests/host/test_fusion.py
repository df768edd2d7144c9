"""TSDF fusion: a simulated box is rebuilt with its true dimensions; configuration and writing."""

from __future__ import annotations

import numpy as np
import pytest

from stereopath.device.errors import ConfigError, StereopathError
from stereopath.device.core.geometry import rot_z
from stereopath.host.mapping.fusion import FUSION_PRESETS, FusionConfig, TsdfVolume, fusion_preset, write_cloud, write_mesh
from stereopath.host.mapping.preview import look_at

BOX_SIZE = np.array([0.30, 0.20, 0.15])
BOX_YAW_DEG = 20.0


def _box_scene():
    from stereopath.device.sim.scene import BoxGeometry, Quad, Scene, facing_quad, texture_shape
    from stereopath.device.sim.textures import make_texture

    T_box = np.eye(4)
    T_box[:3, :3] = rot_z(np.radians(BOX_YAW_DEG))
    T_box[:3, 3] = (0.02, -0.01, 0.0)
    box = BoxGeometry("box", T_box, BOX_SIZE.copy())
    quads, textures = [], []

    def add(name, origin, u, v, style, mpt):
        shape = texture_shape(np.linalg.norm(u), np.linalg.norm(v), mpt)
        quads.append(Quad(np.asarray(origin, float), np.asarray(u, float), np.asarray(v, float), len(textures), mpt, name))
        textures.append(make_texture(7, shape, style, key=len(textures), texel_px=1.0))

    add("floor", *facing_quad((0, 0, 0), (0, 0, 1), (0, 1, 0), 2.0, 2.0), "floor", 0.002)
    for fname, o, u, v in box.face_quads():
        add(f"box.{fname}", o, u, v, "box", 0.0006)
    return Scene(quads, textures, [box], name="box"), box


def _ring_poses(n: int, radius: float = 0.65, height: float = 0.45) -> list[np.ndarray]:
    target = np.array([0.02, -0.01, 0.06])
    poses = []
    for k in range(n):
        a = 2 * np.pi * k / n
        eye = np.array([radius * np.cos(a), radius * np.sin(a), height])
        poses.append(look_at(eye, target, np.array([0.0, 0.0, 1.0])))
    return poses


@pytest.fixture(scope="module")
def box_world():
    from stereopath.device.sim.render import Renderer
    from stereopath.device.sim.session import sim_rig

    scene, box = _box_scene()
    rig = sim_rig()
    return scene, box, rig, Renderer(scene, rig, noise_sigma=2.0, seed=1)


def _measure_box(vertices: np.ndarray, box) -> np.ndarray:
    """(x, y, z) extent of the box read off mesh vertices: opposite faces' median positions."""
    T = box.T_world_box
    p = (vertices - T[:3, 3]) @ T[:3, :3]  # box frame
    half = BOX_SIZE / 2
    m = 0.02  # stay this far from edges when picking a face's vertices
    near_box = (np.abs(p[:, 0]) < half[0] + 0.02) & (np.abs(p[:, 1]) < half[1] + 0.02)
    out = []
    for ax, other in ((0, 1), (1, 0)):
        band = near_box & (np.abs(p[:, other]) < half[other] - m) & (p[:, 2] > m) & (p[:, 2] < BOX_SIZE[2] - m)
        pos = p[band & (p[:, ax] > half[ax] / 2), ax]
        neg = p[band & (p[:, ax] < -half[ax] / 2), ax]
        assert len(pos) > 50 and len(neg) > 50
        out.append(np.median(pos) - np.median(neg))
    top = near_box & (np.abs(p[:, 0]) < half[0] - m) & (np.abs(p[:, 1]) < half[1] - m) & (p[:, 2] > BOX_SIZE[2] / 2)
    floor = (np.abs(p[:, 0]) > half[0] + 0.05) & (np.abs(p[:, 2]) < 0.02)
    assert top.sum() > 50 and floor.sum() > 50
    out.append(np.median(p[top, 2]) - np.median(p[floor, 2]))
    return np.array(out)


def test_box_from_ground_truth_depth_has_true_dimensions(box_world):
    scene, box, rig, rend = box_world
    vol = TsdfVolume(FusionConfig(voxel_m=0.004, max_depth_m=1.5, color=False))
    for T in _ring_poses(12):
        _, depth = rend.render_view(rig.cam0.K, rig.cam0.size, T)
        vol.integrate(depth, rig.cam0.K, T)
    assert vol.frames_integrated == 12 and vol.block_count > 0
    mesh = vol.extract_mesh()
    dims = _measure_box(np.asarray(mesh.vertices), box)
    np.testing.assert_allclose(dims, BOX_SIZE, rtol=0.01)


@pytest.mark.slow
def test_box_from_stereo_depth_has_true_dimensions(box_world):
    """End to end: rendered stereo pairs -> SGBM depth (rectified frame) -> TSDF -> mesh."""
    from stereopath.host.mapping.depth import DEPTH_PRESETS, StereoDepth

    scene, box, rig, rend = box_world
    sd = StereoDepth(rig, DEPTH_PRESETS["object"])
    vol = TsdfVolume(FUSION_PRESETS["object"])
    for k, T in enumerate(_ring_poses(16)):
        left, right, _ = rend.render(T, key=k)
        vol.integrate_depth_map(sd.compute(left, right), T)
    mesh = vol.extract_mesh()
    assert mesh.has_vertex_colors()
    dims = _measure_box(np.asarray(mesh.vertices), box)
    np.testing.assert_allclose(dims, BOX_SIZE, rtol=0.01)


def test_wrong_extrinsic_convention_would_be_caught(box_world):
    """Integrating with the world-to-camera matrix instead of the pose does not rebuild the box."""
    scene, box, rig, rend = box_world
    from stereopath.device.sim.scene import point_to_scene_distance

    right = TsdfVolume(FusionConfig(voxel_m=0.004, max_depth_m=1.5, color=False))
    wrong = TsdfVolume(FusionConfig(voxel_m=0.004, max_depth_m=1.5, color=False))
    for T in _ring_poses(6):
        _, depth = rend.render_view(rig.cam0.K, rig.cam0.size, T)
        right.integrate(depth, rig.cam0.K, T)
        wrong.integrate(depth, rig.cam0.K, np.linalg.inv(T))
    v_right = np.asarray(right.extract_mesh().vertices)
    v = np.asarray(wrong.extract_mesh().vertices)
    # the same depth maps at the poses rebuild the scene; at their inverses they build something else
    assert len(v_right) > 0 and np.median(point_to_scene_distance(scene, v_right)) < 0.005
    assert len(v) > 0 and np.median(point_to_scene_distance(scene, v)) > 0.02


def test_config_and_presets():
    assert fusion_preset("object").voxel_m == pytest.approx(0.004)
    assert fusion_preset("room").voxel_m == pytest.approx(0.02)
    assert FusionConfig(voxel_m=0.01, trunc_voxels=3).trunc_m == pytest.approx(0.03)
    with pytest.raises(ConfigError, match="voxel_m"):
        FusionConfig(voxel_m=0.0)
    with pytest.raises(ConfigError, match="block_resolution"):
        FusionConfig(block_resolution=7)
    with pytest.raises(ConfigError, match="unknown fusion preset"):
        fusion_preset("castle")


def test_integrate_validates_input():
    K = np.array([[100.0, 0, 31.5], [0, 100.0, 23.5], [0, 0, 1]])
    vol = TsdfVolume(FusionConfig(color=True))
    depth = np.full((48, 64), 1.0, np.float32)
    with pytest.raises(StereopathError, match="no colour image"):
        vol.integrate(depth, K, np.eye(4))
    with pytest.raises(StereopathError, match="colour image is"):
        vol.integrate(depth, K, np.eye(4), np.zeros((10, 10, 3), np.uint8))
    with pytest.raises(StereopathError, match="finite"):
        vol.integrate(depth, K, np.full((4, 4), np.nan))
    vol.integrate(np.zeros((48, 64), np.float32), K, np.eye(4), np.zeros((48, 64, 3), np.uint8))
    assert vol.pixels_integrated == 0 and len(vol.extract_mesh().vertices) == 0


def test_writers_are_atomic_and_refuse_empty(tmp_path):
    import open3d as o3d

    with pytest.raises(StereopathError, match="empty mesh"):
        write_mesh(o3d.geometry.TriangleMesh(), tmp_path / "mesh.ply")
    with pytest.raises(StereopathError, match="empty point cloud"):
        write_cloud(o3d.geometry.PointCloud(), tmp_path / "cloud.ply")
    assert list(tmp_path.iterdir()) == []
    mesh = o3d.geometry.TriangleMesh.create_box(0.1, 0.2, 0.3)
    write_mesh(mesh, tmp_path / "mesh.ply")
    back = o3d.io.read_triangle_mesh(str(tmp_path / "mesh.ply"))
    assert len(back.triangles) == len(mesh.triangles)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["mesh.ply"]


def test_compact_voxels_keep_the_surface_and_the_colours_in_fewer_bytes():
    """Weight and colour as uint16 (the default when colour is fused): the same mesh vertices as float32
    voxels, colours within a grey level or two, 12 bytes a voxel instead of 20."""
    yy, xx = np.mgrid[0:120, 0:160]
    depth = (0.8 + 0.1 * np.sin(xx / 20.0) + 0.05 * np.cos(yy / 15.0)).astype(np.float32)
    rgb = np.stack([xx * 255 // 160, yy * 255 // 120, np.full_like(xx, 77)], -1).astype(np.uint8)
    K = np.array([[150.0, 0, 80], [0, 150.0, 60], [0, 0, 1]])
    meshes = {}
    for compact in (False, True):
        vol = TsdfVolume(FusionConfig(voxel_m=0.004, max_depth_m=1.5, compact=compact))
        for i in range(6):
            T = np.eye(4)
            T[0, 3] = 0.005 * i
            vol.integrate(depth, K, T, rgb)
        mesh = vol.extract_mesh()
        meshes[compact] = (np.asarray(mesh.vertices), np.asarray(mesh.vertex_colors), vol.nbytes, vol.block_count)
    (v0, c0, b0, n0), (v1, c1, b1, n1) = meshes[False], meshes[True]
    assert len(v0) > 1000 and len(v0) == len(v1) and n0 == n1
    from scipy.spatial import cKDTree

    dist, nearest = cKDTree(v0).query(v1)
    assert dist.max() < 1e-6
    # the colour each compact vertex carries against the float volume's (the rounding to whole grey levels
    # at each integration: a level or two)
    diff = np.abs(c1 - c0[nearest]).max(axis=1)
    assert np.median(diff) <= 2.0 / 255 and np.percentile(diff, 99) <= 5.0 / 255
    assert abs(float(c1.mean()) - float(c0.mean())) < 1.0 / 255
    assert b1 * 20 == b0 * 12
    assert FusionConfig(color=False).voxel_bytes == 8
