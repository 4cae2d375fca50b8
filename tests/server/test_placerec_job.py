"""A query's verification as a job: in a worker process it reports what the recogniser's own thread
reports (the job carries the maps' slices as arrays); and what the queue skips in a backlog."""

from __future__ import annotations

import asyncio
import pickle

import pytest
from test_placerec import _recognizer, scene  # noqa: F401  (the synthetic scene fixture)

from hivemap.server.backend.backlog import QueryQueue
from hivemap.server.backend.executor import ProcessVerifier
from hivemap.server.placerec.phases import combine_phases
from hivemap.server.placerec.shipping import Shipper
from hivemap.server.placerec.verify import run_job


def _summary(reports: list) -> list[tuple]:
    return [(r.candidate_key, r.kind, r.accepted, r.reason, r.n_matches, r.n_inliers) for r in reports]


def test_a_job_verified_in_a_worker_process_reports_what_the_thread_does(scene) -> None:  # noqa: F811
    maps = {0: scene["A"], 1: scene["B"], 2: scene["C"], 3: scene["D"]}
    pr = _recognizer(maps)
    result, job = pr.prepare(maps, 0, ("uavA", 6), loop=False)
    assert job.candidates, result.reason
    # the job holds slices of the maps it reads, not the maps: the query's and the candidates' windows;
    # phase 1's without the points' descriptors and observations
    assert job.phase == 1 and all(s.light and len(s.desc) == 0 for s in job.slices)
    assert {s.map_id for s in job.slices} <= {0, 1, 2, 3}
    assert sum(len(s.keyframes) for s in job.slices) <= 1 + 6 * len(job.candidates)
    pool = ProcessVerifier(1)
    try:
        first_inline = run_job(job)
        first = asyncio.run(pool.run(job))
        assert _summary(first) == _summary(first_inline)
        second_job = pr.second_phase(maps, job, first)
        assert second_job is not None and second_job.phase == 2
        assert not any(s.light for s in second_job.slices)
        inline = run_job(second_job)
        remote = asyncio.run(pool.run(second_job))
    finally:
        pool.shutdown()
    assert _summary(remote) == _summary(inline)
    acc = [(a, b) for a, b in zip(inline, remote, strict=True) if a.accepted]
    assert acc, _summary(inline)
    for a, b in acc:
        assert a.target_from_source is not None and b.target_from_source is not None
        assert abs(a.target_from_source.s - b.target_from_source.s) < 1e-9
        assert a.query_points == b.query_points and a.candidate_points == b.candidate_points
    # the detection concluded from the worker's reports is the inline one's
    det = pr.conclude(result, combine_phases(job, first, remote)).detection
    assert det is not None and det.candidate_map == 1


@pytest.mark.parametrize("cache", [4, 3000])
def test_jobs_shipped_without_the_features_a_worker_holds_report_what_whole_jobs_do(scene, cache) -> None:  # noqa: F811
    maps = {0: scene["A"], 1: scene["B"], 2: scene["C"], 3: scene["D"]}
    pr = _recognizer(maps)
    jobs = []
    for key in sorted(maps[0].keyframes)[2:]:
        _, job = pr.prepare(maps, 0, key, loop=False)
        if job is not None and job.candidates:
            jobs.append(job)
    assert len(jobs) >= 4
    whole = [_summary(run_job(j)) for j in jobs]
    # what the packer sends, on a mirror of the one the verifier uses (same jobs, same order)
    shipper = Shipper(cache)
    sizes = [(len(pickle.dumps(j)), len(pickle.dumps(shipper.pack(j)))) for j in jobs]
    pool = ProcessVerifier(1, keyframe_cache=cache)
    try:
        # a small cache evicts keyframes within and between jobs: a worker that disagreed with its packer
        # about what it holds would fail the job
        shipped = [_summary(asyncio.run(pool.run(j))) for j in jobs]
    finally:
        pool.shutdown()
    assert shipped == whole
    assert all(b <= a + 1024 for a, b in sizes)  # never more than the whole job (and the wrapper)
    if cache >= 3000:  # the later jobs re-read the same places: most of their features are held
        later = sizes[len(sizes) // 2 :]
        assert sum(b for _, b in later) < 0.6 * sum(a for a, _ in later), sizes


def test_a_reset_packer_tells_its_worker_to_forget_what_it_holds(scene) -> None:  # noqa: F811
    from hivemap.server.placerec import shipping

    maps = {0: scene["A"], 1: scene["B"], 2: scene["C"], 3: scene["D"]}
    pr = _recognizer(maps)
    jobs = [j for k in sorted(maps[0].keyframes)[2:8] if (j := pr.prepare(maps, 0, k, loop=False)[1])]
    jobs = [j for j in jobs if j.candidates]
    assert len(jobs) >= 2
    shipper = Shipper(3000)
    whole = _summary(run_job(jobs[1]))
    shipping.unpack(shipper.pack(jobs[0]), 3000)  # in this process, as the worker would
    # the worker's cache out of step (a failed job): a reset packer ships everything and says so
    assert shipping._CACHE is not None
    shipping._CACHE.items.clear()
    shipping._CACHE.touch(("stale", 0), shipping.Bundle((), None))  # what the mirror no longer knows of
    shipper.reset()
    again = shipper.pack(jobs[1])
    assert again.reset and _summary(run_job(shipping.unpack(again, 3000))) == whole
    # the worker forgot the entry its packer does not know of (it would evict out of step)
    assert ("stale", 0) not in shipping._CACHE.items
    assert not shipper.pack(jobs[1]).reset


def test_a_backlog_skips_keyframes_whose_place_their_agent_just_queried() -> None:
    # a track of agent a: each keyframe's best covisible keyframes are its two predecessors
    def best(key: tuple[str, int], n: int) -> list[tuple[str, int]]:
        return [(key[0], key[1] - i) for i in range(1, n + 1)]

    q = QueryQueue(queue_max=100, backlog=3)
    for k in range(3):
        q.push(("a", k))
    # a short queue: every keyframe, in order
    assert [q.pop(best)[0] for _ in range(3)] == [("a", 0), ("a", 1), ("a", 2)] and q.skipped == 0
    for k in range(3, 10):
        q.push(("a", k))
    q.push(("b", 0))
    # a backlog: a3 and a4 see the place a2 was queried at; a5 does not; in order per agent
    assert q.pop(best) == (("a", 5), [("a", 3), ("a", 4)])
    assert q.pop(best) == (("a", 8), [("a", 6), ("a", 7)])
    # back at the backlog (2 waiting): every keyframe again
    assert q.pop(best) == (("a", 9), []) and q.pop(best) == (("b", 0), [])
    assert q.skipped == 4 and not q


def test_a_full_queue_drops_the_oldest() -> None:
    q = QueryQueue(queue_max=2, backlog=0)
    assert q.push(("a", 0)) is None and q.push(("a", 1)) is None
    assert q.push(("a", 2)) == ("a", 0) and q.dropped == 1
    assert list(q) == [("a", 1), ("a", 2)]


def test_done_through_counts_the_arrivals_the_back_end_has_finished_in_order() -> None:
    """A finishing agent compares ``done_through`` with the arrivals it saw: every arrival up to it is
    finished (queried and concluded, skipped or dropped), whatever order queries end in."""
    q = QueryQueue(queue_max=3, backlog=0)
    for k in range(3):
        q.push(("a", k))
    assert (q.n_arrived, q.done_through()) == (3, 0)
    a0, _ = q.pop(lambda key, n: [])
    a1, _ = q.pop(lambda key, n: [])
    q.done(a1)
    q.finished(a1)  # the second query ends first: the first still holds the count
    assert q.done_through() == 0
    q.finished(a0)
    assert q.done_through() == 2  # a2 still waits
    for k in (3, 4, 5):  # the third fills the queue past 3: a2 (arrival 3) is dropped, i.e. finished
        q.push(("a", k))
    assert q.dropped == 1 and q.done_through() == 3
    for key in list(q):
        q.finished(key)
    assert (q.n_arrived, q.done_through()) == (6, 6)
