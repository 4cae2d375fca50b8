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
