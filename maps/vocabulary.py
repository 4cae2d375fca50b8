"""A DBoW2-style bag-of-words vocabulary for 256-bit ORB descriptors.

Why hand-written: no maintained Python package provides a binary-descriptor vocabulary that installs
here (pydbow3 / fbow fail to build; pycolmap's ``VisualIndex`` takes float descriptors only and its
query results are not readable from Python; see DESIGN.md, "Algorithms"). The algorithm follows
DBoW2 (Galvez-Lopez & Tardos 2012): a hierarchical tree of ``k`` branches and ``depth`` levels built
by k-majority clustering (k-medians on bits, k-means++ seeding, Hamming distance), leaves are words,
tf-idf weights, L1-normalised vectors and the L1 score ``s(v, w) = 1 - 0.5 * |v - w|_1`` (which, for
non-negative L1-normalised vectors, equals ``sum_i min(v_i, w_i)`` over the common words).

Everything is vectorised: a batch of descriptors descends the tree level by level, with the Hamming
distances to the ``k`` children of every descriptor's current node computed at once on ``uint64``
views with ``np.bitwise_count``.

Node numbering: node 0 is the root; ``children[n]`` lists the children of node ``n`` (-1 = none);
``level[n]`` is the depth of node ``n`` (root 0, words at most ``depth``). The direct index
(``FeatureVector``) groups features by their ancestor node at ``fv_level`` (levels from the root;
default 2 = ~100 nodes for k = 10, as ORB-SLAM's ``levelsup = 4`` on a 6-level tree).
"""

from __future__ import annotations

import logging
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass
from functools import lru_cache
from importlib import resources
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

log = logging.getLogger(__name__)

U8 = NDArray[np.uint8]
I32 = NDArray[np.int32]
I64 = NDArray[np.int64]
F64 = NDArray[np.float64]

FORMAT_VERSION = 1
DEFAULT_VOCAB_PATH = "data/orb_vocab.npz"


def hamming_matrix(a: U8, b: U8) -> NDArray[np.int32]:
    """All-pairs Hamming distances between (N, 32) and (M, 32) uint8 descriptors -> (N, M) int32."""
    a64 = _as_u64(a)
    b64 = _as_u64(b)
    return np.bitwise_count(a64[:, None, :] ^ b64[None, :, :]).sum(axis=2, dtype=np.int32)


def _as_u64(d: U8) -> NDArray[np.uint64]:
    d = np.ascontiguousarray(d, dtype=np.uint8).reshape(-1, 32)
    return d.view(np.uint64)


class BowVector(Mapping[int, float]):
    """Sparse tf-idf bag-of-words vector (word id -> weight), L1-normalised.

    Stored as two aligned arrays, ``words`` (sorted unique int32) and ``weights`` (float64); it is a
    read-only ``Mapping`` so ``bow[word]``, ``bow.items()``, ``dict(bow)`` work.
    """

    __slots__ = ("words", "weights")

    def __init__(self, words: NDArray[np.integer], weights: NDArray[np.floating]) -> None:
        self.words: I32 = np.asarray(words, dtype=np.int32)
        self.weights: F64 = np.asarray(weights, dtype=np.float64)

    def __getitem__(self, word: int) -> float:
        i = int(np.searchsorted(self.words, word))
        if i < len(self.words) and self.words[i] == word:
            return float(self.weights[i])
        raise KeyError(word)

    def __iter__(self) -> Iterator[int]:
        return iter(self.words.tolist())

    def __len__(self) -> int:
        return len(self.words)

    def __repr__(self) -> str:
        return f"BowVector({len(self)} words)"

    def score(self, other: BowVector) -> float:
        """DBoW2 L1 score in [0, 1] (1 = identical)."""
        return l1_score(self, other)


class FeatureVector(Mapping[int, I64]):
    """Direct index: node at the direct-index level -> indices of the features under it.

    ``node_of_feature[i]`` is the node (at ``level``) of feature ``i``; ``word_of_feature[i]`` its word.
    A ``Mapping`` node -> sorted feature indices (int64), as DBoW2's ``FeatureVector``.
    """

    __slots__ = ("node_of_feature", "word_of_feature", "level", "_groups")

    def __init__(self, node_of_feature: I32, word_of_feature: I32, level: int) -> None:
        self.node_of_feature = np.asarray(node_of_feature, dtype=np.int32)
        self.word_of_feature = np.asarray(word_of_feature, dtype=np.int32)
        self.level = level
        self._groups: dict[int, I64] | None = None

    def _build(self) -> dict[int, I64]:
        if self._groups is None:
            order = np.argsort(self.node_of_feature, kind="stable")
            nodes = self.node_of_feature[order]
            if len(nodes) == 0:
                self._groups = {}
                return self._groups
            starts = np.concatenate([[0], np.flatnonzero(np.diff(nodes)) + 1])
            self._groups = {
                int(nodes[s]): order[s:e].astype(np.int64)
                for s, e in zip(starts, np.append(starts[1:], len(nodes)), strict=True)
            }
        return self._groups

    def __getitem__(self, node: int) -> I64:
        return self._build()[node]

    def __iter__(self) -> Iterator[int]:
        return iter(self._build())

    def __len__(self) -> int:
        return len(self._build())


def l1_score(a: BowVector, b: BowVector) -> float:
    """DBoW2 L1 score ``1 - 0.5 |a - b|_1`` of two L1-normalised vectors = sum of min over common words."""
    _, ia, ib = np.intersect1d(a.words, b.words, assume_unique=True, return_indices=True)
    if len(ia) == 0:
        return 0.0
    return float(np.minimum(a.weights[ia], b.weights[ib]).sum())


@dataclass(frozen=True)
class TrainOptions:
    """Vocabulary training options (DBoW2 defaults for ORB: k = 10, L = 6; we use L = 4)."""

    k: int = 10
    depth: int = 4
    max_iterations: int = 12
    seed: int = 0


class Vocabulary:
    """Hierarchical k-majority vocabulary tree over 256-bit binary descriptors."""

    def __init__(
        self,
        centers: U8,
        children: I32,
        level: NDArray[np.int8],
        word_of_node: I32,
        idf: F64,
        k: int,
        depth: int,
        fv_level: int = 2,
    ) -> None:
        self.centers = np.ascontiguousarray(centers, dtype=np.uint8)
        self.children = np.asarray(children, dtype=np.int32)
        self.level = np.asarray(level, dtype=np.int8)
        self.word_of_node = np.asarray(word_of_node, dtype=np.int32)
        self.idf = np.asarray(idf, dtype=np.float64)
        self.k = int(k)
        self.depth = int(depth)
        self.fv_level = int(fv_level)
        self._prepare()

    def _prepare(self) -> None:
        n = len(self.centers)
        # Descent table: missing children replaced by the first child (duplicates do not change the
        # argmin); a leaf above the last level points to itself so the descent stays on it.
        table = self.children.copy()
        first = table[:, 0]
        is_leaf = first < 0
        table[is_leaf] = np.arange(n, dtype=np.int32)[is_leaf, None]
        missing = table < 0
        table[missing] = np.broadcast_to(table[:, :1], table.shape)[missing]
        self._table = table
        self._centers64 = self.centers.view(np.uint64).reshape(n, 4)
        self.num_words = int(self.word_of_node.max()) + 1 if n else 0
        if len(self.idf) != self.num_words:
            raise ValueError(f"idf has {len(self.idf)} entries, vocabulary has {self.num_words} words")
        self.node_of_word = np.full(self.num_words, -1, dtype=np.int32)
        leaves = np.flatnonzero(self.word_of_node >= 0)
        self.node_of_word[self.word_of_node[leaves]] = leaves

    # ------------------------------------------------------------------------------------------
    @property
    def num_nodes(self) -> int:
        return len(self.centers)

    def __repr__(self) -> str:
        return f"Vocabulary(k={self.k}, depth={self.depth}, words={self.num_words}, nodes={self.num_nodes})"

    def lookup(self, descriptors: U8, fv_level: int | None = None) -> tuple[I32, I32]:
        """Descend the tree: (N, 32) descriptors -> (word id per descriptor, node at ``fv_level``)."""
        L = self.fv_level if fv_level is None else int(fv_level)
        d64 = _as_u64(descriptors)
        n = len(d64)
        cur = np.zeros(n, dtype=np.int32)
        at_level = cur
        rows = np.arange(n)
        for lev in range(1, self.depth + 1):
            ch = self._table[cur]  # (N, k)
            dist = np.bitwise_count(self._centers64[ch] ^ d64[:, None, :]).sum(axis=2, dtype=np.int32)
            cur = ch[rows, np.argmin(dist, axis=1)]
            if lev == L:
                at_level = cur
        return self.word_of_node[cur], at_level

    def transform(self, descriptors: U8, fv_level: int | None = None) -> tuple[BowVector, FeatureVector]:
        """(N, 32) uint8 ORB descriptors -> (tf-idf BoW vector, direct index at ``fv_level``).

        tf-idf as DBoW2: each feature adds its word's idf, then the vector is L1-normalised; words with
        zero idf (seen in every training image) are dropped from the BoW vector but kept in the
        direct index.
        """
        L = self.fv_level if fv_level is None else int(fv_level)
        if len(descriptors) == 0:
            empty = np.zeros(0, dtype=np.int32)
            return BowVector(empty, np.zeros(0)), FeatureVector(empty, empty, L)
        words, nodes = self.lookup(descriptors, L)
        acc = np.bincount(words, weights=self.idf[words], minlength=self.num_words)
        nz = np.flatnonzero(acc > 0)
        w = acc[nz].astype(np.float64)
        total = w.sum()
        if total > 0:
            w = w / total
        return BowVector(nz.astype(np.int32), w), FeatureVector(nodes, words, L)

    def score(self, a: BowVector, b: BowVector) -> float:
        return l1_score(a, b)

    # ------------------------------------------------------------------------------------------
    def save(self, path: str | Path) -> None:
        """Write a compact compressed ``.npz`` (a few hundred KB for 10^4 words)."""
        np.savez_compressed(
            path,
            format_version=np.int32(FORMAT_VERSION),
            centers=self.centers,
            children=self.children,
            level=self.level,
            word_of_node=self.word_of_node,
            idf=self.idf.astype(np.float32),
            k=np.int32(self.k),
            depth=np.int32(self.depth),
            fv_level=np.int32(self.fv_level),
        )

    @staticmethod
    def load(path: str | Path) -> Vocabulary:
        with np.load(path) as z:
            version = int(z["format_version"])
            if version != FORMAT_VERSION:
                raise ValueError(f"{path}: vocabulary format {version}, expected {FORMAT_VERSION}")
            return Vocabulary(
                centers=z["centers"],
                children=z["children"],
                level=z["level"],
                word_of_node=z["word_of_node"],
                idf=z["idf"].astype(np.float64),
                k=int(z["k"]),
                depth=int(z["depth"]),
                fv_level=int(z["fv_level"]),
            )

    def save_dbow2_text(self, path: str | Path, levels_up: int = 4) -> None:
        """Write the tree in DBoW2's text format (ORB-SLAM's ``ORBvoc.txt``), so ORB-SLAM runs on it.

        Header ``k L scoring weighting`` (L1 score, tf-idf: ``0 0``), then one line per node but the
        root, breadth-first: ``parent is_leaf 32 descriptor bytes weight`` (the idf on a word, 0 on an
        inner node); DBoW2 numbers nodes and words in file order. ORB-SLAM puts its direct index
        ``levels_up`` levels above the declared depth ``L`` (4 on its 6-level tree), so ``L`` is
        declared as ``fv_level + levels_up`` to keep our direct-index level; the descent itself stops
        at the leaves whatever ``L`` says. No trailing newline: DBoW2's reader, looping on ``eof``,
        would read an empty last line as a node.
        """
        parent = np.full(self.num_nodes, -1, dtype=np.int64)
        new_id = np.full(self.num_nodes, -1, dtype=np.int64)
        new_id[0] = 0
        order: list[int] = []
        queue = [0]
        while queue:
            node = queue.pop(0)
            for c in self.children[node]:
                if c < 0:
                    continue
                parent[c] = node
                new_id[c] = len(order) + 1
                order.append(int(c))
                queue.append(int(c))
        lines = [f"{self.k} {max(self.depth, self.fv_level + levels_up)} 0 0"]
        for n in order:
            word = int(self.word_of_node[n])
            weight = repr(float(self.idf[word])) if word >= 0 else "0"
            desc = " ".join(str(b) for b in self.centers[n].tolist())
            lines.append(f"{new_id[parent[n]]} {1 if word >= 0 else 0} {desc} {weight}")
        Path(path).write_text("\n".join(lines))

    # ------------------------------------------------------------------------------------------
    @staticmethod
    def train(
        images_descriptors: Iterable[U8],
        options: TrainOptions = TrainOptions(),
        progress: bool = False,
    ) -> Vocabulary:
        """Train on a list of per-image descriptor arrays (each (N_i, 32) uint8).

        Every image is one document for the idf (``idf = log(N_images / N_images_with_word)``).
        """
        per_image = [np.ascontiguousarray(d, dtype=np.uint8).reshape(-1, 32) for d in images_descriptors]
        per_image = [d for d in per_image if len(d)]
        if not per_image:
            raise ValueError("no descriptors to train on")
        all_desc = np.concatenate(per_image)
        log.info(
            "training vocabulary k=%d depth=%d on %d descriptors", options.k, options.depth, len(all_desc)
        )
        rng = np.random.default_rng(options.seed)
        centers: list[U8] = [np.zeros(32, dtype=np.uint8)]
        children: list[list[int]] = [[]]
        levels: list[int] = [0]

        # Breadth-first: (node, indices of descriptors under it).
        frontier: list[tuple[int, I64]] = [(0, np.arange(len(all_desc)))]
        bar = None
        if progress:
            from tqdm import tqdm

            bar = tqdm(desc="vocab nodes")
        while frontier:
            node, idx = frontier.pop(0)
            if bar is not None:
                bar.update(1)
            if levels[node] >= options.depth or len(idx) == 0:
                continue
            desc = all_desc[idx]
            if len(desc) <= options.k:
                # DBoW2: fewer descriptors than branches -> each (distinct) descriptor is a child.
                uniq = np.unique(desc, axis=0)
                groups = [(uniq[i], idx[(desc == uniq[i]).all(axis=1)]) for i in range(len(uniq))]
            else:
                labels, cents = _kmajority(desc, options.k, rng, options.max_iterations)
                groups = [(cents[j], idx[labels == j]) for j in range(len(cents)) if np.any(labels == j)]
            for cent, sub in groups:
                cid = len(centers)
                centers.append(cent)
                children.append([])
                levels.append(levels[node] + 1)
                children[node].append(cid)
                frontier.append((cid, sub))
        if bar is not None:
            bar.close()

        n = len(centers)
        child_arr = np.full((n, options.k), -1, dtype=np.int32)
        for i, ch in enumerate(children):
            child_arr[i, : len(ch)] = ch
        leaf = child_arr[:, 0] < 0
        leaf[0] = False
        word_of_node = np.full(n, -1, dtype=np.int32)
        word_of_node[leaf] = np.arange(int(leaf.sum()), dtype=np.int32)
        vocab = Vocabulary(
            centers=np.stack(centers),
            children=child_arr,
            level=np.asarray(levels, dtype=np.int8),
            word_of_node=word_of_node,
            idf=np.ones(int(leaf.sum())),
            k=options.k,
            depth=options.depth,
        )
        # idf from document frequencies.
        df = np.zeros(vocab.num_words)
        for d in per_image:
            w, _ = vocab.lookup(d)
            df[np.unique(w)] += 1
        idf = np.log(len(per_image) / np.maximum(df, 1.0))
        # A word never seen in training keeps the largest idf (it is rare by definition).
        idf[df == 0] = np.log(len(per_image))
        vocab.idf = idf
        log.info("vocabulary trained: %s", vocab)
        return vocab


def _kmajority(desc: U8, k: int, rng: np.random.Generator, iterations: int) -> tuple[I64, U8]:
    """k-majority clustering (k-medians on bits) with k-means++ seeding. Returns (labels, centres (k, 32))."""
    n = len(desc)
    d64 = _as_u64(desc)
    # k-means++ seeding on squared Hamming distances.
    first = int(rng.integers(n))
    cidx = [first]
    mind = np.bitwise_count(d64 ^ d64[first]).sum(axis=1).astype(np.float64)
    for _ in range(1, k):
        p = mind**2
        tot = p.sum()
        if tot <= 0:
            break
        c = int(rng.choice(n, p=p / tot))
        cidx.append(c)
        mind = np.minimum(mind, np.bitwise_count(d64 ^ d64[c]).sum(axis=1))
    cents = desc[cidx].copy()
    labels = np.full(n, -1, dtype=np.int64)
    bits = None
    for _ in range(max(1, iterations)):
        dist = np.bitwise_count(d64[:, None, :] ^ _as_u64(cents)[None, :, :]).sum(axis=2)
        new = np.argmin(dist, axis=1)
        if np.array_equal(new, labels):
            break
        labels = new
        if bits is None:
            bits = np.unpackbits(desc, axis=1).astype(np.float32)  # (n, 256)
        onehot = np.zeros((len(cents), n), dtype=np.float32)
        onehot[labels, np.arange(n)] = 1.0
        counts = onehot.sum(axis=1)
        sums = onehot @ bits
        keep = counts > 0
        maj = (sums[keep] * 2 >= counts[keep, None]).astype(np.uint8)
        cents = cents.copy()
        cents[keep] = np.packbits(maj, axis=1)
    return labels, cents


@lru_cache(maxsize=1)
def default_vocabulary() -> Vocabulary:
    """The vocabulary shipped with the package (``hivemap/maps/data/orb_vocab.npz``), loaded once."""
    ref = resources.files("hivemap.maps").joinpath(DEFAULT_VOCAB_PATH)
    with resources.as_file(ref) as p:
        if not Path(p).exists():
            raise FileNotFoundError(f"{p}: no shipped vocabulary; run `hivemap vocab train`")
        return Vocabulary.load(p)
