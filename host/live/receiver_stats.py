"""What the host receiver counts (``receiver.json``) and what the live view shows."""

from __future__ import annotations

import collections
from dataclasses import dataclass, field
from typing import Any

from stereopath.device.wire.protocol import Pose, Status

@dataclass
class SessionStats:
    poses: int = 0
    pose_gaps: int = 0            # poses missing between consecutive received seqs
    pose_out_of_order: int = 0
    keyframes: int = 0            # new keyframes stored
    keyframe_duplicates: int = 0
    last_pose_seq: int = -1
    first_t_ns: int | None = None
    last_t_ns: int | None = None

    def to_json(self) -> dict[str, Any]:
        return dict(vars(self))


@dataclass
class ReceiverStats:
    """Counters written to ``receiver.json`` (cumulative over receiver restarts)."""

    received: dict[str, int] = field(default_factory=lambda: {"pose": 0, "keyframe": 0, "status": 0, "session": 0})
    duplicates: int = 0
    pose_seq_gaps: int = 0
    rejected_by_reason: dict[str, int] = field(default_factory=dict)
    rejected_by_channel: dict[str, int] = field(default_factory=lambda: {"pose": 0, "keyframe": 0})
    link: dict[str, int] = field(default_factory=lambda: {
        "connects": 0, "disconnects": 0, "auth_failures": 0, "handshake_failures": 0, "hellos": 0,
        "rehellos_after_stall": 0, "acks_unsent": 0,
        "store_failures": 0, "poses_unsaved": 0, "rehellos_silent": 0})
    sessions: dict[str, SessionStats] = field(default_factory=dict)
    runs: int = 0

    @property
    def rejected(self) -> int:
        return sum(self.rejected_by_reason.values())

    def to_json(self) -> dict[str, Any]:
        return {
            "received": dict(self.received),
            "duplicates": self.duplicates,
            "pose_seq_gaps": self.pose_seq_gaps,
            "rejected": {"total": self.rejected, "by_reason": dict(self.rejected_by_reason),
                         "by_channel": dict(self.rejected_by_channel)},
            "link": dict(self.link),
            "sessions": {sid: s.to_json() for sid, s in self.sessions.items()},
            "runs": self.runs,
        }

    @classmethod
    def from_json(cls, data: dict[str, Any]) -> "ReceiverStats":
        st = cls()
        st.received.update({k: int(v) for k, v in data.get("received", {}).items() if k in st.received})
        st.duplicates = int(data.get("duplicates", 0))
        st.pose_seq_gaps = int(data.get("pose_seq_gaps", 0))
        rej = data.get("rejected", {})
        st.rejected_by_reason = {str(k): int(v) for k, v in rej.get("by_reason", {}).items()}
        st.rejected_by_channel.update({k: int(v) for k, v in rej.get("by_channel", {}).items()
                                       if k in st.rejected_by_channel})
        st.link.update({k: int(v) for k, v in data.get("link", {}).items() if k in st.link})
        for sid, s in data.get("sessions", {}).items():
            known = {k: v for k, v in s.items() if k in SessionStats.__dataclass_fields__}
            st.sessions[str(sid)] = SessionStats(**known)
        st.runs = int(data.get("runs", 0))
        return st


class EventRate:
    """Events per second over a sliding window (bounded memory)."""

    def __init__(self, window_s: float = 2.0, max_events: int = 4096) -> None:
        self.window_s = window_s
        self.t: collections.deque[float] = collections.deque(maxlen=max_events)

    def add(self, now: float) -> None:
        self.t.append(now)

    def rate(self, now: float) -> float:
        while self.t and now - self.t[0] > self.window_s:
            self.t.popleft()
        return len(self.t) / self.window_s


@dataclass
class LiveState:
    """What the live view shows (updated by the receiver as messages arrive)."""

    session_id: str | None = None
    pose: Pose | None = None
    speed_m_s: float = 0.0
    pose_rate_hz: float = 0.0
    keyframe_rate_hz: float = 0.0
    acked_seq: int = -1
    status: Status | None = None
    connected: bool = False
    last_rx: float | None = None           # monotonic time of the last message of any kind
    link_quality: str = "waiting"
    pose_window_ratio: float = 0.0          # poses received / poses sent over the last window
