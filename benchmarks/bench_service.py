"""Capture-service benchmark: ``device run`` on the simulator, and its cost over the bare estimator.

Runs the service in this process (simulator source, its own IMU, the configured estimator,
recorder on, streaming on loopback without CURVE and with no host, so nothing is
acknowledged) for ``--frames`` frames, several times, and prints medians of

* wall frame rate after READY (what the pipeline sustains on this machine),
* process CPU time per frame, and CPU use in % of one core,
* time per frame of each stage (record, estimate, stream; exponential averages),

next to a reference measured in the same process: the same simulated frames rendered and
estimated by :func:`stereopath.device.estimation.base.run_estimator` without recording or streaming.
The ratio (service CPU per frame / reference CPU per frame) is the cost of recording,
streaming and supervision.

    .venv/bin/python benchmarks/bench_service.py [--frames 60] [--runs 3] [--estimator stereo]
"""

from __future__ import annotations

import argparse
import logging
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from stereopath.device.commands.blas_threads import use_one_blas_thread  # noqa: E402

use_one_blas_thread()  # the device path's BLAS, set before numpy is loaded


def _cpu() -> float:
    t = os.times()
    return t.user + t.system


def run_service_once(frames: int, estimator: str, tmp: Path) -> dict:
    from stereopath.device.service.options import RunOptions, load_config
    from stereopath.device.service.service import CaptureService

    cfg_path = tmp / "device.toml"
    cfg_path.write_text(
        f'[source]\nbackend = "sim"\n[source.sim]\nframes = {frames}\nseed = 0\n[imu]\nbackend = "source"\n'
        f'[estimator]\nname = "{estimator}"\n'
        '[stream]\npose_endpoint = "tcp://127.0.0.1:*"\nkeyframe_endpoint = "tcp://127.0.0.1:*"\ninsecure = true\n'
        'drain_s = 0.0\n'
        f'[recorder]\nreserve_mb = 1.0\n[service]\nstatus_file = "{tmp / "status.json"}"\n')
    opts = RunOptions(out=str(tmp / "session"))
    service = CaptureService(load_config(cfg_path, opts), opts, cfg_path, environ={})
    cpu0, t0 = _cpu(), time.perf_counter()
    code = service.run()
    cpu, wall = _cpu() - cpu0, time.perf_counter() - t0
    status = service.last_status
    run_s = status["uptime_s"] or wall
    return {"code": code, "frames": service.frames_in, "fps": service.frames_in / run_s if run_s else 0.0,
            "cpu_s_per_frame": cpu / max(service.frames_in, 1), "cpu_pct": 100.0 * cpu / wall,
            "stage_ms": status.get("stage_ms", {}), "keyframes": service.keyframes}


def run_reference_once(frames: int, estimator: str) -> dict:
    from stereopath.device.estimation.base import run_estimator
    from stereopath.device.estimation.registry import make_estimator
    from stereopath.device.settings import SimSettings, SourceSettings
    from stereopath.device.capture.sources import create_source

    src = create_source(SourceSettings(backend="sim", sim=SimSettings(frames=frames, seed=0)))
    cpu0, t0 = _cpu(), time.perf_counter()
    with src:
        est = make_estimator(estimator, src.rig)
        run_ = run_estimator(est, src, src.session.imu)
        close = getattr(est, "close", None)
        if close:
            close()
    cpu, wall = _cpu() - cpu0, time.perf_counter() - t0
    n = len(run_.estimates)
    return {"frames": n, "fps": n / wall, "cpu_s_per_frame": cpu / n, "cpu_pct": 100.0 * cpu / wall,
            "estimate_ms": statistics.median(run_.frame_ms)}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=60)
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--estimator", default="stereo")
    args = ap.parse_args()
    logging.basicConfig(level=logging.ERROR)
    services, refs = [], []
    for _ in range(args.runs):
        with tempfile.TemporaryDirectory() as d:
            services.append(run_service_once(args.frames, args.estimator, Path(d)))
        refs.append(run_reference_once(args.frames, args.estimator))
    med = lambda rows, key: statistics.median(r[key] for r in rows)  # noqa: E731
    stages = {k: statistics.median(r["stage_ms"].get(k, 0.0) for r in services) for k in services[0]["stage_ms"]}
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    print(f"capture service on the simulator: {args.frames} frames x {args.runs} runs, estimator {args.estimator}, "
          f"{os.cpu_count()} cores, load average {load:.1f}")
    print(f"  service:   {med(services, 'fps'):6.2f} frames/s, "
          f"{1e3 * med(services, 'cpu_s_per_frame'):7.1f} ms CPU/frame, {med(services, 'cpu_pct'):5.0f} % of one core;"
          f" exit codes {[r['code'] for r in services]}")
    print("  stages:    " + ", ".join(f"{k} {v:.1f} ms" for k, v in stages.items()) + " per frame (EMA)")
    print(f"  reference: {med(refs, 'fps'):6.2f} frames/s, {1e3 * med(refs, 'cpu_s_per_frame'):7.1f} ms CPU/frame,"
          f" {med(refs, 'cpu_pct'):5.0f} % of one core (render + estimate only)")
    ratio = med(services, "cpu_s_per_frame") / med(refs, "cpu_s_per_frame")
    print(f"  ratio service / reference CPU per frame: {ratio:.2f} (recording, streaming, supervision on top)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
