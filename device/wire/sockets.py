"""Socket options shared by the device and the host: linger 0, ZMTP heartbeats, size bounds, backoff."""

from __future__ import annotations

from typing import Any


def apply_common_options(sock: Any, *, heartbeat_ivl_ms: int, heartbeat_timeout_ms: int, heartbeat_ttl_ms: int,
                         maxmsgsize: int, reconnect_ivl_ms: int = 100, reconnect_ivl_max_ms: int = 5000) -> None:
    """Set the options every stereopath socket carries (before bind/connect).

    ``linger`` 0 (close never waits on the network), ZMTP heartbeats (a dead peer is dropped
    after ``heartbeat_timeout_ms``), ``maxmsgsize`` (a peer sending a bigger frame is
    disconnected) and reconnection with exponential backoff from ``reconnect_ivl_ms`` up to
    ``reconnect_ivl_max_ms``.
    """
    import zmq

    sock.setsockopt(zmq.LINGER, 0)
    sock.setsockopt(zmq.HEARTBEAT_IVL, int(heartbeat_ivl_ms))
    sock.setsockopt(zmq.HEARTBEAT_TIMEOUT, int(heartbeat_timeout_ms))
    sock.setsockopt(zmq.HEARTBEAT_TTL, int(heartbeat_ttl_ms))
    sock.setsockopt(zmq.MAXMSGSIZE, int(maxmsgsize))
    sock.setsockopt(zmq.RECONNECT_IVL, int(reconnect_ivl_ms))
    sock.setsockopt(zmq.RECONNECT_IVL_MAX, int(reconnect_ivl_max_ms))
