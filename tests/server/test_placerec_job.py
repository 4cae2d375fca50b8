"""A query's verification as a job: in a worker process it reports what the recogniser's own thread
reports (the job carries the maps' slices as arrays), and the queue's order under a backlog."""

from __future__ import annotations

import asyncio

from test_placerec import _recognizer, scene  # noqa: F401  (the synthetic scene fixture)

from hivemap.server.backend.backlog import QueryQueue
from hivemap.server.backend.executor import ProcessVerifier
from hivemap.server.placerec.verify import run_job


def _summary(reports: list) -> list[tuple]:
    return [(r.candidate_key, r.kind, r.accepted, r.reason, r.n_matches, r.n_inliers) for r in reports]


def test_a_job_verified_in_a_worker_process_reports_what_the_thread_does(scene) -> None:  # noqa: F811
    maps = {0: scene["A"], 1: scene["B"], 2: scene["C"], 3: scene["D"]}
    pr = _recognizer(maps)
    result, job = pr.prepare(maps, 0, ("uavA", 6), loop=False)
    assert job.candidates, result.reason
    # the job holds slices of the maps it reads, not the maps: the query's and the candidates' windows
    assert {s.map_id for s in job.slices} <= {0, 1, 2, 3}
    assert sum(len(s.keyframes) for s in job.slices) <= 1 + 6 * len(job.candidates)
    inline = run_job(job)
    pool = ProcessVerifier(1)
    try:
        remote = asyncio.run(pool.run(job))
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
    det = pr.conclude(result, remote).detection
    assert det is not None and det.candidate_map == 1


def test_a_backlog_queries_the_newest_first_and_skips_its_covisible_keyframes() -> None:
    q = QueryQueue(queue_max=100, backlog=3)
    for k in range(3):
        q.push(("a", k))
    # short queue: oldest first, nothing skipped
    assert q.pop(lambda key: []) == (("a", 0), [])
    for k in range(3, 8):
        q.push(("a", k))
    q.push(("b", 0))
    # a backlog (7 waiting > 3): the newest first, with its agent's waiting covisible keyframes skipped
    key, skipped = q.pop(lambda key: [("b", 1)])
    assert key == ("b", 0) and skipped == []
    covis = {("a", 7): [("a", 6), ("a", 5), ("b", 9)]}
    key, skipped = q.pop(lambda key: covis.get(key, []))
    assert key == ("a", 7) and skipped == [("a", 5), ("a", 6)]
    assert list(q) == [("a", 1), ("a", 2), ("a", 3), ("a", 4)] and q.skipped == 2
    assert q.pop(lambda key: [])[0] == ("a", 4)  # 4 waiting: still a backlog
    assert q.pop(lambda key: [])[0] == ("a", 1)  # back at the backlog: oldest first again


def test_a_full_queue_drops_the_oldest() -> None:
    q = QueryQueue(queue_max=2, backlog=0)
    assert q.push(("a", 0)) is None and q.push(("a", 1)) is None
    assert q.push(("a", 2)) == ("a", 0) and q.dropped == 1
    assert list(q) == [("a", 1), ("a", 2)]
