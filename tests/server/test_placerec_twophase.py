"""Two-phase verification of place-recognition candidates (server/placerec/phases.py, consensus.py):
phase 1 (BoW matches and RANSAC on light slices) for every candidate, the full verification only for
its survivors. It must find what one phase finds, refuse wrong candidates before the full
verification, and the rigid-consensus pre-test must never refuse a candidate RANSAC would pass."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from test_backend import UAV_FROM_WORLD, Server, agent_transform, check_transform, stream
from test_placerec import LOOP_DRIFT, _check_sim, _loop_map, _recognizer, scene  # noqa: F401
from test_placerec_frontend import _recognizer as _fe_recognizer
from test_placerec_frontend import agents  # noqa: F401  (maps built by the real front-end)

from hivemap.maps.geometry import Sim3, so3_exp
from hivemap.server.backend import preset
from hivemap.server.backend.options import SchedulerOptions
from hivemap.server.backend_synth import UGV_FROM_WORLD, agent_stream, make_world
from hivemap.server.placerec import PlaceRecognizer
from hivemap.server.placerec.consensus import rigid_consensus_bound
from hivemap.server.placerec.phases import PASSED
from hivemap.server.placerec.verify import run_job

# what phase 1 refuses with, and what one phase refuses the same candidates with
PHASE1_REASONS = {"few_bow_matches", "few_consistent_matches", "ransac_failed", "few_ransac_inliers"}


def _with(pr: PlaceRecognizer, **kw: Any) -> PlaceRecognizer:
    pr.options = replace(pr.options, **kw)
    return pr


def _report(r: Any) -> tuple[Any, ...]:
    s = None if r.scale is None else round(r.scale, 9)
    return (r.candidate_key, r.kind, r.accepted, r.reason, r.n_matches, r.n_ransac_inliers, r.n_projected,
            r.n_inliers, s)  # fmt: skip


def test_a_true_revisit_is_found_in_two_phases_with_its_drift() -> None:
    """One agent passes a place twice, its second pass drifted: the loop goes through both phases and its
    transform is the inverse drift (rotation < 0.5 deg, translation and scale < 1 %), as with one phase."""
    maps = _loop_map()
    pr = _recognizer(maps)
    assert pr.options.two_phase
    dets = []
    for k in (3, 4, 5):
        res = pr.detect(maps, 0, ("uavL", 10_000 + k))
        assert res.detection is not None, [c.to_dict() for c in res.candidates]
        acc = [c for c in res.candidates if c.accepted]
        assert acc and all(c.phase == 2 for c in acc)
        dets.append(res.detection)
    assert dets[-1].confirmed and dets[-1].is_loop and dets[-1].candidate_key[1] < 10_000
    _check_sim(dets[-1].target_from_source, LOOP_DRIFT.inverse())


@pytest.mark.parametrize("fix_scale", [False, True])
def test_an_aliased_candidate_is_refused_in_phase_1_and_never_fully_verified(scene, fix_scale) -> None:  # noqa: F811
    """Map D has A's appearance over a scrambled structure: BoW retrieves it, its matches fit no
    transform, rigid or not. Every candidate is refused in phase 1, so no phase-2 job is made."""
    maps = {0: scene["A"], 3: scene["D"]}
    pr = _with(_recognizer(maps), use_feasibility=False)
    for k in range(10):
        result, job = pr.prepare(maps, 0, ("uavA", k), fix_scale=fix_scale, loop=False)
        assert job.phase == 1 and job.candidates, result.reason
        first = run_job(job)
        assert all(r.reason in PHASE1_REASONS and r.phase == 1 for r in first), [r.reason for r in first]
        assert pr.second_phase(maps, job, first) is None
        res = pr.detect(maps, 0, ("uavA", k), fix_scale=fix_scale, loop=False)
        assert res.detection is None and all(c.phase == 1 and not c.accepted for c in res.candidates)


def test_the_consensus_pretest_bounds_the_inliers_of_any_rigid_transform() -> None:
    """Matches with ``n`` inliers of a rigid transform among outliers: the bound is at least ``n`` whenever
    ``n`` reaches the threshold, and random matches (no transform) come out below it."""
    rng = np.random.default_rng(7)
    T = Sim3(so3_exp(np.array([0.2, -1.0, 0.4])), np.array([3.0, -2.0, 5.0]), 1.0)
    err = 0.3
    for n_in, n_out in ((20, 0), (20, 200), (25, 400), (60, 100)):
        xq = rng.uniform(-10, 10, (n_in + n_out, 3))
        xc = T.apply(xq)
        # inliers up to the error bound (on a sphere of radius err: the worst case of the triangle
        # inequality); outliers anywhere in the scene
        d = rng.normal(size=(n_in, 3))
        xc[:n_in] += err * d / np.linalg.norm(d, axis=1, keepdims=True)
        xc[n_in:] = rng.uniform(-10, 10, (n_out, 3)) + T.t
        assert rigid_consensus_bound(xq, xc, err, 20) >= n_in, (n_in, n_out)
        perm = rng.permutation(len(xq))
        assert rigid_consensus_bound(xq, xc[perm], err, 20) < 20


@pytest.mark.slow
def test_two_phases_report_what_one_phase_does_on_frontend_maps(agents) -> None:  # noqa: F811
    """Maps of the real front-end (agents A and B in one scene, C in another): every query of A gives the
    same candidates, acceptances, inlier counts, scales and detections with two phases as with one (and
    without the pre-test, which only refuses candidates earlier, under its own reason)."""
    maps = {0: agents["A"][1], 1: agents["B"][1], 2: agents["C"][1]}
    prs = {
        "two": _with(_fe_recognizer(maps), use_feasibility=False),
        "one": _with(_fe_recognizer(maps), use_feasibility=False, two_phase=False),
        "old": _with(_fe_recognizer(maps), use_feasibility=False, two_phase=False, consensus_pretest=False),
    }
    n_full = n_cand = n_det = 0
    for k in sorted(maps[0].keyframes):
        res = {name: pr.detect(maps, 0, k, fix_scale=True) for name, pr in prs.items()}
        two, one, old = res["two"], res["one"], res["old"]
        assert [_report(r) for r in two.candidates] == [_report(r) for r in one.candidates], k
        for a, b in zip(two.candidates, old.candidates, strict=True):
            if a.reason == "few_consistent_matches":
                assert b.reason in ("ransac_failed", "few_ransac_inliers") and not b.accepted
            else:
                assert _report(a) == _report(b), k
        dets = [r.detection for r in (two, one, old)]
        assert (dets[0] is None) == (dets[1] is None) == (dets[2] is None), k
        if dets[0] is not None:
            n_det += 1
            for d in dets[1:]:
                assert d is not None and d.candidate_key == dets[0].candidate_key
                assert np.allclose(
                    d.target_from_source.matrix(), dets[0].target_from_source.matrix(), atol=1e-9
                )
                assert d.query_points == dets[0].query_points
        n_cand += sum(1 for c in two.candidates if c.reason != "covered_by_accepted_window")
        n_full += sum(1 for c in two.candidates if c.phase == 2 and c.reason != "covered_by_accepted_window")
    # the scenario has both: detections, and candidates that phase 1 refuses
    assert n_det >= 3 and n_full < n_cand, (n_det, n_full, n_cand)


def test_a_real_server_verifies_fully_only_what_passes_phase_1(tmp_path: Path) -> None:
    """Three agents over a real WebSocket, two overlapping and one elsewhere: the two merge with the true
    transform, and the back-end counts fewer full verifications than verified candidates."""
    rng = np.random.default_rng(1)
    pts, desc = make_world(rng, 2500, (-20, 30))
    far, far_desc = make_world(rng, 2000, (200, 250))
    ugv_msgs, _, _ = agent_stream(rng, pts, desc, np.linspace(-6, 8, 10), UGV_FROM_WORLD)
    uav_msgs, uav_true, _ = agent_stream(rng, pts, desc, np.linspace(-2, 12, 10), UAV_FROM_WORLD)
    # the third agent sees the first world's descriptors over another structure: retrieved, refused
    alias_msgs, _, _ = agent_stream(rng, far, desc[: len(far)], np.linspace(205, 220, 10), UAV_FROM_WORLD)
    opts = preset("monocular", scheduler=SchedulerOptions(backlog=0))
    opts = replace(opts, placerec=replace(opts.placerec, use_feasibility=False))
    s = Server(tmp_path / "data", opts)
    try:
        with (
            stream(s, "ugv1", "ugv", ugv_msgs),
            stream(s, "uav1", "uav", uav_msgs),
            stream(s, "uav2", "uav", alias_msgs),
        ):
            s.wait_idle()
        maps = s.call(lambda: sorted(sorted(m.agents) for m in s.hive.stack.maps.values()))
        counts = s.call(lambda: (s.backend.verifications, s.backend.full_verifications))
        true = UGV_FROM_WORLD @ UAV_FROM_WORLD.inverse()
        check_transform(agent_transform(s, "uav1"), true, uav_true[:, :3, 3])
        passed = s.call(lambda: [e.data for e in s.hive.events.since(0, kind="placerec_candidate")])
    finally:
        s.stop()
    assert maps == [["uav1", "ugv1"], ["uav2"]], maps
    verified, full = counts
    assert 0 < full < verified, counts
    assert all(d["reason"] != PASSED for d in passed)  # phase 1's mark never reaches /events
