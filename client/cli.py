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
    max_connect_attempts: Annotated[
        int,
        typer.Option(
            "--max-connect-attempts",
            min=1,
            help="Give up (exit 4) after this many consecutive failed connection attempts.",
        ),
    ] = 10,
    wait_corrections: Annotated[
        float,
        typer.Option(
            "--wait-corrections",
            min=0.0,
            help="Streaming: after the last frame, wait at most this many seconds for the server's last "
            "corrections (0: do not wait).",
        ),
    ] = 120.0,
    no_imu_factors: Annotated[
        bool,
        typer.Option(
            "--no-imu-factors",
            help="Second stage without IMU factors between keyframes (the IMU then only aligns gravity).",
        ),
    ] = False,
) -> None:
    """Run one agent on a dataset: offline (front-end + second stage) or streaming to a server.

    Streaming, SIGTERM/SIGINT stop the replay: unacknowledged messages stay in OUT/outbox.sqlite (sent
    at the next start with the same --out) and the agent exits 0. Exit 3: the server refused the agent;
    exit 4: the server could not be reached (--max-connect-attempts)."""
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
        gnss=mode, seed=seed, max_frames=max_frames, progress=not no_progress, imu_factors=not no_imu_factors,
        max_connect_attempts=max_connect_attempts, corrections_max_wait_s=wait_corrections,
    )  # fmt: skip
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
    from hivemap.client.link import LinkRefused, check_server_url
    from hivemap.client.streaming import StreamFailed, run_streaming

    if (bad := check_server_url(server or "")) is not None:
        typer.echo(f"hivemap agent: --server: {bad}", err=True)  # one line, not a usage box
        raise typer.Exit(2)
    try:
        summary = run_streaming(dataset, out_dir, server or "", agent_id, token, options)
    except StreamFailed as exc:
        # one line: what failed, and what is still waiting to be sent
        typer.echo(
            f"hivemap agent: {exc}; {exc.unsent} messages unsent in {exc.outbox} (kept for the next start)",
            err=True,
        )
        raise typer.Exit(3 if isinstance(exc.__cause__, LinkRefused) else 4) from exc
    stopped = f"stopped by {summary.stopped_by} after" if summary.stopped_by else "streamed"
    typer.echo(
        f"agent {summary.agent_id}: {stopped} {summary.keyframes} keyframes of {summary.frames} frames to "
        f"{server}, {summary.tracking_losses} tracking losses, {summary.unsent} messages unsent "
        f"in {out_dir / 'outbox.sqlite'} -> {out_dir}"
    )
