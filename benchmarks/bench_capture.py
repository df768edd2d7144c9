"""Capture + pairing overhead of the picamera2 path at 30 fps, 640x480, on pre-rendered frames.

Pre-rendered simulator frames (rendering excluded) are played through the fake picamera2
(two camera threads, synchronised, YUV420 buffers built once) into the real
:class:`~stereopath.device.capture.sources.csi.Picamera2Source`: per frame and camera the callback maps the
request, copies the luma plane, and the pairer matches the two; the consumer receives
:class:`StereoFrame` objects.  The process CPU time over the run, as a share of one core,
is the figure; the reference measured in the same process is the fake cameras alone
(same threads and requests, a callback that returns at once).  Target: overhead <= 5 %.

Run: .venv/bin/python benchmarks/bench_capture.py [--seconds 5] [--runs 3]
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from stereopath.device.core.config import from_mapping  # noqa: E402
from stereopath.device.settings import SourceSettings  # noqa: E402
from stereopath.device.capture.sources.csi import Picamera2Source  # noqa: E402
from tests.fakes.fake_picamera2 import FakeCameraWorld  # noqa: E402

W, H, FPS = 640, 480, 30.0


def prerendered(n: int) -> list[tuple[np.ndarray, np.ndarray]]:
    try:
        from stereopath.device.sim.session import SimConfig, open_sim

        sess = open_sim(SimConfig(frames=n, seed=0))
        frames = [sess.render(i) for i in range(n)]
        out = [(f.left, f.right) for f in frames]
        if out[0][0].shape == (H, W):
            return out
    except Exception as exc:  # the simulator is optional here
        print(f"(simulator unavailable: {exc}; using random textures)")
    rng = np.random.default_rng(0)
    return [(rng.integers(0, 255, (H, W), np.uint8), rng.integers(0, 255, (H, W), np.uint8)) for _ in range(n)]


def settings() -> SourceSettings:
    return from_mapping(SourceSettings, {"backend": "picamera2", "fps": FPS, "size": [W, H], "exposure_us": 8000,
                                         "pair_tolerance_us": 1000, "timeout_s": 2.0})


def run_source(images, seconds: float) -> tuple[float, int, dict]:
    world = FakeCameraWorld(images=images, sync_ready_after=0)
    for c in world.cameras:
        c.skew_ns = 0
    world.cameras[1].skew_ns = 25_000
    src = Picamera2Source(settings(), api=world.api())
    src.open()
    n = 0
    w0, c0 = time.monotonic(), time.process_time()
    for f in src:
        n += 1
        if time.monotonic() - w0 >= seconds:
            break
    cpu, wall = time.process_time() - c0, time.monotonic() - w0
    src.close()
    return cpu / wall, n, src.stats.as_dict()


def run_fake_only(images, seconds: float) -> float:
    world = FakeCameraWorld(images=images, sync_ready_after=0)
    api = world.api()
    cams = [api.Picamera2(i) for i in (0, 1)]
    fd = int(1e6 / FPS)
    for cam in cams:
        cfg = cam.create_video_configuration(main={"size": (W, H), "format": "YUV420"}, buffer_count=6, queue=False,
                                             controls={"FrameDurationLimits": (fd, fd), "ExposureTime": 8000,
                                                       "SyncMode": api.controls.rpi.SyncModeEnum.Server})
        cam.configure(cfg)
        cam.post_callback = lambda req: None
    for cam in cams:
        cam.start()
    # warm the YUV cache like the measured run's first frames do
    time.sleep(min(1.0, len(images) / FPS))
    w0, c0 = time.monotonic(), time.process_time()
    time.sleep(seconds)
    cpu, wall = time.process_time() - c0, time.monotonic() - w0
    for cam in cams:
        cam.close()
    return cpu / wall


def main() -> None:
    logging.basicConfig(level=logging.ERROR)
    ap = argparse.ArgumentParser()
    ap.add_argument("--seconds", type=float, default=5.0)
    ap.add_argument("--runs", type=int, default=3)
    args = ap.parse_args()
    images = prerendered(30)
    # warm-up run (YUV buffers of the pre-rendered frames are built on first use)
    run_source(images, 1.0)
    ours, refs, frames = [], [], []
    for _ in range(args.runs):
        share, n, stats = run_source(images, args.seconds)
        ours.append(share)
        frames.append(n)
        refs.append(run_fake_only(images, args.seconds))
    o, r = float(np.median(ours)), float(np.median(refs))
    print(f"picamera2 path, {W}x{H} at {FPS:g} fps, pre-rendered frames, {args.runs} runs of {args.seconds:g} s (medians)")
    print(f"  pairs delivered per run: {frames} (expected ~{FPS * args.seconds:.0f}); last stats {stats}")
    print(f"  process CPU, source + pairing + fake cameras: {100 * o:.2f} % of one core")
    print(f"  process CPU, fake cameras alone (reference):  {100 * r:.2f} % of one core")
    print(f"  capture + pairing overhead:                   {100 * (o - r):.2f} % of one core (target <= 5 %); "
          f"ratio to reference {o / r if r > 0 else float('inf'):.1f}x")
    print(f"  per pair: {(o - r) / FPS * 1e6:.0f} us of CPU")


if __name__ == "__main__":
    main()
