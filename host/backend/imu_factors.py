"""IMU preintegration between keyframes for the GTSAM back end (stereo-inertial bundle adjustment).

The samples between consecutive keyframes are preintegrated (``PreintegratedCombinedMeasurements``)
into one ``CombinedImuFactor`` on the two keyframes' poses, velocities and biases (a bias per keyframe,
a random walk between them); the IMU's pose in the camera (``body_P_sensor``) carries the lever arm.
Noise: what the session records in ``imu0/sensor.yaml``.  Gravity's direction from the still start is
only a starting point (it holds the accelerometer bias too): the held first pose is free to tilt, so
gravity is estimated jointly.  A session with no still start takes its starting values from the path
(:mod:`stereopath.device.estimation.inertial_init`) and is refused (``EstimationError``: the caller
adjusts without the IMU) when the readings do not fit it.  See docs/architecture.md, "Reprocessing".
"""

from __future__ import annotations

import logging
from pathlib import Path
from dataclasses import dataclass
from typing import Any

import numpy as np

from stereopath.device.errors import EstimationError, ImuMismatchError

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ImuNoise:
    gyro_noise_density: float  # rad/s/sqrt(Hz)
    gyro_random_walk: float  # rad/s^2/sqrt(Hz)
    accel_noise_density: float  # m/s^2/sqrt(Hz)
    accel_random_walk: float  # m/s^3/sqrt(Hz)
    gravity_m_s2: float = 9.80665  # what the accelerometer reads at rest (its units' 1 g)
    gyro_bias_prior: float = 0.02  # rad/s: the first keyframe's gyro bias around the still estimate
    accel_bias_prior: float = 0.2  # m/s^2: the first keyframe's accelerometer bias around 0

    @staticmethod
    def of(seq: Any) -> "ImuNoise":
        """The noise recorded with ``seq``: the simulator's ``imu_noise_figures``, else the session's
        ``imu0/sensor.yaml``, else the MPU-6050 figures the recorder writes by default."""
        from stereopath.device.estimation.inertial import GRAVITY_M_S2
        from stereopath.device.formats.rig_files import MPU6050_NOISE

        d = {**MPU6050_NOISE, **(getattr(seq, "imu_noise_figures", None) or _sensor_yaml_noise(seq))}
        return ImuNoise(float(d["gyroscope_noise_density"]), float(d["gyroscope_random_walk"]),
                        float(d["accelerometer_noise_density"]), float(d["accelerometer_random_walk"]),
                        float(d.get("gravity_m_s2", GRAVITY_M_S2)))


def _sensor_yaml_noise(seq: Any) -> dict[str, float]:
    """The noise entries of ``mav0/imu0/sensor.yaml`` of an ASL sequence ({} if there is none)."""
    from stereopath.device.errors import CalibrationError
    from stereopath.device.formats.rig_files import load_imu_noise

    mav0 = getattr(seq, "mav0", None)
    if mav0 is None:
        return {}
    try:
        return load_imu_noise(Path(mav0) / "imu0" / "sensor.yaml")
    except CalibrationError as exc:
        log.warning("%s: the MPU-6050 noise figures are used", exc)
        return {}


@dataclass
class ImuTerms:
    """Everything the graph needs: one preintegration per consecutive keyframe pair."""

    pims: list  # (i, j, PreintegratedCombinedMeasurements)
    velocities: np.ndarray  # (K, 3) initial world velocities of the keyframes (camera origin)
    bias0: Any  # gtsam.imuBias.ConstantBias: the first keyframe's bias prior mean
    noise: ImuNoise
    gravity_world: np.ndarray


def _params(gtsam: Any, noise: ImuNoise, gravity_world: np.ndarray, T_body_cam0: np.ndarray) -> Any:
    p = gtsam.PreintegrationCombinedParams(np.asarray(gravity_world, float))
    p.setGyroscopeCovariance(noise.gyro_noise_density ** 2 * np.eye(3))
    p.setAccelerometerCovariance(noise.accel_noise_density ** 2 * np.eye(3))
    p.setIntegrationCovariance(1e-8 * np.eye(3))
    p.setBiasOmegaCovariance(noise.gyro_random_walk ** 2 * np.eye(3))
    p.setBiasAccCovariance(noise.accel_random_walk ** 2 * np.eye(3))
    T_cam_body = np.linalg.inv(np.asarray(T_body_cam0, float))
    p.setBodyPSensor(gtsam.Pose3(gtsam.Rot3.ClosestTo(T_cam_body[:3, :3]), T_cam_body[:3, 3]))
    return p


def _velocities(t_ns: np.ndarray, T_world_cam: np.ndarray) -> np.ndarray:
    """Central differences of the keyframe positions (initial values only)."""
    p = T_world_cam[:, :3, 3]
    t = np.asarray(t_ns, float) * 1e-9
    if len(t) < 2:
        return np.zeros((len(t), 3))
    return np.gradient(p, t, axis=0)


def imu_terms(seq: Any, t_kf: np.ndarray, T_world_cam: np.ndarray, noise: ImuNoise | None = None,
              gravity_world: np.ndarray | None = None) -> ImuTerms:
    """Preintegrated IMU between consecutive keyframes (times ``t_kf``, poses ``T_world_cam``).

    ``noise``: default :meth:`ImuNoise.of` the sequence; ``gravity_world``: default from the still
    start, or, when the rig does not rest before its first frame, from the path itself
    (:mod:`stereopath.device.estimation.inertial_init`: the gyro bias from the path's rotations,
    gravity and the keyframe velocities from its positions).  EstimationError when the sequence has
    no IMU or no ``T_body_cam0``, or when the path and the IMU disagree."""
    from stereopath.device.estimation.inertial import estimate_still
    from stereopath.host.backend.gtsam_lib import import_gtsam

    g = import_gtsam()
    imu, rig = getattr(seq, "imu", None), seq.rig
    if imu is None or not len(imu) or rig.T_body_cam0 is None:
        raise EstimationError("IMU preintegration needs an IMU stream and the rig's T_body_cam0")
    noise = noise or ImuNoise.of(seq)
    T_world_cam = np.asarray(T_world_cam, float)
    still = estimate_still(imu.between(int(imu.t_ns[0]) - 1, int(seq.t_ns[0])))
    R_cb = np.linalg.inv(np.asarray(rig.T_body_cam0, float))[:3, :3]
    if still is not None:
        gyro_bias = np.asarray(still.gyro_bias_rad_s, float)
    else:
        gyro_bias = _gyro_bias_from_path(imu, t_kf, T_world_cam, R_cb)
    bias0 = g.imuBias.ConstantBias(np.zeros(3), gyro_bias)
    velocities = _velocities(t_kf, T_world_cam)
    if gravity_world is not None:
        gravity = np.asarray(gravity_world, float)
    elif still is not None:
        f_world = T_world_cam[0][:3, :3] @ R_cb @ still.accel_mean_m_s2  # first kf ~ the still pose
        gravity = -f_world / np.linalg.norm(f_world) * noise.gravity_m_s2
    else:
        # the increments do not depend on gravity (the parameters' gravity only enters the factors)
        first = _preintegrate(g, _params(g, noise, np.array([0.0, 0.0, -noise.gravity_m_s2]), rig.T_body_cam0),
                              bias0, imu, t_kf)
        gravity, velocities = _gravity_from_path(t_kf, T_world_cam, first, noise, velocities)
    pims = _preintegrate(g, _params(g, noise, gravity, rig.T_body_cam0), bias0, imu, t_kf)
    return ImuTerms(pims, velocities, bias0, noise, gravity)


# a path whose increments leave more than this (per keyframe interval) does not agree with its IMU
MAX_GRAVITY_FIT_RMS_M_S = 0.5
MAX_GRAVITY_NORM_ERROR = 0.1  # share of the accelerometer's 1 g
# the gyro's rotations against the path's (per keyframe interval; the simulated scan leaves 2e-4 rad, a gyro
# 1.3x too sensitive 4e-2 rad, one read in deg/s far more)
MAX_GYRO_FIT_RMS_RAD = 0.02


def _gyro_bias_from_path(imu: Any, t_kf: np.ndarray, T_world_cam: np.ndarray, R_cb: np.ndarray) -> np.ndarray:
    from stereopath.device.estimation.inertial_init import gyro_bias_from_path

    fit = gyro_bias_from_path(imu, t_kf, T_world_cam[:, :3, :3] @ R_cb)
    if fit is None:
        raise EstimationError("IMU preintegration without a still start needs the IMU over at least two keyframe "
                              "intervals (for the gyro bias)")
    if fit.rms_rad > MAX_GYRO_FIT_RMS_RAD:
        raise ImuMismatchError(
            f"the path and the IMU disagree: the gyro's rotations leave {fit.rms_rad:.3f} rad per keyframe interval "
            "against the path's (check the gyro's units and scale, and T_body_cam0)")
    log.info("no still start: gyro bias %s rad/s from the path's rotations (%d intervals, residual %.2g rad)",
             np.array2string(fit.bias_rad_s, precision=5), fit.intervals, fit.rms_rad)
    return fit.bias_rad_s


def _gravity_from_path(t_kf: np.ndarray, T_world_cam: np.ndarray, pims: list, noise: ImuNoise,
                       velocities: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Gravity (scaled to the accelerometer's 1 g) and the keyframe velocities from the path."""
    from stereopath.device.estimation.inertial_init import gravity_from_path

    fit = gravity_from_path(t_kf, T_world_cam, [(i, j, pim.deltaPij(), pim.deltaVij()) for i, j, pim in pims])
    # three intervals at least: with two, the solve is exactly determined and its residual says nothing
    if fit is None or fit.intervals < 3:
        raise EstimationError("IMU preintegration without a still start needs at least three keyframe intervals "
                              "with IMU samples (for gravity)")
    norm = float(np.linalg.norm(fit.gravity_world))
    if abs(norm - noise.gravity_m_s2) > MAX_GRAVITY_NORM_ERROR * noise.gravity_m_s2 or fit.rms_m_s > MAX_GRAVITY_FIT_RMS_M_S:
        raise ImuMismatchError(
            f"the path and the IMU disagree: gravity from the path is {norm:.2f} m/s^2 (the accelerometer's 1 g is "
            f"{noise.gravity_m_s2:.2f}), velocity residual {fit.rms_m_s:.3f} m/s per keyframe interval (check the "
            "accelerometer's units and scale, and T_body_cam0)")
    log.info("no still start: gravity %s m/s^2 from the path (%d intervals, residual %.3f m/s)",
             np.array2string(fit.gravity_world, precision=3), fit.intervals, fit.rms_m_s)
    v = np.where(np.isfinite(fit.velocities), fit.velocities, velocities)
    return fit.gravity_world / norm * noise.gravity_m_s2, v


def _preintegrate(g: Any, params: Any, bias0: Any, imu: Any, t_kf: np.ndarray) -> list:
    """One preintegration per keyframe interval the IMU covers (an interval it covers only in part is
    left out: holding the first or last sample over the rest would make a wrong factor)."""
    pims = []
    period = float(np.median(np.diff(imu.t_ns))) if len(imu) > 1 else 0.0
    slack = max(5_000_000, 2 * period)  # the samples' own spacing at the interval's ends
    for i in range(len(t_kf) - 1):
        a, b = int(t_kf[i]), int(t_kf[i + 1])
        blk = imu.between(a - 1, b)
        if len(blk) < 2 or blk.t_ns[0] > a + slack or (b - blk.t_ns[-1]) > slack:
            continue
        pim = g.PreintegratedCombinedMeasurements(params, bias0)
        # samples are instantaneous values: integrate each interval with the mean of its two ends
        ts = np.concatenate([[a], blk.t_ns, [b]]).astype(np.int64)
        acc = np.vstack([blk.accel_m_s2[:1], blk.accel_m_s2, blk.accel_m_s2[-1:]])
        gyr = np.vstack([blk.gyro_rad_s[:1], blk.gyro_rad_s, blk.gyro_rad_s[-1:]])
        for k in range(len(ts) - 1):
            dt = (ts[k + 1] - ts[k]) * 1e-9
            if dt > 0:
                pim.integrateMeasurement(0.5 * (acc[k] + acc[k + 1]), 0.5 * (gyr[k] + gyr[k + 1]), dt)
        pims.append((i, i + 1, pim))
    return pims
