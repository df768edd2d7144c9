"""The stereo rig model: two pinhole cameras with distortion and their relative pose.

Extrinsics follow OpenCV's ``stereoCalibrate``: ``R``, ``T`` map a point from
camera 1 (left, ``cam0``) coordinates into camera 2 (right, ``cam1``)
coordinates, ``x_cam1 = R @ x_cam0 + T``, i.e. they form ``T_cam1_cam0``.  A
right camera to the right of the left one therefore has ``T[0] < 0`` (the
reference paper's Table 1: T = [-47.917, -0.142, -13.373] mm).

Pure: no files.  :func:`rig_from_dict`/:func:`rig_to_dict` are the schema of our rig YAML;
the files themselves (our YAML, KITTI ``calib.txt``, EuRoC ``sensor.yaml``) are read and
written by :mod:`stereopath.device.formats.rig_files`.
"""

from __future__ import annotations

import dataclasses
import logging
import operator
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from stereopath.device.errors import CalibrationError
from stereopath.device.core.geometry import invert_pose, make_pose, project_to_so3

if TYPE_CHECKING:
    from numpy.typing import ArrayLike

log = logging.getLogger(__name__)

ORTHO_TOL = 1e-2  # |R^T R - I| (max element) above this is not a rotation
ORTHO_SILENT = 1e-9  # below this R is taken as it is
ORTHO_ROUNDED = 1e-3  # up to this R is a rotation written with rounded elements (projected, logged as info)

# Physical plausibility of a calibration.  A focal length f (pixels) across w pixels sees a field of view of
# 2 atan(w / 2f): below half a degree no hand-held scan holds a target in view (a 2,000 mm lens on a
# full-frame sensor still sees 1 deg), above 170 deg a pinhole image cannot hold it (the image plane runs to
# infinity at 180 deg; a fisheye camera is read through a pinhole view of at most that).  The principal
# point is where the optical axis meets the image: inside it.  A stereo baseline under 1 mm gives no depth
# at any range, over 10 m no two cameras on one rig overlap at scanning distance.
FOV_MIN_DEG = 0.5
FOV_MAX_DEG = 170.0
BASELINE_MIN_M = 1e-3
BASELINE_MAX_M = 10.0
MAX_IMAGE_SIDE = 65536  # px: past any camera sensor (the largest are ~20,000 px across)
DISTORTION_MAX = 1e4  # |coefficient|: OpenCV's rational and thin-prism terms stay in the tens


def focal_range_px(pixels: int) -> tuple[float, float]:
    """The focal lengths (pixels) that see between :data:`FOV_MAX_DEG` and :data:`FOV_MIN_DEG` across ``pixels``."""
    lo = pixels / (2.0 * np.tan(np.radians(FOV_MAX_DEG) / 2.0))
    hi = pixels / (2.0 * np.tan(np.radians(FOV_MIN_DEG) / 2.0))
    return float(lo), float(hi)


def check_plausible_camera(name: str, K: np.ndarray, size: tuple[int, int]) -> None:
    """Refuse focal lengths whose field of view is outside [FOV_MIN_DEG, FOV_MAX_DEG] and a principal point
    outside the image; the message names the field, the value and the range."""
    w, h = size
    for label, f, pixels, axis in (("fx", K[0, 0], w, "width"), ("fy", K[1, 1], h, "height")):
        lo, hi = focal_range_px(pixels)
        if not lo <= f <= hi:
            raise CalibrationError(
                f"{name}.K: {label} = {f:.6g} px is implausible for an image {pixels} px in {axis}: a field of "
                f"view between {FOV_MIN_DEG:g} and {FOV_MAX_DEG:g} deg needs {lo:.4g} to {hi:.4g} px")
    for label, c, pixels in (("cx", K[0, 2], w), ("cy", K[1, 2], h)):
        if not 0.0 <= c <= pixels:
            raise CalibrationError(f"{name}.K: principal point {label} = {c:.6g} px lies outside the image "
                                   f"(0 to {pixels} px)")


def check_plausible_baseline(T: np.ndarray) -> None:
    big = float(np.max(np.abs(T)))
    b = big * float(np.linalg.norm(T / big)) if big > 0 else 0.0  # scaled: 1e308 squared overflows
    if not BASELINE_MIN_M <= b <= BASELINE_MAX_M:
        raise CalibrationError(f"T: baseline {b:.6g} m is implausible (a stereo rig's is between "
                               f"{BASELINE_MIN_M * 1000:g} mm and {BASELINE_MAX_M:g} m; T is in metres)")


@dataclass(frozen=True, eq=False)
class CameraModel:
    """One pinhole camera: 3x3 ``K`` (pixels), OpenCV distortion ``dist`` and ``(width, height)``."""

    K: np.ndarray
    dist: np.ndarray
    size: tuple[int, int]

    @property
    def fx(self) -> float:
        return float(self.K[0, 0])

    @property
    def fy(self) -> float:
        return float(self.K[1, 1])

    @property
    def cx(self) -> float:
        return float(self.K[0, 2])

    @property
    def cy(self) -> float:
        return float(self.K[1, 2])


@dataclass(frozen=True)
class Rectification:
    """Result of ``cv2.stereoRectify`` plus the undistort-rectify maps for both cameras."""

    R0: np.ndarray  # rectifying rotation of cam0 (rectified <- original)
    R1: np.ndarray
    P0: np.ndarray  # 3x4 projection of the rectified cam0
    P1: np.ndarray
    Q: np.ndarray
    maps0: tuple[np.ndarray, np.ndarray]
    maps1: tuple[np.ndarray, np.ndarray]
    size: tuple[int, int]

    @property
    def f(self) -> float:
        return float(self.P0[0, 0])

    @property
    def cx(self) -> float:
        return float(self.P0[0, 2])

    @property
    def cy(self) -> float:
        return float(self.P0[1, 2])

    @property
    def baseline_m(self) -> float:
        return float(-self.P1[0, 3] / self.P1[0, 0])

    @property
    def K(self) -> np.ndarray:
        return self.P0[:, :3].copy()

    def rectify(self, left: np.ndarray, right: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Undistort and rectify a left/right image pair (bilinear)."""
        import cv2

        l = cv2.remap(left, self.maps0[0], self.maps0[1], cv2.INTER_LINEAR)
        r = cv2.remap(right, self.maps1[0], self.maps1[1], cv2.INTER_LINEAR)
        return l, r


@dataclass(frozen=True, eq=False)
class Rig:
    """A calibrated stereo pair.  ``R``, ``T`` form ``T_cam1_cam0`` (see module doc)."""

    cam0: CameraModel
    cam1: CameraModel
    R: np.ndarray
    T: np.ndarray
    name: str = "rig"
    T_body_cam0: np.ndarray | None = None  # IMU/body frame <- cam0, when known
    # the fisheye calibration these pinhole cameras are views of ("" = the lenses themselves are pinhole):
    # images of such a rig were resampled (stereopath.device.core.fisheye), its K are the views'
    views_of: str = ""
    _cache: dict[str, Any] = field(default_factory=dict, repr=False, compare=False)

    @property
    def baseline_m(self) -> float:
        return float(np.linalg.norm(self.T))

    @property
    def T_cam1_cam0(self) -> np.ndarray:
        return make_pose(self.R, self.T)

    @property
    def T_cam0_cam1(self) -> np.ndarray:
        return invert_pose(self.T_cam1_cam0)

    @property
    def is_rectified(self) -> bool:
        """True when the pair is already row-aligned (KITTI): no rotation, no distortion, x-only baseline.

        The principal points may differ along x (a refined calibration's constant disparity
        offset, see ``host reprocess``'s ``rig_refined.yaml``): rows stay aligned."""
        K0, K1 = self.cam0.K, self.cam1.K
        same = np.array([[1, 1, 0], [1, 1, 1], [1, 1, 1]], bool)  # every entry but cx
        return (
            np.allclose(self.R, np.eye(3), atol=1e-9)
            and abs(self.T[1]) < 1e-9
            and abs(self.T[2]) < 1e-9
            and not np.any(self.cam0.dist)
            and not np.any(self.cam1.dist)
            and np.allclose(K0[same], K1[same])
        )

    def rectification(self, alpha: float = 0.0) -> Rectification:
        """Rectification maps (computed once per rig and alpha, then cached)."""
        key = f"rect:{alpha}"
        if key not in self._cache:
            self._cache[key] = _compute_rectification(self, alpha)
        return self._cache[key]


def _compute_rectification(rig: Rig, alpha: float) -> Rectification:
    import cv2

    size = rig.cam0.size
    R0, R1, P0, P1, Q, _, _ = cv2.stereoRectify(
        rig.cam0.K, rig.cam0.dist, rig.cam1.K, rig.cam1.dist, size, rig.R, rig.T.reshape(3, 1),
        flags=cv2.CALIB_ZERO_DISPARITY, alpha=alpha,
    )
    m0 = cv2.initUndistortRectifyMap(rig.cam0.K, rig.cam0.dist, R0, P0, size, cv2.CV_32FC1)
    m1 = cv2.initUndistortRectifyMap(rig.cam1.K, rig.cam1.dist, R1, P1, size, cv2.CV_32FC1)
    return Rectification(R0, R1, P0, P1, Q, m0, m1, size)


# ---------------------------------------------------------------------------------------------
# construction and validation


def checked_array(name: str, value: object, shape: tuple[int, ...]) -> np.ndarray:
    try:
        a = np.asarray(value, dtype=float)
    except (TypeError, ValueError, OverflowError):  # OverflowError: an integer beyond any float
        raise CalibrationError(f"{name}: not numeric: {value!r}") from None
    if a.size == int(np.prod(shape)) and a.shape != shape:
        a = a.reshape(shape)
    if a.shape != shape:
        raise CalibrationError(f"{name}: expected shape {shape}, got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise CalibrationError(f"{name}: contains non-finite values")
    return a


def checked_intrinsics(name: str, K: object) -> np.ndarray:
    """A validated 3x3 intrinsic matrix (positive focal lengths, upper triangular, ``K[2,2] = 1``)."""
    K = checked_array(f"{name}.K", K, (3, 3))
    if K[0, 0] <= 0 or K[1, 1] <= 0:
        raise CalibrationError(f"{name}.K: focal length must be positive, got fx={K[0, 0]}, fy={K[1, 1]}")
    if abs(K[2, 2] - 1.0) > 1e-9 or abs(K[1, 0]) > 1e-9 or abs(K[2, 0]) > 1e-9 or abs(K[2, 1]) > 1e-9:
        raise CalibrationError(f"{name}.K: not an upper-triangular intrinsic matrix with K[2,2] = 1")
    return K


def intrinsic_matrix(where: str, intr: object) -> np.ndarray:
    """``[fx, fy, cx, cy]`` (our YAML, EuRoC ``intrinsics``, Kalibr) -> K; errors name ``where``."""
    if not isinstance(intr, (list, tuple)) or len(intr) != 4:
        raise CalibrationError(f"{where}.intrinsics must be [fx, fy, cx, cy], got {intr!r}")
    try:
        fx, fy, cx, cy = (float(v) for v in intr)
    except (TypeError, ValueError, OverflowError):
        raise CalibrationError(f"{where}.intrinsics must be numbers, got {intr!r}") from None
    return np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])


def _whole_number(v: object) -> int:
    """``v`` as an int if it is a whole number (``640``, ``640.0``, ``"640"``); else ValueError/TypeError."""
    if isinstance(v, (bool, np.bool_)):
        raise TypeError("a boolean is not a size")
    try:
        return operator.index(v)  # int, numpy integer
    except TypeError:
        pass
    if isinstance(v, str):
        return int(v)
    f = float(v)
    if not f.is_integer():  # also rejects inf and nan
        raise ValueError(f"{v!r} is not a whole number")
    return int(f)


def checked_size(name: str, size: object) -> tuple[int, int]:
    try:
        w, h = (_whole_number(v) for v in size)
    except (TypeError, ValueError, OverflowError):
        raise CalibrationError(f"{name}.image_size: expected [width, height] in whole pixels, got {size!r}") from None
    if w <= 0 or h <= 0:
        raise CalibrationError(f"{name}.image_size: must be positive, got {w}x{h}")
    if w > MAX_IMAGE_SIDE or h > MAX_IMAGE_SIDE:
        raise CalibrationError(f"{name}.image_size: {w}x{h} is implausible (at most {MAX_IMAGE_SIDE} px a side)")
    return w, h


def make_camera(name: str, K: object, dist: object, size: object) -> CameraModel:
    """Validated :class:`CameraModel`; errors name the field (e.g. ``cam0.K``)."""
    K = checked_intrinsics(name, K)
    try:
        d = np.asarray(dist if dist is not None else np.zeros(5), dtype=float).reshape(-1)
    except (TypeError, ValueError, OverflowError):
        raise CalibrationError(f"{name}.distortion: not numeric: {dist!r}") from None
    if d.size not in (4, 5, 8, 12, 14):
        raise CalibrationError(f"{name}.distortion: expected 4, 5, 8, 12 or 14 coefficients, got {d.size}")
    if not np.all(np.isfinite(d)):
        raise CalibrationError(f"{name}.distortion: contains non-finite values")
    if np.any(np.abs(d) > DISTORTION_MAX):
        raise CalibrationError(f"{name}.distortion: a coefficient beyond +-{DISTORTION_MAX:g}: {d.tolist()}")
    wh = checked_size(name, size)
    check_plausible_camera(name, K, wh)
    return CameraModel(K=K, dist=d, size=wh)


def validated_rotation(name: str, R: ArrayLike) -> np.ndarray:
    """Check that ``R`` is (nearly) a rotation; project a nearly orthonormal one onto SO(3)."""
    R = checked_array(name, R, (3, 3))
    if float(np.max(np.abs(R))) > 1.0 + ORTHO_TOL:  # before any product: 1e308 squared overflows
        raise CalibrationError(f"{name}: not a rotation (an element is {float(np.max(np.abs(R))):.3g}, beyond +-1)")
    err = float(np.max(np.abs(R.T @ R - np.eye(3))))
    det = float(np.linalg.det(R))
    if det <= 0:
        raise CalibrationError(f"{name}: not a rotation (det = {det:.4f} <= 0)")
    if err > ORTHO_TOL:
        raise CalibrationError(f"{name}: not a rotation (max |R^T R - I| = {err:.3g} > {ORTHO_TOL})")
    if err > ORTHO_SILENT:
        Rp = project_to_so3(R)
        # a rotation written with 4 decimals is off by up to ~5e-4: projected as a matter of course
        log.log(logging.WARNING if err > ORTHO_ROUNDED else logging.INFO,
                "%s is not exactly orthonormal (max |R^T R - I| = %.2e); projected onto SO(3), "
                "largest element change %.2e", name, err, float(np.max(np.abs(Rp - R))))
        R = Rp
    return R


def check_baseline_sign(R: np.ndarray, T: np.ndarray) -> None:
    """Refuse a rig whose right camera (cam1) sits to the LEFT of cam0.

    The baseline is judged in the rectified frame: the centre of cam1 seen from cam0 is
    ``c1 = -R^T T``; a side-by-side pair has it mostly along +x (cam0 = left).  ``c1`` along -x
    means the cameras are exchanged (or ``R``, ``T`` were given as ``T_cam0_cam1``, or the sign
    of ``T`` is flipped), which would make every disparity negative.
    """
    c1 = -np.asarray(R, float).T @ np.asarray(T, float)
    axis = int(np.argmax(np.abs(c1)))
    if axis == 0 and c1[0] < 0:
        raise CalibrationError(
            f"T: cam1 sits {abs(c1[0]) * 1000:.1f} mm to the LEFT of cam0 (T_cam1_cam0 = "
            f"{np.round(T, 6).tolist()} m has x > 0): the cameras are exchanged, or R/T give T_cam0_cam1 instead "
            f"of T_cam1_cam0 (invert them), or the sign of T is flipped; for a right camera to the right of the "
            f"left one T[0] is negative")
    if axis != 0:
        log.warning("the baseline (cam1 centre %s m from cam0) is mostly along %s, not x: stereopath expects a "
                    "side-by-side pair", np.round(c1, 4).tolist(), "xyz"[axis])


def make_rig(cam0: CameraModel, cam1: CameraModel, R: ArrayLike, T: ArrayLike, name: str = "rig",
             T_body_cam0: ArrayLike | None = None, views_of: str = "") -> Rig:
    """Validated :class:`Rig` from parts (``R``, ``T`` = ``T_cam1_cam0``, metres)."""
    R = validated_rotation(f"rig {name!r}: R", R)
    T = checked_array("T", T, (3,))
    if float(np.max(np.abs(T))) < 1e-6:
        raise CalibrationError("T: zero baseline (the two cameras coincide)")
    check_plausible_baseline(T)
    check_baseline_sign(R, T)
    Tb = None if T_body_cam0 is None else checked_array("T_body_cam0", T_body_cam0, (4, 4))
    if Tb is not None:
        Tb = Tb.copy()
        Tb[:3, :3] = validated_rotation(f"rig {name!r}: T_body_cam0 rotation", Tb[:3, :3])
    return Rig(cam0=cam0, cam1=cam1, R=R, T=T, name=name, T_body_cam0=Tb, views_of=str(views_of))


# ---------------------------------------------------------------------------------------------
# our YAML format


def rig_from_dict(data: object, source: str = "rig") -> Rig:
    """Rig from our YAML schema (see ``firmware_cfg/rig_paper.yaml``)."""
    if not isinstance(data, dict):
        raise CalibrationError(f"{source}: expected a mapping at top level")
    known = {"name", "units", "cam0", "cam1", "R_cam1_cam0", "T_cam1_cam0_m", "T_body_cam0", "comment", "source",
             "pinhole_views_of"}
    unknown = sorted(set(data) - known)
    if unknown:
        raise CalibrationError(f"{source}: unknown key(s) {', '.join(unknown)}")
    for key in ("cam0", "cam1", "R_cam1_cam0", "T_cam1_cam0_m"):
        if key not in data:
            raise CalibrationError(f"{source}: missing key {key}")
    cams = []
    for cname in ("cam0", "cam1"):
        c = data[cname]
        if not isinstance(c, dict):
            raise CalibrationError(f"{source}: {cname} must be a mapping")
        for key in ("intrinsics", "image_size"):
            if key not in c:
                raise CalibrationError(f"{source}: missing key {cname}.{key}")
        K = intrinsic_matrix(f"{source}: {cname}", c["intrinsics"])
        cams.append(make_camera(cname, K, c.get("distortion", [0, 0, 0, 0, 0]), c["image_size"]))
    return make_rig(cams[0], cams[1], data["R_cam1_cam0"], data["T_cam1_cam0_m"],
                    name=str(data.get("name", Path(source).stem)), T_body_cam0=data.get("T_body_cam0"),
                    views_of=str(data.get("pinhole_views_of") or ""))


def rig_to_dict(rig: Rig) -> dict[str, Any]:
    """Inverse of :func:`rig_from_dict` (plain lists, ready for YAML)."""
    def cam(c: CameraModel) -> dict[str, Any]:
        return {
            "image_size": [int(c.size[0]), int(c.size[1])],
            "intrinsics": [c.fx, c.fy, c.cx, c.cy],
            "distortion": [float(v) for v in c.dist],
        }

    out: dict[str, Any] = {
        "name": rig.name,
        "units": "metres",
        "cam0": cam(rig.cam0),
        "cam1": cam(rig.cam1),
        "R_cam1_cam0": [[float(v) for v in row] for row in rig.R],
        "T_cam1_cam0_m": [float(v) for v in rig.T],
    }
    if rig.T_body_cam0 is not None:
        out["T_body_cam0"] = [[float(v) for v in row] for row in rig.T_body_cam0]
    if rig.views_of:
        out["pinhole_views_of"] = rig.views_of
    return out


def with_name(rig: Rig, name: str) -> Rig:
    return dataclasses.replace(rig, name=name, _cache={})


# ---------------------------------------------------------------------------------------------
# the built-in rig (identical to firmware_cfg/rig_paper.yaml; a test keeps them equal)

PAPER_R_CAM1_CAM0 = [[1.0, 0.011, 0.0163], [-0.011, 1.0, 0.008], [-0.0162, -0.008, 1.0]]
PAPER_T_CAM1_CAM0_MM = [-47.917, -0.142, -13.373]
PAPER_IMAGE_SIZE = (640, 480)
PAPER_INTRINSICS = (500.0, 500.0, 319.5, 239.5)  # fx, fy, cx, cy at 640x480 (our choice)


def paper_rig(T_body_cam0: ArrayLike | None = None) -> Rig:
    """The reference paper's rig (Table 1 extrinsics, mm -> m) with our 640x480 intrinsics."""
    fx, fy, cx, cy = PAPER_INTRINSICS
    K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])
    cam = make_camera("cam0", K, np.zeros(5), PAPER_IMAGE_SIZE)
    cam1 = make_camera("cam1", K, np.zeros(5), PAPER_IMAGE_SIZE)
    T = np.array(PAPER_T_CAM1_CAM0_MM) / 1000.0
    return make_rig(cam, cam1, PAPER_R_CAM1_CAM0, T, name="paper", T_body_cam0=T_body_cam0)
