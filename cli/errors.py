"""Errors a person can read: the mistakes users make (a wrong dataset folder, a corrupt file, a bad TOML
setting, an unreachable server) end the command with one line naming the file or field, not a
traceback. ``hivemap -v ...`` prints the traceback too.

``one_line(exc)`` knows these errors; anything else is a bug and keeps its traceback.
"""

from __future__ import annotations

import tomllib
from pathlib import Path

# Exit code of a known input/configuration error (2, as for a command-line usage error).
EXIT_INPUT = 2


class ConfigError(Exception):
    """A configuration file that cannot be used; the message names the file and the field."""

    def __init__(self, path: Path | str | None, message: str) -> None:
        self.path = None if path is None else Path(path)
        super().__init__(message if path is None else f"{path}: {message}")


def config_error(path: Path | str | None, exc: Exception) -> ConfigError:
    """A ``ConfigError`` from a TOML syntax error or a pydantic validation error (first bad field)."""
    if isinstance(exc, tomllib.TOMLDecodeError):
        return ConfigError(path, f"invalid TOML: {exc}")
    errors = getattr(exc, "errors", None)
    if callable(errors):
        items = errors()
        if items:
            first = items[0]
            field = ".".join(str(p) for p in first.get("loc", ())) or "(root)"
            more = f" (and {len(items) - 1} more)" if len(items) > 1 else ""
            msg = str(first.get("msg", "invalid")).removeprefix("Value error, ")
            if msg.startswith("unknown key"):  # the back-end's options name the whole key themselves
                return ConfigError(path, f"{msg}{more}")
            return ConfigError(path, f"field {field!r}: {msg}{more}")
    return ConfigError(path, str(exc))


def one_line(exc: BaseException) -> str | None:
    """The one-line message of a known error, or None for an unexpected one."""
    from hivemap.client.dataset import DatasetError
    from hivemap.maps.markers import LayoutError

    known: tuple[type[BaseException], ...] = (DatasetError, ConfigError, LayoutError)
    try:
        from hivemap.client.link import LinkFailed, LinkRefused
        from hivemap.client.outbox import OutboxError

        known += (LinkFailed, LinkRefused, OutboxError)
    except ImportError:  # the client's link dependencies are optional for the other commands
        pass
    if isinstance(exc, known):
        return _first_line(str(exc)) or type(exc).__name__
    if isinstance(exc, tomllib.TOMLDecodeError):
        return f"invalid TOML: {_first_line(str(exc))}"
    if isinstance(exc, FileNotFoundError | PermissionError | IsADirectoryError | NotADirectoryError):
        where = f"{exc.filename}: " if exc.filename else ""
        return f"{where}{exc.strerror or exc}"
    return None


def _first_line(text: str) -> str:
    return text.strip().splitlines()[0] if text.strip() else ""
