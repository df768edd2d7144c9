"""Rig calibration files: our rig YAML, KITTI odometry ``calib.txt`` and EuRoC/ASL ``sensor.yaml`` (read and written).

The rig itself (cameras, extrinsics, rectification) is the pure model of
:mod:`stereopath.device.core.rig`; this module only reads and writes it.
"""

from __future__ import annotations

import logging
import re
from pathlib import Path
from typing import Any

import numpy as np

from stereopath.device.core.geometry import invert_pose
from stereopath.device.core.rig import CameraModel, Rig, checked_array, make_camera, make_rig, rig_from_dict, \
    rig_to_dict
from stereopath.device.errors import CalibrationError
from stereopath.device.formats.fileio import write_text_atomic

log = logging.getLogger(__name__)


def load_rig_yaml(path: str | Path) -> Rig:
    """Load our rig YAML; any problem raises :class:`CalibrationError` naming the file and field."""
    import yaml

    p = Path(path)
    try:
        text = p.read_text()
    except FileNotFoundError:
        raise CalibrationError(f"calibration file not found: {p}") from None
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise CalibrationError(f"{p}: invalid YAML: {exc}") from None
    try:
        return rig_from_dict(data, source=str(p))
    except CalibrationError as exc:
        msg = str(exc)
        raise CalibrationError(msg if msg.startswith(str(p)) else f"{p}: {msg}") from None


def save_rig_yaml(rig: Rig, path: str | Path, comment: str | None = None) -> None:
    import yaml

    text = yaml.safe_dump(rig_to_dict(rig), sort_keys=False, default_flow_style=None)
    header = "".join(f"# {line}\n" for line in (comment or "").splitlines())
    write_text_atomic(path, header + text)




def load_kitti_calib(path: str | Path, image_size: tuple[int, int]) -> Rig:
    """KITTI odometry ``calib.txt``: ``P0``, ``P1`` (rectified, so R = I, T = [-B, 0, 0])."""
    p = Path(path)
    try:
        lines = p.read_text().splitlines()
    except FileNotFoundError:
        raise CalibrationError(f"KITTI calibration not found: {p}") from None
    mats: dict[str, np.ndarray] = {}
    for i, line in enumerate(lines, 1):
        if not line.strip():
            continue
        key, _, rest = line.partition(":")
        try:
            vals = np.array([float(v) for v in rest.split()])
        except ValueError:
            raise CalibrationError(f"{p}:{i}: {key.strip()}: non-numeric value") from None
        mats[key.strip()] = vals
    for key in ("P0", "P1"):
        if key not in mats:
            raise CalibrationError(f"{p}: missing {key}")
        if mats[key].size != 12:
            raise CalibrationError(f"{p}: {key} must have 12 values, got {mats[key].size}")
    P0 = mats["P0"].reshape(3, 4)
    P1 = mats["P1"].reshape(3, 4)
    if P1[0, 0] <= 0:
        raise CalibrationError(f"{p}: P1: focal length must be positive")
    baseline = -P1[0, 3] / P1[0, 0]
    cam0 = make_camera("cam0", P0[:, :3], np.zeros(5), image_size)
    cam1 = make_camera("cam1", P1[:, :3], np.zeros(5), image_size)
    return make_rig(cam0, cam1, np.eye(3), [-baseline, 0.0, 0.0], name="kitti")


def _euroc_sensor(path: Path) -> dict[str, Any]:
    import yaml

    try:
        text = path.read_text()
    except FileNotFoundError:
        raise CalibrationError(f"EuRoC sensor file not found: {path}") from None
    text = re.sub(r"^%YAML.*$", "", text, count=1, flags=re.MULTILINE)  # OpenCV-style header
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise CalibrationError(f"{path}: invalid YAML: {exc}") from None
    if not isinstance(data, dict):
        raise CalibrationError(f"{path}: expected a mapping")
    return data


def _euroc_camera(name: str, path: Path) -> tuple[CameraModel, np.ndarray]:
    d = _euroc_sensor(path)
    for key in ("T_BS", "intrinsics", "resolution", "distortion_coefficients"):
        if key not in d:
            raise CalibrationError(f"{path}: missing {key}")
    model = d.get("distortion_model", "radial-tangential")
    if model not in ("radial-tangential", "radtan"):
        raise CalibrationError(f"{path}: distortion_model {model!r} is not supported (radial-tangential only)")
    tbs = d["T_BS"]
    data = tbs.get("data") if isinstance(tbs, dict) else tbs
    T_BS = checked_array(f"{name}.T_BS", data, (4, 4))
    intr = d["intrinsics"]
    if not isinstance(intr, list) or len(intr) != 4:
        raise CalibrationError(f"{path}: intrinsics must be [fu, fv, cu, cv]")
    fu, fv, cu, cv = (float(v) for v in intr)
    K = np.array([[fu, 0, cu], [0, fv, cv], [0, 0, 1.0]])
    cam = make_camera(name, K, d["distortion_coefficients"], d["resolution"])
    return cam, T_BS


def load_euroc_rig(mav0: str | Path) -> Rig:
    """EuRoC/ASL rig from ``mav0/cam0/sensor.yaml`` and ``mav0/cam1/sensor.yaml``."""
    m = Path(mav0)
    cam0, T_B_C0 = _euroc_camera("cam0", m / "cam0" / "sensor.yaml")
    cam1, T_B_C1 = _euroc_camera("cam1", m / "cam1" / "sensor.yaml")
    T_C1_C0 = invert_pose(T_B_C1) @ T_B_C0
    return make_rig(cam0, cam1, T_C1_C0[:3, :3], T_C1_C0[:3, 3], name="euroc", T_body_cam0=T_B_C0)


# ---------------------------------------------------------------------------------------------
# EuRoC sensor.yaml writers (the recorder's session layout)

# MPU-6050 nominal noise (datasheet densities; random walks are typical values) for imu0/sensor.yaml
MPU6050_NOISE = {
    "gyroscope_noise_density": 8.7266e-05,  # rad/s/sqrt(Hz)   (0.005 deg/s/sqrt(Hz))
    "gyroscope_random_walk": 2.0e-05,  # rad/s^2/sqrt(Hz)
    "accelerometer_noise_density": 3.9227e-03,  # m/s^2/sqrt(Hz)  (400 ug/sqrt(Hz))
    "accelerometer_random_walk": 3.0e-04,  # m/s^3/sqrt(Hz)
}


IMU_NOISE_KEYS = ("gyroscope_noise_density", "gyroscope_random_walk", "accelerometer_noise_density",
                  "accelerometer_random_walk", "gravity_m_s2")


def load_imu_noise(path: str | Path) -> dict[str, float]:
    """The positive noise entries (and ``gravity_m_s2``) of an EuRoC/ASL ``imu0/sensor.yaml``.

    A missing file is ``{}``; a file that does not parse raises :class:`CalibrationError`; an entry
    that is not a positive number is named in a warning and left out."""
    p = Path(path)
    if not p.is_file():
        return {}
    data = _euroc_sensor(p)
    out: dict[str, float] = {}
    for k in IMU_NOISE_KEYS:
        v = data.get(k)
        if isinstance(v, (int, float)) and not isinstance(v, bool) and v > 0:
            out[k] = float(v)
        elif v is not None:
            log.warning("%s: %s = %r is not a positive number: ignored", p, k, v)
    return out


def _yaml_list(values: Any) -> str:
    return "[" + ", ".join(repr(float(v)) for v in values) + "]"


def _t_bs_block(T: np.ndarray) -> str:
    rows = [", ".join(repr(float(v)) for v in row) for row in np.asarray(T, dtype=float)]
    data = ",\n         ".join(rows)
    return f"T_BS:\n  cols: 4\n  rows: 4\n  data: [{data}]\n"


def camera_sensor_yaml(cam: Any, name: str, T_body_cam: np.ndarray, rate_hz: float) -> str:
    """EuRoC ``camN/sensor.yaml`` text (pinhole, radial-tangential k1 k2 p1 p2)."""
    dist = np.asarray(cam.dist, dtype=float).reshape(-1)
    if dist.size > 4 and np.any(dist[4:] != 0):
        log.warning("%s: sensor.yaml keeps only k1 k2 p1 p2 (EuRoC radial-tangential); the further "
                    "coefficients %s are only in rig.yaml", name, dist[4:].tolist())
    d4 = np.zeros(4)
    d4[: min(4, dist.size)] = dist[:4]
    return (
        "%YAML:1.0\n"
        "# General sensor definitions.\n"
        "sensor_type: camera\n"
        f"comment: stereopath {name}\n\n"
        "# Sensor extrinsics wrt. the body-frame (the IMU frame).\n"
        + _t_bs_block(T_body_cam)
        + "\n# Camera specific definitions.\n"
        f"rate_hz: {float(rate_hz)!r}\n"
        f"resolution: [{int(cam.size[0])}, {int(cam.size[1])}]\n"
        "camera_model: pinhole\n"
        f"intrinsics: {_yaml_list([cam.fx, cam.fy, cam.cx, cam.cy])} #fu, fv, cu, cv\n"
        "distortion_model: radial-tangential\n"
        f"distortion_coefficients: {_yaml_list(d4)}\n"
    )


def imu_sensor_yaml(rate_hz: float, noise: dict[str, float]) -> str:
    """EuRoC ``imu0/sensor.yaml`` text (the body frame is the IMU frame)."""
    lines = "".join(f"{k}: {float(v)!r}\n" for k, v in noise.items())
    return (
        "%YAML:1.0\n"
        "sensor_type: imu\n"
        "comment: stereopath IMU (MPU-6050 class)\n\n"
        + _t_bs_block(np.eye(4))
        + f"rate_hz: {float(rate_hz)!r}\n\n"
        "# inertial sensor noise model parameters (static)\n"
        + lines
    )
