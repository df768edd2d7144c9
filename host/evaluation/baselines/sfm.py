"""The ``sfm`` baseline of the paper's Table 2: camera 1 only, SIFT + essential matrix chaining.

Monocular structure from motion has no scale, so each step's length is taken
from the ground truth ("oracle scale"): this shows what monocular SFM reaches
at best, and every report of it says so.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from stereopath.device.core.config import check_ranges, ranged
from stereopath.device.estimation.base import PoseEstimate, WorldFrame
from stereopath.host.evaluation.baselines.paper import match_indices
from stereopath.device.core.features import gray
from stereopath.device.core.frames import ImuSamples, StereoFrame
from stereopath.device.core.geometry import make_pose
from stereopath.device.core.rig import Rig
from stereopath.device.formats.tum import Trajectory


@dataclass(frozen=True)
class SfmConfig:
    feature_preset: str = "sift"
    ransac_iterations: int = ranged(10_000, 10, 1_000_000)
    frame_step: int = ranged(4, 1, 1000)  # a "position" every N video frames (consecutive 20 Hz frames barely move)
    ransac_threshold_px: float = 1.0
    min_matches: int = 15

    def __post_init__(self) -> None:
        check_ranges(self)


class SfmEstimator:
    name = "sfm"
    oracle_scale = True

    def __init__(self, rig: Rig, groundtruth: Trajectory, config: SfmConfig | None = None) -> None:
        from stereopath.device.core.features import get_preset

        self.rig = rig
        self.cfg = config or SfmConfig()
        self._fcfg = get_preset(self.cfg.feature_preset)
        self._gt = groundtruth
        self.world_frame: WorldFrame = "first_camera"
        self._prev = None
        self._prev_t: int | None = None
        self._T = np.eye(4)
        self._count = 0
        self._last_dir = np.array([0.0, 0.0, 1.0])
        self.counters = {"failures": 0, "no_translation": 0}

    def stats(self) -> dict:
        return {**self.counters, "oracle_scale": True}

    def _gt_position(self, t_ns: int) -> np.ndarray:
        t = self._gt.t_ns
        p = self._gt.positions
        return np.array([np.interp(t_ns, t, p[:, k]) for k in range(3)])

    def process(self, frame: StereoFrame, imu: ImuSamples | None) -> PoseEstimate | None:
        from stereopath.device.core.features import detect
        from stereopath.device.core.matching import MatchConfig, match
        from stereopath.device.core.twoview import TwoViewConfig, relative_pose

        self._count += 1
        if (self._count - 1) % self.cfg.frame_step:
            return None
        img = gray(frame.left)
        f = detect(img, self._fcfg)
        if self._prev is None:
            self._prev, self._prev_t = f, frame.t_ns
            return PoseEstimate(frame.seq, frame.t_ns, self._T.copy(), "ok", note="oracle_scale")
        step = float(np.linalg.norm(self._gt_position(frame.t_ns) - self._gt_position(self._prev_t)))
        idx = match_indices(match(self._prev.original_view(), f, MatchConfig()))
        status, note = "ok", "oracle_scale"
        if len(idx) >= self.cfg.min_matches:
            K = self.rig.cam0.K
            res = relative_pose(self._prev.original_view().xy[idx[:, 0]], f.xy[idx[:, 1]], K, K,
                                TwoViewConfig(max_iters=self.cfg.ransac_iterations,
                                              threshold_px=self.cfg.ransac_threshold_px))
        else:
            res = None
        if res is None or res.R is None:
            self.counters["failures"] += 1
            status, note = "lost", "two_view_failed"
        else:
            # x_P = R x_{P-1} + t  ->  camera P in camera P-1's frame: R_rel = R^T, centre = -R^T t
            R_rel = res.R.T
            if res.t is None:  # too little parallax for a direction: keep the last one
                self.counters["no_translation"] += 1
                c = self._last_dir
            else:
                c = -res.R.T @ np.asarray(res.t, dtype=float).reshape(3)
                c = c / max(np.linalg.norm(c), 1e-12)
                self._last_dir = R_rel.T @ c  # expressed in the new camera's axes for next time
            c = c * step
            self._T = self._T @ make_pose(R_rel, c)
        self._prev, self._prev_t = f, frame.t_ns
        return PoseEstimate(frame.seq, frame.t_ns, self._T.copy(), status, note=note)
