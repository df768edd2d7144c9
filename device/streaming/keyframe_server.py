"""Loss-free keyframes: a ROUTER socket with credit-based flow control, resending from the spool.

Protocol (ZeroMQ Guide ch.7 "credit-based flow control" + ch.4 "disconnected reliability"):

* a host connects a DEALER and says ``hello(session, acked_seq, credit)``: the last session it
  stored keyframes of, the highest seq it holds contiguously from 0, and its window;
* the server sends the spooled keyframes after ``acked_seq`` (or from 0 when the host knows
  another session), one per unit of credit, never more than ``max_credit`` in flight.  A hello's
  ``acked_seq`` is taken only as far as that host key acknowledged keyframes it was sent in this
  run; anything claimed beyond is sent again (the host stores it once), and only acknowledgements
  advance what the spool records as delivered (``acked.json``, which a later run reads);
* the host stores each keyframe, then answers ``ack(session, seq, credit=1)``;
* after a reconnect the host says hello again and receives everything newer than what it holds,
  so it gets every keyframe exactly once (it deduplicates by (session, seq)).

Each host connection is a peer of its own, acknowledged on its own: two hosts holding the same
key (two laptops, or ``host live`` started twice) each receive every keyframe and the status,
and neither starves the other.  A peer is identified by its CURVE public key (the ``User-Id``
ZAP sets on each message; the routing id without CURVE) and its connection (the ROUTER routing
id, new on every reconnection, which always starts with a hello); a connection that became
unreachable is forgotten.  Memory is bounded: at most ``max_peers`` connections, at most
``max_credit`` keyframes in flight per host (the bytes are read from the spool on demand), and
the ROUTER's high-water marks bound what ZeroMQ queues.

After each hello the host gets the status and the live session's ``session`` message (its rig),
then the live keyframes; once it holds every live keyframe it also gets, oldest first, the
keyframes of earlier sessions no host acknowledged (:mod:`stereopath.device.streaming.backlog`),
each session's message before its first keyframe.  Such a keyframe is deleted from the device when
a host acknowledges it on the connection it was sent on.

Also sent on this channel: the status heartbeat (to every connected host, dropped when a host's
queue is full).  Everything a host sends is decoded as untrusted input; rejected messages are
counted by reason.
"""

from __future__ import annotations

import logging
import time
from typing import TYPE_CHECKING, Any, Callable

from stereopath.device.errors import DatasetError
from stereopath.device.wire.protocol import Ack, Credit, DecodeError, Hello, decode_control
from stereopath.device.settings import StreamSettings
from stereopath.device.wire.ratelog import RateLimitedLog
from stereopath.device.wire.sockets import CurveKeys, bind_or_close, open_socket
from stereopath.device.streaming.acks import ContiguousAcks
from stereopath.device.streaming.backlog import Backlog
from stereopath.device.streaming.spool import KeyframeSpool

if TYPE_CHECKING:
    import zmq

log = logging.getLogger(__name__)

# a frame above this drops the connection in libzmq (it must leave room for the CURVE handshake);
# control messages above CONTROL_LIMITS.max_message_bytes are rejected and counted by the decoder
SOCKET_MAX_BYTES = 4096
KEY_HISTORY_PER_PEER = 4  # host keys remembered (what each was sent and acknowledged) per connection slot
PEER_LOG_INTERVAL_S = 10.0  # at most one hello line per host key in this time (the rest are counted)


def _conn_id(key: str, routing_id: bytes) -> str:
    return f"{key}@{routing_id.hex()}"


class _Peer:
    __slots__ = ("key", "conn", "routing_id", "next_seq", "credit", "acks", "max_sent", "connected",
                 "last_heard", "bl_cursor", "bl_info_sent", "bl_inflight")

    def __init__(self, key: str, routing_id: bytes) -> None:
        self.key = key
        self.conn = _conn_id(key, routing_id)
        self.routing_id = routing_id
        self.next_seq = 0
        self.credit = 0
        self.acks = ContiguousAcks()  # acks are per keyframe: a keyframe the host could not store leaves a gap
        self.max_sent = -1
        self.connected = True
        self.last_heard = time.monotonic()
        self.restart_backlog()

    @property
    def acked(self) -> int:
        """The highest seq this host holds with every seq before it."""
        return self.acks.acked

    def restart_backlog(self) -> None:
        self.bl_cursor = (0, -1)                    # (backlog session index, last seq sent)
        self.bl_info_sent: set[int] = set()         # backlog sessions whose message this connection got
        self.bl_inflight: set[tuple[str, int]] = set()  # backlog keyframes sent, not yet acknowledged


class KeyframeServer:
    """ROUTER socket bound to ``config.keyframe_endpoint``; driven by the streamer's I/O thread."""

    def __init__(self, ctx: zmq.Context, config: StreamSettings, spool: KeyframeSpool, session_id: str,
                 curve_keys: CurveKeys | None, status_fn: Callable[[], bytes],
                 session_fn: Callable[[], bytes] | None = None, backlog: Backlog | None = None) -> None:
        import zmq

        self._zmq = zmq
        self.config = config
        self.spool = spool
        self.session_id = session_id
        self.secure = curve_keys is not None
        self._status_fn = status_fn
        self._session_fn = session_fn
        self.backlog = backlog if backlog is not None and backlog.sessions else None
        self.sock = open_socket(ctx, zmq.ROUTER, curve_keys,
                                options={zmq.ROUTER_MANDATORY: 1, zmq.SNDHWM: config.bounds.keyframe_sndhwm,
                                         zmq.RCVHWM: config.bounds.control_rcvhwm},
                                heartbeat_ivl_ms=config.heartbeat.ivl_ms,
                                heartbeat_timeout_ms=config.heartbeat.timeout_ms,
                                heartbeat_ttl_ms=config.heartbeat.ttl_ms, maxmsgsize=SOCKET_MAX_BYTES)
        self.endpoint = bind_or_close(self.sock, config.keyframe_endpoint)
        self._peers: dict[str, _Peer] = {}
        self._sent_by_key: dict[str, int] = {}  # highest seq sent to any connection of a key (bounded)
        self._acked_by_key: dict[str, ContiguousAcks] = {}  # what each key acknowledged of what it was sent
        self._max_sent_any = -1  # the highest seq sent to any host
        self._peer_log = RateLimitedLog(log, PEER_LOG_INTERVAL_S)  # lines a peer's messages provoke
        self.stats: dict[str, int] = {
            "control_received": 0, "control_rejected": 0, "hellos": 0, "acks": 0, "credits": 0,
            "keyframes_sent": 0, "keyframes_resent": 0, "status_sent": 0, "status_dropped": 0,
            "unroutable": 0, "peers_evicted": 0, "spool_errors": 0, "send_blocked": 0,
            "backlog_sent": 0, "session_sent": 0,
        }
        self.rejected: dict[str, int] = {}

    # ------------------------------------------------------------------ incoming

    def handle_incoming(self, max_messages: int = 256) -> int:
        """Read and handle up to ``max_messages`` control messages without blocking."""
        zmq = self._zmq
        handled = 0
        while handled < max_messages:
            try:
                rid = self.sock.recv(zmq.NOBLOCK)
            except zmq.Again:
                break
            handled += 1
            payload = None
            parts = 0
            more = self.sock.getsockopt(zmq.RCVMORE)
            while more:  # read part by part, keep only the first payload frame
                frame = self.sock.recv(copy=False)
                parts += 1
                if parts == 1:
                    payload = frame
                more = frame.more
            self.stats["control_received"] += 1
            if parts != 1 or payload is None:
                self._reject("frames", f"{parts} payload frames")
                continue
            key = self._peer_key(rid, payload)
            try:
                msg = decode_control(payload.bytes)
            except DecodeError as exc:
                self._reject(exc.reason, str(exc))
                continue
            self.handle(key, rid, msg)
        return handled

    def _peer_key(self, rid: bytes, frame: zmq.Frame) -> str:
        if self.secure:
            try:
                user = frame.get("User-Id")
            except self._zmq.ZMQError:
                user = None
            if user:
                return "curve:" + str(user)
        return "rid:" + rid.hex()

    def _reject(self, reason: str, detail: str) -> None:
        self.stats["control_rejected"] += 1
        self.rejected[reason] = self.rejected.get(reason, 0) + 1
        log.debug("rejected control message (%s): %s", reason, detail[:200])

    def handle(self, key: str, rid: bytes, msg: Hello | Ack | Credit) -> None:
        """One decoded control message from host ``key`` on its connection ``rid``."""
        peer = self._peers.get(_conn_id(key, rid))
        if isinstance(msg, Hello):
            self.stats["hellos"] += 1
            if peer is None:
                same_key = sum(1 for p in list(self._peers.values()) if p.key == key and p.connected)
                if same_key:
                    self._peer_log.log(logging.INFO, "same:" + key[:64], "host %s: another connection with the same "
                                       "key (%d already connected); each gets every keyframe", key[:20], same_key)
                peer = self._add_peer(key, rid)
            peer.connected = True
            peer.last_heard = time.monotonic()
            claimed = msg.acked_seq if msg.session_id == self.session_id else -1
            # a claim counts only as far as acknowledgements confirm it (each checked against what was sent):
            # this key's own, or the spool's record of what hosts hold. A stale, corrupt or hostile hello can
            # skip no keyframe, and that record advances on acknowledgements alone
            verified = self._acked_by_key.get(key)
            trusted = max(self.spool.acked_seq, -1 if verified is None else verified.acked)
            acked = min(claimed, self.spool.last_seq, trusted)
            peer.acks.reset(acked, keep_above=False)
            peer.next_seq = peer.acked + 1
            peer.credit = min(msg.credit, self.config.bounds.max_credit)
            peer.restart_backlog()
            if peer.acked >= 0:
                self.spool.release(peer.acked)
            log_key = key if key.startswith("curve:") else "insecure"  # a plain connection's key is new each time
            if claimed > self._max_sent_any:  # beyond anything any host was sent: a stale or forged state
                self._peer_log.log(logging.WARNING, "claim:" + log_key,
                                   "host %s: hello says it holds keyframes up to %d of this session, of which "
                                   "no host was sent more than %d: sending from seq %d", key[:20], claimed,
                                   self._max_sent_any, peer.next_seq)
            self._peer_log.log(logging.INFO, "hello:" + log_key,
                               "host %s: hello (session %s, acked %d, credit %d) -> sending from seq %d",
                               key[:20], msg.session_id, msg.acked_seq, msg.credit, peer.next_seq)
            self._send_to(peer, self._status_fn(), status=True)
            if self._session_fn is not None and self._send_to(peer, self._session_fn()):
                self.stats["session_sent"] += 1
            return
        if peer is None:
            self._reject("no_hello", f"{type(msg).__name__} from {key[:20]} before hello")
            return
        peer.last_heard = time.monotonic()
        if not peer.connected:
            # reachable again without a hello: whatever was in flight is lost (go back)
            peer.connected = True
            peer.next_seq = peer.acked + 1
        if isinstance(msg, Ack):
            self.stats["acks"] += 1
            if msg.session_id == self.session_id and msg.seq <= peer.max_sent:
                # an ack is for its own keyframe only: one the host could not store (its disk full) stays
                # unacknowledged before it, to be resent after the host's next hello
                peer.acks.add(msg.seq)
                self._key_acks(key).add(msg.seq)
                self.spool.release(peer.acked)  # held by a host: what a full disk kept in memory can go
                self.spool.mark_acked(msg.seq)
            elif (msg.session_id, msg.seq) in peer.bl_inflight and self.backlog is not None:
                peer.bl_inflight.discard((msg.session_id, msg.seq))
                self.backlog.acknowledged(msg.session_id, msg.seq)
            peer.credit = min(peer.credit + msg.credit, self.config.bounds.max_credit)
        else:
            self.stats["credits"] += 1
            peer.credit = min(peer.credit + msg.n, self.config.bounds.max_credit)

    def _key_acks(self, key: str) -> ContiguousAcks:
        acks = self._acked_by_key.pop(key, None) or ContiguousAcks()
        self._acked_by_key[key] = acks
        self._bound_history(self._acked_by_key)
        return acks

    def _bound_history(self, history: dict[str, Any]) -> None:
        """Forget the least recently updated keys of a per-key history (insertion order) beyond a bound."""
        while len(history) > KEY_HISTORY_PER_PEER * self.config.bounds.max_peers:
            history.pop(next(iter(history)))

    def _add_peer(self, key: str, rid: bytes) -> _Peer:
        if len(self._peers) >= self.config.bounds.max_peers:
            oldest = min(list(self._peers.values()), key=lambda p: (p.connected, p.last_heard))
            self._peers.pop(oldest.conn, None)
            self.stats["peers_evicted"] += 1
            self._peer_log.log(logging.WARNING, "evict", "too many host connections (max %d): "
                               "forgetting one of %s", self.config.bounds.max_peers, oldest.key[:20])
        peer = _Peer(key, rid)
        peer.max_sent = self._sent_by_key.get(key, -1)  # what this key had: later sends count as resends
        self._peers[peer.conn] = peer
        return peer

    # ------------------------------------------------------------------ outgoing

    def _send_to(self, peer: _Peer, data: bytes, status: bool = False) -> bool:
        zmq = self._zmq
        try:
            self.sock.send_multipart([peer.routing_id, data], flags=zmq.NOBLOCK, copy=len(data) < 65536)
        except zmq.Again:
            if status:
                self.stats["status_dropped"] += 1
            return False
        except zmq.ZMQError as exc:
            if exc.errno != zmq.EHOSTUNREACH:
                raise
            peer.connected = False
            self.stats["unroutable"] += 1
            if status:
                self.stats["status_dropped"] += 1
            return False
        if status:
            self.stats["status_sent"] += 1
        return True

    def pump(self, burst: int = 32) -> bool:
        """Send spooled keyframes to hosts with credit; True if a host's queue was full (retry soon)."""
        blocked = False
        last = self.spool.last_seq
        for peer in list(self._peers.values()):
            sent = 0
            while peer.connected and peer.credit > 0 and peer.next_seq <= last and sent < burst:
                seq = peer.next_seq
                if self.spool.delivered_from_memory(seq):  # a host has it; it was never on disk (a full disk)
                    peer.acks.add(seq)  # nothing to wait for from this host
                    peer.next_seq += 1
                    continue
                try:
                    data = self.spool.read(seq)
                except DatasetError as exc:
                    self.stats["spool_errors"] += 1
                    log.error("cannot resend keyframe %d: %s (skipped)", seq, exc)
                    peer.next_seq += 1
                    continue
                if not self._send_to(peer, data):
                    if peer.connected:
                        blocked = True
                        self.stats["send_blocked"] += 1
                    break
                sent += 1
                self.stats["keyframes_sent"] += 1
                if seq <= peer.max_sent:
                    self.stats["keyframes_resent"] += 1
                peer.max_sent = max(peer.max_sent, seq)
                self._max_sent_any = max(self._max_sent_any, seq)
                if self._sent_by_key.get(peer.key, -1) < seq:
                    self._sent_by_key.pop(peer.key, None)
                    self._sent_by_key[peer.key] = seq
                    self._bound_history(self._sent_by_key)
                peer.next_seq = seq + 1
                peer.credit -= 1
            if self.backlog is not None and peer.next_seq > last and sent < burst:
                blocked = self._pump_backlog(peer, burst - sent) or blocked
        return blocked

    def _pump_backlog(self, peer: _Peer, burst: int) -> bool:
        """Earlier sessions' undelivered keyframes to a host that holds every live one; True if blocked."""
        backlog = self.backlog
        assert backlog is not None
        sent = 0
        while peer.connected and peer.credit > 0 and sent < burst:
            item = backlog.next_after(peer.bl_cursor)
            if item is None:
                return False
            si, seq = item
            sess = backlog.sessions[si]
            if si not in peer.bl_info_sent:
                if not self._send_to(peer, sess.message):
                    return peer.connected
                peer.bl_info_sent.add(si)
                self.stats["session_sent"] += 1
                log.info("host %s: offering %d undelivered keyframe(s) of earlier session %s", peer.key[:20],
                         len(sess.pending), sess.session_id)
            data = backlog.read(si, seq)
            if data is None:  # delivered through another connection meanwhile
                peer.bl_cursor = (si, seq)
                continue
            if not self._send_to(peer, data):
                if peer.connected:
                    self.stats["send_blocked"] += 1
                return peer.connected
            peer.bl_cursor = (si, seq)
            peer.bl_inflight.add((sess.session_id, seq))
            peer.credit -= 1
            sent += 1
            self.stats["backlog_sent"] += 1
        return False

    def broadcast_status(self, data: bytes) -> None:
        for peer in list(self._peers.values()):
            if peer.connected:
                self._send_to(peer, data, status=True)
            if not peer.connected:  # unreachable: that connection is gone (a reconnection says hello)
                self._peers.pop(peer.conn, None)

    def peers(self) -> list[dict[str, Any]]:
        """Each connection's state.  Read from the service's status thread while the I/O thread adds and
        forgets connections: the connections are taken as one snapshot first (every walk over them here
        does the same)."""
        return [{"key": p.key, "connected": p.connected, "acked": p.acked, "next_seq": p.next_seq,
                 "credit": p.credit, "max_sent": p.max_sent} for p in list(self._peers.values())]

    def close(self) -> None:
        self.sock.close(linger=0)
