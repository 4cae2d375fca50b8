"""The live mission in Foxglove: the server's maps as Foxglove messages, on a Foxglove WebSocket
(``hivemap server --foxglove-port``) or in an MCAP file (``hivemap export mcap``, :mod:`.export`).

Topics (all ``foxglove.*`` protobuf schemas, built with the ``foxglove-sdk`` package):

* ``/tf`` ``FrameTransforms``: the frame tree. ``global`` is the frame of the primary map (the one with the
  UGV, else the most agents, else the lowest id); other maps are ``map<ID>`` under ``global`` with an
  identity transform (they are not aligned until they merge). Each agent session's ``<agent>/local``
  frame hangs under its map's frame by ``global_from_local`` (scale is dropped: Foxglove transforms are
  rigid; metric agents have scale 1). ``enu`` is the parent of a map once the GNSS stage has moved that
  map into ENU (then the transform is the identity).
* ``/scene`` ``SceneUpdate``: per agent its trajectory (line strip), keyframe frustums (line list) and
  current pose (arrow); per map its loop edges.
* ``/agents/<agent>/trajectory`` ``PosesInFrame`` and ``/agents/<agent>/pose`` ``PoseInFrame``: keyframe
  poses (``world_from_cam``) in the map frame, and the latest one.
* ``/maps/<ID>/points`` ``PointCloud``: map points (float32 x, y, z), evenly subsampled above
  ``max_points`` so that a large map stays viewable.
* ``/events`` ``Log``: merges, loops, corrections, GNSS stages, sessions, connections and errors.

The live publisher snapshots the server state on the event loop every ``interval_s`` (the only thread
that changes the maps, so a snapshot is consistent) and publishes what changed; a new subscriber gets
the current state at the next tick rather than waiting for the next change.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from hivemap.maps.geometry import quat_wxyz_from_rotmat

logger = logging.getLogger(__name__)

F64 = NDArray[np.float64]

# Event kinds logged on /events (candidates and acks are not: they would flood the log).
LOGGED_EVENTS = (
    "merge", "loop", "correction", "gnss_stage", "session", "connect", "disconnect", "error", "refused",
)  # fmt: skip
WARNING_EVENTS = ("error", "refused")

# 16 well-separated colours, picked by a hash of the agent id: stable across restarts and page loads, and
# the same as the web viewer's (viewer/src/main.js PALETTE and hashId).
PALETTE_HEX = (
    0x1F77B4, 0xFF7F0E, 0x2CA02C, 0xD62728, 0x9467BD, 0x8C564B, 0xE377C2, 0x7F7F7F,
    0xBCBD22, 0x17BECF, 0x66FFCC, 0x99CC33, 0xB266FF, 0xFFCC00, 0x4DA6FF, 0xCC6666,
)  # fmt: skip
PALETTE = tuple(((c >> 16) / 255.0, ((c >> 8) & 0xFF) / 255.0, (c & 0xFF) / 255.0) for c in PALETTE_HEX)


@dataclass(frozen=True)
class FoxgloveOptions:
    """The live Foxglove WebSocket."""

    host: str = "127.0.0.1"
    port: int = 8766
    interval_s: float = 1.0
    """How often the state is snapshotted and published."""
    max_points: int = 500_000
    """Map points published per map at most (evenly subsampled above)."""
    frustum_depth_m: float = 0.3
    """Depth of the drawn keyframe frustums."""
    event_backlog: int = 200
    """Events sent again when a viewer subscribes (so it sees the mission's recent history)."""


def agent_color(agent_id: str) -> tuple[float, float, float]:
    """The agent's colour (r, g, b in 0..1): a hash of its id (session suffix ``#n`` ignored)."""
    return PALETTE[hash_id(agent_id.split("#", 1)[0]) % len(PALETTE)]


def hash_id(agent_id: str) -> int:
    """FNV-1a (32 bit) of the id's UTF-8 bytes: the viewer's ``hashId``."""
    h = 0x811C9DC5
    for b in agent_id.encode():
        h = ((h ^ b) * 0x01000193) & 0xFFFFFFFF
    return h


# ---------------------------------------------------------------------------------------------
# Snapshot of the server state (plain data, built on the event loop)
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class AgentTrack:
    """One agent session's keyframes in its map's frame."""

    folded: str
    map_id: int
    times: F64  # (N,) seconds
    world_from_cam: F64  # (N, 4, 4)
    global_from_local: F64  # (4, 4) rigid part
    camera: Any  # PinholeCamera


@dataclass(frozen=True)
class MapSnapshot:
    map_id: int
    frame: str
    parent: str | None
    in_enu: bool
    points: NDArray[np.float32]  # (N, 3)
    n_points: int
    loop_segments: F64  # (M, 2, 3)
    version: tuple[int, int]  # (keyframes, points): cheap change detector


@dataclass(frozen=True)
class Snapshot:
    maps: list[MapSnapshot]
    tracks: list[AgentTrack]
    events: list[Any] = field(default_factory=list)  # hivemap.server.events.Event


def primary_map(server: Any) -> int | None:
    """The map that defines ``global``: the one with a UGV, else the most agents, else the lowest id."""
    kinds = {a.agent_id: a.kind for a in server.agents.values()}

    def has_ugv(m: Any) -> bool:
        return any(kinds.get(str(f).split("#", 1)[0]) == "ugv" for f in m.agents)

    ms = sorted(server.stack.maps.values(), key=lambda m: (not has_ugv(m), -len(m.agents), m.id))
    return ms[0].id if ms else None


def _maps_in_enu(server: Any) -> set[int]:
    """Maps the GNSS stage has moved into ENU (its accepted ``gnss_stage`` events)."""
    out: set[int] = set()
    for e in server.events.since(0, "gnss_stage"):
        if e.map_id is not None and not e.data.get("refused") and "enu_from_map" in e.data:
            out.add(int(e.map_id))
    return out


def snapshot(
    server: Any, options: FoxgloveOptions, map_ids: Iterable[int] | None = None, events_since: int = 0
) -> Snapshot:
    """Copy what the topics need out of the server (call on the event loop)."""
    wanted = set(server.stack.maps) if map_ids is None else set(map_ids)
    primary = primary_map(server) if map_ids is None else min(wanted, default=None)
    enu = _maps_in_enu(server)
    maps: list[MapSnapshot] = []
    for mid in sorted(wanted):
        m = server.stack.maps.get(mid)
        if m is None:
            continue
        frame = "global" if mid == primary else f"map{mid}"
        parent = "enu" if mid in enu else (None if mid == primary else "global")
        pts = np.array([p.xyz for p in m.points.values()], dtype=np.float32).reshape(-1, 3)
        n = len(pts)
        if n > options.max_points:
            pts = pts[:: int(np.ceil(n / options.max_points))]
        segs = [
            (m.keyframes[a].world_from_cam[:3, 3], m.keyframes[b].world_from_cam[:3, 3])
            for a, b in m.loop_edges()
            if a in m.keyframes and b in m.keyframes
        ]
        loops = np.asarray(segs, dtype=np.float64).reshape(-1, 2, 3)
        maps.append(MapSnapshot(mid, frame, parent, mid in enu, pts, n, loops, (len(m.keyframes), n)))
    map_ids_kept = {s.map_id for s in maps}
    tracks: list[AgentTrack] = []
    for agent in sorted(server.agents.values(), key=lambda a: a.agent_id):
        for am in agent.maps.values():
            m = server.stack.map_of_agent(am.folded)
            if m is None or m.id not in map_ids_kept:
                continue
            kfs = sorted(
                (kf for kf in m.keyframes.values() if kf.agent_id == am.folded), key=lambda k: k.timestamp
            )
            if not kfs:
                continue
            g = am.global_from_vio
            rigid = np.eye(4)
            rigid[:3, :3], rigid[:3, 3] = g.R, g.t
            tracks.append(
                AgentTrack(
                    am.folded, m.id,
                    np.array([kf.timestamp for kf in kfs], dtype=np.float64),
                    np.array([kf.world_from_cam for kf in kfs], dtype=np.float64).reshape(-1, 4, 4),
                    rigid, am.camera,
                )
            )  # fmt: skip
    evs = [e for e in server.events.since(events_since) if e.kind in LOGGED_EVENTS]
    return Snapshot(maps, tracks, evs[-options.event_backlog :] if events_since == 0 else evs)


# ---------------------------------------------------------------------------------------------
# Snapshot -> Foxglove messages
# ---------------------------------------------------------------------------------------------


def _ts(t_s: float) -> Any:
    from foxglove.messages import Timestamp

    sec = int(t_s)
    return Timestamp(sec, int(round((t_s - sec) * 1e9)) % 1_000_000_000)


def _vec_quat(T: F64) -> tuple[Any, Any]:
    """(Vector3 translation, Quaternion rotation) of a 4x4 pose (the messages are write-only)."""
    from foxglove.messages import Quaternion, Vector3

    w, x, y, z = quat_wxyz_from_rotmat(T[:3, :3])
    return (
        Vector3(x=float(T[0, 3]), y=float(T[1, 3]), z=float(T[2, 3])),
        Quaternion(x=float(x), y=float(y), z=float(z), w=float(w)),
    )


def _pose(T: F64) -> Any:
    from foxglove.messages import Pose

    position, orientation = _vec_quat(T)
    return Pose(position=position, orientation=orientation)


def _points(xyz: Iterable[Any]) -> list[Any]:
    from foxglove.messages import Point3

    return [Point3(x=float(p[0]), y=float(p[1]), z=float(p[2])) for p in xyz]


def frame_of(snap: Snapshot, map_id: int) -> str:
    for m in snap.maps:
        if m.map_id == map_id:
            return m.frame
    return f"map{map_id}"


def frame_transforms(snap: Snapshot, stamp: float) -> Any:
    from foxglove.messages import FrameTransform, FrameTransforms

    def tf(parent: str, child: str, T: F64) -> Any:
        translation, rotation = _vec_quat(T)
        return FrameTransform(
            timestamp=_ts(stamp), parent_frame_id=parent, child_frame_id=child,
            translation=translation, rotation=rotation,
        )  # fmt: skip

    out = [tf(m.parent, m.frame, np.eye(4)) for m in snap.maps if m.parent is not None]
    out += [tf(frame_of(snap, t.map_id), f"{t.folded}/local", t.global_from_local) for t in snap.tracks]
    return FrameTransforms(transforms=out)


def frustum_segments(T: F64, camera: Any, depth: float) -> F64:
    """(16, 3) endpoints of a camera pyramid's 8 edges in the world frame (``T`` = world_from_cam)."""
    w, h = float(camera.width), float(camera.height)
    corners = np.array(
        [[(u - camera.cx) / camera.fx * depth, (v - camera.cy) / camera.fy * depth, depth]
         for u, v in ((0, 0), (w, 0), (w, h), (0, h))]
    )  # fmt: skip
    c = (T[:3, :3] @ corners.T).T + T[:3, 3]
    o = T[:3, 3]
    segs = [(o, c[i]) for i in range(4)] + [(c[i], c[(i + 1) % 4]) for i in range(4)]
    return np.asarray(segs, dtype=np.float64).reshape(-1, 3)


def scene_update(snap: Snapshot, stamp: float, options: FoxgloveOptions) -> Any:
    from foxglove.messages import (
        ArrowPrimitive,
        Color,
        LinePrimitive,
        LinePrimitiveLineType,
        SceneEntity,
        SceneUpdate,
    )

    entities = []
    for t in snap.tracks:
        r, g, b = agent_color(t.folded)
        frame = frame_of(snap, t.map_id)
        fr = np.concatenate(
            [frustum_segments(T, t.camera, options.frustum_depth_m) for T in t.world_from_cam]
        )
        lines = [
            LinePrimitive(type=LinePrimitiveLineType.LineStrip, thickness=2.0, scale_invariant=True,
                          points=_points(t.world_from_cam[:, :3, 3]), color=Color(r=r, g=g, b=b, a=1.0)),
            LinePrimitive(type=LinePrimitiveLineType.LineList, thickness=1.0, scale_invariant=True,
                          points=_points(fr), color=Color(r=r, g=g, b=b, a=0.6)),
        ]  # fmt: skip
        # the arrow is along the camera's viewing direction (+z): rotate x onto z
        look = t.world_from_cam[-1].copy()
        look[:3, :3] = look[:3, :3] @ np.array([[0.0, 0.0, -1.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]])
        arrow = ArrowPrimitive(pose=_pose(look), shaft_length=0.3, shaft_diameter=0.04, head_length=0.1,
                               head_diameter=0.1, color=Color(r=r, g=g, b=b, a=1.0))  # fmt: skip
        entities.append(
            SceneEntity(
                timestamp=_ts(stamp), frame_id=frame, id=f"agent/{t.folded}", lines=lines, arrows=[arrow]
            )
        )
    for m in snap.maps:
        if len(m.loop_segments):
            line = LinePrimitive(type=LinePrimitiveLineType.LineList, thickness=3.0, scale_invariant=True,
                                 points=_points(m.loop_segments.reshape(-1, 3)),
                                 color=Color(r=1.0, g=0.0, b=1.0, a=1.0))  # fmt: skip
            entities.append(SceneEntity(timestamp=_ts(stamp), frame_id=m.frame, id=f"map{m.map_id}/loops",
                                        lines=[line]))  # fmt: skip
    return SceneUpdate(entities=entities)


def trajectory(t: AgentTrack, frame: str, stamp: float) -> Any:
    from foxglove.messages import PosesInFrame

    return PosesInFrame(timestamp=_ts(stamp), frame_id=frame, poses=[_pose(T) for T in t.world_from_cam])


def current_pose(t: AgentTrack, frame: str) -> Any:
    from foxglove.messages import PoseInFrame

    return PoseInFrame(timestamp=_ts(float(t.times[-1])), frame_id=frame, pose=_pose(t.world_from_cam[-1]))


def point_cloud(m: MapSnapshot, stamp: float) -> Any:
    from foxglove.messages import PackedElementField, PackedElementFieldNumericType, PointCloud

    f32 = PackedElementFieldNumericType.Float32
    fields = [PackedElementField(name=n, offset=4 * i, type=f32) for i, n in enumerate("xyz")]
    return PointCloud(
        timestamp=_ts(stamp), frame_id=m.frame, pose=_pose(np.eye(4)), point_stride=12, fields=fields,
        data=np.ascontiguousarray(m.points, dtype="<f4").tobytes(),
    )  # fmt: skip


def log_message(event: Any) -> Any:
    from foxglove.messages import Log, LogLevel

    level = LogLevel.Warning if event.kind in WARNING_EVENTS else LogLevel.Info
    who = "".join(
        f" [{x}]" for x in (event.agent_id, None if event.map_id is None else f"map {event.map_id}") if x
    )
    return Log(timestamp=_ts(event.time), level=level, message=f"{event.kind}{who}: {event.message}",
               name=f"hivemap.{event.kind}", file="", line=0)  # fmt: skip


def messages(snap: Snapshot, stamp: float, options: FoxgloveOptions) -> list[tuple[str, Any, float]]:
    """Every (topic, message, log time [s]) of a snapshot, in the order they are published."""
    out: list[tuple[str, Any, float]] = [("/tf", frame_transforms(snap, stamp), stamp)]
    out.append(("/scene", scene_update(snap, stamp, options), stamp))
    for t in snap.tracks:
        frame = frame_of(snap, t.map_id)
        out.append((f"/agents/{t.folded}/trajectory", trajectory(t, frame, stamp), stamp))
        out.append((f"/agents/{t.folded}/pose", current_pose(t, frame), stamp))
    for m in snap.maps:
        out.append((f"/maps/{m.map_id}/points", point_cloud(m, stamp), stamp))
    out += [("/events", log_message(e), float(e.time)) for e in snap.events]
    return out


# ---------------------------------------------------------------------------------------------
# Channels
# ---------------------------------------------------------------------------------------------


class Channels:
    """One Foxglove channel per topic in a ``foxglove.Context``, made on first use by message type."""

    def __init__(self, context: Any) -> None:
        self.context = context
        self._channels: dict[str, Any] = {}

    def log(self, topic: str, msg: Any, log_time_s: float) -> None:
        ch = self._channels.get(topic)
        if ch is None:
            from foxglove import channels

            cls = getattr(channels, f"{type(msg).__name__}Channel")
            ch = self._channels[topic] = cls(topic, context=self.context)
        ch.log(msg, log_time=int(log_time_s * 1e9))

    def close(self, keep: set[str] | None = None) -> None:
        """Close every channel, or those not in ``keep`` (an agent or map that went away)."""
        for topic in [t for t in self._channels if keep is None or t not in keep]:
            self._channels.pop(topic).close()


class LivePublisher:
    """Publishes the server's state on a Foxglove WebSocket (started and stopped with the server)."""

    def __init__(self, server: Any, options: FoxgloveOptions) -> None:
        self.server = server
        self.options = options
        self.ws: Any = None
        self.port: int | None = None
        self._task: asyncio.Task[None] | None = None
        self._channels: Channels | None = None
        self._last_event = 0
        self._published: dict[str, Any] = {}
        self._replay = False

    async def start(self, _server: Any = None) -> None:
        import foxglove

        ctx = foxglove.Context()
        self._channels = Channels(ctx)
        publisher = self

        class _Listener(foxglove.ServerListener):
            def on_subscribe(self, client: Any, channel: Any) -> None:
                # a new viewer gets the full state and the recent events at the next tick, not only what
                # changes later (the others get them again too: Foxglove channels have no latching)
                publisher._published.clear()
                publisher._replay = True

        self.ws = foxglove.start_server(
            name="hivemap", host=self.options.host, port=self.options.port, context=ctx,
            server_listener=_Listener(),
        )  # fmt: skip
        self.port = int(self.ws.port)
        logger.info("Foxglove WebSocket on ws://%s:%d", self.options.host, self.port)
        self._task = asyncio.create_task(self._run(), name="hivemap-foxglove")

    async def stop(self, _server: Any = None) -> None:
        if self._task is not None:
            self._task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._task
        if self._channels is not None:
            self._channels.close()
        if self.ws is not None:
            self.ws.stop()

    async def _run(self) -> None:
        while True:
            try:
                self.publish_once()
            except Exception:  # a bad snapshot must not end the live view
                logger.exception("Foxglove publish failed")
            await asyncio.sleep(self.options.interval_s)

    def publish_once(self) -> int:
        """Snapshot and publish what changed since the last call; returns the number of messages sent."""
        assert self._channels is not None
        since, self._replay = (0 if self._replay else self._last_event), False
        snap = snapshot(self.server, self.options, events_since=since)
        if snap.events:
            self._last_event = max(self._last_event, *(e.id for e in snap.events))
        now = time.time()
        versions: dict[str, Any] = {f"/maps/{m.map_id}/points": m.version for m in snap.maps}
        versions.update({f"/agents/{t.folded}/pose": len(t.times) for t in snap.tracks})
        sent = 0
        for topic, msg, t in messages(snap, now, self.options):
            # points and poses only when they changed (points are the bulk of the bytes); the rest (scene,
            # frame tree, trajectories that corrections may have moved) every tick
            key = versions.get(topic)
            if key is not None and self._published.get(topic) == key:
                continue
            self._channels.log(topic, msg, t)
            if key is not None:
                self._published[topic] = key
            sent += 1
        return sent


def installer(options: FoxgloveOptions) -> Any:
    """An ``extensions`` entry for ``create_app``: a :class:`LivePublisher` started after the store loads."""

    def install(server: Any) -> LivePublisher:
        pub = LivePublisher(server, options)
        server.foxglove = pub
        server.startup_hooks.append(pub.start)
        server.shutdown_hooks.append(pub.stop)
        return pub

    return install
