"""Synthetic multi-agent worlds for the back-end's tests and bench (no rendering).

3D points on non-coplanar facades with random 256-bit descriptors; an agent flies along x looking +z and its
keyframes see the points through a pinhole camera (0.5 px x 1.2^octave noise, 3 flipped descriptor bits per
observation, clutter keypoints). Each agent's map is the world under its own ``local_from_world`` Sim(3).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from hivemap.maps.geometry import Sim3, se3, so3_exp
from hivemap.protocol import Keyframe, MapPoints, Message
from hivemap.server.loadgen import CAMERA


def flip_bits(desc: np.ndarray, rng: np.random.Generator, n_bits: int) -> np.ndarray:
    bits = np.unpackbits(desc, axis=-1)
    for row in bits.reshape(-1, 256):
        row[rng.choice(256, n_bits, replace=False)] ^= 1
    return np.packbits(bits, axis=-1)


def make_world(
    rng: np.random.Generator, n: int, x_range: tuple[float, float]
) -> tuple[np.ndarray, np.ndarray]:
    x = rng.uniform(*x_range, n)
    kind = rng.integers(0, 3, n)
    z = np.where(kind == 0, 25.0 + rng.normal(0, 0.3, n), rng.uniform(12, 35, n))
    y = np.where(kind == 1, 4.0 + rng.normal(0, 0.1, n), rng.uniform(-6, 4, n))
    return np.stack([x, y, z], axis=1), rng.integers(0, 256, size=(n, 32), dtype=np.uint8)


def agent_stream(
    rng: np.random.Generator,
    pts: np.ndarray,
    desc: np.ndarray,
    centres_x: np.ndarray,
    local_from_world: Sim3,
    pose_noise: tuple[float, float] = (0.0, 0.0),
    id0: int = 0,
    point_id0: int = 0,
    drift: Sim3 | None = None,
    gnss_sigma: float | None = None,
    up_tilt_deg: float | np.ndarray | None = None,
) -> tuple[list[Message], np.ndarray, np.ndarray]:
    """Messages of one agent (points first, then keyframes) + true and sent poses in its local frame.

    ``pose_noise`` (metres in the world, degrees): perturbation of the sent keyframe poses (drift-like
    error the server's global BA should remove); observations come from the true poses. ``id0`` /
    ``point_id0``: first keyframe / point id (a second pass). ``drift``: the sent poses
    and points are moved by it (odometry drift on a second pass); true poses are returned without it.
    ``gnss_sigma``: each keyframe carries a GNSS fix (the true camera centre in the world frame, taken as
    ENU, plus noise of this standard deviation). ``up_tilt_deg``: each keyframe carries ``up_cam``, the
    world's z axis in its camera frame (an IMU's up direction), turned by this angle about the camera's x
    axis (0: exact; an array: one angle per keyframe)."""
    true = []
    for cx in centres_x:
        R = so3_exp(rng.normal(0, 0.05, 3))
        true.append(se3(R, np.array([cx, rng.normal(0, 0.3), rng.normal(0, 0.3)])))
    seen: dict[int, list[tuple[int, np.ndarray, int]]] = {}
    for k, T in enumerate(true):
        pc = pts @ T[:3, :3] - T[:3, 3] @ T[:3, :3]
        uv, valid = CAMERA.project(pc)
        valid &= CAMERA.in_image(uv, margin=5) & (pc[:, 2] > 1)
        for i in np.flatnonzero(valid).tolist():
            seen.setdefault(i, []).append((k, uv[i], int(rng.integers(0, 4))))
    used = sorted(i for i, obs in seen.items() if len(obs) >= 2)
    ids = {i: point_id0 + j for j, i in enumerate(used)}
    sent_from_local = drift if drift is not None else Sim3.identity()
    xyz = (sent_from_local @ local_from_world).apply(pts[used] + rng.normal(0, 0.02, (len(used), 3)))
    msgs: list[Message] = [
        MapPoints(
            ids=point_id0 + np.arange(len(used), dtype=np.int64),
            xyz=xyz,
            descriptors=flip_bits(desc[used], rng, 2),
        )
    ]
    sent = []
    tilts = np.broadcast_to(np.asarray(0.0 if up_tilt_deg is None else up_tilt_deg, float), len(true))
    leans = [so3_exp(np.array([np.deg2rad(a), 0.0, 0.0])) for a in tilts]
    for k, T in enumerate(true):
        rows = [(i, uv, o) for i in used for (kk, uv, o) in seen[i] if kk == k]
        n_cl = 150
        octs = np.array([o for _, _, o in rows] + list(rng.integers(0, 4, n_cl)), dtype=np.uint8)
        kps = np.concatenate(
            [np.array([uv for _, uv, _ in rows]).reshape(-1, 2), rng.uniform([0, 0], [640, 480], (n_cl, 2))]
        )
        kps[: len(rows)] += rng.normal(0, 0.5, (len(rows), 2)) * (1.2 ** octs[: len(rows), None])
        d = np.concatenate(
            [flip_bits(desc[[i for i, _, _ in rows]], rng, 3), rng.integers(0, 256, (n_cl, 32), np.uint8)]
        )
        pids = np.array([ids[i] for i, _, _ in rows] + [-1] * n_cl, dtype=np.int64)
        dT = se3(so3_exp(np.deg2rad(pose_noise[1]) * rng.normal(0, 1, 3) / np.sqrt(3)),
                 pose_noise[0] * rng.normal(0, 1, 3) / np.sqrt(3))  # fmt: skip
        T_sent = (sent_from_local @ local_from_world).transform_pose(T @ dT)  # perturbed in the camera frame
        sent.append(T_sent)
        msgs.append(
            Keyframe(kf_id=id0 + k, timestamp=float(id0 + k), world_from_cam=T_sent,
                     keypoints=kps.astype(np.float32), octaves=octs, descriptors=d, point_ids=pids,
                     gnss_enu=None if gnss_sigma is None else T[:3, 3] + rng.normal(0, gnss_sigma, 3),
                     gnss_cov=None if gnss_sigma is None else np.eye(3) * gnss_sigma**2,
                     up_cam=None if up_tilt_deg is None else leans[k] @ T[:3, :3].T @ np.eye(3)[2])
        )  # fmt: skip
    true_local = np.array([local_from_world.transform_pose(T) for T in true])
    return msgs, true_local, np.array(sent)


# the UGV's map frame in the back-end tests (the UGV defines the global frame)
UGV_FROM_WORLD = Sim3(so3_exp(np.array([0.0, 0.0, 0.4])), np.array([3.0, -2.0, 0.5]), 1.0)


def loop_passes(
    seed: int = 5, local_from_world: Sim3 = UGV_FROM_WORLD
) -> tuple[list[Message], list[Message], np.ndarray, np.ndarray]:
    """One agent passes a place twice, the second pass with its own keyframe and point ids and under a
    rigid drift (2.3 deg + ~0.5 m): an intra-map loop closure. No keyframe lies between the passes, 12 m
    apart, so the agent did not track that stretch: the second pass's first keyframe says so
    (``odom_sigma``), as a front-end does after a tracking loss, and the server's pose graph lets the loop
    take the drift there. Returns the two passes' messages and the second pass's true and sent poses."""
    rng = np.random.default_rng(seed)
    pts, desc = make_world(rng, 2500, (-20, 30))
    drift = Sim3(so3_exp(np.array([0.0, 0.04, 0.0])), np.array([0.4, -0.2, 0.3]), 1.0)
    first, _, _ = agent_stream(rng, pts, desc, np.linspace(-6, 8, 10), local_from_world)
    second, true2, sent2 = agent_stream(
        rng, pts, desc, np.linspace(-4, 10, 10), local_from_world, id0=1000, point_id0=100000, drift=drift
    )
    untracked = np.array([0.5, 3.0])  # m, deg: at least the drift
    second = [replace(msg, odom_sigma=untracked) if isinstance(msg, Keyframe) and msg.kf_id == 1000 else msg
              for msg in second]  # fmt: skip
    return first, second, true2, sent2
