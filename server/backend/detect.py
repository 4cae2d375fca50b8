"""Detection: the place recogniser's set-up, indexing keyframes, a query keyframe's BoW look-up and
its verification jobs (:class:`~hivemap.server.placerec.PlaceRecognizer`; phase 1 for every candidate,
phase 2 for its survivors; the jobs run where the scheduler's verifier runs them) and publishing what
it found on ``/events``. Runs in the place-recognition thread, which alone touches the recogniser and
its keyframe database.
"""

from __future__ import annotations

import logging
import time
from dataclasses import replace
from typing import Any

from hivemap.server.backend.options import BackendOptions
from hivemap.server.convert import split_folded
from hivemap.server.placerec import CandidateReport, PlaceRecognizer, RecognitionResult
from hivemap.server.placerec.job import QueryJob

logger = logging.getLogger(__name__)

KfKey = tuple[str, int]

# A look-up that meets a map changing under it (the event loop merges meanwhile) is retried this often.
DETECT_RETRIES = 3


def make_recognizer(vocabulary: Any, o: BackendOptions) -> PlaceRecognizer:
    """The recogniser with a fresh keyframe database; for metric maps it rejects loop candidates asking
    for more than ``AcceptOptions.loop_max_correction_*`` right after RANSAC, so a false candidate
    neither wins a query nor restarts the consistency count."""
    from hivemap.maps.kfdb import KeyframeDatabase
    from hivemap.maps.vocabulary import default_vocabulary

    vocab = vocabulary if vocabulary is not None else default_vocabulary()
    pr = o.placerec
    if o.fix_scale:
        pr = replace(pr, loop_max_correction_m=o.accept.loop_max_correction_m,
                     loop_max_correction_deg=o.accept.loop_max_correction_deg)  # fmt: skip
    return PlaceRecognizer(vocab, KeyframeDatabase(), pr)


def index_many(recognizer: PlaceRecognizer, stack: Any, keys: list[tuple[int, KfKey]]) -> None:
    """Add keyframes (reloaded from the store) to the database without looking them up."""
    for _, key in keys:
        m = stack.map_of_agent(key[0])
        kf = m.keyframes.get(key) if m is not None else None
        if m is not None and kf is not None and key not in recognizer.kfdb:
            recognizer.add_keyframe(m.id, kf)


def best_covisible(stack: Any, key: KfKey, n: int) -> list[KfKey]:
    """The ``n`` keyframes sharing most map points with ``key`` (none if it is gone)."""
    m = stack.map_of_agent(key[0])
    return list(m.best_covisible(key, n)) if m is not None and key in m.keyframes else []


def prepare(
    recognizer: PlaceRecognizer, stack: Any, key: KfKey, fix_scale: bool
) -> tuple[RecognitionResult, QueryJob, float] | None:
    """Index the keyframe, retrieve its candidates in the other maps (merge) and its own (loop), and
    take the verification job (:meth:`PlaceRecognizer.prepare`); with the CPU ms it took. None: the
    keyframe is gone."""
    for _ in range(DETECT_RETRIES):
        c0 = time.thread_time()
        try:
            m = stack.map_of_agent(key[0])
            kf = m.keyframes.get(key) if m is not None else None
            if m is None or kf is None:
                return None  # culled or gone
            if key not in recognizer.kfdb:
                recognizer.add_keyframe(m.id, kf)
            result, job = recognizer.prepare(stack.maps, m.id, key, fix_scale=fix_scale)
            return result, job, (time.thread_time() - c0) * 1e3
        except RuntimeError as exc:  # "dictionary changed size during iteration"
            logger.debug("detect %s retried: %s", key, exc)
    return None


def second_phase(
    recognizer: PlaceRecognizer, stack: Any, job: QueryJob, reports: list[CandidateReport]
) -> tuple[QueryJob | None, float]:
    """The full verification job of a two-phase query's survivors (:meth:`PlaceRecognizer.second_phase`),
    with the CPU ms it took; None when there is nothing to verify (or the maps kept changing under it)."""
    for _ in range(DETECT_RETRIES):
        c0 = time.thread_time()
        try:
            return recognizer.second_phase(stack.maps, job, reports), (time.thread_time() - c0) * 1e3
        except RuntimeError as exc:  # "dictionary changed size during iteration"
            logger.debug("phase 2 of %s retried: %s", job.query_key, exc)
    return None, 0.0


def publish(events: Any, res: RecognitionResult) -> None:
    """Every candidate and rejection reason as ``placerec_candidate`` / ``placerec`` events."""
    if not res.candidates and res.reason in ("no_other_map_keyframes", "no_bow_candidates"):
        return  # nothing to see: keep /events readable
    agent = split_folded(res.query_key[0])[0]
    for ev in res.events():
        kind = ev.pop("type")
        if kind == "placerec_candidate":
            msg = (
                f"{ev['kind']} candidate {tuple(ev['candidate_key'])} for {tuple(ev['query_key'])}: "
                f"{'accepted' if ev['accepted'] else 'rejected'} ({ev['reason']})"
            )
        else:
            msg = f"place recognition {tuple(ev['query_key'])}: {ev['reason']}"
        events.add(kind, msg, agent_id=agent, map_id=res.query_map, data=ev)
