"""Sockets as both sides open them: linger 0, ZMTP heartbeats, size bounds, backoff, and CURVE (or loopback)."""

from __future__ import annotations

import logging
import socket
from typing import TYPE_CHECKING, Callable, Mapping, Sequence

if TYPE_CHECKING:
    import zmq

log = logging.getLogger(__name__)


def apply_common_options(sock: zmq.Socket, *, heartbeat_ivl_ms: int, heartbeat_timeout_ms: int, heartbeat_ttl_ms: int,
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


class CurveKeys:
    """One side's CURVE keys: the device serves (``server_key`` None), a host connects to ``server_key``."""

    def __init__(self, public: bytes, secret: bytes, server_key: bytes | None = None) -> None:
        self.public, self.secret, self.server_key = public, secret, server_key

    def apply(self, sock: zmq.Socket) -> None:
        """Make ``sock`` a CURVE server or client (before bind/connect)."""
        sock.curve_publickey, sock.curve_secretkey = self.public, self.secret
        if self.server_key is None:
            sock.curve_server = True
        else:
            sock.curve_serverkey = self.server_key


def secure_channel(insecure: bool, endpoints: Sequence[str], load_keys: Callable[[], CurveKeys],
                   what: str) -> CurveKeys | None:
    """The CURVE keys of a channel, or None for plain TCP, which only loopback endpoints may use.

    The one set-up of security for both sides: the device's streamer and the host's receiver.
    """
    from stereopath.device.wire.security import check_loopback_endpoint, require_curve

    if insecure:
        for endpoint in endpoints:
            check_loopback_endpoint(endpoint)
        log.warning("%s WITHOUT CURVE (insecure, loopback only)", what)
        return None
    require_curve()
    return load_keys()


def open_socket(ctx: zmq.Context, kind: int, keys: CurveKeys | None, *, options: Mapping[int, int] | None = None,
                **common: int) -> zmq.Socket:
    """A socket of ``kind`` with the common options (:func:`apply_common_options`), ``options`` and CURVE."""
    sock = ctx.socket(kind)
    apply_common_options(sock, **common)
    for opt, value in (options or {}).items():
        sock.setsockopt(opt, value)
    if keys is not None:
        keys.apply(sock)
    return sock


def bind_or_close(sock: zmq.Socket, endpoint: str) -> str:
    """Bind ``sock`` and return the endpoint it got; on failure close it (linger 0) and re-raise.

    A socket left open after a failed bind would hang the context's ``term()`` for good.
    """
    import zmq

    try:
        sock.bind(endpoint)
    except zmq.ZMQError:
        sock.close(linger=0)
        raise
    return sock.getsockopt_string(zmq.LAST_ENDPOINT)


def zmtp_greeting(endpoint: str, timeout_s: float = 1.0) -> str:
    """What answers at a ``tcp://host:port`` endpoint, read from the greeting a ZeroMQ peer sends.

    ZMTP 3 (RFC 23): each side sends a 10-byte signature ``FF 00*8 7F`` and its major version as soon
    as the TCP connection opens; once it has seen the other side's signature it sends the rest of its
    64-byte greeting, whose bytes 12-31 name its security mechanism.  This sends a signature and
    version only (nothing a peer could refuse), reads the peer's greeting and closes before any
    handshake.  Returns ``"zmtp:<MECHANISM>"``
    (``zmtp:CURVE``, ``zmtp:NULL``: a ZeroMQ peer), ``"no greeting"`` (the connection was accepted, then
    closed or silent: a forwarder or tunnel with nothing behind it, or another program), ``"refused"``
    (nothing listens) or ``"unknown"`` (not a TCP endpoint, or another error).
    """
    if not endpoint.startswith("tcp://"):
        return "unknown"
    host, _, port = endpoint[len("tcp://"):].rpartition(":")
    host = host.strip("[]")
    try:
        conn = socket.create_connection((host, int(port)), timeout=timeout_s)
    except ConnectionRefusedError:
        return "refused"
    except (OSError, ValueError):
        return "unknown"
    ours = b"\xff" + bytes(8) + b"\x7f" + bytes([3])  # signature and major version only: no mechanism to refuse
    data = b""
    with conn:
        try:
            conn.settimeout(timeout_s)
            while len(data) < 64:
                chunk = conn.recv(64 - len(data))
                if not chunk:
                    break
                data += chunk
                if len(data) >= 10 and len(data) - len(chunk) < 10:  # its signature seen: ours, in full
                    if data[0] != 0xFF or data[9] != 0x7F:
                        break
                    conn.sendall(ours)
        except OSError:  # a timeout, or a reset
            pass
    if len(data) < 10 or data[0] != 0xFF or data[9] != 0x7F:
        return "no greeting"
    if len(data) < 32:
        return "zmtp:?"
    return "zmtp:" + data[12:32].rstrip(b"\0").decode("ascii", "replace")
