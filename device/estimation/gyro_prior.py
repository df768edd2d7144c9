"""The gyro's rotation as a prior of each frame's pose solve (pure compute).

The camera's orientation at a frame is predicted from the last keyframe's pose and the gyro integrated
since, with the bias in use (:class:`GyroSinceKeyframe`).  The anchor is the keyframe because the
tracked map was measured from it: the prediction then agrees with the map's own frame, error and all.
Anchored at the previous frame instead, the prior would carry that frame's error against the map on,
and the translation would absorb it.  The integrated rotation is a measurement with a known error:

* the gyro's white noise over the interval, ``n * sqrt(dt)`` (``n``: its noise density);
* the bias's uncertainty carried over the interval, ``sigma_b * dt``;
* a relative error of the rotation itself, ``k * |theta|``: the gyro's scale factor and the
  body-to-camera rotation's calibration, which grow with the rotation measured.

Those add in quadrature into one isotropic ``sigma`` (radians).  The pose refinement minimises the
sum of squared reprojection errors (pixels); a pixel error of standard deviation ``sigma_px`` makes
the prior's residual ``log(R R_gyro^T) * sigma_px / sigma`` the same kind of term (both whitened, then
scaled by ``sigma_px``).  ``sigma_px`` is measured on the frame itself: the RMS of the PnP consensus's
inlier errors (:func:`pixel_sigma`).  The images say how well they measure, the gyro's model how
well it does, and the solve weighs them so: the visual constraint's information grows with its
points, so a frame with few inliers or blurred, spread residuals leans on the gyro, and a sharp,
well-textured frame on its points.  Without a gyro or before the bias is known (its uncertainty is
then a MEMS gyro's whole bias range) the prior weighs little or nothing.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from stereopath.device.core.geometry import make_pose, so3_log
from stereopath.device.core.stereo import RotationPrior
from stereopath.device.core.stereo_config import GyroBiasConfig
from stereopath.device.errors import ConfigError
from stereopath.device.estimation.inertial import VisionGyroBias

MIN_PIXEL_SIGMA_PX = 0.05  # the pixel noise at least (a near-perfect fit on few points says little)


@dataclass(frozen=True)
class GyroRotationModel:
    """The error model of a gyro-integrated rotation (see the module doc)."""

    noise_rad_s_rthz: float  # the gyro's white noise density
    relative: float  # relative error of a measured rotation (scale factor and body-to-camera alignment)

    @classmethod
    def of(cls, cfg: GyroBiasConfig) -> GyroRotationModel | None:
        """The model of a ``[estimator.stereo.gyro]`` section (None: the prior is off)."""
        return cls(cfg.noise_rad_s_rthz, cfg.relative_error) if cfg.rotation_prior else None

    def __post_init__(self) -> None:
        if not (self.noise_rad_s_rthz >= 0.0 and self.relative >= 0.0):
            raise ConfigError(f"gyro rotation model: noise {self.noise_rad_s_rthz!r} and relative error "
                              f"{self.relative!r} must be >= 0")

    def sigma_rad(self, R_step: np.ndarray, dt_s: float, bias_sigma_rad_s: float) -> float:
        """The standard deviation (radians) of rotation ``R_step`` integrated over ``dt_s`` seconds with a
        bias known to ``bias_sigma_rad_s``."""
        dt = max(float(dt_s), 0.0)
        angle = float(np.linalg.norm(so3_log(np.asarray(R_step, float))))
        var = self.noise_rad_s_rthz**2 * dt + (bias_sigma_rad_s * dt) ** 2 + (self.relative * angle) ** 2
        return float(np.sqrt(var))


@dataclass(frozen=True, eq=False)
class GyroRotation:
    """The frame's camera orientation predicted by the gyro (``R_cam_world``: the last keyframe's pose times
    the gyro's rotation since) and its standard deviation (radians)."""

    R_cam_world: np.ndarray
    sigma_rad: float

    def prior(self, pixel_sigma_px: float) -> RotationPrior:
        """The refinement's prior when its pixels are measured to ``pixel_sigma_px``."""
        return RotationPrior(self.R_cam_world, float(pixel_sigma_px) / max(self.sigma_rad, 1e-9))


def camera_step(step_body: tuple[np.ndarray, float] | None,
                R_body_cam: np.ndarray | None) -> tuple[np.ndarray, float] | None:
    """A gyro step (body rotation, seconds) as the camera's rotation (None without either)."""
    if step_body is None or R_body_cam is None:
        return None
    return R_body_cam.T @ step_body[0] @ R_body_cam, step_body[1]


class GyroSinceKeyframe:
    """The gyro's camera rotation since the last keyframe: the prior's anchor is the keyframe's pose, from
    which the tracked map's newest points were measured, not the previous frame's (whose error against
    the map a frame-to-frame prior would carry on, and the translation would then absorb)."""

    def __init__(self) -> None:
        self.R_cam = np.eye(3)
        self.dt_s = 0.0
        self.unbroken = False  # until a keyframe anchors it

    def restart(self) -> None:
        """A new keyframe: the anchor."""
        self.R_cam, self.dt_s, self.unbroken = np.eye(3), 0.0, True

    def add(self, step: tuple[np.ndarray, float] | None) -> None:
        """One frame's camera rotation and its length (None: no gyro over it, the chain breaks until the next
        keyframe)."""
        if step is None:
            self.unbroken = False
        elif self.unbroken:
            self.R_cam, self.dt_s = self.R_cam @ step[0], self.dt_s + float(step[1])

    def frame(self, step: tuple[np.ndarray, float] | None, T_world_kf: np.ndarray | None, bias_sigma_rad_s: float,
              model: GyroRotationModel | None) -> GyroRotation | None:
        """:meth:`add` this frame's step; the prior of its pose solve from the keyframe's pose ``T_world_kf``
        (None: no prior, when the model is off, the chain broken or no keyframe)."""
        self.add(step)
        if model is None or not self.unbroken or T_world_kf is None:
            return None
        return gyro_rotation(T_world_kf @ make_pose(self.R_cam, np.zeros(3)), self.R_cam, self.dt_s, bias_sigma_rad_s,
                             model)


class GyroPrior:
    """The pose solve's prior frame by frame: the model of ``[estimator.stereo.gyro]`` (None: off), the
    rotation since the last keyframe (restarted when the keyframe count moves) and the bias's uncertainty
    (``unknown_bias_sigma_rad_s`` while the bias is not refined on line)."""

    def __init__(self, cfg: GyroBiasConfig, R_body_cam: np.ndarray | None, unknown_bias_sigma_rad_s: float) -> None:
        self.model = GyroRotationModel.of(cfg)
        self.R_body_cam = R_body_cam
        self.unknown_bias_sigma_rad_s = float(unknown_bias_sigma_rad_s)
        self.since = GyroSinceKeyframe()
        self._keyframes = -1

    def frame(self, step_body: tuple[np.ndarray, float] | None, T_world_kf: np.ndarray | None, keyframes: int,
              bias: VisionGyroBias | None) -> GyroRotation | None:
        """This frame's prior from the gyro's body step over it, the last keyframe's pose and the number of
        keyframes so far (a new one restarts the chain), or None."""
        if keyframes != self._keyframes:
            self.since.restart()
            self._keyframes = keyframes
        sigma_b = self.unknown_bias_sigma_rad_s if bias is None else bias.sigma_rad_s
        return self.since.frame(camera_step(step_body, self.R_body_cam), T_world_kf, sigma_b, self.model)


def gyro_rotation(T_world_pred: np.ndarray, R_step_cam: np.ndarray, dt_s: float, bias_sigma_rad_s: float,
                  model: GyroRotationModel) -> GyroRotation:
    """The gyro's prediction of the frame's orientation: ``T_world_pred`` (whose rotation is the anchor's,
    the last keyframe's, times ``R_step_cam``, the gyro's camera rotation over the ``dt_s`` seconds since)
    and its error."""
    return GyroRotation(np.asarray(T_world_pred, float)[:3, :3].T.copy(),
                        model.sigma_rad(R_step_cam, dt_s, bias_sigma_rad_s))


def pixel_sigma(errors_px: np.ndarray, threshold_px: float, ceiling_px: float, n_params: int = 6) -> float:
    """The pixel noise of a pose fit: the RMS of its errors under ``threshold_px`` (the inliers), corrected
    for the ``n_params`` the fit took from them (two residuals per point), within
    [:data:`MIN_PIXEL_SIGMA_PX`, ``ceiling_px``] (beyond the robust loss's width errors are not Gaussian).
    Few inliers say little: the ceiling then."""
    e = np.asarray(errors_px, float)
    e = e[np.isfinite(e) & (e < threshold_px)]
    dof = 2 * len(e) - n_params
    if dof <= 0:
        return float(ceiling_px)
    rms = float(np.sqrt(np.sum(e**2) / dof))
    return float(np.clip(rms, MIN_PIXEL_SIGMA_PX, ceiling_px))
