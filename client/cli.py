"""`hivemap agent` (owned by the client package)."""

from __future__ import annotations

import typer


def agent_command() -> None:
    """Run one agent. Not built yet: the agent front-end is work in progress."""
    typer.echo("hivemap agent: not implemented yet (front-end and link are in progress)", err=True)
    raise typer.Exit(2)
