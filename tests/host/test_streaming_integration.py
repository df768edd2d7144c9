"""Device -> ZeroMQ -> host on loopback: flow, sessions, authentication, malformed traffic, rerun output.

Every socket binds a random 127.0.0.1 port, closes with linger 0, and every wait is bounded.
"""

from __future__ import annotations

import threading
import time
from pathlib import Path

import msgpack
import numpy as np
import pytest
import zmq

from stereopath.device.wire.protocol import Hello, Keyframe, Status, decode_message, encode_hello, encode_keyframe, \
    encode_status, make_keyframe, KEYFRAME_LIMITS
from stereopath.device.wire.security import generate_keypair, load_public_key, load_secret_keypair, make_demo_keys
from stereopath.device.formats.tum import read_tum
from stereopath.host.live.receiver import Receiver
from stereopath.host.live.receiver_config import ReceiverConfig, SocketTiming
from tests.device.test_streaming_support import assert_exactly_once, make_device, port_of, small_images, stored_seqs, \
    wait_for

pytestmark = pytest.mark.timeout(60)
FAST_SOCKETS = SocketTiming(heartbeat_ivl_ms=250, heartbeat_timeout_ms=1500, reconnect_ivl_ms=50, reconnect_ivl_max_ms=400)


@pytest.fixture(scope="module")
def keys(tmp_path_factory):
    return make_demo_keys(tmp_path_factory.mktemp("keys"))


def _receiver(dev, keys, out: Path, **kw) -> Receiver:
    cfg = ReceiverConfig(dev.pose_endpoint, dev.keyframe_endpoint, insecure=keys is None,
                         keys_dir=None if keys is None else str(keys.host_keys_dir), fsync=False,
                         sockets=FAST_SOCKETS, stall_timeout_s=1.0, **kw)
    return Receiver(cfg, out)


def _pose_T(i: int) -> np.ndarray:
    T = np.eye(4)
    T[:3, 3] = [0.01 * i, 0.0, 0.002 * i]
    return T


def _stream(dev, rx, n_poses: int, kf_every: int, first: int = 0) -> None:
    """Publish poses (and keyframes every ``kf_every``) while polling the receiver."""
    for i in range(first, first + n_poses):
        dev.publish_pose(i, 1_000_000 + i * 50_000_000, _pose_T(i), inliers=100 + i)
        if kf_every and i % kf_every == 0:
            assert dev.offer_keyframe(i, 1_000_000 + i * 50_000_000, _pose_T(i), *small_images(i))
        rx.poll(0.01)


@pytest.mark.parametrize("secure", [True, False])
def test_poses_keyframes_and_status_reach_the_host(tmp_path, keys, secure):
    k = keys if secure else None
    dev = make_device(tmp_path, k, "sessA")
    rx = _receiver(dev, k, tmp_path / "out")
    try:
        assert wait_for(lambda: rx.live.connected, 5, between=lambda: rx.poll(0.02))
        wait_for(lambda: False, 0.3, between=lambda: rx.poll(0.02))  # let the SUB subscription propagate
        _stream(dev, rx, 40, 4)
        assert dev.wait_spooled(10, 10)
        assert wait_for(lambda: len(stored_seqs(tmp_path / "out", "sessA")) == 10, 10, between=lambda: rx.poll(0.02))
        assert wait_for(lambda: rx.live.status is not None, 5, between=lambda: rx.poll(0.02))
        st = rx.stats
        assert st.received.pose >= 20 and st.rejected == 0 and st.duplicates == 0
        assert rx.live.status.session_id == "sessA" and rx.live.acked_seq == 9
        assert rx.live.link_quality in ("good", "poor")
    finally:
        rx.close()
        dev.close()
    assert_exactly_once(tmp_path / "out", "sessA", dev.spool)
    traj = read_tum(tmp_path / "out" / "sessA" / "poses.tum")
    assert len(traj) == st.received.pose
    assert np.allclose(traj.T_world_cam[-1], _pose_T(39), atol=1e-5)
    stats = dev.stats()
    assert stats["keyframes_sent"] == 10 and stats["acks"] == 10 and stats["keyframes_resent"] == 0
    assert (tmp_path / "out" / "receiver.json").is_file()


def test_device_restart_new_session_kept_apart(tmp_path, keys):
    out = tmp_path / "out"
    dev_a = make_device(tmp_path, keys, "sessA")
    pport, kport = port_of(dev_a.pose_endpoint), port_of(dev_a.keyframe_endpoint)
    rx = _receiver(dev_a, keys, out)
    try:
        assert wait_for(lambda: rx.live.connected, 5, between=lambda: rx.poll(0.02))
        wait_for(lambda: False, 0.3, between=lambda: rx.poll(0.02))
        _stream(dev_a, rx, 20, 4)
        assert wait_for(lambda: len(stored_seqs(out, "sessA")) == 5, 10, between=lambda: rx.poll(0.02))
        dev_a.close()
        # the device comes back on the same ports with a new session id
        dev_b = make_device(tmp_path, keys, "sessB", pose_endpoint=f"tcp://127.0.0.1:{pport}",
                            keyframe_endpoint=f"tcp://127.0.0.1:{kport}")
        try:
            assert wait_for(lambda: rx.stats.link.connects >= 2, 10, between=lambda: rx.poll(0.02))
            wait_for(lambda: False, 0.3, between=lambda: rx.poll(0.02))
            _stream(dev_b, rx, 12, 4)
            assert wait_for(lambda: len(stored_seqs(out, "sessB")) == 3, 10, between=lambda: rx.poll(0.02))
            assert wait_for(lambda: rx.stats.sessions.get("sessB") and rx.stats.sessions["sessB"].poses > 0, 5,
                            between=lambda: rx.poll(0.02))
        finally:
            dev_b.close()
    finally:
        rx.close()
    assert_exactly_once(out, "sessA", dev_a.spool)
    assert_exactly_once(out, "sessB", dev_b.spool)
    assert (out / "sessA" / "poses.tum").is_file() and (out / "sessB" / "poses.tum").is_file()
    assert rx.live.session_id == "sessB"
    assert set(rx.stats.sessions) == {"sessA", "sessB"}
    # the sessions' poses did not mix: sessB's file starts at its own first pose
    assert len(read_tum(out / "sessB" / "poses.tum")) == rx.stats.sessions["sessB"].poses


def _attacker(ctx: zmq.Context, dev, curve: tuple[bytes, bytes, bytes] | None):
    sub = ctx.socket(zmq.SUB)
    dealer = ctx.socket(zmq.DEALER)
    for s in (sub, dealer):
        s.linger = 0
        if curve is not None:
            s.curve_publickey, s.curve_secretkey, s.curve_serverkey = curve
    sub.setsockopt(zmq.SUBSCRIBE, b"")
    sub.connect(dev.pose_endpoint)
    dealer.connect(dev.keyframe_endpoint)
    dealer.send(encode_hello(Hello(None, -1, 16)))
    return sub, dealer


def test_unauthorised_clients_receive_nothing(tmp_path, keys):
    dev = make_device(tmp_path, keys, "sessA")
    for i in range(3):
        dev.offer_keyframe(i, i, np.eye(4), *small_images(i))
    assert dev.wait_spooled(3, 10)
    device_pub = load_public_key(keys.device_public)
    rand_pub, rand_sec = zmq.curve_keypair()
    _, unlisted = generate_keypair(tmp_path / "intruder", "intruder")
    un_pub, un_sec = load_secret_keypair(unlisted)
    ctx = zmq.Context()
    attackers = {
        "random key": _attacker(ctx, dev, (rand_pub, rand_sec, zmq.curve_keypair()[0])),
        "random key, right device key": _attacker(ctx, dev, (rand_pub, rand_sec, device_pub)),
        "no CURVE": _attacker(ctx, dev, None),
        "unlisted key": _attacker(ctx, dev, (un_pub, un_sec, device_pub)),
    }
    rx = _receiver(dev, keys, tmp_path / "out")
    got = {name: 0 for name in attackers}
    stop = threading.Event()

    def produce():
        i = 0
        while not stop.is_set():
            dev.publish_pose(i, i, np.eye(4))
            i += 1
            time.sleep(0.01)

    th = threading.Thread(target=produce)
    th.start()
    try:
        deadline = time.monotonic() + 2.0
        while time.monotonic() < deadline:
            rx.poll(0.01)
            for name, (sub, dealer) in attackers.items():
                for s in (sub, dealer):
                    while s.poll(0):
                        s.recv_multipart()
                        got[name] += 1
        assert wait_for(lambda: len(stored_seqs(tmp_path / "out", "sessA")) == 3, 5, between=lambda: rx.poll(0.02))
    finally:
        stop.set()
        th.join()
        for sub, dealer in attackers.values():
            sub.close(linger=0)
            dealer.close(linger=0)
        ctx.term()
        rx.close()
        dev.close()
    assert got == {name: 0 for name in attackers}
    assert rx.stats.received.pose > 0  # the authorised host did receive
    stats = dev.stats()
    assert stats["hellos"] == 1 and len(stats["peers"]) == 1  # no intruder hello reached the device


def _malformed_control(rng: np.random.Generator, n: int) -> list[list[bytes]]:
    good = encode_hello(Hello("sessA", 0, 4))
    out = []
    for i in range(n):
        kind = i % 8
        if kind == 0:
            out.append([rng.bytes(int(rng.integers(1, 1500)))])              # random (some over 512 bytes)
        elif kind == 1:
            out.append([good[: int(rng.integers(1, len(good)))]])            # truncated
        elif kind == 2:
            out.append([msgpack.packb({"v": 1, "type": "hello", "sid": 5, "acked": "x", "credit": []})])
        elif kind == 3:
            out.append([b"\xc6\xff\xff\xff\xff" + rng.bytes(8)])             # huge declared length
        elif kind == 4:
            out.append([b"\x91" * int(rng.integers(100, 2000)) + b"\xc0"])   # deep nesting
        elif kind == 5:
            out.append([good, b"extra frame"])                               # multipart
        elif kind == 6:
            out.append([msgpack.packb({"v": 99, "type": "hello", "sid": None, "acked": -1, "credit": 1})])
        else:
            out.append([msgpack.packb({"v": 1, "type": "keyframe"})])        # wrong type for the channel
    return out


def test_malformed_control_messages_rejected_valid_traffic_continues(tmp_path, keys):
    dev = make_device(tmp_path, keys, "sessA")
    for i in range(2):
        dev.offer_keyframe(i, i, np.eye(4), *small_images(i))
    assert dev.wait_spooled(2, 10)
    host_pub, host_sec = load_secret_keypair(keys.host_secret)
    ctx = zmq.Context()
    d = ctx.socket(zmq.DEALER)
    d.linger = 0
    d.curve_publickey, d.curve_secretkey = host_pub, host_sec
    d.curve_serverkey = load_public_key(keys.device_public)
    mon = d.get_monitor_socket(zmq.EVENT_DISCONNECTED)
    d.connect(dev.keyframe_endpoint)
    n = 1000
    try:
        for parts in _malformed_control(np.random.default_rng(7), n):
            d.send_multipart(parts)
        assert wait_for(lambda: dev.stats()["control_received"] >= n, 20)
        stats = dev.stats()
        assert stats["control_rejected"] == n and stats["hellos"] == 0
        assert set(stats["control_rejected_by_reason"]) <= {"malformed", "too_large", "field", "type", "version",
                                                            "frames"}
        # valid traffic still works on the same connection
        d.send(encode_hello(Hello(None, -1, 4)))
        received: list[object] = []

        def drain() -> None:
            if d.poll(20):
                received.append(decode_message(d.recv(), KEYFRAME_LIMITS, ("keyframe", "status", "session")))

        assert wait_for(lambda: sum(isinstance(m, Keyframe) for m in received) == 2, 10, between=drain)
        # an oversized frame (over the socket's maxmsgsize) drops the connection; it reconnects and works
        d.send(b"\0" * 100_000)
        time.sleep(0.3)
        received.clear()

        def hello_and_drain() -> None:
            try:
                d.send(encode_hello(Hello(None, -1, 4)), zmq.NOBLOCK)
            except zmq.Again:
                pass
            for _ in range(5):
                drain()

        assert wait_for(lambda: any(isinstance(m, Keyframe) for m in received), 10, between=hello_and_drain)
        assert mon.poll(1000), "the oversized frame should have dropped the connection"
    finally:
        d.disable_monitor()
        mon.close(linger=0)
        d.close(linger=0)
        ctx.term()
        dev.close()


def test_host_rejects_malformed_device_messages_and_carries_on(tmp_path, keys):
    """A compromised or buggy device: garbage on both channels is counted by reason, then a valid keyframe lands."""
    from zmq.auth.thread import ThreadAuthenticator

    dev_pub, dev_sec = load_secret_keypair(keys.device_secret)
    ctx = zmq.Context()
    auth = ThreadAuthenticator(ctx)
    auth.start()
    auth.configure_curve(domain="*", location=str(keys.clients_dir))
    router, pub = ctx.socket(zmq.ROUTER), ctx.socket(zmq.PUB)
    for s in (router, pub):
        s.linger = 0
        s.curve_publickey, s.curve_secretkey, s.curve_server = dev_pub, dev_sec, True
        s.sndhwm = 100_000
    kport = router.bind_to_random_port("tcp://127.0.0.1")
    pport = pub.bind_to_random_port("tcp://127.0.0.1")
    cfg = ReceiverConfig(f"tcp://127.0.0.1:{pport}", f"tcp://127.0.0.1:{kport}", keys_dir=str(keys.host_keys_dir),
                         fsync=False, stall_timeout_s=100.0)
    rx = Receiver(cfg, tmp_path / "out")
    rng = np.random.default_rng(11)
    kf = make_keyframe("fake", 0, 0, 5, np.eye(4), small_images(0), ("rig", "0123456789abcdef"), "png")
    good = encode_keyframe(kf)
    bad_kf = msgpack.unpackb(good)
    bad_kf["l"]["dtype"] = "<f8"
    garbage = [rng.bytes(int(rng.integers(1, 2000))), good[: len(good) // 2], msgpack.packb(bad_kf),
               msgpack.packb({"v": 2, "type": "status"}), b"\x91" * 3000 + b"\xc0", b"\xc6\xff\xff\xff\xff",
               encode_status(Status("fake", 1))[:-3], msgpack.packb({"v": 1, "type": "hello", "sid": None}),
               msgpack.packb({"v": 1, "type": "rebase", "sid": "fake", "t": -1, "p": [0.0, 0.0, 0.0],
                              "q": [0.0, 0.0, 0.0, 1.0]})]  # a rebase whose time is out of range
    try:
        rid: list[bytes] = []

        def wait_hello() -> None:
            rx.poll(0.01)
            if router.poll(0):
                frames = router.recv_multipart()
                rid.append(frames[0])

        assert wait_for(lambda: bool(rid), 10, between=wait_hello)
        n = 400
        for i in range(n):
            router.send_multipart([rid[0], garbage[i % len(garbage)]])
        router.send_multipart([rid[0], b"a", b"b"])  # two frames
        for i in range(50):
            pub.send(garbage[i % len(garbage)])
        assert wait_for(lambda: rx.stats.rejected_by_channel["keyframe"] == n + 1, 20, between=lambda: rx.poll(0.02))
        router.send_multipart([rid[0], good])
        assert wait_for(lambda: stored_seqs(tmp_path / "out", "fake") == [0], 10, between=lambda: rx.poll(0.02))
        wait_for(lambda: False, 0.2, between=lambda: rx.poll(0.02))
    finally:
        rx.close()
        router.close(linger=0)
        pub.close(linger=0)
        auth.stop()
        ctx.term()
    st = rx.stats
    assert st.rejected_by_reason.get("frames") == 1 and st.rejected_by_reason.get("version", 0) >= n // len(garbage)
    assert st.rejected_by_channel["pose"] <= 50  # conflated SUB: some garbage is replaced before it is read
    assert st.received.keyframe == 1 and st.received.rebase == 0


def test_live_command_writes_rerun_recording(tmp_path, keys):
    pytest.importorskip("rerun")
    from stereopath.host.cli import main as stereopath_cli

    dev = make_device(tmp_path, keys, "sessR")
    stop = threading.Event()

    def produce():
        i = 0
        while not stop.is_set():
            dev.publish_pose(i, i * 50_000_000, _pose_T(i))
            if i % 5 == 0:
                dev.offer_keyframe(i, i * 50_000_000, _pose_T(i), *small_images(i))
            i += 1
            time.sleep(0.02)

    th = threading.Thread(target=produce)
    th.start()
    rrd = tmp_path / "live.rrd"
    try:
        rc = stereopath_cli(["host", "live", "--device", f"127.0.0.1:{port_of(dev.pose_endpoint)}",
                        "--keyframe-port", str(port_of(dev.keyframe_endpoint)), "--keys", str(keys.host_keys_dir),
                        "--out", str(tmp_path / "out"), "--rerun-save", str(rrd), "--duration", "2", "--no-fsync",
                        "--mcap", str(tmp_path / "live.mcap")])
    finally:
        stop.set()
        th.join()
        dev.close()
    assert rc == 0
    assert rrd.is_file() and rrd.stat().st_size > 1000
    from mcap.reader import make_reader

    with open(tmp_path / "live.mcap", "rb") as fh:  # --mcap: the stream as it arrived, complete at the end
        topics = [ch.topic for _, ch, _ in make_reader(fh).iter_messages()]
    assert topics.count("/pose") >= 10 and topics.count("/cam0/image") == topics.count("/cam1/image") >= 1
    assert len(stored_seqs(tmp_path / "out", "sessR")) >= 1
    assert (tmp_path / "out" / "sessR" / "poses.tum").stat().st_size > 0


def test_resend_after_host_lost_a_keyframe_is_deduplicated(tmp_path, keys):
    """A host restarting with a hole in its store asks from the hole: the rest arrive as counted duplicates."""
    out = tmp_path / "out"
    dev = make_device(tmp_path, keys, "sessD")
    try:
        for i in range(5):
            dev.offer_keyframe(i, i, np.eye(4), *small_images(i))
        assert dev.wait_spooled(5, 10)
        rx = _receiver(dev, keys, out)
        assert wait_for(lambda: len(stored_seqs(out, "sessD")) == 5, 10, between=lambda: rx.poll(0.02))
        rx.close()
        (out / "sessD" / "keyframes" / "kf_00000001.msgpack").unlink()
        rx = _receiver(dev, keys, out)
        assert wait_for(lambda: len(stored_seqs(out, "sessD")) == 5, 10, between=lambda: rx.poll(0.02))
        assert wait_for(lambda: rx.stats.duplicates >= 3, 5, between=lambda: rx.poll(0.02))
        rx.close()
    finally:
        dev.close()
    assert rx.stats.duplicates == 3 and rx.stats.sessions["sessD"].keyframe_duplicates == 3
    assert dev.stats()["keyframes_resent"] == 4
    assert_exactly_once(out, "sessD", dev.spool)


def test_a_keyframe_the_host_did_not_acknowledge_is_not_taken_as_stored(tmp_path):
    """Acks are per keyframe: a host that stored 0, 1, 3, 4, 5 but not 2 (its disk was full) holds up to 1 (what
    the device's drain looks at), the keyframes the device's full disk holds in memory from 2 on stay there,
    and the host's next hello has 2-5 resent from memory."""
    from stereopath.device.wire.protocol import Ack, encode_ack

    dev = make_device(tmp_path, None, "sessG")
    dev.spool.reserve_bytes = 2**62  # the device's disk is full: every keyframe waits in memory for a host
    n = 6
    for i in range(n):
        dev.offer_keyframe(i, i, np.eye(4), *small_images(i))
    assert dev.wait_spooled(n, 10)
    ctx = zmq.Context()
    d = ctx.socket(zmq.DEALER)
    d.linger = 0
    d.connect(dev.keyframe_endpoint)
    got: list[int] = []

    def receive() -> None:
        if d.poll(20):
            m = decode_message(d.recv(), KEYFRAME_LIMITS, ("keyframe", "status", "session"))
            if isinstance(m, Keyframe):
                got.append(m.seq)
                if m.seq != 2 or got.count(2) > 1:  # the first copy of 2 could not be stored
                    d.send(encode_ack(Ack("sessG", m.seq, 1)))

    def acked() -> int:
        return max((p["acked"] for p in dev.stats()["peers"]), default=-2)

    try:
        d.send(encode_hello(Hello(None, -1, 8)))
        assert wait_for(lambda: sorted(got) == list(range(n)) and dev.stats()["acks"] >= n - 1, 10, between=receive)
        time.sleep(0.2)
        assert acked() == 1  # not 5: keyframe 2 is not on the host
        assert dev.spool.memory_count == n - 2  # 0 and 1 freed; 2-5 kept for the resend
        assert dev.spool.memory_unacked_count == 1  # only 2 would be lost if the device stopped now
        d.send(encode_hello(Hello("sessG", 1, 8)))  # what the host's stall check sends
        assert wait_for(lambda: acked() == n - 1, 10, between=receive)
        assert got[n:] == [2, 3, 4, 5]  # resent from the hole
        assert dev.spool.memory_count == 0
    finally:
        d.close(linger=0)
        ctx.term()
        dev.close()


def test_poses_appended_after_a_torn_last_line_still_read(tmp_path):
    """poses.tum whose last line a full disk or a power cut tore: the host cuts it before appending, so the
    file reads (a glued line used to make every pose of it unreadable)."""
    out = tmp_path / "out"
    (out / "sessT").mkdir(parents=True)
    (out / "sessT" / "poses.tum").write_text("0.000000001 0 0 0 0 0 0 1\n0.5 0.1 0.2 0.3 0 0 0.9")
    dev = make_device(tmp_path, None, "sessT")
    rx = _receiver(dev, None, out)
    try:
        assert wait_for(lambda: rx.live.connected, 5, between=lambda: rx.poll(0.02))
        wait_for(lambda: False, 0.3, between=lambda: rx.poll(0.02))  # let the SUB subscription propagate
        _stream(dev, rx, 10, 0)
        assert wait_for(lambda: rx.stats.received.pose >= 5, 5, between=lambda: rx.poll(0.02))
    finally:
        rx.close()
        dev.close()
    traj = read_tum(out / "sessT" / "poses.tum")
    assert len(traj) == 1 + rx.stats.received.pose and traj.t_ns[0] == 1


def test_a_failed_pose_write_leaves_no_torn_line_even_if_the_host_stops_then(tmp_path):
    """The torn tail a refused write leaves is cut at once, not only at the next append (the host may stop
    while its disk is still full)."""
    import errno

    dev = make_device(tmp_path, None, "sessU")
    out = tmp_path / "out"
    rx = _receiver(dev, None, out)
    try:
        (out / "sessU").mkdir(parents=True)
        (out / "sessU" / "poses.tum").write_text("0.000000001 0 0 0 0 0 0 1\n0.5 0.1 0.2")
        rx._pose_write_failed("sessU", OSError(errno.ENOSPC, "No space left on device"))
    finally:
        rx.close()
        dev.close()
    assert len(read_tum(out / "sessU" / "poses.tum")) == 1
