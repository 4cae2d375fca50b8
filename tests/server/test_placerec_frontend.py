"""Place recognition on maps built by the real front-end (hivemap.client.frontend) from rendered
stereo-inertial sequences of its self-contained synthetic scene: real ORB keypoints, triangulated
points with their real noise, each agent in its own VIO frame.

Agents A and B fly different circles (radius 12 m / 11 m, height 3 m / 3.8 m) in the same scene;
agent C flies in another scene (different textures). Ground truth of ``vioB_from_vioA`` comes from the
rendered ground-truth poses of the keyframes.
"""

from __future__ import annotations

import numpy as np
import pytest

from hivemap.client.frontend.convert import map_from_frontend
from hivemap.client.frontend.synthetic import SyntheticSequence, make_sequence
from hivemap.client.frontend.tracker import Frontend
from hivemap.maps import Keyframe, Map, MapPoint
from hivemap.maps.geometry import Sim3, rotation_angle_deg, se3_inverse
from hivemap.maps.vocabulary import default_vocabulary
from hivemap.server.placerec import PlaceRecognizer

N_FRAMES = 24


def _run(seq: SyntheticSequence) -> Frontend:
    fe = Frontend(seq.rig, imu_params={})
    t_prev = None
    for i in range(N_FRAMES):
        t = float(seq.times[i])
        left, right = seq.images(i)
        fe.process(t, left, right, seq.imu_between(t_prev, t))
        t_prev = t
    fe.flush()
    return fe


def _world_from_vio(seq: SyntheticSequence, m: Map) -> np.ndarray:
    kf = m.keyframes[min(m.keyframes)]
    i = int(np.argmin(np.abs(seq.times - kf.timestamp)))
    return seq.world_from_body[i] @ seq.rig.body_from_left @ se3_inverse(kf.world_from_cam)


@pytest.fixture(scope="module")
def agents() -> dict:
    out = {}
    for name, mid, kw in (
        ("A", 0, {"seed": 3}),
        ("B", 1, {"seed": 3, "height": 3.8, "radius": 11.0}),
        ("C", 2, {"seed": 8}),
    ):
        seq = make_sequence(N_FRAMES, **kw)  # type: ignore[arg-type]
        m = map_from_frontend(_run(seq), f"uav{name}", mid)
        out[name] = (seq, m)
    return out


def _recognizer(maps: dict[int, Map]) -> PlaceRecognizer:
    pr = PlaceRecognizer(default_vocabulary())
    for mid, m in maps.items():
        for kf in m.keyframes.values():
            pr.add_keyframe(mid, kf)
    return pr


def _scaled(m: Map, s: float, map_id: int) -> Map:
    """The map as a monocular agent would hold it: every length multiplied by ``s``."""
    S = Sim3(np.eye(3), np.zeros(3), s)
    out = Map(map_id)
    for p in m.points.values():
        out.add_point(MapPoint(p.agent_id, p.id, S.apply(p.xyz), p.descriptor))
    for kf in m.keyframes.values():
        out.add_keyframe(
            Keyframe(kf.agent_id, kf.id, kf.timestamp, S.transform_pose(kf.world_from_cam), kf.camera,
                     kf.keypoints, kf.octaves, kf.descriptors, kf.point_ids.copy())
        )  # fmt: skip
    return out


@pytest.mark.slow
@pytest.mark.parametrize("scale", [1.0, 2.5])
def test_merge_of_frontend_maps_matches_ground_truth(agents, scale: float) -> None:
    (sa, ma), (sb, mb) = agents["A"], agents["B"]
    mb_s = mb if scale == 1.0 else _scaled(mb, scale, 1)
    true_rigid = se3_inverse(_world_from_vio(sb, mb)) @ _world_from_vio(sa, ma)
    true = Sim3(np.eye(3), np.zeros(3), scale) @ Sim3.from_se3(true_rigid)
    maps = {0: ma, 1: mb_s}
    pr = _recognizer(maps)
    confirmed = None
    for k in sorted(ma.keyframes):
        r = pr.detect(maps, 0, k, loop=False, fix_scale=scale == 1.0)
        if r.confirmed is not None:
            confirmed = r.confirmed
            break
    assert confirmed is not None
    S = confirmed.target_from_source
    # front-end drift over these 4 m is ~1 cm / 0.05 deg (measured errors: < 0.1 deg, < 1 cm);
    # issue 6 acceptance is 0.2 m / 1 deg, we require 0.5 deg, 5 cm and scale to 1 %
    assert rotation_angle_deg(S.R @ true.R.T) < 0.5
    assert np.linalg.norm(S.t - true.t) / scale < 0.05
    assert abs(S.s / scale - 1) < 0.01
    assert confirmed.n_inliers >= 40


@pytest.mark.slow
def test_no_merge_between_different_scenes(agents) -> None:
    (_, ma), (_, mc) = agents["A"], agents["C"]
    maps = {0: ma, 2: mc}
    pr = _recognizer(maps)
    pr.options = type(pr.options)(use_feasibility=False)  # verify every candidate geometrically
    for k in sorted(ma.keyframes):
        r = pr.detect(maps, 0, k, loop=False)
        assert r.detection is None
        assert r.candidates and not any(c.accepted for c in r.candidates)
