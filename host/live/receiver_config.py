"""The host receiver's settings and the device address grammar (``HOST[:PORT]`` -> endpoints)."""

from __future__ import annotations

from dataclasses import dataclass, field

from stereopath.device.core.config import check_ranges, ranged
from stereopath.device.errors import ConfigError
from stereopath.device.wire.protocol import KEYFRAME_LIMITS

RECEIVER_JSON = "receiver.json"
DEFAULT_POSE_PORT = 5555
HEARTBEAT_TTL_MS = 10000  # how long the device may wait for this host's heartbeats (ZMTP heartbeat TTL)
MAX_KEYFRAME_BYTES = KEYFRAME_LIMITS.max_message_bytes  # a bigger keyframe message is refused (socket limit)


@dataclass(frozen=True)
class SocketTiming:
    """ZMTP heartbeats and reconnection backoff of the receiver's sockets (milliseconds)."""

    heartbeat_ivl_ms: int = 1000
    heartbeat_timeout_ms: int = 5000  # a silent device is dropped after this (then reconnected)
    reconnect_ivl_ms: int = 100
    reconnect_ivl_max_ms: int = 5000


@dataclass(frozen=True)
class ReceiverConfig:
    """Where the device is, how to authenticate, and the flow-control window."""

    pose_endpoint: str
    keyframe_endpoint: str
    insecure: bool = False
    keys_dir: str | None = None      # the host's key pair (*.key_secret) and device.key
    device_key: str | None = None    # the device's public key, if not KEYS/device.key
    window: int = ranged(8, 1, 1024)  # keyframes in flight (credit)
    sockets: SocketTiming = field(default_factory=SocketTiming)
    stall_timeout_s: float = ranged(3.0, 0.05, 3600.0)  # no keyframe while the device has some: hello again
    fsync: bool = True
    stats_interval_s: float = 1.0    # between rewrites of receiver.json
    max_new_sessions: int = ranged(64, 1, 1_000_000)  # new session ids one run accepts (each gets a folder)

    def __post_init__(self) -> None:
        check_ranges(self)
        if not self.insecure and not self.keys_dir:
            raise ConfigError("a host key directory (--keys DIR) is required unless --insecure is given")


def endpoints_from_address(address: str, keyframe_port: int | None = None) -> tuple[str, str]:
    """``HOST``, ``HOST:PORT``, ``[IPv6]:PORT`` or ``tcp://HOST:PORT`` -> (pose, keyframe) endpoints.

    The pose port defaults to 5555; the keyframe port to the pose port + 1.
    """
    a = address.strip()
    if a.startswith("tcp://"):
        a = a[len("tcp://"):]
    port = DEFAULT_POSE_PORT
    if a.startswith("["):
        host, sep, rest = a[1:].partition("]")
        if not sep:
            raise ConfigError(f"device address {address!r}: unterminated IPv6 address")
        host_part = f"[{host}]"
        if rest:
            if not rest.startswith(":"):
                raise ConfigError(f"device address {address!r} is not HOST[:PORT]")
            port_text = rest[1:]
        else:
            port_text = ""
    else:
        host, sep, port_text = a.partition(":")
        host_part = host
        if ":" in port_text:
            raise ConfigError(f"device address {address!r}: write IPv6 addresses as [ADDR]:PORT")
    if not host_part or any(c in host_part for c in "/;* "):
        raise ConfigError(f"device address {address!r} is not HOST[:PORT]")
    if port_text:
        if not port_text.isdigit() or not 1 <= int(port_text) <= 65535:
            raise ConfigError(f"device address {address!r}: bad port {port_text!r}")
        port = int(port_text)
    kport = keyframe_port if keyframe_port is not None else port + 1
    if not 1 <= kport <= 65535:
        raise ConfigError(f"keyframe port {kport} out of range")
    return f"tcp://{host_part}:{port}", f"tcp://{host_part}:{kport}"
