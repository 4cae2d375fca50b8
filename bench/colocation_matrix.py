"""The co-location matrix of issue 27 ("no wrong map"): run it, and print each row against its bounds.

``run`` calls ``hivemap eval experiment`` once per world and start prior, one after the other (the runner
skips what is done, so a stopped matrix resumes): ``<out>/<world>-perturbed`` holds the single-agent runs
and GNSS-denied co-location with the nominal start poses perturbed by 0.2 m / 5 deg, ``<out>/<world>-none``
co-location without start poses; ``--challenged`` adds ``single+gnss``, ``challenged1`` and ``challenged2``
to the perturbed runs. ``table`` reads those folders and prints, per run:

- clear worlds (factory 01, 03, 05, 07, 08): the time all four agents were in one map (bound 30 s), the
  team ATE in the server's frame (one SE(3) alignment per map; bound 0.15 m), each agent's final ATE and
  its gain against its single run (none worse than -5 %, mean >= +25 %);
- fog and somber mist (factory 02, 04, 06): every map's team ATE (bound 0.5 m);
- every run: accepted loops and merges, the worst against ground truth (bound 0.5 m / 2 deg);
- GNSS-challenged: each agent's gain against single+gnss (none worse than -5 %, mean >= +20 %);

then mean and worst per agent over the worlds of each scenario, and the rows that miss a bound.

    .venv/bin/python bench/colocation_matrix.py run --scenarios factory01,factory03 --seeds default,1,2 \\
        --data data/full --out runs/matrix
    .venv/bin/python bench/colocation_matrix.py table --out runs/matrix

``default`` is the preset's own world (seed 3), rendered as ``factory01`` rather than ``factory01-s3``.
"""

from __future__ import annotations

import argparse
import json
import math
import subprocess
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

AGENTS = ("uav1", "uav2", "uav3", "ugv")
CLEAR = {"factory01", "factory03", "factory05", "factory07", "factory08"}
HARD = {"factory02", "factory04", "factory06"}
ONE_MAP_S, TEAM_M, HARD_TEAM_M = 30.0, 0.15, 0.5
WORST_LOSS, MEAN_GAIN, MEAN_GAIN_GNSS = -0.05, 0.25, 0.20
WRONG_M, WRONG_DEG = 0.5, 2.0
CHALLENGED = ("challenged1", "challenged2")
PRIORS = ("perturbed", "none")
HIVEMAP = [sys.executable, "-m", "hivemap.cli.main"]


def world_key(scenario: str, seed: str) -> str:
    """The runner's folder name of a world; ``seed`` as given on the command line (``default`` or N)."""
    from hivemap.eval.experiment import world_key as runner_key

    return runner_key(scenario, None if seed == "default" else int(seed))


def cmd_run(a: argparse.Namespace) -> None:
    out = Path(a.out)
    for scenario in a.scenarios.split(","):
        for seed in a.seeds.split(","):
            world = world_key(scenario, seed)
            seeds = [] if seed == "default" else ["--seeds", seed]
            modes = "single,denied" + (",single+gnss,challenged1,challenged2" if a.challenged else "")
            for prior, m in (("perturbed", modes), ("none", "denied")):
                if prior not in a.priors.split(","):
                    continue
                run_dir = out / f"{world}-{prior}"
                cmd = [*HIVEMAP, "eval", "experiment", "--scenarios", scenario, *seeds, "--modes", m,
                       "--start-poses", prior, "--data", a.data, "--out", str(run_dir),
                       "--no-progress"]  # fmt: skip
                cmd += ["--stream-tracking"] if a.stream_tracking else []
                print(f"{world} {prior}: {m}", flush=True)
                run_dir.mkdir(parents=True, exist_ok=True)
                with open(run_dir.with_suffix(".log"), "ab") as log:
                    rc = subprocess.run(cmd, stdout=log, stderr=subprocess.STDOUT).returncode
                if rc != 0:
                    raise SystemExit(f"{world} {prior}: the experiment exited with {rc}; see {log.name}")


# ---------------------------------------------------------------------------------------------- table
@dataclass
class Row:
    world: str
    prior: str
    mode: str
    one_map_s: float | None
    maps: list[tuple[list[str], float]]  # (agents, team ATE) per map with keyframes
    loops: int
    worst_m: float
    worst_deg: float
    wrong: int
    ate: dict[str, float]
    gain: dict[str, float] = field(default_factory=dict)
    misses: list[str] = field(default_factory=list)


def _read(path: Path) -> dict[str, Any] | None:
    return json.loads(path.read_text()) if path.exists() else None


def _ates(res: dict[str, Any] | None) -> dict[str, float]:
    if res is None:
        return {}
    return {r["agent_id"]: r["ate_rmse"] for r in res["agents"] if r.get("ate_rmse") is not None}


def _row(world: str, prior: str, mode: str, res: dict[str, Any], base: dict[str, float]) -> Row:
    errs = res.get("loop_errors") or []
    worst_m = max((abs(e.get("trans_err_m") or 0.0) for e in errs), default=0.0)
    worst_deg = max((abs(e.get("rot_err_deg") or 0.0) for e in errs), default=0.0)
    wrong = sum(abs(e.get("trans_err_m") or 0.0) > WRONG_M or abs(e.get("rot_err_deg") or 0.0) > WRONG_DEG
                for e in errs)  # fmt: skip
    maps = [(list(t["agents"]), float(t["team_ate_rmse"])) for t in res.get("team") or []]
    ate = _ates(res)
    gain = {k: (base[k] - v) / base[k] for k, v in ate.items() if base.get(k)}
    one_map = res.get("all_merged_s")
    row = Row(world, prior, mode, one_map, maps, len(errs), worst_m, worst_deg, wrong, ate, gain)
    scenario = world.split("-s")[0]
    if wrong:
        row.misses.append(f"{wrong} loop(s)/merge(s) over {WRONG_M} m / {WRONG_DEG} deg")
    if scenario in HARD and mode == "denied":
        row.misses += [f"map of {'+'.join(a)} at {t:.3f} m" for a, t in maps if t > HARD_TEAM_M]
    elif mode == "denied" and scenario in CLEAR:
        if row.one_map_s is None or row.one_map_s > ONE_MAP_S:
            row.misses.append(f"one map at {row.one_map_s} s")
        row.misses += [f"team ATE {t:.3f} m" for _, t in maps if t > TEAM_M]
    if mode == "denied" and scenario in CLEAR or mode in CHALLENGED:
        floor = MEAN_GAIN if mode == "denied" else MEAN_GAIN_GNSS
        row.misses += [f"{k} {g * 100:+.1f} %" for k, g in gain.items() if g < WORST_LOSS]
        if gain and sum(gain.values()) / len(gain) < floor:
            row.misses.append(f"mean gain {sum(gain.values()) / len(gain) * 100:+.1f} %")
        if len(gain) < len(ate) or not gain:
            row.misses.append("no single-agent baseline for some agents")
    return row


def rows(out: Path) -> list[Row]:
    found: list[Row] = []
    for d in sorted(p for p in out.iterdir() if p.is_dir() and p.name.rsplit("-", 1)[-1] in PRIORS):
        world, prior = d.name.rsplit("-", 1)
        res_dir = d / "results" / world
        # the runs without a prior have no single-agent runs of their own: the perturbed run's
        own = res_dir / "single.json"
        single = _read(own) or _read(out / f"{world}-perturbed/results/{world}/single.json")
        singles = _ates(single)
        single_gnss = _ates(_read(res_dir / "single+gnss.json"))
        for mode in ("denied", *CHALLENGED):
            res = _read(res_dir / f"{mode}.json")
            if res is not None:
                found.append(_row(world, prior, mode, res, singles if mode == "denied" else single_gnss))
    return found


def _fmt(x: float | None, spec: str = ".3f") -> str:
    return "-" if x is None or (isinstance(x, float) and math.isnan(x)) else format(x, spec)


def cmd_table(a: argparse.Namespace) -> None:
    if not Path(a.out).is_dir():
        raise SystemExit(f"{a.out}: no such folder (give the --out of `run`)")
    rs = rows(Path(a.out))
    if not rs:
        raise SystemExit(f"no runs under {a.out}")
    print("| world | prior | mode | all in one map [s] | team ATE per map [m] | loops+merges, worst | "
          + " | ".join(AGENTS) + " | mean gain | misses |")  # fmt: skip
    print("|---" * (9 + len(AGENTS)) + "|")
    for r in rs:
        one = len(r.maps) == 1
        team = ", ".join(_fmt(t) + ("" if one else f" ({'+'.join(ag)})") for ag, t in r.maps)
        per = [_fmt(r.ate.get(k)) + (f" ({r.gain[k] * 100:+.0f} %)" if k in r.gain else "") for k in AGENTS]
        mean = sum(r.gain.values()) / len(r.gain) * 100 if r.gain else None
        print(f"| {r.world} | {r.prior} | {r.mode} | {_fmt(r.one_map_s, '.1f')} | {team} | {r.loops}, "
              f"{r.worst_m:.3f} m / {r.worst_deg:.2f} deg | " + " | ".join(per)
              + f" | {_fmt(mean, '+.1f')} % | {'; '.join(r.misses) or 'met'} |")  # fmt: skip
    print()
    by: dict[tuple[str, str], list[Row]] = {}
    for r in rs:
        by.setdefault((r.world.split("-s")[0], r.mode), []).append(r)
    print("| scenario | mode | runs | " + " | ".join(f"{k} mean / worst gain" for k in AGENTS) + " |")
    print("|---" * (3 + len(AGENTS)) + "|")
    for (scenario, mode), group in sorted(by.items()):
        cells = []
        for k in AGENTS:
            g = [r.gain[k] * 100 for r in group if k in r.gain]
            cells.append(f"{sum(g) / len(g):+.1f} / {min(g):+.1f} %" if g else "-")
        print(f"| {scenario} | {mode} | {len(group)} | " + " | ".join(cells) + " |")
    missed = [r for r in rs if r.misses]
    print(f"\n{len(rs) - len(missed)} of {len(rs)} runs meet every bound of their row")
    have = {(r.world, r.prior) for r in rs if r.mode == "denied"}
    want = [(world_key(sc, sd), p) for sc in a.scenarios.split(",") for sd in a.seeds.split(",")
            for p in a.priors.split(",")]  # fmt: skip
    missing = [f"{w} {p}" for w, p in want if (w, p) not in have]
    print(f"not run yet ({len(missing)} of {len(want)}): {', '.join(missing) or 'none'}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("run", help="run the matrix (resumable)")
    t = sub.add_parser("table", help="print the runs under --out against the bounds, and those not run yet")
    for p in (r, t):
        p.add_argument("--scenarios", default="factory01,factory03,factory05,factory07,factory08")
        p.add_argument("--seeds", default="default,1,2")
        p.add_argument("--priors", default="perturbed,none")
        p.add_argument("--out", required=True)
    r.add_argument("--challenged", action="store_true", help="also single+gnss, challenged1, challenged2")
    r.add_argument("--data", default="data")
    r.add_argument("--stream-tracking", action="store_true",
                   help="agents stream their visual tracking instead of their IMU-only fusion "
                   "(`hivemap agent --stream-tracking`); give it its own --out")  # fmt: skip
    if not sys.argv[1:]:  # `make bench` runs every bench bare
        print("bench/colocation_matrix.py: hours of runs, on request only (`run`, then `table`; see --help)")
        return
    a = ap.parse_args()
    cmd_run(a) if a.cmd == "run" else cmd_table(a)


if __name__ == "__main__":
    main()
