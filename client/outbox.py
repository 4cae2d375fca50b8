"""The agent's durable outbox: every message is stored (with its seq) before it is sent and kept after the
server acknowledged it, so nothing the front-end produced is ever lost and seqs never repeat. Survives agent
crashes (SQLite, synchronous FULL).

An outbox is one *mission* (DESIGN.md "Protocol v1"): a UUID created with the outbox and sent in every
hello; its seqs count 1, 2, 3, ... An agent that restarts on the same outbox resumes the mission and starts
its front-end in a new session (``next_session``), so the restarted map never collides with what the
earlier process sent. Acknowledged frames stay as the mission's record: a server that does not know the
mission (it lost its data) gets all of them again (:meth:`Outbox.reopen_after`).
"""

from __future__ import annotations

import logging
import sqlite3
import threading
import time
import uuid
from collections.abc import Iterator
from pathlib import Path

from hivemap.protocol import Message, encode

log = logging.getLogger(__name__)
SCHEMA_VERSION = 2


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
        self._db.execute(
            "CREATE TABLE IF NOT EXISTS outbox (seq INTEGER PRIMARY KEY, frame BLOB NOT NULL, "
            "acked INTEGER NOT NULL DEFAULT 0)"
        )
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
                        ("mission", uuid.uuid4().hex),
                        ("last_acked", "0"),
                        ("last_seq", "0"),
                        ("next_session", "0"),
                        ("finished", "0"),
                    ],
                )
                meta = dict(self._db.execute("SELECT key, value FROM meta").fetchall())
            elif meta.get("schema") == "1":
                meta = self._upgrade_v1(meta)
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
        self.mission: str = meta["mission"]
        self._last_seq = int(meta["last_seq"])
        self._last_acked = int(meta["last_acked"])
        self._next_session = int(meta["next_session"])
        self._finished = meta["finished"] == "1"

    def _upgrade_v1(self, meta: dict[str, str]) -> dict[str, str]:
        """A v1 outbox (acked frames deleted, no mission id): it resumes as mission ``legacy``, the one a
        server upgraded from before missions files that agent's data under. v1 did not record the sessions
        its front-ends used, so the next one starts well above any they could have reached."""
        self._db.execute("ALTER TABLE outbox ADD COLUMN acked INTEGER NOT NULL DEFAULT 0")
        new = {"schema": str(SCHEMA_VERSION), "mission": "legacy", "next_session": "1000", "finished": "0"}
        self._db.executemany("INSERT OR REPLACE INTO meta VALUES (?, ?)", list(new.items()))
        return {**meta, **new}

    def _set_meta(self, key: str, value: object) -> None:
        self._db.execute("UPDATE meta SET value = ? WHERE key = ?", (str(value), key))

    @property
    def finished(self) -> bool:
        """True once :meth:`finish` was called: the mission ended with everything acknowledged."""
        return self._finished

    def start_session(self) -> int:
        """The front-end session a new process on this outbox starts with (0, then 1, 2, ... on each
        restart): the sessions an earlier process of this mission used are never reused."""
        with self._lock:
            session = self._next_session
            self._next_session += 1
            self._db.execute("BEGIN")
            self._set_meta("next_session", self._next_session)
            self._db.execute("COMMIT")
            return session

    def reserve_sessions(self, last: int) -> None:
        """Sessions up to ``last`` are in use by this process (a tracking loss started a new one)."""
        with self._lock:
            if last + 1 > self._next_session:
                self._next_session = last + 1
                self._db.execute("BEGIN")
                self._set_meta("next_session", self._next_session)
                self._db.execute("COMMIT")

    def finish(self) -> bool:
        """Mark the mission ended if the server acknowledged everything; True if it was marked."""
        with self._lock:
            unacked = int(self._db.execute("SELECT COUNT(*) FROM outbox WHERE acked = 0").fetchone()[0])
            if unacked:
                return False
            self._db.execute("BEGIN")
            self._set_meta("finished", "1")
            self._db.execute("COMMIT")
            self._finished = True
            return True

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
            if self._finished:
                raise OutboxError(f"{self.path}: mission {self.mission} has ended; start a new outbox")
            seq = self._last_seq + 1
            frame = encode(msg, seq)
            self._db.execute("BEGIN")
            self._db.execute("INSERT INTO outbox (seq, frame) VALUES (?, ?)", (seq, frame))
            self._set_meta("last_seq", seq)
            self._db.execute("COMMIT")
            self._last_seq = seq
            return seq

    def ack(self, seq: int) -> None:
        """The server stored ``seq``: it is not sent again (the frame stays as the mission's record)."""
        with self._lock:
            self._db.execute("BEGIN")
            self._db.execute("UPDATE outbox SET acked = 1 WHERE seq = ?", (seq,))
            if seq > self._last_acked:
                self._last_acked = seq
                self._set_meta("last_acked", seq)
            self._db.execute("COMMIT")

    def ack_through(self, last_seq: int) -> None:
        """The server stored everything up to ``last_seq`` (a welcome)."""
        with self._lock:
            if last_seq > self._last_seq:
                log.warning(
                    "server reports seq %d stored but this outbox only assigned %d (was %s reset?)",
                    last_seq,
                    self._last_seq,
                    self.path,
                )
            self._db.execute("BEGIN")
            self._db.execute("UPDATE outbox SET acked = 1 WHERE seq <= ?", (last_seq,))
            self._last_acked = max(self._last_acked, last_seq)
            self._set_meta("last_acked", self._last_acked)
            self._db.execute("COMMIT")

    def reopen_after(self, last_seq: int) -> int:
        """The server has nothing of this mission after ``last_seq`` (0: nothing at all): every kept frame
        after it is sent again. Returns how many frames that re-opened."""
        with self._lock:
            self._db.execute("BEGIN")
            n = self._db.execute(
                "UPDATE outbox SET acked = 0 WHERE seq > ? AND acked = 1", (last_seq,)
            ).rowcount
            self._last_acked = min(self._last_acked, last_seq)
            self._set_meta("last_acked", self._last_acked)
            self._set_meta("finished", "0")
            self._finished = False
            self._db.execute("COMMIT")
            return int(n)

    def pending(self, after: int = 0, limit: int = 256) -> list[tuple[int, bytes]]:
        """Unacknowledged frames with seq > ``after``, in seq order."""
        with self._lock:
            rows = self._db.execute(
                "SELECT seq, frame FROM outbox WHERE seq > ? AND acked = 0 ORDER BY seq LIMIT ?",
                (after, limit),
            ).fetchall()
        return [(int(s), bytes(f)) for s, f in rows]

    def frames(self) -> Iterator[tuple[int, bytes, bool]]:
        """Every frame of the mission (seq, frame, acknowledged), in seq order: the agent's own record."""
        with self._lock:
            rows = self._db.execute("SELECT seq, frame, acked FROM outbox ORDER BY seq").fetchall()
        for seq, frame, acked in rows:
            yield int(seq), bytes(frame), bool(acked)

    def __len__(self) -> int:
        """Messages not yet acknowledged by the server (still to send)."""
        with self._lock:
            return int(self._db.execute("SELECT COUNT(*) FROM outbox WHERE acked = 0").fetchone()[0])

    def close(self) -> None:
        with self._lock:
            self._db.close()


def open_mission_outbox(out_dir: str | Path, agent_id: str, name: str = "outbox.sqlite") -> Outbox:
    """The outbox a new run of an agent writes to in ``out_dir``: the existing one while its mission is
    unfinished (the run resumes it in a new session), else a new mission in a fresh outbox; the ended
    mission's file is kept beside it as ``outbox-<mission>.sqlite``."""
    path = Path(out_dir) / name
    box = Outbox(path, agent_id)
    if not box.finished:
        return box
    box.close()
    archived = path.with_name(f"{path.stem}-{box.mission}{path.suffix}")
    for suffix in ("", "-wal", "-shm"):
        src = Path(str(path) + suffix)
        if src.exists():
            src.replace(Path(str(archived) + suffix))
    log.info("mission %s of %s ended; its outbox is kept as %s", box.mission, agent_id, archived)
    return Outbox(path, agent_id)
