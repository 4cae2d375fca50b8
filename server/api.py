"""Thin REST routes over :mod:`hivemap.server.views`.

The routes are ``async`` on purpose: they then run on the event loop thread, the only thread that changes the
maps, so a view never sees a map half-way through an update (sync routes would run in a thread pool).
"""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import APIRouter, Depends, HTTPException, Path, Query, Request
from fastapi.responses import PlainTextResponse, RedirectResponse, StreamingResponse

from hivemap.server import schemas, views, views_metrics, views_uncertainty
from hivemap.server.core import HiveServer
from hivemap.server.metrics import CONTENT_TYPE


async def get_server(request: Request) -> HiveServer:
    server: HiveServer = request.app.state.hive
    return server


Server = Annotated[HiveServer, Depends(get_server)]
MapId = Annotated[int, Path(ge=0, le=2**62, description="map id (see /maps)")]
AgentId = Annotated[str, Path(min_length=1, max_length=64, description="agent id (see /agents)")]

NOT_FOUND: dict[int | str, dict[str, Any]] = {404: {"model": schemas.ErrorBody, "description": "unknown id"}}

router = APIRouter()


@router.get("/", include_in_schema=False)
async def root() -> RedirectResponse:
    return RedirectResponse("/viewer/")


@router.get("/health", response_model=schemas.Health, tags=["server"])
async def health(server: Server) -> schemas.Health:
    """Liveness and store status."""
    return views.health(server)


@router.get("/agents", response_model=schemas.AgentList, tags=["agents"])
async def agents(server: Server) -> schemas.AgentList:
    """Every agent configured or seen: state, last seen, keyframes, bandwidth (bytes/s), map id."""
    return views.agents(server)


@router.get("/agents/{agent_id}", response_model=schemas.AgentInfo, responses=NOT_FOUND, tags=["agents"])
async def agent(server: Server, agent_id: AgentId) -> schemas.AgentInfo:
    """One agent."""
    return views.agent_info(server, views.get_agent(server, agent_id))


@router.get(
    "/agents/{agent_id}/trajectory",
    response_model=schemas.Trajectory,
    responses={**NOT_FOUND, 200: {"content": {"text/plain": {}, "application/json": {}}}},
    tags=["agents"],
)
async def trajectory(
    server: Server,
    agent_id: AgentId,
    frame: Annotated[
        schemas.Frame, Query(description="local = the agent's own (VIO) frame, global = its map's frame")
    ] = schemas.Frame.global_,
    format: Annotated[
        schemas.TrajectoryFormat, Query(description="tum text or json")
    ] = schemas.TrajectoryFormat.json,
    session: Annotated[
        int | None, Query(ge=0, le=1_000_000, description="default: the current session")
    ] = None,
) -> schemas.Trajectory | PlainTextResponse:
    """Keyframe poses (world_from_cam) of an agent, ordered by time."""
    if format == schemas.TrajectoryFormat.tum:
        return PlainTextResponse(views.trajectory_tum(server, agent_id, frame, session))
    return views.trajectory_json(server, agent_id, frame, session)


@router.get("/maps", response_model=schemas.MapList, tags=["maps"])
async def maps(server: Server) -> schemas.MapList:
    """The map stack: one map per agent session until the back-end merges them."""
    return views.maps(server)


@router.get("/maps/digest", response_model=schemas.StackDigest, tags=["maps"])
async def maps_digest(server: Server) -> schemas.StackDigest:
    """A SHA-256 of every map's whole content (keyframes, points, graphs, history): equal digests before
    and after a restart mean the store gave back the same map stack. Reads every map: not for polling."""
    return views.stack_digest(server)


@router.get("/maps/{map_id}", response_model=schemas.MapDetail, responses=NOT_FOUND, tags=["maps"])
async def map_detail(server: Server, map_id: MapId) -> schemas.MapDetail:
    """Agents, keyframe and point counts, merge history of one map."""
    return views.map_detail(server, map_id)


@router.get("/maps/{map_id}/rendezvous", responses=NOT_FOUND, tags=["maps"])
async def map_rendezvous(server: Server, map_id: MapId) -> dict[str, Any]:
    """The rendezvous observations of the map's agents (either end): state (held, pending, judging, kept,
    rejected) and why, the edge's residual in the map now (m, deg), and both agents' poses at its
    keyframes (the viewer draws a line between them)."""
    return views.map_rendezvous(server, map_id)


@router.get("/rendezvous", tags=["server"])
async def rendezvous(
    server: Server, state: Annotated[str | None, Query(max_length=16, description="only this state")] = None
) -> dict[str, Any]:
    """Every rendezvous observation the server holds, with its state."""
    return views.rendezvous_list(server, state)


@router.get(
    "/maps/{map_id}/keyframes", response_model=schemas.KeyframeList, responses=NOT_FOUND, tags=["maps"]
)
async def map_keyframes(
    server: Server,
    map_id: MapId,
    offset: Annotated[int, Query(ge=0, le=10_000_000)] = 0,
    limit: Annotated[int, Query(ge=1, le=10_000)] = 1000,
) -> schemas.KeyframeList:
    """Keyframes of a map (pose, number of keypoints and linked points), ordered by (agent, id), paged."""
    return views.keyframes(server, map_id, offset, limit)


@router.get(
    "/maps/{map_id}/uncertainty",
    response_model=schemas.MapUncertainty,
    responses=NOT_FOUND,
    tags=["maps"],
)
async def map_uncertainty(
    server: Server,
    map_id: MapId,
    offset: Annotated[int, Query(ge=0, le=10_000_000)] = 0,
    limit: Annotated[int, Query(ge=1, le=10_000)] = 1000,
) -> schemas.MapUncertainty:
    """Every keyframe's marginal covariance from the map's pose graph (3x3 position and 6x6 pose, map
    frame; ``convention`` says how the 6x6 is parameterised), from the last solve (at most about once a
    second), ordered by (agent, id), paged."""
    return views_uncertainty.map_uncertainty(server, views.get_map(server, map_id), offset, limit)


@router.get(
    "/maps/{map_id}/points",
    responses={
        **NOT_FOUND,
        200: {
            "content": {"application/octet-stream": {}, "application/json": {}},
            "description": "binary little-endian PLY (double x, y, z; uint observations) or JSON",
        },
    },
    tags=["maps"],
)
async def map_points(
    server: Server,
    map_id: MapId,
    format: Annotated[schemas.PointsFormat, Query(description="ply (binary little-endian) or json")] = (
        schemas.PointsFormat.ply
    ),
    max_points: Annotated[
        int | None, Query(ge=1, le=100_000_000, description="ply: an even subsample of at most this many")
    ] = None,
    part: Annotated[
        int | None,
        Query(ge=0, le=4095, description="ply: only level-of-detail part PART of PARTS (float x, y, z)"),
    ] = None,
    parts: Annotated[
        int, Query(ge=1, le=4096, description="with part: the number of parts (each an even 1/PARTS)")
    ] = 1,
) -> StreamingResponse:
    """The map points, streamed. With ``part``: one of ``parts`` disjoint, evenly spread subsets that
    together hold every point (a point's part is a hash of its key), for drawing progressively."""
    if part is not None:
        if part >= parts:
            raise HTTPException(422, f"part {part} is not in 0..{parts - 1}")
        return StreamingResponse(
            await views.points_part_ply(server, map_id, part, parts), media_type="application/octet-stream"
        )
    if format == schemas.PointsFormat.ply:
        return StreamingResponse(
            views.points_ply(server, map_id, max_points),
            media_type="application/octet-stream",
            headers={"Content-Disposition": f'attachment; filename="map{map_id}.ply"'},
        )
    return StreamingResponse(views.points_json(server, map_id), media_type="application/json")


@router.get("/maps/{map_id}/edges", response_model=schemas.MapEdges, responses=NOT_FOUND, tags=["maps"])
async def map_edges(server: Server, map_id: MapId) -> schemas.MapEdges:
    """Loop edges (within and across agents) with the two keyframes' camera centres."""
    return views.map_edges(server, map_id)


@router.get(
    "/maps/{map_id}/groundtruth", response_model=schemas.MapGroundTruth, responses=NOT_FOUND, tags=["maps"]
)
async def map_groundtruth(server: Server, map_id: MapId) -> schemas.MapGroundTruth:
    """Ground truth of the map's agents when the server was given a ground-truth folder (setting
    ``groundtruth``, ``--groundtruth``), aligned to the map by one rigid transform (evo's Umeyama)."""
    return views.map_groundtruth(server, map_id)


@router.get("/events", response_model=schemas.EventList, tags=["server"])
async def events(
    server: Server,
    since: Annotated[int, Query(ge=0, le=2**62, description="only events with a larger id")] = 0,
    kind: Annotated[str | None, Query(max_length=32, description="connect, error, merge, loop, ...")] = None,
    limit: Annotated[int, Query(ge=1, le=100_000, description="at most this many (the newest)")] = 1000,
) -> schemas.EventList:
    """Merges, loops, corrections, connections and errors (a ring buffer)."""
    return views.events(server, since, kind, limit)


@router.get(
    "/maps/{map_id}/frontiers", response_model=schemas.FrontierList, responses=NOT_FOUND, tags=["team"]
)
async def map_frontiers(server: Server, map_id: MapId) -> schemas.FrontierList:
    """Frontier goals of the map (hivemap.server.team.frontiers), recomputed at most once per
    ``[team] min_interval_s``, off the event loop."""
    from hivemap.server.team.service import TeamOff, frontier_list, team_service

    views.get_map(server, map_id)  # 404 for an unknown map
    svc = team_service(server)
    try:
        at, fr = await svc.frontiers(map_id)
    except TeamOff as exc:
        raise HTTPException(503, str(exc)) from exc
    return frontier_list(map_id, at, fr, svc.options.frontiers.voxel_m)


@router.get("/team/assignments", response_model=schemas.TeamAssignments, tags=["team"])
async def team_assignments(server: Server) -> schemas.TeamAssignments:
    """Per map: the SSI auction of its frontiers among its connected agents and each agent's ORCA
    advisory (safe velocity for its desired one), recomputed at most once per ``[team] min_interval_s``."""
    from hivemap.server.team.service import TeamOff, team_service

    try:
        return await team_service(server).assignments()
    except TeamOff as exc:
        raise HTTPException(503, str(exc)) from exc


@router.get(
    "/metrics",
    response_class=PlainTextResponse,
    responses={200: {"content": {CONTENT_TYPE: {}}}},
    tags=["server"],
)
async def metrics(server: Server) -> PlainTextResponse:
    """Prometheus text format."""
    return PlainTextResponse(views_metrics.metrics(server), media_type=CONTENT_TYPE)
