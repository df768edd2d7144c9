"""``host live --mcap FILE``: the live stream recorded into an MCAP file as it arrives.

A small sink with the receiver's two callbacks: :meth:`McapSink.on_pose` (the pose thread) and
:meth:`McapSink.on_keyframe` (the polling thread), serialised by a lock onto one
:class:`~stereopath.host.export.mcap_recording.McapRecorder` (poses on ``/tf`` and ``/pose``, each
new keyframe's two images on ``/cam0/image`` and ``/cam1/image`` as the device encoded them, the
rig transform once it is known, a world rebase as metadata: :meth:`McapSink.on_rebase`).  Messages
are written as they come with their device times; the
file is complete (its summary and index written) when :meth:`close` runs.  Poses of every session
go into the one file; the session id is in the file's metadata as sessions appear.
"""

from __future__ import annotations

import json
import logging
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from stereopath.device.wire.messages import WorldRebase
from stereopath.device.wire.protocol import EncodedImage, Keyframe, Pose

log = logging.getLogger(__name__)

FORMATS = {"jpg": "jpeg", "jpeg": "jpeg", "png": "png"}


def _compressed(img: EncodedImage) -> tuple[bytes, str]:
    """An encoded image's bytes and Foxglove format (raw images are encoded as PNG)."""
    fmt = FORMATS.get(str(img.encoding).lower())
    if fmt is not None:
        return bytes(img.data), fmt
    import cv2

    from stereopath.device.wire.protocol import decode_image

    return cv2.imencode(".png", decode_image(img))[1].tobytes(), "png"


class McapSink:
    """Records poses and keyframes into ``path`` (see the module doc)."""

    def __init__(self, path: str | Path, rig_for: Callable[[str], Any] | None = None) -> None:
        from stereopath.host.export.mcap_recording import open_recorder

        self.path = Path(path)
        self.recorder, self.stream = open_recorder(self.path, source="host live")
        self.rig_for = rig_for
        self.lock = threading.Lock()
        self.sessions: set[str] = set()
        self.rigs_written: set[str] = set()
        self.failed: str | None = None
        self.rebases = 0

    def _session(self, sid: str, t_ns: int) -> None:
        if sid not in self.sessions:
            self.sessions.add(sid)
            self.recorder.writer.add_metadata(f"session {len(self.sessions)}", {"session_id": sid})
        if sid in self.rigs_written:
            return
        rig = self.rig_for(sid) if self.rig_for is not None else None
        if rig is not None:  # the device sends its rig once per session: written when first known
            self.rigs_written.add(sid)
            from stereopath.device.core.geometry import invert_pose
            from stereopath.host.export.conventions import T_cam1_cam0

            self.recorder.rig(t_ns, invert_pose(T_cam1_cam0(rig.R, rig.T)))

    def _guarded(self, what: str, write: Callable[[], None]) -> None:
        with self.lock:
            if self.failed is not None or self.stream.closed:
                return
            try:
                write()
            except OSError as exc:  # a full disk stops the recording, never the receiver
                self.failed = f"{what}: {exc}"
                log.error("--mcap %s: writing stopped (%s); the keyframe store is unaffected", self.path, exc)

    def on_pose(self, pose: Pose) -> None:
        def write() -> None:
            self._session(pose.session_id, pose.t_ns)
            self.recorder.pose(pose.t_ns, np.asarray(pose.T_world_cam, float))

        self._guarded("pose", write)

    def on_keyframe(self, kf: Keyframe, new: bool) -> None:
        if not new:
            return

        def write() -> None:
            self._session(kf.session_id, kf.t_ns)
            (left, fmt), (right, _) = _compressed(kf.left), _compressed(kf.right)
            self.recorder.images(kf.t_ns, left, right, fmt)

        self._guarded("keyframe", write)

    def on_rebase(self, msg: WorldRebase) -> None:
        """A session's world redefined on board (a start in motion): the poses and images written before
        ``msg.from_t_ns`` stay as written (an MCAP file is only appended to), and the file records the
        rebase as metadata ``world rebase N`` (``session_id``, ``from_t_ns``, ``T_new_old``: 4x4 as JSON,
        maps those poses into the world of the later ones), as the session folder's ``world_rebase.json`` does."""
        def write() -> None:
            self.rebases += 1
            self.recorder.writer.add_metadata(f"world rebase {self.rebases}", {
                "session_id": msg.session_id, "from_t_ns": str(int(msg.from_t_ns)),
                "T_new_old": json.dumps(np.round(np.asarray(msg.T_new_old, float), 12).tolist())})

        self._guarded("world rebase", write)

    def close(self) -> dict[str, int]:
        with self.lock:
            if not self.stream.closed:
                try:
                    self.recorder.close()
                finally:
                    self.stream.close()
        return dict(self.recorder.counts)
