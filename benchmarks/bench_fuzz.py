"""Fuzz benchmark (issue 39): a seeded mutator over the file inputs of every command.

Each input is one file of a small workspace (TUM and KITTI poses, our rig YAML, KITTI ``calib.txt``,
EuRoC ``sensor.yaml`` and ``data.csv``, a Kalibr camchain, ``device.toml``, a recorded session's files,
PNG images, the host store's state files) changed by one mutation (bit flips, truncation, huge
numbers, NaN/inf, deep nesting, wrong types, lines dropped or repeated, garbage), then a command that
reads it runs in this process through the CLI's ``main(argv)``.  An exception that leaves ``main`` (the
project's errors never do: they become one line and an exit code) is a traceback, and so is an error
logged with its traceback; a ``SystemExit`` (argparse) is not.  A run is bounded by a time budget and a
count of inputs; it prints the inputs tried and the tracebacks found, each with the input that caused it
saved under ``--keep DIR`` when given.

    .venv/bin/python benchmarks/bench_fuzz.py [--seconds 180] [--inputs N] [--seed 0] [--only NAME,...]
                                               [--keep DIR] [--json]
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import logging
import os
import random
import re
import shutil
import signal
import sys
import tempfile
import time
import traceback
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
DATA = Path(os.environ.get("STEREOPATH_DATA", ROOT.parent / "shared" / "data"))

INPUT_TIME_LIMIT_S = 30.0  # one command on one input; longer counts as a hang

# ---------------------------------------------------------------------------------------------------
# mutations: bytes in, bytes out, all drawn from one random.Random

_NUMBER = re.compile(rb"-?\d+(?:\.\d+)?(?:[eE][-+]?\d+)?")
HUGE = [b"1e308", b"-1e308", b"1.7976931348623157e308", b"1e999", b"9" * 400, b"4294967296", b"-9223372036854775809",
        b"1e-320", b"0", b"-0"]
NONFINITE = [b"nan", b"inf", b"-inf", b".nan", b".inf", b"-.inf", b"NaN", b"Infinity"]
WRONG_TYPES = [b"abc", b"true", b"[]", b"{}", b'""', b"null", b"~", b"[1, 2]", b"{a: 1}", b"'x'", b"0x10", b"1_0"]


def _numbers(data: bytes) -> list[re.Match]:
    return list(_NUMBER.finditer(data))


def _replace_number(rng: random.Random, data: bytes, choices: list[bytes]) -> bytes:
    nums = _numbers(data)
    if not nums:
        return data + rng.choice(choices)
    m = rng.choice(nums)
    return data[:m.start()] + rng.choice(choices) + data[m.end():]


def m_bitflip(rng: random.Random, data: bytes, kind: str) -> bytes:
    if not data:
        return bytes([rng.randrange(256)])
    b = bytearray(data)
    for _ in range(rng.randint(1, 8)):
        i = rng.randrange(len(b))
        b[i] ^= 1 << rng.randrange(8)
    return bytes(b)


def m_truncate(rng: random.Random, data: bytes, kind: str) -> bytes:
    return data[:rng.randrange(len(data) + 1)] if data else data


def m_huge(rng: random.Random, data: bytes, kind: str) -> bytes:
    out = data
    for _ in range(rng.randint(1, 3)):
        out = _replace_number(rng, out, HUGE)
    return out


def m_nonfinite(rng: random.Random, data: bytes, kind: str) -> bytes:
    return _replace_number(rng, data, NONFINITE)


def m_wrong_type(rng: random.Random, data: bytes, kind: str) -> bytes:
    return _replace_number(rng, data, WRONG_TYPES)


def m_nesting(rng: random.Random, data: bytes, kind: str) -> bytes:
    n = rng.choice([50, 500, 2000, 5000])
    if kind == "toml":
        deep = rng.choice([b"x = " + b"[" * n + b"]" * n, b"x = " + b"{a=" * n + b"1" + b"}" * n])
        return deep + b"\n" + data
    if kind in ("yaml", "json"):
        deep = rng.choice([b"[" * n + b"]" * n, b"{a: " * n + b"1" + b"}" * n]) if kind == "yaml" else \
            b"[" * n + b"]" * n
        nums = _numbers(data)
        if nums:
            m = rng.choice(nums)
            return data[:m.start()] + deep + data[m.end():]
        return deep
    return data + b"\n" + b"(" * n + b"\n"


def m_lines(rng: random.Random, data: bytes, kind: str) -> bytes:
    lines = data.split(b"\n")
    if len(lines) < 2:
        return data + data
    i = rng.randrange(len(lines))
    op = rng.choice(["drop", "repeat", "swap", "shuffle_fields", "join"])
    if op == "drop":
        del lines[i]
    elif op == "repeat":
        lines.insert(i, lines[i])
    elif op == "swap":
        j = rng.randrange(len(lines))
        lines[i], lines[j] = lines[j], lines[i]
    elif op == "shuffle_fields":
        sep = b"," if b"," in lines[i] else b" "
        parts = lines[i].split(sep)
        rng.shuffle(parts)
        parts = parts[:rng.randint(0, len(parts))]
        lines[i] = sep.join(parts)
    else:
        j = min(i + 1, len(lines) - 1)
        lines[i:j + 1] = [lines[i] + lines[j]]
    return b"\n".join(lines)


def m_garbage(rng: random.Random, data: bytes, kind: str) -> bytes:
    choice = rng.choice(["empty", "binary", "insert", "bom", "nul"])
    if choice == "empty":
        return b""
    if choice == "binary":
        return bytes(rng.randrange(256) for _ in range(rng.randint(1, 300)))
    if choice == "bom":
        return b"\xef\xbb\xbf" + data
    if choice == "nul":
        i = rng.randrange(len(data) + 1)
        return data[:i] + b"\x00" + data[i:]
    i = rng.randrange(len(data) + 1)
    return data[:i] + bytes(rng.randrange(256) for _ in range(rng.randint(1, 16))) + data[i:]


def m_png(rng: random.Random, data: bytes, kind: str) -> bytes:
    """A valid PNG of the wrong kind: another size, 16-bit, colour, one pixel, all black."""
    import cv2

    img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED) if data else None
    if img is None:
        img = np.zeros((48, 64), np.uint8)
    choice = rng.choice(["size", "16bit", "colour", "one", "black", "alpha"])
    if choice == "size":
        img = cv2.resize(img, (max(1, img.shape[1] // rng.choice([2, 3])), max(1, img.shape[0] // 2)))
    elif choice == "16bit":
        img = img.astype(np.uint16) * 257
    elif choice == "colour":
        img = cv2.cvtColor(img, cv2.COLOR_GRAY2BGR) if img.ndim == 2 else img
    elif choice == "one":
        img = img[:1, :1]
    elif choice == "black":
        img = np.zeros_like(img)
    else:
        g = img if img.ndim == 2 else img[..., 0]
        img = np.dstack([g, g, g, np.full_like(g, 255)])
    ok, buf = cv2.imencode(".png", img)
    return buf.tobytes() if ok else data


TEXT_MUTATORS: dict[str, Callable[[random.Random, bytes, str], bytes]] = {
    "bitflip": m_bitflip, "truncate": m_truncate, "huge": m_huge, "nonfinite": m_nonfinite,
    "wrong_type": m_wrong_type, "nesting": m_nesting, "lines": m_lines, "garbage": m_garbage,
}
PNG_MUTATORS: dict[str, Callable[[random.Random, bytes, str], bytes]] = {
    "bitflip": m_bitflip, "truncate": m_truncate, "garbage": m_garbage, "png_kind": m_png,
}


# ---------------------------------------------------------------------------------------------------
# the workspace: small copies of every kind of file the commands read


@dataclass(frozen=True)
class Target:
    """One file (``rel``, in the workspace) and a command that reads it (``argv(workspace, out)``)."""

    name: str
    rel: str
    kind: str                                   # text | toml | yaml | json | png
    argv: Callable[[Path, Path], list[str]]
    cheap: bool = True                          # False: seconds per input (only a few in the short run)
    restore: str = ""                           # a folder restored after each input (the command may rewrite it)


def _circle_poses(n: int = 30) -> tuple[np.ndarray, np.ndarray]:
    from stereopath.device.core.geometry import make_pose

    t = np.arange(n, dtype=np.int64) * 50_000_000
    Ts = []
    for i in range(n):
        a = 0.1 * i
        R = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1.0]])
        Ts.append(make_pose(R, np.array([np.cos(a), np.sin(a), 0.01 * i])))
    return t, np.array(Ts)


def _kitti_text(Ts: np.ndarray) -> str:
    return "".join(" ".join(f"{v:.9e}" for v in T[:3, :].reshape(-1)) + "\n" for T in Ts)


def _mini_euroc(src: Path, dst: Path, frames: int) -> None:
    """The first ``frames`` images of an EuRoC ``mav0`` with its IMU and ground truth over that span."""
    from stereopath.device.formats.tum import read_tum

    for cam in ("cam0", "cam1"):
        (dst / cam / "data").mkdir(parents=True)
        shutil.copy(src / cam / "sensor.yaml", dst / cam / "sensor.yaml")
        rows = [r for r in (src / cam / "data.csv").read_text().splitlines() if r and not r.startswith("#")]
        rows = rows[:frames]
        (dst / cam / "data.csv").write_text("#timestamp [ns],filename\n" + "\n".join(rows) + "\n")
        for r in rows:
            name = r.split(",")[1].strip()
            shutil.copy(src / cam / "data" / name, dst / cam / "data" / name)
    t_end = int(rows[-1].split(",")[0]) + 50_000_000
    (dst / "imu0").mkdir()
    shutil.copy(src / "imu0" / "sensor.yaml", dst / "imu0" / "sensor.yaml")
    imu = (src / "imu0" / "data.csv").read_text().splitlines()
    keep = [imu[0]] + [r for r in imu[1:] if r and int(r.split(",")[0]) <= t_end]
    (dst / "imu0" / "data.csv").write_text("\n".join(keep) + "\n")
    gt = read_tum(src.parent / "groundtruth_tum.txt")
    from stereopath.device.core.geometry import matrix_to_quat_xyzw

    lines = ["#timestamp, p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], q_RS_w [], q_RS_x [], q_RS_y [], q_RS_z []"]
    for t, T in zip(gt.t_ns, gt.T_world_cam):
        if t > t_end + 200_000_000:
            break
        x, y, z, w = matrix_to_quat_xyzw(T[:3, :3])
        lines.append(f"{int(t)},{T[0, 3]:.6f},{T[1, 3]:.6f},{T[2, 3]:.6f},{w:.9f},{x:.9f},{y:.9f},{z:.9f}")
    (dst / "state_groundtruth_estimate0").mkdir()
    (dst / "state_groundtruth_estimate0" / "data.csv").write_text("\n".join(lines) + "\n")


def _kalibr_from_euroc(mav0: Path) -> str:
    """A Kalibr camchain (camera-IMU) with the EuRoC folder's own calibration."""
    import yaml

    from stereopath.device.core.geometry import invert_pose

    out = {}
    for cam in ("cam0", "cam1"):
        d = yaml.safe_load(re.sub(r"^%YAML.*$", "", (mav0 / cam / "sensor.yaml").read_text(), flags=re.M))
        T_BS = np.array(d["T_BS"]["data"], float).reshape(4, 4)
        out[cam] = {"T_cam_imu": invert_pose(T_BS).tolist(), "camera_model": "pinhole",
                    "distortion_coeffs": d["distortion_coefficients"], "distortion_model": "radtan",
                    "intrinsics": d["intrinsics"], "resolution": d["resolution"], "rostopic": f"/{cam}/image_raw"}
    T0, T1 = (np.array(out[c]["T_cam_imu"]) for c in ("cam0", "cam1"))
    out["cam1"]["T_cn_cnm1"] = (T1 @ invert_pose(T0)).tolist()
    return yaml.safe_dump(out, default_flow_style=None)


def build_workspace(w: Path, session_frames: int = 8) -> list[Target]:
    """Write the pristine files into ``w`` and return the targets whose files are there."""
    import cv2

    from stereopath.device.core.rig import paper_rig
    from stereopath.device.formats.recorder import record_sequence
    from stereopath.device.formats.rig_files import save_rig_yaml
    from stereopath.device.formats.tum import Trajectory, write_tum
    from stereopath.device.sim.session import SimConfig, open_sim
    from stereopath.device.wire.protocol import encode_keyframe, make_keyframe, rig_reference
    from stereopath.host.live.store import KeyframeStore

    w.mkdir(parents=True, exist_ok=True)
    S = w / "S"
    record_sequence(open_sim(SimConfig(frames=session_frames)), S, config_dict={"source": "sim"})
    shutil.copy(S / "groundtruth.tum", S / "trajectory.tum")  # a path to map with
    t, Ts = _circle_poses()
    (w / "poses").mkdir()
    write_tum(w / "poses" / "gt.tum", Trajectory(t, Ts))
    write_tum(w / "poses" / "est.tum", Trajectory(t, Ts @ np.diag([1, 1, 1, 1.0])))
    (w / "poses" / "gt_kitti.txt").write_text(_kitti_text(Ts))
    (w / "poses" / "est_kitti.txt").write_text(_kitti_text(Ts))
    save_rig_yaml(paper_rig(), w / "rig.yaml")
    (w / "cfg").mkdir()
    toml = (ROOT / "firmware_cfg" / "device.toml").read_text()
    (w / "cfg" / "device.toml").write_text(toml.replace("/var/lib/stereopath/sessions", str(w / "rec")))
    (w / "cfg" / "rig.toml").write_text(f'[source]\nrig_file = "{w / "rig.yaml"}"\n[recorder]\ndir = "{w / "rec"}"\n'
                                        f'reserve_mb = 0\n[stream]\nenabled = false\n')
    # images for `features`: two small crops of the simulated session
    img = cv2.imread(str(sorted((S / "mav0" / "cam0" / "data").glob("*.png"))[0]), cv2.IMREAD_GRAYSCALE)
    (w / "img").mkdir()
    cv2.imwrite(str(w / "img" / "a.png"), img[100:260, 100:320])
    cv2.imwrite(str(w / "img" / "b.png"), img[104:264, 96:316])
    # the host store: three keyframes of one session, the rig beside them
    from stereopath.device.formats import open_source

    seq = open_source(f"session:{S}")
    store = KeyframeStore(w / "live", fsync=False)
    for k in range(3):
        fr = seq.frame(k)
        kf = make_keyframe("sessX", k, k, int(seq.t_ns[k]), seq.groundtruth.T_world_cam[k], (fr.left, fr.right),
                           rig_reference(seq.rig), "png")
        store.put(kf, encode_keyframe(kf))
        store.set_last_session("sessX")
    store.save_state()
    store.close()
    save_rig_yaml(seq.rig, w / "live" / "sessX" / "keyframes" / "rig.yaml")

    def out_arg(o: Path) -> list[str]:
        return ["--out", str(o)]

    first_png = sorted((S / "mav0" / "cam0" / "data").glob("*.png"))[0].relative_to(w).as_posix()
    kf_file = sorted(p for p in (w / "live" / "sessX" / "keyframes").iterdir()
                     if p.is_file() and p.name != "rig.yaml")
    targets = [
        Target("tum_gt", "poses/gt.tum", "text", lambda w, o: ["eval", "--gt", str(w / "poses/gt.tum"),
                                                                "--est", str(w / "poses/est.tum")]),
        Target("tum_est", "poses/est.tum", "text", lambda w, o: ["eval", "--gt", str(w / "poses/gt.tum"),
                                                                  "--est", str(w / "poses/est.tum"), "--json"]),
        Target("kitti_poses", "poses/gt_kitti.txt", "text",
               lambda w, o: ["eval", "--gt", str(w / "poses/gt_kitti.txt"), "--est", str(w / "poses/est_kitti.txt")]),
        Target("map_poses", "poses/gt.tum", "text",
               lambda w, o: ["host", "map", str(w / "S"), "--poses", str(w / "poses/gt.tum"), "--max-keyframes", "1",
                             "--no-progress", *out_arg(o)], cheap=False),
        Target("rig_yaml_map", "rig.yaml", "yaml",
               lambda w, o: ["host", "map", str(w / "S"), "--rig", str(w / "rig.yaml"), "--max-keyframes", "1",
                             "--no-progress", *out_arg(o)], cheap=False),
        Target("rig_yaml_selftest", "rig.yaml", "yaml",
               lambda w, o: ["device", "selftest", "--config", str(w / "cfg/rig.toml"), "--source",
                             f"replay:session:{w / 'S'}", "--imu", "none", "--frames", "2"]),
        Target("device_toml_status", "cfg/device.toml", "toml",
               lambda w, o: ["device", "status", "--config", str(w / "cfg/device.toml"), "--status-file",
                             str(o / "status.json")]),
        Target("device_toml_selftest", "cfg/device.toml", "toml",
               lambda w, o: ["device", "selftest", "--config", str(w / "cfg/device.toml"), "--source",
                             f"replay:session:{w / 'S'}", "--frames", "2"]),
        Target("device_toml_run", "cfg/device.toml", "toml",
               lambda w, o: ["device", "run", "--config", str(w / "cfg/device.toml"), "--source",
                             f"replay:session:{w / 'S'}", "--frames", "1", "--no-stream", "--status-file", "",
                             *out_arg(o / "session")], cheap=False),
        Target("session_manifest", "S/manifest.json", "json",
               lambda w, o: ["device", "selftest", "--config", str(w / "cfg/rig.toml"), "--source",
                             f"replay:session:{w / 'S'}", "--frames", "2"]),
        Target("session_cam_csv", "S/mav0/cam0/data.csv", "text",
               lambda w, o: ["device", "selftest", "--config", str(w / "cfg/rig.toml"), "--source",
                             f"replay:session:{w / 'S'}", "--imu", "none", "--frames", "2"]),
        Target("session_imu_csv", "S/mav0/imu0/data.csv", "text",
               lambda w, o: ["device", "calibrate-imu", f"session:{w / 'S'}", ]),
        Target("session_imu_yaml", "S/mav0/imu0/sensor.yaml", "yaml",
               lambda w, o: ["odometry", f"session:{w / 'S'}", "--frames", "3", *out_arg(o)], cheap=False),
        Target("session_rig_yaml", "S/mav0/rig.yaml", "yaml",
               lambda w, o: ["device", "selftest", "--config", str(w / "cfg/rig.toml"), "--source",
                             f"replay:session:{w / 'S'}", "--imu", "none", "--frames", "2"]),
        Target("session_trajectory", "S/trajectory.tum", "text",
               lambda w, o: ["host", "map", str(w / "S"), "--max-keyframes", "1", "--no-progress", *out_arg(o)],
               cheap=False),
        Target("session_groundtruth", "S/groundtruth.tum", "text",
               lambda w, o: ["odometry", f"session:{w / 'S'}", "--frames", "3", *out_arg(o)], cheap=False),
        Target("session_groundtruth_reprocess", "S/groundtruth.tum", "text",
               lambda w, o: ["host", "reprocess", str(w / "S"), "--preset", "quick", "--no-map", "--no-progress",
                             *out_arg(o)], cheap=False),
        Target("session_png", first_png, "png",
               lambda w, o: ["device", "selftest", "--config", str(w / "cfg/rig.toml"), "--source",
                             f"replay:session:{w / 'S'}", "--imu", "none", "--frames", "2"]),
        Target("features_png", "img/a.png", "png",
               lambda w, o: ["features", str(w / "img/a.png"), str(w / "img/b.png"), "--json"]),
        Target("store_state", "live/state.json", "json", lambda w, o: ["host", "sessions", str(w / "live")],
               restore="live"),
        Target("store_keyframe", kf_file[0].relative_to(w).as_posix(), "bin",
               lambda w, o: ["host", "sessions", str(w / "live")], restore="live"),
        Target("store_map", kf_file[0].relative_to(w).as_posix(), "bin",
               lambda w, o: ["host", "map", str(w / "live" / "sessX"), "--no-progress", *out_arg(o)],
               cheap=False, restore="live"),
    ]
    index = [p for p in (w / "live" / "sessX").rglob("*") if p.is_file() and p.suffix in (".csv", ".json", ".txt")]
    for p in index:
        targets.append(Target(f"store_{p.stem}", p.relative_to(w).as_posix(), "json" if p.suffix == ".json" else
                              "text", lambda w, o: ["host", "sessions", str(w / "live")], restore="live"))
    # third-party data: chessboard pairs, a KITTI sequence, an EuRoC recording, the same with a Kalibr camchain
    board = DATA / "stereo_calib_chessboard"
    if board.is_dir():
        (w / "B").mkdir()
        for k in ("01", "02", "03", "04", "05", "06"):
            for side in ("left", "right"):
                shutil.copy(board / f"{side}{k}.jpg", w / "B" / f"{side}{k}.jpg")
        targets.append(Target("chessboard_jpg", "B/right03.jpg", "png", lambda w, o: [
            "device", "calibrate-stereo", str(w / "B"), "--board", "9x6", "--square-mm", "25", "--out",
            str(o / "rig.yaml")], cheap=False))
    kitti = DATA / "kitti_odometry" / "sequences" / "06"
    if kitti.is_dir():
        K = w / "K" / "sequences" / "06"
        for cam in ("image_0", "image_1"):
            (K / cam).mkdir(parents=True)
            for i in range(3):
                shutil.copy(kitti / cam / f"{i:06d}.png", K / cam / f"{i:06d}.png")
        shutil.copy(kitti / "calib.txt", K / "calib.txt")
        (K / "times.txt").write_text("\n".join((kitti / "times.txt").read_text().splitlines()[:3]) + "\n")
        (w / "K" / "poses").mkdir()
        (w / "K" / "poses" / "06.txt").write_text(
            "\n".join((DATA / "kitti_odometry" / "poses" / "06.txt").read_text().splitlines()[:3]) + "\n")
        kargs = lambda w, o: ["odometry", f"kitti:{w / 'K/sequences/06'}", "--frames", "3", *out_arg(o)]  # noqa: E731
        targets += [Target("kitti_calib", "K/sequences/06/calib.txt", "text", kargs, cheap=False),
                    Target("kitti_times", "K/sequences/06/times.txt", "text", kargs, cheap=False),
                    Target("kitti_gt", "K/poses/06.txt", "text", kargs, cheap=False),
                    Target("kitti_png", "K/sequences/06/image_1/000001.png", "png", kargs, cheap=False)]
    euroc = DATA / "euroc_v1_01_head" / "mav0"
    if euroc.is_dir():
        _mini_euroc(euroc, w / "E" / "mav0", 3)
        eargs = lambda w, o: ["odometry", f"euroc:{w / 'E/mav0'}", "--frames", "3", *out_arg(o)]  # noqa: E731
        ecal = lambda w, o: ["device", "calibrate-imu", f"euroc:{w / 'E/mav0'}", ]  # noqa: E731
        targets += [Target("euroc_sensor_yaml", "E/mav0/cam1/sensor.yaml", "yaml", eargs, cheap=False),
                    Target("euroc_cam_csv", "E/mav0/cam0/data.csv", "text", eargs, cheap=False),
                    Target("euroc_imu_csv", "E/mav0/imu0/data.csv", "text", ecal),
                    Target("euroc_imu_yaml", "E/mav0/imu0/sensor.yaml", "yaml", ecal),
                    Target("euroc_gt_csv", "E/mav0/state_groundtruth_estimate0/data.csv", "text", eargs, cheap=False)]
        shutil.copytree(w / "E", w / "C")
        for cam in ("cam0", "cam1"):
            p = w / "C" / "mav0" / cam / "sensor.yaml"
            p.write_text("\n".join(ln for ln in p.read_text().splitlines()
                                   if not ln.startswith(("intrinsics", "distortion", "camera_model"))) + "\n")
        (w / "C" / "camchain-imucam.yaml").write_text(_kalibr_from_euroc(w / "E" / "mav0"))
        (w / "cfg" / "chain.toml").write_text(f'[source]\nrig_file = "{w / "C" / "camchain-imucam.yaml"}"\n'
                                              f'[stream]\nenabled = false\n')
        targets += [Target("kalibr_camchain", "C/camchain-imucam.yaml", "yaml",
                           lambda w, o: ["device", "calibrate-imu", f"euroc:{w / 'C/mav0'}"]),
                    Target("kalibr_camchain_device", "C/camchain-imucam.yaml", "yaml", lambda w, o: [
                        "device", "selftest", "--config", str(w / "cfg/chain.toml"), "--source",
                        f"replay:euroc:{w / 'C/mav0'}", "--imu", "none", "--frames", "2"], cheap=False)]
    return targets


# ---------------------------------------------------------------------------------------------------
# running


class _Hang(BaseException):
    """Raised by the alarm in a command that ran past :data:`INPUT_TIME_LIMIT_S`."""


class _TracebackLog(logging.Handler):
    """Counts records logged at ERROR or above with a traceback (a crash a thread or the service caught)."""

    def __init__(self) -> None:
        super().__init__(logging.ERROR)
        self.records: list[logging.LogRecord] = []

    def emit(self, record: logging.LogRecord) -> None:
        if record.exc_info and record.exc_info[0] is not None:
            self.records.append(record)


@dataclass
class Finding:
    target: str
    mutator: str
    error: str
    where: str
    saved: str = ""


@dataclass
class FuzzResult:
    tried: int = 0
    tracebacks: list[Finding] = field(default_factory=list)
    hangs: list[Finding] = field(default_factory=list)
    exit_codes: dict[str, int] = field(default_factory=dict)
    per_target: dict[str, int] = field(default_factory=dict)
    seconds_per_target: dict[str, float] = field(default_factory=dict)
    seconds: float = 0.0


def _where(exc: BaseException) -> str:
    tb = traceback.extract_tb(exc.__traceback__)
    own = [f for f in tb if "stereopath" in f.filename or "/device/" in f.filename or "/host/" in f.filename]
    f = (own or tb)[-1] if (own or tb) else None
    return f"{Path(f.filename).name}:{f.lineno} ({f.name})" if f else "?"


def run_one(argv: list[str], log_handler: _TracebackLog) -> tuple[str, str, str]:
    """(outcome, detail, where): outcome is ``ok`` (an exit code), ``traceback`` or ``hang``."""
    from stereopath.host.cli import main

    log_handler.records.clear()
    out, err = io.StringIO(), io.StringIO()

    def alarm(_signum, _frame):
        raise _Hang()

    old = signal.signal(signal.SIGALRM, alarm)
    signal.setitimer(signal.ITIMER_REAL, INPUT_TIME_LIMIT_S)
    try:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            rc = main(["-q", *argv])
    except _Hang:
        return "hang", f"over {INPUT_TIME_LIMIT_S:g} s", ""
    except SystemExit as exc:  # argparse: a usage line and exit 2
        rc = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 2)
    except Exception as exc:  # noqa: BLE001 - the very thing counted
        return "traceback", f"{type(exc).__name__}: {str(exc)[:300]}", _where(exc)
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, old)
    if log_handler.records:
        r = log_handler.records[0]
        exc = r.exc_info[1]
        return "traceback", f"logged: {r.getMessage()[:150]} ({type(exc).__name__}: {str(exc)[:150]})", \
            _where(exc) if exc else "?"
    return "ok", str(rc), ""


def fuzz(targets: list[Target], workspace: Path, seed: int = 0, max_inputs: int | None = None,
         seconds: float | None = None, expensive_share: float = 0.15, keep: Path | None = None,
         progress: Callable[[str], None] | None = None) -> FuzzResult:
    """Mutate the targets' files in turn (cheap ones more often) until ``max_inputs`` or ``seconds``."""
    rng = random.Random(seed)
    res = FuzzResult()
    handler = _TracebackLog()
    root = logging.getLogger()
    root.addHandler(handler)
    cheap = [t for t in targets if t.cheap]
    dear = [t for t in targets if not t.cheap]
    pristine = {t.rel: (workspace / t.rel).read_bytes() for t in targets}
    restore_trees = {}
    for t in targets:
        if t.restore and t.restore not in restore_trees:
            restore_trees[t.restore] = workspace.parent / f"{workspace.name}.pristine.{t.restore}"
            shutil.rmtree(restore_trees[t.restore], ignore_errors=True)
            shutil.copytree(workspace / t.restore, restore_trees[t.restore])
    scratch = workspace.parent / f"{workspace.name}.out"
    start = time.perf_counter()
    try:
        while True:
            if max_inputs is not None and res.tried >= max_inputs:
                break
            if seconds is not None and time.perf_counter() - start >= seconds:
                break
            pool = dear if dear and (not cheap or rng.random() < expensive_share) else cheap
            t = pool[res.tried % len(pool)] if rng.random() < 0.5 else rng.choice(pool)
            mutators = PNG_MUTATORS if t.kind in ("png", "bin") else TEXT_MUTATORS
            mname = rng.choice(sorted(mutators))
            data = mutators[mname](rng, pristine[t.rel], t.kind)
            path = workspace / t.rel
            path.write_bytes(data)
            shutil.rmtree(scratch, ignore_errors=True)
            scratch.mkdir()
            t_in = time.perf_counter()
            outcome, detail, where = run_one(t.argv(workspace, scratch / "o"), handler)
            res.seconds_per_target[t.name] = res.seconds_per_target.get(t.name, 0.0) + time.perf_counter() - t_in
            res.tried += 1
            res.per_target[t.name] = res.per_target.get(t.name, 0) + 1
            if outcome == "ok":
                res.exit_codes[detail] = res.exit_codes.get(detail, 0) + 1
            else:
                f = Finding(t.name, mname, detail, where)
                if keep is not None:
                    keep.mkdir(parents=True, exist_ok=True)
                    saved = keep / f"{len(res.tracebacks) + len(res.hangs):03d}-{t.name}-{mname}{path.suffix}"
                    saved.write_bytes(data)
                    f.saved = str(saved)
                (res.tracebacks if outcome == "traceback" else res.hangs).append(f)
                if progress:
                    progress(f"{outcome}: {t.name} / {mname}: {detail} at {where}")
            path.write_bytes(pristine[t.rel])
            if t.restore:
                shutil.rmtree(workspace / t.restore)
                shutil.copytree(restore_trees[t.restore], workspace / t.restore)
    finally:
        root.removeHandler(handler)
        for t in targets:
            (workspace / t.rel).write_bytes(pristine[t.rel])
        shutil.rmtree(scratch, ignore_errors=True)
    res.seconds = time.perf_counter() - start
    return res


def quiet_logging() -> None:
    """The commands' log lines go nowhere (main's basicConfig is a no-op once the root has a handler)."""
    logging.basicConfig(handlers=[logging.NullHandler()], force=True)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=180.0, help="time budget (default 180)")
    ap.add_argument("--inputs", type=int, default=None, help="stop after this many inputs")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--only", default="", help="comma-separated target names")
    ap.add_argument("--expensive-share", type=float, default=0.25,
                    help="share of inputs for the targets that take seconds (odometry, map, device run)")
    ap.add_argument("--keep", type=Path, default=None, help="save every input that gave a traceback here")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    sys.path.insert(0, str(ROOT))
    quiet_logging()
    with tempfile.TemporaryDirectory(prefix="stereopath-fuzz-") as tmp:
        t0 = time.perf_counter()
        targets = build_workspace(Path(tmp) / "w")
        if args.only:
            names = set(args.only.split(","))
            targets = [t for t in targets if t.name in names]
        print(f"workspace built in {time.perf_counter() - t0:.1f} s: {len(targets)} targets "
              f"({', '.join(t.name for t in targets)})", flush=True)
        res = fuzz(targets, Path(tmp) / "w", seed=args.seed, max_inputs=args.inputs, seconds=args.seconds,
                   expensive_share=args.expensive_share, keep=args.keep,
                   progress=lambda s: print(s, flush=True))
    if args.json:
        print(json.dumps({"tried": res.tried, "tracebacks": [f.__dict__ for f in res.tracebacks],
                          "hangs": [f.__dict__ for f in res.hangs], "exit_codes": res.exit_codes,
                          "per_target": res.per_target, "seconds": res.seconds}, indent=1))
    else:
        print(f"inputs per target: {json.dumps(res.per_target)}")
        print(f"exit codes: {json.dumps(res.exit_codes)}")
        print(f"{res.tried} inputs tried in {res.seconds:.0f} s (seed {args.seed}): {len(res.tracebacks)} tracebacks, "
              f"{len(res.hangs)} hangs")
        for f in res.tracebacks + res.hangs:
            print(f"  {f.target} / {f.mutator}: {f.error} at {f.where}" + (f" [{f.saved}]" if f.saved else ""))
    return 1 if res.tracebacks or res.hangs else 0


if __name__ == "__main__":
    raise SystemExit(main())
