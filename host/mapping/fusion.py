"""TSDF fusion of keyframe depth maps into one volume, and mesh / point cloud export.

Backend: Open3D's tensor :class:`open3d.t.geometry.VoxelBlockGrid` on the CPU (a sparse
voxel-block hash map).  The legacy ``ScalableTSDFVolume`` of the Open3D build we use returns empty
meshes, and the block grid is fast enough (``benchmarks/bench_fusion.py``).

Conventions: depth maps are metres along the camera's z axis (0 = no depth), ``K`` is the
3x3 intrinsic matrix of the camera the depth belongs to, and poses are ``T_world_cam``
(camera-to-world).  Open3D wants the world-to-camera extrinsic, so :meth:`TsdfVolume.integrate`
inverts the pose.  For a :class:`stereopath.host.mapping.depth.DepthMap` (depth in the *rectified* left camera)
use :meth:`TsdfVolume.integrate_depth_map` with the camera-0 pose: it applies
``T_world_rect = T_world_cam0 @ [R0^T | 0]``.

Open3D is imported inside the functions that need it.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import os
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from stereopath.device.core.config import check_range
from stereopath.device.errors import ConfigError, StereopathError
from stereopath.device.formats.fileio import replacing

if TYPE_CHECKING:
    import open3d

    from stereopath.host.mapping.depth import DepthMap

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class FusionConfig:
    """TSDF settings: voxel size, truncation (in voxels), integration range, colour, mesh threshold."""

    voxel_m: float = 0.004
    trunc_voxels: float = 6.0  # truncation distance = trunc_voxels * voxel_m
    max_depth_m: float = 2.0  # depth beyond this is not integrated
    color: bool = True  # fuse colour (the grey image when the source has no colour)
    min_weight: float = 3.0  # voxels observed fewer times than this are left out of the mesh/cloud
    block_resolution: int = 8  # voxels per block side
    initial_blocks: int = 20000  # hash-map capacity to start with (grows when needed)
    # weight and colour as uint16 when colour is fused (12 bytes a voxel instead of 20; the same surface,
    # colours kept in whole grey levels); Open3D takes (float32, float32) or (uint16, uint16) for (weight, colour)
    compact: bool = True

    def __post_init__(self) -> None:
        check_range("voxel_m", self.voxel_m, 1e-4, 1.0)
        check_range("trunc_voxels", self.trunc_voxels, 1.0, 64.0)
        check_range("max_depth_m", self.max_depth_m, 0.01, 1e3)
        check_range("min_weight", self.min_weight, 0.0, 1e6)
        if self.block_resolution not in (4, 8, 16, 32):
            raise ConfigError(f"block_resolution = {self.block_resolution} must be one of 4, 8, 16, 32")
        check_range("initial_blocks", self.initial_blocks, 100, 10_000_000)

    @property
    def trunc_m(self) -> float:
        return self.voxel_m * self.trunc_voxels

    @property
    def voxel_bytes(self) -> int:
        """Bytes of one voxel's attributes: float32 TSDF, the weight and, when fused, the colour (uint16 each
        when ``compact``, else float32)."""
        if not self.color:
            return 4 + 4
        return 4 + (2 + 3 * 2 if self.compact else 4 + 3 * 4)


FUSION_PRESETS: dict[str, FusionConfig] = {
    # truncation 6 voxels (24 mm, 12 cm for rooms): wide enough to average the stereo depth noise
    "object": FusionConfig(voxel_m=0.004, trunc_voxels=6.0, max_depth_m=2.0),
    "room": FusionConfig(voxel_m=0.02, trunc_voxels=6.0, max_depth_m=6.0, initial_blocks=5000),
    "large_room": FusionConfig(voxel_m=0.05, trunc_voxels=6.0, max_depth_m=15.0, initial_blocks=5000),
}


def fusion_preset(name: str) -> FusionConfig:
    """The named :data:`FUSION_PRESETS` entry (ConfigError naming the choices otherwise)."""
    if name not in FUSION_PRESETS:
        raise ConfigError(f"unknown fusion preset {name!r}; known: {', '.join(sorted(FUSION_PRESETS))}")
    return FUSION_PRESETS[name]


class TsdfVolume:
    """A growing TSDF volume.  ``integrate`` keyframes, then ``extract_mesh`` / ``extract_cloud``."""

    def __init__(self, config: FusionConfig | None = None) -> None:
        import open3d as o3d

        self.config = config or FusionConfig()
        self._o3d = o3d
        self._device = o3d.core.Device("CPU:0")
        c = self.config
        f32 = o3d.core.float32
        if c.color:
            wc = o3d.core.uint16 if c.compact else f32
            attrs, dtypes, channels = ("tsdf", "weight", "color"), (f32, wc, wc), (1, 1, 3)
        else:
            attrs, dtypes, channels = ("tsdf", "weight"), (f32, f32), (1, 1)
        self._attrs, self._dtypes, self._channels = attrs, dtypes, channels
        self._grid = o3d.t.geometry.VoxelBlockGrid(attrs, dtypes, channels, float(c.voxel_m),
                                                   int(c.block_resolution), int(c.initial_blocks), self._device)
        self.frames_integrated = 0
        self.pixels_integrated = 0

    @property
    def block_count(self) -> int:
        return int(self._grid.hashmap().size())

    @property
    def voxel_bytes(self) -> int:
        """Bytes of one voxel's attributes (:attr:`FusionConfig.voxel_bytes`)."""
        return self.config.voxel_bytes

    @property
    def nbytes(self) -> int:
        """Bytes of the allocated voxel blocks (the hash map's own tables not counted)."""
        return self.block_count * self.config.block_resolution ** 3 * self.voxel_bytes

    def integrate(self, depth_m: np.ndarray, K: np.ndarray, T_world_cam: np.ndarray,
                  color_rgb: np.ndarray | None = None) -> None:
        """Fuse one depth map (float32 metres, 0 = none) seen by a camera ``K`` at ``T_world_cam``.

        ``color_rgb`` is (H, W, 3) uint8 RGB; required when the volume fuses colour.
        """
        o3d = self._o3d
        depth = np.ascontiguousarray(depth_m, dtype=np.float32)
        if depth.ndim != 2:
            raise StereopathError(f"depth map must be 2-D, got shape {depth.shape}")
        K = np.asarray(K, dtype=np.float64)
        T = np.asarray(T_world_cam, dtype=np.float64)
        if K.shape != (3, 3) or T.shape != (4, 4) or not np.all(np.isfinite(T)) or not np.all(np.isfinite(K)):
            raise StereopathError("integrate: K must be a finite 3x3 and T_world_cam a finite 4x4 matrix")
        c = self.config
        rgb = None
        if c.color:
            if color_rgb is None:
                raise StereopathError("integrate: this volume fuses colour but no colour image was given")
            rgb = np.asarray(color_rgb)
            if rgb.shape != depth.shape + (3,):
                raise StereopathError(f"colour image is {rgb.shape} but the depth map is {depth.shape}")
        n_valid = int(np.count_nonzero(depth > 0))
        self.frames_integrated += 1
        if n_valid == 0:
            return
        self.pixels_integrated += n_valid
        extrinsic = o3d.core.Tensor(np.linalg.inv(T), o3d.core.float64)  # world -> camera
        intrinsic = o3d.core.Tensor(K, o3d.core.float64)
        dimg = o3d.t.geometry.Image(o3d.core.Tensor(depth))
        dmax, trunc = float(c.max_depth_m), float(c.trunc_voxels)
        blocks = self._grid.compute_unique_block_coordinates(dimg, intrinsic, extrinsic, 1.0, dmax, trunc)
        if rgb is not None:
            cimg = o3d.t.geometry.Image(o3d.core.Tensor(np.ascontiguousarray(rgb, dtype=np.float32) * (1.0 / 255.0)))
            self._grid.integrate(blocks, dimg, cimg, intrinsic, intrinsic, extrinsic, 1.0, dmax, trunc)
        else:
            self._grid.integrate(blocks, dimg, intrinsic, extrinsic, 1.0, dmax, trunc)

    def integrate_depth_map(self, depth_map: DepthMap, T_world_cam0: np.ndarray) -> None:
        """Fuse a :class:`stereopath.host.mapping.depth.DepthMap` given the pose of camera 0 (not the rectified camera)."""
        color = depth_map.colors_rgb() if self.config.color else None
        self.integrate(depth_map.depth_m, depth_map.K, depth_map.pose_world_rect(T_world_cam0), color)

    def store(self, folder: Path) -> None:
        """Write the volume into ``folder`` (created): its blocks' keys and attributes, the active ones
        only, a slice at a time from the hash map's own buffers (no copy of the volume is made), and
        ``volume.json`` (counts and the fusion settings); :meth:`restore` reads it back."""
        hm = self._grid.hashmap()
        active = np.sort(hm.active_buf_indices().numpy().astype(np.int64))
        folder.mkdir(parents=True, exist_ok=True)
        _write_rows(folder / "keys.npy", hm.key_tensor().numpy(), active)
        for name in self._attrs:
            _write_rows(folder / f"{name}.npy", self._grid.attribute(name).numpy(), active)
        (folder / "volume.json").write_text(json.dumps({
            "capacity": int(hm.capacity()), "blocks": len(active), "fusion": dataclasses.asdict(self.config),
            "frames_integrated": self.frames_integrated, "pixels_integrated": self.pixels_integrated}))

    def restore(self, folder: Path) -> None:
        """Replace this (empty) volume by the one :meth:`store` wrote into ``folder``, a slice of blocks at a
        time; StereopathError when it was stored with other fusion settings or is inconsistent."""
        o3d = self._o3d
        info = json.loads((folder / "volume.json").read_text())
        if info.get("fusion") != dataclasses.asdict(self.config):
            raise StereopathError(f"{folder}: the volume was stored with other fusion settings")
        n, cap = int(info["blocks"]), int(info["capacity"])
        if not 0 <= n <= cap <= 10_000_000:
            raise StereopathError(f"{folder}: {n} blocks in a table of {cap}")
        c = self.config
        grid = o3d.t.geometry.VoxelBlockGrid(self._attrs, self._dtypes, self._channels, float(c.voxel_m),
                                             int(c.block_resolution), cap, self._device)
        hm = grid.hashmap()
        views = [grid.attribute(name).numpy() for name in self._attrs]
        with _RowReader(folder / "keys.npy", (3,), np.dtype(np.int32), n) as keys:
            readers = [_RowReader(folder / f"{name}.npy", v.shape[1:], v.dtype, n) for name, v in zip(self._attrs, views)]
            try:
                for s in range(0, n, _SLICE):
                    k = keys.read(min(_SLICE, n - s))
                    buf, ok = hm.activate(o3d.core.Tensor(k))
                    if not ok.numpy().all():
                        raise StereopathError(f"{folder}: the stored volume holds a block twice")
                    rows = buf.numpy().astype(np.int64)
                    for v, r in zip(views, readers):
                        v[rows] = r.read(len(k))
            finally:
                for r in readers:
                    r.close()
        self._grid = grid
        self.frames_integrated = int(info["frames_integrated"])
        self.pixels_integrated = int(info["pixels_integrated"])

    def extract_mesh(self) -> open3d.geometry.TriangleMesh:
        """Legacy ``open3d.geometry.TriangleMesh`` (vertex normals, and colours when fused)."""
        if self.block_count == 0:
            return self._o3d.geometry.TriangleMesh()
        m = self._grid.extract_triangle_mesh(weight_threshold=float(self.config.min_weight))
        mesh = m.to_legacy()
        if len(mesh.vertices):
            mesh.compute_vertex_normals()
        return mesh

    def extract_cloud(self) -> open3d.geometry.PointCloud:
        """Legacy ``open3d.geometry.PointCloud`` of the zero crossings (normals, colours when fused)."""
        if self.block_count == 0:
            return self._o3d.geometry.PointCloud()
        p = self._grid.extract_point_cloud(weight_threshold=float(self.config.min_weight))
        return p.to_legacy()


_SLICE = 4096  # blocks written or read at a time when a volume is stored or restored


def _write_rows(path: Path, arr: np.ndarray, rows: np.ndarray) -> None:
    """``arr[rows]`` as a .npy file, written a slice of rows at a time (never all of them copied), synced."""
    header = {"descr": np.lib.format.dtype_to_descr(arr.dtype), "fortran_order": False,
              "shape": (len(rows), *arr.shape[1:])}
    with open(path, "wb") as f:
        np.lib.format.write_array_header_1_0(f, header)
        for s in range(0, len(rows), _SLICE):
            f.write(np.ascontiguousarray(arr[rows[s:s + _SLICE]]).tobytes())
        f.flush()
        os.fsync(f.fileno())


class _RowReader:
    """Rows of a .npy file written by :func:`_write_rows`, read in order a slice at a time; StereopathError
    when its shape or type is not the one expected."""

    def __init__(self, path: Path, row_shape: tuple[int, ...], dtype: np.dtype, n: int) -> None:
        self._f = open(path, "rb")
        try:
            if np.lib.format.read_magic(self._f) != (1, 0):
                raise StereopathError(f"{path}: not a stored volume file")
            shape, fortran, file_dtype = np.lib.format.read_array_header_1_0(self._f)
        except (ValueError, EOFError) as exc:
            self._f.close()
            raise StereopathError(f"{path}: not a stored volume file ({exc})") from None
        if tuple(shape) != (n, *row_shape) or fortran or file_dtype != dtype:
            self._f.close()
            raise StereopathError(f"{path}: holds {shape} {file_dtype}, expected {(n, *row_shape)} {dtype}")
        self._row_shape, self._dtype = row_shape, dtype
        self._per_row = int(np.prod(row_shape))

    def read(self, count: int) -> np.ndarray:
        a = np.fromfile(self._f, self._dtype, count * self._per_row)
        if a.size != count * self._per_row:
            raise StereopathError(f"{self._f.name}: cut short")
        return a.reshape(count, *self._row_shape)

    def close(self) -> None:
        self._f.close()

    def __enter__(self) -> _RowReader:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


# ---------------------------------------------------------------------------------------------
# writing


def _write_ply(path: str | Path, count: int, what: str, write) -> Path:
    """Atomic PLY write (temporary file, then rename) through Open3D's ``write(tmp_path)``."""
    p = Path(path)
    if count == 0:
        raise StereopathError(f"refusing to write an empty {what} to {p}")
    with replacing(p) as tmp:  # Open3D picks the format from the extension, so the temporary name keeps it
        if not write(str(tmp)) or not tmp.is_file():
            raise StereopathError(f"could not write {what} {p}")
    return p


def write_mesh(mesh: open3d.geometry.TriangleMesh, path: str | Path) -> Path:
    """Write a legacy triangle mesh (binary PLY) atomically: temporary file, then rename."""
    import open3d as o3d

    return _write_ply(path, len(mesh.vertices), "mesh", lambda t: o3d.io.write_triangle_mesh(
        t, mesh, write_ascii=False, compressed=False, print_progress=False))


def write_cloud(cloud: open3d.geometry.PointCloud, path: str | Path) -> Path:
    """Write a legacy point cloud (binary PLY) atomically."""
    import open3d as o3d

    return _write_ply(path, len(cloud.points), "point cloud", lambda t: o3d.io.write_point_cloud(
        t, cloud, write_ascii=False, compressed=False, print_progress=False))


def mesh_arrays(mesh: open3d.geometry.TriangleMesh) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """``(vertices (N, 3), triangles (M, 3), vertex colours (N, 3) in [0, 1] or None)`` of a legacy mesh."""
    v = np.asarray(mesh.vertices, dtype=np.float64)
    t = np.asarray(mesh.triangles, dtype=np.int64)
    c = np.asarray(mesh.vertex_colors, dtype=np.float64) if mesh.has_vertex_colors() else None
    return v, t, c
