"""The agent's durable outbox: every message is stored (with its seq) before it is sent, and removed
only when the server acknowledges that it stored it. Survives agent crashes (SQLite, synchronous
FULL), so nothing the front-end produced is ever lost, and seqs never repeat across restarts.
"""

from __future__ import annotations

import logging
import sqlite3
import threading
import time
from pathlib import Path

from hivemap.protocol import Message, encode

log = logging.getLogger(__name__)
SCHEMA_VERSION = 1


class OutboxError(RuntimeError):
    """The outbox file is unusable (another agent's, or a newer schema)."""


def _set_wal(db: sqlite3.Connection, timeout_s: float = 10.0) -> None:
    """``PRAGMA journal_mode=WAL``, retried: SQLite answers "database is locked" at once, without its
    busy handler, while another process is creating the same file (a restarted agent next to a reader
    of its outbox)."""
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            db.execute("PRAGMA journal_mode=WAL")
            return
        except sqlite3.OperationalError as exc:
            if "locked" not in str(exc) or time.monotonic() > deadline:
                raise
            time.sleep(0.02)


class Outbox:
    """SQLite-backed queue of encoded frames keyed by seq (1, 2, 3, ... per agent)."""

    def __init__(self, path: str | Path, agent_id: str) -> None:
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._lock = threading.Lock()
        self._db = sqlite3.connect(str(self.path), check_same_thread=False, isolation_level=None)
        _set_wal(self._db)
        self._db.execute("PRAGMA synchronous=FULL")
        self._db.execute("CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT NOT NULL)")
        self._db.execute("CREATE TABLE IF NOT EXISTS outbox (seq INTEGER PRIMARY KEY, frame BLOB NOT NULL)")
        # Check-and-create under a write lock: two processes opening a new outbox at once (a restarted
        # agent next to a reader) both saw an empty meta table and the second insert failed.
        self._db.execute("BEGIN IMMEDIATE")
        try:
            meta = dict(self._db.execute("SELECT key, value FROM meta").fetchall())
            if not meta:
                self._db.executemany(
                    "INSERT INTO meta VALUES (?, ?)",
                    [
                        ("schema", str(SCHEMA_VERSION)),
                        ("agent_id", agent_id),
                        ("last_acked", "0"),
                        ("last_seq", "0"),
                    ],
                )
                meta = dict(self._db.execute("SELECT key, value FROM meta").fetchall())
            self._db.execute("COMMIT")
        except BaseException:
            self._db.execute("ROLLBACK")
            raise
        if int(meta["schema"]) != SCHEMA_VERSION:
            raise OutboxError(
                f"{self.path}: outbox schema {meta['schema']}, this hivemap reads {SCHEMA_VERSION}"
            )
        if meta["agent_id"] != agent_id:
            raise OutboxError(f"{self.path} belongs to agent {meta['agent_id']!r}, not {agent_id!r}")
        self.agent_id = agent_id
        self._last_seq = int(meta["last_seq"])
        self._last_acked = int(meta["last_acked"])

    @property
    def last_seq(self) -> int:
        """Highest seq ever assigned."""
        return self._last_seq

    @property
    def last_acked(self) -> int:
        """Highest seq the server confirmed (acks or a welcome)."""
        return self._last_acked

    def put(self, msg: Message) -> int:
        """Assign the next seq, store the encoded frame durably, return the seq."""
        with self._lock:
            seq = self._last_seq + 1
            frame = encode(msg, seq)
            self._db.execute("BEGIN")
            self._db.execute("INSERT INTO outbox VALUES (?, ?)", (seq, frame))
            self._db.execute("UPDATE meta SET value = ? WHERE key = 'last_seq'", (str(seq),))
            self._db.execute("COMMIT")
            self._last_seq = seq
            return seq

    def ack(self, seq: int) -> None:
        """The server stored ``seq``: drop it."""
        with self._lock:
            self._db.execute("BEGIN")
            self._db.execute("DELETE FROM outbox WHERE seq = ?", (seq,))
            if seq > self._last_acked:
                self._last_acked = seq
                self._db.execute("UPDATE meta SET value = ? WHERE key = 'last_acked'", (str(seq),))
            self._db.execute("COMMIT")

    def ack_through(self, last_seq: int) -> None:
        """The server stored everything up to ``last_seq`` (a welcome): drop it all."""
        with self._lock:
            if last_seq > self._last_seq:
                log.warning(
                    "server reports seq %d stored but this outbox only assigned %d (was %s reset?)",
                    last_seq,
                    self._last_seq,
                    self.path,
                )
            self._db.execute("BEGIN")
            self._db.execute("DELETE FROM outbox WHERE seq <= ?", (last_seq,))
            self._last_acked = max(self._last_acked, last_seq)
            self._db.execute("UPDATE meta SET value = ? WHERE key = 'last_acked'", (str(self._last_acked),))
            self._db.execute("COMMIT")

    def pending(self, after: int = 0, limit: int = 256) -> list[tuple[int, bytes]]:
        """Unacknowledged frames with seq > ``after``, in seq order."""
        with self._lock:
            rows = self._db.execute(
                "SELECT seq, frame FROM outbox WHERE seq > ? ORDER BY seq LIMIT ?", (after, limit)
            ).fetchall()
        return [(int(s), bytes(f)) for s, f in rows]

    def __len__(self) -> int:
        with self._lock:
            return int(self._db.execute("SELECT COUNT(*) FROM outbox").fetchone()[0])

    def close(self) -> None:
        with self._lock:
            self._db.close()
