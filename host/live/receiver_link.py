"""The receiver's side of the keyframe link: handshakes, hellos, stall and silence checks, link quality.

Mixed into :class:`stereopath.host.live.receiver.Receiver` (which owns the sockets, the store and
the counters these methods use); split out so each module holds one responsibility.  On every
completed handshake (the DEALER's socket monitor reports it, so reconnects are noticed) the
receiver says ``hello(last session, highest contiguous seq, window)``; when the device's status
shows keyframes the receiver does not have and none arrived for ``stall_timeout_s``, or when the
connection stays silent (no status, no keyframe), it says hello again.
"""

from __future__ import annotations

import logging
import threading
import time
from typing import Any, Callable

from stereopath.device.wire.protocol import Hello, encode_hello
from stereopath.device.wire.sockets import zmtp_greeting

log = logging.getLogger("stereopath.host.live.receiver")  # one logger for the receiver's lines
PROBE_INTERVAL_S = 30.0  # between probes of an endpoint whose handshakes keep failing


class LinkControl:
    """Flow-control and link-state methods of the receiver (see the module doc)."""

    config: Any
    dealer: Any
    monitor: Any
    store: Any
    stats: Any
    live: Any
    lock: Any
    _zmq: Any
    _hello_pending: bool
    _auth_warned: bool
    _probe_next: float  # when a failed handshake may be probed again
    _probe_said: str    # the last reason logged
    _warned: set[str]
    _last_progress: float
    _last_hello_at: float
    _last_dealer_rx: float
    _pose_rate: Any
    _kf_rate: Any
    _pose_window: Any
    _storage_failed: Callable[[str, OSError], None]
    storage_error: str | None
    _refused_since_hello: bool

    def _handle_monitor(self) -> None:
        from zmq.utils.monitor import recv_monitor_message

        zmq = self._zmq
        while True:
            try:
                ev = recv_monitor_message(self.monitor, zmq.NOBLOCK)
            except zmq.Again:
                break
            e = ev["event"]
            if e == zmq.EVENT_HANDSHAKE_SUCCEEDED:
                self.stats.link["connects"] += 1
                self.live.connected = True
                log.info("connected to device %s", self.config.keyframe_endpoint)
                self._hello_pending = True
            elif e == zmq.EVENT_DISCONNECTED:
                if self.live.connected:
                    self.stats.link["disconnects"] += 1
                    log.info("disconnected from device; reconnecting")
                self.live.connected = False
            elif e == zmq.EVENT_HANDSHAKE_FAILED_AUTH:
                self.stats.link["auth_failures"] += 1
                if not self._auth_warned:
                    self._auth_warned = True
                    log.warning("device refused this host's key (is its public key in the device's clients dir?)")
            else:
                self.stats.link["handshake_failures"] += 1
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
        self.stats.link["hellos"] += 1
        self._last_progress = time.monotonic()
        log.debug("hello: session %s, acked %d, window %d", sid, acked, self.config.window)

    def _check_silence(self, now: float) -> None:
        """Connected, yet neither status nor keyframes for a while: the device has lost track of this
        connection (or the stream died); say hello again instead of showing a good link forever."""
        if not self.live.connected or self._hello_pending:
            return
        quiet = now - max(self._last_dealer_rx, self._last_hello_at)
        if quiet < max(self.config.stall_timeout_s, 2.0 * self.config.heartbeat_ivl_ms / 1000.0):
            return
        self.stats.link["rehellos_silent"] += 1
        if "silent" not in self._warned:
            self._warned.add("silent")
            log.warning("no status or keyframes from the device for %.1f s although connected: hello again", quiet)
        self.live.link_quality = "lost"
        self._send_hello()

    def _check_stall(self, now: float) -> None:
        self._check_silence(now)
        st = self.live.status
        if not self.live.connected or st is None or now - self._last_progress < self.config.stall_timeout_s:
            return
        try:
            have = self.store.session(st.session_id).acked_seq if st.session_id == self.store.last_session else -1
        except OSError as exc:
            self._storage_failed(f"session {st.session_id}", exc)
            self._last_progress = now
            return
        if st.keyframes_spooled - 1 > have:
            self.stats.link["rehellos_after_stall"] += 1
            log.info("keyframes stalled (device has %d, host holds up to %d): hello again",
                     st.keyframes_spooled, have)
            if st.session_id != self.store.last_session:
                self.store.set_last_session(st.session_id)
            self._send_hello()
        elif self._refused_since_hello:
            # a keyframe was not stored (e.g. an earlier session's, disk full) even if later ones were:
            # the device resends what no host acknowledged after a hello
            self.stats.link["rehellos_after_stall"] += 1
            self._send_hello()
        self._last_progress = now

    def _update_live(self, now: float) -> None:
        with self.lock:
            self._update_live_locked(now)

    def _update_live_locked(self, now: float) -> None:
        live = self.live
        live.pose_rate_hz = self._pose_rate.rate(now)
        live.keyframe_rate_hz = self._kf_rate.rate(now)
        w = self._pose_window
        while w and now - w[0][0] > 2.0:
            w.popleft()
        if len(w) >= 2:
            span = max(s for _, s in w) - min(s for _, s in w) + 1
            live.pose_window_ratio = min(1.0, len(w) / span)
        age = None if live.last_rx is None else now - live.last_rx
        if self.stats.link["auth_failures"] and not live.connected:
            live.link_quality = "refused"
        elif age is None:
            live.link_quality = "waiting"
        elif age > 3.0 or not live.connected:
            live.link_quality = "lost"
        elif age > 0.5 or live.pose_window_ratio < 0.9 or now - self._last_dealer_rx > self.config.stall_timeout_s:
            live.link_quality = "poor"  # (the last: poses flow but no status or keyframes on the keyframe link)
        else:
            live.link_quality = "good"
