"""`hivemap agent` (owned by the client package)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any

import typer


def agent_command(
    dataset: Annotated[
        Path | None,
        typer.Option(
            "--dataset",
            help="Agent dataset: a EuRoC-layout dir, a ROS 1 .bag or a ROS 2 bag dir (sqlite3/MCAP).",
        ),
    ] = None,
    sim: Annotated[
        str | None,
        typer.Option(
            "--sim",
            help="Instead of a dataset: a simulated agent SCENARIO:AGENT (e.g. factory01:uav1), with --live.",
        ),
    ] = None,
    live: Annotated[
        bool,
        typer.Option(
            "--live",
            help="--sim: render frames, IMU and GNSS on the fly while the agent moves towards the server's "
            "exploration goals, obeying its collision advisories (issue 26).",
        ),
    ] = False,
    duration: Annotated[
        float, typer.Option("--duration", min=0.0, help="--live: mission time, simulated seconds.")
    ] = 120.0,
    hold: Annotated[
        float | None,
        typer.Option("--hold", min=0.0, help="--live: standstill at the start, s (default: the scenario's)."),
    ] = None,
    backend: Annotated[str, typer.Option("--backend", help="--live: renderer, auto|gl|numpy.")] = "auto",
    out: Annotated[
        Path | None,
        typer.Option("--out", help="Output dir (default ./out/<id>)."),
    ] = None,
    offline: Annotated[bool, typer.Option("--offline", help="Run without a server.")] = False,
    gnss: Annotated[
        str, typer.Option("--gnss", help="GNSS mode: denied, every:20s, random:4 or all (paper Table 8).")
    ] = "denied",
    seed: Annotated[
        int | None,
        typer.Option(
            "--seed",
            help="Seed of the random GNSS mode; with --sim the world seed (default: the scenario's).",
        ),
    ] = None,
    max_frames: Annotated[int | None, typer.Option("--max-frames", help="Stop after N frames.")] = None,
    pace: Annotated[
        str,
        typer.Option(
            "--pace",
            help="--dataset: asap (every frame, as fast as the front-end takes them), camera (at the "
            "recording's clock, every frame however late) or live (the recording's clock; when the "
            "front-end falls behind it takes the newest frame and the older ones are dropped).",
        ),
    ] = "asap",
    server: Annotated[
        str | None, typer.Option("--server", help="Stream to this server, e.g. ws://HOST:PORT/ws.")
    ] = None,
    agent_id: Annotated[str | None, typer.Option("--agent-id", help="Agent id (default: dataset's).")] = None,
    token: Annotated[str | None, typer.Option("--token", help="Agent token for the server.")] = None,
    no_progress: Annotated[bool, typer.Option("--no-progress", help="No progress bar.")] = False,
    no_markers: Annotated[
        bool,
        typer.Option(
            "--no-markers",
            help="Send no rendezvous messages for the marker carriers the dataset's markers.yaml lists "
            "(they are still masked out of tracking).",
        ),
    ] = False,
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
            "corrections: until its back-end is through with what the team had sent by then (it stops "
            "earlier when the server makes no progress for a minute; 0: do not wait).",
        ),
    ] = 600.0,
    no_imu_factors: Annotated[
        bool,
        typer.Option(
            "--no-imu-factors",
            help="Second stage without IMU factors between keyframes (the IMU then only aligns gravity).",
        ),
    ] = False,
    stream_imu_odometry: Annotated[
        bool,
        typer.Option(
            "--stream-imu-odometry/--stream-tracking",
            help="Streaming: send keyframes at an IMU-only fusion of the odometry (default), or at the "
            "visual tracking's poses (in fog 2-5x further off; docs/decisions.md).",
        ),
    ] = True,
    calib: Annotated[
        list[Path] | None,
        typer.Option(
            "--calib",
            help="Bags: calibration, a EuRoC mav0 dir (cam0/cam1/imu0 sensor.yaml) or Kalibr yaml files "
            "(camchain, then optionally the IMU yaml; repeat --calib).",
        ),
    ] = None,
    cam0_topic: Annotated[
        str, typer.Option("--cam0-topic", help="Bags: left image topic.")
    ] = "/cam0/image_raw",
    cam1_topic: Annotated[
        str, typer.Option("--cam1-topic", help="Bags: right image topic ('' for none).")
    ] = "/cam1/image_raw",
    imu_topic: Annotated[str, typer.Option("--imu-topic", help="Bags: sensor_msgs/Imu topic.")] = "/imu0",
    gnss_topic: Annotated[
        str | None, typer.Option("--gnss-topic", help="Bags: sensor_msgs/NavSatFix topic (default: none).")
    ] = None,
) -> None:
    """Run one agent on a dataset: offline (front-end + second stage) or streaming to a server.

    Streaming, SIGTERM/SIGINT stop the replay: unacknowledged messages stay in OUT/outbox.sqlite (sent
    at the next start with the same --out) and the agent exits 0. Exit 3: the server refused the agent;
    exit 4: the server could not be reached (--max-connect-attempts)."""
    import cv2

    from hivemap.client.frontend.markers import MarkerOptions
    from hivemap.client.pacing import check_pace
    from hivemap.client.runner import RunnerOptions, parse_gnss_mode

    # One OpenCV thread: agents share the cores with each other and the server, and OpenCV's worker
    # pool spends more CPU on hand-offs than it saves in wall time (the results do not depend on it).
    cv2.setNumThreads(1)

    try:
        mode = parse_gnss_mode(gnss)
    except ValueError as exc:
        raise typer.BadParameter(str(exc), param_hint="--gnss") from exc
    if offline == (server is not None):
        raise typer.BadParameter("give exactly one of --offline or --server URL")
    if (dataset is None) == (sim is None):
        raise typer.BadParameter("give exactly one of --dataset or --sim SCENARIO:AGENT")
    if (sim is not None) != live:
        raise typer.BadParameter("--sim and --live go together (a rendered dataset replays with --dataset)")
    try:
        check_pace(pace)
    except ValueError as exc:
        raise typer.BadParameter(str(exc), param_hint="--pace") from exc
    if sim is not None and pace != "asap":
        raise typer.BadParameter("a live agent runs at its simulation's clock", param_hint="--pace")
    if sim is not None:
        _live_agent(sim, seed, duration, hold, backend, out, offline, server, agent_id, token, mode,
                    max_connect_attempts, wait_corrections, no_imu_factors, stream_imu_odometry)  # fmt: skip
        return
    assert dataset is not None
    from hivemap.client.bag import BagTopics, dataset_source

    topics = BagTopics(cam0_topic, cam1_topic or None, imu_topic, gnss_topic or None)
    source = dataset_source(dataset, calib or [], topics)  # DatasetError: one line (hivemap.cli.errors)
    options = RunnerOptions(
        gnss=mode, seed=seed or 0, max_frames=max_frames, progress=not no_progress,
        imu_factors=not no_imu_factors, max_connect_attempts=max_connect_attempts,
        corrections_max_wait_s=wait_corrections, markers=MarkerOptions(enabled=not no_markers),
        stream_imu_odometry=stream_imu_odometry, pace=pace,
    )  # fmt: skip
    out_dir = (
        out
        if out is not None
        else Path("out") / (agent_id or (dataset.stem if dataset.is_file() else dataset.name))
    )
    if offline:
        from hivemap.client.runner import run_offline

        summary = run_offline(source, out_dir, options)
        typer.echo(
            f"agent {summary.agent_id}: {summary.frames} frames ({summary.tracked_frames} tracked), "
            f"{summary.keyframes} keyframes, {summary.tracking_losses} tracking losses, "
            f"GNSS {summary.gnss_used} used / {summary.gnss_rejected} rejected ({summary.gnss_mode}), "
            f"{summary.fps:.1f} frames/s{_paced(summary)} -> {out_dir}"
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
        summary = run_streaming(source, out_dir, server or "", agent_id, token, options)
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
        f"in {out_dir / 'outbox.sqlite'}{_paced(summary)} -> {out_dir}"
    )


def _paced(summary: Any) -> str:
    """What pacing did to the replay, for the closing line (nothing at the default pace)."""
    if summary.pace == "asap":
        return ""
    late = f"at most {summary.late_max_s:.2f} s late"
    return f", {summary.pace} pace: {summary.frames_dropped} frames dropped, {late}"


def _live_agent(
    sim: str, seed: int | None, duration: float, hold: float | None, backend: str, out: Path | None,
    offline: bool, server: str | None, agent_id: str | None, token: str | None, mode: object,
    max_connect_attempts: int, wait_corrections: float, no_imu_factors: bool, stream_imu_odometry: bool,
) -> None:  # fmt: skip
    """``hivemap agent --sim SCENARIO:AGENT --live``: see :mod:`hivemap.client.live`."""
    import signal
    import threading

    from hivemap.client.runner import RunnerOptions
    from hivemap.sim.live import LiveOptions

    scenario, sep, agent = sim.rpartition(":")
    if not sep or not scenario or not agent:
        raise typer.BadParameter(
            f"expected SCENARIO:AGENT, e.g. factory01:uav1, got {sim!r}", param_hint="--sim"
        )
    if server is not None:
        from hivemap.client.link import check_server_url

        if (bad := check_server_url(server)) is not None:
            typer.echo(f"hivemap agent: --server: {bad}", err=True)
            raise typer.Exit(2)
        if not token:
            raise typer.BadParameter("--token is required with --server", param_hint="--token")
    sim_options = LiveOptions(scenario, agent, seed, duration, hold, backend)
    options = RunnerOptions(
        gnss=mode, progress=False, imu_factors=not no_imu_factors, max_connect_attempts=max_connect_attempts,
        corrections_max_wait_s=wait_corrections, stream_imu_odometry=stream_imu_odometry,
    )  # type: ignore[arg-type]  # fmt: skip
    stopping = threading.Event()
    stopped_by: list[str] = []

    def on_signal(sig: int, _frame: object) -> None:
        stopped_by.append(signal.Signals(sig).name)
        stopping.set()

    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, on_signal)
    from hivemap.client.link import LinkRefused
    from hivemap.client.live import run_live
    from hivemap.client.streaming import StreamFailed

    out_dir = out if out is not None else Path("out") / (agent_id or agent)
    try:
        summary, ls = run_live(sim_options, out_dir, None if offline else server, agent_id, token or "",
                               options, stopping)  # fmt: skip
    except KeyError as exc:  # an agent the scenario does not have
        typer.echo(f"hivemap agent: --sim: {exc.args[0]}", err=True)
        raise typer.Exit(2) from exc
    except StreamFailed as exc:
        typer.echo(f"hivemap agent: {exc}; {exc.unsent} messages unsent in {exc.outbox}", err=True)
        raise typer.Exit(3 if isinstance(exc.__cause__, LinkRefused) else 4) from exc
    why = stopped_by[0] if stopped_by else ls.stopped_by
    typer.echo(
        f"agent {summary.agent_id}: live {ls.scenario} (world seed {ls.world_seed}), {ls.frames} frames, "
        f"{ls.sim_s:.1f} s simulated, {ls.path_length_m:.1f} m, {summary.keyframes} keyframes, "
        f"{ls.advisories} advisories, {ls.goals_reached} goals reached, stopped by {why} -> {out_dir}"
    )
