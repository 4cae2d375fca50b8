"""The report's Tables 6 and 7 (paper seed 003): inter-agent place recognitions per camera-angle pair,
lighting and weather, from the GNSS-denied co-location runs' events, beside the paper's figures."""

from __future__ import annotations

from pathlib import Path
from typing import Any


def _row(cols: list[str]) -> str:
    return "| " + " | ".join(cols) + " |"


PAPER_TABLE6 = {  # (camera-angle pair, lighting) -> (successful relocations, average matched pairs)
    ("25-25", "bright"): (28, 123.83), ("25-25", "somber"): (27.3, 110.0),
    ("45-45", "bright"): (27, 139.0), ("45-45", "somber"): (27, 113.0),
    ("75-75", "bright"): (28, 128.33), ("75-75", "somber"): (27, 129.5),
    ("25-75", "bright"): (5, 36.0), ("25-75", "somber"): (4, 35.0),
    ("25-45", "bright"): (11, 47.0), ("25-45", "somber"): (10, 44.83),
    ("45-75", "bright"): (14, 55.5), ("45-75", "somber"): (11, 49.0),
    ("0-25", "bright"): (12, 47.0), ("0-25", "somber"): (10, 42.0),
    ("0-45", "bright"): (17, 51.5), ("0-45", "somber"): (17, 38.83),
    ("0-75", "bright"): (4, 23.33), ("0-75", "somber"): (0, 18.0),
}  # fmt: skip
PAPER_TABLE7 = {  # (lighting, weather) -> (average successful relocations, average matched pairs); FAIL = 0
    ("bright", "clear"): (27, 125.83), ("bright", "mist"): (11, 58.0), ("bright", "fog"): (0, 17.5),
    ("somber", "clear"): (27, 112.0), ("somber", "mist"): (7, 39.83), ("somber", "fog"): (0, 15.33),
}  # fmt: skip


def inter_agent_recognitions(data: dict[str, Any]) -> list[dict[str, Any]]:
    """Geometrically verified inter-agent place recognitions of one co-location run (accepted
    ``placerec_candidate`` events whose query and candidate keyframes belong to different agents), each
    with both agents' camera pitch and the scenario's lighting and weather (from its manifest)."""
    import yaml

    from hivemap.server.convert import split_folded

    man = yaml.safe_load((Path(data["scenario_dir"]) / "manifest.yaml").read_text())
    pitch = {
        a["id"]: (0.0 if a["kind"] == "ugv" else float(a.get("camera_pitch_deg", 0.0))) for a in man["agents"]
    }
    lighting, weather = str(man.get("lighting", "?")), str(man.get("weather", "?"))
    out = []
    for e in data.get("events", []):
        d = e.get("data") or {}
        if e.get("kind") != "placerec_candidate" or not d.get("accepted"):
            continue
        qa, ca = split_folded(d["query_key"][0])[0], split_folded(d["candidate_key"][0])[0]
        if qa == ca or qa not in pitch or ca not in pitch:
            continue
        lo, hi = sorted((pitch[qa], pitch[ca]))
        out.append({"agents": (qa, ca), "angles": f"{lo:.0f}-{hi:.0f}", "lighting": lighting,
                    "weather": weather, "n_inliers": int(d.get("n_inliers", 0))})  # fmt: skip
    return out


def table67(results: dict[tuple[str, str], dict[str, Any]]) -> list[str]:
    """Tables 6 and 7 from the GNSS-denied co-location runs (the paper's figures beside ours)."""
    recs = []
    for (_s, m), data in results.items():
        if m == "denied":
            recs.append(inter_agent_recognitions(data))
    md = ["### Table 6: successful inter-agent place recognitions and average matched pairs, "
          "per camera-angle pair and lighting (GNSS-denied runs)", ""]  # fmt: skip
    if not recs:
        return [*md, "(no GNSS-denied co-location run)", ""]
    head = ["runs", "ours: recognitions / run", "ours: avg matched pairs", "paper: relocations",
            "paper: avg matched pairs"]  # fmt: skip
    md.append(_row(["camera angles", "lighting", *head]))
    md.append("|---|---|---|---|---|---|---|")
    groups6: dict[tuple[str, str], list[list[dict[str, Any]]]] = {}
    groups7: dict[tuple[str, str], list[list[dict[str, Any]]]] = {}
    for run in recs:
        if not run:
            continue
        for key in {(r["angles"], r["lighting"]) for r in run}:
            groups6.setdefault(key, []).append([r for r in run if (r["angles"], r["lighting"]) == key])
        groups7.setdefault((run[0]["lighting"], run[0]["weather"]), []).append(run)

    def rows(
        groups: dict[tuple[str, str], list[list[dict[str, Any]]]], paper: dict[Any, Any], unit: str
    ) -> None:
        for (a, b), runs in sorted(groups.items()):
            n = [len(r) for r in runs]
            inl = [x["n_inliers"] for r in runs for x in r]
            p = paper.get((a, b))
            avg = sum(inl) / max(1, len(inl))
            md.append(f"| {a}{unit} | {b} | {len(runs)} | {sum(n) / len(n):.1f} | {avg:.1f} | "
                      f"{p[0] if p else '-'} | {p[1] if p else '-'} |")  # fmt: skip

    rows(groups6, PAPER_TABLE6, " deg")
    md += ["", "### Table 7: the same per lighting and weather", ""]
    md.append(_row(["lighting", "weather", *head]))
    md.append("|---|---|---|---|---|---|---|")
    rows(groups7, PAPER_TABLE7, "")
    md += ["", "Recognitions are geometrically verified candidates between different agents (before the "
           "3-detection consistency check); the paper counts successful relocations. Only the scenarios run "
           "in GNSS-denied mode appear.", ""]  # fmt: skip
    return md
