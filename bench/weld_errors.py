"""Accuracy of each loop's and merge's transform before and after the weld (issue 27), from experiment runs.

For every loop and merge a run's server welded (``[backend.fit] weld = true``), its record carries the
unwelded relative pose and, with ``weld_compare = true``, the other variants' (4 DoF, tilt free within a
0.2 deg prior, 6 DoF). This prints each one's error against ground truth, and per run the worst and mean
of each, so that one run compares them on the same detections. Refused welds are listed with the error
their unwelded transform had.

    python bench/weld_errors.py --data /work/data OUT/results/*/denied.json
"""

from __future__ import annotations

import argparse
import copy
import json
from pathlib import Path
from typing import Any


def _errors(events: list[dict[str, Any]], gt: dict[str, Any], which: str) -> list[dict[str, Any]]:
    """``loop_errors`` with each welded record's relative pose replaced by ``which``'s (None: left out)."""
    from hivemap.eval.globalmap import loop_errors

    out = []
    for e in events:
        d = (e.get("data") or {}).get("weld")
        if e.get("kind") not in ("loop", "merge_detail", "merge") or not d or d.get("skipped"):
            continue
        if which == "welded" and d.get("ok"):
            pose = e["data"].get("candidate_from_query")
        elif which == "unwelded":
            pose = d.get("unwelded_candidate_from_query")
        else:
            pose = (d.get("variants") or {}).get(which, {}).get("candidate_from_query")
        if pose is None or "query" not in d:
            continue
        ev = copy.deepcopy(e)
        ev["kind"] = "loop" if e["kind"] == "loop" else "merge_detail"
        ev["data"] = {**e["data"], **{k: d[k] for k in ("query", "candidate", "query_t", "candidate_t")}}
        ev["data"].pop("refused", None)
        ev["data"]["candidate_from_query"] = pose
        ev["data"]["weld_refused"] = not d.get("ok")
        errs = loop_errors([ev], gt)
        for r in errs:
            r["refused"] = not d.get("ok")
            r["bound_m"], r["bound_deg"] = d.get("bound_m"), d.get("bound_deg")
        out += errs
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("results", nargs="+", type=Path)
    ap.add_argument("--data", type=Path, required=True, help="the rendered worlds (one folder per world)")
    args = ap.parse_args()
    from hivemap.eval.trajectory import groundtruth_trajectory

    for path in args.results:
        world = path.parent.name
        res = json.loads(path.read_text())
        events = res.get("events") or []
        agents = [a["agent_id"] for a in res.get("agents", [])]
        gt = {a: groundtruth_trajectory(args.data / world / a, sensor="cam0") for a in agents}
        print(f"== {world} ({path})")
        table = {w: _errors(events, gt, w) for w in ("unwelded", "welded", "4dof", "tilt0.2", "6dof")}
        for w, errs in table.items():
            kept = [r for r in errs if not r["refused"]]
            if not kept:
                continue
            tm = [r["trans_err_m"] for r in kept]
            rd = [r["rot_err_deg"] for r in kept]
            tl = [r["tilt_err_deg"] for r in kept]
            n = len(kept)
            print(f"  {w:9s} n={n:3d}  worst {max(tm):.3f} m / {max(rd):.2f} deg  mean {sum(tm) / n:.3f} m / "
                  f"{sum(rd) / n:.2f} deg  (tilt mean {sum(tl) / n:.2f} deg)")  # fmt: skip
        for r in table["unwelded"]:
            pair = (r["query"], r["candidate"])
            same = [x for x in table["welded"] if (x["query"], x["candidate"]) == pair]
            match = next((x for x in same if abs(x["distance_m"] - r["distance_m"]) < 1e-6), None)
            after = f"{match['trans_err_m']:.3f} m / {match['rot_err_deg']:.2f} deg" if match else "refused"
            print(f"    {r['kind']:5s} {r['query']}->{r['candidate']} {r['distance_m']:5.1f} m apart: "
                  f"{r['trans_err_m']:.3f} m / {r['rot_err_deg']:.2f} deg (tilt {r['tilt_err_deg']:.2f}) -> "
                  f"{after}  bound {r['bound_m']:.3f} m / {r['bound_deg']:.2f} deg")  # fmt: skip


if __name__ == "__main__":
    main()
