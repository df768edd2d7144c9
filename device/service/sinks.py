"""Where estimated frames go: the recorder and the streamer behind one small protocol.

The frame pipeline hands every IMU block, frame and estimate to each of its sinks; a sink that is
switched off is a do-nothing default (:class:`NoRecording`, :class:`NoStreaming`), so neither the
pipeline nor the service asks "is there a recorder?" before using one.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Protocol

if TYPE_CHECKING:
    import numpy as np

    from stereopath.device.core.frames import ImuSamples, StereoFrame
    from stereopath.device.core.trajectory import Trajectory
    from stereopath.device.estimation.base import PoseEstimate
    from stereopath.device.formats.recorder import SessionRecorder
    from stereopath.device.streaming.streamer import DeviceStreamer

log = logging.getLogger(__name__)


class FrameSink(Protocol):
    """What the frame pipeline calls, in this order for each frame."""

    name: str          # the stage name in the status report's ``stage_ms``

    def add_imu(self, block: ImuSamples) -> None: ...

    def add_frame(self, frame: StereoFrame) -> None: ...

    def add_estimate(self, frame: StereoFrame, est: PoseEstimate) -> None: ...

    def world_rebased(self, from_t_ns: int, T_new_old: np.ndarray) -> None: ...

    def status_fields(self) -> dict[str, Any]: ...

    def close(self) -> None: ...


class NullSink:
    """The do-nothing default of every sink method."""

    name = "off"
    active = False

    def add_imu(self, block: ImuSamples) -> None:
        pass

    def add_frame(self, frame: StereoFrame) -> None:
        pass

    def add_estimate(self, frame: StereoFrame, est: PoseEstimate) -> None:
        pass

    def world_rebased(self, from_t_ns: int, T_new_old: np.ndarray) -> None:
        """The estimator redefined its world at ``from_t_ns``: what came before maps by ``T_new_old``."""

    def status_fields(self) -> dict[str, Any]:
        return {}

    def close(self) -> None:
        pass


# ---------------------------------------------------------------------------------------- recording


class NoRecording(NullSink):
    """``recorder.enabled = false``."""

    state = "off"

    def status_fields(self) -> dict[str, Any]:
        return {"recorder_state": "off", "recorder_counts": {}}

    def set_reserve_bytes(self, n: int) -> None:
        pass

    def write_groundtruth(self, groundtruth: Trajectory | None) -> None:
        pass

    def write_json(self, name: str, data: object) -> None:
        pass


class RecordingSink(NoRecording):
    """The session on disk (:class:`~stereopath.device.formats.recorder.SessionRecorder`)."""

    name = "record"
    active = True

    def __init__(self, recorder: SessionRecorder) -> None:
        self.recorder = recorder

    @property
    def state(self) -> str:  # type: ignore[override]
        return self.recorder.state

    def add_imu(self, block: ImuSamples) -> None:
        self.recorder.add_imu(block)

    def add_frame(self, frame: StereoFrame) -> None:
        self.recorder.add_frame(frame)

    def add_estimate(self, frame: StereoFrame, est: PoseEstimate) -> None:
        self.recorder.add_pose(est.t_ns, est.T_world_cam)

    def status_fields(self) -> dict[str, Any]:
        return {"recorder_state": self.recorder.state, "recorder_counts": dict(self.recorder.counts)}

    def set_reserve_bytes(self, n: int) -> None:
        self.recorder.reserve_bytes = int(n)

    def write_groundtruth(self, groundtruth: Trajectory | None) -> None:
        """Simulated runs: ground truth over the frames recorded (for evaluating the session)."""
        rec = self.recorder
        if groundtruth is None or rec.state not in ("recording", "stopped_low_disk") or not rec.counts["frames"]:
            return
        from stereopath.device.formats.tum import Trajectory

        keep = groundtruth.t_ns <= rec.manifest().get("last_frame_t_ns")
        if keep.any():
            rec.write_groundtruth(Trajectory(groundtruth.t_ns[keep], groundtruth.T_world_cam[keep]))

    def write_json(self, name: str, data: object) -> None:
        from stereopath.device.formats.fileio import write_json_atomic

        try:
            write_json_atomic(Path(self.recorder.dir) / name, data)
        except OSError as exc:
            log.warning("could not write %s: %s", name, exc)

    def close(self) -> None:
        self.recorder.close()


# ---------------------------------------------------------------------------------------- streaming


class NoStreaming(NullSink):
    """``stream.enabled = false``."""

    pose_endpoint: str | None = None
    keyframe_endpoint: str | None = None

    def stats(self) -> dict[str, Any]:
        return {}

    def peers(self) -> list[dict[str, Any]]:
        return []

    def status_fields(self) -> dict[str, Any]:
        return {"streaming": False, "pose_endpoint": None, "keyframe_endpoint": None, "hosts": 0,
                "poses_sent": 0, "keyframes_spooled": 0, "keyframes_refused": 0}

    def publish_health(self, status: dict[str, Any]) -> None:
        pass

    def drain(self, seconds: float, clock: Callable[[], float]) -> None:
        pass


class StreamingSink(NoStreaming):
    """Poses and keyframes to the hosts (:class:`~stereopath.device.streaming.DeviceStreamer`)."""

    name = "stream"
    active = True

    def __init__(self, streamer: DeviceStreamer) -> None:
        self.streamer = streamer
        self.pose_endpoint = streamer.pose_endpoint
        self.keyframe_endpoint = streamer.keyframe_endpoint

    def add_estimate(self, frame: StereoFrame, est: PoseEstimate) -> None:
        st = self.streamer
        st.publish_pose(est.seq, est.t_ns, est.T_world_cam, tracking=est.status, inliers=int(est.inliers),
                        keyframe=bool(est.keyframe))
        if est.keyframe:
            st.offer_keyframe(frame.seq, frame.t_ns, est.T_world_cam, frame.left, frame.right)

    def world_rebased(self, from_t_ns: int, T_new_old: np.ndarray) -> None:
        """The poses and keyframes already sent are in the earlier world: the hosts are told how to map them."""
        self.streamer.publish_rebase(from_t_ns, T_new_old)

    def stats(self) -> dict[str, Any]:
        try:
            return self.streamer.stats()
        except RuntimeError:  # peers changed while copied; next time
            return {}

    def peers(self) -> list[dict[str, Any]]:
        return self.stats().get("peers", [])

    def status_fields(self) -> dict[str, Any]:
        s = self.stats()
        return {"streaming": True, "pose_endpoint": self.pose_endpoint, "keyframe_endpoint": self.keyframe_endpoint,
                "hosts": sum(1 for p in s.get("peers", []) if p.get("connected")),
                "poses_sent": s.get("poses_sent", 0), "keyframes_spooled": s.get("spool_count", 0),
                "keyframes_refused": s.get("keyframes_refused", 0),
                "keyframes_failed": s.get("keyframes_failed", 0),
                "spool_disk_full": s.get("spool_disk_full"), "keyframes_in_memory": s.get("keyframes_in_memory", 0),
                "keyframes_in_memory_unacked": s.get("keyframes_in_memory_unacked", 0),
                "backlog_keyframes": s.get("backlog_keyframes", 0), "backlog_sessions": s.get("backlog_sessions", 0)}

    def publish_health(self, status: dict[str, Any]) -> None:
        """The device health part of the status report, sent to the hosts on the keyframe channel."""
        from stereopath.device.wire.protocol import HEALTH_FIELDS

        self.streamer.publish_status(**{k: status[k] for k in HEALTH_FIELDS})

    def drain(self, seconds: float, clock: Callable[[], float]) -> None:
        """Wait up to ``seconds`` for a connected host to acknowledge every spooled keyframe (and those of
        earlier sessions offered in this run)."""
        st = self.streamer
        if seconds <= 0:
            return
        deadline = clock() + seconds
        while clock() < deadline:
            s = st.stats()
            accepted = s["keyframes_offered"] - s["keyframes_refused"]
            spooled_all = s["keyframes_spooled"] + s["keyframes_failed"] >= accepted
            peers = s.get("peers", [])
            if not peers:
                return  # no host has said hello: nobody to wait for
            if spooled_all and any(p["acked"] >= st.spool.last_seq for p in peers) and not s.get("backlog_keyframes"):
                log.info("every keyframe (%d) acknowledged by a host%s", st.spool.count,
                         f", and {s['backlog_delivered']} of earlier sessions" if s.get("backlog_delivered") else "")
                return
            time.sleep(0.05)
        left = st.stats().get("backlog_keyframes", 0)
        in_memory = st.spool.memory_count
        log.warning("stopping with keyframes not yet acknowledged by any host (those on disk stay in %s%s; the "
                    "next run offers them again%s)", st.spool.dir, f", and {left} of earlier sessions" if left else "",
                    f"; {in_memory} held in memory, the disk being full, do not" if in_memory else "")

    def close(self) -> None:
        self.streamer.close()
