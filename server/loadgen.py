"""Synthetic agent streams and a minimal WebSocket agent, for the server's tests and ``bench/ingest.py``.

The stream is what a front-end would send: for each keyframe, first the map points it creates, then the
keyframe (referencing new and older points), and now and then a ``pose_updates`` (local BA) moving the last
few keyframes and their points. :class:`StreamTruth` holds what the server must end up with.
"""

from __future__ import annotations

import asyncio
import time
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from hivemap.maps.camera import PinholeCamera
from hivemap.maps.geometry import se3, so3_exp
from hivemap.protocol import Ack, Hello, Keyframe, MapPoints, Message, PoseUpdates, Welcome, decode, encode
from hivemap.protocol import Error as ErrorMsg

CAMERA = PinholeCamera(width=640, height=480, fx=400.0, fy=400.0, cx=320.0, cy=240.0)


@dataclass
class StreamTruth:
    """The final state the server must hold for one agent session (VIO frame)."""

    agent_id: str
    session: int
    kf_poses: dict[int, NDArray[np.float64]] = field(default_factory=dict)
    kf_timestamps: dict[int, float] = field(default_factory=dict)
    points: dict[int, NDArray[np.float64]] = field(default_factory=dict)


def synthetic_stream(
    agent_id: str,
    n_keyframes: int,
    *,
    features: int = 200,
    new_points_per_kf: int = 40,
    observed_per_kf: int = 120,
    pose_update_every: int = 5,
    session: int = 0,
    seed: int = 0,
    offset: tuple[float, float, float] = (0.0, 0.0, 0.0),
    kf_before_points_every: int = 0,
) -> tuple[list[Message], StreamTruth]:
    """Messages (send order) of one agent session with ``n_keyframes`` keyframes of ``features`` keypoints.

    ``kf_before_points_every=n``: every n-th keyframe is sent before the points it creates (the server must
    hold it until they arrive).
    """
    rng = np.random.default_rng(seed)
    truth = StreamTruth(agent_id, session)
    msgs: list[Message] = []
    next_point = 0
    kf_points: dict[int, list[int]] = {}
    origin = np.asarray(offset, dtype=np.float64)
    observed_per_kf = min(observed_per_kf, features)
    for k in range(n_keyframes):
        R = so3_exp(np.array([0.0, 0.0, 0.02 * k]) + rng.normal(0, 0.01, 3))
        T = se3(R, origin + np.array([0.5 * k, 0.1 * np.sin(k), 1.5]))
        new_ids = np.arange(next_point, next_point + new_points_per_kf, dtype=np.int64)
        next_point += new_points_per_kf
        xyz = T[:3, 3] + rng.normal(0, 5.0, (len(new_ids), 3))
        desc = rng.integers(0, 256, (len(new_ids), 32), dtype=np.uint8)
        if len(new_ids):
            msgs.append(MapPoints(ids=new_ids, xyz=xyz, descriptors=desc, session=session))
        for pid, p in zip(new_ids.tolist(), xyz, strict=True):
            truth.points[pid] = p
        older = np.arange(
            max(0, next_point - 4 * new_points_per_kf), next_point - len(new_ids), dtype=np.int64
        )
        n_old = min(len(older), observed_per_kf - len(new_ids))
        seen = np.concatenate([new_ids, rng.choice(older, n_old, replace=False) if n_old > 0 else older[:0]])
        point_ids = np.full(features, -1, dtype=np.int64)
        slots = rng.choice(features, len(seen), replace=False)
        point_ids[slots] = seen
        kf_points[k] = seen.tolist()
        kf = Keyframe(
            kf_id=k,
            timestamp=1000.0 + 0.2 * k,
            world_from_cam=T,
            keypoints=rng.uniform(0, [640, 480], (features, 2)).astype(np.float32),
            octaves=rng.integers(0, 8, features, dtype=np.uint8),
            descriptors=rng.integers(0, 256, (features, 32), dtype=np.uint8),
            point_ids=point_ids,
            session=session,
        )
        if kf_before_points_every and k % kf_before_points_every == 0 and len(new_ids):
            msgs.insert(len(msgs) - 1, kf)
        else:
            msgs.append(kf)
        truth.kf_poses[k] = T
        truth.kf_timestamps[k] = kf.timestamp
        if pose_update_every and k % pose_update_every == pose_update_every - 1:
            ks = np.arange(max(0, k - 2), k + 1, dtype=np.int64)
            poses = np.stack([truth.kf_poses[int(i)].copy() for i in ks])
            poses[:, :3, 3] += rng.normal(0, 0.01, (len(ks), 3))
            pids = np.array(sorted({p for i in ks.tolist() for p in kf_points[i]}), dtype=np.int64)
            pxyz = np.stack([truth.points[int(p)] for p in pids]) + rng.normal(0, 0.01, (len(pids), 3))
            msgs.append(
                PoseUpdates(kf_ids=ks, world_from_cam=poses, point_ids=pids, xyz=pxyz, session=session)
            )
            for i, P in zip(ks.tolist(), poses, strict=True):
                truth.kf_poses[i] = P
            for p, x in zip(pids.tolist(), pxyz, strict=True):
                truth.points[p] = x
    return msgs, truth


def mission_of(agent_id: str) -> str:
    """A fixed mission id per agent id: the load generator's reconnects resume one mission."""
    import uuid

    return uuid.uuid5(uuid.NAMESPACE_URL, f"hivemap-loadgen/{agent_id}").hex


def hello(
    agent_id: str,
    token: str,
    kind: str = "uav",
    session: int = 0,
    resume_from: int = 0,
    mission: str | None = None,
) -> Hello:
    return Hello(
        mission=mission or mission_of(agent_id),
        agent_id=agent_id,
        kind=kind,
        camera=CAMERA.to_dict(),
        token=token,
        resume_from=resume_from,
        session=session,
    )


@dataclass
class StreamStats:
    sent: int = 0
    acked: int = 0
    bytes_sent: int = 0
    keyframes: int = 0
    keyframe_bytes: int = 0
    latencies: list[float] = field(default_factory=list)
    errors: list[ErrorMsg] = field(default_factory=list)
    elapsed: float = 0.0


async def stream_agent(
    url: str,
    agent_id: str,
    token: str,
    messages: list[Message],
    *,
    rate_hz: float | None = None,
    window: int = 64,
    first_seq: int = 1,
    timeout: float = 120.0,
    phase: float = 0.0,
) -> StreamStats:
    """Send ``messages`` (seq = first_seq, first_seq + 1, ...) and wait for every ack.

    ``rate_hz`` paces keyframes (other messages go out right before their keyframe), starting ``phase``
    seconds late (agents are not synchronised); ``window`` bounds the unacknowledged messages in flight.
    Latency = send to ack, per message.
    """
    import websockets

    stats = StreamStats()
    sent_at: dict[int, float] = {}
    inflight = asyncio.Semaphore(window)
    t0 = time.perf_counter()
    async with websockets.connect(url, max_size=None, compression=None) as ws:
        await ws.send(encode(hello(agent_id, token), 0))
        _, welcome = decode(await ws.recv())
        if not isinstance(welcome, Welcome):
            raise RuntimeError(f"expected welcome, got {welcome}")
        last = first_seq + len(messages) - 1
        done = asyncio.Event()

        async def reader() -> None:
            async for frame in ws:
                assert isinstance(frame, bytes)
                _, msg = decode(frame)
                if isinstance(msg, Ack):
                    t = sent_at.pop(msg.seq, None)
                    if t is not None:
                        stats.latencies.append(time.perf_counter() - t)
                        stats.acked += 1
                        inflight.release()
                    if msg.seq >= last or (not sent_at and stats.sent == len(messages)):
                        done.set()
                elif isinstance(msg, ErrorMsg):
                    stats.errors.append(msg)

        task = asyncio.create_task(reader())
        next_t = time.perf_counter() + phase
        for i, msg in enumerate(messages):
            if rate_hz and isinstance(msg, Keyframe):
                next_t += 1.0 / rate_hz
                delay = next_t - time.perf_counter()
                if delay > 0:
                    await asyncio.sleep(delay)
            await inflight.acquire()
            seq = first_seq + i
            frame = encode(msg, seq)
            sent_at[seq] = time.perf_counter()
            await ws.send(frame)
            stats.sent += 1
            stats.bytes_sent += len(frame)
            if isinstance(msg, Keyframe):
                stats.keyframes += 1
                stats.keyframe_bytes += len(frame)
        if messages:
            await asyncio.wait_for(done.wait(), timeout)
        stats.elapsed = time.perf_counter() - t0
        task.cancel()
    return stats
