"""The real depthai 3.x run host-side, with only the device nodes (Camera, IMU) stood in for.

``FakeOakWorld(...).module()`` returns what the backend uses in place of ``import depthai``:
every name is the **real** depthai module's (``ImgFrame``, ``MessageGroup``,
``MessageQueue``, ``node.Sync``, ``CalibrationHandler``, ``ImgTransformation``, enums...)
except three:

* ``Pipeline``: the real ``dai.Pipeline`` built with ``createImplicitDevice=False`` (no OAK
  here), so ``start``/``stop``/``wait``/``isRunning``, the host-side ``Sync`` node, output
  queues (``createOutputQueue`` defaults ``maxSize=16, blocking=False``) and their closing
  on ``stop()`` are all depthai's own.  Without a device ``dai.Pipeline()`` raises
  ``RuntimeError("No available devices")``; ``device_present=False`` copies that.
* ``node.Camera`` / ``node.IMU``: ``ThreadedHostNode`` subclasses that stand in for the
  device nodes (depthai refuses to create those without a device: "Pipeline is host only,
  cannot create device node").  Their outputs are real ``Node.Output``\\ s linked into the
  real ``Sync`` node and queues.
* ``getDefaultDevice().readCalibration()``: a real ``CalibrationHandler`` filled with the
  world's factory calibration (intrinsics at 1280x800, 14 distortion terms, CAM_B -> CAM_C
  extrinsics in centimetres, IMU extrinsics), so every getter is depthai's own arithmetic.

What the stand-in device does, copied from the device's documented behaviour:

* ``Camera.requestOutput(size, type, resizeMode=ImgResizeMode.CROP, fps)`` (CROP is the
  real default): each frame carries a real ``ImgTransformation`` from the 1280x800 sensor,
  built with depthai's own ``addCrop``/``addScale``: CROP = centred crop to the output
  aspect ratio, then scale; STRETCH = independent x/y scale; LETTERBOX = uniform scale and
  padding.  ``ImgFrame.getTransformation().getIntrinsicMatrix()`` is therefore depthai's
  answer for the frame, not ours.
* frame timestamps (``dai::Clock`` = CLOCK_MONOTONIC) mark the end of exposure (``clock_steps``
  shifts ``getTimestamp`` from a frame on, as a time-sync update does; ``getTimestampDevice``
  never steps), with the
  exposure in ``ImgFrame.cam.exposureTimeUs`` so ``getTimestamp(MIDDLE)`` is depthai's; the
  right camera may lag by ``right_skew_ns``; ``drop_left``/``drop_right`` frames never come;
  after ``disappear_after`` frames the device is lost: the node calls ``stopPipeline()``,
  which closes every queue (``get`` then raises ``QueueException``).
* ``IMU``: real ``IMUData`` messages of ``batch`` packets; accelerometer and gyroscope
  reports carry **their own timestamps** (the accelerometer ``accel_lag_ns`` after the
  gyroscope).  ``*_RAW`` reports are in the sensor-native frame (``R_native_imu`` applied,
  as the 3.x docs of ``IMUSensor`` say); ``*_CALIBRATED``/``*_UNCALIBRATED`` are in the
  DepthAI IMU frame that ``getCameraToImuExtrinsics`` refers to.  The true motion in the
  IMU frame is ``imu_truth(t_s) -> (gyro, accel)``.
"""

from __future__ import annotations

import datetime as dt
import threading
import time
from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np

import depthai as dai

SENSOR_SIZE = (1280, 800)


def _ts(ns: int) -> dt.timedelta:
    return dt.timedelta(microseconds=int(ns) // 1000)


def _timestamp(ns: int) -> Any:
    t = dai.Timestamp()
    t.sec, t.nsec = int(ns) // 1_000_000_000, int(ns) % 1_000_000_000
    return t


def sensor_transformation(K: list[list[float]], size: tuple[int, int], mode: Any) -> Any:
    """The ImgTransformation a frame of ``size`` gets from the 1280x800 sensor under ``mode``."""
    sw, sh = SENSOR_SIZE
    w, h = size
    t = dai.ImgTransformation(sw, sh, K)
    if mode == dai.ImgResizeMode.CROP:
        if sw * h > sh * w:      # sensor wider than the output: crop columns
            cw, ch = int(round(sh * w / h)), sh
        else:
            cw, ch = sw, int(round(sw * h / w))
        t.addCrop((sw - cw) // 2, (sh - ch) // 2, cw, ch)
        t.addScale(w / cw, h / ch)
    elif mode == dai.ImgResizeMode.STRETCH:
        t.addScale(w / sw, h / sh)
    else:  # LETTERBOX
        s = min(w / sw, h / sh)
        t.addScale(s, s)
        t.addPadding(0, 0, w - int(round(sw * s)), h - int(round(sh * s)))
    return t


class _StubCamera(dai.node.ThreadedHostNode):
    """Stands in for ``dai.node.Camera`` (a device node)."""

    _world: "FakeOakWorld"

    def __init__(self) -> None:
        super().__init__()
        self.out = self.createOutput()
        self.socket: Any = None
        self.initialControl = dai.CameraControl()  # the real control message
        self.request: dict[str, Any] | None = None

    def build(self, boardSocket: Any = dai.CameraBoardSocket.AUTO, sensorResolution: Any = None,
              sensorFps: Any = None) -> "_StubCamera":
        self.socket = boardSocket
        self._world.cameras[boardSocket.name] = self
        return self

    def requestOutput(self, size: tuple[int, int], type: Any = None, resizeMode: Any = dai.ImgResizeMode.CROP,
                      fps: float | None = None, enableUndistortion: Any = None, alphaScaling: Any = None) -> Any:
        if self.request is not None:
            raise RuntimeError("stand-in camera: one output per camera is all the backend needs")
        self.request = {"size": (int(size[0]), int(size[1])), "type": type, "resizeMode": resizeMode, "fps": fps,
                        "enableUndistortion": enableUndistortion}
        return self.out

    def run(self) -> None:
        w = self._world
        req = self.request
        assert req is not None
        size, fps = req["size"], float(req["fps"] or 30.0)
        period = int(round(1e9 / fps))
        exp_us = int(self.initialControl.getExposureTime().total_seconds() * 1e6) or 10000
        right = self.socket == dai.CameraBoardSocket.CAM_C
        skew = w.right_skew_ns if right else 0
        drops = w.drop_right if right else w.drop_left
        K = w.K_full[self.socket.name]
        transform = sensor_transformation(K, size, req["resizeMode"])
        t0 = w.grid_start(period)
        k = 0
        while self.isRunning():
            if w.max_frames is not None and k >= w.max_frames:
                return
            if w.disappear_after is not None and k >= w.disappear_after:
                w.lost = True
                self.stopPipeline()  # the device went away: depthai stops and closes the queues
                return
            t_end = t0 + k * period + exp_us * 1000 + skew
            delay = (t_end - time.monotonic_ns()) / 1e9
            if delay > 0:
                time.sleep(delay)
            if k not in drops:
                f = dai.ImgFrame()
                f.setType(dai.ImgFrame.Type.GRAY8)
                f.setFrame(w.image(1 if right else 0, k, size))
                f.setWidth(size[0])
                f.setHeight(size[1])
                f.setSequenceNum(k)
                f.setInstanceNum(self.socket.value)
                cam = f.cam
                cam.exposureTimeUs = exp_us
                f.cam = cam
                # getTimestamp: the host-synchronised clock, which steps where the time sync re-estimates
                # the offset (clock_steps: frame index -> step from that frame on); the device clock does not
                f.setTimestamp(_ts(t_end + sum(d for at, d in w.clock_steps.items() if k >= at)))
                f.setTimestampDevice(_ts(t_end + 1234 * 10**9))
                f.setTransformation(transform)
                self.out.send(f)
            k += 1


class _StubIMU(dai.node.ThreadedHostNode):
    """Stands in for ``dai.node.IMU`` (a device node)."""

    _world: "FakeOakWorld"

    def __init__(self) -> None:
        super().__init__()
        self.out = self.createOutput()
        self.sensors: list[Any] = []
        self.rate = 0
        self.batch = 1
        self.max_batch = 1
        self._world.imus.append(self)

    def enableIMUSensor(self, sensors: Any, reportRate: int) -> None:
        self.sensors = list(sensors) if isinstance(sensors, (list, tuple)) else [sensors]
        self.rate = int(reportRate)

    def setBatchReportThreshold(self, batchReportThreshold: int) -> None:
        self.batch = int(batchReportThreshold)

    def setMaxBatchReports(self, maxBatchReports: int) -> None:
        self.max_batch = int(maxBatchReports)

    def _frame_of(self, kind: str) -> Any:
        names = {s.name for s in self.sensors}
        if f"{kind}_RAW" in names:
            return self._world.R_native_imu           # sensor-native frame
        if names & {f"{kind}_CALIBRATED", f"{kind}_UNCALIBRATED", kind}:
            return np.eye(3)                          # DepthAI IMU frame
        return None

    def run(self) -> None:
        w = self._world
        if not self.rate:
            return
        period = int(round(1e9 / self.rate))
        R_gyro, R_acc = self._frame_of("GYROSCOPE"), self._frame_of("ACCELEROMETER")
        t = w.grid_start(period)
        seq = 0
        while self.isRunning():
            packets = []
            for _ in range(max(1, self.batch)):
                t_g, t_a = t, t + w.accel_lag_ns
                delay = (t_a - time.monotonic_ns()) / 1e9
                if delay > 0:
                    time.sleep(delay)
                pk = dai.IMUPacket()
                if R_gyro is not None:
                    g = dai.IMUReportGyroscope()
                    g.x, g.y, g.z = (float(v) for v in R_gyro @ w.imu_truth(t_g / 1e9)[0])
                    g.timestamp, g.sequence = _timestamp(t_g), seq
                    pk.gyroscope = g
                if R_acc is not None:
                    a = dai.IMUReportAccelerometer()
                    a.x, a.y, a.z = (float(v) for v in R_acc @ w.imu_truth(t_a / 1e9)[1])
                    a.timestamp, a.sequence = _timestamp(t_a), seq
                    pk.acceleroMeter = a
                packets.append(pk)
                t += period
                seq += 1
            msg = dai.IMUData()
            msg.packets = packets
            if not self.isRunning():
                return
            self.out.send(msg)


class _Device:
    def __init__(self, world: "FakeOakWorld") -> None:
        self._w = world

    def readCalibration(self) -> Any:
        return self._w.calibration()

    def readFactoryCalibration(self) -> Any:
        return self._w.calibration()


def _linear_motion(t_s: float) -> tuple[np.ndarray, np.ndarray]:
    """Gyro and accel in the IMU frame, linear in time (so interpolation between samples is exact)."""
    return (np.array([0.01, -0.02 + 0.1 * t_s, 0.005]),
            np.array([0.3 * t_s, -9.81, 0.2]))


@dataclass
class FakeOakWorld:
    device_present: bool = True
    right_skew_ns: int = 0
    drop_left: frozenset[int] = frozenset()
    drop_right: frozenset[int] = frozenset()
    disappear_after: int | None = None
    max_frames: int | None = None
    clock_steps: dict[int, int] = field(default_factory=dict)  # frame index -> host-clock step (ns) from then on
    K_full: dict[str, list[list[float]]] = field(default_factory=lambda: {
        "CAM_B": [[800.0, 0.0, 640.0], [0.0, 800.0, 400.0], [0.0, 0.0, 1.0]],
        "CAM_C": [[802.0, 0.0, 636.0], [0.0, 801.0, 402.0], [0.0, 0.0, 1.0]],
    })
    dist: dict[str, list[float]] = field(default_factory=lambda: {
        "CAM_B": [-0.1, 0.02] + [0.0] * 12, "CAM_C": [-0.11, 0.021] + [0.0] * 12})
    T_C_B_m: list[list[float]] = field(default_factory=lambda: [
        [1.0, 0.0, 0.0, -0.075], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0]])
    # IMU -> CAM_B (what setImuExtrinsics stores); None: a board without IMU calibration
    T_camB_imu_m: list[list[float]] | None = field(default_factory=lambda: np.eye(4).tolist())
    # sensor-native axes of the IMU chip relative to the DepthAI IMU frame (what *_RAW reports use)
    R_native_imu: np.ndarray = field(default_factory=lambda: np.array([[0.0, 1.0, 0.0], [-1.0, 0.0, 0.0],
                                                                        [0.0, 0.0, 1.0]]))
    accel_lag_ns: int = 1_300_000
    imu_truth: Callable[[float], tuple[np.ndarray, np.ndarray]] = _linear_motion

    def __post_init__(self) -> None:
        self.pipelines: list[Any] = []
        self.cameras: dict[str, _StubCamera] = {}
        self.imus: list[_StubIMU] = []
        self.lost = False
        self._lock = threading.Lock()
        self._t0: int | None = None

    def grid_start(self, period: int) -> int:
        """One start instant shared by every stand-in node (the device's frame grid)."""
        with self._lock:
            if self._t0 is None:
                self._t0 = time.monotonic_ns() + 20_000_000
            return self._t0

    def image(self, side: int, k: int, size: tuple[int, int]) -> np.ndarray:
        w, h = size
        img = np.full((h, w), 40 + side, np.uint8)
        img[0, :4] = np.frombuffer(int(k).to_bytes(4, "little"), np.uint8)
        return img

    def calibration(self) -> Any:
        """A real CalibrationHandler holding this world's factory calibration."""
        cal = dai.CalibrationHandler()
        for name in ("CAM_B", "CAM_C"):
            sock = getattr(dai.CameraBoardSocket, name)
            cal.setCameraIntrinsics(sock, self.K_full[name], *SENSOR_SIZE)
            cal.setDistortionCoefficients(sock, self.dist[name])
            cal.setCameraType(sock, dai.CameraModel.Perspective)
        T = np.asarray(self.T_C_B_m, float)
        cal.setCameraExtrinsics(dai.CameraBoardSocket.CAM_B, dai.CameraBoardSocket.CAM_C,
                                T[:3, :3].tolist(), (T[:3, 3] * 100.0).tolist())  # stored in centimetres
        if self.T_camB_imu_m is not None:
            Ti = np.asarray(self.T_camB_imu_m, float)
            cal.setImuExtrinsics(dai.CameraBoardSocket.CAM_B, Ti[:3, :3].tolist(), (Ti[:3, 3] * 100.0).tolist())
        return cal

    def module(self) -> "_OakModule":
        return _OakModule(self)


class _Nodes:
    def __init__(self, world: FakeOakWorld) -> None:
        self.Camera = type("Camera", (_StubCamera,), {"_world": world})
        self.IMU = type("IMU", (_StubIMU,), {"_world": world})

    def __getattr__(self, name: str) -> Any:
        return getattr(dai.node, name)


class _OakModule:
    """``depthai`` as the backend sees it: the real module, device nodes and device stood in for."""

    def __init__(self, world: FakeOakWorld) -> None:
        self.node = _Nodes(world)
        stubs = (self.node.Camera, self.node.IMU)

        class Pipeline(dai.Pipeline):
            def __init__(self, createImplicitDevice: bool = True) -> None:
                if createImplicitDevice and not world.device_present:
                    raise RuntimeError("No available devices")  # what dai.Pipeline() raises here
                super().__init__(False)
                self.world = world
                world.pipelines.append(self)

            def create(self, cls: Any) -> Any:
                node = super().create(cls)
                if cls not in stubs and isinstance(node, dai.node.Sync):
                    node.setRunOnHost(True)  # no device to run it on
                return node

            def getDefaultDevice(self) -> _Device:
                return _Device(world)

        self.Pipeline = Pipeline

    def __getattr__(self, name: str) -> Any:
        return getattr(dai, name)
