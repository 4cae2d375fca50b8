"""Compare what agents sent (their outboxes: the agents' own records) with what a server stored.

An agent's record is every keyframe message of its outbox with the last pose it gave the keyframe (its
``pose_updates`` applied in seq order). The stored side is the server's SQLite file, read after the server
stopped, keyed the same way through the agent maps' (mission, client session). On a server without a
back-end nothing may move a stored keyframe, so stored poses must equal the record's bit for bit.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from hivemap.client.outbox import Outbox
from hivemap.protocol import Keyframe, PoseUpdates, decode
from hivemap.server.persist import ServerStore

Key = tuple[str, int, int]  # (mission, session the agent gave it, keyframe id)


@dataclass
class Record:
    mission: str
    poses: dict[Key, np.ndarray] = field(default_factory=dict)
    keyframe_messages: int = 0
    unacked: int = 0


def agent_record(outbox_path: Path, agent_id: str) -> Record:
    box = Outbox(outbox_path, agent_id)
    try:
        rec = Record(box.mission)
        for _, frame, acked in box.frames():
            rec.unacked += not acked
            _, msg = decode(frame)
            if isinstance(msg, Keyframe):
                rec.keyframe_messages += 1
                rec.poses[(box.mission, msg.session, msg.kf_id)] = np.array(msg.world_from_cam)
            elif isinstance(msg, PoseUpdates):
                for i, k in enumerate(msg.kf_ids.tolist()):
                    key = (box.mission, msg.session, int(k))
                    if key in rec.poses:
                        rec.poses[key] = np.array(msg.world_from_cam[i])
        return rec
    finally:
        box.close()


def stored_keyframes(db: Path, agent_id: str) -> tuple[dict[Key, np.ndarray], Counter[Key]]:
    """The agent's stored keyframes by (mission, client session, id), and how often each key is stored."""
    store = ServerStore(db)
    try:
        loaded = store.load_all()
    finally:
        store.close()
    by_folded = {f: (r["mission"], r["client_session"]) for f, r in loaded.agent_maps.items()}
    poses: dict[Key, np.ndarray] = {}
    count: Counter[Key] = Counter()
    for m in loaded.stack.maps.values():
        for (folded, kf_id), kf in m.keyframes.items():
            if folded.partition("#")[0] != agent_id:
                continue
            mission, session = by_folded[folded]
            key = (mission, session, kf_id)
            poses[key] = kf.world_from_cam
            count[key] += 1
    for folded, _kf_id, msg in loaded.pending:
        if folded.partition("#")[0] == agent_id:
            mission, session = by_folded[folded]
            key = (mission, session, msg.kf_id)
            poses[key] = np.array(msg.world_from_cam)
            count[key] += 1
    return poses, count


@dataclass
class Comparison:
    lost: int
    duplicated: int
    changed: int
    foreign: int  # stored under this agent id but in no record given

    @property
    def clean(self) -> bool:
        return self.lost == self.duplicated == self.changed == self.foreign == 0


def compare(records: list[Record], db: Path, agent_id: str, tol: float = 1e-9) -> Comparison:
    stored, count = stored_keyframes(db, agent_id)
    wanted: dict[Key, np.ndarray] = {}
    for r in records:
        wanted.update(r.poses)
    lost = sum(1 for k in wanted if k not in stored)
    changed = sum(
        1 for k, T in wanted.items() if k in stored and not np.allclose(stored[k], T, atol=tol, rtol=0)
    )
    return Comparison(
        lost=lost,
        duplicated=sum(n - 1 for n in count.values() if n > 1),
        changed=changed,
        foreign=sum(1 for k in stored if k not in wanted),
    )
