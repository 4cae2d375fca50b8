"""World seeds in the experiment runner and the report's over-seeds table."""

from __future__ import annotations

from hivemap.eval.experiment import ExperimentOptions, world_key
from hivemap.eval.seeds import seeds_section, split_world


def test_worlds_are_named_by_scenario_and_seed() -> None:
    opts = ExperimentOptions(scenarios=["factory01", "factory03"], seeds=[None, 2])
    assert opts.worlds() == [
        ("factory01", "factory01", None),
        ("factory01-s2", "factory01", 2),
        ("factory03", "factory03", None),
        ("factory03-s2", "factory03", 2),
    ]
    assert ExperimentOptions(scenarios=["tiny"]).worlds() == [("tiny", "tiny", None)]
    assert split_world(world_key("factory01", 7)) == ("factory01", "7")
    assert split_world("factory01") == ("factory01", "default")
    # a scenario file is named by its stem: its world goes under --data, not beside the file
    assert world_key("/some/dir/f01short.toml", 2) == "f01short-s2"
    assert ExperimentOptions(scenarios=["cases/my.toml"], seeds=[1]).worlds() == [
        ("my-s1", "cases/my.toml", 1)
    ]


def _row(world: str, agent: str, rmse: float, base: float | None) -> dict[str, object]:
    return {"scenario": world, "agent": agent, "mode": "denied", "ate_rmse": rmse, "baseline_rmse": base}


def test_seed_table_gives_mean_and_worst_per_agent() -> None:
    rows = [
        _row("factory01", "uav1", 0.04, 0.08),
        _row("factory01-s1", "uav1", 0.06, 0.06),
        _row("factory01-s2", "uav1", 0.11, 0.10),
        _row("factory01", "ugv", 0.05, 0.10),
        _row("factory01-s1", "ugv", 2.1, 2.0),
    ]
    md = "\n".join(seeds_section(rows))
    # uav1: RMSE mean (0.04+0.06+0.11)/3 = 0.070, worst 0.110; gains +50 %, 0 %, -10 % -> mean +13.3 %
    assert "| factory01 | denied | uav1 | 1,2,default | 0.070 | 0.110 | +13.3% | -10.0% |" in md
    assert "| factory01 | denied | ugv | 1,default | 1.075 | 2.100 | +22.5% | -5.0% |" in md
    assert seeds_section([_row("factory01", "uav1", 0.04, 0.08)]) == []  # one world: nothing over seeds
