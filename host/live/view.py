"""Live views of a receiving session: a terminal status line and (optionally) a rerun 3D view.

:class:`TerminalView` renders one updating block on stderr when it is a terminal; otherwise it
logs a summary line every ``log_interval_s``.  :class:`RerunView` logs the camera path, the
camera frustum and the latest keyframe images to rerun (spawned viewer or an ``.rrd`` file);
rerun-sdk is imported only when a RerunView is created.
"""

from __future__ import annotations

import logging
import sys
import threading
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol, TextIO

import numpy as np

from stereopath.device.core.rig import Rig
from stereopath.device.wire.protocol import Keyframe, Pose, WorldRebase, decode_image
from stereopath.host.live.receiver_stats import LiveState, ReceiverStats
from stereopath.host.live.world_rebase import SessionRebases

if TYPE_CHECKING:
    import open3d as o3d

log = logging.getLogger(__name__)


class LiveReport(Protocol):
    """What a view reads of a receiver: its live state and statistics (a ``lock``, where it has one, is held
    while they are read)."""

    live: LiveState
    stats: ReceiverStats


def _fmt_bytes(n: int | None) -> str:
    if n is None:
        return "?"
    for unit in ("B", "KB", "MB", "GB", "TB"):
        if n < 1024 or unit == "TB":
            return f"{n:.0f}{unit}" if unit == "B" else f"{n:.1f}{unit}"
        n /= 1024  # type: ignore[assignment]
    return f"{n}"


def summary_lines(receiver: LiveReport) -> list[str]:
    """The live view's text: session/pose line, rates line, device line."""
    live = receiver.live
    stats = receiver.stats
    p = live.pose
    sid = live.session_id or "-"
    if p is not None:
        pos = f"pos {p.position_m[0]:+8.3f} {p.position_m[1]:+8.3f} {p.position_m[2]:+8.3f} m"
        track = f"{p.tracking:<8} inl {p.inliers:4d}"
    else:
        pos, track = "pos      -        -        -   ", "-"
    st = live.status
    spooled = st.keyframes_spooled if st is not None and st.session_id == live.session_id else None
    backlog = "?" if spooled is None else str(max(0, spooled - 1 - live.acked_seq))
    line1 = f"[{sid}] {track}  {pos}  speed {live.speed_m_s:5.2f} m/s"
    line2 = (f"poses {live.pose_rate_hz:5.1f}/s  keyframes {live.keyframe_rate_hz:4.1f}/s "
             f"(stored to {live.acked_seq}, backlog {backlog})  pose gaps {stats.pose_seq_gaps}  "
             f"dup {stats.duplicates}  rejected {stats.rejected}  link {live.link_quality}")
    if st is not None:
        cpu = "?" if st.cpu_load_pct is None else f"{st.cpu_load_pct:.0f}%"
        temp = "?" if st.temperature_c is None else f"{st.temperature_c:.0f}C"
        line3 = (f"device: {st.frame_rate_hz:4.1f} fps  IMU {st.imu_rate_hz:5.0f} Hz  dropped {st.dropped_frames}  "
                 f"IMU gaps {st.imu_gaps}  cpu {cpu}  temp {temp}  disk {_fmt_bytes(st.disk_free_bytes)}  "
                 f"rec {st.recorder_state}  pose drops {st.poses_dropped}")
    else:
        line3 = "device: no status yet"
    return [line1, line2, line3]


class TerminalView:
    """Redraws a small block on a TTY; logs a line every ``log_interval_s`` otherwise."""

    def __init__(self, stream: TextIO | None = None, log_interval_s: float = 5.0, tty: bool | None = None) -> None:
        self.stream = stream if stream is not None else sys.stderr
        self.tty = self.stream.isatty() if tty is None else tty
        self.log_interval_s = log_interval_s
        self._next_log = time.monotonic() + log_interval_s
        self._drawn = 0

    def update(self, receiver: LiveReport) -> None:
        lock = getattr(receiver, "lock", None)
        if lock is not None:
            with lock:
                lines = summary_lines(receiver)
        else:
            lines = summary_lines(receiver)
        if self.tty:
            out = []
            if self._drawn:
                out.append(f"\x1b[{self._drawn}F")  # cursor up to the block's first line
            out.extend(f"\x1b[2K{line}\n" for line in lines)
            self.stream.write("".join(out))
            self.stream.flush()
            self._drawn = len(lines)
        elif time.monotonic() >= self._next_log:
            self._next_log = time.monotonic() + self.log_interval_s
            log.info("%s | %s", lines[0], lines[1])

    def close(self) -> None:
        if self.tty and self._drawn:
            self.stream.flush()


class RerunView:
    """3D path, camera frustum and latest keyframe images in rerun.

    ``save_path``: write an ``.rrd`` file; otherwise spawn a viewer.  ``rig`` (optional
    :class:`stereopath.device.core.rig.Rig`) gives the frustum's intrinsics; without it a 60-degree camera of the
    keyframe image size is drawn.
    """

    PATH_EVERY_S = 0.5
    MAX_PATH_POINTS = 20000

    def __init__(self, save_path: str | Path | None = None, spawn: bool = True, rig: Rig | None = None,
                 application_id: str = "stereopath_live") -> None:
        import rerun as rr

        self.rr = rr
        self.rec = rr.RecordingStream(application_id)
        if save_path is not None:
            self.rec.save(str(save_path))
        elif spawn:
            self.rec.spawn()
        self.rig = rig
        self._paths: dict[str, list[tuple[float, float, float]]] = {}
        self._kf_points: dict[str, list[tuple[float, float, float]]] = {}
        self._path_t: dict[str, list[int]] = {}  # the device times of each path's points (a world rebase maps them)
        self._kf_t: dict[str, list[int]] = {}
        self._rebases = SessionRebases()  # the rebases applied to what the view holds (each once)
        self._pinhole_size: dict[str, tuple[int, int]] = {}
        self._next_path = 0.0
        self._t0: dict[str, int] = {}
        self._last_t_ns: dict[str, int] = {}  # each session's latest device time (for the mapper thread's meshes)
        self._lock = threading.Lock()  # on_pose and on_keyframe come from different receiver threads
        self.rec.log("world", rr.ViewCoordinates.RDF, static=True)  # camera convention: x right, y down, z forward

    def _time(self, sid: str, t_ns: int) -> None:
        """Set device_time for what this thread logs next (rerun's time is per thread)."""
        t0 = self._t0.setdefault(sid, t_ns)
        self._last_t_ns[sid] = max(t_ns, self._last_t_ns.get(sid, t_ns))
        self.rec.set_time("device_time", duration=(t_ns - t0) * 1e-9)

    def on_pose(self, pose: Pose) -> None:
        with self._lock:
            self._on_pose(pose)

    def _on_pose(self, pose: Pose) -> None:
        rr = self.rr
        sid = pose.session_id
        self._time(sid, pose.t_ns)
        path, times = self._paths.setdefault(sid, []), self._path_t.setdefault(sid, [])
        path.append(tuple(pose.position_m))  # type: ignore[arg-type]
        times.append(pose.t_ns)
        if len(path) > self.MAX_PATH_POINTS:
            del path[: len(path) - self.MAX_PATH_POINTS], times[: len(times) - self.MAX_PATH_POINTS]
        self.rec.log(f"world/{sid}/camera", rr.Transform3D(translation=pose.position_m,
                                                            quaternion=rr.Quaternion(xyzw=pose.quat_xyzw)))
        if sid not in self._pinhole_size:
            self._log_pinhole(sid, 640, 480)
        now = time.monotonic()
        if now >= self._next_path:
            self._next_path = now + self.PATH_EVERY_S
            self.rec.log(f"world/{sid}/path", rr.LineStrips3D([np.asarray(path, dtype=np.float32)]))
        self.rec.log(f"status/{sid}/inliers", rr.Scalars([float(pose.inliers)]))

    def _log_pinhole(self, sid: str, w: int, h: int) -> None:
        rr = self.rr
        if self.rig is not None:
            cam = self.rig.cam0
            sx, sy = w / cam.size[0], h / cam.size[1]
            kwargs: dict[str, Any] = {"focal_length": [float(cam.fx * sx), float(cam.fy * sy)],
                                      "principal_point": [float(cam.cx * sx), float(cam.cy * sy)]}
        else:
            kwargs = {"focal_length": float(0.5 * w / np.tan(np.radians(30.0)))}
        self.rec.log(f"world/{sid}/camera/image", rr.Pinhole(width=w, height=h, camera_xyz=rr.ViewCoordinates.RDF,
                                                             **kwargs), static=True)
        self._pinhole_size[sid] = (w, h)

    def on_mesh(self, session_id: str, mesh: o3d.geometry.TriangleMesh) -> None:
        """Show the live dense model (called by the live mapper's thread)."""
        from stereopath.host.mapping.fusion import mesh_arrays

        v, f, c = mesh_arrays(mesh)
        with self._lock:
            if session_id in self._last_t_ns:  # on the device_time timeline too, at the latest pose or keyframe
                self._time(session_id, self._last_t_ns[session_id])
            kw = {} if c is None else {"vertex_colors": c}
            self.rec.log(f"world/{session_id}/model", self.rr.Mesh3D(vertex_positions=v, triangle_indices=f, **kw))

    def on_keyframe(self, kf: Keyframe, new: bool) -> None:
        if new:
            with self._lock:
                self._on_keyframe(kf)

    def _on_keyframe(self, kf: Keyframe) -> None:
        rr = self.rr
        sid = kf.session_id
        self._time(sid, kf.t_ns)
        h, w = kf.left.shape[:2]
        if self._pinhole_size.get(sid) != (w, h):
            self._log_pinhole(sid, w, h)
        pts, times = self._kf_points.setdefault(sid, []), self._kf_t.setdefault(sid, [])
        pts.append(tuple(kf.position_m))  # type: ignore[arg-type]
        times.append(kf.t_ns)
        del pts[: max(0, len(pts) - self.MAX_PATH_POINTS)], times[: max(0, len(times) - self.MAX_PATH_POINTS)]
        self.rec.log(f"world/{sid}/keyframes", rr.Points3D(np.asarray(pts, dtype=np.float32), radii=0.01))
        for name, img in (("left", kf.left), ("right", kf.right)):
            entity = f"world/{sid}/camera/image" if name == "left" else f"images/{sid}/right"
            if img.encoding in ("jpg", "png"):
                media = "image/jpeg" if img.encoding == "jpg" else "image/png"
                self.rec.log(entity, rr.EncodedImage(contents=img.data, media_type=media))
            else:
                self.rec.log(entity, rr.Image(decode_image(img)))

    def on_rebase(self, msg: WorldRebase) -> None:
        """The device redefined the session's world: the path and keyframe points shown from before it move
        into the new world (the receiver maps the live poses that arrive after this)."""
        with self._lock:
            new = self._rebases.add(msg)
            if new is None:
                return
            sid = msg.session_id
            for points, times, entity in ((self._paths, self._path_t, "path"), (self._kf_points, self._kf_t, "keyframes")):
                pts = points.get(sid)
                if not pts:
                    continue
                P = np.asarray(pts, float)
                before = np.asarray(times[sid]) < new.from_t_ns
                P[before] = P[before] @ new.T_new_old[:3, :3].T + new.T_new_old[:3, 3]
                points[sid] = [tuple(p) for p in P]
                data = np.asarray(points[sid], dtype=np.float32)
                self.rec.log(f"world/{sid}/{entity}", self.rr.LineStrips3D([data]) if entity == "path"
                             else self.rr.Points3D(data, radii=0.01))

    def close(self) -> None:
        self.rec.flush()
        self.rec.disconnect()
