"""Fisheye (equidistant) cameras read through pinhole views (pure: arrays in, arrays out).

Wide-angle stereo-inertial rigs (the TUM VI benchmark's, most Kalibr calibrations of fisheye
modules) use the Kannala-Brandt model that Kalibr calls ``equidistant`` and OpenCV implements in
``cv2.fisheye``: a ray at angle ``theta`` from the optical axis lands at radius
``f * theta_d`` with ``theta_d = theta (1 + k1 theta^2 + k2 theta^4 + k3 theta^6 + k4 theta^8)``.
Everything downstream of the readers (tracking, stereo, rectification, bundle adjustment) works
on pinhole cameras with OpenCV's radial-tangential distortion, so a fisheye camera is read
through a :class:`PinholeView`: the same ``K`` with no distortion, each image resampled once
(bilinear) with ``cv2.fisheye.initUndistortRectifyMap``.  The view keeps the centre's
resolution and the camera's own frame (no rotation), so extrinsics, IMU and ground truth stay
as calibrated; it gives up the periphery beyond the pinhole image's edge (a fisheye of 190 px
focal length at 512 x 512 keeps +-53 deg across, of its +-77 deg).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from stereopath.device.core.rig import DISTORTION_MAX, CameraModel, check_plausible_camera, checked_array, checked_intrinsics, \
    checked_size, make_camera
from stereopath.device.errors import CalibrationError

# A view whose pixels fall outside the fisheye image more than this is refused; below it the few
# outside pixels repeat the image's edge (no black border to make false corners).
MAX_OUTSIDE = 0.02


@dataclass(frozen=True, eq=False)
class FisheyeCamera:
    """A Kannala-Brandt (``equidistant``) camera: 3x3 ``K``, ``dist`` = (k1, k2, k3, k4), ``(width, height)``."""

    K: np.ndarray
    dist: np.ndarray
    size: tuple[int, int]


def make_fisheye_camera(name: str, K: object, dist: object, size: object) -> FisheyeCamera:
    """Validated :class:`FisheyeCamera`; errors name the field (e.g. ``cam0.distortion``)."""
    if dist is None:
        raise CalibrationError(f"{name}.distortion: missing (an equidistant camera has k1, k2, k3, k4)")
    d = checked_array(f"{name}.distortion", dist, (4,))
    if np.any(np.abs(d) > DISTORTION_MAX):
        raise CalibrationError(f"{name}.distortion: a coefficient beyond +-{DISTORTION_MAX:g}: {d.tolist()}")
    K, wh = checked_intrinsics(name, K), checked_size(name, size)
    check_plausible_camera(name, K, wh)
    return FisheyeCamera(K=K, dist=d, size=wh)


@dataclass(frozen=True, eq=False)
class PinholeView:
    """A fisheye camera seen as ``camera`` (pinhole, same ``K``, no distortion): ``apply`` resamples an image."""

    source: FisheyeCamera
    camera: CameraModel
    map_x: np.ndarray
    map_y: np.ndarray
    half_fov_deg: tuple[float, float]

    def apply(self, image: np.ndarray) -> np.ndarray:
        import cv2

        return cv2.remap(image, self.map_x, self.map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)


def pinhole_view(cam: FisheyeCamera, name: str) -> PinholeView:
    """The pinhole view of ``cam`` (see the module doc); refuses a calibration under which the view
    would look outside the fisheye image (coefficients that fold the lens model back)."""
    import cv2

    w, h = cam.size
    K = cam.K.copy()
    K[0, 1] = 0.0  # the pinhole model downstream has no skew
    pinhole = make_camera(name, K, np.zeros(5), cam.size)
    try:
        map_x, map_y = cv2.fisheye.initUndistortRectifyMap(cam.K, cam.dist, np.eye(3), K, (w, h), cv2.CV_32FC1)
    except cv2.error as exc:
        raise CalibrationError(f"{name}: OpenCV cannot build the pinhole view of this {w}x{h} camera: "
                               f"{str(exc).strip().splitlines()[-1]}") from None
    ok = np.isfinite(map_x) & np.isfinite(map_y)
    inside = ok & (map_x >= -0.5) & (map_x <= w - 0.5) & (map_y >= -0.5) & (map_y <= h - 0.5)
    outside = 1.0 - float(inside.mean())
    if outside > MAX_OUTSIDE:
        raise CalibrationError(f"{name}: the equidistant calibration maps {100 * outside:.1f} % of the pinhole view "
                               f"outside the {w}x{h} image (distortion {cam.dist.tolist()}): not a usable fisheye model")
    map_x = np.where(ok, map_x, 0.0).astype(np.float32)
    map_y = np.where(ok, map_y, 0.0).astype(np.float32)
    fov = (float(np.degrees(np.arctan(max(K[0, 2], w - 1 - K[0, 2]) / K[0, 0]))),
           float(np.degrees(np.arctan(max(K[1, 2], h - 1 - K[1, 2]) / K[1, 1]))))
    return PinholeView(source=cam, camera=pinhole, map_x=map_x, map_y=map_y, half_fov_deg=fov)
