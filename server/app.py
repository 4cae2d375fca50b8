"""The FastAPI application factory."""

from __future__ import annotations

import asyncio
import contextlib
import importlib
import logging
import os
import signal
from collections.abc import AsyncIterator, Callable, Sequence
from contextlib import asynccontextmanager
from pathlib import Path

from fastapi import FastAPI, Request
from fastapi.responses import JSONResponse
from fastapi.staticfiles import StaticFiles

from hivemap import __version__
from hivemap.server.api import router
from hivemap.server.core import HiveServer
from hivemap.server.docs import install_offline_docs
from hivemap.server.settings import ServerSettings
from hivemap.server.views import NotFound
from hivemap.server.ws import agent_endpoint

logger = logging.getLogger(__name__)

STATIC_DIR = Path(__file__).parent / "static"


def create_app(
    settings: ServerSettings | None = None, extensions: Sequence[Callable[[HiveServer], None]] | None = None
) -> FastAPI:
    """Build the app; its :class:`HiveServer` (``app.state.hive``) starts and stops with the lifespan.

    ``extensions``: callables ``(server) -> None`` that install themselves (observers, hooks). Default: the
    collaboration back-end's ``hivemap.server.backend.install`` when that module exists and
    ``settings.backend`` is on.
    """
    settings = settings or ServerSettings()
    server = HiveServer(settings)
    for install in default_extensions(settings) if extensions is None else extensions:
        install(server)
    if settings.foxglove_port is not None:
        from hivemap.server.foxglove import FoxgloveOptions, installer

        installer(FoxgloveOptions(host=settings.host, port=settings.foxglove_port))(server)

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        # The store loads in the background so that HTTP answers meanwhile (/health: "loading"); a large
        # store takes tens of seconds and a silent server looks dead.
        await server.open_store()
        loading = asyncio.create_task(server.load(), name="hivemap-load")
        loading.add_done_callback(lambda task: _report_load_failure(app, task))
        try:
            yield
        finally:
            if not loading.done():
                loading.cancel()
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await loading
            await server.stop()

    app = FastAPI(
        title="hivemap server",
        version=__version__,
        description="Collaborative SLAM server: agents stream keyframes over the WebSocket `/ws` "
        "(protocol v1, msgpack); these routes inspect what the server holds.",
        lifespan=lifespan,
        docs_url=None,  # served offline below, not from a CDN
        redoc_url=None,
    )
    install_offline_docs(app)
    app.state.hive = server
    app.state.load_error = None
    app.state.settings = settings
    app.include_router(router)
    app.add_api_websocket_route("/ws", agent_endpoint)

    @app.exception_handler(NotFound)
    async def not_found(request: Request, exc: NotFound) -> JSONResponse:
        return JSONResponse({"detail": str(exc)}, status_code=404)

    if STATIC_DIR.is_dir():
        app.mount("/viewer", StaticFiles(directory=STATIC_DIR, html=True), name="viewer")
    return app


def _report_load_failure(app: FastAPI, task: asyncio.Task[None]) -> None:
    """A store that cannot be loaded is fatal: say why and shut the server down (``hivemap server`` then
    exits non-zero, seeing ``app.state.load_error``)."""
    if task.cancelled() or task.exception() is None:
        return
    app.state.load_error = task.exception()
    logger.error("loading the store failed: %s", task.exception(), exc_info=task.exception())
    os.kill(os.getpid(), signal.SIGTERM)


def default_extensions(settings: ServerSettings) -> list[Callable[[HiveServer], None]]:
    """``hivemap.server.backend.install`` if the back-end module exists (and is enabled)."""
    if not settings.backend.enabled:
        return []
    try:
        backend = importlib.import_module("hivemap.server.backend")
    except ModuleNotFoundError as exc:
        if exc.name != "hivemap.server.backend":
            raise  # the back-end exists but one of its imports is missing: say so
        return []
    install = getattr(backend, "install", None)
    if install is None:
        logger.warning("hivemap.server.backend has no install(server): back-end not started")
        return []
    return [install]


def uvicorn_config_kwargs(settings: ServerSettings) -> dict[str, object]:
    """The uvicorn options that enforce the server's limits (frame size, queue, compression, pings)."""
    return {
        "host": settings.host,
        "port": settings.port,
        "ws": "websockets-sansio",
        "ws_max_size": settings.max_frame_bytes,
        "ws_max_queue": settings.ws_max_queue,
        "ws_per_message_deflate": settings.per_message_deflate,
        "ws_ping_interval": settings.ping_interval_s,
        "ws_ping_timeout": settings.ping_interval_s,
        "log_level": settings.log_level,
        "lifespan": "on",
        "timeout_graceful_shutdown": settings.shutdown_timeout_s,
    }
