"""How often can a GNSS-challenged co-location row be met at all? Fix draws against perfect maps.

The GNSS rows of the co-location acceptance compare one draw of sparse, white GNSS noise in two modes:
each agent alone on its every-20 s fixes (``single+gnss``) against the team on the mode's fixes
(``challenged1``: every agent's every-20 s fixes; ``challenged2``: 4 random fixes per UAV, none for the
UGV). With so few fixes the placement of a trajectory in ENU is itself a random draw. This bench takes
the estimator out: every agent's *true* trajectory is placed on the fixes by yaw + translation (gravity
known, the ML placement of a perfect map), alone in ``single+gnss`` and as one rigid team in the
co-location mode, and the two placements' position RMSEs are compared per agent.

Per world seed it prints the ratios team / single for the world's own fixes (the draw its renders hold,
the same seeded noise, so the same for every preset of that seed) and, over ``--draws`` fresh draws of
the noise and of the random fixes, how often perfect maps meet the row: no agent worse by more than
``--margin``, and the mean gain at least ``--gain``. Geometry only: no rendering, no SLAM.

Run: .venv/bin/python bench/gnss_draws.py [--scenario factory01] [--seeds 1,2,3] [--draws 2000]
"""

from __future__ import annotations

import argparse

import numpy as np
from numpy.typing import NDArray

from hivemap.client.replay_io import parse_gnss_mode, select_gnss
from hivemap.client.second_stage.factors import yaw_translation_alignment
from hivemap.eval.experiment import gnss_mode
from hivemap.sim.dataset import cached_world
from hivemap.sim.scenario_file import resolve_scenario
from hivemap.sim.sensor_files import gnss_rng
from hivemap.sim.sensors import simulate_gnss
from hivemap.sim.trajectories import plan_trajectories

F64 = NDArray[np.float64]


def placement_errors(truth: F64, fix_truth: F64, fix_meas: F64) -> F64:
    """The true positions (N, 3) moved by the yaw + translation that takes the fixes' true positions onto
    their measurements: returns the per-point error vectors (N, 3)."""
    T = yaw_translation_alignment(fix_truth, fix_meas)
    return truth @ T[:3, :3].T + T[:3, 3] - truth


def rmse(err: F64) -> float:
    return float(np.sqrt(np.mean(np.sum(err**2, axis=1))))


def ratios(
    truth: dict[str, F64],
    meas: dict[str, F64],
    single_sel: dict[str, NDArray[np.intp]],
    team_sel: dict[str, NDArray[np.intp]],
) -> F64:
    """Per agent: team placement RMSE / single placement RMSE (agents without fixes in the team mode
    follow the team's transform)."""
    single = [rmse(placement_errors(truth[a], truth[a][s], meas[a][s])) for a, s in single_sel.items()]
    used = [a for a, s in team_sel.items() if len(s)]
    ft = np.concatenate([truth[a][team_sel[a]] for a in used])
    fm = np.concatenate([meas[a][team_sel[a]] for a in used])
    team = [rmse(placement_errors(truth[a], ft, fm)) for a in single_sel]
    return np.array(team) / np.maximum(np.array(single), 1e-12)


def selection(times: F64, mode: str, kind: str, seed: int) -> NDArray[np.intp]:
    """The indices of the fixes an agent of ``kind`` uses in ``mode`` (the runner's rule)."""
    return np.flatnonzero(
        select_gnss(times, np.ones(len(times), bool), parse_gnss_mode(gnss_mode(mode, kind)), seed)
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenario", default="factory01")
    ap.add_argument(
        "--seeds", default="1,2,3", help="comma-separated world seeds ('default': the scenario's)"
    )
    ap.add_argument("--modes", default="challenged1,challenged2")
    ap.add_argument("--draws", type=int, default=2000)
    ap.add_argument("--margin", type=float, default=0.05, help="no agent worse than single by more than this")
    ap.add_argument("--gain", type=float, default=0.20, help="mean gain at least this")
    args = ap.parse_args()
    rng = np.random.default_rng(0)
    print("| seed | mode | own draw: team / single per agent | perfect maps meet the row | P(agent worse) |")
    print("|---|---|---|---|---|")
    for s in args.seeds.split(","):
        sc = resolve_scenario(args.scenario, None if s == "default" else int(s))
        plan = plan_trajectories(cached_world(sc.seed, sc.world_size_m), sc)
        truth, own, times, kinds = {}, {}, {}, {}
        for i, spec in enumerate(sc.agents):
            traj = plan.trajectories[spec.agent_id]
            dur = traj.duration if sc.duration_s is None else min(sc.duration_s, traj.duration)
            g = simulate_gnss(traj, sc.gnss_rate_hz, sc.gnss_noise, gnss_rng(sc, i), dur)
            truth[spec.agent_id], own[spec.agent_id], times[spec.agent_id] = g.enu_true, g.enu, g.t
            kinds[spec.agent_id] = spec.kind
        sig = np.array([sc.gnss_noise.sigma_horizontal] * 2 + [sc.gnss_noise.sigma_vertical])
        agents = list(truth)
        single_sel = {a: selection(times[a], "single+gnss", kinds[a], 0) for a in agents}
        for mode in args.modes.split(","):
            r0 = ratios(truth, own, single_sel, {a: selection(times[a], mode, kinds[a], 0) for a in agents})
            worse = np.zeros(len(agents))
            met = 0
            for _ in range(args.draws):
                meas = {a: truth[a] + rng.normal(0.0, 1.0, truth[a].shape) * sig for a in agents}
                team_sel = {
                    a: selection(times[a], mode, kinds[a], int(rng.integers(1 << 31))) for a in agents
                }
                r = ratios(truth, meas, single_sel, team_sel)
                bad = r > 1.0 + args.margin
                worse += bad
                met += int(not bad.any() and float(np.mean(1.0 - r)) >= args.gain)
            own_s = " / ".join(f"{a} {x:.2f}" for a, x in zip(agents, r0, strict=True))
            p_s = " / ".join(f"{100 * w / args.draws:.0f} %" for w in worse)
            print(f"| {s} | {mode} | {own_s} | {100 * met / args.draws:.1f} % | {p_s} |")


if __name__ == "__main__":
    main()
