"""Hostile frames for fuzz tests (the protocol's own tests and the server's live-socket tests).

``fuzz_frames(n, seed)`` yields ``n`` byte strings: random bytes, valid frames with bit flips,
truncations and splices, random msgpack objects, envelopes with wrong field types, arrays whose
declared shape lies about their size, deep nesting and oversized declared lengths.
"""

from __future__ import annotations

import random
import struct
from collections.abc import Iterator
from typing import Any

import msgpack
import numpy as np

from hivemap.protocol.codec import encode
from hivemap.protocol.messages import (
    Ack,
    Bye,
    Correction,
    Hello,
    Keyframe,
    MapPoints,
    Message,
    PoseUpdates,
    Rendezvous,
)


def sample_messages(rng: np.random.Generator, n_features: int = 200) -> list[Message]:
    """A set of valid messages of every agent -> server type (and a correction)."""
    pose = np.eye(4)
    pose[:3, 3] = rng.normal(size=3)
    return [
        Hello(
            "uav1",
            "uav",
            {
                "width": 640,
                "height": 480,
                "fx": 400.0,
                "fy": 400.0,
                "cx": 320.0,
                "cy": 240.0,
                "dist": [0.0, 0.0, 0.0, 0.0],
            },
            "token-uav1",
            mission="0f8e4c2a9b1d4e6f8a7b6c5d4e3f2a1b",
            stereo_baseline=0.11,
        ),
        Keyframe(
            kf_id=int(rng.integers(0, 1000)),
            timestamp=float(rng.uniform(0, 100)),
            world_from_cam=pose,
            keypoints=rng.uniform(0, 640, (n_features, 2)).astype(np.float32),
            octaves=rng.integers(0, 8, n_features).astype(np.uint8),
            descriptors=rng.integers(0, 256, (n_features, 32)).astype(np.uint8),
            point_ids=rng.integers(-1, 500, n_features).astype(np.int64),
            u_right=np.where(rng.random(n_features) < 0.6, rng.uniform(0, 640, n_features), np.nan).astype(
                np.float32
            ),
        ),
        MapPoints(
            np.arange(50, dtype=np.int64),
            rng.normal(size=(50, 3)),
            rng.integers(0, 256, (50, 32)).astype(np.uint8),
        ),
        PoseUpdates(
            np.arange(3, dtype=np.int64),
            np.stack([pose] * 3),
            np.arange(5, dtype=np.int64),
            rng.normal(size=(5, 3)),
        ),
        Rendezvous(
            timestamp=12.5,
            observed_agent="ugv",
            marker_ids=np.array([3, 4, 7], dtype=np.int64),
            ref_kf_id=4,
            ref_from_cam=pose,
            cam_from_observed=pose,
            covariance=np.diag([1e-4, 1e-4, 1e-4, 1e-3, 1e-3, 4e-3]),
            reproj_rms_px=0.4,
        ),
        Correction(0, np.eye(4), np.arange(2, dtype=np.int64), np.stack([pose] * 2)),
        Ack(7),
        Bye("done"),
    ]


def _random_obj(r: random.Random, depth: int = 0) -> Any:
    kind = r.randrange(9 if depth < 4 else 6)
    if kind == 0:
        return r.randint(-(2**63), 2**64 - 1)
    if kind == 1:
        return r.choice([float("nan"), float("inf"), -0.0, r.uniform(-1e308, 1e308)])
    if kind == 2:
        return "".join(chr(r.randrange(32, 0x2FFF)) for _ in range(r.randrange(20)))
    if kind == 3:
        return bytes(r.randrange(256) for _ in range(r.randrange(40)))
    if kind == 4:
        return r.choice([None, True, False])
    if kind == 5:
        return msgpack.ExtType(r.randrange(128), bytes(r.randrange(256) for _ in range(r.randrange(30))))
    if kind == 6:
        return [_random_obj(r, depth + 1) for _ in range(r.randrange(5))]
    keys = ["v", "type", "seq", "body", "kf_id", "keypoints", "agent_id", "token", "ids", "xyz"]
    return {r.choice(keys): _random_obj(r, depth + 1) for _ in range(r.randrange(5))}


def _lying_array(r: random.Random) -> msgpack.ExtType:
    """An array ext whose header declares a huge or inconsistent shape."""
    ndim = r.randrange(0, 5)
    shape = [r.choice([0, 1, 2, 4, 32, 2**31, 2**32 - 1]) for _ in range(ndim)]
    head = struct.pack(f"<BB{ndim}I", r.randrange(0, 9), ndim, *shape)
    return msgpack.ExtType(1, head + bytes(r.randrange(64)))


def fuzz_frames(n: int, seed: int = 0) -> Iterator[bytes]:
    """Yield ``n`` hostile frames (deterministic for a seed)."""
    r = random.Random(seed)
    rng = np.random.default_rng(seed)
    valid = [encode(m, i + 1) for i, m in enumerate(sample_messages(rng))]
    types = ["hello", "keyframe", "map_points", "pose_updates", "ack", "bye", "correction", "nope", 7, None]
    for i in range(n):
        k = i % 8
        if k == 0:
            yield bytes(r.randrange(256) for _ in range(r.randrange(1, 200)))
        elif k == 1:  # bit flips in a valid frame
            b = bytearray(r.choice(valid))
            for _ in range(r.randrange(1, 8)):
                pos = r.randrange(len(b))
                b[pos] ^= 1 << r.randrange(8)
            yield bytes(b)
        elif k == 2:  # truncation
            b = r.choice(valid)
            yield b[: r.randrange(len(b))]
        elif k == 3:  # splice of two frames
            a, c = r.choice(valid), r.choice(valid)
            yield a[: r.randrange(len(a))] + c[r.randrange(len(c)) :]
        elif k == 4:  # random msgpack object
            yield msgpack.packb(_random_obj(r), use_bin_type=True)
        elif k == 5:  # well-formed envelope, hostile body
            body = {"kf_id": _random_obj(r), "keypoints": _lying_array(r), "agent_id": _random_obj(r),
                    "u_right": r.choice([_lying_array(r), _random_obj(r)])}  # fmt: skip
            frame = {
                "v": r.choice([1, 2, 2, 2, 3, "2", None]),
                "type": r.choice(types),
                "seq": _random_obj(r),
                "body": body,
            }
            yield msgpack.packb(frame, use_bin_type=True)
        elif k == 6:  # huge declared lengths (array32/map32/str32/bin32 headers with little data)
            hdr = r.choice([b"\xdd", b"\xdf", b"\xdb", b"\xc6", b"\xc9"])
            yield hdr + struct.pack(">I", r.choice([2**31, 2**32 - 1, 10**8])) + bytes(r.randrange(16))
        else:  # deep nesting
            depth = r.choice([100, 1000, 5000, 100000])
            yield b"\x91" * depth + b"\xc0"
