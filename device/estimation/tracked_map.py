"""The estimator's tracked map: its points and what is known of each, as parallel arrays (pure data)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class TrackedMap:
    """Tracked points (world), their pixels and their stereo observations at keyframes."""

    X: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))  # world points
    uv: np.ndarray = field(default_factory=lambda: np.zeros((0, 2), np.float32))  # left pixels, last frame
    uv_kf: np.ndarray = field(default_factory=lambda: np.zeros((0, 2), np.float32))  # at keyframe
    ids: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))  # stable point ids
    nobs: np.ndarray = field(default_factory=lambda: np.zeros(0, np.float64))  # stereo observations averaged
    # rectified (u, v, disparity) as measured at the keyframe numbered obs_kf (the disparity offset estimate)
    obs: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    obs_kf: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))

    def keep(self, mask: np.ndarray) -> None:
        self.X, self.uv, self.uv_kf, self.ids = self.X[mask], self.uv[mask], self.uv_kf[mask], self.ids[mask]
        self.nobs, self.obs, self.obs_kf = self.nobs[mask], self.obs[mask], self.obs_kf[mask]

    def move(self, G: np.ndarray) -> None:
        self.X = self.X @ G[:3, :3].T + G[:3, 3]

    def __len__(self) -> int:
        return len(self.X)
