"""A server killed outright (SIGKILL, out of memory) cannot shut its process pools down: its verification and
global-BA workers must end by themselves instead of waiting on their queues for ever. A real process makes
the pools (as the server does), prints its workers' pids and is killed; each worker must be gone within a
few seconds, while a plain spawned pool's worker, the control, is still there."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

CHILD = """
import concurrent.futures, multiprocessing, os, time
from hivemap.server.backend.executor import ProcessVerifier, spawn_pool

verifier = ProcessVerifier(2)
ba = spawn_pool(0.2)
control = concurrent.futures.ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn"))
pids = [pool.submit(os.getpid).result() for pool in (*verifier._pools, ba, control)]
print(" ".join(map(str, pids)), flush=True)
time.sleep(600)
"""


def _alive(pid: int) -> bool:
    """Running, not a zombie waiting to be reaped."""
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except (FileNotFoundError, ProcessLookupError):
        return False
    return state != "Z"


def test_the_workers_of_a_killed_server_end_by_themselves() -> None:
    proc = subprocess.Popen([sys.executable, "-c", CHILD], stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout is not None
        *workers, control = (int(x) for x in proc.stdout.readline().split())
        assert len(workers) == 3 and all(_alive(p) for p in (*workers, control))
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(timeout=10)
        deadline = time.monotonic() + 10.0
        while any(_alive(p) for p in workers) and time.monotonic() < deadline:
            time.sleep(0.1)
        assert not any(_alive(p) for p in workers), [p for p in workers if _alive(p)]
        # the control: a spawned worker without the watch outlives its killed parent
        assert _alive(control)
    finally:
        proc.kill()
        if "control" in locals() and _alive(control):
            os.kill(control, signal.SIGKILL)
