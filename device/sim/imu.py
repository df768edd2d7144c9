"""Simulated MPU-6050: IMU truth from the trajectory's analytic derivatives, then a measurement model.

Body (IMU) frame.  The IMU sits on the rig board between the cameras, 24 mm to the right of cam0,
15 mm below and 10 mm behind its optical centre, with its axes forward-left-up relative to the
camera (body x = camera z, body y = -camera x, body z = -camera y), so a level camera at rest reads
``+9.81`` on body z.  :data:`T_BODY_CAM0` maps cam0 coordinates into body coordinates
(``p_body = T_BODY_CAM0 @ p_cam0``) and goes into the rig as ``paper_rig(T_body_cam0=...)``.

Truth (:func:`imu_truth`): with the camera's world pose ``R_wc, p_wc`` and its exact angular
velocity/acceleration ``w_c, dw_c`` (camera frame) and acceleration ``a_c`` (world),

* gyro ``w_b = R_bc w_c`` (rad/s, body frame);
* the body origin, ``r = -R_bc^T t_bc`` in camera coordinates, accelerates by
  ``a_b = a_c + R_wc (dw_c x r + w_c x (w_c x r))``; the accelerometer measures the specific force
  ``f_b = R_bc R_wc^T (a_b - g)`` with ``g = (0, 0, -9.81)`` (so ``+9.81`` "up" at rest).

Measurement (:func:`measure`, MPU-6050 datasheet figures where it gives them):

* white noise with the datasheet densities, gyro 0.005 deg/s/sqrt(Hz) and accelerometer
  400 ug/sqrt(Hz); per-sample sigma = density * sqrt(rate) (the digital low-pass filter is not
  modelled, i.e. the full noise bandwidth is assumed to reach the samples);
* a constant bias per axis drawn once (residual after a factory offset trim: 0.2 deg/s and
  0.03 m/s^2 standard deviation) plus a random-walk bias (1e-4 rad/s^2/sqrt(Hz) and
  1e-3 m/s^3/sqrt(Hz));
* int16 quantisation at the configured full-scale range (gyro +-250/500/1000/2000 deg/s:
  131/65.5/32.8/16.4 LSB per deg/s; accelerometer +-2/4/8/16 g: 16384/8192/4096/2048 LSB/g, with
  1 g = :data:`G_M_S2`), clipped to [-32768, 32767];
* the temperature register ``raw = (T - 36.53) * 340``.

:class:`RawImu` holds the int16 register values (for the MPU-6050 register emulator);
:func:`counts_to_si` converts them back.  Everything is deterministic for a seed.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from stereopath.device.errors import ConfigError
from stereopath.device.core.frames import ImuSamples
from stereopath.device.sim.scene import GRAVITY_WORLD

G_M_S2 = 9.81  # 1 g: both the simulated gravity and the accelerometer's LSB/g scale
GYRO_LSB_PER_DPS = {250: 131.0, 500: 65.5, 1000: 32.8, 2000: 16.4}
ACCEL_LSB_PER_G = {2: 16384.0, 4: 8192.0, 8: 4096.0, 16: 2048.0}
TEMP_LSB_PER_C = 340.0
TEMP_OFFSET_C = 36.53

# cam0 -> body: body x = cam z, body y = -cam x, body z = -cam y; IMU origin at (24, 15, -10) mm in cam0
_R_BODY_CAM0 = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
IMU_POSITION_CAM0_M = np.array([0.024, 0.015, -0.010])


def _body_from_cam0() -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = _R_BODY_CAM0
    T[:3, 3] = -_R_BODY_CAM0 @ IMU_POSITION_CAM0_M
    T.setflags(write=False)
    return T


T_BODY_CAM0 = _body_from_cam0()


@dataclass(frozen=True)
class ImuNoiseModel:
    """MPU-6050-like measurement parameters (see the module doc)."""

    gyro_noise_density_dps_rthz: float = 0.005
    accel_noise_density_ug_rthz: float = 400.0
    gyro_bias_sigma_dps: float = 0.2
    accel_bias_sigma_m_s2: float = 0.03
    gyro_bias_walk_rad_s2_rthz: float = 1e-4
    accel_bias_walk_m_s3_rthz: float = 1e-3
    gyro_fs_dps: int = 500
    accel_fs_g: int = 4
    temp_c: float = 30.0

    def __post_init__(self) -> None:
        if self.gyro_fs_dps not in GYRO_LSB_PER_DPS:
            raise ConfigError(f"gyro_fs_dps = {self.gyro_fs_dps!r} must be one of {sorted(GYRO_LSB_PER_DPS)}")
        if self.accel_fs_g not in ACCEL_LSB_PER_G:
            raise ConfigError(f"accel_fs_g = {self.accel_fs_g!r} must be one of {sorted(ACCEL_LSB_PER_G)}")
        for key in ("gyro_noise_density_dps_rthz", "accel_noise_density_ug_rthz", "gyro_bias_sigma_dps",
                    "accel_bias_sigma_m_s2", "gyro_bias_walk_rad_s2_rthz", "accel_bias_walk_m_s3_rthz"):
            if getattr(self, key) < 0:
                raise ConfigError(f"{key} = {getattr(self, key)!r} must be >= 0")

    @property
    def gyro_lsb_per_rad_s(self) -> float:
        return GYRO_LSB_PER_DPS[self.gyro_fs_dps] * 180.0 / np.pi

    @property
    def accel_lsb_per_m_s2(self) -> float:
        return ACCEL_LSB_PER_G[self.accel_fs_g] / G_M_S2

    def sensor_noise(self) -> dict[str, float]:
        """The noise this model draws, in ``imu0/sensor.yaml``'s (EuRoC/Kalibr) keys and SI units,
        and the gravity the accelerometer reads at rest (``gravity_m_s2``: 1 g of its m/s^2)."""
        return {
            "gravity_m_s2": G_M_S2,
            "gyroscope_noise_density": float(np.radians(self.gyro_noise_density_dps_rthz)),
            "gyroscope_random_walk": float(self.gyro_bias_walk_rad_s2_rthz),
            "accelerometer_noise_density": float(self.accel_noise_density_ug_rthz * 1e-6 * G_M_S2),
            "accelerometer_random_walk": float(self.accel_bias_walk_m_s3_rthz),
        }

    def white_sigma(self, rate_hz: float) -> tuple[float, float]:
        """Per-sample white-noise sigma (gyro rad/s, accel m/s^2) at ``rate_hz``."""
        g = np.radians(self.gyro_noise_density_dps_rthz) * np.sqrt(rate_hz)
        a = self.accel_noise_density_ug_rthz * 1e-6 * G_M_S2 * np.sqrt(rate_hz)
        return float(g), float(a)


@dataclass
class RawImu:
    """MPU-6050 register values: int16 gyro/accel counts (N, 3), temperature counts (N,), and scales."""

    t_ns: np.ndarray
    gyro: np.ndarray
    accel: np.ndarray
    temp: np.ndarray
    gyro_lsb_per_dps: float
    accel_lsb_per_g: float


@dataclass
class ImuBiases:
    """The biases that were added (for tests and evaluation): (N, 3) each, SI units."""

    gyro_rad_s: np.ndarray
    accel_m_s2: np.ndarray


def imu_sample_times(t_end_ns: int, rate_hz: float, t_start_ns: int = 0) -> np.ndarray:
    """int64 times ``t_start + round(k * 1e9 / rate)`` up to and including ``t_end_ns``."""
    n = int(np.floor((t_end_ns - t_start_ns) * rate_hz / 1e9 + 1e-9)) + 1
    return t_start_ns + np.round(np.arange(n) * (1e9 / rate_hz)).astype(np.int64)


def imu_truth(traj, t_ns: np.ndarray, T_body_cam0: np.ndarray = T_BODY_CAM0,
              gravity_world: np.ndarray = GRAVITY_WORLD) -> ImuSamples:
    """Noise-free gyro and specific force in the body frame at ``t_ns`` (trajectory time = t_ns * 1e-9)."""
    t_ns = np.asarray(t_ns, np.int64)
    st = traj.state(t_ns * 1e-9)
    R_bc = np.asarray(T_body_cam0, float)[:3, :3]
    t_bc = np.asarray(T_body_cam0, float)[:3, 3]
    r = -R_bc.T @ t_bc  # body origin in camera coordinates
    w, dw = st.omega_cam, st.alpha_cam
    lever_c = np.cross(dw, r) + np.cross(w, np.cross(w, r))
    a_body_w = st.a_world + np.einsum("nij,nj->ni", st.R_world_cam, lever_c)
    f_c = np.einsum("nji,nj->ni", st.R_world_cam, a_body_w - np.asarray(gravity_world, float))
    return ImuSamples(t_ns, w @ R_bc.T, f_c @ R_bc.T)


def measure(truth: ImuSamples, model: ImuNoiseModel | None = None, seed: int = 0, rate_hz: float | None = None,
            noise: bool = True) -> tuple[ImuSamples, RawImu, ImuBiases]:
    """MPU-6050-like measurement of ``truth``: ``(samples in SI, raw register counts, biases added)``.

    ``noise=False`` keeps only the quantisation (no white noise, no bias).
    """
    model = model or ImuNoiseModel()
    t_ns = truth.t_ns
    n = len(t_ns)
    if rate_hz is None:
        rate_hz = 1e9 / float(np.median(np.diff(t_ns))) if n > 1 else 200.0
    rng = np.random.default_rng([int(seed) & 0xFFFFFFFF, 0x1A0, 6050])
    dt = 1.0 / rate_hz
    sg, sa = model.white_sigma(rate_hz)
    # draw everything unconditionally so that noise=False/True share the other streams
    g_white = rng.standard_normal((n, 3)) * sg
    a_white = rng.standard_normal((n, 3)) * sa
    g_b0 = rng.standard_normal(3) * np.radians(model.gyro_bias_sigma_dps)
    a_b0 = rng.standard_normal(3) * model.accel_bias_sigma_m_s2
    g_rw = np.cumsum(rng.standard_normal((n, 3)) * model.gyro_bias_walk_rad_s2_rthz * np.sqrt(dt), axis=0)
    a_rw = np.cumsum(rng.standard_normal((n, 3)) * model.accel_bias_walk_m_s3_rthz * np.sqrt(dt), axis=0)
    temp = model.temp_c + 0.5 * (np.arange(n) * dt) / max(n * dt, 1e-9) + rng.standard_normal(n) * 0.05
    if noise:
        gb, ab = g_b0 + g_rw, a_b0 + a_rw
        gyro = truth.gyro_rad_s + gb + g_white
        acc = truth.accel_m_s2 + ab + a_white
    else:
        gb, ab = np.zeros((n, 3)), np.zeros((n, 3))
        gyro, acc = truth.gyro_rad_s.copy(), truth.accel_m_s2.copy()
    gs, as_ = model.gyro_lsb_per_rad_s, model.accel_lsb_per_m_s2
    g_cnt = np.clip(np.round(gyro * gs), -32768, 32767).astype(np.int16)
    a_cnt = np.clip(np.round(acc * as_), -32768, 32767).astype(np.int16)
    t_cnt = np.clip(np.round((temp - TEMP_OFFSET_C) * TEMP_LSB_PER_C), -32768, 32767).astype(np.int16)
    raw = RawImu(t_ns.copy(), g_cnt, a_cnt, t_cnt, GYRO_LSB_PER_DPS[model.gyro_fs_dps], ACCEL_LSB_PER_G[model.accel_fs_g])
    return counts_to_si(raw), raw, ImuBiases(gb, ab)


def counts_to_si(raw: RawImu) -> ImuSamples:
    """Register counts -> :class:`ImuSamples` (rad/s, m/s^2 with 1 g = :data:`G_M_S2`, deg C)."""
    gyro = raw.gyro.astype(float) / (raw.gyro_lsb_per_dps * 180.0 / np.pi)
    acc = raw.accel.astype(float) * (G_M_S2 / raw.accel_lsb_per_g)
    temp = raw.temp.astype(float) / TEMP_LSB_PER_C + TEMP_OFFSET_C
    return ImuSamples(raw.t_ns.copy(), gyro, acc, temp)


def simulate_imu(traj, t_end_ns: int, rate_hz: float = 200.0, model: ImuNoiseModel | None = None, seed: int = 0,
                 T_body_cam0: np.ndarray = T_BODY_CAM0, noise: bool = True,
                 ) -> tuple[ImuSamples, ImuSamples, RawImu, ImuBiases]:
    """``(truth, measured, raw counts, biases)`` sampled at ``rate_hz`` over ``[0, t_end_ns]``."""
    if rate_hz <= 0:
        raise ConfigError(f"imu_rate_hz = {rate_hz!r} must be positive")
    t_ns = imu_sample_times(int(t_end_ns), rate_hz)
    truth = imu_truth(traj, t_ns, T_body_cam0)
    meas, raw, biases = measure(truth, model, seed, rate_hz, noise)
    return truth, meas, raw, biases
