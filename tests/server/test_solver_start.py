"""The pose graph's process is spawned and has imported the solvers when the back-end starts, so that
the first merge's solve (at take-off) does not wait seconds for a process to start; a solver that is
off (global BA by default) gets no process."""

from __future__ import annotations

import asyncio
import os
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_backend import Server  # noqa: E402

from hivemap.server.backend.options import preset  # noqa: E402


def test_the_pose_graph_process_is_started_with_the_back_end(tmp_path: Path) -> None:
    srv = Server(tmp_path / "data", opts=preset("default"))
    try:
        be = srv.backend
        started = srv.call(lambda: set(getattr(be._pg_proc._pool, "_processes", None) or {}))
        assert len(started) == 1  # spawned by the start, before any job
        # the first solve runs in that process (no spawn on the way)
        pid = asyncio.run_coroutine_threadsafe(be._pg_proc.run(os.getpid), srv.hive.loop).result(120)
        assert pid in started and pid != os.getpid()
        assert be._ba_proc._pool is None  # global BA is off in the default preset: no process for it
    finally:
        srv.stop()
