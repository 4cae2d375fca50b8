"""Accuracy of the server's global map against ground truth (issue 27): the team ATE per map (one SE(3)
alignment for all of a map's agents) and each accepted loop's and merge's measured relative pose error."""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from hivemap.eval.trajectory import AgentRun, evaluate_team, read_tum

F64 = NDArray[np.float64]


def loop_errors(
    events: Sequence[dict[str, Any]], gt_cam: dict[str, Any], max_diff: float = 0.02
) -> list[dict[str, Any]]:
    """Accuracy of the server's accepted loop closures and merges: each ``loop`` and ``merge_detail``
    event that carries its measured ``candidate_from_query`` (camera poses) against the true relative
    pose of the two keyframes' cameras at their data times (``gt_cam``: agent -> ground truth with
    ``sensor="cam0"``). Per loop or merge (``kind``): agents, translation error (m; its vertical part in
    the candidate camera's world orientation), rotation error (deg) and its tilt part (deg: how far the
    error turns the true up direction). Those whose keyframes have no ground truth within ``max_diff`` s
    are left out, and so are the ones the server took back: a loop whose last verdict is
    ``loop_rejected`` (until a ``loop_readmitted``) and a merge a ``merge_undone`` event names."""
    from hivemap.maps.geometry import rotation_angle_deg, se3_inverse

    def pose_at(agent: str, t: float) -> F64 | None:
        gt = gt_cam.get(agent)
        if gt is None:
            return None
        ts = np.asarray(gt.timestamps)
        j = int(np.argmin(np.abs(ts - t)))
        return None if abs(ts[j] - t) > max_diff else np.asarray(gt.poses_se3[j])

    def edge_key(d: dict[str, Any]) -> tuple[str, ...]:
        return (*map(str, d.get("query") or ()), "|", *map(str, d.get("candidate") or ()))

    rejected: set[tuple[str, ...]] = set()
    undone: set[int] = set()
    for e in events:
        d = e.get("data") or {}
        if e.get("kind") == "loop_rejected":
            rejected.add(edge_key(d))
        elif e.get("kind") == "loop_readmitted":
            rejected.discard(edge_key(d))
        elif e.get("kind") == "merge_undone" and d.get("merge_id") is not None:
            undone.add(int(d["merge_id"]))
    out: list[dict[str, Any]] = []
    for e in events:
        d = e.get("data") or {}
        kind = {"loop": "loop", "merge_detail": "merge"}.get(str(e.get("kind")))
        if kind is None or "candidate_from_query" not in d or d.get("refused"):
            continue
        if (kind == "loop" and edge_key(d) in rejected) or (
            kind == "merge" and d.get("merge_id") is not None and int(d["merge_id"]) in undone
        ):
            continue
        qa, ca = str(d["query"][0]).split("#")[0], str(d["candidate"][0]).split("#")[0]
        if "candidate_t" not in d:  # (a merge record without its keyframes' times: nothing to check)
            continue
        # a rendezvous merge's query_t is its observation's time; its edge's keyframe has its own
        Tq = pose_at(qa, float(d.get("query_kf_t", d["query_t"])))
        Tc = pose_at(ca, float(d["candidate_t"]))
        if Tq is None or Tc is None:
            continue
        meas = np.asarray(d["candidate_from_query"], dtype=np.float64)
        true = se3_inverse(Tc) @ Tq
        dt_world = Tc[:3, :3] @ (meas[:3, 3] - true[:3, 3])
        up_c = Tc[:3, :3].T @ np.array([0.0, 0.0, 1.0])  # the world's up in the candidate camera
        up_err = meas[:3, :3] @ true[:3, :3].T @ up_c
        out.append({
            "kind": kind, "query": qa, "candidate": ca, "distance_m": float(np.linalg.norm(true[:3, 3])),
            "trans_err_m": float(np.linalg.norm(dt_world)), "vertical_err_m": float(dt_world[2]),
            "rot_err_deg": rotation_angle_deg(meas[:3, :3].T @ true[:3, :3]),
            "tilt_err_deg": math.degrees(math.acos(float(np.clip(up_err @ up_c, -1.0, 1.0)))),
            "n_inliers": int(d.get("n_inliers", 0)),
        })  # fmt: skip
    return out


def team_by_map(
    server_dir: Path, agents: Sequence[tuple[str, Any]], max_diff: float = 0.03
) -> list[dict[str, Any]]:
    """The team ATE in the server's global frame per map (issue 27): every agent's final server keyframes
    (``server_dir``/<agent>.est.tum vs .gt.tum, camera poses), one SE(3) alignment per map for all of its
    agents (``agents``: (agent, map id at the end)), so an agent misplaced against the others counts;
    with each pair's relative pose error at keyframes within ``max_diff`` s. Agents without both files
    are left out; empty if none has them."""
    runs = []
    for aid, map_id in agents:
        est, gt = server_dir / f"{aid}.est.tum", server_dir / f"{aid}.gt.tum"
        if est.exists() and gt.exists():
            runs.append(AgentRun(aid, read_tum(est), read_tum(gt), [(-1e18, f"map {map_id}")]))
    if not runs:
        return []
    rep = evaluate_team(runs, "se3", max_diff=max_diff, rpe_delta=None)
    out = []
    for fid, fr in rep.frames.items():
        errs = [rep.agents[a].ate for a in fr.agents]
        n = sum(e.n for e in errs)
        out.append({
            "map": fid, "agents": list(fr.agents), "n": n,
            "team_ate_rmse": (sum(e.rmse**2 * e.n for e in errs) / n) ** 0.5 if n else None,
            "pairs": [{"agents": [p.agent_a, p.agent_b], "n": p.trans.n, "trans_rmse": p.trans.rmse,
                       "rot_rmse_deg": p.rot_deg.rmse} for p in rep.inter_agent if p.frame_id == fid],
        })  # fmt: skip
    return out


def globalmap_section(results: dict[tuple[str, str], dict[str, Any]]) -> list[str]:
    """The report's check of the global map per co-location run: which start poses the server had, what
    the agents streamed, when all agents were in one map, the team ATE per map and the accepted loops' and
    merges' errors."""
    from hivemap.eval.startposes import describe

    md = ["## Global map against ground truth", "",
          "Team ATE: one SE(3) alignment per map for all its agents' final server keyframes. Loop and merge "
          "errors: each accepted loop's or merge's measured relative pose against the true one of its two "
          "keyframes (over 0.5 m or 2 deg counts as wrong).", "",
          _row(["scenario", "mode", "start poses", "streamed", "all in one map [s]",
                "maps: team ATE RMSE [m]", "loops", "merges", "worst [m / deg]", "wrong"]),
          "|---|---|---|---|---|---|---|---|---|---|"]  # fmt: skip
    n = 0
    for (s, m), data in results.items():
        if "team" not in data:
            continue
        n += 1
        errs = data.get("loop_errors") or []
        worst = (
            max((e["trans_err_m"] for e in errs), default=0.0),
            max((e["rot_err_deg"] for e in errs), default=0.0),
        )
        wrong = sum(1 for e in errs if e["trans_err_m"] > 0.5 or e["rot_err_deg"] > 2.0)
        teams = "; ".join(
            f"{t['map']} ({', '.join(t['agents'])}): {_f(t['team_ate_rmse'])}" for t in data["team"]
        )
        when = data.get("all_merged_s")
        start = (data.get("start_poses") or {}).get("mode", "truth (old run)")
        # runs written before the IMU-aided stream existed streamed the tracking
        streamed = "IMU fusion" if data.get("stream_imu_odometry", False) else "tracking"
        md.append(_row([s, m, str(start), streamed, "never" if when is None else f"{when:.1f}", teams or "-",
                        str(sum(1 for e in errs if e.get("kind", "loop") == "loop")),
                        str(sum(1 for e in errs if e.get("kind") == "merge")),
                        f"{worst[0]:.3f} / {worst[1]:.2f}", str(wrong)]))  # fmt: skip
    if not n:
        md.append("| (no co-location run) ||||||||||")
    md.append("")
    for (s, m), data in results.items():
        if "team" in data:
            md.append(f"- {s} / {m}: {describe(data.get('start_poses'))}")
    return [*md, ""]


def _row(cols: list[str]) -> str:
    return "| " + " | ".join(cols) + " |"


def _f(x: float | None) -> str:
    return "-" if x is None or not math.isfinite(x) else f"{x:.3f}"
