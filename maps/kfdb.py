"""Keyframe database: an inverted index (word -> keyframes) over every map of the stack.

Scores are DBoW2 L1 scores (``sum_i min(v_i, w_i)`` over common words of L1-normalised tf-idf
vectors), computed for all keyframes at once: the postings of the query's words are concatenated and
accumulated with ``np.bincount`` (measured: a few ms at 10k keyframes; bench/placerec.py).

Each keyframe occupies a slot; ``slot -> key, map id`` live in arrays so map filters are vectorised.
Removing a keyframe deletes its postings (swap-with-last) and frees the slot for reuse.
After a merge, ``reassign_map(source, target)`` relabels every keyframe of the source map.
The BoW vector and direct index (``FeatureVector``) of each keyframe are kept for the matcher.
"""

from __future__ import annotations

import logging
from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from hivemap.maps.vocabulary import BowVector, FeatureVector

log = logging.getLogger(__name__)

KfKey = tuple[str, int]


class _Posting:
    """Growable (slot, weight) arrays of one word."""

    __slots__ = ("slots", "weights", "n")

    def __init__(self) -> None:
        self.slots = np.empty(8, dtype=np.int32)
        self.weights = np.empty(8, dtype=np.float32)
        self.n = 0

    def append(self, slot: int, weight: float) -> None:
        if self.n == len(self.slots):
            self.slots = np.resize(self.slots, 2 * self.n)
            self.weights = np.resize(self.weights, 2 * self.n)
        self.slots[self.n] = slot
        self.weights[self.n] = weight
        self.n += 1

    def remove(self, slot: int) -> None:
        hit = np.flatnonzero(self.slots[: self.n] == slot)
        for i in hit[::-1]:
            last = self.n - 1
            self.slots[i] = self.slots[last]
            self.weights[i] = self.weights[last]
            self.n = last


@dataclass(frozen=True)
class Feasibility:
    """Outcome of the cheap BoW check "is a merge with another map even possible" (seed 004, Alg. 1).

    ``external_score``: best score of the query against keyframes of OTHER maps (``best_key``);
    ``internal_score``: best score of ``best_key`` against its own map (itself excluded), i.e. how well
    that place matches its own neighbours. Feasible when ``external >= ratio * internal`` and
    ``external >= min_score``.
    """

    feasible: bool
    external_score: float
    internal_score: float
    best_key: KfKey | None
    best_map: int | None


class KeyframeDatabase:
    """Inverted index over the keyframes of every map in the stack."""

    def __init__(self) -> None:
        self._postings: dict[int, _Posting] = {}
        self._slot_of: dict[KfKey, int] = {}
        self._keys: list[KfKey | None] = []
        self._map = np.zeros(0, dtype=np.int64)
        self._alive = np.zeros(0, dtype=bool)
        self._free: list[int] = []
        self._bows: dict[KfKey, BowVector] = {}
        self._features: dict[KfKey, FeatureVector] = {}

    # ------------------------------------------------------------------------------------------
    def __len__(self) -> int:
        return len(self._slot_of)

    def __contains__(self, key: object) -> bool:
        return key in self._slot_of

    def keys(self) -> list[KfKey]:
        return list(self._slot_of)

    def bow(self, key: KfKey) -> BowVector:
        return self._bows[key]

    def features(self, key: KfKey) -> FeatureVector | None:
        return self._features.get(key)

    def map_of(self, key: KfKey) -> int:
        return int(self._map[self._slot_of[key]])

    def keys_of_map(self, map_id: int) -> list[KfKey]:
        slots = np.flatnonzero(self._alive & (self._map == map_id))
        return [k for s in slots if (k := self._keys[s]) is not None]

    # ------------------------------------------------------------------------------------------
    def add(self, key: KfKey, map_id: int, bow: BowVector, features: FeatureVector | None = None) -> None:
        """Index a keyframe (re-adding a key replaces its entry)."""
        if key in self._slot_of:
            self.remove(key)
        if self._free:
            slot = self._free.pop()
        else:
            slot = len(self._keys)
            self._keys.append(None)
            if slot >= len(self._map):
                cap = max(64, 2 * len(self._map))
                self._map = np.resize(self._map, cap)
                self._alive = np.concatenate([self._alive, np.zeros(cap - len(self._alive), dtype=bool)])
        self._keys[slot] = key
        self._slot_of[key] = slot
        self._map[slot] = map_id
        self._alive[slot] = True
        self._bows[key] = bow
        if features is not None:
            self._features[key] = features
        postings = self._postings
        for w, x in zip(bow.words.tolist(), bow.weights.tolist(), strict=True):
            p = postings.get(w)
            if p is None:
                p = postings[w] = _Posting()
            p.append(slot, x)

    def remove(self, key: KfKey) -> None:
        """Forget a keyframe (no-op if unknown)."""
        slot = self._slot_of.pop(key, None)
        if slot is None:
            return
        bow = self._bows.pop(key)
        self._features.pop(key, None)
        for w in bow.words.tolist():
            p = self._postings.get(w)
            if p is not None:
                p.remove(slot)
        self._keys[slot] = None
        self._alive[slot] = False
        self._free.append(slot)

    def set_map(self, key: KfKey, map_id: int) -> None:
        self._map[self._slot_of[key]] = map_id

    def reassign_map(self, source_map: int, target_map: int) -> int:
        """After merging ``source_map`` into ``target_map``: relabel its keyframes. Returns how many."""
        sel = self._alive & (self._map == source_map)
        self._map[sel] = target_map
        return int(sel.sum())

    # ------------------------------------------------------------------------------------------
    def scores(self, bow: BowVector) -> NDArray[np.float64]:
        """L1 score of ``bow`` against every slot (dead slots score 0)."""
        n_slots = len(self._keys)
        slot_parts: list[NDArray[np.int32]] = []
        weight_parts: list[NDArray[np.float32]] = []
        qw: list[float] = []
        lens: list[int] = []
        postings = self._postings
        for w, x in zip(bow.words.tolist(), bow.weights.tolist(), strict=True):
            p = postings.get(w)
            if p is None or p.n == 0:
                continue
            slot_parts.append(p.slots[: p.n])
            weight_parts.append(p.weights[: p.n])
            qw.append(x)
            lens.append(p.n)
        if not slot_parts:
            return np.zeros(n_slots)
        slots = np.concatenate(slot_parts)
        weights = np.concatenate(weight_parts)
        qrep = np.repeat(np.asarray(qw, dtype=np.float32), lens)
        out = np.bincount(slots, weights=np.minimum(weights, qrep), minlength=n_slots).astype(np.float64)
        return out

    def scores_of(self, keys: list[KfKey], scores: NDArray[np.float64]) -> NDArray[np.float64]:
        """The entries of ``scores`` (from :meth:`scores`) for ``keys`` (0 for unknown keys)."""
        out = np.zeros(len(keys))
        for i, k in enumerate(keys):
            slot = self._slot_of.get(k)
            if slot is not None and slot < len(scores):
                out[i] = scores[slot]
        return out

    def query(
        self,
        bow: BowVector,
        n: int,
        exclude_map: int | None = None,
        only_map: int | None = None,
        exclude_keys: Iterable[KfKey] = (),
        min_score: float = 0.0,
        scores: NDArray[np.float64] | None = None,
    ) -> list[tuple[KfKey, float]]:
        """Best ``n`` keyframes by L1 score, highest first.

        ``exclude_map``: skip keyframes of that map (merge candidates: "only other maps");
        ``only_map``: only that map (loop candidates: pass the query's covisible keyframes and itself in
        ``exclude_keys``, and ORB-SLAM's lowest covisible score as ``min_score``);
        ``scores``: ``self.scores(bow)`` if the caller has it already (one query's merge, loop and
        feasibility look-ups share it: the scoring is most of a look-up's time).
        """
        s = self.scores(bow) if scores is None else scores
        if len(s) == 0 or n <= 0:
            return []
        ok = self._alive[: len(s)] & (s > max(min_score, 0.0))
        m = self._map[: len(s)]
        if exclude_map is not None:
            ok &= m != exclude_map
        if only_map is not None:
            ok &= m == only_map
        for k in exclude_keys:
            slot = self._slot_of.get(k)
            if slot is not None and slot < len(ok):
                ok[slot] = False
        cand = np.flatnonzero(ok)
        if len(cand) > n:
            top = np.argpartition(-s[cand], n - 1)[:n]
            cand = cand[top]
        cand = cand[np.argsort(-s[cand], kind="stable")]
        out: list[tuple[KfKey, float]] = []
        for c in cand:
            key = self._keys[c]
            if key is not None:
                out.append((key, float(s[c])))
        return out

    def feasibility(
        self,
        bow: BowVector,
        map_id: int,
        ratio: float = 0.5,
        min_score: float = 0.01,
        exclude_keys: Iterable[KfKey] = (),
        scores: NDArray[np.float64] | None = None,
    ) -> Feasibility:
        """Seed 004's cheap "is a merge feasible" check for a keyframe of map ``map_id``.

        Finds the best keyframe of another map; feasible when the query scores against it at least
        ``ratio`` times as well as that keyframe scores against its own map (itself excluded).
        ``scores``: as in :meth:`query`.
        """
        best = self.query(bow, 1, exclude_map=map_id, exclude_keys=exclude_keys, scores=scores)
        if not best:
            return Feasibility(False, 0.0, 0.0, None, None)
        key, ext = best[0]
        other = self.map_of(key)
        own = self.query(self._bows[key], 1, only_map=other, exclude_keys=[key])
        internal = own[0][1] if own else 0.0
        ok = ext >= min_score and ext >= ratio * internal
        return Feasibility(bool(ok), ext, internal, key, other)
