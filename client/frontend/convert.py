"""Front-end events -> ``hivemap.maps`` model objects (VIO frame).

A session > 0 is folded into the agent id as ``"<agent>#<session>"`` (the server's convention for a
map reset, CONTRACTS.md).
"""

from __future__ import annotations

from hivemap.client.frontend.tracker import Frontend, KeyframeEvent
from hivemap.maps import Keyframe, Map, MapPoint
from hivemap.maps.camera import PinholeCamera


def session_agent_id(agent_id: str, session: int) -> str:
    return agent_id if session == 0 else f"{agent_id}#{session}"


def keyframe_from_event(ev: KeyframeEvent, agent_id: str, camera: PinholeCamera) -> Keyframe:
    """A maps ``Keyframe`` (its point references are the event's point ids, same agent/session)."""
    return Keyframe(
        session_agent_id(agent_id, ev.session),
        ev.kf_id,
        ev.timestamp,
        ev.world_from_cam,
        camera,
        ev.keypoints,
        ev.octaves,
        ev.descriptors,
        ev.point_ids,
    )


def points_from_event(ev: KeyframeEvent, agent_id: str) -> list[MapPoint]:
    aid = session_agent_id(agent_id, ev.session)
    return [
        MapPoint(aid, int(i), x, d)
        for i, x, d in zip(ev.new_point_ids, ev.new_point_xyz, ev.new_point_descriptors, strict=True)
    ]


def map_from_frontend(frontend: Frontend, agent_id: str, map_id: int = 0) -> Map:
    """Snapshot of the current session (all keyframes and alive points) as a maps ``Map``."""
    m = Map(map_id)
    aid = session_agent_id(agent_id, frontend.session)
    pts = frontend.points
    for pid in pts.alive_ids():
        m.add_point(MapPoint(aid, int(pid), pts.xyz[pid], pts.desc[pid]))
    for kid in sorted(frontend.keyframes):
        kf = frontend.keyframes[kid]
        f = kf.frame
        pids = f.point_ids.copy()
        ok = pids >= 0
        ok[ok] = pts.alive[pids[ok]]
        pids[~ok] = -1
        m.add_keyframe(Keyframe(aid, kid, kf.timestamp, kf.T_wc, frontend.cam, f.uv, f.octaves, f.desc, pids))
    return m
