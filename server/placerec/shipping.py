"""A keyframe's features go to a verification worker once, not with every job.

A job's slices carry copies of ~15-30 keyframes, and about three quarters of a job's bytes are their
features (keypoints, octaves, descriptors, stereo u) and direct-index vectors, which never change once a
keyframe is in the server. Each worker process keeps the features of the keyframes it was sent in a
bounded least-recently-used cache; the event loop's side keeps a mirror of that cache's keys, updated in
the same order as the worker updates its own, so it knows without asking which keyframes a job can ship
bare. Jobs to one worker run in the order they were sent (one process, one queue), which is what keeps
the two in step; a restarted worker starts with both empty.
"""

from __future__ import annotations

import copy
from collections import OrderedDict
from dataclasses import dataclass, replace
from typing import Any, Generic, TypeVar

from hivemap.maps.vocabulary import FeatureVector
from hivemap.server.placerec.job import QueryJob
from hivemap.server.placerec.types import CandidateReport

KfKey = tuple[str, int]
V = TypeVar("V")

# what a keyframe copy in a job holds that never changes (its pose and point references do)
_FEATURES = ("camera", "keypoints", "octaves", "descriptors", "u_right", "stereo_baseline")


@dataclass
class Bundle:
    """One keyframe's features and, when a job had it, its direct-index vector."""

    features: tuple[Any, ...]
    vector: FeatureVector | None


@dataclass
class ShippedJob:
    """A job whose keyframe copies the worker holds come without their features (``descriptors`` None),
    and without the direct-index vectors listed in ``vectors_held``. Both sides update their caches in
    the order of the job's slices and their keyframes."""

    job: QueryJob
    vectors_held: set[KfKey]
    reset: bool = False  # the worker empties its cache first (the packer forgot what it holds)


class _Lru(Generic[V]):
    """Keys in least-recently-used order, at most ``capacity``: one class for the worker's cache and
    the packer's mirror of it, so both evict alike."""

    def __init__(self, capacity: int) -> None:
        self.capacity = max(1, int(capacity))
        self.items: OrderedDict[KfKey, V] = OrderedDict()

    def touch(self, key: KfKey, value: V | None = None) -> None:
        """``key`` becomes the most recent, with ``value`` when given (a new key needs one)."""
        if key in self.items:
            self.items.move_to_end(key)
            if value is not None:
                self.items[key] = value
        else:
            assert value is not None, key
            self.items[key] = value
            while len(self.items) > self.capacity:
                self.items.popitem(last=False)


class Shipper:
    """The event loop's side, one per worker process: which keyframes that worker holds (the value:
    whether with its direct-index vector)."""

    def __init__(self, capacity: int) -> None:
        self._held: _Lru[bool] = _Lru(capacity)
        self._reset = False

    def reset(self) -> None:
        """Forget what the worker holds (it died, or a job failed there): the next job tells it to
        empty its cache too."""
        self._held.items.clear()
        self._reset = True

    def pack(self, job: QueryJob) -> ShippedJob:
        """``job`` with the features the worker holds left out (``job`` itself is not changed: the
        keyframe copies shipped bare are copied again)."""
        held = self._held.items
        features = dict(job.features)
        vectors_held: set[KfKey] = set()
        slices = []
        for s in job.slices:
            kfs = []
            for kf in s.keyframes:
                key = kf.key
                with_vector = held.get(key)
                if with_vector is None or (not with_vector and key in job.features):
                    # not held (first time, or evicted), or held without the vector this job has
                    kfs.append(kf)
                    self._held.touch(key, key in job.features)
                else:
                    c = copy.copy(kf)
                    for a in _FEATURES:
                        setattr(c, a, None)
                    kfs.append(c)
                    if with_vector and features.pop(key, None) is not None:
                        vectors_held.add(key)
                    self._held.touch(key)
            slices.append(replace(s, keyframes=kfs))
        reset, self._reset = self._reset, False
        return ShippedJob(replace(job, slices=slices, features=features), vectors_held, reset)


# the worker's side: one cache per worker process
_CACHE: _Lru[Bundle] | None = None


def unpack(shipped: ShippedJob, capacity: int) -> QueryJob:
    """The job as it was packed, its features from this worker's cache, which is updated keyframe by
    keyframe in the packer's order (so a keyframe shipped bare is held when it is read)."""
    global _CACHE
    if _CACHE is None or _CACHE.capacity != max(1, int(capacity)) or shipped.reset:
        _CACHE = _Lru(capacity)
    cache = _CACHE
    job = shipped.job
    for s in job.slices:
        for kf in s.keyframes:
            key = kf.key
            if kf.descriptors is None:  # shipped bare
                b = cache.items.get(key)
                if b is None:
                    raise RuntimeError(f"keyframe {key} was shipped bare to a worker that does not hold it")
                for a, v in zip(_FEATURES, b.features, strict=True):
                    setattr(kf, a, v)
                if key in shipped.vectors_held:
                    assert b.vector is not None
                    job.features[key] = b.vector
                cache.touch(key)
            else:
                old = cache.items.get(key)
                vec = job.features.get(key, old.vector if old is not None else None)
                cache.touch(key, Bundle(tuple(getattr(kf, a) for a in _FEATURES), vec))
    return job


def run_shipped(shipped: ShippedJob, capacity: int) -> list[CandidateReport]:
    """:func:`..verify.run_job` of a shipped job, in a worker process."""
    from hivemap.server.placerec.verify import run_job

    return run_job(unpack(shipped, capacity))
