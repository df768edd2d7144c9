"""Simulator speed: stereo frames per second at 640x480 (target >= 30/s on the 2-core machine).

Measures, in this process: building the scene and the renderer, simulating the IMU of the full
default session, and rendering stereo frames of the default 5.12 m arc (noise on; also noise-free,
with motion blur, and with exposure drift).  Each figure is the median over ``--runs`` interleaved runs
of ``--frames`` frames spread along the arc.  A reference operation (one bilinear ``cv2.remap`` of a
640x480 image) is timed too so that figures from different machines can be compared.

    .venv/bin/python benchmarks/bench_sim.py [--runs 5] [--frames 40] [--json-out FILE]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from stereopath.device.commands.blas_threads import use_one_blas_thread  # noqa: E402

use_one_blas_thread()  # the device path's BLAS, set before numpy is loaded


def _time_frames(session, indices) -> tuple[float, float]:
    """(wall seconds, process CPU seconds) per stereo frame, averaged over ``indices``."""
    t0, c0 = time.perf_counter(), time.process_time()
    for i in indices:
        session.render(i)
    n = len(indices)
    return (time.perf_counter() - t0) / n, (time.process_time() - c0) / n


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--frames", type=int, default=40, help="frames per run, spread over the 400-frame arc")
    ap.add_argument("--json-out", metavar="FILE", help="also write the figures as JSON (benchmarks/write_table.py)")
    args = ap.parse_args()

    import cv2
    import numpy as np

    from stereopath.device.sim import open_sim

    print(f"cv2 threads: {cv2.getNumThreads()}")
    src = (np.random.default_rng(0).random((480, 640)) * 255).astype(np.uint8)
    mx, my = np.meshgrid(np.arange(640, dtype=np.float32) + 0.3, np.arange(480, dtype=np.float32) + 0.7)
    ref = []
    for _ in range(max(3, args.runs)):
        t0 = time.perf_counter()
        for _ in range(50):
            cv2.remap(src, mx, my, cv2.INTER_LINEAR)
        ref.append((time.perf_counter() - t0) / 50 * 1e3)
    ref_ms = statistics.median(ref)
    print(f"reference: cv2.remap 640x480 bilinear: {ref_ms:.3f} ms")

    t0 = time.perf_counter()
    sess = open_sim()
    t_session = time.perf_counter() - t0
    t0 = time.perf_counter()
    sess.render(0)
    t_first = time.perf_counter() - t0
    print(f"session (trajectory calibration + IMU, {len(sess.imu)} samples): {t_session * 1e3:.0f} ms; "
          f"scene + renderer build and first frame: {t_first * 1e3:.0f} ms "
          f"({len(sess.renderer.tiles.names)} render tiles)")
    indices = [int(i) for i in np.linspace(0, len(sess) - 1, args.frames)]

    rows = [("default (noise 2 DN)", sess)]
    rows.append(("noise-free", open_sim(noise_sigma=0.0)))
    rows.append(("exposure drift + vignetting", open_sim(exposure_drift=True, vignetting=0.3)))
    rows.append(("motion blur (5 sub-frames)", open_sim(motion_blur=True)))
    for _, s in rows:
        s.render(0)  # build outside the timing
    times: dict[str, list[float]] = {label: [] for label, _ in rows}
    cpu: dict[str, list[float]] = {label: [] for label, _ in rows}
    for _ in range(args.runs):  # interleaved, so that load from other processes hits all alike
        for label, s in rows:
            wall, c = _time_frames(s, indices)
            times[label].append(wall)
            cpu[label].append(c)
    results, cpu_ms = {}, {}
    print(f"\nstereo 640x480, median of {args.runs} interleaved runs x {len(indices)} frames:")
    for label, _ in rows:
        ms = statistics.median(times[label]) * 1e3
        results[label] = 1e3 / ms
        cms = cpu_ms[label] = statistics.median(cpu[label]) * 1e3
        print(f"  {label:32s} {1e3 / ms:7.1f} frames/s  {ms:6.2f} ms/frame  ({ms / ref_ms:6.1f} x reference remap)"
              f"   CPU {cms:6.2f} ms/frame (all threads)")
    try:
        load = " ".join(f"{v:.1f}" for v in __import__("os").getloadavg())
    except OSError:
        load = "n/a"
    print(f"load average during the run: {load} (other processes share the 2 cores; wall figures drop with load)")
    fps = results["default (noise 2 DN)"]
    print(f"\ntarget >= 30 stereo frames/s: {'MET' if fps >= 30 else 'NOT MET'} ({fps:.1f}/s, {fps / 30:.2f} x target)")
    if args.json_out:
        from results_file import write_results

        write_results(args.json_out, "bench_sim.py", {
            "sim.frames_per_s": fps,
            "sim.cpu_ms_per_frame": cpu_ms["default (noise 2 DN)"],
            "sim.motion_blur_frames_per_s": results["motion blur (5 sub-frames)"],
        })
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
