"""`hivemap sim` sub-commands (owned by the sim package).

hivemap sim list
hivemap sim render --scenario factory01|my.toml --out DIR [--seed N] [--backend auto|gl|numpy]
                   [--agents uav1,ugv] [--duration S] [--no-progress]
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

app = typer.Typer(no_args_is_help=True)


@app.command("list")
def list_scenarios() -> None:
    """List the scenario presets."""
    from hivemap.sim.scenarios import SCENARIOS

    for name, s in SCENARIOS.items():
        agents = ", ".join(
            f"{a.agent_id}({a.kind} {a.camera_pitch_deg:g}deg {a.path_length_m:g}m)" for a in s.agents
        )
        c = s.camera
        dur = "full" if s.duration_s is None else f"{s.duration_s:g}s"
        res = f"{c.width}x{c.height}@{c.rate_hz:g}Hz"
        typer.echo(f"{name:10s} {s.lighting:6s} {s.weather:5s} {res} {dur:5s} {agents}")


@app.command("render")
def render(
    out: Annotated[Path, typer.Option("--out", help="Output folder (agent folders + manifest).")],
    scenario: Annotated[
        str,
        typer.Option(
            "--scenario", "--preset", help="Preset (see `sim list`) or a scenario TOML file (see README)."
        ),
    ] = "factory01",
    seed: Annotated[
        int | None,
        typer.Option(
            help="World seed: site layout, texture placement, routes, start (default: the scenario's)."
        ),
    ] = None,
    backend: Annotated[str, typer.Option(help="Renderer: auto | gl | numpy.")] = "auto",
    agents: Annotated[str | None, typer.Option(help="Comma-separated agent ids (default: all).")] = None,
    duration: Annotated[float | None, typer.Option(help="Render only the first S seconds.")] = None,
    progress: Annotated[bool, typer.Option("--progress/--no-progress")] = True,
) -> None:
    """Render a scenario into EuRoC-format agent datasets (resumes an interrupted render)."""
    import logging

    from hivemap.sim.dataset import RenderMismatch, render_scenario
    from hivemap.sim.scenario_file import ScenarioError, resolve_scenario

    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    if backend not in ("auto", "gl", "numpy"):
        raise typer.BadParameter("--backend must be auto, gl or numpy")
    try:
        sc = resolve_scenario(scenario, seed)
    except ScenarioError as e:
        raise typer.BadParameter(str(e), param_hint="--scenario") from e
    ids = [a.strip() for a in agents.split(",") if a.strip()] if agents else None
    if ids:
        known = {a.agent_id for a in sc.agents}
        bad = [a for a in ids if a not in known]
        if bad:
            raise typer.BadParameter(f"unknown agents {bad}; {sc.name} has {sorted(known)}")
    try:
        res = render_scenario(sc, out, backend=backend, agents=ids, duration=duration, progress=progress)
    except RenderMismatch as e:
        typer.echo(f"hivemap sim render: {e}", err=True)
        raise typer.Exit(2) from e
    total = 0
    for r in res.agents:
        state = "skipped (complete)" if r.skipped else f"rendered {r.rendered} frames in {r.seconds:.1f} s"
        typer.echo(f"{r.agent_id}: {r.n_frames} stereo frames, {state}, {r.bytes / 1e6:.1f} MB")
        total += r.bytes
    typer.echo(f"{sc.name} (seed {sc.seed}) -> {res.out_dir}: {total / 1e6:.1f} MB, {res.seconds:.1f} s")
