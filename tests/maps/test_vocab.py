"""Vocabulary: training recovers clusters, transform is a proper tf-idf vector with a direct index,
save/load is lossless, and BoW scores rank the same place (new viewpoint) above other places."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import skimage.data

from hivemap.maps.vocabulary import (
    BowVector,
    TrainOptions,
    Vocabulary,
    default_vocabulary,
    hamming_matrix,
    l1_score,
)

# Training photos and held-out photos (the test places) are disjoint, so scores are not inflated by
# the vocabulary having seen the test images.
TRAIN = ("brick", "grass", "gravel", "camera", "coffee", "hubble_deep_field", "text", "clock")
HELD_OUT = ("astronaut", "chelsea", "rocket", "coins", "moon", "retina", "page", "immunohistochemistry")


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
    """A nearby viewpoint: small perspective change, rotation and scale."""
    h, w = gray.shape
    src = np.array([[0, 0], [w, 0], [w, h], [0, h]], dtype=np.float32)
    dst = (src + rng.uniform(-strength, strength, size=(4, 2)) * [w, h]).astype(np.float32)
    H = cv2.getPerspectiveTransform(src, dst)
    return cv2.warpPerspective(gray, H, (w, h), borderMode=cv2.BORDER_REFLECT)


@pytest.fixture(scope="module")
def small_vocab() -> Vocabulary:
    rng = np.random.default_rng(1)
    docs = []
    for name in TRAIN:
        g = _gray(name)
        docs.append(_orb(g))
        docs.extend(_orb(_warp(g, rng, 0.15)) for _ in range(2))
    return Vocabulary.train(docs, TrainOptions(k=10, depth=3, seed=0))


def test_kmajority_recovers_planted_clusters() -> None:
    rng = np.random.default_rng(0)
    centres = rng.integers(0, 256, size=(10, 32), dtype=np.uint8)
    bits = np.unpackbits(centres, axis=1)
    samples, labels = [], []
    for c in range(10):
        b = np.repeat(bits[c : c + 1], 60, axis=0)
        flip = rng.random(b.shape) < 0.04  # ~10 of 256 bits flipped; centres are ~128 bits apart
        samples.append(np.packbits(b ^ flip, axis=1))
        labels += [c] * 60
    desc = np.concatenate(samples)
    vocab = Vocabulary.train([desc[i::3] for i in range(3)], TrainOptions(k=10, depth=1, seed=3))
    words, _ = vocab.lookup(desc)
    lab = np.asarray(labels)
    # every planted cluster lands in exactly one word and no two clusters share a word
    for c in range(10):
        assert len(np.unique(words[lab == c])) == 1
    assert len(np.unique(words)) == 10
    # the learned centres are the planted ones up to a couple of bits (majority of 60 noisy copies)
    d = hamming_matrix(vocab.centers[vocab.node_of_word], centres)
    assert d.min(axis=1).max() <= 2


def test_transform_is_normalised_tfidf_with_direct_index(small_vocab: Vocabulary) -> None:
    d = _orb(_gray("astronaut"))
    bow, fv = small_vocab.transform(d)
    assert np.all(bow.weights > 0)
    assert bow.weights.sum() == pytest.approx(1.0)
    assert np.all(np.diff(bow.words) > 0)
    assert sum(len(v) for v in fv.values()) == len(d)  # direct index covers every feature once
    assert np.all(small_vocab.level[fv.node_of_feature] == 2)  # nodes at the default direct-index level
    words, _ = small_vocab.lookup(d)
    # each feature's word sits under its direct-index node: walk parents up from the word's node
    parent = np.full(small_vocab.num_nodes, -1)
    for n, ch in enumerate(small_vocab.children):
        parent[ch[ch >= 0]] = n
    node = small_vocab.node_of_word[words]
    while np.any(small_vocab.level[node] > 2):
        node = np.where(small_vocab.level[node] > 2, parent[node], node)
    assert np.array_equal(node, fv.node_of_feature)
    assert l1_score(bow, bow) == pytest.approx(1.0)
    assert dict(bow)[int(bow.words[0])] == pytest.approx(bow.weights[0])


def test_descent_matches_brute_force_nearest_child(small_vocab: Vocabulary) -> None:
    """The vectorised descent picks, at every level, the child at minimum Hamming distance."""
    d = _orb(_gray("rocket"))[:200]
    words, _ = small_vocab.lookup(d)
    for i in range(len(d)):
        node = 0
        while small_vocab.children[node, 0] >= 0:
            ch = small_vocab.children[node]
            ch = ch[ch >= 0]
            dist = hamming_matrix(d[i : i + 1], small_vocab.centers[ch])[0]
            node = int(ch[np.argmin(dist)])
        assert small_vocab.word_of_node[node] == words[i]


def test_save_load_roundtrip(tmp_path, small_vocab: Vocabulary) -> None:
    p = tmp_path / "v.npz"
    small_vocab.save(p)
    v2 = Vocabulary.load(p)
    d = _orb(_gray("chelsea"))
    a, fa = small_vocab.transform(d)
    b, fb = v2.transform(d)
    assert np.array_equal(a.words, b.words)
    np.testing.assert_allclose(a.weights, b.weights, rtol=1e-6)  # idf stored as float32
    assert np.array_equal(fa.node_of_feature, fb.node_of_feature)


def _read_dbow2_text(path) -> tuple[list[int], list[list[int]], list[np.ndarray], list[float], list[int]]:
    """Parse DBoW2's text vocabulary as its loader does: header, then nodes numbered in file order."""
    lines = path.read_text().split("\n")
    k, depth, scoring, weighting = (int(x) for x in lines[0].split())
    assert (scoring, weighting) == (0, 0) and 0 < k <= 20 and 1 <= depth <= 10  # L1 score, tf-idf
    children: list[list[int]] = [[]]
    centers = [np.zeros(32, dtype=np.uint8)]
    weights, word_of_node = [0.0], [-1]
    n_words = 0
    for line in lines[1:]:
        f = line.split()
        assert len(f) == 35, line
        nid = len(children)
        children.append([])
        children[int(f[0])].append(nid)
        centers.append(np.array([int(x) for x in f[2:34]], dtype=np.uint8))
        weights.append(float(f[34]))
        word_of_node.append(n_words if f[1] == "1" else -1)
        n_words += f[1] == "1"
    return [k, depth], children, centers, weights, word_of_node


def test_dbow2_text_export_gives_the_same_words_and_weights(tmp_path, small_vocab: Vocabulary) -> None:
    """ORB-SLAM reading the exported file (first-minimum descent to a leaf) finds our word and idf."""
    p = tmp_path / "voc.txt"
    small_vocab.save_dbow2_text(p)
    (k, depth), children, centers, weights, word_of_node = _read_dbow2_text(p)
    assert k == small_vocab.k and depth == small_vocab.fv_level + 4  # ORB-SLAM's direct index level
    assert len(children) == small_vocab.num_nodes and max(word_of_node) + 1 == small_vocab.num_words
    d = _orb(_gray("rocket"))[:200]
    words, _ = small_vocab.lookup(d)
    for i in range(len(d)):
        node = 0
        while children[node]:
            dist = hamming_matrix(d[i : i + 1], np.stack([centers[c] for c in children[node]]))[0]
            node = children[node][int(np.argmin(dist))]
        assert word_of_node[node] == words[i]
        assert weights[node] == pytest.approx(small_vocab.idf[words[i]], rel=1e-12)


@pytest.mark.parametrize("which", ["small", "shipped"])
def test_same_place_scores_higher_than_other_places(which: str, small_vocab: Vocabulary) -> None:
    vocab = small_vocab if which == "small" else default_vocabulary()
    rng = np.random.default_rng(7)
    grays = [_gray(n) for n in HELD_OUT]
    ref = [vocab.transform(_orb(g))[0] for g in grays]
    margins = []
    for i, g in enumerate(grays):
        q = vocab.transform(_orb(_warp(g, rng, 0.08)))[0]
        scores = np.array([l1_score(q, r) for r in ref])
        assert int(np.argmax(scores)) == i, (HELD_OUT[i], scores)
        margins.append(scores[i] / np.delete(scores, i).max())
    # the same place (8% corner jitter viewpoint change) scores well above the best other place
    print(which, np.round(margins, 2))
    assert np.median(margins) > 1.3, margins


def test_shipped_vocabulary_shape() -> None:
    v = default_vocabulary()
    assert v.k == 10 and v.depth == 4
    assert 5000 <= v.num_words <= 10**4
    assert np.all(np.isfinite(v.idf)) and np.all(v.idf >= 0)
    empty, fv = v.transform(np.zeros((0, 32), dtype=np.uint8))
    assert isinstance(empty, BowVector) and len(empty) == 0 and len(fv) == 0
