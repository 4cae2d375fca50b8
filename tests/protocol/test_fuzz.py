"""10,000 random and mutated frames: the decoder only ever raises ProtocolError, in bounded memory.

A hang is caught by the test's timeout; how fast decoding is belongs to the benchmarks, not here."""

from __future__ import annotations

import tracemalloc

import pytest

from hivemap.protocol import Limits, ProtocolError, decode
from hivemap.protocol.fuzz import fuzz_frames


@pytest.mark.timeout(60)
def test_decoder_survives_10k_hostile_frames() -> None:
    limits = Limits()
    frames = list(fuzz_frames(10_000, seed=42))
    assert len(frames) == 10_000
    rejected = 0
    tracemalloc.start()
    try:
        for f in frames:
            try:
                decode(f, limits)
            except ProtocolError:
                rejected += 1
            # anything else propagates and fails the test
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    # Most frames are invalid; a few bit flips land in array data and stay valid.
    assert rejected > 9000, rejected
    # Never allocates more than the frame limit, however large the lengths a frame declares
    # (arrays are views on the frame; lists/maps are capped at 64 entries).
    assert peak < limits.max_frame_bytes, peak
