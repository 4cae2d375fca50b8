"""`hivemap agent` (owned by the client package)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer


def agent_command(
    dataset: Annotated[Path, typer.Option("--dataset", help="Agent dataset dir (EuRoC layout).")],
    out: Annotated[
        Path | None,
        typer.Option("--out", help="Output dir (default ./out/<id>)."),
    ] = None,
    offline: Annotated[bool, typer.Option("--offline", help="Run without a server.")] = False,
    gnss: Annotated[
        str, typer.Option("--gnss", help="GNSS mode: denied, every:20s, random:4 or all (paper Table 8).")
    ] = "denied",
    seed: Annotated[int, typer.Option("--seed", help="Seed of the random GNSS mode.")] = 0,
    max_frames: Annotated[int | None, typer.Option("--max-frames", help="Stop after N frames.")] = None,
    server: Annotated[
        str | None, typer.Option("--server", help="Stream to this server, e.g. ws://HOST:PORT/ws.")
    ] = None,
    agent_id: Annotated[str | None, typer.Option("--agent-id", help="Agent id (default: dataset's).")] = None,
    token: Annotated[str | None, typer.Option("--token", help="Agent token for the server.")] = None,
    no_progress: Annotated[bool, typer.Option("--no-progress", help="No progress bar.")] = False,
    no_imu_factors: Annotated[
        bool,
        typer.Option(
            "--no-imu-factors",
            help="Second stage without IMU factors between keyframes (the IMU then only aligns gravity).",
        ),
    ] = False,
) -> None:
    """Run one agent on a dataset: offline (front-end + second stage) or streaming to a server."""
    from hivemap.client.runner import RunnerOptions, parse_gnss_mode

    try:
        mode = parse_gnss_mode(gnss)
    except ValueError as exc:
        raise typer.BadParameter(str(exc), param_hint="--gnss") from exc
    if offline == (server is not None):
        raise typer.BadParameter("give exactly one of --offline or --server URL")
    if not dataset.is_dir():
        raise typer.BadParameter(f"{dataset} is not a directory", param_hint="--dataset")
    options = RunnerOptions(
        gnss=mode, seed=seed, max_frames=max_frames, progress=not no_progress, imu_factors=not no_imu_factors
    )
    out_dir = out if out is not None else Path("out") / (agent_id or dataset.name)
    if offline:
        from hivemap.client.runner import run_offline

        summary = run_offline(dataset, out_dir, options)
        typer.echo(
            f"agent {summary.agent_id}: {summary.frames} frames ({summary.tracked_frames} tracked), "
            f"{summary.keyframes} keyframes, {summary.tracking_losses} tracking losses, "
            f"GNSS {summary.gnss_used} used / {summary.gnss_rejected} rejected ({summary.gnss_mode}), "
            f"{summary.fps:.1f} frames/s -> {out_dir}"
        )
        return
    if not token:
        raise typer.BadParameter("--token is required with --server", param_hint="--token")
    from hivemap.client.link import LinkRefused
    from hivemap.client.streaming import run_streaming

    try:
        summary = run_streaming(dataset, out_dir, server or "", agent_id, token, options)
    except LinkRefused as exc:
        typer.echo(f"hivemap agent: {exc}", err=True)
        raise typer.Exit(3) from exc
    typer.echo(
        f"agent {summary.agent_id}: streamed {summary.keyframes} keyframes of {summary.frames} frames to "
        f"{server}, {summary.tracking_losses} tracking losses -> {out_dir}"
    )
