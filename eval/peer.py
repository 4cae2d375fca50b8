"""The experiment report's section on the peer: hivemap's single-agent runs beside ORB-SLAM3.

ORB-SLAM3 is no dependency of hivemap, so ``bench/orbslam3.py`` runs it in a venv of its own and
leaves ``<out>/orbslam3/summary.json`` next to the experiment's results; this module only reads that
summary, so the report can say how the two systems compare on the same sequences.
"""

from __future__ import annotations

import json
import statistics
from pathlib import Path
from typing import Any

PEER_DIR = "orbslam3"


def peer_rows(out: Path) -> list[dict[str, Any]]:
    """The bench's rows (world, agent, ``hm``/``orb`` ATEs, ORB-SLAM3's run stats), [] without a run."""
    p = out / PEER_DIR / "summary.json"
    if not p.exists():
        return []
    rows = json.loads(p.read_text())
    if not isinstance(rows, list):
        raise ValueError(f"{p}: expected a list of rows, got {type(rows).__name__}")
    return rows


def _cell(part: dict[str, Any] | None) -> str:
    if not part or part.get("ate_rmse") is None:
        return "-"
    return f"{part['ate_rmse']:.3f} ({part['ate_pct']:.3f} %)"


def peer_section(out: Path) -> list[str]:
    """Markdown lines: per world and agent both ATEs (m, % of path), ORB-SLAM3's losses and maps; the
    mean and worst over the agents with both figures, per world and overall. Empty without a run."""
    rows = peer_rows(out)
    if not rows:
        return []
    md = [
        "## Single agent beside ORB-SLAM3 stereo-inertial (bench/orbslam3.py)",
        "",
        "Same sequences, GNSS denied, evo SE(3) ATE against the body ground truth. ORB-SLAM3's figure "
        "covers its largest map when it lost tracking.",
        "",
        "| world | agent | hivemap ATE m (% of path) | ORB-SLAM3 ATE m (% of path) "
        "| ORB-SLAM3 losses / maps |",
        "|---|---|---|---|---|",
    ]
    for r in rows:
        st = r.get("orbslam3", {})
        runs = st["error"] if "error" in st else f"{st.get('tracking_losses', '-')} / {st.get('maps', '-')}"
        md.append(f"| {r['world']} | {r['agent']} | {_cell(r.get('hm'))} | {_cell(r.get('orb'))} | {runs} |")
    both = [r for r in rows if all(r.get(k, {}).get("ate_rmse") is not None for k in ("hm", "orb"))]
    if not both:
        md += ["", "No agent has both figures.", ""]
        return md
    md += ["", "| over | agents | hivemap mean / worst [m] | ORB-SLAM3 mean / worst [m] |"]
    md.append("|---|---|---|---|")
    worlds = sorted({r["world"] for r in both})
    for label, group in [*((w, [r for r in both if r["world"] == w]) for w in worlds), ("all", both)]:
        hm = [float(r["hm"]["ate_rmse"]) for r in group]
        orb = [float(r["orb"]["ate_rmse"]) for r in group]
        md.append(
            f"| {label} | {len(group)} | {statistics.fmean(hm):.3f} / {max(hm):.3f} | "
            f"{statistics.fmean(orb):.3f} / {max(orb):.3f} |"
        )
    hm_mean = statistics.fmean(float(r["hm"]["ate_rmse"]) for r in both)
    orb_mean = statistics.fmean(float(r["orb"]["ate_rmse"]) for r in both)
    verdict = "at most" if hm_mean <= orb_mean else "above"
    md += ["", f"hivemap's mean ATE ({hm_mean:.3f} m) is {verdict} ORB-SLAM3's ({orb_mean:.3f} m).", ""]
    return md


def rewrite_report(out: Path) -> Path:
    """Re-write the report of the experiment in ``out`` from the results it holds, e.g. once the peer's
    summary has been added; returns the report.md path."""
    from hivemap.eval.report import MODE_NAMES, write_report

    res = out / "results"
    if not res.is_dir():
        raise FileNotFoundError(f"{out}: no results/ (not the --out of `hivemap eval experiment`)")
    scenarios = sorted(p.name for p in res.iterdir() if p.is_dir())
    found = {p.stem for s in scenarios for p in (res / s).glob("*.json")}
    modes = [m for m in MODE_NAMES if m in found]
    return write_report(out, scenarios, modes)
