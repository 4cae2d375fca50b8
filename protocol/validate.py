"""Validation of each message type's decoded body (:func:`hivemap.protocol.codec.decode` calls these):
field types, dtypes, shapes, sizes against :class:`Limits`, finiteness, rigid poses. Each raises a
:class:`~hivemap.protocol.errors.ProtocolError` naming the field."""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np

from hivemap.protocol.errors import FieldError
from hivemap.protocol.fields import (
    as_array,
    as_bool,
    as_camera,
    as_float,
    as_int,
    as_opt_str,
    as_str,
    check_psd,
    check_rigid,
    check_same_rows,
    check_similarity,
    is_spd3,
)
from hivemap.protocol.limits import Limits
from hivemap.protocol.messages import (
    Ack,
    Bye,
    Correction,
    Error,
    Hello,
    Keyframe,
    MapPoints,
    Message,
    PoseUpdates,
    Rendezvous,
    TeamAdvisory,
    Welcome,
)


def _session(b: dict[str, Any]) -> int:
    return as_int(b.get("session", 0), "body.session", 0, 2**31)


def _v_hello(b: dict[str, Any], lim: Limits) -> Hello:
    kind = as_str(b["kind"], "body.kind", 8)
    if kind not in ("uav", "ugv"):
        raise FieldError(f"kind must be 'uav' or 'ugv', got {kind!r}", "body.kind")
    return Hello(
        agent_id=as_str(b["agent_id"], "body.agent_id", lim.max_agent_id_len, allow_empty=False),
        kind=kind,
        camera=as_camera(b["camera"], "body.camera"),
        token=as_str(b["token"], "body.token", lim.max_token_len),
        resume_from=as_int(b.get("resume_from", 0), "body.resume_from", 0, lim.max_seq),
        session=_session(b),
        cam_from_antenna=(
            None
            if b.get("cam_from_antenna") is None
            else as_array(b["cam_from_antenna"], "body.cam_from_antenna", "<f8", (3,))
        ),
        mission=_mission(b.get("mission")),
        stereo_baseline=_baseline(b.get("stereo_baseline"), lim),
        team_advisories=as_bool(b.get("team_advisories", False), "body.team_advisories"),
    )


def _baseline(v: Any, lim: Limits) -> float | None:
    if v is None:
        return None
    b = as_float(v, "body.stereo_baseline")
    if not 0 < b <= lim.max_baseline_m:
        raise FieldError(
            f"stereo baseline must be in (0, {lim.max_baseline_m}] m, got {b}", "body.stereo_baseline"
        )
    return b


def _mission(v: Any) -> str:
    """A mission id: 1-64 characters of letters, digits, '-' and '_' (a UUID in hex or canonical form)."""
    s = as_str(v, "body.mission", 64, allow_empty=False) if v is not None else ""
    if not s:
        raise FieldError("hello needs a mission id (a UUID created with the agent's outbox)", "body.mission")
    if not all(c.isascii() and (c.isalnum() or c in "-_") for c in s):
        raise FieldError("mission id may hold only letters, digits, '-' and '_'", "body.mission")
    return s


def _v_welcome(b: dict[str, Any], lim: Limits) -> Welcome:
    return Welcome(
        last_seq=as_int(b["last_seq"], "body.last_seq", 0, lim.max_seq),
        server_version=as_str(b["server_version"], "body.server_version", lim.max_string_len),
        mission_known=as_bool(b.get("mission_known", True), "body.mission_known"),
    )


def _v_keyframe(b: dict[str, Any], lim: Limits) -> Keyframe:
    kp = as_array(b["keypoints"], "body.keypoints", "<f4", (None, 2), lim.max_keypoints)
    octv = as_array(b["octaves"], "body.octaves", "u1", (None,), lim.max_keypoints)
    desc = as_array(b["descriptors"], "body.descriptors", "u1", (None, 32), lim.max_keypoints)
    pids = as_array(b["point_ids"], "body.point_ids", "<i8", (None,), lim.max_keypoints)
    for name, a in (("octaves", octv), ("descriptors", desc), ("point_ids", pids)):
        check_same_rows("body.keypoints", kp, f"body.{name}", a)
    if pids.size and pids.min() < -1:
        raise FieldError("point ids must be >= 0, or -1 for none", "body.point_ids")
    pose = as_array(b["world_from_cam"], "body.world_from_cam", "<f8", (4, 4))
    check_rigid(pose, "body.world_from_cam")
    ur = b.get("u_right")
    if ur is not None:
        ur = _u_right(ur, kp)
    enu = b.get("gnss_enu")
    cov = b.get("gnss_cov")
    if (enu is None) != (cov is None):
        raise FieldError(
            "gnss_enu and gnss_cov go together", "body.gnss_cov" if cov is None else "body.gnss_enu"
        )
    if enu is not None:
        enu = as_array(enu, "body.gnss_enu", "<f8", (3,))
        cov = as_array(cov, "body.gnss_cov", "<f8", (3, 3))
        if not is_spd3(cov.tolist()):
            raise FieldError("covariance must be symmetric positive definite", "body.gnss_cov")
    up = b.get("up_cam")
    if up is not None:
        up = as_array(up, "body.up_cam", "<f8", (3,))
        norm = float(np.linalg.norm(up)) if np.all(np.isfinite(up)) else math.nan
        if not 0.99 <= norm <= 1.01:
            raise FieldError(f"up direction must be a unit vector, its norm is {norm:.3g}", "body.up_cam")
    guess, sigma, session = b.get("prev_session_from_world"), b.get("prev_session_sigma"), _session(b)
    if (guess is None) != (sigma is None):
        missing = "body.prev_session_sigma" if sigma is None else "body.prev_session_from_world"
        raise FieldError("prev_session_from_world and prev_session_sigma go together", missing)
    if guess is not None:
        if session < 1:
            raise FieldError(
                "a guess in the previous session needs session >= 1", "body.prev_session_from_world"
            )
        guess = as_array(guess, "body.prev_session_from_world", "<f8", (4, 4))
        check_rigid(guess, "body.prev_session_from_world")
        sigma = as_array(sigma, "body.prev_session_sigma", "<f8", (2,))
        if not (np.all(np.isfinite(sigma)) and np.all(sigma > 0)):
            raise FieldError("sigmas must be finite and positive", "body.prev_session_sigma")
    odom = b.get("odom_sigma")
    if odom is not None:
        odom = as_array(odom, "body.odom_sigma", "<f8", (2,))
        if not (np.all(np.isfinite(odom)) and np.all(odom >= 0)):
            raise FieldError("sigmas must be finite and >= 0", "body.odom_sigma")
    track = b.get("track_sigma")
    if track is not None:
        track = as_array(track, "body.track_sigma", "<f8", (2,))
        if not (np.all(np.isfinite(track)) and np.all(track > 0)):
            raise FieldError("sigmas must be finite and positive", "body.track_sigma")
    intent = b.get("intent_velocity")
    if intent is not None:
        intent = as_array(intent, "body.intent_velocity", "<f8", (3,))
        speed = float(np.linalg.norm(intent)) if np.all(np.isfinite(intent)) else math.nan
        if not speed <= lim.max_speed_mps:
            raise FieldError(f"intended speed must be finite and <= {lim.max_speed_mps} m/s, got {speed:.3g}",
                             "body.intent_velocity")  # fmt: skip
    return Keyframe(
        kf_id=as_int(b["kf_id"], "body.kf_id", 0),
        timestamp=as_float(b["timestamp"], "body.timestamp"),
        world_from_cam=pose,
        keypoints=kp,
        octaves=octv,
        descriptors=desc,
        point_ids=pids,
        gnss_enu=enu,
        gnss_cov=cov,
        session=session,
        up_cam=up,
        prev_session_from_world=guess,
        prev_session_sigma=sigma,
        u_right=ur,
        odom_sigma=odom,
        track_sigma=track,
        intent_velocity=intent,
    )


def _u_right(v: Any, kp: np.ndarray) -> np.ndarray:
    """One f32 per keypoint: finite, or NaN for a keypoint without a stereo match (never inf)."""
    if not isinstance(v, np.ndarray) or v.dtype != np.dtype("<f4") or v.ndim != 1:
        what = type(v).__name__ if not isinstance(v, np.ndarray) else f"{v.dtype} {v.shape}"
        raise FieldError(f"expected an f32 array of one value per keypoint, got {what}", "body.u_right")
    check_same_rows("body.keypoints", kp, "body.u_right", v)
    if np.isinf(v).any():
        raise FieldError("contains inf (NaN marks a keypoint without a stereo match)", "body.u_right")
    return v


def _v_map_points(b: dict[str, Any], lim: Limits) -> MapPoints:
    ids = as_array(b["ids"], "body.ids", "<i8", (None,), lim.max_points_per_msg)
    xyz = as_array(b["xyz"], "body.xyz", "<f8", (None, 3), lim.max_points_per_msg)
    desc = as_array(b["descriptors"], "body.descriptors", "u1", (None, 32), lim.max_points_per_msg)
    check_same_rows("body.ids", ids, "body.xyz", xyz)
    check_same_rows("body.ids", ids, "body.descriptors", desc)
    if ids.size and ids.min() < 0:
        raise FieldError("point ids must be >= 0", "body.ids")
    return MapPoints(ids=ids, xyz=xyz, descriptors=desc, session=_session(b))


def _v_pose_updates(b: dict[str, Any], lim: Limits) -> PoseUpdates:
    kf_ids = as_array(b["kf_ids"], "body.kf_ids", "<i8", (None,), lim.max_poses_per_msg)
    poses = as_array(b["world_from_cam"], "body.world_from_cam", "<f8", (None, 4, 4), lim.max_poses_per_msg)
    check_same_rows("body.kf_ids", kf_ids, "body.world_from_cam", poses)
    check_rigid(poses, "body.world_from_cam")
    pids = as_array(b["point_ids"], "body.point_ids", "<i8", (None,), lim.max_points_per_msg)
    xyz = as_array(b["xyz"], "body.xyz", "<f8", (None, 3), lim.max_points_per_msg)
    check_same_rows("body.point_ids", pids, "body.xyz", xyz)
    if (kf_ids.size and kf_ids.min() < 0) or (pids.size and pids.min() < 0):
        raise FieldError(
            "ids must be >= 0", "body.kf_ids" if kf_ids.size and kf_ids.min() < 0 else "body.point_ids"
        )
    follow = as_bool(b.get("points_follow", False), "body.points_follow")
    return PoseUpdates(kf_ids=kf_ids, world_from_cam=poses, point_ids=pids, xyz=xyz, session=_session(b),
                       points_follow=follow)  # fmt: skip


def _v_rendezvous(b: dict[str, Any], lim: Limits) -> Rendezvous:
    ids = as_array(b["marker_ids"], "body.marker_ids", "<i8", (None,), lim.max_markers)
    if ids.size == 0:
        raise FieldError("at least one marker id", "body.marker_ids")
    if ids.min() < 0:
        raise FieldError("ids must be >= 0", "body.marker_ids")
    ref = as_array(b["ref_from_cam"], "body.ref_from_cam", "<f8", (4, 4))
    check_rigid(ref, "body.ref_from_cam")
    rel = as_array(b["cam_from_observed"], "body.cam_from_observed", "<f8", (4, 4))
    check_rigid(rel, "body.cam_from_observed")
    cov = as_array(b["covariance"], "body.covariance", "<f8", (6, 6))
    if np.abs(cov - cov.T).max() > 1e-9 * max(float(np.abs(cov).max()), 1e-300):
        raise FieldError("covariance must be symmetric", "body.covariance")
    try:
        np.linalg.cholesky(cov)
    except np.linalg.LinAlgError:
        raise FieldError("covariance must be positive definite", "body.covariance") from None
    rms = as_float(b["reproj_rms_px"], "body.reproj_rms_px")
    if rms < 0:
        raise FieldError("must be >= 0", "body.reproj_rms_px")
    return Rendezvous(
        timestamp=as_float(b["timestamp"], "body.timestamp"),
        observed_agent=as_str(
            b["observed_agent"], "body.observed_agent", lim.max_agent_id_len, allow_empty=False
        ),
        marker_ids=ids,
        ref_kf_id=as_int(b["ref_kf_id"], "body.ref_kf_id", 0),
        ref_from_cam=ref,
        cam_from_observed=rel,
        covariance=cov,
        reproj_rms_px=rms,
        session=_session(b),
    )


def _v_ack(b: dict[str, Any], lim: Limits) -> Ack:
    return Ack(seq=as_int(b["seq"], "body.seq", 0, lim.max_seq))


def _v_correction(b: dict[str, Any], lim: Limits) -> Correction:
    g = as_array(b["global_from_local"], "body.global_from_local", "<f8", (4, 4))
    check_similarity(g, "body.global_from_local")
    kf_ids = as_array(b["kf_ids"], "body.kf_ids", "<i8", (None,), lim.max_poses_per_msg)
    poses = as_array(b["world_from_cam"], "body.world_from_cam", "<f8", (None, 4, 4), lim.max_poses_per_msg)
    check_same_rows("body.kf_ids", kf_ids, "body.world_from_cam", poses)
    check_rigid(poses, "body.world_from_cam")
    cov, cov_kf = b.get("pose_covariance"), b.get("covariance_kf_id")
    if (cov is None) != (cov_kf is None):
        missing = "body.covariance_kf_id" if cov_kf is None else "body.pose_covariance"
        raise FieldError("pose_covariance and covariance_kf_id go together", missing)
    if cov is not None:
        cov = as_array(cov, "body.pose_covariance", "<f8", (6, 6))
        check_psd(cov, "body.pose_covariance")
        cov_kf = as_int(cov_kf, "body.covariance_kf_id", 0)
    return Correction(
        map_id=as_int(b["map_id"], "body.map_id", 0),
        global_from_local=g,
        kf_ids=kf_ids,
        world_from_cam=poses,
        session=_session(b),
        global_frame=_global_frame(b.get("global_frame", "map")),
        pose_covariance=cov,
        covariance_kf_id=cov_kf,
    )


def _global_frame(v: Any) -> str:
    frame = as_str(v, "body.global_frame", 8)
    if frame not in ("map", "enu"):
        raise FieldError(f"global_frame must be 'map' or 'enu', got {frame!r}", "body.global_frame")
    return frame


def _v_team_advisory(b: dict[str, Any], lim: Limits) -> TeamAdvisory:
    radius = as_float(b["radius_m"], "body.radius_m")
    if radius < 0:
        raise FieldError(f"radius must be >= 0, got {radius}", "body.radius_m")
    half = as_float(b.get("half_height_m", 0.0), "body.half_height_m")
    if not half >= 0:
        raise FieldError(f"half height must be >= 0, got {half}", "body.half_height_m")
    return TeamAdvisory(
        map_id=as_int(b["map_id"], "body.map_id", 0),
        computed_at=as_float(b["computed_at"], "body.computed_at"),
        goals=as_array(b["goals"], "body.goals", "<f8", (None, 3), lim.max_goals),
        desired_velocity=as_array(b["desired_velocity"], "body.desired_velocity", "<f8", (3,)),
        safe_velocity=as_array(b["safe_velocity"], "body.safe_velocity", "<f8", (3,)),
        radius_m=radius,
        session=_session(b),
        half_height_m=half,
    )


def _v_error(b: dict[str, Any], lim: Limits) -> Error:
    seq = b.get("seq")
    return Error(
        code=as_str(b["code"], "body.code", 64),
        message=as_str(b["message"], "body.message", lim.max_string_len),
        field=as_opt_str(b.get("field"), "body.field", 256),
        seq=None if seq is None else as_int(seq, "body.seq", 0, lim.max_seq),
    )


def _v_bye(b: dict[str, Any], lim: Limits) -> Bye:
    return Bye(reason=as_str(b.get("reason", ""), "body.reason", lim.max_string_len))


VALIDATORS: dict[str, Callable[[dict[str, Any], Limits], Message]] = {
    "hello": _v_hello,
    "welcome": _v_welcome,
    "keyframe": _v_keyframe,
    "map_points": _v_map_points,
    "pose_updates": _v_pose_updates,
    "rendezvous": _v_rendezvous,
    "ack": _v_ack,
    "correction": _v_correction,
    "team_advisory": _v_team_advisory,
    "error": _v_error,
    "bye": _v_bye,
}
