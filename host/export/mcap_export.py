"""``--format mcap``: the scan as an MCAP recording (:class:`~stereopath.host.export.mcap_recording.McapRecorder`).

Every pose of the source (a reprocessed output: the refined path of every frame; a session: its
on-board path; a ``host live`` store: the keyframes), the images at those poses (the recorded
files' bytes as they are, or the keyframes encoded as PNG), the IMU samples between the first and
the last pose, the rig transform once and the bundle-adjusted points once at the last pose; in
time order, one frame at a time.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from stereopath.host.export.conventions import T_cam1_cam0
from stereopath.host.export.result import ExportSource
from stereopath.host.progress import Bar

log = logging.getLogger(__name__)

FILE_NAME = "scan.mcap"


def _encoded(src: ExportSource) -> Callable[[int], tuple[bytes, bytes, str]]:
    """Pose index -> (left bytes, right bytes, format)."""
    if src.frame_images is not None:
        return src.frame_images
    import cv2

    def encode(i: int) -> tuple[bytes, bytes, str]:
        left, right = src.frame_loader(i)
        return tuple(cv2.imencode(".png", im)[1].tobytes() for im in (left, right)) + ("png",)

    return encode


def export_mcap(src: ExportSource, out: Path, progress: bool | None = None) -> dict[str, Any]:
    """Write ``OUT/scan.mcap``; returns the message counts per channel."""
    from stereopath.host.export.mcap_recording import McapRecorder

    t, T = np.asarray(src.t_ns, np.int64), np.asarray(src.T_world_cam0, float)
    read = _encoded(src)
    imu = src.imu if src.imu is not None and len(src.imu) else None
    imu_t = np.asarray(imu.t_ns, np.int64) if imu is not None else np.zeros(0, np.int64)
    lo = int(np.searchsorted(imu_t, t[0])) if len(t) else 0
    with open(out / FILE_NAME, "wb") as stream:
        rec = McapRecorder(stream, source=str(src.path))
        with Bar(len(t), "mcap", progress, "frame") as tick:
            for i in range(len(t)):
                hi = int(np.searchsorted(imu_t, t[i], side="right"))
                if imu is not None and hi > lo:
                    rec.imu(imu_t[lo:hi], imu.gyro_rad_s[lo:hi], imu.accel_m_s2[lo:hi])
                lo = max(lo, hi)
                if i == 0:
                    rec.rig(int(t[0]), np.linalg.inv(T_cam1_cam0(src.rig.R, src.rig.T)))
                rec.pose(int(t[i]), T[i])
                left, right, fmt = read(i)
                rec.images(int(t[i]), left, right, fmt)
                tick(1)
        if src.has_points:
            rec.points(int(t[-1]), src.point_xyz)
        rec.close()
    return {"messages": dict(rec.counts), "file": FILE_NAME}
