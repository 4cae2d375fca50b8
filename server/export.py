"""``hivemap export mcap``: one map of a server's store as an MCAP file with the Foxglove topics the live
server publishes (:mod:`hivemap.server.foxglove`), for Foxglove or any MCAP reader.

The store is read as the server reloads it at start-up; run it on a stopped server's ``--data-dir`` (or a
copy): the server's SQLite store has one writer. The map's merge history comes out as ``/events`` logs at
the merges' times (the live event buffer is not stored).
"""

from __future__ import annotations

import asyncio
import logging
from pathlib import Path
from typing import Annotated, Any

import typer

from hivemap.server.events import Event
from hivemap.server.foxglove import Channels, FoxgloveOptions, messages, snapshot

logger = logging.getLogger(__name__)


def merge_events(m: Any) -> list[Event]:
    """The map's stored merge history as ``merge`` events (for ``/events``)."""
    out = []
    for i, rec in enumerate(getattr(m, "merge_history", [])):
        agents = ", ".join(str(a) for a in rec.get("source_agents", []))
        msg = (
            f"map {rec.get('source')} ({agents}) merged into map {rec.get('target')}: "
            f"{rec.get('n_keyframes_moved', 0)} keyframes moved, {rec.get('n_fused', 0)} points fused"
        )
        out.append(Event(i + 1, float(rec.get("time", 0.0)), "merge", msg, None, int(m.id), dict(rec)))
    return out


async def _load(data_dir: Path) -> Any:
    from hivemap.server.core import HiveServer
    from hivemap.server.settings import ServerSettings

    server = HiveServer(ServerSettings(data_dir=data_dir, backend=False))
    await server.start()
    return server


def export_mcap(data_dir: Path, map_id: int, out: Path, options: FoxgloveOptions | None = None) -> int:
    """Write map ``map_id`` of the store in ``data_dir`` to ``out``; returns the number of messages.
    Raises ``LookupError`` naming the maps the store has when ``map_id`` is not one of them."""
    import foxglove

    options = options or FoxgloveOptions()
    if not (data_dir / "hivemap.sqlite").is_file():
        raise FileNotFoundError(2, "no hivemap store (hivemap.sqlite) here", str(data_dir))

    async def run() -> int:
        server = await _load(data_dir)
        try:
            m = server.stack.maps.get(map_id)
            if m is None:
                have = ", ".join(str(i) for i in sorted(server.stack.maps)) or "none"
                raise LookupError(f"{data_dir}: no map {map_id} in the store (maps: {have})")
            snap = snapshot(server, options, map_ids=[map_id])
            snap.events.extend(merge_events(m))
            stamp = max([float(t.times[-1]) for t in snap.tracks] or [0.0])
            ctx = foxglove.Context()
            writer = foxglove.open_mcap(out, allow_overwrite=True, context=ctx)
            channels = Channels(ctx)
            msgs = messages(snap, stamp, options)
            for topic, msg, t in msgs:
                channels.log(topic, msg, t)
            channels.close()
            writer.close()
            return len(msgs)
        finally:
            await server.stop()

    return asyncio.run(run())


export_app = typer.Typer(no_args_is_help=True, add_completion=False)


@export_app.command("mcap")
def mcap_command(
    map_id: Annotated[int, typer.Option("--map", help="Map id (see GET /maps).")],
    data_dir: Annotated[
        Path, typer.Option("--data-dir", help="The server's data dir (a stopped server's, or a copy).")
    ] = Path("hivemap-data"),
    out: Annotated[Path | None, typer.Option("--out", help="MCAP file (default map<ID>.mcap).")] = None,
    max_points: Annotated[
        int, typer.Option("--max-points", min=1, help="Map points written at most (evenly subsampled).")
    ] = 2_000_000,
) -> None:
    """Write one map (frame tree, trajectories, frustums, points, merges) as Foxglove topics to MCAP."""
    path = out if out is not None else Path(f"map{map_id}.mcap")
    try:
        n = export_mcap(data_dir, map_id, path, FoxgloveOptions(max_points=max_points))
    except LookupError as exc:
        typer.echo(f"hivemap export: {exc}", err=True)
        raise typer.Exit(2) from exc
    typer.echo(f"map {map_id}: {n} messages -> {path}")
