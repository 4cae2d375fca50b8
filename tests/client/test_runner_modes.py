"""GNSS modes of the offline runner (paper Table 8 semantics)."""

from __future__ import annotations

import numpy as np
import pytest

from hivemap.client.runner import GnssMode, parse_gnss_mode, select_gnss


def test_parse_modes():
    assert parse_gnss_mode("denied") == GnssMode("denied")
    assert parse_gnss_mode("all") == GnssMode("all")
    assert parse_gnss_mode("every:20s") == GnssMode("every", period_s=20.0)
    assert parse_gnss_mode("every:2.5") == GnssMode("every", period_s=2.5)
    assert parse_gnss_mode("random:4") == GnssMode("random", count=4)
    assert str(parse_gnss_mode("every:20s")) == "every:20s"
    for bad in ("every:0s", "random:x", "sometimes", "every:-3s"):
        with pytest.raises(ValueError):
            parse_gnss_mode(bad)


def test_select_modes():
    t = np.arange(0, 100, 0.2)  # 5 Hz for 100 s
    valid = np.ones(t.size, bool)
    valid[(t > 39.0) & (t < 41.5)] = False  # an outage around 40 s
    assert not select_gnss(t, valid, GnssMode("denied")).any()
    assert select_gnss(t, valid, GnssMode("all")).sum() == valid.sum()
    every = select_gnss(t, valid, GnssMode("every", period_s=20.0))
    used = t[every]
    # 0, 20, then the first valid fix after the outage (41.6), then 61.6, 81.6
    assert np.allclose(used, [0.0, 20.0, 41.6, 61.6, 81.6])
    assert np.all(np.diff(used) >= 20.0 - 1e-9)
    assert valid[every].all()
    r1 = select_gnss(t, valid, GnssMode("random", count=4), seed=7)
    r2 = select_gnss(t, valid, GnssMode("random", count=4), seed=7)
    r3 = select_gnss(t, valid, GnssMode("random", count=4), seed=8)
    assert r1.sum() == 4 and valid[r1].all()
    assert np.array_equal(r1, r2)  # seeded: reproducible
    assert not np.array_equal(r1, r3)
    # fewer valid fixes than asked for: all of them
    few = np.zeros(t.size, bool)
    few[[3, 50]] = True
    assert select_gnss(t, few, GnssMode("random", count=4)).sum() == 2
