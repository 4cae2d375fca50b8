"""The server's store: the maps' :class:`~hivemap.maps.store.MapStore` plus the ingest bookkeeping tables
(agents and their last seq, agent-map transforms, keyframes waiting for their points), in ONE SQLite file and
ONE connection, so a batch of map data and the agents' last seqs commit in the same transaction.

Used only from the writer thread (:mod:`hivemap.server.writer`).
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass, field
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np

from hivemap.maps import MapStack
from hivemap.maps.store import MapStore
from hivemap.protocol import Keyframe, decode, encode

logger = logging.getLogger(__name__)

SCHEMA = """
CREATE TABLE IF NOT EXISTS server_agents (
    agent_id TEXT PRIMARY KEY,
    record TEXT NOT NULL,          -- json: kind, camera, session
    last_seq INTEGER NOT NULL DEFAULT 0
);
CREATE TABLE IF NOT EXISTS server_agent_maps (
    folded TEXT PRIMARY KEY,       -- agent id with the session folded in ("uav1", "uav1#1")
    agent_id TEXT NOT NULL,
    session INTEGER NOT NULL,
    global_from_vio BLOB NOT NULL  -- 16 float64, row-major Sim(3) matrix
);
CREATE TABLE IF NOT EXISTS server_pending (
    folded TEXT NOT NULL,
    kf_id INTEGER NOT NULL,
    frame BLOB NOT NULL,           -- the keyframe message, protocol-encoded
    PRIMARY KEY (folded, kf_id)
);
"""


@dataclass
class Loaded:
    stack: MapStack
    agents: list[dict[str, Any]] = field(default_factory=list)
    agent_maps: dict[str, dict[str, Any]] = field(default_factory=dict)
    pending: list[tuple[str, int, Keyframe]] = field(default_factory=list)


class GraphSnapshot:
    """What ``MapStore.sync_graph`` reads from a map, copied on the event loop thread so that the writer
    thread never iterates a map the loop is changing."""

    def __init__(self, m: Any) -> None:
        self.id = m.id
        changed = [k for k in m.drain_tree_changes() if k in m.keyframes]
        self.keyframes = {k: SimpleNamespace(parent=m.keyframes[k].parent) for k in changed}
        self.agents = set(m.agents)
        self.orphans = set(m.orphans)
        self.point_redirects = dict(m.point_redirects)
        self._loops = list(m.loop_edges())

    def drain_tree_changes(self) -> list[Any]:
        return list(self.keyframes)

    def loop_edges(self) -> list[Any]:
        return self._loops


class ServerStore:
    """``maps`` is the MapStore (map data); the methods here keep the ingest state next to it."""

    def __init__(self, path: Path, synchronous: str = "FULL") -> None:
        self.path = Path(path)
        self.maps = MapStore(self.path, autocommit=False, synchronous=synchronous)
        self.conn = self.maps.conn
        self.conn.executescript(SCHEMA)
        self.conn.commit()

    # -- transactions (driven by the writer) ---------------------------------------------------------
    def commit(self) -> None:
        self.conn.commit()

    def rollback(self) -> None:
        self.conn.rollback()

    def close(self) -> None:
        self.maps.close()

    def sync_graph(self, snapshot: GraphSnapshot) -> None:
        self.maps.sync_graph(snapshot)  # type: ignore[arg-type]

    # -- ingest state --------------------------------------------------------------------------------
    def put_agent(self, record: dict[str, Any]) -> None:
        self.conn.execute(
            "INSERT INTO server_agents (agent_id, record) VALUES (?, ?) "
            "ON CONFLICT(agent_id) DO UPDATE SET record = excluded.record",
            (record["agent_id"], json.dumps(record)),
        )

    def set_last_seq(self, agent_id: str, seq: int) -> None:
        self.conn.execute(
            "UPDATE server_agents SET last_seq = MAX(last_seq, ?) WHERE agent_id = ?", (int(seq), agent_id)
        )

    def put_agent_map(self, folded: str, agent_id: str, session: int, global_from_vio: np.ndarray) -> None:
        blob = np.ascontiguousarray(global_from_vio, dtype="<f8").tobytes()
        self.conn.execute(
            "INSERT OR REPLACE INTO server_agent_maps (folded, agent_id, session, global_from_vio) "
            "VALUES (?, ?, ?, ?)",
            (folded, agent_id, int(session), blob),
        )

    def put_pending(self, folded: str, msg: Keyframe) -> None:
        self.conn.execute(
            "INSERT OR REPLACE INTO server_pending (folded, kf_id, frame) VALUES (?, ?, ?)",
            (folded, int(msg.kf_id), encode(msg, 0)),
        )

    def delete_pending(self, folded: str, kf_id: int) -> None:
        self.conn.execute("DELETE FROM server_pending WHERE folded = ? AND kf_id = ?", (folded, int(kf_id)))

    # -- message and bandwidth counters (their own table: written apart from the data, see core) --------
    COUNTERS_SCHEMA = """
    CREATE TABLE IF NOT EXISTS server_counters (
        agent_id TEXT PRIMARY KEY,
        record TEXT NOT NULL           -- json: received per type, duplicates, errors, bandwidth
    );
    """

    def put_counters(self, agent_id: str, record: dict[str, Any]) -> None:
        self.conn.execute(
            "INSERT INTO server_counters (agent_id, record) VALUES (?, ?) "
            "ON CONFLICT(agent_id) DO UPDATE SET record = excluded.record",
            (agent_id, json.dumps(record)),
        )

    def load_counters(self) -> dict[str, dict[str, Any]]:
        """Every agent's counters as last written (creates the table in older stores)."""
        self.conn.executescript(self.COUNTERS_SCHEMA)
        rows = self.conn.execute("SELECT agent_id, record FROM server_counters")
        return {a: json.loads(r) for a, r in rows}

    # -- start-up ------------------------------------------------------------------------------------
    def load_all(self) -> Loaded:
        out = Loaded(stack=self.maps.load_stack())
        for record, last_seq in self.conn.execute("SELECT record, last_seq FROM server_agents"):
            rec = json.loads(record)
            rec["last_seq"] = int(last_seq)
            out.agents.append(rec)
        for folded, agent_id, session, blob in self.conn.execute(
            "SELECT folded, agent_id, session, global_from_vio FROM server_agent_maps"
        ):
            out.agent_maps[folded] = {
                "agent_id": agent_id,
                "session": int(session),
                "global_from_vio": np.frombuffer(blob, dtype="<f8").reshape(4, 4).copy(),
            }
        for folded, kf_id, frame in self.conn.execute("SELECT folded, kf_id, frame FROM server_pending"):
            _, msg = decode(bytes(frame))
            if isinstance(msg, Keyframe):
                out.pending.append((folded, int(kf_id), msg))
        return out
