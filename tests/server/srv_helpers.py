"""Helpers for the server tests: a real `hivemap server` subprocess on a loopback port, PLY parsing."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import httpx
import numpy as np

TOKENS = {"uav1": "tok-uav1", "uav2": "tok-uav2", "ugv1": "tok-ugv1"}


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def write_config(path: Path, tokens: dict[str, str] = TOKENS, **extra: Any) -> Path:
    """A server TOML; the back-end is off unless ``backend=True`` (ingest tests need exact maps)."""
    extra.setdefault("backend", False)

    def toml(v: Any) -> str:
        return (
            ("true" if v else "false") if isinstance(v, bool) else f'"{v}"' if isinstance(v, str) else repr(v)
        )

    lines = [f"{k} = {toml(v)}" for k, v in extra.items()]
    lines.append("[tokens]")
    lines += [f'{a} = "{t}"' for a, t in tokens.items()]
    path.write_text("\n".join(lines) + "\n")
    return path


class ServerProcess:
    """`python -m hivemap.cli.main server ...` in a subprocess; restartable on the same port and data dir."""

    def __init__(self, data_dir: Path, config: Path, port: int | None = None) -> None:
        self.data_dir = data_dir
        self.config = config
        self.port = port or free_port()
        self.proc: subprocess.Popen[bytes] | None = None
        self.log = data_dir.parent / f"server-{self.port}.log"

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    @property
    def ws_url(self) -> str:
        return f"ws://127.0.0.1:{self.port}/ws"

    def start(self, timeout: float = 30.0, wait_loaded: bool = True) -> ServerProcess:
        """Start and wait for ``/health``; with ``wait_loaded`` until its store is loaded too (the HTTP
        server answers while the store loads, with status ``loading``)."""
        cmd = [
            sys.executable, "-m", "hivemap.cli.main", "server",
            "--host", "127.0.0.1", "--port", str(self.port),
            "--data-dir", str(self.data_dir), "--config", str(self.config),
        ]  # fmt: skip
        env = {k: v for k, v in os.environ.items() if not k.startswith("HIVEMAP_")}
        with open(self.log, "ab") as log:
            self.proc = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, env=env)
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                raise RuntimeError(
                    f"server exited with {self.proc.returncode}:\n{self.log.read_text()[-3000:]}"
                )
            try:
                r = httpx.get(self.url + "/health", timeout=1.0)
                if r.status_code == 200 and not (wait_loaded and r.json().get("status") == "loading"):
                    return self
            except httpx.HTTPError:
                pass
            time.sleep(0.1)
        raise TimeoutError(f"server did not start:\n{self.log.read_text()[-3000:]}")

    def kill(self) -> None:
        """SIGKILL: no shutdown handler runs."""
        if self.proc is not None and self.proc.poll() is None:
            self.proc.send_signal(signal.SIGKILL)
            self.proc.wait(10)

    def stop(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
            try:
                self.proc.wait(10)
            except subprocess.TimeoutExpired:
                self.kill()

    def wait_backend_idle(self, timeout: float = 90.0) -> None:
        """Until ``/health`` reports the back-end idle three polls in a row."""
        deadline = time.monotonic() + timeout
        idle = 0
        while time.monotonic() < deadline:
            idle = idle + 1 if self.json("/health").get("backend_idle") is True else 0
            if idle >= 3:
                return
            time.sleep(0.3)
        raise TimeoutError("back-end still busy")

    def alive(self) -> bool:
        return self.proc is not None and self.proc.poll() is None

    def get(self, path: str, **params: Any) -> httpx.Response:
        return httpx.get(self.url + path, params=params, timeout=10.0)

    def json(self, path: str, **params: Any) -> Any:
        r = self.get(path, **params)
        assert r.status_code == 200, (path, r.status_code, r.text)
        return r.json()


def parse_ply(data: bytes) -> tuple[list[tuple[str, str]], np.ndarray]:
    """Parse a binary little-endian PLY with one vertex element -> (properties, structured array)."""
    end = data.index(b"end_header\n") + len(b"end_header\n")
    header = data[:end].decode("ascii").splitlines()
    assert header[0] == "ply" and header[1] == "format binary_little_endian 1.0", header[:2]
    n = None
    props: list[tuple[str, str]] = []
    for line in header:
        parts = line.split()
        if parts[0] == "element":
            assert parts[1] == "vertex"
            n = int(parts[2])
        elif parts[0] == "property":
            props.append((parts[1], parts[2]))
    types = {"double": "<f8", "float": "<f4", "uint": "<u4", "int": "<i4", "uchar": "u1"}
    dtype = np.dtype([(name, types[t]) for t, name in props])
    assert n is not None
    assert len(data) - end == n * dtype.itemsize, "PLY body size does not match the vertex count"
    return props, np.frombuffer(data[end:], dtype=dtype)


def map_of(server: ServerProcess, agent_id: str) -> dict[str, Any]:
    agents = {a["agent_id"]: a for a in server.json("/agents")["agents"]}
    map_id = agents[agent_id]["map_id"]
    assert map_id is not None, agents[agent_id]
    detail: dict[str, Any] = server.json(f"/maps/{map_id}")
    return detail


def snapshot(server: ServerProcess) -> dict[str, Any]:
    """Everything observable about the stored maps: counts, keyframe poses, PLY bytes of each map."""
    out: dict[str, Any] = {"maps": server.json("/maps")["maps"]}
    for m in out["maps"]:
        out[f"kf{m['id']}"] = server.json(f"/maps/{m['id']}/keyframes", limit=10000)["keyframes"]
        out[f"ply{m['id']}"] = server.get(f"/maps/{m['id']}/points", format="ply").content
    return out


def ids(items: Iterable[dict[str, Any]], key: str = "id") -> list[int]:
    return sorted(int(i[key]) for i in items)
