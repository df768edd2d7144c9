"""An MCAP recording of a scan for Foxglove (and any MCAP reader), written with the ``mcap`` package.

Channels (Foxglove's protobuf schemas from ``foxglove-schemas-protobuf``; each schema is stored as
the ``FileDescriptorSet`` of its message, the way MCAP's protobuf profile asks):

==================  ==========================  ===================================================
topic               schema                      what
==================  ==========================  ===================================================
``/tf``             ``foxglove.FrameTransform``  ``world`` -> ``cam0`` at every pose; ``cam0`` ->
                                                ``cam1`` (the rig) once, at the first pose
``/pose``           ``foxglove.PoseInFrame``     camera 0's pose in ``world`` at every pose
``/cam0/image``,    ``foxglove.CompressedImage`` the left and right images (PNG or JPEG bytes as
``/cam1/image``                                 recorded or stored)
``/map``            ``foxglove.PointCloud``      the bundle-adjusted points with colours, once
``/imu``            ``stereopath.Imu`` (JSON)    gyro (rad/s) and specific force (m/s^2), body frame
==================  ==========================  ===================================================

Log and publish times are the data's own times (the session clock, ns).  :class:`McapRecorder`
is the one writer: the export drives it from stored data, ``host live --mcap`` from the stream
as it arrives; it writes messages as they come (chunked, bounded memory).
"""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import TYPE_CHECKING, BinaryIO

import numpy as np

if TYPE_CHECKING:
    from google.protobuf.descriptor import FileDescriptor
    from google.protobuf.message import Message

log = logging.getLogger(__name__)

IMU_SCHEMA = {
    "title": "stereopath.Imu",
    "description": "One IMU sample in the body (IMU) frame",
    "type": "object",
    "properties": {
        "timestamp": {"type": "object", "properties": {"sec": {"type": "integer"}, "nsec": {"type": "integer"}}},
        "frame_id": {"type": "string"},
        "angular_velocity": {"type": "object", "description": "rad/s",
                             "properties": {k: {"type": "number"} for k in "xyz"}},
        "linear_acceleration": {"type": "object", "description": "specific force, m/s^2 (+9.81 up at rest)",
                                "properties": {k: {"type": "number"} for k in "xyz"}},
    },
}
TOPICS = {"tf": "/tf", "pose": "/pose", "cam0": "/cam0/image", "cam1": "/cam1/image", "map": "/map", "imu": "/imu"}
WORLD, CAM0, CAM1, IMU_FRAME = "world", "cam0", "cam1", "imu"


def file_descriptor_set(message_class: type[Message]) -> bytes:
    """The serialized ``FileDescriptorSet`` of a protobuf message class and every file it depends on."""
    from google.protobuf.descriptor_pb2 import FileDescriptorSet

    fds = FileDescriptorSet()
    seen: set[str] = set()

    def add(fd: FileDescriptor) -> None:
        if fd.name in seen:
            return
        seen.add(fd.name)
        for dep in fd.dependencies:
            add(dep)
        fd.CopyToProto(fds.file.add())

    add(message_class.DESCRIPTOR.file)
    return fds.SerializeToString()


def quat_xyzw(R: np.ndarray) -> np.ndarray:
    from stereopath.device.core.geometry import matrix_to_quat_xyzw

    return np.asarray(matrix_to_quat_xyzw(np.asarray(R, float)), float)


class McapRecorder:
    """Writes a scan's messages into an MCAP stream as they come; ``close()`` finishes the file."""

    def __init__(self, stream: BinaryIO, profile: str = "", source: str = "") -> None:
        from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
        from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
        from foxglove_schemas_protobuf.PointCloud_pb2 import PointCloud
        from foxglove_schemas_protobuf.PoseInFrame_pb2 import PoseInFrame
        from mcap.writer import Writer

        self.classes = {"tf": FrameTransform, "pose": PoseInFrame, "image": CompressedImage, "map": PointCloud}
        self.writer = Writer(stream)
        self.writer.start(profile=profile, library="stereopath")
        if source:
            self.writer.add_metadata("stereopath", {"source": source})
        self.schema: dict[str, int] = {}
        for key, cls in self.classes.items():
            self.schema[key] = self.writer.register_schema(cls.DESCRIPTOR.full_name, "protobuf",
                                                           file_descriptor_set(cls))
        imu_schema = self.writer.register_schema("stereopath.Imu", "jsonschema", json.dumps(IMU_SCHEMA).encode())
        self.channel = {
            "tf": self.writer.register_channel(TOPICS["tf"], "protobuf", self.schema["tf"]),
            "pose": self.writer.register_channel(TOPICS["pose"], "protobuf", self.schema["pose"]),
            "cam0": self.writer.register_channel(TOPICS["cam0"], "protobuf", self.schema["image"]),
            "cam1": self.writer.register_channel(TOPICS["cam1"], "protobuf", self.schema["image"]),
            "map": self.writer.register_channel(TOPICS["map"], "protobuf", self.schema["map"]),
            "imu": self.writer.register_channel(TOPICS["imu"], "json", imu_schema),
        }
        self.sequence = {k: 0 for k in self.channel}
        self.rig_written = False
        self.counts = {k: 0 for k in self.channel}

    def _put(self, key: str, t_ns: int, data: bytes) -> None:
        self.writer.add_message(self.channel[key], log_time=int(t_ns), data=data, publish_time=int(t_ns),
                                sequence=self.sequence[key])
        self.sequence[key] += 1
        self.counts[key] += 1

    def _transform(self, t_ns: int, parent: str, child: str, T: np.ndarray) -> bytes:
        m = self.classes["tf"]()
        m.timestamp.FromNanoseconds(int(t_ns))
        m.parent_frame_id, m.child_frame_id = parent, child
        x, y, z = (float(v) for v in T[:3, 3])
        m.translation.x, m.translation.y, m.translation.z = x, y, z
        q = quat_xyzw(T[:3, :3])
        m.rotation.x, m.rotation.y, m.rotation.z, m.rotation.w = (float(v) for v in q)
        return m.SerializeToString()

    def rig(self, t_ns: int, T_cam0_cam1: np.ndarray) -> None:
        """The right camera in the left one's frame (written once)."""
        self._put("tf", t_ns, self._transform(t_ns, CAM0, CAM1, T_cam0_cam1))
        self.rig_written = True

    def pose(self, t_ns: int, T_world_cam0: np.ndarray) -> None:
        T = np.asarray(T_world_cam0, float)
        self._put("tf", t_ns, self._transform(t_ns, WORLD, CAM0, T))
        m = self.classes["pose"]()
        m.timestamp.FromNanoseconds(int(t_ns))
        m.frame_id = WORLD
        p, q = m.pose.position, m.pose.orientation
        p.x, p.y, p.z = (float(v) for v in T[:3, 3])
        q.x, q.y, q.z, q.w = (float(v) for v in quat_xyzw(T[:3, :3]))
        self._put("pose", t_ns, m.SerializeToString())

    def images(self, t_ns: int, left: bytes, right: bytes, fmt: str) -> None:
        for key, data in (("cam0", left), ("cam1", right)):
            m = self.classes["image"]()
            m.timestamp.FromNanoseconds(int(t_ns))
            m.frame_id = key
            m.format = fmt
            m.data = bytes(data)
            self._put(key, t_ns, m.SerializeToString())

    def imu(self, t_ns: np.ndarray, gyro_rad_s: np.ndarray, accel_m_s2: np.ndarray) -> None:
        for t, g, a in zip(np.asarray(t_ns, np.int64), np.asarray(gyro_rad_s, float), np.asarray(accel_m_s2, float)):
            msg = {"timestamp": {"sec": int(t) // 1_000_000_000, "nsec": int(t) % 1_000_000_000}, "frame_id": IMU_FRAME,
                   "angular_velocity": dict(zip("xyz", map(float, g))),
                   "linear_acceleration": dict(zip("xyz", map(float, a)))}
            self._put("imu", int(t), json.dumps(msg).encode())

    def points(self, t_ns: int, xyz: np.ndarray, rgb: np.ndarray | None = None) -> None:
        from foxglove_schemas_protobuf.PackedElementField_pb2 import PackedElementField

        xyz = np.asarray(xyz, "<f4").reshape(-1, 3)
        rgb = np.full((len(xyz), 3), 255, np.uint8) if rgb is None else np.asarray(rgb, np.uint8).reshape(-1, 3)
        rec = np.empty(len(xyz), np.dtype([("p", "<f4", 3), ("c", "u1", 3), ("a", "u1")]))
        rec["p"], rec["c"], rec["a"] = xyz, rgb, 255
        m = self.classes["map"]()
        m.timestamp.FromNanoseconds(int(t_ns))
        m.frame_id = WORLD
        m.pose.orientation.w = 1.0
        m.point_stride = rec.dtype.itemsize
        for name, off, typ in (("x", 0, PackedElementField.FLOAT32), ("y", 4, PackedElementField.FLOAT32),
                               ("z", 8, PackedElementField.FLOAT32), ("red", 12, PackedElementField.UINT8),
                               ("green", 13, PackedElementField.UINT8), ("blue", 14, PackedElementField.UINT8),
                               ("alpha", 15, PackedElementField.UINT8)):
            f = m.fields.add()
            f.name, f.offset, f.type = name, off, typ
        m.data = rec.tobytes()
        self._put("map", t_ns, m.SerializeToString())

    def close(self) -> None:
        self.writer.finish()


def open_recorder(path: str | Path, source: str = "") -> tuple[McapRecorder, BinaryIO]:
    """A recorder writing into ``path`` (created); close the recorder, then the stream."""
    stream = open(path, "wb")
    try:
        return McapRecorder(stream, source=source), stream
    except BaseException:
        stream.close()
        raise
