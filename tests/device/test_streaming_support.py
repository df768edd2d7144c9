"""Helpers shared by the streaming tests (no tests here): devices on random loopback ports, waits."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any, Callable

import numpy as np

from stereopath.device.core.config import from_mapping
from stereopath.device.settings import KeySettings, StreamSettings, nest_moved_keys
from stereopath.device.streaming import DeviceStreamer, KeyframeSpool
from stereopath.device.wire.security import DemoKeys
from stereopath.host.live.store import read_index

LOOPBACK_ANY = "tcp://127.0.0.1:*"


def small_images(seed: int, h: int = 96, w: int = 128) -> tuple[np.ndarray, np.ndarray]:
    """A small textured stereo pair (deterministic)."""
    rng = np.random.default_rng(seed)
    base = rng.integers(0, 255, (h // 8, w // 8), dtype=np.uint8)
    left = np.kron(base, np.ones((8, 8), dtype=np.uint8))
    return left, np.roll(left, 3, axis=1)


def device_config(keys: DemoKeys | None, pose_endpoint: str = LOOPBACK_ANY, keyframe_endpoint: str = LOOPBACK_ANY,
                  **overrides: Any) -> StreamSettings:
    """A ``[stream]`` section; ``overrides`` may use the flat keys of the sub-tables (``max_credit=4``)."""
    base: dict[str, Any] = dict(pose_endpoint=pose_endpoint, keyframe_endpoint=keyframe_endpoint,
                                heartbeat={"ivl_ms": 250, "timeout_ms": 1500, "ttl_ms": 3000}, spool_fsync=False)
    if keys is None:
        base["insecure"] = True
    nested, _ = nest_moved_keys("stream", overrides)
    for key, value in nested.items():
        base[key] = {**base[key], **value} if isinstance(value, dict) and isinstance(base.get(key), dict) else value
    return from_mapping(StreamSettings, base)


def key_settings(keys: DemoKeys | None) -> KeySettings | None:
    return None if keys is None else KeySettings(server_secret=str(keys.device_secret),
                                                 clients_dir=str(keys.clients_dir))


def make_device(tmp: Path, keys: DemoKeys | None, session: str, backlog_roots: Any = (),
                **overrides: Any) -> DeviceStreamer:
    spool = KeyframeSpool(tmp / f"spool_{session}", fsync=False)
    return DeviceStreamer(device_config(keys, **overrides), spool, session, rig_ref=("testrig", "0123456789abcdef"),
                          keys=key_settings(keys), status_interval_s=0.2, backlog_roots=backlog_roots)


def free_ports(n: int) -> list[int]:
    """``n`` loopback TCP ports free right now (for configurations that name their ports)."""
    import socket

    out = []
    for _ in range(n):
        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            out.append(s.getsockname()[1])
    return out


def loopback_stream(**extra: Any) -> dict[str, Any]:
    """A ``[stream]`` table on two free loopback ports, without CURVE."""
    pose, keyframe = free_ports(2)
    return {"insecure": True, "pose_endpoint": f"tcp://127.0.0.1:{pose}",
            "keyframe_endpoint": f"tcp://127.0.0.1:{keyframe}", **extra}


def write_or_enospc(real: Callable[..., Any], full: dict[str, bool]) -> Callable[..., Any]:
    """A stand-in for a write helper (``write_atomic``...) that fails with ENOSPC while ``full["on"]``."""
    import errno

    def write(path: Any, *a: Any, **k: Any) -> Any:
        if full["on"]:
            raise OSError(errno.ENOSPC, "No space left on device", str(path))
        return real(path, *a, **k)
    return write


def kill_9_once_spooled(proc: Any, sessions: Path, n: int) -> Path:
    """SIGKILL the ``device run`` child ``proc`` once its session under ``sessions`` spooled ``n``
    keyframes; returns that session folder."""
    import os
    import signal

    try:
        assert wait_for(lambda: sessions.is_dir() and any(len(list(d.glob("keyframes/*.kf"))) >= n
                                                          for d in sessions.iterdir()), 60, step_s=0.1)
        os.kill(proc.pid, signal.SIGKILL)
        proc.communicate(timeout=20)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    (session,) = list(sessions.iterdir())
    return session


def port_of(endpoint: str) -> int:
    return int(endpoint.rsplit(":", 1)[1])


def wait_for(cond: Callable[[], bool], timeout_s: float, step_s: float = 0.02,
             between: Callable[[], Any] | None = None) -> bool:
    """Poll ``cond`` until true or ``timeout_s``; ``between`` runs each step (e.g. a receiver poll)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if cond():
            return True
        if between is not None:
            between()
        else:
            time.sleep(step_s)
    return cond()


def stored_seqs(out: Path, session: str) -> list[int]:
    d = out / session / "keyframes"
    if not d.is_dir():
        return []
    return sorted(int(p.name[3:-8]) for p in d.glob("kf_*.msgpack"))


def assert_exactly_once(out: Path, session: str, spool: KeyframeSpool) -> None:
    """Every spooled keyframe is in the host store once, byte for byte, and indexed once."""
    seqs = stored_seqs(out, session)
    assert seqs == list(range(spool.count)), f"host holds {seqs}, device spooled 0..{spool.count - 1}"
    d = out / session / "keyframes"
    for seq in seqs:
        assert (d / f"kf_{seq:08d}.msgpack").read_bytes() == spool.read(seq), f"keyframe {seq} differs"
    rows = [r["seq"] for r in read_index(out / session)]
    assert sorted(rows) == seqs, f"index rows {sorted(rows)}"
    assert not list(d.glob("*.tmp"))


def receive_until_done(th: Any, rx: Any) -> None:
    """Poll the receiver ``rx`` while the service thread ``th`` runs (and a little after, for the last
    acknowledgements), then join it and close ``rx``."""
    try:
        while th.is_alive():
            rx.poll(0.02)
        for _ in range(20):
            rx.poll(0.02)
    finally:
        th.join(30)
        rx.close()
