"""Device-to-host streaming: lossy live poses (PUB) and loss-free keyframes (ROUTER, credit flow control).

The public entry point is :class:`DeviceStreamer`, set up by the ``[stream]`` section
(:class:`stereopath.device.settings.StreamSettings`) and the ``[keys]`` section; the pieces it is made of live in one module
each: :mod:`.security` (CURVE keys, ZAP, loopback checks),
:mod:`.spool` (the on-disk keyframe spool), :mod:`.pose_publisher`, :mod:`.keyframe_server`,
:mod:`.health` (CPU, temperature and disk probes) and :mod:`.streamer` (the I/O threads).
Importing this package opens nothing: sockets are created when a streamer is constructed.
"""

from stereopath.device.streaming.spool import KeyframeSpool
from stereopath.device.streaming.streamer import DeviceStreamer

__all__ = ["DeviceStreamer", "KeyframeSpool"]
