"""EuRoC/ASL reader: ``mav0/cam0``, ``mav0/cam1``, ``mav0/imu0`` plus ground truth.

Reads third-party EuRoC sequences and our own recordings (see :mod:`stereopath.device.formats.layout`)
through one class.  Stereo pairs are the timestamps listed in both cameras' ``data.csv`` whose
image files exist in both ``data/`` folders; anything else is dropped with ONE warning giving
the counts.  Images, IMU and ground truth are loaded only when asked for.

Ground truth (``T_world_cam0``), first found wins:

1. ``groundtruth.tum`` beside ``mav0`` (our sessions): camera-0 poses as they are;
2. ``groundtruth_tum.txt`` beside ``mav0`` (EuRoC body poses, TUM): ``T_world_body @ T_BS(cam0)``;
3. ``mav0/state_groundtruth_estimate0/data.csv`` (EuRoC body poses): same composition;
4. ``mav0/mocap0/data.csv`` (TUM VI: motion-capture poses of the IMU, the same columns): same composition.

Calibration: our ``mav0/rig.yaml``, else EuRoC's ``camN/sensor.yaml``, else a Kalibr camchain beside
the data (:func:`stereopath.device.formats.rig_files.load_euroc_calibration`).  A fisheye
(equidistant) camera's images are read through its pinhole view
(:mod:`stereopath.device.core.fisheye`), so the sequence's rig is always pinhole.
"""

from __future__ import annotations

import json
import logging
import os
from pathlib import Path
from typing import Any

import numpy as np

from stereopath.device.formats import layout
from stereopath.device.formats.fileio import load_json
from stereopath.device.formats.sequence import SequenceBase
from stereopath.device.formats.csvrows import parse_float, parse_int, read_rows
from stereopath.device.formats.images import read_gray
from stereopath.device.errors import DatasetError
from stereopath.device.core.frames import ImuSamples, StereoFrame
from stereopath.device.core.rig import Rig
from stereopath.device.core.fisheye import PinholeView
from stereopath.device.formats.rig_files import load_euroc_calibration, load_rig_yaml
from stereopath.device.formats.tum import Trajectory, check_position, check_quaternion, read_tum, read_tum_poses

log = logging.getLogger(__name__)


class AslSequence(SequenceBase):
    """A stereo(-inertial) sequence in the ASL layout.  Build with :func:`open_asl`."""

    def __init__(self, mav0: Path, rig: Rig, t_ns: np.ndarray, files0: list[Path], files1: list[Path],
                 name: str, spec: str, views: tuple[PinholeView | None, PinholeView | None] = (None, None)) -> None:
        super().__init__(rig, t_ns)
        self.views = views  # per camera: the pinhole view a fisheye camera's images are read through
        self.mav0 = mav0
        self.name = name
        self.spec = spec
        self._files = (files0, files1)
        self._imu: ImuSamples | None | bool = False  # False = not loaded yet
        self._gt: Trajectory | None | bool = False
        self.session_dir: Path | None = None  # set by open_session
        self.manifest: dict[str, Any] | None = None

    def image_paths(self, i: int) -> tuple[Path, Path]:
        return self._files[0][i], self._files[1][i]

    def _load(self, i: int) -> StereoFrame:
        p0, p1 = self._files[0][i], self._files[1][i]
        left, right = read_gray(p0), read_gray(p1)
        images = []
        for cam, view, img, path in ((self.rig.cam0, self.views[0], left, p0), (self.rig.cam1, self.views[1], right, p1)):
            size = cam.size if view is None else view.source.size
            if (img.shape[1], img.shape[0]) != tuple(size):
                raise DatasetError(f"{path}: image is {img.shape[1]}x{img.shape[0]} but the calibration "
                                   f"says {size[0]}x{size[1]}")
            images.append(img if view is None else view.apply(img))
        left, right = images
        return StereoFrame(seq=i, t_ns=int(self.t_ns[i]), left=left, right=right, meta={"source": self.name})

    @property
    def imu(self) -> ImuSamples | None:
        if self._imu is False:
            self._imu = read_asl_imu(self.mav0 / layout.IMU)
        return self._imu  # type: ignore[return-value]

    @property
    def groundtruth(self) -> Trajectory | None:
        if self._gt is False:
            self._gt = _read_groundtruth(self.mav0, self.rig)
        return self._gt  # type: ignore[return-value]

    @property
    def trajectory(self) -> Trajectory | None:
        """The estimated path recorded with the session (``trajectory.tum``), if any."""
        if self.session_dir is None:
            return None
        p = self.session_dir / layout.TRAJECTORY
        if not p.is_file():
            return None
        return rebased_trajectory(read_tum_poses(p, torn_tail_ok=True), self.session_dir / "estimator.json")


def rebased_trajectory(traj: Trajectory, estimator_json: Path) -> Trajectory:
    """The recorded path in one world: when the on-board estimator levelled its world during the session
    (``world_rebase`` in ``estimator.json``: a start in motion), the poses recorded before it are mapped."""
    if not estimator_json.is_file():
        return traj
    try:
        info = json.loads(estimator_json.read_text())
        rebase = info.get("world_rebase") if isinstance(info, dict) else None
        if rebase is None:
            return traj
        G = np.asarray(rebase["T_new_old"], float)
        t0 = int(rebase["from_t_ns"])
    except (ValueError, KeyError, TypeError) as exc:
        raise DatasetError(f"{estimator_json}: unreadable world_rebase ({exc})") from None
    if G.shape != (4, 4) or not np.isfinite(G).all():
        raise DatasetError(f"{estimator_json}: world_rebase.T_new_old is not a finite 4x4 matrix")
    T = traj.T_world_cam.copy()
    before = traj.t_ns < t0
    T[before] = G @ T[before]
    return Trajectory(traj.t_ns, T)


def open_asl(mav0_dir: str | Path, spec: str | None = None) -> AslSequence:
    """Open an ASL ``mav0`` folder (or a folder containing ``mav0``)."""
    m = Path(mav0_dir)
    if not m.is_dir():
        raise DatasetError(f"ASL folder not found: {m}")
    if not (m / "cam0").exists() and (m / layout.MAV0).is_dir():
        m = m / layout.MAV0
    for cam in layout.CAMERAS:
        if not (m / cam).is_dir():
            raise DatasetError(f"missing folder {m / cam}")
        if not (m / cam / "data").is_dir():
            raise DatasetError(f"missing folder {m / cam / 'data'}")
    views: tuple[PinholeView | None, PinholeView | None] = (None, None)
    if (m / layout.RIG_YAML).is_file():
        rig = load_rig_yaml(m / layout.RIG_YAML)
    else:
        calib = load_euroc_calibration(m)
        rig, views = calib.rig, calib.views

    rows = [_read_camera_csv(m / cam / "data.csv") for cam in layout.CAMERAS]
    present = [set(os.listdir(m / cam / "data")) for cam in layout.CAMERAS]
    with_image = [{t: f for t, f in r.items() if f in files} for r, files in zip(rows, present)]
    t_pairs = sorted(set(with_image[0]) & set(with_image[1]))
    dropped = sum(len(r) for r in rows) - 2 * len(t_pairs)
    if dropped:
        log.warning(
            "%s: cam0 lists %d rows (%d with an image), cam1 lists %d rows (%d with an image); "
            "using the %d timestamps present in both cameras with both images, dropping %d rows",
            m, len(rows[0]), len(with_image[0]), len(rows[1]), len(with_image[1]), len(t_pairs), dropped,
        )
    if not t_pairs:
        raise DatasetError(f"{m}: no stereo pairs (no timestamp with an image in both cam0 and cam1)")
    files = [[m / cam / "data" / with_image[k][t] for t in t_pairs] for k, cam in enumerate(layout.CAMERAS)]
    name = m.parent.name if m.name == layout.MAV0 else m.name
    return AslSequence(m, rig, np.array(t_pairs, dtype=np.int64), files[0], files[1],
                       name=name, spec=spec or f"euroc:{m}", views=views)


def open_session(session_dir: str | Path) -> AslSequence:
    """Open one of our recordings: ``SESSION/mav0`` plus manifest, ground truth and estimate."""
    d = Path(session_dir)
    if not d.is_dir():
        raise DatasetError(f"session folder not found: {d}")
    if not (d / layout.MAV0).is_dir():
        raise DatasetError(f"missing folder {d / layout.MAV0} (not a stereopath session)")
    seq = open_asl(d / layout.MAV0, spec=f"session:{d}")
    seq.session_dir = d
    seq.name = d.name
    mpath = d / layout.MANIFEST
    if mpath.is_file():
        try:
            seq.manifest = load_json(mpath)
        except (json.JSONDecodeError, UnicodeDecodeError) as exc:  # it only describes the recording:
            log.warning("%s: invalid JSON, ignored (%s)", mpath, exc)  # the images and IMU are what count
        status = seq.manifest.get("status") if isinstance(seq.manifest, dict) else None
        if status == "recording":
            log.warning("%s: the session was not closed (the recorder stopped while recording)", d)
    else:
        log.warning("%s: no %s", d, layout.MANIFEST)
    return seq


# ---------------------------------------------------------------------------------------------
# the individual files


def _read_camera_csv(path: Path) -> dict[int, str]:
    out: dict[int, str] = {}
    for line, (ts, fname) in read_rows(path, 2):
        t = parse_int(path, line, ts)
        if not fname or fname != os.path.basename(fname) or fname in (".", ".."):
            raise DatasetError(f"{path}:{line}: bad image file name {fname!r}")
        if t in out:
            raise DatasetError(f"{path}:{line}: duplicate timestamp {t}")
        out[t] = fname
    return out


def read_asl_imu(imu_dir: Path) -> ImuSamples | None:
    """``imu0/data.csv`` (EuRoC columns) plus our optional ``temperature.csv``."""
    path = imu_dir / "data.csv"
    if not imu_dir.is_dir():
        log.info("%s: no IMU folder; the sequence has no IMU", imu_dir)
        return None
    rows = read_rows(path, 7)
    n = len(rows)
    t = np.empty(n, dtype=np.int64)
    v = np.empty((n, 6))
    prev = None
    for k, (line, f) in enumerate(rows):
        t[k] = parse_int(path, line, f[0])
        if prev is not None and t[k] <= prev:
            raise DatasetError(f"{path}:{line}: timestamp {t[k]} does not increase (previous {prev})")
        prev = t[k]
        for j in range(6):
            v[k, j] = parse_float(path, line, f[j + 1], what=f"column {j + 2}")
    temp = None
    tpath = imu_dir / layout.IMU_TEMPERATURE
    if tpath.is_file():
        temps = {parse_int(tpath, line, f[0]): parse_float(tpath, line, f[1], "temperature")
                 for line, f in read_rows(tpath, 2)}
        covered = sum(1 for x in t.tolist() if x in temps)
        if covered == n:
            temp = np.array([temps[x] for x in t.tolist()])
        else:
            log.warning("%s: temperature rows cover %d of %d IMU samples; temperature ignored", tpath, covered, n)
    return ImuSamples(t, v[:, :3], v[:, 3:], temp)


def _read_groundtruth(mav0: Path, rig: Rig) -> Trajectory | None:
    root = mav0.parent
    ours = root / layout.GROUNDTRUTH
    if ours.is_file():
        return read_tum(ours)
    body: Trajectory | None = None
    if (root / layout.EUROC_GROUNDTRUTH_TUM).is_file():
        body = read_tum(root / layout.EUROC_GROUNDTRUTH_TUM)
    elif (mav0 / layout.EUROC_GROUNDTRUTH_CSV).is_file():
        body = _read_euroc_state_csv(mav0 / layout.EUROC_GROUNDTRUTH_CSV)
    elif (mav0 / layout.MOCAP_GROUNDTRUTH_CSV).is_file():
        body = _read_euroc_state_csv(mav0 / layout.MOCAP_GROUNDTRUTH_CSV)
    if body is None:
        return None
    T_body_cam0 = rig.T_body_cam0
    if T_body_cam0 is None:
        log.warning("%s: the rig has no T_body_cam0; taking the body ground truth as camera-0 poses", mav0)
        T_body_cam0 = np.eye(4)
    return Trajectory(body.t_ns, body.T_world_cam @ T_body_cam0)


def _read_euroc_state_csv(path: Path) -> Trajectory:
    """EuRoC ``state_groundtruth_estimate0/data.csv`` (or TUM VI ``mocap0/data.csv``): t, p_RS_R (3),
    q_RS (w, x, y, z), ..."""
    rows = read_rows(path, (8, 64))
    ts, Ts = [], []
    for line, f in rows:
        t = parse_int(path, line, f[0])
        v = [parse_float(path, line, x) for x in f[1:8]]
        row = [*v[:3], v[4], v[5], v[6], v[3]]  # q w, x, y, z -> x, y, z, w
        check_position(path, line, np.array(row[:3]))
        check_quaternion(path, line, np.array(row[3:]))
        ts.append(t)
        Ts.append(row)
    if not ts:
        raise DatasetError(f"{path}: no poses")
    return Trajectory.from_pose_rows(ts, Ts)
