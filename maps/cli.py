"""`hivemap vocab` sub-commands (owned by the maps package)."""

from __future__ import annotations

import typer

vocab_app = typer.Typer(no_args_is_help=True)
