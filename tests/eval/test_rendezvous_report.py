"""The markers condition's figures: when the UGV joined the UAVs' map and how well it sits against them."""

from __future__ import annotations

import math

from hivemap.eval.rendezvous import (
    all_together_s,
    merge_timeline,
    rendezvous_section,
    ugv_joined_s,
    ugv_uav_pair_error,
)


def _merge(t: float, q: str, c: str, by: str) -> dict[str, object]:
    det = {"query_key": [q, 3], "candidate_key": [c, 5]}
    return {"kind": "merge_detail", "data": {"query_t": 100.0 + t, "by": by, "detection": det}}


def test_timeline_follows_groups_and_finds_the_ugv() -> None:
    events = [
        {"kind": "connect", "data": {}},
        _merge(0.5, "uav1", "uav2", "place_recognition"),
        _merge(0.6, "uav2", "uav1", "place_recognition"),  # same group again: not a join
        _merge(4.0, "uav3", "uav2", "place_recognition"),
        _merge(9.0, "ugv#1", "uav3", "rendezvous"),
    ]
    tl = merge_timeline(events, 100.0)
    assert [m["agents"] for m in tl] == [["uav1", "uav2"], ["uav3", "uav2"], ["ugv#1", "uav3"]]
    assert tl[-1]["together"] == ["uav1", "uav2", "uav3", "ugv"]
    joined = ugv_joined_s(tl)
    assert joined is not None and math.isclose(joined, 9.0)
    assert ugv_joined_s(tl[:2]) is None
    joined = all_together_s(tl, ["uav1", "uav2", "uav3", "ugv"])
    assert joined is not None and math.isclose(joined, 9.0)
    assert all_together_s(tl[:2], ["uav1", "uav2", "uav3", "ugv"]) is None


def test_a_new_session_merged_back_by_its_guess_joins_its_agent_not_the_team() -> None:
    # uav1 lost tracking: its session 1 goes back into session 0's map by the guess (no detection), then
    # session 1 meets uav2 by place recognition; the team was together only then
    guess = {"kind": "merge_detail", "data": {"query_t": 103.0, "by": "session_guess",
             "query": ["uav1#1", 2], "candidate": ["uav1", 1]}}  # fmt: skip
    tl = merge_timeline([guess, _merge(6.0, "uav1#1", "uav2", "place_recognition")], 100.0)
    assert [m["agents"] for m in tl] == [["uav1#1", "uav1"], ["uav1#1", "uav2"]]
    assert tl[0]["together"] == ["uav1"]
    when = all_together_s(tl, ["uav1", "uav2"])
    assert when is not None and math.isclose(when, 6.0)


def test_pair_error_weights_ugv_pairs_by_count_and_the_section_lists_the_run() -> None:
    team = [{"pairs": [
        {"agents": ["uav1", "ugv"], "n": 10, "trans_rmse": 0.3},
        {"agents": ["uav2", "ugv"], "n": 30, "trans_rmse": 0.1},
        {"agents": ["uav1", "uav2"], "n": 50, "trans_rmse": 9.0},
    ]}]  # fmt: skip
    err, n = ugv_uav_pair_error(team)
    assert n == 40 and err is not None and math.isclose(err, math.sqrt((0.09 * 10 + 0.01 * 30) / 40))
    data = {
        "team": team,
        "markers": {"condition": "on"},
        "merge_timeline": merge_timeline([_merge(9.0, "ugv", "uav3", "rendezvous")], 100.0),
        "agents": [{"run": {"rendezvous_sent": 4}}, {"run": {"rendezvous_sent": 2}}],
        "events": [{"kind": "rendezvous_rejected"}],
    }
    md = "\n".join(rendezvous_section({("f01-s1", "denied"): data}))
    assert "| f01-s1 | denied | on | 6 | 1 | 9.0 | rendezvous | 0.173 (40) |" in md
