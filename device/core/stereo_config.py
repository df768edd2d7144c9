"""Settings of the on-board ``stereo`` estimator, one frozen section per stage (pure data).

``StereoConfig`` gathers the sections; each is a TOML table ``[estimator.stereo.<section>]`` of
``device.toml`` (``firmware_cfg/device.toml`` documents every key) and a nested table of the
estimator's ``options`` (``make_estimator("stereo", rig, options={"klt": {...}})``).  The sections:

``keyframes``         when a frame becomes a keyframe, and how many points the tracked map keeps;
``klt``               the KLT searches (frame to frame and left to right);
``asift``             the modified-ASIFT work at keyframes and the keyframe corrections it gives;
``geometry``          stereo points and the pose solve (depth range, thresholds);
``gyro``              the gyro bias refined from the tracked rotation;
``disparity_offset``  the stereo disparity offset (its prior, and whether it is refined on line);
``exposure``          the right camera's grey levels fitted to the left's;
``window``            the local window: a bundle adjustment over the last keyframes on the keyframe worker.

They live in the core (below the settings schema, which embeds them) because the offline tracks'
configuration shares the KLT and stereo-geometry settings.  The estimator itself is
:mod:`stereopath.device.estimation.stereo_vo`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

from stereopath.device.core.config import check_range, check_ranges, ranged
from stereopath.device.errors import ConfigError


@dataclass(frozen=True)
class KeyframePolicy:
    """When a frame becomes a keyframe: what the path needs (points to track, a view change ASIFT can
    still bridge, age); and where the keyframe's ASIFT work runs."""

    max_points: int = ranged(400, 20, 20000)  # map points kept for tracking (the frame loop's cost grows with them)
    min_tracked: int = ranged(100, 8)  # fewer tracked inliers -> keyframe (at most max_points)
    track_ratio: float = ranged(0.6, 0.0, 1.0)  # tracked inliers below this share of the map at the last keyframe
    rotation_deg: float = ranged(15.0, 0.5, 180.0)  # rotation since the last keyframe (the view change ASIFT bridges)
    parallax_px: float = ranged(0.0, 0.0, 10000.0)  # median flow since the keyframe (0 = off)
    max_frames: int = ranged(20, 1, 1000)  # frames since the last keyframe
    background: bool = True  # keyframe ASIFT work on a worker thread (False: at the keyframe itself, deterministic)
    # the worker thread's niceness above the frame loop's (Linux, per thread; 0 = the same priority) when the
    # process may run on at most worker_nice_max_cores cores: on a core the two share the frame loop runs
    # first and the keyframe work, with fewer ASIFT corrections when the core is saturated, takes what is
    # left; with a core of its own the worker keeps the loop's priority (docs/architecture.md, "Cost on fast
    # motion and at full load")
    worker_nice: int = ranged(10, 0, 19)
    worker_nice_max_cores: int = ranged(1, 0, 4096)  # 0: never

    def __post_init__(self) -> None:
        check_ranges(self, "keyframes.")
        check_range("keyframes.min_tracked", self.min_tracked, 8, self.max_points)


@dataclass(frozen=True)
class KltConfig:
    """The pyramidal KLT searches: frame to frame (tracking) and left to right (stereo)."""

    klt_window: int = ranged(19, 5, 61)  # tracking and stereo (15 lost tracks on the blurrier EuRoC frames)
    klt_levels: int = ranged(3, 0, 6)  # pyramid of a search without a 3D guess (new stereo points)
    seeded_stereo_levels: int = ranged(1, 0, 6)  # right-image search from a known 3D point (a guess within ~1 px)
    fb_max_px: float = 0.6  # forward-backward KLT disagreement
    epipolar_max_dy_px: float = ranged(1.0, 0.1, 5.0)  # rectified rows of a stereo match differ by at most this
    # frame-to-frame tracking compares each point's window at the scale its predicted depth change gives,
    # in rungs of (1 + klt_scale_step)^k (device/core/scaled_klt.py; 0 = plain KLT): moving along the
    # optical axis grows near windows from frame to frame, which pulls plain KLT off the points
    klt_scale_step: float = ranged(0.05, 0.0, 0.5)

    def __post_init__(self) -> None:
        check_ranges(self, "klt.")
        if 0.0 < self.klt_scale_step < 0.01:  # finer rungs than 1 % cost a resampling per handful of points
            raise ConfigError(f"klt.klt_scale_step = {self.klt_scale_step!r}: 0 (plain KLT) or 0.01 to 0.5")


@dataclass(frozen=True)
class AsiftWork:
    """The modified-ASIFT work at keyframes (off the frame loop) and the keyframe corrections it gives."""

    enabled: bool = True  # ASIFT work at keyframes (and relocalisation against its libraries)
    feature_preset: str = "onboard"  # modified-ASIFT preset (`fast` costs more CPU for no gain here)
    min_rotation_deg: float = ranged(3.0, 0.0, 180.0)  # rotation since the last ASIFT keyframe that asks for it
    max_frames: int = ranged(30, 1, 100000)  # ... or frames since it
    views: Literal["predicted", "preset"] = "predicted"  # affine views for the predicted view change, or the preset's
    view_min_tilt: float = ranged(1.41, 1.0, 16.0)  # ... above the tilt SIFT bridges itself (sqrt(2): ASIFT's step)
    guided_radius_px: float = 24.0  # keyframe matching around the predicted positions (0 = global)
    library_max: int = 6000  # keypoints (all views) kept with 3D per keyframe for the next match
    max_correction_deg: float = ranged(2.0, 0.0, 180.0)  # larger keyframe corrections are rejected
    map_agreement: float = ranged(0.8, 0.0, 1.0)  # share of the tracked map that must stay inlier in the solve

    def __post_init__(self) -> None:
        from stereopath.device.core.features import get_preset

        get_preset(self.feature_preset)  # an unknown name is refused here, not by each keyframe's job
        if self.views not in ("predicted", "preset"):
            raise ConfigError(f"asift.views must be 'predicted' or 'preset', got {self.views!r}")
        check_ranges(self, "asift.")


@dataclass(frozen=True)
class StereoGeometry:
    """Stereo points (depth range, triangulation) and the two-camera pose solve."""

    min_depth_m: float = ranged(0.1, 0.01)  # at most max_depth_m
    max_depth_m: float = 1000.0
    min_disparity_px: float = 2.0  # farther points (depth > f * baseline / this) are not mapped
    triangulation_max_px: float = 1.0
    pnp_reproj_px: float = 2.0
    min_pnp_inliers: int = ranged(12, 6, 10000)
    huber_px: float = 1.0

    def __post_init__(self) -> None:
        check_ranges(self, "geometry.")
        check_range("geometry.min_depth_m", self.min_depth_m, 0.01, self.max_depth_m)


@dataclass(frozen=True)
class GyroBiasConfig:
    """The gyro bias refined from the tracked rotation, window by window; and the gyro's rotation over
    each frame as a prior of the frame's pose refinement, weighed by its error model
    (:mod:`~stereopath.device.estimation.gyro_prior`) against the frame's measured pixel noise."""

    estimate_bias: bool = True
    rotation_prior: bool = True
    # the prior's error model: white noise density (rad/s/sqrt(Hz); datasheets: MPU-6050 8.7e-5, ADIS16448
    # 1.7e-4) and the relative error of a measured rotation (scale factor and body-to-camera alignment)
    noise_rad_s_rthz: float = ranged(2e-4, 1e-6, 1.0)
    relative_error: float = ranged(0.005, 0.0, 0.5)

    def __post_init__(self) -> None:
        check_ranges(self, "gyro.")


@dataclass(frozen=True)
class DisparityOffsetConfig:
    """The stereo disparity offset: a known prior, refined on line from points seen in stereo at the last
    keyframes where it is identifiable (an orbit around an object leaves it at the prior)."""

    prior_px: float = ranged(0.0, -10.0, 10.0)  # a known offset (calibration): the prior of the estimate
    estimate: bool = True
    keyframes: int = ranged(4, 2, 20)  # keyframes per solve: the last ones, every point seen at two of them

    def __post_init__(self) -> None:
        check_ranges(self, "disparity_offset.")


@dataclass(frozen=True)
class ExposureConfig:
    """Fit the right camera's grey levels to the left's on the stereo matches of every frame and keyframe,
    and correct the right image when the median of the last fits changes the matched texture by more
    than ``tolerance`` grey levels."""

    match: bool = True
    tolerance: float = ranged(4.0, 0.0, 255.0)

    def __post_init__(self) -> None:
        check_ranges(self, "exposure.")


@dataclass(frozen=True)
class WindowConfig:
    """The local window (:mod:`~stereopath.device.estimation.local_window`): the last keyframes' poses and
    their stereo points solved together on the keyframe worker at every keyframe, the oldest held, the
    gyro's rotations between them when there is a gyro; the newest keyframe's refinement corrects the
    live state."""

    enabled: bool = False
    keyframes: int = ranged(6, 2, 30)  # keyframes in the window
    fixed: int = ranged(3, 1, 29)  # the oldest ones held (the gauge; fewer let the windows' errors chain)
    iterations: int = ranged(5, 1, 50)  # Gauss-Newton steps at most
    huber_px: float = ranged(1.0, 0.1, 20.0)
    # of the disparity residual against the pixel's (u, v); not 0: a point seen from keyframes along its
    # ray would have no depth
    disparity_weight: float = ranged(1.0, 0.01, 10.0)
    min_points: int = ranged(20, 6, 100000)  # points seen at two keyframes or more, else no solve
    gyro: bool = True  # the gyro's rotation between consecutive keyframes as a residual
    gyro_noise_rad_s_rthz: float = ranged(2e-3, 1e-6, 1.0)  # the gyro's white noise (rad/s/sqrt(Hz))
    gyro_bias_floor_rad_s: float = ranged(1e-3, 0.0, 1.0)  # the bias's uncertainty at least (rad/s)
    # larger corrections of the newest keyframe are refused, and shifts larger than this angle subtends at
    # the median depth of its points
    max_correction_deg: float = ranged(2.0, 0.0, 180.0)
    # the tracked map's points (each the mean of its stereo triangulations) as a prior of the window's, at
    # this weight times sqrt(their count): what keyframes that left the window knew (0 = no prior)
    map_prior_weight: float = ranged(0.0, 0.0, 10.0)

    def __post_init__(self) -> None:
        check_ranges(self, "window.")
        check_range("window.fixed", self.fixed, 1, self.keyframes - 1)


@dataclass(frozen=True)
class StereoConfig:
    """The ``stereo`` estimator's settings by stage (``[estimator.stereo.*]``)."""

    keyframes: KeyframePolicy = field(default_factory=KeyframePolicy)
    klt: KltConfig = field(default_factory=KltConfig)
    asift: AsiftWork = field(default_factory=AsiftWork)
    geometry: StereoGeometry = field(default_factory=StereoGeometry)
    gyro: GyroBiasConfig = field(default_factory=GyroBiasConfig)
    disparity_offset: DisparityOffsetConfig = field(default_factory=DisparityOffsetConfig)
    exposure: ExposureConfig = field(default_factory=ExposureConfig)
    window: WindowConfig = field(default_factory=WindowConfig)

