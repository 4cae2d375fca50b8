"""Protocol v2: every message round-trips exactly; bad frames raise ProtocolError naming the field; v1
frames still read."""

from __future__ import annotations

from dataclasses import fields, replace
from typing import Any

import msgpack
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from hivemap.maps.geometry import se3, so3_exp
from hivemap.protocol import (
    PROTOCOL_VERSION,
    Ack,
    Bye,
    Correction,
    Error,
    FieldError,
    FrameTooLarge,
    Hello,
    Keyframe,
    Limits,
    MapPoints,
    PoseUpdates,
    ProtocolError,
    Rendezvous,
    TeamAdvisory,
    UnknownTypeError,
    VersionError,
    Welcome,
    decode,
    decode_versioned,
    downgrade,
    encode,
)

finite = st.floats(-1e6, 1e6, allow_nan=False, allow_infinity=False)
seqs = st.integers(0, 2**62)
ids = st.integers(0, 2**62)
text = st.text(max_size=60)


@st.composite
def poses(draw: Any) -> np.ndarray:
    rv = draw(hnp.arrays(np.float64, 3, elements=st.floats(-3, 3)))
    t = draw(hnp.arrays(np.float64, 3, elements=finite))
    return se3(so3_exp(rv), t)


@st.composite
def pose_stacks(draw: Any, n: int) -> np.ndarray:
    return np.array([draw(poses()) for _ in range(n)]).reshape(n, 4, 4)


def arr(dtype: Any, shape: tuple[int, ...], elements: Any = None) -> Any:
    return hnp.arrays(dtype, shape, elements=elements)


cameras = st.fixed_dictionaries(
    {
        "width": st.integers(1, 4000),
        "height": st.integers(1, 4000),
        "fx": st.floats(1, 5000),
        "fy": st.floats(1, 5000),
        "cx": finite,
        "cy": finite,
        "dist": st.lists(st.floats(-1, 1), min_size=4, max_size=4),
    }
)


@st.composite
def keyframes(draw: Any) -> Keyframe:
    n = draw(st.integers(0, 300))
    has_gnss = draw(st.booleans())
    up = draw(st.one_of(st.none(), arr(np.float64, (3,), st.floats(-1, 1))))
    session = draw(st.integers(0, 100))
    guess = session >= 1 and draw(st.booleans())
    if up is not None and np.linalg.norm(up) < 0.1:
        up = None
    stereo = draw(st.booleans())
    ur = st.one_of(st.just(float("nan")), st.floats(-1e4, 1e4, width=32))
    return Keyframe(
        kf_id=draw(ids),
        timestamp=draw(finite),
        world_from_cam=draw(poses()),
        keypoints=draw(arr(np.float32, (n, 2), st.floats(-1e4, 1e4, width=32))),
        octaves=draw(arr(np.uint8, (n,))),
        descriptors=draw(arr(np.uint8, (n, 32))),
        point_ids=draw(arr(np.int64, (n,), st.integers(-1, 2**40))),
        gnss_enu=draw(arr(np.float64, (3,), finite)) if has_gnss else None,
        gnss_cov=np.diag(draw(arr(np.float64, (3,), st.floats(1e-4, 10)))) if has_gnss else None,
        session=session,
        up_cam=None if up is None else up / np.linalg.norm(up),
        prev_session_from_world=draw(poses()) if guess else None,
        prev_session_sigma=draw(arr(np.float64, (2,), st.floats(1e-3, 100))) if guess else None,
        u_right=draw(arr(np.float32, (n,), ur)) if stereo else None,
        odom_sigma=draw(st.one_of(st.none(), arr(np.float64, (2,), st.floats(0, 100)))),
        track_sigma=draw(st.one_of(st.none(), arr(np.float64, (2,), st.floats(1e-6, 100)))),
        intent_velocity=draw(st.one_of(st.none(), arr(np.float64, (3,), st.floats(-50, 50)))),
    )


@st.composite
def map_points(draw: Any) -> MapPoints:
    m = draw(st.integers(0, 300))
    return MapPoints(
        draw(arr(np.int64, (m,), st.integers(0, 2**40))),
        draw(arr(np.float64, (m, 3), finite)),
        draw(arr(np.uint8, (m, 32))),
        draw(st.integers(0, 5)),
    )


@st.composite
def pose_updates(draw: Any) -> PoseUpdates:
    k, p = draw(st.integers(0, 20)), draw(st.integers(0, 200))
    return PoseUpdates(
        draw(arr(np.int64, (k,), st.integers(0, 2**40))),
        draw(pose_stacks(k)),
        draw(arr(np.int64, (p,), st.integers(0, 2**40))),
        draw(arr(np.float64, (p, 3), finite)),
    )


@st.composite
def corrections(draw: Any) -> Correction:
    k = draw(st.integers(0, 20))
    g = draw(poses())
    g[:3, :3] *= draw(st.floats(0.1, 10))
    return Correction(draw(ids), g, draw(arr(np.int64, (k,), st.integers(0, 2**40))), draw(pose_stacks(k)))


messages = st.one_of(
    st.builds(
        Hello,
        st.text(min_size=1, max_size=64),
        st.sampled_from(["uav", "ugv"]),
        cameras,
        st.text(max_size=256),
        seqs,
        st.integers(0, 1000),
        st.none(),
        st.text("0123456789abcdef-_", min_size=1, max_size=64),
        st.none() | st.floats(1e-3, 100),
    ),
    st.builds(Welcome, seqs, text, st.booleans()),
    keyframes(),
    map_points(),
    pose_updates(),
    st.builds(Ack, seqs),
    corrections(),
    st.builds(Error, text, text, st.none() | text, st.none() | seqs),
    st.builds(Bye, text),
)


def assert_same(a: Any, b: Any) -> None:
    assert type(a) is type(b)
    for f in fields(a):
        x, y = getattr(a, f.name), getattr(b, f.name)
        if isinstance(x, np.ndarray):
            assert isinstance(y, np.ndarray) and x.dtype == y.dtype and x.shape == y.shape
            assert x.tobytes() == y.tobytes(), f.name  # bit-identical
        else:
            assert x == y, f.name


@settings(max_examples=300, deadline=None)
@given(messages, seqs)
def test_every_message_round_trips(msg: Any, seq: int) -> None:
    got_seq, got = decode(encode(msg, seq))
    assert got_seq == seq
    assert_same(msg, got)


def _kf(n: int = 100) -> Keyframe:
    rng = np.random.default_rng(0)
    return Keyframe(
        kf_id=3,
        timestamp=1.5,
        world_from_cam=np.eye(4),
        keypoints=rng.uniform(0, 600, (n, 2)).astype(np.float32),
        octaves=np.zeros(n, np.uint8),
        descriptors=rng.integers(0, 256, (n, 32), dtype=np.uint8),
        point_ids=np.arange(n, dtype=np.int64),
    )


def _tamper(frame: bytes, **changes: Any) -> bytes:
    """Re-encode a valid frame with some envelope or body entries changed (None value -> removed)."""
    obj = msgpack.unpackb(frame, raw=False)
    for key, val in changes.items():
        target, k = (obj["body"], key[5:]) if key.startswith("body_") else (obj, key)
        if val is None:
            target.pop(k, None)
        else:
            target[k] = val
    return msgpack.packb(obj, use_bin_type=True)


@pytest.mark.parametrize(
    ("mutate", "error", "field"),
    [
        (lambda m: replace(m, keypoints=m.keypoints.astype(np.float64)), FieldError, "body.keypoints"),
        (lambda m: replace(m, descriptors=m.descriptors[:, :16].copy()), FieldError, "body.descriptors"),
        (lambda m: replace(m, octaves=m.octaves[:-1].copy()), FieldError, "body.octaves"),
        (lambda m: replace(m, timestamp=float("nan")), FieldError, "body.timestamp"),
        (lambda m: replace(m, keypoints=np.full((100, 2), np.inf, np.float32)), FieldError, "body.keypoints"),
        (lambda m: replace(m, world_from_cam=np.full((4, 4), 2.0)), FieldError, "body.world_from_cam"),
        (lambda m: replace(m, point_ids=np.full(100, -5, np.int64)), FieldError, "body.point_ids"),
        (lambda m: replace(m, gnss_enu=np.zeros(3)), FieldError, "body.gnss_cov"),
        (lambda m: replace(m, up_cam=np.array([0.0, 0.0, 2.0])), FieldError, "body.up_cam"),
        (lambda m: replace(m, up_cam=np.array([np.nan, 0.0, 1.0])), FieldError, "body.up_cam"),
        (lambda m: replace(m, up_cam=np.zeros(2)), FieldError, "body.up_cam"),
        (lambda m: replace(m, u_right=np.zeros(99, np.float32)), FieldError, "body.u_right"),
        (lambda m: replace(m, u_right=np.zeros(100, np.float64)), FieldError, "body.u_right"),
        (lambda m: replace(m, u_right=np.full(100, np.inf, np.float32)), FieldError, "body.u_right"),
        (lambda m: replace(m, u_right=np.zeros((100, 1), np.float32)), FieldError, "body.u_right"),
        (lambda m: replace(m, odom_sigma=np.array([-1.0, 1.0])), FieldError, "body.odom_sigma"),
        (lambda m: replace(m, odom_sigma=np.array([np.inf, 1.0])), FieldError, "body.odom_sigma"),
        (lambda m: replace(m, odom_sigma=np.ones(3)), FieldError, "body.odom_sigma"),
        (lambda m: replace(m, track_sigma=np.array([0.0, 1.0])), FieldError, "body.track_sigma"),
        (lambda m: replace(m, track_sigma=np.array([np.nan, 1.0])), FieldError, "body.track_sigma"),
        (lambda m: replace(m, track_sigma=np.ones((2, 2))), FieldError, "body.track_sigma"),
        (
            lambda m: replace(m, session=1, prev_session_from_world=np.eye(4)),
            FieldError,
            "body.prev_session_sigma",
        ),
        (
            lambda m: replace(m, prev_session_from_world=np.eye(4), prev_session_sigma=np.ones(2)),
            FieldError,
            "body.prev_session_from_world",
        ),
        (
            lambda m: replace(
                m, session=1, prev_session_from_world=np.full((4, 4), 2.0), prev_session_sigma=np.ones(2)
            ),
            FieldError,
            "body.prev_session_from_world",
        ),
        (
            lambda m: replace(
                m, session=1, prev_session_from_world=np.eye(4), prev_session_sigma=np.array([0.1, -1.0])
            ),
            FieldError,
            "body.prev_session_sigma",
        ),
    ],
)
def test_bad_keyframe_fields_are_named(mutate: Any, error: type[ProtocolError], field: str) -> None:
    with pytest.raises(error) as e:
        decode(encode(mutate(_kf()), 1))
    assert e.value.field == field


def test_limits_are_enforced() -> None:
    big = _kf(5000)
    with pytest.raises(FieldError) as e:
        decode(encode(big, 1))
    assert e.value.field == "body.keypoints" and "limit" in str(e.value)
    frame = encode(_kf(), 1)
    with pytest.raises(FrameTooLarge):
        decode(frame, Limits(max_frame_bytes=len(frame) - 1))


def test_envelope_errors() -> None:
    frame = encode(Ack(5), 9)
    with pytest.raises(VersionError):
        decode(_tamper(frame, v=PROTOCOL_VERSION + 1))
    with pytest.raises(UnknownTypeError):
        decode(_tamper(frame, type="teleport"))
    with pytest.raises(FieldError) as e:
        decode(_tamper(frame, seq=-1))
    assert e.value.field == "seq"
    with pytest.raises(FieldError) as e:
        decode(_tamper(frame, body_seq=None))
    assert e.value.field == "body.seq"
    with pytest.raises(FieldError) as e:
        decode(_tamper(frame, body_extra=1))
    assert e.value.field == "body.extra"
    with pytest.raises(ProtocolError):
        decode(b"\x81\xa1v\x01")  # a map without the other keys
    with pytest.raises(FieldError) as e:
        decode(encode(Hello("", "uav", {}, "t"), 1))
    assert e.value.field in {"body.agent_id", "body.camera"}


def test_decoded_arrays_are_read_only() -> None:
    _, kf = decode(encode(_kf(), 1))
    assert isinstance(kf, Keyframe)
    with pytest.raises(ValueError):
        kf.keypoints[0, 0] = 1.0


def test_pose_rigidity_threshold() -> None:
    """Rotation blocks must be orthonormal to 1e-6 (well above float64 noise from composing poses)."""
    R = so3_exp(np.array([0.3, -0.2, 0.1]))
    ok = se3(R, np.array([1.0, 2.0, 3.0]))
    ok[0, 0] += 1e-8  # below the tolerance: accepted
    decode(encode(replace(_kf(), world_from_cam=ok), 1))
    bad = ok.copy()
    bad[0, 0] += 1e-5  # non-orthonormal beyond 1e-6
    with pytest.raises(FieldError) as e:
        decode(encode(replace(_kf(), world_from_cam=bad), 1))
    assert e.value.field == "body.world_from_cam"
    mirror = se3(R @ np.diag([1.0, 1.0, -1.0]), np.zeros(3))  # orthonormal but det -1
    bottom = se3(R, np.zeros(3))
    bottom[3, 0] = 1e-3
    stack = np.stack([se3(R, np.zeros(3)), mirror])
    for msg, field in (
        (replace(_kf(), world_from_cam=mirror), "body.world_from_cam"),
        (replace(_kf(), world_from_cam=bottom), "body.world_from_cam"),
        (PoseUpdates(np.arange(2), stack, np.zeros(0, np.int64), np.zeros((0, 3))), "body.world_from_cam"),
        (Correction(1, np.eye(4), np.arange(2), stack), "body.world_from_cam"),
        (
            Correction(1, np.diag([1.0, 2.0, 1.0, 1.0]), np.zeros(0, np.int64), np.zeros((0, 4, 4))),
            "body.global_from_local",
        ),
        (replace(_kf(), gnss_enu=np.zeros(3), gnss_cov=np.diag([1.0, -1.0, 1.0])), "body.gnss_cov"),
        (
            replace(_kf(), gnss_enu=np.zeros(3), gnss_cov=np.array([[1.0, 0.5, 0], [0, 1, 0], [0, 0, 1]])),
            "body.gnss_cov",
        ),
        (replace(_kf(), gnss_enu=np.array([0.0, np.nan, 0.0]), gnss_cov=np.eye(3)), "body.gnss_enu"),
    ):
        with pytest.raises(FieldError) as e:
            decode(encode(msg, 1))
        assert e.value.field == field, (msg, e.value)


def test_huge_finite_values_are_not_mistaken_for_inf() -> None:
    """Finite values near the float64 maximum are valid data, not inf."""
    xyz = np.full((10, 3), 1e308)
    _, got = decode(encode(MapPoints(np.arange(10), xyz, np.zeros((10, 32), np.uint8)), 1))
    assert isinstance(got, MapPoints) and np.array_equal(got.xyz, xyz)


def test_gnss_lever_arm_and_enu_corrections_round_trip_and_are_validated() -> None:
    cam = {"width": 640, "height": 480, "fx": 430.0, "fy": 430.0, "cx": 319.5, "cy": 239.5, "dist": [0.0] * 4}
    hello = Hello("uav1", "uav", cam, "t", cam_from_antenna=np.array([0.1, -0.05, 0.06]), mission="m1")
    _, back = decode(encode(hello, 1))
    assert isinstance(back, Hello) and back.cam_from_antenna is not None
    np.testing.assert_array_equal(back.cam_from_antenna, hello.cam_from_antenna)
    _, plain = decode(encode(Hello("uav1", "uav", cam, "t", mission="m1"), 1))
    assert isinstance(plain, Hello) and plain.cam_from_antenna is None
    corr = Correction(1, np.eye(4), np.arange(1), np.eye(4)[None], global_frame="enu")
    _, c2 = decode(encode(corr, 2))
    assert isinstance(c2, Correction) and c2.global_frame == "enu"
    with pytest.raises(FieldError) as e:
        decode(encode(replace(corr, global_frame="ecef"), 3))
    assert e.value.field == "body.global_frame"
    with pytest.raises(FieldError) as e:
        decode(encode(replace(hello, cam_from_antenna=np.array([np.nan, 0.0, 0.0])), 4))
    assert e.value.field == "body.cam_from_antenna"


def test_hello_needs_a_mission_id_and_welcome_carries_whether_it_is_known() -> None:
    cam = {"width": 640, "height": 480, "fx": 430.0, "fy": 430.0, "cx": 319.5, "cy": 239.5, "dist": [0.0] * 4}
    for bad in ("", "a b", "x" * 65, "m\u00e9"):
        with pytest.raises(FieldError) as e:
            decode(encode(Hello("uav1", "uav", cam, "t", mission=bad), 0))
        assert e.value.field == "body.mission"
    _, ok = decode(encode(Hello("uav1", "uav", cam, "t", mission="3f2b-9c_1"), 0))
    assert isinstance(ok, Hello) and ok.mission == "3f2b-9c_1"
    _, w = decode(encode(Welcome(7, "v", mission_known=False), 0))
    assert isinstance(w, Welcome) and w.last_seq == 7 and w.mission_known is False


def test_a_v1_keyframe_still_reads_as_all_mono() -> None:
    """An older agent's v1 frames (no ``u_right``, ``odom_sigma``, ``stereo_baseline``) decode with those
    unset; a v1 frame carrying a v2 field is refused, naming it."""
    kf = _kf()
    v1 = _tamper(
        encode(kf, 4),
        v=1,
        body_u_right=None,
        body_odom_sigma=None,
        body_track_sigma=None,
        body_intent_velocity=None,
    )
    _, got = decode(v1)
    assert isinstance(got, Keyframe) and got.u_right is None and got.odom_sigma is None
    assert_same(kf, got)
    stereo = replace(kf, u_right=np.where(np.arange(100) % 2 == 0, 300.0, np.nan).astype(np.float32))
    with pytest.raises(FieldError) as e:
        decode(
            _tamper(
                encode(stereo, 4), v=1, body_odom_sigma=None, body_track_sigma=None, body_intent_velocity=None
            )
        )
    assert e.value.field == "body.u_right"
    weak = replace(kf, odom_sigma=np.array([0.5, 2.0]))
    with pytest.raises(FieldError) as e:
        decode(
            _tamper(encode(weak, 4), v=1, body_u_right=None, body_track_sigma=None, body_intent_velocity=None)
        )
    assert e.value.field == "body.odom_sigma"
    _, both = decode(encode(replace(stereo, odom_sigma=np.array([0.5, 2.0])), 4))
    assert isinstance(both, Keyframe) and both.u_right is not None and both.odom_sigma is not None
    hello = Hello("uav1", "uav", _CAMERA, "t", mission="m1", stereo_baseline=0.11)
    with pytest.raises(FieldError) as e:
        decode(_tamper(encode(hello, 1), v=1, body_team_advisories=None))
    assert e.value.field == "body.stereo_baseline"
    _, h = decode(_tamper(encode(hello, 1), v=1, body_stereo_baseline=None, body_team_advisories=None))
    assert isinstance(h, Hello) and h.stereo_baseline is None


def test_u_right_costs_four_bytes_per_keypoint() -> None:
    """The stereo observation grows a keyframe frame by 4 bytes per keypoint plus a fixed header."""
    kf = _kf(1000)
    stereo = replace(kf, u_right=np.full(1000, 300.0, np.float32))
    grow = len(encode(stereo, 1)) - len(encode(kf, 1))
    assert 4000 <= grow <= 4000 + 32, grow


@pytest.mark.parametrize("baseline", [0.0, -0.1, 1e3, float("nan")])
def test_bad_stereo_baseline_is_named(baseline: float) -> None:
    hello = Hello("uav1", "uav", _CAMERA, "t", mission="m1", stereo_baseline=baseline)
    with pytest.raises(FieldError) as e:
        decode(encode(hello, 1))
    assert e.value.field == "body.stereo_baseline"


_CAMERA: dict[str, object] = {
    "width": 640, "height": 480, "fx": 400.0, "fy": 400.0, "cx": 320.0, "cy": 240.0, "dist": [0.0] * 4,
}  # fmt: skip


def _rendezvous(**changes: Any) -> Rendezvous:
    pose = se3(so3_exp(np.array([0.1, -0.2, 0.3])), np.array([1.0, 2.0, 3.0]))
    msg = Rendezvous(
        timestamp=3.25,
        observed_agent="ugv",
        marker_ids=np.array([1, 2, 5], dtype=np.int64),
        ref_kf_id=7,
        ref_from_cam=pose,
        cam_from_observed=pose,
        covariance=np.diag([1e-4, 1e-4, 1e-4, 1e-3, 1e-3, 4e-3]),
        reproj_rms_px=0.3,
        session=1,
    )
    return replace(msg, **changes)


def test_rendezvous_round_trips_in_v3_and_is_refused_in_older_frames() -> None:
    msg = _rendezvous()
    seq, out = decode(encode(msg, 4))
    assert seq == 4
    assert_same(msg, out)
    with pytest.raises(UnknownTypeError) as e:
        decode(_tamper(encode(msg, 4), v=2))
    assert "v3" in str(e.value)


@pytest.mark.parametrize(
    ("changes", "field"),
    [
        ({"marker_ids": np.zeros(0, dtype=np.int64)}, "body.marker_ids"),
        ({"marker_ids": np.array([-1], dtype=np.int64)}, "body.marker_ids"),
        ({"observed_agent": ""}, "body.observed_agent"),
        ({"ref_kf_id": -3}, "body.ref_kf_id"),
        ({"cam_from_observed": np.diag([1.0, 1.0, -1.0, 1.0])}, "body.cam_from_observed"),
        ({"covariance": np.diag([1.0, 1.0, 1.0, 1.0, 1.0, -1.0])}, "body.covariance"),
        ({"covariance": np.eye(6) + np.eye(6, k=1) * 0.1}, "body.covariance"),
        ({"reproj_rms_px": -0.5}, "body.reproj_rms_px"),
        ({"timestamp": float("nan")}, "body.timestamp"),
    ],
)
def test_bad_rendezvous_fields_are_named(changes: dict[str, Any], field: str) -> None:
    with pytest.raises(FieldError) as e:
        decode(encode(_rendezvous(**changes), 1))
    assert e.value.field == field


def _cov6() -> np.ndarray:
    A = np.random.default_rng(3).normal(size=(6, 6))
    return A @ A.T * 1e-3


def test_a_correction_carries_a_pose_covariance() -> None:
    """Protocol v4: the covariance of the agent's latest keyframe rides on the correction, checked as
    a covariance (symmetric, positive semi-definite, finite; zero is one: a held keyframe's)."""
    corr = Correction(
        1, np.eye(4), np.arange(1), np.eye(4)[None], pose_covariance=_cov6(), covariance_kf_id=7
    )
    _, got = decode(encode(corr, 3))
    assert isinstance(got, Correction) and got.covariance_kf_id == 7
    assert got.pose_covariance is not None
    np.testing.assert_array_equal(got.pose_covariance, corr.pose_covariance)
    _, zero = decode(encode(replace(corr, pose_covariance=np.zeros((6, 6))), 3))
    assert isinstance(zero, Correction) and zero.pose_covariance is not None
    _, plain = decode(encode(Correction(1, np.eye(4), np.arange(1), np.eye(4)[None]), 3))
    assert isinstance(plain, Correction) and plain.pose_covariance is None and plain.covariance_kf_id is None
    skew = _cov6()
    skew[0, 1] += 1e-4
    neg = _cov6() - 0.01 * np.eye(6) * np.linalg.eigvalsh(_cov6()).max()
    nan = _cov6()
    nan[2, 2] = np.nan
    for bad, field, why in [
        (replace(corr, pose_covariance=skew), "body.pose_covariance", "symmetric"),
        (replace(corr, pose_covariance=neg), "body.pose_covariance", "semi-definite"),
        (replace(corr, pose_covariance=nan), "body.pose_covariance", "NaN"),
        (replace(corr, pose_covariance=_cov6()[:3, :3].copy()), "body.pose_covariance", "shape"),
        (replace(corr, covariance_kf_id=None), "body.covariance_kf_id", "together"),
        (replace(corr, pose_covariance=None), "body.pose_covariance", "together"),
        (replace(corr, covariance_kf_id=-1), "body.covariance_kf_id", "outside"),
    ]:
        with pytest.raises(FieldError) as e:
            decode(encode(bad, 3))
        assert e.value.field == field and why in str(e.value), (field, str(e.value))


def test_older_readers_get_frames_of_their_version() -> None:
    """A v3 frame cannot carry the v4 fields (refused, naming one); a v4 correction downgraded for a v3
    peer is written as v3 without them, which a reader of v3 takes; setting them at v3 is an error."""
    corr = Correction(
        1, np.eye(4), np.arange(1), np.eye(4)[None], pose_covariance=_cov6(), covariance_kf_id=7
    )
    with pytest.raises(FieldError) as e:
        decode(_tamper(encode(corr, 3), v=3))
    assert e.value.field in {"body.pose_covariance", "body.covariance_kf_id"}
    with pytest.raises(ValueError):
        encode(corr, 3, version=3)
    old = encode(downgrade(corr, 3), 3, version=3)
    obj = msgpack.unpackb(old, raw=False)
    assert obj["v"] == 3 and not {"pose_covariance", "covariance_kf_id"} & set(obj["body"])
    version, _, got = decode_versioned(old)
    assert version == 3 and isinstance(got, Correction) and got.pose_covariance is None
    np.testing.assert_array_equal(got.world_from_cam, corr.world_from_cam)
    assert downgrade(corr, 4) is corr
    # a v1 peer: the rendezvous message does not exist for it
    with pytest.raises(ValueError):
        encode(_rendezvous(), 1, version=2)


def test_a_v4_frame_cannot_carry_track_sigma_and_a_v4_reader_gets_the_keyframe_without_it() -> None:
    """``Keyframe.track_sigma`` is protocol v5: a v4 frame carrying it is refused naming the field, a
    keyframe downgraded for a v4 peer travels without it, and a v5 frame keeps it exactly."""
    kf = replace(_kf(), track_sigma=np.array([0.006, 0.08]))
    with pytest.raises(FieldError) as e:
        decode(_tamper(encode(kf, 3), v=4, body_intent_velocity=None))
    assert e.value.field == "body.track_sigma"
    with pytest.raises(ValueError):
        encode(kf, 3, version=4)
    version, _, old = decode_versioned(encode(downgrade(kf, 4), 3, version=4))
    assert version == 4 and isinstance(old, Keyframe) and old.track_sigma is None
    _, new = decode(encode(kf, 3))
    assert isinstance(new, Keyframe) and new.track_sigma is not None
    np.testing.assert_array_equal(new.track_sigma, [0.006, 0.08])


def test_points_follow_is_protocol_v6() -> None:
    """``PoseUpdates.points_follow`` is protocol v6: a v5 frame carrying it is refused naming the field, an
    update downgraded for a v5 peer travels without it, a v6 frame keeps it, and a non-bool is refused."""
    upd = PoseUpdates(np.array([4], np.int64), np.eye(4)[None], np.zeros(0, np.int64), np.zeros((0, 3)),
                      points_follow=True)  # fmt: skip
    with pytest.raises(FieldError) as e:
        decode(_tamper(encode(upd, 3), v=5))
    assert e.value.field == "body.points_follow"
    version, _, old = decode_versioned(encode(downgrade(upd, 5), 3, version=5))
    assert version == 5 and isinstance(old, PoseUpdates) and old.points_follow is False
    _, new = decode(encode(upd, 3))
    assert isinstance(new, PoseUpdates) and new.points_follow is True
    with pytest.raises(FieldError) as e:
        decode(_tamper(encode(upd, 3), body_points_follow=1))
    assert e.value.field == "body.points_follow"


def test_intent_velocity_and_half_height_are_protocol_v7() -> None:
    """``Keyframe.intent_velocity`` and ``TeamAdvisory.half_height_m`` are protocol v7: a v6 frame
    carrying either is refused naming the field, a message downgraded for a v6 peer travels without it,
    a v7 frame keeps it exactly; an intent that is not finite or faster than the limit is refused."""
    kf = replace(_kf(), intent_velocity=np.array([1.5, -0.25, 0.5]))
    with pytest.raises(FieldError) as e:
        decode(_tamper(encode(kf, 3), v=6))
    assert e.value.field == "body.intent_velocity"
    version, _, old = decode_versioned(encode(downgrade(kf, 6), 3, version=6))
    assert version == 6 and isinstance(old, Keyframe) and old.intent_velocity is None
    _, new = decode(encode(kf, 3))
    assert isinstance(new, Keyframe) and new.intent_velocity is not None
    np.testing.assert_array_equal(new.intent_velocity, [1.5, -0.25, 0.5])
    for bad in (np.array([np.nan, 0.0, 0.0]), np.array([0.0, 101.0, 0.0]), np.zeros(2)):
        with pytest.raises(FieldError) as e:
            decode(encode(replace(kf, intent_velocity=bad), 3))
        assert e.value.field == "body.intent_velocity"
    adv = TeamAdvisory(map_id=1, computed_at=1.0, goals=np.zeros((0, 3)), desired_velocity=np.zeros(3),
                       safe_velocity=np.zeros(3), radius_m=0.8, half_height_m=0.45)  # fmt: skip
    with pytest.raises(FieldError) as e:
        decode(_tamper(encode(adv, 3), v=6))
    assert e.value.field == "body.half_height_m"
    _, old_adv = decode(encode(downgrade(adv, 6), 3, version=6))
    assert isinstance(old_adv, TeamAdvisory) and old_adv.half_height_m == 0.0
    _, new_adv = decode(encode(adv, 3))
    assert isinstance(new_adv, TeamAdvisory) and new_adv.half_height_m == 0.45
    with pytest.raises(FieldError) as e:
        decode(encode(replace(adv, half_height_m=-0.1), 3))
    assert e.value.field == "body.half_height_m"
