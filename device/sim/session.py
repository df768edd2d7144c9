"""A simulated stereo-inertial session: the embedded default source of stereopath.

``open_sim(SimConfig(...))`` gives a :class:`SimSession` with the paper rig (plus the simulated
IMU's ``T_body_cam0``), the frame times, the ground truth, the IMU samples (measured and
noise-free) and random-access rendering of stereo frames.

Clock: ``t_ns`` counts from the first IMU sample (``t_ns = 0``); the first camera frame is at
``1_000_000_000`` (one second of IMU data before it, during which the rig is still; it starts to
move at 1.25 s, see :mod:`stereopath.device.sim.trajectories`), frame ``i`` at ``1e9 + round(i * 1e9 / rate_hz)``
(mid-exposure).  The IMU covers ``[0, t_ns[-1]]`` at ``imu.rate_hz``.  The hand-held trajectory
(:mod:`stereopath.device.sim.handheld`) has no still start: it moves from the first IMU sample on.

World frame: z up, gravity ``(0, 0, -9.81)``; ground truth is ``T_world_cam0`` of the left camera.
Frame ``meta``: ``"T_world_cam0"`` (4x4 ground truth), ``"gains"`` (left, right exposure gain),
``"source": "sim"``, ``"shutter_ms"`` on a hand-held trajectory, and ``"depth0"`` (float32 metres along cam0's z, 0 = no surface) when
``with_depth``.
"""

from __future__ import annotations

import dataclasses
import functools
import logging
from collections.abc import Iterator
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from stereopath.device.core.config import check_range, check_ranges, from_mapping, ranged, replace
from stereopath.device.errors import ConfigError
from stereopath.device.core.frames import ImuSamples, StereoFrame
from stereopath.device.core.rig import Rig, paper_rig
from stereopath.device.sim.imu import ACCEL_LSB_PER_G, GYRO_LSB_PER_DPS, T_BODY_CAM0, ImuNoiseModel, simulate_imu
from stereopath.device.sim.scene import GRAVITY_WORLD
from stereopath.device.sim.exposure import auto_exposure, drift_gains
from stereopath.device.sim.trajectories import FIRST_FRAME_S, TRAJECTORIES, get_trajectory
from stereopath.device.core.trajectory import Trajectory

if TYPE_CHECKING:
    from stereopath.device.sim.render import Renderer
    from stereopath.device.sim.scene import Scene

log = logging.getLogger(__name__)

FIRST_FRAME_NS = int(FIRST_FRAME_S * 1e9)


BLUR_SAMPLES = 5  # sub-frame renders averaged into a motion-blurred frame


@dataclass(frozen=True)
class SimImuConfig:
    """The simulated IMU (section ``imu`` of :class:`SimConfig`)."""

    rate_hz: float = ranged(200.0, 1.0, 8000.0)  # sample rate
    gyro_fs_dps: int = 500          # MPU-6050 gyro full scale: 250, 500, 1000, 2000 deg/s
    accel_fs_g: int = 4             # MPU-6050 accelerometer full scale: 2, 4, 8, 16 g
    noise: bool = True              # False: the measured IMU is the quantised truth (no noise, no bias)

    def __post_init__(self) -> None:
        check_ranges(self, "imu.")
        if self.gyro_fs_dps not in GYRO_LSB_PER_DPS:
            raise ConfigError(f"imu.gyro_fs_dps = {self.gyro_fs_dps!r} must be one of {sorted(GYRO_LSB_PER_DPS)}")
        if self.accel_fs_g not in ACCEL_LSB_PER_G:
            raise ConfigError(f"imu.accel_fs_g = {self.accel_fs_g!r} must be one of {sorted(ACCEL_LSB_PER_G)}")


@dataclass(frozen=True)
class SimConfig:
    """Simulator settings (defaults: the paper-like 5.12 m scan, 400 frames at 20 Hz).

    A hand-held trajectory (``"handheld"``) is always rendered with motion blur and auto-exposure
    changes (:mod:`stereopath.device.sim.exposure`); ``exposure_ms`` is then its nominal shutter time.
    """

    frames: int = ranged(400, 1, 1_000_000)        # stereo frames
    rate_hz: float = ranged(20.0, 0.1, 1000.0)     # frame rate
    seed: int = ranged(0, 0, 2**32 - 1)            # textures, hand shake, image and IMU noise
    trajectory: str = "arc"         # a name in stereopath.device.sim.trajectories.TRAJECTORIES
    noise_sigma: float = ranged(2.0, 0.0, 64.0)    # image noise (DN, Gaussian)
    exposure_drift: bool = False    # slow per-frame gain changes (and a small left/right difference)
    motion_blur: bool = False       # average BLUR_SAMPLES sub-frame renders over exposure_ms
    exposure_ms: float = 8.0        # shutter time used for motion blur
    vignetting: float = ranged(0.0, 0.0, 0.9)      # relative brightness loss in the image corners (0 = none)
    with_depth: bool = False        # put ground-truth depth0 into frame.meta
    imu: SimImuConfig = dataclasses.field(default_factory=SimImuConfig)

    def __post_init__(self) -> None:
        check_ranges(self)
        if self.trajectory not in TRAJECTORIES:
            raise ConfigError(f"trajectory = {self.trajectory!r} is unknown; choose one of {', '.join(TRAJECTORIES)}")
        check_range("exposure_ms", self.exposure_ms, 0.0, 1000.0 / self.rate_hz)

    @property
    def duration_s(self) -> float:
        """Session length from the first IMU sample to the last frame."""
        return FIRST_FRAME_S + (self.frames - 1) / self.rate_hz


@functools.lru_cache(maxsize=1)
def sim_rig() -> Rig:
    """The simulated rig: :func:`stereopath.device.core.rig.paper_rig` with the simulated IMU's ``T_body_cam0``."""
    return paper_rig(T_body_cam0=np.array(T_BODY_CAM0))


@functools.lru_cache(maxsize=2)
def _scene(seed: int) -> Scene:
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
        self.imu_model = ImuNoiseModel(gyro_fs_dps=cfg.imu.gyro_fs_dps, accel_fs_g=cfg.imu.accel_fs_g)
        truth, meas, raw, biases = simulate_imu(
            self.trajectory, int(self.t_ns[-1]), cfg.imu.rate_hz, self.imu_model, cfg.seed,
            T_body_cam0=self.rig.T_body_cam0, noise=cfg.imu.noise,
        )
        self.imu_truth: ImuSamples = truth
        self.imu: ImuSamples = meas
        self.imu_raw = raw            # int16 register counts (stereopath.device.sim.imu.RawImu)
        self.imu_biases = biases      # biases that were added (SI, per sample)
        # the noise drawn, for the recording's imu0/sensor.yaml (None: no noise was added)
        self.imu_noise_figures = self.imu_model.sensor_noise() if cfg.imu.noise else None
        self.hand_held = bool(getattr(self.trajectory, "hand_held", False))
        self._shutter_ms, self._gains = (auto_exposure(self.t_ns * 1e-9, cfg.seed, cfg.exposure_ms) if self.hand_held
                                         else (None, None))
        self._renderer: Renderer | None = None
        log.debug("sim session: %d frames, %s, %.2f m", cfg.frames, cfg.trajectory, self.groundtruth.path_length_m())

    # ------------------------------------------------------------------ sequence interface

    def __len__(self) -> int:
        return len(self.t_ns)

    def __repr__(self) -> str:
        return f"<SimSession {self.cfg.trajectory} seed={self.cfg.seed}: {len(self)} stereo frames>"

    @property
    def scene(self) -> Scene:
        """The rendered :class:`stereopath.device.sim.scene.Scene` (built on first use)."""
        return _scene(self.cfg.seed)

    @property
    def renderer(self) -> Renderer:
        if self._renderer is None:
            from stereopath.device.sim.render import Renderer

            self._renderer = Renderer(self.scene, self.rig, noise_sigma=self.cfg.noise_sigma, seed=self.cfg.seed,
                                      vignetting=self.cfg.vignetting)
        return self._renderer

    def gains(self, i: int) -> tuple[float, float]:
        """Exposure gains (left, right) of frame ``i`` (1, 1 without exposure changes)."""
        if self._gains is not None:
            return float(self._gains[i, 0]), float(self._gains[i, 1])
        if not self.cfg.exposure_drift:
            return 1.0, 1.0
        gl, gr = drift_gains(float(self.t_ns[i]) * 1e-9, self.cfg.seed)
        return float(gl), float(gr)

    def shutter_ms(self, i: int) -> float:
        """Shutter time of frame ``i`` (the auto-exposure's on a hand-held trajectory, else ``exposure_ms``)."""
        return float(self._shutter_ms[i]) if self._shutter_ms is not None else self.cfg.exposure_ms

    @property
    def blurred(self) -> bool:
        """True when frames are rendered with motion blur."""
        return self.hand_held or (self.cfg.motion_blur and BLUR_SAMPLES > 1 and self.cfg.exposure_ms > 0)

    def render(self, i: int) -> StereoFrame:
        """Stereo frame ``i`` (``seq = i``), rendered on demand."""
        n = len(self)
        if not -n <= int(i) < n:
            raise IndexError(f"sim: frame {i} out of range (0..{n - 1})")
        i = int(i) % n
        t_s = float(self.t_ns[i]) * 1e-9
        T = self.groundtruth.T_world_cam[i]
        if self.blurred:
            e = self.shutter_ms(i) * 1e-3
            poses = self.trajectory.pose(t_s + np.linspace(-e / 2, e / 2, BLUR_SAMPLES))
            if BLUR_SAMPLES % 2 == 1:
                poses[BLUR_SAMPLES // 2] = T
            pose_arg = poses
        else:
            pose_arg = T
        gains = self.gains(i)
        left, right, depth0 = self.renderer.render(pose_arg, key=i, gains=gains)
        meta: dict[str, object] = {"T_world_cam0": T.copy(), "gains": gains, "source": "sim"}
        if self.hand_held:
            meta["shutter_ms"] = self.shutter_ms(i)
        if self.cfg.with_depth:
            if pose_arg is not T and BLUR_SAMPLES % 2 == 0:
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


def open_sim(cfg: SimConfig | None = None, **overrides: object) -> SimSession:
    """A :class:`SimSession` for ``cfg`` (default settings if None) with ``overrides`` applied (validated)."""
    if cfg is None:
        cfg = from_mapping(SimConfig, overrides)
    elif overrides:
        cfg = replace(cfg, **overrides)
    return SimSession(cfg)


def config_dict(cfg: SimConfig) -> dict[str, object]:
    return dataclasses.asdict(cfg)
