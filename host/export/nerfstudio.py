"""``--format nerfstudio``: ``transforms.json``, ``images/`` and ``sparse_pc.ply`` for nerfstudio's
``splatfacto`` / ``nerfacto``, gsplat's and Brush's nerfstudio readers.

The conventions follow nerfstudio's own code (nerfstudio-project/nerfstudio):

* ``nerfstudio/data/dataparsers/nerfstudio_dataparser.py: Nerfstudio._generate_dataparser_outputs``
  reads ``frames[*].file_path`` and ``transform_matrix`` (camera to world), takes ``fl_x``,
  ``fl_y``, ``cx``, ``cy``, ``w``, ``h`` and ``k1, k2, k3, p1, p2`` from the top level when there,
  else from every frame (we have two cameras: per frame), ``camera_model`` from the top level,
  ``applied_transform`` (3x4, original data coordinates -> the saved ones; we save ours unchanged:
  identity, which also stops it from assuming COLMAP's axis swap) and ``ply_file_path``, read by
  ``_load_3D_points`` with Open3D and moved by the same transform as the poses.
* ``nerfstudio/process_data/colmap_utils.py: colmap_to_json`` turns COLMAP's OpenCV camera
  (``w2c``) into ``c2w = inv(w2c)`` with columns 1 and 2 negated (OpenGL camera axes), and
  ``parse_colmap_camera_params`` writes a PINHOLE camera as ``camera_model: OPENCV`` with zero
  ``k1, k2, p1, p2``: what we write for our undistorted keyframe images.

Not checked here: training.  The world is ours (metres; gravity-aligned z up when the
reprocessing levelled it); nerfstudio re-orients and re-scales it itself (``orientation_method``,
``auto_scale_poses``).
"""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any

import numpy as np

from stereopath.device.core.rig import CameraModel
from stereopath.host.export.conventions import T_world_cam1, opengl_from_opencv
from stereopath.host.export.keyframe_images import write_keyframe_images
from stereopath.host.export.result import ExportSource

log = logging.getLogger(__name__)

PLY_NAME = "sparse_pc.ply"
CHUNK = 65536  # points written per block


def camera_entry(cam: CameraModel) -> dict[str, float | int]:
    """A pinhole camera as nerfstudio's per-frame intrinsics (no distortion left in the written images)."""
    K = np.asarray(cam.K, float)
    return {"fl_x": float(K[0, 0]), "fl_y": float(K[1, 1]), "cx": float(K[0, 2]), "cy": float(K[1, 2]),
            "w": int(cam.size[0]), "h": int(cam.size[1]), "k1": 0.0, "k2": 0.0, "p1": 0.0, "p2": 0.0}


def write_ply(path: Path, xyz: np.ndarray, rgb: np.ndarray) -> None:
    """A binary little-endian PLY of points with 8-bit colours, written in blocks."""
    header = ("ply\nformat binary_little_endian 1.0\n"
              f"element vertex {len(xyz)}\n"
              "property float x\nproperty float y\nproperty float z\n"
              "property uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n")
    dt = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("r", "u1"), ("g", "u1"), ("b", "u1")])
    with open(path, "wb") as fh:
        fh.write(header.encode("ascii"))
        for s in range(0, len(xyz), CHUNK):
            block = np.empty(min(CHUNK, len(xyz) - s), dt)
            for i, n in enumerate("xyz"):
                block[n] = xyz[s:s + len(block), i]
            for i, n in enumerate("rgb"):
                block[n] = rgb[s:s + len(block), i]
            fh.write(block.tobytes())


def export_nerfstudio(src: ExportSource, out: Path, progress: bool | None = None) -> dict[str, Any]:
    """Write the nerfstudio dataset into the (empty) folder ``out``; returns counts for the report."""
    written, rgb = write_keyframe_images(src, out / "images", progress)
    cams = (camera_entry(src.rig.cam0), camera_entry(src.rig.cam1))
    frames = []
    for im in written:
        T = im.T_world_cam0 if im.cam == 0 else T_world_cam1(im.T_world_cam0, src.rig.R, src.rig.T)
        frames.append({"file_path": f"images/{im.name}", "transform_matrix": opengl_from_opencv(T).tolist(),
                       **cams[im.cam], "camera": f"cam{im.cam}", "keyframe": im.k, "t_ns": im.t_ns})
    meta: dict[str, Any] = {"camera_model": "OPENCV", "frames": frames,
                            "applied_transform": np.eye(4)[:3].tolist(),
                            "stereopath": {"source": str(src.path), "kind": src.kind, "world_frame": src.world_frame,
                                           "units": "metres"}}
    if src.has_points:
        write_ply(out / PLY_NAME, src.point_xyz, rgb)
        meta["ply_file_path"] = PLY_NAME
    (out / "transforms.json").write_text(json.dumps(meta, indent=1) + "\n")
    return {"images": len(written), "keyframes": len(src.keyframes), "points": int(len(src.point_ids))}
