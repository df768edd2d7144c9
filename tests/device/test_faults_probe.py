"""The hostile probe's wire findings: session ids that name the host's own files, a journal an
authorised peer can flood, and handshake failures named for what they are."""

from __future__ import annotations

import logging
import socket
import sys
import threading
from pathlib import Path

import numpy as np
import pytest

from stereopath.device.wire.protocol import Hello
from stereopath.device.wire.ratelog import RateLimitedLog
from stereopath.device.wire.security import make_demo_keys
from stereopath.device.wire.sockets import zmtp_greeting
from tests.host.test_streaming_integration import _receiver
from tests.device.test_streaming_support import make_device, small_images, stored_seqs, wait_for

pytestmark = pytest.mark.timeout(90)


@pytest.fixture(scope="module")
def keys(tmp_path_factory):
    return make_demo_keys(tmp_path_factory.mktemp("keys"))


# ------------------------------------------------------------------ session ids against the host's files

@pytest.mark.parametrize("sid", ["receiver.json", "state.json", "user.rrd"])
def test_a_session_id_naming_a_host_file_is_refused_and_the_host_carries_on(tmp_path, sid, caplog):
    out = tmp_path / "out"
    out.mkdir()
    (out / "user.rrd").write_bytes(b"a recording the user keeps here")
    dev = make_device(tmp_path, None, sid)
    rx = _receiver(dev, None, out)
    try:
        with caplog.at_level(logging.WARNING, logger="stereopath.host.live.receiver"):
            for i in range(3):
                assert dev.offer_keyframe(i, i, np.eye(4), *small_images(i))
            assert wait_for(lambda: rx.stats.rejected_by_reason.get("session_id", 0) >= 3, 20,
                            between=lambda: rx.poll(0.02))
            rx.write_stats()
    finally:
        rx.close()
        dev.close()
    assert (out / "receiver.json").is_file()  # the host's own files are still files
    assert not (out / sid).is_dir()
    assert (out / "user.rrd").read_bytes() == b"a recording the user keeps here"
    assert not list(out.glob(".*tmp"))  # no temporary file left behind
    lines = [r.getMessage() for r in caplog.records if "not stored" in r.getMessage()]
    assert len(lines) == 1 and sid in lines[0], lines
    assert dev.stats()["keyframes_acked"] == 0  # never acknowledged: the device keeps them


def test_a_stale_host_file_folder_is_not_taken_for_a_session(tmp_path):
    """A ``state.json`` folder left by an older version does not make that name a session."""
    from stereopath.host.live.receiver import session_name_clash

    (tmp_path / "state.json").mkdir()
    (tmp_path / "notes.txt").write_text("x")
    assert "host's own file" in session_name_clash(tmp_path, "state.json")
    assert "not a session folder" in session_name_clash(tmp_path, "notes.txt")
    assert session_name_clash(tmp_path, "20261128T101500Z-abcdef") == ""


def test_write_atomic_leaves_no_temporary_file_when_the_target_is_a_folder(tmp_path):
    from stereopath.device.formats.fileio import write_atomic

    (tmp_path / "state.json").mkdir()
    with pytest.raises(OSError):
        write_atomic(tmp_path / "state.json", b"{}", fsync=False)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["state.json"]


# ------------------------------------------------------------------ a flood of hellos

def test_rate_limited_log_says_how_many_lines_it_held_back(caplog):
    now = [0.0]
    rl = RateLimitedLog(logging.getLogger("t.ratelog"), interval_s=10.0, clock=lambda: now[0])
    with caplog.at_level(logging.INFO, logger="t.ratelog"):
        logged = [rl.log(logging.INFO, "peerA", "hello %d", i) for i in range(1000)]
        rl.log(logging.INFO, "peerB", "hello from B")
        now[0] = 10.5
        rl.log(logging.INFO, "peerA", "hello %d", 1000)
    assert sum(logged) == 1 and rl.suppressed == 999
    msgs = [r.getMessage() for r in caplog.records]
    assert msgs == ["hello 0", "hello from B", "hello 1000 (and 999 more like it since the last)"]


def test_rate_limited_log_forgets_the_oldest_keys():
    rl = RateLimitedLog(logging.getLogger("t.ratelog2"), interval_s=10.0, max_keys=4, clock=lambda: 0.0)
    for i in range(100):
        rl.log(logging.DEBUG, f"k{i}", "x")
    assert len(rl._keys) == 4


def test_the_connections_can_be_read_while_hosts_come_and_go(tmp_path):
    """The service's status thread reads the connections (``peers()``) while they are added and forgotten
    (more hosts than ``max_peers``): neither side sees the table change under it."""
    dev = make_device(tmp_path, None, "sessP")
    errors: list[BaseException] = []
    stop = threading.Event()

    def read_status() -> None:
        while not stop.is_set():
            try:
                dev._server.peers()
            except Exception as exc:  # noqa: BLE001 - the failure this test looks for
                errors.append(exc)
                return

    switch = sys.getswitchinterval()
    sys.setswitchinterval(1e-5)  # switch threads often, as a loaded machine does
    reader = threading.Thread(target=read_status)
    reader.start()
    try:
        for i in range(3000):
            dev._server.handle(f"curve:host{i % 24}", i.to_bytes(4, "big"), Hello("sessP", -1, 4))
    finally:
        stop.set()
        reader.join()
        sys.setswitchinterval(switch)
        dev.close()
    assert not errors and dev._server.stats["peers_evicted"] > 0


def test_a_peer_flooding_hellos_gets_one_journal_line_per_interval(tmp_path, caplog):
    dev = make_device(tmp_path, None, "sessH")
    try:
        with caplog.at_level(logging.INFO, logger="stereopath.device.streaming.keyframe_server"):
            for i in range(2000):
                dev._server.handle("curve:flooder", i.to_bytes(4, "big"), Hello("sessH", -1, 4))
    finally:
        dev.close()
    lines = [r for r in caplog.records if r.name == "stereopath.device.streaming.keyframe_server"]
    assert 1 <= len(lines) <= 3, [r.getMessage() for r in lines]


# ------------------------------------------------------------------ a hello's claim

def test_a_hello_claiming_unsent_keyframes_skips_nothing_and_records_nothing(tmp_path, caplog):
    """The probe's first finding, over real sockets: a hello claiming 2^32-1 before anything was received."""
    import zmq

    from stereopath.device.streaming.spool import read_acked
    from stereopath.device.wire.protocol import Keyframe, decode_message, encode_hello, KEYFRAME_LIMITS

    dev = make_device(tmp_path, None, "sessR")
    ctx = zmq.Context()
    d = ctx.socket(zmq.DEALER)
    d.setsockopt(zmq.LINGER, 0)
    try:
        for i in range(4):
            assert dev.offer_keyframe(i, i, np.eye(4), *small_images(i))
        assert dev.wait_spooled(4, 10)
        d.connect(dev.keyframe_endpoint)
        with caplog.at_level(logging.WARNING, logger="stereopath.device.streaming.keyframe_server"):
            d.send(encode_hello(Hello("sessR", 2**32 - 1, 8)))
            seqs: list[int] = []

            def drain() -> None:
                while d.poll(20):
                    msg = decode_message(d.recv(), KEYFRAME_LIMITS)
                    if isinstance(msg, Keyframe):
                        seqs.append(msg.seq)
            assert wait_for(lambda: len(seqs) >= 4, 10, between=drain)
        assert sorted(seqs) == [0, 1, 2, 3]  # everything is sent: the claim skipped nothing
        assert dev.spool.acked_seq == -1 and read_acked(dev.spool.dir) == -1
        assert any("no host was sent more than -1" in r.getMessage() for r in caplog.records)
    finally:
        d.close(0)
        ctx.term()
        dev.close()


# ------------------------------------------------------------------ handshake failures named

def _closing_forwarder() -> tuple[socket.socket, int]:
    """A port that accepts TCP connections and closes them at once (a tunnel whose far end is gone)."""
    srv = socket.socket()
    srv.bind(("127.0.0.1", 0))
    srv.listen(16)

    def serve() -> None:
        while True:
            try:
                c, _ = srv.accept()
            except OSError:
                return
            c.close()
    threading.Thread(target=serve, daemon=True).start()
    return srv, srv.getsockname()[1]


def test_zmtp_greeting_tells_a_device_from_a_dead_forwarder(tmp_path):
    srv, port = _closing_forwarder()
    try:
        assert zmtp_greeting(f"tcp://127.0.0.1:{port}") == "no greeting"
    finally:
        srv.close()
    dev = make_device(tmp_path, None, "sessG")
    try:
        assert zmtp_greeting(dev.keyframe_endpoint) == "zmtp:NULL"
    finally:
        dev.close()
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        free = s.getsockname()[1]
    assert zmtp_greeting(f"tcp://127.0.0.1:{free}") == "refused"
    assert zmtp_greeting("ipc:///tmp/x") == "unknown"


def _receiver_at(endpoint: str, keys, out: Path, device_key: Path | None = None):
    from stereopath.host.live.receiver import Receiver, ReceiverConfig
    from stereopath.host.live.receiver_config import SocketTiming

    cfg = ReceiverConfig(endpoint, endpoint, insecure=keys is None,
                         keys_dir=None if keys is None else str(keys.host_keys_dir),
                         device_key=None if device_key is None else str(device_key), fsync=False,
                         sockets=SocketTiming(heartbeat_ivl_ms=250, heartbeat_timeout_ms=1500, reconnect_ivl_ms=50,
                                              reconnect_ivl_max_ms=200),
                         stall_timeout_s=1.0)
    return Receiver(cfg, out)


def _warnings_until(rx, caplog, text: str) -> list[str]:
    with caplog.at_level(logging.WARNING, logger="stereopath.host.live.receiver"):
        wait_for(lambda: any(text in r.getMessage() for r in caplog.records), 10, between=lambda: rx.poll(0.05))
    return [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING]


def test_a_dead_tunnel_is_named_as_such_not_as_a_wrong_key(tmp_path, keys, caplog):
    srv, port = _closing_forwarder()
    rx = _receiver_at(f"tcp://127.0.0.1:{port}", keys, tmp_path / "out")
    try:
        msgs = _warnings_until(rx, caplog, "does not answer as a stereopath device")
    finally:
        rx.close()
        srv.close()
    assert any("port forwarder or SSH tunnel" in m for m in msgs), msgs
    assert not any("device public key" in m for m in msgs), msgs


@pytest.mark.parametrize("device_curve, host_curve, wrong_key, waited, said", [
    (True, True, True, "closed the CURVE handshake", "is not that device's"),
    (False, True, False, "CURVE on one side only", "streams without CURVE"),
    (True, False, False, "CURVE on one side only", "requires CURVE and this host runs --insecure"),
], ids=["wrong device key", "device without CURVE", "host without CURVE"])
def test_a_failed_handshake_is_named_for_what_it_is(tmp_path, keys, caplog, device_curve, host_curve, wrong_key,
                                                     waited, said):
    other = make_demo_keys(tmp_path / "other").device_public if wrong_key else None
    dev = make_device(tmp_path, keys if device_curve else None, "sessK")
    rx = _receiver_at(dev.keyframe_endpoint, keys if host_curve else None, tmp_path / "out", device_key=other)
    try:
        msgs = _warnings_until(rx, caplog, waited)
    finally:
        rx.close()
        dev.close()
    assert any(said in m for m in msgs), msgs


# ------------------------------------------------------------------ key files named for what they are

def test_a_secret_key_that_is_a_fifo_or_a_folder_is_named_as_such(tmp_path):
    import os

    from stereopath.device.errors import ConfigError
    from stereopath.device.wire.security import load_secret_keypair

    fifo = tmp_path / "device.key_secret"
    os.mkfifo(fifo)
    with pytest.raises(ConfigError, match=r"is a FIFO \(named pipe\), not a regular file"):
        load_secret_keypair(fifo)
    (tmp_path / "dir.key_secret").mkdir()
    with pytest.raises(ConfigError, match="is a directory, not a regular file"):
        load_secret_keypair(tmp_path / "dir.key_secret")
    with pytest.raises(ConfigError, match="key file not found"):
        load_secret_keypair(tmp_path / "missing.key_secret")


def test_a_damaged_acked_record_offers_everything_again(tmp_path):
    """acked.json nested too deep (or not JSON): read as 'nothing acknowledged', so the keyframes are offered."""
    from stereopath.device.streaming.spool import ACKED_NAME, read_acked

    (tmp_path / ACKED_NAME).write_text("[" * 100_000 + "]" * 100_000)
    assert read_acked(tmp_path) == -1
    (tmp_path / ACKED_NAME).write_text('{"acked_seq": true}')
    assert read_acked(tmp_path) == -1


def test_json_nested_too_deep_is_invalid_json_like_any_other(tmp_path):
    import json

    from stereopath.device.formats.fileio import load_json

    (tmp_path / "deep.json").write_text("[" * 100_000 + "]" * 100_000)
    with pytest.raises(json.JSONDecodeError, match="nested too deeply"):
        load_json(tmp_path / "deep.json")
    (tmp_path / "ok.json").write_text('{"a": [1, 2]}')
    assert load_json(tmp_path / "ok.json") == {"a": [1, 2]}
