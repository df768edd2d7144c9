"""``--format mcap --ros2``: the scan as a ROS 2 bag (MCAP storage) in ROS 2 message types, written
with ``rosbags`` (its ROS 2 Humble type store serialises CDR and stores each type's definition).

``OUT/rosbag2/`` (``metadata.yaml`` + the ``.mcap``), readable by ``ros2 bag play``, Foxglove and
``rosbags``:

================  ==========================  =================================================
topic             type                        what
================  ==========================  =================================================
``/cam0/image``,  ``sensor_msgs/msg/Image``   the images at every pose (``mono8`` or ``bgr8``)
``/cam1/image``
``/imu0``         ``sensor_msgs/msg/Imu``     gyro and specific force (no orientation:
                                              ``orientation_covariance[0] = -1``)
``/odom``         ``nav_msgs/msg/Odometry``   camera 0 (``cam0``) in ``world`` at every pose
``/tf``           ``tf2_msgs/msg/TFMessage``  ``world`` -> ``cam0`` at every pose
``/tf_static``    ``tf2_msgs/msg/TFMessage``  ``cam0`` -> ``cam1`` (the rig), once
================  ==========================  =================================================
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from stereopath.device.core.geometry import invert_pose, matrix_to_quat_xyzw
from stereopath.host.export.conventions import T_cam1_cam0
from stereopath.host.export.result import ExportSource
from stereopath.host.progress import Bar

if TYPE_CHECKING:
    from rosbags.typesys.store import Typestore

log = logging.getLogger(__name__)

BAG = "rosbag2"
TOPICS = {"cam0": "/cam0/image", "cam1": "/cam1/image", "imu": "/imu0", "odom": "/odom", "tf": "/tf",
          "tf_static": "/tf_static"}
TYPES = {"cam0": "sensor_msgs/msg/Image", "cam1": "sensor_msgs/msg/Image", "imu": "sensor_msgs/msg/Imu",
         "odom": "nav_msgs/msg/Odometry", "tf": "tf2_msgs/msg/TFMessage", "tf_static": "tf2_msgs/msg/TFMessage"}


class _Messages:
    """ROS 2 messages of the type store (instances of the classes it generates: opaque here)."""

    def __init__(self, typestore: Typestore) -> None:
        self.ts = typestore
        self.T = typestore.types

    def header(self, t_ns: int, frame: str) -> object:
        stamp = self.T["builtin_interfaces/msg/Time"](sec=int(t_ns) // 1_000_000_000, nanosec=int(t_ns) % 1_000_000_000)
        return self.T["std_msgs/msg/Header"](stamp=stamp, frame_id=frame)

    def vec(self, v: Sequence[float] | np.ndarray) -> object:
        return self.T["geometry_msgs/msg/Vector3"](x=float(v[0]), y=float(v[1]), z=float(v[2]))

    def quat(self, R: np.ndarray) -> object:
        q = matrix_to_quat_xyzw(np.asarray(R, float))
        return self.T["geometry_msgs/msg/Quaternion"](x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3]))

    def transform(self, t_ns: int, parent: str, child: str, T: np.ndarray) -> object:
        tr = self.T["geometry_msgs/msg/Transform"](translation=self.vec(T[:3, 3]), rotation=self.quat(T[:3, :3]))
        stamped = self.T["geometry_msgs/msg/TransformStamped"](header=self.header(t_ns, parent), child_frame_id=child,
                                                               transform=tr)
        return self.T["tf2_msgs/msg/TFMessage"](transforms=[stamped])

    def odometry(self, t_ns: int, T: np.ndarray) -> object:
        pt = self.T["geometry_msgs/msg/Point"](x=float(T[0, 3]), y=float(T[1, 3]), z=float(T[2, 3]))
        pose = self.T["geometry_msgs/msg/PoseWithCovariance"](
            pose=self.T["geometry_msgs/msg/Pose"](position=pt, orientation=self.quat(T[:3, :3])),
            covariance=np.zeros(36))
        twist = self.T["geometry_msgs/msg/TwistWithCovariance"](
            twist=self.T["geometry_msgs/msg/Twist"](linear=self.vec((0, 0, 0)), angular=self.vec((0, 0, 0))),
            covariance=np.full(36, -1.0))  # not estimated
        return self.T["nav_msgs/msg/Odometry"](header=self.header(t_ns, "world"), child_frame_id="cam0", pose=pose,
                                               twist=twist)

    def image(self, t_ns: int, frame: str, img: np.ndarray) -> object:
        img = np.ascontiguousarray(img, np.uint8)
        enc = "mono8" if img.ndim == 2 else "bgr8"
        h, w = img.shape[:2]
        return self.T["sensor_msgs/msg/Image"](header=self.header(t_ns, frame), height=h, width=w, encoding=enc,
                                               is_bigendian=0, step=int(img.strides[0]), data=img.reshape(-1))

    def imu(self, t_ns: int, gyro: np.ndarray, accel: np.ndarray) -> object:
        cov = np.zeros(9)
        no_orientation = np.zeros(9)
        no_orientation[0] = -1.0
        return self.T["sensor_msgs/msg/Imu"](
            header=self.header(t_ns, "imu"), orientation=self.T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
            orientation_covariance=no_orientation, angular_velocity=self.vec(gyro), angular_velocity_covariance=cov,
            linear_acceleration=self.vec(accel), linear_acceleration_covariance=cov)


def export_ros2(src: ExportSource, out: Path, progress: bool | None = None) -> dict[str, Any]:
    """Write ``OUT/rosbag2/``; returns the message counts per topic."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_HUMBLE)
    m = _Messages(ts)
    t, T = np.asarray(src.t_ns, np.int64), np.asarray(src.T_world_cam0, float)
    imu = src.imu if src.imu is not None and len(src.imu) else None
    imu_t = np.asarray(imu.t_ns, np.int64) if imu is not None else np.zeros(0, np.int64)
    counts = {k: 0 for k in TOPICS}
    with Writer(out / BAG, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        conn = {k: writer.add_connection(TOPICS[k], TYPES[k], typestore=ts) for k in TOPICS if k != "imu" or imu is not None}

        def put(key: str, t_ns: int, msg: object) -> None:
            writer.write(conn[key], int(t_ns), ts.serialize_cdr(msg, TYPES[key]))
            counts[key] += 1

        lo = int(np.searchsorted(imu_t, t[0])) if len(t) else 0
        with Bar(len(t), "ros2 bag", progress, "frame") as tick:
            for i in range(len(t)):
                hi = int(np.searchsorted(imu_t, t[i], side="right"))
                for j in range(lo, hi):
                    put("imu", imu_t[j], m.imu(imu_t[j], imu.gyro_rad_s[j], imu.accel_m_s2[j]))
                lo = max(lo, hi)
                if i == 0:
                    put("tf_static", t[0], m.transform(t[0], "cam0", "cam1", invert_pose(T_cam1_cam0(src.rig.R, src.rig.T))))
                put("tf", t[i], m.transform(t[i], "world", "cam0", T[i]))
                put("odom", t[i], m.odometry(t[i], T[i]))
                left, right = src.frame_loader(i)
                put("cam0", t[i], m.image(t[i], "cam0", left))
                put("cam1", t[i], m.image(t[i], "cam1", right))
                tick(1)
    return {"messages": counts, "file": BAG}
