"""What the host receiver counts (``receiver.json``) and what the live view shows."""

from __future__ import annotations

import collections
from dataclasses import asdict, dataclass, field, fields
from typing import Any, Mapping

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


def _int_fields(cls: type, data: Mapping[str, int | str | float]) -> dict[str, int]:
    """The entries of ``data`` (a JSON object) that name a field of the counter dataclass ``cls``, as ints."""
    names = {f.name for f in fields(cls)}
    return {k: int(v) for k, v in data.items() if k in names}


@dataclass
class MessageCounts:
    """Messages received, by kind (``receiver.json``'s ``received``)."""

    pose: int = 0
    keyframe: int = 0
    status: int = 0
    session: int = 0
    rebase: int = 0  # world rebases (repeated with every status; each applied once)

    def total(self) -> int:
        return self.pose + self.keyframe + self.status + self.session + self.rebase

    def to_json(self) -> dict[str, int]:
        return asdict(self)

    @classmethod
    def from_json(cls, data: Mapping[str, int | str | float]) -> "MessageCounts":
        return cls(**_int_fields(cls, data))


@dataclass
class LinkCounters:
    """The keyframe link's and the host store's events (``receiver.json``'s ``link``)."""

    connects: int = 0
    disconnects: int = 0
    auth_failures: int = 0
    handshake_failures: int = 0
    hellos: int = 0
    rehellos_after_stall: int = 0
    acks_unsent: int = 0             # acknowledgements the socket would not take (the next hello resynchronises)
    store_failures: int = 0          # keyframes or rigs this host could not store (not acknowledged)
    poses_unsaved: int = 0           # poses shown live but not appended to poses.tum (disk full)
    rehellos_silent: int = 0

    def to_json(self) -> dict[str, int]:
        return asdict(self)

    @classmethod
    def from_json(cls, data: Mapping[str, int | str | float]) -> "LinkCounters":
        return cls(**_int_fields(cls, data))


@dataclass
class ReceiverStats:
    """Counters written to ``receiver.json`` (cumulative over receiver restarts)."""

    received: MessageCounts = field(default_factory=MessageCounts)
    duplicates: int = 0
    pose_seq_gaps: int = 0
    rejected_by_reason: dict[str, int] = field(default_factory=dict)  # keyed by DecodeError reason (open set)
    rejected_by_channel: dict[str, int] = field(default_factory=lambda: {"pose": 0, "keyframe": 0})
    link: LinkCounters = field(default_factory=LinkCounters)
    sessions: dict[str, SessionStats] = field(default_factory=dict)
    runs: int = 0

    @property
    def rejected(self) -> int:
        return sum(self.rejected_by_reason.values())

    def to_json(self) -> dict[str, Any]:
        return {
            "received": self.received.to_json(),
            "duplicates": self.duplicates,
            "pose_seq_gaps": self.pose_seq_gaps,
            "rejected": {"total": self.rejected, "by_reason": dict(self.rejected_by_reason),
                         "by_channel": dict(self.rejected_by_channel)},
            "link": self.link.to_json(),
            "sessions": {sid: s.to_json() for sid, s in self.sessions.items()},
            "runs": self.runs,
        }

    @classmethod
    def from_json(cls, data: dict[str, Any]) -> "ReceiverStats":
        st = cls()
        st.received = MessageCounts.from_json(data.get("received", {}))
        st.duplicates = int(data.get("duplicates", 0))
        st.pose_seq_gaps = int(data.get("pose_seq_gaps", 0))
        rej = data.get("rejected", {})
        st.rejected_by_reason = {str(k): int(v) for k, v in rej.get("by_reason", {}).items()}
        st.rejected_by_channel.update({k: int(v) for k, v in rej.get("by_channel", {}).items()
                                       if k in st.rejected_by_channel})
        st.link = LinkCounters.from_json(data.get("link", {}))
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
