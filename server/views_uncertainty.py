"""REST views of the back-end's covariances (:mod:`hivemap.server.backend.uncertainty`)."""

from __future__ import annotations

from typing import Any

import numpy as np

from hivemap.server import schemas
from hivemap.server.backend.uncertainty import PoseCovariance, RelativeCovariance
from hivemap.server.core import HiveServer
from hivemap.server.marginals import CONVENTION, position_covariance


def _row(
    m: Any, map_id: int, key: tuple[str, int], cov: np.ndarray, t: float, velocity: np.ndarray | None = None
) -> schemas.PoseUncertainty:
    T = m.keyframes[key].world_from_cam
    return schemas.PoseUncertainty(
        agent_id=key[0], kf_id=int(key[1]), map_id=map_id, position=np.asarray(T[:3, 3], float).tolist(),
        position_cov=position_covariance(cov).tolist(), pose_cov=np.asarray(cov, float).tolist(),
        velocity_cov=None if velocity is None else np.asarray(velocity, float).tolist(),
        computed_at=t, convention=CONVENTION,
    )  # fmt: skip


def latest_pose_covariance(server: Any, folded: str) -> PoseCovariance | None:
    """The back-end's covariance of agent session ``folded``'s latest keyframe (as of its last solve), if
    it is of a map that still holds that keyframe: what ``/agents/{id}``, the corrections and the team
    service's advisories report (on the event loop)."""
    unc = getattr(getattr(server, "backend", None), "uncertainty", None)
    cov: PoseCovariance | None = unc.of_agent(folded) if unc is not None else None
    m = server.stack.maps.get(cov.map_id) if cov is not None else None
    if cov is None or m is None or cov.key not in m.keyframes:
        return None
    return cov


def latest_relative_covariance(server: Any, a: str, b: str) -> RelativeCovariance | None:
    """The back-end's covariance of ``p_a - p_b`` for agent sessions ``a`` and ``b`` (folded), as of its
    last solve, if one map holds both keyframes it was of (on the event loop)."""
    unc = getattr(getattr(server, "backend", None), "uncertainty", None)
    rel: RelativeCovariance | None = unc.between(a, b) if unc is not None else None
    m = server.stack.maps.get(rel.map_id) if rel is not None else None
    if rel is None or m is None or any(k not in m.keyframes for k in rel.keys):
        return None
    return rel


def agent_uncertainty(server: HiveServer, folded: str) -> schemas.PoseUncertainty | None:
    """The latest keyframe's covariance of agent session ``folded``, if the back-end has one for the map
    the session is in now."""
    cov = latest_pose_covariance(server, folded)
    if cov is None:
        return None
    return _row(
        server.stack.maps[cov.map_id], cov.map_id, cov.key, cov.covariance, cov.computed_at, cov.velocity
    )


def map_uncertainty(server: HiveServer, m: Any, offset: int, limit: int) -> schemas.MapUncertainty:
    """Every keyframe's covariance of map ``m`` from its last solve, ordered by (agent, id), paged;
    keyframes that arrived after it are not listed."""
    unc = getattr(getattr(server, "backend", None), "uncertainty", None)
    res = unc.of_map(m.id) if unc is not None else None
    if res is None:
        return schemas.MapUncertainty(map_id=m.id, computed_at=None, cpu_s=None, total=0, offset=offset,
                                      convention=CONVENTION, keyframes=[])  # fmt: skip
    rows = sorted((k, i) for i, k in enumerate(res.keys) if k in m.keyframes)
    page = rows[offset : offset + limit]
    return schemas.MapUncertainty(
        map_id=m.id, computed_at=res.computed_at, cpu_s=res.cpu_s, total=len(rows), offset=offset,
        convention=CONVENTION,
        keyframes=[_row(m, m.id, k, res.covariances[i], res.computed_at) for k, i in page],
    )  # fmt: skip
