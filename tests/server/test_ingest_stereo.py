"""Stereo observations travel to the server: a v2 agent's ``u_right`` is kept with its keyframes and
persisted; an older (v1) agent's keyframes, without it, are stored mono (real server, WebSocket, store)."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
from agent_client import SyncAgent
from srv_helpers import TOKENS, ServerProcess, map_of, write_config

from hivemap.maps.store import MapStore
from hivemap.protocol import Keyframe, Message, downgrade, encode
from hivemap.server.loadgen import hello, synthetic_stream


def _v1(msg: Message, seq: int) -> bytes:
    """The frame as a v1 agent writes it: version 1, none of the later versions' fields."""
    return encode(downgrade(msg, 1), seq, version=1)


def _stereo(kf: Keyframe) -> Keyframe:
    ur = np.where(np.arange(len(kf.keypoints)) % 3 == 0, np.nan, kf.keypoints[:, 0] - 6.25)
    return replace(kf, u_right=ur.astype(np.float32))


def test_u_right_is_kept_and_persisted_and_v1_agents_are_mono(tmp_path: Path) -> None:
    server = ServerProcess(tmp_path / "data", write_config(tmp_path / "server.toml")).start()
    try:
        msgs, truth = synthetic_stream("uav1", 3, seed=5, pose_update_every=0)
        stereo = [_stereo(m) if isinstance(m, Keyframe) else m for m in msgs]
        with SyncAgent(server.ws_url, "uav1", TOKENS["uav1"]) as ag:
            ag.send(replace(hello("uav1", TOKENS["uav1"]), stereo_baseline=0.11), 0)
            ag.recv()
            _, errors = ag.send_all(stereo, 1)
            assert not errors
        old, _ = synthetic_stream("uav2", 3, seed=6, pose_update_every=0)
        with SyncAgent(server.ws_url, "uav2", TOKENS["uav2"]) as ag:
            ag.send_raw(_v1(hello("uav2", TOKENS["uav2"]), 0))
            ag.recv()
            for seq, m in enumerate(old, 1):
                ag.send_raw(_v1(m, seq))
            acks = [ag.recv() for _ in old]
            assert all(type(a).__name__ == "Ack" for a in acks), acks
        assert map_of(server, "uav1")["keyframes"] == len(truth.kf_poses)
        assert map_of(server, "uav2")["keyframes"] == len(truth.kf_poses)
    finally:
        server.stop()
    stack = MapStore(tmp_path / "data" / "hivemap.sqlite").load_stack()
    kfs = {k: kf for m in stack.maps.values() for k, kf in m.keyframes.items()}
    sent = {m.kf_id: m for m in stereo if isinstance(m, Keyframe)}
    for kid, msg in sent.items():
        kf = kfs[("uav1", kid)]
        assert kf.stereo_baseline == 0.11 and kf.u_right is not None and msg.u_right is not None
        assert kf.u_right.tobytes() == msg.u_right.tobytes()  # bit-exact, NaNs included
    uav2 = [kf for k, kf in kfs.items() if k[0] == "uav2"]
    assert uav2 and all(kf.u_right is None and kf.stereo_baseline is None for kf in uav2)
