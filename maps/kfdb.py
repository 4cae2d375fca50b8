"""Keyframe database: an inverted index (word -> keyframes) over every map of the stack.

Scores are DBoW2 L1 scores (``sum_i min(v_i, w_i)`` over common words of L1-normalised tf-idf
vectors). As DBoW2's ``detectLoopCandidates``, only the keyframes sharing a word with the query are
touched: the postings of the query's words are gathered from one word-sorted array and accumulated with
``np.bincount``, with no Python loop per word or posting (:class:`_Postings`).

Each keyframe occupies a slot; ``slot -> key, map id`` live in arrays so map filters are vectorised.
Removing a keyframe zeroes its postings and frees the slot for reuse.
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


class _Postings:
    """The inverted index as arrays (word, slot, weight), sorted by word, plus the keyframes added since
    the last merge into them: scoring a query gathers its words' ranges and accumulates them in C, with no
    Python loop per word or per posting (that loop, and appending postings one by one, were most of a
    look-up's BoW time and grew with the database). A posting's order within its word is its arrival's.
    Removing a keyframe zeroes its weights (its slot may be reused: zeros add nothing to a score)."""

    MERGE_EVERY = 16  # keyframes kept aside before they are merged into the sorted arrays

    def __init__(self) -> None:
        self.words = np.zeros(0, dtype=np.int32)
        self.slots = np.zeros(0, dtype=np.int32)
        self.weights = np.zeros(0, dtype=np.float32)
        self._new: list[tuple[NDArray[np.int32], NDArray[np.int32], NDArray[np.float32]]] = []
        self._new_cat: tuple[NDArray[np.int32], NDArray[np.int32], NDArray[np.float32]] | None = None

    def add(self, slot: int, words: NDArray[np.int32], weights: NDArray[np.float32]) -> None:
        self._new.append((words, np.full(len(words), slot, np.int32), weights))
        self._new_cat = None
        if len(self._new) >= self.MERGE_EVERY:
            self._merge()

    def _pending(self) -> tuple[NDArray[np.int32], NDArray[np.int32], NDArray[np.float32]]:
        if self._new_cat is None:
            if self._new:
                w, s, x = zip(*self._new, strict=True)
                self._new_cat = (np.concatenate(w), np.concatenate(s), np.concatenate(x))
            else:
                self._new_cat = (self.words[:0], self.slots[:0], self.weights[:0])
        return self._new_cat

    def _merge(self) -> None:
        w, s, x = self._pending()
        order = np.argsort(w, kind="stable")
        pos = np.searchsorted(self.words, w[order], side="right")  # after the word's older postings
        self.words = np.insert(self.words, pos, w[order])
        self.slots = np.insert(self.slots, pos, s[order])
        self.weights = np.insert(self.weights, pos, x[order])
        self._new, self._new_cat = [], None

    def remove(self, slot: int) -> None:
        self.weights[self.slots == slot] = 0.0
        self._new = [(w, s, np.where(s == slot, np.float32(0.0), x)) for w, s, x in self._new]
        self._new_cat = None

    def scores(
        self, words: NDArray[np.int32], weights: NDArray[np.float64], n_slots: int
    ) -> NDArray[np.float64]:
        """Per slot, the sum over the query's words of ``min(query weight, posting weight)``; each slot's
        terms are summed in the query's word order, as one loop over the words would."""
        qw = weights.astype(np.float32)
        lo = np.searchsorted(self.words, words, side="left")
        hi = np.searchsorted(self.words, words, side="right")
        lens = hi - lo
        total = int(lens.sum())
        out = np.zeros(n_slots)
        if total:
            # the postings of every query word, in the query's word order: ranges lo[i]:hi[i] laid end to end
            starts = np.repeat(lo - np.cumsum(lens) + lens, lens)
            idx = starts + np.arange(total)
            terms = np.minimum(self.weights[idx], np.repeat(qw, lens))
            out += np.bincount(self.slots[idx], weights=terms, minlength=n_slots)[:n_slots]
        pw, ps, px = self._pending()
        if len(pw):
            i = np.searchsorted(words, pw)
            hit = (i < len(words)) & (words[np.minimum(i, len(words) - 1)] == pw) if len(words) else pw < 0
            if hit.any():
                terms = np.minimum(px[hit], qw[i[hit]])
                out += np.bincount(ps[hit], weights=terms, minlength=n_slots)[:n_slots]
        return out


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
        self._postings = _Postings()
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
        self._postings.add(slot, bow.words, bow.weights.astype(np.float32))

    def remove(self, key: KfKey) -> None:
        """Forget a keyframe (no-op if unknown)."""
        slot = self._slot_of.pop(key, None)
        if slot is None:
            return
        self._bows.pop(key)
        self._features.pop(key, None)
        self._postings.remove(slot)
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
        """L1 score of ``bow`` against every slot (dead slots and keyframes sharing no word score 0)."""
        return self._postings.scores(bow.words, bow.weights, len(self._keys))

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
