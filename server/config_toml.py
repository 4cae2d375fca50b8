"""The server's effective settings as TOML (``hivemap server --print-config``) and one-line messages for
invalid settings. TOML has no null: fields that are None are left out (their default is None too)."""

from __future__ import annotations

import json
import math
import re
from typing import Any

from pydantic import ValidationError

_BARE = re.compile(r"^[A-Za-z0-9_-]+$")


def _key(k: str) -> str:
    return k if _BARE.match(k) else json.dumps(k)


def _value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        if math.isnan(v):
            return "nan"
        if math.isinf(v):
            return "inf" if v > 0 else "-inf"
        return repr(v)
    if isinstance(v, str):
        return json.dumps(v, ensure_ascii=False)
    if isinstance(v, list | tuple):
        return "[" + ", ".join(_value(x) for x in v if x is not None) + "]"
    if isinstance(v, dict):  # inside an array
        return "{" + ", ".join(f"{_key(k)} = {_value(x)}" for k, x in v.items() if x is not None) + "}"
    raise TypeError(f"cannot write {type(v).__name__} as TOML")


def to_toml(data: dict[str, Any]) -> str:
    """``data`` (nested dicts of TOML-able values; None left out) as a TOML document."""
    lines: list[str] = []

    def table(d: dict[str, Any], path: list[str]) -> None:
        subs = [(k, v) for k, v in d.items() if isinstance(v, dict)]
        if path:
            if lines:
                lines.append("")
            lines.append("[" + ".".join(_key(p) for p in path) + "]")
        lines.extend(
            f"{_key(k)} = {_value(v)}" for k, v in d.items() if v is not None and not isinstance(v, dict)
        )
        for k, v in subs:
            table(v, [*path, k])

    table(data, [])
    return "\n".join(lines) + "\n"


def settings_toml(settings: Any) -> str:
    """A pydantic settings object as TOML that loads back into the same settings."""
    return to_toml(settings.model_dump(mode="json"))


def one_line_errors(exc: ValidationError) -> list[str]:
    """One line per invalid setting: where it is and why (the back-end's own messages name the key)."""
    out = []
    for err in exc.errors():
        where = ".".join(str(p) for p in err["loc"])
        msg = str(err["msg"]).removeprefix("Value error, ")
        out.append(msg if msg.startswith("unknown key") else f"{where}: {msg}")
    return out
