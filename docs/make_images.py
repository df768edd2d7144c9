"""Refresh every picture under docs/img/ from the project's own commands (a few minutes).

    .venv/bin/python docs/make_images.py [--only demo,reprocess,fleet,calibration,live,wiring] [--work DIR]

- ``path.png``, ``model.png``: ``stereopath demo --out DIR`` (the full simulated scan).
- ``report.png``: ``stereopath host reprocess SESSION --out DIR``'s ``report.html`` in headless Chromium
  (its top: paths, errors, model), SESSION recorded by ``device run --source sim`` (100 frames).
- ``fleet.png``: ``host reprocess S1 S2 --out DIR --ray auto``'s ``fleet.html`` in headless Chromium.
- ``calib-reprojection.png``, ``calib-imu-window.png``: ``device calibrate-stereo`` on
  ``../shared/data/stereo_calib_chessboard`` and ``device calibrate-imu`` on a simulated session.
- ``live-view.png``: ``device run --source sim`` streaming to ``host live --map --rerun-save FILE.rrd``; the
  recording opened in the rerun viewer on a virtual display (Xvfb, Mesa's software Vulkan driver), at
  the end of the scan, side panels collapsed.
- ``wiring.svg``: ``docs/make_wiring.py``.

Needs (Debian 12): ``apt-get install chromium xvfb mesa-vulkan-drivers``.  Not part of the test suite.
"""

from __future__ import annotations

import argparse
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
IMG = ROOT / "docs" / "img"
BIN = Path(sys.executable).parent
STEPS = ("wiring", "calibration", "demo", "reprocess", "fleet", "live")


def stereopath(*args: str, log: Path | None = None, timeout: float = 1800) -> None:
    cmd = [str(BIN / "stereopath"), *args]
    print("$", " ".join(cmd), flush=True)
    with open(log or os.devnull, "w") as out:
        r = subprocess.run(cmd, stdout=out, stderr=subprocess.STDOUT, timeout=timeout)
    if r.returncode != 0:
        raise SystemExit(f"failed ({r.returncode}): {' '.join(cmd)}" + (f"; see {log}" if log else ""))


def need(program: str, package: str) -> str:
    path = shutil.which(program)
    if path is None:
        raise SystemExit(f"{program} not found: apt-get install {package}")
    return path


def screenshot_html(html: Path, png: Path, width: int, height: int) -> None:
    """A page as the user's browser shows it: headless Chromium, no sandbox (root in a container)."""
    chromium = shutil.which("chromium") or need("chromium-browser", "chromium")
    if not html.is_file():
        raise SystemExit(f"{html} was not written")
    cmd = [chromium, "--headless", "--no-sandbox", "--disable-gpu", "--hide-scrollbars",
           f"--screenshot={png}", f"--window-size={width},{height}", html.resolve().as_uri()]
    print("$", " ".join(cmd), flush=True)
    subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, timeout=120)


def copy(src: Path, name: str) -> None:
    if not src.is_file():
        raise SystemExit(f"{src} was not written")
    IMG.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(src, IMG / name)
    print(f"  -> docs/img/{name}")


def data_dir() -> Path:
    return Path(os.environ.get("STEREOPATH_DATA", ROOT.parent / "shared" / "data"))


def sim_session(work: Path, name: str, frames: int, seed: int) -> Path:
    out = work / name
    if not (out / "mav0").is_dir():
        stereopath("sim", "--out", str(out), "--frames", str(frames), "--seed", str(seed), log=work / f"{name}.log")
    return out


def device_session(work: Path, name: str, frames: int, seed: int) -> Path:
    """A session recorded by the device service (with its on-board path), from the simulated rig."""
    out = work / name
    if not (out / "mav0").is_dir():
        cfg = work / f"{name}.toml"
        cfg.write_text(f'[source]\nbackend = "sim"\n\n[source.sim]\nframes = {frames}\nseed = {seed}\n')
        stereopath("device", "run", "--config", str(cfg), "--source", "sim", "--no-stream", "--status-file", "",
                   "--out", str(out), log=work / f"{name}.log")
    return out


# ------------------------------------------------------------------------------------ steps


def step_wiring(work: Path) -> None:
    subprocess.run([sys.executable, str(ROOT / "docs" / "make_wiring.py"), "--out", str(IMG / "wiring.svg")],
                   check=True)


def step_calibration(work: Path) -> None:
    boards = data_dir() / "stereo_calib_chessboard"
    if not boards.is_dir():
        raise SystemExit(f"{boards} not found (set STEREOPATH_DATA)")
    stereopath("device", "calibrate-stereo", str(boards), "--board", "9x6", "--square-mm", "25",
               "--out", str(work / "calib" / "rig.yaml"), log=work / "calibrate-stereo.log")
    copy(work / "calib" / "rig_reprojection.png", "calib-reprojection.png")
    session = sim_session(work, "s_calib", 40, 0)  # a still second, then the hand-held scan
    stereopath("device", "calibrate-imu", f"session:{session}", "--window", "auto", "--min-still-s", "0.9",
               "--out", str(work / "calib" / "imu.yaml"), log=work / "calibrate-imu.log")
    copy(work / "calib" / "imu_still_window.png", "calib-imu-window.png")


def step_demo(work: Path) -> None:
    out = work / "demo"
    if out.exists():
        shutil.rmtree(out)
    stereopath("demo", "--out", str(out), log=work / "demo.log")
    copy(out / "path.png", "path.png")
    copy(out / "model.png", "model.png")


def step_reprocess(work: Path) -> None:
    session = device_session(work, "session1", 100, 1)
    out = work / "reprocess"
    stereopath("host", "reprocess", str(session), "--out", str(out), log=work / "reprocess.log")
    screenshot_html(out / "report.html", IMG / "report.png", 1100, 2080)  # the top: paths, errors, model
    print("  -> docs/img/report.png")


def step_fleet(work: Path) -> None:
    s1, s2 = device_session(work, "session1", 100, 1), device_session(work, "session2", 60, 2)
    out = work / "fleet"
    stereopath("host", "reprocess", str(s1), str(s2), "--out", str(out), "--ray", "auto", log=work / "fleet.log")
    screenshot_html(out / "fleet.html", IMG / "fleet.png", 1400, 420)
    print("  -> docs/img/fleet.png")


def _free_port_pair() -> int:
    """A port P with P and P+1 free on loopback (pose and keyframe endpoints)."""
    for _ in range(50):
        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            port = s.getsockname()[1]
        try:
            with socket.socket() as s:
                s.bind(("127.0.0.1", port + 1))
        except OSError:
            continue
        return port
    raise SystemExit("no two neighbouring free ports on 127.0.0.1")


def step_live(work: Path) -> None:
    live = work / "live"
    if live.exists():
        shutil.rmtree(live)
    live.mkdir(parents=True)
    port = _free_port_pair()
    (live / "device.toml").write_text(f"""\
[source]
backend = "sim"

[source.sim]
frames = 160
rate_hz = 20.0

[recorder]
dir = "{live / 'sessions'}"

[service]
status_file = ""

[stream]
pose_endpoint = "tcp://127.0.0.1:{port}"
keyframe_endpoint = "tcp://127.0.0.1:{port + 1}"
insecure = true
""")
    rrd = live / "live.rrd"
    host_cmd = [str(BIN / "stereopath"), "host", "live", "--device", f"127.0.0.1:{port}", "--insecure",
                "--out", str(live / "scans"), "--map", "--rerun-save", str(rrd), "--duration", "600"]
    dev_cmd = [str(BIN / "stereopath"), "device", "run", "--config", str(live / "device.toml"), "--source", "sim",
               "--insecure", "--wait-for-host", "30"]
    print("$", " ".join(host_cmd), flush=True)
    with open(live / "host.log", "w") as hlog, open(live / "device.log", "w") as dlog:
        host = subprocess.Popen(host_cmd, stdout=hlog, stderr=subprocess.STDOUT)
        try:
            print("$", " ".join(dev_cmd), flush=True)
            rc = subprocess.run(dev_cmd, stdout=dlog, stderr=subprocess.STDOUT, timeout=900).returncode
            if rc != 0:
                raise SystemExit(f"device run exited {rc}; see {live / 'device.log'}")
            time.sleep(2.0)  # the last keyframes' acknowledgements
        finally:
            host.send_signal(signal.SIGTERM)  # host live stops on SIGTERM and writes its model
            try:
                host.wait(timeout=600)
            except subprocess.TimeoutExpired:
                host.kill()
                raise SystemExit(f"host live did not stop; see {live / 'host.log'}") from None
    if not rrd.is_file():
        raise SystemExit(f"{rrd} was not written; see {live / 'host.log'}")
    sessions = sorted(d.name for d in (live / "scans").iterdir() if (d / "session.json").is_file())
    if len(sessions) != 1:
        raise SystemExit(f"expected one session in {live / 'scans'}, found {sessions}")
    screenshot_rrd(rrd, sessions[0], live / "live-view.png", live)
    copy(live / "live-view.png", "live-view.png")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def screenshot_rrd(rrd: Path, session: str, png: Path, work: Path, size: tuple[int, int] = (1600, 1000)) -> None:
    """The recording in the rerun viewer, at the end of its device_time timeline, as a user opens it
    (``rerun FILE.rrd``), with the side panels collapsed and three views: 3D, latest keyframe, inliers.

    The viewer runs in a window on a virtual display (Xvfb) with Mesa's software Vulkan driver and
    is driven over its gRPC port (``rerun.experimental.ViewerClient``)."""
    import rerun as rr
    import rerun.blueprint as rrb
    from rerun.experimental import ViewerClient

    xvfb = need("Xvfb", "xvfb")
    rerun = shutil.which("rerun", path=str(BIN)) or need("rerun", "rerun-sdk (pip)")
    read_fd, write_fd = os.pipe()
    display = subprocess.Popen([xvfb, "-displayfd", str(write_fd), "-screen", "0", "3000x2000x24", "-nolisten", "tcp"],
                               pass_fds=(write_fd,), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                               start_new_session=True)
    os.close(write_fd)
    viewer = None
    try:
        with os.fdopen(read_fd) as f:
            number = f.readline().strip()
        if not number:
            raise SystemExit("Xvfb did not start")
        port = _free_port()
        runtime = work / "xdg"
        runtime.mkdir(mode=0o700, exist_ok=True)
        env = dict(os.environ, DISPLAY=f":{number}", XDG_RUNTIME_DIR=str(runtime))
        cmd = [rerun, "--port", str(port), "--hide-welcome-screen", "--window-size", f"{size[0]}x{size[1]}",
               "--renderer", "vulkan"]
        print("$", " ".join(cmd), flush=True)
        with open(work / "rerun.log", "w") as log:
            viewer = subprocess.Popen(cmd, env=env, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
        url = f"rerun+http://127.0.0.1:{port}/proxy"
        client = None
        for _ in range(120):
            try:
                client = ViewerClient.connect(url)
                client.get_state()
                break
            except Exception:  # not listening yet
                client = None
                time.sleep(0.5)
        if client is None:
            raise SystemExit(f"the rerun viewer did not come up; see {work / 'rerun.log'}")
        store = client.open(str(rrd)).store_ids[0]  # "Recording:<application id>:<recording id>"
        _, app_id, recording_id = store.split(":")
        recording = next(r for r in client.get_state().recordings if r.store_id == store)
        end = next(t for t in recording.timelines if t.name == "device_time").end
        blueprint = rrb.Blueprint(
            rrb.Horizontal(
                rrb.Spatial3DView(origin="world", name="path, keyframes and model"),
                rrb.Vertical(rrb.Spatial2DView(origin=f"world/{session}/camera/image", name="latest keyframe (left)"),
                             rrb.TimeSeriesView(origin="status", name="tracked points (inliers)"), row_shares=[2, 1]),
                column_shares=[3, 2]),
            collapse_panels=True)
        stream = rr.RecordingStream(app_id, recording_id=recording_id)
        stream.connect_grpc(url)
        stream.send_blueprint(blueprint, make_active=True)
        stream.flush()
        time.sleep(2.0)
        client.set_location(recording.location)
        client.set_time("device_time", duration=end * 1e-9, play_state="paused")
        time.sleep(4.0)  # a few frames of the software rasterizer
        client.save_screenshot(str(png.resolve()))
        stream.disconnect()
    finally:
        for proc in (viewer, display):
            if proc is not None and proc.poll() is None:
                os.killpg(proc.pid, signal.SIGTERM)  # the group this script started
                try:
                    proc.wait(timeout=10)
                except subprocess.TimeoutExpired:
                    os.killpg(proc.pid, signal.SIGKILL)
    if not png.is_file():
        raise SystemExit(f"the viewer wrote no screenshot; see {work / 'rerun.log'}")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--only", default=",".join(STEPS), help=f"comma-separated steps of {', '.join(STEPS)}")
    ap.add_argument("--work", default=None, help="keep the intermediate outputs here (default: a temporary folder)")
    args = ap.parse_args(argv)
    steps = [s.strip() for s in args.only.split(",") if s.strip()]
    for s in steps:
        if s not in STEPS:
            ap.error(f"unknown step {s!r}; known: {', '.join(STEPS)}")
    work = Path(args.work) if args.work else Path(tempfile.mkdtemp(prefix="stereopath_images_"))
    work.mkdir(parents=True, exist_ok=True)
    try:
        for s in steps:
            t0 = time.monotonic()
            print(f"== {s}", flush=True)
            globals()[f"step_{s}"](work)
            print(f"== {s}: {time.monotonic() - t0:.0f} s", flush=True)
    finally:
        if not args.work:
            shutil.rmtree(work, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
