"""Small stand-ins for a recorded sequence and a simulated session (the interfaces the sources use)."""

from __future__ import annotations

import numpy as np

from stereopath.device.core.frames import ImuSamples, StereoFrame
from stereopath.device.core.rig import paper_rig


def frame_image(i: int, side: int, size: tuple[int, int] = (64, 48)) -> np.ndarray:
    w, h = size
    img = np.full((h, w), 100 + side, np.uint8)
    img[0, :4] = np.frombuffer(int(i).to_bytes(4, "little"), np.uint8)
    return img


def image_index(img: np.ndarray) -> int:
    return int.from_bytes(bytes(np.asarray(img[0, :4], np.uint8)), "little")


class StandinSequence:
    """Sequence interface: rig, t_ns, len, frame(i), imu (200 Hz still IMU or None)."""

    name = "standin"

    def __init__(self, n: int = 20, fps: float = 20.0, t0_ns: int = 5_000_000_000, with_imu: bool = True,
                 imu_hz: float = 200.0, size: tuple[int, int] = (64, 48)) -> None:
        self.rig = paper_rig()
        self.size = size
        self.t_ns = t0_ns + np.round(np.arange(n) * 1e9 / fps).astype(np.int64)
        self.loaded: list[int] = []
        self.imu = None
        if with_imu:
            m = int((self.t_ns[-1] - self.t_ns[0]) / 1e9 * imu_hz) + 40
            t = self.t_ns[0] - int(0.1e9) + np.round(np.arange(m) * 1e9 / imu_hz).astype(np.int64)
            gyro = np.zeros((m, 3))
            gyro[:, 2] = (t - t[0]) / 1e9 * 0.1  # a slowly rising yaw rate: linear in time
            accel = np.tile([0.0, 0.0, 9.80665], (m, 1))
            self.imu = ImuSamples(t, gyro, accel)

    def __len__(self) -> int:
        return len(self.t_ns)

    def frame(self, i: int) -> StereoFrame:
        self.loaded.append(i)
        return StereoFrame(i, int(self.t_ns[i]), frame_image(i, 0, self.size), frame_image(i, 1, self.size),
                           {"index": i})

    # the simulator's name for it
    def render(self, i: int) -> StereoFrame:
        return self.frame(i)


def source_settings(backend: str, size: list[int], pair_tolerance_us: int, **kw):
    """A validated SourceSettings for a fake-backed source test (fast frame rate, short timeout)."""
    from stereopath.device.core.config import from_mapping
    from stereopath.device.settings import SourceSettings

    base = {"backend": backend, "fps": 100.0, "exposure_us": 2000, "pair_tolerance_us": pair_tolerance_us,
            "timeout_s": 0.4, "size": size}
    sub = dict(kw.pop(backend, {}))
    if backend == "picamera2":  # libcamera's software sync start-up at its shortest (the client's first packet)
        sub.setdefault("sync_frames", 30)
    base.update(kw)
    base[backend] = sub
    return from_mapping(SourceSettings, base)


def take(src, n: int) -> list:
    """The first ``n`` frames of a source (stops iterating as soon as it has them)."""
    out = []
    for f in src:
        out.append(f)
        if len(out) >= n:
            break
    return out
