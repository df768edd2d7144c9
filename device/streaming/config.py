"""Settings of the device's streaming stage (the ``[stream]`` and ``[keys]`` parts of device.toml)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from stereopath.device.core.config import check_range


@dataclass(frozen=True)
class StreamConfig:
    """Endpoints, security and bounds of :class:`stereopath.device.streaming.DeviceStreamer`.

    Every in-memory queue is bounded by one of these numbers, so the device's memory does not
    depend on what the host does.  Times are milliseconds unless the name says otherwise.
    """

    pose_endpoint: str = "tcp://*:5555"        # PUB, lossy live poses (bound by the device)
    keyframe_endpoint: str = "tcp://*:5556"    # ROUTER, loss-free keyframes, status, control
    insecure: bool = False                     # plain TCP, only on loopback endpoints
    server_secret: str = "/etc/stereopath/server.key_secret"  # the device's CURVE key pair (secret file)
    clients_dir: str = "/etc/stereopath/clients"              # authorised host public keys (*.key)
    image_encoding: Literal["jpg", "png", "raw"] = "jpg"      # keyframe images
    jpeg_quality: int = 90
    png_compression: int = 1
    max_credit: int = 16                # keyframes in flight per host, whatever credit it asks for
    max_peers: int = 8                  # hosts tracked at once (least recently heard is evicted)
    pose_sndhwm: int = 16               # PUB high-water mark (per subscriber, then dropped)
    keyframe_sndhwm: int = 64           # ROUTER outbound messages per host
    control_rcvhwm: int = 64            # ROUTER inbound messages per host
    max_pending_keyframes: int = 16     # keyframes waiting to be encoded and spooled
    status_interval_s: float = 1.0      # status heartbeat on the keyframe channel
    heartbeat_ivl_ms: int = 1000        # ZMTP heartbeats (PING every ivl, drop after timeout)
    heartbeat_timeout_ms: int = 5000
    heartbeat_ttl_ms: int = 10000
    spool_fsync: bool = True            # fsync each spooled keyframe before offering it

    def __post_init__(self) -> None:
        check_range("stream.jpeg_quality", self.jpeg_quality, 1, 100)
        check_range("stream.png_compression", self.png_compression, 0, 9)
        check_range("stream.max_credit", self.max_credit, 1, 1024)
        check_range("stream.max_peers", self.max_peers, 1, 256)
        check_range("stream.pose_sndhwm", self.pose_sndhwm, 1, 100000)
        check_range("stream.keyframe_sndhwm", self.keyframe_sndhwm, self.max_credit + 2, 100000)
        check_range("stream.control_rcvhwm", self.control_rcvhwm, 1, 100000)
        check_range("stream.max_pending_keyframes", self.max_pending_keyframes, 1, 1024)
        check_range("stream.status_interval_s", self.status_interval_s, 0.01, 3600.0)
        check_range("stream.heartbeat_ivl_ms", self.heartbeat_ivl_ms, 0, 3_600_000)
        check_range("stream.heartbeat_timeout_ms", self.heartbeat_timeout_ms, 0, 3_600_000)
        check_range("stream.heartbeat_ttl_ms", self.heartbeat_ttl_ms, 0, 6_553_500)
