"""Did a team run keep up with its recording (issue 23)? The agents' wall time against the data's
duration, and what pacing cost each agent (frames dropped, how late it took them)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from hivemap.eval.trajectory import read_tum


def _span_s(tum: Path) -> float | None:
    """First to last timestamp of a TUM file [s] (the frames the agent tracked), None when it has none."""
    if not tum.exists() or tum.stat().st_size == 0:
        return None
    stamps = read_tum(tum).timestamps
    return float(stamps[-1] - stamps[0]) if len(stamps) > 1 else None


def realtime(results: dict[str, Any], outs: dict[str, Path], pace: str) -> dict[str, Any]:
    """``results``: agent id -> its AgentResult (start/end wall times, ``run`` = its run.json);
    ``outs``: agent id -> its output dir. The wall time runs from the first agent's start to the last
    one's end, so it includes each agent's end-of-mission wait for the server; the data's duration is
    the longest span an agent tracked."""
    starts = [r.start_wall for r in results.values() if r.start_wall is not None]
    ends = [r.end_wall for r in results.values() if r.end_wall is not None]
    spans = {aid: _span_s(out / "local.tum") for aid, out in outs.items()}
    data_s = max((s for s in spans.values() if s is not None), default=None)
    wall_s = max(ends) - min(starts) if starts and ends else None
    return {
        "pace": pace,
        "data_s": data_s,
        "agents_wall_s": wall_s,
        "ratio": wall_s / data_s if wall_s is not None and data_s else None,
        "agents": {
            aid: {
                "data_s": spans.get(aid),
                "wall_s": r.end_wall - r.start_wall
                if r.start_wall is not None and r.end_wall is not None
                else None,
                "frames": r.run.get("frames"),
                "frames_dropped": r.run.get("frames_dropped", 0),
                "late_max_s": r.run.get("late_max_s", 0.0),
            }
            for aid, r in results.items()
        },
    }


def realtime_section(results: dict[tuple[str, str], dict[str, Any]]) -> list[str]:
    """Markdown: per co-location run, its pace, the data's duration, the agents' wall time and their
    ratio, and per agent the frames it processed / dropped and its latest frame. Empty without such runs."""
    rows = [(s, m, d["realtime"]) for (s, m), d in results.items() if d.get("realtime")]
    if not rows:
        return []
    md = ["## Real time: the agents' wall time against the data's duration", ""]
    md.append(
        "| scenario | mode | pace | data [s] | agents' wall [s] | ratio "
        "| per agent: frames / dropped, latest [s] |"
    )
    md.append("|---|---|---|---|---|---|---|")
    for s, m, rt in rows:
        per = "; ".join(
            f"{aid} {a.get('frames')} / {a.get('frames_dropped', 0)}, {a.get('late_max_s', 0.0):.2f}"
            for aid, a in sorted(rt.get("agents", {}).items())
        )
        data, wall, ratio = (rt.get(k) for k in ("data_s", "agents_wall_s", "ratio"))
        figs = " | ".join(
            "-" if x is None else f"{x:.{nd}f}{u}"
            for x, nd, u in ((data, 1, ""), (wall, 1, ""), (ratio, 2, "x"))
        )
        md.append(f"| {s} | {m} | {rt.get('pace')} | {figs} | {per} |")
    md.append("")
    return md
