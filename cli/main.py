"""The `hivemap` command: one sub-command per pipeline stage.

Each package owns its command in its own ``cli.py``; this module only wires them together.
Heavy imports (gtsam, pycolmap, moderngl) happen inside the commands, so ``hivemap --help`` is fast.
"""

from __future__ import annotations

import os

# One BLAS thread per process: agents and server already run their own worker threads, and
# multithreaded OpenBLAS under contention made the front-end's local BA 5x slower (measured).
# Must be set before numpy is first imported.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import logging  # noqa: E402
import sys  # noqa: E402
import traceback  # noqa: E402
from typing import Any  # noqa: E402

import typer  # noqa: E402

from hivemap import __version__  # noqa: E402
from hivemap.cli.errors import EXIT_INPUT, one_line  # noqa: E402
from hivemap.client.cli import agent_command  # noqa: E402
from hivemap.eval.cli import app as eval_app  # noqa: E402
from hivemap.maps.cli import vocab_app  # noqa: E402
from hivemap.server.cli import server_command  # noqa: E402
from hivemap.server.export import export_app  # noqa: E402
from hivemap.sim.cli import app as sim_app  # noqa: E402


class _HivemapTyper(typer.Typer):
    """Known errors (``hivemap.cli.errors.one_line``) end the command with one line on stderr and exit 2;
    with ``-v`` (DEBUG logging) the traceback comes first. Other exceptions keep Typer's traceback."""

    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        try:
            return super().__call__(*args, **kwargs)
        except Exception as exc:
            line = one_line(exc)
            if line is None:
                raise
            if logging.getLogger().isEnabledFor(logging.DEBUG):
                traceback.print_exception(exc)
            typer.echo(f"hivemap: error: {line}", err=True)
            sys.exit(EXIT_INPUT)


app = _HivemapTyper(
    name="hivemap",
    help="hivemap: collaborative visual(-inertial) SLAM for teams of UAVs and UGVs.",
    no_args_is_help=True,
    add_completion=False,
)


def _version(value: bool) -> None:
    if value:
        typer.echo(f"hivemap {__version__}")
        raise typer.Exit()


@app.callback()
def main(
    verbose: bool = typer.Option(False, "--verbose", "-v", help="Log at DEBUG level."),
    version: bool = typer.Option(
        False, "--version", callback=_version, is_eager=True, help="Print the version and exit."
    ),
) -> None:
    """Collaborative SLAM: run a server, run agents, render datasets, evaluate."""
    logging.basicConfig(
        level=logging.DEBUG if verbose else logging.INFO,
        format="%(asctime)s %(levelname)s %(agent)s%(name)s: %(message)s",
    )
    from hivemap.client.logtags import AgentTag

    for handler in logging.getLogger().handlers:
        if not any(isinstance(f, AgentTag) for f in handler.filters):
            handler.addFilter(AgentTag())  # fills %(agent)s: "[uav1] " in an agent's lines


app.command("server", help="Run the hivemap server (WebSocket ingest, back-end, REST, viewer).")(
    server_command
)
app.command(
    "agent",
    help="Run one agent: replay a dataset offline or stream it to a server, or a live simulated agent.",
)(agent_command)
app.add_typer(sim_app, name="sim", help="Render simulated multi-agent datasets.")
app.add_typer(vocab_app, name="vocab", help="Train and inspect the ORB vocabulary.")
app.add_typer(eval_app, name="eval", help="Evaluate trajectories and run the paper's experiments.")
app.add_typer(export_app, name="export", help="Export a server's maps (MCAP with Foxglove topics).")

# Plain help text: in Typer's "rich" markup mode, brackets in help strings are markup, so units such as
# "[s]" and "[tokens]" vanished from --help; the plain formatter keeps them and shows no "<bool>" for flags.
for _typer_app in (app, sim_app, vocab_app, eval_app, export_app):
    _typer_app.rich_markup_mode = None

if __name__ == "__main__":
    app()
