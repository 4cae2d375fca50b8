"""``eval.processes.wait_health`` against real processes: a server that comes up late is waited for, one
that exits fails at once, one that never answers fails naming its URL and the time it was given."""

from __future__ import annotations

import subprocess
import sys
import time

import pytest

from hivemap.eval.processes import free_port, wait_health

LATE_SERVER = """
import http.server, json, sys, time
time.sleep(float(sys.argv[2]))  # slow imports on a loaded machine

class H(http.server.BaseHTTPRequestHandler):
    def do_GET(self):
        body = json.dumps({"status": "ok"}).encode()
        self.send_response(200)
        self.send_header("Content-Type", "application/json")
        self.end_headers()
        self.wfile.write(body)

    def log_message(self, *args):
        pass

http.server.HTTPServer(("127.0.0.1", int(sys.argv[1])), H).serve_forever()
"""


def _start(*args: str) -> subprocess.Popen[bytes]:
    return subprocess.Popen([sys.executable, *args])


def test_a_server_that_comes_up_late_is_waited_for() -> None:
    port = free_port()
    proc = _start("-c", LATE_SERVER, str(port), "2.0")
    try:
        t0 = time.monotonic()
        wait_health(f"http://127.0.0.1:{port}", proc, timeout=60.0)
        assert 2.0 <= time.monotonic() - t0 < 60.0
    finally:
        proc.kill()
        proc.wait()


def test_a_server_that_exits_fails_at_once_and_one_that_never_answers_names_its_wait() -> None:
    proc = _start("-c", "import sys; sys.exit(3)")
    t0 = time.monotonic()
    with pytest.raises(RuntimeError, match="exited with code 3"):
        wait_health(f"http://127.0.0.1:{free_port()}", proc, timeout=60.0)
    assert time.monotonic() - t0 < 30.0
    port = free_port()
    silent = _start("-c", "import time; time.sleep(60)")
    try:
        with pytest.raises(RuntimeError, match=rf"127\.0\.0\.1:{port} did not become healthy within 1 s"):
            wait_health(f"http://127.0.0.1:{port}", silent, timeout=1.0)
    finally:
        silent.kill()
        silent.wait()
