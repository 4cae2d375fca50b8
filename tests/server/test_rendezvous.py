"""Rendezvous observations on the server end to end (real server, real WebSocket, real store).

A UAV and a UGV map two worlds that share no points (place recognition cannot merge them), related by a
known transform. The UAV sees the UGV's markers between its keyframes: each observation's relative pose is
the truth (the UGV's pose at that time interpolated between its keyframes, slerp and linear, as the
server's model) plus 1 cm / 0.1 deg of noise. Truth: the UGV's map frame from the UAV's is
``UGV_FROM_WORLD @ B_from_W @ inv(UAV_FROM_WORLD)``.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Any

import httpx
import numpy as np
from scipy.spatial.transform import Rotation, Slerp
from test_backend import FAST, UAV_FROM_WORLD, Server, stream

from hivemap.maps.geometry import Sim3, rotation_angle_deg, se3, se3_inverse, so3_exp
from hivemap.protocol import Keyframe, Message, Rendezvous
from hivemap.server.backend import preset
from hivemap.server.backend_synth import UGV_FROM_WORLD, agent_stream, make_world

# the UGV's world (its points' frame B) in the UAV's world W: 3 m below, 2 m aside, turned 10 deg
W_FROM_B = se3(so3_exp(np.array([0.0, 0.0, np.radians(10.0)])), np.array([1.0, 2.0, -3.0]))
TRUE = UGV_FROM_WORLD @ Sim3.from_se3(se3_inverse(W_FROM_B)) @ UAV_FROM_WORLD.inverse()
SIGMA_ROT, SIGMA_TRANS = 0.003, 0.02  # the covariance the observations carry (rad, m)


def at(poses: np.ndarray, t: float) -> np.ndarray:
    """The pose at time ``t`` between keyframes at integer times (slerp, linear)."""
    k = int(np.floor(t))
    a = t - k
    R = Slerp([0.0, 1.0], Rotation.from_matrix(poses[k : k + 2, :3, :3]))(a).as_matrix()
    return se3(R, (1 - a) * poses[k, :3, 3] + a * poses[k + 1, :3, 3])


def world_poses(true_local: np.ndarray, local_from_world: Sim3, world_from: np.ndarray) -> np.ndarray:
    inv = local_from_world.inverse()
    return np.array([world_from @ inv.transform_pose(T) for T in true_local])


def setup(seed: int = 3, up: bool = False) -> tuple[list[Message], list[Message], np.ndarray, np.ndarray]:
    """Both agents' streams and their true keyframe poses in W; ``up``: the keyframes carry their IMU up
    directions (exact; W's and B's z axes are both up)."""
    rng = np.random.default_rng(seed)
    pa, da = make_world(rng, 2500, (-20, 30))
    pb, db = make_world(rng, 2500, (-20, 30))
    tilt = 0.0 if up else None
    uav, uav_true, _ = agent_stream(rng, pa, da, np.linspace(-6, 8, 10), UAV_FROM_WORLD, up_tilt_deg=tilt)
    ugv, ugv_true, _ = agent_stream(rng, pb, db, np.linspace(-6, 8, 10), UGV_FROM_WORLD, point_id0=50000,
                                    up_tilt_deg=tilt)  # fmt: skip
    return (
        uav,
        ugv,
        world_poses(uav_true, UAV_FROM_WORLD, np.eye(4)),
        world_poses(ugv_true, UGV_FROM_WORLD, W_FROM_B),
    )


def observation(uav_w: np.ndarray, seen_w: np.ndarray, t: float, rng: np.random.Generator) -> Rendezvous:
    """The UAV at time ``t`` (reference keyframe floor(t)) sees the agent whose poses are ``seen_w``, and
    names the UGV."""
    k = int(np.floor(t))
    cam = at(uav_w, t)
    noise = se3(so3_exp(rng.normal(0, np.radians(0.1), 3)), rng.normal(0, 0.01, 3))
    return Rendezvous(
        timestamp=float(t), observed_agent="ugv1", marker_ids=np.array([3, 4], dtype=np.int64), ref_kf_id=k,
        ref_from_cam=se3_inverse(uav_w[k]) @ cam, cam_from_observed=se3_inverse(cam) @ at(seen_w, t) @ noise,
        covariance=np.diag([SIGMA_ROT**2] * 3 + [SIGMA_TRANS**2] * 3), reproj_rms_px=0.4,
    )  # fmt: skip


def uav_transform(srv: Server) -> Sim3:
    return srv.call(lambda: srv.hive.agents["uav1"].maps[0].global_from_vio)  # type: ignore[no-any-return]


def rest(srv: Server, path: str, **params: Any) -> Any:
    r = httpx.get(f"http://127.0.0.1:{srv.port}{path}", params=params, timeout=10)
    assert r.status_code == 200, r.text
    return r.json()


def events(srv: Server, kind: str) -> list[dict[str, Any]]:
    return rest(srv, "/events", kind=kind, limit=1000)["events"]  # type: ignore[no-any-return]


def check_transform(est: Sim3, tol_m: float = 0.05, tol_deg: float = 0.5) -> tuple[float, float]:
    """The estimated UAV-map -> UGV-map transform against the truth at the UAV's keyframes."""
    pts = UAV_FROM_WORLD.apply(np.array([[x, 0.0, 0.0] for x in np.linspace(-6, 8, 10)]))
    err_m = float(np.max(np.linalg.norm(est.apply(pts) - TRUE.apply(pts), axis=1)))
    err_deg = rotation_angle_deg(est.R @ TRUE.R.T)
    assert err_m < tol_m and err_deg < tol_deg, (err_m, err_deg)
    return err_m, err_deg


def test_rendezvous_merge_the_maps_by_the_true_transform_and_survive_a_restart(tmp_path: Path) -> None:
    uav, ugv, uav_w, ugv_w = setup()
    rng = np.random.default_rng(7)
    srv = Server(tmp_path / "data", preset("default", scheduler=FAST))
    try:
        stream(srv, "ugv1", "ugv", ugv).close()
        agent = stream(srv, "uav1", "uav", uav)
        srv.wait_idle(120)
        assert len(rest(srv, "/maps")["maps"]) == 2  # no place recognition between the worlds
        # two observations only: not enough to merge
        _, errors = agent.send_all([observation(uav_w, ugv_w, t, rng) for t in (1.3, 2.6)], len(uav) + 1)
        assert not errors, errors
        srv.wait_idle(60)
        assert len(rest(srv, "/maps")["maps"]) == 2
        assert {r["state"] for r in rest(srv, "/rendezvous")["rendezvous"]} == {"pending"}
        # a third and fourth, later: the maps merge by the transform they agree on
        _, errors = agent.send_all([observation(uav_w, ugv_w, t, rng) for t in (4.5, 6.7)], len(uav) + 3)
        assert not errors, errors
        srv.wait_idle(120)
        maps = rest(srv, "/maps")["maps"]
        assert len(maps) == 1, maps
        merges = events(srv, "rendezvous_merge")
        # the third merges them (or the third and fourth, if they arrive within one agreement interval);
        # a later one is an edge of the merged map
        assert len(merges) == 1 and merges[0]["data"]["n_observations"] >= 3, merges
        err_m, err_deg = check_transform(uav_transform(srv))
        print(f"rendezvous merge: {err_m * 100:.1f} cm, {err_deg:.2f} deg from the truth")
        listing = rest(srv, f"/maps/{maps[0]['id']}/rendezvous")["rendezvous"]
        assert [r["state"] for r in listing] == ["kept"] * 4, listing
        assert all(r["residual_m"] < 0.05 and r["position_map"] == maps[0]["id"] for r in listing), listing
        agent.close()
    finally:
        srv.stop()
    srv = Server(tmp_path / "data", preset("default", scheduler=FAST))
    try:
        srv.wait_idle(60)
        again = rest(srv, "/rendezvous")["rendezvous"]
        assert [(r["id"], r["state"]) for r in again] == [(r["id"], "kept") for r in listing], again
        assert len(rest(srv, "/maps")["maps"]) == 1
        check_transform(uav_transform(srv))
    finally:
        srv.stop()


def test_wrong_observed_agent_is_rejected_and_changes_nothing(tmp_path: Path) -> None:
    """The UAV reads a marker id wrong: it names the UGV but sees another UAV 4 m away. Among the
    observations between the maps it is refused at the merge; within the merged map the robust pose graph
    rejects it; the maps are as without it. A right observation within the merged map starts no pose graph
    (the map satisfies it) and is kept by the next one."""
    uav, ugv, uav_w, ugv_w = setup()
    other = np.array([T @ se3(so3_exp(np.array([0.0, 0.5, 0.0])), np.array([4.0, 0.0, 1.0])) for T in ugv_w])
    rng = np.random.default_rng(8)
    srv = Server(tmp_path / "data", preset("default", scheduler=FAST))
    try:
        stream(srv, "ugv1", "ugv", ugv).close()
        agent = stream(srv, "uav1", "uav", uav)
        srv.wait_idle(120)
        obs = [observation(uav_w, other, 0.8, rng)]
        obs += [observation(uav_w, ugv_w, t, rng) for t in (1.3, 3.5, 5.6)]
        _, errors = agent.send_all(obs, len(uav) + 1)
        assert not errors, errors
        srv.wait_idle(120)
        assert len(rest(srv, "/maps")["maps"]) == 1
        check_transform(uav_transform(srv))
        before = srv.call(lambda: {k: kf.world_from_cam.copy() for m in srv.hive.stack.maps.values()
                                   for k, kf in m.keyframes.items()})  # fmt: skip
        # a right one within the merged map: the map already satisfies it, so it asks for no pose graph
        # of its own and waits for the next one's verdict
        n_graphs = len(events(srv, "pose_graph"))
        _, errors = agent.send_all([observation(uav_w, ugv_w, 6.7, rng)], len(uav) + 5)
        assert not errors, errors
        srv.wait_idle(120)
        assert len(events(srv, "pose_graph")) == n_graphs
        settled = {r["id"]: r for r in rest(srv, "/rendezvous")["rendezvous"]}[5]
        assert settled["state"] == "judging" and "agrees with the map" in settled["reason"], settled
        # a wrong one within the merged map: far off the map, it asks for one, which judges both
        _, errors = agent.send_all([observation(uav_w, other, 7.4, rng)], len(uav) + 6)
        assert not errors, errors
        srv.wait_idle(120)
        graphs = events(srv, "pose_graph")
        assert len(graphs) > n_graphs
        # each solve reports its CPU time in the solver's process beside its wall time
        solved = [e["data"] for e in graphs if "ms" in e["data"]]
        assert solved and all(d["cpu_ms"] > 0 and d["n_edges"] > 0 for d in solved), solved
        states = {r["id"]: r for r in rest(srv, "/rendezvous")["rendezvous"]}
        expected = ["rejected", "kept", "kept", "kept", "kept", "rejected"]
        assert [states[i]["state"] for i in sorted(states)] == expected, states
        assert "inconsistent" in states[1]["reason"] and "robust pose graph" in states[6]["reason"], states
        rejected = events(srv, "rendezvous_rejected")
        assert sorted(e["data"]["id"] for e in rejected) == [1, 6], rejected
        after = srv.call(lambda: {k: kf.world_from_cam.copy() for m in srv.hive.stack.maps.values()
                                  for k, kf in m.keyframes.items()})  # fmt: skip
        # the right one (1 cm / 0.1 deg of noise) joins that pose graph and may move keyframes by about
        # its noise; the wrong one, 4 m off, would move them by metres
        moved = max(float(np.linalg.norm(after[k][:3, 3] - before[k][:3, 3])) for k in before)
        assert moved < 0.03, moved
        check_transform(uav_transform(srv))
        agent.close()
    finally:
        srv.stop()


def test_observation_of_a_keyframe_not_arrived_yet_is_held_until_it_arrives(tmp_path: Path) -> None:
    """Acked and kept (held) while its reference keyframe is on its way, and while its observed agent is
    unknown; resolved when they arrive."""
    uav, ugv, uav_w, ugv_w = setup()
    rng = np.random.default_rng(9)
    last = max(i for i, m in enumerate(uav) if isinstance(m, Keyframe))
    srv = Server(tmp_path / "data", preset("default", scheduler=FAST))
    try:
        agent = stream(srv, "uav1", "uav", uav[:last])  # keyframes 0-8
        obs = [observation(uav_w, ugv_w, t, rng) for t in (1.2, 3.4, 5.5, 8.5)]  # 8.5: keyframe 8 ok
        obs.append(observation(uav_w, ugv_w, 8.5, rng))
        obs[-1] = replace(obs[-1], ref_kf_id=9, ref_from_cam=se3_inverse(uav_w[9]) @ at(uav_w, 8.5))
        acks, errors = agent.send_all(obs, last + 1)
        assert not errors and len(acks) == 5, errors
        held = rest(srv, "/rendezvous", state="held")["rendezvous"]
        assert len(held) == 5 and "not known yet" in held[0]["reason"], held
        assert "not arrived yet" in held[-1]["reason"], held[-1]
        _, errors = agent.send_all([uav[last]], last + 6)  # keyframe 9
        assert not errors
        srv.wait_idle(60)
        held = rest(srv, "/rendezvous", state="held")["rendezvous"]
        assert len(held) == 5 and all("not known yet" in r["reason"] for r in held), held
        stream(srv, "ugv1", "ugv", ugv).close()  # the observed agent appears: they resolve and merge
        srv.wait_idle(120)
        assert rest(srv, "/rendezvous", state="held")["rendezvous"] == []
        assert len(rest(srv, "/maps")["maps"]) == 1
        agent.close()
    finally:
        srv.stop()


def test_a_wrong_rendezvous_merge_is_undone_and_the_maps_merge_right(tmp_path: Path) -> None:
    """Three observations of the wrong agent that agree with each other (the same marker misread while
    another agent drives the UGV's path 4 m ahead of it) merge the maps wrongly, on trial. Five right
    ones follow: the robust pose graph rejects the merge's edge, the merge is undone, and the right ones
    merge the maps by the true transform."""
    uav, ugv, uav_w, ugv_w = setup()
    # another agent on the UGV's path 4 m ahead of it: the wrong observations agree with each other
    ahead = np.array([se3(np.eye(3), np.array([4.0, 0.0, 0.0])) @ T for T in ugv_w])
    rng = np.random.default_rng(10)
    srv = Server(tmp_path / "data", preset("default", scheduler=FAST))
    try:
        stream(srv, "ugv1", "ugv", ugv).close()
        agent = stream(srv, "uav1", "uav", uav)
        srv.wait_idle(120)
        wrong = [observation(uav_w, ahead, t, rng) for t in (0.8, 1.9, 3.1)]
        _, errors = agent.send_all(wrong, len(uav) + 1)
        assert not errors, errors
        srv.wait_idle(120)
        assert len(rest(srv, "/maps")["maps"]) == 1, rest(srv, "/rendezvous")
        right = [observation(uav_w, ugv_w, t, rng) for t in (4.2, 5.3, 6.4, 7.5, 8.3)]
        _, errors = agent.send_all(right, len(uav) + 4)
        assert not errors, errors
        srv.wait_idle(120)
        undone = events(srv, "merge_undone")
        merges = events(srv, "rendezvous_merge")
        states = [r["state"] for r in rest(srv, "/rendezvous")["rendezvous"]]
        print("undone:", [e["message"] for e in undone], "merges:", len(merges), "states:", states)
        assert len(undone) == 1 and len(merges) == 2, (undone, merges)
        assert states == ["rejected"] * 3 + ["kept"] * 5, states
        assert len(rest(srv, "/maps")["maps"]) == 1
        check_transform(uav_transform(srv))
        agent.close()
    finally:
        srv.stop()


def far_observation(uav_w: np.ndarray, ugv_w: np.ndarray, t: float, rng: np.random.Generator) -> Rendezvous:
    """The UGV's roof board seen from afar: its PnP knows the board's tilt (the UGV's roll and pitch) to
    1.5 deg, its yaw to 0.2 deg and its position to 2 cm, and every observation of the sighting is off by
    the same 2 deg of tilt (one viewpoint, slowly changing: the error of one is the error of the next)."""
    obs = observation(uav_w, ugv_w, t, rng)
    T_wq = at(ugv_w, t)
    up_q = T_wq[:3, :3].T @ np.array([0.0, 0.0, 1.0])  # up in the UGV's camera
    across = np.cross(up_q, T_wq[:3, :3].T @ np.array([1.0, 0.0, 0.0]))
    across /= np.linalg.norm(across)
    tilted = obs.cam_from_observed @ se3(so3_exp(np.radians(2.0) * across), np.zeros(3))
    s_tilt, s_yaw = np.radians(1.5), np.radians(0.2)
    cov = np.diag([0.0] * 3 + [SIGMA_TRANS**2] * 3)
    cov[:3, :3] = s_tilt**2 * np.eye(3) + (s_yaw**2 - s_tilt**2) * np.outer(up_q, up_q)
    return replace(obs, cam_from_observed=tilted, covariance=cov)


def test_a_far_sighting_with_a_shared_tilt_error_does_not_tilt_the_ugv(tmp_path: Path) -> None:
    """Six observations of one sighting, each 2 deg off in tilt where its covariance says tilt is known
    to 1.5 deg (yaw 0.2 deg): the keyframes' IMU up directions know the two agents' relative tilt, so
    the merged map's transform is off by far less than the observations' shared 2 deg."""
    uav, ugv, uav_w, ugv_w = setup(up=True)
    rng = np.random.default_rng(11)
    srv = Server(tmp_path / "data", preset("default", scheduler=FAST))
    try:
        stream(srv, "ugv1", "ugv", ugv).close()
        agent = stream(srv, "uav1", "uav", uav)
        srv.wait_idle(120)
        obs = [far_observation(uav_w, ugv_w, t, rng) for t in (1.3, 2.4, 3.6, 4.7, 5.8, 6.9)]
        _, errors = agent.send_all(obs, len(uav) + 1)
        assert not errors, errors
        srv.wait_idle(120)
        assert len(rest(srv, "/maps")["maps"]) == 1, rest(srv, "/rendezvous")
        err_m, err_deg = check_transform(uav_transform(srv), tol_m=0.1, tol_deg=0.5)
        print(f"far sighting: {err_m * 100:.1f} cm, {err_deg:.2f} deg from the truth")
        agent.close()
    finally:
        srv.stop()
