"""Accuracy over world seeds: per scenario, mode and agent, the mean and the worst over its worlds.

Results keys name a world (``factory01`` for the preset's own seed, ``factory01-s7`` for seed 7, see
``hivemap.eval.experiment.world_key``); this groups Table 8's rows by scenario so that a claim about
accuracy is a claim over seeds, with its spread in view.
"""

from __future__ import annotations

import re
from collections import defaultdict
from typing import Any

_KEY = re.compile(r"^(?P<scenario>.+)-s(?P<seed>-?\d+)$")


def split_world(key: str) -> tuple[str, str]:
    """(scenario, world) of a results key: ``("factory01", "7")``, ``("factory01", "default")``."""
    m = _KEY.match(key)
    return (m["scenario"], m["seed"]) if m else (key, "default")


def _gain(base: float | None, x: float | None) -> float | None:
    return None if base is None or x is None or base <= 0 else (base - x) / base


def seeds_section(table8: list[dict[str, Any]]) -> list[str]:
    """Markdown: per (scenario, mode, agent) over its worlds, ATE RMSE mean / worst and the gain against
    the agent's own baseline in the same world (mean / worst). Empty when no scenario has two worlds."""
    groups: dict[tuple[str, str, str], list[dict[str, Any]]] = defaultdict(list)
    for row in table8:
        if row.get("ate_rmse") is None:
            continue
        scenario, world = split_world(row["scenario"])
        groups[(scenario, row["mode"], row["agent"])].append({**row, "world": world})
    if not any(len({r["world"] for r in rows}) > 1 for rows in groups.values()):
        return []
    md = ["## Over world seeds: ATE RMSE per agent [m], and the gain against its baseline in each world", ""]
    md.append("| scenario | mode | agent | worlds | RMSE mean | RMSE worst | gain mean | gain worst |")
    md.append("|---|---|---|---|---|---|---|---|")
    for (scenario, mode, agent), rows in sorted(groups.items()):
        rmse = [float(r["ate_rmse"]) for r in rows]
        gains = [g for r in rows if (g := _gain(r.get("baseline_rmse"), r["ate_rmse"])) is not None]
        worlds = ",".join(sorted({str(r["world"]) for r in rows}))
        gm = f"{100 * sum(gains) / len(gains):+.1f}%" if gains else "-"
        gw = f"{100 * min(gains):+.1f}%" if gains else "-"
        md.append(
            f"| {scenario} | {mode} | {agent} | {worlds} | {sum(rmse) / len(rmse):.3f} | {max(rmse):.3f} "
            f"| {gm} | {gw} |"
        )
    md.append("")
    return md
