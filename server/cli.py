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
) -> None:
    """Run the server: WebSocket ingest at /ws, REST inspection, viewer at /viewer/. Env: HIVEMAP_*."""
    import uvicorn

    from hivemap.server.app import create_app, uvicorn_config_kwargs
    from hivemap.server.settings import load_settings

    settings = load_settings(config, host=host, port=port, data_dir=data_dir)
    if not settings.tokens:
        typer.echo(
            "warning: no agent tokens configured ([tokens] in --config): every agent is refused", err=True
        )
    uvicorn.run(create_app(settings), **uvicorn_config_kwargs(settings))  # type: ignore[arg-type]
