"""`hivemap server` (owned by the server package)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer


def server_command(
    host: Annotated[
        str | None, typer.Option("--host", help="Interface to listen on (default 127.0.0.1).")
    ] = None,
    port: Annotated[int | None, typer.Option("--port", help="TCP port (default 8765).")] = None,
    data_dir: Annotated[
        Path | None, typer.Option("--data-dir", help="Where the SQLite map store lives.")
    ] = None,
    config: Annotated[
        Path | None,
        typer.Option(
            "--config", exists=True, dir_okay=False, help="TOML settings ([tokens] agent = token, ...)."
        ),
    ] = None,
    print_config: Annotated[
        bool, typer.Option("--print-config", help="Print the effective settings as TOML and exit.")
    ] = False,
) -> None:
    """Run the server: WebSocket ingest at /ws, REST inspection, viewer at /viewer/. Env: HIVEMAP_*."""
    import uvicorn
    from pydantic import ValidationError

    from hivemap.server.app import create_app, uvicorn_config_kwargs
    from hivemap.server.config_toml import one_line_errors, settings_toml
    from hivemap.server.settings import load_settings

    try:
        settings = load_settings(config, host=host, port=port, data_dir=data_dir)
    except ValidationError as exc:
        for line in one_line_errors(exc):
            typer.echo(f"error: {line}", err=True)
        raise typer.Exit(2) from None
    if print_config:
        typer.echo(settings_toml(settings), nl=False)
        return
    if not settings.tokens:
        typer.echo(
            "warning: no agent tokens configured ([tokens] in --config): every agent is refused", err=True
        )
    uvicorn.run(create_app(settings), **uvicorn_config_kwargs(settings))  # type: ignore[arg-type]
