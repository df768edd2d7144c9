"""KITTI odometry reader: ``sequences/NN/{image_0,image_1,calib.txt,times.txt}`` + ``poses/NN.txt``.

Frame ``i`` is ``image_0/%06d.png`` and ``image_1/%06d.png`` at ``times.txt`` row ``i``.  Frames
whose image is missing in either camera are dropped with ONE warning giving the counts.  The
image size for the calibration is read from the first image.  Ground truth ``T_world_cam0`` comes
from ``<root>/poses/NN.txt`` where ``<root>`` is two levels above the sequence folder; the
sequence has no IMU.
"""

from __future__ import annotations

import logging
import os
from decimal import InvalidOperation
from pathlib import Path

import numpy as np

from stereopath.device.formats.sequence import SequenceBase
from stereopath.device.formats.csvrows import read_lines
from stereopath.device.formats.images import read_gray
from stereopath.device.errors import DatasetError
from stereopath.device.core.frames import StereoFrame
from stereopath.device.core.rig import Rig
from stereopath.device.formats.rig_files import load_kitti_calib
from stereopath.device.formats.tum import Trajectory, read_kitti_poses, seconds_to_ns

log = logging.getLogger(__name__)


class KittiSequence(SequenceBase):
    """A KITTI odometry sequence.  Build with :func:`open_kitti`."""

    def __init__(self, seq_dir: Path, rig: Rig, t_ns: np.ndarray, index: list[int], poses_path: Path,
                 times_all_ns: np.ndarray, spec: str) -> None:
        super().__init__(rig, t_ns)
        self.seq_dir = seq_dir
        self.name = f"kitti-{seq_dir.name}"
        self.spec = spec
        self.index = index  # KITTI frame number of each pair
        self._poses_path = poses_path
        self._times_all = times_all_ns
        self._gt: Trajectory | None | bool = False

    def image_paths(self, i: int) -> tuple[Path, Path]:
        name = f"{self.index[i]:06d}.png"
        return self.seq_dir / "image_0" / name, self.seq_dir / "image_1" / name

    def _load(self, i: int) -> StereoFrame:
        p0, p1 = self.image_paths(i)
        left, right = read_gray(p0), read_gray(p1)
        for img, path in ((left, p0), (right, p1)):
            if (img.shape[1], img.shape[0]) != tuple(self.rig.cam0.size):
                raise DatasetError(f"{path}: image is {img.shape[1]}x{img.shape[0]}, the sequence's first image "
                                   f"is {self.rig.cam0.size[0]}x{self.rig.cam0.size[1]}")
        return StereoFrame(seq=i, t_ns=int(self.t_ns[i]), left=left, right=right,
                           meta={"source": self.name, "kitti_frame": self.index[i]})

    @property
    def groundtruth(self) -> Trajectory | None:
        if self._gt is False:
            self._gt = self._read_poses()
        return self._gt  # type: ignore[return-value]

    def _read_poses(self) -> Trajectory | None:
        p = self._poses_path
        if not p.is_file():
            log.info("%s: no ground truth (%s not found)", self.name, p)
            return None
        traj = read_kitti_poses(p)
        n = len(self._times_all)
        if len(traj) < n:
            raise DatasetError(f"{p}: {len(traj)} poses but times.txt has {n} rows")
        if len(traj) > n:
            log.info("%s: using the first %d of %d poses (times.txt rows)", p, n, len(traj))
        return Trajectory(self._times_all, traj.T_world_cam[:n])


def read_times(path: Path) -> np.ndarray:
    """KITTI ``times.txt`` (one time in seconds a line) -> int64 nanoseconds."""
    out = []
    for line, s in read_lines(path, torn_tail_ok=False):
        try:
            out.append(seconds_to_ns(s))
        except (InvalidOperation, ValueError):
            raise DatasetError(f"{path}:{line}: time is not a number: {s!r}") from None
    if not out:
        raise DatasetError(f"{path}: no times")
    t = np.array(out, dtype=np.int64)
    bad = np.nonzero(np.diff(t) <= 0)[0]
    if len(bad):
        raise DatasetError(f"{path}: times do not increase at row {int(bad[0]) + 2}")
    return t


def open_kitti(seq_dir: str | Path, spec: str | None = None) -> KittiSequence:
    d = Path(seq_dir)
    if not d.is_dir():
        raise DatasetError(f"KITTI sequence folder not found: {d}")
    for sub in ("image_0", "image_1"):
        if not (d / sub).is_dir():
            raise DatasetError(f"missing folder {d / sub}")
    for f in ("calib.txt", "times.txt"):
        if not (d / f).is_file():
            raise DatasetError(f"missing file {d / f}")
    times = read_times(d / "times.txt")
    present = [set(os.listdir(d / sub)) for sub in ("image_0", "image_1")]
    names = [f"{i:06d}.png" for i in range(len(times))]
    index = [i for i, nm in enumerate(names) if nm in present[0] and nm in present[1]]
    extra = sum(len({f for f in p if f.endswith(".png")} - set(names)) for p in present)
    if len(index) < len(times) or extra:
        log.warning("%s: times.txt has %d rows, image_0 has %d and image_1 has %d of them (%d images beyond "
                    "times.txt); using the %d frames present in both cameras",
                    d, len(times), sum(nm in present[0] for nm in names), sum(nm in present[1] for nm in names),
                    extra, len(index))
    if not index:
        raise DatasetError(f"{d}: no frame has an image in both image_0 and image_1")
    first = read_gray(d / "image_0" / names[index[0]])
    rig = load_kitti_calib(d / "calib.txt", (first.shape[1], first.shape[0]))
    poses = d.parent.parent / "poses" / f"{d.name}.txt"
    return KittiSequence(d, rig, times[index], index, poses, times, spec or f"kitti:{d}")
