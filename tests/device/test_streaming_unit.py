"""Streaming pieces without the network: configuration, endpoint rules, keys, spool, host store, views."""

from __future__ import annotations

import argparse
import io
import logging
import os
import stat

import numpy as np
import pytest

from stereopath.device.core.config import from_mapping
from stereopath.device.errors import ConfigError, DatasetError
from stereopath.device.wire.protocol import Status, encode_keyframe, make_keyframe
from stereopath.device.settings import StreamSettings
from stereopath.device.streaming import KeyframeSpool
from stereopath.device.wire.security import (
    authorized_keys, check_loopback_endpoint, generate_keypair, load_host_keys, load_secret_keypair, make_demo_keys)
from stereopath.host.live.store import KeyframeStore, list_sessions, load_keyframe, read_index
from stereopath.host.live.view import TerminalView, summary_lines
from stereopath.host.live.receiver import Receiver
from stereopath.host.live.receiver_config import ReceiverConfig, endpoints_from_address
from stereopath.host.live.receiver_stats import LiveState, ReceiverStats
from tests.device.test_streaming_support import make_device, small_images


def _kf(session: str, seq: int):
    left, right = small_images(seq)
    T = np.eye(4)
    T[:3, 3] = [seq * 0.1, 0.0, 0.0]
    kf = make_keyframe(session, seq, seq * 10, 1000 + seq, T, (left, right), ("rig", "0123456789abcdef"), "png")
    return kf, encode_keyframe(kf)


# ----------------------------------------------------------------------------- configuration and endpoints


def test_stream_config_from_mapping_rejects_unknown_and_out_of_range():
    cfg = from_mapping(StreamSettings, {"pose_endpoint": "tcp://*:6000", "bounds": {"max_credit": 4}})
    assert cfg.bounds.max_credit == 4 and cfg.keyframe_endpoint == "tcp://*:5556"
    with pytest.raises(ConfigError, match="bogus"):
        from_mapping(StreamSettings, {"bogus": 1})
    with pytest.raises(ConfigError, match=r"stream\.bounds\.max_credit"):
        from_mapping(StreamSettings, {"bounds": {"max_credit": 0}})
    with pytest.raises(ConfigError, match=r"images\.encoding"):
        from_mapping(StreamSettings, {"images": {"encoding": "bmp"}})


@pytest.mark.parametrize("ep", ["tcp://127.0.0.1:5555", "tcp://127.0.0.1:*", "tcp://127.8.9.10:1", "tcp://[::1]:5",
                                "tcp://localhost:5555", "ipc:///tmp/x", "inproc://x"])
def test_loopback_endpoints_allowed(ep):
    check_loopback_endpoint(ep)


@pytest.mark.parametrize("ep", ["tcp://*:5555", "tcp://0.0.0.0:5555", "tcp://192.168.1.20:5555", "tcp://lo:5555",
                                "tcp://example.com:5555", "tcp://[::]:5555", "tcp://10.0.0.1;127.0.0.1:5555",
                                "udp://127.0.0.1:5", "5555"])
def test_non_loopback_endpoints_refused_without_curve(ep):
    with pytest.raises(ConfigError):
        check_loopback_endpoint(ep)


def test_insecure_device_refuses_wildcard_bind(tmp_path):
    with pytest.raises(ConfigError, match="loopback"):
        make_device(tmp_path, None, "s1", pose_endpoint="tcp://*:0")


def test_insecure_receiver_refuses_remote_device(tmp_path):
    cfg = ReceiverConfig(*endpoints_from_address("192.168.4.1"), insecure=True)
    with pytest.raises(ConfigError, match="loopback"):
        Receiver(cfg, tmp_path)
    with pytest.raises(ConfigError, match="--keys"):
        ReceiverConfig(*endpoints_from_address("192.168.4.1"))


@pytest.mark.parametrize("address,expected", [
    ("pi.local", ("tcp://pi.local:5555", "tcp://pi.local:5556")),
    ("10.0.0.7:6000", ("tcp://10.0.0.7:6000", "tcp://10.0.0.7:6001")),
    ("tcp://127.0.0.1:7000", ("tcp://127.0.0.1:7000", "tcp://127.0.0.1:7001")),
    ("[::1]:7000", ("tcp://[::1]:7000", "tcp://[::1]:7001")),
    ("[fe80::1]", ("tcp://[fe80::1]:5555", "tcp://[fe80::1]:5556")),
])
def test_endpoints_from_address(address, expected):
    assert endpoints_from_address(address) == expected


@pytest.mark.parametrize("address", ["", "host:0", "host:99999", "host:abc", "fe80::1:5555", "*:5555", "[::1"])
def test_endpoints_from_bad_address(address):
    with pytest.raises(ConfigError):
        endpoints_from_address(address)


def test_explicit_keyframe_port():
    assert endpoints_from_address("h:1", keyframe_port=9) == ("tcp://h:1", "tcp://h:9")


# ----------------------------------------------------------------------------- keys


def test_generate_keypair_and_refuse_overwrite(tmp_path):
    pub, sec = generate_keypair(tmp_path / "k", "laptop")
    assert pub.name == "laptop.key" and sec.name == "laptop.key_secret"
    assert stat.S_IMODE(os.stat(sec).st_mode) == 0o600
    public, secret = load_secret_keypair(sec)
    assert len(public) == 40 and len(secret) == 40
    with pytest.raises(ConfigError, match="already exist"):
        generate_keypair(tmp_path / "k", "laptop")
    generate_keypair(tmp_path / "k", "laptop", overwrite=True)
    with pytest.raises(ConfigError, match="key name"):
        generate_keypair(tmp_path / "k", "../evil")
    with pytest.raises(ConfigError, match="no secret key"):
        load_secret_keypair(pub)


def test_keys_command(tmp_path, capsys):
    from stereopath.host.commands import keys

    parser = argparse.ArgumentParser()
    keys.add_arguments(parser)
    assert keys.run(parser.parse_args([str(tmp_path / "d"), "--name", "device"])) == 0
    assert (tmp_path / "d" / "device.key").is_file() and (tmp_path / "d" / "device.key_secret").is_file()
    assert "device.key_secret" in capsys.readouterr().out


def test_demo_keys_layout_and_host_key_errors(tmp_path):
    keys = make_demo_keys(tmp_path / "keys")
    host_pub, _, device_pub = load_host_keys(keys.host_keys_dir)
    assert device_pub == load_secret_keypair(keys.device_secret)[0]
    assert [p.name for p in authorized_keys(keys.clients_dir)] == ["host.key"]
    assert host_pub == load_secret_keypair(keys.host_secret)[0]
    (keys.host_keys_dir / "device.key").unlink()
    with pytest.raises(ConfigError, match="device.key"):
        load_host_keys(keys.host_keys_dir)
    generate_keypair(keys.host_keys_dir, "second")
    with pytest.raises(ConfigError, match="exactly one"):
        load_host_keys(keys.host_keys_dir)
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(ConfigError, match="no authorised host keys"):
        authorized_keys(empty)


# ----------------------------------------------------------------------------- spool


def test_spool_append_read_resume(tmp_path):
    spool = KeyframeSpool(tmp_path / "sp", fsync=True)
    assert spool.count == 0 and spool.last_seq == -1
    spool.append(0, b"zero")
    spool.append(1, b"one")
    assert spool.read(1) == b"one" and spool.seqs() == [0, 1]
    with pytest.raises(DatasetError, match="expected seq 2"):
        spool.append(5, b"x")
    with pytest.raises(DatasetError, match="not in spool"):
        spool.read(2)
    (tmp_path / "sp" / "00000002.kf.tmp").write_bytes(b"partial")  # an interrupted write
    again = KeyframeSpool(tmp_path / "sp")
    assert again.count == 2 and not list((tmp_path / "sp").glob("*.tmp"))
    (tmp_path / "sp" / "00000005.kf").write_bytes(b"stray")
    with pytest.raises(DatasetError, match="not contiguous"):
        KeyframeSpool(tmp_path / "sp")


# ----------------------------------------------------------------------------- host store


def test_store_dedup_acked_and_persistence(tmp_path):
    store = KeyframeStore(tmp_path, fsync=False)
    for seq in (0, 1, 3):
        kf, data = _kf("sessA", seq)
        assert store.put(kf, data) is True
    kf1, data1 = _kf("sessA", 1)
    assert store.put(kf1, data1) is False  # duplicate
    assert store.session("sessA").acked_seq == 1  # 2 is missing
    store.set_last_session("sessA")
    store.close()
    reopened = KeyframeStore(tmp_path, fsync=False)
    assert reopened.hello_state() == ("sessA", 1)
    kf2, data2 = _kf("sessA", 2)
    reopened.put(kf2, data2)
    assert reopened.hello_state() == ("sessA", 3)
    assert [r["seq"] for r in read_index(tmp_path / "sessA")] == [0, 1, 3, 2]
    back = load_keyframe(tmp_path / "sessA" / "keyframes" / "kf_00000003.msgpack")
    assert back.seq == 3 and back.frame_seq == 30
    assert list_sessions(tmp_path) == ["sessA"]
    reopened.close()


def test_store_rebuilds_index_after_crash(tmp_path):
    store = KeyframeStore(tmp_path, fsync=False)
    for seq in range(3):
        store.put(*_kf("s", seq))
    store.close()
    kdir = tmp_path / "s" / "keyframes"
    # a crash between the rename and the index line: a file the index does not list, plus a temp file
    kf, data = _kf("s", 3)
    (kdir / "kf_00000003.msgpack").write_bytes(data)
    (kdir / "kf_00000004.msgpack.tmp").write_bytes(b"partial")
    store = KeyframeStore(tmp_path, fsync=False)
    sess = store.session("s")
    assert sess.acked_seq == 3
    assert sorted(r["seq"] for r in read_index(tmp_path / "s")) == [0, 1, 2, 3]
    assert not list(kdir.glob("*.tmp"))
    store.close()


def test_store_drops_corrupt_file_on_rebuild(tmp_path):
    store = KeyframeStore(tmp_path, fsync=False)
    store.put(*_kf("s", 0))
    store.close()
    (tmp_path / "s" / "keyframes" / "kf_00000001.msgpack").write_bytes(b"garbage")
    store = KeyframeStore(tmp_path, fsync=False)
    assert store.session("s").acked_seq == 0
    assert not (tmp_path / "s" / "keyframes" / "kf_00000001.msgpack").exists()
    store.close()


def test_receiver_stats_json_round_trip():
    st = ReceiverStats()
    st.received.pose = 5
    st.rejected_by_reason["malformed"] = 2
    st.duplicates = 1
    back = ReceiverStats.from_json(st.to_json())
    assert back.to_json() == st.to_json() and back.rejected == 2


# ----------------------------------------------------------------------------- terminal view


class _FakeReceiver:
    def __init__(self):
        from stereopath.device.wire.protocol import Pose

        self.live = LiveState(session_id="sessA", pose=Pose("sessA", 3, 10, (1.0, 2.0, 3.0), (0, 0, 0, 1), "ok", 99),
                              speed_m_s=0.5, pose_rate_hz=20.0, keyframe_rate_hz=2.0, acked_seq=4,
                              status=Status("sessA", 1, 20.0, 200.0, keyframes_spooled=7, temperature_c=51.0),
                              connected=True, link_quality="good")
        self.stats = ReceiverStats()


def test_terminal_view_tty_and_log_modes(caplog):
    rx = _FakeReceiver()
    lines = summary_lines(rx)
    assert "sessA" in lines[0] and "+1.000" in lines[0] and "backlog 2" in lines[1] and "51C" in lines[2]
    buf = io.StringIO()
    view = TerminalView(buf, tty=True)
    view.update(rx)
    view.update(rx)
    text = buf.getvalue()
    assert text.count("\x1b[2K") == 6 and "\x1b[3F" in text
    quiet = io.StringIO()
    with caplog.at_level(logging.INFO, logger="stereopath.host.live.view"):
        logged = TerminalView(quiet, tty=False, log_interval_s=0.0)
        logged.update(rx)
    assert quiet.getvalue() == "" and "link good" in caplog.text


def test_pose_publisher_counts_subscriptions_and_a_pose_sent_after_one_arrives(tmp_path):
    """``--wait-for-host`` starts capture once a host's pose subscription has reached the publisher: the
    XPUB hands each subscription up, and a pose published after it is not lost to the slow-joiner gap."""
    import time

    import zmq

    from stereopath.device.streaming.pose_publisher import PosePublisher
    from tests.device.test_streaming_support import device_config

    ctx = zmq.Context()
    pub = PosePublisher(ctx, device_config(None), None)
    sub = ctx.socket(zmq.SUB)
    try:
        assert pub.subscriptions() == 0
        sub.connect(pub.endpoint)
        sub.setsockopt(zmq.SUBSCRIBE, b"")
        deadline = time.monotonic() + 10
        while pub.subscriptions() == 0 and time.monotonic() < deadline:
            time.sleep(0.01)
        assert pub.subscriptions() == 1
        assert pub.send(b"first pose")
        assert sub.poll(5000) and sub.recv() == b"first pose"
        second = ctx.socket(zmq.SUB)  # every host's subscription counts (XPUB_VERBOSE), not only the first
        second.connect(pub.endpoint)
        second.setsockopt(zmq.SUBSCRIBE, b"")
        deadline = time.monotonic() + 10
        while pub.subscriptions() < 2 and time.monotonic() < deadline:
            time.sleep(0.01)
        second.close(linger=0)
        assert pub.subscriptions() == 2
    finally:
        sub.close(linger=0)
        pub.close()
        ctx.term()


def test_the_last_poses_of_a_run_reach_a_connected_host_when_the_publisher_closes():
    """Closing right after a burst: without the flush, ZeroMQ drops what its I/O thread has not sent yet."""
    import dataclasses
    import time

    import zmq

    from stereopath.device.streaming.pose_publisher import PosePublisher
    from tests.device.test_streaming_support import device_config

    ctx = zmq.Context()
    cfg = device_config(None, pose_sndhwm=5000)
    pub = PosePublisher(ctx, cfg, None)
    sub = ctx.socket(zmq.SUB)
    sub.setsockopt(zmq.RCVHWM, 5000)
    got = 0
    try:
        sub.connect(pub.endpoint)
        sub.setsockopt(zmq.SUBSCRIBE, b"")
        deadline = time.monotonic() + 10
        while pub.subscriptions() == 0 and time.monotonic() < deadline:
            time.sleep(0.01)
        payload = bytes(2000)  # a backlog the I/O thread cannot have sent by the close (linger 0 loses most of it)
        sent = sum(pub.send(payload) for _ in range(3000))
        pub.close(flush_ms=cfg.bounds.pose_flush_ms)
        while sub.poll(2000):
            sub.recv()
            got += 1
    finally:
        sub.close(linger=0)
        pub.close()  # (closed already unless the test failed before)
        ctx.term()
    assert cfg.bounds.pose_flush_ms > 0 and sent == 3000
    assert got == sent
