"""Stereo sources: one protocol (:class:`StereoSource`), four backends chosen from configuration.

``create_source(settings)`` returns an unopened source for ``settings.backend``:
``picamera2`` (two CSI cameras, :mod:`stereopath.device.capture.sources.csi`), ``depthai`` (OAK-D mono pair,
:mod:`stereopath.device.capture.sources.oak`), ``replay`` (a recorded sequence, :mod:`stereopath.device.capture.sources.replay`)
or ``sim`` (the simulator, :mod:`stereopath.device.capture.sources.sim`).  Nothing touches hardware or
imports a camera library until the source is opened::

    with create_source(cfg.source) as src:
        for frame in src:          # StereoFrame, t_ns at mid-exposure
            ...

Test seams: ``api=`` (picamera2 names), ``dai=`` (depthai module), ``sequence=``
(replay), ``session=`` (sim), ``rig=``, ``clock_ns=``/``sleep=`` (pacing).
"""

from __future__ import annotations

from stereopath.device.errors import ConfigError
from stereopath.device.settings import SourceSettings
from stereopath.device.capture.sources.base import SourceBase, SourceStats, StereoSource

__all__ = ["SourceBase", "SourceStats", "StereoSource", "create_source"]


def create_source(settings: SourceSettings, **inject: object) -> StereoSource:
    """The configured backend, not yet opened (see module doc for the injectable seams)."""
    backend = settings.backend
    if backend == "picamera2":
        from stereopath.device.capture.sources.csi import Picamera2Source

        route = {"route_reader": inject["route_reader"]} if "route_reader" in inject else {}
        return Picamera2Source(settings, api=inject.get("api"), rig=inject.get("rig"), **route)
    if backend == "depthai":
        from stereopath.device.capture.sources.oak import DepthaiSource

        return DepthaiSource(settings, dai=inject.get("dai"), rig=inject.get("rig"))
    pacing = {k: inject[k] for k in ("clock_ns", "sleep") if k in inject}
    if backend == "replay":
        from stereopath.device.capture.sources.replay import ReplaySource

        return ReplaySource(settings.replay, sequence=inject.get("sequence"), rig_file=settings.rig_file, **pacing)
    if backend == "sim":
        from stereopath.device.capture.sources.sim import SimSource

        return SimSource(settings.sim, sequence=inject.get("session"), rig_file=settings.rig_file, **pacing)
    raise ConfigError(f"source.backend = {backend!r} is not one of picamera2, depthai, replay, sim")
