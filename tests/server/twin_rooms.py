"""Synthetic streams with perceptual aliasing: a room and its twin (same points, same descriptors) 10 m away.

A camera in the twin sees exactly what a camera in the original room sees 10 m off, so place recognition
finds a geometrically perfect match (hundreds of inliers) that is wrong by 10 m. Unlike
:func:`hivemap.server.backend_synth.agent_stream`, each keyframe sees only the point sets it is given
(walls between the rooms), from a known true pose.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from hivemap.maps.geometry import Sim3, se3, so3_exp
from hivemap.protocol import Keyframe, MapPoints, Message
from hivemap.server.backend_synth import flip_bits, make_world
from hivemap.server.loadgen import CAMERA

TWIN_SHIFT = np.array([10.0, 0.0, 0.0])  # the twin room is the room moved by this (m)


@dataclass
class PointSet:
    xyz: np.ndarray  # (N, 3) true positions
    desc: np.ndarray  # (N, 32)
    id0: int  # point ids id0 .. id0 + N - 1 (sets seen by several passes share ids)


def room(rng: np.random.Generator, n: int = 2500) -> tuple[np.ndarray, np.ndarray]:
    return make_world(rng, n, (-20, 30))


def twin(ps: PointSet, id0: int, shift: np.ndarray = TWIN_SHIFT) -> PointSet:
    """The same room ``shift`` away, its points under new ids."""
    return PointSet(ps.xyz + shift, ps.desc, id0)


def doorway(rng: np.random.Generator, id0: int, x0: float = 2.0) -> PointSet:
    """Points with their own descriptors at x = x0 .. x0 + 12 that the cameras on both sides of a door
    see (the agent's path from one room into the next passes it): they connect its two passes."""
    xyz = np.column_stack([rng.uniform(x0, x0 + 12, 400), rng.uniform(-6, 4, 400), rng.uniform(12, 30, 400)])
    return PointSet(xyz, rng.integers(0, 256, size=(400, 32), dtype=np.uint8), id0)


def path(rng: np.random.Generator, xs: np.ndarray, offset: np.ndarray | None = None) -> list[np.ndarray]:
    """True world_from_cam poses along x (looking +z, small random tilt), moved by ``offset``."""
    off = np.zeros(3) if offset is None else offset
    return [
        se3(so3_exp(rng.normal(0, 0.05, 3)), off + np.array([x, rng.normal(0, 0.3), rng.normal(0, 0.3)]))
        for x in xs
    ]


def stream(
    rng: np.random.Generator,
    poses: list[np.ndarray],
    sees: list[list[PointSet]],
    local_from_world: Sim3,
    id0: int,
    gnss_sigma: float | None = None,
) -> list[Message]:
    """One agent's messages (points first, then keyframes ``id0``...): keyframe ``k`` at true pose
    ``poses[k]`` observes the points of ``sees[k]`` that project into its image (0.5 px noise, 3 flipped
    descriptor bits, 150 clutter keypoints). Poses and points are sent exact, in ``local_from_world``.
    ``gnss_sigma``: each keyframe carries a fix, its true camera centre (the world taken as ENU) plus
    noise of this standard deviation."""
    obs: dict[tuple[int, int], list[tuple[int, np.ndarray]]] = {}  # (set index, point) -> [(kf, uv)]
    sets: list[PointSet] = []
    for k, (T, seen) in enumerate(zip(poses, sees, strict=True)):
        for ps in seen:
            si = next((i for i, s in enumerate(sets) if s is ps), None)
            if si is None:
                si = len(sets)
                sets.append(ps)
            pc = ps.xyz @ T[:3, :3] - T[:3, 3] @ T[:3, :3]
            uv, valid = CAMERA.project(pc)
            valid &= CAMERA.in_image(uv, margin=5) & (pc[:, 2] > 1)
            for i in np.flatnonzero(valid).tolist():
                obs.setdefault((si, i), []).append((k, uv[i]))
    used = sorted(key for key, o in obs.items() if len(o) >= 2)
    msgs: list[Message] = []
    for si, ps in enumerate(sets):
        idx = [i for s, i in used if s == si]
        if idx:
            xyz = local_from_world.apply(ps.xyz[idx] + rng.normal(0, 0.02, (len(idx), 3)))
            ids = ps.id0 + np.array(idx, dtype=np.int64)
            msgs.append(MapPoints(ids=ids, xyz=xyz, descriptors=flip_bits(ps.desc[idx], rng, 2)))
    for k, T in enumerate(poses):
        rows = [(sets[si], i, uv) for si, i in used for kk, uv in obs[(si, i)] if kk == k]
        n_cl = 150
        octs = np.concatenate([rng.integers(0, 4, len(rows)), rng.integers(0, 4, n_cl)]).astype(np.uint8)
        kps = np.concatenate([np.array([uv for _, _, uv in rows]).reshape(-1, 2),
                              rng.uniform([0, 0], [640, 480], (n_cl, 2))])  # fmt: skip
        kps[: len(rows)] += rng.normal(0, 0.5, (len(rows), 2)) * (1.2 ** octs[: len(rows), None])
        d = np.concatenate([flip_bits(np.array([ps.desc[i] for ps, i, _ in rows]).reshape(-1, 32), rng, 3),
                            rng.integers(0, 256, (n_cl, 32), np.uint8)])  # fmt: skip
        pids = np.array([ps.id0 + i for ps, i, _ in rows] + [-1] * n_cl, dtype=np.int64)
        pose = local_from_world.transform_pose(T)
        kf = Keyframe(
            kf_id=id0 + k,
            timestamp=float(id0 + k),
            world_from_cam=pose,
            keypoints=kps.astype(np.float32),
            octaves=octs,
            descriptors=d,
            point_ids=pids,
            gnss_enu=None if gnss_sigma is None else T[:3, 3] + rng.normal(0, gnss_sigma, 3),
            gnss_cov=None if gnss_sigma is None else np.eye(3) * gnss_sigma**2,
        )
        msgs.append(kf)
    return msgs
