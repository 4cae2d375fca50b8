"""`hivemap eval` sub-commands (owned by the eval package)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any

import typer

app = typer.Typer(no_args_is_help=True)


def load_reference(path: Path, sensor: str | None = None) -> Any:
    """Ground truth from a dataset agent directory (``hivemap.client.dataset``), an EuRoC
    ``state_groundtruth_estimate0/data.csv`` or a TUM file."""
    from hivemap.eval.trajectory import groundtruth_trajectory, read_tum

    if path.is_dir():
        return groundtruth_trajectory(path, sensor=sensor)
    if path.suffix == ".csv":
        from evo.tools import file_interface

        return file_interface.read_euroc_csv_trajectory(str(path))
    return read_tum(path)


@app.command("ate")
def ate_command(
    est: Annotated[
        Path, typer.Option("--est", exists=True, dir_okay=False, help="Estimated trajectory (TUM).")
    ],
    gt: Annotated[
        Path,
        typer.Option("--gt", exists=True, help="Ground truth: dataset agent dir, EuRoC csv or TUM."),
    ],
    align: Annotated[str, typer.Option("--align", help="se3, sim3 or none (ENU, GNSS).")] = "se3",
    max_diff: Annotated[
        float, typer.Option("--max-diff", help="Max timestamp difference for association [s].")
    ] = 0.01,
    rpe_delta: Annotated[float, typer.Option("--rpe-delta", help="RPE distance [m].")] = 10.0,
    sensor: Annotated[
        str | None, typer.Option("--gt-sensor", help="Ground truth of this sensor (e.g. cam0), not the body.")
    ] = None,
) -> None:
    """ATE (and RPE) of one trajectory against ground truth, printed as a table."""
    from hivemap.eval.trajectory import ALIGNMENTS, ate, rpe

    if align not in ALIGNMENTS:
        raise typer.BadParameter(f"--align must be one of {', '.join(ALIGNMENTS)}")
    ref = load_reference(gt, sensor)
    traj = load_reference(est)
    a = ate(traj, ref, alignment=align, max_diff=max_diff)  # type: ignore[arg-type]
    r = rpe(traj, ref, delta=rpe_delta, unit="m", alignment=align, max_diff=max_diff)  # type: ignore[arg-type]
    length = float(ref.path_length)
    rows = [
        ("poses matched", f"{a.stats.n}"),
        ("alignment", align + (f" (scale {a.scale:.4f})" if align == "sim3" else "")),
        ("ATE RMSE [m]", f"{a.stats.rmse:.4f}"),
        ("ATE mean [m]", f"{a.stats.mean:.4f}"),
        ("ATE median [m]", f"{a.stats.median:.4f}"),
        ("ATE max [m]", f"{a.stats.max:.4f}"),
        ("ATE RMSE / path [%]", f"{100 * a.stats.rmse / length:.3f}" if length > 0 else "n/a"),
        (f"RPE trans RMSE /{rpe_delta:g} m [m]", f"{r.trans.rmse:.4f}"),
        (f"RPE rot RMSE /{rpe_delta:g} m [deg]", f"{r.rot_deg.rmse:.4f}"),
        ("GT path length [m]", f"{length:.2f}"),
    ]
    w = max(len(k) for k, _ in rows)
    typer.echo(f"{'metric':<{w}}  value")
    typer.echo(f"{'-' * w}  {'-' * 10}")
    for k, v in rows:
        typer.echo(f"{k:<{w}}  {v}")


@app.command("team")
def team_command(
    agent: Annotated[
        list[str],
        typer.Option(
            "--agent",
            help="ID=EST.tum,GT[,FRAMES.csv] per agent (GT: dataset agent dir, EuRoC csv or TUM; "
            "FRAMES: t_start,frame_id rows, the frame changes at merges). Repeat per agent.",
        ),
    ],
    align: Annotated[str, typer.Option("--align", help="se3, sim3 or none (ENU, GNSS).")] = "se3",
    max_diff: Annotated[float, typer.Option("--max-diff", help="Association tolerance [s].")] = 0.01,
    rpe_delta: Annotated[float, typer.Option("--rpe-delta", help="RPE distance [m].")] = 10.0,
) -> None:
    """Multi-agent ATE/RPE: per agent and team, frame changes at merges, inter-agent relative error."""
    from hivemap.eval.trajectory import ALIGNMENTS, AgentRun, evaluate_team, read_frame_timeline

    if align not in ALIGNMENTS:
        raise typer.BadParameter(f"--align must be one of {', '.join(ALIGNMENTS)}")
    runs = []
    for spec in agent:
        if "=" not in spec:
            raise typer.BadParameter(f"--agent {spec!r}: expected ID=EST,GT[,FRAMES]")
        aid, rest = spec.split("=", 1)
        parts = rest.split(",")
        if len(parts) not in (2, 3):
            raise typer.BadParameter(f"--agent {spec!r}: expected ID=EST,GT[,FRAMES]")
        frames = read_frame_timeline(parts[2]) if len(parts) == 3 else []
        runs.append(AgentRun(aid, load_reference(Path(parts[0])), load_reference(Path(parts[1])), frames))
    rep = evaluate_team(runs, alignment=align, max_diff=max_diff, rpe_delta=rpe_delta)  # type: ignore[arg-type]
    typer.echo(f"alignment: {align}")
    cols = ("ATE rmse", "mean", "median", "RPE t", "RPE r°", "merge t")
    header = f"{'agent':<10} {'n':>6} {cols[0]:>9} " + " ".join(f"{c:>8}" for c in cols[1:])
    typer.echo(header)
    typer.echo("-" * len(header))
    for aid, a in rep.agents.items():
        rt = f"{a.rpe.trans.rmse:8.4f}" if a.rpe else f"{'-':>8}"
        rr = f"{a.rpe.rot_deg.rmse:8.4f}" if a.rpe else f"{'-':>8}"
        mt = f"{a.merge_time:8.2f}" if a.merge_time is not None else f"{'-':>8}"
        typer.echo(
            f"{aid:<10} {a.ate.n:>6} {a.ate.rmse:9.4f} {a.ate.mean:8.4f} {a.ate.median:8.4f} {rt} {rr} {mt}"
        )
    t = rep.team
    typer.echo(f"{'team':<10} {t.n:>6} {t.rmse:9.4f} {t.mean:8.4f} {t.median:8.4f}")
    if rep.inter_agent:
        typer.echo("\ninter-agent relative pose error (same frame, simultaneous poses)")
        for e in rep.inter_agent:
            typer.echo(
                f"{e.agent_a}-{e.agent_b} [{e.frame_id}] n={e.trans.n} "
                f"trans rmse {e.trans.rmse:.4f} m, rot rmse {e.rot_deg.rmse:.4f} deg"
            )


def _world_seeds(text: str) -> list[int | None]:
    out: list[int | None] = []
    for tok in (t.strip() for t in text.split(",")):
        if not tok:
            continue
        if tok == "default":
            out.append(None)
            continue
        try:
            out.append(int(tok))
        except ValueError:
            msg = f"{tok!r} is not a seed (an integer or 'default')"
            raise typer.BadParameter(msg, param_hint="--seeds") from None
    return out


@app.command("experiment")
def experiment_command(
    scenarios: Annotated[str, typer.Option("--scenarios", help="Comma-separated scenario names.")],
    out: Annotated[Path, typer.Option("--out", help="Output dir (results/, report.md, report.html).")],
    modes: Annotated[
        str,
        typer.Option(
            "--modes",
            help="Comma-separated: single,single+gnss,denied,challenged1,challenged2; explore (live agents "
            "on the server's exploration goals) and explore1 (the first UAV alone) on request.",
        ),
    ] = "single,single+gnss,denied,challenged1,challenged2",
    data: Annotated[
        Path, typer.Option("--data", help="Rendered scenarios dir (rendered when missing).")
    ] = Path("data"),
    agents: Annotated[
        str | None, typer.Option("--agents", help="Comma-separated agent ids (default all).")
    ] = None,
    max_frames: Annotated[int | None, typer.Option("--max-frames", help="Frames per agent (tests).")] = None,
    seed: Annotated[int, typer.Option("--seed", help="Seed of the random GNSS mode.")] = 0,
    seeds: Annotated[
        str | None,
        typer.Option(
            "--seeds",
            help="World seeds, comma-separated (e.g. default,1,2,3; 'default' is the preset's own world): "
            "every scenario x mode runs on each; the report adds mean and worst per agent over them.",
        ),
    ] = None,
    no_progress: Annotated[bool, typer.Option("--no-progress", help="No progress bar.")] = False,
    start_poses: Annotated[
        str,
        typer.Option(
            "--start-poses",
            help="Co-location: the server's nominal start configuration (paper 2.4), a prior of "
            "--start-sigma-m / --start-sigma-deg: 'perturbed' (the true start poses moved by a draw of "
            "those sigmas, seeded by --seed and the world), 'none', or 'truth' (exact, explicit only).",
        ),
    ] = "perturbed",
    start_sigma_m: Annotated[
        float, typer.Option("--start-sigma-m", help="Start position sigma per axis (m).")
    ] = 0.2,
    start_sigma_deg: Annotated[
        float, typer.Option("--start-sigma-deg", help="Start orientation sigma per axis (deg).")
    ] = 5.0,
    report_only: Annotated[
        bool,
        typer.Option(
            "--report-only",
            help="Run nothing: write the report from the results already in --out (runs not done are "
            "left out of Table 8).",
        ),
    ] = False,
    report_dir: Annotated[
        Path | None,
        typer.Option("--report-dir", help="Write report.md/html/json and img/ here (default: --out)."),
    ] = None,
    server_config: Annotated[
        Path | None,
        typer.Option(
            "--server-config",
            help="A TOML file appended to every run's server config (e.g. a [backend.optimise] table), to "
            "compare back-end options on the same worlds.",
        ),
    ] = None,
    markers: Annotated[
        str,
        typer.Option(
            "--markers",
            help="'on': agents detect the marker carriers their datasets describe (issue 25); 'off':"
            " the same images, no detection. Run each into its own --out to compare.",
        ),
    ] = "on",
    explore_duration: Annotated[
        float, typer.Option("--explore-duration", min=1.0, help="explore modes: mission time, simulated s.")
    ] = 120.0,
    stream_imu_odometry: Annotated[
        bool,
        typer.Option(
            "--stream-imu-odometry/--stream-tracking",
            help="Agents stream keyframes at an IMU-only fusion of their odometry (default) or at their "
            "visual tracking (`hivemap agent --stream-tracking`); run each setting into its own --out.",
        ),
    ] = True,
    pace: Annotated[
        str,
        typer.Option(
            "--pace",
            help="How agents replay their datasets (`hivemap agent --pace`): asap (default, every frame as "
            "fast as it goes), camera (the recording's clock) or live (the recording's clock, late frames "
            "dropped). The report's real-time section gives the agents' wall time against the data's.",
        ),
    ] = "asap",
) -> None:
    """Paper Tables 5-8: run scenarios x modes (resumable) and write report.md / report.html."""
    from hivemap.eval.experiment import ExperimentOptions, run_experiment
    from hivemap.eval.startposes import StartPoseOptions

    def split(s: str) -> list[str]:
        return [x.strip() for x in s.split(",") if x.strip()]

    try:
        starts = StartPoseOptions(start_poses, start_sigma_m, start_sigma_deg, seed)
    except ValueError as exc:
        raise typer.BadParameter(str(exc), param_hint="--start-poses") from exc
    from hivemap.client.pacing import check_pace

    try:
        check_pace(pace)
    except ValueError as exc:
        raise typer.BadParameter(str(exc), param_hint="--pace") from exc
    if markers not in ("on", "off"):
        raise typer.BadParameter(f"expected 'on' or 'off', got {markers!r}", param_hint="--markers")
    opts = ExperimentOptions(
        scenarios=split(scenarios),
        modes=split(modes),
        out=out,
        data=data,
        agents=split(agents) if agents else None,
        max_frames=max_frames,
        seed=seed,
        seeds=_world_seeds(seeds) if seeds else None,
        progress=not no_progress,
        start_poses=starts,
        report_only=report_only,
        report_dir=report_dir,
        server_toml=server_config.read_text() if server_config is not None else "",
        markers=markers == "on",
        explore_duration_s=explore_duration,
        stream_imu_odometry=stream_imu_odometry,
        pace=pace,
    )
    try:
        report = run_experiment(opts)
    except (ValueError, FileNotFoundError) as exc:
        raise typer.BadParameter(str(exc)) from exc
    typer.echo(f"report: {report} (and {report.with_suffix('.html')})")
