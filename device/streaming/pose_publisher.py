"""Live poses on an XPUB socket: lossy by design, never blocks.

:meth:`PosePublisher.send` is called from the producer's thread (under a lock, so several
producer threads may share it): a ``NOBLOCK`` send only hands the frame to ZeroMQ, whose own I/O
thread encrypts and transmits it, so the caller never waits on the network and the pose avoids a
thread hop of latency.  A message a subscriber cannot take (its high-water mark reached) is
dropped by ZeroMQ, and an ``EAGAIN`` is counted as a drop.  Hosts see drops as gaps in the pose
seq.

The socket is an XPUB (a PUB that also hands up its subscribers' subscriptions, ``XPUB_VERBOSE``:
every one), so the device can tell when a host's subscription has reached it:
``device run --wait-for-host`` starts capture only then, and the host sees the first pose.
"""

from __future__ import annotations

import logging
import threading
from typing import TYPE_CHECKING

from stereopath.device.settings import StreamSettings
from stereopath.device.wire.sockets import CurveKeys, bind_or_close, open_socket

if TYPE_CHECKING:
    import zmq

log = logging.getLogger(__name__)

# inbound traffic on a PUB is subscriptions and the CURVE handshake (INITIATE is ~300 bytes)
INBOUND_MAX_BYTES = 4096


class PosePublisher:
    """XPUB socket bound to ``config.pose_endpoint`` (CURVE server unless insecure)."""

    def __init__(self, ctx: zmq.Context, config: StreamSettings, curve_keys: CurveKeys | None) -> None:
        import zmq

        self._zmq = zmq
        self.sock = open_socket(ctx, zmq.XPUB, curve_keys, options={zmq.SNDHWM: config.bounds.pose_sndhwm,
                                                                   zmq.XPUB_VERBOSE: 1},
                                heartbeat_ivl_ms=config.heartbeat.ivl_ms,
                                heartbeat_timeout_ms=config.heartbeat.timeout_ms,
                                heartbeat_ttl_ms=config.heartbeat.ttl_ms, maxmsgsize=INBOUND_MAX_BYTES)
        self.endpoint = bind_or_close(self.sock, config.pose_endpoint)
        self.sent = 0
        self.dropped = 0
        self.subscribed = 0  # subscriptions seen (a host's SUB socket, once per connection)
        self._lock = threading.Lock()
        self._closed = False

    def send(self, data: bytes) -> bool:
        """Hand one pose frame to ZeroMQ without blocking; False if it was dropped."""
        with self._lock:
            if self._closed:
                self.dropped += 1
                return False
            try:
                self.sock.send(data, self._zmq.NOBLOCK)
            except self._zmq.Again:
                self.dropped += 1
                return False
            self.sent += 1
            return True

    def subscriptions(self) -> int:
        """Read the subscriptions that arrived (never blocks); the number seen since the start."""
        with self._lock:
            while not self._closed:
                try:
                    msg = self.sock.recv(self._zmq.NOBLOCK)
                except self._zmq.Again:
                    break
                if msg[:1] == b"\x01":  # 1 = subscribe, 0 = unsubscribe (a host went away)
                    self.subscribed += 1
            return self.subscribed

    def close(self, flush_ms: int = 0) -> None:
        """Close the socket; poses ZeroMQ still holds for a connected host get up to ``flush_ms`` to
        leave (the context's ``term`` waits at most that long; with no host nothing waits)."""
        with self._lock:
            self._closed = True
            self.sock.close(linger=int(flush_ms))
