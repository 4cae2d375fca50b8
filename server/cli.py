"""`hivemap server` (owned by the server package)."""

from __future__ import annotations

import typer


def server_command() -> None:
    """Run the server. Not built yet."""
    typer.echo("hivemap server: not implemented yet", err=True)
    raise typer.Exit(2)
