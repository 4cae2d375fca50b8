"""10,000 random and mutated frames: the decoder only ever raises ProtocolError, fast, in bounded memory."""

from __future__ import annotations

import time
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
    t0 = time.perf_counter()
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
    elapsed = time.perf_counter() - t0
    # Most frames are invalid; a few bit flips land in array data and stay valid.
    assert rejected > 9000, rejected
    # Never allocates more than the frame limit, however large the lengths a frame declares
    # (arrays are views on the frame; lists/maps are capped at 64 entries).
    assert peak < limits.max_frame_bytes, peak
    assert elapsed < 30, elapsed  # no hang: ~2 s on the 2-core dev machine
