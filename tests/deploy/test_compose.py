"""docker/compose.yaml is valid and every service runs a real `hivemap` command with valid options.

No Docker engine runs here, so the file is validated by Debian's docker-compose (`config`), and each
service's command is parsed by the real `hivemap` CLI (click) without running it.
"""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path
from typing import Any

import pytest
import typer
import yaml
from typer.exceptions import TyperException

from hivemap.cli.main import app

ROOT = Path(__file__).resolve().parents[2]
COMPOSE = ROOT / "docker" / "compose.yaml"


def _resolved_config() -> dict:
    exe = shutil.which("docker-compose")
    assert exe, "docker-compose (Debian package docker-compose) is required; `make test` installs it"
    out = subprocess.run(
        [exe, "-f", str(COMPOSE), "config"], cwd=COMPOSE.parent, capture_output=True, text=True, check=True
    )
    return yaml.safe_load(out.stdout)


def _parse_cli(argv: list[str]) -> Any:
    """Resolve argv through the real command tree (typer's click) and parse the leaf's options.

    Raises typer's UsageError (a TyperException) on an unknown command or a bad option.
    """
    assert argv[0] == "hivemap", argv
    cmd: Any = typer.main.get_command(app)
    ctx = cmd.make_context("hivemap", list(argv[1:]), resilient_parsing=False)
    while hasattr(cmd, "resolve_command"):  # a group: descend into the sub-command
        rest = list(getattr(ctx, "_protected_args", [])) + list(ctx.args)
        name, sub, rest = cmd.resolve_command(ctx, rest)
        assert sub is not None, f"unknown sub-command in {argv}"
        cmd = sub
        ctx = cmd.make_context(name or "", list(rest), parent=ctx, resilient_parsing=False)
    return cmd


def test_compose_config_is_valid_and_has_the_services() -> None:
    cfg = _resolved_config()
    services = cfg["services"]
    assert {"server", "render", "uav1", "uav2", "uav3", "ugv"} <= set(services)
    # `docker compose up server` must start the server alone: it depends on nothing.
    assert not services["server"].get("depends_on")
    for agent in ("uav1", "uav2", "uav3", "ugv"):
        assert set(services[agent]["depends_on"]) == {"server", "render"}
    assert "hivemap-data" in cfg["volumes"]


@pytest.mark.parametrize("service", ["server", "render", "uav1", "uav2", "uav3", "ugv"])
def test_compose_commands_are_real_hivemap_commands(service: str) -> None:
    cmd = _resolved_config()["services"][service]["command"]
    leaf = _parse_cli([str(c) for c in cmd])
    assert leaf.name in {"server", "render", "agent"}


def test_cli_parser_rejects_a_bad_option() -> None:
    """The check above can fail: an unknown option is a usage error."""
    with pytest.raises(TyperException):
        _parse_cli(["hivemap", "server", "--no-such-option", "1"])


def test_compose_is_mission_safe_and_stops_cleanly() -> None:
    """Each agent's outbox (--out) is on a named volume, its own; every hivemap service gets SIGTERM via an
    init process and a grace period to close its store or outbox (issue 21)."""
    cfg = _resolved_config()
    services = cfg["services"]
    outs = set()
    for agent in ("uav1", "uav2", "uav3", "ugv"):
        svc = services[agent]
        cmd = [str(c) for c in svc["command"]]
        out = cmd[cmd.index("--out") + 1]
        mounts = [v.split(":") for v in svc["volumes"]]
        on_volume = [dst for src, dst, *_ in mounts if src in cfg["volumes"] and out.startswith(dst + "/")]
        assert on_volume, (agent, out, mounts)
        outs.add(out)
    assert len(outs) == 4  # one outbox per agent
    for name in ("server", "uav1", "uav2", "uav3", "ugv"):
        svc = services[name]
        assert svc.get("init") is True and svc.get("stop_signal", "SIGTERM") == "SIGTERM", name
        assert int(str(svc["stop_grace_period"]).rstrip("s")) >= 20, name
