"""The processes of an experiment run: the server (config, start, health, state) and the agents' clean
environment, started as ``python -m hivemap.cli.main`` subprocesses on free local ports."""

from __future__ import annotations

import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

from hivemap.eval.startposes import start_poses_toml

HIVEMAP = [sys.executable, "-m", "hivemap.cli.main"]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def clean_env() -> dict[str, str]:
    return {k: v for k, v in os.environ.items() if not k.startswith("HIVEMAP_")}


def wait_health(url: str, proc: subprocess.Popen[bytes], timeout: float = 300.0) -> None:
    """Wait until the server at ``url`` answers healthy. A server that exits fails at once; one that is
    alive gets ``timeout`` seconds, as its imports and store load can take minutes on a loaded machine."""
    import httpx

    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise RuntimeError(f"server exited with code {proc.returncode}")
        try:
            r = httpx.get(url + "/health", timeout=1.0)
            # "loading": the HTTP server is up but the store is still loading (agents would be told to retry)
            if r.status_code == 200 and r.json().get("status") != "loading":
                return
        except httpx.HTTPError:
            pass
        time.sleep(0.2)
    raise RuntimeError(f"server at {url} did not become healthy within {timeout:.0f} s")


def stop(proc: subprocess.Popen[bytes], timeout: float = 15.0) -> None:
    if proc.poll() is None:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(timeout)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


# The server keeps this many events; the runner reads them all (one /events request allows 100k). The
# default 10k ring buffer lost the first 3-18 % of the events of a 4-agent factory run (placerec_candidate
# events dominate), and with them the start merges and early recognitions of Tables 6-7.
EXPERIMENT_EVENT_BUFFER = 100_000


def write_server_config(
    path: Path,
    tokens: dict[str, str],
    start_table: dict[str, Any] | None = None,
    event_buffer: int | None = None,
    extra: str = "",
) -> None:
    """A server TOML config: one token per agent, the start configuration (:mod:`.startposes`) and the
    ``extra`` TOML tables."""
    path.write_text(
        ("" if event_buffer is None else f"event_buffer = {int(event_buffer)}\n")
        + "[tokens]\n"
        + "".join(f'{a} = "{t}"\n' for a, t in tokens.items())
        + (start_poses_toml(start_table) if start_table else "")
        + ("\n" + extra if extra else "")
    )


def git_revision() -> str:
    try:
        root = Path(__file__).resolve().parents[1]
        rev = subprocess.run(
            ["git", "-C", str(root), "rev-parse", "HEAD"], capture_output=True, text=True, check=True
        ).stdout.strip()
        dirty = subprocess.run(
            ["git", "-C", str(root), "status", "--porcelain", "--untracked-files=no"],
            capture_output=True,
            text=True,
        ).stdout.strip()
        return rev + ("+dirty" if dirty else "")
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def versions() -> dict[str, str]:
    from importlib import metadata

    out = {"python": sys.version.split()[0]}
    for pkg in ("hivemap", "numpy", "gtsam", "pycolmap", "evo", "opencv-python-headless"):
        try:
            out[pkg] = metadata.version(pkg)
        except metadata.PackageNotFoundError:
            out[pkg] = "not installed"
    return out


def start_server(
    work: Path, tokens: dict[str, str], start_table: dict[str, Any] | None, extra: str
) -> tuple[str, str, subprocess.Popen[bytes], Any]:
    """A fresh server for one run in ``work/server`` (its config, data and log there), on a free local
    port: (REST url, agents' WebSocket url, its process, its open log file, to close when it stops)."""
    port = free_port()
    sdir = work / "server"
    shutil.rmtree(sdir, ignore_errors=True)
    sdir.mkdir(parents=True)
    cfg = sdir / "server.toml"
    write_server_config(cfg, tokens, start_table, event_buffer=EXPERIMENT_EVENT_BUFFER, extra=extra)
    slog = open(sdir / "server.log", "wb")  # noqa: SIM115
    server = subprocess.Popen(
        [*HIVEMAP, "server", "--host", "127.0.0.1", "--port", str(port),
         "--data-dir", str(sdir / "data"), "--config", str(cfg)],
        stdout=slog, stderr=subprocess.STDOUT, env=clean_env(),
    )  # fmt: skip
    return f"http://127.0.0.1:{port}", f"ws://127.0.0.1:{port}/ws", server, slog


def server_state(url: str) -> tuple[dict[str, Any], list[Any], list[Any]]:
    """The server's agents (by id), all its events and its maps, as a finished run is read."""
    import httpx

    agents = {a["agent_id"]: a for a in httpx.get(url + "/agents", timeout=30).json()["agents"]}
    query = {"limit": EXPERIMENT_EVENT_BUFFER}
    events = httpx.get(url + "/events", params=query, timeout=30).json()["events"]
    maps = httpx.get(url + "/maps", timeout=30).json()["maps"]
    return agents, events, maps
