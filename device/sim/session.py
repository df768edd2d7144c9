"""A simulated stereo-inertial session: the embedded default source of stereopath.

``open_sim(SimConfig(...))`` gives a :class:`SimSession` with the paper rig (plus the simulated
IMU's ``T_body_cam0``), the frame times, the ground truth, the IMU samples (measured and
noise-free) and random-access rendering of stereo frames.

Clock: ``t_ns`` counts from the first IMU sample (``t_ns = 0``); the first camera frame is at
``1_000_000_000`` (one second of IMU data before it, during which the rig is still; it starts to
move at 1.25 s, see :mod:`stereopath.device.sim.trajectories`), frame ``i`` at ``1e9 + round(i * 1e9 / rate_hz)``
(mid-exposure).  The IMU covers ``[0, t_ns[-1]]`` at ``imu_rate_hz``.

World frame: z up, gravity ``(0, 0, -9.81)``; ground truth is ``T_world_cam0`` of the left camera.
Frame ``meta``: ``"T_world_cam0"`` (4x4 ground truth), ``"gains"`` (left, right exposure gain),
``"source": "sim"``, and ``"depth0"`` (float32 metres along cam0's z, 0 = no surface) when
``with_depth``.
"""

from __future__ import annotations

import dataclasses
import functools
import logging
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np

from stereopath.device.core.config import check_range, from_mapping, replace
from stereopath.device.errors import ConfigError
from stereopath.device.core.frames import ImuSamples, StereoFrame
from stereopath.device.core.rig import Rig, paper_rig
from stereopath.device.sim.imu import ACCEL_LSB_PER_G, GYRO_LSB_PER_DPS, T_BODY_CAM0, ImuNoiseModel, simulate_imu
from stereopath.device.sim.scene import GRAVITY_WORLD
from stereopath.device.sim.trajectories import FIRST_FRAME_S, TRAJECTORIES, get_trajectory
from stereopath.device.core.trajectory import Trajectory

log = logging.getLogger(__name__)

FIRST_FRAME_NS = int(FIRST_FRAME_S * 1e9)


@dataclass(frozen=True)
class SimConfig:
    """Simulator settings (defaults: the paper-like 5.12 m scan, 400 frames at 20 Hz)."""

    frames: int = 400               # stereo frames
    rate_hz: float = 20.0           # frame rate
    seed: int = 0                   # textures, hand shake, image and IMU noise
    trajectory: str = "arc"         # a name in stereopath.device.sim.trajectories.TRAJECTORIES
    imu_rate_hz: float = 200.0      # IMU sample rate
    noise_sigma: float = 2.0        # image noise (DN, Gaussian)
    exposure_drift: bool = False    # slow per-frame gain changes (and a small left/right difference)
    motion_blur: bool = False       # average blur_samples sub-frame renders over exposure_ms
    gyro_fs_dps: int = 500          # MPU-6050 gyro full scale: 250, 500, 1000, 2000 deg/s
    accel_fs_g: int = 4             # MPU-6050 accelerometer full scale: 2, 4, 8, 16 g
    with_depth: bool = False        # put ground-truth depth0 into frame.meta
    exposure_ms: float = 8.0        # shutter time used for motion blur
    blur_samples: int = 5           # sub-frame renders per blurred frame
    vignetting: float = 0.0         # relative brightness loss in the image corners (0 = none)
    imu_noise: bool = True          # False: the measured IMU is the quantised truth (no noise, no bias)

    def __post_init__(self) -> None:
        check_range("frames", self.frames, 1, 1_000_000)
        check_range("rate_hz", self.rate_hz, 0.1, 1000.0)
        check_range("seed", self.seed, 0, 2**32 - 1)
        if self.trajectory not in TRAJECTORIES:
            raise ConfigError(f"trajectory = {self.trajectory!r} is unknown; choose one of {', '.join(TRAJECTORIES)}")
        check_range("imu_rate_hz", self.imu_rate_hz, 1.0, 8000.0)
        check_range("noise_sigma", self.noise_sigma, 0.0, 64.0)
        if self.gyro_fs_dps not in GYRO_LSB_PER_DPS:
            raise ConfigError(f"gyro_fs_dps = {self.gyro_fs_dps!r} must be one of {sorted(GYRO_LSB_PER_DPS)}")
        if self.accel_fs_g not in ACCEL_LSB_PER_G:
            raise ConfigError(f"accel_fs_g = {self.accel_fs_g!r} must be one of {sorted(ACCEL_LSB_PER_G)}")
        check_range("exposure_ms", self.exposure_ms, 0.0, 1000.0 / self.rate_hz)
        check_range("blur_samples", self.blur_samples, 1, 64)
        check_range("vignetting", self.vignetting, 0.0, 0.9)

    @property
    def duration_s(self) -> float:
        """Session length from the first IMU sample to the last frame."""
        return FIRST_FRAME_S + (self.frames - 1) / self.rate_hz


@functools.lru_cache(maxsize=1)
def sim_rig() -> Rig:
    """The simulated rig: :func:`stereopath.device.core.rig.paper_rig` with the simulated IMU's ``T_body_cam0``."""
    return paper_rig(T_body_cam0=np.array(T_BODY_CAM0))


@functools.lru_cache(maxsize=2)
def _scene(seed: int):
    from stereopath.device.sim.scene import table_top_scene

    return table_top_scene(seed)


class SimSession:
    """One simulated session (see the module doc).  Rendering is random access and deterministic."""

    name = "sim"

    def __init__(self, cfg: SimConfig) -> None:
        if not isinstance(cfg, SimConfig):
            raise ConfigError(f"SimSession needs a SimConfig, got {type(cfg).__name__}")
        self.cfg = cfg
        self.rig: Rig = sim_rig()
        self.spec = f"sim:{cfg.seed}"
        self.t_ns: np.ndarray = FIRST_FRAME_NS + np.round(np.arange(cfg.frames) * (1e9 / cfg.rate_hz)).astype(np.int64)
        self.trajectory = get_trajectory(cfg.trajectory, cfg.duration_s, seed=cfg.seed)
        self.groundtruth: Trajectory = Trajectory(self.t_ns, self.trajectory.pose(self.t_ns * 1e-9))
        self.gravity_world: np.ndarray = GRAVITY_WORLD.copy()
        self.imu_model = ImuNoiseModel(gyro_fs_dps=cfg.gyro_fs_dps, accel_fs_g=cfg.accel_fs_g)
        truth, meas, raw, biases = simulate_imu(
            self.trajectory, int(self.t_ns[-1]), cfg.imu_rate_hz, self.imu_model, cfg.seed,
            T_body_cam0=self.rig.T_body_cam0, noise=cfg.imu_noise,
        )
        self.imu_truth: ImuSamples = truth
        self.imu: ImuSamples = meas
        self.imu_raw = raw            # int16 register counts (stereopath.device.sim.imu.RawImu)
        self.imu_biases = biases      # biases that were added (SI, per sample)
        # the noise drawn, for the recording's imu0/sensor.yaml (None: no noise was added)
        self.imu_noise_figures = self.imu_model.sensor_noise() if cfg.imu_noise else None
        self._renderer = None
        log.debug("sim session: %d frames, %s, %.2f m", cfg.frames, cfg.trajectory, self.groundtruth.path_length_m())

    # ------------------------------------------------------------------ sequence interface

    def __len__(self) -> int:
        return len(self.t_ns)

    def __repr__(self) -> str:
        return f"<SimSession {self.cfg.trajectory} seed={self.cfg.seed}: {len(self)} stereo frames>"

    @property
    def scene(self):
        """The rendered :class:`stereopath.device.sim.scene.Scene` (built on first use)."""
        return _scene(self.cfg.seed)

    @property
    def renderer(self):
        if self._renderer is None:
            from stereopath.device.sim.render import Renderer

            self._renderer = Renderer(self.scene, self.rig, noise_sigma=self.cfg.noise_sigma, seed=self.cfg.seed,
                                      vignetting=self.cfg.vignetting)
        return self._renderer

    def gains(self, i: int) -> tuple[float, float]:
        """Exposure gains (left, right) of frame ``i`` (1, 1 without exposure drift)."""
        if not self.cfg.exposure_drift:
            return 1.0, 1.0
        t = float(self.t_ns[i]) * 1e-9
        ph = np.random.default_rng([self.cfg.seed & 0xFFFFFFFF, 0xE9]).uniform(0, 2 * np.pi, 3)
        gl = 1.0 + 0.15 * np.sin(2 * np.pi * t / 11.0 + ph[0]) + 0.06 * np.sin(2 * np.pi * t / 3.7 + ph[1])
        gr = gl * (1.0 + 0.03 * np.sin(2 * np.pi * t / 5.3 + ph[2]))
        return float(gl), float(gr)

    def render(self, i: int) -> StereoFrame:
        """Stereo frame ``i`` (``seq = i``), rendered on demand."""
        n = len(self)
        if not -n <= int(i) < n:
            raise IndexError(f"sim: frame {i} out of range (0..{n - 1})")
        i = int(i) % n
        t_s = float(self.t_ns[i]) * 1e-9
        T = self.groundtruth.T_world_cam[i]
        if self.cfg.motion_blur and self.cfg.blur_samples > 1 and self.cfg.exposure_ms > 0:
            e = self.cfg.exposure_ms * 1e-3
            poses = self.trajectory.pose(t_s + np.linspace(-e / 2, e / 2, self.cfg.blur_samples))
            if self.cfg.blur_samples % 2 == 1:
                poses[self.cfg.blur_samples // 2] = T
            pose_arg = poses
        else:
            pose_arg = T
        gains = self.gains(i)
        left, right, depth0 = self.renderer.render(pose_arg, key=i, gains=gains)
        meta: dict[str, Any] = {"T_world_cam0": T.copy(), "gains": gains, "source": "sim"}
        if self.cfg.with_depth:
            if pose_arg is not T and self.cfg.blur_samples % 2 == 0:
                _, depth0 = self.renderer.render_view(self.rig.cam0.K, self.rig.cam0.size, T, self.rig.cam0.dist)
            meta["depth0"] = depth0
        return StereoFrame(seq=i, t_ns=int(self.t_ns[i]), left=left, right=right, meta=meta)

    def frame(self, i: int) -> StereoFrame:
        """Alias of :meth:`render` (the recorded-sequence interface)."""
        return self.render(i)

    def frames(self, start: int = 0, stop: int | None = None, step: int = 1) -> Iterator[StereoFrame]:
        """All frames in order (or a slice of them)."""
        for i in range(*slice(start, stop, step).indices(len(self))):
            yield self.render(i)

    def __iter__(self) -> Iterator[StereoFrame]:
        return self.frames()


def open_sim(cfg: SimConfig | None = None, **overrides: Any) -> SimSession:
    """A :class:`SimSession` for ``cfg`` (default settings if None) with ``overrides`` applied (validated)."""
    if cfg is None:
        cfg = from_mapping(SimConfig, overrides)
    elif overrides:
        cfg = replace(cfg, **overrides)
    return SimSession(cfg)


def config_dict(cfg: SimConfig) -> dict[str, Any]:
    return dataclasses.asdict(cfg)
