"""The simulated stereo-inertial rig: the embedded default source (no hardware, no downloads).

* :mod:`stereopath.device.sim.textures`     procedural grey textures from a seed;
* :mod:`stereopath.device.sim.scene`        the table-top scene of textured quads (world z up) and its true geometry;
* :mod:`stereopath.device.sim.render`       exact-perspective z-buffered rendering of the rig's two cameras;
* :mod:`stereopath.device.sim.trajectories` analytic trajectories with exact derivatives (default: the 5.12 m arc);
* :mod:`stereopath.device.sim.imu`          IMU truth and the MPU-6050-like measurement model;
* :mod:`stereopath.device.sim.session`      ``open_sim(SimConfig(...)) -> SimSession`` ties them together;
* :mod:`stereopath.device.sim.source`       parses ``sim[:SEED or key=value,...]`` for :func:`stereopath.device.formats.open_source`.

Nothing is imported until used: ``from stereopath.device.sim import open_sim, SimConfig`` loads the session module.
"""

from __future__ import annotations

__all__ = ["SimConfig", "SimSession", "open_sim"]


def __getattr__(name: str) -> object:
    if name in __all__:
        from stereopath.device.sim import session

        return getattr(session, name)
    raise AttributeError(f"module 'stereopath.device.sim' has no attribute {name!r}")
