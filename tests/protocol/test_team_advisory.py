"""Protocol v4's ``team_advisory`` (server -> agent) and the hello's ``team_advisories``: round trip, the
field validation, and older frames that cannot carry them."""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import msgpack
import numpy as np
import pytest

from hivemap.protocol import FieldError, Hello, TeamAdvisory, UnknownTypeError, decode, encode

CAMERA: dict[str, object] = {
    "width": 640, "height": 480, "fx": 400.0, "fy": 400.0, "cx": 320.0, "cy": 240.0, "dist": [0.0] * 4,
}  # fmt: skip


def _advisory(**changes: Any) -> TeamAdvisory:
    msg = TeamAdvisory(
        map_id=3,
        computed_at=1.8e9,
        goals=np.array([[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]]),
        desired_velocity=np.array([1.0, 0.0, 0.0]),
        safe_velocity=np.array([0.9, -0.1, 0.0]),
        radius_m=0.8,
        session=2,
    )
    return replace(msg, **changes)


def _as_version(frame: bytes, v: int, drop: tuple[str, ...] = ()) -> bytes:
    obj = msgpack.unpackb(frame, raw=False)
    obj["v"] = v
    for k in drop:
        obj["body"].pop(k)
    return msgpack.packb(obj, use_bin_type=True)


def test_team_advisory_round_trips_and_needs_v4() -> None:
    for msg in (_advisory(), _advisory(goals=np.zeros((0, 3)))):
        seq, got = decode(encode(msg, 5))
        assert seq == 5 and isinstance(got, TeamAdvisory)
        for f in ("goals", "desired_velocity", "safe_velocity"):
            assert getattr(got, f).tobytes() == getattr(msg, f).tobytes()
        assert (got.map_id, got.computed_at, got.radius_m, got.session) == (3, 1.8e9, 0.8, 2)
    with pytest.raises(UnknownTypeError, match="v4"):
        decode(_as_version(encode(_advisory(), 1), 3))


@pytest.mark.parametrize(
    ("changes", "field"),
    [
        ({"goals": np.zeros((2, 2))}, "body.goals"),
        ({"goals": np.zeros((300, 3))}, "body.goals"),
        ({"safe_velocity": np.array([np.nan, 0.0, 0.0])}, "body.safe_velocity"),
        ({"desired_velocity": np.zeros(2)}, "body.desired_velocity"),
        ({"radius_m": -1.0}, "body.radius_m"),
        ({"map_id": -1}, "body.map_id"),
    ],
)
def test_bad_team_advisory_fields_are_named(changes: dict[str, Any], field: str) -> None:
    with pytest.raises(FieldError) as e:
        decode(encode(_advisory(**changes), 1))
    assert e.value.field == field


def test_hello_team_advisories_is_v4_and_defaults_off() -> None:
    hello = Hello("uav1", "uav", CAMERA, "t", mission="m1", team_advisories=True)
    _, got = decode(encode(hello, 0))
    assert isinstance(got, Hello) and got.team_advisories is True
    # a v3 agent's hello has no such field: it reads as off (the server then never sends it one)
    _, old = decode(_as_version(encode(replace(hello, team_advisories=False), 0), 3, ("team_advisories",)))
    assert isinstance(old, Hello) and old.team_advisories is False
    with pytest.raises(FieldError) as e:
        decode(_as_version(encode(hello, 0), 3))
    assert e.value.field == "body.team_advisories"
    bad = msgpack.unpackb(encode(hello, 0), raw=False)
    bad["body"]["team_advisories"] = 1
    with pytest.raises(FieldError) as e:
        decode(msgpack.packb(bad, use_bin_type=True))
    assert e.value.field == "body.team_advisories"


def test_team_advisory_is_not_written_for_a_v3_reader() -> None:
    """A v3 peer cannot read the type at all (``carries``; ``encode`` refuses), and a hello downgraded to v3
    loses its opt-in (a v3 reader never knew the field)."""
    from hivemap.protocol import carries, downgrade

    assert carries(4, "team_advisory") and not carries(3, "team_advisory") and carries(3, "correction")
    with pytest.raises(ValueError, match="v4"):
        encode(_advisory(), 1, version=3)
    hello = Hello("uav1", "uav", CAMERA, "t", mission="m1", team_advisories=True)
    with pytest.raises(ValueError, match="team_advisories"):
        encode(hello, 0, version=3)
    _, old = decode(encode(downgrade(hello, 3), 0, version=3))
    assert isinstance(old, Hello) and old.team_advisories is False
