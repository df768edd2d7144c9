"""Issue 15 item 11: the smaller faults (files for folders, zero frames, refused keys, permissions, bogus sessions)."""

from __future__ import annotations

import json
import logging
import os
import stat
import time
from pathlib import Path

import pytest

from stereopath.device.wire.security import generate_keypair, make_demo_keys

pytestmark = pytest.mark.timeout(60)


def _cli(argv):
    from stereopath.host.cli import main

    return main(argv)


@pytest.mark.parametrize("argv", [
    ["odometry", "sim", "--frames", "3"],
    ["demo", "--frames", "8"],
    ["host", "live", "--device", "127.0.0.1:5999", "--insecure", "--duration", "0.1"],
    ["host", "map", "."],
    ["host", "reprocess", "."],
])
def test_out_naming_a_file_is_a_clear_error(tmp_path, capsys, argv):
    f = tmp_path / "a_file"
    f.write_text("x")
    assert _cli(argv + ["--out", str(f)]) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err and "stereopath: error" in err
    assert f.read_text() == "x"


@pytest.mark.parametrize("frames", ["0", "7"])
def test_demo_with_too_few_frames_is_refused(tmp_path, capsys, frames):
    # the simulated rig rests for its first 6 frames: 7 would leave one moving pose to evaluate
    assert _cli(["demo", "--frames", frames, "--out", str(tmp_path / "d")]) == 2
    assert f"--frames must be at least 8 (the simulated rig rests for its first 6 frames" in capsys.readouterr().err
    assert not (tmp_path / "d").exists()


@pytest.fixture(scope="module")
def keys(tmp_path_factory):
    return make_demo_keys(tmp_path_factory.mktemp("keys"))


def test_live_exits_nonzero_when_the_device_refuses_its_key_and_device_logs_it(tmp_path, keys, caplog):
    import shutil

    from tests.device.test_streaming_support import make_device, port_of

    stranger = tmp_path / "stranger"
    generate_keypair(stranger, "laptop2")
    shutil.copy(keys.device_public, stranger / "device.key")
    dev = make_device(tmp_path, keys, "sessK")
    caplog.set_level(logging.WARNING)
    try:
        rc = _cli(["host", "live", "--device", f"127.0.0.1:{port_of(dev.pose_endpoint)}",
                        "--keyframe-port", str(port_of(dev.keyframe_endpoint)), "--keys", str(stranger),
                        "--out", str(tmp_path / "out"), "--duration", "1.5", "--no-fsync"])
    finally:
        dev.close()
    assert rc == 2
    refused = [r for r in caplog.records if "refused a client" in r.getMessage()]
    assert refused and refused[0].levelno == logging.WARNING
    assert len(refused) <= 2  # once per key and address, not once per reconnect attempt


def test_host_live_that_never_hears_from_a_device_says_so(tmp_path, capsys):
    """A wrong port (nothing listening): not a silent exit 0 that a script takes for an empty scan."""
    import socket

    with socket.socket() as s:  # a loopback port nobody listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    out = tmp_path / "out"
    out.mkdir()  # an OUT an earlier run used: its counters are not this run's
    (out / "receiver.json").write_text(json.dumps({"received": {"status": 3}, "link": {"connects": 1}}))
    argv = ["host", "live", "--device", f"127.0.0.1:{port}", "--insecure", "--out", str(out), "--duration", "0.5",
            "--no-fsync"]
    assert _cli(argv) == 1
    err = capsys.readouterr().err
    assert f"no connection to 127.0.0.1:{port} in 0." in err and "Traceback" not in err


def test_host_live_connected_to_a_quiet_device_is_not_an_error(tmp_path, capsys, caplog):
    """Connected (the keyframe socket's handshake), but nothing sent yet: a warning, exit 0."""
    import zmq

    ctx = zmq.Context.instance()
    pub, router = ctx.socket(zmq.PUB), ctx.socket(zmq.ROUTER)
    try:
        port = pub.bind_to_random_port("tcp://127.0.0.1")
        router.bind(f"tcp://127.0.0.1:{port + 1}")
    except zmq.ZMQError:
        pub.close(0)
        router.close(0)
        pytest.skip("the port after a random one is taken")
    try:
        rc = _cli(["host", "live", "--device", f"127.0.0.1:{port}", "--insecure", "--out", str(tmp_path / "out"),
                   "--duration", "1.0", "--no-fsync"])
    finally:
        pub.close(0)
        router.close(0)
    assert rc == 0 and "no connection" not in capsys.readouterr().err
    assert "connected to 127.0.0.1:%d, but nothing arrived" % port in caplog.text


def test_secret_key_is_created_private(tmp_path, monkeypatch):
    def no_chmod(*a, **k):
        raise AssertionError("the secret key must not need a chmod")

    old = os.umask(0o000)
    try:
        monkeypatch.setattr(os, "chmod", no_chmod)
        pub, sec = generate_keypair(tmp_path / "k", "me")
    finally:
        os.umask(old)
    assert stat.S_IMODE(sec.stat().st_mode) == 0o600
    assert stat.S_IMODE(pub.stat().st_mode) == 0o644
    assert not [p for p in (tmp_path / "k").iterdir() if p.name.startswith(".keys-")]
    pub2, sec2 = generate_keypair(tmp_path / "k", "me", overwrite=True)  # overwrite still works
    assert stat.S_IMODE(sec2.stat().st_mode) == 0o600


def test_model_folder_respects_the_umask(tmp_path, monkeypatch):
    from stereopath.host.mapping import fusion, mapper, preview

    for mod, name in ((fusion, "write_mesh"), (fusion, "write_cloud"), (preview, "write_png")):
        monkeypatch.setattr(mod, name, lambda obj, path: path.write_bytes(b"x"))
    result = mapper.MapResult(mesh=None, cloud=None, preview=None, stats={"k": 1})
    old = os.umask(0o077)
    try:
        mapper.write_map(result, tmp_path / "model")
    finally:
        os.umask(old)
    assert stat.S_IMODE((tmp_path / "model").stat().st_mode) == 0o700


def test_bogus_session_ids_are_bounded(tmp_path):
    import zmq

    from stereopath.device.wire.protocol import Pose, encode_pose
    from stereopath.host.live.receiver import Receiver, ReceiverConfig

    ctx = zmq.Context()
    pub = ctx.socket(zmq.PUB)
    port = pub.bind_to_random_port("tcp://127.0.0.1")
    router = ctx.socket(zmq.ROUTER)
    kport = router.bind_to_random_port("tcp://127.0.0.1")
    cfg = ReceiverConfig(f"tcp://127.0.0.1:{port}", f"tcp://127.0.0.1:{kport}", insecure=True, fsync=False,
                         max_new_sessions=3)
    rx = Receiver(cfg, tmp_path / "out")
    try:
        deadline = time.monotonic() + 10
        sent = 0
        while time.monotonic() < deadline and rx.stats.received.pose + rx.stats.rejected < 20:
            pub.send(encode_pose(Pose(f"bogus{sent % 40:03d}", sent, sent + 1, (0.0, 0.0, 0.0),
                                      (0.0, 0.0, 0.0, 1.0))))
            sent += 1
            rx.poll(0.02)
    finally:
        rx.close()
        pub.close(linger=0)
        router.close(linger=0)
        ctx.term()
    folders = [p for p in (tmp_path / "out").iterdir() if p.is_dir()]
    assert len(folders) == 3
    assert rx.stats.rejected_by_reason.get("session_limit", 0) > 0


def test_host_store_is_private_by_default(tmp_path):
    from stereopath.host.live.store import KeyframeStore

    old = os.umask(0o022)
    try:
        KeyframeStore(tmp_path / "live", fsync=False).close()
    finally:
        os.umask(old)
    assert stat.S_IMODE((tmp_path / "live").stat().st_mode) == 0o700


@pytest.mark.parametrize("argv", [
    ["odometry", "sim", "--frames", "3"],
    ["demo", "--frames", "8"],
    ["host", "map", "."],
    ["host", "reprocess", "."],
])
def test_out_in_a_folder_that_cannot_be_written_is_refused_before_any_work(tmp_path, capsys, monkeypatch, argv):
    """A read-only or foreign --out is named before the work starts (the odometry used to estimate the whole
    path first, then fail writing it)."""
    from stereopath.device.formats import fileio

    locked = tmp_path / "locked"
    locked.mkdir()
    real = os.access
    monkeypatch.setattr(fileio.os, "access", lambda p, mode, **kw: Path(p) != locked and real(p, mode, **kw))
    for out in (locked, locked / "new" / "deeper"):
        assert _cli(argv + ["--out", str(out)]) == 2
        err = capsys.readouterr().err
        assert "Traceback" not in err and f"cannot write in {locked}" in err
        assert list(locked.iterdir()) == []


def test_a_refused_write_is_one_line_not_a_traceback(tmp_path, capsys, monkeypatch):
    """An OSError (disk full, read-only file system) that reaches the command line is printed on one line."""
    import errno

    from stereopath.host.commands import sim

    def full(args):
        raise OSError(errno.ENOSPC, "No space left on device", str(tmp_path / "s" / "x.png"))

    monkeypatch.setattr(sim, "run", full)
    assert _cli(["sim", "--out", str(tmp_path / "s"), "--frames", "2"]) == 74
    err = capsys.readouterr().err
    assert "Traceback" not in err and "No space left on device" in err and "x.png" in err


def test_the_model_is_written_inside_its_folder(tmp_path, monkeypatch):
    """write_map's temporary folder is inside the model folder (a mount point, or a parent that cannot be
    written, works), a killed writer's old leftover is removed (not one another writer may be using), and
    only the four files are added."""
    from stereopath.host.mapping import fusion, mapper, preview

    out = tmp_path / "parent" / "model"
    seen = []

    def write(obj, path):
        seen.append(path.parent.parent)
        path.write_bytes(b"x")

    for mod, name in ((fusion, "write_mesh"), (fusion, "write_cloud"), (preview, "write_png")):
        monkeypatch.setattr(mod, name, write)
    out.mkdir(parents=True)
    dead, busy = out / f"{mapper.MAP_TEMP_PREFIX}dead.tmp", out / f"{mapper.MAP_TEMP_PREFIX}busy.tmp"
    dead.mkdir()  # left by a writer that was killed two hours ago
    os.utime(dead, (time.time() - 7200, time.time() - 7200))
    busy.mkdir()  # another writer's, now
    (out / "report.json").write_text("{}")
    mapper.write_map(mapper.MapResult(mesh=None, cloud=None, preview=None, stats={"k": 1}), out)
    assert seen == [out] * 3
    assert sorted(p.name for p in out.iterdir()) == sorted([*mapper.MAP_FILES, "report.json", busy.name])
    assert [p.name for p in out.parent.iterdir()] == ["model"]


def test_an_unknown_feature_preset_is_refused_before_the_odometry_runs(tmp_path, capsys):
    """It used to be found by every keyframe's background job (a traceback each), the run ending with exit 0."""
    from stereopath.device.errors import ConfigError
    from stereopath.device.core.stereo_config import AsiftWork

    with pytest.raises(ConfigError, match="unknown feature preset 'nope'"):
        AsiftWork(feature_preset="nope")
    assert _cli(["odometry", "sim", "--frames", "3", "--preset", "nope", "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err and "unknown feature preset 'nope'" in err
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("frames", ["-3", "0", "1"])
def test_odometry_refuses_fewer_than_two_frames(tmp_path, capsys, frames):
    assert _cli(["odometry", "sim", "--frames", frames, "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err and f"--frames must be at least 2 (a path needs two frames), got {frames}" in err
    assert not (tmp_path / "o").exists()


def test_cut_torn_tail(tmp_path):
    from stereopath.device.formats.fileio import cut_torn_tail

    p = tmp_path / "rows.txt"
    assert cut_torn_tail(p) == 0  # missing
    p.write_bytes(b"")
    assert cut_torn_tail(p) == 0
    p.write_bytes(b"a 1\nb 2\n")
    assert cut_torn_tail(p) == 0 and p.read_bytes() == b"a 1\nb 2\n"
    p.write_bytes(b"a 1\nb 2\nc")
    assert cut_torn_tail(p) == 1 and p.read_bytes() == b"a 1\nb 2\n"
    p.write_bytes(b"only a torn line")
    assert cut_torn_tail(p) == 16 and p.read_bytes() == b""
    p.write_bytes(b"x" * 100 + b"\n" + b"y" * 50)
    assert cut_torn_tail(p, window=20) == 0 and p.stat().st_size == 151  # no newline in reach: not cut


@pytest.mark.parametrize("argv,option", [
    (["host", "live", "--device", "127.0.0.1:5999", "--insecure", "--out", "o", "--duration"], "--duration"),
    (["host", "reprocess", "s", "--out", "o", "--task-cpus"], "--task-cpus"),
    (["host", "reprocess", "s", "--out", "o", "--task-memory-gb"], "--task-memory-gb"),
    (["features", "a.png", "b.png", "--tolerance"], "--tolerance"),
    (["host", "map", "s", "--out", "o", "--voxel-mm"], "--voxel-mm"),
    (["device", "calibrate-stereo", "d", "--square-mm"], "--square-mm"),
    (["device", "calibrate-stereo", "d", "--square-mm", "20", "--max-rms"], "--max-rms"),
    (["device", "run", "--duration"], "--duration"),
    (["device", "run", "--wait-for-host"], "--wait-for-host"),
    (["device", "run", "--drain"], "--drain"),
])
@pytest.mark.parametrize("value", ["nan", "inf", "-1"])
def test_numeric_options_refuse_nan_inf_and_negatives(capsys, argv, option, value):
    """nan passes every `value < 0` check (all comparisons with nan are false): each number is checked as parsed."""
    with pytest.raises(SystemExit) as info:
        _cli(argv + [value])
    assert info.value.code == 2
    assert f"argument {option}: must be a finite number" in capsys.readouterr().err


def test_an_out_name_too_long_is_one_line(tmp_path, capsys):
    assert _cli(["host", "reprocess", str(tmp_path), "--out", str(tmp_path / ("x" * 300))]) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err and "File name too long" in err
