"""The ingest core's bookkeeping of agents: missions, sessions (agent maps), pending keyframes, and the
connection and refusal types the WebSocket handler shares with it."""

from __future__ import annotations

from collections import Counter, deque
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from hivemap.maps.camera import PinholeCamera
from hivemap.maps.geometry import Sim3
from hivemap.protocol import Correction, Keyframe, Message
from hivemap.server.bandwidth import Bandwidth


class Rejected(Exception):
    """A message that is refused as a whole (nothing applied); becomes an ``error`` reply."""

    def __init__(self, code: str, message: str, field: str | None = None) -> None:
        super().__init__(message)
        self.code = code
        self.message = message
        self.field = field


class Connection(Protocol):
    """What the core needs from a WebSocket connection (implemented in :mod:`hivemap.server.ws`)."""

    agent_id: str | None
    mission: str | None
    replaced: bool

    def send(self, msg: Message) -> bool: ...

    async def close(self, code: int, reason: str) -> None: ...


@dataclass
class PendingKeyframe:
    msg: Keyframe
    missing: set[int]


@dataclass
class AgentMap:
    """One (agent, mission, session): the ingest bookkeeping of one agent map (the data lives in the
    MapStack). ``session`` is the server's number of it among all the agent's maps (the ``#n`` of its
    folded id); ``mission`` and ``client_session`` are what the agent calls it."""

    agent_id: str
    session: int
    folded: str
    camera: PinholeCamera
    mission: str = ""
    client_session: int = 0
    global_from_vio: Sim3 = field(default_factory=Sim3.identity)
    arrived_points: set[int] = field(default_factory=set)
    arrived_kfs: set[int] = field(default_factory=set)
    pending: dict[int, PendingKeyframe] = field(default_factory=dict)
    waiting: dict[int, set[int]] = field(default_factory=dict)
    # the first keyframe's guess of this session's VIO frame in the previous session's (kf id,
    # prev_from_this 4x4, sigmas [m, deg]) until the back-end has used it (memory only)
    session_guess: tuple[int, NDArray[np.float64], NDArray[np.float64]] | None = None
    # the latest keyframe's intended velocity (kf id, f64 (3,) in its cam0 frame; protocol v7), for the team
    # services' collision advisories (memory only: advisory, not map data)
    intent: tuple[int, NDArray[np.float64]] | None = None

    def row(self) -> tuple[str, str, int, NDArray[np.float64], str, int]:
        """What the store keeps of it (``ServerStore.put_agent_map``), copied on the loop."""
        return (self.folded, self.agent_id, self.session, self.global_from_vio.matrix(), self.mission,
                self.client_session)  # fmt: skip


@dataclass
class MissionState:
    """One mission of an agent (one run of its outbox): its seqs count from 1 within it."""

    mission: str
    last_seq: int = 0  # durably stored
    applied_seq: int = 0  # applied in memory (>= last_seq)
    undelivered: deque[Correction] = field(default_factory=lambda: deque(maxlen=16))


@dataclass
class AgentState:
    agent_id: str
    kind: str = "uav"
    camera: dict[str, Any] = field(default_factory=dict)
    session: int = 0  # the newest server session (see AgentMap)
    maps: dict[int, AgentMap] = field(default_factory=dict)  # by server session
    missions: dict[str, MissionState] = field(default_factory=dict)
    mission: str | None = None  # the mission of the latest hello
    connection: Connection | None = None
    connected_since: float | None = None
    last_seen: float | None = None
    bandwidth: Bandwidth = field(default_factory=Bandwidth)
    received: Counter[str] = field(default_factory=Counter)
    duplicates: int = 0
    errors: int = 0
    cam_from_antenna: NDArray[np.float64] | None = None  # GNSS lever arm from the hello (not persisted)
    stereo_baseline: float | None = None  # m, from the hello (not persisted: every connection sends it)
    team_advisories: bool = False  # the hello asked for team advisories (protocol v4; not persisted)

    @property
    def state(self) -> str:
        return "connected" if self.connection is not None else "disconnected"

    def record(self) -> dict[str, Any]:
        """What the store keeps of the agent (``ServerStore.put_agent``)."""
        return {"agent_id": self.agent_id, "kind": self.kind, "camera": self.camera, "session": self.session,
                "mission": self.mission}  # fmt: skip

    @property
    def last_seq(self) -> int:
        """The last stored seq of the latest mission."""
        ms = self.missions.get(self.mission) if self.mission is not None else None
        return ms.last_seq if ms is not None else 0

    def session_of(self, mission: str, client_session: int) -> AgentMap | None:
        for am in self.maps.values():
            if am.mission == mission and am.client_session == client_session:
                return am
        return None
