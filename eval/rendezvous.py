"""Markers as an experimental condition (issue 25): when each agent joined the others' map, by what
evidence, and how well the UGV sits against the UAVs in the team map, per co-location run."""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any


def base_agent(key: str) -> str:
    """``ugv#1`` (a later session) -> ``ugv``."""
    return key.split("#", 1)[0]


def _key_agent(k: Any) -> str | None:
    """The agent (with its session suffix) of a keyframe key ``[agent, id]`` as events carry it."""
    if isinstance(k, list | tuple) and len(k) == 2 and isinstance(k[0], str):
        return k[0]
    return None


def _merge_agents(d: dict[str, Any]) -> tuple[str, str] | None:
    """The two agent sessions a merge event joined: from its detection (place recognition), its own
    query / candidate keys (a session guess), or an ``agents`` pair (a rendezvous)."""
    det = d.get("detection") or {}
    for q, c in ((det.get("query_key"), det.get("candidate_key")), (d.get("query"), d.get("candidate"))):
        a, b = _key_agent(q), _key_agent(c)
        if a and b:
            return a, b
    agents = d.get("agents")
    if isinstance(agents, list | tuple) and len(agents) == 2:
        return str(agents[0]), str(agents[1])
    return None


def merge_timeline(events: Sequence[dict[str, Any]], mission_t0: float) -> list[dict[str, Any]]:
    """Each merge that joined two groups of agent sessions, in order: mission time (s, of the query
    keyframe or observation), the two sessions, the evidence (``by``), and the agents (without session
    suffix) together after it. A merge undone later stays in the list: the question is when the agents
    first shared a map."""
    group: dict[str, set[str]] = {}
    out = []
    for e in events:
        if e.get("kind") != "merge_detail":
            continue
        d = e.get("data") or {}
        pair = _merge_agents(d)
        if pair is None:
            continue
        a, b = pair
        ga, gb = group.setdefault(a, {a}), group.setdefault(b, {b})
        if ga is gb:
            continue
        joined = ga | gb
        for x in joined:
            group[x] = joined
        t = d.get("query_t")
        out.append({
            "t": None if t is None else float(t) - mission_t0,
            "agents": [a, b],
            "by": d.get("by", ""),
            "together": sorted({base_agent(x) for x in joined}),
        })  # fmt: skip
    return out


def all_together_s(timeline: Sequence[dict[str, Any]], agents: Sequence[str]) -> float | None:
    """Mission time of the first merge after which every one of ``agents`` (some session of it) shared
    one map; None if they never did (0 for one agent)."""
    if len(set(agents)) <= 1:
        return 0.0
    for m in timeline:
        if set(agents) <= set(m["together"]):
            return m["t"]
    return None


def ugv_joined_s(timeline: Sequence[dict[str, Any]], ugv: str = "ugv") -> float | None:
    """Mission time of the first merge that put the UGV into a map with a UAV; None if it never was."""
    for m in timeline:
        if ugv in m["together"] and len(m["together"]) > 1:
            return m["t"]
    return None


def ugv_uav_pair_error(team: Sequence[dict[str, Any]], ugv: str = "ugv") -> tuple[float | None, int]:
    """RMS over the UGV-UAV pairs of their relative-position error at keyframes within the team map's
    pair tolerance (``team_by_map``'s pairs), weighted by pair counts; (None, 0) without such pairs."""
    se, n = 0.0, 0
    for t in team:
        for p in t.get("pairs") or []:
            if ugv in p["agents"] and p.get("trans_rmse") is not None and p["n"]:
                se += float(p["trans_rmse"]) ** 2 * p["n"]
                n += int(p["n"])
    return (math.sqrt(se / n) if n else None), n


def rendezvous_section(results: dict[tuple[str, str], dict[str, Any]]) -> list[str]:
    """The report's table of the markers condition per co-location run (issue 25)."""
    rows = []
    for (s, m), data in results.items():
        if "team" not in data:
            continue
        tl = data.get("merge_timeline") or []
        err, n = ugv_uav_pair_error(data.get("team") or [])
        mk = data.get("markers") or {}
        sent = sum(int((a.get("run") or {}).get("rendezvous_sent", 0)) for a in data.get("agents", []))
        kinds = [e.get("kind") for e in data.get("events", [])]
        joined = ugv_joined_s(tl)
        by = next((x["by"] for x in tl if "ugv" in x["together"] and len(x["together"]) > 1), "")
        rows.append(
            f"| {s} | {m} | {mk.get('condition', 'n/a')} | {sent} | {kinds.count('rendezvous_rejected')} | "
            f"{'never' if joined is None else f'{joined:.1f}'} | {by or '-'} | "
            f"{'-' if err is None else f'{err:.3f}'} ({n}) |"
        )
    if not rows:
        return []
    return [
        "## Markers: agents that see each other (issue 25)",
        "",
        "Markers: whether the agents detected the marker carriers in their images. Observations: rendezvous "
        "messages the agents sent. UGV joined: mission time of the merge that first put the UGV into a map "
        "with a UAV, and by what evidence. UGV-UAV error: RMS relative-position error of UGV-UAV keyframe "
        "pairs within 30 ms in the team map (pairs in brackets).",
        "",
        "| scenario | mode | markers | observations | rejected | UGV joined [s] | by | UGV-UAV error [m] |",
        "|---|---|---|---|---|---|---|---|",
        *rows,
        "",
    ]
