"""A fake of the depthai v3 module: the names, shapes, threads and failures the backend meets.

``FakeOakWorld(...).module()`` returns a namespace used in place of ``import depthai``:
``Pipeline`` (context manager; ``create``, ``start``, ``stop``, ``isRunning``,
``getDefaultDevice().readCalibration()``), ``node.Camera`` (``build``,
``requestOutput(size, type=, fps=)``, ``initialControl.setManualExposure``),
``node.Sync`` (``setSyncThreshold``, ``inputs["name"]``, ``out``), ``node.IMU``,
``ImgFrame`` (``getTimestamp(offset)`` as ``timedelta`` on the monotonic clock, default
end of exposure; ``getFrame``, ``getSequenceNum``), ``MessageGroup``, ``MessageQueue``
(``get(timeout=)`` -> message or None, ``tryGet``, ``tryGetAll``; raises
``MessageQueue.QueueException`` once closed) and ``CalibrationHandler`` (extrinsics in
centimetres unless ``unit=LengthUnit.METER``; ``getCameraExtrinsics(src, dst)`` maps
src-camera points into dst-camera coordinates).

The device runs on its own thread: the two mono cameras expose at ``fps`` (the right
one ``skew_ns`` later), frames listed in ``drop_left``/``drop_right`` never arrive (so
the Sync node cannot group them and the sequence numbers jump), and after
``disappear_after`` frames the device is lost: queues close and the pipeline stops.
"""

from __future__ import annotations

import collections
import datetime as dt
import enum
import threading
import time
from dataclasses import dataclass, field
from types import SimpleNamespace
from typing import Any

import numpy as np


class CameraBoardSocket(enum.Enum):
    AUTO = -1
    CAM_A = 0
    CAM_B = 1
    CAM_C = 2
    CAM_D = 3
    LEFT = 1   # deprecated aliases of CAM_B / CAM_C, as in depthai
    RIGHT = 2


class CameraExposureOffset(enum.Enum):
    START = 0
    MIDDLE = 1
    END = 2


class LengthUnit(enum.Enum):
    METER = 0
    CENTIMETER = 1
    MILLIMETER = 2
    INCH = 3
    FOOT = 4
    CUSTOM = 5


class IMUSensor(enum.Enum):
    ACCELEROMETER_RAW = 1
    ACCELEROMETER = 2
    GYROSCOPE_RAW = 4
    GYROSCOPE_CALIBRATED = 5


class CameraModel(enum.Enum):
    Perspective = 0
    Fisheye = 1
    Equirectangular = 2
    RadialDivision = 3


_UNIT_PER_M = {LengthUnit.METER: 1.0, LengthUnit.CENTIMETER: 100.0, LengthUnit.MILLIMETER: 1000.0}


class ImgFrame:
    class Type(enum.Enum):
        GRAY8 = 0
        NV12 = 1
        RAW8 = 2

    def __init__(self, data: np.ndarray, t_end_ns: int, exposure_us: int, seq: int, socket: CameraBoardSocket) -> None:
        self._data = data
        self._t_end = t_end_ns
        self._exp = exposure_us
        self._seq = seq
        self._socket = socket

    def getTimestamp(self, offset: CameraExposureOffset = CameraExposureOffset.END) -> dt.timedelta:
        t = self._t_end
        if offset == CameraExposureOffset.MIDDLE:
            t -= self._exp * 500
        elif offset == CameraExposureOffset.START:
            t -= self._exp * 1000
        return dt.timedelta(microseconds=t // 1000)

    def getTimestampDevice(self, offset: CameraExposureOffset = CameraExposureOffset.END) -> dt.timedelta:
        return self.getTimestamp(offset) + dt.timedelta(seconds=1234)

    def getExposureTime(self) -> dt.timedelta:
        return dt.timedelta(microseconds=self._exp)

    def getSequenceNum(self) -> int:
        return self._seq

    def getInstanceNum(self) -> int:
        return self._socket.value

    def getWidth(self) -> int:
        return self._data.shape[1]

    def getHeight(self) -> int:
        return self._data.shape[0]

    def getType(self) -> "ImgFrame.Type":
        return ImgFrame.Type.GRAY8

    def getFrame(self) -> np.ndarray:
        return self._data

    def getCvFrame(self) -> np.ndarray:
        return self._data


class MessageGroup:
    def __init__(self, msgs: dict[str, Any]) -> None:
        self._msgs = msgs

    def __getitem__(self, name: str) -> Any:
        return self._msgs[name]

    def getNumMessages(self) -> int:
        return len(self._msgs)

    def getIntervalNs(self) -> int:
        ts = [m._t_end for m in self._msgs.values()]
        return max(ts) - min(ts)


class _QueueException(RuntimeError):
    pass


class MessageQueue:
    QueueException = _QueueException

    def __init__(self, name: str = "", maxSize: int = 16, blocking: bool = True) -> None:
        self._name = name
        self._max = maxSize
        self._blocking = blocking
        self._items: collections.deque = collections.deque()
        self._cond = threading.Condition()
        self._closed = False
        self.overflowed = 0

    def send(self, msg: Any) -> None:
        with self._cond:
            if self._closed:
                raise _QueueException("MessageQueue was closed")
            if len(self._items) >= self._max:
                self._items.popleft()  # non-blocking queue: the oldest message is discarded
                self.overflowed += 1
            self._items.append(msg)
            self._cond.notify_all()

    def close(self) -> None:
        with self._cond:
            self._closed = True
            self._cond.notify_all()

    def isClosed(self) -> bool:
        return self._closed

    def get(self, timeout: dt.timedelta | None = None) -> Any:
        deadline = None if timeout is None else time.monotonic() + timeout.total_seconds()
        with self._cond:
            while not self._items:
                if self._closed:
                    raise _QueueException("MessageQueue was closed")
                if deadline is None:
                    self._cond.wait(0.1)
                    continue
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    return None
                self._cond.wait(remaining)
            return self._items.popleft()

    def tryGet(self) -> Any:
        with self._cond:
            if self._closed and not self._items:
                raise _QueueException("MessageQueue was closed")
            return self._items.popleft() if self._items else None

    def tryGetAll(self) -> list[Any]:
        with self._cond:
            if self._closed and not self._items:
                raise _QueueException("MessageQueue was closed")
            out = list(self._items)
            self._items.clear()
            return out


class _Output:
    def __init__(self, owner: Any, name: str) -> None:
        self.owner = owner
        self.name = name
        self.links: list[Any] = []
        self.queues: list[MessageQueue] = []

    def link(self, target: Any) -> None:
        self.links.append(target)

    def createOutputQueue(self, maxSize: int = 16, blocking: bool = True) -> MessageQueue:
        q = MessageQueue(self.name, maxSize, blocking)
        self.queues.append(q)
        return q


class _Input:
    def __init__(self, owner: Any, name: str) -> None:
        self.owner = owner
        self.name = name


class _CameraControl:
    def __init__(self) -> None:
        self.exposure_us: int | None = None
        self.iso: int | None = None

    def setManualExposure(self, exposureTimeUs: int, sensitivityIso: int) -> None:
        self.exposure_us, self.iso = int(exposureTimeUs), int(sensitivityIso)


class _Camera:
    def __init__(self, pipeline: "_Pipeline") -> None:
        self.pipeline = pipeline
        self.socket: CameraBoardSocket | None = None
        self.initialControl = _CameraControl()
        self.outputs: list[tuple[_Output, tuple[int, int], Any, float]] = []

    def build(self, boardSocket: CameraBoardSocket = CameraBoardSocket.AUTO, *args: Any, **kwargs: Any) -> "_Camera":
        if not self.pipeline._has_device:
            raise RuntimeError("Pipeline is host only, cannot create device node")
        self.socket = boardSocket
        return self

    def requestOutput(self, size: tuple[int, int], type: Any = None, resizeMode: Any = None,
                      fps: float | None = None, enableUndistortion: Any = None) -> _Output:
        out = _Output(self, f"cam{self.socket.value}")
        self.outputs.append((out, tuple(size), type, fps))
        return out


class _InputMap(dict):
    def __init__(self, owner: Any) -> None:
        super().__init__()
        self.owner = owner

    def __getitem__(self, name: str) -> _Input:
        if name not in self:
            super().__setitem__(name, _Input(self.owner, name))
        return super().__getitem__(name)


class _Sync:
    def __init__(self, pipeline: "_Pipeline") -> None:
        self.pipeline = pipeline
        self.threshold = dt.timedelta(milliseconds=10)
        self.attempts = -1
        self.inputs = _InputMap(self)
        self.out = _Output(self, "sync")

    def setSyncThreshold(self, syncThreshold: dt.timedelta) -> None:
        self.threshold = syncThreshold

    def setSyncAttempts(self, syncAttempts: int) -> None:
        self.attempts = syncAttempts

    def setRunOnHost(self, runOnHost: bool) -> None:
        pass


class _ImuReport:
    def __init__(self, x: float, y: float, z: float, t_ns: int) -> None:
        self.x, self.y, self.z = x, y, z
        self._t = t_ns

    def getTimestamp(self) -> dt.timedelta:
        return dt.timedelta(microseconds=self._t // 1000)


class _IMU:
    def __init__(self, pipeline: "_Pipeline") -> None:
        self.pipeline = pipeline
        self.sensors: list[IMUSensor] = []
        self.rate = 0
        self.batch = 1
        self.max_batch = 1
        self.out = _Output(self, "imu")

    def enableIMUSensor(self, sensors: list[IMUSensor], reportRate: int) -> None:
        self.sensors = list(sensors)
        self.rate = int(reportRate)

    def setBatchReportThreshold(self, batchReportThreshold: int) -> None:
        self.batch = int(batchReportThreshold)

    def setMaxBatchReports(self, maxBatchReports: int) -> None:
        self.max_batch = int(maxBatchReports)


class CalibrationHandler:
    """Factory calibration at 1280x800: intrinsics, 14 distortion terms, T_C_B in centimetres."""

    def __init__(self, world: "FakeOakWorld") -> None:
        self._w = world

    def getCameraIntrinsics(self, cameraId: CameraBoardSocket, resizeWidth: int = -1, resizeHeight: int = -1,
                            *args: Any, **kwargs: Any) -> list[list[float]]:
        K = np.array(self._w.K_full[cameraId.name], float)
        if resizeWidth > 0:
            sx, sy = resizeWidth / 1280.0, resizeHeight / 800.0
            K[0] *= sx
            K[1] *= sy
        return K.tolist()

    def getDistortionCoefficients(self, cameraId: CameraBoardSocket) -> list[float]:
        return list(self._w.dist[cameraId.name])

    def getDistortionModel(self, cameraId: CameraBoardSocket) -> CameraModel:
        return CameraModel.Perspective

    def getCameraExtrinsics(self, srcCamera: CameraBoardSocket, dstCamera: CameraBoardSocket,
                            useSpecTranslation: bool = False, unit: LengthUnit = LengthUnit.CENTIMETER) -> list[list[float]]:
        T = np.array(self._w.T_C_B_m, float)
        if (srcCamera, dstCamera) == (CameraBoardSocket.CAM_C, CameraBoardSocket.CAM_B):
            R, t = T[:3, :3], T[:3, 3]
            T = np.eye(4)
            T[:3, :3] = R.T
            T[:3, 3] = -R.T @ t
        elif (srcCamera, dstCamera) != (CameraBoardSocket.CAM_B, CameraBoardSocket.CAM_C):
            raise RuntimeError("There is no Camera data available corresponding to the requested source cameraId")
        T[:3, 3] *= _UNIT_PER_M[unit]
        return T.tolist()

    def getCameraToImuExtrinsics(self, cameraId: CameraBoardSocket, useSpecTranslation: bool = False,
                                 unit: LengthUnit = LengthUnit.CENTIMETER) -> list[list[float]]:
        T = np.array(self._w.T_imu_camB_m, float)
        T[:3, 3] *= _UNIT_PER_M[unit]
        return T.tolist()


class _Device:
    def __init__(self, world: "FakeOakWorld") -> None:
        self._w = world

    def readCalibration(self) -> CalibrationHandler:
        return CalibrationHandler(self._w)

    def readFactoryCalibration(self) -> CalibrationHandler:
        return CalibrationHandler(self._w)


class _Pipeline:
    _world: "FakeOakWorld"

    def __init__(self, createImplicitDevice: bool = True) -> None:
        w = self._world
        self._has_device = createImplicitDevice
        if createImplicitDevice and not w.device_present:
            raise RuntimeError("No available devices")
        self._nodes: list[Any] = []
        self._running = False
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        w.pipelines.append(self)

    def __enter__(self) -> "_Pipeline":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.stop()

    def create(self, cls: type) -> Any:
        node = cls(self)
        self._nodes.append(node)
        return node

    def getDefaultDevice(self) -> _Device:
        return _Device(self._world)

    def isRunning(self) -> bool:
        return self._running

    def start(self) -> None:
        if self._running:
            raise RuntimeError("Pipeline is already running")
        self._running = True
        self._thread = threading.Thread(target=self._run, name="fake-oak-device", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout=2.0)
            if self._thread.is_alive():
                self._world.errors.append("device thread did not stop")
        self._running = False

    def _queues_of(self, kind: type) -> list[MessageQueue]:
        return [q for n in self._nodes if isinstance(n, kind) for q in n.out.queues]

    def _run(self) -> None:
        w = self._world
        cams = {n.socket: n for n in self._nodes if isinstance(n, _Camera)}
        syncs = [n for n in self._nodes if isinstance(n, _Sync)]
        imus = [n for n in self._nodes if isinstance(n, _IMU)]
        left, right = cams[CameraBoardSocket.CAM_B], cams[CameraBoardSocket.CAM_C]
        (lout, size, _, fps) = left.outputs[0]
        period = int(1e9 / fps)
        exp_us = left.initialControl.exposure_us or 10000
        thr_ns = int(syncs[0].threshold.total_seconds() * 1e9) if syncs else 0
        sync_queues = self._queues_of(_Sync)
        imu_queues = self._queues_of(_IMU)
        imu_period = int(1e9 / imus[0].rate) if imus and imus[0].rate else 0
        t0 = time.monotonic_ns() + period
        next_imu = t0
        imu_batch: list[Any] = []
        k = 0
        try:
            while not self._stop.is_set():
                if w.max_frames is not None and k >= w.max_frames:
                    break
                t_end = t0 + k * period + exp_us * 1000
                delay = (t_end + w.right_skew_ns - time.monotonic_ns()) / 1e9
                if delay > 0 and self._stop.wait(delay):
                    break
                if w.disappear_after is not None and k >= w.disappear_after:
                    w.lost = True
                    break
                while imu_period and next_imu <= t_end:
                    g = _ImuReport(0.01, -0.02, 0.005, next_imu)
                    a = _ImuReport(0.0, -9.81, 0.0, next_imu)
                    imu_batch.append(SimpleNamespace(acceleroMeter=a, gyroscope=g))
                    next_imu += imu_period
                    if len(imu_batch) >= max(1, imus[0].batch):
                        for q in imu_queues:
                            q.send(SimpleNamespace(packets=list(imu_batch)))
                        imu_batch.clear()
                have_l, have_r = k not in w.drop_left, k not in w.drop_right
                if have_l and have_r and w.right_skew_ns <= thr_ns:
                    lf = ImgFrame(w.image(0, k, size), t_end, exp_us, k, CameraBoardSocket.CAM_B)
                    rf = ImgFrame(w.image(1, k, size), t_end + w.right_skew_ns, exp_us, k, CameraBoardSocket.CAM_C)
                    for q in sync_queues:
                        q.send(MessageGroup({"left": lf, "right": rf}))
                    w.groups_sent += 1
                k += 1
        finally:
            if w.lost:
                self._running = False
                for n in self._nodes:
                    if hasattr(n, "out"):
                        for q in n.out.queues:
                            q.close()


@dataclass
class FakeOakWorld:
    device_present: bool = True
    right_skew_ns: int = 0
    drop_left: frozenset[int] = frozenset()
    drop_right: frozenset[int] = frozenset()
    disappear_after: int | None = None
    max_frames: int | None = None
    K_full: dict[str, list[list[float]]] = field(default_factory=lambda: {
        "CAM_B": [[800.0, 0.0, 640.0], [0.0, 800.0, 400.0], [0.0, 0.0, 1.0]],
        "CAM_C": [[802.0, 0.0, 636.0], [0.0, 801.0, 402.0], [0.0, 0.0, 1.0]],
    })
    dist: dict[str, list[float]] = field(default_factory=lambda: {
        "CAM_B": [-0.1, 0.02] + [0.0] * 12, "CAM_C": [-0.11, 0.021] + [0.0] * 12})
    T_C_B_m: list[list[float]] = field(default_factory=lambda: [
        [1.0, 0.0, 0.0, -0.075], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0]])
    T_imu_camB_m: list[list[float]] = field(default_factory=lambda: np.eye(4).tolist())

    def __post_init__(self) -> None:
        self.pipelines: list[_Pipeline] = []
        self.errors: list[str] = []
        self.groups_sent = 0
        self.lost = False

    def image(self, side: int, k: int, size: tuple[int, int]) -> np.ndarray:
        w, h = size
        img = np.full((h, w), 40 + side, np.uint8)
        img[0, :4] = np.frombuffer(int(k).to_bytes(4, "little"), np.uint8)
        return img

    def module(self) -> SimpleNamespace:
        world = self

        class Pipeline(_Pipeline):
            _world = world

        node = SimpleNamespace(Camera=_Camera, Sync=_Sync, IMU=_IMU)
        return SimpleNamespace(
            Pipeline=Pipeline, node=node, CameraBoardSocket=CameraBoardSocket, ImgFrame=ImgFrame,
            CameraExposureOffset=CameraExposureOffset, LengthUnit=LengthUnit, IMUSensor=IMUSensor,
            CameraModel=CameraModel, MessageGroup=MessageGroup, MessageQueue=MessageQueue,
            CalibrationHandler=CalibrationHandler,
        )
