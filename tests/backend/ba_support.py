"""The bundle adjustment called the way the back-end tests use it (shared by several test modules)."""

from __future__ import annotations

from stereopath.host.backend import gtsam_ba
from stereopath.host.backend.ba_common import BAConfig, BAProblem


def adjust(rig, T, pts, obs, priors=(), n_fixed=1, loops=(), imu=None, **settings):
    """:func:`gtsam_ba.bundle_adjust` with the plain settings these tests were written for (50 iterations,
    no disparity offset) changed by ``settings`` (:class:`BAConfig` fields)."""
    cfg = BAConfig(**{"max_iterations": 50, "disparity_offset": False, "disparity_offset_min_px": 0.0, **settings})
    return gtsam_ba.bundle_adjust(rig, BAProblem(T, pts, obs, list(loops), imu, n_fixed), cfg, priors)
