"""Unit tests of the server's plain modules: settings, bandwidth windows, Prometheus text, group commit."""

from __future__ import annotations

import asyncio
import re
import sqlite3
import threading
from pathlib import Path

import pytest

from hivemap.server.bandwidth import Bandwidth, RateMeter
from hivemap.server.events import EventLog
from hivemap.server.metrics import Histogram, MetricsWriter
from hivemap.server.settings import load_settings
from hivemap.server.writer import StoreWriter


def test_settings_precedence_toml_env_cli(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    cfg = tmp_path / "s.toml"
    cfg.write_text('port = 1111\nhost = "0.0.0.0"\ncommit_interval_ms = 2\n[tokens]\nuav1 = "a"\nug = "b"\n')
    s = load_settings(cfg)
    assert (s.port, s.host, s.commit_interval_ms, s.tokens) == (1111, "0.0.0.0", 2, {"uav1": "a", "ug": "b"})
    monkeypatch.setenv("HIVEMAP_PORT", "2222")
    monkeypatch.setenv("HIVEMAP_TOKENS", '{"x": "y"}')
    s = load_settings(cfg)
    assert (s.port, s.tokens, s.host) == (2222, {"x": "y"}, "0.0.0.0")  # env beats the file
    s = load_settings(cfg, port=3333, data_dir=None)
    assert s.port == 3333  # the CLI beats env; None means "not given"
    cfg.write_text("no_such_setting = 1\n")
    with pytest.raises(ValueError, match="no_such_setting"):
        load_settings(cfg)


def test_rate_meter_average_and_peak_over_1s_windows() -> None:
    m = RateMeter()
    # 1000 B at t=10.1 and 10.9 (same window: 2000 B), 500 B at 11.5, 3000 B at 14.2.
    for nbytes, t in [(1000, 10.1), (1000, 10.9), (500, 11.5), (3000, 14.2)]:
        m.add(nbytes, t)
    assert m.total == 5500
    assert m.peak_rate() == 3000.0  # the window in progress counts
    assert m.peak == 2000.0  # completed windows only
    assert m.average() == pytest.approx(5500 / 5)  # windows 10, 11, 12, 13, 14
    clock = iter([0.0, 0.2, 5.0]).__next__
    bw = Bandwidth(clock=clock)
    bw.received(100)
    bw.received(100)
    bw.sent(7)
    s = bw.summary()
    assert (s["up_total"], s["up_peak"], s["down_total"]) == (200.0, 200.0, 7.0)
    assert s["up_avg"] == 200.0  # active for 0.2 s, within one 1 s window


def test_prometheus_text_format() -> None:
    w = MetricsWriter()
    w.family("hm_total", "counter", "Things.", [({"agent": 'a"b\\c'}, 3), (None, 1.5)])
    h = Histogram((0.01, 0.1))
    for v in (0.005, 0.05, 0.05, 3.0):
        h.observe(v)
    w.histogram("hm_lat_seconds", "Latency.", h)
    text = w.render()
    assert text.endswith("\n")
    lines = text.splitlines()
    assert lines[:2] == ["# HELP hm_total Things.", "# TYPE hm_total counter"]
    assert 'hm_total{agent="a\\"b\\\\c"} 3' in lines
    assert "hm_total 1.5" in lines
    assert 'hm_lat_seconds_bucket{le="0.01"} 1' in lines
    assert 'hm_lat_seconds_bucket{le="0.1"} 3' in lines
    assert 'hm_lat_seconds_bucket{le="+Inf"} 4' in lines
    assert "hm_lat_seconds_count 4" in lines
    sample = re.compile(r'^[a-zA-Z_:][a-zA-Z0-9_:]*(\{([a-zA-Z_]\w*="([^"\\]|\\.)*",?)*\})? \S+$')
    for line in lines:
        assert line.startswith("# ") or sample.match(line), line
    assert h.quantile(0.5) == 0.1


def test_event_log_ring_buffer_and_since() -> None:
    log = EventLog(capacity=5)
    for i in range(8):
        log.add("merge" if i % 2 else "error", f"e{i}")
    evs = log.since(0)
    assert [e.message for e in evs] == ["e3", "e4", "e5", "e6", "e7"]
    assert [e.message for e in log.since(evs[2].id)] == ["e6", "e7"]
    assert [e.message for e in log.since(0, kind="merge")] == ["e3", "e5", "e7"]
    assert [e.message for e in log.since(0, limit=2)] == ["e6", "e7"]
    assert log.counts == {"error": 4, "merge": 4}


class _Sqlite:
    def __init__(self, path: Path) -> None:
        self.conn = sqlite3.connect(path)
        self.conn.execute("CREATE TABLE IF NOT EXISTS t (v INTEGER)")
        self.thread = threading.get_ident()

    def commit(self) -> None:
        self.conn.commit()

    def rollback(self) -> None:
        self.conn.rollback()

    def close(self) -> None:
        self.conn.close()


def test_writer_acks_only_after_commit_and_batches(tmp_path: Path) -> None:
    db = tmp_path / "w.sqlite"

    async def main() -> tuple[list[int], int, int]:
        loop = asyncio.get_running_loop()
        writer: StoreWriter[_Sqlite] = StoreWriter(lambda: _Sqlite(db), loop, min_commit_interval=0.01)
        store = await writer.start()
        assert store.thread != threading.get_ident(), "the store is opened in the writer thread"
        acked: list[int] = []
        done = asyncio.Event()

        def make_done(i: int):  # noqa: ANN202
            def cb(exc: BaseException | None) -> None:
                assert exc is None
                # Every acked row is already visible to another connection: it is committed.
                with sqlite3.connect(db) as other:
                    n = other.execute("SELECT COUNT(*) FROM t WHERE v = ?", (i,)).fetchone()[0]
                assert n == 1
                acked.append(i)
                if len(acked) == 200:
                    done.set()

            return cb

        for i in range(200):
            writer.submit(lambda s, i=i: s.conn.execute("INSERT INTO t VALUES (?)", (i,)), make_done(i))
        await asyncio.wait_for(done.wait(), 10)
        assert await writer.call(lambda s: s.conn.execute("SELECT COUNT(*) FROM t").fetchone()[0]) == 200
        with pytest.raises(ZeroDivisionError):
            await writer.call(lambda s: 1 / 0)
        await writer.stop()
        return acked, writer.commits, writer.ops

    acked, commits, ops = asyncio.run(main())
    assert acked == list(range(200)), "callbacks run in submission order"
    assert commits < 50, f"200 operations were group-committed, not one commit each ({commits})"
    assert ops == 202


def test_writer_fails_stop_after_a_failed_operation(tmp_path: Path) -> None:
    """A failed operation rolls back its whole batch and nothing later is written: an agent's stored last
    seq can never move past a message that is not on disk (the agent resends after a restart)."""
    db = tmp_path / "w.sqlite"

    async def main() -> dict[int, BaseException | None]:
        loop = asyncio.get_running_loop()
        writer: StoreWriter[_Sqlite] = StoreWriter(lambda: _Sqlite(db), loop, min_commit_interval=0.05)
        await writer.start()
        results: dict[int, BaseException | None] = {}
        finished = asyncio.Event()

        def make_done(i: int):  # noqa: ANN202
            def cb(exc: BaseException | None) -> None:
                results[i] = exc
                if len(results) == 20:
                    finished.set()

            return cb

        def op(s: _Sqlite, i: int) -> None:
            if i == 10:
                raise OSError("disk error")
            s.conn.execute("INSERT INTO t VALUES (?)", (i,))

        for i in range(10):
            writer.submit(lambda s, i=i: op(s, i), make_done(i))
        await writer.flush()
        for i in range(10, 20):
            writer.submit(lambda s, i=i: op(s, i), make_done(i))
        await asyncio.wait_for(finished.wait(), 10)
        assert writer.failed
        await writer.stop()
        return results

    results = asyncio.run(main())
    assert all(results[i] is None for i in range(10))
    assert all(results[i] is not None for i in range(10, 20))
    with sqlite3.connect(db) as other:
        stored = sorted(v for (v,) in other.execute("SELECT v FROM t"))
    assert stored == list(range(10)), stored
