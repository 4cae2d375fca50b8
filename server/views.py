"""Read-only views of the server state for the REST routes (plain functions, no FastAPI here)."""

from __future__ import annotations

import json
import math
import time
from collections.abc import Iterator
from typing import Any

import numpy as np

from hivemap import __version__
from hivemap.maps.geometry import quat_wxyz_from_rotmat
from hivemap.server import schemas
from hivemap.server.core import AgentMap, AgentState, HiveServer
from hivemap.server.views_uncertainty import agent_uncertainty


class NotFound(LookupError):
    """An unknown id; the routes turn it into a 404 with this message."""


def health(server: HiveServer) -> schemas.Health:
    w = server.writer
    backend = getattr(server, "backend", None)  # set by hivemap.server.backend.install when it is on
    return schemas.Health(
        status="degraded" if w.failed else "loading" if server.loading else "ok",
        version=__version__,
        uptime_s=time.time() - server.started_at,
        agents_connected=sum(a.connection is not None for a in server.agents.values()),
        maps=len(server.stack.maps),
        store=schemas.StoreStats(
            commits=w.commits, operations=w.ops, commit_seconds=w.commit_seconds, failed=w.failed
        ),
        backend_idle=None if backend is None else backend.idle(),
        backend_queue=0 if backend is None else len(backend.queue),
        backend_arrived=0 if backend is None else backend.queue.n_arrived,
        backend_done=0 if backend is None else backend.queue.done_through(),
        backend_optimising=False if backend is None else backend.optimising(),
    )


def _current_map(server: HiveServer, agent: AgentState) -> AgentMap | None:
    return agent.maps.get(agent.session)


def agent_info(server: HiveServer, agent: AgentState) -> schemas.AgentInfo:
    am = _current_map(server, agent)
    m = server.stack.map_of_agent(am.folded) if am is not None else None
    never = agent.connected_since is None and agent.last_seq == 0 and agent.connection is None
    return schemas.AgentInfo(
        agent_id=agent.agent_id,
        kind=agent.kind if agent.camera else None,
        state="never_connected" if never else agent.state,
        session=agent.session,
        map_id=m.id if m is not None else None,
        keyframes=sum(len(a.arrived_kfs) for a in agent.maps.values()),
        pending_keyframes=server.pending_count(agent),
        points=sum(len(a.arrived_points) for a in agent.maps.values()),
        last_seq=agent.last_seq,
        connected_since=agent.connected_since,
        last_seen=agent.last_seen,
        messages=dict(agent.received),
        duplicates=agent.duplicates,
        errors=agent.errors,
        bandwidth=schemas.BandwidthInfo(**agent.bandwidth.summary()),
        mission=agent.mission,
        missions=[
            schemas.MissionInfo(mission=ms.mission, last_seq=ms.last_seq) for ms in agent.missions.values()
        ],
        sessions=[_session_info(server, a) for _, a in sorted(agent.maps.items())],
        uncertainty=agent_uncertainty(server, am.folded) if am is not None else None,
    )


def _session_info(server: HiveServer, am: AgentMap) -> schemas.SessionInfo:
    m = server.stack.map_of_agent(am.folded)
    return schemas.SessionInfo(
        session=am.session,
        mission=am.mission,
        client_session=am.client_session,
        map_id=m.id if m is not None else None,
        keyframes=len(am.arrived_kfs),
        points=len(am.arrived_points),
    )


def stack_digest(server: HiveServer) -> schemas.StackDigest:
    from hivemap.maps.digest import stack_digest as digest

    return schemas.StackDigest(digests=digest(server.stack))


def agents(server: HiveServer) -> schemas.AgentList:
    out = [agent_info(server, a) for a in server.agents.values()]
    for agent_id in server.settings.tokens:
        if agent_id not in server.agents:
            out.append(agent_info(server, AgentState(agent_id=agent_id)))
    out.sort(key=lambda a: a.agent_id)
    return schemas.AgentList(agents=out)


def get_agent(server: HiveServer, agent_id: str) -> AgentState:
    agent = server.agents.get(agent_id)
    if agent is None:
        raise NotFound(f"unknown agent '{agent_id}'")
    return agent


def trajectory_poses(
    server: HiveServer, agent_id: str, frame: schemas.Frame, session: int | None
) -> tuple[AgentMap, int | None, list[tuple[int, float, np.ndarray]]]:
    """(agent map, stack map id, [(kf id, timestamp, world_from_cam 4x4)] sorted by time)."""
    agent = get_agent(server, agent_id)
    s = agent.session if session is None else session
    am = agent.maps.get(s)
    if am is None:
        raise NotFound(f"agent '{agent_id}' has no session {s}")
    m = server.stack.map_of_agent(am.folded)
    if m is None:
        return am, None, []
    local_from_global = am.global_from_vio.inverse()
    poses = []
    for kf in m.keyframes.values():
        if kf.agent_id != am.folded:
            continue
        T = np.asarray(kf.world_from_cam, dtype=np.float64)
        if frame == schemas.Frame.local:
            T = local_from_global.transform_pose(T)
        poses.append((int(kf.id), float(kf.timestamp), T))
    poses.sort(key=lambda p: (p[1], p[0]))
    return am, m.id, poses


def trajectory_json(
    server: HiveServer, agent_id: str, frame: schemas.Frame, session: int | None
) -> schemas.Trajectory:
    am, map_id, poses = trajectory_poses(server, agent_id, frame, session)
    return schemas.Trajectory(
        agent_id=agent_id,
        session=am.session,
        map_id=map_id,
        frame=frame,
        poses=[
            schemas.Pose(
                kf_id=k,
                timestamp=t,
                position=T[:3, 3].tolist(),
                quat_wxyz=quat_wxyz_from_rotmat(T[:3, :3]).tolist(),
            )
            for k, t, T in poses
        ],
    )


def trajectory_tum(server: HiveServer, agent_id: str, frame: schemas.Frame, session: int | None) -> str:
    """TUM text: ``timestamp tx ty tz qx qy qz qw`` (TUM's x, y, z, w order), one line per keyframe."""
    _, _, poses = trajectory_poses(server, agent_id, frame, session)
    lines = []
    for _, t, T in poses:
        w, x, y, z = quat_wxyz_from_rotmat(T[:3, :3])
        tx, ty, tz = T[:3, 3]
        lines.append(f"{t:.9f} {tx:.9f} {ty:.9f} {tz:.9f} {x:.9f} {y:.9f} {z:.9f} {w:.9f}")
    return "\n".join(lines) + ("\n" if lines else "")


def get_map(server: HiveServer, map_id: int) -> Any:
    m = server.stack.maps.get(map_id)
    if m is None:
        raise NotFound(f"unknown map {map_id}")
    return m


def map_summary(m: Any) -> schemas.MapSummary:
    return schemas.MapSummary(
        id=m.id,
        agents=sorted(m.agents),
        keyframes=len(m.keyframes),
        points=len(m.points),
        merges=len(m.merge_history),
    )


def maps(server: HiveServer) -> schemas.MapList:
    return schemas.MapList(maps=[map_summary(m) for _, m in sorted(server.stack.maps.items())])


def _jsonable(value: Any) -> Any:
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_jsonable(v) for v in value]
    if isinstance(value, np.ndarray):
        return _jsonable(value.tolist())
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if value is None or isinstance(value, str | int | float | bool):
        return value
    return str(value)


def map_detail(server: HiveServer, map_id: int) -> schemas.MapDetail:
    m = get_map(server, map_id)
    kfs: dict[str, int] = {}
    for kf in m.keyframes.values():
        kfs[kf.agent_id] = kfs.get(kf.agent_id, 0) + 1
    pts: dict[str, int] = {}
    for p in m.points.values():
        pts[p.agent_id] = pts.get(p.agent_id, 0) + 1
    return schemas.MapDetail(
        **map_summary(m).model_dump(),
        keyframes_per_agent=kfs,
        points_per_agent=pts,
        merge_history=[_jsonable(h) for h in m.merge_history],
        selfcheck=_jsonable(getattr(getattr(server, "backend", None), "selfcheck", {}).get(map_id)),
    )


def keyframes(server: HiveServer, map_id: int, offset: int, limit: int) -> schemas.KeyframeList:
    m = get_map(server, map_id)
    ordered = sorted(m.keyframes.values(), key=lambda kf: (kf.agent_id, kf.id))
    page = ordered[offset : offset + limit]
    return schemas.KeyframeList(
        map_id=map_id,
        total=len(ordered),
        offset=offset,
        keyframes=[
            schemas.KeyframeInfo(
                agent_id=kf.agent_id,
                id=int(kf.id),
                timestamp=float(kf.timestamp),
                world_from_cam=np.asarray(kf.world_from_cam, dtype=np.float64).tolist(),
                keypoints=len(kf.keypoints),
                points=sum(k is not None for k in kf.point_keys),
            )
            for kf in page
        ],
    )


PLY_DTYPE = np.dtype([("x", "<f8"), ("y", "<f8"), ("z", "<f8"), ("observations", "<u4")])
CHUNK_POINTS = 20000


def _point_snapshot(
    server: HiveServer, map_id: int, max_points: int | None = None
) -> tuple[list[Any], np.ndarray]:
    """The map's points (copied list, so ingest may go on while we stream) and their xyz (N, 3); with
    ``max_points`` an even subsample of at most that many (a viewer's first, coarse level of detail)."""
    m = get_map(server, map_id)
    pts = sorted(m.points.values(), key=lambda p: (p.agent_id, p.id))
    if max_points is not None and len(pts) > max_points:
        pts = pts[:: -(-len(pts) // max_points)]
    xyz = np.array([p.xyz for p in pts], dtype=np.float64).reshape(-1, 3)
    return pts, xyz


def points_ply(server: HiveServer, map_id: int, max_points: int | None = None) -> Iterator[bytes]:
    """Binary little-endian PLY: ``double x, y, z`` and ``uint observations`` per vertex."""
    pts, xyz = _point_snapshot(server, map_id, max_points)

    def gen() -> Iterator[bytes]:
        header = (
            "ply\nformat binary_little_endian 1.0\n"
            f"comment hivemap map {map_id}\n"
            f"element vertex {len(pts)}\n"
            "property double x\nproperty double y\nproperty double z\n"
            "property uint observations\nend_header\n"
        )
        yield header.encode("ascii")
        for start in range(0, len(pts), CHUNK_POINTS):
            chunk = pts[start : start + CHUNK_POINTS]
            rec = np.empty(len(chunk), dtype=PLY_DTYPE)
            rec["x"], rec["y"], rec["z"] = xyz[start : start + len(chunk)].T
            rec["observations"] = [len(p.observations) for p in chunk]
            yield rec.tobytes()

    return gen()


def points_json(server: HiveServer, map_id: int) -> Iterator[bytes]:
    """``{"map_id", "count", "points": [{"agent_id", "id", "xyz", "observations"}, ...]}``, streamed."""
    pts, xyz = _point_snapshot(server, map_id)

    def gen() -> Iterator[bytes]:
        yield f'{{"map_id": {map_id}, "count": {len(pts)}, "points": ['.encode()
        for start in range(0, len(pts), CHUNK_POINTS):
            rows = [
                json.dumps(
                    {
                        "agent_id": p.agent_id,
                        "id": int(p.id),
                        "xyz": xyz[start + i].tolist(),
                        "observations": len(p.observations),
                    }
                )
                for i, p in enumerate(pts[start : start + CHUNK_POINTS])
            ]
            yield (("," if start else "") + ",".join(rows)).encode()
        yield b"]}"

    return gen()


def map_edges(server: HiveServer, map_id: int) -> schemas.MapEdges:
    m = get_map(server, map_id)
    loops, segs = [], []
    for a, b in m.loop_edges():
        ka, kb = m.keyframes.get(a), m.keyframes.get(b)
        if ka is None or kb is None:
            continue
        loops.append((str(a[0]), int(a[1]), str(b[0]), int(b[1])))
        segs.append(
            [np.asarray(ka.world_from_cam)[:3, 3].tolist(), np.asarray(kb.world_from_cam)[:3, 3].tolist()]
        )
    return schemas.MapEdges(map_id=map_id, loops=loops, segments=segs)


def _groundtruth_source(server: HiveServer) -> Any:
    from hivemap.server.groundtruth import source_of

    src = getattr(server, "_groundtruth_source", None)
    if src is None and server.settings.groundtruth is not None:
        src = source_of(server.settings)
        server._groundtruth_source = src  # type: ignore[attr-defined]
    return src


def map_groundtruth(server: HiveServer, map_id: int) -> schemas.MapGroundTruth:
    from hivemap.server.groundtruth import aligned_groundtruth

    m = get_map(server, map_id)
    src = _groundtruth_source(server)
    if src is None:
        return schemas.MapGroundTruth(map_id=map_id, configured=False, aligned=False, agents=[])
    kfs: dict[str, list[tuple[float, np.ndarray]]] = {}
    for kf in m.keyframes.values():
        kfs.setdefault(kf.agent_id, []).append(
            (float(kf.timestamp), np.asarray(kf.world_from_cam, dtype=np.float64)[:3, 3])
        )
    tracks, aligned = aligned_groundtruth(src, kfs)
    return schemas.MapGroundTruth(
        map_id=map_id,
        configured=True,
        aligned=aligned,
        agents=[
            schemas.AgentGroundTruth(
                agent_id=t.agent_id,
                matched=t.matched,
                rmse_m=t.rmse_m if math.isfinite(t.rmse_m) else None,
                positions=t.xyz.tolist(),
            )
            for t in sorted(tracks, key=lambda t: t.agent_id)
        ],
    )


async def points_part_ply(server: HiveServer, map_id: int, part: int, parts: int) -> Iterator[bytes]:
    """Part ``part`` of ``parts`` of the map's points (``hivemap.server.lod``) as PLY with float x, y, z."""
    from hivemap.server import lod

    m = get_map(server, map_id)
    cache = getattr(server, "_lod_clouds", None)
    if cache is None:
        cache = server._lod_clouds = {}  # type: ignore[attr-defined]
    c = await lod.cloud(m, cache, set(server.stack.maps))
    return lod.ply_float(await lod.part(c, part, parts), f"hivemap map {map_id} part {part} of {parts}")


def events(server: HiveServer, since: int, kind: str | None, limit: int) -> schemas.EventList:
    evs = server.events.since(since, kind, limit)
    return schemas.EventList(
        last_id=server.events.last_id,
        events=[
            schemas.EventInfo(
                id=e.id,
                time=e.time,
                kind=e.kind,
                message=e.message,
                agent_id=e.agent_id,
                map_id=e.map_id,
                data=_jsonable(e.data),
            )
            for e in evs
        ],
    )


def _rendezvous_row(server: HiveServer, obs: Any) -> dict[str, Any]:
    from hivemap.server.backend.rendezvous import edge_from, residual

    rec = obs.record()
    row = {k: rec[k] for k in ("id", "observer", "observed_agent", "timestamp", "marker_ids", "ref_kf_id",
                               "reproj_rms_px", "state", "reason", "chi2", "map_id")}  # fmt: skip
    res = residual(server, obs)
    row["residual_m"], row["residual_deg"] = (None, None) if res is None else res
    # the positions are in the frame of map ``position_map`` (the observer's)
    row["candidate"] = row["query"] = row["observer_position"] = row["observed_position"] = None
    row["position_map"] = None
    if obs.edge is not None:
        e = edge_from(obs.edge)
        row["candidate"], row["query"] = list(e.candidate), list(e.query)
        m = server.stack.map_of_agent(e.candidate[0])
        if m is not None and e.candidate in m.keyframes:
            W = m.keyframes[e.candidate].world_from_cam @ obs.ref_from_cam
            row["observer_position"] = W[:3, 3].tolist()
            row["observed_position"] = (W @ obs.cam_from_observed)[:3, 3].tolist()  # as the marker says
            row["position_map"] = m.id
    return row


def map_rendezvous(server: HiveServer, map_id: int) -> dict[str, Any]:
    m = get_map(server, map_id)
    agents = {a.partition("#")[0] for a in m.agents}
    rows = [_rendezvous_row(server, obs) for _, obs in sorted(getattr(server, "rendezvous", {}).items())
            if obs.observer in m.agents or obs.observed_agent in agents]  # fmt: skip
    return {"map_id": map_id, "rendezvous": rows}


def rendezvous_list(server: HiveServer, state: str | None) -> dict[str, Any]:
    rows = [_rendezvous_row(server, obs) for _, obs in sorted(getattr(server, "rendezvous", {}).items())
            if state is None or obs.state == state]  # fmt: skip
    return {"rendezvous": rows}
