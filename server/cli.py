"""`hivemap server` (owned by the server package)."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path
from typing import Annotated, Any

import typer


def preload_signal_installers() -> None:
    """Import the native libraries that install their own signal handlers, before the server installs
    its own. pycolmap installs glog's failure handler for SIGTERM at import; imported lazily by the
    back-end (after uvicorn's handlers are in place) it took SIGTERM over, so a server that had handled
    data died with a glog stack dump instead of shutting down. Imported first, uvicorn's handler wins."""
    with contextlib.suppress(ImportError):
        import pycolmap  # noqa: F401


def make_uvicorn_server(config: Any) -> Any:
    """A ``uvicorn.Server`` whose graceful shutdown on SIGTERM/SIGINT ends in a normal exit (code 0).
    Stock uvicorn re-raises the captured signal after shutting down, so the process died by SIGTERM
    (exit 143) even when every worker was stopped and the store closed."""
    import uvicorn

    class _Server(uvicorn.Server):
        @contextlib.contextmanager
        def capture_signals(self) -> Iterator[None]:
            with super().capture_signals():
                yield
                # shut down cleanly: nothing is left for the default signal action to do
                captured = getattr(self, "_captured_signals", None)
                if isinstance(captured, list):
                    captured.clear()

    return _Server(config)


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
            "--config",
            exists=True,
            dir_okay=False,
            help="TOML settings ([tokens] agent = token, ..., [quotas], see the README).",
        ),
    ] = None,
    foxglove_port: Annotated[
        int | None,
        typer.Option(
            "--foxglove-port", help="Also publish the mission on a Foxglove WebSocket on this port."
        ),
    ] = None,
    groundtruth: Annotated[
        Path | None,
        typer.Option(
            "--groundtruth",
            help="Ground truth for the viewer: a scenario folder (DIR/<agent>/mav0/...) or DIR/<agent>.tum.",
        ),
    ] = None,
    workers: Annotated[
        int | None,
        typer.Option(
            "--workers", min=0, help="Verification worker processes (default: cores less one, at least 1)."
        ),
    ] = None,
    executor: Annotated[
        str | None,
        typer.Option(
            "--executor", help="Where verification runs: local (worker processes), thread, ray (Ray tasks)."
        ),
    ] = None,
    ray_address: Annotated[
        str | None,
        typer.Option("--ray-address", help="With --executor ray: the cluster (default: a local Ray)."),
    ] = None,
    print_config: Annotated[
        bool, typer.Option("--print-config", help="Print the effective settings as TOML and exit.")
    ] = False,
) -> None:
    """Run the server: WebSocket ingest at /ws, REST inspection, viewer at /viewer/. Env: HIVEMAP_*.

    SIGTERM and SIGINT shut it down cleanly (connections closed, back-end stopped, store closed; exit 0)."""
    import tomllib

    import uvicorn
    from pydantic import ValidationError

    from hivemap.cli.errors import config_error
    from hivemap.server.app import create_app, uvicorn_config_kwargs
    from hivemap.server.backend.executor import EXECUTORS
    from hivemap.server.config_toml import settings_toml
    from hivemap.server.settings import load_settings

    try:
        settings = load_settings(
            config, host=host, port=port, data_dir=data_dir, foxglove_port=foxglove_port,
            groundtruth=groundtruth,
        )  # fmt: skip
    except (tomllib.TOMLDecodeError, ValidationError) as exc:
        raise config_error(config, exc) from exc  # one line naming the file and field
    sched = {k: v for k, v in (("workers", workers), ("executor", executor), ("ray_address", ray_address))
             if v is not None}  # fmt: skip
    if sched:
        if sched.get("executor", "local") not in EXECUTORS:
            raise typer.BadParameter(f"one of {', '.join(EXECUTORS)}", param_hint="--executor")
        b = settings.backend
        settings = settings.model_copy(
            update={"backend": replace(b, scheduler=replace(b.scheduler, **sched))}
        )
    if print_config:
        typer.echo(settings_toml(settings), nl=False)
        return
    if not settings.tokens:
        typer.echo(
            "warning: no agent tokens configured ([tokens] in --config): every agent is refused", err=True
        )
    preload_signal_installers()
    app = create_app(settings)
    server = make_uvicorn_server(uvicorn.Config(app, **uvicorn_config_kwargs(settings)))  # type: ignore[arg-type]
    server.run()
    if not server.started:
        raise typer.Exit(3)  # could not start (port in use, ...): uvicorn's own exit code
    if app.state.load_error is not None:
        typer.echo(f"hivemap server: loading the store failed: {app.state.load_error}", err=True)
        raise typer.Exit(1)
