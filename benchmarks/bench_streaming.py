"""Streaming benchmark: pose size and latency, keyframe throughput, device CPU, full-size fault runs.

The device runs as a separate process (this script with ``--role device``); the host is this
process (``Receiver``) or, for the fault runs, ``python -m stereopath.host host live``.  Everything is on
loopback with CURVE on.  Keyframes are 640x480 stereo pairs cut from the EuRoC V1_01 head
(synthetic texture if the data is absent), JPEG quality 90 unless said otherwise.

Targets (issue 4): pose publish -> receive p99 <= 5 ms; pose message <= 128 bytes; keyframe
channel >= 20 keyframes/s; device CPU on streaming <= 10 % of one core at 20 Hz poses and
2 keyframes/s (process CPU with the streamer minus the same capture loop without it).

    .venv/bin/python benchmarks/bench_streaming.py [--runs 3] [--seconds 15] [--sections latency,faults]
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import signal
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
DATA = Path(os.environ.get("STEREOPATH_DATA", ROOT.parent / "shared" / "data")) / "euroc_v1_01_head" / "mav0"


# ----------------------------------------------------------------------------- shared helpers


def load_pairs(n: int = 8) -> tuple[list[tuple[np.ndarray, np.ndarray]], str]:
    import cv2

    left_dir, right_dir = DATA / "cam0" / "data", DATA / "cam1" / "data"
    if left_dir.is_dir():
        names = sorted(p.name for p in left_dir.glob("*.png"))[:n]
        pairs = []
        for name in names:
            left = cv2.imread(str(left_dir / name), cv2.IMREAD_GRAYSCALE)
            right = cv2.imread(str(right_dir / name), cv2.IMREAD_GRAYSCALE)
            if left is None or right is None:
                continue
            x0 = (left.shape[1] - 640) // 2
            pairs.append((np.ascontiguousarray(left[:480, x0:x0 + 640]), np.ascontiguousarray(right[:480, x0:x0 + 640])))
        if pairs:
            return pairs, "EuRoC V1_01 (cropped to 640x480)"
    rng = np.random.default_rng(0)
    pairs = []
    for _ in range(n):
        base = cv2.resize(rng.integers(0, 255, (60, 80), dtype=np.uint8), (640, 480), interpolation=cv2.INTER_CUBIC)
        pairs.append((base, np.roll(base, 12, axis=1)))
    return pairs, "synthetic texture 640x480"


def pct(values: list[float], q: float) -> float:
    return float(np.percentile(np.asarray(values), q)) if values else float("nan")


def wait_file(path: Path, timeout_s: float) -> dict:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if path.is_file():
            try:
                return json.loads(path.read_text())
            except ValueError:
                pass
        time.sleep(0.02)
    raise RuntimeError(f"timed out waiting for {path}")


def start_device(work: Path, keys_root: Path, name: str, **opts) -> tuple[subprocess.Popen, dict, Path]:
    ready, result = work / f"{name}.ready.json", work / f"{name}.result.json"
    cmd = [sys.executable, __file__, "--role", "device", "--keys-root", str(keys_root), "--spool", str(work / name),
           "--session", name, "--ready", str(ready), "--result", str(result), "--stop-file", str(work / f"{name}.stop")]
    for k, v in opts.items():
        flag = "--" + k.replace("_", "-")
        if v is True:
            cmd.append(flag)
        elif v is not False and v is not None:
            cmd += [flag, str(v)]
    proc = subprocess.Popen(cmd, cwd=ROOT)
    return proc, wait_file(ready, 30), result


def stop_device(proc: subprocess.Popen, work: Path, name: str, result: Path) -> dict:
    (work / f"{name}.stop").touch()
    proc.wait(120)
    return json.loads(result.read_text())


def receiver_config(ready: dict, keys_root: Path, **kw):
    from stereopath.host.live.receiver_config import ReceiverConfig

    return ReceiverConfig(ready["pose_endpoint"], ready["keyframe_endpoint"], keys_dir=str(keys_root / "host"), **kw)


def kf_count(out: Path, session: str) -> int:
    d = out / session / "keyframes"
    return len(list(d.glob("kf_*.msgpack"))) if d.is_dir() else 0


# ----------------------------------------------------------------------------- device role


def device_role(args: argparse.Namespace) -> int:
    from stereopath.device.settings import KeySettings, StreamImageSettings, StreamSettings
    from stereopath.device.streaming import DeviceStreamer, KeyframeSpool

    pairs, _ = load_pairs()
    keys = Path(args.keys_root)
    cfg = StreamSettings(pose_endpoint="tcp://127.0.0.1:*", keyframe_endpoint="tcp://127.0.0.1:*",
                         images=StreamImageSettings(encoding=args.encoding), spool_fsync=True)
    key_files = KeySettings(server_secret=str(keys / "device" / "device.key_secret"),
                            clients_dir=str(keys / "device" / "clients"))
    spool = KeyframeSpool(args.spool)
    streamer = None if (args.no_stream or args.bare) else DeviceStreamer(cfg, spool, args.session, keys=key_files)
    bare = None
    if args.bare:  # reference: a plain CURVE PUB socket sending the same bytes from the capture loop
        import zmq

        from stereopath.device.wire.protocol import encode_pose, pose_from_matrix
        from stereopath.device.wire.security import load_secret_keypair, start_authenticator

        bare_ctx = zmq.Context()
        bare_auth = start_authenticator(bare_ctx, key_files.clients_dir)
        bare = bare_ctx.socket(zmq.PUB)
        bare.linger = 0
        bare.curve_publickey, bare.curve_secretkey = load_secret_keypair(key_files.server_secret)
        bare.curve_server = True
        bare.bind("tcp://127.0.0.1:*")
    if streamer is not None and args.prefill:
        from stereopath.device.wire.protocol import encode_keyframe, make_keyframe

        for i in range(args.prefill):
            left, right = pairs[i % len(pairs)]
            kf = make_keyframe(args.session, i, i, i, np.eye(4), (left, right), ("euroc", "0123456789abcdef"),
                               args.encoding)
            spool.append(i, encode_keyframe(kf))
    Path(args.ready).write_text(json.dumps({
        "pose_endpoint": streamer.pose_endpoint if streamer else (bare.last_endpoint.decode() if bare else ""),
        "pid": os.getpid(),
        "keyframe_endpoint": streamer.keyframe_endpoint if streamer else ""}))
    if args.start_delay:
        time.sleep(args.start_delay)
    n_frames = int(round(args.seconds * args.pose_hz))
    kf_every = max(1, int(round(args.pose_hz / args.kf_hz))) if args.kf_hz > 0 else 0
    lateness, calls = [], []
    ru0 = resource.getrusage(resource.RUSAGE_SELF)
    t_start = time.monotonic()
    T = np.eye(4)
    for i in range(n_frames):
        scheduled = t_start + i / args.pose_hz
        now = time.monotonic()
        if scheduled > now:
            time.sleep(scheduled - now)
        lateness.append(time.monotonic() - scheduled)
        T[0, 3] = 0.01 * i
        c0 = time.perf_counter()
        if bare is not None:
            bare.send(encode_pose(pose_from_matrix(args.session, i, time.monotonic_ns(), T, inliers=150)), zmq.NOBLOCK)
        if streamer is not None:
            streamer.publish_pose(i, time.monotonic_ns(), T, inliers=150)
            if kf_every and i % kf_every == 0:
                left, right = pairs[(i // kf_every) % len(pairs)]
                streamer.offer_keyframe(i, time.monotonic_ns(), T, left, right)
            if i % int(args.pose_hz) == 0:
                streamer.publish_status(frame_rate_hz=args.pose_hz, recorder_state="recording")
        calls.append(time.perf_counter() - c0)
    t_prod = time.monotonic() - t_start
    if streamer is not None and kf_every:
        streamer.wait_spooled(spool.count, 60)
    ru1 = resource.getrusage(resource.RUSAGE_SELF)
    cpu_s = (ru1.ru_utime - ru0.ru_utime) + (ru1.ru_stime - ru0.ru_stime)
    stop = Path(args.stop_file)
    deadline = time.monotonic() + args.serve_max_s
    while not stop.exists() and time.monotonic() < deadline:
        time.sleep(0.05)
    stats = streamer.stats() if streamer is not None else {}
    if streamer is not None:
        streamer.close()
    if bare is not None:
        bare.close(linger=0)
        bare_auth.stop()
        bare_ctx.term()
    Path(args.result).write_text(json.dumps({
        "cpu_s": cpu_s, "wall_s": t_prod, "frames": n_frames, "max_lateness_s": max(lateness, default=0.0),
        "p99_lateness_s": pct(lateness, 99), "max_call_s": max(calls, default=0.0), "p99_call_s": pct(calls, 99),
        "maxrss_kb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss, "spool_count": spool.count,
        "stats": {k: v for k, v in stats.items() if k != "peers"}}))
    return 0


# ----------------------------------------------------------------------------- sections


def bench_sizes(pairs) -> None:
    from stereopath.device.wire.protocol import Pose, encode_keyframe, encode_pose, make_keyframe, new_session_id

    real = encode_pose(Pose(new_session_id(), 123456, time.monotonic_ns(), (1.234, -0.5, 2.0),
                            (0.1, 0.2, 0.3, float(np.sqrt(1 - 0.14))), "ok", 250, False))
    worst = encode_pose(Pose("x" * 31, 2**32 - 1, 2**63 - 1, (-999999.0,) * 3, (0.5, 0.5, 0.5, 0.5), "imu_only",
                             65535, True))
    print(f"pose message: {len(real)} bytes typical, {len(worst)} bytes worst case (target <= 128)")
    left, right = pairs[0]
    for enc in ("jpg", "png", "raw"):
        t0 = time.perf_counter()
        kf = make_keyframe("s", 0, 0, 0, np.eye(4), (left, right), ("r", "0123456789abcdef"), enc)
        data = encode_keyframe(kf)
        dt = time.perf_counter() - t0
        print(f"keyframe 640x480 stereo {enc:>3}: {len(data) / 1024:7.1f} KiB, encode {dt * 1e3:6.1f} ms")


def _bare_latency(work: Path, keys_root: Path, name: str, seconds: float) -> list[float]:
    """Reference: the same pose bytes over a plain CURVE PUB -> SUB pair (no streamer, no receiver)."""
    import zmq

    from stereopath.device.wire.protocol import decode_pose
    from stereopath.device.wire.security import load_host_keys

    proc, ready, result = start_device(work, keys_root, name, seconds=seconds, pose_hz=20, kf_hz=0, bare=True,
                                       start_delay=1.0)
    ctx = zmq.Context()
    sub = ctx.socket(zmq.SUB)
    sub.linger = 0
    sub.curve_publickey, sub.curve_secretkey, sub.curve_serverkey = load_host_keys(keys_root / "host")
    sub.setsockopt(zmq.SUBSCRIBE, b"")
    sub.connect(ready["pose_endpoint"])
    lat: list[float] = []
    t_end = time.monotonic() + seconds + 3.0
    while time.monotonic() < t_end and len(lat) < int(seconds * 20) - 2:
        if sub.poll(50):
            p = decode_pose(sub.recv())
            lat.append((time.monotonic_ns() - p.t_ns) * 1e-6)
    sub.close(linger=0)
    ctx.term()
    stop_device(proc, work, name, result)
    return lat


def bench_latency_cpu(work: Path, keys_root: Path, runs: int, seconds: float) -> None:
    from stereopath.host.live.receiver import Receiver

    print(f"\n-- pose latency and device CPU: 20 Hz poses + 2 keyframes/s, {seconds:.0f} s per run, CURVE; "
          f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cpus")
    base = []
    for r in range(runs):
        proc, ready, result = start_device(work, keys_root, f"base{r}", no_stream=True, seconds=seconds,
                                           pose_hz=20, kf_hz=2)
        base.append(stop_device(proc, work, f"base{r}", result))
    base_cpu = statistics.median(b["cpu_s"] / b["wall_s"] for b in base)
    p50s, p99s, cpus, ref99 = [], [], [], []
    for r in range(runs):
        ref = _bare_latency(work, keys_root, f"bare{r}", seconds)
        ref99.append(pct(ref, 99))
        name = f"lat{r}"
        proc, ready, result = start_device(work, keys_root, name, seconds=seconds, pose_hz=20, kf_hz=2,
                                           start_delay=1.0)
        lat: list[float] = []
        rx = Receiver(receiver_config(ready, keys_root, fsync=True), work / f"out_{name}",
                      on_pose=lambda p: lat.append((time.monotonic_ns() - p.t_ns) * 1e-6))
        t_end = time.monotonic() + seconds + 3.0
        while time.monotonic() < t_end and proc.poll() is None and not (work / f"{name}.result.json").exists():
            rx.poll(0.05)
            if len(lat) >= int(seconds * 20) - 2 and kf_count(work / f"out_{name}", name) >= int(seconds * 2):
                break
        res = stop_device(proc, work, name, result)
        got_kf = kf_count(work / f"out_{name}", name)
        rx.close()
        p50s.append(pct(lat, 50))
        p99s.append(pct(lat, 99))
        cpus.append(res["cpu_s"] / res["wall_s"])
        print(f"run {r}: {len(lat)} poses, p50 {p50s[-1]:.2f} ms, p99 {p99s[-1]:.2f} ms, max {max(lat):.2f} ms "
              f"(bare PUB/SUB reference: p50 {pct(ref, 50):.2f}, p99 {ref99[-1]:.2f} ms); "
              f"{got_kf}/{res['spool_count']} keyframes; device CPU {100 * cpus[-1]:.1f} % "
              f"(loop alone {100 * base_cpu:.1f} %), producer call p99 {1e3 * res['p99_call_s']:.2f} ms, "
              f"max {1e3 * res['max_call_s']:.2f} ms")
    stream_cpu = statistics.median(cpus) - base_cpu
    print(f"pose latency p99 (median of runs): {statistics.median(p99s):.2f} ms (target <= 5 ms); "
          f"p50 {statistics.median(p50s):.2f} ms; ratio to the bare PUB/SUB reference p99 "
          f"{statistics.median(p99s) / statistics.median(ref99):.2f}")
    print(f"device CPU on streaming: {100 * stream_cpu:.1f} % of one core (target <= 10 %), "
          f"incl. JPEG encoding and spool fsync")


def bench_throughput(work: Path, keys_root: Path, runs: int, n: int) -> None:
    from stereopath.host.live.receiver import Receiver

    print(f"\n-- keyframe channel throughput: {n} spooled 640x480 stereo keyframes, CURVE, loopback")
    for enc, fsync_options in (("jpg", (True, False)), ("png", (True,))):
        for fsync in fsync_options:
            rates, mbs = [], []
            for r in range(runs if enc == "jpg" else 1):
                name = f"tp_{enc}_{int(fsync)}_{r}"
                proc, ready, result = start_device(work, keys_root, name, seconds=0, pose_hz=20, kf_hz=0,
                                                   prefill=n, encoding=enc)
                out = work / f"out_{name}"
                first: list[float] = []
                rx = Receiver(receiver_config(ready, keys_root, fsync=fsync, window=16), out,
                              on_keyframe=lambda kf, new: first.append(time.perf_counter()) if not first else None)
                deadline = time.monotonic() + 120
                while rx.store.session(name).acked_seq < n - 1 and time.monotonic() < deadline:
                    rx.poll(0.005)
                t_last = time.perf_counter()
                nbytes = sum(p.stat().st_size for p in (out / name / "keyframes").glob("kf_*.msgpack"))
                rx.close()
                stop_device(proc, work, name, result)
                dt = t_last - first[0]
                rates.append((n - 1) / dt)
                mbs.append(nbytes / dt / 2**20)
            print(f"{enc:>3}, host fsync {'on ' if fsync else 'off'}: {statistics.median(rates):6.1f} keyframes/s "
                  f"({statistics.median(mbs):5.1f} MiB/s; runs {', '.join(f'{x:.1f}' for x in rates)}) "
                  f"(target >= 20)")


def _live_host(ready: dict, keys_root: Path, out: Path, log: Path) -> subprocess.Popen:
    host, port = ready["pose_endpoint"].rsplit(":", 1)
    kport = ready["keyframe_endpoint"].rsplit(":", 1)[1]
    cmd = [sys.executable, "-m", "stereopath.host", "host", "live", "--device", f"127.0.0.1:{port}", "--keyframe-port", kport,
           "--keys", str(keys_root / "host"), "--out", str(out), "--duration", "600"]
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    return subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.DEVNULL,
                            stderr=log.open("ab"), env=env)


def _check_exactly_once(out: Path, spool_dir: Path, session: str) -> str:
    from stereopath.device.streaming import KeyframeSpool
    from stereopath.host.live.store import read_index

    spool = KeyframeSpool(spool_dir, fsync=False)
    d = out / session / "keyframes"
    seqs = sorted(int(p.name[3:-8]) for p in d.glob("kf_*.msgpack"))
    same = all((d / f"kf_{s:08d}.msgpack").read_bytes() == spool.read(s) for s in seqs)
    rows = sorted(r["seq"] for r in read_index(out / session))
    ok = seqs == list(range(spool.count)) and same and rows == seqs
    return f"{'OK' if ok else 'FAILED'}: host holds {len(seqs)} of {spool.count}, byte-identical {same}, " \
           f"index rows {len(rows)}"


def bench_faults(work: Path, keys_root: Path) -> None:
    print("\n-- full-size faults (device and host as separate processes, CURVE)")
    # kill -9 halfway through a 300-keyframe run (10 keyframes/s, 20 Hz poses)
    name, out, log = "kill9", work / "out_kill9", work / "kill9.log"
    proc, ready, result = start_device(work, keys_root, name, seconds=30, pose_hz=20, kf_hz=10, start_delay=2.0,
                                       serve_max_s=300)
    host = _live_host(ready, keys_root, out, log)
    t0 = time.monotonic()
    while kf_count(out, name) < 150 and time.monotonic() - t0 < 120:
        time.sleep(0.05)
    host.kill()
    host.wait()
    at_kill = kf_count(out, name)
    time.sleep(2.0)
    host = _live_host(ready, keys_root, out, log)
    while kf_count(out, name) < 300 and time.monotonic() - t0 < 240:
        time.sleep(0.1)
    host.terminate()
    host.wait(20)
    res = stop_device(proc, work, name, result)
    rj = json.loads((out / "receiver.json").read_text())
    print(f"kill -9 at {at_kill}/300 stored, restarted 2 s later: {_check_exactly_once(out, work / name, name)}; "
          f"host duplicates {rj['duplicates']}, device resent {res['stats'].get('keyframes_resent')}")

    # SIGSTOP the host for 10 s in a 20 s run at 20 Hz poses + 2 keyframes/s
    name, out, log = "pause", work / "out_pause", work / "pause.log"
    proc, ready, result = start_device(work, keys_root, name, seconds=20, pose_hz=20, kf_hz=2, start_delay=2.0,
                                       serve_max_s=300)
    host = _live_host(ready, keys_root, out, log)
    time.sleep(2.0 + 5.0)
    host.send_signal(signal.SIGSTOP)
    time.sleep(10.0)
    backlog = len(list((work / name).glob("*.kf"))) - kf_count(out, name)
    host.send_signal(signal.SIGCONT)
    t0 = time.monotonic()
    target = len(list((work / name).glob("*.kf")))
    while kf_count(out, name) < target and time.monotonic() - t0 < 60:
        time.sleep(0.01)
    caught_up = time.monotonic() - t0
    while kf_count(out, name) < 40 and time.monotonic() - t0 < 60:
        time.sleep(0.05)
    host.terminate()
    host.wait(20)
    res = stop_device(proc, work, name, result)
    print(f"SIGSTOP 10 s: device frame loop max lateness {1e3 * res['max_lateness_s']:.1f} ms "
          f"(p99 {1e3 * res['p99_lateness_s']:.1f} ms), max producer call {1e3 * res['max_call_s']:.2f} ms, "
          f"device max RSS {res['maxrss_kb'] / 1024:.0f} MiB, keyframes refused {res['stats']['keyframes_refused']}; "
          f"backlog of {backlog} keyframes delivered {caught_up:.2f} s after SIGCONT; at the end: "
          f"{_check_exactly_once(out, work / name, name)}")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--role", choices=["bench", "device"], default="bench")
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--seconds", type=float, default=15.0)
    ap.add_argument("--keyframes", type=int, default=300)
    ap.add_argument("--sections", default="sizes,latency,throughput,faults",
                    help="comma-separated subset of sizes,latency,throughput,faults")
    ap.add_argument("--keep", action="store_true", help="keep the work directory (logs, stores, spools)")
    # device role
    ap.add_argument("--keys-root")
    ap.add_argument("--spool")
    ap.add_argument("--session", default="bench")
    ap.add_argument("--ready")
    ap.add_argument("--result")
    ap.add_argument("--stop-file")
    ap.add_argument("--pose-hz", type=float, default=20.0)
    ap.add_argument("--kf-hz", type=float, default=2.0)
    ap.add_argument("--prefill", type=int, default=0)
    ap.add_argument("--encoding", default="jpg")
    ap.add_argument("--start-delay", type=float, default=0.0)
    ap.add_argument("--serve-max-s", type=float, default=120.0)
    ap.add_argument("--no-stream", action="store_true")
    ap.add_argument("--bare", action="store_true")
    args = ap.parse_args()
    if args.role == "device":
        return device_role(args)

    import zmq

    from stereopath.device.wire.security import make_demo_keys

    pairs, source = load_pairs()
    print(f"pyzmq {zmq.__version__}, libzmq {zmq.zmq_version()}, CURVE {zmq.has('curve')}, cpus {os.cpu_count()}; "
          f"images: {source}")
    work = Path(tempfile.mkdtemp(prefix="bench_streaming_"))
    try:
        keys = make_demo_keys(work / "keys")
        sections = set(args.sections.split(","))
        if "sizes" in sections:
            bench_sizes(pairs)
        if "latency" in sections:
            bench_latency_cpu(work, keys.root, args.runs, args.seconds)
        if "throughput" in sections:
            bench_throughput(work, keys.root, args.runs, args.keyframes)
        if "faults" in sections:
            bench_faults(work, keys.root)
    finally:
        if args.keep:
            print(f"work directory kept: {work}")
        else:
            shutil.rmtree(work, ignore_errors=True)
    return 0


if __name__ == "__main__":
    threading.current_thread().name = "bench"
    sys.exit(main())
