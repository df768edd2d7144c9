"""The keyframe delivery state machine under random interleavings (hypothesis).

The device side is the real :class:`KeyframeServer` over real spools and backlogs; the host side
is the real :class:`KeyframeStore`.  Only the wire between them is a model: a ROUTER stand-in that
queues what the server sends per connection, loses it when the connection drops, and refuses a
connection that is gone (``EHOSTUNREACH``, as a ROUTER_MANDATORY socket does).  The steps are the
ones a field run sees: keyframes produced, sends, deliveries with acknowledgements that arrive or
get lost, reconnections, hellos (honest, stale or hostile), host restarts and device kills.

The property, after every step: every keyframe the device produced is on the host, or still on
the device's disk beyond the seq its spool records as acknowledged (so the next run offers it).
At the end an honest host and a restarted device settle, and the host then holds every keyframe.
"""

from __future__ import annotations

import shutil
import tempfile
from pathlib import Path

import numpy as np
import pytest

hypothesis = pytest.importorskip("hypothesis")
from hypothesis import HealthCheck, settings, strategies as st  # noqa: E402
from hypothesis.stateful import RuleBasedStateMachine, initialize, invariant, precondition, rule  # noqa: E402

from stereopath.device.errors import DatasetError  # noqa: E402
from stereopath.device.streaming.backlog import Backlog, find_backlog, write_marker  # noqa: E402
from stereopath.device.streaming.keyframe_server import KeyframeServer  # noqa: E402
from stereopath.device.streaming.spool import KeyframeSpool, read_acked  # noqa: E402
from stereopath.device.wire.protocol import KEYFRAME_LIMITS, SESSION_LIMITS, Ack, Hello, Keyframe, Limits, \
    Status, decode_message, encode_keyframe, encode_session, encode_status, make_keyframe, make_session_info  # noqa: E402
from stereopath.host.live.store import KeyframeStore  # noqa: E402
from tests.device.test_streaming_support import device_config  # noqa: E402

RIG_REF = ("testrig", "0123456789abcdef")
HOST_KEY = "curve:host-under-test"
LIMITS = Limits(max_message_bytes=KEYFRAME_LIMITS.max_message_bytes, max_bin_len=KEYFRAME_LIMITS.max_bin_len,
                max_array_len=SESSION_LIMITS.max_array_len, max_str_len=SESSION_LIMITS.max_str_len)
_IMG = np.arange(64, dtype=np.uint8).reshape(8, 8)


class FakeRouter:
    """What the server's ROUTER does with a send, per connection (routing id)."""

    HWM = 6

    def __init__(self) -> None:
        import zmq

        self._zmq = zmq
        self.outbox: dict[bytes, list[bytes]] = {}

    def connect(self, rid: bytes) -> None:
        self.outbox[rid] = []

    def drop(self, rid: bytes) -> None:
        self.outbox.pop(rid, None)  # in flight: lost with the connection

    def send_multipart(self, parts: list[bytes], flags: int = 0, copy: bool = True) -> None:
        rid, data = parts
        box = self.outbox.get(rid)
        if box is None:
            raise self._zmq.ZMQError(self._zmq.EHOSTUNREACH)
        if len(box) >= self.HWM:
            raise self._zmq.Again()
        box.append(bytes(data))

    def close(self, linger: int = 0) -> None:
        self.outbox.clear()


class Delivery(RuleBasedStateMachine):
    def __init__(self) -> None:
        super().__init__()
        import zmq

        self.ctx = zmq.Context.instance()
        self.tmp = Path(tempfile.mkdtemp(prefix="stereopath-delivery-"))
        self.root = self.tmp / "sessions"
        self.root.mkdir()
        self.produced: dict[str, int] = {}  # session id -> keyframes produced
        self.run = -1
        self.conn = 0
        self.store = KeyframeStore(self.tmp / "host", fsync=False)
        self.server: KeyframeServer | None = None

    @initialize(curve=st.booleans(), disk_full=st.booleans())
    def start(self, curve: bool, disk_full: bool) -> None:
        """``curve``: the host is known by its CURVE key (else by its connection, new on each reconnect, as
        without CURVE); ``disk_full``: the device's disk is full from the start (keyframes wait in memory)."""
        self.curve, self.disk_full = curve, disk_full
        self._start_device()

    # ------------------------------------------------------------------ the device

    def _start_device(self) -> None:
        if self.server is not None:
            self.server.sock.close()
        self.run += 1
        self.session = f"sess{self.run:03d}"
        spool_dir = self.root / self.session / "keyframes"
        full = dict(reserve_bytes=1, disk_free=lambda p: 0, max_memory_bytes=12 * 1024) if self.disk_full else {}
        self.spool = KeyframeSpool(spool_dir, fsync=False, **full)
        info = make_session_info(self.session, None, RIG_REF)
        write_marker(spool_dir, encode_session(info))
        self.produced[self.session] = 0
        server = KeyframeServer(self.ctx, device_config(None, max_credit=4), self.spool, self.session, None,
                                lambda: encode_status(Status(self.session, 1)),
                                lambda: encode_session(info), Backlog(find_backlog([self.root], spool_dir)))
        server.sock.close(linger=0)
        self.router = server.sock = FakeRouter()
        self.server = server
        self._reconnect()

    def _reconnect(self, hello: Hello | None = None) -> None:
        self.router.drop(self._rid())
        self.conn += 1
        self.router.connect(self._rid())
        sid, acked = self.store.hello_state()
        self.server.handle(self._key(), self._rid(), hello or Hello(sid, acked, 4))

    def _rid(self) -> bytes:
        return self.conn.to_bytes(4, "big")

    def _key(self) -> str:
        return HOST_KEY if self.curve else "rid:" + self._rid().hex()

    # ------------------------------------------------------------------ steps

    @rule(n=st.integers(1, 4))
    def produce(self, n: int) -> None:
        for _ in range(n):
            seq = self.spool.count
            kf = make_keyframe(self.session, seq, 10 * seq, 1000 + seq, np.eye(4), (_IMG, _IMG), RIG_REF, "png")
            try:
                self.spool.append(seq, encode_keyframe(kf))
            except DatasetError:  # disk and memory full: refused (the streamer counts it), never offered
                assert self.disk_full
                return
            self.produced[self.session] = seq + 1

    @rule()
    def pump(self) -> None:
        self.server.pump(burst=3)

    @rule(n=st.integers(1, 6), lose_acks=st.booleans())
    def deliver(self, n: int, lose_acks: bool) -> None:
        """The host reads up to ``n`` messages; each keyframe is stored, then acknowledged (or the ack is lost)."""
        box = self.router.outbox.get(self._rid(), [])
        for data in box[:n]:
            msg = decode_message(data, LIMITS)
            if not isinstance(msg, Keyframe):
                continue
            self.store.put(msg, data)
            if msg.session_id == self.session:
                self.store.set_last_session(msg.session_id)
            if not lose_acks:
                self.server.handle(self._key(), self._rid(), Ack(msg.session_id, msg.seq, 1))
        del box[:n]

    @rule()
    def connection_drops(self) -> None:
        self._reconnect()

    @rule(claim=st.one_of(st.integers(-1, 40), st.just(2**32 - 1)), own_session=st.booleans())
    def rogue_hello(self, claim: int, own_session: bool) -> None:
        """A hello claiming keyframes the host may never have received (stale state, or hostile)."""
        self._reconnect(Hello(self.session if own_session else "someOther", claim, 4))

    @rule()
    def host_restarts(self) -> None:
        self.store.close()
        self.store = KeyframeStore(self.tmp / "host", fsync=False)
        self._reconnect()

    @precondition(lambda self: self.run < 4 and not self.disk_full)  # (memory is lost with the process, by design)
    @rule()
    def device_killed_and_restarted(self) -> None:
        self._start_device()

    # ------------------------------------------------------------------ the property

    def _on_host(self, sid: str) -> set[int]:
        if not (self.tmp / "host" / sid).is_dir():
            return set()
        s = self.store.session(sid)
        return {seq for seq in range(self.produced[sid]) if s.has(seq)}

    @invariant()
    def every_keyframe_is_on_the_host_or_still_offered(self) -> None:
        for sid, n in self.produced.items():
            spool_dir = self.root / sid / "keyframes"
            live = sid == self.session
            acked = self.spool.acked_seq if live else read_acked(spool_dir)
            held = self._on_host(sid)
            for seq in range(n):
                if seq in held:
                    continue
                if live:
                    self.spool.read(seq)  # on the device (disk or memory), else DatasetError
                else:
                    assert (spool_dir / f"{seq:08d}.kf").is_file(), f"{sid}/{seq}: on no host and gone"
                assert seq > acked, (f"{sid}/{seq}: on no host, yet recorded as acknowledged (up to {acked}): "
                                     f"no later run offers it")
                assert seq > read_acked(spool_dir), f"{sid}/{seq}: acked.json says delivered"

    def teardown(self) -> None:
        try:
            if self.server is None:
                return
            # an honest host reconnects to the device as it is: everything, earlier sessions included,
            # reaches it within this run (nothing stalls)
            self._reconnect()
            for _ in range(2000):
                self.server.pump(burst=8)
                box = self.router.outbox.get(self._rid())
                if not box:
                    break
                self.deliver(len(box), False)
            for sid, n in self.produced.items():
                missing = set(range(n)) - self._on_host(sid)
                assert not missing, f"after settling, {sid} misses {sorted(missing)[:10]} on the host"
            if self.disk_full:
                assert self.spool.memory_count == 0, "keyframes held in memory after every one was acknowledged"
        finally:
            self.store.close()
            if self.server is not None:
                self.server.sock.close()
            shutil.rmtree(self.tmp, ignore_errors=True)


Delivery.TestCase.settings = settings(max_examples=80, stateful_step_count=30, deadline=None, derandomize=True,
                                      database=None, suppress_health_check=[HealthCheck.too_slow])
test_keyframe_delivery_state_machine = Delivery.TestCase


@pytest.mark.parametrize("curve", [False, True])
def test_a_reconnect_after_keyframes_left_memory_on_a_full_disk_still_frees_memory(curve):
    """A full disk: keyframes wait in memory and leave it once acknowledged.  A host that reconnects
    (without CURVE it is a new peer each time) must not be stuck waiting for those it already holds."""
    m = Delivery()
    m.start(curve=curve, disk_full=True)
    m.produce(4)
    for _ in range(3):
        m.pump()
        m.deliver(6, False)
    assert m.spool.memory_count == 0 and m.spool.acked_seq == 3
    m.connection_drops()
    m.produce(4)
    for _ in range(5):
        m.pump()
        m.deliver(6, False)
    assert m.spool.memory_count == 0 and m.spool.acked_seq == 7
    assert m.server.stats["spool_errors"] == 0
    m.teardown()
