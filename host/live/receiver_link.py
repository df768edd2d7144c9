"""The receiver's side of the keyframe link: its sockets, handshakes, hellos, stall and silence checks.

:class:`Link` owns the pose SUB and keyframe DEALER sockets and the flow-control state; the
:class:`stereopath.host.live.receiver.Receiver` composes one and calls it.  On every completed
handshake (the DEALER's socket monitor reports it, so reconnects are noticed) the link says
``hello(last session, highest contiguous seq, window)``; when the device's status shows keyframes
the host does not have and none arrived for ``stall_timeout_s``, or when the connection stays
silent (no status, no keyframe), it says hello again.
"""

from __future__ import annotations

import logging
import threading
import time
from typing import TYPE_CHECKING, Callable

from stereopath.device.errors import ConfigError
from stereopath.device.wire.protocol import POSE_LIMITS, Ack, Hello, Status, encode_ack, encode_hello
from stereopath.device.wire.sockets import CurveKeys, open_socket, zmtp_greeting
from stereopath.host.live.receiver_config import HEARTBEAT_TTL_MS, MAX_KEYFRAME_BYTES, ReceiverConfig
from stereopath.host.live.receiver_stats import LinkCounters
from stereopath.host.live.store import KeyframeStore

if TYPE_CHECKING:
    import zmq

log = logging.getLogger("stereopath.host.live.receiver")  # one logger for the receiver's lines
PROBE_INTERVAL_S = 30.0  # between probes of an endpoint whose handshakes keep failing
RECOVERY_HELLO_MIN_S = 1.0  # seconds between hellos asking for refused keyframes once storing works again


class Link:
    """The connection to one device: sockets, handshake and probe state, hellos; counts into ``counters``.

    ``store`` says what the host holds (for hellos and the stall check); ``on_storage_failed(what,
    exc)`` is called when reading it fails.  The polling thread drives the link; :attr:`sub` is read
    by the receiver's pose thread, and the handshake probe thread reads :attr:`config` and notes what it
    said.  ``counters`` is shared with the receiver: each field has one writer (the link its own
    counts, the receiver ``poses_unsaved`` and ``store_failures`` under its lock).
    """

    def __init__(self, config: ReceiverConfig, curve: CurveKeys | None, store: KeyframeStore,
                 counters: LinkCounters, on_storage_failed: Callable[[str, OSError], None]) -> None:
        import zmq

        self._zmq = zmq
        self.config = config
        self.store = store
        self.counters = counters
        self._on_storage_failed = on_storage_failed
        self.connected = False
        self._hello_pending = False
        self._hello_after: float | None = None  # a hello due then (storing works again after a refusal)
        self._last_progress = time.monotonic()
        self._auth_warned = False
        self._silent_warned = False
        self._probe_next = 0.0  # when a failed handshake may be probed again
        self._probe_said = ""   # the last reason logged
        self._refused_since_hello = False  # a keyframe went unacknowledged: a later hello has it resent
        self._last_dealer_rx = self._last_hello_at = time.monotonic()
        self._ctx = zmq.Context()
        t = config.sockets
        common = dict(heartbeat_ivl_ms=t.heartbeat_ivl_ms, heartbeat_timeout_ms=t.heartbeat_timeout_ms,
                      heartbeat_ttl_ms=HEARTBEAT_TTL_MS, reconnect_ivl_ms=t.reconnect_ivl_ms,
                      reconnect_ivl_max_ms=t.reconnect_ivl_max_ms)
        self.sub: zmq.Socket = open_socket(self._ctx, zmq.SUB, curve, options={zmq.CONFLATE: 1},
                                           maxmsgsize=max(4096, 4 * POSE_LIMITS.max_message_bytes), **common)
        self.sub.setsockopt(zmq.SUBSCRIBE, b"")
        hwm = 4 * config.window + 64
        self.dealer: zmq.Socket = open_socket(self._ctx, zmq.DEALER, curve,
                                              options={zmq.IMMEDIATE: 1, zmq.RCVHWM: hwm, zmq.SNDHWM: hwm},
                                              maxmsgsize=MAX_KEYFRAME_BYTES, **common)
        self._monitor: zmq.Socket = self.dealer.get_monitor_socket(
            zmq.EVENT_HANDSHAKE_SUCCEEDED | zmq.EVENT_DISCONNECTED | zmq.EVENT_HANDSHAKE_FAILED_AUTH
            | zmq.EVENT_HANDSHAKE_FAILED_NO_DETAIL | zmq.EVENT_HANDSHAKE_FAILED_PROTOCOL)
        try:
            self.sub.connect(config.pose_endpoint)
            self.dealer.connect(config.keyframe_endpoint)
        except zmq.ZMQError as exc:
            self.close()
            raise ConfigError(f"cannot connect to {config.pose_endpoint} / {config.keyframe_endpoint}: {exc}") from None
        self._poller = zmq.Poller()
        for s in (self.dealer, self._monitor):
            self._poller.register(s, zmq.POLLIN)

    def close(self) -> None:
        try:
            self.dealer.disable_monitor()
        except self._zmq.ZMQError:
            pass
        for s in (self._monitor, self.sub, self.dealer):
            s.close(linger=0)
        self._ctx.term()

    # ------------------------------------------------------------------ polling thread

    def wait(self, timeout_s: float) -> bool:
        """Wait up to ``timeout_s`` for the keyframe socket; handle the socket monitor's events.  True when
        the keyframe socket has messages to read."""
        events = dict(self._poller.poll(int(max(0.0, timeout_s) * 1000)))
        if self._monitor in events:
            self._handle_monitor()
        return self.dealer in events

    def heard(self, now: float) -> None:
        """Something arrived on the keyframe socket (keyframe, status or session)."""
        self._last_dealer_rx = now
        self._silent_warned = False

    def progress(self, now: float) -> None:
        """A keyframe was handled: the stall check starts over."""
        self._last_progress = now

    def refused(self) -> None:
        """A keyframe could not be stored: not acknowledged, so a later hello has the device resend it."""
        self._refused_since_hello = True

    def storing_again(self) -> None:
        """Storing works again after a refusal: hello soon, not after a stall (a run's end waits only
        stream.drain_s for hosts), but at most once per RECOVERY_HELLO_MIN_S: a keyframe that keeps failing
        must not have the device resend in a loop."""
        self._hello_after = max(time.monotonic(), self._last_hello_at + RECOVERY_HELLO_MIN_S)

    def ack(self, session_id: str, seq: int) -> None:
        """Acknowledge keyframe ``seq`` of ``session_id`` (one more credit)."""
        try:
            self.dealer.send(encode_ack(Ack(session_id, seq, 1)), self._zmq.NOBLOCK)
        except self._zmq.Again:
            self.counters.acks_unsent += 1  # not connected: the next hello resynchronises

    def hello_if_due(self, now: float) -> None:
        """Say hello after a handshake, a hello the socket would not take, or recovered storage."""
        if self._hello_pending or (self._hello_after is not None and now >= self._hello_after):
            self._hello_after = None
            self._send_hello()

    def check(self, now: float, status: Status | None) -> None:
        """The silence and stall checks; ``status``: the device's last status (None: none yet)."""
        self._check_silence(now)
        self._check_stall(now, status)

    def quality(self, now: float, last_rx: float | None, pose_window_ratio: float) -> str:
        """The link as the live view shows it; ``last_rx``: monotonic time of the last message of any kind."""
        age = None if last_rx is None else now - last_rx
        if self.counters.auth_failures and not self.connected:
            return "refused"
        if age is None:
            return "waiting"
        if age > 3.0 or not self.connected:
            return "lost"
        if age > 0.5 or pose_window_ratio < 0.9 or now - self._last_dealer_rx > self.config.stall_timeout_s:
            return "poor"  # (the last: poses flow but no status or keyframes on the keyframe link)
        return "good"

    # ------------------------------------------------------------------ internals

    def _handle_monitor(self) -> None:
        from zmq.utils.monitor import recv_monitor_message

        zmq = self._zmq
        while True:
            try:
                ev = recv_monitor_message(self._monitor, zmq.NOBLOCK)
            except zmq.Again:
                break
            e = ev["event"]
            if e == zmq.EVENT_HANDSHAKE_SUCCEEDED:
                self.counters.connects += 1
                self.connected = True
                log.info("connected to device %s", self.config.keyframe_endpoint)
                self._hello_pending = True
            elif e == zmq.EVENT_DISCONNECTED:
                if self.connected:
                    self.counters.disconnects += 1
                    log.info("disconnected from device; reconnecting")
                self.connected = False
            elif e == zmq.EVENT_HANDSHAKE_FAILED_AUTH:
                self.counters.auth_failures += 1
                if not self._auth_warned:
                    self._auth_warned = True
                    log.warning("device refused this host's key (is its public key in the device's clients dir?)")
            else:
                self.counters.handshake_failures += 1
                now = time.monotonic()
                if now >= self._probe_next:  # ask the endpoint itself what answers there (again while it fails)
                    self._probe_next = now + PROBE_INTERVAL_S
                    threading.Thread(target=self._explain_failed_handshake, name="stereopath-probe",
                                     daemon=True).start()

    def _explain_failed_handshake(self) -> None:
        """Log why the handshake failed, from the endpoint's ZMTP greeting; a reason is said once in a row."""
        endpoint = self.config.keyframe_endpoint
        answer = zmtp_greeting(endpoint)
        if answer == "zmtp:NULL" and not self.config.insecure:
            why = (f"handshake with {endpoint} failed: the device streams without CURVE (stream.insecure) and "
                   f"this host uses CURVE: CURVE on one side only")
        elif answer == "zmtp:CURVE" and self.config.insecure:
            why = (f"handshake with {endpoint} failed: the device requires CURVE and this host runs --insecure: "
                   f"CURVE on one side only")
        elif answer == "zmtp:CURVE":
            why = (f"the device at {endpoint} closed the CURVE handshake: the device public key this host uses "
                   f"is not that device's (check --device-key / the host's keys folder)")
        elif answer == "no greeting":
            why = (f"something at {endpoint} accepts connections but does not answer as a stereopath device (no "
                   f"ZeroMQ greeting): a port forwarder or SSH tunnel whose device is gone, or another program "
                   f"on that port; retrying")
        else:
            why = f"handshake with {endpoint} failed (the endpoint answers: {answer}); retrying"
        if why != self._probe_said:
            self._probe_said = why
            log.warning("%s", why)

    def _send_hello(self) -> None:
        sid, acked = self.store.hello_state()
        try:
            self.dealer.send(encode_hello(Hello(sid, acked, self.config.window)), self._zmq.NOBLOCK)
        except self._zmq.Again:
            self._hello_pending = True  # pipe not attached yet: retry on the next poll
            return
        self._hello_pending = False
        self._refused_since_hello = False
        self._last_hello_at = time.monotonic()
        self.counters.hellos += 1
        self._last_progress = time.monotonic()
        log.debug("hello: session %s, acked %d, window %d", sid, acked, self.config.window)

    def _check_silence(self, now: float) -> None:
        """Connected, yet neither status nor keyframes for a while: the device has lost track of this
        connection (or the stream died); say hello again instead of showing a good link forever."""
        if not self.connected or self._hello_pending:
            return
        quiet = now - max(self._last_dealer_rx, self._last_hello_at)
        if quiet < max(self.config.stall_timeout_s, 2.0 * self.config.sockets.heartbeat_ivl_ms / 1000.0):
            return
        self.counters.rehellos_silent += 1
        if not self._silent_warned:
            self._silent_warned = True
            log.warning("no status or keyframes from the device for %.1f s although connected: hello again", quiet)
        self._send_hello()

    def _check_stall(self, now: float, st: Status | None) -> None:
        if not self.connected or st is None or now - self._last_progress < self.config.stall_timeout_s:
            return
        try:
            have = self.store.session(st.session_id).acked_seq if st.session_id == self.store.last_session else -1
        except OSError as exc:
            self._on_storage_failed(f"session {st.session_id}", exc)
            self._last_progress = now
            return
        if st.keyframes_spooled - 1 > have:
            self.counters.rehellos_after_stall += 1
            log.info("keyframes stalled (device has %d, host holds up to %d): hello again",
                     st.keyframes_spooled, have)
            if st.session_id != self.store.last_session:
                self.store.set_last_session(st.session_id)
            self._send_hello()
        elif self._refused_since_hello:
            # a keyframe was not stored (e.g. an earlier session's, disk full) even if later ones were:
            # the device resends what no host acknowledged after a hello
            self.counters.rehellos_after_stall += 1
            self._send_hello()
        self._last_progress = now
