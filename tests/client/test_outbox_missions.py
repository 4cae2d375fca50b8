"""The outbox as one mission: its id, its sessions, its record of acknowledged frames, its end."""

from __future__ import annotations

import sqlite3
from pathlib import Path

import numpy as np

from hivemap.client.outbox import Outbox, open_mission_outbox
from hivemap.protocol import MapPoints, decode, encode


def _msg(i: int) -> MapPoints:
    return MapPoints(np.array([i]), np.zeros((1, 3)), np.zeros((1, 32), np.uint8))


def test_acknowledged_frames_stay_as_the_record_and_can_be_sent_again(tmp_path: Path) -> None:
    box = Outbox(tmp_path / "o.sqlite", "uav1")
    for i in range(1, 6):
        box.put(_msg(i))
    box.ack_through(3)
    box.ack(5)
    assert len(box) == 1 and [s for s, _ in box.pending()] == [4]
    assert [(s, a) for s, _, a in box.frames()] == [(1, True), (2, True), (3, True), (4, False), (5, True)]
    assert box.reopen_after(0) == 4  # a server without the mission: everything goes again
    assert [s for s, _ in box.pending()] == [1, 2, 3, 4, 5] and box.last_acked == 0
    assert isinstance(decode(box.pending()[0][1])[1], MapPoints)


def test_sessions_of_a_resumed_mission_never_repeat(tmp_path: Path) -> None:
    box = Outbox(tmp_path / "o.sqlite", "uav1")
    mission = box.mission
    assert box.start_session() == 0
    box.reserve_sessions(2)  # a tracking loss or two in this process
    box.close()
    again = Outbox(tmp_path / "o.sqlite", "uav1")
    assert again.mission == mission and again.start_session() == 3


def test_a_finished_mission_is_archived_and_the_next_run_is_a_new_one(tmp_path: Path) -> None:
    box = open_mission_outbox(tmp_path, "uav1")
    box.put(_msg(1))
    assert not box.finish()  # not acknowledged yet: the mission stays open
    box.close()
    resumed = open_mission_outbox(tmp_path, "uav1")
    first = resumed.mission
    assert len(resumed) == 1
    resumed.ack(1)
    assert resumed.finish()
    resumed.close()
    new = open_mission_outbox(tmp_path, "uav1")
    assert new.mission != first and new.last_seq == 0 and new.start_session() == 0
    archived = Outbox(tmp_path / f"outbox-{first}.sqlite", "uav1")
    assert archived.finished and [s for s, _, _ in archived.frames()] == [1]


def test_a_version_1_outbox_resumes_as_the_legacy_mission_with_its_unsent_frames(tmp_path: Path) -> None:
    path = tmp_path / "v1.sqlite"
    db = sqlite3.connect(path)
    db.execute("CREATE TABLE meta (key TEXT PRIMARY KEY, value TEXT NOT NULL)")
    db.execute("CREATE TABLE outbox (seq INTEGER PRIMARY KEY, frame BLOB NOT NULL)")
    db.executemany(
        "INSERT INTO meta VALUES (?, ?)",
        [("schema", "1"), ("agent_id", "uav1"), ("last_acked", "7"), ("last_seq", "9")],
    )
    db.executemany("INSERT INTO outbox VALUES (?, ?)", [(8, encode(_msg(8), 8)), (9, encode(_msg(9), 9))])
    db.commit()
    db.close()
    box = Outbox(path, "uav1")
    assert box.mission == "legacy" and box.last_acked == 7 and box.last_seq == 9
    assert [s for s, _ in box.pending()] == [8, 9]
    assert box.start_session() >= 1  # v1 front-ends used session 0 (and maybe a few more)
    assert box.put(_msg(10)) == 10
