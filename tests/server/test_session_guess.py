"""A new front-end session merged back by its agent's guess (real server, real WebSocket, real store).

The UAV maps room A (session 0), loses tracking and starts session 1 in room B, which session 0 never saw;
session 1's first keyframe carries the agent's guess of its frame in session 0's (identity: the front-end
starts the new map at the IMU-propagated pose) with the propagation's sigmas. The true frame is off by
the propagation error. Then the UAV flies back through a door into room A: mapped ground.

* A guess within its sigmas: session 1 goes into session 0's map at its first keyframe (no place
  recognition could: room B is new), the loops on the return confirm the merge and correct session 1.
* A guess 4 m (or 0.6 m) off with a 5 (2) cm sigma: the loops on the return contradict it, the robust pose
  graph rejects its edge and the merge is undone; place recognition then merges the sessions right.
  Never a wrong map.
* No guess: session 1 stays a map of its own while it sees nothing session 0 saw.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest
import twin_rooms as tr
from test_backend import FAST, UAV_FROM_WORLD, Server, sigma_at_merge_write, stream

from hivemap.maps.geometry import Sim3, so3_exp
from hivemap.protocol import Keyframe, MapPoints, Message
from hivemap.server.backend import preset

B_SHIFT = np.array([10.0, 0.0, 0.0])


def _about(p: np.ndarray, R: np.ndarray, dt: np.ndarray) -> Sim3:
    """A turn ``R`` about point ``p`` followed by a shift ``dt`` (a propagation error at ``p``)."""
    return Sim3(R, p - R @ p + dt, 1.0)


def sessions(
    error: tuple[np.ndarray, float], sigma: tuple[float, float] | None, seed: int = 5, back: bool = True
) -> tuple[list[Message], list[Message], list[np.ndarray], Sim3]:
    """Session 0 (room A, then the door) and session 1 (room B, the door, room A backwards if ``back``),
    session 1 sent in its true frame: session 0's moved by ``error`` (shift m, yaw deg) about session 1's
    first camera. ``sigma``: the guess's sigmas on session 1's first keyframe (None: no guess). Returns
    both streams, session 1's true poses and session 1's true local frame."""
    rng = np.random.default_rng(seed)
    a = tr.PointSet(*tr.room(rng), 0)
    bx, bd = tr.room(rng)
    b = tr.PointSet(bx + B_SHIFT, bd, 300000)
    door = tr.doorway(rng, 200000)
    s0_path = tr.path(rng, np.linspace(-6, 8, 10))
    s0 = tr.stream(rng, s0_path, [[a, door] if k >= 7 else [a] for k in range(10)], UAV_FROM_WORLD, 0)
    s1_path = tr.path(rng, np.linspace(-6, 8, 10), offset=B_SHIFT)  # x 4 .. 18
    # without the return, room B only: nothing session 0 saw
    sees: list[list[tr.PointSet]] = [[b, door] if k >= 7 and back else [b] for k in range(10)]
    if back:
        s1_path += tr.path(rng, np.linspace(8, -6, 12))
        sees += [[a, door] if k < 3 else [a] for k in range(12)]
    first = UAV_FROM_WORLD.apply(s1_path[0][:3, 3])
    shift, yaw = error
    truth1 = _about(first, so3_exp(np.array([0.0, np.radians(yaw), 0.0])), shift) @ UAV_FROM_WORLD
    s1 = tr.stream(rng, s1_path, sees, truth1, 1000)
    s1 = [replace(m, session=1) if isinstance(m, Keyframe | MapPoints) else m for m in s1]
    if sigma is not None:
        i = next(i for i, m in enumerate(s1) if isinstance(m, Keyframe))
        s1[i] = replace(s1[i], prev_session_from_world=np.eye(4), prev_session_sigma=np.array(sigma))
    return s0, s1, s1_path, truth1


def _run(tmp_path: Path, s0: list[Message], s1: list[Message]) -> dict[str, Any]:
    srv = Server(tmp_path / "data", preset("default", scheduler=FAST))
    try:
        with stream(srv, "uav1", "uav", s0) as agent:
            srv.wait_idle(300)
            _, errors = agent.send_all(s1, first_seq=len(s0) + 1)  # the same mission goes on
            assert not errors, errors
            srv.wait_idle(300)
        out: dict[str, Any] = srv.call(lambda: {
            "merges": [dict(r) for r in srv.backend.merges],
            "loops": [dict(r) for r in srv.backend.loops],
            "maps": {mid: (sorted(m.agents), {k: kf.world_from_cam.copy() for k, kf in m.keyframes.items()})
                     for mid, m in srv.hive.stack.maps.items()},
        })  # fmt: skip
        base = f"http://127.0.0.1:{srv.port}"
        out["events"] = httpx.get(base + "/events", params={"kind": "merge", "limit": 1000}).json()["events"]
        out["rest_maps"] = httpx.get(base + "/maps").json()
    finally:
        srv.stop()
    return out


def _session1_errors(kfs: dict[tuple[str, int], np.ndarray], s1_path: list[np.ndarray]) -> np.ndarray:
    """Session 1's keyframe position errors (m) in session 0's frame (the map's: uav1 is its only agent)."""
    est = np.array([kfs[("uav1#1", 1000 + k)][:3, 3] for k in range(len(s1_path))])
    true = UAV_FROM_WORLD.apply(np.array([T[:3, 3] for T in s1_path]))
    return np.asarray(np.linalg.norm(est - true, axis=1))


def test_new_session_is_merged_back_by_its_guess_and_corrected_on_return(tmp_path: Path) -> None:
    s0, s1, s1_path, truth1 = sessions((np.array([0.25, -0.15, 0.1]), 1.0), sigma=(0.3, 2.0))
    world = np.array([T[:3, 3] for T in s1_path])
    guess_err = np.linalg.norm(truth1.apply(world) - UAV_FROM_WORLD.apply(world), axis=1)
    assert guess_err.min() > 0.25 and guess_err.max() < 0.5, guess_err  # what the loop has to correct
    out = _run(tmp_path, s0, s1)
    guess = [r for r in out["merges"] if r.get("by") == "session_guess"]
    assert len(guess) == 1 and len(out["merges"]) == 1, out["merges"]
    g = guess[0]
    assert g["query"] == ["uav1#1", 1000] and g["candidate"] == ["uav1", 9], g
    assert abs(g["sigma_trans_m"] - 0.3) < 1e-9 and abs(g["sigma_rot_deg"] - 2.0) < 1e-9
    # the loop on the return to room A joins the two sessions and confirms the guess (its duplicate
    # points fused, the rest of room A is covisible: one loop per place, as in ORB-SLAM)
    across = [lp for lp in out["loops"] if {lp["query"][0], lp["candidate"][0]} == {"uav1", "uav1#1"}
              and not lp.get("rejected")]  # fmt: skip
    assert len(across) >= 1, out["loops"]
    assert g.get("on_trial") is False and not g.get("undone") and g["confirmations"] >= 1, g
    # one map; session 1 corrected from the guess's error (0.25-0.35 m at its keyframes) to the loops'
    maps = list(out["maps"].values())
    assert len(maps) == 1 and maps[0][0] == ["uav1", "uav1#1"], [m[0] for m in maps]
    err = _session1_errors(maps[0][1], s1_path)
    print(f"guess merge confirmed; session 1 error max {err.max():.3f} m mean {err.mean():.3f} m")
    assert err.max() < 0.1, err
    # the merge event says what it rests on; REST lists one map holding both sessions
    events = [e for e in out["events"] if (e["data"] or {}).get("by") == "session_guess"]
    assert len(events) == 1 and "target" in events[0]["data"], out["events"]
    rest = out["rest_maps"]["maps"]
    assert len(rest) == 1 and sorted(rest[0]["agents"]) == ["uav1", "uav1#1"], rest


@pytest.mark.parametrize(("off_m", "sigma"), [(4.0, (0.05, 0.5)), (0.6, (0.02, 0.2))])
def test_wrong_guess_is_undone_and_the_sessions_merge_by_place_recognition(
    tmp_path: Path, off_m: float, sigma: tuple[float, float]
) -> None:
    """4 m off: the first loop refutes the guess. 0.6 m off: the first two loops are rejected (bending
    session 1 is cheaper), the third refutes it; the return's keyframes are looked up again against the
    split-off map and the sessions merge by place recognition."""
    s0, s1, s1_path, _ = sessions((np.array([off_m, 0.0, 0.0]), 0.0), sigma=sigma)
    out = _run(tmp_path, s0, s1)
    guess = [r for r in out["merges"] if r.get("by") == "session_guess"]
    assert len(guess) == 1 and guess[0].get("undone") and "robust pose graph" in guess[0]["undo_reason"], (
        guess
    )
    # never a wrong map: wherever both sessions share a map, session 1 is where it truly is
    together = [kfs for agents, kfs in out["maps"].values() if agents == ["uav1", "uav1#1"]]
    for kfs in together:
        err = _session1_errors(kfs, s1_path)
        assert err.max() < 0.1, err
    # and they do share one: place recognition merged them on the return
    assert len(together) == 1 and len(out["maps"]) == 1, [a for a, _ in out["maps"].values()]
    visual = [r for r in out["merges"] if r.get("by") != "session_guess" and not r.get("undone")]
    assert len(visual) == 1, out["merges"]
    print(
        f"{off_m} m off: {len(out['loops'])} loops, after undo + visual merge session 1 error max "
        f"{_session1_errors(together[0], s1_path).max():.3f} m"
    )


def test_session_without_guess_stays_apart_until_place_recognition(tmp_path: Path) -> None:
    s0, s1, _, _ = sessions((np.array([0.25, -0.15, 0.1]), 1.0), sigma=None, back=False)
    out = _run(tmp_path, s0, s1)
    assert out["merges"] == [], out["merges"]
    assert sorted(a for a, _ in out["maps"].values()) == [["uav1"], ["uav1#1"]]


def test_guess_goes_through_the_frame_the_previous_session_has_merged_into() -> None:
    """The previous session was merged into another agent's map (moved by a Sim(3)) and its last keyframe
    corrected there by a loop: the plan places the new session relative to that keyframe where it is now,
    and its edge measures the guess itself."""
    from hivemap.maps import Keyframe as MapKeyframe
    from hivemap.maps import MapStack
    from hivemap.maps.geometry import se3
    from hivemap.server.agents import AgentMap, AgentState
    from hivemap.server.backend import sessionguess
    from hivemap.server.loadgen import CAMERA

    def kf(folded: str, i: int, T: np.ndarray) -> MapKeyframe:
        z = np.zeros((0, 2), np.float32)
        return MapKeyframe(folded, i, float(i), T, CAMERA, z, np.zeros(0, np.uint8),
                           np.zeros((0, 32), np.uint8), np.zeros(0, np.int64))  # fmt: skip

    rng = np.random.default_rng(2)
    stack = MapStack()
    ugv_map, new_map = stack.new_map(), stack.new_map()
    moved = Sim3(so3_exp(rng.normal(0, 0.5, 3)), rng.normal(0, 5, 3), 1.0)  # session 0 into the UGV's map
    fix = Sim3(so3_exp(np.array([0, 0, 0.02])), np.array([0.1, -0.2, 0.05]), 1.0)  # a loop's correction there
    vio_last = se3(so3_exp(rng.normal(0, 0.3, 3)), rng.normal(0, 3, 3))
    vio_first = se3(so3_exp(rng.normal(0, 0.3, 3)), rng.normal(0, 3, 3))
    guess = se3(so3_exp(np.array([0.0, 0.0, 0.1])), np.array([0.5, 0.0, 0.0]))  # prev VIO from new VIO
    ugv_map.agents.update({"ugv1", "uav1"})
    ugv_map.add_keyframe(kf("uav1", 7, (fix @ moved).transform_pose(vio_last)))
    ugv_map.keyframes[("uav1", 7)].vio_from_cam = vio_last
    new_map.agents.add("uav1#1")
    new_map.add_keyframe(kf("uav1#1", 0, vio_first))
    new_map.keyframes[("uav1#1", 0)].vio_from_cam = vio_first
    agent = AgentState("uav1")
    prev = AgentMap("uav1", 0, "uav1", CAMERA, "m", 0, global_from_vio=moved)
    new = AgentMap("uav1#1", 1, "uav1#1", CAMERA, "m", 1)
    agent.maps = {0: prev, 1: new}
    assert sessionguess.previous_session(agent, new, stack) is prev
    plan = sessionguess.plan(stack, prev, new, ("uav1#1", 0), guess, np.array([0.3, 2.0]), lambda f: "uav")
    assert not isinstance(plan, str)
    assert (plan.target, plan.source) == (ugv_map.id, new_map.id)
    expected = (fix @ moved).transform_pose(guess @ vio_first)
    np.testing.assert_allclose(plan.target_from_source.transform_pose(vio_first), expected, atol=1e-9)
    np.testing.assert_allclose(plan.edge.measured.matrix(), np.linalg.inv(vio_last) @ guess @ vio_first,
                               atol=1e-9)  # fmt: skip
    assert plan.edge.candidate == ("uav1", 7) and abs(plan.edge.sigma_trans - 0.3) < 1e-12


def test_a_solve_during_the_guess_merge_sees_the_new_session_held_by_its_guess(tmp_path: Path) -> None:
    """The merge is written to the store (an await) after the maps are merged in memory: a covariance solve
    that runs then (the back-end's scheduled ones, the team services' readers) must see the new session
    joined to the map by the guess's edge. Without the edge the session hangs on its loose gauge prior
    (100 m) and its position sigma is metres (a live UGV's ORCA radius read 200 m)."""
    s0, s1, _, _ = sessions((np.array([0.25, -0.15, 0.1]), 1.0), sigma=(0.3, 2.0), back=False)
    srv = Server(tmp_path / "data", preset("default", scheduler=FAST))
    try:
        seen = sigma_at_merge_write(srv, {"uav1", "uav1#1"}, "uav1#1")
        with stream(srv, "uav1", "uav", s0) as agent:
            srv.wait_idle(300)
            _, errors = agent.send_all(s1, first_seq=len(s0) + 1)
            assert not errors, errors
            srv.wait_idle(300)
        merges = srv.call(lambda: [dict(r) for r in srv.backend.merges])
    finally:
        srv.stop()
    assert [r.get("by") for r in merges] == ["session_guess"], merges
    assert len(seen) == 1, seen
    # the guess's sigma (0.3 m, 2 deg at ~3 m from session 0's last keyframe) plus session 0's own
    print(f"new session's position sigma while the merge is written: {seen[0][1]:.3f} m")
    assert seen[0][1] < 1.0, seen
