"""A camera trajectory: timestamps and world-from-camera poses (pure; files are in :mod:`stereopath.device.formats`)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from stereopath.device.core.geometry import quat_xyzw_to_matrix


@dataclass
class Trajectory:
    """``t_ns`` (N,) int64 and ``T_world_cam`` (N, 4, 4)."""

    t_ns: np.ndarray
    T_world_cam: np.ndarray

    def __post_init__(self) -> None:
        self.t_ns = np.asarray(self.t_ns, dtype=np.int64).reshape(-1)
        self.T_world_cam = np.asarray(self.T_world_cam, dtype=float).reshape(-1, 4, 4)
        if len(self.t_ns) != len(self.T_world_cam):
            raise ValueError("Trajectory: t_ns and T_world_cam lengths differ")

    def __len__(self) -> int:
        return len(self.t_ns)

    @property
    def positions(self) -> np.ndarray:
        return self.T_world_cam[:, :3, 3]

    def path_length_m(self) -> float:
        p = self.positions
        return float(np.sum(np.linalg.norm(np.diff(p, axis=0), axis=1))) if len(p) > 1 else 0.0

    @classmethod
    def from_pose_rows(cls, t_ns: Sequence[int], rows: Sequence[Sequence[float]]) -> "Trajectory":
        """Rows of ``tx ty tz qx qy qz qw`` (quaternion need not be unit length, must not be zero)."""
        v = np.asarray(rows, dtype=float).reshape(-1, 7)
        T = np.tile(np.eye(4), (len(v), 1, 1))
        for i, row in enumerate(v):
            T[i, :3, :3] = quat_xyzw_to_matrix(row[3:])
        T[:, :3, 3] = v[:, :3]
        return cls(np.asarray(t_ns, dtype=np.int64), T)
