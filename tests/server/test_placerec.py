"""Place recognition + Sim(3) on synthetic maps with known ground truth.

Scene: ~2500 3D points (with unique random ORB descriptors) in front of two agents' trajectories.
Each agent observes the points it sees (pixel noise 0.5 px x 1.2^octave, 3 flipped descriptor bits per
observation, plus clutter keypoints) and holds its own map with its own point ids. Agent B's map is the
world under a known Sim(3) (scale 2.5, as a monocular agent's), so place recognition must return
``B_from_A`` with the query in map A.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from hivemap.maps import Keyframe, Map, MapPoint, MapStack
from hivemap.maps.camera import PinholeCamera
from hivemap.maps.geometry import Sim3, rotation_angle_deg, se3, so3_exp
from hivemap.maps.kfdb import KeyframeDatabase
from hivemap.maps.vocabulary import default_vocabulary, hamming_matrix
from hivemap.server.placerec import (
    PlaceRecognizer,
    PlaceRecOptions,
    correction_of,
    estimate_sim3_ransac,
    match_bow,
    match_projected,
)
from hivemap.server.placerec.verify import verify

CAM = PinholeCamera(640, 480, 450.0, 450.0, 320.0, 240.0, (-0.1, 0.01, 0.0, 0.0))
S_TRUE = Sim3(so3_exp(np.array([0.3, -0.5, 1.2])), np.array([12.0, -7.0, 4.0]), 2.5)


def _flip(desc: np.ndarray, rng: np.random.Generator, n_bits: int) -> np.ndarray:
    bits = np.unpackbits(desc, axis=-1)
    for row in bits.reshape(-1, 256):
        row[rng.choice(256, n_bits, replace=False)] ^= 1
    return np.packbits(bits, axis=-1)


def _world(rng: np.random.Generator, n: int, x_range: tuple[float, float]) -> tuple[np.ndarray, np.ndarray]:
    """Points on three non-coplanar "facades" plus scattered clutter, in front of cameras looking +z."""
    x = rng.uniform(*x_range, n)
    kind = rng.integers(0, 3, n)
    z = np.where(kind == 0, 25.0 + rng.normal(0, 0.3, n), rng.uniform(12, 35, n))
    y = np.where(kind == 1, 4.0 + rng.normal(0, 0.1, n), rng.uniform(-6, 4, n))
    pts = np.stack([x, y, z], axis=1)
    desc = rng.integers(0, 256, size=(n, 32), dtype=np.uint8)
    return pts, desc


def _make_map(
    rng: np.random.Generator,
    map_id: int,
    agent: str,
    world_pts: np.ndarray,
    world_desc: np.ndarray,
    centres_x: np.ndarray,
    frame_from_world: Sim3,
    point_noise: float = 0.02,
    into: Map | None = None,
    id0: int = 0,
) -> Map:
    """A map of ``agent`` whose keyframes sit at ``centres_x``; ``into``/``id0``: append to an existing
    map with keyframe and point ids starting at ``id0`` (a second pass over the same place)."""
    m = Map(map_id) if into is None else into
    poses = []
    for cx in centres_x:
        R = so3_exp(rng.normal(0, 0.05, 3))
        poses.append(se3(R, np.array([cx, rng.normal(0, 0.3), rng.normal(0, 0.3)])))
    seen: dict[int, list[tuple[int, np.ndarray, int]]] = {}
    for k, T in enumerate(poses):
        pc = world_pts @ T[:3, :3] - T[:3, 3] @ T[:3, :3]
        uv, valid = CAM.project(pc)
        valid &= CAM.in_image(uv, margin=5) & (pc[:, 2] > 1)
        for i in np.flatnonzero(valid).tolist():
            seen.setdefault(i, []).append((k, uv[i], int(rng.integers(0, 4))))
    ids = {i: id0 + j for j, i in enumerate(sorted(i for i, obs in seen.items() if len(obs) >= 2))}
    for i, j in ids.items():
        xyz = frame_from_world.apply(world_pts[i] + rng.normal(0, point_noise, 3))
        m.add_point(MapPoint(agent, j, xyz, _flip(world_desc[i], rng, 2)))
    for k, T in enumerate(poses):
        rows = [(i, uv, octv) for i, obs in seen.items() if i in ids for (kk, uv, octv) in obs if kk == k]
        n_clutter = 150
        kps = np.array([uv for _, uv, _ in rows] + [[0.0, 0.0]] * n_clutter, dtype=np.float64)
        octs = np.array([o for _, _, o in rows] + list(rng.integers(0, 4, n_clutter)), dtype=np.uint8)
        kps[: len(rows)] += rng.normal(0, 0.5, (len(rows), 2)) * (1.2 ** octs[: len(rows), None])
        kps[len(rows) :] = rng.uniform([0, 0], [640, 480], (n_clutter, 2))
        desc = np.concatenate(
            [
                _flip(world_desc[[i for i, _, _ in rows]], rng, 3),
                rng.integers(0, 256, (n_clutter, 32), np.uint8),
            ]
        )
        pids = np.array([ids[i] for i, _, _ in rows] + [-1] * n_clutter, dtype=np.int64)
        T_map = frame_from_world.transform_pose(T)
        kf = Keyframe(agent, id0 + k, float(id0 + k), T_map, CAM, kps, octs, desc, pids)
        m.add_keyframe(kf)
    return m


@pytest.fixture(scope="module")
def scene() -> dict:
    rng = np.random.default_rng(42)
    pts, desc = _world(rng, 2500, (-20, 30))
    far_pts, far_desc = _world(rng, 1500, (200, 240))  # another part of the site, never seen by A or B
    a = _make_map(rng, 0, "uavA", pts, desc, np.linspace(-6, 8, 10), Sim3.identity())
    b = _make_map(rng, 1, "uavB", pts, desc, np.linspace(-2, 12, 10), S_TRUE)
    c = _make_map(rng, 2, "uavC", far_pts, far_desc, np.linspace(205, 220, 10), S_TRUE)
    # D: same appearance as the A/B area but a scrambled 3D structure (BoW alike, geometry not)
    shuffled = pts[rng.permutation(len(pts))]
    d = _make_map(rng, 3, "uavD", shuffled, desc, np.linspace(-6, 8, 10), Sim3.identity())
    return {"A": a, "B": b, "C": c, "D": d}


def _copy_map(m: Map) -> Map:
    out = Map(m.id)
    for p in m.points.values():
        out.add_point(MapPoint(p.agent_id, p.id, p.xyz.copy(), p.descriptor))
    for kf in m.keyframes.values():
        out.add_keyframe(
            Keyframe(kf.agent_id, kf.id, kf.timestamp, kf.world_from_cam.copy(), kf.camera, kf.keypoints,
                     kf.octaves, kf.descriptors, kf.point_ids.copy())
        )  # fmt: skip
    return out


def _recognizer(maps: dict[int, Map]) -> PlaceRecognizer:
    pr = PlaceRecognizer(default_vocabulary(), KeyframeDatabase())
    for mid, m in maps.items():
        for kf in m.keyframes.values():
            pr.add_keyframe(mid, kf)
    return pr


def _check_sim(est: Sim3, true: Sim3) -> None:
    # paper/issue tolerances: rotation < 0.5 deg, translation < 1 %, scale < 1 %
    assert rotation_angle_deg(est.R @ true.R.T) < 0.5
    assert np.linalg.norm(est.t - true.t) / np.linalg.norm(true.t) < 0.01
    assert abs(est.s / true.s - 1) < 0.01


def test_match_bow_and_projection_agree_with_brute_force() -> None:
    rng = np.random.default_rng(0)
    vocab = default_vocabulary()
    a = rng.integers(0, 256, (400, 32), dtype=np.uint8)
    perm = rng.permutation(400)
    b = _flip(a[perm], rng, 4)
    _, fa = vocab.transform(a)
    _, fb = vocab.transform(b)
    pairs = match_bow(fa, a, fb, b)
    # every returned pair is a true correspondence
    assert np.all(perm[pairs[:, 1]] == pairs[:, 0])
    # reference with loops: same node, best within 50 bits, ratio 0.75 to the second best, unique b
    D = hamming_matrix(a, b)
    ref: dict[int, tuple[int, int]] = {}
    for i in range(400):
        same = np.flatnonzero(fb.node_of_feature == fa.node_of_feature[i])
        if len(same) == 0:
            continue
        d = np.sort(D[i, same])
        j = int(same[np.argmin(D[i, same])])
        if d[0] <= 50 and (len(d) == 1 or d[0] < 0.75 * d[1]) and (j not in ref or ref[j][1] > d[0]):
            ref[j] = (i, int(d[0]))
    assert {(i, j) for j, (i, _) in ref.items()} == {tuple(p) for p in pairs.tolist()}
    # Random descriptors are ~128 bits from every centre, so 4 flipped bits often change the node at
    # level 2 and recall is lower than on real (clustered) ORB descriptors: require > 50 %.
    assert len(pairs) > 0.5 * 400
    # projection: points at their true pixel (+1 px) among 400 random keypoints
    kp = rng.uniform(0, 600, (400, 2))
    uv = kp[perm] + rng.normal(0, 1.0, (400, 2))
    m = match_projected(uv, b, kp, np.zeros(400, np.uint8), a, radius=5.0, max_distance=50)
    assert len(m) > 0.95 * 400 and np.all(perm[m[:, 0]] == m[:, 1])
    assert hamming_matrix(a[:1], b[:1]).shape == (1, 1)


def test_ransac_recovers_sim3_with_outliers() -> None:
    rng = np.random.default_rng(1)
    src = rng.uniform(-10, 10, (300, 3))
    tgt = S_TRUE.apply(src)
    tgt[:90] += rng.normal(0, 5.0, (90, 3))
    est = estimate_sim3_ransac(src, tgt, max_error=0.05, fix_scale=False)
    assert est is not None
    sim, inl = est
    _check_sim(sim, S_TRUE)
    assert inl[90:].all()


def test_merge_recovers_known_sim3_after_three_consistent_detections(scene) -> None:
    a, b = scene["A"], scene["B"]
    maps = {0: a, 1: b}
    pr = _recognizer(maps)
    results = [pr.detect(maps, 0, ("uavA", k), loop=False) for k in (5, 6, 7)]
    for r in results:
        assert r.detection is not None, [c.to_dict() for c in r.candidates]
        assert r.detection.candidate_map == 1
    assert [r.detection.consistent for r in results if r.detection] == [1, 2, 3]
    assert results[0].confirmed is None and results[1].confirmed is None
    det = results[2].confirmed
    assert det is not None
    _check_sim(det.target_from_source, S_TRUE)
    assert det.n_inliers >= 40
    # fused pairs are the same physical point: B's copy == S_TRUE applied to A's copy (point noise 2 cm)
    qa = np.array([a.points[k].xyz for k in det.query_points])
    cb = np.array([b.points[k].xyz for k in det.candidate_points])
    assert np.median(np.linalg.norm(S_TRUE.apply(qa) - cb, axis=1)) < 0.1 * S_TRUE.s
    # merging through the model with the detection (either map as target) puts the fused points together
    for target in (1, 0):
        stack = MapStack()
        stack.add_map(_copy_map(a))
        stack.add_map(_copy_map(b))
        tid, sid, sim, pairs = det.merge_args(target)
        merged = stack.merge(tid, sid, sim, pairs)
        assert len(merged.points) == len(a.points) + len(b.points) - len(set(pairs))
        # the merged map is in the target's frame: A's keyframe centres land where they truly are, to
        # 5 cm (metric) over the 14 m trajectory (issue 6 acceptance: < 0.2 m at merge; measured 2.3 cm)
        to_target = Sim3.identity() if target == 0 else S_TRUE
        for kf in a.keyframes.values():
            moved = merged.keyframes[kf.key].center
            assert np.linalg.norm(moved - to_target.apply(kf.center)) < 0.05 * to_target.s
    # every candidate is reported with a reason, JSON-able for /events
    ev = results[2].events()
    assert ev[-1]["type"] == "placerec" and ev[-1]["detection"]["confirmed"] is True
    assert all(e["reason"] for e in ev)


def test_retrieved_keyframes_of_one_place_are_verified_once_per_covisibility_group(scene) -> None:
    """B's ten keyframes see one place and are all covisible: a query retrieving all of them verifies one,
    the best-scoring keyframe of the group, and finds the same Sim(3) as verifying every one of them."""
    from dataclasses import replace

    maps = {0: scene["A"], 1: scene["B"]}
    pr = _recognizer(maps)
    grouped = pr.detect(maps, 0, ("uavA", 6), loop=False)
    pr_all = _recognizer(maps)
    pr_all.options = replace(pr_all.options, group_covisible=0)
    every = pr_all.detect(maps, 0, ("uavA", 6), loop=False)
    assert grouped.retrieved == every.retrieved == 10  # all of B's keyframes (16 asked for)
    verified = [c for c in every.candidates if c.reason != "covered_by_accepted_window"]
    assert len(verified) >= 2  # without grouping: several verifications of the one place
    assert len(grouped.candidates) == 1
    scores = pr.kfdb.scores(pr.kfdb.bow(("uavA", 6)))
    best = max(maps[1].keyframes, key=lambda k: pr.kfdb.scores_of([k], scores)[0])
    assert grouped.candidates[0].candidate_key == best
    assert grouped.detection is not None and every.detection is not None
    _check_sim(grouped.detection.target_from_source, S_TRUE)
    assert grouped.detection.n_inliers >= 0.9 * every.detection.n_inliers


def test_metric_mode_recovers_se3_and_rejects_a_scaled_map(scene) -> None:
    a, b = scene["A"], scene["B"]
    # B' = B brought back to metric scale: rigid B'_from_A
    rigid = Sim3(S_TRUE.R, S_TRUE.t, 1.0)
    b_metric = Map(5)
    for p in b.points.values():
        xyz = rigid.apply(S_TRUE.inverse().apply(p.xyz))
        b_metric.add_point(MapPoint(p.agent_id, p.id, xyz, p.descriptor))
    for kf in b.keyframes.values():
        T = rigid.transform_pose(S_TRUE.inverse().transform_pose(kf.world_from_cam))
        b_metric.add_keyframe(
            Keyframe(kf.agent_id, kf.id, kf.timestamp, T, kf.camera, kf.keypoints, kf.octaves,
                     kf.descriptors, kf.point_ids)
        )  # fmt: skip
    maps = {0: a, 5: b_metric}
    pr = _recognizer(maps)
    r = pr.detect(maps, 0, ("uavA", 6), fix_scale=True, loop=False)
    assert r.detection is not None
    assert r.detection.target_from_source.s == 1.0
    _check_sim(r.detection.target_from_source, rigid)
    # metric-mode attempts against scaled maps are refused: at scale 2.5 no rigid transform fits; at 1.5
    # one fits the points near the centroid, and the free-scale sanity gate (run once the rigid estimate
    # passed) refuses it
    maps2 = {0: a, 1: b}
    pr2 = _recognizer(maps2)
    r2 = pr2.detect(maps2, 0, ("uavA", 6), fix_scale=True, loop=False)
    assert r2.detection is None and r2.candidates
    assert all(c.reason == "few_ransac_inliers" for c in r2.candidates)
    rng = np.random.default_rng(5)
    pts, desc = _world(rng, 2500, (-20, 30))
    a3 = _make_map(rng, 0, "uavA", pts, desc, np.linspace(-6, 8, 10), Sim3.identity())
    b3 = _make_map(rng, 1, "uavB", pts, desc, np.linspace(-2, 12, 10), Sim3(S_TRUE.R, S_TRUE.t, 1.5))
    maps3 = {0: a3, 1: b3}
    r3 = _recognizer(maps3).detect(maps3, 0, ("uavA", 6), fix_scale=True, loop=False)
    assert r3.detection is None
    gated = [c for c in r3.candidates if c.reason == "metric_scale_inconsistent"]
    assert gated and all(c.scale == pytest.approx(1.5, rel=0.01) for c in gated)


@pytest.mark.parametrize("other", ["C", "D"])
def test_disjoint_or_inconsistent_maps_are_never_merged(scene, other: str) -> None:
    """C: another part of the site. D: the same appearance with a scrambled structure (BoW matches,
    geometry does not). Every query keyframe of A must end without an accepted candidate."""
    a, o = scene["A"], scene[other]
    maps = {0: a, 9: o}
    pr = _recognizer(maps)
    pr.options = type(pr.options)(use_feasibility=False)  # verify every candidate geometrically
    for k in range(10):
        r = pr.detect(maps, 0, ("uavA", k), loop=False)
        assert r.detection is None, [c.to_dict() for c in r.candidates]
        assert all(not c.accepted for c in r.candidates)
    if other == "D":
        # BoW alone is fooled (same descriptors); the geometric stages reject it
        assert r.candidates and all(
            c.reason in ("few_bow_matches", "ransac_failed", "few_ransac_inliers", "few_projected_inliers")
            for c in r.candidates
        )


def test_gnss_retry_with_lowered_thresholds(scene) -> None:
    """A weak overlap (map E shares only 32 points with A, the rest of E is elsewhere) is refused by the
    normal thresholds (>= 40 after projection) and accepted, correctly, by the GNSS-guided retry."""
    rng = np.random.default_rng(5)
    a = scene["A"]
    pts, desc = _world(np.random.default_rng(42), 2500, (-20, 30))  # the same world as the fixture
    kf = a.keyframes[("uavA", 5)]
    pc = pts @ kf.world_from_cam[:3, :3] - kf.world_from_cam[:3, 3] @ kf.world_from_cam[:3, :3]
    uv, valid = CAM.project(pc)
    shared = rng.choice(np.flatnonzero(valid & CAM.in_image(uv, 20)), 32, replace=False)
    far_pts, far_desc = _world(rng, 1500, (200, 240))
    e_pts = np.concatenate([pts[shared], far_pts - [0, 0, 0]])
    e_desc = np.concatenate([desc[shared], far_desc])
    centres = np.concatenate([[kf.world_from_cam[0, 3]] * 2, np.linspace(205, 220, 6)])
    e = _make_map(rng, 4, "ugvE", e_pts, e_desc, centres, S_TRUE)
    maps = {0: a, 4: e}
    pr = _recognizer(maps)
    normal = pr.detect(maps, 0, ("uavA", 5), loop=False)
    assert normal.detection is None
    retry = pr.verify_pair(maps, 0, ("uavA", 5), 4, [("ugvE", 0), ("ugvE", 1)], fix_scale=False)
    assert retry.detection is not None and retry.detection.confirmed, [c.to_dict() for c in retry.candidates]
    assert retry.detection.n_inliers < 40
    _check_sim(retry.detection.target_from_source, S_TRUE)


LOOP_DRIFT = Sim3(so3_exp(np.array([0.0, 0.03, 0.01])), np.array([0.8, -0.2, 0.3]), 1.04)


def _loop_map() -> dict[int, Map]:
    """One agent passing the same place twice, its second pass (ids from 10000) drifted by LOOP_DRIFT."""
    rng = np.random.default_rng(11)
    pts, desc = _world(rng, 2500, (-20, 30))
    m = _make_map(rng, 0, "uavL", pts, desc, np.linspace(-6, 6, 8), Sim3.identity())
    _make_map(rng, 0, "uavL", pts, desc, np.linspace(-5, 7, 8), LOOP_DRIFT, into=m, id0=10_000)
    return {0: m}


def test_intra_map_loop_with_drift() -> None:
    """One agent passes the same place twice; its second pass drifted by a small Sim(3) (as monocular
    VO does). A loop is found in its own map, outside the covisible keyframes, with the drift."""
    maps = _loop_map()
    drift = LOOP_DRIFT
    pr = _recognizer(maps)
    dets = [pr.detect(maps, 0, ("uavL", 10_000 + k)).detection for k in (3, 4, 5)]
    assert all(d is not None and d.is_loop and d.candidate_key[1] < 10_000 for d in dets), dets
    last = dets[-1]
    assert last is not None and last.confirmed
    # query points (second pass, drifted frame) -> candidate points (first pass): the inverse drift
    _check_sim(last.target_from_source, drift.inverse())


def test_loop_candidate_asking_for_an_implausible_correction_is_rejected() -> None:
    """A loop candidate whose transform would move the query keyframe farther (or turn it more) than
    PlaceRecOptions.loop_max_correction_m/_deg is a false match (the rendered site repeats its textures):
    it is rejected as implausible_correction, so it cannot win the query. The same loop within the
    limits is accepted, and correction_of measures its move as the true drift's (5 %)."""
    maps = _loop_map()
    q = ("uavL", 10_004)
    centre = maps[0].keyframes[q].world_from_cam[:3, 3]
    true_move = float(np.linalg.norm(LOOP_DRIFT.inverse().apply(centre) - centre))
    assert 0.5 < true_move < 3.0, true_move

    def detect(**limits: float) -> tuple[PlaceRecognizer, Any]:
        pr = PlaceRecognizer(default_vocabulary(), KeyframeDatabase(), PlaceRecOptions(**limits))  # type: ignore[arg-type]
        for kf in maps[0].keyframes.values():
            pr.add_keyframe(0, kf)
        return pr, pr.detect(maps, 0, q)

    _, ok = detect(loop_max_correction_m=2 * true_move, loop_max_correction_deg=5.0)
    assert ok.detection is not None and ok.detection.candidate_key[1] < 10_000
    move, turn = correction_of(ok.detection.target_from_source, maps[0].keyframes[q].world_from_cam)
    assert abs(move / true_move - 1) < 0.05 and turn < 5.0, (move, true_move, turn)

    for limits in ({"loop_max_correction_m": 0.5 * true_move}, {"loop_max_correction_deg": 0.5 * turn}):
        _, res = detect(**limits)
        assert res.detection is None, limits
        reasons = [c.reason for c in res.candidates]
        assert "implausible_correction" in reasons and not any(c.accepted for c in res.candidates), reasons


def _verify(pr: PlaceRecognizer, maps: dict[int, Map], *args: Any) -> Any:
    """One candidate's verification read straight from the maps (as a job's worker reads its slices)."""
    return verify(pr.options, lambda kf: pr._fv(kf)[1], maps, *args)


def test_candidate_in_a_map_merged_meanwhile_is_skipped_without_error(scene, caplog) -> None:
    """The event loop merges maps while the recognition thread verifies: a candidate whose map is gone
    is reported as such (not an exception with a traceback in the log) and the query goes on."""
    a, b = scene["A"], scene["B"]
    maps = {0: a, 1: b}
    pr = _recognizer(maps)
    ck = sorted(b.keyframes)[5]
    with caplog.at_level("ERROR", logger="hivemap.server.placerec"):
        rep = _verify(pr, {0: a}, 0, ("uavA", 5), 1, ck, True, pr.options.thresholds, "merge")
    assert not rep.accepted and rep.reason == "map_merged_meanwhile"
    assert not caplog.records
    # with both maps there, the same pair verifies (the skip is only for the missing map)
    assert _verify(pr, maps, 0, ("uavA", 5), 1, ck, False, pr.options.thresholds, "merge").reason != (
        "map_merged_meanwhile"
    )


def test_candidate_whose_points_were_fused_meanwhile_is_skipped_without_error(scene, caplog) -> None:
    """The event loop fuses points while the recognition thread verifies: a point that was in the map
    when the verification checked it and is gone when it reads it (simulated: the map's points answer
    ``in`` but not ``[]`` for half the query keyframe's points) is reported as points_fused_meanwhile;
    two factory01 challenged1 runs logged 9 and 12 such KeyError tracebacks as errors."""
    a, b = scene["A"], scene["B"]
    maps = {0: a, 1: b}
    pr = _recognizer(maps)
    ck = sorted(b.keyframes)[5]
    q = a.keyframes[("uavA", 5)]
    gone = {k for k in q.point_keys[::2] if k is not None}

    class Racing(dict):  # type: ignore[type-arg]
        def __getitem__(self, k: object) -> object:
            if k in gone:
                raise KeyError(k)
            return super().__getitem__(k)

    real = a.points
    a.points = Racing(real)
    try:
        with caplog.at_level("ERROR", logger="hivemap.server.placerec"):
            rep = _verify(pr, maps, 0, ("uavA", 5), 1, ck, False, pr.options.thresholds, "merge")
    finally:
        a.points = real
    assert not rep.accepted and rep.reason == "points_fused_meanwhile", rep.reason
    assert not caplog.records
    # the same pair verifies with its points all there
    assert _verify(pr, maps, 0, ("uavA", 5), 1, ck, False, pr.options.thresholds, "merge").accepted


def test_point_masks_kept_across_queries_follow_points_arriving_and_leaving() -> None:
    """The recogniser keeps each keyframe's "references a point of the map" mask across queries; it must
    see a pending point that arrived since, a removed point, and the keyframe moving to another map."""
    from hivemap.server.placerec.match import _point_keys
    from hivemap.server.placerec.views import HasCache

    rng = np.random.default_rng(0)
    m = Map(0)
    m.add_point(MapPoint("a", 0, np.zeros(3), rng.integers(0, 256, 32, np.uint8)))
    kps = np.array([[10.0, 10.0], [20.0, 20.0], [30.0, 30.0]])
    desc = rng.integers(0, 256, (3, 32), np.uint8)
    kf = Keyframe("a", 0, 0.0, np.eye(4), CAM, kps, np.zeros(3, np.uint8), desc, np.array([0, 1, -1]))
    m.add_keyframe(kf)  # point 1 not in the map yet: pending
    cache = HasCache()
    assert cache.get(m, kf, _point_keys(kf)).tolist() == [True, False, False]
    m.add_point(MapPoint("a", 1, np.ones(3), rng.integers(0, 256, 32, np.uint8)))
    assert cache.get(m, kf, _point_keys(kf)).tolist() == [True, True, False]
    m.remove_point(("a", 0))
    assert cache.get(m, kf, _point_keys(kf)).tolist() == [False, True, False]
    other = Map(1)  # a merge moves the keyframe into another map object
    assert cache.get(other, kf, _point_keys(kf)).tolist() == [False, False, False]


def test_point_keys_read_from_the_id_array_equal_the_keyframe_property() -> None:
    from hivemap.server.placerec.match import _point_keys

    rng = np.random.default_rng(0)
    n = 60
    ids = rng.integers(-1, 100, n)
    kf = Keyframe("a", 0, 0.0, np.eye(4), CAM, rng.uniform(0, 100, (n, 2)), np.zeros(n, np.uint8),
                  rng.integers(0, 256, (n, 32), np.uint8), ids)  # fmt: skip
    for i in range(0, n, 3):  # references to another agent's points (fused after a merge)
        if ids[i] >= 0:
            kf.set_point_key(i, ("b", int(ids[i])))
    assert _point_keys(kf) == kf.point_keys
