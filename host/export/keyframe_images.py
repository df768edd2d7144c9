"""The keyframe images of an export, written one keyframe at a time, and the points' colours read from them.

Images are written as 8-bit 3-channel PNG (grey recordings repeated into three channels: some
readers take the first three channels of whatever they load) under ``images/cam0/`` and
``images/cam1/``, named by the frame time (``<t_ns>.png``, the same name in both folders, as
COLMAP's rig layout expects).  A camera with lens distortion is resampled onto its own ``K``
without distortion (``cv2.initUndistortRectifyMap`` with no rotation), so the observations of the
bundle adjustment, which are undistorted pixels, fall on the written pixels of a pinhole camera.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from stereopath.device.core.rig import CameraModel
from stereopath.host.export.result import ExportSource
from stereopath.host.progress import Bar

log = logging.getLogger(__name__)

CAMERA_DIRS = ("cam0", "cam1")


@dataclass(frozen=True)
class WrittenImage:
    k: int  # keyframe index
    cam: int  # 0 left, 1 right
    name: str  # relative to the images folder, e.g. "cam0/123.png"
    t_ns: int
    T_world_cam0: np.ndarray


class _Undistort:
    """One camera's resampling onto its own pinhole K (identity for a camera without distortion)."""

    def __init__(self, cam: CameraModel) -> None:
        self.maps = None
        if np.any(np.asarray(cam.dist) != 0):
            import cv2

            self.maps = cv2.initUndistortRectifyMap(cam.K, cam.dist, None, cam.K, tuple(cam.size), cv2.CV_32FC1)

    def __call__(self, img: np.ndarray) -> np.ndarray:
        if self.maps is None:
            return img
        import cv2

        return cv2.remap(img, self.maps[0], self.maps[1], cv2.INTER_LINEAR)


def _bgr(img: np.ndarray) -> np.ndarray:
    img = np.asarray(img)
    if img.dtype != np.uint8:
        img = np.clip(img, 0, 255).astype(np.uint8)
    return np.repeat(img[:, :, None], 3, axis=2) if img.ndim == 2 else img[:, :, :3]


def first_left_observation(observations: np.ndarray) -> dict[int, tuple[int, float, float]]:
    """Point id -> (keyframe, u, v) of its first left observation (where its colour is read)."""
    out: dict[int, tuple[int, float, float]] = {}
    left = observations[observations[:, 2] == 0]
    order = np.lexsort((left[:, 0], left[:, 1]))
    ids = left[order, 1].astype(np.int64)
    firsts = np.flatnonzero(np.r_[True, ids[1:] != ids[:-1]]) if len(ids) else np.zeros(0, np.int64)
    for r in left[order][firsts]:
        out[int(r[1])] = (int(r[0]), float(r[3]), float(r[4]))
    return out


def write_keyframe_images(src: ExportSource, images_dir: Path, progress: bool | None,
                          desc: str = "keyframe images") -> tuple[list[WrittenImage], np.ndarray]:
    """Write every keyframe's two images; returns them and the points' RGB colours (``src.point_ids`` order)."""
    import cv2

    from stereopath.device.errors import StereopathError

    for d in CAMERA_DIRS:
        (images_dir / d).mkdir(parents=True, exist_ok=True)
    undistort = (_Undistort(src.rig.cam0), _Undistort(src.rig.cam1))
    firsts = first_left_observation(src.observations) if src.has_points else {}
    by_kf: dict[int, list[tuple[int, float, float]]] = {}
    row_of = {int(p): i for i, p in enumerate(src.point_ids)}
    for pid, (k, u, v) in firsts.items():
        by_kf.setdefault(k, []).append((row_of[pid], u, v))
    rgb = np.full((len(src.point_ids), 3), 128, np.uint8)
    written: list[WrittenImage] = []
    with Bar(len(src.keyframes), desc, progress, "kf") as tick:
        for kf in src.keyframes:
            images = kf.load()
            for cam, img in enumerate(images):
                bgr = undistort[cam](_bgr(img))
                name = f"{CAMERA_DIRS[cam]}/{kf.t_ns}.png"
                if not cv2.imwrite(str(images_dir / name), bgr):
                    raise StereopathError(f"cannot write {images_dir / name}")
                written.append(WrittenImage(kf.k, cam, name, kf.t_ns, kf.T_world_cam0))
                if cam == 0 and kf.k in by_kf:
                    rows = np.array(by_kf[kf.k])
                    h, w = bgr.shape[:2]
                    x = np.clip(np.round(rows[:, 1]).astype(int), 0, w - 1)
                    y = np.clip(np.round(rows[:, 2]).astype(int), 0, h - 1)
                    rgb[rows[:, 0].astype(int)] = bgr[y, x, ::-1]
            tick(1)
    return written, rgb
