"""Response models of the REST inspection API (they document the OpenAPI spec at /docs)."""

from __future__ import annotations

from enum import StrEnum
from typing import Any

from pydantic import BaseModel, Field


class Frame(StrEnum):
    local = "local"
    global_ = "global"


class TrajectoryFormat(StrEnum):
    tum = "tum"
    json = "json"


class PointsFormat(StrEnum):
    ply = "ply"
    json = "json"


class StoreStats(BaseModel):
    commits: int
    operations: int
    commit_seconds: float
    failed: bool


class Health(BaseModel):
    status: str = Field(
        description="'ok'; 'loading' while the stored maps load at start-up (agents are told to retry); "
        "'degraded' when the store failed to commit"
    )
    version: str
    uptime_s: float
    agents_connected: int
    maps: int
    store: StoreStats
    backend_idle: bool | None = Field(
        default=None,
        description="the collaboration back-end has no keyframe queued and no recognition or optimisation "
        "in flight (streaming agents wait for this before they stop); null when the back-end is off",
    )
    backend_queue: int = Field(default=0, description="keyframes waiting for place recognition")
    backend_arrived: int = Field(
        default=0, description="keyframes that have reached the back-end since the server started"
    )
    backend_done: int = Field(
        default=0,
        description="the back-end is through with the first this-many of them (looked up, and what they "
        "found merged or added): a finishing agent waits until this reaches the arrivals it saw, so it "
        "gets the corrections from everything the team had sent by then",
    )
    backend_optimising: bool = Field(
        default=False, description="an optimisation is running or asked for (corrections still to come)"
    )


class BandwidthInfo(BaseModel):
    up_total: float = Field(description="bytes received from the agent")
    up_avg: float = Field(description="bytes/s, average while active")
    up_peak: float = Field(description="bytes/s, largest 1 s window")
    down_total: float
    down_avg: float
    down_peak: float


class SessionInfo(BaseModel):
    session: int = Field(description="server session: the n of the agent map's id 'agent#n'")
    mission: str = Field(description="the mission (agent outbox UUID) it came from")
    client_session: int = Field(description="the session number the agent gave it within its mission")
    map_id: int | None = Field(description="stack map holding it")
    keyframes: int
    points: int


class MissionInfo(BaseModel):
    mission: str
    last_seq: int = Field(description="highest seq of this mission durably stored")


class PoseUncertainty(BaseModel):
    """The marginal covariance of one keyframe pose from the server's pose graph, in the map frame
    (``hivemap.server.marginals``; ``convention`` says how the 6x6 is parameterised)."""

    agent_id: str = Field(description="the keyframe's agent session (folded id: agent, or agent#session)")
    kf_id: int
    map_id: int
    position: list[float] = Field(description="the camera centre now, map frame (m)")
    position_cov: list[list[float]] = Field(description="3x3 covariance of the camera centre, map frame, m^2")
    pose_cov: list[list[float]] = Field(description="6x6 covariance of [dtheta (rad), dp (m)], map frame")
    velocity_cov: list[list[float]] | None = Field(
        default=None,
        description="3x3 covariance of the velocity differenced from this keyframe and the agent's newest "
        "one at least [backend.uncertainty] velocity_baseline_s older (their joint marginal), map frame, "
        "(m/s)^2; agent rows only, null with one keyframe",
    )
    computed_at: float = Field(description="unix time of the solve")
    convention: str


class AgentInfo(BaseModel):
    agent_id: str
    kind: str | None
    state: str = Field(description="connected | disconnected | never_connected")
    session: int
    map_id: int | None = Field(description="stack map holding the agent's current session")
    keyframes: int = Field(description="keyframes inserted (all sessions)")
    pending_keyframes: int = Field(description="keyframes waiting for their map points")
    points: int = Field(description="map points received (all sessions)")
    last_seq: int = Field(description="highest seq durably stored")
    connected_since: float | None
    last_seen: float | None = Field(description="unix time of the last message")
    messages: dict[str, int]
    duplicates: int
    errors: int
    bandwidth: BandwidthInfo
    mission: str | None = Field(default=None, description="mission of the agent's latest hello")
    missions: list[MissionInfo] = Field(default_factory=list)
    sessions: list[SessionInfo] = Field(default_factory=list, description="every agent map, all missions")
    uncertainty: PoseUncertainty | None = Field(
        default=None, description="covariance of the current session's latest keyframe (back-end on)"
    )


class AgentList(BaseModel):
    agents: list[AgentInfo]


class Pose(BaseModel):
    kf_id: int
    timestamp: float
    position: list[float] = Field(description="camera centre x, y, z (metres)")
    quat_wxyz: list[float] = Field(description="orientation world_from_cam as (w, x, y, z)")


class Trajectory(BaseModel):
    agent_id: str
    session: int
    map_id: int | None
    frame: Frame
    poses: list[Pose]


class MapSummary(BaseModel):
    id: int
    agents: list[str]
    keyframes: int
    points: int
    merges: int


class MapList(BaseModel):
    maps: list[MapSummary]


class MapDetail(MapSummary):
    keyframes_per_agent: dict[str, int]
    points_per_agent: dict[str, int]
    merge_history: list[dict[str, Any]]
    selfcheck: dict[str, Any] | None = Field(
        default=None,
        description="The back-end's last self-check of the map (agent pairs' consistency at their merges "
        "and loops, GNSS residuals per agent, alarms); None before its first optimisation.",
    )


class KeyframeInfo(BaseModel):
    agent_id: str
    id: int
    timestamp: float
    world_from_cam: list[list[float]]
    keypoints: int
    points: int = Field(description="keypoints linked to a map point")


class KeyframeList(BaseModel):
    map_id: int
    total: int
    offset: int
    keyframes: list[KeyframeInfo]


class MapUncertainty(BaseModel):
    """Every keyframe's marginal covariance of a map (``/maps/{id}/uncertainty``), paged like
    ``/maps/{id}/keyframes``; ``computed_at`` None (and no keyframes) until the first solve."""

    map_id: int
    computed_at: float | None
    cpu_s: float | None = Field(description="CPU time of that solve (s)")
    total: int
    offset: int
    convention: str
    keyframes: list[PoseUncertainty]


class EventInfo(BaseModel):
    id: int
    time: float
    kind: str
    message: str
    agent_id: str | None = None
    map_id: int | None = None
    data: dict[str, Any] = Field(default_factory=dict)


class EventList(BaseModel):
    last_id: int
    events: list[EventInfo]


class ErrorBody(BaseModel):
    detail: str


class StackDigest(BaseModel):
    digests: dict[int, str] = Field(description="map id -> SHA-256 of the map's whole content")


class MapEdges(BaseModel):
    """Loop edges of a map (within and across agents) as keyframe pairs with their camera centres."""

    map_id: int
    loops: list[tuple[str, int, str, int]] = Field(description="(agent, kf id, agent, kf id) per edge")
    segments: list[list[list[float]]] = Field(description="[[x, y, z], [x, y, z]] per edge, map frame")


class AgentGroundTruth(BaseModel):
    """One agent's ground truth in its map's frame (see ``hivemap.server.groundtruth``)."""

    agent_id: str
    matched: int = Field(description="keyframes paired with a ground-truth time (used by the alignment)")
    rmse_m: float | None = Field(description="keyframe camera centres against the aligned ground truth")
    positions: list[list[float]] = Field(description="[x, y, z] camera positions, map frame, in time order")


class MapGroundTruth(BaseModel):
    """Ground truth of a map's agents, aligned to the map by one rigid transform."""

    map_id: int
    configured: bool = Field(description="the server was given a ground-truth folder (groundtruth)")
    aligned: bool = Field(description="an alignment was possible (>= 3 keyframes with ground truth)")
    agents: list[AgentGroundTruth]


# Team services (hivemap.server.team): frontier goals, their auction, ORCA advisories.


class FrontierInfo(BaseModel):
    id: int = Field(description="frontier id within this computation of the map's frontiers")
    goal: list[float] = Field(
        description="x, y on the explored region's boundary; z the median of its points"
    )
    points: int = Field(description="down-sampled frontier points in the cluster")
    reachable: list[str] = Field(
        description="agent kinds that can reach it (ugv: near the ground, uav: in band)"
    )
    goals: dict[str, list[float]] = Field(description="kind -> goal [x, y, z] at that kind's height")


class FrontierList(BaseModel):
    map_id: int
    computed_at: float = Field(description="unix time of the computation (recomputed at a bounded rate)")
    voxel_m: float
    ground: list[float] = Field(description="ground plane z = a x + b y + c as [a, b, c], map frame")
    known_cells: int = Field(description="explored ground cells")
    frontier_points: int
    frontiers: list[FrontierInfo]


class Advisory(BaseModel):
    desired_velocity: list[float] = Field(
        description="the agent's intent when it sent one, else what it flies now (moving), else towards the "
        "first goal at cruise speed"
    )
    safe_velocity: list[float] = Field(description="ORCA: collision-free over the time horizon (horizontal)")
    radius_m: float
    inflated_radius_m: float = Field(
        description="radius + k_sigma * (sigma_pos + t_v * sigma_vel); sigma_pos: the largest of the agent's "
        "shares of its relative sigmas to the map's other agents, each pair's split in proportion to the two "
        "agents' own sigmas (an unknown pair, or none: the agent's own)"
    )
    half_height_m: float = Field(
        description="half height of the agent's cylinder: its own ([team.orca] half_height_uav_m / _ugv_m) "
        "+ k_sigma * its largest share of its relative vertical sigmas; agents whose heights differ by more "
        "than their two half heights are not neighbours"
    )
    intent: list[float] | None = Field(
        default=None,
        description="the velocity the agent said it will fly (its latest keyframe's intent_velocity, map "
        "frame), ORCA's preferred velocity for it; null: it did not say",
    )
    neighbours: list[str]
    covariance: str = Field(description="'graph' (the server's marginals) or 'default' (configured sigmas)")
    relative_position_cov: dict[str, list[list[float]] | None] = Field(
        default_factory=dict,
        description="per other agent of the map: 3x3 covariance of this agent's position minus that one's "
        "(their joint marginal), map frame, m^2; null: not solved yet",
    )


class AgentAssignment(BaseModel):
    agent_id: str
    kind: str
    position: list[float] = Field(description="latest keyframe camera centre, map frame")
    velocity: list[float] = Field(
        description="from the latest keyframe and the newest one at least velocity_baseline_s older, m/s"
    )
    goals: list[int] = Field(description="frontier ids in visiting order")
    goal_positions: list[list[float]]
    path_cost_m: float = Field(description="straight-line length of the tour")
    advisory: Advisory


class AuctionRound(BaseModel):
    round: int
    agent_id: str
    frontier_id: int
    bid_m: float = Field(description="the winning bid: added path cost less the uncertainty value")
    added_cost_m: float


class MapAssignments(BaseModel):
    map_id: int
    frontiers: int
    agents: list[AgentAssignment]
    rounds: list[AuctionRound]
    unassigned: list[int] = Field(description="frontier ids no agent took (cap or reachability)")


class TeamAssignments(BaseModel):
    computed_at: float
    maps: list[MapAssignments] = Field(description="one per map with a connected agent")
