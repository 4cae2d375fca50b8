"""Keyframe database: exact DBoW2 L1 scores through the inverted index, map filters, removal, the right
keyframe first for a new view of a known place, and seed 004's feasibility check."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import skimage.data

from hivemap.maps.kfdb import KeyframeDatabase
from hivemap.maps.vocabulary import BowVector, default_vocabulary, l1_score

PLACES = ("astronaut", "chelsea", "rocket", "coins", "moon", "retina", "page", "immunohistochemistry")


def _gray(name: str) -> np.ndarray:
    img = np.asarray(getattr(skimage.data, name)())
    if img.ndim == 3:
        img = cv2.cvtColor(img[..., :3], cv2.COLOR_RGB2GRAY)
    return img.astype(np.uint8)


def _orb(gray: np.ndarray, n: int = 1000) -> np.ndarray:
    orb = cv2.ORB_create(nfeatures=n)  # type: ignore[attr-defined]
    _, d = orb.detectAndCompute(gray, None)
    return d


def _warp(gray: np.ndarray, rng: np.random.Generator, strength: float) -> np.ndarray:
    h, w = gray.shape
    src = np.array([[0, 0], [w, 0], [w, h], [0, h]], dtype=np.float32)
    dst = (src + rng.uniform(-strength, strength, size=(4, 2)) * [w, h]).astype(np.float32)
    H = cv2.getPerspectiveTransform(src, dst)
    return cv2.warpPerspective(gray, H, (w, h), borderMode=cv2.BORDER_REFLECT)


def _random_bow(rng: np.random.Generator, n_words: int, vocab_size: int = 10_000) -> BowVector:
    w = np.unique(rng.integers(0, vocab_size, size=n_words)).astype(np.int32)
    x = rng.random(len(w))
    return BowVector(w, x / x.sum())


def test_inverted_index_scores_equal_direct_l1_scores() -> None:
    rng = np.random.default_rng(0)
    db = KeyframeDatabase()
    bows = {("a", i): _random_bow(rng, 300, 2000) for i in range(200)}
    for i, (k, b) in enumerate(bows.items()):
        db.add(k, i % 3, b)
    q = _random_bow(rng, 300, 2000)
    res = db.query(q, 200)
    assert len(res) == 200
    for k, s in res:
        assert s == pytest.approx(l1_score(q, bows[k]), rel=1e-5)  # float32 postings
    assert [s for _, s in res] == sorted((s for _, s in res), reverse=True)


def test_shared_scores_give_the_same_look_ups() -> None:
    """PlaceRecognizer.detect scores a query once and passes the scores to the feasibility check and the
    merge and loop look-ups: the results must equal scoring in each call."""
    rng = np.random.default_rng(2)
    db = KeyframeDatabase()
    bows = [_random_bow(rng, 200, 1000) for _ in range(60)]
    for i, b in enumerate(bows):
        db.add((f"agent{i % 4}", i), i % 4, b)
    q = _random_bow(rng, 200, 1000)
    s = db.scores(q)
    assert db.query(q, 10, exclude_map=1, scores=s) == db.query(q, 10, exclude_map=1)
    ex = [("agent1", 1), ("agent1", 5)]
    assert db.query(q, 10, only_map=1, exclude_keys=ex, min_score=0.05, scores=s) == db.query(
        q, 10, only_map=1, exclude_keys=ex, min_score=0.05
    )
    assert db.feasibility(q, 2, ratio=0.3, scores=s) == db.feasibility(q, 2, ratio=0.3)
    # one query's score per keyframe, read from the shared scores (unknown keys score 0)
    keys = [("agent3", 3), ("agent0", 8), ("nobody", 1)]
    assert db.scores_of(keys, s) == pytest.approx([l1_score(q, bows[3]), l1_score(q, bows[8]), 0.0], rel=1e-5)


def test_filters_remove_and_reassign() -> None:
    rng = np.random.default_rng(1)
    db = KeyframeDatabase()
    bows = [_random_bow(rng, 200, 1000) for _ in range(30)]
    for i, b in enumerate(bows):
        db.add((f"agent{i % 3}", i), i % 3, b)
    q = bows[4]  # map 1
    assert db.query(q, 1)[0] == (("agent1", 4), pytest.approx(1.0))
    assert all(db.map_of(k) != 1 for k, _ in db.query(q, 30, exclude_map=1))
    assert all(db.map_of(k) == 1 for k, _ in db.query(q, 30, only_map=1))
    res = db.query(q, 30, only_map=1, exclude_keys=[("agent1", 4), ("agent1", 7)])
    assert ("agent1", 4) not in dict(res) and ("agent1", 7) not in dict(res) and len(res) == 8
    db.remove(("agent1", 4))
    assert ("agent1", 4) not in db and len(db) == 29
    assert ("agent1", 4) not in dict(db.query(q, 30))
    # the freed slot is reused and scores stay exact
    db.add(("agent9", 99), 5, bows[4])
    assert db.query(q, 1)[0] == (("agent9", 99), pytest.approx(1.0))
    assert db.reassign_map(1, 0) == 9
    assert set(db.keys_of_map(0)) >= {("agent1", 1), ("agent0", 0)}
    assert db.keys_of_map(1) == []


def test_scores_stay_exact_while_keyframes_come_and_go() -> None:
    """Postings are merged into the sorted index in batches: a keyframe removed before or after its batch
    is merged, and its slot reused, leaves every score the direct L1 score (only sharers score > 0)."""
    rng = np.random.default_rng(4)
    db = KeyframeDatabase()
    bows: dict[tuple[str, int], BowVector] = {}
    for i in range(120):
        k = (f"agent{i % 3}", i)
        bows[k] = _random_bow(rng, 150, 3000)
        db.add(k, i % 3, bows[k])
        if i % 5 == 2:  # sometimes a keyframe just added, sometimes an old one
            gone = list(bows)[int(rng.integers(len(bows)))]
            db.remove(gone)
            del bows[gone]
        if i % 9 == 0:
            q = _random_bow(rng, 150, 3000)
            got = dict(db.query(q, len(bows)))
            want = {k: l1_score(q, b) for k, b in bows.items()}
            assert set(got) == {k for k, v in want.items() if v > 0}
            for k, v in got.items():
                assert v == pytest.approx(want[k], rel=1e-5)


@pytest.fixture(scope="module")
def place_db() -> tuple[KeyframeDatabase, list[list[BowVector]]]:
    """Map 0 = a "trajectory" of 3 nearby views of each place; queries are fresh views of each place."""
    vocab = default_vocabulary()
    rng = np.random.default_rng(3)
    db = KeyframeDatabase()
    queries = []
    for p, name in enumerate(PLACES):
        g = _gray(name)
        for j in range(3):
            bow, fv = vocab.transform(_orb(_warp(g, rng, 0.06)))
            db.add(("uav1", 10 * p + j), 0, bow, fv)
        queries.append([vocab.transform(_orb(_warp(g, rng, 0.08)))[0] for _ in range(2)])
    return db, queries


def test_query_returns_a_keyframe_of_the_right_place_first(place_db) -> None:
    db, queries = place_db
    for p, qs in enumerate(queries):
        for q in qs:
            best = db.query(q, 3, exclude_map=1)
            assert best[0][0][1] // 10 == p, (PLACES[p], best)
            # the 3 views of that place are the 3 best
            assert {k[1] // 10 for k, _ in best} == {p}


def test_feasibility_check(place_db) -> None:
    """Seed 004: a new view of a mapped place is a feasible merge; an unmapped place is not."""
    db, queries = place_db
    vocab = default_vocabulary()
    for qs in queries:
        f = db.feasibility(qs[0], map_id=1, ratio=0.5)
        assert f.feasible and f.best_map == 0, f
    for name in ("gravel", "text"):  # places map 0 never saw
        q = vocab.transform(_orb(_gray(name)))[0]
        f = db.feasibility(q, map_id=1, ratio=0.5)
        assert not f.feasible, (name, f)
