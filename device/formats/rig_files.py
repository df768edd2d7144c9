"""Rig calibration files: our rig YAML, KITTI odometry ``calib.txt``, EuRoC/ASL ``sensor.yaml`` (read and
written) and Kalibr camchains (read).

The rig itself (cameras, extrinsics, rectification) is the pure model of
:mod:`stereopath.device.core.rig`; this module only reads and writes it.
"""

from __future__ import annotations

import logging
import math
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterable

import numpy as np

from stereopath.device.core.fisheye import FisheyeCamera, PinholeView, make_fisheye_camera, pinhole_view
from stereopath.device.core.geometry import invert_pose
from stereopath.device.core.rig import CameraModel, Rig, checked_array, intrinsic_matrix, make_camera, make_rig, \
    rig_from_dict, rig_to_dict, validated_rotation
from stereopath.device.errors import CalibrationError
from stereopath.device.formats.fileio import write_text_atomic

log = logging.getLogger(__name__)


def _read_yaml(path: Path, what: str) -> object:
    """A YAML file's content (an OpenCV ``%YAML`` header allowed); a missing, binary or invalid file
    raises :class:`CalibrationError` naming it."""
    import yaml

    try:
        text = path.read_text()
    except FileNotFoundError:
        raise CalibrationError(f"{what} not found: {path}") from None
    except UnicodeDecodeError:
        raise CalibrationError(f"{path}: not a text file") from None
    except OSError as exc:  # a folder, a name too long, a loop of links, no permission
        raise CalibrationError(f"{what} {str(path)[:200]}: cannot be read: {exc.strerror or exc}") from None
    text = re.sub(r"^%YAML.*$", "", text, count=1, flags=re.MULTILINE)  # OpenCV-style header
    try:
        return yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise CalibrationError(f"{path}: invalid YAML: {exc}") from None
    except RecursionError:  # PyYAML composes nested collections recursively
        raise CalibrationError(f"{path}: invalid YAML: collections nested too deeply") from None


def _rig_from_yaml_data(p: Path, data: object) -> Rig:
    try:
        return rig_from_dict(data, source=str(p))
    except CalibrationError as exc:
        msg = str(exc)
        raise CalibrationError(msg if msg.startswith(str(p)) else f"{p}: {msg}") from None


def load_rig_yaml(path: str | Path) -> Rig:
    """Load our rig YAML; any problem raises :class:`CalibrationError` naming the file and field."""
    p = Path(path)
    return _rig_from_yaml_data(p, _read_yaml(p, "calibration file"))


def save_rig_yaml(rig: Rig, path: str | Path, comment: str | None = None) -> None:
    import yaml

    text = yaml.safe_dump(rig_to_dict(rig), sort_keys=False, default_flow_style=None)
    header = "".join(f"# {line}\n" for line in (comment or "").splitlines())
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    write_text_atomic(path, header + text)




def load_kitti_calib(path: str | Path, image_size: tuple[int, int]) -> Rig:
    """KITTI odometry ``calib.txt``: ``P0``, ``P1`` (rectified, so R = I, T = [-B, 0, 0])."""
    p = Path(path)
    try:
        lines = p.read_text().splitlines()
    except FileNotFoundError:
        raise CalibrationError(f"KITTI calibration not found: {p}") from None
    except UnicodeDecodeError:
        raise CalibrationError(f"{p}: not a text file") from None
    except OSError as exc:
        raise CalibrationError(f"KITTI calibration {p}: cannot be read: {exc.strerror or exc}") from None
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
    try:
        baseline = -P1[0, 3] / P1[0, 0]
        cam0 = make_camera("P0", P0[:, :3], np.zeros(5), image_size)
        cam1 = make_camera("P1", P1[:, :3], np.zeros(5), image_size)
        return make_rig(cam0, cam1, np.eye(3), [-baseline, 0.0, 0.0], name="kitti")
    except CalibrationError as exc:
        raise CalibrationError(f"{p}: {exc}") from None


def _euroc_sensor(path: Path, what: str = "EuRoC sensor file") -> dict[str, Any]:
    data = _read_yaml(path, what)
    if not isinstance(data, dict):
        raise CalibrationError(f"{path}: expected a mapping")
    return data


PINHOLE_MODELS = ("radial-tangential", "radtan", "plumb_bob")
FISHEYE_MODELS = ("equidistant", "fisheye", "kannala-brandt", "kannala_brandt", "kb4")


def _camera(name: str, where: str, camera_model: object, model: object, intr: object, dist: object,
            resolution: object) -> CameraModel | FisheyeCamera:
    """A camera from the fields EuRoC's ``sensor.yaml`` and Kalibr's camchain share; errors start
    with ``where`` (the file) and name the field."""
    if str(camera_model or "pinhole").lower() != "pinhole":
        raise CalibrationError(f"{where}: {name}.camera_model {camera_model!r} is not supported (pinhole with "
                               f"radial-tangential or equidistant distortion)")
    model = str(model or "radial-tangential").lower()
    try:
        if dist is None:
            raise CalibrationError(f"{name}.distortion: missing")
        K = intrinsic_matrix(name, intr)
        if model in PINHOLE_MODELS:
            return make_camera(name, K, dist, resolution)
        if model in FISHEYE_MODELS:
            return make_fisheye_camera(name, K, dist, resolution)
    except CalibrationError as exc:
        raise CalibrationError(f"{where}: {exc}") from None
    raise CalibrationError(f"{where}: {name}.distortion_model {model!r} is not supported "
                           f"({', '.join(PINHOLE_MODELS + FISHEYE_MODELS)})")


def _pose(where: str, name: str, value: object) -> np.ndarray:
    """A 4x4 rigid transform from a file: rotation checked, last row [0, 0, 0, 1]."""
    try:
        T = checked_array(name, value, (4, 4))
        if not np.allclose(T[3], [0, 0, 0, 1], atol=1e-9):
            raise CalibrationError(f"{name}: last row must be [0, 0, 0, 1], got {T[3].tolist()}")
        T = T.copy()
        T[:3, :3] = validated_rotation(f"{name} rotation", T[:3, :3])
    except CalibrationError as exc:
        raise CalibrationError(f"{where}: {exc}") from None
    return T


def _euroc_camera(name: str, path: Path, d: dict[str, Any]) -> tuple[CameraModel | FisheyeCamera, np.ndarray]:
    """Camera ``name`` from its parsed ``sensor.yaml`` ``d`` (read from ``path``)."""
    for key in ("T_BS", "intrinsics", "resolution", "distortion_coefficients"):
        if key not in d:
            raise CalibrationError(f"{path}: missing {key}")
    tbs = d["T_BS"]
    data = tbs.get("data") if isinstance(tbs, dict) else tbs
    T_BS = _pose(str(path), f"{name}.T_BS", data)
    cam = _camera(name, str(path), d.get("camera_model"), d.get("distortion_model"), d["intrinsics"],
                  d["distortion_coefficients"], d["resolution"])
    return cam, T_BS


def _kalibr_camchain(path: Path, d: dict[str, Any]) -> tuple[CameraModel | FisheyeCamera, CameraModel | FisheyeCamera,
                                                             np.ndarray, np.ndarray | None]:
    """Kalibr ``camchain(-imucam).yaml`` (parsed ``d``, read from ``path``): the two cameras,
    ``T_cam1_cam0`` and ``T_body_cam0`` (None without ``T_cam_imu``, i.e. a camera-only calibration)."""
    where = str(path)
    cams, T_cam_imu = [], []
    for name in ("cam0", "cam1"):
        c = d.get(name)
        if not isinstance(c, dict):
            raise CalibrationError(f"{where}: missing {name} (or not a mapping)")
        for key in ("intrinsics", "resolution", "distortion_coeffs"):
            if key not in c:
                raise CalibrationError(f"{where}: missing {name}.{key}")
        cams.append(_camera(name, where, c.get("camera_model"), c.get("distortion_model"), c["intrinsics"],
                            c["distortion_coeffs"], c["resolution"]))
        T_cam_imu.append(_pose(where, f"{name}.T_cam_imu", c["T_cam_imu"]) if "T_cam_imu" in c else None)
    if "T_cn_cnm1" in d["cam1"]:
        T_c1_c0 = _pose(where, "cam1.T_cn_cnm1", d["cam1"]["T_cn_cnm1"])
    elif T_cam_imu[0] is not None and T_cam_imu[1] is not None:
        T_c1_c0 = T_cam_imu[1] @ invert_pose(T_cam_imu[0])
    else:
        raise CalibrationError(f"{where}: cam1 has neither T_cn_cnm1 nor (with cam0) T_cam_imu")
    T_b_c0 = None if T_cam_imu[0] is None else invert_pose(T_cam_imu[0])
    return cams[0], cams[1], T_c1_c0, T_b_c0


def kalibr_camchain_path(mav0: Path) -> Path | None:
    """A Kalibr camchain beside the ASL data: ``*camchain*.yaml`` in ``mav0``, its parent or the
    parent's ``dso/`` (the TUM VI layout); an ``imucam`` one (with the IMU) first."""
    found: list[Path] = []
    for folder in (mav0, mav0.parent, mav0.parent / "dso"):
        if folder.is_dir():
            found += sorted(folder.glob("*camchain*.yaml"))
    found.sort(key=lambda p: "imucam" not in p.name)  # stable: folder order kept within each kind
    return found[0] if found else None


@dataclass(frozen=True)
class RigCalibration:
    """A rig as its images are read: ``rig`` is pinhole; ``views`` holds, for each fisheye camera,
    the :class:`~stereopath.device.core.fisheye.PinholeView` its images go through (None: as they are)."""

    rig: Rig
    views: tuple[PinholeView | None, PinholeView | None]
    source: str

    @property
    def has_views(self) -> bool:
        return any(v is not None for v in self.views)


def _as_pinhole(cam: CameraModel | FisheyeCamera, name: str) -> tuple[CameraModel, PinholeView | None]:
    if isinstance(cam, FisheyeCamera):
        view = pinhole_view(cam, name)
        return view.camera, view
    return cam, None


def load_euroc_calibration(mav0: str | Path) -> RigCalibration:
    """The rig of an ASL ``mav0`` folder: ``cam0/sensor.yaml`` and ``cam1/sensor.yaml`` (EuRoC), or when
    they carry no intrinsics (or are missing) a Kalibr camchain beside the data (see
    :func:`kalibr_camchain_path`).  Equidistant cameras come with their pinhole views."""
    m = Path(mav0)
    sensors = [m / "cam0" / "sensor.yaml", m / "cam1" / "sensor.yaml"]
    # each read once; some datasets ship sensor files without a calibration
    docs = [_euroc_sensor(p) if p.is_file() else None for p in sensors]
    if all(d is not None and "intrinsics" in d for d in docs):
        cam0, T_B_C0 = _euroc_camera("cam0", sensors[0], docs[0])
        cam1, T_B_C1 = _euroc_camera("cam1", sensors[1], docs[1])
        T_body: np.ndarray | None = T_B_C0
        T_C1_C0 = invert_pose(T_B_C1) @ T_B_C0
        source = f"{sensors[0]}, {sensors[1]}"
    else:
        chain = kalibr_camchain_path(m)
        if chain is None:
            missing = [str(p) for p, d in zip(sensors, docs) if d is None or "intrinsics" not in d]
            raise CalibrationError(f"no calibration for {m}: {', '.join(missing)} missing or without intrinsics, "
                                   f"and no Kalibr *camchain*.yaml in {m}, {m.parent} or {m.parent / 'dso'}")
        cam0, cam1, T_C1_C0, T_body = _kalibr_camchain(chain, _euroc_sensor(chain, "Kalibr camchain"))
        source = str(chain)
    return _calibration(cam0, cam1, T_C1_C0, T_body, source, name="euroc", where=str(m))


def _calibration(cam0: CameraModel | FisheyeCamera, cam1: CameraModel | FisheyeCamera, T_C1_C0: np.ndarray, T_body: np.ndarray | None, source: str, name: str,
                 where: str) -> RigCalibration:
    """The pinhole rig of two cameras (fisheye ones through their views); errors name ``source``."""
    try:
        pin0, view0 = _as_pinhole(cam0, "cam0")
        pin1, view1 = _as_pinhole(cam1, "cam1")
        views_of = source if (view0 is not None or view1 is not None) else ""
        rig = make_rig(pin0, pin1, T_C1_C0[:3, :3], T_C1_C0[:3, 3], name=name, T_body_cam0=T_body, views_of=views_of)
    except CalibrationError as exc:
        raise CalibrationError(f"{source}: {exc}") from None
    log.info("%s: calibration from %s", where, source)
    for cam, view in (("cam0", view0), ("cam1", view1)):
        if view is not None:
            log.info("%s is an equidistant (fisheye) camera: its images are read through a pinhole view of the "
                     "same K (+-%.0f x +-%.0f deg)", cam, *view.half_fov_deg)
    return RigCalibration(rig=rig, views=(view0, view1), source=source)


def is_kalibr_camchain(data: object) -> bool:
    """True for a parsed Kalibr camchain (``cam0`` a mapping with Kalibr's ``resolution`` and
    ``distortion_coeffs``), not our rig YAML (which has ``R_cam1_cam0`` and ``T_cam1_cam0_m``)."""
    if not isinstance(data, dict) or "R_cam1_cam0" in data or "T_cam1_cam0_m" in data:
        return False
    c = data.get("cam0")
    return isinstance(c, dict) and "resolution" in c and "distortion_coeffs" in c


def load_rig_file(path: str | Path) -> RigCalibration:
    """A rig file as the device's ``source.rig_file`` names it: our rig YAML (pinhole cameras), or a
    Kalibr camchain (radial-tangential or equidistant cameras; a fisheye camera comes with its view)."""
    p = Path(path)
    data = _read_yaml(p, "calibration file")  # read once, then taken as what it is
    if not is_kalibr_camchain(data):
        return RigCalibration(rig=_rig_from_yaml_data(p, data), views=(None, None), source=str(p))
    cam0, cam1, T_C1_C0, T_body = _kalibr_camchain(p, data)
    return _calibration(cam0, cam1, T_C1_C0, T_body, str(p), name=p.stem, where=str(p))


def load_euroc_rig(mav0: str | Path) -> Rig:
    """The rig of an ASL ``mav0`` folder of pinhole cameras.  A fisheye camera's images must go
    through its view, so a fisheye rig is refused here: open the data with
    :func:`stereopath.device.formats.asl.open_asl` (or use :func:`load_euroc_calibration`)."""
    calib = load_euroc_calibration(mav0)
    if calib.has_views:
        raise CalibrationError(f"{calib.source}: fisheye cameras: their images must be read through their pinhole "
                               f"views (open the folder as a sequence, euroc:{mav0})")
    return calib.rig


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
        if isinstance(v, str):  # "2e-05": a number YAML 1.1 reads as text (sessions recorded before 2026-11-27)
            try:
                v = float(v)
            except ValueError:
                pass
        if isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and v > 0:
            out[k] = float(v)
        elif v is not None:
            log.warning("%s: %s = %r is not a positive number: ignored", p, k, v)
    return out


def yaml_float(v: float) -> str:
    """``v`` as YAML reads a float back: Python writes ``2e-05``, which YAML 1.1 (PyYAML, OpenCV's
    ``%YAML:1.0``) reads as a string; ``2.0e-05`` it reads as a number."""
    r = repr(float(v))
    if r in ("inf", "-inf", "nan"):
        return {"inf": ".inf", "-inf": "-.inf", "nan": ".nan"}[r]
    mant, e, exp = r.partition("e")
    return f"{mant}.0e{exp}" if e and "." not in mant else r


def _yaml_list(values: Iterable[float]) -> str:
    return "[" + ", ".join(yaml_float(v) for v in values) + "]"


def _t_bs_block(T: np.ndarray) -> str:
    rows = [", ".join(yaml_float(v) for v in row) for row in np.asarray(T, dtype=float)]
    data = ",\n         ".join(rows)
    return f"T_BS:\n  cols: 4\n  rows: 4\n  data: [{data}]\n"


def camera_sensor_yaml(cam: CameraModel, name: str, T_body_cam: np.ndarray, rate_hz: float) -> str:
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
        f"rate_hz: {yaml_float(rate_hz)}\n"
        f"resolution: [{int(cam.size[0])}, {int(cam.size[1])}]\n"
        "camera_model: pinhole\n"
        f"intrinsics: {_yaml_list([cam.fx, cam.fy, cam.cx, cam.cy])} #fu, fv, cu, cv\n"
        "distortion_model: radial-tangential\n"
        f"distortion_coefficients: {_yaml_list(d4)}\n"
    )


def imu_sensor_yaml(rate_hz: float, noise: dict[str, float]) -> str:
    """EuRoC ``imu0/sensor.yaml`` text (the body frame is the IMU frame)."""
    lines = "".join(f"{k}: {yaml_float(v)}\n" for k, v in noise.items())
    return (
        "%YAML:1.0\n"
        "sensor_type: imu\n"
        "comment: stereopath IMU (MPU-6050 class)\n\n"
        + _t_bs_block(np.eye(4))
        + f"rate_hz: {yaml_float(rate_hz)}\n\n"
        "# inertial sensor noise model parameters (static)\n"
        + lines
    )
