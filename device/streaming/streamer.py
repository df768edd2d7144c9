"""The device's streaming stage: capture and estimation hand data over, never wait on the network.

:class:`DeviceStreamer` owns a ZeroMQ context, the ZAP authenticator, the pose PUB socket and the
keyframe ROUTER socket, and two threads:

* the **I/O thread** owns the keyframe socket: it answers hosts (hello, ack, credit), sends
  spooled keyframes as credit allows, and sends the status heartbeat;
* the **spool writer** encodes offered keyframes (``cv2.imencode``), writes each atomically
  to the spool, and only then makes it available to the I/O thread.

The producer-facing calls never block and never raise because of the network:
:meth:`publish_pose` hands the encoded pose to ZeroMQ with a non-blocking send (ZeroMQ's own
I/O thread encrypts and transmits it; a subscriber that cannot keep up loses poses, the PUB
pattern's "latest wins"); :meth:`offer_keyframe` and :meth:`publish_status` append to bounded
queues and wake the I/O thread through a pipe.  When the keyframe queue is full the offered
keyframe is refused (``False``) and counted.

Example::

    spool = KeyframeSpool(session_dir / "keyframes")
    with DeviceStreamer(cfg.stream, spool, session_id, rig=rig, keys=cfg.keys) as streamer:
        streamer.publish_pose(seq, t_ns, T_world_cam, tracking="ok", inliers=120)
        streamer.offer_keyframe(seq, t_ns, T_world_cam, left, right)
        streamer.publish_status(frame_rate_hz=20.0, imu_rate_hz=200.0, recorder_state="recording")
"""

from __future__ import annotations

import logging
import os
import queue
import threading
import time
import dataclasses
from pathlib import Path
from typing import TYPE_CHECKING, Any, Sequence

import numpy as np

from stereopath.device.errors import ConfigError, DatasetError, ProtocolError
from stereopath.device.wire.protocol import HEALTH_FIELDS, DeviceHealth, SessionInfo, Status, check_session_id, encode_keyframe, \
    decode_session, encode_pose, encode_rebase, encode_session, encode_status, make_keyframe, make_rebase, make_session_info, \
    pose_from_matrix, rig_reference
from stereopath.device.streaming.backlog import Backlog, find_backlog, write_marker
from stereopath.device.streaming import health
from stereopath.device.settings import KeySettings, StreamSettings
from stereopath.device.streaming.keyframe_server import KeyframeServer
from stereopath.device.streaming.pose_publisher import PosePublisher
from stereopath.device.wire.security import load_secret_keypair, start_authenticator
from stereopath.device.wire.sockets import CurveKeys, secure_channel
from stereopath.device.streaming.spool import KeyframeSpool

if TYPE_CHECKING:
    from stereopath.device.core.rig import Rig

log = logging.getLogger(__name__)

UNKNOWN_RIG = ("unknown", "0000000000000000")


class DeviceStreamer:
    """Streams poses, keyframes and status to hosts; see the module docstring.

    ``rig`` (a :class:`stereopath.device.core.rig.Rig`) or ``rig_ref`` (``(name, hash)``) names the calibration
    sent with every keyframe; the rig itself goes to each host once per connection (the session
    message).  ``backlog_roots``: folders holding earlier sessions' spools, whose keyframes no host
    acknowledged are offered after this session's (:mod:`stereopath.device.streaming.backlog`).
    Bind errors and key problems raise :class:`ConfigError` here.
    """

    def __init__(self, config: StreamSettings, spool: KeyframeSpool, session_id: str, rig: Rig | None = None,
                 rig_ref: tuple[str, str] | None = None, *, keys: KeySettings | None = None,
                 status_interval_s: float = 1.0, backlog_roots: Sequence[str | Path] = ()) -> None:
        import zmq

        self.config = config
        self.status_interval_s = status_interval_s
        self.spool = spool
        try:
            self.session_id = check_session_id(session_id)
        except ProtocolError as exc:
            raise ConfigError(f"streaming: {exc}") from None
        self.rig_ref = rig_ref or (rig_reference(rig) if rig is not None else UNKNOWN_RIG)
        self._session_info = self._checked_session_info(rig)
        self._zmq = zmq
        self.backlog = self._open_backlog(backlog_roots)

        def server_keys() -> CurveKeys:
            if keys is None:
                raise ConfigError("streaming with CURVE needs the [keys] section (or stream.insecure on loopback)")
            return CurveKeys(*load_secret_keypair(keys.server_secret))

        curve_keys = secure_channel(config.insecure, (config.pose_endpoint, config.keyframe_endpoint), server_keys,
                                    "streaming")
        self._ctx = zmq.Context()
        self._auth = None
        self._pub: PosePublisher | None = None
        self._server: KeyframeServer | None = None
        try:
            if curve_keys is not None and keys is not None:
                self._auth = start_authenticator(self._ctx, keys.clients_dir)
            self._pub = PosePublisher(self._ctx, config, curve_keys)
            self._server = KeyframeServer(self._ctx, config, spool, self.session_id, curve_keys, self._status_bytes,
                                          self._session_bytes, self.backlog)
        except zmq.ZMQError as exc:
            self._teardown()
            raise ConfigError(f"cannot bind streaming endpoints ({config.pose_endpoint}, "
                              f"{config.keyframe_endpoint}): {exc}") from None
        except BaseException:
            self._teardown()
            raise
        self._lock = threading.Lock()
        self._keyframes: queue.Queue[Any] = queue.Queue(maxsize=config.bounds.max_pending_keyframes)
        self._health = DeviceHealth()
        self._status_due = threading.Event()
        self._stop = threading.Event()
        self._wake_r, self._wake_w = os.pipe()
        os.set_blocking(self._wake_r, False)
        os.set_blocking(self._wake_w, False)
        self._counters: dict[str, Any] = {
            "poses_offered": 0, "keyframes_offered": 0, "keyframes_refused": 0,
            "keyframes_spooled": 0, "keyframes_failed": 0, "max_keyframe_queue": 0,
            "max_call_s": 0.0, "io_thread_cpu_s": 0.0, "writer_thread_cpu_s": 0.0, "status_built": 0,
        }
        self._rebase: bytes | None = None  # the session's world rebase, sent with every status from then on
        self._closed = False
        self._writer = threading.Thread(target=self._writer_loop, name="stereopath-spool", daemon=True)
        self._io = threading.Thread(target=self._io_loop, name="stereopath-stream-io", daemon=True)
        self._writer.start()
        self._io.start()
        log.info("streaming session %s: poses on %s, keyframes on %s (%s), spool %s", self.session_id,
                 self.pose_endpoint, self.keyframe_endpoint, "insecure" if config.insecure else "CURVE",
                 spool.dir)

    # ------------------------------------------------------------------ producer side (never blocks)

    @property
    def pose_endpoint(self) -> str:
        """The bound pose endpoint (with the real port when a wildcard port was configured)."""
        return self._pub.endpoint if self._pub else ""

    @property
    def keyframe_endpoint(self) -> str:
        return self._server.endpoint if self._server else ""

    def publish_pose(self, seq: int, t_ns: int, T_world_cam: np.ndarray, tracking: str = "ok", inliers: int = 0,
                     keyframe: bool = False) -> bool:
        """Publish a live pose (lossy, latest wins); False if ZeroMQ dropped it.

        Raises :class:`ProtocolError` only for invalid input (non-finite pose, bad tracking state).
        """
        t0 = time.perf_counter()
        data = encode_pose(pose_from_matrix(self.session_id, seq, t_ns, T_world_cam, tracking, inliers, keyframe))
        sent = self._pub.send(data) if self._pub is not None else False
        with self._lock:
            self._counters["poses_offered"] += 1
        self._note_call(t0)
        return sent

    def offer_keyframe(self, frame_seq: int, t_ns: int, T_world_cam: np.ndarray, left: np.ndarray,
                       right: np.ndarray) -> bool:
        """Queue a keyframe for encoding, spooling and sending; False (and counted) if the queue is full.

        The images are copied, so the caller may reuse its buffers at once.
        """
        t0 = time.perf_counter()
        if self._closed:
            log.warning("keyframe of frame %d offered after close(): refused", frame_seq)
            return False
        T = np.array(T_world_cam, dtype=float)
        item = (int(frame_seq), int(t_ns), T, np.array(left, copy=True), np.array(right, copy=True))
        try:
            self._keyframes.put_nowait(item)
            accepted = True
        except queue.Full:
            accepted = False
        with self._lock:
            c = self._counters
            c["keyframes_offered"] += 1
            c["keyframes_refused"] += int(not accepted)
            c["max_keyframe_queue"] = max(c["max_keyframe_queue"], self._keyframes.qsize())
        if not accepted:
            log.warning("keyframe of frame %d refused: %d keyframes already wait for the spool writer",
                        frame_seq, self.config.bounds.max_pending_keyframes)
        self._note_call(t0)
        return accepted

    def publish_status(self, **health: object) -> None:
        """Update device health fields (keyword names from :class:`DeviceHealth`) and send a status soon.

        ``None`` leaves a field as it was.  The status is also sent every ``status_interval_s`` with
        the latest values; CPU load, temperature and free disk are probed when never given.
        """
        t0 = time.perf_counter()
        unknown = set(health) - set(HEALTH_FIELDS)
        if unknown:
            raise TypeError(f"publish_status: unknown health field(s) {sorted(unknown)}; known: {HEALTH_FIELDS}")
        changes = {k: v for k, v in health.items() if v is not None}
        with self._lock:
            self._health = dataclasses.replace(self._health, **changes)
        self._status_due.set()
        self._wake()
        self._note_call(t0)

    def publish_rebase(self, from_t_ns: int, T_new_old: np.ndarray) -> None:
        """The estimator redefined the session's world: the poses and keyframes timed before ``from_t_ns``
        were sent in the earlier one, ``T_new_old`` maps them.  Sent at once and with every status after
        (a host that connects later gets it too; hosts apply it once).

        Raises :class:`ProtocolError` for a motion that is not a finite rigid 4x4 matrix."""
        data = encode_rebase(make_rebase(self.session_id, from_t_ns, T_new_old))
        with self._lock:
            self._rebase = data
        self._status_due.set()
        self._wake()

    def stats(self) -> dict[str, Any]:
        """A snapshot of counters (queues, drops, keyframes sent/resent, rejected control messages, hosts)."""
        with self._lock:
            out = dict(self._counters)
        out["pending_keyframes"] = self._keyframes.qsize()
        out["spool_count"] = self.spool.count
        out["spool_disk_full"] = self.spool.disk_full
        out["keyframes_in_memory"] = self.spool.memory_count
        out["keyframes_in_memory_unacked"] = self.spool.memory_unacked_count
        out["keyframes_held_in_memory"] = self.spool.held_in_memory
        out["keyframes_acked"] = self.spool.acked_seq + 1
        out.update(self.backlog.summary())
        if self._pub is not None:
            out["poses_sent"] = self._pub.sent
            out["poses_dropped_send"] = self._pub.dropped
            out["pose_subscriptions"] = self._pub.subscriptions()
        if self._server is not None:
            out.update(self._server.stats)
            out["control_rejected_by_reason"] = dict(self._server.rejected)
            out["peers"] = self._server.peers()
        return out

    def wait_spooled(self, count: int, timeout_s: float) -> bool:
        """Wait until at least ``count`` keyframes are on disk (for tests and shutdown)."""
        deadline = time.monotonic() + timeout_s
        while self.spool.count < count:
            if time.monotonic() > deadline:
                return False
            time.sleep(0.005)
        return True

    def close(self, timeout_s: float = 10.0) -> None:
        """Spool the keyframes still queued, stop both threads, close the sockets (the keyframe socket
        at once, the pose socket after at most ``pose_flush_ms`` for the last poses)."""
        if self._closed:
            return
        self._closed = True
        try:
            self._keyframes.put(None, timeout=timeout_s)
        except queue.Full:
            log.error("spool writer stuck: %d keyframes not spooled", self._keyframes.qsize())
        self._writer.join(timeout_s)
        self._stop.set()
        self._wake()
        self._io.join(timeout_s)
        self._teardown()
        os.close(self._wake_r)
        os.close(self._wake_w)
        log.info("streaming session %s closed: %s", self.session_id,
                 {k: v for k, v in self.stats().items() if k not in ("peers", "control_rejected_by_reason")})

    def __enter__(self) -> "DeviceStreamer":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ internals

    def _open_backlog(self, roots: Sequence[str | Path]) -> Backlog:
        """Mark this spool as this session's and find earlier sessions' undelivered keyframes."""
        try:
            write_marker(self.spool.dir, encode_session(self._session_info))
        except (OSError, ProtocolError) as exc:  # a later run cannot offer this session's keyframes again
            log.error("cannot write the session marker of spool %s: %s; if this run dies, its undelivered "
                      "keyframes stay on the device", self.spool.dir, exc)
        backlog = Backlog(find_backlog(roots, self.spool.dir) if roots else [])
        if backlog.sessions:
            log.warning("%d earlier session(s) left %d keyframe(s) no host acknowledged (%s): offered to hosts "
                        "after this session's", len(backlog.sessions), backlog.pending,
                        ", ".join(b.session_id for b in backlog.sessions[:5]) +
                        (", ..." if len(backlog.sessions) > 5 else ""))
        return backlog

    def _checked_session_info(self, rig: Rig | None) -> SessionInfo:
        """The session message, decodable by a host (else sent without the rig, with a warning)."""
        info = make_session_info(self.session_id, rig, self.rig_ref)
        try:
            decode_session(encode_session(info))
        except ProtocolError as exc:
            log.warning("the rig cannot be sent to hosts (%s): they need --rig to map this session", exc)
            info = dataclasses.replace(info, rig=None)
        return info

    def _session_bytes(self) -> bytes:
        return encode_session(dataclasses.replace(self._session_info, keyframes=self.spool.count))

    def _note_call(self, t0: float) -> None:
        dt = time.perf_counter() - t0
        if dt > self._counters["max_call_s"]:
            self._counters["max_call_s"] = dt

    def _wake(self) -> None:
        try:
            os.write(self._wake_w, b"\0")
        except (BlockingIOError, OSError):
            pass  # pipe full: the I/O thread is already due to wake up

    def _teardown(self) -> None:
        if self._server is not None:
            self._server.close()
        if self._pub is not None:  # the last poses of the run still reach a connected host
            self._pub.close(flush_ms=self.config.bounds.pose_flush_ms)
        if self._auth is not None:
            self._auth.stop()
        self._ctx.term()

    def _status_bytes(self) -> bytes:
        with self._lock:
            h = self._health
        pub = self._pub
        probed = dataclasses.replace(
            h, cpu_load_pct=h.cpu_load_pct if h.cpu_load_pct is not None else health.cpu_load_pct(),
            temperature_c=h.temperature_c if h.temperature_c is not None else health.cpu_temperature_c(),
            disk_free_bytes=h.disk_free_bytes if h.disk_free_bytes is not None else
            health.disk_free_bytes(self.spool.dir))
        status = Status(
            self.session_id, time.monotonic_ns(), **dataclasses.asdict(probed),
            poses_sent=pub.sent if pub else 0,
            poses_dropped=pub.dropped if pub else 0,
            keyframes_spooled=self.spool.count, keyframes_pending=self._keyframes.qsize(),
        )
        self._counters["status_built"] += 1
        try:
            return encode_status(status)
        except ProtocolError as exc:  # a bad health value must not stop the stream
            log.warning("status not encodable (%s); sending defaults", exc)
            return encode_status(Status(self.session_id, time.monotonic_ns(), keyframes_spooled=self.spool.count))

    def _writer_loop(self) -> None:
        cfg = self.config
        while True:
            item = self._keyframes.get()
            if item is None:
                break
            frame_seq, t_ns, T, left, right = item
            seq = self.spool.count
            try:
                kf = make_keyframe(self.session_id, seq, frame_seq, t_ns, T, (left, right), self.rig_ref, cfg.images)
                self.spool.append(seq, encode_keyframe(kf))
            except (ProtocolError, DatasetError, OSError) as exc:
                log.error("keyframe of frame %d not spooled: %s", frame_seq, exc)
                with self._lock:
                    self._counters["keyframes_failed"] += 1
                continue
            with self._lock:
                self._counters["keyframes_spooled"] += 1
                self._counters["writer_thread_cpu_s"] = time.thread_time()
            self._wake()

    def _io_loop(self) -> None:
        zmq = self._zmq
        server = self._server
        if server is None:  # constructed in __init__; cannot happen
            raise ConfigError("streamer sockets missing")
        poller = zmq.Poller()
        poller.register(server.sock, zmq.POLLIN)
        poller.register(self._wake_r, zmq.POLLIN)
        interval = self.status_interval_s
        next_status = time.monotonic()
        blocked = False
        try:
            while not self._stop.is_set():
                now = time.monotonic()
                timeout_ms = 5 if blocked else max(0, min(200, int((next_status - now) * 1000)))
                events = dict(poller.poll(timeout_ms))
                if self._wake_r in events:
                    try:
                        while os.read(self._wake_r, 4096):
                            pass
                    except BlockingIOError:
                        pass
                if server.sock in events:
                    server.handle_incoming()
                blocked = server.pump()
                now = time.monotonic()
                if now >= next_status or self._status_due.is_set():
                    self._status_due.clear()
                    server.broadcast_status(self._status_bytes())
                    with self._lock:
                        rebase = self._rebase
                    if rebase is not None:
                        server.broadcast_status(rebase)
                    next_status = now + interval
                self._counters["io_thread_cpu_s"] = time.thread_time()
        except Exception:  # a bug here must not pass silently: log it, the producer side stays non-blocking
            log.exception("streaming I/O thread failed")
            raise
