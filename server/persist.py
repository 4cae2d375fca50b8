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
LEGACY_MISSION = "legacy"  # the mission of data stored before missions existed

SCHEMA = """
CREATE TABLE IF NOT EXISTS server_agents (
    agent_id TEXT PRIMARY KEY,
    record TEXT NOT NULL,          -- json: kind, camera, session
    last_seq INTEGER NOT NULL DEFAULT 0  -- before missions existed: the agent's one seq counter
);
CREATE TABLE IF NOT EXISTS server_missions (
    agent_id TEXT NOT NULL,
    mission TEXT NOT NULL,         -- the agent outbox's UUID, from its hello
    last_seq INTEGER NOT NULL DEFAULT 0,
    PRIMARY KEY (agent_id, mission)
);
CREATE TABLE IF NOT EXISTS server_agent_maps (
    folded TEXT PRIMARY KEY,       -- agent id with the server session folded in ("uav1", "uav1#1")
    agent_id TEXT NOT NULL,
    session INTEGER NOT NULL,      -- the server's number of this map among the agent's maps
    global_from_vio BLOB NOT NULL, -- 16 float64, row-major Sim(3) matrix
    mission TEXT NOT NULL DEFAULT '',
    client_session INTEGER         -- the session number the agent gave it within its mission
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
    missions: list[tuple[str, str, int]] = field(default_factory=list)  # (agent id, mission, last seq)
    agent_maps: dict[str, dict[str, Any]] = field(default_factory=dict)
    pending: list[tuple[str, int, Keyframe]] = field(default_factory=list)
    rendezvous: dict[int, dict[str, Any]] = field(default_factory=dict)  # id -> RendezvousObs record


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
        self._upgrade()
        self.conn.commit()

    def _upgrade(self) -> None:
        """Stores written before missions: their agent maps and seqs belong to the mission ``legacy``, the
        mission an outbox written before missions resumes as (``hivemap.client.outbox``)."""
        cols = {r[1] for r in self.conn.execute("PRAGMA table_info(server_agent_maps)")}
        if "mission" not in cols:
            self.conn.execute(
                f"ALTER TABLE server_agent_maps ADD COLUMN mission TEXT NOT NULL DEFAULT '{LEGACY_MISSION}'"
            )
            self.conn.execute("ALTER TABLE server_agent_maps ADD COLUMN client_session INTEGER")
            self.conn.execute("UPDATE server_agent_maps SET client_session = session")
            self.conn.execute(
                "INSERT OR IGNORE INTO server_missions (agent_id, mission, last_seq) "
                f"SELECT agent_id, '{LEGACY_MISSION}', last_seq FROM server_agents"
            )

    # -- transactions (driven by the writer) ---------------------------------------------------------
    def commit(self) -> None:
        self.conn.commit()

    def rollback(self) -> None:
        self.conn.rollback()
        self.maps.forget_caches()

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

    def put_mission(self, agent_id: str, mission: str) -> None:
        self.conn.execute(
            "INSERT OR IGNORE INTO server_missions (agent_id, mission) VALUES (?, ?)", (agent_id, mission)
        )

    def set_last_seq(self, agent_id: str, mission: str, seq: int) -> None:
        self.conn.execute(
            "UPDATE server_missions SET last_seq = MAX(last_seq, ?) WHERE agent_id = ? AND mission = ?",
            (int(seq), agent_id, mission),
        )

    def put_agent_map(self, row: tuple[str, str, int, np.ndarray, str, int]) -> None:
        """``row``: ``AgentMap.row()`` (folded id, agent id, session, global_from_vio, mission, client
        session)."""
        folded, agent_id, session, global_from_vio, mission, client_session = row
        blob = np.ascontiguousarray(global_from_vio, dtype="<f8").tobytes()
        self.conn.execute(
            "INSERT OR REPLACE INTO server_agent_maps "
            "(folded, agent_id, session, global_from_vio, mission, client_session) VALUES (?, ?, ?, ?, ?, ?)",
            (folded, agent_id, int(session), blob, mission, int(client_session)),
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
        for (record,) in self.conn.execute("SELECT record FROM server_agents"):
            out.agents.append(json.loads(record))
        for agent_id, mission, last_seq in self.conn.execute(
            "SELECT agent_id, mission, last_seq FROM server_missions"
        ):
            out.missions.append((agent_id, mission, int(last_seq)))
        for folded, agent_id, session, blob, mission, client_session in self.conn.execute(
            "SELECT folded, agent_id, session, global_from_vio, mission, client_session "
            "FROM server_agent_maps"
        ):
            out.agent_maps[folded] = {
                "agent_id": agent_id,
                "session": int(session),
                "mission": mission,
                "client_session": int(session if client_session is None else client_session),
                "global_from_vio": np.frombuffer(blob, dtype="<f8").reshape(4, 4).copy(),
            }
        for folded, kf_id, frame in self.conn.execute("SELECT folded, kf_id, frame FROM server_pending"):
            _, msg = decode(bytes(frame))
            if isinstance(msg, Keyframe):
                out.pending.append((folded, int(kf_id), msg))
        out.rendezvous = self.maps.load_rendezvous()
        return out
