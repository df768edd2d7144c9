"""``--format colmap``: a COLMAP 4 sparse model written with pycolmap, and the keyframe images.

Layout (what COLMAP, gsplat's and nerfstudio's COLMAP readers open)::

    OUT/images/cam0/<t_ns>.png, OUT/images/cam1/<t_ns>.png
    OUT/sparse/0/{cameras,images,points3D,rigs,frames}.bin   (or .txt with ``text=True``)

One rig (``rig_id`` 1) of two PINHOLE cameras (``camera_id`` 1 left, the reference sensor; 2
right, ``sensor_from_rig`` = the rig's ``X1 = R X0 + T``), one frame per keyframe (``frame_id``
k + 1, ``rig_from_world`` = the adjusted ``inv(T_world_cam0)``), two images per frame
(``image_id`` 2k + 1 and 2k + 2).  The cameras are pinhole because the written images are resampled
onto the calibrated ``K`` without distortion (:mod:`stereopath.host.export.keyframe_images`);
the right camera's principal point carries the disparity offset the bundle adjustment applied.
Each bundle-adjusted point is a ``Point3D`` with its colour and one track element per kept
observation, whose ``Point2D`` is the observed (undistorted) pixel.
"""

from __future__ import annotations

import logging
from pathlib import Path
from types import ModuleType
from typing import TYPE_CHECKING, Any

import numpy as np

from stereopath.device.core.geometry import invert_pose
from stereopath.device.core.rig import CameraModel
from stereopath.host.export.conventions import T_cam1_cam0
from stereopath.host.export.keyframe_images import write_keyframe_images
from stereopath.host.export.result import ExportSource

if TYPE_CHECKING:
    import pycolmap

log = logging.getLogger(__name__)

SPARSE = Path("sparse") / "0"


def _rigid(pycolmap: ModuleType, T: np.ndarray) -> pycolmap.Rigid3d:
    T = np.asarray(T, float)
    return pycolmap.Rigid3d(pycolmap.Rotation3d(T[:3, :3]), T[:3, 3].copy())


def _camera(pycolmap: ModuleType, camera_id: int, cam: CameraModel) -> pycolmap.Camera:
    K = np.asarray(cam.K, float)
    return pycolmap.Camera(camera_id=camera_id, model="PINHOLE", width=int(cam.size[0]), height=int(cam.size[1]),
                           params=[K[0, 0], K[1, 1], K[0, 2], K[1, 2]])


def build_reconstruction(src: ExportSource, names: dict[tuple[int, int], str],
                         rgb: np.ndarray) -> pycolmap.Reconstruction:
    """The pycolmap ``Reconstruction`` of ``src`` (``names[(k, cam)]``: each image's name under images/)."""
    import pycolmap

    rec = pycolmap.Reconstruction()
    rec.add_camera(_camera(pycolmap, 1, src.rig.cam0))
    rec.add_camera(_camera(pycolmap, 2, src.rig.cam1))
    sensors = [pycolmap.sensor_t(type=pycolmap.SensorType.CAMERA, id=c) for c in (1, 2)]
    rig = pycolmap.Rig(rig_id=1)
    rig.add_ref_sensor(sensors[0])
    rig.add_sensor(sensors[1], _rigid(pycolmap, T_cam1_cam0(src.rig.R, src.rig.T)))
    rec.add_rig(rig)
    obs = src.observations
    order = np.lexsort((obs[:, 1], obs[:, 2], obs[:, 0])) if len(obs) else np.zeros(0, np.int64)
    obs = obs[order]
    key = obs[:, 0].astype(np.int64) * 2 + obs[:, 2].astype(np.int64)  # image_id - 1
    starts = np.searchsorted(key, np.arange(2 * len(src.keyframes) + 1))
    for kf in src.keyframes:
        frame = pycolmap.Frame(frame_id=kf.k + 1, rig_id=1)
        frame.rig_from_world = _rigid(pycolmap, invert_pose(kf.T_world_cam0))
        for cam in (0, 1):
            frame.add_data_id(pycolmap.data_t(sensor_id=sensors[cam], id=2 * kf.k + cam + 1))
        rec.add_frame(frame)
        for cam in (0, 1):
            i = 2 * kf.k + cam
            rows = obs[starts[i]:starts[i + 1]]
            im = pycolmap.Image(name=names[(kf.k, cam)], keypoints=np.ascontiguousarray(rows[:, 3:5], float),
                                camera_id=cam + 1, image_id=i + 1)
            im.frame_id = kf.k + 1
            rec.add_image(im)
        rec.register_frame(kf.k + 1)
    # track elements: (image_id, index of the observation among its image's keypoints)
    image_id = key + 1
    idx2d = np.arange(len(obs)) - starts[key]
    by_point = np.argsort(obs[:, 1], kind="stable")
    pids = obs[by_point, 1].astype(np.int64)
    bounds = np.flatnonzero(np.r_[True, pids[1:] != pids[:-1], True]) if len(pids) else np.zeros(1, np.int64)
    row_of = {int(p): i for i, p in enumerate(src.point_ids)}
    for a, b in zip(bounds[:-1], bounds[1:]):
        pid = int(pids[a])
        track = pycolmap.Track()
        for r in by_point[a:b]:
            track.add_element(int(image_id[r]), int(idx2d[r]))
        row = row_of[pid]
        rec.add_point3D(np.asarray(src.point_xyz[row], float), track, np.asarray(rgb[row], np.uint8))
    return rec


def export_colmap(src: ExportSource, out: Path, progress: bool | None = None, text: bool = False) -> dict[str, Any]:
    """Write the COLMAP model and images into the (empty) folder ``out``; returns counts and pycolmap's
    mean reprojection error for the report."""
    from stereopath.device.errors import DatasetError

    if not src.has_points:
        raise DatasetError(f"{src.path}: a {src.kind} holds no bundle-adjusted points; a COLMAP model needs them "
                           f"(run `stereopath host reprocess` and export its output)")
    written, rgb = write_keyframe_images(src, out / "images", progress)
    rec = build_reconstruction(src, {(w.k, w.cam): w.name for w in written}, rgb)
    rec.update_point_3d_errors()
    (out / SPARSE).mkdir(parents=True)
    if text:
        rec.write_text(str(out / SPARSE))
    else:
        rec.write_binary(str(out / SPARSE))
    return {"images": len(written), "keyframes": len(src.keyframes), "points": int(rec.num_points3D()),
            "observations": int(len(src.observations)),
            "mean_reprojection_error_px": float(rec.compute_mean_reprojection_error())}
