"""Which keyframe a rendezvous observation is anchored to (``client.rendezvous._reference``)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from hivemap.client.rendezvous import _reference
from hivemap.maps.geometry import se3, so3_exp


def _kf(kid: int, emitted: bool, odom_sigma: tuple[float, float] | None, x: float) -> SimpleNamespace:
    return SimpleNamespace(
        id=kid, emitted=emitted, odom_sigma=odom_sigma, T_wc=se3(so3_exp([0, 0, 0.1]), [x, 0, 0])
    )


def test_the_reference_is_the_newest_emitted_keyframe_and_only_if_it_was_tracked_well() -> None:
    frame = se3(so3_exp([0.0, 0.0, 0.3]), [2.0, 1.0, 0.5])
    res = SimpleNamespace(session=0, world_from_cam=frame)
    kfs = {0: _kf(0, True, None, 0.0), 1: _kf(1, True, None, 1.0), 2: _kf(2, False, None, 1.5)}
    fe = SimpleNamespace(session=0, keyframes=kfs)
    kid, ref_from_cam = _reference(fe, res)  # type: ignore[misc]
    assert kid == 1  # keyframe 2 is not on the server yet
    np.testing.assert_allclose(kfs[1].T_wc @ ref_from_cam, frame, atol=1e-12)
    # a newest emitted keyframe made after lost or weak tracking (at the IMU's pose): no observation
    kfs[1] = _kf(1, True, (0.03, 0.4), 1.0)
    assert _reference(fe, res) is None
    # until a keyframe tracked well is emitted after it
    kfs[2] = _kf(2, True, None, 1.5)
    assert _reference(fe, res)[0] == 2  # type: ignore[index]
    # another session's frame is never anchored here
    assert _reference(SimpleNamespace(session=1, keyframes=kfs), res) is None
