"""Marker carriers on a live agent (issue 25): a carrier in view becomes rendezvous messages whose pose
matches ground truth, anchored to a keyframe the agent already emitted; none with detection off (the
carrier still masked out of tracking); a bad
layout stops the agent at start-up with one line; today's server keeps the link and every keyframe."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
from marker_carriers import board_carrier

from hivemap.client import Agent
from hivemap.client.agent import AgentOptions
from hivemap.client.frontend.events import KeyframeEvent
from hivemap.client.frontend.markers import MarkerOptions
from hivemap.client.frontend.synthetic import SyntheticSequence, body_from_cam_pitched, make_sequence
from hivemap.client.runner import RunnerOptions
from hivemap.maps.geometry import rotation_angle_deg, se3, se3_inverse
from hivemap.protocol import Rendezvous

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "server"))

UGV_CAM = body_from_cam_pitched(0.0)
UGV_AT = se3(np.eye(3), np.array([-1.5, 8.0, 0.8]))  # a parked UGV whose roof board is 0.8 m up
CARRIERS = {"ugv": board_carrier("ugv", 10, 0.5, 0.1, UGV_CAM)}


@pytest.fixture(scope="module")
def flight() -> tuple[SyntheticSequence, list]:
    """40 frames (2 s) of a UAV whose camera sees the parked UGV's board from ~1.2 s on; rendered once."""
    seq = make_sequence(40, rate=20.0, seed=3)
    seq.scene.add_marker_carrier(CARRIERS["ugv"], UGV_AT)
    return seq, [seq.images(i) for i in range(len(seq.times))]


def _run(
    flight: tuple[SyntheticSequence, list], agent: Agent
) -> tuple[list[Rendezvous], list[KeyframeEvent]]:
    seq, images = flight
    seen: list[Rendezvous] = []
    agent.on_rendezvous(seen.append)
    kfs: list[KeyframeEvent] = []
    chained = agent.core.on_event

    def on_event(ev: object) -> None:
        if isinstance(ev, KeyframeEvent):
            kfs.append(ev)
        if chained is not None:
            chained(ev)

    agent.core.on_event = on_event
    prev = None
    for t, (left, right) in zip(seq.times, images, strict=True):
        agent.feed_imu_batch(seq.imu_between(prev, float(t)))
        agent.feed_stereo(float(t), left, right)
        prev = float(t)
    return seen, kfs


def _agent(flight: tuple[SyntheticSequence, list], markers: MarkerOptions | None = None) -> Agent:
    runner = RunnerOptions(progress=False, corrections_max_wait_s=0.0, markers=markers or MarkerOptions())
    opts = AgentOptions(runner=runner)
    return Agent(flight[0].rig, agent_id="uav1", imu_noise={}, options=opts, carriers=CARRIERS)


def _cam_truth(seq: SyntheticSequence, t: float) -> np.ndarray:
    i = int(np.argmin(np.abs(seq.times - t)))
    return seq.world_from_body[i] @ seq.rig.body_from_left


def test_rendezvous_match_ground_truth(flight: tuple[SyntheticSequence, list]) -> None:
    seq = flight[0]
    agent = _agent(flight)
    seen, kfs = _run(flight, agent)
    agent.close()
    assert len(seen) >= 5 and agent.rendezvous is not None and agent.rendezvous.observations == len(seen)
    # one detection per frame: the rendezvous stream reuses the carrier mask's
    cm = agent.core.frontend.carrier_mask
    assert cm is not None and cm.stats.frames == len(seq.times) and agent.rendezvous.cpu_s == 0.0
    emitted_before: set[int] = set()
    kf_t = {e.kf_id: e.timestamp for e in kfs}
    for r in seen:
        gt = se3_inverse(_cam_truth(seq, r.timestamp)) @ UGV_AT @ UGV_CAM
        d = float(np.linalg.norm(gt[:3, 3]))
        assert r.observed_agent == "ugv" and r.session == 0
        assert np.linalg.norm(r.cam_from_observed[:3, 3] - gt[:3, 3]) <= 0.02 * d
        assert rotation_angle_deg(gt[:3, :3].T @ r.cam_from_observed[:3, :3]) <= 1.0
        # the reference keyframe was emitted (its message precedes this one) and the relative pose is
        # the agent's tracking: against ground truth within VIO drift over a fraction of a second
        assert r.ref_kf_id in kf_t and kf_t[r.ref_kf_id] <= r.timestamp
        ref_gt = se3_inverse(_cam_truth(seq, kf_t[r.ref_kf_id])) @ _cam_truth(seq, r.timestamp)
        assert np.linalg.norm(r.ref_from_cam[:3, 3] - ref_gt[:3, 3]) < 0.05
        assert rotation_angle_deg(ref_gt[:3, :3].T @ r.ref_from_cam[:3, :3]) < 0.5
        emitted_before.add(r.ref_kf_id)
    assert emitted_before


def test_no_rendezvous_with_detection_off(flight: tuple[SyntheticSequence, list]) -> None:
    agent = _agent(flight, MarkerOptions(enabled=False))
    seen, _ = _run(flight, agent)
    agent.close()
    assert seen == [] and agent.rendezvous is None
    # the carrier still moves through the images: masked out of tracking all the same
    cm = agent.core.frontend.carrier_mask
    assert cm is not None and cm.stats.frames_masked >= 10


def test_streamed_rendezvous_keep_the_link_and_every_keyframe(
    flight: tuple[SyntheticSequence, list], tmp_path: Path
) -> None:
    """The rendezvous go through the outbox with the keyframes; the server (one that may not apply them
    yet) keeps the connection and stores every keyframe, and nothing stays unsent."""
    from srv_helpers import TOKENS, ServerProcess, write_config

    server = ServerProcess(tmp_path / "data", write_config(tmp_path / "server.toml")).start()
    try:
        agent = _agent(flight)
        agent.connect(server.ws_url, TOKENS["uav1"], tmp_path / "agent")
        seen, kfs = _run(flight, agent)
        assert agent.close(timeout=30) == 0
        info = server.json("/agents/uav1")
    finally:
        server.stop()
    assert len(seen) >= 5
    assert agent.link_error is None and agent.link_stats.connects == 1
    assert info["keyframes"] == len(kfs) and info["pending_keyframes"] == 0
