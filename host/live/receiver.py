"""The host's receiving end: live poses (SUB), keyframes and status (DEALER), stored per session.

:class:`Receiver` connects to a device (CURVE by default; plain TCP only to loopback), and for
each device session id it sees keeps a folder ``OUT/<session>/`` with

* ``poses.tum``  every received pose, appended and flushed as it arrives;
* ``keyframes/`` every keyframe exactly once (see :mod:`stereopath.host.live.store`);
* ``rig.yaml`` and ``session.json``: the device's rig and keyframe count, from its ``session``
  message (see :mod:`stereopath.host.live.receiver_sessions`);
* ``world_rebase.json`` when the device's estimator redefined its world during the session (a start
  in motion): the poses held (``poses.tum``, the live pose, later arrivals) are mapped into the new
  world once; the keyframes keep the poses they came with and that file maps them
  (see :mod:`stereopath.host.live.world_rebase`).  Keyframes of an earlier session
  the device still held (it was killed before a host had them) arrive after the live ones and
  are stored under their own session id; incomplete sessions are logged at start and at the end.

``OUT/receiver.json`` counts messages received, keyframe duplicates, gaps in the pose seq and
rejected messages by reason (totals over restarts of the receiver).

Keyframe flow control (see :mod:`stereopath.device.streaming.keyframe_server`): the receiver's
:class:`~stereopath.host.live.receiver_link.Link` owns the sockets; on every completed handshake
(a socket monitor reports it, so reconnects are noticed) it says ``hello(last session, highest
contiguous seq, window)``; the receiver acknowledges each keyframe after storing it, granting one
more credit; if the device's status shows keyframes the receiver does not have and none arrived
for ``stall_timeout_s``, the link says hello again.

Poses are received on their own thread (they never wait behind a keyframe being written to
disk); keyframes, status and the flow control run in :meth:`Receiver.poll`.  Callbacks
``on_pose`` run on the pose thread, ``on_keyframe``/``on_status`` on the polling thread.

Everything received is decoded as untrusted input; a rejected message is counted and dropped,
and the receiver carries on.
"""

from __future__ import annotations

import collections
import json
import logging
import math
import threading
import time
from pathlib import Path
from types import TracebackType
from typing import TYPE_CHECKING, Callable, TextIO

from stereopath.device.errors import ConfigError, StereopathError
from stereopath.device.wire.protocol import KEYFRAME_LIMITS, POSE_LIMITS, SESSION_LIMITS, DecodeError, \
    Keyframe, Limits, Pose, SessionInfo, Status, WorldRebase, decode_message
from stereopath.device.wire.security import load_host_keys
from stereopath.device.wire.sockets import CurveKeys, secure_channel
from stereopath.device.formats.tum import ns_to_seconds_str
from stereopath.device.formats.fileio import cut_torn_tail, write_json_atomic
from stereopath.host.live.receiver_config import MAX_KEYFRAME_BYTES, RECEIVER_JSON, ReceiverConfig
from stereopath.host.live.receiver_link import Link
from stereopath.host.live.receiver_sessions import SessionCatalog, describe_incomplete
from stereopath.host.live.receiver_stats import EventRate, LiveState, ReceiverStats, SessionStats
from stereopath.host.live.store import STATE_NAME, KeyframeStore, list_sessions
from stereopath.host.live.world_rebase import SessionRebases, read_rebases, record, rewrite_tum

if TYPE_CHECKING:
    import zmq

log = logging.getLogger(__name__)

__all__ = ["HOST_FILES", "Receiver", "ReceiverConfig", "session_name_clash"]
HOST_FILES = (RECEIVER_JSON, STATE_NAME)  # what the host itself keeps in OUT beside the session folders


def session_name_clash(out: Path, sid: str) -> str:
    """Why ``OUT/<sid>`` cannot be a session folder ('' when it can): the name of one of the host's own
    files, or of something in OUT that is not a folder (a user's file)."""
    path = out / sid
    if sid.casefold() in HOST_FILES:  # (case-insensitive file systems too)
        return f"its folder would be the host's own file {path}"
    try:
        if path.exists() and not path.is_dir():
            return f"{path} exists and is not a session folder"
    except OSError as exc:
        return f"{path}: {exc.strerror or exc}"
    return ""


class Receiver:
    """Receives from one device into ``out_dir``; drive it with :meth:`poll` or :meth:`run`."""

    def __init__(self, config: ReceiverConfig, out_dir: str | Path,
                 on_pose: Callable[[Pose], None] | None = None,
                 on_keyframe: Callable[[Keyframe, bool], None] | None = None,
                 on_status: Callable[[Status], None] | None = None,
                 on_rebase: Callable[[WorldRebase], None] | None = None) -> None:
        import zmq

        self._zmq = zmq
        self.config = config
        self.out = Path(out_dir)
        self.on_pose, self.on_keyframe, self.on_status = on_pose, on_keyframe, on_status
        self.on_rebase = on_rebase
        self.rebases = SessionRebases()
        self._tum_lock = threading.Lock()  # a pose's mapping and append against a rebase's rewrite of the file
        curve = secure_channel(config.insecure, (config.pose_endpoint, config.keyframe_endpoint),
                               lambda: CurveKeys(*load_host_keys(config.keys_dir or "", config.device_key)),
                               "receiving")
        self.out.mkdir(parents=True, exist_ok=True)
        self.stats = self._load_stats()
        self.stats.runs += 1
        self.store = KeyframeStore(self.out, fsync=config.fsync)
        self.live = LiveState(session_id=self.store.last_session)
        self.sessions = SessionCatalog(self.out, fsync=config.fsync)
        self.device_session: str | None = None  # the device's live session (from its status / session message)
        self._kf_limits = Limits(max_message_bytes=MAX_KEYFRAME_BYTES,
                                 max_bin_len=min(KEYFRAME_LIMITS.max_bin_len, MAX_KEYFRAME_BYTES),
                                 max_array_len=SESSION_LIMITS.max_array_len, max_str_len=SESSION_LIMITS.max_str_len)
        for line in describe_incomplete(self.out):
            log.warning("incomplete session in %s: %s", self.out, line)
        self._tum: dict[str, TextIO] = {}
        self._pose_rate, self._kf_rate = EventRate(), EventRate()
        self._pose_window: collections.deque[tuple[float, int]] = collections.deque(maxlen=4096)
        self._next_stats = time.monotonic()
        self._warned: set[str] = set()
        self._known_sessions: set[str] = {s for s in list_sessions(self.out) if not session_name_clash(self.out, s)}
        self._refused_sessions: dict[str, str] = {}  # session ids whose folder cannot be made, and why (bounded)
        self.storage_error: str | None = None  # set while keyframes cannot be stored (disk full)
        self._new_sessions = 0
        self.lock = threading.RLock()  # hold it to read stats/live consistently (the pose thread writes them)
        try:
            self.link = Link(config, curve, self.store, self.stats.link, self._storage_failed)
        except ConfigError:
            self.store.close()
            raise
        self._closed = False
        self._stop = threading.Event()
        self._pose_thread = threading.Thread(target=self._pose_loop, name="stereopath-poses", daemon=True)
        self._pose_thread.start()
        log.info("receiving from %s (poses) and %s (keyframes), %s, into %s", config.pose_endpoint,
                 config.keyframe_endpoint, "insecure" if config.insecure else "CURVE", self.out)

    # ------------------------------------------------------------------ main loop

    def poll(self, timeout_s: float = 0.1) -> int:
        """Wait up to ``timeout_s`` for traffic and handle everything available; returns messages handled."""
        n = 0
        readable = self.link.wait(timeout_s)
        self.live.connected = self.link.connected
        if readable:
            n += self._drain(self.link.dealer, "keyframe", 64)
        now = time.monotonic()
        self.link.hello_if_due(now)
        self.link.check(now, self.live.status)
        self._update_live(now)
        if now >= self._next_stats:
            self.write_stats()
            self._next_stats = now + self.config.stats_interval_s
        return n

    def run(self, duration_s: float | None = None, stop: threading.Event | None = None,
            on_tick: Callable[["Receiver"], None] | None = None, tick_s: float = 0.25) -> None:
        """Poll until ``duration_s`` elapsed or ``stop`` is set, calling ``on_tick`` every ``tick_s``."""
        t_end = None if duration_s is None else time.monotonic() + duration_s
        next_tick = time.monotonic() + tick_s
        while not (stop is not None and stop.is_set()):
            now = time.monotonic()
            if t_end is not None and now >= t_end:
                break
            wait = min(tick_s, max(0.0, next_tick - now))
            if t_end is not None:
                wait = min(wait, t_end - now)
            self.poll(wait)
            if on_tick is not None and time.monotonic() >= next_tick:
                on_tick(self)
                next_tick = time.monotonic() + tick_s

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        self._stop.set()
        self._pose_thread.join(5.0)
        self.write_stats()
        for fh in self._tum.values():
            try:
                fh.close()
            except OSError as exc:
                log.error("closing a poses.tum: %s", exc.strerror or exc)
        self._tum.clear()
        self.store.close()
        for line in describe_incomplete(self.out):
            log.warning("incomplete session: %s", line)
        self.link.close()

    def __enter__(self) -> "Receiver":
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()

    # ------------------------------------------------------------------ handlers

    def _pose_loop(self) -> None:
        zmq = self._zmq
        poller = zmq.Poller()
        poller.register(self.link.sub, zmq.POLLIN)
        try:
            while not self._stop.is_set():
                if poller.poll(100):
                    self._drain(self.link.sub, "pose", 256)
        except Exception:  # a bug must not pass silently
            log.exception("pose receiver thread failed")
            raise

    def _drain(self, sock: zmq.Socket, channel: str, limit: int) -> int:
        zmq = self._zmq
        n = 0
        while n < limit:
            try:
                frames = sock.recv_multipart(zmq.NOBLOCK)
            except zmq.Again:
                break
            n += 1
            self.live.last_rx = time.monotonic()
            if channel == "keyframe":
                self.link.heard(time.monotonic())
            if len(frames) != 1:
                self._reject(channel, "frames")
                continue
            try:
                if channel == "pose":
                    msg = decode_message(frames[0], POSE_LIMITS, ("pose",))
                else:
                    msg = decode_message(frames[0], self._kf_limits, ("keyframe", "status", "session", "rebase"))
            except DecodeError as exc:
                self._reject(channel, exc.reason, str(exc))
                continue
            refused = self._admit_session(msg.session_id)
            if refused:
                self._reject(channel, *refused)
                continue
            if isinstance(msg, Pose):
                self._handle_pose(msg)
            elif isinstance(msg, Keyframe):
                self._handle_keyframe(msg, frames[0])
            elif isinstance(msg, Status):
                self._handle_status(msg)
            elif isinstance(msg, SessionInfo):
                self._handle_session(msg)
            elif isinstance(msg, WorldRebase):
                self._handle_rebase(msg)
        return n

    def _admit_session(self, sid: str) -> tuple[str, str] | None:
        """None for a session whose messages are taken, else ``(reason, message)`` for the rejection.

        Known sessions always; a new one only while this run has accepted fewer than the limit (a
        device starts one session per run, so a flood of new ids from a client holding the device
        key cannot fill the disk with folders), and only when its folder ``OUT/<session>`` can be
        one: never the name of the host's own files, nor of anything in OUT that is not a folder.
        """
        with self.lock:
            if sid in self._known_sessions:
                return None
            refused = self._refused_sessions.get(sid)
            if refused is not None:
                return "session_id", refused
            if self._new_sessions >= self.config.max_new_sessions:
                return "session_limit", (f"session {sid!r}: over the limit of {self.config.max_new_sessions} "
                                         f"new sessions in this run")
            clash = session_name_clash(self.out, sid)
            if clash:
                if len(self._refused_sessions) >= 64:
                    self._refused_sessions.pop(next(iter(self._refused_sessions)))
                refused = self._refused_sessions[sid] = f"device session {sid!r} not stored: {clash}"
                return "session_id", refused
            self._new_sessions += 1
            self._known_sessions.add(sid)
            return None

    def _reject(self, channel: str, reason: str, detail: str = "") -> None:
        with self.lock:
            st = self.stats
            st.rejected_by_reason[reason] = st.rejected_by_reason.get(reason, 0) + 1
            st.rejected_by_channel[channel] = st.rejected_by_channel.get(channel, 0) + 1
            tag = f"{reason}:{detail}" if reason == "session_id" else reason  # once per clashing id
            warn = reason in ("version", "session_limit", "session_id") and tag not in self._warned
            if warn:
                self._warned.add(tag)
        if warn:
            log.warning("%s", detail)
        else:
            log.debug("rejected %s message (%s): %s", channel, reason, detail[:200])

    def _session(self, sid: str, live: bool = True) -> SessionStats:
        """The counters of ``sid``; ``live``: it is the device's current session (shown in the live view)."""
        s = self.stats.sessions.get(sid)
        if s is None:
            s = self.stats.sessions[sid] = SessionStats()
        if live and sid != self.live.session_id:
            log.info("device session %s (previous: %s): stored apart in %s", sid, self.live.session_id,
                     self.out / sid)
            self.live.session_id = sid
            self.live.pose = None
        return s

    def _handle_pose(self, pose: Pose) -> None:
        with self._tum_lock:  # mapped and stored in one world, whatever rebase arrives meanwhile
            self._take_pose(self.rebases.map_pose(pose))

    def _take_pose(self, pose: Pose) -> None:
        now = time.monotonic()
        with self.lock:
            self.stats.received.pose += 1
            s = self._session(pose.session_id)
            if s.last_pose_seq >= 0:
                if pose.seq > s.last_pose_seq + 1:
                    s.pose_gaps += pose.seq - s.last_pose_seq - 1
                    self.stats.pose_seq_gaps += pose.seq - s.last_pose_seq - 1
                elif pose.seq <= s.last_pose_seq:
                    s.pose_out_of_order += 1
            s.last_pose_seq = max(s.last_pose_seq, pose.seq)
            s.poses += 1
            s.first_t_ns = pose.t_ns if s.first_t_ns is None else s.first_t_ns
            s.last_t_ns = pose.t_ns
            prev = self.live.pose
            if prev is not None and prev.session_id == pose.session_id and pose.t_ns > prev.t_ns:
                dt = (pose.t_ns - prev.t_ns) * 1e-9
                v = math.dist(pose.position_m, prev.position_m) / dt
                self.live.speed_m_s = 0.7 * self.live.speed_m_s + 0.3 * v
            self.live.pose = pose
            self._pose_rate.add(now)
            self._pose_window.append((now, pose.seq))
        if self.on_pose is not None:  # before the file write: the live view first
            self.on_pose(pose)
        p, q = pose.position_m, pose.quat_xyzw
        line = (f"{ns_to_seconds_str(pose.t_ns)} {p[0]:.6f} {p[1]:.6f} {p[2]:.6f} "
                f"{q[0]:.7f} {q[1]:.7f} {q[2]:.7f} {q[3]:.7f}\n")
        try:
            fh = self._tum_file(pose.session_id)
            fh.write(line)
            fh.flush()
        except OSError as exc:  # disk full: the live pose is shown, only its host copy is lost
            self._pose_write_failed(pose.session_id, exc)

    def _pose_write_failed(self, sid: str, exc: OSError) -> None:
        fh = self._tum.pop(sid, None)
        if fh is not None:
            try:
                fh.close()
            except OSError:
                pass  # what the buffer held is lost with the write that failed
        try:  # now, not only at the next append: the host may stop before the disk has room again
            cut_torn_tail(self.out / sid / "poses.tum")
        except OSError:
            pass
        with self.lock:
            self.stats.link.poses_unsaved += 1
            first = self.stats.link.poses_unsaved == 1 or "poses" not in self._warned
            self._warned.add("poses")
        if first:
            log.error("cannot append to %s: %s; live poses are shown but not saved on this host (the device "
                      "records its own trajectory.tum)", self.out / sid / "poses.tum", exc.strerror or exc)

    def _tum_file(self, sid: str) -> TextIO:
        fh = self._tum.get(sid)
        if fh is None:
            if len(self._tum) >= 4:
                self._tum.pop(next(iter(self._tum))).close()
            d = self.out / sid
            d.mkdir(parents=True, exist_ok=True)
            if cut := cut_torn_tail(d / "poses.tum"):  # a full disk or a power cut tore the last line
                log.warning("%s: cut a torn last line (%d bytes) before appending", d / "poses.tum", cut)
            fh = self._tum[sid] = (d / "poses.tum").open("a")
        return fh

    def _handle_keyframe(self, kf: Keyframe, data: bytes) -> None:
        live = self.device_session is None or kf.session_id == self.device_session  # else an earlier session's
        try:
            new = self.store.put(kf, data)  # written (and fsynced) before the ack
            if live:
                self.store.set_last_session(kf.session_id)
        except OSError as exc:  # disk full, read-only, ...: not acknowledged, so the device keeps it
            self._storage_failed(f"keyframe {kf.seq} of session {kf.session_id}", exc)
            return
        if self.storage_error is not None and new:  # a duplicate writes nothing: it says nothing of the disk
            log.info("storing keyframes again (after: %s): hello, so the device resends the ones refused",
                     self.storage_error)
            self.storage_error = None
            self.link.storing_again()
        self.sessions.on_count(kf.session_id, kf.seq + 1)  # the device holds at least this many
        now = time.monotonic()
        with self.lock:
            self.stats.received.keyframe += 1
            s = self._session(kf.session_id, live)
            if new:
                s.keyframes += 1
                self._kf_rate.add(now)
            else:
                s.keyframe_duplicates += 1
                self.stats.duplicates += 1
            if live:
                self.live.acked_seq = self.store.session(kf.session_id).acked_seq
        self.link.progress(now)
        self.link.ack(kf.session_id, kf.seq)
        if self.on_keyframe is not None:  # in the session's current world (stored as sent: world_rebase.json maps it)
            self.on_keyframe(self.rebases.map_keyframe(kf), new)

    def _storage_failed(self, what: str, exc: OSError) -> None:
        """Log a storage failure once per streak; the device resends what was not acknowledged."""
        with self.lock:
            self.stats.link.store_failures += 1
            self.link.refused()
            first = self.storage_error is None
            self.storage_error = f"{exc.strerror or exc} ({self.out})"
        if first:
            log.error("cannot store %s: %s; not acknowledged: the device keeps it and sends it again once "
                      "there is space", what, self.storage_error)
        else:
            log.debug("cannot store %s: %s", what, exc)

    def _handle_status(self, st: Status) -> None:
        self.device_session = st.session_id
        self.sessions.on_count(st.session_id, st.keyframes_spooled)
        with self.lock:
            self.stats.received.status += 1
            self._session(st.session_id)
            self.live.status = st
        if self.on_status is not None:
            self.on_status(st)

    def _handle_session(self, info: SessionInfo) -> None:
        if info.live:
            self.device_session = info.session_id
        with self.lock:
            self.stats.received.session += 1
        try:
            self.sessions.on_session(info)
        except OSError as exc:  # the next connection sends it again
            self._storage_failed(f"the rig of session {info.session_id}", exc)

    def _handle_rebase(self, msg: WorldRebase) -> None:
        """The device redefined the session's world: the poses held from before it are mapped once (the
        device repeats the message with every status), and the rebase is recorded in the session folder."""
        sid = msg.session_id
        with self._tum_lock:
            if not self.rebases.of(sid):  # after a restart of the receiver: what it applied before
                try:
                    self.rebases.load(sid, read_rebases(self.out / sid))
                except StereopathError as exc:
                    log.warning("%s; the rebase is applied again", exc)
            rebase = self.rebases.add(msg)
            with self.lock:
                self.stats.received.rebase += 1
                if rebase is not None and self.live.pose is not None and self.live.pose.session_id == sid:
                    self.live.pose = rebase.map(self.live.pose)
            if rebase is None:
                return
            fh = self._tum.pop(sid, None)
            try:
                if fh is not None:
                    fh.close()
                n = rewrite_tum(self.out / sid / "poses.tum", rebase)
                record(self.out / sid, self.rebases.of(sid))
            except OSError as exc:
                log.error("session %s: world rebase from t=%d ns not written to %s: %s", sid, rebase.from_t_ns,
                          self.out / sid, exc.strerror or exc)
                n = 0
            if self.on_rebase is not None:  # under the lock: no pose mapped here reaches the view before it
                self.on_rebase(msg)
        log.info("session %s: the device's world was redefined at t=%d ns; %d stored poses mapped into it "
                 "(world_rebase.json maps the keyframes before it)", sid, rebase.from_t_ns, n)

    def _update_live(self, now: float) -> None:
        with self.lock:
            live = self.live
            live.pose_rate_hz = self._pose_rate.rate(now)
            live.keyframe_rate_hz = self._kf_rate.rate(now)
            w = self._pose_window
            while w and now - w[0][0] > 2.0:
                w.popleft()
            if len(w) >= 2:
                span = max(s for _, s in w) - min(s for _, s in w) + 1
                live.pose_window_ratio = min(1.0, len(w) / span)
            live.link_quality = self.link.quality(now, live.last_rx, live.pose_window_ratio)

    # ------------------------------------------------------------------ statistics

    def _load_stats(self) -> ReceiverStats:
        p = self.out / RECEIVER_JSON
        if p.is_file():
            try:
                return ReceiverStats.from_json(json.loads(p.read_text()))
            except (OSError, ValueError, TypeError, AttributeError) as exc:
                log.warning("starting fresh counters: %s unreadable (%s)", p, exc)
        return ReceiverStats()

    def write_stats(self) -> None:
        """Write ``receiver.json`` (atomically) and the store's state."""
        with self.lock:
            data = self.stats.to_json()
            data["current_session"] = self.live.session_id
        data["updated_unix"] = time.time()
        try:
            write_json_atomic(self.out / RECEIVER_JSON, data, indent=1, fsync=False)
            if self.store.last_session:
                self.store.save_state()
            self.sessions.save()
        except OSError as exc:  # disk full: the counters are rewritten on the next period
            if "stats" not in self._warned:
                self._warned.add("stats")
                log.warning("cannot write %s: %s (retried every %g s)", self.out / RECEIVER_JSON,
                            exc.strerror or exc, self.config.stats_interval_s)
